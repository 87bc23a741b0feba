"""A candidate's force noise scale from the model's own predicted force (``design.force_relative``)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..rft.contacts import Contacts

__all__ = ["force_relative"]


@dataclass
class _ForceRelative:
    """sqrt(F^2 + floor^2) of the model's predicted force (a class, not a closure: a scorer pickles)."""

    model: Any  # an InverseRFT (design/ never imports the front door)
    floor: float

    def __call__(self, c: Contacts) -> Tensor:
        with torch.no_grad():
            f = self.model.predict_forces(c).mean
        return (f.pow(2) + self.floor**2).sqrt()


def force_relative(model, floor: float) -> Callable[[Contacts], Tensor]:
    """A candidate noise scale proportional to the model's predicted force, sqrt(F^2 + floor^2) (N),
    a function of the candidate's contacts returning (T, 2): the counterpart of fitting with
    ``noise_scale=(forces**2 + floor**2).sqrt()``."""
    if not (math.isfinite(floor) and floor > 0):
        raise ValueError(f"floor must be a positive force in N, got {floor}")
    return _ForceRelative(model, float(floor))
