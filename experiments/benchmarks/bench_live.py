"""The live estimator's latency and throughput (hardware.LiveEstimator), on this machine.

Data: the simulated leg walking on python-can's virtual bus. Run time: about 100 s with the
defaults (2 cores, 2026-12-03).

1. Latency, end of stance -> updated estimate: a model holding ``--history`` stances (1,000 by default:
   ~150,000 force samples) is streamed the stances of the simulated leg walking in real time on python-can's
   virtual bus (2 motors x 1 kHz, encoder + current each: 4,000 frames/s); per stance, the wall-clock time
   from the arrival of the frames that closed it to the published estimate (p50, p99), and the part of it
   spent on the stance itself (contacts, checks, residual, add_data, map summary).
2. Sustained frame rate: the same walk sent as fast as the virtual bus takes it; the rate at which the
   estimator's worker gets through the frames (stances included) is what it sustains before its queue grows.

The walking leg runs in the same process (the virtual bus is in-process): it takes a share of the GIL a
robot's controllers would not. A benchmark, not a test (timings depend on the machine and its load).

3. Against the offline path: ``--offline-strides`` (200) strides from a start model in real time, then the log
   it wrote through ``read_log`` -> ``resample`` -> ``forces_from_log`` -> ``zero_phase_filter`` ->
   ``build_dataset`` and ``add_data`` into the same start model: the largest difference of the maps.

    python experiments/benchmarks/bench_live.py [--history 1000] [--strides 40] [--priors physical|none]
                                     [--out experiments/results/bench_live.json]
"""

from __future__ import annotations

import argparse
import json
import time
import uuid
from pathlib import Path

import can
import numpy as np
import torch

import irft_torch as irft
from irft_torch.gp import InverseRFT, MapPrior
from irft_torch.hardware import LiveEstimator, WalkingLeg

TOE = irft.rft.CToe(0.02, 0.008, n_segments=10)
SAND = irft.rft.FourierStressMap.generic(1.0, 1.5)


def history_model(leg: WalkingLeg, n_stances: int, seed: int = 0, priors: str | None = "physical") -> InverseRFT:
    """A model fitted on 3 stances, then given ``n_stances`` more by add_data (the live path's history)."""
    rng = torch.Generator().manual_seed(seed)
    parts = []
    for k in range(len(leg.depths)):
        truth = leg.stride_truth(k)
        path = irft.rft.pose_path(torch.as_tensor(truth.time), torch.as_tensor(truth.toe[:, 0]),
                                  torch.as_tensor(truth.toe[:, 1] + leg.hip_height))
        c = irft.rft.contacts(TOE, path)
        keep = (c.weight_z != 0).any(-1)
        parts.append((irft.rft.Contacts(*(v[keep] for v in c.as_dict().values())), irft.rft.forces(SAND, c)[keep]))

    def noisy(k):
        c, f = parts[k % len(parts)]
        return c, f + 0.02 * torch.randn(f.shape, generator=rng)

    first = [noisy(k) for k in range(3)]
    c0 = irft.rft.Contacts(*(torch.cat(v) for v in zip(*(c.as_dict().values() for c, _ in first))))
    model = InverseRFT(c0, torch.cat([f for _, f in first]), hyper_posterior="map", prior=MapPrior(hyperpriors=priors),
                       engine="spectral")
    model.fit(100, progress=False)
    if n_stances:
        more = [noisy(k) for k in range(n_stances)]
        c1 = irft.rft.Contacts(*(torch.cat(v) for v in zip(*(c.as_dict().values() for c, _ in more))))
        model.add_data(c1, torch.cat([f for _, f in more]))
    return model


def walk(model, strides: int, realtime: bool, out_dir: Path | None, keep: bool = False) -> dict:
    leg = WalkingLeg(TOE, SAND, current_noise=0.05)
    channel = f"bench-live-{uuid.uuid4().hex}-bus"
    bus = can.Bus(channel=channel, interface="virtual")
    est = LiveEstimator(bus, leg.leg, leg.motors, TOE, leg.hip_height, model=model, firmware=leg.firmware,
                        out_dir=out_dir, stale_after=5.0, snapshot_period=1e9)
    t0 = time.monotonic()
    with est:
        leg.walk(channel, strides, realtime=realtime)
        sent = time.monotonic()
        est.drain(timeout=600)
        done = time.monotonic()
    bus.shutdown()
    lat, comp = np.asarray(est.latencies), np.asarray(est.compute_times)
    return {"strides": strides, "realtime": realtime, "frames_sent": leg.frames_sent,
            "frames_received": est.intake.received, "frames_logged": est.intake.logged,
            "frames_dropped": est.intake.dropped, "queue_high_water": est.intake.high_water,
            "stances": est.n_stances, "updates": est.n_updates, "unused": est.unused,
            "send_s": sent - t0, "total_s": done - t0, "frames_per_s_processed": leg.frames_sent / (done - t0),
            "latency_ms": {"p50": 1e3 * float(np.percentile(lat, 50)), "p99": 1e3 * float(np.percentile(lat, 99)),
                           "max": 1e3 * float(lat.max())} if len(lat) else None,
            "stance_compute_ms": {"p50": 1e3 * float(np.percentile(comp, 50)),
                                  "p99": 1e3 * float(np.percentile(comp, 99))} if len(comp) else None,
            **({"estimator": est} if keep else {})}


def against_offline(strides: int, out_dir: Path) -> dict:
    """``strides`` strides in real time from a start model; then the log it wrote through the offline path
    (read_log -> resample at the live rate -> forces_from_log -> zero_phase_filter -> build_dataset) and
    add_data into the same start model: the largest difference of the two maps' means and stds."""
    from irft_torch.hardware import build_dataset, forces_from_log, read_log, zero_phase_filter
    from irft_torch.hardware.live import MAP_POINTS

    leg = WalkingLeg(TOE, SAND, current_noise=0.05)
    start = history_model(leg, 0)
    start.save(out_dir / "start.pt")
    live = walk(InverseRFT.load(out_dir / "start.pt"), strides, True, out_dir, keep=True)
    est = live.pop("estimator")
    log = read_log(out_dir / "frames.blf", firmware=leg.firmware)
    trace = zero_phase_filter(forces_from_log(log.resample((0, 1), rate=leg.rate), leg.leg, leg.motors), 5)
    ds = build_dataset(trace, leg.leg, TOE, leg.hip_height)
    offline = InverseRFT.load(out_dir / "start.pt").add_data(ds.contacts, ds.forces)
    b, g = torch.as_tensor(MAP_POINTS[:, 0]), torch.as_tensor(MAP_POINTS[:, 1])
    with torch.no_grad():
        a, o = est.model.stress_map(b, g), offline.stress_map(b, g)
    return {**live, "frames_in_log": log.n_frames,
            "map_mean_max_abs_diff": float((a.mean - o.mean).abs().max()),
            "map_mean_max_abs": float(o.mean.abs().max()),
            "map_std_max_rel_diff": float(((a.variance.sqrt() - o.variance.sqrt()) / o.variance.sqrt()).abs().max()),
            "scale": est.last.scale, "scale_std": est.last.scale_std}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--history", type=int, default=1000, help="stances the model holds before the walk")
    ap.add_argument("--strides", type=int, default=40, help="strides walked in real time (0.3 s each)")
    ap.add_argument("--flood-strides", type=int, default=40, help="strides sent as fast as the bus takes them")
    ap.add_argument("--priors", choices=["physical", "none"], default="physical",
                    help="the model's hyperparameter priors (physical: add_data updates their centres from running "
                         "sums, O(new samples) per stance)")
    ap.add_argument("--offline-strides", type=int, default=200,
                    help="strides walked in real time and compared with the offline path of their log (0: skip)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1: the other core for the bus)")
    ap.add_argument("--out", default="experiments/results/bench_live.json")
    a = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(a.threads)
    leg = WalkingLeg(TOE, SAND)
    t = time.monotonic()
    priors = None if a.priors == "none" else "physical"
    model = history_model(leg, a.history, priors=priors)
    built = time.monotonic() - t
    n = len(model.train_forces)
    print(f"model: {a.history} stances of history + 3, {n} samples, {model.backend.describe()} ({built:.1f} s)")
    results = {"history_stances": a.history, "history_samples": n, "torch_threads": a.threads, "priors": a.priors}
    results["realtime"] = walk(model, a.strides, True, None)
    print("real time:", json.dumps(results["realtime"]))
    flood = history_model(leg, a.history, priors=priors)
    results["flood"] = walk(flood, a.flood_strides, False, None)
    print("flood:", json.dumps(results["flood"]))
    if a.offline_strides:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            results["against_offline"] = against_offline(a.offline_strides, Path(tmp))
        print("against offline:", json.dumps(results["against_offline"]))
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
