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
from .kernels.angle import AngleKernel, RFTCompositeKernel, angle_covariance
from .kernels.embedding import embed_angles, rbf
from .kernels.encoding import decode_rows, encode_contacts, encode_points, encode_rows
from .kernels.fourier import FourierBasis
from .kernels.hyperparameters import RFTHyperparameters
from .kernels.means import GenericShapeMean
from .kernels.operators import RFTKernelLinearOperator, RowSeparableRFTOperator, memory_budget, unique_pairs
from .model import InverseRFT
from .model_file import ModelFileError
from .options import Engine, MapPrior
from .posterior import Posterior
from .statistics import recording_statistics, statistics_arrays, statistics_from_arrays
from .streaming.filter import TerrainFilter
from .streaming.filter_mixture import TerrainFilterMixture
from .streaming.tiles import SpatialTiles
from .surface.profile import profile_surface

__all__ = [
    "embed_angles", "rbf", "AngleKernel", "angle_covariance", "RFTCompositeKernel", "RFTKernelLinearOperator",
    "RowSeparableRFTOperator",
    "memory_budget", "unique_pairs", "GenericShapeMean", "RFTHyperparameters", "FourierBasis", "RFTBackend",
    "FunctionalPosterior", "ObservationsBackend", "PairsBackend", "SpectralBackend", "FeatureStatistics",
    "make_backend", "InverseRFT", "MapPrior", "Engine", "Posterior", "ModelFileError", "encode_rows", "decode_rows",
    "encode_contacts",
    "encode_points", "recording_statistics", "statistics_arrays", "statistics_from_arrays",
    "fit_together", "shares_fit", "cross_validate", "GroupPredictions", "profile_surface", "TerrainFilter",
    "TerrainFilterMixture", "SpatialTiles",
]
