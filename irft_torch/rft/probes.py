"""Probes: a toe moved along a path, the unit a robot runs to learn about the ground.

A ``Probe`` is what active probing scores and designs (``irft_torch.design``: ``ProbeScorer``,
``optimize_probe``); ``ProbeBounds`` is the leg's workspace; ``random_probes`` draws an
equal-length library of candidate probes inside it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from .contacts import Contacts, contacts
from .paths import Path, course_path
from .toes import Toe

__all__ = ["Probe", "ProbeBounds", "random_probes"]


@dataclass(frozen=True)
class Probe:
    """A toe moved along a path.

    Attributes:
        toe: the toe (``IToe``, ``CToe``, ``PolylineToe``).
        path: the path of its body frame.
        name: a label for tables and plots.
        spec: for a ``course_path``, the keyword arguments that rebuild it (course and heading knots,
            length, start, n_steps, speed), so a design can start from this probe; else None.
    """

    toe: Toe
    path: Path
    name: str = ""
    spec: dict | None = None

    @classmethod
    def from_course(cls, toe: Toe, name: str = "", **spec) -> Probe:
        """A probe along ``course_path(**spec)``, remembering ``spec``."""
        return cls(toe, course_path(**spec), name, dict(spec))

    def contacts(self) -> Contacts:
        """Per-segment angles and weights along the path, (T, M)."""
        return contacts(self.toe, self.path)

    @property
    def length(self) -> float:
        """Arc length of the body origin's path, m."""
        return float(self.path.length)


@dataclass(frozen=True)
class ProbeBounds:
    """Where a probe may take the toe (the leg's workspace), in m and rad.

    Attributes:
        max_depth: deepest the body origin may go below the surface (z >= -max_depth).
        max_height: highest it may go above the surface (z <= max_height).
        x_range: (x_min, x_max) of the body origin.
        tilt_range: (min, max) toe heading.
    """

    max_depth: float = 0.06
    max_height: float = 0.02
    x_range: tuple[float, float] = (-0.25, 0.25)
    tilt_range: tuple[float, float] = (-math.pi / 2, math.pi / 2)

    def __post_init__(self) -> None:
        for name in ("max_depth", "max_height"):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v < 0 or v > 2.0:
                raise ValueError(f"{name} must be a length in metres in [0, 2], got {v}")
        lo, hi = (float(v) for v in self.x_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi and hi - lo <= 10.0):
            raise ValueError(f"x_range must be (x_min < x_max) in metres, got {self.x_range}")
        tlo, thi = (float(v) for v in self.tilt_range)
        if not (tlo <= thi and abs(tlo) <= math.pi and abs(thi) <= math.pi):
            raise ValueError(f"tilt_range must be (min <= max) within [-pi, pi] rad, got {self.tilt_range}")

    def _excess(self, path: Path) -> Tensor:
        """(T, 6) how far each sample lies beyond each bound (m, or rad for the tilt); 0 inside."""
        x, z, h = path.position[:, 0], path.position[:, 1], path.heading
        return torch.relu(torch.stack([-self.max_depth - z, z - self.max_height, self.x_range[0] - x,
                                       x - self.x_range[1], self.tilt_range[0] - h, h - self.tilt_range[1]], -1))

    def violation(self, path: Path) -> Tensor:
        """How far the path leaves the workspace: the sum over samples of the squared distance
        outside each bound, m^2 (0 inside; differentiable)."""
        return self._excess(path).pow(2).sum()

    def contains(self, path: Path, tol: float = 1e-9) -> bool:
        """Whether every sample lies inside the bounds (within ``tol`` m)."""
        return bool((self._excess(path) <= tol).all())


def _waypoint_course(g: torch.Generator, start_x: float, length: float, bounds: ProbeBounds,
                     n_knots: int) -> Tensor:
    """Course knots (n_knots,) following a random polyline: a steep entry, then legs to random
    waypoints inside the workspace (random depth, random horizontal step that may reverse)."""
    lo, hi = bounds.x_range
    d = bounds.max_depth
    rnd = lambda: float(torch.rand((), generator=g, dtype=torch.float64))  # noqa: E731
    pts = [(start_x, 0.0)]
    direction = 1.0 if rnd() < 0.5 else -1.0
    x, z = start_x + direction * 0.3 * d * rnd(), -d * (0.5 + 0.5 * rnd())
    pts.append((x, z))
    total = math.hypot(x - start_x, z)
    while total < 1.2 * length:
        if rnd() < 0.25:
            direction = -direction
        step = (0.25 + rnd()) * length / 4
        nx = x + direction * step
        if not lo + 0.01 <= nx <= hi - 0.01:
            direction = -direction
            nx = min(max(x + direction * step, lo + 0.01), hi - 0.01)
        nz = -d * (0.1 + 0.9 * rnd())
        total += math.hypot(nx - x, nz - z)
        x, z = nx, nz
        pts.append((x, z))
    leg = torch.tensor(pts, dtype=torch.float64).diff(dim=0)
    cum = torch.cat([leg.new_zeros(1), torch.linalg.vector_norm(leg, dim=-1).cumsum(0)])
    s = torch.linspace(0.0, length, n_knots, dtype=torch.float64)
    k = torch.clamp(torch.searchsorted(cum, s, right=True) - 1, 0, len(leg) - 1)
    angle = torch.atan2(leg[k, 1], leg[k, 0])
    turn = torch.remainder(angle.diff() + math.pi, 2 * math.pi) - math.pi  # unwrap: no 2 pi jumps
    return torch.cat([angle[:1], angle[:1] + turn.cumsum(0)])


def random_probes(toes: Mapping[str, Toe], n: int, length: float, bounds: ProbeBounds | None = None,
                  n_knots: int = 12, n_steps: int = 100, speed: float = 0.02, min_submerged: float = 0.6,
                  seed: int = 0, max_tries: int = 500) -> list[Probe]:
    """``n`` random equal-length probes per toe, inside ``bounds``.

    Each path is a ``course_path`` of ``length`` m starting at the surface at a random x: it enters
    steeply, then follows legs to random waypoints inside the workspace (random depth; horizontal
    steps that may reverse, so the toe also moves toward -x), with its course smoothed through
    ``n_knots`` knots; the toe has a random constant tilt within the bounds. Paths that leave the
    bounds, or spend less than ``min_submerged`` of their samples below the surface, are redrawn.

    Returns:
        A list of ``len(toes) * n`` probes named ``"<toe name> #k (tilt d deg)"``.
    """
    bounds = bounds or ProbeBounds()
    if int(n) != n or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n}")
    g = torch.Generator().manual_seed(seed)
    out = []
    lo, hi = bounds.x_range
    for name, toe in toes.items():
        for k in range(int(n)):
            for _ in range(max_tries):
                u = torch.rand(2, generator=g, dtype=torch.float64)
                start_x = lo + 0.05 * (hi - lo) + 0.9 * (hi - lo) * float(u[0])
                course = _waypoint_course(g, start_x, length, bounds, n_knots)
                tilt = bounds.tilt_range[0] + (bounds.tilt_range[1] - bounds.tilt_range[0]) * float(u[1])
                spec = dict(course=course, length=length, start=(start_x, 0.0), heading=tilt, n_steps=n_steps,
                            speed=speed)
                probe = Probe.from_course(toe, f"{name} #{k} (tilt {math.degrees(tilt):.0f} deg)", **spec)
                submerged = float((probe.path.position[:, 1] < 0).double().mean())
                if bounds.contains(probe.path) and submerged >= min_submerged:
                    break
            else:
                raise RuntimeError(f"no random path of length {length} m fits {bounds} after {max_tries} tries: "
                                   "widen the bounds or shorten the probe")
            out.append(probe)
    return out
