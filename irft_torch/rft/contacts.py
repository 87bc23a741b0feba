"""Per-segment contact state of a toe moving along a path: the inputs of RFT and of I-RFT.

For segment m at time t (world frame, x right, z up, free surface at z = 0):

    beta  = tilt of the segment from the horizontal, wrapped to [-pi/2, pi/2)
    gamma = atan2(-v_z, v_x), direction of the segment's velocity, positive downward
    depth = max(0, -z) of the segment's centre

Motion toward -x is mirrored into the canonical square (beta, gamma) -> (-beta, pi - gamma), and
the sign of the x contribution flipped (an exact identity of the Fourier form), so every stored
angle pair lies in [-pi/2, pi/2]^2 and

    F_x[t] = sum_m weight_x[t, m] alpha_x(beta[t, m], gamma[t, m])
    F_z[t] = sum_m weight_z[t, m] alpha_z(beta[t, m], gamma[t, m])

with weight_z = depth [cm] x area [cm^2] (cm^3) and weight_x = -sign(v_x) weight_z: drag opposes
the horizontal motion.

The free surface is rarely known exactly. ``contacts`` therefore also keeps, per segment, the signed
centre depth (cm, positive below the stated surface, negative above it) and the signed areas that
multiply it on each axis (cm^2, zero for a segment too slow to have a direction), so that
``Contacts.with_surface_offset(delta)`` recomputes the weights for a surface ``delta`` m higher than
stated (converted to cm with ``M_TO_CM``), differentiably in ``delta``: weight = relu(depth + delta)
x area (docs/surface.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .paths import Path
from .stress_maps import wrap_beta
from .toes import Toe

__all__ = ["Contacts", "SegmentKinematics", "segment_kinematics", "contacts", "check_locations", "M_TO_CM",
           "SURFACE_FIELDS"]

M_TO_CM = 100.0  # the one place that converts SI lengths to the literature's centimetres
SURFACE_FIELDS = ("depth", "area_x", "area_z")  # the optional fields that let the surface move


@dataclass
class Contacts:
    """Per-segment RFT inputs: four tensors of shape (..., T, M) on one device and dtype.

    Attributes:
        beta: segment tilt in the canonical square, rad.
        gamma: velocity direction in the canonical square, rad.
        weight_x: signed weight of alpha_x in F_x, cm^3 (zero above the surface).
        weight_z: weight of alpha_z in F_z, cm^3, >= 0 (zero above the surface).
        depth: optional (all three or none): signed depth of each segment's centre below the stated
            surface, cm (negative above it, where the weights are zero).
        area_x: optional: the signed area multiplying relu(depth) in weight_x, cm^2 (it carries the
            sign of the drag, and is zero for a segment too slow to have a direction).
        area_z: optional: the area multiplying relu(depth) in weight_z, cm^2, >= 0.
        locations: optional (..., T, 2): each sample's place on the ground (x, y), m, world frame (a foothold, or
            where a drag has moved to): what a model of maps that change over the ground needs
            (``InverseRFT(..., locations=)``). Carried by indexing, ``cat``, ``to`` and the weight changes; not
            in ``as_dict`` (the per-segment tensors).

    With the optional three, ``weight_c = relu(depth) * area_c`` (checked), and
    ``with_surface_offset`` can move the surface; without them (older datasets, hand-built
    contacts) everything else works the same.
    """

    beta: Tensor
    gamma: Tensor
    weight_x: Tensor
    weight_z: Tensor
    depth: Tensor | None = None
    area_x: Tensor | None = None
    area_z: Tensor | None = None
    locations: Tensor | None = None

    def __post_init__(self) -> None:
        extra = [getattr(self, n) is None for n in SURFACE_FIELDS]
        if any(extra) and not all(extra):
            missing = [n for n, e in zip(SURFACE_FIELDS, extra) if e]
            raise ValueError(f"Contacts.depth, area_x and area_z go together (all three or none); missing {missing}")
        names = [f.name for f in fields(self) if getattr(self, f.name) is not None and f.name != "locations"]
        for name in names:
            v = getattr(self, name)
            if not isinstance(v, Tensor):
                v = torch.as_tensor(v, dtype=torch.get_default_dtype())
                setattr(self, name, v)
            if v.ndim < 2:
                raise ValueError(f"Contacts.{name} must be (..., T, M), got shape {tuple(v.shape)}")
            if not v.dtype.is_floating_point:
                raise ValueError(f"Contacts.{name} must be a floating tensor, got {v.dtype}")
            if not torch.isfinite(v).all():
                raise ValueError(f"Contacts.{name} contains NaN or inf")
        shape = self.beta.shape
        for name in names[1:]:
            if getattr(self, name).shape != shape:
                raise ValueError(
                    f"Contacts.{name} has shape {tuple(getattr(self, name).shape)}, "
                    f"beta has {tuple(shape)}: all four must match"
                )
        if self.locations is not None:
            loc = check_locations(self.locations, name="Contacts.locations").to(self.beta)
            if loc.shape != (*self.beta.shape[:-1], 2):
                raise ValueError(f"Contacts.locations must be {(*tuple(self.beta.shape[:-1]), 2)}, one place (x, y) "
                                 f"in m per sample, got shape {tuple(loc.shape)}")
            self.locations = loc
        if (self.weight_z < 0).any():
            raise ValueError("Contacts.weight_z must be >= 0 (depth x area)")
        if self.has_surface:
            if (self.area_z < 0).any():
                raise ValueError("Contacts.area_z must be >= 0 (cm^2)")
            d = torch.relu(self.depth)
            for axis in ("x", "z"):
                w, a = getattr(self, f"weight_{axis}"), getattr(self, f"area_{axis}")
                with torch.no_grad():
                    err = (w - d * a).abs().max() if w.numel() else w.new_zeros(())
                    tol = 1e-5 * float(w.abs().max()) if w.numel() else 0.0
                if float(err) > max(tol, 1e-12):
                    raise ValueError(f"Contacts.weight_{axis} must equal relu(depth) * area_{axis} (max difference "
                                     f"{float(err):.3g} cm^3): depth, area_x, area_z do not describe these weights")

    @property
    def has_surface(self) -> bool:
        """Whether the signed depths and areas are kept (``with_surface_offset`` works)."""
        return self.depth is not None

    def _apply(self, fn, on_locations: bool = True) -> Contacts:
        """fn applied to every tensor held (the optional ones where present; the locations too where
        ``on_locations``, else kept as they are)."""
        loc = self.locations if self.locations is None or not on_locations else fn(self.locations)
        return Contacts(**{k: fn(v) for k, v in self.as_dict().items()}, locations=loc)

    def with_locations(self, locations) -> Contacts:
        """The same contacts with each sample's place on the ground, (..., T, 2) m (None: without places)."""
        return Contacts(**self.as_dict(), locations=locations)

    def with_surface_offset(self, delta, groups=None) -> Contacts:
        """The contacts for a free surface ``delta`` m higher than the stated one (every depth grows
        by delta): ``depth + delta`` and weights ``relu(depth + delta) * area``, differentiable in
        delta (segments enter and leave contact as it changes).

        Args:
            delta: a scalar (one offset), or (G,) offsets with ``groups``, m (a tensor that requires
                grad gives the weights' gradient).
            groups: optional (T,) integer group of each time sample in [0, G) (one offset per
                recording or trial); ``delta[groups]`` then shifts sample t.
        """
        return self.with_depth_shift_cm(torch.as_tensor(delta) * M_TO_CM, groups)

    def with_depth_shift_cm(self, delta, groups=None) -> Contacts:
        """``with_surface_offset`` with ``delta`` in cm, the unit of ``depth`` (what ``gp.surface.offset``
        learns in)."""
        if not self.has_surface:
            raise ValueError("with_surface_offset needs Contacts.depth, area_x and area_z (the signed depths and "
                             "areas, filled by rft.contacts); these contacts carry weights only")
        delta = torch.as_tensor(delta, dtype=self.depth.dtype, device=self.depth.device)
        if groups is None:
            if delta.numel() != 1:
                raise ValueError(f"delta must be one offset without groups, got shape {tuple(delta.shape)}")
            shift = delta.reshape(())
        else:
            groups = torch.as_tensor(groups, device=self.depth.device)
            if groups.dtype.is_floating_point or groups.shape != (len(self),):
                raise ValueError(f"groups must be ({len(self)},) integers, got {groups.dtype} {tuple(groups.shape)}")
            if delta.ndim != 1 or (len(groups) and (groups.min() < 0 or groups.max() >= delta.shape[0])):
                raise ValueError(f"groups index delta (G,) = {tuple(delta.shape)}: need 0 <= groups < G")
            shift = delta[groups][:, None]
        depth = self.depth + shift
        d = torch.relu(depth)
        return Contacts(self.beta, self.gamma, d * self.area_x, d * self.area_z, depth, self.area_x, self.area_z,
                        self.locations)

    def scale_weights(self, sx: Tensor, sz: Tensor) -> Contacts:
        """Weights (and areas) of each axis multiplied by ``sx``, ``sz`` (broadcast against (..., T, M))."""
        if not self.has_surface:
            return Contacts(self.beta, self.gamma, self.weight_x * sx, self.weight_z * sz, locations=self.locations)
        return Contacts(self.beta, self.gamma, self.weight_x * sx, self.weight_z * sz, self.depth, self.area_x * sx,
                        self.area_z * sz, self.locations)

    @property
    def shape(self) -> torch.Size:
        """(..., T, M)."""
        return self.beta.shape

    @property
    def n_segments(self) -> int:
        return self.beta.shape[-1]

    def __len__(self) -> int:
        return self.beta.shape[-2]

    def __getitem__(self, index) -> Contacts:
        """Select time steps (the second-to-last dimension), e.g. ``contacts[10:20]``."""
        return self._apply(lambda v: v[..., index, :])

    def to(self, *args, **kwargs) -> Contacts:
        """The contacts with every tensor ``.to(*args, **kwargs)``; ``self`` when nothing changes (as
        ``Tensor.to``: no copy, no second validation)."""
        old = self.as_dict()
        if self.locations is not None:
            old["locations"] = self.locations
        moved = {k: v.to(*args, **kwargs) for k, v in old.items()}
        if all(moved[k] is v for k, v in old.items()):
            return self
        return Contacts(**moved)

    def pad_segments(self, M: int) -> Contacts:
        """Pad to M segments with zero-weight segments (which add nothing to any force)."""
        extra = M - self.n_segments
        if extra < 0:
            raise ValueError(f"cannot pad {self.n_segments} segments down to M={M}")
        if extra == 0:
            return self
        pad = lambda v: torch.nn.functional.pad(v, (0, extra))  # noqa: E731
        return self._apply(pad, on_locations=False)

    @classmethod
    def cat(cls, parts: list[Contacts]) -> Contacts:
        """Concatenate along time, padding to the largest M."""
        if not parts:
            raise ValueError("Contacts.cat needs at least one Contacts")
        M = max(p.n_segments for p in parts)
        parts = [p.pad_segments(M) for p in parts]
        names = [n for n in parts[0].as_dict() if all(getattr(p, n) is not None for p in parts)]
        placed = [p.locations is not None for p in parts]
        if any(placed) and not all(placed):
            raise ValueError(f"Contacts.cat: parts {[i for i, h in enumerate(placed) if not h]} have no locations and "
                             f"the others do; give every part its places on the ground (or none)")
        loc = torch.cat([p.locations for p in parts], dim=-2) if all(placed) else None
        return cls(**{n: torch.cat([getattr(p, n) for p in parts], dim=-2) for n in names}, locations=loc)

    @classmethod
    def points(cls, beta, gamma, dtype=None, device=None) -> Contacts:
        """Point evaluations of the maps as one-segment functionals: angles of any broadcast shape
        (rad) -> Contacts (N, 1), N = their number, mapped into the canonical square (the mirror
        identity's sign on weight_x, 1 on weight_z), so that the "forces" of these contacts are
        (alpha_x(beta, gamma), alpha_z(beta, gamma)) in N/cm^3.
        """
        from .stress_maps import mirror_to_canonical

        dtype = dtype or (beta.dtype if isinstance(beta, Tensor) and beta.dtype.is_floating_point
                          else torch.get_default_dtype())
        beta = torch.as_tensor(beta, dtype=dtype, device=device)
        gamma = torch.as_tensor(gamma, dtype=dtype, device=device)
        beta, gamma = torch.broadcast_tensors(beta, gamma)
        for name, v in (("beta", beta), ("gamma", gamma)):
            if not torch.isfinite(v).all():
                raise ValueError(f"{name} contains NaN or inf")
        bc, gc, sx = mirror_to_canonical(beta.reshape(-1), gamma.reshape(-1))
        return cls(bc[:, None], gc[:, None], sx[:, None], torch.ones_like(bc)[:, None])

    def as_dict(self) -> dict[str, Tensor]:
        """The per-segment tensors (..., T, M) held, by name, in field order (the optional depth and areas only
        where present; never ``locations``)."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) is not None and f.name != "locations"}


def check_locations(locations, n: int | None = None, name: str = "locations") -> Tensor:
    """``locations`` as a float tensor (..., 2) of finite horizontal places in m; ``n``: the number of
    samples it must have (its first dimension). Raises ``ValueError`` naming ``name`` otherwise."""
    s = torch.as_tensor(locations)
    if not s.is_floating_point():
        s = s.to(torch.get_default_dtype())
    if s.ndim < 1 or s.shape[-1] != 2:
        raise ValueError(f"{name} must be (..., 2) horizontal places (x, y) in m, got shape {tuple(s.shape)}")
    if n is not None and (s.ndim != 2 or s.shape[0] != n):
        raise ValueError(f"{name} must be ({n}, 2), one place per sample, got shape {tuple(s.shape)}")
    if not bool(torch.isfinite(s).all()):
        raise ValueError(f"{name} has NaN or infinite entries")
    return s


@dataclass
class SegmentKinematics:
    """World-frame state of every segment, each (T, M, 2) or (T, M).

    Attributes:
        position: segment centres (x, z), m.
        tangent: unit tangents (x, z).
        velocity: v + omega x r, m/s.
        depth: max(0, -z), m.
        area: length x width, m^2 (T, M).
    """

    position: Tensor
    tangent: Tensor
    velocity: Tensor
    depth: Tensor
    area: Tensor


def _rotate(heading: Tensor, vectors: Tensor) -> Tensor:
    """Rotate body vectors (M, 2) by headings (T,) -> (T, M, 2)."""
    c, s = torch.cos(heading)[:, None], torch.sin(heading)[:, None]
    vx, vz = vectors[..., 0], vectors[..., 1]
    return torch.stack([c * vx - s * vz, s * vx + c * vz], dim=-1)


def segment_kinematics(toe: Toe, path: Path) -> SegmentKinematics:
    """Positions, tangents and rigid-body velocities (v + omega x r) of every segment."""
    dtype = path.position.dtype
    toe = toe.to(dtype=dtype, device=path.position.device)
    r = _rotate(path.heading, toe.centres)  # (T, M, 2): offset of each centre from the origin
    position = path.position[:, None, :] + r
    tangent = _rotate(path.heading, toe.tangents)
    omega = path.angular_velocity[:, None]
    # omega x r in the x-z plane, omega counter-clockwise (x toward z): (-omega r_z, omega r_x)
    velocity = path.velocity[:, None, :] + torch.stack([-omega * r[..., 1], omega * r[..., 0]], dim=-1)
    depth = torch.clamp(-position[..., 1], min=0.0)
    area = toe.areas.expand(position.shape[:-1])
    return SegmentKinematics(position, tangent, velocity, depth, area)


def contacts(toe: Toe, path: Path, min_speed: float = 1e-9) -> Contacts:
    """Contact angles and weights of every segment of ``toe`` along ``path``.

    Segments above the surface get weight 0. A segment slower than ``min_speed`` [m/s] has no
    defined direction of motion; RFT gives it no force, so it gets weight 0 too (and gamma 0).
    Differentiable in the toe's and the path's tensors.

    Returns:
        Contacts with tensors of shape (T, M).
    """
    if not isinstance(toe, Toe):
        raise TypeError(f"toe must be a Toe (IToe, CToe, PolylineToe), got {type(toe).__name__}")
    if not isinstance(path, Path):
        raise TypeError(f"path must be a Path, got {type(path).__name__}")
    if not (math.isfinite(float(min_speed)) and float(min_speed) >= 0):
        raise ValueError(f"min_speed must be a finite speed >= 0 in m/s, got {min_speed}")
    k = segment_kinematics(toe, path)
    vx, vz = k.velocity[..., 0], k.velocity[..., 1]
    moving = torch.hypot(vx, vz) > min_speed
    toward_minus_x = vx < 0
    beta = torch.atan2(k.tangent[..., 1], k.tangent[..., 0])
    beta = torch.where(toward_minus_x, -beta, beta)
    beta = wrap_beta(beta)
    gamma = torch.where(moving, torch.atan2(-vz, vx.abs()), torch.zeros_like(vx))
    area = (k.area * M_TO_CM**2) * moving
    depth = -k.position[..., 1] * M_TO_CM  # signed: negative above the surface
    weight = torch.relu(depth) * area
    sign = torch.where(toward_minus_x, -torch.ones_like(vx), torch.ones_like(vx))
    return Contacts(beta=beta, gamma=gamma, weight_x=-sign * weight, weight_z=weight, depth=depth, area_x=-sign * area,
                    area_z=area)
