"""Inference backends: one interface (``RFTBackend``), one covariance W K W^T + noise, computed in the
smallest exact space: observations (T), distinct angle pairs (U) or a Fourier basis (F)."""

from .base import FunctionalPosterior, RFTBackend
from .observations import CompositeExactGP, ObservationsBackend, PriorBackend
from .pairs import PairsBackend
from .select import METHODS, choose_method, estimated_costs, make_backend
from .spectral import SpectralBackend
from .weight_space import FeatureStatistics, WeightSpaceBackend

__all__ = ["RFTBackend", "FunctionalPosterior", "ObservationsBackend", "PriorBackend", "CompositeExactGP",
           "PairsBackend", "SpectralBackend", "WeightSpaceBackend", "FeatureStatistics", "METHODS", "choose_method",
           "estimated_costs", "make_backend"]
