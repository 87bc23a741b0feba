"""Inference only: the angle kernel, the RFT-weighted LinearOperator, the force likelihood, the
prior means and the InverseRFT model."""

from .encoding import decode_rows, encode_contacts, encode_points, encode_rows
from .kernels import AngleRBFKernel, RFTCompositeKernel, embed_angles
from .likelihoods import ForceNoise, ForceNoiseLikelihood
from .means import GenericShapeMean
from .model import CompositeExactGP, InverseRFT, Posterior
from .operators import RFTKernelLinearOperator, memory_budget, rbf

__all__ = [
    "embed_angles", "AngleRBFKernel", "RFTCompositeKernel", "RFTKernelLinearOperator", "rbf", "memory_budget",
    "ForceNoise", "ForceNoiseLikelihood", "GenericShapeMean", "CompositeExactGP", "InverseRFT", "Posterior",
    "encode_rows", "decode_rows", "encode_contacts", "encode_points",
]
