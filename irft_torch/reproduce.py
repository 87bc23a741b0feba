"""Deprecated: moved to ``irft_torch.studies.reproduce``, ``run_study`` to
``irft_torch.studies.paper_study`` (this alias goes in 0.4)."""

from ._deprecated import moved
from .studies import paper_study as _paper_study
from .studies import reproduce as _new

__getattr__, __dir__ = moved(__name__, _new, run_study=_paper_study.run_study)
