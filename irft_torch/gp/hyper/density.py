r"""The hyperparameters' log posterior in closed form: one theta with its gradient, or a batch of draws.

theta = log(value) for the free hyperparameters (``hyper_posterior.HyperSpec``), and

    log p(theta | F) = -n sum_a nll_a(values) + log p(values),     values = exp(theta),
    d log p / d theta = (-n d nll / d value + d log p(values) / d value) * value,

with nll and its gradient from the backend's ``closed_form()`` (``backends.closed_form``: no autograd
through the Cholesky, one call for a whole batch of draws) and the physical priors' density in closed
form (``closed_form.prior_terms``). ``hyper_posterior.log_posterior`` uses this for L-BFGS and NUTS (a
value attached to theta with its closed-form gradient, ``closed_form_log_posterior``) and ``laplace`` for its proposals
(``log_posterior_batch``). Where there is no closed form (a backend without one, a prior registered by
hand, a free parameter no term covers), each function returns None and the autograd path serves.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..backends.closed_form import closed_form_of, current_values, prior_terms
from ..backends.covariance_terms import LENGTHSCALE
from ..backends.spectral import draws_in_one_basis

__all__ = ["log_posterior_and_grad", "log_posterior_and_grad_chunked", "log_posterior_batch",
           "closed_form_log_posterior", "draws_in_one_basis"]

# On the CPU a batch's largest intermediate (S x 2 x r x F numbers) is kept near this size, and near the second with
# gradients (each chunk keeps several blocks of that size alive). Measured on the 1,000-sample varied recording
# (r = F = 539, bench_inference case 12): its draws' likelihoods 3.3 s at 2**22 against 2.3 s at 2**20 and 2**19; the
# 29 points of its Hessian 536 ms in one batch against 284 ms one at a time. On a GPU, where a step is bound by
# kernel launches, not memory (docs/backends.md), the batches stay as large as before (not measured smaller there).
BATCH_ELEMENTS = 2**20
GRADIENT_ELEMENTS = 2**19
GPU_BATCH_ELEMENTS = 2**22


def _chunk(theta: Tensor, elements: int, grad: bool) -> int:
    """Draws per chunk for draws of ``elements`` numbers each: ``GRADIENT_ELEMENTS`` (``grad``) or ``BATCH_ELEMENTS``
    of them on the CPU; on a GPU ``GPU_BATCH_ELEMENTS``, and with gradients the whole batch (as before)."""
    if theta.device.type == "cpu":
        budget = GRADIENT_ELEMENTS if grad else BATCH_ELEMENTS
    else:
        budget = 2**62 if grad else GPU_BATCH_ELEMENTS
    return max(1, budget // max(elements, 1))


def _values(backend, spec, theta: Tensor) -> tuple[dict[str, Tensor], Tensor]:
    """Every hyperparameter's value (name -> (*S, *shape)) for theta (*S, P_free), the fixed ones at their
    current values, and whether each draw is possible (every value above its constraint's lower bound)."""
    full = spec.full(theta).exp()
    batch = full.shape[:-1]
    values, valid, i = {}, torch.ones(batch, dtype=torch.bool, device=full.device), 0
    for name, shape, c in zip(spec.names, spec.shapes, spec.constraints):
        k = shape.numel()
        v = full[..., i:i + k].reshape(*batch, *shape)
        valid &= (v > c.lower_bound.to(v)).reshape(*batch, -1).all(-1)
        values[name] = v
        i += k
    for name, v in current_values(backend.hypers, skip=values).items():  # those held at their values
        values[name] = v.expand(*batch, *v.shape)
    return values, valid


def log_posterior_and_grad(backend, spec, theta: Tensor, grad: bool = True,
                           prepare: bool = True) -> tuple[Tensor, Tensor | None] | None:
    """log p(theta | F) (*S,) (-inf where a value is impossible or the covariance not positive definite)
    and its gradient (*S, P_free) (zeros where -inf), for theta (*S, P_free); None without a closed form.
    ``prepare``: let the backend adapt to the values first (False: it holds them already)."""
    cf = closed_form_of(backend)
    if cf is None or any(name not in cf.names for name in spec.names):
        return None
    hypers = backend.hypers
    theta = theta.detach()
    values, valid = _values(backend, spec, theta)
    if not bool(valid.any()):  # nothing possible to evaluate (nor to size a basis for)
        lp = theta.new_full(theta.shape[:-1], -math.inf)
        return lp, (torch.zeros_like(theta) if grad else None)
    if prepare and theta.dim() == 1 and LENGTHSCALE in values:  # one setting (L-BFGS, NUTS): the space it needs
        space = backend.space_for(values[LENGTHSCALE])
        if space is not backend:
            return log_posterior_and_grad(space, spec, theta, grad, prepare=False)
    if prepare:
        backend.prepare({n: v[valid] for n, v in values.items()} if valid.dim() else values)
        cf = closed_form_of(backend)  # rebuilt if ``prepare`` grew the spectral basis
    lp_prior, g_prior, others = prior_terms(hypers, values, grad)
    if others:
        return None
    nll, g, ok = cf.evaluate(values, grad)
    n = backend.n_samples
    lp = -nll.sum(-1) * n + lp_prior
    good = valid & ok & torch.isfinite(lp)
    lp = torch.where(good, lp, torch.full_like(lp, -math.inf))
    if not grad:
        return lp, None
    batch = theta.shape[:-1]
    parts = []
    for name in spec.names:
        d = -n * g[name]
        if name in g_prior:
            d = d + g_prior[name]
        parts.append((d * values[name]).reshape(*batch, -1))
    d_theta = spec.free_part(torch.cat(parts, -1))
    return lp, torch.where(good[..., None], d_theta, torch.zeros_like(d_theta))


def log_posterior_batch(backend, spec, theta: Tensor, grouped: bool = True) -> Tensor | None:
    """log p(theta_s | F) (S,) for theta (S, P_free), in chunks of draws (no gradient); None without a
    closed form. ``grouped``: each draw in the space its own values need (``backend.draw_groups``: a spectral
    backend evaluates each group of draws in the basis their lengthscales need, and keeps its own); False: every
    draw in this backend, grown first to hold them all."""
    cf = closed_form_of(backend)
    if cf is None:
        return None
    S = theta.shape[0]
    if S == 0:
        return theta.new_zeros(0)
    values, valid = _values(backend, spec, theta)
    groups = (backend.draw_groups(values[LENGTHSCALE][valid]) if grouped and bool(valid.any())
              and LENGTHSCALE in values else None)
    if groups is None or (len(groups) == 1 and groups[0][1] is backend):
        if bool(valid.any()):
            backend.prepare({n: v[valid] for n, v in values.items()})  # one basis for every possible draw
        return _in_chunks(backend, spec, theta, prepare=True)
    lp = theta.new_full((S,), -math.inf)
    where = valid.nonzero()[:, 0]
    for mask, part in groups:  # each part holds its draws already
        idx = where[mask]
        if len(idx):
            got = _in_chunks(part, spec, theta[idx], prepare=False)
            if got is None:
                return None
            lp[idx] = got
    return lp


def log_posterior_and_grad_chunked(backend, spec, theta: Tensor) -> tuple[Tensor, Tensor | None] | None:
    """``log_posterior_and_grad`` over theta (S, P_free) in chunks (on the CPU, each's largest intermediate about
    ``GRADIENT_ELEMENTS`` numbers; on a GPU one chunk), the backend prepared once for all of them (every point in the
    same space: the differences between their gradients carry no change of basis); None without a closed form."""
    cf = closed_form_of(backend)
    if cf is None or any(name not in cf.names for name in spec.names):
        return None
    if theta.shape[0] == 0:
        return theta.new_zeros(0), theta.new_zeros(theta.shape)
    values, valid = _values(backend, spec, theta.detach())
    if bool(valid.any()):
        backend.prepare({n: v[valid] for n, v in values.items()})
    cf = closed_form_of(backend)
    chunk = _chunk(theta, cf.elements, True) if cf is not None else theta.shape[0]
    parts = [log_posterior_and_grad(backend, spec, theta[i:i + chunk], prepare=False)
             for i in range(0, theta.shape[0], chunk)]
    if any(p is None for p in parts):
        return None
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


def _in_chunks(backend, spec, theta: Tensor, prepare: bool) -> Tensor | None:
    """``log_posterior_and_grad`` (no gradient) over theta (S, P_free) in chunks whose largest intermediate is
    about ``BATCH_ELEMENTS`` numbers."""
    cf = closed_form_of(backend)
    if cf is None:
        return None
    chunk = _chunk(theta, cf.elements, False)
    out = []
    with torch.no_grad():
        for i in range(0, theta.shape[0], chunk):
            res = log_posterior_and_grad(backend, spec, theta[i:i + chunk], grad=False, prepare=prepare)
            if res is None:
                return None
            out.append(res[0])
    return torch.cat(out)


class _WithGradient(torch.autograd.Function):
    """A value computed elsewhere, attached to theta with its known gradient (first derivatives only)."""

    @staticmethod
    def forward(ctx, theta: Tensor, value: Tensor, gradient: Tensor) -> Tensor:
        ctx.save_for_backward(gradient)
        return value.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_output: Tensor):
        (g,) = ctx.saved_tensors
        return grad_output * g, None, None


def closed_form_log_posterior(backend, spec, theta: Tensor) -> Tensor | None:
    """log p(theta | F) for one theta (P_free,), differentiable in theta with the closed-form gradient (what
    L-BFGS and pyro's NUTS differentiate; no second derivatives: the Laplace Hessian takes the autograd
    path); None without a closed form."""
    need = torch.is_grad_enabled() and theta.requires_grad
    res = log_posterior_and_grad(backend, spec, theta, grad=need)
    if res is None:
        return None
    lp, g = res
    return _WithGradient.apply(theta, lp, g) if need else lp
