"""A planar five-bar leg driven by two motors: kinematics, Jacobian and statics (F = J^-T tau).

Frame: x right, z up, the midpoint between the two motor axes at the origin. Motor i sits at
hip_i = (-/+ hip_spacing / 2, 0); its proximal link (length l1) points at angle q_i from straight
down, counter-clockwise positive:  knee_i = hip_i + l1 (sin q_i, -cos q_i).  Both distal links
(length l2) meet at the toe, knees out: knee 1 on the +x side of the toe, knee 2 on the -x side.

Statics: the distal links are two-force members, so with A = [(p - knee_1)^T; (p - knee_2)^T] and
b_i = (p - knee_i) . d knee_i / d q_i, the Jacobian is J = A^-1 diag(b) and
J^-T tau = sum_i tau_i (p - knee_i) / b_i. For the symmetric coaxial leg (Minitaur family) this
is F_radial = (tau1 - tau2) / L'(g), F_tangential = (tau1 + tau2) / L.

Extension (``extension`` = l3 > 0, e.g. the Traveler's 0.05 m): the toe sits l3 beyond the distal
joint p along the leg axis (the line from the origin through p), toe = p + l3 p / |p|. Its
Jacobian is M J_p with M = I + (l3 / |p|)(I - u u^T), u = p / |p|: the radial part of a force is
unchanged and the tangential part is scaled by |p| / (|p| + l3) (F_tangential = (tau1 + tau2) /
(L + l3) for the symmetric leg). With l3 = 0 (the default) nothing changes.

Sign: ``tau`` is the torque the motors apply to hold the leg (what tau = k_t I measures). In
static balance tau + J^T F_ground = 0, so the force of the ground on the toe is -J^-T tau.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rft.paths import Path, pose_path

__all__ = ["FiveBarLeg", "SingularConfigurationWarning"]


class SingularConfigurationWarning(UserWarning):
    """Some samples are near a kinematic singularity; their forces are masked (NaN)."""


@dataclass(frozen=True)
class FiveBarLeg:
    """Args:
        l1: proximal link length, m (default Minitaur's 0.1).
        l2: distal link length, m (default 0.2).
        hip_spacing: distance between the two motor axes along x, m (0: coaxial).
        max_condition: samples whose Jacobian condition number exceeds this are masked.
        extension: l3, how far the toe sits beyond the distal joint along the leg axis (origin to
            distal joint), m (default 0: the toe is the distal joint).
    """

    l1: float = 0.10
    l2: float = 0.20
    hip_spacing: float = 0.0
    max_condition: float = 50.0
    extension: float = 0.0

    def __post_init__(self) -> None:
        for name in ("l1", "l2"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive length in metres, got {v}")
            if v > 2.0:
                raise ValueError(f"{name}={v} m: lengths are in metres (millimetres passed?)")
        if not (math.isfinite(self.hip_spacing) and self.hip_spacing >= 0):
            raise ValueError(f"hip_spacing must be >= 0 (m), got {self.hip_spacing}")
        if not (math.isfinite(self.extension) and 0 <= self.extension <= 2.0):
            raise ValueError(f"extension must be a length >= 0 in metres, got {self.extension}")

    def hips(self, dtype=torch.float64) -> Tensor:
        """(2, 2) motor axis positions."""
        d = self.hip_spacing / 2
        return torch.tensor([[-d, 0.0], [d, 0.0]], dtype=dtype)

    # ---- kinematics ------------------------------------------------------------------------
    def _knees(self, q: Tensor) -> tuple[Tensor, Tensor]:
        hips = self.hips(q.dtype).to(q.device)
        dir_ = torch.stack([torch.sin(q), -torch.cos(q)], -1)  # (..., 2, 2)
        knees = hips + self.l1 * dir_
        dknees = self.l1 * torch.stack([torch.cos(q), torch.sin(q)], -1)
        return knees, dknees

    def forward_kinematics(self, q) -> Tensor:
        """Toe position (..., 2) [m] from joint angles q (..., 2) [rad]; NaN where unreachable, and
        where the knees coincide (the toe could be anywhere on a circle of radius l2 around them)."""
        q = torch.as_tensor(q, dtype=torch.float64) if not torch.is_tensor(q) else q
        p = self._distal_joint(q)
        if self.extension == 0:
            return p
        return p + self.extension * p / torch.linalg.vector_norm(p, dim=-1, keepdim=True)

    def _distal_joint(self, q: Tensor) -> Tensor:
        """Where the two distal links meet (..., 2) [m] (the toe when ``extension`` is 0)."""
        knees, _ = self._knees(q)
        k1, k2 = knees[..., 0, :], knees[..., 1, :]
        mid = (k1 + k2) / 2
        d = k2 - k1
        D = torch.linalg.vector_norm(d, dim=-1, keepdim=True)
        h = torch.sqrt(torch.clamp(self.l2**2 - (D / 2) ** 2, min=0.0))
        h = torch.where((D / 2 > self.l2) | (D < 1e-12), torch.full_like(h, math.nan), h)
        # Knee 1 on the +x side of the toe, knee 2 on the -x side ("knees out"): the toe lies on the
        # side of the knee line given by the fixed rotation of k2 - k1 (straight down at q = (g, -g)).
        n = torch.stack([-d[..., 1], d[..., 0]], -1) / D.clamp_min(1e-12)
        return mid + h * n

    def inverse_kinematics(self, p) -> Tensor:
        """Joint angles (..., 2) [rad] placing the toe at p (..., 2) [m] (knee 1 on the +x side of
        its hip-to-toe line, knee 2 on the -x side, as forward_kinematics assumes).

        Raises ValueError naming the first such p[i] for a toe outside the workspace, and for one
        these knees reach only with the distal links assembled the other way (with the hips apart,
        toes beyond where the knees cross past each other): forward_kinematics keeps the toe on one
        side of the knee line and would put it at the mirror image of p there."""
        p = torch.as_tensor(p, dtype=torch.float64) if not torch.is_tensor(p) else p
        toe = p
        if self.extension > 0:  # back from the toe to the distal joint, along the leg axis
            r = torch.linalg.vector_norm(p, dim=-1, keepdim=True)
            if (r <= self.extension).any():
                raise ValueError(f"toe positions must be farther than extension={self.extension} m from the origin")
            p = p * (1 - self.extension / r)
        hips = self.hips(p.dtype).to(p.device)
        rel = p[..., None, :] - hips  # (..., 2, 2)
        r = torch.linalg.vector_norm(rel, dim=-1)
        out = (r > self.l1 + self.l2) | (r < abs(self.l1 - self.l2))
        if out.any():
            i = int(out.any(-1).reshape(-1).nonzero()[0])
            raise ValueError(f"toe position p[{i}] = {p.reshape(-1, 2)[i].tolist()} m is outside the leg's workspace "
                             f"({abs(self.l1 - self.l2):.3f} to {self.l1 + self.l2:.3f} m from each hip)")
        theta = torch.atan2(rel[..., 0], -rel[..., 1])
        g = torch.acos(((self.l1**2 + r**2 - self.l2**2) / (2 * self.l1 * r)).clamp(-1, 1))
        q = theta + torch.stack([g[..., 0], -g[..., 1]], -1)
        other = torch.linalg.vector_norm(self._distal_joint(q) - p, dim=-1) > 1e-7 * (self.l1 + self.l2)
        if other.any():
            i = int(other.reshape(-1).nonzero()[0])
            knees = [round(v, 4) for v in self._knees(q.reshape(-1, 2)[i])[0].reshape(-1).tolist()]
            raise ValueError(f"toe position p[{i}] = {toe.reshape(-1, 2)[i].tolist()} m is reached only with the "
                             f"knees crossed past each other (knees at {knees} m) and the distal links assembled "
                             "the other way: for those joint angles this leg model (forward_kinematics) puts the toe "
                             "on the other side of the knee line")
        return q

    def jacobian(self, q) -> Tensor:
        """d toe / d q, (..., 2, 2): rows (x, z), columns (q1, q2).

        Raises ValueError naming the first q[i] where it is not defined: a singular configuration
        (the knees coincide, or both distal links lie on one line) or unreachable joint angles."""
        q = torch.as_tensor(q, dtype=torch.float64) if not torch.is_tensor(q) else q
        A, b = self._statics(q)
        J, info = torch.linalg.solve_ex(torch.nan_to_num(A), torch.diag_embed(b))
        bad = (info != 0) | ~torch.isfinite(J).all(-1).all(-1) | ~torch.isfinite(A).all(-1).all(-1)
        if bad.any():
            i = int(bad.reshape(-1).nonzero()[0])
            raise ValueError(f"q[{i}] = {[round(v, 4) for v in q.reshape(-1, 2)[i].tolist()]} rad: the Jacobian is "
                             "not defined there (a singular leg configuration: the knees coincide or both distal "
                             "links lie on one line; or joint angles the leg cannot reach)")
        return J

    def _statics(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """A, b with J = A^-1 diag(b)."""
        p = self._distal_joint(q)
        knees, dknees = self._knees(q)
        A = p[..., None, :] - knees  # rows p - knee_i
        b = (A * dknees).sum(-1)
        if self.extension > 0:  # J = M J_p, so A -> A M^-1; M^-1 = u u^T + r / (r + l3) (I - u u^T)
            r = torch.linalg.vector_norm(p, dim=-1, keepdim=True)[..., None]
            u = (p[..., :, None] / r)
            uu = u @ u.mT
            eye = torch.eye(2, dtype=p.dtype, device=p.device)
            A = A @ (uu + r / (r + self.extension) * (eye - uu))
        return A, b

    def condition_number(self, q) -> Tensor:
        """Condition number of J (inf where singular or unreachable)."""
        A, b = self._statics(q)
        jinv = A / b[..., None]  # J^-1 = diag(1/b) A
        ok = torch.isfinite(jinv).all(-1).all(-1)
        s = torch.linalg.svdvals(torch.where(ok[..., None, None], jinv, torch.eye(2, dtype=jinv.dtype)))
        cond = s[..., 0] / s[..., -1]
        return torch.where(ok, cond, torch.full_like(cond, math.inf))

    # ---- statics ---------------------------------------------------------------------------
    def ground_force(self, q, tau, warn: bool = True) -> tuple[Tensor, Tensor]:
        """Force of the ground on the toe, F = -J^-T tau, (..., 2) [N], and a validity mask (...,).

        Samples with condition number above ``max_condition`` (near a singularity, fully stretched or
        folded) are masked: their force is NaN, never a huge number, and a warning says how many.
        """
        q = torch.as_tensor(q, dtype=torch.float64) if not torch.is_tensor(q) else q
        tau = torch.as_tensor(tau, dtype=q.dtype)
        if q.shape[-1] != 2 or tau.shape != q.shape:
            raise ValueError(f"q and tau must both be (..., 2), got {tuple(q.shape)} and {tuple(tau.shape)}")
        A, b = self._statics(q)
        force = -((tau / b)[..., :, None] * A).sum(-2)
        valid = (self.condition_number(q) <= self.max_condition) & torch.isfinite(force).all(-1)
        if warn and not bool(valid.all()):
            n = int((~valid).sum())
            warnings.warn(f"{n} of {valid.numel()} samples are near a singular leg configuration "
                          f"(condition number > {self.max_condition}); their forces are masked (NaN)",
                          SingularConfigurationWarning, stacklevel=2)
        return torch.where(valid[..., None], force, torch.full_like(force, math.nan)), valid

    def holding_torques(self, q, ground_force) -> Tensor:
        """Motor torques (..., 2) [N m] that hold the leg against a ground force (..., 2) [N]:
        tau = -J^T F."""
        J = self.jacobian(q)
        return -(J.mT @ torch.as_tensor(ground_force, dtype=J.dtype)[..., None])[..., 0]

    # ---- paths -----------------------------------------------------------------------------
    def toe_path(self, time, q, heading: str | float = 0.0, hip_height: float = 0.0) -> Path:
        """The toe's path over a joint log, for ``rft.contacts``.

        Args:
            time: (T,) s. q: (T, 2) joint angles, rad.
            heading: a fixed toe heading [rad] (default 0: the toe keeps its orientation), or "link1"
                / "link2" for a toe fixed to that distal link (its heading follows the link).
            hip_height: height of the motor axes above the sand surface, m (world z = leg z + this).
        """
        q = torch.as_tensor(q, dtype=torch.float64)
        p = self.forward_kinematics(q)
        if not torch.isfinite(p).all():
            bad = int((~torch.isfinite(p).all(-1)).nonzero()[0])
            raise ValueError(f"joint angles are unreachable (first at sample {bad})")
        if isinstance(heading, str):
            if heading not in ("link1", "link2"):
                raise ValueError(f"heading must be a number or 'link1'/'link2', got {heading!r}")
            knees, _ = self._knees(q)
            i = 0 if heading == "link1" else 1
            d = self._distal_joint(q) - knees[..., i, :]
            h = torch.atan2(d[..., 1], d[..., 0]) + math.pi / 2  # 0 when the link points straight down
        else:
            h = torch.full(p.shape[:-1], float(heading), dtype=p.dtype)
        return pose_path(time, p[:, 0], p[:, 1] + hip_height, h)
