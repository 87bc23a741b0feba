r"""Active probing: score a candidate probe (toe + path) by what it would teach, before running it.

A GP's posterior covariance does not depend on the measured values, so the information a probe
would bring follows from its contacts alone. For a candidate with contacts c (T_c rows), per map
axis a in (x, z), let Sigma_a be the current posterior covariance of its forces (T_c x T_c,
segments correlated: w^T Sigma w) and sigma_a^2 the force noise. Then

    EIG = sum_a 1/2 log | I + Sigma_a / sigma_a^2 |            (nats: the mutual information
                                                                between the maps and its forces)
    IV  = sum_a sum_j r_j [ v_a(theta_j) - k_aj^T (Sigma_a + sigma_a^2 I)^-1 k_aj ] / s_a
                                                               (the expected integrated variance of
                                                                the maps over a region after it)

with v_a(theta_j) the current map variance at the region's points theta_j, k_aj the covariance
between the map there and the probe's forces, r_j the region's weights (summing to 1) and s_a the
prior variance, so IV is 2 for the prior and 0 for maps known exactly.

``ProbeScorer`` holds the current belief over both maps in one of two forms:

- ``"exact"``: the training forces' covariance W K W^T + noise factored once (L L^T); a candidate
  costs one lazy kernel block against the training segments and one triangular solve. It matches a
  dense computation to round-off.
- ``"grid"``: the posterior covariance of the maps at the nodes of a (beta, gamma) grid (exact at
  the nodes, for either kind of model), read between nodes by bilinear interpolation as the grid
  path does; a candidate then costs a few small matrix products, whatever the amount of training
  data. On the grid path (``InverseRFT(method="grid")``) this is the model's own posterior.

Conditioning on a probe (``ProbeScorer.condition``) updates the factor without touching the model;
``greedy_design`` chains it. Everything is differentiable in the candidate's contacts, so a path can
be designed by gradient descent (``irft_torch.probe_design``).

Example:
    >>> scorer = ProbeScorer.from_model(model)              # or ProbeScorer.prior(...)
    >>> scores = scorer.score([p.contacts() for p in probes], criterion="variance")
    >>> steps = greedy_design(scorer, probes, budget=3)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor

from ..rft.contacts import Contacts
from ..rft.stress_maps import mirror_to_canonical
from .grid import AngleGrid
from .operators import RFTKernelLinearOperator

__all__ = ["Region", "ProbeScorer", "DesignStep", "greedy_design"]

_BATCH = torch.Size([2])


# ---- regions of interest -------------------------------------------------------------------
@dataclass
class Region:
    """Points of the (beta, gamma) square with weights, over which the map variance is integrated.

    Attributes:
        beta, gamma: (N,) angles in rad (mapped into the canonical square on construction).
        weight: (N,) non-negative weights, normalized to sum to 1 on construction.
    """

    beta: Tensor
    gamma: Tensor
    weight: Tensor

    def __post_init__(self) -> None:
        b, g, w = (torch.as_tensor(v, dtype=torch.get_default_dtype()) for v in (self.beta, self.gamma, self.weight))
        if b.ndim != 1 or b.shape != g.shape or b.shape != w.shape or b.numel() == 0:
            raise ValueError(f"Region needs beta, gamma, weight of one shape (N,), got {tuple(b.shape)}, "
                             f"{tuple(g.shape)}, {tuple(w.shape)}")
        for name, v in (("beta", b), ("gamma", g), ("weight", w)):
            if not torch.isfinite(v).all():
                raise ValueError(f"Region.{name} contains NaN or inf")
        if (w < 0).any() or w.sum() <= 0:
            raise ValueError("Region.weight must be >= 0 with a positive sum")
        self.beta, self.gamma, _ = mirror_to_canonical(b, g)
        self.weight = w / w.sum()

    @classmethod
    def square(cls, n: int = 16, dtype=torch.float64) -> Region:
        """An n x n grid of cell centres over the canonical square, equal weights."""
        e = torch.linspace(-math.pi / 2, math.pi / 2, n + 1, dtype=dtype)
        c = (e[1:] + e[:-1]) / 2
        B, G = torch.meshgrid(c, c, indexing="ij")
        return cls(B.reshape(-1), G.reshape(-1), torch.ones(n * n, dtype=dtype))

    @classmethod
    def sign_change(cls, n: int = 16, gamma_min: float = math.pi / 3, dtype=torch.float64) -> Region:
        """The region the I-RFT paper calls informative: gamma > ``gamma_min`` (default pi/3), where
        alpha_x changes sign with beta."""
        sq = cls.square(n, dtype)
        return cls(sq.beta, sq.gamma, (sq.gamma > gamma_min).to(dtype))

    def contacts(self) -> Contacts:
        """The region's points as (N, 1) point evaluations (weight 1 on both axes)."""
        one = torch.ones_like(self.beta)[:, None]
        return Contacts(self.beta[:, None], self.gamma[:, None], one, one)


def _as_contacts(c) -> Contacts:
    """A Contacts, or anything with a ``contacts()`` method (an ``rft.Probe``)."""
    if isinstance(c, Contacts):
        out = c
    elif hasattr(c, "contacts"):
        out = c.contacts()
    else:
        raise TypeError(f"a candidate must be a Contacts or have a contacts() method (a Probe), got {type(c).__name__}")
    if out.beta.ndim != 2:
        raise ValueError(f"a candidate's contacts must be (T, M), got {tuple(out.shape)}")
    return out


def _axis_stack(c: Contacts) -> tuple[Tensor, Tensor, Tensor]:
    """Angles (1, T, M) and the (x, z) weights stacked (2, T, M)."""
    return c.beta[None], c.gamma[None], torch.stack([c.weight_x, c.weight_z])


# ---- the two forms of the belief -----------------------------------------------------------
@dataclass
class _Handle:
    """What a belief needs of a set of contacts. Exact: the contacts' segment table (``side``) and
    A = L^-1 K(train, c); grid: the interpolation Phi (2, T, U) (``a``) and G = Phi Sigma (``b``)."""

    contacts: Contacts
    a: Tensor
    b: Tensor | None = None
    side: dict | None = None


def _plus_noise(S: Tensor, noise: Tensor) -> Tensor:
    """(S + S^T) / 2 + diag(noise_a) per axis: a force covariance (2, T, T) plus the force noise."""
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    return 0.5 * (S + S.mT) + noise[:, None, None] * eye


def _side(c: Contacts) -> dict:
    """One side of a W1 K W2^T: the contacts' non-zero segments and their distinct angle pairs."""
    b, g, w = _axis_stack(c)
    return RFTKernelLinearOperator.segment_structure(b, g, w, b, g, w, _BATCH, same_inputs=True)


class _ExactBelief:
    """Training contacts and the Cholesky factor of their force covariance, per axis."""

    def __init__(self, lengthscale: Tensor, outputscale: Tensor, noise: Tensor, train: Contacts | None,
                 L: Tensor | None = None) -> None:
        self.lengthscale, self.outputscale, self.noise = lengthscale, outputscale, noise
        self.train = train if train is not None and len(train) > 0 else None
        self.train_side = _side(self.train) if self.train is not None else None
        if self.train is not None and L is None:
            K = self.kernel(self.train_side, self.train_side)
            L = psd_safe_cholesky(_plus_noise(K, self.noise))
        self.L = L

    def kernel(self, side1: dict, side2: dict) -> Tensor:
        """Prior covariance (2, T1, T2) of two sets of weighted sums: the lazy W1 K W2^T, made dense.
        The sides' segment tables are computed once per set of contacts and reused."""
        structure = {"pairs1": side1["pairs1"], "i1": side1["i1"], "w1": side1["w1"], "pairs2": side2["pairs1"],
                     "i2": side2["i1"], "w2": side2["w1"], "same": side1 is side2}
        op = RFTKernelLinearOperator.from_structure(structure, self.lengthscale, self.outputscale, _BATCH)
        return op.to_dense()

    def handle(self, c: Contacts) -> _Handle:
        side = _side(c)
        if self.train is None:
            return _Handle(c, c.beta.new_zeros(2, 0, len(c)), side=side)
        A = torch.linalg.solve_triangular(self.L, self.kernel(self.train_side, side), upper=False)
        return _Handle(c, A, side=side)

    def cov(self, h1: _Handle, h2: _Handle) -> Tensor:
        return self.kernel(h1.side, h2.side) - h1.a.mT @ h2.a

    def condition(self, h: _Handle) -> _ExactBelief:
        S = self.cov(h, h)
        L22 = psd_safe_cholesky(_plus_noise(S, self.noise))
        if self.train is None:
            return _ExactBelief(self.lengthscale, self.outputscale, self.noise, h.contacts, L22)
        T, Tc = self.L.shape[-1], L22.shape[-1]
        L = self.L.new_zeros(2, T + Tc, T + Tc)
        L[:, :T, :T] = self.L
        L[:, T:, :T] = h.a.mT
        L[:, T:, T:] = L22
        return _ExactBelief(self.lengthscale, self.outputscale, self.noise, Contacts.cat([self.train, h.contacts]), L)


class _GridBelief:
    """The posterior covariance Sigma (2, U, U) of both maps at the nodes of an AngleGrid."""

    def __init__(self, grid: AngleGrid, Sigma: Tensor, outputscale: Tensor, noise: Tensor) -> None:
        self.grid, self.Sigma, self.outputscale, self.noise = grid, Sigma, outputscale, noise

    def phi(self, c: Contacts) -> Tensor:
        """Interpolation rows (2, T, U): force_t = sum_u Phi[t, u] alpha(node u)."""
        idx, w = self.grid.interpolation(c.beta, c.gamma)  # (T, M, 4)
        T = idx.shape[0]
        vals = torch.stack([c.weight_x, c.weight_z])[..., None] * w  # (2, T, M, 4)
        out = vals.new_zeros(2, T, self.grid.size)
        return out.scatter_add(-1, idx.reshape(1, T, -1).expand(2, T, -1), vals.reshape(2, T, -1))

    def handle(self, c: Contacts) -> _Handle:
        P = self.phi(c)
        return _Handle(c, P, P @ self.Sigma)

    def cov(self, h1: _Handle, h2: _Handle) -> Tensor:
        return h1.b @ h2.a.mT

    def condition(self, h: _Handle) -> _GridBelief:
        S = self.cov(h, h)
        L = psd_safe_cholesky(_plus_noise(S, self.noise))
        X = torch.linalg.solve_triangular(L, h.b, upper=False)
        Sigma = self.Sigma - X.mT @ X
        return _GridBelief(self.grid, 0.5 * (Sigma + Sigma.mT), self.outputscale, self.noise)


def _node_contacts(grid: AngleGrid, dtype, device) -> Contacts:
    b, g = grid.nodes(dtype, device)
    B, G = torch.meshgrid(b, g, indexing="ij")
    one = torch.ones(grid.size, 1, dtype=dtype, device=device)
    return Contacts(B.reshape(-1, 1), G.reshape(-1, 1), one, one)


def _to_grid(exact: _ExactBelief, grid: AngleGrid) -> _GridBelief:
    """The exact posterior covariance at the grid's nodes."""
    nodes = _node_contacts(grid, exact.noise.dtype, exact.noise.device)
    h = exact.handle(nodes)
    Sigma = exact.cov(h, h)
    return _GridBelief(grid, 0.5 * (Sigma + Sigma.mT), exact.outputscale, exact.noise)


def _contacting_segments(c: Contacts) -> int:
    return int(((c.weight_x != 0) | (c.weight_z != 0)).sum())


# ---- the scorer --------------------------------------------------------------------------------
class ProbeScorer:
    """The current belief over alpha_x, alpha_z, factored to score many candidate probes.

    Build it with ``ProbeScorer.from_model(model)`` (a fitted ``InverseRFT``) or
    ``ProbeScorer.prior(...)`` (nothing measured yet). Candidates are ``Contacts`` (T, M) or
    ``rft.Probe``s. Scores are differentiable in the candidates' contact tensors.

    Attributes:
        method: "exact" or "grid" (see the module docstring).
        outputscale: (2,) prior variances s_a of the maps, (N/cm^3)^2.
        noise: (2,) force noise variances sigma_a^2, N^2.
    """

    def __init__(self, belief: _ExactBelief | _GridBelief) -> None:
        self._belief = belief
        self.method = "exact" if isinstance(belief, _ExactBelief) else "grid"
        self._regions: dict[int, tuple[Region, _Handle, Tensor]] = {}
        self._square: Region | None = None

    @property
    def outputscale(self) -> Tensor:
        return self._belief.outputscale

    @property
    def noise(self) -> Tensor:
        return self._belief.noise

    # ---- construction ----------------------------------------------------------------------
    @classmethod
    def from_model(cls, model, method: str = "auto", grid_size: tuple[int, int] | None = None,
                   exact_max_segments: int = 2000) -> ProbeScorer:
        """The posterior of a (fitted) ``InverseRFT``, with its hyperparameters fixed.

        Args:
            method: "exact", "grid", or "auto": "grid" for a model on the grid path or with more than
                ``exact_max_segments`` training segments in contact (where one exact candidate costs
                a kernel block against all of them), else "exact".
            grid_size: nodes of the grid form; default the model's grid, or 32 x 32.
        """
        if method not in ("auto", "exact", "grid"):
            raise ValueError(f"method must be 'auto', 'exact' or 'grid', got {method!r}")
        k = model.kernel
        ls, os = k.lengthscale.detach(), k.outputscale.detach()
        noise = model.likelihood.noise.detach()
        if model.gp is None:  # the grid path: its own posterior over its nodes
            if method == "exact":
                raise ValueError("a model on the grid path has no exact form; use method='grid' (or 'auto')")
            gm = model.grid_model
            if grid_size is not None and tuple(grid_size) != (gm.grid.n_beta, gm.grid.n_gamma):
                raise ValueError(f"grid_size {tuple(grid_size)} differs from the model's grid "
                                 f"{(gm.grid.n_beta, gm.grid.n_gamma)}")
            with torch.no_grad():
                _, C = gm._prediction_cache()
                Sigma = C @ C.mT
            return cls(_GridBelief(gm.grid, 0.5 * (Sigma + Sigma.mT), os, noise))
        train = model.train_contacts
        if method == "auto":
            method = "grid" if _contacting_segments(train) > exact_max_segments else "exact"
        with torch.no_grad():
            exact = _ExactBelief(ls, os, noise, train)
            if method == "exact":
                return cls(exact)
            return cls(_to_grid(exact, AngleGrid(*(grid_size or (32, 32)))))

    @classmethod
    def prior(cls, lengthscale=1.0, outputscale=0.1, noise=0.01, method: str = "exact",
              grid_size: tuple[int, int] = (32, 32), dtype=torch.float64) -> ProbeScorer:
        """The prior: nothing measured yet.

        Args:
            lengthscale: of every embedding dimension, a float or a (2, 1, 4) tensor (as the model's).
            outputscale: prior variance of the maps, (N/cm^3)^2, a float or (2,) for (x, z).
            noise: force noise variance, N^2, a float or (2,).
            method: "exact" or "grid".
        """
        if method not in ("exact", "grid"):
            raise ValueError(f"method must be 'exact' or 'grid', got {method!r}")
        ls = torch.as_tensor(lengthscale, dtype=dtype).expand(2, 1, 4).clone()
        os = torch.as_tensor(outputscale, dtype=dtype).expand(2).clone()
        nz = torch.as_tensor(noise, dtype=dtype).expand(2).clone()
        for name, v in (("lengthscale", ls), ("outputscale", os), ("noise", nz)):
            if not (torch.isfinite(v).all() and (v > 0).all()):
                raise ValueError(f"{name} must be positive and finite, got {v.tolist()}")
        exact = _ExactBelief(ls, os, nz, None)
        if method == "exact":
            return cls(exact)
        with torch.no_grad():
            return cls(_to_grid(exact, AngleGrid(*grid_size)))

    # ---- covariances and scores ----------------------------------------------------------------
    def _cast(self, c) -> Contacts:
        c = _as_contacts(c)
        return c.to(dtype=self.noise.dtype, device=self.noise.device)

    def covariance(self, contacts) -> Tensor:
        """Posterior covariance (2, T, T) of a candidate's forces (noise not included), N^2."""
        h = self._belief.handle(self._cast(contacts))
        S = self._belief.cov(h, h)
        return 0.5 * (S + S.mT)

    def information_gain(self, contacts, per_axis: bool = False) -> Tensor:
        """EIG of observing the candidate's forces, nats: summed over the two maps (scalar), or
        ``per_axis`` (2,) = (alpha_x, alpha_z) (each map is seen only through its own force axis)."""
        S = self.covariance(contacts)
        eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
        L = psd_safe_cholesky(eye + S / self.noise[:, None, None])
        eig = torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
        return eig if per_axis else eig.sum()

    def _region(self, region: Region | None) -> tuple[Region, _Handle, Tensor]:
        if region is None:
            self._square = self._square or Region.square(dtype=self.noise.dtype)
            region = self._square
        key = id(region)  # the cache holds the region, so its id is not reused while cached
        if key not in self._regions or self._regions[key][0] is not region:
            r = region.contacts().to(dtype=self.noise.dtype, device=self.noise.device)
            with torch.no_grad():
                h = self._belief.handle(r)
                var = torch.diagonal(self._belief.cov(h, h), dim1=-2, dim2=-1)  # (2, N)
            self._regions[key] = (region, h, var)
        return self._regions[key]

    def integrated_variance(self, contacts=None, region: Region | None = None, per_axis: bool = False) -> Tensor:
        """Expected integrated map variance over ``region`` (default: the whole square) after
        observing the candidate (now, if None), each map's divided by its prior variance: summed over
        the two maps (scalar: 2 = the prior, 0 = known), or ``per_axis`` (2,) = (alpha_x, alpha_z)."""
        region, hr, var = self._region(region)
        w = region.weight.to(var)
        if contacts is None:
            iv = (var * w).sum(-1) / self.outputscale
        else:
            iv = self._integrated_variance_after(hr, var, w, self._belief.handle(self._cast(contacts)))
        return iv if per_axis else iv.sum()

    def _integrated_variance_after(self, hr: _Handle, var: Tensor, w: Tensor, hc: _Handle) -> Tensor:
        """Per map (2,)."""
        k = self._belief.cov(hr, hc)  # (2, N, T_c)
        L = psd_safe_cholesky(_plus_noise(self._belief.cov(hc, hc), self.noise))
        B = torch.linalg.solve_triangular(L, k.mT, upper=False)  # (2, T_c, N)
        return ((var - B.pow(2).sum(-2)) * w).sum(-1) / self.outputscale

    def score(self, candidates: Sequence, criterion: str = "variance", region: Region | None = None) -> Tensor:
        """Scores (n,) of several candidates: the integrated variance after each ("variance", lower is
        better) or its information gain ("eig", nats, higher is better)."""
        if criterion not in ("variance", "eig"):
            raise ValueError(f"criterion must be 'variance' or 'eig', got {criterion!r}")
        cands = [self._cast(c) for c in candidates]
        if not cands:
            return torch.zeros(0, dtype=self.noise.dtype, device=self.noise.device)
        if criterion == "eig":
            return torch.stack([self.information_gain(c) for c in cands])
        return torch.stack([self.integrated_variance(c, region) for c in cands])

    def rank(self, candidates: Sequence, criterion: str = "variance",
             region: Region | None = None) -> list[tuple[int, float]]:
        """(index, score) pairs, best first."""
        with torch.no_grad():
            s = self.score(candidates, criterion, region).tolist()
        order = sorted(range(len(s)), key=(lambda i: s[i]) if criterion == "variance" else (lambda i: -s[i]))
        return [(i, s[i]) for i in order]

    def condition(self, contacts) -> ProbeScorer:
        """The belief after observing the candidate's forces (whatever their values): a new scorer;
        this one and the model are unchanged."""
        with torch.no_grad():
            c = self._cast(contacts)
            return ProbeScorer(self._belief.condition(self._belief.handle(c)))

    def map_variance(self, beta, gamma) -> Tensor:
        """Current posterior variance of (alpha_x, alpha_z) at angles of broadcast shape S: S + (2,)."""
        b, g = torch.broadcast_tensors(torch.as_tensor(beta, dtype=self.noise.dtype),
                                       torch.as_tensor(gamma, dtype=self.noise.dtype))
        bc, gc, _ = mirror_to_canonical(b.reshape(-1), g.reshape(-1))
        one = torch.ones_like(bc)[:, None]
        h = self._belief.handle(Contacts(bc[:, None], gc[:, None], one, one))
        with torch.no_grad():
            v = torch.diagonal(self._belief.cov(h, h), dim1=-2, dim2=-1)
        return v.T.reshape(*b.shape, 2)


@dataclass
class DesignStep:
    """One pick of ``greedy_design``: the candidate's index, its score when picked, and the
    integrated variance over the region once it is observed (2 = prior, 0 = known)."""

    index: int
    score: float
    integrated_variance: float


def greedy_design(scorer: ProbeScorer, candidates: Sequence, budget: int, criterion: str = "variance",
                  region: Region | None = None) -> list[DesignStep]:
    """Pick ``budget`` probes one after another, each the best given the ones before (the belief is
    conditioned on every pick; the posterior variance does not depend on the values). Neither the
    scorer nor any model is changed.

    With criterion "eig", the scores add up to the information of the whole sequence (chain rule).
    """
    if int(budget) != budget or budget < 0:
        raise ValueError(f"budget must be an integer >= 0, got {budget}")
    cands = [scorer._cast(c) for c in candidates]
    left = list(range(len(cands)))
    steps: list[DesignStep] = []
    current = scorer
    for _ in range(min(int(budget), len(cands))):
        j, score = current.rank([cands[i] for i in left], criterion, region)[0]
        idx = left.pop(j)
        current = current.condition(cands[idx])
        with torch.no_grad():
            iv = float(current.integrated_variance(region=region))
        steps.append(DesignStep(idx, score, iv))
    return steps

