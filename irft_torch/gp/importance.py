"""Importance sampling of the hyperparameter posterior (``gp.hyper_posterior.laplace``): Student-t
proposals from a scrambled Sobol sequence, their log density, systematic resampling of the weighted draws and
the merging of identical ones."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["_student_t", "_systematic", "_merge"]


def _generator_device(generator: torch.Generator | None) -> torch.device:
    """Where random numbers are drawn: the generator's device (the CPU's default generator when None), then moved
    to the data: a GPU model draws the CPU's proposals, and a CPU ``generator`` works with either."""
    return torch.device("cpu") if generator is None else generator.device


def _student_t(mean: Tensor, cov: Tensor, df: float, n: int, generator, qmc: bool = True) -> tuple[Tensor, Tensor]:
    """n draws (n, P) of a multivariate Student-t and their log density (n,). ``qmc``: from a scrambled
    Sobol sequence in P + 1 dimensions (normals by the inverse normal CDF, the chi-square's inverse CDF
    2 P^-1(df / 2, u) by scipy.special, lighter to import than scipy.stats): importance-sampling estimates then
    converge about as 1/n instead of 1/sqrt(n)."""
    from scipy.special import gammaincinv

    P = mean.numel()
    L = torch.linalg.cholesky(cov)
    if qmc:
        seed = int(torch.randint(0, 2**31 - 1, (), generator=generator, device=_generator_device(generator)))
        u = torch.quasirandom.SobolEngine(P + 1, scramble=True, seed=seed).draw(n, dtype=torch.float64)
        u = u.clamp(1e-12, 1 - 1e-12)
        z = (math.sqrt(2) * torch.special.erfinv(2 * u[:, :P] - 1)).to(mean)
        v = torch.as_tensor(2 * gammaincinv(df / 2, u[:, P].numpy()), dtype=mean.dtype, device=mean.device)
    else:
        gd = _generator_device(generator)
        z = torch.randn(n, P, generator=generator, dtype=mean.dtype, device=gd).to(mean.device)
        v = torch.randn(n, int(df), generator=generator, dtype=mean.dtype, device=gd).pow(2).sum(-1).to(mean.device)
    x = mean + (z @ L.mT) * (df / v).sqrt()[:, None]
    d = torch.linalg.solve_triangular(L, (x - mean).mT, upper=False).pow(2).sum(0)
    logdet = 2 * torch.log(torch.diagonal(L)).sum()
    logq = (math.lgamma((df + P) / 2) - math.lgamma(df / 2) - 0.5 * P * math.log(df * math.pi) - 0.5 * logdet
            - 0.5 * (df + P) * torch.log1p(d / df))
    return x, logq


def _systematic(weights: Tensor, n: int, generator) -> Tensor:
    """Indices (n,) of a systematic resample of ``weights`` (low variance: each index appears
    floor(n w) or ceil(n w) times)."""
    u0 = torch.rand((), generator=generator, dtype=weights.dtype, device=_generator_device(generator))
    u0 = u0.to(weights.device)
    pos = (u0 + torch.arange(n, dtype=weights.dtype, device=weights.device)) / n
    return torch.searchsorted(weights.cumsum(0).clamp_max(1.0), pos).clamp_max(len(weights) - 1)


def _merge(theta: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Identical draws merged, their weights added."""
    uniq, inv = torch.unique(theta, dim=0, return_inverse=True)
    w = weights.new_zeros(uniq.shape[0]).index_add_(0, inv, weights)
    return uniq, w
