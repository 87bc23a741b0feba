"""``irft simulate``: forward RFT, a toe along a path -> contacts and forces (a dataset ``irft fit``
reads), optionally a CSV and figures."""

from __future__ import annotations

import csv
from typing import Any

from .arguments import MAPS, UsageError, _out_dir, _out_file, add_path_args, add_toe_args, make_path, make_toe


def _positive_int(text: str) -> int:
    import argparse

    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text}")
    return v


def _positive_float(text: str) -> float:
    import argparse
    import math

    v = float(text)
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return v


TERRAINS = ("two-media", "compaction", "patches")


def make_terrain(a, smap):
    """The ``--terrain`` field over the walk's route (x from 0 to the last foothold, m): --map's medium and
    --second-map's, or --map's medium scaled 0.5 to 1.5 (compaction)."""
    from .. import rft

    end = a.stride * (a.stances - 1)
    second = MAPS[a.second_map](a.scale_x, a.scale_z)
    if a.terrain == "two-media":
        return rft.TerrainField.two_media(smap, second, boundary=end / 2, width=0.05)
    if a.terrain == "compaction":
        return rft.TerrainField.compaction_gradient(smap, scales=(0.5, 1.5), span=(0.0, max(end, 1e-3)))
    return rft.TerrainField.random_patches([smap, second], n_patches=max(2, a.stances // 4),
                                           extent=(0.0, max(end, 1e-3), -0.5, 0.5), seed=a.seed)


def cmd_simulate(a) -> int:
    import numpy as np
    import torch

    from .. import rft
    from .._files import atomic_path, atomic_write

    out = _out_file(a.out, "--out", ".npz")
    csv_out = _out_file(a.csv, "--csv") if a.csv else None
    plot_dir = _out_dir(a.plot, "--plot") if a.plot else None
    if csv_out and a.terrain:
        raise UsageError("--csv", "writes one stroke's samples; with --terrain read the .npz (locations, stance)")
    toe, stroke = make_toe(a), make_path(a)
    smap = MAPS[a.map](a.scale_x, a.scale_z)
    extra: dict[str, Any] = {}
    if a.terrain:  # a walk: one stroke per stance along a straight route, each sample at its place on the ground
        field = make_terrain(a, smap)
        steps = rft.footholds([(0.0, 0.0), (a.stride * (a.stances - 1) + 1e-9, 0.0)], a.stride)
        wk = rft.walk(toe, stroke, *steps)
        c, f = wk.contacts, rft.forces(field, wk.contacts, locations=wk.locations)
        n = wk.n_stances
        dt = float(stroke.time[-1] - stroke.time[0]) + float(stroke.time[1] - stroke.time[0])
        path = rft.Path(time=torch.cat([stroke.time + k * dt for k in range(n)]),
                        position=stroke.position.repeat(n, 1), heading=stroke.heading.repeat(n),
                        velocity=stroke.velocity.repeat(n, 1), angular_velocity=stroke.angular_velocity.repeat(n))
        extra = dict(locations=wk.locations.numpy(), stance=wk.stance.numpy(), footholds=wk.footholds.numpy(),
                     terrain=np.array(field.name))
    else:
        path = stroke
        c = rft.contacts(toe, path)
        f = rft.forces(smap, c)
    arrays: dict[str, Any] = {k: v.numpy() for k, v in c.as_dict().items()}
    # a dataset (hardware.load_dataset: ``irft fit sim.npz`` reads it), with the simulation's own fields; written
    # whole or not at all (a temporary renamed into place)
    atomic_write(out, lambda fh: np.savez(fh, time=path.time.numpy(), position=path.position.numpy(),
                                          toe_position=path.position.numpy(), heading=path.heading.numpy(),
                                          forces=f.numpy(), **arrays, **extra, map=np.array(a.map),
                                          scale=np.array([a.scale_x, a.scale_z])), "simulation")
    where = f", {a.stances} stances {a.stride:g} m apart on {extra['terrain']}" if a.terrain else ""
    print(f"wrote {out} ({len(path)} samples x {toe.n_segments} segments{where})")
    if csv_out:
        with atomic_path(csv_out, "CSV") as tmp, open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            M = toe.n_segments
            w.writerow(["time_s", "x_m", "z_m", "heading_rad", "F_x_N", "F_z_N"]
                       + [f"{k}_{m}" for k in ("beta", "gamma", "weight_x", "weight_z") for m in range(M)])
            for t in range(len(path)):
                w.writerow([f"{path.time[t]:.6g}", f"{path.position[t, 0]:.6g}", f"{path.position[t, 1]:.6g}",
                            f"{path.heading[t]:.6g}", f"{f[t, 0]:.6g}", f"{f[t, 1]:.6g}"]
                           + [f"{arrays[k][t, m]:.6g}" for k in ("beta", "gamma", "weight_x", "weight_z")
                              for m in range(M)])
        print(f"wrote {csv_out}")
    if plot_dir:
        from .. import plotting

        d = plot_dir
        plotting.save(plotting.plot_stress_map(smap, title=smap.name), d / "stress_map.png")
        if a.terrain:
            end = float(wk.footholds[-1, 0])
            plotting.save(plotting.plot_terrain(field, (-0.25, end + 0.25, -0.5, 0.5), wk.footholds), d / "terrain.png")
        plotting.save(plotting.plot_toe_path(toe, path), d / "toe_path.png")
        plotting.save(plotting.plot_coverage(c), d / "coverage.png")
        plotting.save(plotting.plot_forces(path.time, f, labels=("simulated force", "")), d / "forces.png")
        print(f"wrote figures to {d}/")
    return 0


def register(sub) -> None:
    p = sub.add_parser("simulate", help="forward RFT: a toe along a path -> contacts and forces",
                       description="Simulate a toe moving along a path in a granular medium and "
                                   "write its per-segment contacts and net forces.")
    add_toe_args(p)
    add_path_args(p)
    g = p.add_argument_group("medium")
    g.add_argument("--map", choices=sorted(MAPS), default="generic", help="stress map (default generic)")
    g.add_argument("--scale-x", type=float, default=1.0, help="multiply alpha_x (default 1)")
    g.add_argument("--scale-z", type=float, default=1.0, help="multiply alpha_z (default 1)")
    g = p.add_argument_group("changing ground (a walk: one stroke per stance along x)")
    g.add_argument("--terrain", choices=TERRAINS,
                   help="two-media (--map, then --second-map beyond the route's middle), compaction (--map scaled "
                        "0.5 to 1.5 along the route) or patches (both maps in patches); writes each sample's place "
                        "(locations, m) and stance into the dataset")
    g.add_argument("--second-map", choices=sorted(MAPS), default="poppy-close",
                   help="the other medium of two-media and patches (default poppy-close)")
    g.add_argument("--stances", type=_positive_int, default=12, help="stances walked (default 12)")
    g.add_argument("--stride", type=_positive_float, default=0.25, help="m between footholds (default 0.25)")
    g.add_argument("--seed", type=int, default=0, help="the patches' layout (default 0)")
    p.add_argument("--out", default="simulation.npz",
                   help="output .npz, a dataset that `irft fit` reads (default simulation.npz)")
    p.add_argument("--csv", help="also write a CSV, one row per time step")
    p.add_argument("--plot", metavar="DIR", help="write PNG figures (map, toe path, coverage, forces; with "
                                                 "--terrain the field over the ground)")
    p.set_defaults(func=cmd_simulate)
