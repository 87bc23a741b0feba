"""Deprecated: moved to ``irft_torch.studies.workers`` (this alias goes in 0.4)."""

from ._deprecated import moved
from .studies import workers as _new

__getattr__, __dir__ = moved(__name__, _new)
