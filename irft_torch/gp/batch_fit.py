"""Fitting several models that share their contacts in one batched Adam loop.

A noise study, seeds, bootstrap resamples of the forces, the same recording with other starting
lengthscales: models that differ only in their forces and hyperparameters. In the "pairs" backend
the data enter the likelihood through R (r x F, fixed by the contacts alone: shared) and c, rho
(per model; see ``backends.weight_space``), so the steps of B models are one step of the same
algebra with 2B map axes instead of 2, and the per-step cost of autograd, the priors and Adam,
which is most of a small fit's time, is paid once instead of B times.

Each model still follows its own fit: the batched loss is the sum of the models' losses, so each
model's gradient is that of its own loss, and Adam is elementwise. The result equals fitting each
model on its own (``InverseRFT.fit``) to rounding; ``tests/gp/test_batch_fit.py`` checks it.
"""

from __future__ import annotations

import contextlib
import functools
import math
import warnings
from collections.abc import Sequence

import torch
from gpytorch.constraints import GreaterThan
from gpytorch.likelihoods import GaussianLikelihood
from gpytorch.module import Module
from linear_operator.utils.errors import NotPSDError
from torch import Tensor

from .backends.pairs import PairsBackend
from .backends.weight_space import WeightSpaceBackend, _DataFactor
from .fit_control import adam, progress_bar
from .kernels.angle import AngleKernel
from .kernels.constraints import ScaledGreaterThan
from .kernels.hyperparameters import RFTHyperparameters
from .kernels.li_basis import LiBasisVariance

__all__ = ["fit_together", "shares_fit"]


class _StackedHyperparameters(RFTHyperparameters):
    """The hyperparameters of B models as one batch of 2B map axes (model b: axes 2b, 2b + 1)."""

    def __init__(self, models: Sequence) -> None:
        Module.__init__(self)
        hs = [m.hypers for m in models]
        self.n_models = B = len(hs)
        self.n_maps = 2 * B
        self._tied = hs[0].tied
        k0 = hs[0].kernel
        os_scale = torch.cat([h.kernel.raw_outputscale_constraint.scale.expand(2) for h in hs])
        ls_lower = float(k0.base_kernel.raw_lengthscale_constraint.lower_bound)
        self.kernel = AngleKernel(torch.Size([2 * B]), lengthscale_constraint=GreaterThan(ls_lower),
                                  outputscale_constraint=ScaledGreaterThan(0.0, os_scale))
        per = 1 if self._tied else 2  # noise entries per model
        cons = [h.likelihood.noise_covar.raw_noise_constraint for h in hs]
        floor = torch.cat([c.lower_bound.expand(per) for c in cons])[:, None]  # per model: data-scaled
        scale = torch.cat([c.scale.reshape(-1).expand(per) for c in cons])[:, None]
        self.likelihood = GaussianLikelihood(batch_shape=torch.Size([per * B]),
                                             noise_constraint=ScaledGreaterThan(floor, scale))
        self.mean = None
        self.li = None  # Li et al.'s term (gp.kernels.li_basis): one variance per map axis, as the outputscale
        if hs[0].li is not None:
            li_scale = torch.cat([h.li.raw_variance_constraint.scale.expand(2) for h in hs])
            self.li = LiBasisVariance(li_scale, n_maps=2 * B, generic=hs[0].li.generic)
        with torch.no_grad():
            if self.li is not None:
                self.li.raw_variance.copy_(torch.cat([h.li.raw_variance for h in hs]))
                if self.li.generic:  # the generic shape's variance (gp.kernels.li_basis), stacked the same way
                    self.li.raw_generic_variance.copy_(torch.cat([h.li.raw_generic_variance for h in hs]))
            self.kernel.raw_outputscale.copy_(torch.cat([h.kernel.raw_outputscale for h in hs]))
            self.kernel.base_kernel.raw_lengthscale.copy_(torch.cat([h.kernel.base_kernel.raw_lengthscale for h in hs]))
            raw = torch.cat([h.likelihood.noise_covar.raw_noise.reshape(-1) for h in hs])
            self.likelihood.noise_covar.raw_noise.copy_(raw.reshape(self.likelihood.noise_covar.raw_noise.shape))
        self._stack_priors(hs)
        self.to(dtype=k0.raw_outputscale.dtype, device=k0.raw_outputscale.device)  # the models' (float32, a GPU)

    @property
    def tied(self) -> bool:
        return self._tied

    @property  # type: ignore[misc]  # read-only here: the models' noises are set on the models
    def noise(self) -> Tensor:
        """(2B,) force noise variances, N^2 (model b: entries 2b, 2b + 1)."""
        n = self.likelihood.noise.reshape(-1)
        return n.repeat_interleave(2) if self._tied else n

    def _stack_priors(self, hs) -> None:
        """Register each prior of the models once, with their centres side by side (the priors of
        ``gp.kernels.priors``: the same density on log(value) minus a per-model centre)."""
        places = {"outputscale_prior": (lambda h: h.kernel, self.kernel),
                  "lengthscale_prior": (lambda h: h.kernel.base_kernel, self.kernel.base_kernel),
                  "noise_prior": (lambda h: h.likelihood.noise_covar, self.likelihood.noise_covar)}
        if self.li is not None:
            places["variance_prior"] = (lambda h: h.li, self.li)
            if self.li.generic:
                places["generic_variance_prior"] = (lambda h: h.li, self.li)
        for name, (owner, target) in places.items():
            entries = [owner(h)._priors.get(name) for h in hs]
            if entries[0] is None:
                continue
            prior, closure, _ = entries[0]
            centres = [e[1].keywords["c"] for e in entries]
            at = {"dtype": hs[0].kernel.raw_outputscale.dtype, "device": hs[0].kernel.raw_outputscale.device}
            c = torch.cat([torch.as_tensor(v).reshape(-1).to(**at) for v in centres]) if torch.is_tensor(centres[0]) \
                else torch.tensor(centres, **at)  # the models' dtype and device (a CPU centre met CUDA values)
            if name == "lengthscale_prior":  # one centre per model for (1, 4) lengthscales of 2 axes
                c = c.repeat_interleave(2)[:, None, None] if c.numel() == len(hs) else c
            target.register_prior(name, prior, functools.partial(closure.func, c=c))


def shares_fit(models: Sequence) -> str | None:
    """Why these models cannot be fitted as one batch (None when they can): the same contacts in
    the "pairs" space (and, with ``method="auto"``, no other space that could become 2x cheaper as the
    lengthscales move, so that each model's own fit would stay there too), no physics mean, no learned
    surface, the same priors (``gp.kernels.priors``' own, or none) and noise tying, one dtype and device."""
    if len(models) < 2:
        return "fewer than two models"
    if len({id(m) for m in models}) < len(models):
        return "the same model twice (a batch fits each once)"
    m0 = models[0]
    for m in models:
        if type(m.backend) is not PairsBackend:
            return f"backend {m.method!r} (only 'pairs' is batched)"
        if m.surface is not None or m.hypers.mean is not None:
            return "a learned surface or a physics mean"
        if (m.hypers.li is None) != (m0.hypers.li is None):
            return "Li et al.'s kernel term in some models and not in others (li_basis)"
        if m.hypers.li is not None and m.hypers.li.generic != m0.hypers.li.generic:
            return "the generic shape's kernel term in some models and not in others (generic_shape)"
        if m.priors != m0.priors or m.hypers.tied != m0.hypers.tied:
            return "different priors or noise tying"
        p0, p = m0.hypers.kernel.raw_outputscale, m.hypers.kernel.raw_outputscale
        if p.dtype != p0.dtype or p.device != p0.device:
            return "different dtypes or devices"
        if not all(q.requires_grad for q in m.hypers.parameters()):
            return "a hyperparameter held fixed (requires_grad=False)"
        known = {"kernel.outputscale_prior", "kernel.base_kernel.lengthscale_prior",
                 "likelihood.noise_covar.noise_prior", "li.variance_prior", "li.generic_variance_prior"}
        for name, _, _, closure, _ in m.hypers.named_priors():  # only gp.kernels.priors' own (a user's is not stacked)
            if name not in known or not (isinstance(closure, functools.partial) and "c" in closure.keywords):
                return f"a prior this batching does not know ({name})"
        for name in ("outputscale_prior", "lengthscale_prior", "noise_prior", "variance_prior",
                     "generic_variance_prior"):
            pa, pb = _prior(m, name), _prior(m0, name)
            if (pa is None) != (pb is None) or (pa is not None and not (
                    torch.equal(pa.loc, pb.loc) and torch.equal(pa.scale, pb.scale))):
                return f"different {name}"
        if _auto_may_switch(m):
            return "method='auto' may move it to another space during the fit (another space could become 2x cheaper)"
        if m.backend.table.shape != m0.backend.table.shape or not torch.equal(m.backend.table, m0.backend.table):
            return "different contacts (angle pairs)"
        if not torch.equal(m.backend._factor().R, m0.backend._factor().R):
            return "different contacts (weights)"
        if m.backend.n_samples != m0.backend.n_samples or m.backend.stats.n != m0.backend.stats.n:
            return "different numbers of force samples (rows out of contact count in the likelihood)"
    return None


def _auto_may_switch(model) -> bool:
    """Whether ``InverseRFT.fit`` could move this model out of the pairs space mid-fit (``method="auto"``,
    ``select.pairs_may_move``): if not, the batch follows each model's own fit exactly."""
    return model.auto and model.fit_control.may_leave_pairs(model)


def _prior(model, name):
    h = model.hypers
    owner = {"outputscale_prior": h.kernel, "lengthscale_prior": h.kernel.base_kernel,
             "noise_prior": h.likelihood.noise_covar, "variance_prior": h.li, "generic_variance_prior": h.li}[name]
    if owner is None:  # no Li et al.'s term
        return None
    e = owner._priors.get(name)
    return None if e is None else e[0]


def _stacked_backend(models, hypers: _StackedHyperparameters) -> PairsBackend:
    """A pairs backend over the models' shared angle pairs holding every model's data factor."""
    proto = models[0].backend
    b = PairsBackend.__new__(PairsBackend)
    WeightSpaceBackend.__init__(b, hypers, models[0].train_contacts[:0], proto.stats.b.new_zeros(0, 2))
    b.table = proto.table
    b.stats = proto.stats
    b.n_samples = proto.n_samples
    fs = [m.backend._factor() for m in models]
    b._data_factor = _DataFactor(*(torch.cat([getattr(f, k) for f in fs]) for k in ("R", "c_y", "c_g", "rho", "rank")))
    return b


@contextlib.contextmanager
def _default_dtype(dtype: torch.dtype):
    """torch's default dtype set to the models' while the stacked modules are built (gpytorch's
    constraints and priors make their buffers in the default dtype)."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(before)


def fit_together(models: Sequence, n_iter: int = 300, lr: float = 0.05, progress: bool = False) -> list[list[float]]:
    """Fit B models (``InverseRFT``) that share their contacts at once: Adam on the sum of their
    losses, each model's hyperparameters its own (a noise study, seeds, bootstrap resamples of the
    forces). Returns each model's loss per step (in the order given), as ``InverseRFT.fit`` does, and
    leaves each model fitted, as its own fit would. The models are split into groups that can share a
    batch (``shares_fit`` says why two cannot: another backend than "pairs", a physics mean, a learned
    surface, other contacts or priors, ``method="auto"`` where another space could become cheaper
    during the fit); a model alone in its group is fitted with ``InverseRFT.fit``. When one model's
    covariance breaks down during a batch, every model of that batch goes back to its start and is
    fitted on its own, so that the one that breaks raises its own error."""
    models = list(models)
    if int(n_iter) != n_iter or n_iter < 0 or not math.isfinite(lr) or lr <= 0:
        raise ValueError(f"need an integer n_iter >= 0 and lr > 0, got n_iter={n_iter}, lr={lr}")
    histories: list = [None] * len(models)
    for group in _batches(models):
        batch = [models[i] for i in group]
        done = _fit_batch(batch, n_iter, lr, progress) if len(batch) > 1 else \
            [batch[0].fit(n_iter=n_iter, lr=lr, progress=progress)]
        for i, h in zip(group, done):
            histories[i] = h
    return histories


def _batches(models: list) -> list[list[int]]:
    """The models' indices in groups that can share a batch, in order of first appearance: each group
    those that ``shares_fit`` pairs with its first model (its checks compare with the first model, so
    the group shares them all), a model given twice in separate groups (fitted twice, in order)."""
    left = list(range(len(models)))
    groups = []
    while left:
        first, group, ids = left[0], [left[0]], {id(models[left[0]])}
        for j in left[1:]:
            if id(models[j]) not in ids and shares_fit([models[first], models[j]]) is None:
                group.append(j)
                ids.add(id(models[j]))
        groups.append(group)
        left = [j for j in left if j not in group]
    return groups


def _fit_batch(models: list, n_iter: int, lr: float, progress: bool) -> list[list[float]]:
    """``fit_together`` of models that ``shares_fit`` accepts: one batched Adam loop."""
    B = len(models)
    start = [[p.detach().clone() for p in m.hypers.parameters()] for m in models]
    with _default_dtype(models[0].hypers.kernel.raw_outputscale.dtype):  # no rounding through float32
        hypers = _StackedHyperparameters(models)
    backend = _stacked_backend(models, hypers)
    T = max(backend.n_samples, 1)
    opt = adam(list(hypers.parameters()), lr)
    histories: list[list[float]] = [[] for _ in range(B)]
    # each model's best iterate (loss, its raw hyperparameters, step), kept as its own fit keeps it (fit_control)
    best: list[tuple[float, dict | None, int]] = [(math.inf, None, -1)] * B
    failed = False
    bar = progress_bar(int(n_iter), f"I-RFT fit x {B} (pairs)", progress)
    try:
        for step in bar:
            opt.zero_grad(set_to_none=True)
            per_model = backend.negative_log_likelihood().reshape(B, 2).sum(-1)
            for _, module, prior, closure, _ in hypers.named_priors():
                per_model = per_model - prior.log_prob(closure(module)).reshape(B, -1).sum(-1) / T
            values = per_model.tolist()
            for i, v in enumerate(values):
                if v < best[i][0]:
                    best[i] = (v, _raw_slices(hypers, i), step)
            per_model.sum().backward()
            opt.step()
            for h, v in zip(histories, values):
                h.append(v)
    except KeyboardInterrupt:
        warnings.warn(f"fit interrupted after {len(histories[0])} steps; the models keep those steps", stacklevel=2)
    except (NotPSDError, torch.linalg.LinAlgError):
        failed = True  # one model's covariance broke down: back to the start, and each fit on its own below
    finally:
        bar.close()
        with torch.no_grad():
            for i, m in enumerate(models):
                if failed:
                    for p, p0 in zip(m.hypers.parameters(), start[i]):
                        p.copy_(p0)
                    continue
                h = m.hypers
                h.kernel.raw_outputscale.copy_(hypers.kernel.raw_outputscale[2 * i:2 * i + 2])
                h.kernel.base_kernel.raw_lengthscale.copy_(hypers.kernel.base_kernel.raw_lengthscale[2 * i:2 * i + 2])
                raw, k = hypers.likelihood.noise_covar.raw_noise, 1 if hypers.tied else 2
                own = h.likelihood.noise_covar.raw_noise
                own.copy_(raw[k * i:k * i + k].reshape(own.shape))
                if h.li is not None:
                    h.li.raw_variance.copy_(hypers.li.raw_variance[2 * i:2 * i + 2])
                    if h.li.generic:
                        h.li.raw_generic_variance.copy_(hypers.li.raw_generic_variance[2 * i:2 * i + 2])
    if failed:  # each model's own fit: the one that breaks down raises its own NotPSDError (naming its
        # hyperparameters), the ones before it end fitted, as in a loop of InverseRFT.fit
        return [m.fit(n_iter=n_iter, lr=lr, progress=progress) for m in models]
    for i, (m, h) in enumerate(zip(models, histories)):
        value, raw, step = best[i]
        if raw is not None:  # the best iterate restored where the loss ended above it, as InverseRFT.fit does
            own = m.hypers.likelihood.noise_covar.raw_noise
            raw["likelihood.noise_covar.raw_noise"] = raw["likelihood.noise_covar.raw_noise"].reshape(own.shape)
            m.fit_control.keep_best(m, (value, {**m.fit_control.snapshot(m), **raw}, step), h, lr, stacklevel=3)
        m.loss_history.extend(h)
        m.eval()
        m._last_fit = (int(n_iter), float(lr))
        m._finish_fit()  # the hyperparameter posterior, as the model's own fit ends
    return histories


def _raw_slices(hypers: _StackedHyperparameters, i: int) -> dict[str, Tensor]:
    """Model i's raw hyperparameters in the stacked ones, keyed as its own ``hypers.state_dict()``: a copy."""
    k = 1 if hypers.tied else 2
    out = {"kernel.raw_outputscale": hypers.kernel.raw_outputscale[2 * i:2 * i + 2].detach().clone(),
           "kernel.base_kernel.raw_lengthscale":
               hypers.kernel.base_kernel.raw_lengthscale[2 * i:2 * i + 2].detach().clone(),
           "likelihood.noise_covar.raw_noise":
               hypers.likelihood.noise_covar.raw_noise[k * i:k * i + k].detach().clone()}
    if hypers.li is not None:
        out["li.raw_variance"] = hypers.li.raw_variance[2 * i:2 * i + 2].detach().clone()
        if hypers.li.generic:
            out["li.raw_generic_variance"] = hypers.li.raw_generic_variance[2 * i:2 * i + 2].detach().clone()
    return out
