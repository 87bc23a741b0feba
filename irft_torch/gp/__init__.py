"""Inference only: the angle kernel, the RFT-weighted LinearOperator, the backends (observations,
distinct pairs, spectral) behind one interface, and the InverseRFT front door."""

from .backends import (
                       FeatureStatistics,
                       FunctionalPosterior,
                       ObservationsBackend,
                       PairsBackend,
                       RFTBackend,
                       SpectralBackend,
                       make_backend,
)
from .batch_fit import fit_together, shares_fit
from .cross_validation import GroupPredictions, cross_validate
from .embedding import embed_angles, rbf
from .encoding import decode_rows, encode_contacts, encode_points, encode_rows
from .fourier import FourierBasis
from .hyperparameters import RFTHyperparameters
from .kernels import AngleKernel, RFTCompositeKernel, angle_covariance
from .means import GenericShapeMean
from .model import InverseRFT
from .model_file import ModelFileError
from .operators import RFTKernelLinearOperator, RowSeparableRFTOperator, memory_budget, unique_pairs
from .posterior import Posterior
from .statistics import recording_statistics, statistics_arrays, statistics_from_arrays
from .surface_profile import profile_surface
from .terrain_filter import TerrainFilter
from .terrain_mixture import TerrainFilterMixture

__all__ = [
    "embed_angles", "rbf", "AngleKernel", "angle_covariance", "RFTCompositeKernel", "RFTKernelLinearOperator",
    "RowSeparableRFTOperator",
    "memory_budget", "unique_pairs", "GenericShapeMean", "RFTHyperparameters", "FourierBasis", "RFTBackend",
    "FunctionalPosterior", "ObservationsBackend", "PairsBackend", "SpectralBackend", "FeatureStatistics",
    "make_backend", "InverseRFT", "Posterior", "ModelFileError", "encode_rows", "decode_rows", "encode_contacts",
    "encode_points", "recording_statistics", "statistics_arrays", "statistics_from_arrays",
    "fit_together", "shares_fit", "cross_validate", "GroupPredictions", "profile_surface", "TerrainFilter",
    "TerrainFilterMixture",
]
