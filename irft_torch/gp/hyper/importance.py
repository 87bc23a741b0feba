"""Importance sampling of the hyperparameter posterior (``gp.hyper.posterior.laplace``): Student-t
proposals from a scrambled Sobol sequence, their log density, a second stage moved to the first stage's weighted
draws (always, or where the first stage's weights are unreliable), and the draws kept for prediction (a
moment-matched point set, or a systematic resample of the weighted draws with identical ones merged)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["importance_sample", "first_stage", "second_stage", "_student_t", "_systematic", "_merge", "_moment_points",
           "_always"]


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
    return x, _student_t_log_density(x, mean, L, df)


def _student_t_log_density(x: Tensor, mean: Tensor, L: Tensor, df: float) -> Tensor:
    """log density (n,) at x (n, P) of the multivariate Student-t with location ``mean`` (P,), scale
    L L^T (L (P, P) lower) and ``df`` degrees of freedom."""
    P = mean.numel()
    d = torch.linalg.solve_triangular(L, (x - mean).mT, upper=False).pow(2).sum(0)
    logdet = 2 * torch.log(torch.diagonal(L)).sum()
    return (math.lgamma((df + P) / 2) - math.lgamma(df / 2) - 0.5 * P * math.log(df * math.pi) - 0.5 * logdet
            - 0.5 * (df + P) * torch.log1p(d / df))


def importance_sample(log_p_many: Callable[[Tensor], Tensor], first: tuple[Tensor, Tensor, Tensor], mean: Tensor,
                      cov: Tensor, df: float, generator, qmc: bool = True,
                      adapt: Callable[[Tensor], bool] | None = None,
                      n2: int | None = None) -> tuple[Tensor, Tensor, Tensor, int]:
    """Proposals x (N, P), their log posterior (N,) and log importance weights (N,) (unnormalised), and the
    number of stages, from the first stage's draws ``first`` (``first_stage``: x, log proposal density, log
    posterior) of the Student-t (``mean``, ``cov``, ``df``). Where ``adapt(log weights)`` says they are
    unreliable, stage 2 (``second_stage``, ``n2`` proposals) is drawn and both are weighed together.
    ``log_p_many``: (n, P) -> (n,), -inf where impossible."""
    logw1 = first[2] - first[1]
    if adapt is None or not torch.isfinite(logw1).any() or not adapt(logw1):
        return first[0], first[2], logw1, 1
    return (*second_stage(log_p_many, *first, mean, cov, df, generator, qmc, n2), 2)


def first_stage(log_p_many: Callable[[Tensor], Tensor], mean: Tensor, cov: Tensor, df: float, n: int, generator,
                qmc: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """n proposals x (n, P) of the Student-t (``mean``, ``cov``, ``df``), their log density (n,) and log
    posterior (n,)."""
    x, logq = _student_t(mean, cov, df, n, generator, qmc)
    return x, logq, log_p_many(x)


def second_stage(log_p_many: Callable[[Tensor], Tensor], x1: Tensor, logq1: Tensor, logp1: Tensor, mean: Tensor,
                 cov: Tensor, df: float, generator, qmc: bool = True,
                 n2: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """``n2`` proposals more (None: as many as the first stage's n1), from a Student-t moved to the first stage's
    weighted draws, with the average of their weighted covariance and ``cov`` (the covariance of a few effective
    draws alone can be near singular); every draw of both stages is weighed against the mixture of the two
    proposals in the stages' proportions n1 : n2 (the balance heuristic: Owen & Zhou 2000; adaptive multiple
    importance sampling, Cornuet et al. 2012). Returns x (n1 + n2, P), log posterior and log weights (n1 + n2,)."""
    logw1 = logp1 - logq1
    ok = torch.isfinite(logw1)
    w = torch.where(ok, (logw1 - logw1[ok].max()).exp(), torch.zeros_like(logw1))
    w = w / w.sum()
    mu, C = _weighted_moments(x1, w)
    cov2 = 0.5 * C + 0.5 * cov
    n1 = x1.shape[0]
    n2 = n1 if n2 is None else int(n2)
    x2, _ = _student_t(mu, cov2, df, n2, generator, qmc)
    logp2 = log_p_many(x2)
    x = torch.cat([x1, x2])
    logp = torch.cat([logp1, logp2])
    L1, L2 = torch.linalg.cholesky(cov), torch.linalg.cholesky(cov2)
    logq = torch.logaddexp(_student_t_log_density(x, mean, L1, df) + math.log(n1 / (n1 + n2)),
                           _student_t_log_density(x, mu, L2, df) + math.log(n2 / (n1 + n2)))
    return x, logp, logp - logq


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


def _weighted_moments(x: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Mean (P,) and covariance (P, P) (symmetric) of draws x (N, P) with non-negative weights w (N,)."""
    C = torch.cov(x.mT, correction=0, aweights=w)
    return (w[:, None] * x).sum(0) / w.sum(), 0.5 * (C + C.mT)


def _always(log_weights: Tensor) -> bool:
    """The second importance-sampling stage's rule for ``adapt="always"``."""
    return True


def _moment_points(x: Tensor, w: Tensor, n_draws: int | None, log_p_many) -> Tensor | None:
    """Equally weighted points (n, P) whose mean and covariance are those of the weighted proposals x (N, P)
    with weights w (N,): the symmetric set mu +- sqrt(P) R q_i (n = 2 P) where ``n_draws`` allows, else a regular
    simplex (n = P + 1, at the same radius sqrt(P) in units of the covariance). R R^T is the covariance and q_i
    the columns of a fixed rotation, so that each point moves every coordinate by about one sd rather than one
    coordinate by sqrt(P) sd. None where ``n_draws`` (None: keep every proposal) is below P + 1 or a point is an
    impossible setting (``log_p_many`` -inf): the caller then resamples."""
    if n_draws is None:
        return None
    P = x.shape[1]
    mu, C = _weighted_moments(x, w)
    lam, V = torch.linalg.eigh(C)
    R = V * lam.clamp_min(0).sqrt()  # (P, P) columns: sd directions
    g = torch.Generator().manual_seed(0)
    Q, _ = torch.linalg.qr(torch.randn(P, P, generator=g, dtype=torch.float64))
    R = R @ Q.to(R)  # a fixed rotation: each point moves every coordinate a little, none by sqrt(P) sd
    if 2 * P <= n_draws:
        pts = torch.cat([mu + math.sqrt(P) * R.mT, mu - math.sqrt(P) * R.mT])
    elif P + 1 <= n_draws:
        ones = x.new_ones(P + 1, 1) / math.sqrt(P + 1)
        Q, _ = torch.linalg.qr(torch.cat([ones, torch.eye(P + 1, P, dtype=x.dtype, device=x.device)], 1))
        Z = math.sqrt(P + 1) * Q[:, 1:]  # (P + 1, P): mean 0, covariance I (a regular simplex)
        pts = mu + Z @ R.mT
    else:
        return None
    if not bool(torch.isfinite(log_p_many(pts)).all()):
        return None
    return pts
