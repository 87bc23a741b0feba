"""``irft reproduce`` end to end: the paper's numerical study fitted (``studies.reproduce``), then its
tables, figures and report.md written from the results (``studies.report``). It sits above both;
neither imports it.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import torch

from .report import draw_fig5, write_study
from .reproduce import StudySettings, fit_study, study_fits
from .workers import worker_context

__all__ = ["run_study", "PRELOAD"]

PRELOAD = ("irft_torch.studies.paper_study",)  # what the study's worker processes import (cli.reproduce: the same)


def run_study(out_dir: str | Path = "experiments/results", settings: StudySettings | None = None,
              progress: bool = True, figures: bool = True, workers: int = 1) -> dict:
    """Run Table I (zero and physics prior means, the paper's scale and the unscaled generic map)
    and the Table II noise study; write CSVs, figures and ``report.md`` into ``out_dir``.
    ``workers``: processes running the fits (1: here; ``studies.workers.default_workers()`` for all
    cores). Returns ``{"results": [FitResult, ...], "elapsed_s": s, "out_dir": str}``."""
    s = settings or StudySettings()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_default_dtype(torch.float64)
    jobs = study_fits(s)
    with contextlib.ExitStack() as stack:
        pool = None
        if workers > 1:
            from concurrent.futures import ProcessPoolExecutor

            ctx = worker_context(PRELOAD)  # as cli.reproduce.PRELOAD: a server it started is used
            pool = stack.enter_context(ProcessPoolExecutor(workers, mp_context=ctx))
        t0 = time.perf_counter()
        results = fit_study(jobs, s, progress, pool, workers, figure_dir=out if figures else None, draw=draw_fig5)
        elapsed = time.perf_counter() - t0
        return write_study(out, s, results, elapsed, figures, pool)
