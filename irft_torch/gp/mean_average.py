r"""Averaging over the prior mean: the zero mean and the physics mean, weighed per map by their evidence.

Li et al. (2013) found that granular media share one generic stress map up to a scale; many do, some do
not. Which prior mean a map deserves is a question the forces answer, through each model's marginal
likelihood (its evidence, the hyperparameters integrated out). With M_0 the zero-mean model and M_1 the
physics-mean model (the generic shape times a learned scale per axis, a residual GP), each fitted with
its own hyperparameters, the posterior of map c is the Bayesian model average

    p(alpha_c | F) = sum_m pi_mc p(alpha_c | F, M_m),    pi_mc = p(F_c | M_m) / sum_m' p(F_c | M_m'),

with equal prior odds; the two maps are weighed separately (each its own hyperparameters and force axis,
so the evidence factorises over them: alpha_x may be generic-shaped while alpha_z is not). Each model's
posterior is itself a mixture over its hyperparameter draws (``hyper_posterior``), or its plug-in.
``p(F_c | M_m)`` is the Laplace approximation at the mode of the model's hyperparameter posterior
(``hyper_posterior.log_evidence``), which needs proper priors (``MapPrior(hyperpriors="physical")``, the default).

Why: on the calibration harness (docs/calibration.md) a zero-mean GP seen through a narrow slice of the
square (a rotating leg, a short stroke) extrapolates a generic-shaped medium with intervals that hold the
truth on 30-80 % of the square, and a physics mean does the same to a medium that is not generic-shaped;
the average takes whichever the forces support, and both where they cannot tell.

``InverseRFT(contacts, forces, prior=MapPrior(mean="average"))`` is the zero-mean model (``model.hypers``,
``model.backend``: what ``fit`` trains first) with a physics-mean companion fitted after it on the same data
(``model.companion``); ``model.mean_average`` holds the evidence and the weights. Every prediction is the
mixture over both models' draws with weights pi_mc w_ms per map (``gp.hyper.mixture``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from .backends import RFTBackend
from .hyper.posterior import _polish, hyper_spec, log_evidence
from .options import grouped

__all__ = ["MeanAverage", "MEANS", "new_companion", "fit_companion", "weigh_means", "averaged_backends",
           "stream_into_average"]

MEANS = ("zero", "physics")  # the models averaged, in this order


@dataclass
class MeanAverage:
    """The two prior means' evidence and weights, per map.

    Attributes:
        log_evidence: (2, 2) log p(F_c | M_m), rows the models (zero, physics), columns the maps (x, z).
        weights: (2, 2) pi_mc, each column summing to 1.
    """

    log_evidence: Tensor
    weights: Tensor

    @classmethod
    def from_evidence(cls, log_evidence: Tensor) -> MeanAverage:
        le = torch.as_tensor(log_evidence, dtype=torch.float64).reshape(2, 2)
        return cls(le, torch.softmax(le, 0))

    def summary(self) -> str:
        lines = ["prior mean average (weights per map; log evidence in nats):"]
        for c, name in enumerate(("alpha_x", "alpha_z")):
            lines.append(f"  {name}: zero {self.weights[0, c]:.3f} ({self.log_evidence[0, c]:.2f}), "
                         f"physics {self.weights[1, c]:.3f} ({self.log_evidence[1, c]:.2f})")
        return "\n".join(lines)

    def state(self) -> dict:
        return {"log_evidence": self.log_evidence.detach().cpu()}

    @classmethod
    def from_state(cls, d: dict) -> MeanAverage:
        return cls.from_evidence(d["log_evidence"])


def _polish_to_mode(backend: RFTBackend, max_iter: int = 100) -> None:
    """Move the backend's hyperparameters to the mode of their posterior (where the Laplace evidence is
    taken): what ``laplace`` does first; a plug-in fit (Adam's last iterate) is near it, not at it."""
    spec = hyper_spec(backend.hypers)
    was = backend.training
    backend.train()
    try:
        mode, _, _ = _polish(backend, spec, spec.theta(backend.hypers), max_iter)
        spec.load(backend.hypers, mode)
    finally:
        backend.train(was)


def new_companion(model, method: str | None = None):
    """The physics-mean model on ``model``'s data, with its options (unfitted); ``method``: its backend (default:
    the model's ``method`` argument)."""
    contacts, forces = model._measured()
    opts = model._options()
    opts["prior_mean"] = "physics"
    opts.update(dtype=model.dtype, method=method or model._method_arg)
    return type(model)(contacts, forces, noise_scale=model.noise_scale, **grouped(opts))


def fit_companion(model, n_iter: int, lr: float, progress: bool) -> None:
    """Fit the physics-mean companion as ``model`` was fitted (same steps and rate), on its current data (a new
    companion if the data grew since it was built)."""
    t0 = time.perf_counter()
    if model.companion is None or len(model.companion.train_forces) != len(model.train_forces):
        model._companion[:] = [new_companion(model)]
    model.companion.fit(n_iter, lr, progress=progress)
    model.companion_fit_seconds = time.perf_counter() - t0  # what the average adds to a fit (benchmarks)


def weigh_means(model) -> None:
    """``model.mean_average``: the evidence of the model and its companion per map (each at the mode of its
    hyperparameter posterior) and the weights; None where the model does not average its prior mean. A model
    without a Laplace posterior is polished to its mode first (the plug-in then predicts there)."""
    if not model.averages_means:
        model.mean_average = None
        return
    evidence = []
    for m in (model, model.companion):
        hp = m.hyper_posterior
        if hp is None or hp.method != "laplace":  # laplace leaves them at the mode; a plug-in or NUTS does not
            _polish_to_mode(m.backend)
            if hp is None:
                m._set_hyper_posterior(None)  # the plug-in at the polished hyperparameters
        hessian = hp.extra.get("hessian") if hp is not None and hp.method == "laplace" else None
        m.train()
        try:
            evidence.append(log_evidence(m.backend, hessian).detach().double().cpu())
        finally:
            m.eval()
    model.mean_average = MeanAverage.from_evidence(torch.stack(evidence))


def averaged_backends(model) -> tuple[list[RFTBackend], Tensor | None]:
    """The backends of both models' draws and their weights (S, 2): pi_mc times the draw's weight in its own
    model."""
    own, w_own = model._own_weighted_backends()
    other, w_other = model.companion._own_weighted_backends()
    pi = model.mean_average.weights.to(model._device, model.dtype)
    parts = []
    for w, n, m in ((w_own, len(own), 0), (w_other, len(other), 1)):
        w = torch.ones(1, dtype=model.dtype, device=model._device) if w is None else w
        parts.append(w[:n, None] * pi[m][None, :])
    return own + other, torch.cat(parts)


def _axis_log_likelihoods(model) -> Tensor:
    """(S, 2) log p(F_c | theta_s) per map of the model's own draws (or its plug-in)."""
    backends, _ = model._own_weighted_backends()
    with torch.no_grad():
        return torch.stack([-b.negative_log_likelihood().detach() * b.n_samples for b in backends])


def _own_draw_weights(model) -> Tensor:
    _, w = model._own_weighted_backends()
    return torch.ones(1, dtype=model.dtype, device=model._device) if w is None else w


def stream_into_average(model, contacts, forces, noise_scale, add_own) -> None:
    """``add_data`` of a model that averages its prior mean: stream into both models, and move each model's weight
    per map by the new samples' predictive likelihood under it, log pi_mc += log sum_s w_ms p(F_new,c | F_old,c,
    theta_s): the weights a fit on all the data would give these draws (the models' hyperparameters stay).
    ``add_own``: the model's own ``add_data``."""
    before = [(_axis_log_likelihoods(m), _own_draw_weights(m)) for m in (model, model.companion)]
    add_own()
    model.companion.add_data(contacts, forces, noise_scale)
    gains = []
    for m, (ll0, w) in zip((model, model.companion), before):
        ll1 = _axis_log_likelihoods(m)
        gains.append(torch.logsumexp(w.to(ll1).log()[:, None] + ll1 - ll0.to(ll1), 0))
    le = model.mean_average.log_evidence + torch.stack(gains).detach().double().cpu()
    model.mean_average = MeanAverage.from_evidence(le)


def check_average_options(priors, surface: bool, tied_noise: bool) -> None:
    """``MapPrior(mean="average")`` needs proper priors (evidence) and no learned surface."""
    if priors != "physical":
        raise ValueError("MapPrior(mean='average') weighs the two prior means by their evidence, which needs the "
                         "physical hyperparameter priors (MapPrior(hyperpriors='physical'))")
    if surface:
        raise NotImplementedError("MapPrior(mean='average') with a learned surface offset is not supported; use "
                                  "mean='zero' or 'physics' with surface=True")
    _ = math.inf if tied_noise else 0  # tied noise works: the evidence is then joint (log_evidence)
