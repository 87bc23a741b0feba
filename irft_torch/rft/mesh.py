"""A rigid body's surface for 3-D RFT: E elements, each a point, a unit outward normal and an area.

Body frame: the frame a rigid motion moves (``rft.contacts_3d``); x, y horizontal and z up when the
rotation is the identity. Lengths in m, areas in m^2 (SI, as everywhere at the public boundary).

Two kinds of element (docs/rft3d.md):

- a *face* of a closed body (a wheel's rim, its sidewall): it counts only while it leads, n . v > 0;
- a *thin* element, both faces of a thin plate (a toe): the face that moves into the medium counts,
  the stored one when the motion is exactly tangential, so a thin plate extruded from a planar toe
  gives the planar model's forces (every submerged, moving segment counts).

Constructors: ``Mesh.from_toe`` (a planar ``Toe`` extruded across its width, thin), ``wheel_mesh`` (a
rim with optional sidewalls and grousers), ``Mesh.from_triangles`` and ``read_mesh`` (an STL through
numpy-stl or trimesh, or a MATLAB file with ``Points``/``Normals``/``Area`` as 3-D RFT codes keep them).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from .toes import Toe, _n_segments, _positive

__all__ = ["Mesh", "wheel_mesh", "read_mesh", "triangle_elements"]

_LARGE_BODY_M = 5.0  # a body larger than this is almost surely millimetres passed as metres
_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}


@dataclass
class Mesh:
    """Surface elements of a rigid body in its own frame.

    Attributes:
        points: (E, 3) element centres (a triangle's incenter or centroid), m.
        normals: (E, 3) unit outward normals (kept bit for bit: 3-D RFT's contact rule n . v > 0 can
            rest on their round-off, docs/rft3d.md).
        areas: (E,) element areas, m^2, >= 0.
        thin: (E,) bool, True for both faces of a thin plate (default all False: faces of a closed body).

    Example:
        >>> body = Mesh.from_toe(CToe(radius=0.02, width=0.008))       # a C-toe, two-faced
        >>> body.n_elements, float(body.areas.sum())                    # 10 elements, pi r w / ... m^2
    """

    points: Tensor
    normals: Tensor
    areas: Tensor
    thin: Tensor | None = field(default=None)

    def __post_init__(self) -> None:
        dtype = next((v.dtype for v in (self.points, self.normals, self.areas)
                      if isinstance(v, Tensor) and v.dtype.is_floating_point), torch.get_default_dtype())
        for name in ("points", "normals", "areas"):
            v = getattr(self, name)
            if not isinstance(v, Tensor):
                v = torch.as_tensor(v, dtype=dtype)
                setattr(self, name, v)
            if not v.dtype.is_floating_point:
                raise ValueError(f"Mesh.{name} must be a floating tensor, got {v.dtype}")
            if not torch.isfinite(v).all():
                raise ValueError(f"Mesh.{name} contains NaN or inf")
        E = self.points.shape[0] if self.points.ndim == 2 else -1
        if self.points.shape != (E, 3) or self.normals.shape != (E, 3) or self.areas.shape != (E,):
            raise ValueError(f"Mesh expects points (E, 3) m, normals (E, 3), areas (E,) m^2; got "
                             f"{tuple(self.points.shape)}, {tuple(self.normals.shape)}, {tuple(self.areas.shape)}")
        if E == 0:
            raise ValueError("Mesh has no elements")
        norm = torch.linalg.vector_norm(self.normals.detach(), dim=-1)
        if ((norm - 1).abs() > 1e-6).any():
            i = int(((norm - 1).abs() > 1e-6).nonzero()[0])
            raise ValueError(f"Mesh.normals must be unit vectors (outward); element {i} has length "
                             f"{float(norm[i]):.6g}")
        if (self.areas < 0).any():
            raise ValueError("Mesh.areas must be >= 0 (m^2)")
        if self.thin is None:
            self.thin = torch.zeros(E, dtype=torch.bool, device=self.points.device)
        else:
            self.thin = torch.as_tensor(self.thin, device=self.points.device)
            if self.thin.dtype != torch.bool or self.thin.shape != (E,):
                raise ValueError(f"Mesh.thin must be (E,) = ({E},) bool, got {self.thin.dtype} "
                                 f"{tuple(self.thin.shape)}")
        extent = float((self.points.detach().amax(0) - self.points.detach().amin(0)).max())
        if extent > _LARGE_BODY_M:
            warnings.warn(f"mesh spans {extent:.4g} m: lengths are in metres (did you pass millimetres? read_mesh "
                          f"takes unit='mm')", UserWarning, stacklevel=3)

    @property
    def n_elements(self) -> int:
        return self.points.shape[0]

    def to(self, dtype: torch.dtype | None = None, device=None) -> Mesh:
        return Mesh(self.points.to(dtype=dtype, device=device), self.normals.to(dtype=dtype, device=device),
                    self.areas.to(dtype=dtype, device=device), self.thin.to(device=device))

    def transformed(self, rotation=None, translation=None) -> Mesh:
        """The same body with every point p -> R p + t and normal n -> R n (R (3, 3) a rotation, t (3,) m)."""
        dt, dev = self.points.dtype, self.points.device
        R = torch.eye(3, dtype=dt, device=dev) if rotation is None else torch.as_tensor(rotation, dtype=dt, device=dev)
        t = torch.zeros(3, dtype=dt, device=dev) if translation is None else torch.as_tensor(translation, dtype=dt,
                                                                                            device=dev)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"rotation must be (3, 3) and translation (3,), got {tuple(R.shape)}, {tuple(t.shape)}")
        _check_rotation(R[None], "rotation")
        return Mesh(self.points @ R.mT + t, self.normals @ R.mT, self.areas, self.thin)

    @classmethod
    def cat(cls, parts: list[Mesh]) -> Mesh:
        """One body from several meshes (their elements concatenated)."""
        if not parts:
            raise ValueError("Mesh.cat needs at least one Mesh")
        return cls(torch.cat([p.points for p in parts]), torch.cat([p.normals for p in parts]),
                   torch.cat([p.areas for p in parts]), torch.cat([p.thin for p in parts]))

    @classmethod
    def from_toe(cls, toe: Toe, n_across: int = 1) -> Mesh:
        """A planar toe extruded across its width as thin two-faced plates: segment m becomes
        ``n_across`` elements at y in (-width/2, width/2), each of area length x width / n_across, with
        normal (t_z, 0, -t_x) (the planar tangent rotated by -90 degrees; either face, the element is
        thin). The toe's x-z body frame is the mesh's x-z plane: moved in that plane (``planar_motion``),
        ``contacts_3d`` gives exactly ``rft.contacts``'s weights and ``forces_3d`` its forces."""
        if not isinstance(toe, Toe):
            raise TypeError(f"toe must be a Toe (IToe, CToe, PolylineToe), got {type(toe).__name__}")
        n = _n_segments(n_across)
        M = toe.n_segments
        c, t = toe.centres, toe.tangents
        y = ((torch.arange(n, dtype=c.dtype) + 0.5) / n - 0.5) * toe.width
        points = torch.stack([c[:, None, 0].expand(M, n), y.expand(M, n), c[:, None, 1].expand(M, n)], -1)
        normals = torch.stack([t[:, 1], torch.zeros_like(t[:, 0]), -t[:, 0]], -1)[:, None].expand(M, n, 3)
        areas = (toe.lengths * toe.width)[:, None].expand(M, n) / n
        return cls(points.reshape(-1, 3), normals.reshape(-1, 3), areas.reshape(-1),
                   torch.ones(M * n, dtype=torch.bool))

    @classmethod
    def from_triangles(cls, vertices, thin: bool = False) -> Mesh:
        """Elements from triangles (F, 3, 3) (vertex, coordinate) in m: incenter, unit facet normal (right
        hand over the vertex order: counter-clockwise seen from outside) and area, as 3-D RFT's mesh codes
        take them; degenerate (zero-area) triangles are dropped."""
        p, n, a = triangle_elements(vertices)
        return cls(p, n, a, torch.full((p.shape[0],), bool(thin)))


def triangle_elements(vertices) -> tuple[Tensor, Tensor, Tensor]:
    """Incenters (F, 3), unit normals (F, 3) (right hand over the vertex order) and areas (F,) of triangles
    (F, 3, 3); zero-area triangles dropped. Incenter = (a A + b B + c C) / (a + b + c), a the side
    opposite A (MATLAB's ``incenter``); area = |AB x AC| / 2."""
    v = torch.as_tensor(vertices)
    if not v.dtype.is_floating_point:
        v = v.to(torch.get_default_dtype())
    if v.ndim != 3 or v.shape[1:] != (3, 3):
        raise ValueError(f"vertices must be (F, 3, 3) (triangle, vertex, xyz), got {tuple(v.shape)}")
    if not torch.isfinite(v).all():
        raise ValueError("vertices contains NaN or inf")
    A, B, C = v[:, 0], v[:, 1], v[:, 2]
    cross = torch.linalg.cross(B - A, C - A)
    twice = torch.linalg.vector_norm(cross, dim=-1)
    keep = twice > 0
    A, B, C, cross, twice = A[keep], B[keep], C[keep], cross[keep], twice[keep]
    a = torch.linalg.vector_norm(B - C, dim=-1)[:, None]
    b = torch.linalg.vector_norm(C - A, dim=-1)[:, None]
    c = torch.linalg.vector_norm(A - B, dim=-1)[:, None]
    incenter = (a * A + b * B + c * C) / (a + b + c)
    return incenter, cross / twice[:, None], twice / 2


def _check_rotation(R: Tensor, name: str) -> None:
    with torch.no_grad():
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        err = (R @ R.mT - eye).abs().amax()
        det = torch.linalg.det(R)
    tol = 1e-5 if R.dtype == torch.float32 else 1e-9
    if float(err) > tol or bool(((det - 1).abs() > tol).any()):
        raise ValueError(f"{name} must be proper rotation matrices (R R^T = I, det R = 1); max |R R^T - I| = "
                         f"{float(err):.3g}")


def wheel_mesh(radius: float, width: float, n_around: int = 360, n_across: int = 8, sidewalls: bool = True,
               n_rings: int = 8, grousers: int = 0, grouser_height: float = 0.0, grouser_rows: int = 3,
               dtype=torch.float64) -> Mesh:
    """A rigid wheel, axle along the body y axis, centred on the body origin (it rolls toward +x in the
    x-z plane, like ``rft.wheel``'s planar wheel, with angular velocity (0, +omega, 0)).

    - rim: ``n_around`` x ``n_across`` faces on the cylinder of ``radius`` (centres on it, radial
      normals, exact areas r dphi dy), y in (-width/2, width/2);
    - ``sidewalls``: the two disks at y = -+width/2 (normals -+y), ``n_rings`` x ``n_around`` faces
      (centroids and exact areas of the annular sectors);
    - ``grousers``: that many thin radial plates across the width from ``radius`` to ``radius +
      grouser_height`` (``grouser_rows`` elements along the height), evenly spaced, the first at the
      bottom. Thin: the face that moves into the sand counts.

    Lengths in m. Closed faces count only while they lead (n . v > 0), so of the rim only its front half
    takes load (docs/rft3d.md).
    """
    radius, width = _positive("radius", radius), _positive("width", width)
    na, nx, nr = _n_segments(n_around), _n_segments(n_across), _n_segments(n_rings)
    if na < 3:
        raise ValueError(f"n_around must be >= 3, got {na}")
    two_pi = 2 * math.pi
    phi = -math.pi / 2 + (torch.arange(na, dtype=dtype) + 0.5) * (two_pi / na)  # element centre angles from +x
    y = ((torch.arange(nx, dtype=dtype) + 0.5) / nx - 0.5) * width
    cp, sp = torch.cos(phi), torch.sin(phi)
    P, Y = torch.broadcast_tensors(phi[:, None], y[None, :])
    rim_pts = torch.stack([radius * torch.cos(P), Y, radius * torch.sin(P)], -1).reshape(-1, 3)
    rim_nrm = torch.stack([torch.cos(P), torch.zeros_like(P), torch.sin(P)], -1).reshape(-1, 3)
    rim_area = torch.full((na * nx,), radius * (two_pi / na) * (width / nx), dtype=dtype)
    parts = [Mesh(rim_pts, rim_nrm, rim_area)]
    if sidewalls:
        r = torch.linspace(0, radius, nr + 1, dtype=dtype)
        r1, r2 = r[:-1], r[1:]
        area = (r2**2 - r1**2) / 2 * (two_pi / na)  # (nr,)
        # centroid radius of an annular sector: 2/3 (r2^3 - r1^3) / (r2^2 - r1^2) x sinc(dphi / 2)
        half = math.pi / na
        rc = 2 / 3 * (r2**3 - r1**3) / (r2**2 - r1**2) * math.sin(half) / half
        R_, C_ = torch.broadcast_tensors(rc[:, None], cp[None, :])
        S_ = sp[None, :].expand_as(R_)
        for side in (-1.0, 1.0):
            pts = torch.stack([R_ * C_, torch.full_like(R_, side * width / 2), R_ * S_], -1).reshape(-1, 3)
            nrm = torch.zeros_like(pts)
            nrm[:, 1] = side
            parts.append(Mesh(pts, nrm, area[:, None].expand(nr, na).reshape(-1)))
    if grousers:
        G = _n_segments(grousers)
        h = _positive("grouser_height", grouser_height)
        nh = _n_segments(grouser_rows)
        ga = -math.pi / 2 + torch.arange(G, dtype=dtype) * (two_pi / G)
        rr = radius + (torch.arange(nh, dtype=dtype) + 0.5) / nh * h
        A_, R_, Y_ = torch.meshgrid(ga, rr, y, indexing="ij")
        pts = torch.stack([R_ * torch.cos(A_), Y_, R_ * torch.sin(A_)], -1).reshape(-1, 3)
        nrm = torch.stack([-torch.sin(A_), torch.zeros_like(A_), torch.cos(A_)], -1).reshape(-1, 3)
        area = torch.full((pts.shape[0],), (h / nh) * (width / nx), dtype=dtype)
        parts.append(Mesh(pts, nrm, area, torch.ones(pts.shape[0], dtype=torch.bool)))
    return Mesh.cat(parts)


def read_mesh(path, unit: str | None = None, dtype=torch.float64) -> Mesh:
    """A body's surface from a file.

    - ``.stl``: triangles through numpy-stl (``pip install numpy-stl``, the ``mesh`` extra) or, if that is
      missing, trimesh; each triangle becomes an element (incenter, facet normal, area). STL has no unit:
      give ``unit`` ("m", "cm" or "mm"; a ValueError without it).
    - ``.mat`` (MATLAB, through scipy): ``Points`` (3, E) or (E, 3), ``Normals`` likewise, ``Area`` (E,), as
      3-D RFT codes store them (the rover-wheel meshes: millimetres, ``unit="mm"``, the default for .mat).

    Normals are used as stored (not renormalized), areas scaled by unit^2. All faces (``thin`` False).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no mesh file at {path}")
    suffix = path.suffix.lower()
    if suffix == ".mat":
        unit = unit or "mm"
    if unit not in _UNITS:
        raise ValueError(f"unit must be one of {sorted(_UNITS)} (the file's length unit), got {unit!r}")
    s = _UNITS[unit]
    if suffix == ".stl":
        try:
            tri = _read_stl_triangles(path)
        except ImportError:
            raise
        except Exception as e:  # noqa: BLE001 - the STL readers raise many kinds for a file that is not one
            raise ValueError(f"{path}: not a readable STL file ({type(e).__name__}: {e})") from None
        p, n, a = triangle_elements(torch.as_tensor(tri, dtype=dtype) * s)
        return Mesh(p, n, a)
    if suffix == ".mat":
        import numpy as np
        from scipy.io import loadmat

        try:
            m = loadmat(path)
        except Exception as e:  # noqa: BLE001 - scipy raises many kinds for a file that is not MATLAB's
            raise ValueError(f"{path}: not a readable MATLAB .mat file ({type(e).__name__}: {e})") from None
        missing = [k for k in ("Points", "Normals", "Area") if k not in m]
        if missing:
            raise KeyError(f"{path}: no variable(s) {missing}; has {sorted(k for k in m if not k.startswith('__'))}")

        def rows(x, name):
            x = np.asarray(x, dtype=np.float64)
            if x.ndim == 2 and x.shape[0] == 3 and x.shape[1] != 3:
                x = x.T
            if x.ndim != 2 or x.shape[1] != 3:
                raise ValueError(f"{path}: {name} must be (3, E) or (E, 3), got {x.shape}")
            return torch.as_tensor(x, dtype=dtype)

        P, N = rows(m["Points"], "Points"), rows(m["Normals"], "Normals")
        A = torch.as_tensor(np.asarray(m["Area"], dtype=np.float64).reshape(-1), dtype=dtype)
        return Mesh(P * s, N, A * s * s)
    raise ValueError(f"read_mesh reads .stl and .mat files, got {path.name!r}")


def _read_stl_triangles(path: Path):
    """(F, 3, 3) float64 vertices of an STL file (binary or ASCII)."""
    try:
        from stl import mesh as stl_mesh  # numpy-stl
    except ImportError:
        stl_mesh = None
    if stl_mesh is not None:
        return stl_mesh.Mesh.from_file(str(path)).vectors.astype("float64")
    try:
        import trimesh
    except ImportError as e:
        raise ImportError("reading STL needs numpy-stl or trimesh: pip install numpy-stl (or the irft-torch[mesh] "
                          "extra)") from e
    t = trimesh.load(str(path), force="mesh", process=False)
    return t.triangles.astype("float64")
