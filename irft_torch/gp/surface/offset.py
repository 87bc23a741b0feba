r"""The free surface's height, learned with the maps: one offset per group of samples (learned in
cm, the unit of the segment depths; reported in m, the package's unit of length).

A real log never knows exactly where the sand surface is. With contacts that carry their signed
depths and areas (``rft.contacts`` fills them), a surface ``delta`` higher than stated gives the
weights ``relu(depth + delta) x area`` (``Contacts.with_surface_offset``). ``InverseRFT(contacts,
forces, surface=True)`` (or ``surface=groups``, one offset per group) fits delta with the
hyperparameters by the exact marginal likelihood, its gradient flowing through the weights.

The likelihood while delta moves (W changes every step, so no statistics of W can be cached): the
distinct angle pairs of every segment that could touch (area != 0) do not depend on delta, so
W(delta) = Phi(delta) P with Phi (T x U) the weights summed per pair, and with K = K_UU, per axis,

    log |s2 I_T + Phi K Phi^T| = (T - U) log s2 + log |s2 I_U + K Phi^T Phi|
    y^T (s2 I_T + Phi K Phi^T)^-1 y = (y^T y - b^T (s2 I_U + K Phi^T Phi)^-1 K b) / s2,  b = Phi^T y

(Sylvester's determinant identity and the push-through identity; LU, no inverse of K, no jitter),
or the T x T Cholesky form when T < U. Cost per step O(T U^2 + min(T, U)^3): cheap for a plate, a
flat toe, a toe that does not turn (U small); a rotating toe on a long recording (U ~ T M) is
expensive (then fit the offset on a thinned subset). After the fit the model's usual backend is
rebuilt on the contacts at the fitted offset (exact posterior at that offset).

Uncertainty: ``SurfaceEstimate`` holds the Laplace standard deviation of the offsets from the
Hessian of the total negative log likelihood (T x loss) in the offsets and the raw
hyperparameters, the hyperparameters marginalized (Schur complement; directions the data do not
inform, zero curvature, are dropped), and the conditional one (hyperparameters fixed). See
docs/surface.md for the sign convention and what is and is not identified.

The front door composes it: ``InverseRFT`` holds a ``SurfaceOffset`` and calls ``surface_estimate``,
``init_surface`` and ``surface_loss`` with itself; this module never imports the front door (the profile
likelihood, which builds models, is ``gp.surface.profile``).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ...rft.contacts import M_TO_CM, Contacts
from ..backends.pairs import distinct_pairs
from ..kernels.angle import angle_covariance
from ..kernels.li_basis import li_features

__all__ = ["SurfaceOffset", "SurfaceEstimate", "surface_negative_log_likelihood", "surface_estimate",
           "init_surface", "surface_loss"]


@dataclass
class SurfaceEstimate:
    """The fitted surface offsets, m, positive = the surface is higher than stated (deeper contact).
    ``in_cm()`` gives the same in cm (the unit of depths in RFT tables).

    Attributes:
        mean: (G,) offsets.
        std: (G,) Laplace standard deviations, hyperparameters marginalized (inf: not identified).
        std_conditional: (G,) with the hyperparameters held at their fitted values.
        covariance: (G, G) Laplace covariance of the offsets (hyperparameters marginalized).
        correlation: dict name -> (G,) correlation of each offset with each raw hyperparameter
            (from the inverse Hessian), e.g. how much an offset trades off with an outputscale.
    """

    mean: Tensor
    std: Tensor
    std_conditional: Tensor
    covariance: Tensor
    correlation: dict

    def interval(self, level: float = 0.95) -> tuple[Tensor, Tensor]:
        """Central Laplace interval (lower, upper) in m (in cm after ``in_cm()``)."""
        if not 0 < level < 1:
            raise ValueError(f"level must be in (0, 1), got {level}")
        z = math.sqrt(2) * torch.special.erfinv(torch.tensor(level, dtype=torch.float64)).item()
        return self.mean - z * self.std, self.mean + z * self.std

    def in_cm(self) -> SurfaceEstimate:
        """The same estimate with offsets, stds and covariance in cm (correlations unchanged)."""
        k = M_TO_CM
        return SurfaceEstimate(self.mean * k, self.std * k, self.std_conditional * k, self.covariance * k**2,
                               self.correlation)


class SurfaceOffset(nn.Module):
    """Learnable surface offsets (G,) in cm (the depths' unit; ``surface_estimate`` reports m), and the
    fixed angle-pair structure of the training data.

    Args:
        contacts: the (whitened) training contacts with ``depth``, ``area_x``, ``area_z``.
        groups: None (one offset) or (T,) integers in [0, G): the group (recording, trial) of each
            sample; G = groups.max() + 1.
    """

    def __init__(self, contacts: Contacts, groups=None) -> None:
        super().__init__()
        if not contacts.has_surface:
            raise ValueError("a learned surface (surface=...) needs contacts with depth, area_x and area_z (the signed "
                             "depths and areas that rft.contacts fills); these contacts carry weights only, so the "
                             "surface cannot move. Rebuild them with rft.contacts(toe, path) or pass "
                             "depth/area_x/area_z")
        T = len(contacts)
        dtype, device = contacts.depth.dtype, contacts.depth.device
        if groups is None:
            g = torch.zeros(T, dtype=torch.long, device=device)
        else:
            g = torch.as_tensor(groups, device=device)
            if g.dtype.is_floating_point or g.dtype == torch.bool:
                if g.dtype.is_floating_point and torch.equal(g, g.round()):
                    g = g.long()
                else:
                    raise ValueError(f"surface_groups must be integers (the group of each sample), got {g.dtype}")
            g = g.long()
            if g.shape != (T,):
                raise ValueError(f"surface_groups must be (T,) = ({T},), got shape {tuple(g.shape)}")
            if (g < 0).any():
                raise ValueError("surface_groups must be >= 0")
        G = int(g.max()) + 1 if T else 1
        empty = [k for k in range(G) if not bool((g == k).any())]
        if empty:
            raise ValueError(f"surface_groups: group(s) {empty} have no samples (use 0 .. G-1, each used)")
        self.offset = nn.Parameter(torch.zeros(G, dtype=dtype, device=device))
        self.register_buffer("groups", g, persistent=False)
        self.grouped = groups is not None
        # The angle pairs of every segment that could touch (area != 0), whatever the offset.
        self.table, self.index = distinct_pairs(Contacts(contacts.beta, contacts.gamma, contacts.area_x,
                                                         contacts.area_z))

    @property
    def n_groups(self) -> int:
        return self.offset.shape[0]

    def shifted(self, contacts: Contacts, detach: bool = False) -> Contacts:
        """``contacts`` (the training ones, T rows) at the current offsets."""
        delta = self.offset.detach() if detach else self.offset
        return contacts.with_depth_shift_cm(delta, self.groups)


def surface_negative_log_likelihood(hypers, contacts: Contacts, forces: Tensor, table: Tensor,
                                    index: Tensor) -> Tensor:
    """-log p(F | hyperparameters, weights) / T per axis, (2,), differentiable in the weights.

    Args:
        hypers: the shared ``RFTHyperparameters``.
        contacts: (T, M) contacts at the offset being evaluated (whitened).
        forces: (T, 2) whitened forces.
        table: distinct angle pairs (U, 2) covering every segment of non-zero weight (``distinct_pairs``
            of the contacts' areas).
        index: each segment's row in ``table`` (T, M).
    """
    T, U = len(contacts), table.shape[0]
    w = torch.stack([contacts.weight_x, contacts.weight_z])  # (2, T, M)
    Phi = w.new_zeros(2, T, U).scatter_add(-1, index.expand(2, *index.shape), w)
    K = angle_covariance(hypers.kernel, table[:, 0], table[:, 1], table[:, 0], table[:, 1])  # (2, U, U)
    if getattr(hypers, "li", None) is not None:  # Li et al.'s term (``gp.kernels.li_basis``) at the pairs
        f = li_features(table[:, 0], table[:, 1])
        K = K + hypers.li.weigh(f) @ f.mT
    s2 = hypers.noise  # (2,)
    y = forces.T
    m = hypers.mean_of(contacts)
    if m is not None:
        y = y - m
    if U <= T:
        P = Phi.mT @ Phi
        b = (Phi.mT @ y[..., None])[..., 0]  # (2, U)
        eye = torch.eye(U, dtype=K.dtype, device=K.device)
        B = s2[:, None, None] * eye + K @ P
        LU, piv = torch.linalg.lu_factor(B)
        logdet = (T - U) * torch.log(s2) + torch.linalg.slogdet(B).logabsdet
        sol = torch.linalg.lu_solve(LU, piv, (K @ b[..., None]))[..., 0]
        quad = (y.pow(2).sum(-1) - (b * sol).sum(-1)) / s2
    else:
        A = Phi @ K @ Phi.mT
        A = 0.5 * (A + A.mT) + s2[:, None, None] * torch.eye(T, dtype=K.dtype, device=K.device)
        L = torch.linalg.cholesky(A)
        z = torch.linalg.solve_triangular(L, y[..., None], upper=False)[..., 0]
        quad = z.pow(2).sum(-1)
        logdet = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    return 0.5 * (quad + logdet + T * math.log(2 * math.pi)) / T


def surface_estimate(model) -> SurfaceEstimate:
    """Laplace uncertainty of a fitted ``InverseRFT``'s surface offsets (see the module doc)."""
    surface = model.surface
    names, params = [], []
    for name, p in model.hypers.named_parameters():
        if p.requires_grad:
            names += [f"{name}[{i}]" for i in range(p.numel())]
            params.append(p)
    all_params = [surface.offset] + params
    G = surface.n_groups
    model.train()
    T = len(model.train_forces)
    total = model.loss() * T
    grads = torch.autograd.grad(total, all_params, create_graph=True, allow_unused=True)
    flat = torch.cat([(g if g is not None else torch.zeros_like(p)).reshape(-1) for g, p in zip(grads, all_params)])
    n = flat.shape[0]
    H = flat.new_zeros(n, n)
    for i in range(n):
        if not flat[i].requires_grad:
            continue
        row = torch.autograd.grad(flat[i], all_params, retain_graph=True, allow_unused=True)
        H[i] = torch.cat([(r if r is not None else torch.zeros_like(p)).reshape(-1) for r, p in zip(row, all_params)])
    model.eval()
    H = 0.5 * (H + H.T).detach()
    Hdd, Hdt, Htt = H[:G, :G], H[:G, G:], H[G:, G:]
    evals, evecs = torch.linalg.eigh(Htt)
    tol = 1e-9 * float(evals.abs().max()) if evals.numel() else 0.0
    keep = evals > tol
    if bool((evals < -1e3 * tol).any()) and float(evals.min()) < -1e-6 * float(evals.abs().max()):
        warnings.warn("the loss is not at a minimum in the hyperparameters (negative curvature); the offset's "
                      "marginal std ignores those directions: fit longer", stacklevel=3)
    V = evecs[:, keep]
    Htt_pinv = V @ torch.diag(1 / evals[keep]) @ V.T
    schur = Hdd - Hdt @ Htt_pinv @ Hdt.T
    cond_var = 1 / torch.diagonal(Hdd)
    try:
        cov = torch.linalg.inv(schur)
        ok = torch.linalg.eigvalsh(schur).min() > 0
    except torch.linalg.LinAlgError:
        cov, ok = torch.full_like(schur, math.inf), False
    std = torch.sqrt(torch.diagonal(cov)) if ok else torch.full((G,), math.inf, dtype=H.dtype, device=H.device)
    cond = torch.where(torch.diagonal(Hdd) > 0, cond_var, torch.full_like(cond_var, math.inf)).sqrt()
    # correlations of each offset with each raw hyperparameter (restricted inverse Hessian)
    corr = {}
    Hk = torch.cat([torch.cat([Hdd, Hdt @ V], 1), torch.cat([(Hdt @ V).T, torch.diag(evals[keep])], 1)])
    try:
        Ck = torch.linalg.inv(Hk)
        Cdt = Ck[:G, G:] @ V.T  # (G, n_hyper), back in the raw coordinates
        sd_t = torch.sqrt(torch.clamp(torch.diagonal(V @ Ck[G:, G:] @ V.T), min=1e-300))
        sd_d = torch.sqrt(torch.clamp(torch.diagonal(Ck[:G, :G]), min=1e-300))
        for j, name in enumerate(names):
            informed = float(sd_t[j]) > 1e-150 and bool(keep.any())
            corr[name] = (Cdt[:, j] / (sd_d * sd_t[j])).tolist() if informed else [0.0] * G
    except torch.linalg.LinAlgError:
        pass
    k = 1 / M_TO_CM  # learned in cm (the depths' unit), reported in m
    return SurfaceEstimate(surface.offset.detach().clone() * k, std.detach() * k, cond.detach() * k,
                           cov.detach() * k**2, corr)


def init_surface(model, offsets) -> Tensor:
    """``InverseRFT.init_surface``: start the model's surface offset(s) at the best of ``offsets`` (m, a grid) by the
    loss at the current hyperparameters, one group at a time (the others held). Returns the start (G,) in m."""
    surface = model.surface
    if surface is None:
        raise AttributeError("this model has no learned surface offset (InverseRFT(..., surface=True))")
    grid = torch.as_tensor(offsets, dtype=model.dtype, device=model._device).reshape(-1) * M_TO_CM  # learned in cm
    with torch.no_grad():
        for g in range(surface.n_groups):
            losses = []
            for v in grid:
                surface.offset[g] = v
                losses.append(float(surface_loss(model)))
            surface.offset[g] = grid[int(torch.tensor(losses).argmin())]
    model._rebuild_backend()  # predictions at the chosen offset, as after fit and load
    model.eval()
    return surface.offset.detach().clone() / M_TO_CM


def surface_loss(model) -> Tensor:
    """The loss of a model that learns the surface while its offsets move: the negative log likelihood per sample
    of its data at the current offsets, minus the log hyperparameter prior / T."""
    c, f, _ = model._join()
    surface = model.surface
    nll = surface_negative_log_likelihood(model.hypers, surface.shifted(c), f, surface.table, surface.index)
    return nll.sum() - model.backend.log_prior() / max(len(f), 1)
