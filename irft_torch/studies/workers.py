"""Process pools for many small fits (``irft reproduce``, the experiments).

Workers are forked from a server process that has imported what they need once ("forkserver",
where the platform has it: one import instead of one per worker, and no fork of a process whose
thread pools are running), else spawned. The server also imports ``torch._dynamo``, which the
first optimizer step of every process would otherwise import (0.8-0.9 s each).
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["worker_context", "start_worker_server", "default_workers"]


def default_workers() -> int:
    """Worker processes for many small fits (``irft reproduce``): one per CPU (at most 8); the fits are
    small, so one thread each uses the cores better than threads inside one fit."""
    import os

    return max(1, min(8, os.cpu_count() or 1))


def worker_context(preload: Sequence[str] = ("irft_torch",)):
    """A ``multiprocessing`` context for ``ProcessPoolExecutor(mp_context=...)`` whose workers start
    with the modules ``preload`` (and ``torch._dynamo``) imported."""
    from multiprocessing import get_all_start_methods, get_context

    if "forkserver" not in get_all_start_methods():
        return get_context("spawn")
    ctx = get_context("forkserver")
    ctx.set_forkserver_preload([*preload, "torch._dynamo"])
    return ctx


def start_worker_server(preload: Sequence[str] = ("irft_torch",)) -> None:
    """Start the server of ``worker_context(preload)`` now, so that its imports (torch, gpytorch: seconds)
    run while this process imports its own; a pool made later with the same context uses it. Call it
    before this process imports torch. Nothing to do where the platform has no forkserver."""
    from multiprocessing import forkserver, get_all_start_methods

    if "forkserver" in get_all_start_methods():
        worker_context(preload)
        forkserver.ensure_running()
