"""What several ``irft`` subcommands share: the one-line ``UsageError``, the checks of every numeric
option and output path before any work starts, and the toe, path, medium and CAN-protocol options."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .. import rft

__all__ = ["UsageError", "warn", "MAPS", "add_toe_args", "add_path_args", "add_protocol_args", "make_toe", "make_path"]

MAPS = {
    "generic": lambda sx, sz: _rft().FourierStressMap.generic(sx, sz),
    "poppy-loose": lambda sx, sz: _rft().FourierStressMap.poppy_seeds_loose().scaled(sx, sz),
    "poppy-close": lambda sx, sz: _rft().FourierStressMap.poppy_seeds_close().scaled(sx, sz),
}


def _rft():
    from .. import rft

    return rft


class UsageError(ValueError):
    """A bad command-line value, reported as one line naming the argument."""

    def __init__(self, arg: str, message: str) -> None:
        super().__init__(f"argument {arg}: {message}")


def warn(command: str, text) -> None:
    """Print a warning as one line on stderr: 'irft CMD: warning: TEXT' (every subcommand's warnings,
    Python's included: ``main`` routes ``warnings.warn`` here)."""
    import sys

    print(f"irft {command}: warning: {' '.join(str(text).split())}", file=sys.stderr)


def _opt(dest: str) -> str:
    return "--" + dest.replace("_", "-")


# dest -> (check, what is expected); applied to every command's parsed arguments that have it
_POSITIVE = ("duration", "rate", "l1", "l2", "kt", "kv", "gear_ratio", "max_condition", "radius", "length", "width",
             "speed", "lr", "max_current", "max_torque", "max_depth", "scale_x", "scale_z",
             "mit_p_max", "mit_v_max", "mit_t_max", "path_tol")
_POSITIVE_INT = ("segments", "n_steps", "filter_window", "n_iter", "bitrate", "trials")
_NONNEG = ("hip_spacing", "extension", "arc_noise", "current_noise", "friction", "cogging", "penetration", "shear",
           "extraction")


# dest -> (lowest, highest) plausible value in the option's unit, and the unit: a value beyond is a unit slip
# (cm typed in a metre field, degrees in a radian field, mN m/A ...), refused with the likely meaning
_RANGES = {
    "width": (5e-4, 0.3, "m"), "length": (5e-4, 0.3, "m"), "radius": (5e-4, 0.3, "m"),
    "l1": (5e-3, 2.0, "m"), "l2": (5e-3, 2.0, "m"), "hip_spacing": (0.0, 2.0, "m"), "extension": (0.0, 1.0, "m"),
    "hip_height": (5e-3, 2.0, "m"), "max_depth": (1e-3, 1.0, "m"), "path_tol": (1e-4, 0.1, "m"),
    "arc_noise": (0.0, 0.01, "m"), "penetration": (0.0, 1.0, "m"), "shear": (0.0, 2.0, "m"),
    "extraction": (0.0, 1.0, "m"), "speed": (1e-4, 10.0, "m/s"),
    "kt": (1e-3, 10.0, "N m/A"), "kv": (1.0, 1e4, "rpm/V"), "gear_ratio": (0.1, 1000.0, "motor turns per joint turn"),
}


def _unit_slip(dest: str, v: float) -> str | None:
    """Why ``v`` is implausible for option ``dest`` (a unit slip named), or None."""
    lo, hi, unit = _RANGES[dest]
    if lo <= v <= hi:
        return None
    side = "above" if v > hi else "below"
    if unit == "m":
        guess = (f"did you mean {v:g} cm = {v / 100:g} m, or {v:g} mm = {v / 1000:g} m?" if v > hi
                 else f"that is {v * 1000:g} mm" if v > 0 else "")
    elif unit == "N m/A":
        guess = f"mN m/A? ({v:g} mN m/A = {v / 1000:g} N m/A)" if v > hi else f"that is {v * 1000:g} mN m/A"
    else:
        guess = ""
    return (f"is in {unit}: {v:g} is {side} any plausible value ({lo:g} to {hi:g} {unit})"
            + (f"; {guess}" if guess else ""))


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
    for dest in _RANGES:  # two-sided: a value beyond what any leg, toe or motor has is a unit slip
        v = ns.get(dest)
        if isinstance(v, (int, float)) and math.isfinite(v) and (why := _unit_slip(dest, float(v))) is not None:
            raise UsageError(_opt(dest), why)
    for dest in ("tilt", "heading"):  # angles in rad: beyond pi they add nothing, and 30 or 90 are degrees
        v = ns.get(dest)
        if isinstance(v, float) and abs(v) > math.pi:
            raise UsageError(_opt(dest), f"is an angle in rad, within [-pi, pi]; got {v:g} (degrees? "
                                         f"{v:g} deg = {math.radians(v):.4g} rad)")
    if ns.get("zero_offsets") is not None and not all(math.isfinite(v) for v in a.zero_offsets):
        raise UsageError("--zero-offsets", f"must be finite angles (rad), got {a.zero_offsets}")
    if ns.get("zero_offsets") is not None and any(abs(v) > 2 * math.pi for v in a.zero_offsets):
        big = max(a.zero_offsets, key=abs)
        raise UsageError("--zero-offsets", f"are joint angles in rad, within a turn (|q| <= 2 pi); got "
                                           f"{' '.join(f'{v:g}' for v in a.zero_offsets)} (degrees? {big:g} deg = "
                                           f"{math.radians(big):.4g} rad)")
    for x, z in ns.get("control_points") or []:
        if abs(x) > 2 or abs(z) > 2:
            raise UsageError("--control-points", f"are in m: ({x:g}, {z:g}) is more than 2 m from the start (cm? "
                                                 f"({x / 100:g}, {z / 100:g}) m)")
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
        pts = [[float(v) for v in p.split(",")] for p in text.split(";") if p.strip()]
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"control points must look like 'x,z;x,z;...' in m: {e}") from e
    if any(len(p) != 2 for p in pts):
        raise argparse.ArgumentTypeError("each control point needs two numbers 'x,z' (m)")
    return [(x, z) for x, z in pts]


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
    from .. import rft

    if a.toe == "I":
        return rft.IToe(a.length, a.width, tilt=a.tilt, n_segments=a.segments)
    return rft.CToe(a.radius, a.width, n_segments=a.segments, opening=a.opening)


def make_path(a) -> rft.Path:
    from .. import rft

    if a.path == "rectangle":
        start = (-a.shear / 2, 0.0)
        return rft.rectangle_path(a.penetration, a.shear, a.extraction, start=start,
                                  n_steps=a.n_steps, speed=a.speed)
    return rft.spline_path(a.control_points, n_steps=a.n_steps, speed=a.speed)


def add_protocol_args(p) -> None:
    g = p.add_argument_group("CAN protocol")
    g.add_argument("--protocol", choices=["odrive", "mit"], default="odrive",
                   help="ODrive CANSimple (default) or CubeMars/T-Motor AK MIT mode")
    g.add_argument("--firmware", choices=["0.5", "0.6"], default="0.5", help="ODrive firmware layout (default 0.5)")
