"""The live map converging while the simulated leg walks (``hardware.LiveEstimator``, as ``irft live --simulate``).

Data: the simulated leg walking in real time on a virtual bus. Run time: about 23 s with the
defaults (2 cores, 2026-12-03): the walk is real time (--strides, default 60, of 0.3 s each).

The leg walks ``--strides`` strides in real time on python-can's virtual bus through sand whose stress map is
Li et al.'s generic map x (``--scale-x``, ``--scale-z``). After each stance the estimator publishes its map at
81 points over the (beta, gamma) square; this script keeps each one and compares it with the sand's map:

- the map as a multiple of the generic map per axis (the estimator's summary) with its 95 % interval;
- the map's error, rms over the 81 points relative to the truth's rms, beside the posterior's own rms std;
- the share of the 81 points whose 95 % interval holds the truth.

The start model is the estimator's (fitted on the first ``--warmup`` stances, the plug-in hyperparameters:
every later stance is one streaming update).

    python experiments/validation/live_convergence.py [--strides 60] [--out experiments/results/live_convergence]
"""

from __future__ import annotations

import argparse
import json
import uuid
from pathlib import Path

import can
import numpy as np
import torch

import irft_torch as irft
from irft_torch.cli.live import _start_model  # irft live's own start model (plug-in, spectral, 100 steps)
from irft_torch.hardware import LiveEstimator, WalkingLeg
from irft_torch.hardware.live import MAP_POINTS


def walk(args) -> tuple[list, np.ndarray]:
    toe = irft.rft.CToe(0.02, 0.008, n_segments=10)
    sand = irft.rft.FourierStressMap.generic(args.scale_x, args.scale_z)
    leg = WalkingLeg(toe, sand, current_noise=args.current_noise, seed=args.seed)
    truth = sand(torch.as_tensor(MAP_POINTS[:, 0]), torch.as_tensor(MAP_POINTS[:, 1])).numpy()  # (81, 2)
    channel = f"irft-live-convergence-{uuid.uuid4().hex}-bus"
    bus = can.Bus(channel=channel, interface="virtual")
    seen: list = []
    est = LiveEstimator(bus, leg.leg, leg.motors, toe, leg.hip_height, start_model=_start_model(100),
                        warmup=args.warmup, firmware=leg.firmware,
                        callback=lambda e: seen.append(e) if e.event == "stance" else None)
    with est:
        leg.walk(channel, args.strides)
        est.drain(60.0, ended=True)
    bus.shutdown()
    if est.error is not None:
        raise est.error
    return [e for e in seen if e.used and e.map_mean is not None], truth


def summarise(stances: list, truth: np.ndarray) -> dict:
    rms = np.sqrt((truth**2).mean(0))
    rows = []
    for e in stances:
        err = np.sqrt(((e.map_mean - truth) ** 2).mean(0)) / rms
        sd = np.sqrt((e.map_std**2).mean(0)) / rms
        cover = (np.abs(e.map_mean - truth) <= 1.96 * e.map_std).mean(0)
        rows.append({"stance": e.stance, "scale": e.scale, "scale_std": e.scale_std, "error": err.tolist(),
                     "std": sd.tolist(), "coverage": cover.tolist(), "latency_ms": 1e3 * e.latency})
    return {"stances": rows}


def plot(summary: dict, args, path: Path) -> None:
    import matplotlib.pyplot as plt

    rows = summary["stances"]
    k = np.array([r["stance"] for r in rows])
    scale, sd = np.array([r["scale"] for r in rows]), np.array([r["scale_std"] for r in rows])
    err, std = np.array([r["error"] for r in rows]), np.array([r["std"] for r in rows])
    cover = np.array([r["coverage"] for r in rows])
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    for i, (name, true, colour) in enumerate((("x", args.scale_x, "C0"), ("z", args.scale_z, "C1"))):
        ax[0].fill_between(k, scale[:, i] - 1.96 * sd[:, i], scale[:, i] + 1.96 * sd[:, i], color=colour, alpha=0.25,
                           label=f"alpha_{name}: 95 % interval")
        ax[0].plot(k, scale[:, i], color=colour, label=f"alpha_{name}: live estimate")
        ax[0].axhline(true, color=colour, ls="--", label=f"alpha_{name}: truth ({true:g})")
        ax[1].plot(k, err[:, i], color=colour, label=f"alpha_{name}: error (rms, vs truth)")
        ax[1].plot(k, std[:, i], color=colour, ls=":", label=f"alpha_{name}: posterior std (rms)")
        ax[2].plot(k, cover[:, i], color=colour, label=f"alpha_{name}")
    ax[0].set(xlabel="stance", ylabel="map / Li et al.'s generic map", title="the map's scale per axis")
    ax[1].set(xlabel="stance", ylabel="relative to the true map's rms", yscale="log",
              title="the map over 81 points of (beta, gamma)\n(most never probed by this stride: prior there)")
    ax[2].axhline(0.95, color="k", ls="--", lw=0.8, label="nominal 0.95")
    ax[2].set(xlabel="stance", ylabel="share of the 81 points", ylim=(0, 1.05),
              title="95 % intervals holding the truth")
    for a in ax:
        a.legend(fontsize=7)
        a.grid(alpha=0.3)
    fig.suptitle(f"irft live: a simulated leg walking {args.strides} strides in real time (generic sand x "
                 f"({args.scale_x:g}, {args.scale_z:g}), current noise {args.current_noise:g} A)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--strides", type=int, default=60, help="strides walked in real time (0.3 s each)")
    ap.add_argument("--warmup", type=int, default=3, help="stances the start model is fitted on")
    ap.add_argument("--scale-x", type=float, default=1.0, help="the sand: generic alpha_x times this")
    ap.add_argument("--scale-z", type=float, default=1.5, help="the sand: generic alpha_z times this")
    ap.add_argument("--current-noise", type=float, default=0.05, help="std of the measured currents, A")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("experiments/results/live_convergence"))
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    torch.set_default_dtype(torch.float64)
    stances, truth = walk(args)
    summary = summarise(stances, truth)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "live_convergence.json").write_text(json.dumps(summary, indent=1))
    plot(summary, args, args.out / "live_convergence.png")
    for r in summary["stances"][:: max(1, len(stances) // 8)] + summary["stances"][-1:]:
        (sx, sz), (dx, dz) = r["scale"], r["scale_std"]
        print(f"stance {r['stance']:3d}: scale x {sx:.3f} ± {dx:.3f}, z {sz:.3f} ± {dz:.3f}; "
              f"map error x {r['error'][0]:.3f} z {r['error'][1]:.3f} (std {r['std'][0]:.3f}, "
              f"{r['std'][1]:.3f}); 95 % coverage x {r['coverage'][0]:.2f} z {r['coverage'][1]:.2f}; "
              f"latency {r['latency_ms']:.0f} ms")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
