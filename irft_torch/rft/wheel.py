"""A rigid wheel rolling in sand: its profile, kinematics and RFT contacts (physics only).

Frame and conventions as everywhere (x right, z up, free surface z = 0, depth = max(0, -z)). The
wheel's body origin is its axle. It translates with speed ``v`` along +x (negative: toward -x) and
spins with ``omega`` [rad/s], positive for *forward* rolling (clockwise when v > 0: the bottom of
the rim moves backward), so the rim speed is omega * radius and

    slip = 1 - v / (omega r)   when omega r >= v   (driving: 0 pure rolling, 1 spinning in place)
    slip = omega r / v - 1     when omega r <  v   (skidding: -1 a locked wheel)

(``slip_ratio``; the skid branch is the convention of the rover-wheel data and of most testbeds,
and keeps slip in [-1, 1]). With its lowest point at depth ``sinkage`` the axle sits at
z = radius - sinkage.

A profile is any ``Toe`` (segments in the axle's frame) traversed counter-clockwise, so that each
segment's outward normal is its tangent rotated by -90 degrees: ``circle_profile`` for a plain rim,
``profile_from_elements`` for a list of surface elements (points, outward normals, lengths), e.g. a
grousered wheel's mesh cut at the mid-plane. ``envelope_profile`` replaces a profile by its convex
hull: the surface that meets the sand when the pockets between grousers fill with sand that turns
with the wheel (the shear surface at the grouser tips of terramechanics, Wong's "Theory of Ground
Vehicles" and Bekker for closely spaced grousers); for a convex rim it is the rim itself.

Which part of the rim is in contact (a modelling choice, stated here): ``contact="leading"``
(default) keeps a submerged segment only when it moves into the sand, i.e. its velocity has a
non-negative component along its outward normal (n . v >= -tol |v|; a segment sliding along its own
tangent counts). The trailing part, moving away from the sand it compacted, is taken to have
separated from it. This is the choice of 3-D RFT's mesh codes (leading facets only) and of the
rover-wheel data's own RFT. For a circular rim translating with v > 0 it is exactly the front half
(n . v = v sin phi for the rim point at angle phi from the bottom, whatever omega is), so the
contact arc at sinkage s spans phi in [0, acos(1 - s / r)]. ``contact="submerged"`` keeps every
submerged segment (2-D plate RFT's convention).

Steady states of a wheel whose contact changes as it turns (grousers) are averaged over a
stationary sequence of poses: ``wheel_contacts(..., phases=...)`` gives one row per pose and
``average_rows`` turns them into a single observation of the mean force (the weights of every pose,
divided by their number), which is what a measured run's mean force is.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .contacts import SURFACE_FIELDS, Contacts, SegmentKinematics, contacts, segment_kinematics
from .paths import Path
from .toes import Toe, _from_vertices, _n_segments, _positive

__all__ = ["circle_profile", "profile_from_elements", "envelope_profile", "slip_ratio", "wheel_speeds", "wheel_path",
           "wheel_kinematics", "contact_mask", "wheel_contacts", "average_rows"]


def circle_profile(radius: float, width: float, n_segments: int = 360, dtype=torch.float64) -> Toe:
    """A circular rim of ``radius`` [m] and ``width`` [m] as ``n_segments`` chords, counter-clockwise,
    centred on the axle (body origin); the first vertex is the lowest point."""
    radius, width = _positive("radius", radius), _positive("width", width)
    M = _n_segments(n_segments)
    if M < 3:
        raise ValueError(f"a closed rim needs n_segments >= 3, got {M}")
    phi = -math.pi / 2 + 2 * math.pi * torch.arange(M + 1, dtype=dtype) / M
    return _from_vertices(radius * torch.stack([torch.cos(phi), torch.sin(phi)], -1), width)


def profile_from_elements(points, normals, lengths, width: float, dtype=torch.float64) -> Toe:
    """A profile from surface elements in the axle's frame.

    Args:
        points: (M, 2) element centres (x, z), m.
        normals: (M, 2) outward normals (normalized here).
        lengths: (M,) element lengths in the plane, m (an element's area divided by ``width``).
        width: out-of-plane width, m.
    """
    width = _positive("width", width)
    p = torch.as_tensor(points, dtype=dtype)
    n = torch.as_tensor(normals, dtype=dtype)
    L = torch.as_tensor(lengths, dtype=dtype)
    if p.ndim != 2 or p.shape[-1] != 2 or n.shape != p.shape or L.shape != p.shape[:1]:
        raise ValueError(f"points and normals must be (M, 2) and lengths (M,), got {tuple(p.shape)}, "
                         f"{tuple(n.shape)}, {tuple(L.shape)}")
    norm = torch.linalg.vector_norm(n, dim=-1, keepdim=True)
    if not (norm > 0).all():
        raise ValueError("normals has a zero vector")
    n = n / norm
    tangent = torch.stack([-n[:, 1], n[:, 0]], -1)  # outward normal = tangent rotated by -90 degrees
    return Toe(p, tangent, L, width)


def envelope_profile(profile: Toe) -> Toe:
    """The convex hull of a profile (counter-clockwise ``Toe`` with the same width): its segments'
    end points (centre -+ tangent x length / 2) hulled, one segment per hull edge. A grousered rim
    becomes the polygon through its grouser tips (the sand in the pockets moves with the wheel); a
    convex rim (``circle_profile``) comes back unchanged up to the order of its segments."""
    if not isinstance(profile, Toe):
        raise TypeError(f"profile must be a Toe, got {type(profile).__name__}")
    import numpy as np
    from scipy.spatial import ConvexHull, QhullError

    half = profile.tangents * (profile.lengths / 2)[:, None]
    pts = torch.cat([profile.centres - half, profile.centres + half]).detach().cpu().double().numpy()
    try:
        hull = pts[ConvexHull(pts).vertices]  # counter-clockwise in 2-D, collinear points dropped
    except QhullError as e:
        raise ValueError("the profile's convex hull is degenerate (all points on a line)") from e
    # adjacent segments' shared end points differ by rounding: merge vertices closer than 1e-6 x size
    size = np.ptp(pts, axis=0).max()
    gap = np.linalg.norm(hull - np.roll(hull, 1, axis=0), axis=1)
    hull = hull[gap > 1e-6 * size]
    if len(hull) < 3:
        raise ValueError("the profile's convex hull is degenerate (all points on a line)")
    v = torch.as_tensor(hull, dtype=profile.centres.dtype, device=profile.centres.device)
    return _from_vertices(torch.cat([v, v[:1]]), profile.width)


def _float_dtype(*xs) -> torch.dtype:
    """The dtype of the widest floating tensor among ``xs``, else torch's default (Python numbers)."""
    fl = [x.dtype for x in xs if isinstance(x, Tensor) and x.dtype.is_floating_point]
    return torch.promote_types(*fl) if len(fl) > 1 else (fl[0] if fl else torch.get_default_dtype())


def slip_ratio(v, omega, radius: float) -> Tensor:
    """Slip of a wheel moving at ``v`` [m/s] with spin ``omega`` [rad/s] (see the module doc); in
    the inputs' floating dtype (torch's default for numbers)."""
    dtype = _float_dtype(v, omega)
    v = torch.as_tensor(v, dtype=dtype)
    rim = torch.as_tensor(omega, dtype=dtype) * radius
    if (v.abs() + rim.abs() == 0).any():
        raise ValueError("slip is undefined for a wheel at rest (v = omega = 0)")
    driving = rim.abs() >= v.abs()
    return torch.where(driving, 1 - v / torch.where(driving, rim, torch.ones_like(rim)),
                       rim / torch.where(driving, torch.ones_like(v), v) - 1)


def wheel_speeds(slip, radius: float, v: float | None = None, rim_speed: float | None = None) -> tuple[Tensor, Tensor]:
    """(v, omega) for a slip in [-1, 1) given either the travel speed ``v`` or the ``rim_speed``; in
    the slip's floating dtype (torch's default for numbers)."""
    s = torch.as_tensor(slip, dtype=_float_dtype(slip))
    if (v is None) == (rim_speed is None):
        raise ValueError("give exactly one of v and rim_speed")
    if ((s < -1) | (s >= 1)).any():
        raise ValueError("slip must lie in [-1, 1)")
    if v is not None:
        rim = torch.where(s >= 0, v / (1 - s), v * (1 + s))
        return torch.full_like(s, float(v)), rim / radius
    vv = torch.where(s >= 0, rim_speed * (1 - s), rim_speed / (1 + s).clamp_min(1e-300))
    return vv, torch.full_like(s, float(rim_speed) / radius)


def wheel_path(v: float, omega: float, radius: float, sinkage: float, phases=None, dtype=torch.float64) -> Path:
    """A stationary sequence of wheel poses: the axle at (0, radius - sinkage), velocity (v, 0),
    heading = -phase (the wheel turned forward by ``phase``), angular velocity -omega.

    ``phases`` [rad] (default: one pose, phase 0); the poses share the same velocities.
    """
    for name, val in (("v", v), ("omega", omega)):
        if not math.isfinite(float(val)):
            raise ValueError(f"{name} must be finite, got {val}")
    radius = _positive("radius", radius)
    if not (math.isfinite(float(sinkage)) and 0 <= float(sinkage) <= 2 * radius):
        raise ValueError(f"sinkage must be between 0 and 2 x radius (m), got {sinkage}")
    ph = torch.zeros(1, dtype=dtype) if phases is None else torch.as_tensor(phases, dtype=dtype).reshape(-1)
    K = ph.shape[0]
    if K == 1:  # Path needs two samples: duplicate, keep the first
        ph2 = torch.cat([ph, ph])
    else:
        ph2 = ph
    n = ph2.shape[0]
    position = torch.tensor([0.0, radius - float(sinkage)], dtype=dtype).expand(n, 2).clone()
    velocity = torch.tensor([float(v), 0.0], dtype=dtype).expand(n, 2).clone()
    return Path(torch.arange(n, dtype=dtype), position, -ph2, velocity, torch.full((n,), -float(omega), dtype=dtype))


def wheel_kinematics(profile: Toe, v: float, omega: float, radius: float, sinkage: float,
                     phases=None) -> SegmentKinematics:
    """Positions, tangents and velocities (v + omega x r) of the profile's segments, (K, M, ...)."""
    path = wheel_path(v, omega, radius, sinkage, phases, dtype=profile.centres.dtype)
    K = 1 if phases is None else torch.as_tensor(phases).numel()
    k = segment_kinematics(profile, path)
    return SegmentKinematics(*(getattr(k, f)[:K] for f in ("position", "tangent", "velocity", "depth", "area")))


def contact_mask(kin: SegmentKinematics, contact: str = "leading", tol: float = 1e-9) -> Tensor:
    """(K, M) bool: which submerged segments are in contact (see the module doc)."""
    if contact not in ("leading", "submerged"):
        raise ValueError(f"contact must be 'leading' or 'submerged', got {contact!r}")
    submerged = kin.depth > 0
    if contact == "submerged":
        return submerged
    return submerged & _moving_into(kin, tol)


def _moving_into(kin: SegmentKinematics, tol: float = 1e-9) -> Tensor:
    """(K, M) bool: which segments move into the sand, n . v >= -tol |v| (whatever their depth)."""
    t, vel = kin.tangent, kin.velocity
    normal = torch.stack([t[..., 1], -t[..., 0]], -1)
    return (normal * vel).sum(-1) >= -tol * torch.linalg.vector_norm(vel, dim=-1).clamp_min(1e-300)


def _check_counter_clockwise(profile: Toe) -> None:
    """ValueError unless the profile turns counter-clockwise about the axle: its signed area
    1/2 sum (x t_z - z t_x) L (m^2, the shoelace formula over the segments) must be positive, or the
    tangents rotated by -90 degrees point inward and "leading" keeps the trailing arc."""
    c, t = profile.centres, profile.tangents
    area = 0.5 * float(((c[:, 0] * t[:, 1] - c[:, 1] * t[:, 0]) * profile.lengths).sum())
    if not area > 0:
        raise ValueError(f"profile must be traversed counter-clockwise (outward normal = tangent rotated by -90 "
                         f"degrees); its signed area is {area:.3g} m^2: reverse its points")


def wheel_contacts(profile: Toe, v: float, omega: float, radius: float, sinkage: float, phases=None,
                   contact: str = "leading", min_speed: float = 1e-9) -> Contacts:
    """RFT contacts of a wheel, one row per pose (K, M): canonical angles and weights in cm^3 exactly
    as ``rft.contacts`` computes them for the profile moving with the wheel, with the segments out of
    contact (above the sand, or trailing for ``contact="leading"``) given weight 0.

    The signed depths (cm) and areas (cm^2) are kept as ``rft.contacts`` keeps them, a trailing
    segment's areas 0 (it never touches, at any surface height), so ``with_surface_offset(delta)`` is
    the wheel ``delta`` m deeper (the leading part of the rim does not depend on the sinkage).

    Args:
        profile: the rim as a counter-clockwise ``Toe`` centred on the axle (clockwise: a ValueError for
            ``contact="leading"``, which finds the outward normals from the order).
        v: travel speed along x, m/s. omega: spin, rad/s, positive rolling forward.
        radius: distance from the axle to the lowest point of the profile, m.
        sinkage: depth of that lowest point below the free surface, m.
        phases: rotation angles of the poses, rad (default one pose).
    """
    if not isinstance(profile, Toe):
        raise TypeError(f"profile must be a Toe, got {type(profile).__name__}")
    if contact == "leading":
        _check_counter_clockwise(profile)
    path = wheel_path(v, omega, radius, sinkage, phases, dtype=profile.centres.dtype)
    K = 1 if phases is None else torch.as_tensor(phases).numel()
    c = contacts(profile, path, min_speed=min_speed)[:K]
    kin = segment_kinematics(profile, path)
    kin = SegmentKinematics(*(getattr(kin, f)[:K] for f in ("position", "tangent", "velocity", "depth", "area")))
    keep = contact_mask(kin, contact).to(c.weight_z.dtype)
    into = _moving_into(kin).to(c.weight_z.dtype) if contact == "leading" else torch.ones_like(keep)
    return Contacts(beta=c.beta, gamma=c.gamma, weight_x=c.weight_x * keep, weight_z=c.weight_z * keep,
                    depth=c.depth, area_x=c.area_x * into, area_z=c.area_z * into)


def average_rows(c: Contacts, drop_zero: bool = True) -> Contacts:
    """One observation of the mean force over the rows (poses) of ``c`` (K, M): shape (1, K*M') with
    every weight divided by K. Contacts with depths and areas keep them (areas divided by K, depths as
    they are), so ``with_surface_offset`` of the average is the average of ``with_surface_offset``.
    ``drop_zero`` removes segments that carry nothing: zero weight in both axes or, with depths and
    areas, zero area in both axes (a segment above the sand but facing it is kept: a higher surface
    brings it into contact)."""
    K = len(c)
    names = ("beta", "gamma", "weight_x", "weight_z", *(SURFACE_FIELDS if c.has_surface else ()))
    flat = {n: getattr(c, n).reshape(1, -1) for n in names}
    if drop_zero:
        carried = ("area_x", "area_z") if c.has_surface else ("weight_x", "weight_z")
        keep = ((flat[carried[0]] != 0) | (flat[carried[1]] != 0))[0]
        if not keep.any():
            keep = keep.clone()
            keep[0] = True  # keep one (zero) segment so the shape stays (1, >= 1)
        flat = {n: t[:, keep] for n, t in flat.items()}
    for n in ("weight_x", "weight_z", "area_x", "area_z"):
        if n in flat:
            flat[n] = flat[n] / K
    return Contacts(**flat)
