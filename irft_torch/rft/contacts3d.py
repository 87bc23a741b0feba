"""3-D RFT contacts: which elements of a moving rigid body meet the medium, at which angles and weights.

The 3-D resistive force theory of Treers et al. (2021) with Li et al.'s maps, exactly as the rover-wheel
authors' code computes it (checked formula by formula in ``shared/reference/rft3d_facts.md``; docs/rft3d.md).
World frame x, y horizontal, z up (right-handed); flat free surface at height ``surface``.

Per element (point p, outward normal n, area A in the body frame) and sample t, with the body at
``position`` x_t, ``rotation`` R_t, velocity v_t and angular velocity w_t (world frame):

    point  x_t + R_t p,  normal  R_t n,  velocity  v_t + w_t x (R_t p),  unit velocity  v^
    in contact: it leads (n . v^ > 0; a thin element: always, with the face that leads) and its point
                lies below the surface; depth d = surface - z
    e2 = unit horizontal part of n (|n_z| >= 0.999: of v^ + (1e-5, 0, 0) instead), e1 = e2 x z
    v1 = (v^ . e1) e1 (out of the e2-z plane), v23 = v^ - v1
    beta = atan2(n_z, n . e2) + pi/2,  gamma = -atan2(v23_z, v23 . e2)
    force = d A [-f1(|v1|) alpha_y sgn(v^ . e1) e1 - f23(|v23|) alpha_x(beta, gamma) e2
                 + f23(|v23|) alpha_z(beta, gamma) z]

The angles are stored in the library's canonical square (beta in [-pi/2, pi/2), gamma in [-pi/2, pi/2]):
with u = sgn(v23 . e2) e2 (the in-plane direction of motion; +x, then +y, first on a tie), beta = tilt
in the u-z plane and gamma = atan2(-v_z, |v23 . e2|). This is the mirror identity alpha_x(-b, pi - g) =
-alpha_x(b, g), alpha_z(-b, pi - g) = alpha_z(b, g); the alpha_y term does not change (e1 flips with e2).
So every force axis is linear in the three maps with signed weights (cm^3), like the planar ``Contacts``:

    F_x = sum_k weight_x[k, 0] alpha_x(b_k, g_k) + weight_y[k, 0] alpha_y(b_k, g_k)
    F_y = sum_k weight_x[k, 1] alpha_x(b_k, g_k) + weight_y[k, 1] alpha_y(b_k, g_k)
    F_z = sum_k weight_z[k] alpha_z(b_k, g_k)

weight_x = -f23 w (u_x, u_y), weight_y = -f1 w sgn(v^ . e1) (e1_x, e1_y), weight_z = f23 w, w = d [cm] A [cm^2].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .contacts import M_TO_CM, Contacts
from .mesh import Mesh, _check_rotation
from .paths import Path
from .stress_maps import wrap_beta

__all__ = ["Contacts3D", "contacts_3d", "element_kinematics", "planar_motion", "f1", "f23", "NEAR_HORIZONTAL"]

NEAR_HORIZONTAL = 1 - 1e-3  # |n_z| at and above which e2 follows the velocity (the authors' rule)
_TIE = 1e-5  # the authors' (1e-5, 0, 0) added to the unit velocity for a near-horizontal element's e2
_CHUNK_ELEMENTS = 2**19  # samples x elements evaluated at once (memory bound)


def f1(vt: Tensor) -> Tensor:
    """Treers et al. 2021's scaling of the out-of-plane stress by |v1| in [0, 1] (0 at 0, 1 at 1)."""
    a = 1.60910808139526
    return 0.440850096954369 * (torch.tanh(3.62263982880971 * vt - a) + math.tanh(a)) / 0.832324700111401


def f23(vn: Tensor) -> Tensor:
    """Treers et al. 2021's scaling of the in-plane stresses by |v23| in [0, 1] (0 at 0, 1 at 1)."""
    b = 0.973746396532650
    return 1.99392673405210 * (torch.atanh(1.61146827229181 * vn - b) + math.atanh(b)) / 5.81083560370960


_FIELDS = ("beta", "gamma", "weight_x", "weight_y", "weight_z")


@dataclass
class Contacts3D:
    """3-D RFT inputs of T samples, K elements in contact each (padded with zero weights), one dtype.

    Attributes:
        beta, gamma: (T, K) canonical angles, rad.
        weight_x: (T, K, 2) weights of alpha_x in (F_x, F_y), cm^3 (signs included).
        weight_y: (T, K, 2) weights of alpha_y in (F_x, F_y), cm^3.
        weight_z: (T, K) weights of alpha_z in F_z, cm^3, >= 0.
        element: optional (T, K) long, the mesh element of each entry (-1 for padding).

    Example:
        >>> c = contacts_3d(Mesh.from_toe(CToe(0.02, 0.008)), velocity, angular_velocity, surface=0.0)
        >>> forces_3d(FourierStressMap.generic(), c)      # (T, 3) N
    """

    beta: Tensor
    gamma: Tensor
    weight_x: Tensor
    weight_y: Tensor
    weight_z: Tensor
    element: Tensor | None = None

    def __post_init__(self) -> None:
        for name in _FIELDS:
            v = getattr(self, name)
            if not isinstance(v, Tensor):
                v = torch.as_tensor(v, dtype=torch.get_default_dtype())
                setattr(self, name, v)
            if not v.dtype.is_floating_point:
                raise ValueError(f"Contacts3D.{name} must be a floating tensor, got {v.dtype}")
            if not torch.isfinite(v).all():
                raise ValueError(f"Contacts3D.{name} contains NaN or inf")
        shape = self.beta.shape
        if len(shape) != 2:
            raise ValueError(f"Contacts3D.beta must be (T, K), got {tuple(shape)}")
        want = {"gamma": shape, "weight_x": (*shape, 2), "weight_y": (*shape, 2), "weight_z": shape}
        for name, s in want.items():
            if tuple(getattr(self, name).shape) != tuple(s):
                raise ValueError(f"Contacts3D.{name} has shape {tuple(getattr(self, name).shape)}, want {tuple(s)} "
                                 f"(beta is {tuple(shape)})")
        if self.element is not None and tuple(self.element.shape) != tuple(shape):
            raise ValueError(f"Contacts3D.element must be (T, K) = {tuple(shape)}, got {tuple(self.element.shape)}")
        if (self.weight_z < 0).any():
            raise ValueError("Contacts3D.weight_z must be >= 0 (f23 x depth x area)")

    @property
    def shape(self) -> torch.Size:
        """(T, K)."""
        return self.beta.shape

    @property
    def n_elements(self) -> int:
        return self.beta.shape[-1]

    def __len__(self) -> int:
        return self.beta.shape[0]

    def as_dict(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    def _apply(self, fn) -> Contacts3D:
        return Contacts3D(**{k: fn(v) for k, v in self.as_dict().items()})

    def __getitem__(self, index) -> Contacts3D:
        """Select samples (the first dimension), e.g. ``c[10:20]`` or a bool / index tensor."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return self._apply(lambda v: v[index])

    def to(self, *args, **kwargs) -> Contacts3D:
        """Every floating tensor ``.to(*args, **kwargs)`` (the element index follows the device only)."""
        moved = self.beta.to(*args, **kwargs)
        return Contacts3D(**{k: v.to(*args, **kwargs) if v.dtype.is_floating_point else v.to(device=moved.device)
                             for k, v in self.as_dict().items()})

    def pad_elements(self, K: int) -> Contacts3D:
        """Pad to K elements per sample with zero-weight entries (which add nothing)."""
        extra = K - self.n_elements
        if extra < 0:
            raise ValueError(f"cannot pad {self.n_elements} elements down to K={K}")
        if extra == 0:
            return self
        out = {}
        for k, v in self.as_dict().items():
            pad = (0, 0, 0, extra) if v.ndim == 3 else (0, extra)
            out[k] = torch.nn.functional.pad(v, pad, value=-1 if k == "element" else 0)
        return Contacts3D(**out)

    @classmethod
    def cat(cls, parts: list[Contacts3D]) -> Contacts3D:
        """Concatenate along samples, padding to the largest K."""
        if not parts:
            raise ValueError("Contacts3D.cat needs at least one Contacts3D")
        K = max(p.n_elements for p in parts)
        parts = [p.pad_elements(K) for p in parts]
        names = [n for n in parts[0].as_dict() if all(getattr(p, n) is not None for p in parts)]
        return cls(**{n: torch.cat([getattr(p, n) for p in parts]) for n in names})

    def planar(self) -> Contacts:
        """The planar model's view: ``Contacts`` with weight_x = the alpha_x weights on F_x, weight_z as here
        (the F_y row and alpha_y dropped). What a planar I-RFT fitted to (F_x, F_z) assumes."""
        return Contacts(self.beta, self.gamma, self.weight_x[..., 0], self.weight_z)

    def alpha_y_weight(self) -> Tensor:
        """(T, 2): the alpha_y weights summed over elements, cm^3: F_(x, y) = this x alpha_y for a constant alpha_y."""
        return self.weight_y.sum(-2)

    def in_contact(self) -> Tensor:
        """(T, K) bool: entries that carry weight on some axis (False for padding)."""
        return (self.weight_x != 0).any(-1) | (self.weight_y != 0).any(-1) | (self.weight_z != 0)


def _as_samples(x, name: str, T: int | None, dtype, device, tail: tuple) -> Tensor:
    t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == len(tail):
        t = t[None]
    if t.ndim != len(tail) + 1 or tuple(t.shape[1:]) != tail or (T is not None and t.shape[0] not in (1, T)):
        want = f"({'T' if T is None else T}, {', '.join(map(str, tail))})"
        raise ValueError(f"{name} must be {want} (or {tail} for every sample), got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} contains NaN or inf")
    return t


def contacts_3d(mesh: Mesh, velocity, angular_velocity, surface, position=None, rotation=None,
                min_speed: float = 1e-9) -> Contacts3D:
    """3-D RFT contacts of ``mesh`` in rigid motion (module doc for every formula).

    Args:
        mesh: the body's surface in its own frame (``rft.Mesh``).
        velocity: (T, 3) velocity of the body origin, world frame, m/s.
        angular_velocity: (T, 3) rad/s, world frame (element velocity v + w x (R p)).
        surface: free-surface height, m: a scalar or (T,).
        position: (T, 3) body origin, m (default 0).
        rotation: (T, 3, 3) body-to-world rotations (default identity).
        min_speed: elements slower than this (m/s) have no direction of motion and take no force.

    Returns:
        ``Contacts3D`` (T, K): only the elements in contact are kept (K = the most in any sample), so memory
        follows the contact, not the mesh; samples are evaluated in chunks of about 5e5 sample-elements.
        Differentiable in the mesh, the motion and the surface (the contact set itself is piecewise constant).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be an irft_torch.rft.Mesh, got {type(mesh).__name__}")
    if not (math.isfinite(float(min_speed)) and float(min_speed) >= 0):
        raise ValueError(f"min_speed must be a finite speed >= 0 in m/s, got {min_speed}")
    dtype, device = mesh.points.dtype, mesh.points.device
    if isinstance(velocity, Tensor) and velocity.dtype.is_floating_point:
        dtype = torch.promote_types(dtype, velocity.dtype)
    v = _as_samples(velocity, "velocity", None, dtype, device, (3,))
    T = v.shape[0]
    w = _as_samples(angular_velocity, "angular_velocity", T, dtype, device, (3,))
    T = max(T, w.shape[0])
    x0 = torch.zeros(1, 3, dtype=dtype, device=device) if position is None else \
        _as_samples(position, "position", T, dtype, device, (3,))
    R = torch.eye(3, dtype=dtype, device=device)[None] if rotation is None else \
        _as_samples(rotation, "rotation", T, dtype, device, (3, 3))
    T = max(T, x0.shape[0], R.shape[0])
    if rotation is not None:
        _check_rotation(R.detach(), "rotation")
    zs = torch.as_tensor(surface, dtype=dtype, device=device)
    if zs.ndim == 0:
        zs = zs[None]
    if zs.ndim != 1 or zs.shape[0] not in (1, T) or not torch.isfinite(zs).all():
        raise ValueError(f"surface must be a finite height in m, a scalar or ({T},), got shape {tuple(zs.shape)}")
    for name, t in (("velocity", v), ("angular_velocity", w), ("position", x0), ("rotation", R)):
        if t.shape[0] not in (1, T):
            raise ValueError(f"{name} has {t.shape[0]} samples, others {T}")
    m = mesh.to(dtype=dtype, device=device)
    E = m.n_elements
    step = max(1, _CHUNK_ELEMENTS // E)
    rows, cols, values, K = [], [], [], 1
    for t0 in range(0, T, step):
        t1 = min(T, t0 + step)
        pick = lambda a: a.expand(T, *a.shape[1:])[t0:t1]  # noqa: E731
        ti, ki, ei, vals = _chunk(m, pick(v), pick(w), pick(x0), None if rotation is None else pick(R), pick(zs),
                                  float(min_speed))
        rows.append(ti + t0)
        cols.append(ki)
        values.append((*vals, ei))
        if ki.numel():
            K = max(K, int(ki.max()) + 1)
    ti, ki = torch.cat(rows), torch.cat(cols)
    out = []
    for j, tail in enumerate(((), (), (2,), (2,), (), ())):
        vals = torch.cat([vv[j] for vv in values])
        fill = -1 if j == 5 else 0.0
        out.append(vals.new_full((T, K, *tail), fill).index_put((ti, ki), vals))
    return Contacts3D(*out)


def _chunk(m: Mesh, v, w, x0, R, zs, min_speed: float):
    """One chunk of samples (t,): (sample, slot, element) of each contact and its terms (``_element_terms``)."""
    pts, n, vel = _kinematics(m, v, w, x0, R)
    z = pts[..., 2]
    speed = torch.linalg.vector_norm(vel, dim=-1)
    nv = (n * vel).sum(-1)  # the sign of n . v^
    lead = m.thin[None, :] | (nv > 0)
    contact = lead & (speed > min_speed) & (z < zs[:, None]) & (m.areas > 0)[None, :]
    ti, ei = contact.nonzero(as_tuple=True)
    ki = (torch.cumsum(contact.to(torch.int32), 1) - 1)[ti, ei].long()
    nc = n[ti, ei]
    vc = vel[ti, ei] / speed[ti, ei, None]
    flip = m.thin[ei] & (nv[ti, ei] < 0)  # a thin element's leading face
    nc = torch.where(flip[:, None], -nc, nc)
    depth = (zs[ti] - z[ti, ei]) * M_TO_CM
    wgt = depth * (m.areas[ei] * M_TO_CM**2)
    return ti, ki, ei, _element_terms(nc, vc, wgt)


def _kinematics(m: Mesh, v, w, x0, R):
    """World points, normals and velocities (t, E, 3) of every element (R None: the identity)."""
    if R is None:
        r = m.points.expand(v.shape[0], *m.points.shape)  # (t, E, 3) offsets R p
        n = m.normals.expand_as(r)
    else:
        r = torch.einsum("tij,ej->tei", R, m.points)
        n = torch.einsum("tij,ej->tei", R, m.normals)
    vel = v[:, None, :] + torch.linalg.cross(w[:, None, :].expand_as(r), r)
    return x0[:, None, :] + r, n, vel


def element_kinematics(mesh: Mesh, velocity, angular_velocity, position=None, rotation=None):
    """World-frame (points, normals, velocities), each (T, E, 3) in m, 1, m/s, of every element of ``mesh`` under
    the rigid motion of ``contacts_3d`` (x + R p, R n, v + w x (R p)): what its contact rule sees. Dense in E:
    for inspection and small meshes."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be an irft_torch.rft.Mesh, got {type(mesh).__name__}")
    dtype, device = mesh.points.dtype, mesh.points.device
    v = _as_samples(velocity, "velocity", None, dtype, device, (3,))
    w = _as_samples(angular_velocity, "angular_velocity", None, dtype, device, (3,))
    x0 = torch.zeros(1, 3, dtype=dtype, device=device) if position is None else \
        _as_samples(position, "position", None, dtype, device, (3,))
    R = None if rotation is None else _as_samples(rotation, "rotation", None, dtype, device, (3, 3))
    if R is not None:
        _check_rotation(R.detach(), "rotation")
    T = max(v.shape[0], w.shape[0], x0.shape[0], 1 if R is None else R.shape[0])
    ex = lambda a: a.expand(T, *a.shape[1:])  # noqa: E731
    return _kinematics(mesh, ex(v), ex(w), ex(x0), None if R is None else ex(R))


def _element_terms(n: Tensor, vh: Tensor, wgt: Tensor):
    """Canonical angles and per-map weights of contact elements: n (N, 3) leading normals, vh (N, 3) unit
    velocities, wgt (N,) depth x area in cm^3 (module doc)."""
    near = n[:, 2].abs() >= NEAR_HORIZONTAL
    hv = torch.stack([vh[:, 0] + _TIE, vh[:, 1]], -1)
    h = torch.where(near[:, None], hv, n[:, :2])
    hn = torch.linalg.vector_norm(h, dim=-1, keepdim=True)
    x_axis = torch.tensor([1.0, 0.0], dtype=h.dtype, device=h.device)
    e2 = torch.where(hn > 0, h / hn.clamp_min(torch.finfo(h.dtype).tiny), x_axis)
    e1 = torch.stack([e2[:, 1], -e2[:, 0]], -1)  # e2 x z (both horizontal)
    s1 = (vh[:, :2] * e1).sum(-1)  # v^ . e1
    v23 = torch.cat([vh[:, :2] - s1[:, None] * e1, vh[:, 2:]], -1)
    along = (v23[:, :2] * e2).sum(-1)  # v23 . e2 (= v^ . e2)
    tie = (e2[:, 0] > 0) | ((e2[:, 0] == 0) & (e2[:, 1] > 0))
    s = torch.where(along > 0, 1.0, torch.where(along < 0, -1.0, torch.where(tie, 1.0, -1.0))).to(n.dtype)
    n2 = (n[:, :2] * e2).sum(-1)
    beta = wrap_beta(torch.atan2(n[:, 2], s * n2) + math.pi / 2)
    gamma = torch.atan2(-v23[:, 2], along.abs())
    g23 = f23(torch.linalg.vector_norm(v23, dim=-1).clamp(max=1.0))
    g1 = f1(s1.abs().clamp(max=1.0))
    wx = -(wgt * g23 * s)[:, None] * e2
    wy = -(wgt * g1 * torch.sign(s1))[:, None] * e1
    wz = wgt * g23
    return beta, gamma, wx, wy, wz


def planar_motion(path: Path) -> dict[str, Tensor]:
    """A planar ``Path`` as a 3-D rigid motion (keyword arguments of ``contacts_3d``): the x-z plane is the
    world's, the heading (counter-clockwise from +x toward +z) a rotation about -y, the planar angular
    velocity omega the vector (0, -omega, 0)."""
    if not isinstance(path, Path):
        raise TypeError(f"path must be a Path, got {type(path).__name__}")
    p, h = path.position, path.heading
    zero = torch.zeros_like(h)
    c, s = torch.cos(h), torch.sin(h)
    rot = torch.stack([torch.stack([c, zero, -s], -1), torch.stack([zero, torch.ones_like(h), zero], -1),
                       torch.stack([s, zero, c], -1)], -2)
    return {"position": torch.stack([p[:, 0], zero, p[:, 1]], -1), "rotation": rot,
            "velocity": torch.stack([path.velocity[:, 0], zero, path.velocity[:, 1]], -1),
            "angular_velocity": torch.stack([zero, -path.angular_velocity, zero], -1)}
