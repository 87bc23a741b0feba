"""Inference speed: the issue-12 cases, each against a reference timed in the same run.

Data: simulated (C-toe gaits, DEM-like plates, varied plate strokes). Run time: cases 1-5 about 1 min (2026-11-22);
case 11 alone 52-76 s; case 12 with --repeats 3 and 8 about 100 s together (2026-12-02); all 12 together not
measured here.

    python experiments/benchmarks/bench_inference.py [--quick] [--device cuda] [--out experiments/results]

Cases (float64, this machine's threads; the engine cases fit the plug-in RBF, ``PLUG_IN``: ``InverseRFT(contacts,
forces, prior=MapPrior(kernel="rbf"), hyper_posterior="map")``, the former default; case 8 the default itself):
  1. paper scale: C-toe (M = 10) on the paper's cubic gait, T = 200: one likelihood + gradient step
     vs the paper's dense formula (explicit W, explicit K, Cholesky); same loss checked;
  2. DEM-like: T = 810 plate samples x M = 5 segments with 54 distinct (beta, gamma) pairs: Adam
     steps per second, vs the observations backend's step;
  3. T = 10^4 x M = 10, C-toe, every angle pair distinct: construction + 300 Adam steps + a 50 x 50
     map, vs one observations-backend step at T = 1,000 (the reference cannot run at 10^4);
  4. 10^6 samples x M = 10 (a fresh process, so its peak memory is its own): one pass + 100 steps +
     map; peak resident memory, and what the data alone take;
  5. streaming: add_data in batches of 100 samples to a T = 10^4 model, ms per sample;
  6. a fleet: 4 datasets of 250,000 samples x M = 10 reduced to their spectral statistics (what
     ``irft fit a.npz b.npz ...`` does first) in 2 worker processes, and from statistics saved with
     the datasets (``irft ingest`` saves them), vs one process making every pass;
  7. 8 models on the same contacts (a noise study, C-toe gait 1): ``gp.fit_together`` vs fitting each.
  8. the default fit (``InverseRFT(c, f).fit()``: Li et al.'s term and the Laplace hyperparameter posterior) vs the
     former default's plug-in fit, paper scale, DEM-like and the harness' turning scoop (issue 51: <= 1.5x); and the
     default against its draws all in one basis grown for them (``gp.hyper.density.draws_in_one_basis``, issue 52);
  9. parallel environments (issue 33): ``TerrainFilter`` with B = 4096 environments of a C-toe (M = 10)
     on the paper's gait, one update and a 16-point map query per step (windows of 8, 16 and 32 samples):
     env-steps per second, vs a loop over one ``InverseRFT`` per environment doing the same (``add_data``
     of the sample, ``stress_map`` of the 16 points), timed on 8 environments and scaled; and a spatial model's
     filter (each sample at its environment's foothold, the map asked at one place each) against the planar one.
 10. a turning C-toe (T = 200 x M = 12, the calibration harness' ``turning`` motion): Adam steps of the
     default fit, closed form vs autograd (issue 30: < 3.3 ms);
 11. NUTS (pyro) on C-toe gait 2 (the paper study's configuration, tied noise): 4 chains x 500 draws after
     500 warm-up (Laplace metric, chains in worker processes), and a short chain in both engines for the
     ratio (issue 30: < 60 s).
 12. varied recordings (issue 52): default fits of 1,000 and 10,000 samples of short plate strokes, each its own
     tilt sweep (nearly every angle pair distinct; the harness' held-out "sharp" medium): first and last Adam
     step, whole fit, the basis it ended in and its kernel error.
 13. the 3-D wheel fold (issue 52): ``InverseRFT(contacts_3d, forces).fit()`` on the measured smooth wheel, one slip
     angle held out, against the engine before e2da7f5 in the same run (``bench_wheel3d.py``; needs
     ``--wheel-data ../shared/data/rover_wheel``, skipped without it; about 40 s).
"Today's engine" (the reference in cases 2, 8, 10, 11) is the autograd path, run in the same process
(``gp.backends.closed_form.autograd_only``).
Case 6 also reduces the 4 datasets on a local Dask cluster (2 worker processes, start-up included), beside
the 2-process pool.
Writes benchmarks.md under --out (benchmarks_cuda.md with ``--device cuda``: the data and the model on the
GPU, the references too; cases 6 and 8 are skipped there: 6 reduces files in CPU worker processes).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import resource
import subprocess
import sys
import time
import warnings
from pathlib import Path

import torch

import irft_torch as irft
from irft_torch.gp.backends.closed_form import autograd_only

TRUTH = irft.rft.FourierStressMap.generic(0.452, 0.417)
PLUG_IN = {"hyper_posterior": "map", "prior": irft.MapPrior(kernel="rbf")}  # the engine cases: the plug-in RBF
DEVICE = torch.device("cpu")


def on_device(c, f):
    return c.to(device=DEVICE), f.to(DEVICE)


def sync():
    if DEVICE.type == "cuda":
        torch.cuda.synchronize()


def paper_contacts(T: int, M: int = 10):
    toe = irft.rft.CToe(0.02, 0.008, M)
    path = irft.rft.spline_path([(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)], n_steps=T)
    return irft.rft.contacts(toe, path)


def recording(T: int, seed: int = 0):
    """T samples: repeats of the C-toe gait-2 run (1,000 samples each), angles jittered (every pair
    distinct), forces from the generic map with 1 % noise."""
    base = paper_contacts(1000)
    reps = math.ceil(T / 1000)
    g = torch.Generator().manual_seed(seed)
    parts = [torch.cat([v] * reps)[:T] for v in (base.beta, base.gamma, base.weight_x, base.weight_z)]
    jit = lambda v: v + 1e-3 * torch.randn(v.shape, generator=g)  # noqa: E731
    c = irft.rft.Contacts(jit(parts[0]).clamp(-math.pi / 2, math.pi / 2 - 1e-9), jit(parts[1]).clamp(-1.5, 1.5),
                          parts[2], parts[3])
    f = irft.rft.forces(TRUTH, c)
    return c, f + 0.01 * f.abs().amax(0) * torch.randn(f.shape, generator=g)


def dem_like(T: int = 810, M: int = 5, seed: int = 0):
    """A plate at 9 tilts x 6 directions (54 pairs), T samples of M segments at random depths."""
    g = torch.Generator().manual_seed(seed)
    betas = torch.linspace(-math.pi / 3, math.pi / 2 - 0.1, 9)
    gammas = torch.linspace(-math.pi / 2 + 0.1, math.pi / 2 - 0.1, 6)
    k = torch.arange(T) % 54
    b = betas[k // 6][:, None].expand(T, M).clone()
    gm = gammas[k % 6][:, None].expand(T, M).clone()
    w = torch.rand(T, 1, generator=g) * torch.linspace(0.5, 1.5, M)[None]
    c = irft.rft.Contacts(b, gm, -w, w)
    f = irft.rft.forces(TRUTH, c)
    return c, f + 0.02 * f.abs().amax(0) * torch.randn(f.shape, generator=g)


def varied_recording(T: int, seed: int = 0, M: int = 6):
    """T samples of short plate strokes (about 31 samples each), every stroke its own course and tilt sweep (the
    plate turns as it moves): a recording whose angle pairs are nearly all distinct. Forces from the calibration
    harness' held-out "sharp" medium (a stress map with short-lengthscale features) with 2 % noise."""
    from irft_torch.studies.calibration import medium

    g = torch.Generator().manual_seed(seed)
    n_strokes = max(1, round(T / 31))
    parts = []
    for i in range(n_strokes):
        n = T // n_strokes + (1 if i < T % n_strokes else 0)
        u = torch.rand(5, generator=g, dtype=torch.float64)
        course = [-math.pi / 2 + 0.3 + float(v) * (math.pi - 0.6) for v in u[:2]]
        path = irft.rft.course_path(course, 0.04, start=(0.0, -0.02 - 0.03 * float(u[4])),
                                    heading=[(float(u[2]) - 0.5) * 2.4, (float(u[3]) - 0.5) * 2.4], n_steps=n)
        parts.append(irft.rft.contacts(irft.rft.IToe(0.03, 0.02, n_segments=M), path))
    c = irft.rft.Contacts(*(torch.cat([getattr(p, k) for p in parts])
                            for k in ("beta", "gamma", "weight_x", "weight_z")))
    f = irft.rft.forces(medium("sharp", 0)[0], c)
    return c, f + 0.02 * f.abs().amax(0) * torch.randn(f.shape, generator=g, dtype=f.dtype)


def timed_fit(c, f, **options):
    """A default fit (``InverseRFT(c, f, **options).fit()``) with each Adam step timed: (steps (s,), whole fit in s
    (construction, Adam, the hyperparameter posterior), the model, warnings raised)."""
    import warnings
    from unittest import mock

    import irft_torch.gp.fit_control as front_door  # the fit loop (FitControl.run) makes its bar there

    marks: list[float] = []
    make_bar = front_door.progress_bar

    class TimedBar:  # the fit's own bar (silent), each step's start and the end marked
        def __init__(self, total, desc, enabled=True):
            self.bar = make_bar(total, desc, False)

        def __iter__(self):
            for i in self.bar:
                marks.append(time.perf_counter())
                yield i
            marks.append(time.perf_counter())

        def __getattr__(self, name):
            return getattr(self.bar, name)

    sync()
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught, mock.patch.object(front_door, "progress_bar", TimedBar):
        warnings.simplefilter("always")
        model = irft.InverseRFT(c, f, **options)
        model.fit()
    sync()
    whole = time.perf_counter() - t0
    steps = torch.tensor(marks).diff()
    return steps, whole, model, [str(w.message) for w in caught]


def varied_case(q: bool, row) -> None:
    """12. Varied recordings (issue 52): default fits of 1,000 and 10,000 samples of short plate strokes, each with
    its own tilt sweep; time of the first and last Adam steps (median of 5), the whole fit, the basis it ended in and
    the kernel's truncation error there; and the 1,000-sample default against the mode's fit alone."""
    sizes = (150,) if q else (1000, 10_000)  # --quick (the test suite): one size, the mode row beside it
    irft.InverseRFT(*on_device(*varied_recording(60, seed=1))).fit(n_iter=5, progress=False)  # one-time costs paid
    whole = {}
    for T in sizes:
        c, f = on_device(*varied_recording(T))
        steps, whole[T], model, said = timed_fit(c, f)
        first, last = steps[:5].median().item(), steps[-5:].median().item()
        row(f"12. varied recording, T = {T:,} samples of plate strokes x M = 6, default fit ({len(steps)} Adam steps; "
            f"ended in {model.backend.describe()})",
            f"{whole[T]:.1f} s; first steps {first * 1e3:.0f} ms, last {last * 1e3:.0f} ms (x{last / first:.1f}); "
            f"{len(said)} warnings", "no second engine yet" if T == sizes[0] else
            f"{sizes[0]:,} samples: {whole[sizes[0]]:.1f} s", "-" if T == sizes[0] else
            f"{whole[T] / whole[sizes[0]]:.1f}x", "< 60 s, last <= 3x first" if T == sizes[0] else "<= 10x")
        if T == sizes[0]:  # the same fit with the widest basis kept to the end (before SpectralBackend.shrink)
            from unittest import mock

            from irft_torch.gp.backends.spectral import SpectralBackend

            with mock.patch.object(SpectralBackend, "shrink", return_value=False):
                kept_steps, kept, kept_model, _ = timed_fit(c, f)
            k_last = kept_steps[-5:].median().item()
            row(f"12. the same {T:,} samples: the basis shrinking to what the lengthscales need, against the widest "
                f"kept to the end (ended in {kept_model.backend.describe()})",
                f"{whole[T]:.1f} s; last steps {last * 1e3:.0f} ms", f"kept {kept:.1f} s; last steps "
                f"{k_last * 1e3:.0f} ms (x{k_last / kept_steps[:5].median().item():.1f} the first)",
                f"{whole[T] / kept:.2f}x", "-")
        if T == sizes[0]:  # the hyperparameter posterior's cost here: the default against the mode's fit alone
            _, mode, plug_in, said_map = timed_fit(c, f, hyper_posterior="map")
            row(f"12. the same {T:,} samples: the default (Laplace) against the mode's fit (hyper_posterior='map', "
                f"ended in {plug_in.backend.describe()})", f"{whole[T]:.1f} s; {len(said)} warnings",
                f"mode only {mode:.1f} s; {len(said_map)} warnings", f"{whole[T] / mode:.1f}x", "<= 2x, no warning")
            from irft_torch.gp.hyper.density import draws_in_one_basis

            with draws_in_one_basis():  # the draws as before they were grouped: one basis grown for all of them
                _, one, _, said_one = timed_fit(c, f)
            row(f"12. the same {T:,} samples: the default, the draws each in the basis they need", f"{whole[T]:.1f} s",
                f"every draw in one basis grown for all {one:.1f} s; {len(said_one)} warnings",
                f"{one / whole[T]:.2f}x", "-")


def step(model) -> float:
    """One likelihood + gradient step as ``InverseRFT.fit`` takes it (closed form where the backend has
    one; inside ``autograd_only``, today's autograd step)."""
    model.train()
    for p in model.hypers.parameters():
        p.grad = None
    loss = model.backend.loss_and_grad()
    if loss is None:
        loss = model.loss()
        loss.backward()
        loss = loss.item()
    return loss


def fit_time(c, f, n: int, repeats: int, **options) -> tuple[float, irft.InverseRFT]:
    """Seconds per Adam step of ``InverseRFT(c, f, **options).fit(n)``, best of ``repeats`` fits, and the
    last model."""
    best = float("inf")
    for _ in range(repeats):
        model = irft.InverseRFT(c, f, **options)
        sync()
        t0 = time.perf_counter()
        model.fit(n_iter=n, progress=False)
        sync()
        best = min(best, (time.perf_counter() - t0) / n)
    return best, model


def dense_step(model, c, f) -> float:
    """The paper's formula: dense W (T x TM), dense K (TM x TM), per axis, Cholesky."""
    for p in model.hypers.parameters():
        p.grad = None
    ls, os, noise = model.hypers.lengthscale, model.hypers.outputscale, model.hypers.noise
    T, M = c.shape
    th_b, th_g = c.beta.reshape(-1), c.gamma.reshape(-1)
    phi = torch.stack([torch.sin(2 * th_b), torch.cos(2 * th_b), torch.sin(th_g), torch.cos(th_g)], -1)
    total = 0.0
    dev = c.beta.device
    rows = torch.arange(T, device=dev).repeat_interleave(M)
    cols = torch.arange(T * M, device=dev)
    for a, w in enumerate((c.weight_x, c.weight_z)):
        W = torch.zeros(T, T * M, device=dev)
        W[rows, cols] = w.reshape(-1)
        x = phi / ls[a, 0]
        K = os[a] * torch.exp(-0.5 * ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1))
        S = W @ K @ W.T + noise[a] * torch.eye(T, device=dev)
        L = torch.linalg.cholesky(S)
        y = f[:, a]
        alpha = torch.cholesky_solve(y[:, None], L)[:, 0]
        total = total + (0.5 * y @ alpha + torch.log(torch.diagonal(L)).sum() + 0.5 * T * math.log(2 * math.pi)) / T
    total.backward()
    return total.item()


def best_time(fn, repeats: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        best = min(best, time.perf_counter() - t0)
    return best


def ratio(r: float) -> str:
    return f"{r:.0f}x" if r >= 10 else f"{r:.2g}x"


def grid(n=50):
    g = torch.linspace(-1.5, 1.5, n, device=DEVICE)
    return torch.meshgrid(g, g, indexing="ij")


def big_child(T: int, n_iter: int) -> None:
    torch.set_default_dtype(torch.float64)
    gpu = DEVICE.type == "cuda"
    rss = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # noqa: E731  GB (Linux: KB)
    before = rss()
    c, f = on_device(*recording(T))
    with_data = rss()
    sync()
    t0 = time.perf_counter()
    model = irft.InverseRFT(c, f, **PLUG_IN)
    sync()
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    model.fit(n_iter=n_iter, progress=False)
    sync()
    t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    model.stress_map(*grid())
    sync()
    t_map = time.perf_counter() - t0
    print(json.dumps({"T": T, "backend": model.backend.describe(), "build_s": t_build, "fit_s": t_fit,
                      "map_s": t_map, "peak_gb": rss(), "import_gb": before, "data_gb": with_data - before,
                      "gpu_peak_gb": torch.cuda.max_memory_allocated() / 2**30 if gpu else 0.0}))


def fit_together_case(q: bool, row) -> None:
    """Case 7: several models on the same contacts (a noise study): gp.fit_together vs one by one."""
    from irft_torch.studies.reproduce import configuration

    toe, path = configuration("C-toe gait 1")
    c7 = irft.rft.contacts(toe, path)
    f7 = irft.rft.forces(TRUTH, c7)
    B7, n7 = (4, 40) if q else (8, 150)
    g7 = torch.Generator().manual_seed(7)
    sets = [f7 * (1 + 0.3 * i / B7 * torch.randn(f7.shape, generator=g7, dtype=f7.dtype)) for i in range(B7)]
    c7, sets = on_device(c7, torch.stack(sets))
    tied = {**PLUG_IN, "prior": irft.MapPrior(kernel="rbf", noise="tied")}
    alone = [irft.InverseRFT(c7, fs, **tied) for fs in sets]
    together = [irft.InverseRFT(c7, fs, **tied) for fs in sets]
    sync()
    t0 = time.perf_counter()
    for m in alone:
        m.fit(n_iter=n7, lr=0.1, progress=False)
    sync()
    t_alone = time.perf_counter() - t0
    t0 = time.perf_counter()
    irft.gp.fit_together(together, n_iter=n7, lr=0.1)
    sync()
    t_together = time.perf_counter() - t0
    diff = max(float(((x.hypers.outputscale - y.hypers.outputscale) / x.hypers.outputscale).abs().max().detach())
               for x, y in zip(alone, together))
    assert diff < 1e-6, diff
    row(f"7. {B7} models on the same contacts (C-toe gait 1, T = {len(c7)}, {n7} steps, {together[0].method}): "
        f"gp.fit_together", f"{t_together:.2f} s (outputscales equal to {diff:.0e})",
        f"InverseRFT.fit one by one {t_alone:.2f} s", ratio(t_alone / t_together), "-")


def hyper_posterior_case(q: bool, row, repeats: int = 3) -> None:
    """8. The default fit (``InverseRFT(c, f).fit()``: Li et al.'s term, Adam to near the mode, the Laplace
    hyperparameter posterior: polish, Hessian, 128 + 64 weighed proposals, 15 draw backends) against the former
    default, the plug-in RBF (``hyper_posterior="map", li_basis=False``), 300 steps each, best of ``repeats`` fits
    alternated, on paper-scale and DEM-like data (issue 51: <= 1.5x)."""
    from irft_torch.gp.hyper.density import draws_in_one_basis
    from irft_torch.studies.calibration import medium, motion, simulate

    n_iter = 60 if q else 300
    scoop = motion("turning", 0)  # the harness' turning scoop: the Laplace proposals' lengthscales reach 0.07
    scoop_forces = simulate(medium("scaled", 0)[0], scoop, 0.02, 0)
    for name, (c, f) in (("paper scale, C-toe T = 200 x M = 10", _paper_case(60 if q else 200)),
                         ("DEM-like, T = 810 x M = 5", dem_like()),
                         ("turning scoop, T = 150 x M = 12", (scoop, scoop_forces))):
        c, f = on_device(c, f)
        irft.InverseRFT(c, f).fit(n_iter=5, progress=False)  # warm: a process' first fit pays one-time costs
        times: dict[str, float] = {"default": math.inf, "plug-in": math.inf, "mode": math.inf, "one basis": math.inf}
        said = 0
        for _ in range(repeats):
            for label, opts in (("default", {}), ("plug-in", PLUG_IN), ("mode", {"hyper_posterior": "map"}),
                                ("one basis", {})):
                model = irft.InverseRFT(c, f, **opts)
                sync()
                t0 = time.perf_counter()
                with warnings.catch_warnings(record=True) as caught, (
                        draws_in_one_basis() if label == "one basis" else contextlib.nullcontext()):
                    warnings.simplefilter("always")
                    steps = len(model.fit(n_iter=n_iter, progress=False))
                sync()
                times[label] = min(times[label], time.perf_counter() - t0)
                if label == "default":
                    hpost, default_steps, kernel = model.hyper_posterior, steps, model.backend.describe()
                    said = max(said, len(caught))
        row(f"8. default fit, {name} ({kernel}): {default_steps} Adam steps + Laplace (ESS {hpost.ess:.0f} of "
            f"{hpost.n_proposals}, k-hat {hpost.khat:.2f}, {hpost.n_draws} draws)",
            f"{times['default']:.2f} s", f"the former default's plug-in fit {times['plug-in']:.2f} s",
            f"{times['default'] / times['plug-in']:.2f}x", "<= 1.5x")
        row(f"8. the same, the default against the mode's fit (Li et al.'s term, hyper_posterior='map'; {said} "
            f"warnings from the default)", f"{times['default']:.2f} s", f"the mode's fit {times['mode']:.2f} s",
            f"{times['default'] / times['mode']:.2f}x", "<= 2x, no warning" if "scoop" in name else "-")
        row("8. the same, the draws each in the basis they need (beyond 30 harmonics, or where cheaper: the exact "
            "pairs space)",
            f"{times['default']:.2f} s", f"every draw in one basis grown for all (truncated at 30 harmonics) "
            f"{times['one basis']:.2f} s", f"{times['one basis'] / times['default']:.2f}x", "-")


def turning_case(q: bool, row) -> None:
    """10. Adam steps of the default fit on a turning C-toe (the calibration harness' motion, T = 200 x 12),
    best of 3, closed form vs autograd."""
    from irft_torch.studies.calibration import _rng, _turning, medium, simulate

    T = 80 if q else 200
    c = _turning(_rng("motion", "turning", 0), T)
    truth, _ = medium("perturbed", 0)
    c, f = on_device(c, simulate(truth, c, 0.02, 0))
    n = 20 if q else 60
    t_new, model = fit_time(c, f, n, 3, **PLUG_IN)
    with autograd_only():
        t_old, _ = fit_time(c, f, n, 3, **PLUG_IN)
    row(f"10. turning C-toe T = {T} x M = 12, Adam ({model.backend.describe()} after {n} steps; best of 3)",
        f"{t_new * 1e3:.2f} ms/step", f"today's engine (autograd) {t_old * 1e3:.2f} ms/step", ratio(t_old / t_new),
        "< 3.3 ms/step")


def nuts_case(q: bool, row) -> None:
    """11. NUTS (pyro) on the hyperparameters of C-toe gait 2 (the paper study's configuration: tied noise,
    5 % relative force noise): 4 chains x 500 draws after 500 warm-up, each from the polished mode with the
    Laplace covariance as its metric, the chains in worker processes (one per core); a short chain in one
    process, both engines, gives the ratio (today's engine, autograd and pyro's diagonal metric from the
    fitted point, takes minutes for the full run)."""
    try:
        import pyro  # noqa: F401
    except ImportError:
        row("11. NUTS", "skipped: pyro not installed", "-", "-", "< 60 s")
        return
    from irft_torch.gp.hyper.nuts import nuts
    from irft_torch.studies.reproduce import configuration

    toe, path = configuration("C-toe gait 2")
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(TRUTH, c)
    f = f * (1 + math.sqrt(0.05) * torch.randn(f.shape, generator=torch.Generator().manual_seed(0), dtype=f.dtype))
    c, f = on_device(c, f)
    model = irft.InverseRFT(c, f, **{**PLUG_IN, "prior": irft.MapPrior(kernel="rbf", noise="tied")})
    model.fit(n_iter=300, progress=False)
    short = (10, 10) if q else (50, 50)
    times = {}
    for engine in ("new", "old"):  # today's engine: autograd, pyro's diagonal metric from the fitted point
        with autograd_only() if engine == "old" else contextlib.nullcontext():
            t0 = time.perf_counter()
            nuts(model.backend, n_samples=short[1], warmup=short[0], num_chains=1, seed=1, processes=1,
                 metric="laplace" if engine == "new" else "diagonal")
            times[engine] = time.perf_counter() - t0
    chains, draws = (2, 20) if q else (4, 500)
    procs = min(chains, os.cpu_count() or 1)
    t0 = time.perf_counter()
    hp = nuts(model.backend, n_samples=draws, warmup=draws, num_chains=chains, processes=procs)
    t_full = time.perf_counter() - t0
    per_draw = sum(hp.extra["gradient_evaluations"]) / (chains * 2 * draws)
    row(f"11. NUTS on C-toe gait 2 ({model.method}, {len(hp.labels)} hyperparameters): {chains} chains x {draws} "
        f"draws after {draws} warm-up, Laplace metric, {procs} processes (ESS {hp.ess:.0f}, {per_draw:.1f} "
        f"gradients per iteration)", f"{t_full:.1f} s",
        f"one chain of {sum(short)} iterations: {times['new']:.1f} s, today's engine {times['old']:.1f} s",
        ratio(times["old"] / times["new"]), "< 60 s")


def _paper_case(T: int):
    c = paper_contacts(T)
    f = irft.rft.forces(TRUTH, c)
    return c, f + 0.01 * f.abs().amax(0) * torch.randn(f.shape, generator=torch.Generator().manual_seed(1))


def _same_hypers(dst, src):
    """dst's hyperparameters set to src's values (their raw values are in each model's own data scales)."""
    with torch.no_grad():
        h, k = dst.hypers, src.hypers
        h.lengthscale, h.outputscale, h.noise = k.lengthscale.detach(), k.outputscale.detach(), k.noise.detach()
    return dst


def backend_steps_case(q: bool, row, repeats: int) -> None:
    """2b. Like for like: one likelihood + gradient step (no optimiser, no fit bookkeeping) in each
    backend on the same data, DEM-like and paper scale: which space is fastest on this device."""
    cases = (("DEM-like, T = 810 x M = 5", dem_like()), ("paper scale, C-toe T = 200 x M = 10", _paper_case(
        60 if q else 200)))
    for name, (c, f) in cases:
        c, f = on_device(c, f)
        times = {}
        for method in ("observations", "pairs", "spectral"):
            m = irft.InverseRFT(c, f, engine=method, **PLUG_IN)
            times[method] = best_time(lambda: step(m), max(2, repeats))
        auto = irft.InverseRFT(c, f, **PLUG_IN).method
        row(f"2b. {name}: one likelihood + gradient step per backend (auto picks {auto})",
            f"pairs {times['pairs'] * 1e3:.2f} ms, spectral {times['spectral'] * 1e3:.2f} ms",
            f"observations {times['observations'] * 1e3:.2f} ms",
            f"{times['observations'] / times['pairs']:.2f}x, {times['observations'] / times['spectral']:.2f}x",
            "pairs and spectral >= 1x on a GPU")


def terrain_filter_case(q: bool, row, n_ref: int = 8) -> None:
    """9. B parallel environments, one sample and a 16-point map query each per step: ``TerrainFilter``
    vs a loop over one ``InverseRFT`` per environment (timed on ``n_ref`` of them, per env-step)."""
    B, steps = (256, 8) if q else (4096, 20)
    c = paper_contacts(1000)
    f = irft.rft.forces(TRUTH, c)
    f = f + 0.01 * f.abs().amax(0) * torch.randn(f.shape, generator=torch.Generator().manual_seed(9))
    c, f = on_device(c, f)
    model = irft.InverseRFT(c[::10], f[::10], **PLUG_IN)
    model.fit(n_iter=30 if q else 100, progress=False)
    g = torch.Generator().manual_seed(5)
    e = torch.linspace(-1.2, 1.2, 4, device=DEVICE)
    bq, gq = e.repeat_interleave(4), e.repeat(4)  # 16 map points
    for window, dtype, li in ((8, torch.float64, False), (16, torch.float64, False), (32, torch.float64, False),
                              (16, torch.float32, False), (16, torch.float64, True)):
        prior = irft.MapPrior(kernel="li" if li else "rbf")
        m = model if dtype == torch.float64 and not li else irft.InverseRFT(c[::10], f[::10], prior=prior,
                                                                            engine=irft.Engine(dtype=dtype),
                                                                            hyper_posterior="map")
        if m is not model:
            _same_hypers(m, model)
        if li:  # Li et al.'s term at the outputscale's size (its cost, not its fit)
            m.hypers.li.variance = model.hypers.outputscale.detach()
        filt = irft.TerrainFilter(m, B, window=window)
        warm = window + 3  # fill the window, then a few full-window steps: their first calls (kernels, handles) untimed
        idx = torch.randint(0, len(c), (warm + steps, B), generator=g).to(DEVICE)
        cs, fs = [c[i] for i in idx], [f[i] for i in idx]

        def step(t):
            filt.update(cs[t], fs[t])
            return filt.stress_map(bq, gq)

        for t in range(warm):  # the steady state: a full window
            step(t)
        sync()
        t0 = time.perf_counter()
        for t in range(warm, warm + steps):
            step(t)
        sync()
        rate = B * steps / (time.perf_counter() - t0)
        if window == 16 and dtype == torch.float64 and not li:  # the reference: one InverseRFT per environment
            refs = []
            for b in range(n_ref):
                r = irft.InverseRFT(irft.rft.Contacts.cat([x[b:b + 1] for x in cs[:window]]),
                                    torch.stack([x[b] for x in fs[:window]]), engine="observations", **PLUG_IN)
                refs.append(_same_hypers(r, model))
            for r in refs:  # warm: the first query builds the factor
                r.stress_map(bq, gq)
            sync()
            t0 = time.perf_counter()
            for t in range(window, window + 3):
                for b, r in enumerate(refs):
                    r.add_data(cs[t][b:b + 1], fs[t][b:b + 1])
                    r.stress_map(bq, gq)
            sync()
            ref_rate = n_ref * 3 / (time.perf_counter() - t0)  # (each equals its filter: tests/gp/test_terrain_filter)
        dt = "float32" if dtype == torch.float32 else "float64"
        if window == 16 and dtype == torch.float64 and not li:
            planar_rate = rate
        if li:
            row(f"9. the same, window {window}, {dt}, li_basis=True", f"{rate:,.0f} env-steps/s", "-",
                ratio(rate / ref_rate), ">= 1e5 env-steps/s")
        elif window == 16 and dtype == torch.float64:
            row(f"9. parallel environments: TerrainFilter, B = {B}, M = 10, window {window}, {dt}: one update + a "
                f"16-point map query per step", f"{rate:,.0f} env-steps/s",
                f"a loop over InverseRFT (add_data + stress_map; {n_ref} environments timed, scaled) "
                f"{ref_rate:,.1f} env-steps/s", ratio(rate / ref_rate), ">= 1e5 env-steps/s, >= 100x")
        else:
            row(f"9. the same, window {window}, {dt}", f"{rate:,.0f} env-steps/s", "-",
                ratio(rate / ref_rate) if window != 8 else "-", ">= 1e5 env-steps/s")
    # over the ground: a spatial model's filter, each sample at its environment's foothold (a random walk, m)
    places = torch.rand(len(c[::10]), 2, generator=g, dtype=torch.float64).to(DEVICE) * 3.0
    spatial = _same_hypers(irft.InverseRFT(c[::10], f[::10], locations=places, **PLUG_IN), model)
    filt_s = irft.TerrainFilter(spatial, B, window=16)
    idx = torch.randint(0, len(c), (19 + steps, B), generator=g).to(DEVICE)
    cs, fs = [c[i] for i in idx], [f[i] for i in idx]
    walk = (torch.rand(B, 2, generator=g, dtype=torch.float64) * 3.0).to(DEVICE)
    steps_s = [walk + 0.2 * t * torch.tensor([1.0, 0.0], dtype=torch.float64, device=DEVICE)
               for t in range(19 + steps)]
    here = steps_s[-1][:, None]  # (B, 1, 2): each environment's place at the end of the timed steps

    def step_s(t):
        filt_s.update(cs[t], fs[t], locations=steps_s[t])
        return filt_s.stress_map(bq, gq, locations=here)

    for t in range(19):
        step_s(t)
    sync()
    t0 = time.perf_counter()
    for t in range(19, 19 + steps):
        step_s(t)
    sync()
    rate_s = B * steps / (time.perf_counter() - t0)
    row("9. over the ground: a spatial model's TerrainFilter, window 16, float64 (each sample at its environment's "
        "foothold, the map asked at one place each)", f"{rate_s:,.0f} env-steps/s",
        f"the planar filter, window 16: {planar_rate:,.0f} env-steps/s", ratio(rate_s / planar_rate), "-")
    # a hyperparameter posterior's draws, each environment its own mixture (S filters)
    mixed = irft.InverseRFT(c[::10], f[::10], hyper_posterior="laplace", prior=irft.MapPrior(kernel="rbf"))
    torch.manual_seed(0)
    mixed.fit(n_iter=30 if q else 100, progress=False)
    filt_m = irft.gp.TerrainFilterMixture(mixed, B, window=16)
    idx = torch.randint(0, len(c), (19 + steps, B), generator=g).to(DEVICE)
    cs, fs = [c[i] for i in idx], [f[i] for i in idx]
    for t in range(19):
        filt_m.update(cs[t], fs[t])
        filt_m.stress_map(bq, gq)
    sync()
    t0 = time.perf_counter()
    for t in range(19, 19 + steps):
        filt_m.update(cs[t], fs[t])
        filt_m.stress_map(bq, gq)
    sync()
    rate_m = B * steps / (time.perf_counter() - t0)
    row(f"9. TerrainFilterMixture over {filt_m.n_draws} Laplace draws, window 16, float64 (each environment its own "
        "mixture)", f"{rate_m:,.0f} env-steps/s", "-", ratio(rate_m / ref_rate), ">= 1e5 env-steps/s")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (seconds; for tests)")
    ap.add_argument("--out", default="experiments/results")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu", help="cpu (default) or cuda: data, model and references there")
    ap.add_argument("--only", default="", help="comma-separated case numbers to run (default: all), e.g. 1,2,8,10")
    ap.add_argument("--wheel-data", type=Path, default=None,
                    help="the rover-wheel data folder, for case 13 (the 3-D wheel fold; skipped without it)")
    ap.add_argument("--before-tree", default=None,
                    help="case 13: a checkout of the commit before e2da7f5 to time as the reference (else emulated)")
    ap.add_argument("--_child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--_iters", type=int, default=100, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    global DEVICE
    DEVICE = torch.device(a.device)
    if a._child:
        return big_child(a._child, a._iters)
    torch.set_default_dtype(torch.float64)
    q = a.quick
    only = {int(x) for x in a.only.split(",") if x.strip()}

    def want(k: int) -> bool:
        return not only or k in only
    lines = [f"# Inference benchmarks (`python experiments/benchmarks/bench_inference.py"
             f"{' --quick' if q else ''}`)", "",
             f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64, device "
             f"{torch.cuda.get_device_name() if DEVICE.type == 'cuda' else 'cpu'}.", "",
             "| case | ours | reference (same run) | ratio | target |", "|---|---|---|---|---|"]

    def row(*cells):
        lines.append("| " + " | ".join(cells) + " |")
        print("  ".join(cells), flush=True)

    if want(1):
        # 1. paper scale
        T1 = 60 if q else 200
        c = paper_contacts(T1)
        f = irft.rft.forces(TRUTH, c)
        f = f + 0.01 * f.abs().amax(0) * torch.randn(f.shape, generator=torch.Generator().manual_seed(1))
        c, f = on_device(c, f)
        # the dense formula is the plain marginal likelihood
        model = irft.InverseRFT(c, f, **{**PLUG_IN, "prior": irft.MapPrior(kernel="rbf", hyperpriors=None)})
        ours, ref = step(model), dense_step(model, c, f)
        assert abs(ours - ref) <= 1e-6 * abs(ref), (ours, ref)
        t_ours = best_time(lambda: step(model), a.repeats)
        with autograd_only():
            t_autograd = best_time(lambda: step(model), a.repeats)
        t_dense = best_time(lambda: dense_step(model, c, f), max(1, a.repeats // 2))
        row(f"1. paper scale, C-toe T = {T1} x M = 10, one likelihood + gradient step ({model.method})",
            f"{t_ours * 1e3:.2f} ms (autograd {t_autograd * 1e3:.2f} ms)", f"dense formula {t_dense * 1e3:.1f} ms",
            ratio(t_dense / t_ours), ">= 100x")

    if want(2):
        # 2. DEM-like: Adam steps of the default fit, best of 3 x 60 (issue 30's protocol), both engines
        c, f = on_device(*dem_like())
        n = 20 if q else 60
        t_new, model = fit_time(c, f, n, 3, **PLUG_IN)
        with autograd_only():
            t_old, _ = fit_time(c, f, n, 3, **PLUG_IN)
        obs = irft.InverseRFT(c, f, engine="observations", **PLUG_IN)
        with autograd_only():
            t_obs = best_time(lambda: step(obs), 2)
        row(f"2. DEM-like, T = 810 x M = 5, 54 distinct pairs, Adam ({model.method}, best of 3 x {n} steps)",
            f"{1 / t_new:.0f} steps/s ({t_new * 1e3:.2f} ms/step)",
            f"today's engine (autograd) {1 / t_old:.0f} steps/s ({t_old * 1e3:.2f} ms); observations backend "
            f"{1 / t_obs:.1f} steps/s", f"{ratio(t_old / t_new)} (vs observations {ratio(t_obs / t_new)})",
            "< 1 ms/step; >= 50 steps/s")
        backend_steps_case(q, row, a.repeats)

    if want(3):
        # 3. T = 10^4
        T3 = 2000 if q else 10_000
        c, f = on_device(*recording(T3))
        sync()
        t0 = time.perf_counter()
        model = irft.InverseRFT(c, f, **PLUG_IN)
        model.fit(n_iter=300, progress=False)
        model.stress_map(*grid())
        sync()
        t3 = time.perf_counter() - t0
        ref = irft.InverseRFT(c[:1000], f[:1000], engine="observations", **PLUG_IN)
        t_ref = best_time(lambda: step(ref), 1)
        row(f"3. C-toe T = {T3} x M = 10 (all pairs distinct): build + 300 steps + 50 x 50 map ({model.method}, "
            f"F = {getattr(model.backend, 'basis', None) and model.backend.basis.size})", f"{t3:.1f} s",
            f"one observations step at T = 1,000: {t_ref:.2f} s", f"{t_ref * 300 / t3:.0f}x (vs 300 such steps)",
            "<= 60 s")

    if want(4):
        # 4. 10^6 (a fresh process)
        T4 = 50_000 if q else 1_000_000
        out = subprocess.run([sys.executable, __file__, "--_child", str(T4), "--_iters", "100", "--device", a.device],
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        total = r["build_s"] + r["fit_s"] + r["map_s"]
        row(f"4. T = {T4:,} x M = 10: one pass + 100 steps + map ({r['backend']})",
            f"{total:.1f} s (pass {r['build_s']:.1f}, fit {r['fit_s']:.1f}, map {r['map_s']:.2f}); "
            f"peak {r['peak_gb']:.2f} GB", f"import {r['import_gb']:.2f} GB, the recording itself "
            f"{r['data_gb']:.2f} GB" + (f"; GPU peak {r['gpu_peak_gb']:.2f} GB" if r["gpu_peak_gb"] else ""),
            "-", "<= 20 s, peak < 2 GB")

    if want(5):
        # 5. streaming
        T5 = 2000 if q else 10_000
        c, f = on_device(*recording(T5 + 2000, seed=3))
        model = irft.InverseRFT(c[:T5], f[:T5], engine="spectral", **PLUG_IN)
        sync()
        t0 = time.perf_counter()
        for i in range(T5, T5 + 2000, 100):
            model.add_data(c[i:i + 100], f[i:i + 100])
        z = torch.zeros(1, device=DEVICE)
        model.stress_map(z, z)
        sync()
        per = (time.perf_counter() - t0) / 2000
        t_step = best_time(lambda: step(model), 1)
        row("5. streaming: add_data in batches of 100 samples, then a map query", f"{per * 1e3:.3f} ms/sample",
            f"one Adam step {t_step * 1e3:.1f} ms", "-", "<= 0.1 ms/sample")
    out_dir = Path(a.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    report = out_dir / ("benchmarks.md" if DEVICE.type == "cpu" else f"benchmarks_{DEVICE.type}.md")
    if DEVICE.type != "cpu":  # case 6 reduces files in CPU worker processes
        if want(7):
            fit_together_case(q, row)
        if want(9):
            terrain_filter_case(q, row)
        report.write_text("\n".join(lines) + "\n")
        print(f"wrote {report}")
        return
    if want(6):
        # 6. a fleet of datasets
        import tempfile

        from irft_torch.cli.fit import _reduce_statistics
        from irft_torch.data import Dataset, save_dataset
        from irft_torch.gp.statistics import initial_basis, recording_statistics, statistics_arrays

        T6 = 20_000 if q else 250_000
        basis = initial_basis()
        with tempfile.TemporaryDirectory() as tmp:
            plain, saved = [], []
            for i in range(4):
                c, f = recording(T6, seed=10 + i)
                ds = Dataset(c, f, torch.arange(T6, dtype=torch.float64), torch.zeros(T6, 2))
                plain.append(save_dataset(Path(tmp) / f"plain{i}.npz", ds))
                ds.statistics = statistics_arrays(recording_statistics(c, f, basis), c, f)
                saved.append(save_dataset(Path(tmp) / f"saved{i}.npz", ds))
            times = {}
            for name, paths, jobs in (("one process", plain, 1), ("2 workers", plain, 2), ("saved", saved, 1)):
                t0 = time.perf_counter()
                _reduce_statistics(paths, basis, jobs=jobs)
                times[name] = time.perf_counter() - t0
            try:  # the same reduction on a local Dask cluster of 2 worker processes, started and stopped
                from irft_torch.studies.fleet import reduce_on_dask

                times["dask"] = reduce_on_dask(plain, basis, n_workers=2).seconds
            except ImportError:
                times["dask"] = None
        dask = "not installed" if times["dask"] is None else f"{times['dask']:.1f} s"
        row(f"6. fleet: 4 datasets x {T6:,} samples x M = 10 -> spectral statistics ({basis.size} features)",
            f"2 worker processes {times['2 workers']:.1f} s; on Dask (LocalCluster, 2 worker processes, start-up "
            f"included) {dask}; saved with the datasets {times['saved']:.1f} s",
            f"one process, every pass {times['one process']:.1f} s",
            f"{times['one process'] / times['2 workers']:.1f}x; "
            + ("" if times["dask"] is None else f"Dask / pool {times['dask'] / times['2 workers']:.2f}; ")
            + f"{times['one process'] / times['saved']:.1f}x", "Dask not slower than the pool")
    for k, case in ((7, fit_together_case), (8, hyper_posterior_case), (9, terrain_filter_case), (10, turning_case),
                    (11, nuts_case), (12, varied_case)):
        if want(k):
            case(q, row)
    if want(13) and not q:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_wheel3d import wheel_fold_case

        wheel_fold_case(a.wheel_data, row, a.before_tree)
    report.write_text("\n".join(lines) + "\n")
    print(f"wrote {report}")


if __name__ == "__main__":
    main()
