"""Deprecated: moved to ``irft_torch.studies.report`` (this alias goes in 0.4)."""

from ._deprecated import moved
from .studies import report as _new

__getattr__, __dir__ = moved(__name__, _new)
