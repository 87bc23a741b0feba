"""What issue 34's fixes cost or save, each against a reference measured in the same run.

Data: simulated (the simulated leg on a virtual CAN bus). Run time: 53 s as a whole (2 cores, 2026-12-03); its record,
ingest, fit loop 27.6 s and predict_forces at T = 10^6 14.7 s (docs/faults.md, 2026-11-26).

    python experiments/benchmarks/bench_faults.py [--quick] [--out experiments/results]

1. The loop docs/real_leg.md tells a newcomer to try first, with every default: ``irft record
   --simulate`` (a noise-free simulated leg, 21.7 s at 200 Hz), ``irft ingest`` (with its air run),
   ``irft fit`` (300 steps), each a fresh process as a user runs them; wall time of each. Then the
   same dataset's fit in steps of 30: the last 30 steps' time over the first 30's (was 30x: at ~step
   270 ``method="auto"`` moved to the observations space at T = 4344 when the noise collapsed).
2. ``predict_forces`` at T = 10^6 (the paper's C-toe gait tiled, M = 10) in a fresh process: peak
   resident memory in pieces (the default) and in one pass (the reference, at T = 10^5 and scaled).
Writes bench_faults.md under --out.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PREDICT = r"""
import json, resource, sys, time, torch
torch.set_default_dtype(torch.float64)
import irft_torch as irft
from irft_torch.gp import model as model_module
T, chunked = int(sys.argv[1]), sys.argv[2] == "1"
c = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.spline_path(
    [(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=200))
f = irft.rft.forces(irft.rft.FourierStressMap.generic(), c)
m = irft.InverseRFT(c, f, hyper_posterior="map", prior=irft.MapPrior(kernel="rbf"))
m.fit(20, progress=False)
big = irft.rft.Contacts(*(v.repeat((T + 199) // 200, 1)[:T] for v in c.as_dict().values()))
if not chunked:
    model_module._predict_chunk = lambda backend: 1 << 40
data = sum(v.numel() * 8 for v in big.as_dict().values())
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
t0 = time.perf_counter()
p = m.predict_forces(big)
took = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"T": T, "method": m.method, "data_bytes": data, "before": before, "peak": peak, "seconds": took,
                  "finite": bool(torch.isfinite(p.mean).all())}))
"""


def _irft(*args, cwd) -> float:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "irft_torch.cli", *args], cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"irft {' '.join(args)} failed: {r.stderr[-2000:]}")
    return time.perf_counter() - t0


def pipeline(folder: Path, quick: bool) -> dict:
    import torch

    import irft_torch as irft

    speed = ["--speed", "0.1"] if quick else []
    out = {"record": _irft("record", "--simulate", "--out", "trial.log", *speed, cwd=folder)}
    out["ingest"] = _irft("ingest", "trial.log", "--air", "trial_air.log", "--out", "ds.npz", cwd=folder)
    out["fit"] = _irft("fit", "ds.npz", "--out", "fit", "--no-progress", cwd=folder)
    torch.set_default_dtype(torch.float64)
    ds = irft.data.load_dataset(folder / "ds.npz")
    model = irft.InverseRFT(ds.contacts, ds.forces, hyper_posterior="map", prior=irft.MapPrior(kernel="rbf"))
    chunks = []
    for _ in range(10):
        t0 = time.perf_counter()
        model.fit(30, progress=False)
        chunks.append(time.perf_counter() - t0)
    out.update(samples=len(ds), chunks=chunks, backend=model.backend.describe())
    return out


def predict(T: int, chunked: bool) -> dict:
    r = subprocess.run([sys.executable, "-c", PREDICT, str(T), "1" if chunked else "0"], capture_output=True,
                       text=True)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-2000:])
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a 4 s simulated run, T = 10^5 predictions")
    ap.add_argument("--out", default="experiments/results")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        p = pipeline(Path(tmp), a.quick)
    T = 100_000 if a.quick else 1_000_000
    chunked, whole = predict(T, True), predict(T // 10, False)
    gb = 1024**3
    lines = [
        "# Issue 34's fixes: costs against references from the same run (experiments/benchmarks/bench_faults.py)", "",
        f"`python experiments/benchmarks/bench_faults.py{' --quick' if a.quick else ''}`", "",
        "## The simulated leg with every default", "",
        f"`irft record --simulate`: {p['record']:.1f} s; `irft ingest`: {p['ingest']:.1f} s ({p['samples']} samples); "
        f"`irft fit`: {p['fit']:.1f} s; in all {p['record'] + p['ingest'] + p['fit']:.1f} s.", "",
        f"The same fit in steps of 30 ({p['backend']} at the end): "
        + ", ".join(f"{c:.2f}" for c in p["chunks"]) + " s; the last 30 steps took "
        f"{p['chunks'][-1] / p['chunks'][0]:.2f}x the first 30.", "",
        f"## predict_forces at T = {T:,}", "",
        f"In pieces (the default, {chunked['method']} backend): peak resident memory {chunked['peak'] / gb:.2f} GB "
        f"(the contacts alone {chunked['data_bytes'] / gb:.2f} GB, {chunked['before'] / gb:.2f} GB before the call), "
        f"{chunked['seconds']:.1f} s. In one pass at T = {T // 10:,}: {whole['peak'] / gb:.2f} GB peak "
        f"({(whole['peak'] - whole['before']) / gb:.2f} GB for the call, about "
        f"{10 * (whole['peak'] - whole['before']) / gb:.1f} GB at T = {T:,}).", ""]
    text = "\n".join(lines)
    print(text)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_faults.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
