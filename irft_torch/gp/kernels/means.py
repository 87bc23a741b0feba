"""Prior means of the composite observations: zero, or the generic RFT shape times learned scales."""

from __future__ import annotations

import torch
from gpytorch.means import Mean
from torch import Tensor

from ...rft.stress_maps import FourierStressMap
from .constraints import ScaledGreaterThan
from .encoding import decode_rows

__all__ = ["GenericShapeMean"]


class GenericShapeMean(Mean):
    r"""m_c(theta) = s_c alpha^{generic}_c(theta): the Li et al. generic map with a learned scale per
    axis (media differ mainly by one scale, Li et al. 2013). For a composite row the mean is
    sum_m w_m m_c(theta_m). Inputs are the (x, z) batch of rows, (..., 2, T, 3M).

    Args:
        init_scales: initial (s_x, s_z) in N/cm^3.
    """

    def __init__(self, init_scales: tuple[float, float] = (1.0, 1.0), scale=1.0) -> None:
        """``scale`` (2,): the data's typical stress per depth, N/cm^3, in which the raw scales are
        measured (a unit-free fit; see ``hyperparameters.ScaledGreaterThan``)."""
        super().__init__()
        self.shape_map = FourierStressMap.generic()
        self.register_parameter("raw_scales", torch.nn.Parameter(torch.zeros(2)))
        self.register_constraint("raw_scales", ScaledGreaterThan(0.0, torch.as_tensor(scale).expand(2).clone()))
        self.scales = init_scales

    @property
    def scales(self) -> Tensor:
        return self.raw_scales_constraint.transform(self.raw_scales)

    @scales.setter
    def scales(self, value) -> None:
        value = torch.as_tensor(value, dtype=self.raw_scales.dtype, device=self.raw_scales.device)
        value = torch.maximum(value, 1e-8 * self.raw_scales_constraint.scale)
        self.initialize(raw_scales=self.raw_scales_constraint.inverse_transform(value))

    def shape_forces(self, contacts) -> Tensor:
        """The generic shape's forces on ``contacts`` (N, M), without the scales: (2, N) = (x, z)."""
        a = self.shape_map.to(contacts.beta.dtype)(contacts.beta, contacts.gamma)  # (N, M, 2)
        return torch.stack([(contacts.weight_x * a[..., 0]).sum(-1), (contacts.weight_z * a[..., 1]).sum(-1)])

    def forward(self, x: Tensor) -> Tensor:
        if x.dim() < 3 or x.shape[-3] != 2:
            raise ValueError(f"GenericShapeMean expects (..., 2, T, 3M) rows, got {tuple(x.shape)}")
        beta, gamma, w = decode_rows(x)
        alpha = self.shape_map(beta, gamma)  # (..., 2, T, M, 2)
        per_axis = torch.stack([alpha[..., 0, :, :, 0], alpha[..., 1, :, :, 1]], dim=-3)  # (..., 2, T, M)
        return self.scales[:, None] * (w * per_axis).sum(-1)
