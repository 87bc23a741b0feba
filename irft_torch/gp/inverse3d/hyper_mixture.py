r"""The 3-D model's predictions as mixtures over hyperparameter draws (``hyper_posterior="laplace"`` or "nuts").

The planar machinery (``gp.hyper.posterior``: ``laplace``, ``nuts``, ``log_posterior``) works on any backend with
``negative_log_likelihood()``, ``n_samples``, ``log_prior()`` and a hyperparameter module with gpytorch
constraints; the 3-D backends and ``RFT3DHyperparameters`` have them, so it is used as it is. Here: the draws'
backends (``Backend3D.with_hypers``: data and hyperparameter-free factors shared) and the mixture of each
sample's 3 x 3 force covariance over the draws (weights w_s, means mu_s, covariances C_s):

    mu = sum_s w_s mu_s,      C = sum_s w_s (C_s + (mu_s - mu)(mu_s - mu)^T)

(the law of total covariance; its diagonal is ``gp.hyper.mixture.mixture_moments``' total variance). Intervals invert
the mixture's CDF per axis (``gp.hyper.mixture.mixture_quantile``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..hyper.guard import said_once
from ..hyper.posterior import HYPER_POSTERIORS, HyperPosterior, hyper_spec
from ..hyper.predictions import backends_at_draws, posterior_over_hypers
from .backends import Backend3D
from .hyperparameters import RFT3DHyperparameters

__all__ = ["HyperMixture3DMixin"]


class HyperMixture3DMixin:
    """``fit_hyper_posterior`` and the backends predictions average over (``_weighted_backends``) for
    ``InverseRFT3D`` (it uses the model's ``hypers``, ``backend``, ``hyper_method``, device and dtype)."""

    hypers: RFT3DHyperparameters
    backend: Backend3D
    hyper_method: str
    hyper_posterior: HyperPosterior | None
    _draw_backends: list[Backend3D] | None
    _device: torch.device
    dtype: torch.dtype

    def fit_hyper_posterior(self, method: str | None = None, n_proposals: int = 128, n_draws: int | None = 16,
                            generator: torch.Generator | None = None, **options) -> HyperPosterior | None:
        """The posterior over the hyperparameters at the current (fitted) ones (``fit`` calls it when the model
        was built with ``hyper_posterior`` "laplace" or "nuts"); predictions are then mixtures over its draws.

        Args:
            method: "laplace", "nuts" or "map" (drop the draws: plug-in predictions); default: the model's.
            n_proposals: Laplace: importance-sampling proposals (one marginal likelihood each).
            n_draws: draws kept for prediction (each one backend); None keeps every weighted proposal.
            generator: a ``torch.Generator`` for the draws (None: a fixed seed, so that a refit predicts the same).
            options: for ``gp.hyper.posterior.laplace`` or ``nuts`` (``free``: the labels to marginalise, default
                all but what no likelihood sees: alpha_y's lengthscales when alpha_y is a constant).
        Returns:
            the ``HyperPosterior`` (also ``model.hyper_posterior``; labels ``lengthscale_x[sin2b]``, ...,
            ``outputscale_y``, ``noise_z``), None for "map".
        """
        method = self.hyper_method if method is None else method
        if method not in HYPER_POSTERIORS:
            raise ValueError(f"method must be one of {HYPER_POSTERIORS}, got {method!r}")
        if method == "map":
            self._set_hyper_posterior(None)
            return None
        if options.get("free") is None:
            fixed = set(self.hypers.fixed_labels())
            options["free"] = [lab for lab in hyper_spec(self.hypers).labels if lab not in fixed]
        with said_once():
            try:
                hp = posterior_over_hypers(self.backend, method, n_proposals, n_draws, generator, **options)
            finally:
                self.backend.eval()
            self.backend.refresh()  # at the mode (where the posterior leaves the hyperparameters): the draws'
            # backends start from its basis, as a loaded model's do (save/load then gives the same mixture)
            self._set_hyper_posterior(hp)
        return hp

    def _set_hyper_posterior(self, hp: HyperPosterior | None) -> None:
        """Keep ``hp`` and one backend per draw (sharing the data and hyperparameter-free factors)."""
        self.hyper_posterior = hp
        self._draw_backends = None if hp is None else \
            backends_at_draws(self.hypers, hp, self.backend.with_hypers, self._device, self.dtype)

    def _weighted_backends(self) -> tuple[list[Backend3D], Tensor | None]:
        """The backends predictions average over and their weights (None: the one plug-in backend)."""
        if self._draw_backends is None or self.hyper_posterior is None:
            return [self.backend], None
        return self._draw_backends, self.hyper_posterior.weights.to(self._device, self.dtype)
