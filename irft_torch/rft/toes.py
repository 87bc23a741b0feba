"""Toe geometries, discretized into M straight segments in the toe's body frame.

The body frame is the frame the path moves: a path sample (x, z, heading) places the body origin
at (x, z) and rotates the body by ``heading`` (counter-clockwise, from +x toward +z). Lengths are
in metres. Where each toe puts its origin is stated on its class.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Toe", "IToe", "CToe", "PolylineToe"]

_LARGE_TOE_M = 1.0  # a toe larger than this is almost surely millimetres passed as metres


def radians(name: str, value: float, limit: float = 2 * math.pi) -> float:
    """``value`` as a finite angle in rad; a ``UserWarning`` above ``limit`` in magnitude (default one turn),
    where the number was almost surely given in degrees."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be a finite angle in rad, got {value}")
    if abs(value) > limit:
        warnings.warn(f"{name}={value} rad is more than {limit / (2 * math.pi):g} turn(s): angles are in radians "
                      f"(did you pass degrees? {value} deg = {math.radians(value):.4g} rad)", UserWarning, stacklevel=3)
    return value


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite length in metres, got {value}")
    if value > _LARGE_TOE_M:
        warnings.warn(
            f"{name}={value} m is larger than {_LARGE_TOE_M} m: lengths are in metres "
            "(did you pass millimetres?)",
            UserWarning,
            stacklevel=3,
        )
    return value


def _n_segments(n: int) -> int:
    if int(n) != n or int(n) < 1:
        raise ValueError(f"n_segments must be an integer >= 1, got {n}")
    return int(n)


@dataclass(frozen=True)
class Toe:
    """A toe as M straight segments in its body frame.

    Attributes:
        centres: (M, 2) segment mid-points (x, z) in m.
        tangents: (M, 2) unit tangents (x, z).
        lengths: (M,) segment lengths in m.
        width: out-of-plane width in m (area of segment m = lengths[m] * width).
    """

    centres: Tensor
    tangents: Tensor
    lengths: Tensor
    width: float

    def __post_init__(self) -> None:
        M = self.centres.shape[0] if self.centres.ndim == 2 else -1
        if self.centres.shape != (M, 2) or self.tangents.shape != (M, 2) or self.lengths.shape != (M,):
            raise ValueError(
                "Toe expects centres (M, 2), tangents (M, 2), lengths (M,); got "
                f"{tuple(self.centres.shape)}, {tuple(self.tangents.shape)}, {tuple(self.lengths.shape)}"
            )
        for name in ("centres", "tangents", "lengths"):
            if not torch.isfinite(getattr(self, name)).all():
                raise ValueError(f"Toe.{name} contains NaN or inf")
        if (self.lengths < 0).any():
            raise ValueError("Toe.lengths must be >= 0")

    @property
    def n_segments(self) -> int:
        return self.centres.shape[0]

    @property
    def areas(self) -> Tensor:
        """(M,) segment areas in m^2."""
        return self.lengths * self.width

    def shifted(self, dx: float, dz: float) -> Toe:
        """The same toe with its body origin moved so that every point gets (+dx, +dz)."""
        offset = torch.tensor([dx, dz], dtype=self.centres.dtype)
        return Toe(self.centres + offset, self.tangents, self.lengths, self.width)

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Toe:
        return Toe(
            self.centres.to(dtype=dtype, device=device),
            self.tangents.to(dtype=dtype, device=device),
            self.lengths.to(dtype=dtype, device=device),
            self.width,
        )


def _from_vertices(vertices: Tensor, width: float) -> Toe:
    """Segments between consecutive vertices (K, 2) -> Toe with K - 1 segments."""
    d = vertices[1:] - vertices[:-1]
    lengths = torch.linalg.vector_norm(d, dim=-1)
    if (lengths <= 0).any():
        raise ValueError("polyline has repeated consecutive points (a zero-length segment)")
    return Toe((vertices[1:] + vertices[:-1]) / 2, d / lengths[:, None], lengths, width)


def IToe(
    length: float, width: float, tilt: float = 0.0, n_segments: int = 10, dtype=torch.float64
) -> Toe:
    """A flat plate (the paper's I-toe) centred on the body origin.

    Args:
        length: plate length in the x-z plane, m.
        width: out-of-plane width, m.
        tilt: plate angle from the body x axis, rad (counter-clockwise).
        n_segments: M.
    """
    length, width = _positive("length", length), _positive("width", width)
    tilt = radians("tilt", tilt)
    M = _n_segments(n_segments)
    s = (torch.arange(M + 1, dtype=dtype) / M - 0.5) * length
    direction = torch.tensor([math.cos(tilt), math.sin(tilt)], dtype=dtype)
    return _from_vertices(s[:, None] * direction, width)


_OPENINGS = {"up": -math.pi / 2, "down": math.pi / 2, "left": 0.0, "right": math.pi}


def CToe(
    radius: float,
    width: float,
    n_segments: int = 10,
    opening: str = "up",
    dtype=torch.float64,
) -> Toe:
    """A semicircular toe (the paper's C-toe), as M equal arcs replaced by their chords.

    The body origin is the arc's mid-point (its lowest point for ``opening="up"``, the default: a
    rocker whose convex side meets the ground), so a path gives the path of that point.

    Args:
        radius: arc radius, m.
        width: out-of-plane width, m.
        n_segments: M.
        opening: the side the open face of the semicircle looks to: "up" (a cup, default),
            "down", "left" or "right" (the letter C).
    """
    radius, width = _positive("radius", radius), _positive("width", width)
    M = _n_segments(n_segments)
    if opening not in _OPENINGS:
        raise ValueError(f"opening must be one of {sorted(_OPENINGS)}, got {opening!r}")
    mid = _OPENINGS[opening]  # direction from the circle's centre to the arc's mid-point
    phi = mid + (torch.arange(M + 1, dtype=dtype) / M - 0.5) * math.pi
    vertices = radius * torch.stack([torch.cos(phi), torch.sin(phi)], dim=-1)
    vertices = vertices - radius * torch.tensor([math.cos(mid), math.sin(mid)], dtype=dtype)
    return _from_vertices(vertices, width)


def PolylineToe(points, width: float, n_segments: int | None = None, dtype=torch.float64) -> Toe:
    """A toe along a polyline through ``points`` ((K, 2) in m, body frame).

    With ``n_segments`` given, the polyline is resampled into that many segments of equal length;
    otherwise each pair of consecutive points is one segment.
    """
    width = _positive("width", width)
    pts = torch.as_tensor(points, dtype=dtype)
    if pts.ndim != 2 or pts.shape[-1] != 2 or pts.shape[0] < 2:
        raise ValueError(f"points must be (K >= 2, 2), got {tuple(pts.shape)}")
    if not torch.isfinite(pts).all():
        raise ValueError("points contains NaN or inf")
    extent = (pts.max(0).values - pts.min(0).values).max().item()
    if extent > _LARGE_TOE_M:
        warnings.warn(
            f"toe points span {extent} m: lengths are in metres (did you pass millimetres?)",
            UserWarning,
            stacklevel=2,
        )
    if n_segments is None:
        return _from_vertices(pts, width)
    M = _n_segments(n_segments)
    seg = torch.linalg.vector_norm(pts[1:] - pts[:-1], dim=-1)
    cum = torch.cat([torch.zeros(1, dtype=dtype), seg.cumsum(0)])
    if cum[-1] <= 0:
        raise ValueError("points has zero total length")
    s = torch.linspace(0, 1, M + 1, dtype=dtype) * cum[-1]
    k = torch.clamp(torch.searchsorted(cum, s, right=True) - 1, 0, len(seg) - 1)
    frac = ((s - cum[k]) / seg[k].clamp_min(1e-300))[:, None]
    vertices = pts[k] + frac * (pts[k + 1] - pts[k])
    return _from_vertices(vertices, width)
