"""Deprecated: moved to ``irft_torch.data.wheel`` (this alias goes in 0.4)."""

from ._deprecated import moved
from .data import wheel as _new

__getattr__, __dir__ = moved(__name__, _new)
