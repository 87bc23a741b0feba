r"""Backends of 3-D I-RFT: the block covariance of ``hyperparameters`` computed exactly in the smallest space.

Each block b (horizontal: rows F_x then F_y, maps alpha_x, alpha_y; vertical: rows F_z, map alpha_z) is a
Gaussian linear model F_b = sum_c W_bc alpha_c + eps with one noise variance per row group (axis).

- ``"observations"``: the n_b x n_b covariance sum_c W_bc K_c W_bc^T + D_b, each term the planar library's
  lazy W K W^T (``RFTKernelLinearOperator``) over the rows' elements, made dense; a constant alpha_y is
  s_y (W 1)(W 1)^T. For few samples with few elements each (toes).
- ``"pairs"``: u_c = map c at the U distinct angle pairs of the data, Sigma_c = K_c(U, U): exact, O(U^3).
- ``"spectral"``: u_c = Fourier coefficients on the angle torus (``gp.kernels.fourier``), Sigma_c = s_c Sigma_beta
  kron Sigma_gamma, a basis per map: exact up to the reported truncation; the wheels' tens of thousands of
  elements per run enter once, as T x F features (``spectral.Spectral3D``, on this module's ``WeightSpace3D``;
  ``select.make_backend_3d`` chooses among the three).

With ``kernel="li"`` each map over (beta, gamma) adds Li et al.'s rank-9 term (``gp.kernels.li_basis``): v_c (W
f)(W' f)^T in the observations' space, f_U diag(v_c) f_U^T on the pairs table, v_c / 4 on the 9 first-harmonic weights.

The weight-space pair (pairs, spectral) share one algebra. Per block, the rows of each axis a (group g)
are reduced once, hyperparameter-free, to R_g (r_g x F), c_g = Q_g^T y_g and rho_g = |y_g|^2 - |c_g|^2
(from Phi_g's rows, ``weight_space.data_factor_from_rows``). With R~ = [R_g / sigma_g], c~ = [c_g /
sigma_g] stacked over the groups and A = R~ Sigma R~^T, exactly (Woodbury and Sylvester, D = diag(sigma_g^2)):

    y^T (D + Phi Sigma Phi^T)^{-1} y = sum_g rho_g / sigma_g^2 + c~^T (I + A)^{-1} c~
    log |D + Phi Sigma Phi^T|       = sum_g n_g log sigma_g^2 + log |I + A|

one Cholesky of I + A (r = sum r_g <= n_b) per step, no inverse or root of Sigma; with one group it is the
planar ``WeightSpaceBackend``'s formula. Posterior of query rows with features Phi_q: mean Phi_q Sigma v,
v = H^T L^{-1} c~, covariance Phi_q Sigma Phi_q^T - (H Sigma Phi_q^T)^T (H Sigma Phi_q^T), H = L^{-1} R~.
"""

from __future__ import annotations

import copy
import math
from typing import TYPE_CHECKING, cast

import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor, nn

from ...rft.contacts3d import Contacts3D
from ..backends.weight_space import data_factor_from_rows
from ..kernels.embedding import embed_angles, rbf
from ..kernels.hyperparameters import RFT3DHyperparameters
from ..kernels.li_basis import li_features, weighted_li_features
from ..kernels.operators import RFTKernelLinearOperator, unique_pairs
from .features import SpectralFeatureBank, spectral_features
from .joint import BlockRows
from .rows import BLOCKS, block_rows, block_targets, point_contacts

__all__ = ["Backend3D", "Observations3D", "WeightSpace3D", "Pairs3D", "block_rows", "block_targets",
           "SpectralFeatureBank", "spectral_features"]

ONE = torch.Size([1])


def _pack(c: Contacts3D, parts: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor]:
    """Per-sample (T, 3) means and (T, 3, 3) covariances from the blocks' (mean (n,), cov (n, n) or the per-sample
    blocks (T, A, A))."""
    T = len(c)
    mean = c.beta.new_zeros(T, 3)
    cov = c.beta.new_zeros(T, 3, 3)
    for block, (m, s) in zip(BLOCKS, parts):
        A = len(block.axes)
        mean[:, list(block.axes)] = m.reshape(A, T).T
        idx = torch.tensor(block.axes, device=cov.device)
        cov[:, idx[:, None], idx[None, :]] = s
    return mean, cov


def _sample_blocks(cov: Tensor, A: int, T: int) -> Tensor:
    """(n, n) covariance of axis-major rows -> (T, A, A): each sample's own block."""
    return cov.reshape(A, T, A, T).diagonal(dim1=1, dim2=3).permute(2, 0, 1)


class Backend3D(nn.Module):
    """One interface: ``negative_log_likelihood`` (2,) per block / T, ``loss``, ``posterior`` of any
    ``Contacts3D`` (per sample (T, 3) mean and (T, 3, 3) covariance, or the blocks' joint covariances)."""

    name = "base"

    def __init__(self, hypers: RFT3DHyperparameters, contacts: Contacts3D, forces: Tensor) -> None:
        super().__init__()
        self.hypers = hypers
        self.n_samples = len(contacts)
        self.train_contacts, self.train_forces = contacts, forces
        self.in_fit = False

    def negative_log_likelihood(self) -> Tensor:
        raise NotImplementedError

    def _block_posterior(self, b: int, c: Contacts3D, full: bool) -> tuple[Tensor, Tensor]:
        """Mean (n,) and covariance (n, n) of the block's rows of c (full) or each sample's (T, A, A)."""
        raise NotImplementedError

    def loss(self) -> Tensor:
        """Negative log marginal likelihood per sample summed over the blocks, minus log prior / T (MAP)."""
        return self.negative_log_likelihood().sum() - self.log_prior() / max(self.n_samples, 1)

    def log_prior(self) -> Tensor:
        """Sum of the log densities of the hyperparameter priors registered on the shared modules."""
        return self.hypers.log_prior()

    def posterior(self, c: Contacts3D, joint: bool = False):
        """Posterior of the weighted sums of c: (mean (T, 3), covariance (T, 3, 3)) per sample; with ``joint``,
        also the blocks' joint covariances [(2T, 2T) horizontal, (T, T) vertical]."""
        parts, joints = [], []
        for b, block in enumerate(BLOCKS):
            m, cov = self._block_posterior(b, c, full=joint)
            if joint:
                joints.append(cov)
                cov = _sample_blocks(cov, len(block.axes), len(c))
            parts.append((m, cov))
        mean, cov = _pack(c, parts)
        return (mean, cov, joints) if joint else (mean, cov)

    # ---- the prior covariance of two row sets, through the kernel (dense, any element counts) -------------------
    @staticmethod
    def _structure(b1, g1, w1, b2, g2, w2, same=False):
        with torch.no_grad():
            return RFTKernelLinearOperator.segment_structure(b1[None], g1[None], w1[None], b2[None], g2[None],
                                                             w2[None], ONE, same_inputs=same)

    def _term(self, c: int, structure, r1: tuple, r2: tuple, detach: bool) -> Tensor:
        """Prior covariance of two row sets r = (beta, gamma, weights of map c) (n, K) through map c (n1, n2)."""
        ls, os = self.hypers.lengthscale[c:c + 1], self.hypers.outputscale[c:c + 1]
        if detach:
            ls, os = ls.detach(), os.detach()
        if self.hypers.constant_map(c):
            return os[0] * r1[2].sum(-1)[:, None] * r2[2].sum(-1)[None, :]
        K = RFTKernelLinearOperator.from_structure(structure, ls, os, ONE).to_dense()[0]
        v = self.hypers.li_of(c, detach)
        return K if v is None else K + v * weighted_li_features(*r1) @ weighted_li_features(*r2).mT

    def _cross(self, b: int, q: tuple, t: tuple, same: bool) -> Tensor:
        """Prior covariance (n_q, n_t) of two row sets of block b (``block_rows``: beta, gamma, weights per map)."""
        out: Tensor | int = 0
        for i, c in enumerate(BLOCKS[b].maps):
            s = None if self.hypers.constant_map(c) else \
                self._structure(q[0], q[1], q[2][i], t[0], t[1], t[2][i], same=same)
            out = out + self._term(c, s, (q[0], q[1], q[2][i]), (t[0], t[1], t[2][i]), detach=True)
        return cast(Tensor, out)  # a block has at least one map

    # ---- streaming and hyperparameter draws ------------------------------------------------------------------------
    def add_data(self, contacts: Contacts3D, forces: Tensor) -> None:
        """Append samples at fixed hyperparameters: the posterior becomes exactly a batch fit's on all of them.
        Every data structure is replaced, never changed in place (draws' backends share them)."""
        self.train_contacts = Contacts3D.cat([self.train_contacts, contacts.to(self.train_contacts.beta)])
        self.train_forces = torch.cat([self.train_forces, forces.to(self.train_forces)])
        self.n_samples = len(self.train_contacts)
        self._data_changed(contacts, forces)
        self._reset()

    def _part_rows(self, b: int, part: Contacts3D) -> tuple:
        """Block b's rows q of ``part`` (``rows.block_rows``), their posterior mean (n,), the data's part G (r, n) of
        their covariance and, where the prior is in features, (Phi_q Sigma, Phi_q), else None (``joint.BlockRows``)."""
        raise NotImplementedError

    def _data_changed(self, contacts: Contacts3D, forces: Tensor) -> None:
        """Bring the hyperparameter-free structures up to the data after ``add_data`` appended (contacts, forces)."""

    def _reset(self) -> None:
        """Forget what depends on the hyperparameters (cached factors)."""

    def forget_draws(self) -> None:
        """Drop what evaluating a batch of hyperparameter draws kept (nothing here)."""

    def with_hypers(self, hypers: RFT3DHyperparameters) -> Backend3D:
        """This backend at other hyperparameters (a hyperparameter posterior's draw): the data and whatever does
        not depend on the hyperparameters are shared (pairs table and data factors; spectral features wherever the
        basis still serves the draw's lengthscales, else grown for it)."""
        new = copy.copy(self)
        new._parameters, new._buffers, new._modules = dict(self._parameters), dict(self._buffers), dict(self._modules)
        new._modules["hypers"] = hypers
        new._reset()
        new.refresh()
        return new

    def truncation_error(self) -> Tensor:
        return self.hypers.kernel.outputscale.detach().new_zeros(3)

    def loss_and_grad(self) -> None:
        """No closed-form gradient (the fit loop takes ``loss()`` and autograd)."""
        return None

    def shrink(self) -> bool:
        """The spectral bases do not shrink back during a fit (they grow with ``refresh``)."""
        return False

    def condition(self, contacts: Contacts3D, forces: Tensor | None = None) -> Backend3D:
        """A new backend that has also seen these samples (without forces: as if they equalled their posterior mean;
        the covariance does not depend on them); this one is unchanged."""
        new = self.with_hypers(self.hypers)
        with torch.no_grad():
            new.add_data(contacts, self.posterior(contacts)[0] if forces is None else forces)
        return new

    # ---- what a probe scorer asks (``design.ProbeScorer``), in the planar backends' terms ---------------------------
    contacts_type = Contacts3D
    n_blocks = len(BLOCKS)

    def root_size(self) -> None:
        return None

    def region_rows(self, region) -> list[BlockRows]:
        """The maps at a region's points (``beta``, ``gamma`` (N,)) as each block's rows (horizontal: alpha_x at
        every point, then alpha_y; vertical: alpha_z)."""
        h = self.hypers.noise
        pts = point_contacts(region.beta.to(h), region.gamma.to(h))
        return [BlockRows(self, b, [pts]) for b in range(len(BLOCKS))]

    def region_variance(self, rows: list[BlockRows]) -> Tensor:
        """(2, n') those rows' posterior variances per block, zero-padded to the longest."""
        var = [r.variance(0) for r in rows]
        return torch.stack([torch.nn.functional.pad(v, (0, max(len(u) for u in var) - len(v))) for v in var])

    def candidate_rows(self, cands: list[Contacts3D], rows: list[BlockRows] | None = None) -> tuple:
        """Each candidate's force rows per block, zero-padded to the longest (a padded row has noise 1 and no
        covariance: it adds nothing to a score): S (B, 2, n, n) their posterior covariance (noise not included),
        noise (B, 2, n) each row's noise variance, and their posterior covariance (B, 2, n, n') with ``rows``
        (``region_rows``), or None."""
        nz = self.hypers.noise.detach()
        n = max([len(bl.axes) * len(c) for c in cands for bl in BLOCKS] + [0])
        S, noise = nz.new_zeros(len(cands), 2, n, n), nz.new_ones(len(cands), 2, n)
        cross = None if rows is None else nz.new_zeros(len(cands), 2, n, max(len(r.rows[0][0]) for r in rows))
        for i, c in enumerate(cands):
            for b, block in enumerate(BLOCKS):
                k = len(block.axes) * len(c)
                if k == 0:  # a candidate of no samples: nothing observed (its rows stay padding)
                    continue
                noise[i, b, :k] = torch.cat([nz[a].expand(len(c)) for a in block.axes])
                if rows is None:
                    S[i, b, :k, :k] = BlockRows(self, b, [c]).cov(0, 0)
                else:
                    ext = rows[b].extended([c])
                    S[i, b, :k, :k] = ext.cov(1, 1)
                    cr = ext.cov(1, 0)
                    cross[i, b, :k, :cr.shape[1]] = cr
        return S, noise, cross

    @staticmethod
    def fold_maps(x: Tensor) -> Tensor:
        """(..., 2, n') values of ``region_rows``' rows -> (..., 3, N) per map (alpha_x, alpha_y, alpha_z)."""
        N = x.shape[-1] // 2
        return torch.cat([x[..., b, :len(bl.maps) * N].unflatten(-1, (len(bl.maps), N)) for b, bl in enumerate(BLOCKS)],
                         -2)

    def map_moments(self, beta, gamma) -> tuple[Tensor, Tensor]:
        """Posterior mean and variance (N, 3) of the maps at angles of any broadcast shape (N of them), N/cm^3 and
        (N/cm^3)^2."""
        h = self.hypers.noise
        b, g = torch.broadcast_tensors(torch.as_tensor(beta, dtype=h.dtype, device=h.device),
                                       torch.as_tensor(gamma, dtype=h.dtype, device=h.device))
        mean, cov = self.posterior(point_contacts(b, g))
        return mean, torch.diagonal(cov, dim1=-2, dim2=-1)


    def stale(self) -> bool:
        return False

    def refresh(self) -> bool:
        return False

    def describe(self) -> str:
        return f"{self.name}: T={self.n_samples}"

    @staticmethod
    def _gaussian_nll(quad: Tensor, logdet: Tensor, n: int) -> Tensor:
        return 0.5 * (quad + logdet + n * math.log(2 * math.pi))


# ---- observations ---------------------------------------------------------------------------------------------------
class Observations3D(Backend3D):
    """Exact 3-D I-RFT in the space of the observations (per block n_b x n_b, one Cholesky per step)."""

    name = "observations"

    def __init__(self, hypers, contacts: Contacts3D, forces: Tensor) -> None:
        super().__init__(hypers, contacts, forces)
        self._data_changed(contacts, forces)
        self._factor_cache = None

    def _data_changed(self, contacts, forces) -> None:
        self._train = [block_rows(self.train_contacts, b) for b in BLOCKS]
        self._structures = [[self._structure(rows[0], rows[1], w, rows[0], rows[1], w, same=True)
                             for w in rows[2]] for rows in self._train]

    def _reset(self) -> None:
        self._factor_cache = None

    def _train_cov(self, b: int, detach: bool) -> Tensor:
        block, (beta, gamma, ws) = BLOCKS[b], self._train[b]
        K = cast(Tensor, sum(self._term(c, s, (beta, gamma, w), (beta, gamma, w), detach)
                             for c, s, w in zip(block.maps, self._structures[b], ws)))
        noise = self.hypers.noise.detach() if detach else self.hypers.noise
        d = torch.cat([noise[a].expand(self.n_samples) for a in block.axes])
        return 0.5 * (K + K.mT) + torch.diag(d)

    def negative_log_likelihood(self) -> Tensor:
        out = []
        for b, block in enumerate(BLOCKS):
            C = self._train_cov(b, detach=False)
            L = psd_safe_cholesky(C)
            y = block_targets(self.train_forces, block)
            z = torch.linalg.solve_triangular(L, y[:, None], upper=False)[:, 0]
            nll = self._gaussian_nll(z.pow(2).sum(), 2 * torch.log(torch.diagonal(L)).sum(), y.shape[0])
            out.append(nll / self.n_samples)
        return torch.stack(out)

    def _factor(self):
        key = torch.cat([p.detach().reshape(-1) for p in self.hypers.parameters()])
        if self._factor_cache is None or not torch.equal(self._factor_cache[0], key):
            with torch.no_grad():
                out = []
                for b, block in enumerate(BLOCKS):
                    L = psd_safe_cholesky(self._train_cov(b, detach=True))
                    y = block_targets(self.train_forces, block)
                    out.append((L, torch.cholesky_solve(y[:, None], L)[:, 0]))
            self._factor_cache = (key, out)
        return self._factor_cache[1]

    def _part_rows(self, b: int, part: Contacts3D) -> tuple:
        """Block b's rows q of ``part`` with their posterior mean (n,) and data part G = L^{-1} K(train, q) (r, n)
        (``joint.BlockRows``); no features (None: the prior through the kernel)."""
        L, alpha = self._factor()[b]
        q = block_rows(part, BLOCKS[b])
        Kqt = self._cross(b, q, self._train[b], same=False)
        return q, Kqt @ alpha, torch.linalg.solve_triangular(L, Kqt.mT, upper=False), None

    def _block_posterior(self, b, c, full):
        q, mean, V, _ = self._part_rows(b, c)
        A, T = len(BLOCKS[b].axes), len(c)
        if full:
            cov = self._cross(b, q, q, same=True) - V.mT @ V
            return mean, 0.5 * (cov + cov.mT)
        # each sample's A x A block: prior blocks from the per-sample rows, minus the data's part
        prior = c.beta.new_zeros(T, A, A)
        for t0 in range(0, T, 256):
            sl = slice(t0, min(T, t0 + 256))
            sub = block_rows(c[sl], BLOCKS[b])
            prior[sl] = _sample_blocks(self._cross(b, sub, sub, same=True), A, sl.stop - sl.start)
        Vs = V.reshape(V.shape[0], A, T)
        return mean, prior - torch.einsum("rat,rbt->tab", Vs, Vs)


# ---- weight space (pairs, spectral) ---------------------------------------------------------------------------------
class WeightSpace3D(Backend3D):
    """Shared algebra of the weight-space backends (module doc). Subclasses give the features of rows,
    ``_features(c, b)`` -> Phi (n, F_b) (the maps' features side by side), and ``_sigma(b, X, detach)`` -> X Sigma_b."""

    if TYPE_CHECKING:  # what the subclasses provide
        def _features(self, c: Contacts3D, b: int) -> Tensor: ...
        def _sigma(self, b: int, X: Tensor, detach: bool) -> Tensor: ...

    def __init__(self, hypers, contacts, forces) -> None:
        super().__init__(hypers, contacts, forces)
        # per block, per force axis: the data factor (R, c_y, rho)
        self._factors: list[list[tuple[Tensor, Tensor, Tensor]]] | None = None
        # (the factors, the hyperparameters' key, per block (H, H^T z)): the posterior's terms
        self._post_cache: tuple[list, Tensor, list[tuple[Tensor, Tensor]]] | None = None

    def _reset(self) -> None:
        self._post_cache = None

    def _merge_rows(self, contacts: Contacts3D, forces: Tensor) -> None:
        """The data factors of the old rows and new ones, exactly: stacking [R_g; Phi_new] and [c_g; y_new] keeps
        Phi^T Phi, Phi^T y and |y|^2 (the factor's whole content), and rho adds up."""
        T = len(contacts)
        merged = []
        with torch.no_grad():
            for b, block in enumerate(BLOCKS):
                Phi = self._features(contacts, b)
                y = block_targets(forces.to(Phi), block)
                groups = []
                for g, (R, cy, rho) in enumerate(self._factors[b]):
                    rows = slice(g * T, (g + 1) * T)
                    f = data_factor_from_rows(torch.cat([R, Phi[rows]])[None], torch.cat([cy, y[rows]])[None], None,
                                              Phi.dtype)
                    groups.append((f.R[0], f.c_y[0], rho + f.rho[0, 0]))
                merged.append(groups)
        self._factors = merged

    def _set_features(self) -> None:
        """(Re)compute the training rows' data factors, hyperparameter-free (kept only once all are computed: an
        interrupt part way leaves the old ones)."""
        factors: list[list[tuple[Tensor, Tensor, Tensor]]] = []
        T = self.n_samples
        with torch.no_grad():
            for b, block in enumerate(BLOCKS):
                Phi = self._features(self.train_contacts, b)
                y = block_targets(self.train_forces, block)
                groups = []
                for g in range(len(block.axes)):
                    f = data_factor_from_rows(Phi[None, g * T:(g + 1) * T], y[None, g * T:(g + 1) * T], None,
                                              Phi.dtype)
                    groups.append((f.R[0], f.c_y[0], f.rho[0, 0]))
                factors.append(groups)
        self._factors, self._post_cache = factors, None

    def _system(self, b: int, detach: bool):
        block, groups = BLOCKS[b], self._factors[b]
        noise = self.hypers.noise.detach() if detach else self.hypers.noise
        # R~ = diag(scale) R: A = scale scale^T * (R Sigma R^T), so that the noise's gradient skips the big product
        R = torch.cat([R for (R, _, _) in groups])
        scale = torch.cat([noise[a].rsqrt().expand(len(cy)) for (_, cy, _), a in zip(groups, block.axes)])
        Rt = R * scale[:, None]
        ct = torch.cat([cy for (_, cy, _) in groups]) * scale
        A = (self._sigma(b, R, detach) @ R.mT) * (scale[:, None] * scale[None, :])
        eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
        L = torch.linalg.cholesky(0.5 * (A + A.mT) + eye)
        quad0 = sum(rho / noise[a] for (_, _, rho), a in zip(groups, block.axes))
        logdet0 = sum(self.n_samples * torch.log(noise[a]) for a in block.axes)
        return L, Rt, ct, quad0, logdet0

    def negative_log_likelihood(self) -> Tensor:
        out = []
        for b, block in enumerate(BLOCKS):
            L, _, ct, quad0, logdet0 = self._system(b, detach=False)
            z = torch.linalg.solve_triangular(L, ct[:, None], upper=False)[:, 0]
            logdet = logdet0 + 2 * torch.log(torch.diagonal(L)).sum()
            out.append(self._gaussian_nll(quad0 + z.pow(2).sum(), logdet, self.n_samples * len(block.axes))
                       / self.n_samples)
        return torch.stack(out)

    def _terms(self, b: int):
        key = torch.cat([p.detach().reshape(-1) for p in self.hypers.parameters()])
        if self._post_cache is None or self._post_cache[0] is not self._factors or \
                not torch.equal(self._post_cache[1], key):
            with torch.no_grad():
                out = []
                for bb in range(len(BLOCKS)):
                    L, Rt, ct, _, _ = self._system(bb, detach=True)
                    H = torch.linalg.solve_triangular(L, Rt, upper=False)
                    z = torch.linalg.solve_triangular(L, ct[:, None], upper=False)[:, 0]
                    out.append((H, H.mT @ z))
            self._post_cache = (self._factors, key, out)
        return self._post_cache[2][b]

    def _part_rows(self, b: int, part: Contacts3D) -> tuple:
        """Block b's rows q of ``part``, their posterior mean (n,), data part G = H Sigma Phi_q^T (r, n) and features
        (Phi_q Sigma, Phi_q) (``joint.BlockRows``)."""
        H, v = self._terms(b)
        Phi = self._features(part, b)
        C = self._sigma(b, Phi, detach=True)  # Phi Sigma
        return block_rows(part, BLOCKS[b]), C @ v, H @ C.mT, (C, Phi)

    def _block_posterior(self, b, c, full):
        q, mean, G, feat = self._part_rows(b, c)
        A, T = len(BLOCKS[b].axes), len(c)
        if feat is None:  # pairs at angles off the table: the prior through the kernel
            cov = self._cross(b, q, q, same=True) - G.mT @ G
            return (mean, 0.5 * (cov + cov.mT)) if full else (mean, _sample_blocks(cov, A, T))
        C, Phi = feat
        if full:
            cov = C @ Phi.mT - G.mT @ G
            return mean, 0.5 * (cov + cov.mT)
        Cs, Ps, Gs = C.reshape(A, T, -1), Phi.reshape(A, T, -1), G.reshape(G.shape[0], A, T)
        prior = torch.einsum("atf,btf->tab", Cs, Ps)
        return mean, prior - torch.einsum("rat,rbt->tab", Gs, Gs)


class Pairs3D(WeightSpace3D):
    """Exact 3-D I-RFT in the space of the data's U distinct (beta, gamma) pairs: u_c = map c there,
    Sigma_c = K_c(U, U) (alpha_x and alpha_y share the table)."""

    name = "pairs"

    def __init__(self, hypers, contacts, forces) -> None:
        super().__init__(hypers, contacts, forces)
        self._data_changed(contacts, forces)

    def _data_changed(self, contacts, forces) -> None:
        """The table of all samples' distinct pairs and their data factors, anew (a new sample may add pairs)."""
        c = self.train_contacts
        live = c.in_contact()
        pairs = torch.stack([c.beta[live], c.gamma[live]], -1)
        self.table = unique_pairs(pairs.detach())[0] if pairs.shape[0] else c.beta.new_zeros(1, 2)
        self._set_features()

    def describe(self) -> str:
        return f"pairs: T={self.n_samples}, U={self.table.shape[0]} distinct angle pairs"

    def _index(self, c: Contacts3D) -> Tensor:
        live = c.in_contact()
        own = torch.stack([c.beta[live], c.gamma[live]], -1)
        U = self.table.shape[0]
        both, inverse = unique_pairs(torch.cat([self.table, own.detach()]))
        if both.shape[0] != U:  # a query pair not in the table: not representable in this space
            return None
        remap = torch.empty(U, dtype=torch.long, device=c.beta.device)
        remap[inverse[:U]] = torch.arange(U, device=c.beta.device)
        idx = torch.zeros(c.shape, dtype=torch.long, device=c.beta.device)
        return idx.masked_scatter(live, remap[inverse[U:]])

    def _features(self, c: Contacts3D, b: int) -> Tensor:
        idx = self._index(c)
        block = BLOCKS[b]
        _, _, ws = block_rows(c, block)
        A = len(block.axes)
        out = []
        for i, m in enumerate(block.maps):
            if self.hypers.constant_map(m):
                out.append(ws[i].sum(-1, keepdim=True))
            elif idx is not None:
                j = idx.repeat(A, 1)
                out.append(ws[i].new_zeros(j.shape[0], self.table.shape[0]).scatter_add(-1, j, ws[i]))
            else:
                raise _OffTable()
        return torch.cat(out, -1)

    def _K(self, m: int, detach: bool) -> Tensor:
        ls, s = self.hypers.lengthscale[m], self.hypers.outputscale[m]
        if detach:
            ls, s = ls.detach(), s.detach()
        z = embed_angles(self.table[:, 0], self.table[:, 1]) / ls
        v = self.hypers.li_of(m, detach)
        if v is None:
            return rbf(z, z, s)
        f = li_features(self.table[:, 0], self.table[:, 1])  # (U, 9)
        return rbf(z, z, s) + v * f @ f.mT

    def _sigma(self, b: int, X: Tensor, detach: bool) -> Tensor:
        out, start, U = [], 0, self.table.shape[0]
        for m in BLOCKS[b].maps:
            if self.hypers.constant_map(m):
                s = self.hypers.outputscale[m]
                out.append(X[:, start:start + 1] * (s.detach() if detach else s))
                start += 1
            else:
                out.append(X[:, start:start + U] @ self._K(m, detach))
                start += U
        return torch.cat(out, -1)

    def _part_rows(self, b: int, part: Contacts3D) -> tuple:
        try:
            return super()._part_rows(b, part)
        except _OffTable:  # angles the table does not hold: Cov(q, u) through the kernel, the same H and v
            H, v = self._terms(b)
            q = block_rows(part, BLOCKS[b])
            C = table_columns(self, b, q)
            return q, C @ v, H @ C.mT, None


class _OffTable(Exception):
    pass


def table_columns(backend: Pairs3D, b: int, q: tuple) -> Tensor:
    """Cov(rows q, u) (n, F_b) with u the block's maps at the pairs table: W_q K(q, table) per map side by side
    (a constant alpha_y: s_y W_q 1). For rows whose angles are off the table."""
    beta, gamma, ws = q
    tb, tg = backend.table[:, :1], backend.table[:, 1:]
    ones = torch.ones_like(tb)
    cols = []
    for i, m in enumerate(BLOCKS[b].maps):
        if backend.hypers.constant_map(m):
            cols.append(ws[i].sum(-1, keepdim=True) * backend.hypers.outputscale[m].detach())
        else:
            st = backend._structure(beta, gamma, ws[i], tb, tg, ones)
            cols.append(backend._term(m, st, (beta, gamma, ws[i]), (tb, tg, ones), detach=True))
    return torch.cat(cols, -1)
