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


_EXTRA_COMMANDS: list = [_register_reproduce]


def main(argv: list[str] | None = None) -> int:
    torch.set_default_dtype(torch.float64)
    parser = build_parser()
    a = parser.parse_args(argv)
    try:
        return a.func(a)
    except (ValueError, FileNotFoundError) as e:
        print(f"irft {a.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
