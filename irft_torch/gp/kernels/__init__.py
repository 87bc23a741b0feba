"""What the maps are believed to be before any force is seen: the angle kernel (a gpytorch
``ScaleKernel(RBFKernel)`` on the (sin 2beta, cos 2beta, sin gamma, cos gamma) embedding), its Fourier
basis on the angle torus, the lazy RFT-weighted ``W K W^T`` operator, Li et al.'s 9-function term, the prior
means, the hyperparameters' modules and their physical priors. No data, no solves: the backends use these."""

from .angle import AngleKernel, RFTCompositeKernel, angle_covariance, composite_covariance, embed_angles

__all__ = ["AngleKernel", "RFTCompositeKernel", "angle_covariance", "composite_covariance", "embed_angles"]
