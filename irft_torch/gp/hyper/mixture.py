"""Predictions averaged over hyperparameter draws: a finite Gaussian mixture per output.

With hyperparameters theta_s drawn from their posterior (weights w_s, sum 1), the predictive density
of any output is sum_s w_s N(mu_s, sigma_s^2) (botorch's ``GaussianMixturePosterior`` does the same
for its fully Bayesian GPs). Its mean and total variance are

    mu = sum_s w_s mu_s,     sigma^2 = sum_s w_s (sigma_s^2 + mu_s^2) - mu^2,

and its quantiles come from the mixture CDF F(x) = sum_s w_s Phi((x - mu_s) / sigma_s), inverted by
bisection (a mixture's quantile is not mu + z sigma: that would be the moment-matched Gaussian).

The weights are (S,), one per draw, or (S, K) with K the outputs' last dimension (the two maps or force
axes): a mixture per axis, for draws whose weight differs between the maps (models averaged per map,
``InverseRFT(..., prior=MapPrior(mean="average"))``); or already shaped like the components, with 1 where they are
shared (``TerrainFilterMixture``: (S, B, 1, 2), each environment's own weights).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["mixture_moments", "mixture_quantile", "broadcast_weights", "mixture_covariance"]


def broadcast_weights(weights: Tensor, means: Tensor) -> Tensor:
    """Weights (S,) or (S, K) shaped to broadcast against components (S, ..., K): (S, 1, ..., 1) or
    (S, 1, ..., 1, K)."""
    w = weights.to(means)
    if w.ndim == 1 and w.shape[0] == means.shape[0]:
        return w.reshape(-1, *([1] * (means.ndim - 1)))
    if w.ndim == 2 and w.shape[0] == means.shape[0] and means.ndim >= 2 and w.shape[1] == means.shape[-1]:
        return w.reshape(w.shape[0], *([1] * (means.ndim - 2)), w.shape[1])
    if w.ndim == means.ndim and w.shape[0] == means.shape[0] and all(
            a in (1, b) for a, b in zip(w.shape, means.shape)):  # already shaped: per item (e.g. per environment)
        return w
    raise ValueError(f"weights must be (S,) or (S, K) for components {tuple(means.shape)}, got {tuple(w.shape)}")


def mixture_moments(means: Tensor, variances: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Mean and total variance of the mixture: ``means``, ``variances`` (S, ...) per draw, ``weights``
    (S,) (or (S, K), see the module docstring) summing to 1 over S. Returns two tensors of shape (...)."""
    w = broadcast_weights(weights, means)
    mean = (w * means).sum(0)
    # sum_s w_s (mu_s - mu)^2 rather than E[mu^2] - mu^2: no cancellation when the draws agree
    var = (w * (variances.clamp_min(0) + (means - mean).pow(2))).sum(0)
    return mean, var


def mixture_cdf(x: Tensor, means: Tensor, stds: Tensor, weights: Tensor) -> Tensor:
    """F(x) = sum_s w_s Phi((x - mu_s) / sigma_s), x of shape (...), components (S, ...). A component of
    zero std is a step at its mean."""
    w = broadcast_weights(weights, means)
    z = (x - means) / stds.clamp_min(torch.finfo(means.dtype).tiny)
    return (w * 0.5 * torch.special.erfc(-z / math.sqrt(2))).sum(0)


def mixture_quantile(q: float, means: Tensor, variances: Tensor, weights: Tensor, iters: int = 80) -> Tensor:
    """The q-quantile (q in (0, 1)) of the mixture at every output, (...): bisection of the mixture CDF
    between the components' own q-quantiles (the mixture's lies between their least and greatest, as F is
    a weighted average of the components' CDFs). 80 halvings leave the bracket at 2^-80 of its width."""
    if not 0 < q < 1:
        raise ValueError(f"q must be in (0, 1), got {q}")
    stds = variances.clamp_min(0).sqrt()
    z = math.sqrt(2) * torch.special.erfinv(torch.tensor(2 * q - 1, dtype=torch.float64)).item()
    own = means + z * stds
    live = broadcast_weights(weights, means) > 0
    big = torch.finfo(means.dtype).max
    lo = torch.where(live, own, torch.full_like(own, big)).amin(0)
    hi = torch.where(live, own, torch.full_like(own, -big)).amax(0)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        below = mixture_cdf(mid, means, stds, weights) < q
        lo = torch.where(below, mid, lo)
        hi = torch.where(below, hi, mid)
    return 0.5 * (lo + hi)


def mixture_covariance(means: Tensor, covariances: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Mean (..., K) and covariance (..., K, K) of the mixture over draws: ``means`` (S, ..., K), ``covariances``
    (S, ..., K, K), ``weights`` (S,) summing to 1."""
    w = weights.to(means).reshape(-1, *([1] * (means.ndim - 1)))
    mean = (w * means).sum(0)
    d = means - mean
    cov = (w[..., None] * (covariances + d[..., :, None] * d[..., None, :])).sum(0)
    return mean, cov
