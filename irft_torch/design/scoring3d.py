r"""Score a candidate 3-D probe (``rft.Contacts3D``: a wheel at a slip angle, a leg that turns) before running it.

The 3-D model's force covariance is two independent blocks (docs/inverse3d.md): horizontal, rows (F_x; F_y),
seeing alpha_x and alpha_y; vertical, rows F_z, seeing alpha_z. For a candidate with T samples let S_b be the
current posterior covariance of its block-b rows (2T x 2T and T x T, elements correlated) and D_b the diagonal of
the rows' noise variances (sigma_x^2, sigma_y^2 or sigma_z^2). Then

    EIG = sum_b 1/2 log | I + D_b^{-1/2} S_b D_b^{-1/2} |              (nats)
    IV  = sum_c sum_j r_j [ v_c(theta_j) - k_cj^T (S_b(c) + D_b(c))^{-1} k_cj ] / s_c

with c over the maps (alpha_x, alpha_y, alpha_z), b(c) the block that sees map c, v_c the current map variance at
the region's points theta_j (weights r_j), k_cj the posterior covariance between map c there and the candidate's
block rows, and s_c the prior variance (with Li et al.'s term: s_c + v_c): IV is 3 for the prior and 0 for maps
known exactly (alpha_y a constant: its variance, the same at every point). Every posterior number comes from the
3-D backend (``gp.inverse3d.joint.BlockRows``); the scorer factors only the candidate's own matrices, with the
planar scorer's algebra (``design.belief``).

Example:
    >>> scorer = ProbeScorer3D.from_model(model_3d)
    >>> scorer.score([c1, c2, c3], criterion="eig")           # nats, higher is better
    >>> scorer.integrated_variance(c1, region=Region.square(12), per_map=True)
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..gp.inverse3d import Backend3D, InverseRFT3D, point_contacts
from ..gp.inverse3d.joint import BlockRows
from ..gp.inverse3d.rows import BLOCKS
from ..rft.contacts3d import Contacts3D
from .belief import BeliefScorer, check_criterion, information_nats, variance_after
from .region import Region

__all__ = ["ProbeScorer3D"]


def _as_contacts(c) -> Contacts3D:
    if not isinstance(c, Contacts3D):
        raise TypeError(f"a 3-D candidate must be an rft.Contacts3D (rft.contacts_3d), got {type(c).__name__}")
    return c


class ProbeScorer3D(BeliefScorer):
    """The belief of a 3-D model over alpha_x, alpha_y, alpha_z (a ``Backend3D`` at fixed hyperparameters), to
    score candidate ``Contacts3D`` by information gain or expected integrated map variance (module doc).

    Build it with ``ProbeScorer.from_model(model)``: a 3-D model gives this scorer, or with a hyperparameter
    posterior (``hyper_posterior="laplace"``) a ``design.MixtureScorer`` of one ``ProbeScorer3D`` per draw, every
    score the draws' weighted average. ``ProbeScorer3D.from_model(model)`` scores at the fitted hyperparameters
    alone. Scores are not differentiable in the candidates (no gradient-based 3-D design yet).

    Attributes:
        outputscale: (3,) the kernel's variances s_c of (alpha_x, alpha_y, alpha_z), (N/cm^3)^2.
        prior_variance: (3,) the maps' prior variances (s_c, plus Li et al.'s v_c with ``kernel="li"``): the
            integrated variances are divided by it.
        noise: (3,) force-noise variances of (F_x, F_y, F_z), N^2.
    """

    def __init__(self, backend: Backend3D, model: InverseRFT3D | None = None) -> None:
        if not isinstance(backend, Backend3D):
            raise TypeError(f"backend must be a gp.inverse3d.Backend3D, got {type(backend).__name__}")
        self._own, self._model = backend, model
        self._cache: dict = {}

    @classmethod
    def from_model(cls, model: InverseRFT3D) -> ProbeScorer3D:
        """The posterior of a (fitted) ``InverseRFT3D`` at its fitted hyperparameters; the scorer follows the model
        (``add_data``, a refit). Over a hyperparameter posterior's draws: ``ProbeScorer.from_model``."""
        if not isinstance(model, InverseRFT3D):
            raise TypeError(f"model must be an InverseRFT3D (a planar InverseRFT: design.ProbeScorer), got "
                            f"{type(model).__name__}")
        return cls(model.backend, model)

    @property
    def backend(self) -> Backend3D:
        return self._model.backend if self._model is not None else self._own

    def _cast(self, c) -> Contacts3D:
        return _as_contacts(c).to(dtype=self.noise.dtype, device=self.noise.device)

    def _row_noise(self, b: int, T: int) -> Tensor:
        return torch.cat([self.noise[a].expand(T) for a in BLOCKS[b].axes])

    # ---- the region's part, cached while the belief stays the same -------------------------------------------------
    def _region_rows(self, region: Region | None) -> tuple[Region, list[BlockRows]]:
        backend = self.backend
        with torch.no_grad():
            key = (backend, backend.n_samples, torch.cat([p.detach().reshape(-1) for p in backend.hypers.parameters()]))
        old = self._cache.get("key")
        if old is None or old[0] is not key[0] or old[1] != key[1] or not torch.equal(old[2], key[2]):
            self._cache = {"key": key}
        if region is None:
            region = self._cache.setdefault("square", Region.square(dtype=self.noise.dtype))
        hit = self._cache.get(id(region))
        if hit is None or hit[0] is not region:
            pts = point_contacts(region.beta.to(self.noise), region.gamma.to(self.noise))
            hit = self._cache[id(region)] = (region, [BlockRows(backend, b, [pts]) for b in range(len(BLOCKS))])
        return region, hit[1]

    # ---- scores -------------------------------------------------------------------------------------------------
    def covariance(self, contacts) -> list[Tensor]:
        """Posterior covariances of a candidate's force rows, noise not included, N^2: [(2T, 2T) rows (F_x; F_y),
        (T, T) rows F_z]."""
        c = self._cast(contacts)
        return [BlockRows(self.backend, b, [c]).cov(0, 0) for b in range(len(BLOCKS))]

    def information_gain(self, contacts, per_block: bool = False) -> Tensor:
        """EIG of observing the candidate's three force axes, nats: a scalar, or ``per_block`` (2,) = (horizontal:
        alpha_x and alpha_y through F_x and F_y; vertical: alpha_z through F_z)."""
        c = self._cast(contacts)
        eig = torch.stack([information_nats(S, self._row_noise(b, len(c))) for b, S in enumerate(self.covariance(c))])
        return eig if per_block else eig.sum()

    def integrated_variance(self, contacts=None, region: Region | None = None, per_map: bool = False) -> Tensor:
        """Expected integrated map variance over ``region`` (a ``design.Region``; default the whole square, 16 x 16)
        after observing the candidate (now, if None), each map's divided by its prior variance: a scalar (3 = the
        prior, 0 = known), or ``per_map`` (3,) = (alpha_x, alpha_y, alpha_z)."""
        region, base = self._region_rows(region)
        N = region.beta.numel()
        w = region.weight.to(self.noise)
        c = None if contacts is None else self._cast(contacts)
        out = []
        for b, rows in enumerate(base):
            var = rows.variance(0)
            if c is not None and len(c):
                ext = rows.extended([c])
                var = variance_after(var, ext.cov(1, 0), ext.cov(1, 1), self._row_noise(b, len(c)))
            out.append(var.reshape(len(BLOCKS[b].maps), N))
        iv = (torch.cat(out) * w).sum(-1) / self.prior_variance
        return iv if per_map else iv.sum()

    def score(self, candidates: Sequence, criterion: str = "variance", region: Region | None = None,
              per_axis: bool = False) -> Tensor:
        """Scores (n,) of several candidates: the integrated variance after each ("variance", lower is better) or
        its information gain ("eig", nats, higher is better); ``per_axis``: (n, 3) per map for "variance", (n, 2)
        per block for "eig"."""
        check_criterion(criterion, region)
        with torch.no_grad():
            if criterion == "eig":
                vals = [self.information_gain(c, per_axis) for c in candidates]
            else:
                vals = [self.integrated_variance(c, region, per_axis) for c in candidates]
        if vals:
            return torch.stack(vals)
        width = () if not per_axis else ((3,) if criterion == "variance" else (2,))
        return torch.zeros(0, *width, dtype=self.noise.dtype, device=self.noise.device)

    def condition(self, contacts) -> ProbeScorer3D:
        """The belief after observing the candidate's forces (whatever their values: the covariance does not
        depend on them): a new scorer; this one and the model are unchanged."""
        c = self._cast(contacts)
        backend = self.backend.with_hypers(self.backend.hypers)
        with torch.no_grad():
            backend.add_data(c, c.beta.new_zeros(len(c), 3))
        return ProbeScorer3D(backend)

    def map_variance(self, beta, gamma) -> Tensor:
        """Current posterior variance of (alpha_x, alpha_y, alpha_z) at angles of broadcast shape S: S + (3,)."""
        b = torch.as_tensor(beta, dtype=self.noise.dtype, device=self.noise.device)
        g = torch.as_tensor(gamma, dtype=self.noise.dtype, device=self.noise.device)
        S = torch.broadcast_shapes(b.shape, g.shape)
        b, g = torch.broadcast_tensors(b, g)
        with torch.no_grad():
            _, cov = self.backend.posterior(point_contacts(b, g))
        return torch.diagonal(cov, dim1=-2, dim2=-1).reshape(*S, 3)
