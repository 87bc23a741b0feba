r"""Where the Laplace approximation of the hyperparameter posterior does not hold, and what is done then.

``gp.hyper.posterior.laplace`` puts a Gaussian N(mode, H^-1) at the mode of log p(theta | F) and reweights
proposals from a wider Student-t. Three situations break that, and each is met here instead of giving a
silently wrong mixture:

- **A wall.** A hyperparameter pushed against an impossible setting: noise-free forces drive the noise
  variance down until the kernel matrix stops being positive definite (log p = -inf a little below), so the
  polished point is no mode (the gradient there is large) and the Hessian's width in that coordinate is
  meaningless. A coordinate is *at a wall* when one Laplace standard deviation either way along it is
  impossible (``walls``). Such coordinates are held at the polished value (not marginalised: reported in
  ``HyperPosterior.extra["held"]``) and the rest are polished again.
- **An improper direction.** Without priors (``MapPrior(hyperpriors=None)``) a lengthscale the data do not constrain
  has a flat likelihood: the Hessian is ~0 there and the Gaussian's width unbounded (a proposal at theta = 900, a
  lengthscale of e^900). The proposal's standard deviation is capped at ``MAX_LOG_SD`` in every direction
  (``proposal_covariance``): such a direction is explored within a factor e^5 of its mode.
- **Unreliable weights.** Pareto k-hat above 0.7 (PSIS's threshold) or an effective sample size below 2:
  the mixture rests on a few proposals. A second stage of proposals, moved to where the first stage's weights
  lie (``gp.hyper.importance.importance_sample``), is drawn first; where the weights stay unreliable,
  ``HyperPosteriorWarning`` says so, with the numbers and what
  to do (``hyper_posterior="nuts"``); where every proposal is impossible, the plug-in at the mode is kept
  (a point mass) with the same warning instead of an error in the middle of ``fit``.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Iterator

import torch
from torch import Tensor

from .pareto import pareto_khat

__all__ = ["HyperPosteriorWarning", "MAX_LOG_SD", "KHAT_RELIABLE", "MIN_ESS", "walls", "effective_size",
           "positive_definite", "proposal_covariance", "possible", "lower_bounds", "unreliable", "reliability_message",
           "said_once"]

MAX_LOG_SD = 5.0  # the Laplace Gaussian's widest standard deviation in theta = log(value)
KHAT_RELIABLE = 0.7  # PSIS (Vehtari et al.): above it the importance weights' estimates are unreliable
MIN_ESS = 2.0  # below it the mixture is one proposal: not a posterior


class HyperPosteriorWarning(UserWarning):
    """The hyperparameter posterior is a poor approximation here (``gp.hyper.guard``): unreliable importance
    weights, coordinates held at a wall, or the plug-in kept where every proposal was impossible."""


@contextlib.contextmanager
def said_once(truncated: list[str] | None = None) -> Iterator[None]:
    """What a hyperparameter posterior's many draws warn, said once: each distinct warning once, and the Fourier
    basis' "need more than ... harmonics" (one per short-lengthscale draw, each with its own numbers) either
    appended to ``truncated`` (the caller reports them: ``model.diagnostics()``) or, without a list, one warning
    that counts them. The fit's own warnings (``FitDivergedWarning``, the plug-in's basis) are not here."""
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as recorded:
            warnings.simplefilter("always")
            try:
                yield
            finally:
                caught = list(recorded or [])
    finally:  # said even where the body raised
        _say_once(caught, truncated)


def _say_once(caught: list, truncated: list[str] | None) -> None:
    seen: set[tuple[type, str]] = set()
    cut = [w for w in caught if "harmonics" in str(w.message)]
    for w in caught:
        if w in cut or (w.category, str(w.message)) in seen:
            continue
        seen.add((w.category, str(w.message)))
        warnings.warn(w.message, w.category, stacklevel=4)
    if cut and truncated is not None:
        truncated += [str(w.message) for w in cut]
    elif cut:
        warnings.warn(f"{len(cut)} hyperparameter draw(s) with short lengthscales need a Fourier basis beyond its cap: "
                      f"their kernel is truncated, e.g. {cut[0].message}", cut[0].category, stacklevel=4)


def positive_definite(H: Tensor, floor: float = 1e-6, min_eigenvalue: float = 0.0) -> Tensor:
    """H (P, P) with eigenvalues below ``floor`` x the largest, and below ``min_eigenvalue``, raised to them (a
    direction the posterior is flat or convex in at the point gets a wide, finite Gaussian: the importance
    weights then correct it)."""
    lam, V = torch.linalg.eigh(0.5 * (H + H.mT))
    lam = lam.clamp_min(floor * lam.abs().max().clamp_min(1e-300)).clamp_min(min_eigenvalue)
    return (V * lam) @ V.mT


def proposal_covariance(H: Tensor, floor: float = 1e-6) -> Tensor:
    """H^-1 (P, P) of a Hessian H of -log p, of ``positive_definite(H)`` with eigenvalues also at least
    1 / MAX_LOG_SD^2: no direction wider than MAX_LOG_SD."""
    cov = torch.linalg.inv(positive_definite(H, floor, 1.0 / MAX_LOG_SD**2))
    return 0.5 * (cov + cov.mT)


def walls(log_p_many: Callable[[Tensor], Tensor], mode: Tensor, sd: Tensor) -> Tensor:
    """(P,) bool: the coordinates along which one standard deviation ``sd`` (P,) either way from ``mode`` (P,)
    is impossible (log p not finite). ``log_p_many``: (n, P) -> (n,) log posterior."""
    P = mode.numel()
    step = torch.diag(sd.to(mode))
    x = torch.cat([mode + step, mode - step])  # (2P, P)
    with torch.no_grad():
        lp = log_p_many(x)
    bad = ~torch.isfinite(lp)
    return bad[:P] | bad[P:]


def lower_bounds(spec) -> Tensor:
    """(P,) each coordinate's lower bound (its value must exceed it) of a ``gp.hyper.posterior.HyperSpec``."""
    return torch.cat([c.lower_bound.expand(s).reshape(-1) if c.lower_bound.numel() > 1
                      else c.lower_bound.reshape(1).expand(s.numel())
                      for s, c in zip(spec.shapes, spec.constraints)])


def possible(theta: Tensor, lower: Tensor) -> Tensor:
    """(n,) bool: draws theta (n, P) whose values exp(theta) are finite and above their lower bounds (P,)."""
    v = theta.exp()
    return (torch.isfinite(v) & (v > lower.to(v))).all(-1)


def effective_size(log_weights: Tensor) -> float:
    """The effective sample size (sum w)^2 / sum w^2 of importance weights (unnormalised logs (n,), -inf where
    impossible); 0 where none is possible."""
    ok = torch.isfinite(log_weights)
    if not ok.any():
        return 0.0
    w = (log_weights[ok] - log_weights[ok].max()).exp()
    return float(w.sum() ** 2 / w.pow(2).sum())


def unreliable(log_weights: Tensor) -> bool:
    """Whether importance weights (unnormalised logs (n,), -inf where impossible) are unreliable: Pareto k-hat
    above ``KHAT_RELIABLE`` or an effective sample size below ``MIN_ESS``."""
    if not torch.isfinite(log_weights).any():
        return True
    return effective_size(log_weights) < MIN_ESS or pareto_khat(log_weights) > KHAT_RELIABLE


def reliability_message(ess: float, khat: float, n_proposals: int, held: list[str]) -> str | None:
    """The warning for unreliable importance weights or held coordinates, None where neither applies."""
    parts = []
    why = ([f"Pareto k-hat {khat:.2f} > {KHAT_RELIABLE}"] if khat > KHAT_RELIABLE else []) + \
          ([f"effective sample size {ess:.1f} < {MIN_ESS:g}"] if ess < MIN_ESS else [])
    if why:
        parts.append(f"the Laplace importance weights are unreliable ({' and '.join(why)}, {n_proposals} proposals): "
                     f"the posterior is far from Gaussian here and the mixture rests on few proposals; "
                     f"hyper_posterior='nuts' samples it (pip install pyro-ppl)")
    if held:
        parts.append(f"held at their fitted values, not marginalised (at a wall: one standard deviation away is an "
                     f"impossible setting, e.g. a noise driven to its floor by noise-free forces): {', '.join(held)}")
    return "; ".join(parts) if parts else None
