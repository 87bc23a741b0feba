"""Pareto k-hat: how far importance weights can be trusted (Vehtari, Simpson, Gelman, Yao & Gabry, "Pareto
smoothed importance sampling", JMLR 2024). ``gp.hyper.posterior`` reports it for the Laplace proposals' weights."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["pareto_khat", "gpd_shape"]


def pareto_khat(log_weights: Tensor) -> float:
    """Pareto k-hat of importance weights (Vehtari, Simpson, Gelman, Yao & Gabry, "Pareto smoothed importance
    sampling", JMLR 2024): the shape of a generalized Pareto distribution fitted (``gpd_shape``: Zhang &
    Stephens' estimator, as PSIS uses it) to the M = min(N / 5, 3 sqrt(N)) largest weights above the next one.
    < 0.5: fine; 0.5-0.7: usable; > 0.7: the weights' variance is unreliable."""
    lw = log_weights[torch.isfinite(log_weights)].detach().double().cpu()
    N = lw.numel()
    M = int(min(N / 5, 3 * math.sqrt(N)))
    if M < 5:
        return float("nan")
    w = (lw - lw.max()).exp().sort().values
    tail, cut = w[-M:], w[-M - 1]
    excess = tail - cut
    if excess.max() <= 0:
        return 0.0
    return gpd_shape(excess)


def gpd_shape(x: Tensor, prior_k: float = 10.0) -> float:
    """The shape k of a generalized Pareto distribution (location 0) fitted to exceedances x (n,) > 0, ascending:
    Zhang & Stephens (2009, Technometrics 51:316), the posterior mean of theta = -k / sigma on their grid of
    30 + sqrt(n) points weighted by the profile likelihood, then k = mean(log1p(-theta x)), shrunk toward 0.5
    with weight ``prior_k`` as PSIS does (Vehtari et al. 2024, appendix; the R package loo's ``gpdfit``).
    No iterative fit: a few vectorised passes, where a maximum-likelihood fit takes hundreds of evaluations. pyro's
    ``pyro.ops.stats.fit_generalized_pareto`` is the same estimator; pyro is optional here (the ``bayes`` extra),
    so the library keeps its own and the tests check it against pyro's where pyro is installed."""
    x = x.double().sort().values
    n = x.numel()
    m = 30 + int(math.sqrt(n))
    j = torch.arange(1, m + 1, dtype=torch.float64)
    theta = 1 - torch.sqrt(m / (j - 0.5))
    theta = theta / (3 * x[int(n / 4 + 0.5) - 1]) + 1 / x[-1]
    k = torch.log1p(-theta[:, None] * x[None, :]).mean(-1)
    profile = n * (torch.log(-theta / k) - k - 1)
    w = torch.softmax(profile, 0)
    theta_hat = (w * theta).sum()
    k_hat = float(torch.log1p(-theta_hat * x).mean())
    return (n * k_hat + prior_k * 0.5) / (n + prior_k)
