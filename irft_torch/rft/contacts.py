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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .paths import Path
from .toes import Toe

__all__ = ["Contacts", "SegmentKinematics", "segment_kinematics", "contacts", "M_TO_CM"]

M_TO_CM = 100.0  # the one place that converts SI lengths to the literature's centimetres


@dataclass
class Contacts:
    """Per-segment RFT inputs: four tensors of shape (..., T, M) on one device and dtype.

    Attributes:
        beta: segment tilt in the canonical square, rad.
        gamma: velocity direction in the canonical square, rad.
        weight_x: signed weight of alpha_x in F_x, cm^3 (zero above the surface).
        weight_z: weight of alpha_z in F_z, cm^3, >= 0 (zero above the surface).
    """

    beta: Tensor
    gamma: Tensor
    weight_x: Tensor
    weight_z: Tensor

    def __post_init__(self) -> None:
        names = [f.name for f in fields(self)]
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
        if (self.weight_z < 0).any():
            raise ValueError("Contacts.weight_z must be >= 0 (depth x area)")

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
        return Contacts(*(getattr(self, f.name)[..., index, :] for f in fields(self)))

    def to(self, *args, **kwargs) -> Contacts:
        return Contacts(*(getattr(self, f.name).to(*args, **kwargs) for f in fields(self)))

    def pad_segments(self, M: int) -> Contacts:
        """Pad to M segments with zero-weight segments (which add nothing to any force)."""
        extra = M - self.n_segments
        if extra < 0:
            raise ValueError(f"cannot pad {self.n_segments} segments down to M={M}")
        if extra == 0:
            return self
        pad = lambda v: torch.nn.functional.pad(v, (0, extra))  # noqa: E731
        return Contacts(*(pad(getattr(self, f.name)) for f in fields(self)))

    @classmethod
    def cat(cls, parts: list[Contacts]) -> Contacts:
        """Concatenate along time, padding to the largest M."""
        if not parts:
            raise ValueError("Contacts.cat needs at least one Contacts")
        M = max(p.n_segments for p in parts)
        parts = [p.pad_segments(M) for p in parts]
        return cls(*(torch.cat([getattr(p, f.name) for p in parts], dim=-2) for f in fields(cls)))

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
        return {f.name: getattr(self, f.name) for f in fields(self)}


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
    k = segment_kinematics(toe, path)
    vx, vz = k.velocity[..., 0], k.velocity[..., 1]
    moving = torch.hypot(vx, vz) > min_speed
    toward_minus_x = vx < 0
    beta = torch.atan2(k.tangent[..., 1], k.tangent[..., 0])
    beta = torch.where(toward_minus_x, -beta, beta)
    beta = torch.remainder(beta + math.pi / 2, math.pi) - math.pi / 2
    gamma = torch.where(moving, torch.atan2(-vz, vx.abs()), torch.zeros_like(vx))
    weight = (k.depth * M_TO_CM) * (k.area * M_TO_CM**2) * moving
    sign = torch.where(toward_minus_x, -torch.ones_like(vx), torch.ones_like(vx))
    return Contacts(beta=beta, gamma=gamma, weight_x=-sign * weight, weight_z=weight)
