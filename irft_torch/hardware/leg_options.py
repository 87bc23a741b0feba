"""Which leg options would make a log's toe path plausible, when the ones given do not.

A wrong node order, motor direction or gear ratio turns the encoder readings into joint angles of
another pose: the toe ends up above the hips, out of reach, or deeper than any stroke, and the
physical checks of ``irft ingest`` fail. Each of them used to be blamed on "--hip-height and
--l1/--l2". ``suggest_leg_options`` tries the other node orders, direction signs and common gear
ratios on the log's encoder positions and names those under which every sample is reachable and
the toe dips into the sand no deeper than ``max_depth``.
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import replace

import numpy as np
import torch

from .five_bar import FiveBarLeg, SingularConfigurationWarning
from .motor import MotorModel

__all__ = ["suggest_leg_options", "plausible_path", "COMMON_GEAR_RATIOS"]

COMMON_GEAR_RATIOS = (1.0, 6.0, 9.0, 10.0, 36.0, 64.0)  # direct drive, AK80-6, AK80-9 / AK10-9, AK70-10, ...


def plausible_path(leg: FiveBarLeg, q: np.ndarray, hip_height: float, max_depth: float | None) -> tuple[bool, str]:
    """Whether joint angles q (T, 2) rad give a toe path a leg in sand can run: at least 95 % of the
    samples reachable, the toe below the surface (``hip_height`` m under the motor axes) at some
    sample and never deeper than ``max_depth`` m. Returns (ok, a short description of the path)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SingularConfigurationWarning)
        toe = leg.forward_kinematics(torch.as_tensor(q)).numpy()
    reach = np.isfinite(toe).all(1)
    if reach.mean() < 0.95:
        return False, f"{100 * (1 - reach.mean()):.0f} % of the samples out of reach"
    z = toe[reach, 1] + hip_height
    depth = -float(z.min())
    ok = depth > 0 and (max_depth is None or depth <= max_depth)
    return ok, f"the toe reaches {depth:.3f} m below the surface" if depth > 0 else "the toe never in the sand"


def suggest_leg_options(position: np.ndarray, leg: FiveBarLeg, motors: tuple[MotorModel, MotorModel],
                        nodes: tuple[int, int], hip_height: float, max_depth: float | None,
                        n: int = 200) -> str:
    """A sentence naming the options under which the encoder positions (T, 2) [motor turns, in the
    order of ``nodes``] give a plausible toe path (``plausible_path``), when the given ones do not;
    '' when the given ones do or no alternative does. Tries the other node order, every pair of
    direction signs and ``COMMON_GEAR_RATIOS`` (the zero offsets are kept). Evaluated on ``n``
    evenly spaced samples."""
    pos = np.asarray(position, dtype=float)
    pos = pos[np.linspace(0, len(pos) - 1, min(n, len(pos))).round().astype(int)]
    pos = pos[np.isfinite(pos).all(1)]
    if len(pos) == 0:
        return ""

    def angles(p, ms):
        return np.stack([ms[i].joint_angle(torch.as_tensor(p[:, i])).numpy() for i in range(2)], -1)

    if plausible_path(leg, angles(pos, motors), hip_height, max_depth)[0]:
        return ""
    given = (tuple(nodes), (motors[0].direction, motors[1].direction), motors[0].gear_ratio)
    found = []
    for swap, dirs, gear in itertools.product((False, True), itertools.product((1, -1), repeat=2),
                                              sorted({motors[0].gear_ratio, *COMMON_GEAR_RATIOS})):
        order = tuple(nodes[::-1]) if swap else tuple(nodes)
        if (order, dirs, gear) == given:
            continue
        p = pos[:, ::-1] if swap else pos
        ms = tuple(replace(motors[i], direction=dirs[i], gear_ratio=gear) for i in range(2))
        ok, what = plausible_path(leg, angles(p, ms), hip_height, max_depth)
        if ok:
            changes = []
            if swap:
                changes.append(f"--nodes {order[0]} {order[1]}")
            if dirs != given[1]:
                changes.append(f"--directions {dirs[0]} {dirs[1]}")
            if gear != given[2]:
                changes.append(f"--gear-ratio {gear:g}")
            found.append((len(changes), " ".join(changes), what))
    if not found:
        return ""
    found.sort()
    fewest = [f for f in found if f[0] == found[0][0]][:3]
    options = " or ".join(f"{c} ({w})" for _, c, w in fewest)
    return f"The toe path is one a leg in sand runs with {options}: check those options first"
