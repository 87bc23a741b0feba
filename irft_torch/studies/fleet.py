"""A fleet of recordings reduced to one set of spectral sufficient statistics, on Dask.

The spectral statistics of several recordings add up to those of their union
(``FeatureStatistics.__add__``), so a fleet's dataset files are reduced where they lie: each file to
its statistics (read from the file when ``irft ingest`` saved them there and they cover the basis, else
one pass over its samples), then the parts added up in a tree on the workers; only the sum (a few MB)
comes back. ``InverseRFT(contacts, forces, statistics=...)`` then makes no pass of its own.

Dask (``pip install "irft-torch[dask]"``, i.e. ``dask[distributed]``) runs it on any cluster: a
scheduler address, an existing ``distributed.Client``, or a ``LocalCluster`` started and stopped here.
On one machine, ``irft fit --jobs`` (a process pool) does the same without Dask; docs/backends.md says
when each is the right tool.

Example:
    >>> from irft_torch.studies.fleet import reduce_on_dask
    >>> total = reduce_on_dask(["a.npz", "b.npz", "c.npz"], address="tcp://scheduler:8786").statistics
    >>> model = InverseRFT(all_contacts, all_forces, statistics=total)
"""

from __future__ import annotations

import multiprocessing
import os
import time
import warnings
from dataclasses import dataclass

__all__ = ["dataset_statistics", "reduce_on_dask", "FleetReduction", "DASK_MISSING"]

DASK_MISSING = 'Dask is not installed: pip install "irft-torch[dask]" (dask[distributed])'


def dataset_statistics(path, basis=None, threads: int = 0):
    """One dataset file's spectral statistics in ``basis`` (default ``gp.statistics.initial_basis()``):
    cut from those saved in the file when they are its own (their fingerprint matches the data) and
    cover the basis, else one pass over its samples (float64, unit noise scale, the generic shape's
    forces included). Statistics saved from other data are refused with a warning (and recomputed).
    ``threads``: torch's intra-op threads for the pass (0: leave as is).

    Returns:
        (FeatureStatistics, whether they were read from the file).
    """
    stats, from_file, note = _dataset_statistics(path, basis, threads)
    if note:
        warnings.warn(note, UserWarning, stacklevel=2)
    return stats, from_file


def _dataset_statistics(path, basis, threads: int):
    """``dataset_statistics`` with the refusal as a message instead of a warning (a warning raised in one of
    a Dask worker's threads is neither seen by the client nor safe to catch there)."""
    import json

    import numpy as np
    import torch

    from ..data import load_dataset
    from ..gp.backends.spectral import restrict_statistics
    from ..gp.statistics import data_fingerprint, initial_basis, recording_statistics, statistics_from_arrays

    if threads:
        torch.set_num_threads(int(threads))
    basis = basis or initial_basis()
    ds = load_dataset(path)
    c, f = ds.contacts.to(dtype=torch.float64), ds.forces.to(torch.float64)
    note = None
    if ds.statistics:
        stats = statistics_from_arrays(ds.statistics, source=f"the statistics saved in {path}")  # checked below
        try:
            theirs = json.loads(str(np.asarray(ds.statistics["meta"]))).get("data_sha256")
        except (KeyError, ValueError):
            theirs = None
        if theirs != data_fingerprint(c, f):
            note = (f"the statistics saved in {path} do not belong to its contacts and forces (their data "
                    "fingerprint differs): they are ignored and recomputed")
        elif stats.meta["n_beta"] >= basis.n_beta and stats.meta["n_gamma"] >= basis.n_gamma:
            return restrict_statistics(stats, basis), True, None
    return recording_statistics(c, f, basis), False, note


def _part(path: str, n_beta: int, n_gamma: int, threads: int) -> tuple:
    """A Dask task: (statistics' state, from the file?, notes) of one dataset (plain tensors and strings:
    they pickle anywhere; the client turns the notes into warnings)."""
    from ..gp.kernels.fourier import FourierBasis

    stats, from_file, note = _dataset_statistics(path, FourierBasis(n_beta, n_gamma), threads)
    return stats.state(), int(from_file), [note] if note else []


def _add(a: tuple, b: tuple) -> tuple:
    """A Dask task: the sum of two parts (statistics add up exactly; the counts and notes add too)."""
    from ..gp.backends.weight_space import FeatureStatistics

    total = FeatureStatistics.from_state(a[0]) + FeatureStatistics.from_state(b[0])
    return total.state(), a[1] + b[1], a[2] + b[2]


@dataclass
class FleetReduction:
    """What ``reduce_on_dask`` returns: the summed ``statistics`` (a ``FeatureStatistics``), how many
    datasets were reduced and how many of them were read from statistics saved in the file, the Dask
    workers that ran it and the wall time in s (cluster start-up included where it was started here)."""

    statistics: object
    n_datasets: int
    n_from_files: int
    n_workers: int
    seconds: float


def _dask():
    try:
        import distributed
    except ImportError as e:
        raise ImportError(DASK_MISSING) from e
    return distributed


# The workers of a LocalCluster started here. Dask's default environment for a worker sets
# MALLOC_TRIM_THRESHOLD_=65536, which also fixes glibc's mmap threshold at 128 kB: every large temporary
# of the statistics pass is then mapped and faulted in afresh, and the pass runs 1.6-1.9x slower than
# in a plain process (measured: 6.6-6.9 s against 3.5-4.7 s for one 250,000-sample dataset, one
# thread). Unset here; workers are forked from a server that has imported the pass's modules once
# (where the platform has a forkserver), not spawned and importing torch each.
_LOCAL_WORKER_CONFIG: dict[str, str | None] = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
_PRELOAD = ("distributed", "irft_torch.studies.fleet", "irft_torch.gp.statistics", "irft_torch.data")


def _preload_forkserver(distributed) -> None:
    """Make distributed's forkserver context import the pass's modules once (before the server starts;
    a server already running keeps what it has)."""
    ctx = distributed.utils.get_mp_context()  # distributed sets its own preload list the first time
    ctx.set_forkserver_preload(list(_PRELOAD))


def reduce_on_dask(paths, basis=None, *, address: str | None = None, client=None, n_workers: int | None = None,
                   threads: int | None = None) -> FleetReduction:
    """The summed spectral statistics of the dataset files ``paths`` in ``basis`` (default
    ``gp.statistics.initial_basis()``, the basis a default spectral model starts in), each file reduced by
    one Dask task, the parts added up in a tree on the workers.

    Args:
        paths: dataset .npz files (``irft ingest``), readable by the workers under these names.
        basis: a ``FourierBasis``; every part must be in the same one.
        address: a Dask scheduler (``"tcp://host:8786"``) to connect to (and disconnect from after).
        client: an existing ``distributed.Client`` instead (left open).
        n_workers: with neither: the worker processes of the ``LocalCluster`` started and stopped here
            (default one per dataset, at most one per CPU; one thread each).
        threads: torch threads per task (default: the CPUs shared among the local workers; 0 on a cluster
            of yours: torch's own default there).

    Raises:
        ImportError: Dask is not installed (``pip install "irft-torch[dask]"``).
        ValueError: no paths; FileNotFoundError / ValueError from a missing or damaged dataset (on the worker
            that read it, re-raised here).
    """
    from ..gp.backends.weight_space import FeatureStatistics
    from ..gp.statistics import initial_basis

    paths = [str(p) for p in ([paths] if isinstance(paths, (str, os.PathLike)) else paths)]
    if not paths:
        raise ValueError("paths is empty: give at least one dataset file")
    if client is not None and address is not None:
        raise ValueError("give address or client, not both")
    distributed = _dask()
    import dask

    basis = basis or initial_basis()
    t0 = time.perf_counter()
    own_cluster = own_client = None
    try:
        if client is None:
            if address is None:
                cpus = os.cpu_count() or 1
                n = int(n_workers or min(len(paths), cpus))
                if threads is None:
                    threads = max(1, cpus // n)
                config: dict[str, str | None] = dict(_LOCAL_WORKER_CONFIG)
                if "forkserver" in multiprocessing.get_all_start_methods():
                    config["distributed.worker.multiprocessing-method"] = "forkserver"
                with dask.config.set(config):
                    if dask.config.get("distributed.worker.multiprocessing-method") == "forkserver":
                        _preload_forkserver(distributed)
                    own_cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                           dashboard_address=None)
                client = own_client = distributed.Client(own_cluster)
            else:
                client = own_client = distributed.Client(address)
        threads = 0 if threads is None else int(threads)
        parts = client.map(_part, paths, n_beta=basis.n_beta, n_gamma=basis.n_gamma, threads=threads,
                           pure=False)
        while len(parts) > 1:  # a tree of sums on the workers
            pairs = [client.submit(_add, a, b, pure=False) for a, b in zip(parts[0::2], parts[1::2])]
            parts = pairs + ([parts[-1]] if len(parts) % 2 else [])
        state, n_file, messages = parts[0].result()
        workers = len(client.scheduler_info().get("workers", {}))
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()
    for message in messages:  # what the workers said (statistics saved with other data, ...), here
        warnings.warn(message, UserWarning, stacklevel=2)
    return FleetReduction(FeatureStatistics.from_state(state), len(paths), int(n_file), workers,
                          time.perf_counter() - t0)
