"""The ``irft`` command. Every subcommand has ``--help``."""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
import torch

from . import rft

MAPS = {
    "generic": lambda sx, sz: rft.FourierStressMap.generic(sx, sz),
    "poppy-loose": lambda sx, sz: rft.FourierStressMap.poppy_seeds_loose().scaled(sx, sz),
    "poppy-close": lambda sx, sz: rft.FourierStressMap.poppy_seeds_close().scaled(sx, sz),
}


def _points(text: str) -> list[tuple[float, float]]:
    try:
        pts = [tuple(float(v) for v in p.split(",")) for p in text.split(";") if p.strip()]
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"control points must look like 'x,z;x,z;...' in m: {e}") from e
    if any(len(p) != 2 for p in pts):
        raise argparse.ArgumentTypeError("each control point needs two numbers 'x,z' (m)")
    return pts


def add_toe_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("toe (lengths in m)")
    g.add_argument("--toe", choices=["I", "C"], default="C", help="flat plate (I) or semicircle (C)")
    g.add_argument("--length", type=float, default=0.02, help="I-toe length (default 0.02)")
    g.add_argument("--radius", type=float, default=0.02, help="C-toe radius (default 0.02)")
    g.add_argument("--width", type=float, default=0.008, help="out-of-plane width (default 0.008)")
    g.add_argument("--tilt", type=float, default=0.0, help="I-toe tilt, rad (default 0)")
    g.add_argument("--opening", default="up", choices=["up", "down", "left", "right"],
                   help="which way the C-toe opens (default up)")
    g.add_argument("--segments", type=int, default=10, help="number of segments M (default 10)")


def add_path_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("path (lengths in m)")
    g.add_argument("--path", choices=["rectangle", "spline"], default="spline",
                   help="gait 1 (rectangle) or gait 2 (cubic spline); default spline")
    g.add_argument("--penetration", type=float, default=0.05)
    g.add_argument("--shear", type=float, default=0.40)
    g.add_argument("--extraction", type=float, default=0.05)
    g.add_argument("--control-points", type=_points,
                   default=[(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)],
                   help="spline control points 'x,z;x,z;...' (default the paper's gait 2)")
    g.add_argument("--n-steps", type=int, default=200, help="samples along the path (default 200)")
    g.add_argument("--speed", type=float, default=0.02, help="m/s (default 0.02)")


def make_toe(a) -> rft.Toe:
    if a.toe == "I":
        return rft.IToe(a.length, a.width, tilt=a.tilt, n_segments=a.segments)
    return rft.CToe(a.radius, a.width, n_segments=a.segments, opening=a.opening)


def make_path(a) -> rft.Path:
    if a.path == "rectangle":
        start = (-a.shear / 2, 0.0)
        return rft.rectangle_path(a.penetration, a.shear, a.extraction, start=start,
                                  n_steps=a.n_steps, speed=a.speed)
    return rft.spline_path(a.control_points, n_steps=a.n_steps, speed=a.speed)


def cmd_simulate(a) -> int:
    toe, path = make_toe(a), make_path(a)
    smap = MAPS[a.map](a.scale_x, a.scale_z)
    c = rft.contacts(toe, path)
    f = rft.forces(smap, c)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: v.numpy() for k, v in c.as_dict().items()}
    np.savez(out, time=path.time.numpy(), position=path.position.numpy(), heading=path.heading.numpy(),
             forces=f.numpy(), **arrays, map=np.array(a.map), scale=np.array([a.scale_x, a.scale_z]))
    print(f"wrote {out} ({len(path)} samples x {toe.n_segments} segments)")
    if a.csv:
        with open(a.csv, "w", newline="") as fh:
            w = csv.writer(fh)
            M = toe.n_segments
            w.writerow(["time_s", "x_m", "z_m", "heading_rad", "F_x_N", "F_z_N"]
                       + [f"{k}_{m}" for k in ("beta", "gamma", "weight_x", "weight_z") for m in range(M)])
            for t in range(len(path)):
                w.writerow([f"{path.time[t]:.6g}", f"{path.position[t, 0]:.6g}", f"{path.position[t, 1]:.6g}",
                            f"{path.heading[t]:.6g}", f"{f[t, 0]:.6g}", f"{f[t, 1]:.6g}"]
                           + [f"{arrays[k][t, m]:.6g}" for k in ("beta", "gamma", "weight_x", "weight_z")
                              for m in range(M)])
        print(f"wrote {a.csv}")
    if a.plot:
        from . import plotting

        d = Path(a.plot)
        d.mkdir(parents=True, exist_ok=True)
        plotting.save(plotting.plot_stress_map(smap, title=smap.name), d / "stress_map.png")
        plotting.save(plotting.plot_toe_path(toe, path), d / "toe_path.png")
        plotting.save(plotting.plot_coverage(c), d / "coverage.png")
        plotting.save(plotting.plot_forces(path.time, f), d / "forces.png")
        print(f"wrote figures to {d}/")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="irft", description="Inverse Resistive Force Theory tools.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="forward RFT: a toe along a path -> contacts and forces",
                       description="Simulate a toe moving along a path in a granular medium and "
                                   "write its per-segment contacts and net forces.")
    add_toe_args(p)
    add_path_args(p)
    g = p.add_argument_group("medium")
    g.add_argument("--map", choices=sorted(MAPS), default="generic", help="stress map (default generic)")
    g.add_argument("--scale-x", type=float, default=1.0, help="multiply alpha_x (default 1)")
    g.add_argument("--scale-z", type=float, default=1.0, help="multiply alpha_z (default 1)")
    p.add_argument("--out", default="simulation.npz", help="output .npz (default simulation.npz)")
    p.add_argument("--csv", help="also write a CSV, one row per time step")
    p.add_argument("--plot", metavar="DIR", help="write PNG figures (map, toe path, coverage, forces)")
    p.set_defaults(func=cmd_simulate)

    for register in _EXTRA_COMMANDS:
        register(sub)
    return parser


def cmd_reproduce(a) -> int:
    from .reproduce import StudySettings, run_study

    settings = StudySettings.quick_settings() if a.quick else StudySettings()
    r = run_study(a.out, settings, progress=not a.no_progress)
    print(f"wrote tables, figures and report.md to {r['out_dir']}/ in {r['elapsed_s']:.0f} s")
    return 0


def _register_reproduce(sub) -> None:
    p = sub.add_parser("reproduce", help="rerun the paper's numerical validation (Tables I, II, Fig. 5)",
                       description="Rerun the I-RFT paper's simulation study: four toe/gait configurations, "
                                   "zero vs physics prior mean, the noise study; write table1.csv, "
                                   "table2.csv, figures and report.md.")
    p.add_argument("--out", default="experiments/results", help="output directory (default experiments/results)")
    p.add_argument("--quick", action="store_true", help="smaller grid, fewer steps and seeds (< 1 minute)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_reproduce)


def cmd_record(a) -> int:
    import can

    from .hardware import record

    bus = can.Bus(channel=a.channel, interface=a.interface, **({"bitrate": a.bitrate} if a.bitrate else {}))
    try:
        poll = [(cmd, n) for n in a.nodes for cmd in a.poll]
        n = record(bus, a.out, duration=a.duration, poll=tuple(poll), rate=a.rate, firmware=a.firmware)
    finally:
        bus.shutdown()
    print(f"wrote {n} frames to {a.out}")
    return 0


def _leg_and_motors(a):
    from .hardware import FiveBarLeg, MotorModel

    leg = FiveBarLeg(a.l1, a.l2, hip_spacing=a.hip_spacing, max_condition=a.max_condition)
    kt = a.kt if a.kt is not None else MotorModel.from_kv(a.kv, a.kt_convention).torque_constant
    motors = tuple(MotorModel(kt, direction=d, gear_ratio=a.gear_ratio, zero_offset=z)
                   for d, z in zip(a.directions, a.zero_offsets))
    return leg, motors


def cmd_ingest(a) -> int:
    import warnings

    from .hardware import (
        average_trials,
        build_dataset,
        forces_from_log,
        read_log,
        save_dataset,
        subtract_air,
        zero_phase_filter,
    )

    leg, motors = _leg_and_motors(a)

    def trace(path):
        data = read_log(path, firmware=a.firmware, nodes=set(a.nodes), on_error=a.on_error)
        for issue in data.issues:
            print(f"{path}: {issue}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t = forces_from_log(data.resample(tuple(a.nodes), rate=a.rate), leg, motors)
        for w in caught:
            print(f"{path}: {w.message}")
        return t

    air = average_trials([trace(p) for p in a.air]) if a.air else None
    trials = []
    for p in a.logs:
        t = trace(p)
        if air is not None:
            t = subtract_air(t, air)
        trials.append(zero_phase_filter(t, a.filter_window))
    avg = average_trials(trials)
    ds = build_dataset(avg, leg, make_toe(a), a.hip_height)
    save_dataset(a.out, ds, logs=[str(p) for p in a.logs], air=[str(p) for p in (a.air or [])])
    dropped = len(avg.time) - len(ds)
    print(f"wrote {a.out}: {len(ds)} samples x {ds.contacts.n_segments} segments"
          + (f" ({dropped} masked samples dropped)" if dropped else ""))
    return 0


def cmd_fit(a) -> int:
    from . import plotting
    from .gp import InverseRFT
    from .hardware import load_dataset

    ds = load_dataset(a.dataset)
    if a.max_samples and len(ds) > a.max_samples:
        keep = torch.linspace(0, len(ds) - 1, a.max_samples).round().long()
        print(f"using {a.max_samples} of {len(ds)} samples, evenly spaced (the exact GP is cubic in samples; "
              "raise --max-samples to use more)")
        ds = type(ds)(ds.contacts[keep], ds.forces[keep], ds.time[keep], ds.toe_position[keep])
    model = InverseRFT(ds.contacts, ds.forces, prior_mean=a.prior_mean)
    model.fit(n_iter=a.n_iter, lr=a.lr, progress=not a.no_progress)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / "model.pt")
    fig = plotting.plot_posterior_map(model)
    plotting.save(fig, out / "stress_map.png")
    pred = model.predict_forces(ds.contacts)
    plotting.save(plotting.plot_forces(ds.time, ds.forces, pred.mean, pred.stddev), out / "forces.png")
    rng = (ds.forces.amax(0) - ds.forces.amin(0)).clamp_min(1e-12)
    nrmse = ((pred.mean - ds.forces).pow(2).mean(0).sqrt() / rng * 100).tolist()
    print(f"wrote {out}/model.pt, stress_map.png, forces.png; force RMSE {nrmse[0]:.2f} % (x), "
          f"{nrmse[1]:.2f} % (z) of range")
    return 0


def add_leg_args(p) -> None:
    g = p.add_argument_group("leg and motors (SI units)")
    g.add_argument("--l1", type=float, default=0.15, help="proximal link, m (default 0.15)")
    g.add_argument("--l2", type=float, default=0.30, help="distal link, m (default 0.30)")
    g.add_argument("--hip-spacing", type=float, default=0.0, help="distance between motor axes, m")
    g.add_argument("--hip-height", type=float, default=0.25, help="motor axes above the sand surface, m")
    g.add_argument("--max-condition", type=float, default=50.0, help="mask samples with cond(J) above this")
    g.add_argument("--kt", type=float, default=0.0973, help="torque constant, N m/A (default U8-II 0.0973)")
    g.add_argument("--kv", type=float, help="motor KV (rpm/V), instead of --kt")
    g.add_argument("--kt-convention", choices=["odrive", "si"], default="odrive", help="k_t from KV: 8.27/KV or SI")
    g.add_argument("--directions", type=int, nargs=2, default=[1, 1], help="motor direction signs (+1/-1)")
    g.add_argument("--zero-offsets", type=float, nargs=2, default=[0.0, 0.0], help="joint angle at encoder 0, rad")
    g.add_argument("--gear-ratio", type=float, default=1.0, help="motor turns per joint turn (1: direct drive)")


def _register_hardware(sub) -> None:
    p = sub.add_parser("record", help="log a live CAN bus (ODrive CANSimple) to a python-can log file",
                       description="Poll the motor controllers by RTR and write every frame to a log "
                                   "(.log, .asc, .blf by suffix).")
    p.add_argument("--interface", default="socketcan", help="python-can interface (socketcan, pcan, virtual, ...)")
    p.add_argument("--channel", default="can0")
    p.add_argument("--bitrate", type=int, help="bit rate, if the interface needs it")
    p.add_argument("--out", required=True, help="log file; the suffix picks the format")
    p.add_argument("--duration", type=float, default=20.0, help="seconds (default 20)")
    p.add_argument("--rate", type=float, default=200.0, help="polling rate, Hz (default 200)")
    p.add_argument("--nodes", type=int, nargs="+", default=[0, 1], help="controller node ids (default 0 1)")
    p.add_argument("--poll", nargs="+", default=["get_iq"], help="Get_* commands to poll (default get_iq)")
    p.add_argument("--firmware", choices=["0.5", "0.6"], default="0.5")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("ingest", help="logs -> forces -> air subtraction, filter, trial average -> dataset",
                       description="Turn motor logs of repeated trials (and in-air runs along the same path) "
                                   "into an I-RFT dataset (contacts + forces, npz).")
    p.add_argument("logs", nargs="+", help="log files of the trials in sand")
    p.add_argument("--air", nargs="*", default=[], help="log files of the same path in air")
    p.add_argument("--out", required=True, help="dataset .npz")
    p.add_argument("--nodes", type=int, nargs=2, default=[0, 1], help="node ids of motor 1 and motor 2")
    p.add_argument("--firmware", choices=["0.5", "0.6"], default="0.5")
    p.add_argument("--rate", type=float, help="resampling rate, Hz (default: the logs' current rate)")
    p.add_argument("--filter-window", type=int, default=5, help="zero-phase moving average, samples (default 5)")
    p.add_argument("--on-error", choices=["raise", "warn"], default="raise",
                   help="a truncated log: stop with an error (default) or use what was read")
    add_leg_args(p)
    add_toe_args(p)
    p.set_defaults(func=cmd_ingest)

    p = sub.add_parser("fit", help="fit I-RFT to a dataset; write the map, its uncertainty and figures",
                       description="Fit InverseRFT to an ingested dataset and write model.pt and figures.")
    p.add_argument("dataset", help="dataset .npz from irft ingest")
    p.add_argument("--out", default="irft_fit", help="output directory (default irft_fit)")
    p.add_argument("--n-iter", type=int, default=300)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--prior-mean", choices=["zero", "physics"], default="zero")
    p.add_argument("--max-samples", type=int, default=300, help="thin to this many samples (default 300; 0: all)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_fit)


_EXTRA_COMMANDS: list = [_register_reproduce, _register_hardware]


def main(argv: list[str] | None = None) -> int:
    torch.set_default_dtype(torch.float64)
    parser = build_parser()
    a = parser.parse_args(argv)
    try:
        return a.func(a)
    except (ValueError, FileNotFoundError, OSError) as e:
        print(f"irft {a.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
