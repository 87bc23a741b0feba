"""A positive constraint measured in the data's units (a unit-free fit)."""

from __future__ import annotations

import torch
from gpytorch.constraints import GreaterThan

__all__ = ["ScaledGreaterThan"]


class ScaledGreaterThan(GreaterThan):
    """value = scale * softplus(raw) + lower_bound: a positive hyperparameter whose raw (optimized)
    value is unit-free when ``scale`` carries the data's units (a force variance, a stress per depth
    squared). Adam's steps on raw values then mean the same in N or mN, cm^3 or mm^3 (the way
    botorch's ``Standardize`` makes a fit unit-free), while the value keeps its physical units."""

    def __init__(self, lower_bound=0.0, scale=1.0) -> None:
        super().__init__(lower_bound)
        self.register_buffer("scale", torch.as_tensor(scale, dtype=self.lower_bound.dtype))

    def transform(self, tensor):
        return self._transform(tensor) * self.scale + self.lower_bound

    def inverse_transform(self, transformed_tensor):
        return self._inv_transform((transformed_tensor - self.lower_bound) / self.scale)

    def __repr__(self) -> str:
        return f"ScaledGreaterThan({self.lower_bound.tolist()}, scale={self.scale.tolist()})"
