"""Stress maps that change over the ground: the spatial factor of the prior covariance.

A medium shared by the whole site plus variation around it, per map c in {x, z}:

    alpha_c(theta; s) = a_c(theta) + b_c(theta; s),
    cov = k_theta(theta, theta') * (1 + v_c k_s(|s - s'| / l_c)),

with k_theta the angle kernel (``gp.kernels.angle``, with Li et al.'s term where the model has it), k_s gpytorch's
Matern 5/2 kernel over horizontal places s = (x, y) in m, v_c the spatial variance relative to the shared part
(v_c = 0: one homogeneous medium) and l_c the spatial lengthscale in m. A force sample's segments share one place
(its foothold), so the covariance of two force samples is the planar model's W K W^T times the factor between
their places, elementwise:

    Cov(F_t, F_t') = (W K_theta W^T)_{tt'} (1 + v k_s(s_t, s_t')).

The factor is a stock ``ScaleKernel(MaternKernel(nu=2.5))`` (priors, constraints, state dicts are gpytorch's).
``SpatialCompositeKernel`` is the GPyTorch kernel over rows [s_x, s_y, composite row] that the exact GP uses. Its
product is formed densely rather than as gpytorch's ``ProductKernel`` / ``MulLinearOperator``, whose square case
goes through (approximate, Lanczos) root decompositions of both factors; the observations backend needs the
exact matrix for its Cholesky anyway.
"""

from __future__ import annotations

import torch
from gpytorch import Module
from gpytorch.constraints import GreaterThan
from gpytorch.kernels import Kernel, MaternKernel, ScaleKernel
from linear_operator import to_dense
from linear_operator.operators import DenseLinearOperator
from torch import Tensor

from .angle import BATCH
from .priors import SPATIAL_VARIANCE_START

__all__ = ["SpatialFactor", "SpatialCompositeKernel", "SPATIAL_VARIANCE_START"]


class SpatialFactor(Module):
    """The factor 1 + v k_s(s, s') per map (module docstring).

    Args:
        lengthscale: starting spatial lengthscale l, m (both maps).
        variance: starting v (relative to the shared medium's variance), dimensionless.

    Attributes:
        kernel: gpytorch ``ScaleKernel(MaternKernel(nu=2.5))``, batch (2,): outputscale v (2,), lengthscale l
            (2, 1, 1) m.
    """

    def __init__(self, lengthscale: float = 1.0, variance: float = SPATIAL_VARIANCE_START) -> None:
        super().__init__()
        base = MaternKernel(nu=2.5, batch_shape=BATCH, lengthscale_constraint=GreaterThan(1e-4))
        self.kernel = ScaleKernel(base, batch_shape=BATCH, outputscale_constraint=GreaterThan(1e-8))
        with torch.no_grad():
            self.kernel.base_kernel.lengthscale = torch.full((2, 1, 1), float(lengthscale))
            self.kernel.outputscale = torch.full((2,), float(variance))

    @property
    def variance(self) -> Tensor:
        """(2,) v per map, dimensionless."""
        return self.kernel.outputscale

    @property
    def lengthscale(self) -> Tensor:
        """(2,) l per map, m."""
        return self.kernel.base_kernel.lengthscale.reshape(2)

    def factor(self, s1: Tensor | None, s2: Tensor | None, detach: bool = False) -> Tensor | float:
        """(2, N1, N2) the factor between places s1 (N1, 2) and s2 (N2, 2), m. None on either side stands for
        the shared medium a(theta) (its covariance with anything carries factor 1): returns 1.0."""
        if s1 is None or s2 is None:
            return 1.0
        k = to_dense(self.kernel(s1.expand(2, *s1.shape), s2.expand(2, *s2.shape)))
        return 1.0 + (k.detach() if detach else k)

    def diagonal(self, detach: bool = False) -> Tensor:
        """(2,) the factor at zero distance, 1 + v."""
        v = self.variance
        return 1.0 + (v.detach() if detach else v)


class SpatialCompositeKernel(Kernel):
    """The exact GP's kernel over rows (2, T, 2 + 3M): each sample's place (x, y) in m, then its composite row
    (``gp.kernels.encoding``). Returns the angle part's W K W^T (``angle``, an ``RFTCompositeKernel``) times
    ``spatial``'s factor between the rows' places, elementwise (dense)."""

    def __init__(self, angle: Kernel, spatial: SpatialFactor) -> None:
        super().__init__(batch_shape=BATCH)
        self.angle = angle
        self.spatial = spatial
        self._parts: list = []  # (input, version, place columns, composite rows) of the last two inputs

    def _split(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(places (N, 2), composite rows (2, N, 3M)) of rows x, the same tensors while the same input comes
        back (the angle kernel then reuses its index structure, as it does every step of a planar fit)."""
        for hit in self._parts:
            if hit[0] is x and hit[1] == x._version and not x.requires_grad:
                return hit[2], hit[3]
        parts = (x[0, :, :2], x[..., 2:])
        if not x.requires_grad:
            self._parts = [*self._parts[-1:], (x, x._version, *parts)]
        return parts

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, **params):
        s1, r1 = self._split(x1)
        s2, r2 = self._split(x2)
        k = self.angle.forward(r1, r2, diag=diag, **params)
        if diag:
            d = self.spatial.kernel(s1, s2, diag=True)  # (2, N): v k_s(s_n, s_n) = v
            return to_dense(k) * (1.0 + d)
        return DenseLinearOperator(to_dense(k) * self.spatial.factor(s1, s2))
