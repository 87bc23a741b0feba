"""Deprecated: moved to ``irft_torch.data.dem`` (this alias goes in 0.4)."""

from ._deprecated import moved
from .data import dem as _new

__getattr__, __dir__ = moved(__name__, _new)
