"""Leave-one-group-out predictions of a fitted model's own training forces, without refitting.

Each group of training samples (a run, a trial, one tilt of the plate, one commanded slip) is predicted
from the other groups, with the hyperparameters the model learned on all of them (Rasmussen & Williams
2006, section 5.4.2, with groups in place of single samples: the samples of one run share its errors,
so leaving out one sample at a time would flatter the model). What it is for: choosing between fitted
models (a prior mean, a contact model, hyperparameter priors) on the training data alone, where the
marginal likelihood is known to mislead when every candidate is misspecified.

    cv = model.cross_validate(groups)        # groups: (T,) label per training sample
    cv.rmse()                                # (2,) N, per axis (x, z)
    model.cross_validate(groups, refit=True, n_iter=300, lr=0.05)   # refitted without each group

Cost: one backend per group (``make_backend`` on the other groups' samples, same method), then one
posterior per held-out group.

The hyperparameters were fitted with every group, the held-out one included, so the estimate is
optimistic, and more so for a model whose hyperparameters are free to follow the data (the plain
likelihood, ``MapPrior(hyperpriors=None)``) than for one held by priors: when the choice between such models is
close, use ``refit=True`` (a model fitted without each group, G fits; docs/experiments.md shows both
on measured data).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .backends import make_backend
from .backends.base import touching
from .hyper.mixture import mixture_moments
from .options import grouped

__all__ = ["GroupPredictions", "cross_validate"]


@dataclass
class GroupPredictions:
    """Every training sample predicted from the groups it does not belong to.

    Attributes:
        mean: (T, 2) predicted (F_x, F_z) in N, as measured (``noise_scale`` undone).
        variance: (T, 2) its variance in N^2 (the maps' posterior; plus the sample's own noise where
            the predictions were made with ``include_noise``).
        forces: (T, 2) the measured training forces in N.
        groups: (T,) int64 index of each sample's group into ``labels``.
        labels: the distinct group labels, in the order of their index.
        noise: (T, 2) each sample's own noise variance in N^2 (the learned noise x its ``noise_scale``^2).
        include_noise: whether ``variance`` already holds ``noise``.
    """

    mean: Tensor
    variance: Tensor
    forces: Tensor
    groups: Tensor
    labels: list
    noise: Tensor
    include_noise: bool

    @property
    def residual(self) -> Tensor:
        """(T, 2) predicted minus measured, N."""
        return self.mean - self.forces

    def rmse(self) -> Tensor:
        """(2,) root mean square of the held-out residuals over all samples, N, per axis."""
        return self.residual.pow(2).mean(0).sqrt()

    def coverage(self, level: float = 0.95) -> Tensor:
        """(2,) share of the measured held-out forces inside the central ``level`` interval of their prediction,
        per axis: mean +- z sqrt(variance + noise) (a measurement is checked, so its noise counts whether or not
        ``variance`` holds it; a mixture's prediction by its first two moments). Calibrated intervals give about
        ``level``; well below it, the intervals are too narrow for these data (docs/calibration.md)."""
        if not 0 < level < 1:
            raise ValueError(f"level must be in (0, 1), got {level}")
        v = self.variance if self.include_noise else self.variance + self.noise
        z = math.sqrt(2) * torch.special.erfinv(torch.tensor(level, dtype=torch.float64)).item()
        return (self.residual.abs() <= z * v.clamp_min(0).sqrt()).to(self.mean.dtype).mean(0)

    def log_predictive_density(self) -> Tensor:
        """(2,) mean over samples of the log density of each measured force under its held-out
        prediction, per axis: log N(F | mean, variance + noise), noise included whether or not
        ``variance`` holds it (a measurement is scored, not the noise-free force). Marginal per sample."""
        v = self.variance if self.include_noise else self.variance + self.noise
        v = v.clamp_min(torch.finfo(v.dtype).tiny)
        return (-0.5 * (self.residual.pow(2) / v + v.log() + math.log(2 * math.pi))).mean(0)


def _group_index(groups, T: int, device) -> tuple[Tensor, list]:
    if isinstance(groups, Tensor):
        g = groups.detach().cpu().numpy()
    else:
        g = np.asarray(groups)
    if g.shape != (T,):
        raise ValueError(f"groups must have one label per training sample, shape ({T},), got {g.shape}")
    if g.dtype.kind == "f" and not np.isfinite(g).all():
        raise ValueError("groups has NaN or inf labels")
    labels, index = np.unique(g, return_inverse=True)
    if len(labels) < 2:
        raise ValueError(f"groups needs at least 2 distinct labels to leave one out, got {len(labels)}")
    return torch.as_tensor(index.reshape(-1), dtype=torch.long, device=device), labels.tolist()


def cross_validate(model, groups, include_noise: bool = False, refit: bool = False, n_iter: int = 300,
                   lr: float = 0.05) -> GroupPredictions:
    """Leave-one-group-out predictions of ``model``'s training forces at its current hyperparameters.

    Args:
        model: a (fitted) ``InverseRFT``; nothing in it changes.
        groups: (T,) one label per training sample (any sortable values: run numbers, tilts in rad), in
            the order of the training data (``model.train_forces``; after ``add_data``, the parts in order).
        include_noise: add each held-out sample's own noise variance (predict a measurement).
        refit: instead of the model's hyperparameters, fit a new model on the other groups for each group
            (the model's own settings: prior mean, priors, method, noise scales, dtype; ``n_iter`` Adam
            steps at rate ``lr``, give the ones the model was fitted with): the unbiased estimate, at G
            fits' cost. Not for a model that learns the surface (NotImplementedError).

    Returns:
        GroupPredictions, in measured units (N, N^2).
    """
    if refit:
        return _refit(model, groups, include_noise, n_iter, lr)
    c, f, s = model._join()
    if model.surface is not None:
        c = model.train_contacts  # at the learned offset
    index, labels = _group_index(groups, len(f), f.device)
    rows = touching(c)
    backends, weights = model._weighted_backends()
    parts = [_held_out(model, b.hypers, c, f, index, len(labels), rows) for b in backends]
    if weights is None:
        mean, var = parts[0]
        noise = model.hypers.noise.detach()
    else:  # the mixture over hyperparameter draws: mean, total variance, and the draws' mean noise
        mean, var = mixture_moments(torch.stack([p[0] for p in parts]), torch.stack([p[1] for p in parts]), weights)
        noise = sum(w * b.hypers.noise.detach() for b, w in zip(backends, weights))
    noise = noise * s.pow(2)  # (T, 2) N^2, measured units
    var = var * s.pow(2)
    return GroupPredictions(mean * s, var + noise if include_noise else var, f * s, index, labels, noise,
                            include_noise)


def _held_out(model, hypers, c, f, index, n_groups: int, rows) -> tuple[Tensor, Tensor]:
    """Mean and variance (T, 2) of each group's forces (whitened) from the other groups at ``hypers``."""
    mean, var = torch.zeros_like(f), torch.zeros_like(f)
    with torch.no_grad():
        for g in range(n_groups):
            held = index == g
            keep = ~held
            backend = make_backend(model.method, hypers, c[keep], f[keep], solver=model.solver, tol=model.tol)
            if type(backend) is not type(model.backend):
                raise TypeError(f"cross_validate rebuilds the backend by its name ({model.method!r}); the model's "
                                f"{type(model.backend).__name__} is not that class and would be replaced")
            ask = held & rows  # samples with no segment in contact have force exactly 0, variance 0
            if ask.any():
                post = backend.posterior(c[ask], variance=True)
                mean[ask], var[ask] = post.mean.T, post.variance.T
    return mean, var


def _refit(model, groups, include_noise: bool, n_iter: int, lr: float) -> GroupPredictions:
    """``cross_validate(refit=True)``: one model per group, built and fitted like ``model`` on the others."""
    if model.surface is not None:
        raise NotImplementedError("cross_validate(refit=True) with a learned surface: the held-out group's offset "
                                  "is not learned by a model that never sees it; use refit=False")
    c, f = model._measured()
    s = model.noise_scale
    index, labels = _group_index(groups, len(f), f.device)
    mean, var, noise = torch.zeros_like(f), torch.zeros_like(f), torch.zeros_like(f)
    for g in range(len(labels)):
        held = index == g
        keep = ~held
        options = grouped({**model._options(), "method": model._method_arg})
        m = type(model)(c[keep], f[keep], noise_scale=s[keep], **options)
        m.fit(n_iter=n_iter, lr=lr, progress=False)
        with torch.no_grad():
            post = m.predict_forces(c[held])
            mean[held], var[held] = post.mean, post.variance
            noise[held] = m.hypers.noise.detach() * s[held].pow(2)
    return GroupPredictions(mean, var + noise if include_noise else var, f, index, labels, noise, include_noise)
