"""``irft simulate``: forward RFT, a toe along a path -> contacts and forces (a dataset ``irft fit``
reads), optionally a CSV and figures."""

from __future__ import annotations

import csv
from typing import Any

from .arguments import MAPS, _out_dir, _out_file, add_path_args, add_toe_args, make_path, make_toe


def cmd_simulate(a) -> int:
    import numpy as np

    from .. import rft
    from .._files import atomic_path, atomic_write

    out = _out_file(a.out, "--out", ".npz")
    csv_out = _out_file(a.csv, "--csv") if a.csv else None
    plot_dir = _out_dir(a.plot, "--plot") if a.plot else None
    toe, path = make_toe(a), make_path(a)
    smap = MAPS[a.map](a.scale_x, a.scale_z)
    c = rft.contacts(toe, path)
    f = rft.forces(smap, c)
    arrays: dict[str, Any] = {k: v.numpy() for k, v in c.as_dict().items()}
    # a dataset (hardware.load_dataset: ``irft fit sim.npz`` reads it), with the simulation's own fields; written
    # whole or not at all (a temporary renamed into place)
    atomic_write(out, lambda fh: np.savez(fh, time=path.time.numpy(), position=path.position.numpy(),
                                          toe_position=path.position.numpy(), heading=path.heading.numpy(),
                                          forces=f.numpy(), **arrays, map=np.array(a.map),
                                          scale=np.array([a.scale_x, a.scale_z])), "simulation")
    print(f"wrote {out} ({len(path)} samples x {toe.n_segments} segments)")
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
    p.add_argument("--out", default="simulation.npz",
                   help="output .npz, a dataset that `irft fit` reads (default simulation.npz)")
    p.add_argument("--csv", help="also write a CSV, one row per time step")
    p.add_argument("--plot", metavar="DIR", help="write PNG figures (map, toe path, coverage, forces)")
    p.set_defaults(func=cmd_simulate)
