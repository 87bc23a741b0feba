"""The front doors' predictions as mixtures over hyperparameter draws: a model (``InverseRFT``, planar or
3-D) fits the posterior over its hyperparameters (``gp.hyper.posterior``: Laplace with importance
reweighting, or NUTS) and keeps one backend per draw; every prediction averages over them with the draws'
weights (``gp.hyper.mixture``; a 3-D sample's 3 x 3 force covariance by the law of total covariance,
``mixture_covariance``). One mixin for both models (like botorch's ``FantasizeMixin``): it uses the model's
``hypers``, ``backend``, training data and options, and works on any backend with ``negative_log_likelihood()``,
``n_samples``, ``log_prior()``, ``with_hypers`` and a hyperparameter module with gpytorch constraints."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from ..backends import make_backend
from ..kernels.hyperparameters import MapHyperparameters
from .guard import HyperPosteriorWarning, said_once
from .nuts import nuts
from .posterior import HYPER_POSTERIORS, HyperPosterior, draw_hypers, hyper_spec, laplace

__all__ = ["HyperMixtureMixin", "backends_at_draws", "posterior_over_hypers"]

# what a hyperparameter posterior without priors warns (measured: experiments/validation/wheel_validation.py
# --study planar --hyper-posterior laplace, the plain-likelihood row, 2026-11-27)
IMPROPER = ("MapPrior(hyperpriors=None): under a flat prior on log(hyperparameters) the posterior is improper along "
            "any hyperparameter the forces do not bound; its draws there are as wide as the Laplace guard allows, and "
            "the mixture can predict worse than the plug-in (the planar wheels' smooth F_z at held-out slips: 3.96 N "
            "against 1.66 N). hyperpriors='physical' gives a proper posterior")


def backends_at_draws(hypers: nn.Module, hp: HyperPosterior, make: Callable, device, dtype) -> list:
    """One backend per draw of ``hp`` (``make(draw hyperparameters)``), in eval mode: what a model with a
    hyperparameter posterior predicts with, planar or 3-D. Refuses a posterior over other coordinates."""
    spec = hyper_spec(hypers)
    if list(hp.labels) != spec.labels:
        raise ValueError(f"hyperparameter posterior over {hp.labels}, this model has {spec.labels}")
    out = [make(draw_hypers(hypers, spec, th.to(device, dtype))) for th in hp.theta]
    for b in out:
        b.eval()
    return out


def posterior_over_hypers(backend, method: str, n_proposals: int, n_draws: int | None, generator,
                          **options) -> HyperPosterior:
    """The hyperparameter posterior of ``backend`` by ``method``: "laplace" (``gp.hyper.posterior.laplace``) or
    "nuts" (``gp.hyper.nuts.nuts``, ``n_draws`` None: 16); planar or 3-D."""
    if method == "laplace":
        return laplace(backend, n_proposals=n_proposals, n_draws=n_draws, generator=generator, **options)
    return nuts(backend, n_draws=16 if n_draws is None else n_draws, **options)


class HyperMixtureMixin(nn.Module):
    """``fit_hyper_posterior`` and the backends predictions average over (``_weighted_backends``)."""

    hyper_posterior: HyperPosterior | None  # the draws and weights (None: the plug-in)
    _draw_backends: list | None  # one backend per draw

    if TYPE_CHECKING:  # what the front doors provide (gp.model: planar; gp.inverse3d.model: 3-D, its own types)
        hypers: Any  # RFTHyperparameters or RFT3DHyperparameters (gp.kernels.hyperparameters.MapHyperparameters)
        backend: Any  # an RFTBackend or a Backend3D
        _device: torch.device
        dtype: torch.dtype
        hyper_method: str

    def fit_hyper_posterior(self, method: str | None = None, n_proposals: int = 128, n_draws: int | None = 16,
                            generator: torch.Generator | None = None, **options) -> HyperPosterior | None:
        """Fit the posterior over the hyperparameters at the current (fitted) ones; ``fit`` calls it when the
        model was built with ``hyper_posterior`` "laplace" or "nuts". Predictions are then mixtures over its
        draws.

        Args:
            method: "laplace", "nuts" or "map" (drop the draws: plug-in predictions); default: the model's.
            n_proposals: Laplace: importance-sampling proposals (one marginal likelihood each), then half as many
                again moved to where the first weigh most (``gp.hyper.importance.importance_sample``).
            n_draws: at most this many draws kept for prediction (each is one backend: predictions cost as many
                times a plug-in's); Laplace keeps P + 1 points with the posterior's mean and covariance over its P
                hyperparameters (2 P where ``n_draws`` allows; a resample where it is below P + 1); None keeps
                every weighted proposal.
            generator: a ``torch.Generator`` for the draws (None: a fixed seed, so that a refit predicts the same).
            options: passed to ``gp.hyper.posterior.laplace`` (``free``, ``max_iter``, ``df``, ``inflate``,
                ``qmc``, ``adapt``, ``smooth``, ``points``) or ``gp.hyper.nuts.nuts`` (``free``, ``n_samples``,
                ``warmup``, ``num_chains``, ``seed``, ``metric``, ``adapt_mass``, ``processes``). ``free`` defaults
                to every label but those no likelihood sees (``hypers.fixed_labels()``: a 3-D model's constant
                alpha_y's lengthscales).
        Returns:
            the ``HyperPosterior`` (also ``model.hyper_posterior``; labels such as ``lengthscale_x[sin2b]``,
            ``outputscale_z``, ``noise_x``), None for "map". With ``MapPrior(mean="average")`` the physics-mean
            companion gets the same and the weights are taken again. A planar model's draws whose kernel is
            truncated are counted in ``hyper_posterior.extra["truncated"]`` (``diagnostics()``), not warned one by
            one (a 3-D model's: ``diagnostics()["kernel"]["draws_truncated"]``).
        """
        method = self.hyper_method if method is None else method
        if method not in HYPER_POSTERIORS:
            raise ValueError(f"method must be one of {HYPER_POSTERIORS}, got {method!r}")
        if getattr(self, "surface", None) is not None and method != "map":
            raise NotImplementedError("a hyperparameter posterior with a learned surface offset is not supported")
        if method == "map":
            self._set_hyper_posterior(None)
        else:
            if getattr(self, "priors", "physical") is None:
                warnings.warn(IMPROPER, HyperPosteriorWarning, stacklevel=2)
            fixed = self.hypers.fixed_labels()
            if options.get("free") is None and fixed:
                options["free"] = [lab for lab in hyper_spec(self.hypers).labels if lab not in fixed]
            self.train()
            truncated: list[str] = []
            with said_once(truncated):
                try:
                    hp = posterior_over_hypers(self.backend, method, n_proposals, n_draws, generator, **options)
                finally:
                    self.eval()
                self._at_mode()
                self._set_hyper_posterior(hp)
            self.backend.forget_draws()  # the draws' own backends are built: what their batch kept can go
            if truncated and hp is not None:  # reported by diagnostics(): the draws' share is small, nothing to do
                hp.extra["truncated"] = f"{len(truncated)} of the draws' kernels are truncated ({truncated[0]})"
        companion = getattr(self, "companion", None)
        if companion is not None and getattr(self, "mean_average", None) is not None:  # both means, weighed again
            from ..mean_average import weigh_means

            companion.fit_hyper_posterior(method, n_proposals, n_draws, generator, **options)
            weigh_means(self)
        return self.hyper_posterior

    def _at_mode(self) -> None:
        """Called where the hyperparameter posterior leaves the hyperparameters (at the mode), before the draws'
        backends are built from ``backend``: nothing here (a 3-D spectral backend refreshes its basis)."""

    def _set_hyper_posterior(self, hp: HyperPosterior | None) -> None:
        """Keep ``hp`` and build one backend per draw (``_backend_at``: sharing what does not depend on them)."""
        self.hyper_posterior = hp
        self._draw_backends = None if hp is None else \
            backends_at_draws(self.hypers, hp, self._backend_at, self._device, self.dtype)

    def _backend_at(self, hypers: MapHyperparameters):
        """A backend like ``self.backend`` at other hyperparameters, sharing what does not depend on them:
        the pairs backend's statistics and data factor; the spectral backend's statistics wherever they
        cover the draw's basis (a draw with shorter lengthscales needs a larger basis: one pass)."""
        own = self.backend
        shared = own.with_hypers(hypers)
        if shared is not None:
            return shared
        model: Any = self  # a planar model (a 3-D backend always shares): its data, backend options, statistics
        stats = model._statistics if model._statistics is not None else getattr(own, "stats", None)
        return make_backend(model.method, hypers, model.train_contacts, model.train_forces, solver=model.solver,
                            tol=model.tol, statistics=stats if model.method == "spectral" else None)

    def _weighted_backends(self) -> tuple[list, Tensor | None]:
        """The backends predictions average over and their weights: None (the one plug-in backend), (S,)
        (hyperparameter draws) or (S, 2) per map (prior means averaged, ``gp.mean_average``)."""
        if getattr(self, "mean_average", None) is not None:
            from ..mean_average import averaged_backends

            return averaged_backends(self)
        return self._own_weighted_backends()

    def _own_weighted_backends(self) -> tuple[list, Tensor | None]:
        """This model's own backends (its draws, or the plug-in) and their weights (S,) or None."""
        if self._draw_backends is None:
            return [self.backend], None
        return self._draw_backends, self.hyper_posterior.weights.to(self._device, self.dtype)
