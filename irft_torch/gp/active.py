r"""Choosing the most informative probe (toe + path) before running it.

A GP's posterior variance does not depend on the measured values, so a candidate probe can be
scored before the leg moves. For a candidate with contacts c (T_c, M), per axis a in (x, z):

    Sigma_c   = posterior covariance of its forces (T_c x T_c)   (w^T Sigma w, segments correlated)
    EIG       = sum_a 1/2 log | I + Sigma_c,a / sigma_a^2 |       (nats; mutual information between
                                                                   the map and the probe's forces)
    IV        = sum_a mean_j r_j [ var_a(theta_j) - k_ja (Sigma_c,a + sigma_a^2 I)^-1 k_ja^T ] / s_a
                                                                  (expected integrated variance of the
                                                                   map over a region after the probe,
                                                                   each axis normalized by its prior
                                                                   variance s_a)

where k_ja is the posterior covariance between the map at theta_j and the probe's forces, and r_j
weights the region of interest (all of the square, or e.g. the sign change of alpha_x at
gamma > pi/3). Works on the exact path (``InverseRFT(method="exact")``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rft.contacts import Contacts
from .encoding import encode_contacts

__all__ = ["Region", "PosteriorFactor", "joint_covariance", "information_gain", "integrated_variance",
           "rank_candidates", "greedy_design", "DesignStep"]


@dataclass
class Region:
    """Points of the canonical square (beta, gamma) (N,) with weights (N,) summing to 1."""

    beta: Tensor
    gamma: Tensor
    weight: Tensor

    @classmethod
    def square(cls, n: int = 16, dtype=torch.float64) -> Region:
        """An n x n grid of cell centres over [-pi/2, pi/2]^2, equal weights."""
        e = torch.linspace(-math.pi / 2, math.pi / 2, n + 1, dtype=dtype)
        c = (e[1:] + e[:-1]) / 2
        B, G = torch.meshgrid(c, c, indexing="ij")
        return cls(B.reshape(-1), G.reshape(-1), torch.full((n * n,), 1.0 / (n * n), dtype=dtype))

    @classmethod
    def sign_change(cls, n: int = 16, dtype=torch.float64) -> Region:
        """The region the paper calls informative: gamma > pi/3 (alpha_x changes sign with beta)."""
        sq = cls.square(n, dtype)
        w = (sq.gamma > math.pi / 3).to(dtype)
        return cls(sq.beta, sq.gamma, w / w.sum())


def _point_contacts(region: Region) -> Contacts:
    one = torch.ones_like(region.beta)[:, None]
    return Contacts(region.beta[:, None], region.gamma[:, None], one, one)


class PosteriorFactor:
    """The training covariance factored once, W K W^T + noise = L L^T (per axis), so that the
    posterior covariance of any functionals costs one kernel block and one triangular solve:
    Sigma_ab = K_ab - A_a^T A_b with A = L^-1 K_train,a. (gpytorch's exact predictive covariance
    refactors the training covariance on every call.)"""

    def __init__(self, model) -> None:
        if model.gp is None:
            raise NotImplementedError("active design runs on the exact path (method='exact')")
        self.model = model
        self.kernel = model.gp.covar_module
        self.train = model.gp.train_inputs[0]
        with torch.no_grad(), model._settings():
            K = self.kernel(self.train).to_dense()
            K = K + torch.diag_embed(model.likelihood.noise.detach()[:, None].expand(2, K.shape[-1]))
            self.L = torch.linalg.cholesky(0.5 * (K + K.mT))

    def rows(self, c: Contacts) -> Tensor:
        M = self.train.shape[-1] // 3
        if c.n_segments > M:  # zero-weight padding changes no covariance: L stays valid
            M = c.n_segments
            self.train = encode_contacts(self.model.train_contacts, M)
        return encode_contacts(c.to(dtype=self.model.dtype), M)

    def solve(self, rows: Tensor) -> Tensor:
        """A = L^-1 K_train,rows (2, T, N)."""
        Kt = self.kernel(self.train, rows).to_dense()
        return torch.linalg.solve_triangular(self.L, Kt, upper=False)

    def cov(self, rows_a: Tensor, A_a: Tensor, rows_b: Tensor | None = None, A_b: Tensor | None = None) -> Tensor:
        if rows_b is None:
            rows_b, A_b = rows_a, A_a
        return self.kernel(rows_a, rows_b).to_dense() - A_a.mT @ A_b


def joint_covariance(model, contacts: Sequence[Contacts], factor: PosteriorFactor | None = None) -> Tensor:
    """Posterior covariance (2, N, N) of the stacked weighted sums of several contact sets
    (rows of each (T_i, M_i), concatenated in order), per axis. Exact path."""
    f = factor or PosteriorFactor(model)
    rows = torch.cat([f.rows(c) for c in contacts], dim=-2)
    S = f.cov(rows, f.solve(rows))
    return 0.5 * (S + S.mT)


def information_gain(model, candidate: Contacts, factor: PosteriorFactor | None = None) -> Tensor:
    """EIG (nats) of observing the candidate's forces, summed over the two axes."""
    S = joint_covariance(model, [candidate], factor)
    noise = model.likelihood.noise.detach()
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    L = torch.linalg.cholesky(eye + S / noise[:, None, None])
    return torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum()


class _RegionCache:
    def __init__(self, factor: PosteriorFactor, region: Region) -> None:
        self.rows = factor.rows(_point_contacts(region))
        self.A = factor.solve(self.rows)
        self.var = torch.diagonal(factor.cov(self.rows, self.A), dim1=-2, dim2=-1)


def integrated_variance(model, candidate: Contacts | None = None, region: Region | None = None,
                        factor: PosteriorFactor | None = None, _cache: _RegionCache | None = None) -> Tensor:
    """Expected integrated posterior variance of the two maps over ``region`` after observing
    ``candidate`` (or now, if None), each axis divided by its prior variance; 0 = known, 1 = prior."""
    region = region or Region.square()
    f = factor or PosteriorFactor(model)
    rc = _cache or _RegionCache(f, region)
    s = model.kernel.outputscale.detach()
    if candidate is None:
        return ((rc.var * region.weight).sum(-1) / s).sum()
    rows = f.rows(candidate)
    A = f.solve(rows)
    k = f.cov(rc.rows, rc.A, rows, A)  # (2, n, T_c)
    C = f.cov(rows, A)
    C = 0.5 * (C + C.mT) + model.likelihood.noise.detach()[:, None, None] * torch.eye(C.shape[-1], dtype=C.dtype)
    L = torch.linalg.cholesky(C)
    B = torch.linalg.solve_triangular(L, k.mT, upper=False)
    return (((rc.var - B.pow(2).sum(-2)) * region.weight).sum(-1) / s).sum()


def rank_candidates(model, candidates: Sequence[Contacts], criterion: str = "variance",
                    region: Region | None = None) -> list[tuple[int, float]]:
    """(index, score) best first: lowest integrated variance ("variance") or highest EIG ("eig")."""
    if criterion not in ("variance", "eig"):
        raise ValueError(f"criterion must be 'variance' or 'eig', got {criterion!r}")
    with torch.no_grad():
        f = PosteriorFactor(model)
        if criterion == "eig":
            scores = [float(information_gain(model, c, f)) for c in candidates]
            order = sorted(range(len(candidates)), key=lambda i: -scores[i])
        else:
            region = region or Region.square()
            rc = _RegionCache(f, region)
            scores = [float(integrated_variance(model, c, region, f, rc)) for c in candidates]
            order = sorted(range(len(candidates)), key=lambda i: scores[i])
    return [(i, scores[i]) for i in order]


@dataclass
class DesignStep:
    index: int
    score: float


def greedy_design(model, candidates: Sequence[Contacts], budget: int, criterion: str = "variance",
                  region: Region | None = None) -> list[DesignStep]:
    """Pick ``budget`` probes one after another, each the best given the ones before. The model is
    conditioned on each chosen probe with its predicted forces as stand-in observations (the
    posterior variance does not depend on the values); the model passed in is changed."""
    chosen: list[DesignStep] = []
    left = list(range(len(candidates)))
    for _ in range(min(budget, len(left))):
        ranked = rank_candidates(model, [candidates[i] for i in left], criterion, region)
        j, score = ranked[0]
        idx = left.pop(j)
        chosen.append(DesignStep(idx, score))
        c = candidates[idx]
        with torch.no_grad():
            model.add_data(c, model.predict_forces(c).mean)
    return chosen
