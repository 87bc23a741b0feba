r"""One loss and its gradient in closed form, without autograd through the Cholesky, and over a batch of
hyperparameter draws in one call.

Every exact backend writes the force covariance of axis a as sigma_a^2 I + A_a with A = R Sigma R^T
(pairs, spectral: R (r x F) from the data, ``weight_space``) or A = Sigma itself (observations: R = I).
With L L^T = sigma^2 I + A and alpha = (sigma^2 I + A)^{-1} c (c, rho: the forces' coordinates and their
residual outside R's range, ``weight_space``), per axis

    nll = [rho / sigma^2 + c^T alpha + (n - r) log sigma^2 + log |sigma^2 I + A| + n log 2 pi] / (2 n)
    d nll / d A       = G = [(sigma^2 I + A)^{-1} - alpha alpha^T] / (2 n),   d nll / d Sigma = R^T G R
    d nll / d sigma^2 = [(n - r) / sigma^2 - rho / sigma^4 + tr (sigma^2 I + A)^{-1} - |alpha|^2] / (2 n)
    d nll / d m       = [(m rho_gg - rho_yg) / sigma^2 - alpha^T c_g] / n      (the physics mean's scale m:
                        c = c_y - m c_g, rho = rho_yy - 2 m rho_yg + m^2 rho_gg)

Sigma is a sum of :class:`~irft_torch.gp.backends.covariance_terms.CovarianceTerm` s, each with its own
d Sigma / d value. The registered priors' density (the physical ones in closed form, others by autograd)
and the constraints' chain rule value -> raw parameter complete the gradient of ``RFTBackend.loss``
(``loss_and_grad``, what ``InverseRFT.fit``'s Adam loop calls). ``ClosedForm.evaluate`` takes values
with leading batch dimensions: S hyperparameter draws in one call (``gp.hyper.density``: Laplace's
proposals, NUTS).

**Adding a kernel term** (say k_dev(theta, theta') = sum_k v_k h_k(theta) h_k(theta'), h_k fixed
low-order Fourier functions, with variances v a raw parameter ``"dev.raw_variances"`` registered with a
constraint on ``RFTHyperparameters``): write a ``CovarianceTerm`` with ``names = ("dev.raw_variances",)``,
``forward(values, R)`` returning A_k = (R H^T) diag(v) (R H^T)^T (H (K, F): the h_k at the distinct
pairs, or their coefficients in the spectral basis; R None: at the observations' segments, summed with
their weights) and what ``backward`` needs, and ``backward(values, adj, state)`` returning
{"dev.raw_variances": d nll / d v} with d nll / d v_k = (R h_k)^T G (R h_k) (``adj.G``); append it to the
terms the backend's ``closed_form()`` builds (``_closed_form_terms`` for pairs and spectral). The chain
rule to the raw parameter, its registered priors, the batch over draws and the Adam loop need nothing
more. A free parameter no term claims makes ``loss_and_grad`` return None (autograd then serves): never
a silent zero gradient.
"""

from __future__ import annotations

import contextlib
import functools
import math
import weakref

import torch
from gpytorch.constraints import GreaterThan
from gpytorch.constraints.constraints import softplus as _gpytorch_softplus
from gpytorch.priors import NormalPrior
from torch import Tensor

from ..kernels.li_basis import LI_GENERIC, LI_VARIANCE
from .covariance_terms import LENGTHSCALE, MEAN, NOISE, OUTPUTSCALE, Adjoint, CovarianceTerm

__all__ = ["ClosedForm", "autograd_only", "closed_form_enabled", "closed_form_of", "current_values", "loss_and_grad",
           "prior_terms", "value_gradient_to_raw"]

LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))
_ENABLED = [True]


@contextlib.contextmanager
def autograd_only():
    """Within this context the engine is the one before the closed form existed: every closed-form path
    stands aside and the autograd ones serve, and a data factor computed from rows keeps its zero rows
    (``weight_space.data_factor_from_rows``). The reference in benchmarks
    (``experiments/benchmarks/bench_inference.py``) and tests."""
    _ENABLED.append(False)
    try:
        yield
    finally:
        _ENABLED.pop()


def closed_form_enabled() -> bool:
    """False inside ``autograd_only``."""
    return _ENABLED[-1]


def closed_form_of(backend):
    """``backend.closed_form()``, or None inside ``autograd_only`` and for a backend without one (the 3-D
    backends: their hyperparameter posterior goes through autograd)."""
    make = getattr(backend, "closed_form", None)
    return make() if _ENABLED[-1] and make is not None else None


# ---- the Gaussian likelihood ------------------------------------------------------------------------
def _noise_per_axis(v: Tensor) -> Tensor:
    """The noise value (*S, 2, 1) (per axis) or (*S, 1) (tied) -> (*S, 2)."""
    return v[..., 0] if v.dim() >= 2 and v.shape[-2:] == (2, 1) else v.expand(*v.shape[:-1], 2)


def _noise_gradient(g: Tensor, v: Tensor) -> Tensor:
    """(*S, 2) per-axis gradient -> the noise value's shape."""
    return g[..., None] if v.dim() >= 2 and v.shape[-2:] == (2, 1) else g.sum(-1, keepdim=True)


class ClosedForm:
    """The negative log likelihood per sample and axis, and its gradient in every hyperparameter value, of
    one backend's data: A = sum_k R Sigma_k R^T (module docstring).

    Args:
        R: (2, r, F), or None (A = Sigma: the observations' space).
        c_y: (2, r) the forces' coordinates.
        c_g: (2, r) the physics mean's shape forces' coordinates (None: no mean).
        rho: (2, 3) residuals (rho_yy, rho_yg, rho_gg) outside R's range (zeros in the observations' space).
        n: force samples (the per-sample normalization; rows that never touch count).
        terms: the ``CovarianceTerm`` s of Sigma.
        symmetrize: A <- (A + A^T) / 2 before the Cholesky (as the weight-space backends do).
    """

    def __init__(self, R: Tensor | None, c_y: Tensor, c_g: Tensor | None, rho: Tensor, n: int,
                 terms: list[CovarianceTerm], symmetrize: bool = True) -> None:
        self.R, self.c_y, self.c_g, self.rho, self.n = R, c_y, c_g, rho, int(n)
        self.terms, self.symmetrize = list(terms), symmetrize
        self.names = {NOISE} | {name for t in self.terms for name in t.names} | ({MEAN} if c_g is not None else set())
        r = c_y.shape[-1]
        self.eye = torch.eye(r, dtype=c_y.dtype, device=c_y.device)
        #: numbers in a draw's largest intermediate: 2 r F (2 r^2 without R), or a term's own where larger
        self.elements = max([2 * r * (R.shape[-1] if R is not None else r)]
                            + [int(getattr(t, "elements", 0)) for t in self.terms])

    def evaluate(self, values: dict[str, Tensor], grad: bool = True) -> tuple[Tensor, dict[str, Tensor] | None, Tensor]:
        """nll (*S, 2) (-log p(F_a | values) / n per axis), the gradients of nll.sum(-1) in the values
        (name -> (*S, *shape)) or None, and ok (*S,): False where sigma^2 I + A is not positive definite
        (its nll is then +inf and its gradient meaningless)."""
        noise_v = values[NOISE]
        noise = _noise_per_axis(noise_v)
        parts = [t.forward(values, self.R) for t in self.terms]
        A, fresh = parts[0][0], False  # fresh: A is this call's own tensor (the terms' states may hold theirs)
        for p in parts[1:]:
            if fresh and torch.broadcast_shapes(A.shape, p[0].shape) == A.shape:
                A.add_(p[0])
            else:
                A, fresh = A + p[0], True
        if self.symmetrize:
            A, fresh = 0.5 * (A + A.mT), True
        r = A.shape[-1]
        batch = torch.broadcast_shapes(A.shape[:-2], noise.shape)
        if not fresh or A.shape[:-2] != batch:
            A = A.expand(*batch, r, r).clone()
        A.diagonal(dim1=-2, dim2=-1).add_(noise[..., None])  # sigma^2 I + A in place: no (*S, 2, r, r) noise block
        L, info = torch.linalg.cholesky_ex(A)
        ok = (info == 0).all(-1)
        m = values.get(MEAN) if self.c_g is not None else None
        if m is None:
            c, rho = self.c_y, self.rho[..., 0]
        else:
            c = self.c_y - m[..., None] * self.c_g
            pre = self.rho[..., 0] - 2 * m * self.rho[..., 1] + m.pow(2) * self.rho[..., 2]
            rho = pre.clamp_min(0)
        n = self.n
        z = torch.linalg.solve_triangular(L, c.expand(L.shape[:-1])[..., None], upper=False)
        quad = rho / noise + z.pow(2).sum((-1, -2))
        logdet = (n - r) * torch.log(noise) + 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
        nll = 0.5 * (quad + logdet + n * math.log(2 * math.pi)) / n
        if not bool(ok.all()):
            nll = torch.where(ok[..., None], nll, torch.full_like(nll, math.inf))
        if not grad:
            return nll, None, ok
        alpha = torch.linalg.solve_triangular(L.mT, z, upper=True)  # (*S, 2, r, 1)
        adj = Adjoint(L, alpha, self.R, n, self.eye)
        grads: dict[str, Tensor] = {}
        for t, (_, state) in zip(self.terms, parts):
            for name, g in t.backward(values, adj, state).items():
                grads[name] = grads[name] + g if name in grads else g
        d_noise = ((n - r) / noise - rho / noise.pow(2) + adj.trace_inverse() - alpha.pow(2).sum((-1, -2))) / (2 * n)
        grads[NOISE] = _noise_gradient(d_noise, noise_v)
        if m is not None:
            d_m = -(alpha[..., 0] * self.c_g).sum(-1) / n + (pre >= 0) * (m * self.rho[..., 2] - self.rho[..., 1]) / (
                n * noise)
            grads[MEAN] = d_m
        return nll, grads, ok


# ---- the hyperparameter module: parameters, constraints, priors -------------------------------------
class _Plan:
    """What a step needs of an ``RFTHyperparameters``, found once (walking gpytorch's module tree each
    step costs more than the arithmetic at these sizes): the raw parameters with their constraints and the
    registered priors, the physical ones (``gp.kernels.priors``: a ``NormalPrior`` of log(value) - centre)
    resolved for closed form."""

    def __init__(self, hypers) -> None:
        modules = [m for m in hypers.modules() if hasattr(m, "_priors")]
        self.dicts = [m._parameters for m in modules] + [m._priors for m in modules]
        self.held = [v for d in self.dicts for v in d.values()]  # held: their ids cannot be reused while compared
        self.key = self._key()
        self.entries = list(hypers.named_parameters_and_constraints())
        self.known, self.others = [], []
        for entry in hypers.named_priors():
            _, module, prior, closure, _ = entry
            resolved = _resolve_prior(prior, closure)
            if resolved is None:
                self.others.append(entry)
            else:
                self.known.append(resolved)

    def _key(self) -> tuple:
        """Which parameters and priors are registered (a re-registered prior is a new entry)."""
        return tuple(id(v) for d in self.dicts for v in d.values())

    def valid(self) -> bool:
        return self._key() == self.key

    def flat(self) -> _Flat | None:
        """The one-vector form of a step (``_Flat``), or None where it does not apply; rebuilt when a
        constraint's buffers change."""
        got = self.__dict__.get("_flat", False)
        if got is False or (got is not None and not got.valid()):
            got = self._flat = _Flat.build(self)
        return got


class _Flat:
    """A step's bookkeeping on one vector: the raw hyperparameters concatenated (P,), their values
    softplus(raw) scale + lower in one call, the physical priors' log density and its gradient over the whole
    vector, and the chain rule to the raw parameters in one product. What ``loss_and_grad`` does per parameter
    and per prior (``current_values``, ``prior_terms``, ``value_gradient_to_raw``), in a few operations over the
    whole vector instead of a dozen per parameter and per prior (the fit loop's step, where that bookkeeping cost
    as much as the likelihood's algebra at the DEM's size).
    Built only where every parameter has a softplus ``GreaterThan`` constraint and every registered prior is a
    physical one with at most one per parameter; elsewhere the per-parameter path serves."""

    def __init__(self, entries, slices, scale, lower, centre, inv_var, const, buffers) -> None:
        self.entries, self.slices = entries, slices  # [(name, parameter, shape)], [slice into the vector]
        self.scale, self.lower = scale, lower  # (P,) value = softplus(raw) scale + lower
        self.centre, self.inv_var, self.const = centre, inv_var, const  # (P,) log-normal priors; 0 where none
        self.buffers = buffers  # [(constraint, buffer name, buffer, its version)]: a changed bound or scale rebuilds

    def valid(self) -> bool:
        """False once a bound or scale changed (in place, or replaced: ``model.double()`` makes new buffers and
        keeps the parameters) or a parameter moved to another dtype or device."""
        first = self.entries[0][1]
        return (all(getattr(m, k) is b and b._version == v for m, k, b, v in self.buffers)
                and all(p.dtype == first.dtype and p.device == first.device for _, p, _ in self.entries)
                and self.scale.dtype == first.dtype and self.scale.device == first.device)

    @classmethod
    def build(cls, plan: _Plan) -> _Flat | None:
        if plan.others or not plan.entries:
            return None
        first = plan.entries[0][1]
        entries, slices, scales, lowers, buffers = [], [], [], [], []
        at = 0
        for name, p, c in plan.entries:
            if (c is None or not c.enforced or not isinstance(c, GreaterThan) or c._transform is not _gpytorch_softplus
                    or p.dtype != first.dtype or p.device != first.device):
                return None
            n = p.numel()
            scale = getattr(c, "scale", None)
            try:  # a bound or scale that does not broadcast to its parameter: the per-parameter path decides
                scales.append(torch.broadcast_to((scale if scale is not None else p.new_ones(())).detach().to(p),
                                                 p.shape).reshape(-1))
                lowers.append(torch.broadcast_to(c.lower_bound.detach().to(p), p.shape).reshape(-1))
            except RuntimeError:
                return None
            buffers += [(c, k, getattr(c, k), getattr(c, k)._version) for k in ("scale", "lower_bound")
                        if isinstance(getattr(c, k, None), Tensor)]
            entries.append((name, p, p.shape))
            slices.append(slice(at, at + n))
            at += n
        where = {name: sl for (name, _, _), sl in zip(entries, slices)}
        centre, inv_var = first.new_zeros(at), first.new_zeros(at)
        const, seen = 0.0, set()
        for name, c0, iv, k in plan.known:
            if name in seen or name not in where:
                return None
            seen.add(name)
            sl = where[name]
            n = sl.stop - sl.start
            if c0.numel() not in (1, n):
                return None
            centre[sl] = c0.to(centre).reshape(-1).expand(n)
            inv_var[sl] = iv
            const += k * n
        return cls(entries, slices, torch.cat(scales), torch.cat(lowers), centre, inv_var, const, buffers)

    def values(self) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """(raw (P,), value (P,), name -> value in the parameter's shape)."""
        raw = torch.cat([p.detach().reshape(-1) for _, p, _ in self.entries])
        value = torch.nn.functional.softplus(raw) * self.scale + self.lower
        return raw, value, {name: value[sl].view(shape) for (name, _, shape), sl in zip(self.entries, self.slices)}

    def step(self, raw: Tensor, value: Tensor, grads: dict[str, Tensor], n: int) -> Tensor:
        """The log prior (a 0-dim tensor), and ``.grad`` of each raw parameter that requires one set
        (accumulated) from the likelihood's gradients in the values (``grads``, per sample) and the priors'."""
        dl = value.log() - self.centre
        d = dl * self.inv_var  # -d lp / d log(value)
        lp = -0.5 * (d * dl).sum() + self.const
        g = torch.cat([grads[name].reshape(-1) for name, _, _ in self.entries])
        g_raw = (g + d / (value * n)) * torch.sigmoid(raw) * self.scale
        for (_, p, shape), sl in zip(self.entries, self.slices):
            if p.requires_grad:
                gp = g_raw[sl].view(shape)
                p.grad = gp if p.grad is None else p.grad + gp
        return lp


_PLANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _plan(hypers) -> _Plan:
    plan = _PLANS.get(hypers)
    if plan is None or not plan.valid():
        plan = _PLANS[hypers] = _Plan(hypers)
    return plan


def _resolve_prior(prior, closure):
    """(parameter name, centre + loc, 1 / scale^2, -log scale - log sqrt(2 pi)) of a physical prior, or None
    for any other registered prior."""
    from ..kernels import priors as physical

    if type(prior) is not NormalPrior or getattr(prior, "_transform", None) is not None:
        return None
    if not isinstance(closure, functools.partial) or closure.args or set(closure.keywords) != {"c"}:
        return None
    name = {physical._log_outputscale_ratio: OUTPUTSCALE, physical._log_lengthscale_ratio: LENGTHSCALE,
            physical._log_noise_ratio: NOISE, physical._log_li_ratio: LI_VARIANCE,
            physical._log_generic_ratio: LI_GENERIC}.get(closure.func)
    if name is None or prior.loc.numel() != 1 or prior.scale.numel() != 1:
        return None
    loc, scale = float(prior.loc), float(prior.scale)
    return name, torch.as_tensor(closure.keywords["c"]) + loc, 1 / scale**2, -math.log(scale) - LOG_SQRT_2PI


def current_values(hypers, skip=()) -> dict[str, Tensor]:
    """Each hyperparameter's value (its constraint's transform of the raw parameter), detached: name -> value;
    none for the names in ``skip`` (values the caller has already)."""
    with torch.no_grad():
        return {name: c.transform(p) if c is not None else p.detach() for name, p, c in _plan(hypers).entries
                if name not in skip}


def prior_terms(hypers, values: dict[str, Tensor], grad: bool = True, plan: _Plan | None = None):
    """The registered priors' log density summed (*S,) at ``values`` and its gradient in the values (name ->
    (*S, *shape)), the physical priors in closed form (torch's ``Normal.log_prob`` of log(value) - centre).
    Returns (log prior, gradients, others): ``others`` are the registered priors it does not know (the caller
    evaluates those by autograd, or falls back)."""
    plan = plan or _plan(hypers)
    batch = values[OUTPUTSCALE].shape[:-1]
    total = values[OUTPUTSCALE].new_zeros(batch)
    grads: dict[str, Tensor] = {}
    for name, centre, inv_var, const in plan.known:
        v = values[name]
        if name == NOISE:  # the closure reads m.noise.reshape(-1)
            v = v.reshape(*batch, -1)
        if centre.dtype != v.dtype or centre.device != v.device:
            centre = centre.to(v)
        d = v.log() - centre
        total = total + (d.square().reshape(*batch, -1).sum(-1) * (-0.5 * inv_var) + const * (d.numel() // max(
            batch.numel(), 1)))
        if grad:
            g = (d * (-inv_var) / v).reshape(values[name].shape)
            grads[name] = grads[name] + g if name in grads else g
    return total, grads, plan.others


def value_gradient_to_raw(constraint, raw: Tensor, g: Tensor) -> Tensor:
    """d loss / d raw from d loss / d value, value = constraint.transform(raw): in closed form for the
    softplus ``GreaterThan`` (and ``ScaledGreaterThan``) constraints (softplus' = sigmoid, the identity
    above torch's threshold of 20), else by autograd."""
    if constraint is None or not constraint.enforced:
        return g
    if isinstance(constraint, GreaterThan) and constraint._transform is _gpytorch_softplus:
        d = torch.where(raw > 20, 1.0, torch.sigmoid(raw))
        scale = getattr(constraint, "scale", None)
        return g * d if scale is None else g * d * scale
    with torch.enable_grad():
        r = raw.detach().requires_grad_(True)
        (out,) = torch.autograd.grad(constraint.transform(r), r, grad_outputs=g)
    return out


def loss_and_grad(backend) -> float | None:
    """``backend.loss()`` and its gradient in closed form: sets ``.grad`` of every raw hyperparameter that
    requires one (accumulating, as ``backward`` does) and returns the loss. None where the backend has no
    closed form, where a free parameter is covered by no term, or where the covariance is not positive
    definite: the caller then takes the autograd path (which raises, or adds jitter, as it always did)."""
    cf = closed_form_of(backend)
    if cf is None:
        return None
    plan = _plan(backend.hypers)
    if any(p.requires_grad and name not in cf.names for name, p, _ in plan.entries):
        return None
    flat = plan.flat()
    if flat is not None and not all(name in cf.names for name, _, _ in flat.entries):
        flat = None
    with torch.no_grad():
        if flat is not None:
            raw, value, values = flat.values()
        else:
            values = {name: c.transform(p) if c is not None else p for name, p, c in plan.entries}
        if not backend.in_fit:  # a fit loop adapts the backend itself (``refresh``) every few steps
            backend.prepare(values)
            cf = backend.closed_form()
        nll, grads, ok = cf.evaluate(values, grad=True)
        if not bool(ok.all()):
            return None
        n = max(backend.n_samples, 1)
        if flat is not None:
            return float(nll.sum() - flat.step(raw, value, grads, n) / n)
        lp, g_prior, others = prior_terms(backend.hypers, values, plan=plan)
        loss = nll.sum() - lp / n
        for name, p, c in plan.entries:
            if not p.requires_grad:
                continue
            g = grads[name]
            if name in g_prior:
                g = g - g_prior[name] / n
            g_raw = value_gradient_to_raw(c, p, g)
            p.grad = g_raw if p.grad is None else p.grad + g_raw
    if others:  # priors registered by hand: their gradient by autograd, through the raw parameters
        extra = sum(prior.log_prob(closure(module)).sum() for _, module, prior, closure, _ in others)
        (-extra / n).backward()
        loss = loss - extra.detach() / n
    return float(loss)
