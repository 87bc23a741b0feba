"""Planar paths of a toe's body frame: positions, headings and their rates over time.

A ``Path`` holds T samples of the body origin's position (x, z) [m], heading [rad,
counter-clockwise from +x toward +z], velocity [m/s] and angular velocity [rad/s]. A segment at
body-frame offset r moves with v + omega x r (``contacts`` does that).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .toes import radians

__all__ = ["Path", "rectangle_path", "spline_path", "course_path", "rotating_leg_path", "pose_path"]


@dataclass(frozen=True)
class Path:
    """T samples of a rigid body's planar motion.

    Attributes:
        time: (T,) s, increasing.
        position: (T, 2) body origin (x, z), m.
        heading: (T,) body rotation, rad.
        velocity: (T, 2) body origin velocity, m/s.
        angular_velocity: (T,) d heading / dt, rad/s.
    """

    time: Tensor
    position: Tensor
    heading: Tensor
    velocity: Tensor
    angular_velocity: Tensor

    def __post_init__(self) -> None:
        T = self.time.shape[0] if self.time.ndim == 1 else -1
        want = {"time": (T,), "position": (T, 2), "heading": (T,), "velocity": (T, 2),
                "angular_velocity": (T,)}
        for name, shape in want.items():
            v = getattr(self, name)
            if tuple(v.shape) != shape:
                raise ValueError(f"Path.{name} should have shape {shape}, got {tuple(v.shape)}")
            if not torch.isfinite(v).all():
                raise ValueError(f"Path.{name} contains NaN or inf")
        if T < 2:
            raise ValueError(f"a path needs at least 2 samples, got {T}")

    def __len__(self) -> int:
        return self.time.shape[0]

    @property
    def length(self) -> Tensor:
        """Arc length of the body origin's trajectory, m."""
        return torch.linalg.vector_norm(self.position.diff(dim=0), dim=-1).sum()


def _check_count(name: str, n: int, minimum: int = 2) -> int:
    if int(n) != n or int(n) < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {n}")
    return int(n)


def _check_speed(speed: float) -> float:
    speed = float(speed)
    if not math.isfinite(speed) or speed <= 0:
        raise ValueError(f"speed must be a positive finite value in m/s, got {speed}")
    return speed


def _polyline_path(vertices: Tensor, n_steps: int, speed: float) -> Path:
    """Constant-speed motion along straight legs; samples evenly spaced in arc length.

    A sample's velocity is along the leg it lies on (at a corner, the leg it starts).
    """
    legs = vertices[1:] - vertices[:-1]
    leg_len = torch.linalg.vector_norm(legs, dim=-1)
    cum = torch.cat([leg_len.new_zeros(1), leg_len.cumsum(0)])
    s = torch.linspace(0, 1, n_steps, dtype=vertices.dtype) * cum[-1]
    k = torch.clamp(torch.searchsorted(cum, s, right=True) - 1, 0, len(legs) - 1)
    frac = (s - cum[k]) / leg_len[k]
    position = vertices[k] + frac[:, None] * legs[k]
    velocity = speed * legs[k] / leg_len[k, None]
    zeros = torch.zeros(n_steps, dtype=vertices.dtype)
    return Path(s / speed, position, zeros, velocity, zeros.clone())


def rectangle_path(
    penetration: float = 0.05,
    shear: float = 0.40,
    extraction: float = 0.05,
    start: tuple[float, float] = (-0.20, 0.0),
    n_steps: int = 200,
    speed: float = 0.02,
    dtype=torch.float64,
) -> Path:
    """The paper's gait 1: straight down by ``penetration``, along +x by ``shear``, up by
    ``extraction`` (all m), at constant ``speed`` [m/s], heading 0.

    Samples are evenly spaced in arc length (a fixed sampling rate at constant speed).
    """
    for name, v in (("penetration", penetration), ("shear", shear), ("extraction", extraction)):
        if not math.isfinite(float(v)) or float(v) < 0:
            raise ValueError(f"{name} must be a finite length >= 0 in metres, got {v}")
        if float(v) > 5.0:
            raise ValueError(f"{name}={v} m is implausibly large: lengths are in metres")
    n_steps = _check_count("n_steps", n_steps)
    speed = _check_speed(speed)
    x0, z0 = (float(c) for c in start)
    corners = [(x0, z0), (x0, z0 - penetration), (x0 + shear, z0 - penetration),
               (x0 + shear, z0 - penetration + extraction)]
    vertices = torch.tensor(corners, dtype=dtype)
    keep = torch.cat([torch.tensor([True]), torch.linalg.vector_norm(vertices.diff(dim=0), dim=-1) > 0])
    if keep.sum() < 2:
        raise ValueError("rectangle_path has zero length")
    return _polyline_path(vertices[keep], n_steps, speed)


def _natural_cubic_spline(x: Tensor, y: Tensor) -> Tensor:
    """Second derivatives (K,) at the knots of the natural cubic spline through (x, y).

    Written in torch so positions are differentiable in the control points.
    """
    K = x.shape[0]
    h = x.diff()
    if K == 2:
        return torch.zeros_like(y)
    A = torch.zeros(K, K, dtype=x.dtype)
    rhs = torch.zeros(K, dtype=x.dtype)
    A[0, 0] = A[-1, -1] = 1.0
    i = torch.arange(1, K - 1)
    A = A.index_put((i, i - 1), h[:-1]).index_put((i, i), 2 * (h[:-1] + h[1:]))
    A = A.index_put((i, i + 1), h[1:])
    rhs = rhs.index_put((i,), 6 * ((y[2:] - y[1:-1]) / h[1:] - (y[1:-1] - y[:-2]) / h[:-1]))
    return torch.linalg.solve(A, rhs)


def _spline_eval(x: Tensor, y: Tensor, m: Tensor, xq: Tensor) -> tuple[Tensor, Tensor]:
    """Value and slope dy/dx of the cubic spline (knots x, values y, second derivatives m) at xq."""
    k = torch.searchsorted(x.detach().contiguous(), xq.detach().contiguous(), right=True) - 1
    k = torch.clamp(k, 0, x.shape[0] - 2)
    h = x[k + 1] - x[k]
    a = (x[k + 1] - xq) / h
    b = (xq - x[k]) / h
    value = a * y[k] + b * y[k + 1] + ((a**3 - a) * m[k] + (b**3 - b) * m[k + 1]) * h**2 / 6
    slope = (y[k + 1] - y[k]) / h + ((1 - 3 * a**2) * m[k] + (3 * b**2 - 1) * m[k + 1]) * h / 6
    return value, slope


def spline_path(
    control_points: Sequence[Sequence[float]] | Tensor,
    n_steps: int = 200,
    speed: float = 0.02,
    dtype=torch.float64,
) -> Path:
    """The paper's gait 2: a natural cubic spline z(x) through control points (m), heading 0.

    The toe moves toward +x at constant ``speed`` [m/s]; samples are (very nearly) evenly spaced
    in arc length. Positions and velocities are differentiable in ``control_points`` when it is a
    tensor that requires grad (for designing paths by gradient descent).

    Args:
        control_points: (K >= 2, 2) points (x, z) in m with x strictly increasing.
    """
    pts = control_points if isinstance(control_points, Tensor) else torch.tensor(control_points, dtype=dtype)
    pts = pts.to(dtype)
    if pts.ndim != 2 or pts.shape[-1] != 2 or pts.shape[0] < 2:
        raise ValueError(f"control_points must be (K >= 2, 2), got {tuple(pts.shape)}")
    if not torch.isfinite(pts).all():
        raise ValueError("control_points contains NaN or inf")
    if not (pts[1:, 0] > pts[:-1, 0]).all():
        raise ValueError("control_points must have strictly increasing x (the spline is z(x))")
    if (pts.max(0).values - pts.min(0).values).max() > 5.0:
        raise ValueError("control_points span more than 5 m: lengths are in metres (cm or mm passed?)")
    n_steps = _check_count("n_steps", n_steps)
    speed = _check_speed(speed)
    x, y = pts[:, 0], pts[:, 1]
    m = _natural_cubic_spline(x, y)
    # Arc-length parametrization, computed without gradient on a dense grid: it only chooses
    # where to sample; positions at those parameters stay differentiable.
    with torch.no_grad():
        u_dense = torch.linspace(0, 1, 20 * n_steps + 1, dtype=dtype)
        _, sl = _spline_eval(x, y, m, x[0] + (x[-1] - x[0]) * u_dense)
        ds = torch.sqrt(1 + sl**2) * (x[-1] - x[0])
        arc = torch.cat([ds.new_zeros(1), torch.cumulative_trapezoid(ds, u_dense)])
        target = torch.linspace(0, 1, n_steps, dtype=dtype) * arc[-1]
        j = torch.clamp(torch.searchsorted(arc, target, right=True) - 1, 0, len(arc) - 2)
        u = u_dense[j] + (target - arc[j]) / (arc[j + 1] - arc[j]) * (u_dense[j + 1] - u_dense[j])
        time = target / speed
    xq = x[0] + (x[-1] - x[0]) * u
    z, slope = _spline_eval(x, y, m, xq)
    tangent = torch.stack([torch.ones_like(slope), slope], dim=-1)
    velocity = speed * tangent / torch.linalg.vector_norm(tangent, dim=-1, keepdim=True)
    zeros = torch.zeros(n_steps, dtype=dtype)
    return Path(time, torch.stack([xq, z], dim=-1), zeros, velocity, zeros.clone())


def _knot_values(name: str, values, dtype) -> Tensor:
    v = values if isinstance(values, Tensor) else torch.as_tensor(values, dtype=dtype)
    v = v.to(dtype).reshape(-1) if v.ndim == 0 else v.to(dtype)
    if v.ndim != 1 or v.shape[0] < 1:
        raise ValueError(f"{name} must be a scalar or a 1-D sequence of knot values, got shape {tuple(v.shape)}")
    if not torch.isfinite(v).all():
        raise ValueError(f"{name} contains NaN or inf")
    return v


def _profile(values: Tensor, s: Tensor, length: float) -> tuple[Tensor, Tensor]:
    """A natural cubic spline through K knots evenly spaced over [0, length], and its slope, at s."""
    if values.shape[0] == 1:
        return values.expand(s.shape[0]), torch.zeros_like(s)
    knots = torch.linspace(0.0, length, values.shape[0], dtype=values.dtype)
    return _spline_eval(knots, values, _natural_cubic_spline(knots, values), s)


def course_path(
    course,
    length: float,
    start: tuple[float, float] = (-0.20, 0.0),
    heading=0.0,
    n_steps: int = 200,
    speed: float = 0.02,
    substeps: int = 8,
    dtype=torch.float64,
) -> Path:
    """A path of exactly ``length`` metres given by its direction of motion along the arc length.

    The body origin starts at ``start`` (x, z) [m] and moves at constant ``speed`` [m/s] in the
    direction ``course(s)`` [rad, counter-clockwise from +x: -pi/2 is straight down], a natural cubic
    spline through the K values of ``course`` at knots evenly spaced over s in [0, length] (K = 1:
    a straight line). The toe's ``heading`` [rad] is a constant or likewise a spline through K_h knot
    values (the toe then turns, with angular velocity speed x d heading / ds). Samples are evenly
    spaced in arc length; positions are the velocity integrated by the trapezoidal rule on
    ``substeps`` sub-intervals per sample.

    Because the length is fixed by construction, equal-length probes are compared fairly, and the
    path is differentiable in ``course`` and ``heading`` when they are tensors that require grad
    (gradient-based probe design).
    """
    L = float(length)
    if not math.isfinite(L) or L <= 0:
        raise ValueError(f"length must be a positive finite path length in metres, got {length}")
    if L > 5.0:
        raise ValueError(f"length={L} m is implausibly large: lengths are in metres (cm or mm passed?)")
    n_steps = _check_count("n_steps", n_steps)
    speed = _check_speed(speed)
    substeps = _check_count("substeps", substeps, minimum=1)
    course = _knot_values("course", course, dtype)
    heading = _knot_values("heading", heading, dtype)
    x0, z0 = (float(c) for c in start)
    n_fine = (n_steps - 1) * substeps + 1
    s_fine = torch.linspace(0.0, L, n_fine, dtype=dtype)
    psi, _ = _profile(course, s_fine, L)
    direction = torch.stack([torch.cos(psi), torch.sin(psi)], dim=-1)  # unit velocity direction
    offset = torch.cumulative_trapezoid(direction, dx=L / (n_fine - 1), dim=0)
    offset = torch.cat([direction.new_zeros(1, 2), offset])
    position = (offset + torch.tensor([x0, z0], dtype=dtype))[::substeps]
    s = s_fine[::substeps]
    h, dh = _profile(heading, s, L)
    return Path(s / speed, position, h, speed * direction[::substeps], speed * dh)


def rotating_leg_path(
    hip: tuple[float, float] = (0.0, 0.04),
    start_angle: float = 0.0,
    sweep: float = math.pi,
    angular_speed: float = 1.0,
    direction: str = "cw",
    n_steps: int = 200,
    dtype=torch.float64,
) -> Path:
    """A leg rotating about a fixed hip (a RHex-style C-leg): the body origin stays at ``hip``
    and the heading turns by ``sweep`` [rad] at ``angular_speed`` [rad/s].

    Express the toe relative to the hip (e.g. ``CToe(...).shifted(dx, dz)``): each segment then
    moves on a circle about the hip with velocity omega x r.

    Args:
        direction: "cw" (clockwise as drawn with x right and z up: heading decreasing, so a
            toe below the hip sweeps toward -x and pushes the body toward +x) or "ccw".
    """
    if direction not in ("cw", "ccw"):
        raise ValueError(f"direction must be 'cw' or 'ccw', got {direction!r}")
    for name, v in (("sweep", sweep), ("angular_speed", angular_speed)):
        if not math.isfinite(float(v)) or float(v) <= 0:
            raise ValueError(f"{name} must be positive and finite, got {v}")
    n_steps = _check_count("n_steps", n_steps)
    start_angle = radians("start_angle", start_angle)
    sweep = radians("sweep", sweep, limit=8 * math.pi)  # a few turns are a leg's many strides; 180 is degrees
    sign = -1.0 if direction == "cw" else 1.0
    time = torch.linspace(0, sweep / angular_speed, n_steps, dtype=dtype)
    heading = start_angle + sign * angular_speed * time
    position = torch.tensor(hip, dtype=dtype).expand(n_steps, 2).clone()
    omega = torch.full((n_steps,), sign * angular_speed, dtype=dtype)
    return Path(time, position, heading, torch.zeros(n_steps, 2, dtype=dtype), omega)


def _rate(values: Tensor, time: Tensor) -> Tensor:
    """d values / d time by finite differences, second order everywhere (non-uniform steps allowed): central
    inside, one-sided over three samples at the first and last (first order with two samples). A run cut
    short mid-motion ends with a velocity as good as its inside's (a first-order end put the direction of
    motion, and so a force, a sample's worth of curvature off)."""
    if values.ndim == 1:
        return _rate(values[:, None], time)[:, 0]
    T = time.shape[0]
    out = torch.empty_like(values)
    if T == 2:
        out[:] = (values[1] - values[0]) / (time[1] - time[0])
        return out
    h1 = (time[1:-1] - time[:-2])[:, None]
    h2 = (time[2:] - time[1:-1])[:, None]
    out[1:-1] = (h1**2 * values[2:] - h2**2 * values[:-2] + (h2**2 - h1**2) * values[1:-1]) / (
        h1 * h2 * (h1 + h2)
    )
    a, b = time[1] - time[0], time[2] - time[1]  # numpy.gradient's edge_order=2
    out[0] = (-(2 * a + b) / (a * (a + b)) * values[0] + (a + b) / (a * b) * values[1]
              - a / (b * (a + b)) * values[2])
    a, b = time[-2] - time[-3], time[-1] - time[-2]
    out[-1] = (b / (a * (a + b)) * values[-3] - (a + b) / (a * b) * values[-2]
               + (2 * b + a) / (b * (a + b)) * values[-1])
    return out


def pose_path(time, x, z, heading=None, dtype=torch.float64) -> Path:
    """A path from sampled poses, e.g. a leg's forward kinematics over a joint log.

    Velocities and the angular velocity come from finite differences in time (second order: central inside,
    one-sided at the ends);
    headings are unwrapped first.

    Args:
        time: (T,) s, strictly increasing.
        x: (T,) body origin, horizontal, m.
        z: (T,) body origin, vertical (up), m.
        heading: (T,) rad, default 0.
    """
    t = torch.as_tensor(time, dtype=dtype)
    xs = torch.as_tensor(x, dtype=dtype)
    zs = torch.as_tensor(z, dtype=dtype)
    h = torch.zeros_like(t) if heading is None else torch.as_tensor(heading, dtype=dtype)
    for name, v in (("time", t), ("x", xs), ("z", zs), ("heading", h)):
        if v.ndim != 1:
            raise ValueError(f"{name} must be 1-D (T,), got shape {tuple(v.shape)}")
        if v.shape[0] != t.shape[0]:
            raise ValueError(f"{name} has {v.shape[0]} samples, time has {t.shape[0]}")
        if not torch.isfinite(v).all():
            bad = int((~torch.isfinite(v)).nonzero()[0])
            raise ValueError(f"{name} contains NaN or inf (first at sample {bad})")
    if t.shape[0] < 2:
        raise ValueError(f"a path needs at least 2 poses, got {t.shape[0]}")
    if not (t.diff() > 0).all():
        raise ValueError("time must be strictly increasing")
    # Unwrap headings so a turn through +-pi is not a jump of 2 pi.
    dh = h.diff()
    dh = torch.remainder(dh + math.pi, 2 * math.pi) - math.pi
    h = torch.cat([h[:1], h[:1] + dh.cumsum(0)])
    pos = torch.stack([xs, zs], dim=-1)
    return Path(t, pos, h, _rate(pos, t), _rate(h, t))
