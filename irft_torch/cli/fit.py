"""``irft fit``: fit ``InverseRFT`` to one or more datasets (summed spectral statistics for long
recordings, reduced in worker processes) and write model.pt, the map with its uncertainty and the
forces."""

from __future__ import annotations

import argparse
import os
import warnings
from pathlib import Path

from .arguments import UsageError, _out_dir, warn


def _statistics_of(path: str, n_beta: int, n_gamma: int, threads: int = 0) -> dict:
    """One dataset's spectral statistics in FourierBasis(n_beta, n_gamma) (``studies.fleet.dataset_statistics``:
    cut from those saved in the file when they are its own and cover the basis, else one pass), as a worker
    of ``irft fit`` returns them: the statistics' state and whether they came from the file."""
    from ..gp.kernels.fourier import FourierBasis
    from ..studies.fleet import dataset_statistics

    stats, from_file = dataset_statistics(path, FourierBasis(n_beta, n_gamma), threads)
    return {"state": stats.state(), "from_file": from_file}


def _spectral_start(contacts, method: str):
    """The Fourier basis the model will start in if ``method`` gives the spectral backend on these
    contacts (a default ``InverseRFT``: lengthscale 1, tol 1e-7), else None."""
    from types import SimpleNamespace

    import torch

    from ..gp.backends.select import choose_method
    from ..gp.statistics import initial_basis

    hypers = SimpleNamespace(lengthscale=torch.ones(2, 1, 4, dtype=torch.float64))
    if method == "spectral" or (method == "auto" and choose_method(contacts, hypers) == "spectral"):
        return initial_basis()
    return None


def _reduce_statistics(paths: list[str], basis, jobs: int = 0, n_samples: int = 0, dask: str | None = None):
    """The summed spectral statistics of the datasets at ``paths`` in ``basis``, reduced in ``jobs``
    worker processes (0: up to half the CPU count, from 4 CPUs, when the pass, about ``n_samples`` x
    F^2 flops, is long enough to pay for starting them, a few seconds each; 1: here, where torch
    already spreads the pass's matrix products over the cores), or on Dask (``dask``: a scheduler
    address, or "" for a local cluster started and stopped here; ``studies.fleet.reduce_on_dask``).
    Statistics saved in a file are used when they are that file's own and cover the basis."""
    import time
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from ..gp.backends.weight_space import FeatureStatistics

    if dask is not None:
        from ..studies.fleet import reduce_on_dask

        try:
            r = reduce_on_dask(paths, basis, address=dask or None)
        except ImportError as e:  # a user error on the command line: one line, what to install
            raise UsageError("--dask", str(e)) from None
        where = f"on the Dask cluster at {dask}" if dask else "on a local Dask cluster"
        print(f"spectral statistics ({basis.size} features) of {r.n_datasets} dataset(s): {r.n_from_files} read from "
              f"the files, {r.n_datasets - r.n_from_files} computed {where} ({r.n_workers} workers); "
              f"{r.seconds:.1f} s")
        return r.statistics
    t0 = time.perf_counter()
    if jobs == 0:
        cpus = os.cpu_count() or 1  # one process already uses every core for the pass's matrix products
        jobs = min(len(paths), cpus // 2) if n_samples * basis.size**2 > 4e11 and cpus >= 4 else 1
    args = [(str(p), basis.n_beta, basis.n_gamma) for p in paths]
    if jobs > 1:
        threads = max(1, (os.cpu_count() or 1) // jobs)
        with ProcessPoolExecutor(jobs, mp_context=get_context("spawn")) as pool:
            parts = list(pool.map(_statistics_of, *zip(*args), [threads] * len(args)))
    else:
        parts = [_statistics_of(*x) for x in args]
    total = None
    for part in parts:
        st = FeatureStatistics.from_state(part["state"])
        total = st if total is None else total + st
    n_file = sum(p["from_file"] for p in parts)
    print(f"spectral statistics ({basis.size} features) of {len(paths)} dataset(s): {n_file} read from the files, "
          f"{len(paths) - n_file} computed in {jobs} process(es); {time.perf_counter() - t0:.1f} s")
    return total


def cmd_fit(a) -> int:
    import torch

    from .. import plotting
    from .._files import StagedFiles
    from ..gp import InverseRFT
    from ..gp.model import FitInterruptedWarning
    from ..gp.options import MapPrior
    from ..hardware import load_dataset

    out = _out_dir(a.out, "--out")  # before the fit: a bad --out fails now, not after minutes of training
    if a.dask is not None:
        if a.dask.endswith(".npz") or Path(a.dask).is_file():
            raise UsageError("--dask", f"{a.dask!r} is a dataset file, not a scheduler address: write --dask after "
                                       "the datasets (or give the address, tcp://host:8786)")
        if a.jobs:
            raise UsageError("--jobs", "reduces in local processes, --dask on Dask: give one of them")
    parts = [load_dataset(p) for p in a.dataset]
    placed = sum(d.locations is not None for d in parts)
    if placed:  # a walk over changing ground (irft simulate --terrain): said, not dropped silently
        print(f"{placed} of {len(parts)} dataset(s) carry each sample's place on the ground; this version fits one "
              f"medium to every sample: the map is the walked ground's blend, not a map over space")
    ds = parts[0]
    if len(parts) > 1:  # one recording after another: times shifted so the time axis keeps increasing
        from ..rft import Contacts

        times, t_end = [], 0.0
        for d in parts:
            t = d.time - d.time[0]
            step = float(t[1] - t[0]) if len(t) > 1 else 0.0
            times.append(t + t_end)
            t_end = float(times[-1][-1]) + step
        ds = type(ds)(Contacts.cat([d.contacts for d in parts]), torch.cat([d.forces for d in parts]),
                      torch.cat(times), torch.cat([d.toe_position for d in parts]))
        print(f"{len(parts)} datasets, {len(ds)} samples in all")
    stats = None
    if a.max_samples and len(ds) > a.max_samples:
        keep = torch.linspace(0, len(ds) - 1, a.max_samples).round().long()
        print(f"using {a.max_samples} of {len(ds)} samples, evenly spaced (--max-samples)")
        ds = type(ds)(ds.contacts[keep], ds.forces[keep], ds.time[keep], ds.toe_position[keep])
    elif (basis := _spectral_start(ds.contacts.to(dtype=torch.float64), a.method)) is not None:
        stats = _reduce_statistics(a.dataset, basis, a.jobs, len(ds), dask=a.dask)
    elif a.dask is not None:
        print("--dask: nothing to reduce (the fit does not start in the spectral space: its statistics are not used)")
    kernel = "li+generic" if a.generic_shape else ("li" if a.li_basis else "rbf")
    model = InverseRFT(ds.contacts, ds.forces, statistics=stats, hyper_posterior=a.hyper_posterior, engine=a.method,
                       prior=MapPrior(kernel=kernel, mean=a.prior_mean, hyperpriors=None if a.priors == "none"
                                      else a.priors))
    print(f"backend {model.backend.describe()}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        history = model.fit(n_iter=a.n_iter, lr=a.lr, progress=not a.no_progress)
    interrupted = any(issubclass(w.category, FitInterruptedWarning) for w in caught)
    for w in caught:
        warn("fit", w.message)
    if interrupted and not history:
        warn("fit", f"interrupted before the first step: nothing written (what is in {out} is as it was)")
        return 130
    print(model.diagnostics(warn=False))
    with StagedFiles(out) as staged:  # all three or none, never one run's model beside another's figures
        model.save(staged.path("model.pt"))
        plotting.save(plotting.plot_posterior_map(model), staged.path("stress_map.png"))
        pred = model.predict_forces(ds.contacts)
        meas = model.predict_forces(ds.contacts, include_noise=True)  # a new measurement: mean +- noise too
        plotting.save(plotting.plot_forces(ds.time, ds.forces, pred.mean, meas.stddev,
                                           labels=("dataset", "I-RFT fit"),
                                           band_label=r"$\pm 2\sigma$ of a measurement"), staged.path("forces.png"))
        kept: list[float] = []  # the two losses, where the file's model is kept
        if not staged.commit(check=lambda: _better_than_before(out / "model.pt", model, a.replace, kept)):
            warn("fit", f"{out}/model.pt holds a better fit of these data with these options (loss {kept[0]:.5g} "
                        f"against {kept[1]:.5g} now): it is kept and nothing is written (--replace writes this fit "
                        "anyway)")
            return 1
    rng = (ds.forces.amax(0) - ds.forces.amin(0)).clamp_min(1e-12)
    nrmse = ((pred.mean - ds.forces).pow(2).mean(0).sqrt() / rng * 100).tolist()
    print(f"wrote {out}/model.pt, stress_map.png, forces.png; force RMSE {nrmse[0]:.2f} % (x), "
          f"{nrmse[1]:.2f} % (z) of range" + (f" (interrupted after {len(history)} of {a.n_iter} steps)"
                                              if interrupted else ""))
    return 130 if interrupted else 0


def _better_than_before(path: Path, model, replace: bool, kept: list) -> bool:
    """Whether ``model`` may replace the model file at ``path``: always with ``replace``, or when there is
    none, or it is damaged, or of other data or options (said so); else when its loss on these data is
    not lower than ``model``'s (``kept`` gets the two losses when it is)."""
    import torch

    from ..gp import InverseRFT
    from ..gp.model_file import ModelFileError

    if replace or not path.exists():
        return True
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            old = InverseRFT.load(path)
    except (ModelFileError, OSError, ValueError, RuntimeError) as e:
        print(f"replacing {path}: it is not a model this version reads ({' '.join(str(e).split())[:120]})")
        return True
    if not isinstance(old, InverseRFT):  # a 3-D model's file (InverseRFT.load reads those too)
        print(f"replacing {path} (a fit of a 3-D model)")
        return True
    same_data = torch.equal(old.state_dict()["data_digest"], model.state_dict()["data_digest"])
    if not same_data or old._options() != model._options():
        print(f"replacing {path} (a fit of {'other data' if not same_data else 'other options'})")
        return True
    with torch.no_grad():
        before, now = float(old.loss()), float(model.loss())
    if before < now - 1e-4 * max(1.0, abs(before)):
        kept.extend([before, now])
        return False
    return True


def register(sub) -> None:
    p = sub.add_parser("fit", help="fit I-RFT to a dataset; write the map, its uncertainty and figures",
                       description="Fit InverseRFT to an ingested dataset and write model.pt and figures.")
    p.add_argument("dataset", nargs="+", help="dataset .npz from irft ingest (several: fitted together)")
    p.add_argument("--method", choices=["auto", "observations", "pairs", "spectral"], default="auto",
                   help="inference backend (default auto: the cheapest exact space for the data)")
    p.add_argument("--out", default="irft_fit", help="output directory (default irft_fit)")
    p.add_argument("--n-iter", type=int, default=300)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--prior-mean", choices=["zero", "physics"], default="zero")
    p.add_argument("--priors", choices=["physical", "none"], default="physical",
                   help="hyperparameter priors (default physical: MAP, gp.kernels.priors; none: the paper's plain "
                        "marginal likelihood)")
    p.add_argument("--li-basis", action=argparse.BooleanOptionalAction, default=True,
                   help="Li et al.'s 9 fitting functions in the kernel as a term with its own variance (default; "
                        "--no-li-basis: the paper's RBF alone; docs/calibration.md)")
    p.add_argument("--generic-shape", action="store_true",
                   help="also give Li et al.'s generic map a scale of its own, integrated out (InverseRFT(..., "
                        "prior=MapPrior(kernel='li+generic')); implies --li-basis; docs/calibration.md)")
    p.add_argument("--hyper-posterior", choices=["map", "laplace", "nuts"], default="laplace",
                   help="laplace (default): average the map and its uncertainty over the hyperparameters' posterior "
                        "(intervals that hold on media nobody tuned for); map: the plug-in at the fitted "
                        "hyperparameters (about 1.5x faster, overconfident away from the generic medium; "
                        "docs/calibration.md)")
    p.add_argument("--max-samples", type=int, default=0,
                   help="thin to this many evenly spaced samples (default 0: use every sample; the backend picked "
                        "by method='auto' keeps long recordings fast)")
    p.add_argument("--jobs", type=int, default=0,
                   help="worker processes reducing the datasets to their spectral statistics (default 0: up to half "
                        "the CPUs, from 4, when the pass is long, over about 5 million samples; 1: in this process)")
    p.add_argument("--dask", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="reduce the datasets on Dask instead (pip install \"irft-torch[dask]\"): at the scheduler "
                        "ADDRESS (tcp://host:8786), or without one on a local cluster started and stopped here; "
                        "write it after the datasets")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--replace", action="store_true",
                   help="write this fit even where --out holds a better one (a lower loss) of the same data and "
                        "options; by default that one is kept")
    p.set_defaults(func=cmd_fit)
