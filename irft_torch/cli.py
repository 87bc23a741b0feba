"""The ``irft`` command. Every subcommand has ``--help``."""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from . import rft

# torch (and so rft, gp, hardware) is imported where a command needs it, not here: parsing, --help and
# the start of ``irft reproduce``'s worker processes come first (see ``main``).

MAPS = {
    "generic": lambda sx, sz: _rft().FourierStressMap.generic(sx, sz),
    "poppy-loose": lambda sx, sz: _rft().FourierStressMap.poppy_seeds_loose().scaled(sx, sz),
    "poppy-close": lambda sx, sz: _rft().FourierStressMap.poppy_seeds_close().scaled(sx, sz),
}


def _rft():
    from . import rft

    return rft


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: 'irft CMD: error: argument --x: ... (see irft CMD --help)'."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class UsageError(ValueError):
    """A bad command-line value, reported as one line naming the argument."""

    def __init__(self, arg: str, message: str) -> None:
        super().__init__(f"argument {arg}: {message}")


def _opt(dest: str) -> str:
    return "--" + dest.replace("_", "-")


# dest -> (check, what is expected); applied to every command's parsed arguments that have it
_POSITIVE = ("duration", "rate", "l1", "l2", "kt", "kv", "gear_ratio", "max_condition", "radius", "length", "width",
             "speed", "lr", "max_current", "max_torque", "max_depth", "scale_x", "scale_z",
             "mit_p_max", "mit_v_max", "mit_t_max", "path_tol")
_POSITIVE_INT = ("segments", "n_steps", "filter_window", "n_iter", "bitrate", "trials")
_NONNEG = ("hip_spacing", "extension", "arc_noise", "current_noise", "friction", "cogging", "penetration", "shear",
           "extraction")


def _validate(a) -> None:
    """Check every numeric option before any work starts (UsageError names the argument)."""
    ns = vars(a)
    for dest in _POSITIVE:
        v = ns.get(dest)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise UsageError(_opt(dest), f"must be a positive number, got {v:g}")
    for dest in _POSITIVE_INT:
        v = ns.get(dest)
        if v is not None and v < 1:
            raise UsageError(_opt(dest), f"must be a positive integer, got {v}")
    for dest in _NONNEG:
        v = ns.get(dest)
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise UsageError(_opt(dest), f"must be >= 0, got {v:g}")
    if ns.get("filter_window") is not None and a.filter_window % 2 == 0:
        raise UsageError("--filter-window", f"must be odd (an even moving average shifts the force by half a sample), "
                                            f"got {a.filter_window}")
    if ns.get("max_samples") is not None and a.max_samples < 0:
        raise UsageError("--max-samples", f"must be >= 0 (0: use every sample), got {a.max_samples}")
    if ns.get("frame_drop") is not None and not 0 <= a.frame_drop < 1:
        raise UsageError("--frame-drop", f"must be a probability in [0, 1), got {a.frame_drop:g}")
    hh = ns.get("hip_height")
    if hh is not None and not (math.isfinite(hh) and hh > 0):
        raise UsageError("--hip-height", f"is the height of the motor axes above the sand surface and must be positive "
                                         f"(m), got {hh:g}" + (" (a sign slip?)" if hh < 0 else ""))
    for dest in ("tilt", "frame_tol"):
        v = ns.get(dest)
        if v is not None and not math.isfinite(v):
            raise UsageError(_opt(dest), f"must be finite, got {v}")
    for dest in ("tilt", "heading"):  # angles in rad: beyond pi they add nothing, and 30 or 90 are degrees
        v = ns.get(dest)
        if isinstance(v, float) and abs(v) > math.pi:
            raise UsageError(_opt(dest), f"is an angle in rad, within [-pi, pi]; got {v:g} (degrees? "
                                         f"{v:g} deg = {math.radians(v):.4g} rad)")
    if ns.get("zero_offsets") is not None and not all(math.isfinite(v) for v in a.zero_offsets):
        raise UsageError("--zero-offsets", f"must be finite angles (rad), got {a.zero_offsets}")
    if ns.get("directions") is not None and any(d not in (1, -1) for d in a.directions):
        raise UsageError("--directions", f"each must be +1 or -1, got {a.directions}")
    nodes = ns.get("nodes")
    if nodes is not None:
        top = 255 if ns.get("protocol") == "mit" else 63
        bad = [n for n in nodes if not 0 <= n <= top]
        if bad:
            raise UsageError("--nodes", f"node ids must be in 0..{top}, got {bad}")
        if len(set(nodes)) != len(nodes):
            raise UsageError("--nodes", f"each motor needs its own node id, got {nodes}")
    if ns.get("mit_master_id") is not None and not 0 <= a.mit_master_id <= 0x7FF:
        raise UsageError("--mit-master-id", f"must be an 11-bit CAN id (0..2047), got {a.mit_master_id}")
    if ns.get("kt") is not None and ns.get("kv") is not None:
        raise UsageError("--kt", "give --kt or --kv (with --kt-convention), not both")


def _check_writable(out: Path, arg: str) -> None:
    """The nearest existing folder on the way to ``out`` is a folder we may write in."""
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise UsageError(arg, f"cannot create {out}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK):
        raise UsageError(arg, f"cannot write to {probe} (permission denied)")


def _out_file(path, arg: str, suffix: str | None = None) -> Path:
    """Check an output file before the work: not a directory, its folder exists or can be made and is
    writable. ``suffix`` (e.g. ".npz") is appended when missing, as numpy does; returns the real path."""
    out = Path(path)
    if suffix and out.suffix != suffix:
        out = out.with_name(out.name + suffix)
    if out.is_dir():
        raise UsageError(arg, f"{out} is a directory; give a file name")
    _check_writable(out.parent, arg)
    if out.exists() and not os.access(out, os.W_OK):
        raise UsageError(arg, f"cannot overwrite {out} (permission denied)")
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def _out_dir(path, arg: str) -> Path:
    """Check (and make) an output folder before the work."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UsageError(arg, f"{out} exists and is a file; give a folder (or remove the file)")
    _check_writable(out, arg)
    out.mkdir(parents=True, exist_ok=True)
    return out


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
    from . import rft

    if a.toe == "I":
        return rft.IToe(a.length, a.width, tilt=a.tilt, n_segments=a.segments)
    return rft.CToe(a.radius, a.width, n_segments=a.segments, opening=a.opening)


def make_path(a) -> rft.Path:
    from . import rft

    if a.path == "rectangle":
        start = (-a.shear / 2, 0.0)
        return rft.rectangle_path(a.penetration, a.shear, a.extraction, start=start,
                                  n_steps=a.n_steps, speed=a.speed)
    return rft.spline_path(a.control_points, n_steps=a.n_steps, speed=a.speed)


def cmd_simulate(a) -> int:
    import numpy as np

    from . import rft

    out = _out_file(a.out, "--out", ".npz")
    csv_out = _out_file(a.csv, "--csv") if a.csv else None
    plot_dir = _out_dir(a.plot, "--plot") if a.plot else None
    toe, path = make_toe(a), make_path(a)
    smap = MAPS[a.map](a.scale_x, a.scale_z)
    c = rft.contacts(toe, path)
    f = rft.forces(smap, c)
    arrays = {k: v.numpy() for k, v in c.as_dict().items()}
    # a dataset (hardware.load_dataset: ``irft fit sim.npz`` reads it), with the simulation's own fields
    np.savez(out, time=path.time.numpy(), position=path.position.numpy(), toe_position=path.position.numpy(),
             heading=path.heading.numpy(), forces=f.numpy(), **arrays, map=np.array(a.map),
             scale=np.array([a.scale_x, a.scale_z]))
    print(f"wrote {out} ({len(path)} samples x {toe.n_segments} segments)")
    if csv_out:
        with open(csv_out, "w", newline="") as fh:
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
        from . import plotting

        d = plot_dir
        plotting.save(plotting.plot_stress_map(smap, title=smap.name), d / "stress_map.png")
        plotting.save(plotting.plot_toe_path(toe, path), d / "toe_path.png")
        plotting.save(plotting.plot_coverage(c), d / "coverage.png")
        plotting.save(plotting.plot_forces(path.time, f, labels=("simulated force", "")), d / "forces.png")
        print(f"wrote figures to {d}/")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="irft", description="Inverse Resistive Force Theory tools.")
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
    p.add_argument("--out", default="simulation.npz",
                   help="output .npz, a dataset that `irft fit` reads (default simulation.npz)")
    p.add_argument("--csv", help="also write a CSV, one row per time step")
    p.add_argument("--plot", metavar="DIR", help="write PNG figures (map, toe path, coverage, forces)")
    p.set_defaults(func=cmd_simulate)

    for register in _EXTRA_COMMANDS:
        register(sub)
    return parser


REPRODUCE_PRELOAD = ("irft_torch.reproduce",)  # what the study's worker processes import (reproduce.run_study)


def cmd_reproduce(a) -> int:
    from dataclasses import replace

    from .reproduce import StudySettings, run_study
    from .workers import default_workers

    _out_dir(a.out, "--out")  # before the study: a bad --out fails now
    settings = StudySettings.quick_settings() if a.quick else StudySettings()
    if a.priors == "none":  # the paper's plain marginal likelihood for every fit
        settings = replace(settings, priors=None)
    if a.jobs < 0:
        raise UsageError("--jobs", f"must be 0 (one per CPU) or a positive number of processes, got {a.jobs}")
    workers = default_workers() if a.jobs == 0 else a.jobs
    r = run_study(a.out, settings, progress=not a.no_progress, workers=workers)
    print(f"wrote tables, figures and report.md to {r['out_dir']}/ in {r['elapsed_s']:.0f} s")
    return 0


def _register_reproduce(sub) -> None:
    p = sub.add_parser("reproduce", help="rerun the paper's numerical validation (Tables I, II, Fig. 5)",
                       description="Rerun the I-RFT paper's simulation study: four toe/gait configurations, "
                                   "zero vs physics prior mean, the noise study; write table1.csv, "
                                   "table2.csv, figures and report.md.")
    p.add_argument("--out", default="experiments/results", help="output directory (default experiments/results)")
    p.add_argument("--quick", action="store_true", help="smaller grid, fewer steps and seeds (< 1 minute)")
    p.add_argument("--jobs", type=int, default=0,
                   help="worker processes for the fits (default 0: one per CPU, at most 8; 1: this process)")
    p.add_argument("--priors", choices=["physical", "none"], default="physical",
                   help="hyperparameter priors of every fit: the library's physical priors (MAP, default) or none "
                        "(the paper's plain marginal likelihood; its Table I rows are in every run)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_reproduce)


def _open_bus(a):
    """python-can bus from --interface/--channel/--bitrate, with the usual failures explained."""
    import errno

    import can

    kw = {"bitrate": a.bitrate} if a.bitrate else {}
    try:
        return can.Bus(channel=a.channel, interface=a.interface, **kw)
    except can.exceptions.CanInterfaceNotImplementedError as e:
        raise UsageError("--interface", f"python-can cannot use {a.interface!r} here: {e}") from None
    except OSError as e:
        if e.errno in (errno.EAFNOSUPPORT, errno.ENODEV, errno.ENXIO):
            hint = ("socketcan is not available on this machine (Linux CAN sockets: [Errno 97])"
                    if e.errno == errno.EAFNOSUPPORT else f"no CAN device {a.channel!r}")
            raise UsageError("--interface" if e.errno == errno.EAFNOSUPPORT else "--channel",
                             f"{hint}. Bring up a device (sudo ip link set can0 up type can bitrate 1000000), try a "
                             "virtual one (sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; --channel vcan0), "
                             "or record a simulated leg with --simulate") from None
        raise
    except (can.CanError, ValueError) as e:
        raise UsageError("--interface", f"cannot open {a.interface} channel {a.channel!r}: {e}") from None


def _numbered(out: Path, k: int, n: int) -> Path:
    return out if n == 1 else out.with_name(f"{out.stem}_{k + 1}{out.suffix}")


def _record_simulated(a, out: Path) -> int:
    from .hardware import MotorModel, SimulatedLeg

    if a.protocol != "odrive":
        raise UsageError("--simulate", "the simulated leg speaks ODrive CANSimple only (use --protocol odrive)")
    air = _out_file(a.air_out, "--air-out") if a.air_out else out.with_name(f"{out.stem}_air{out.suffix}")
    if air.suffix.lower() != out.suffix.lower():
        raise UsageError("--air-out", f"use the same log format as --out ({out.suffix})")
    toe, path = make_toe(a), make_path(a)
    sim = SimulatedLeg(toe, MAPS[a.map](a.scale_x, a.scale_z), motors=(MotorModel.u8_ii(), MotorModel.u8_ii()),
                       friction=a.friction, cogging=a.cogging, current_noise=a.current_noise,
                       frame_drop=a.frame_drop, rate=a.rate, nodes=tuple(a.nodes), firmware=a.firmware, seed=a.seed)
    outs = [_numbered(out, k, a.trials) for k in range(a.trials)]
    for k, o in enumerate(outs):
        sim.seed = a.seed + 101 * k
        truth = sim.run(path, o)
        print(f"wrote {o} (simulated trial in sand, {truth.time[-1]:.1f} s at {a.rate:g} Hz)")
    sim.seed = a.seed
    sim.run(path, air, in_air=True)
    print(f"wrote {air} (the same path in air)")
    toe_args = (f" --radius {a.radius} --opening {a.opening}" if a.toe == "C"
                else f" --length {a.length} --tilt {a.tilt}")
    print(f"next: irft ingest {' '.join(map(str, outs))} --air {air} --out dataset.npz --toe {a.toe}{toe_args}"
          f" --width {a.width} --segments {a.segments} --nodes {' '.join(map(str, a.nodes))} --firmware {a.firmware}")
    return 0


def cmd_record(a) -> int:
    from .hardware import SUPPORTED_SUFFIXES, record

    out = _out_file(a.out, "--out")
    if out.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise UsageError("--out", f"the suffix picks the log format; use one of {', '.join(SUPPORTED_SUFFIXES)}, "
                                  f"got {out.name!r}")
    if a.simulate:
        return _record_simulated(a, out)
    if a.protocol == "mit":
        poll = ()
        print("MIT mode: listening only (a poll would be a command); the motors' replies to your controller "
              "are logged")
    else:
        from .hardware.odrive_can import COMMANDS

        unknown = [c for c in a.poll if c not in COMMANDS[a.firmware] or not c.startswith("get_")]
        if unknown:
            raise UsageError("--poll", f"unknown Get_* command(s) {unknown} for firmware {a.firmware}; known: "
                                       f"{sorted(c for c in COMMANDS[a.firmware] if c.startswith('get_'))}")
        poll = tuple((cmd, n) for n in a.nodes for cmd in a.poll)
    bus = _open_bus(a)
    stats: dict = {}
    try:
        n = record(bus, out, duration=a.duration, poll=poll, rate=a.rate, firmware=a.firmware, stats=stats)
    finally:
        bus.shutdown()
    print(f"wrote {n} frames to {out}")
    ids = stats.get("frames_by_id", {})
    if n == 0:
        print(f"irft record: warning: no controller answered on {a.interface} channel {a.channel!r} in "
              f"{a.duration:g} s: check power, wiring, termination, the bit rate (--bitrate) and the node ids "
              "(--nodes)", file=sys.stderr)
        return 1
    if a.protocol == "odrive":
        seen = {i >> 5 for i in ids}
        silent = [nd for nd in a.nodes if nd not in seen]
        if silent:
            print(f"irft record: warning: node(s) {silent} sent no frames (nodes heard: {sorted(seen)}): check "
                  "--nodes and the controllers' CAN node ids", file=sys.stderr)
            return 1
    return 0


def _leg_and_motors(a):
    """The leg and both motors from the leg options. k_t: --kt, else from --kv and --kt-convention,
    else the paper's U8-II 0.0973 N m/A."""
    from .hardware import FiveBarLeg, MotorModel, kt_from_kv

    try:
        leg = FiveBarLeg(a.l1, a.l2, hip_spacing=a.hip_spacing, max_condition=a.max_condition,
                         extension=getattr(a, "extension", 0.0))
    except ValueError as e:
        raise UsageError("--extension" if "extension" in str(e) else "--l1/--l2", str(e)) from None
    if a.kt is not None:
        kt = a.kt
    elif a.kv is not None:
        kt = kt_from_kv(a.kv, a.kt_convention)
    else:
        kt = 0.0973
    try:
        motors = tuple(MotorModel(kt, direction=d, gear_ratio=a.gear_ratio, zero_offset=z)
                       for d, z in zip(a.directions, a.zero_offsets))
    except ValueError as e:
        raise UsageError("--kt/--kv" if "torque_constant" in str(e) else "--gear-ratio", str(e)) from None
    return leg, motors


def _heading(text: str):
    if text in ("link1", "link2"):
        return text
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a toe heading in rad or 'link1'/'link2', got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return v


def _name_trials(message: str, paths, word: str) -> str:
    """'trial 1 covers ...' -> '<word> 1 (path) covers ...'."""
    import re

    return re.sub(r"\btrial (\d+)\b", lambda m: f"{word} {m[1]} ({paths[int(m[1])]})", message)


def cmd_ingest(a) -> int:
    import warnings

    from .hardware import (
        MitModel,
        average_trials,
        build_dataset,
        dataset_summary,
        forces_from_log,
        mit_model,
        read_log,
        save_dataset,
        subtract_air,
        zero_phase_filter,
    )

    out = _out_file(a.out, "--out", ".npz")
    for p in [*a.logs, *a.air]:
        if not Path(p).is_file():
            raise UsageError("logs" if p in a.logs else "--air", f"no log file at {p}")
    leg, motors = _leg_and_motors(a)
    toe = make_toe(a)
    if a.protocol == "mit":
        try:
            model = mit_model(a.mit_model)
        except ValueError as e:
            raise UsageError("--mit-model", str(e)) from None
        if a.mit_p_max or a.mit_v_max or a.mit_t_max or a.mit_quantity:
            model = MitModel(model.name + " (custom)", a.mit_p_max or model.p_max, a.mit_v_max or model.v_max,
                             a.mit_t_max or model.t_max, a.mit_quantity or model.quantity)
    else:
        model = None
    read_kw = ({"protocol": "mit", "mit_model": model, "master_id": a.mit_master_id} if model
               else {"firmware": a.firmware})

    def trace(path):
        data = read_log(path, nodes=set(a.nodes), on_error=a.on_error, **read_kw)
        for issue in data.issues:
            print(f"{path}: {issue}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            log = data.resample(tuple(a.nodes), rate=a.rate, max_current=a.max_current, max_torque=a.max_torque)
            t = forces_from_log(log, leg, motors, arc_noise=a.arc_noise)
        for w in caught:
            if "singular" not in str(w.message):
                print(f"{path}: {w.message}")
        if t.why_masked:
            print(f"{path}: masked " + "; ".join(f"{v} {k}" for k, v in t.why_masked.items()))
        return t

    def average(traces, paths, word: str, label: str = ""):
        """``average_trials`` of the runs (cropped with --crop-trials), its warnings printed, its errors
        naming the runs' files."""
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out = average_trials(traces, coverage="crop" if a.crop_trials else "error", path_tol=a.path_tol)
        except ValueError as e:
            raise ValueError(_name_trials(str(e), paths, word)) from None
        for w in caught:
            print(f"irft ingest: {label}{w.message}")
        return out

    air_traces = [trace(p) for p in a.air]
    air = average(air_traces, a.air, "air run", "air runs: ") if air_traces else None
    trials = []
    for p in a.logs:
        t = trace(p)
        if air is not None:
            try:
                t = subtract_air(t, air, path_tol=a.path_tol)
            except ValueError as e:
                raise ValueError(f"{p}: {e}") from None
        trials.append(zero_phase_filter(t, a.filter_window))
    avg = average(trials, a.logs, "trial")
    ds = build_dataset(avg, leg, toe, a.hip_height, heading=a.heading, max_depth=a.max_depth)
    if a.statistics:
        from .gp.statistics import recording_statistics, statistics_arrays

        ds.statistics = statistics_arrays(recording_statistics(ds.contacts, ds.forces), ds.contacts, ds.forces)
    written = save_dataset(out, ds, logs=[str(p) for p in a.logs], air=[str(p) for p in a.air])
    masked = {}
    for t in trials:
        for k_, v_ in t.why_masked.items():
            masked[k_] = masked.get(k_, 0) + v_
    masked.update({k_: v_ for k_, v_ in avg.why_masked.items()})
    print(f"wrote {written}: {len(ds)} samples x {ds.contacts.n_segments} segments"
          + (" and their spectral statistics" if a.statistics else ""))
    for line in dataset_summary(ds, masked or None, n_before=len(avg.time)):
        print(f"  {line}")
    return 0


def _statistics_of(path: str, n_beta: int, n_gamma: int, threads: int = 0) -> dict:
    """One dataset's spectral statistics in FourierBasis(n_beta, n_gamma): cut from those saved in
    the file when they are its own and cover the basis, else one pass (a worker of ``irft fit``).
    Returns the statistics' state and whether they came from the file."""
    import torch

    from .gp.backends.spectral import restrict_statistics
    from .gp.fourier import FourierBasis
    from .gp.statistics import recording_statistics, statistics_from_arrays
    from .hardware import load_dataset

    if threads:
        torch.set_num_threads(threads)
    torch.set_default_dtype(torch.float64)
    ds = load_dataset(path)
    basis = FourierBasis(n_beta, n_gamma)
    c, f = ds.contacts.to(dtype=torch.float64), ds.forces.to(torch.float64)
    stats = None
    if ds.statistics:
        stats = statistics_from_arrays(ds.statistics, c, f, source=f"the statistics saved in {path}")
        if stats is not None and (stats.meta["n_beta"] < n_beta or stats.meta["n_gamma"] < n_gamma):
            stats = None
    from_file = stats is not None
    stats = restrict_statistics(stats, basis) if from_file else recording_statistics(c, f, basis)
    return {"state": stats.state(), "from_file": from_file}


def _spectral_start(contacts, method: str):
    """The Fourier basis the model will start in if ``method`` gives the spectral backend on these
    contacts (a default ``InverseRFT``: lengthscale 1, tol 1e-7), else None."""
    from types import SimpleNamespace

    import torch

    from .gp.backends.select import choose_method
    from .gp.statistics import initial_basis

    hypers = SimpleNamespace(lengthscale=torch.ones(2, 1, 4, dtype=torch.float64))
    if method == "spectral" or (method == "auto" and choose_method(contacts, hypers) == "spectral"):
        return initial_basis()
    return None


def _reduce_statistics(paths: list[str], basis, jobs: int = 0, n_samples: int = 0):
    """The summed spectral statistics of the datasets at ``paths`` in ``basis``, reduced in ``jobs``
    worker processes (0: up to half the CPU count, from 4 CPUs, when the pass, about ``n_samples`` x
    F^2 flops, is long enough to pay for starting them, a few seconds each; 1: here, where torch
    already spreads the pass's matrix products over the cores). Statistics saved in a file are
    used when they are that file's own and cover the basis."""
    import time
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from .gp.backends.weight_space import FeatureStatistics

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

    from . import plotting
    from .gp import InverseRFT
    from .hardware import load_dataset

    _out_dir(a.out, "--out")  # before the fit: a bad --out fails now, not after minutes of training
    parts = [load_dataset(p) for p in a.dataset]
    ds = parts[0]
    if len(parts) > 1:  # one recording after another: times shifted so the time axis keeps increasing
        from .rft import Contacts

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
        stats = _reduce_statistics(a.dataset, basis, a.jobs, len(ds))
    model = InverseRFT(ds.contacts, ds.forces, prior_mean=a.prior_mean, method=a.method, statistics=stats,
                       priors=None if a.priors == "none" else a.priors)
    print(f"backend {model.backend.describe()}")
    model.fit(n_iter=a.n_iter, lr=a.lr, progress=not a.no_progress)
    print(model.diagnostics(warn=False))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / "model.pt")
    fig = plotting.plot_posterior_map(model)
    plotting.save(fig, out / "stress_map.png")
    pred = model.predict_forces(ds.contacts)
    meas = model.predict_forces(ds.contacts, include_noise=True)  # a new measurement: mean +- noise too
    plotting.save(plotting.plot_forces(ds.time, ds.forces, pred.mean, meas.stddev, labels=("dataset", "I-RFT fit"),
                                       band_label=r"$\pm 2\sigma$ of a measurement"), out / "forces.png")
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
    g.add_argument("--extension", type=float, default=0.0,
                   help="how far the toe sits beyond the distal joint along the leg axis, m (Traveler: 0.05)")
    g.add_argument("--hip-height", type=float, default=0.25, help="motor axes above the sand surface, m (positive)")
    g.add_argument("--max-condition", type=float, default=50.0, help="mask samples with cond(J) above this")
    g.add_argument("--kt", type=float, default=None,
                   help="torque constant, N m/A (default: from --kv if given, else the U8-II's 0.0973)")
    g.add_argument("--kv", type=float, help="motor KV (rpm/V), instead of --kt")
    g.add_argument("--kt-convention", choices=["odrive", "si"], default="odrive",
                   help="k_t from --kv: ODrive's 8.27/KV (default) or SI 60/(2 pi KV)")
    g.add_argument("--directions", type=int, nargs=2, default=[1, 1], help="motor direction signs (+1/-1)")
    g.add_argument("--zero-offsets", type=float, nargs=2, default=[0.0, 0.0], help="joint angle at encoder 0, rad")
    g.add_argument("--gear-ratio", type=float, default=1.0,
                   help="motor turns per joint turn (1: direct drive; 1 for MIT mode, which reports the output)")


def add_protocol_args(p) -> None:
    g = p.add_argument_group("CAN protocol")
    g.add_argument("--protocol", choices=["odrive", "mit"], default="odrive",
                   help="ODrive CANSimple (default) or CubeMars/T-Motor AK MIT mode")
    g.add_argument("--firmware", choices=["0.5", "0.6"], default="0.5", help="ODrive firmware layout (default 0.5)")


def add_sim_args(p) -> None:
    g = p.add_argument_group("simulated leg (with --simulate; leg l1 0.15 m, l2 0.30 m, hips 0.25 m up, U8-II)")
    g.add_argument("--simulate", action="store_true",
                   help="no hardware: a simulated leg (two fake ODrives on a virtual bus) writes --out (in sand) and "
                        "--air-out (the same path in air)")
    g.add_argument("--air-out", help="in-air log (default: OUT_air with the same suffix)")
    g.add_argument("--trials", type=int, default=1, help="trials in sand: OUT_1, OUT_2, ... when more than 1")
    g.add_argument("--map", choices=sorted(MAPS), default="generic", help="the sand's stress map (default generic)")
    g.add_argument("--scale-x", type=float, default=1.0, help="multiply alpha_x (default 1)")
    g.add_argument("--scale-z", type=float, default=1.0, help="multiply alpha_z (default 1)")
    g.add_argument("--current-noise", type=float, default=0.0, help="current noise std, A (default 0)")
    g.add_argument("--friction", type=float, default=0.0, help="Coulomb friction per motor, N m (default 0)")
    g.add_argument("--cogging", type=float, default=0.0, help="cogging ripple, N m (default 0)")
    g.add_argument("--frame-drop", type=float, default=0.0, help="probability that a frame is lost (default 0)")
    g.add_argument("--seed", type=int, default=0)


def _register_hardware(sub) -> None:
    p = sub.add_parser("record", help="log a live CAN bus (ODrive CANSimple or AK MIT mode) to a log file",
                       description="Poll the motor controllers by RTR (ODrive) or listen (MIT mode) and write every "
                                   "frame to a log (.log, .asc, .blf, .csv by suffix). --simulate: no hardware: a "
                                   "simulated leg runs the toe along the path (its length and --speed set the "
                                   "duration; --interface, --channel, --bitrate, --duration and --poll do not apply).")
    p.add_argument("--interface", default="socketcan", help="python-can interface (socketcan, pcan, virtual, ...)")
    p.add_argument("--channel", default="can0")
    p.add_argument("--bitrate", type=int, help="bit rate, if the interface needs it")
    p.add_argument("--out", required=True, help="log file; the suffix picks the format (.log .asc .blf .csv)")
    p.add_argument("--duration", type=float, default=20.0, help="seconds (default 20; not with --simulate)")
    p.add_argument("--rate", type=float, default=200.0, help="polling rate, Hz (default 200)")
    p.add_argument("--nodes", type=int, nargs="+", default=[0, 1], help="controller node ids (default 0 1)")
    p.add_argument("--poll", nargs="+", default=["get_iq"], help="Get_* commands to poll (default get_iq)")
    add_protocol_args(p)
    add_sim_args(p)
    add_toe_args(p)
    add_path_args(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("ingest", help="logs -> forces -> air subtraction, filter, trial average -> dataset",
                       description="Turn motor logs of repeated trials (and in-air runs along the same path) "
                                   "into an I-RFT dataset (contacts + forces, npz). Checks the physics first and "
                                   "prints a summary.")
    p.add_argument("logs", nargs="+", help="log files of the trials in sand")
    p.add_argument("--air", nargs="*", default=[], help="log files of the same path in air")
    p.add_argument("--out", required=True, help="dataset .npz ('.npz' is appended when missing)")
    p.add_argument("--nodes", type=int, nargs=2, default=[0, 1],
                   help="node ids of motor 1 and motor 2 (MIT: the driver ids in byte 0)")
    add_protocol_args(p)
    g = p.add_argument_group("MIT mode (--protocol mit)")
    g.add_argument("--mit-model", default="AK80-9", help="AK model, sets the field ranges (default AK80-9)")
    g.add_argument("--mit-master-id", type=int, default=0, help="CAN id the replies are sent to (default 0)")
    g.add_argument("--mit-p-max", type=float, help="override: position range +-, rad")
    g.add_argument("--mit-v-max", type=float, help="override: velocity range +-, rad/s")
    g.add_argument("--mit-t-max", type=float, help="override: torque (N m) or current (A) range +-")
    g.add_argument("--mit-quantity", choices=["torque", "current"],
                   help="override: what the 12-bit field carries (current: give --kt as output-side N m per A, "
                        "i.e. gear ratio x k_t, and keep --gear-ratio 1: MIT positions are output-side)")
    p.add_argument("--rate", type=float, help="resampling rate, Hz (default: the logs' current rate)")
    p.add_argument("--filter-window", type=int, default=5,
                   help="zero-phase moving average, samples, odd (default 5)")
    p.add_argument("--arc-noise", type=float, default=0.0,
                   help="toe moves below this many m add no arc length when aligning the air run and trials "
                        "(encoder jitter while standing still; default 0, about 2e-4 for a jittery leg)")
    p.add_argument("--no-statistics", dest="statistics", action="store_false",
                   help="do not save the dataset's spectral sufficient statistics (saved by default: irft fit then "
                        "skips its pass over the data; 2 x F^2 x 8 bytes, F = 289 features: 1.3 MB)")
    p.add_argument("--on-error", choices=["raise", "warn"], default="raise",
                   help="a truncated or damaged log: stop with an error (default) or use what was read")
    g = p.add_argument_group("physical checks")
    g.add_argument("--max-current", type=float, default=80.0,
                   help="|current| above this, A, is an outlier: masked and counted (default 80)")
    g.add_argument("--max-torque", type=float, default=None, help="the same for torque logs, N m (default none)")
    g.add_argument("--max-depth", type=float, default=0.15,
                   help="the toe deeper than this, m, is an error (a wrong --hip-height or --l1/--l2); default 0.15")
    g.add_argument("--path-tol", type=float, default=None,
                   help="trials and air runs must follow the same path within this RMS distance, m "
                        "(default max(1 cm, 5 %% of the path))")
    g.add_argument("--crop-trials", action="store_true",
                   help="a trial (or air run) shorter than the others: crop all to the shortest (default: an error)")
    g.add_argument("--heading", type=_heading, default=0.0,
                   help="toe heading: fixed angle, rad (default 0), or link1/link2 (toe fixed to that link)")
    add_leg_args(p)
    add_toe_args(p)
    p.set_defaults(func=cmd_ingest)

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
                   help="hyperparameter priors (default physical: MAP, gp.priors; none: the paper's plain marginal "
                        "likelihood)")
    p.add_argument("--max-samples", type=int, default=0,
                   help="thin to this many evenly spaced samples (default 0: use every sample; the backend picked "
                        "by method='auto' keeps long recordings fast)")
    p.add_argument("--jobs", type=int, default=0,
                   help="worker processes reducing the datasets to their spectral statistics (default 0: up to half "
                        "the CPUs, from 4, when the pass is long, over about 5 million samples; 1: in this process)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_fit)


_EXTRA_COMMANDS: list = [_register_reproduce, _register_hardware]


def main(argv: list[str] | None = None) -> int:
    """Run the ``irft`` command. A user error (bad value, missing or damaged file, no device) prints one
    line naming the argument or file and returns non-zero, never a traceback (IRFT_DEBUG=1 shows one)."""
    parser = build_parser()
    a = parser.parse_args(argv)
    if a.command == "reproduce":  # with worker processes, their imports run beside this process's
        from .workers import default_workers, start_worker_server

        if (a.jobs or default_workers()) > 1:
            start_worker_server(REPRODUCE_PRELOAD)
    import torch

    torch.set_default_dtype(torch.float64)
    debug = os.environ.get("IRFT_DEBUG") == "1"
    try:
        _validate(a)
        return a.func(a)
    except KeyboardInterrupt:
        print(f"irft {a.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - reported as one line; IRFT_DEBUG=1 re-raises
        if debug:
            raise
        import can

        user = isinstance(e, (ValueError, OSError, can.CanError, EOFError, KeyError))
        text = " ".join(str(e).split()) or type(e).__name__
        if not user:
            kind = type(e).__qualname__ if type(e).__module__ == "builtins" else \
                f"{type(e).__module__}.{type(e).__qualname__}"
            text = (f"{kind}: {text} (unexpected: if your input looks right, rerun with IRFT_DEBUG=1 and "
                    "report the traceback)")
        print(f"irft {a.command}: error: {text}", file=sys.stderr)
        return 2 if user else 3


if __name__ == "__main__":
    sys.exit(main())
