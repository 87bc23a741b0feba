"""Importance sampling of the hyperparameter posterior (``gp.hyper.posterior.laplace``): Student-t
proposals from a scrambled Sobol sequence (split along the Laplace covariance's axes where the posterior is wider
on one side, ``split_axes``), their log density, a second stage moved to the first stage's weighted draws (always,
or where the first stage's weights are unreliable), more moved stages while the weights stay unreliable, and the
draws kept for prediction (a moment-matched point set, or a systematic resample of the weighted draws with identical
ones merged)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["importance_sample", "first_stage", "next_stage", "split_axes", "SplitAxes", "_student_t", "_systematic",
           "_merge", "_moment_points", "_always"]

#: Steps (in Laplace standard deviations) at which ``split_axes`` reads the log posterior along each axis, and the
#: most it widens a side (a factor on the Laplace sd).
SPLIT_STEPS = (2.0, 3.0)
SPLIT_MOST = 3.0


@dataclass(frozen=True)
class SplitAxes:
    """The axes of a split Student-t proposal (Geweke 1989, "Bayesian inference in econometric models using Monte
    Carlo integration", Econometrica 57: the split-t importance function): x = mean + L y, L (P, P) lower
    triangular (the Cholesky factor of the proposal's scale), and each y_j a side of a Student-t: scaled by ``hi``
    [j] above 0 and by ``lo`` [j] below (each (P,), dimensionless), with mass in the sides' proportions, so the density
    is continuous. Equal sides of 1 give the symmetric Student-t with scale L L^T. The columns of a Cholesky factor,
    not the covariance's eigenvectors, so the proposal moves continuously with the Hessian (eigenvectors of nearly
    equal eigenvalues turn at a rounding error's push)."""

    L: Tensor
    lo: Tensor
    hi: Tensor


def split_axes(log_p_many: Callable[[Tensor], Tensor], mode: Tensor, cov: Tensor, inflate: float = 1.0,
               steps: tuple[float, ...] = SPLIT_STEPS, most: float = SPLIT_MOST) -> SplitAxes:
    """The split-t's axes at ``mode`` (P,) from the Laplace covariance ``cov`` (P, P) = L L^T: along each column
    of L, on each side, the log posterior is read at ``steps`` (z_j = +-delta: delta Laplace sds along it;
    2 P len(steps) points and the mode, one batch), and the side's factor is the widest of
    delta / sqrt(2 (log p(mode) - log p(mode +- delta L e_j))) over the steps (1 for a Gaussian), kept within
    [1, ``most``]; the proposal's scale is ``inflate`` L L^T. Where the posterior falls more slowly than its
    curvature at the mode says (a lengthscale the data bound on one side only), that side widens to match, so the
    importance weights stay bounded there; a side it cannot reach (an impossible setting) keeps the Laplace
    width."""
    L = torch.linalg.cholesky(0.5 * (cov + cov.mT))
    P = mode.numel()
    d = torch.tensor(steps, dtype=mode.dtype, device=mode.device)
    signs = torch.tensor([-1.0, 1.0], dtype=mode.dtype, device=mode.device)
    moves = signs[:, None, None, None] * d[None, :, None, None] * L.mT[None, None]  # (side, step, axis, P)
    x = torch.cat([mode[None], (mode + moves).reshape(-1, P)])
    with torch.no_grad():
        lp = log_p_many(x)
    drop = (lp[0] - lp[1:]).reshape(2, len(steps), P)
    width = d[None, :, None] / (2 * drop.clamp_min(1e-12)).sqrt()
    width = torch.where(torch.isfinite(drop), width, torch.ones_like(width))  # impossible: keep the Laplace width
    factor = width.amax(1).clamp(1.0, float(most))  # (2, P): the negative, the positive side
    if not bool(torch.isfinite(lp[0])):
        factor = torch.ones_like(factor)
    return SplitAxes(math.sqrt(float(inflate)) * L, factor[0], factor[1])


def _generator_device(generator: torch.Generator | None) -> torch.device:
    """Where random numbers are drawn: the generator's device (the CPU's default generator when None), then moved
    to the data: a GPU model draws the CPU's proposals, and a CPU ``generator`` works with either."""
    return torch.device("cpu") if generator is None else generator.device


def _uniforms(d: int, n: int, generator, qmc: bool) -> Tensor:
    """n points (n, d) in (0, 1)^d, float64 on the CPU: a scrambled Sobol sequence (``qmc``), else pseudo-random."""
    if qmc:
        seed = int(torch.randint(0, 2**31 - 1, (), generator=generator, device=_generator_device(generator)))
        u = torch.quasirandom.SobolEngine(d, scramble=True, seed=seed).draw(n, dtype=torch.float64)
    else:
        u = torch.rand(n, d, generator=generator, dtype=torch.float64, device=_generator_device(generator)).cpu()
    return u.clamp(1e-12, 1 - 1e-12)


def _chi_scale(u: Tensor, df: float) -> Tensor:
    """sqrt(df / v) (n,) for v = 2 P^-1(df / 2, u) a chi-square with ``df`` degrees of freedom at uniforms u (n,)
    (scipy.special's inverse regularised gamma, lighter to import than scipy.stats)."""
    from scipy.special import gammaincinv

    v = torch.as_tensor(2 * gammaincinv(df / 2, u.numpy()), dtype=torch.float64)
    return (df / v).sqrt()


def _standard_t(P: int, df: float, n: int, generator, qmc: bool, dtype, device) -> Tensor:
    """n draws (n, P) of the standard multivariate Student-t (location 0, scale I, ``df`` degrees of freedom);
    ``qmc`` as in ``_student_t``."""
    if qmc:
        u = _uniforms(P + 1, n, generator, True)
        z = math.sqrt(2) * torch.special.erfinv(2 * u[:, :P] - 1)
        return (z * _chi_scale(u[:, P], df)[:, None]).to(dtype=dtype, device=device)
    gd = _generator_device(generator)
    z = torch.randn(n, P, generator=generator, dtype=dtype, device=gd).to(device)
    v = torch.randn(n, int(df), generator=generator, dtype=dtype, device=gd).pow(2).sum(-1).to(device)
    return z * (df / v).sqrt()[:, None]


def _standard_t_log_density(z: Tensor, df: float) -> Tensor:
    """log density (n,) at z (n, P) of the standard multivariate Student-t."""
    P = z.shape[-1]
    return (math.lgamma((df + P) / 2) - math.lgamma(df / 2) - 0.5 * P * math.log(df * math.pi)
            - 0.5 * (df + P) * torch.log1p(z.pow(2).sum(-1) / df))


def _split_t(mean: Tensor, axes: SplitAxes, df: float, n: int, generator, qmc: bool = True) -> tuple[Tensor, Tensor]:
    """n draws (n, P) of the split Student-t at ``mean`` with ``axes`` and their log density (n,). Each coordinate
    of z falls on its positive side with probability hi / (lo + hi) (the split normal's inverse CDF per coordinate,
    from one uniform each: a Sobol point stays one), then the chi-square's scale is applied to all."""
    P = mean.numel()
    u = _uniforms(P + 1, n, generator, qmc)
    lo, hi = axes.lo.detach().double().cpu(), axes.hi.detach().double().cpu()
    q = lo / (lo + hi)  # the negative side's share
    neg = u[:, :P] < q
    a = torch.where(neg, 1 - u[:, :P] / q, (u[:, :P] - q) / (1 - q)).clamp(1e-12, 1 - 1e-12)
    z = torch.where(neg, -1.0, 1.0) * math.sqrt(2) * torch.special.erfinv(a) * _chi_scale(u[:, P], df)[:, None]
    y = (z * torch.where(neg, lo, hi)).to(mean)
    x = mean + y @ axes.L.mT
    return x, _split_t_log_density(x, mean, axes, df)


def _split_t_log_density(x: Tensor, mean: Tensor, axes: SplitAxes, df: float) -> Tensor:
    """log density (n,) at x (n, P) of the split Student-t, continuous across its axes (Geweke 1989): the standard
    t at y / s, y = L^-1 (x - mean) and s each coordinate's side, over det L and prod (lo + hi) / 2 (an orthant
    holds the share prod s / (lo + hi) of the mass: the sides' proportions)."""
    y = torch.linalg.solve_triangular(axes.L, (x - mean).mT, upper=False).mT
    s = torch.where(y > 0, axes.hi, axes.lo)
    return (_standard_t_log_density(y / s, df) - torch.diagonal(axes.L).log().sum()
            - (0.5 * (axes.lo + axes.hi)).log().sum())


def _student_t(mean: Tensor, cov: Tensor, df: float, n: int, generator, qmc: bool = True) -> tuple[Tensor, Tensor]:
    """n draws (n, P) of a multivariate Student-t and their log density (n,). ``qmc``: from a scrambled
    Sobol sequence in P + 1 dimensions (normals by the inverse normal CDF, the chi-square's inverse CDF
    2 P^-1(df / 2, u) by scipy.special, lighter to import than scipy.stats): importance-sampling estimates then
    converge about as 1/n instead of 1/sqrt(n)."""
    L = torch.linalg.cholesky(cov)
    x = mean + _standard_t(mean.numel(), df, n, generator, qmc, mean.dtype, mean.device) @ L.mT
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
                      n2: int | None = None, axes: SplitAxes | None = None,
                      more: Callable[[Tensor], bool] | None = None,
                      max_stages: int = 2) -> tuple[Tensor, Tensor, Tensor, int]:
    """Proposals x (N, P), their log posterior (N,) and log importance weights (N,) (unnormalised), and the
    number of stages, from the first stage's draws ``first`` (``first_stage``: x, log proposal density, log
    posterior) of the Student-t (``mean``, ``cov``, ``df``; split along ``axes`` where given). Where
    ``adapt(log weights)`` says they are unreliable, stage 2 (``next_stage``, ``n2`` proposals, None: as many as
    the first) is drawn and all are weighed together; then more stages of that size, each moved to all the
    weighted draws so far, while ``more(log weights)`` says so, up to ``max_stages`` in all. ``log_p_many``:
    (n, P) -> (n,), -inf where impossible."""
    x, logq1, logp = first
    logw = logp - logq1
    if adapt is None or not torch.isfinite(logw).any() or not adapt(logw):
        return x, logp, logw, 1
    if axes is None:
        L1 = torch.linalg.cholesky(cov)
        stages = [(x.shape[0], lambda y: _student_t_log_density(y, mean, L1, df))]
    else:
        stages = [(x.shape[0], lambda y: _split_t_log_density(y, mean, axes, df))]
    n = x.shape[0] if n2 is None else int(n2)
    x, logp, logw = next_stage(log_p_many, x, logp, logw, stages, cov, df, n, generator, qmc)
    while len(stages) < max_stages and more is not None and torch.isfinite(logw).any() and more(logw):
        x, logp, logw = next_stage(log_p_many, x, logp, logw, stages, cov, df, n, generator, qmc)
    return x, logp, logw, len(stages)


def _balance(x: Tensor, stages: list) -> Tensor:
    """log density (N,) at x (N, P) of the mixture of the stages' proposals in their proportions (the balance
    heuristic: Owen & Zhou 2000); ``stages``: (count, log density) per stage."""
    total = sum(c for c, _ in stages)
    return torch.logsumexp(torch.stack([f(x) + math.log(c / total) for c, f in stages]), 0)


def first_stage(log_p_many: Callable[[Tensor], Tensor], mean: Tensor, cov: Tensor, df: float, n: int, generator,
                qmc: bool = True, axes: SplitAxes | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """n proposals x (n, P) of the Student-t (``mean``, ``cov``, ``df``; the split-t along ``axes`` where given,
    ``cov`` then unused), their log density (n,) and log posterior (n,)."""
    if axes is None:
        x, logq = _student_t(mean, cov, df, n, generator, qmc)
    else:
        x, logq = _split_t(mean, axes, df, n, generator, qmc)
    return x, logq, log_p_many(x)


def next_stage(log_p_many: Callable[[Tensor], Tensor], x: Tensor, logp: Tensor, logw: Tensor, stages: list,
               cov: Tensor, df: float, n: int, generator, qmc: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """``n`` proposals more, from a Student-t moved to the weighted draws so far (x (N, P), log posterior and log
    weights (N,)), with the average of their weighted covariance and ``cov`` (the covariance of a few effective
    draws alone can be near singular); every draw of every stage is weighed against the mixture of the stages'
    proposals in their proportions (the balance heuristic: Owen & Zhou 2000; adaptive multiple importance
    sampling, Cornuet et al. 2012). ``stages``: (count, log density) per stage so far, appended to. Returns x
    (N + n, P), log posterior and log weights (N + n,)."""
    ok = torch.isfinite(logw)
    w = torch.where(ok, (logw - logw[ok].max()).exp(), torch.zeros_like(logw))
    mu, C = _weighted_moments(x, w / w.sum())
    cov_k = 0.5 * C + 0.5 * cov
    L_k = torch.linalg.cholesky(cov_k)
    x_k, _ = _student_t(mu, cov_k, df, int(n), generator, qmc)
    stages.append((int(n), lambda y: _student_t_log_density(y, mu, L_k, df)))
    x = torch.cat([x, x_k])
    logp = torch.cat([logp, log_p_many(x_k)])
    return x, logp, logp - _balance(x, stages)


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
    P = x.shape[-1]
    C = torch.cov(x.mT, correction=0, aweights=w).reshape(P, P)  # (P, P) for one coordinate too (torch: 0-D)
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
