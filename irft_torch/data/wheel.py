"""Reader for the single-wheel testbed runs in sand (by others) and their RFT predictions.

The data are not part of this package (their authors state no licence); point the reader at a
copy, e.g. ``shared/data/rover_wheel``. Files (MATLAB, read with ``scipy.io.loadmat``):
``all_{smooth,grouser}_data_2.mat`` (struct array ``all_results``, one element per run),
``{smooth,grouser}RFT.mat`` (struct array ``RFToutput``, the authors' RFT prediction per run, same
order), ``smooth_wheel_125_2D.mat`` (the smooth rim's planar profile, mm) and
``grousered_wheel_125.mat`` (the grousered wheel's 3-D surface mesh, mm).

Sensor axes -> this package's frame, exactly as the data's own plotting script maps them: the wheel
travels toward +x, and

    longitudinal (drawbar) F_x = -avg_Fy,  lateral = -avg_Fx,  vertical (lift on the wheel) F_z = -avg_Fz,
    sinkage = -avg_Z (mm -> m),

so a locked wheel's F_x is negative (resisting the motion) and F_z is the rig's load (18-25 N).
The authors' RFT: longitudinal ``ForceX``, lateral ``ForceY``, vertical ``ForceZ`` (already in the
wheel frame). Speeds: ``avg_Vx`` the carriage speed and ``avg_Vry`` the measured rim speed (mm/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..rft.toes import Toe
from ..rft.wheel import profile_from_elements

__all__ = ["WheelRun", "read_wheel_runs", "read_profile", "WHEEL_RADIUS", "WHEEL_WIDTH", "WHEELS", "GROUSER_PITCH",
           "read_wheel_mesh", "wheel_motion", "MESHES", "MESH_TO_WHEEL"]

WHEEL_RADIUS = 0.0625  # m, both wheels (grouser tips for the grousered one)
WHEEL_WIDTH = 0.060  # m
GROUSER_PITCH = 2 * math.pi / 24  # rad: the mesh's grouser faces repeat every 15 degrees
WHEELS = {"smooth": ("all_smooth_data_2.mat", "smoothRFT.mat"),
          "grouser": ("all_grouser_data_2.mat", "grouserRFT.mat")}


@dataclass(frozen=True)
class WheelRun:
    """One measured run, in this package's frame and SI units (see the module doc)."""

    wheel: str
    index: int  # position in the file
    slip_angle_deg: float
    slip: float  # the file's slip, 1 - Vx / Vry (skidding: Vry / Vx - 1)
    commanded_rim_speed: float  # m/s, the file's Vry: one of 9 levels at slip angle 0 (groups the slips)
    trial: int
    v: float  # carriage speed, m/s
    rim_speed: float  # measured rim speed omega r, m/s
    sinkage: float  # m (>= 0 when sunk)
    force: tuple  # (F_x longitudinal, F_z vertical), N, mean over the steady run
    force_std: tuple  # their standard deviations over the run, N
    lateral: float  # N
    rft_force: tuple  # the authors' RFT (longitudinal, vertical), N
    rft_lateral: float = math.nan  # the authors' RFT lateral force (their ForceY), N

    @property
    def omega(self) -> float:
        """Spin, rad/s (positive rolling forward)."""
        return self.rim_speed / WHEEL_RADIUS


def _scalar(x) -> float:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.size != 1:
        raise ValueError(f"expected a scalar field, got shape {np.asarray(x).shape}")
    return float(a[0])


def _read_mat(path: Path) -> dict:
    """scipy's loadmat of ``path``; a file that is not MATLAB's is a ValueError naming it."""
    from scipy.io import loadmat  # scipy is a dependency of the experiments only

    if not path.is_file():
        raise FileNotFoundError(f"no file {path.name} in {path.parent} (the rover-wheel data are not shipped)")
    try:
        return loadmat(path)
    except Exception as e:  # noqa: BLE001 - scipy raises many kinds for a damaged or foreign file
        raise ValueError(f"{path}: not a readable MATLAB .mat file ({type(e).__name__}: {e}); is it the rover-wheel "
                         "data's file of that name?") from None


def _data_dir(data_dir) -> Path:
    data_dir = Path(data_dir)
    if data_dir.is_file():
        raise NotADirectoryError(f"{data_dir} is a file: give the folder that holds the rover-wheel data "
                                 f"({', '.join(sorted({f for w in WHEELS.values() for f in w}))}), e.g. "
                                 f"{data_dir.parent}")
    if not data_dir.is_dir():
        raise FileNotFoundError(f"no rover-wheel data directory at {data_dir}")
    return data_dir


def _loadmat(path: Path, key: str):
    m = _read_mat(path)
    if key not in m:
        raise KeyError(f"{path}: no variable {key!r}; has {sorted(k for k in m if not k.startswith('__'))}")
    return m[key].reshape(-1)


def read_wheel_runs(data_dir, wheel: str, slip_angle_deg: float | None = 0.0) -> list[WheelRun]:
    """Runs of one wheel ("smooth" or "grouser"), with the authors' RFT prediction matched element
    by element (their slip and slip angle are checked to agree). ``slip_angle_deg=None``: all; a slip
    angle no run has is a ValueError listing the file's. A file that is not MATLAB's, or a file given
    for the folder, is an error naming it."""
    if wheel not in WHEELS:
        raise ValueError(f"wheel must be one of {sorted(WHEELS)}, got {wheel!r}")
    data_dir = _data_dir(data_dir)
    runs_file, rft_file = WHEELS[wheel]
    runs = _loadmat(data_dir / runs_file, "all_results")
    rft = _loadmat(data_dir / rft_file, "RFToutput")
    if len(runs) != len(rft):
        raise ValueError(f"{runs_file} has {len(runs)} runs but {rft_file} {len(rft)} predictions")
    out = []
    angles = set()
    for i, (r, p) in enumerate(zip(runs, rft)):
        angle, slip = _scalar(r["beta"]), _scalar(r["slip"])
        angles.add(angle)
        if abs(_scalar(p["beta"]) - angle) > 1e-6 or abs(_scalar(p["slip"]) - slip) > 1e-6:
            raise ValueError(f"{wheel} run {i}: the RFT file's slip/slip angle ({_scalar(p['slip'])}, "
                             f"{_scalar(p['beta'])}) do not match the run's ({slip}, {angle})")
        if slip_angle_deg is not None and abs(angle - slip_angle_deg) > 1e-6:
            continue
        out.append(WheelRun(
            wheel=wheel, index=i, slip_angle_deg=angle, slip=slip,
            commanded_rim_speed=_scalar(r["Vry"]) / 1000, trial=int(_scalar(r["trial_num"])),
            v=_scalar(r["avg_Vx"]) / 1000, rim_speed=_scalar(r["avg_Vry"]) / 1000,
            sinkage=-_scalar(r["avg_Z"]) / 1000,
            force=(-_scalar(r["avg_Fy"]), -_scalar(r["avg_Fz"])),
            force_std=(_scalar(r["std_Fy"]), _scalar(r["std_Fz"])),
            lateral=-_scalar(r["avg_Fx"]),
            rft_force=(_scalar(p["ForceX"]), _scalar(p["ForceZ"])), rft_lateral=_scalar(p["ForceY"]),
        ))
    if not out and slip_angle_deg is not None:
        raise ValueError(f"no {wheel} run at slip angle {slip_angle_deg:g} deg: {runs_file} holds slip angles "
                         f"{', '.join(f'{x:g}' for x in sorted(angles))} deg (slip_angle_deg=None: all)")
    return out


def read_profile(data_dir, wheel: str, angle_bins: int = 360, normal_bins: int = 8) -> Toe:
    """The wheel's planar profile (counter-clockwise ``Toe`` about the axle, m).

    Smooth: the file's 2-D elements (points, normals, arc lengths). Grousered: the 3-D mesh cut to a
    planar profile for slip angle 0: elements whose normal lies in the wheel plane (|n_across| < 0.5;
    the side walls drop out) and farther than radius / 2 from the axle (not the hub), projected on the
    plane, each of length area / width; they are merged
    per (position-angle bin, normal-direction bin) into one segment (area-weighted centre and normal,
    summed length), which keeps the rim, the grouser faces and the tips apart.
    """
    data_dir = _data_dir(data_dir)
    if wheel == "smooth":
        f = data_dir / "smooth_wheel_125_2D.mat"
        if not f.is_file():
            raise FileNotFoundError(f"no {f.name} in {data_dir}")
        m = _read_mat(f)
        pts, nrm, area = m["Points"].T / 1000, m["Normals"].T, m["Area"].reshape(-1) / 1000
        return profile_from_elements(pts, nrm, area, WHEEL_WIDTH)
    if wheel != "grouser":
        raise ValueError(f"wheel must be 'smooth' or 'grouser', got {wheel!r}")
    f = data_dir / "grousered_wheel_125.mat"
    if not f.is_file():
        raise FileNotFoundError(f"no {f.name} in {data_dir}")
    m = _read_mat(f)
    P, N, A = m["Points"], m["Normals"], m["Area"].reshape(-1)
    keep = (np.abs(N[0]) < 0.5) & (np.hypot(P[1], P[2]) > 500 * WHEEL_RADIUS)  # rim and grousers, not the hub
    pts = P[1:, keep].T / 1000  # (x, z) in m
    nrm = N[1:, keep].T
    nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    length = A[keep] / 1e6 / WHEEL_WIDTH  # m^2 / m
    pos_ang = np.arctan2(pts[:, 1], pts[:, 0])
    radial = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    # normal direction relative to the radial one, so grouser faces (tangential normals) separate
    rel = np.arctan2(radial[:, 0] * nrm[:, 1] - radial[:, 1] * nrm[:, 0], (radial * nrm).sum(1))
    ia = np.floor((pos_ang + math.pi) / (2 * math.pi) * angle_bins).astype(int) % angle_bins
    inb = np.floor((rel + math.pi) / (2 * math.pi) * normal_bins + 0.5).astype(int) % normal_bins
    key = ia * normal_bins + inb
    uniq, inv = np.unique(key, return_inverse=True)
    wsum = np.bincount(inv, weights=length)
    c = np.stack([np.bincount(inv, weights=length * pts[:, j]) for j in range(2)], 1) / wsum[:, None]
    n = np.stack([np.bincount(inv, weights=length * nrm[:, j]) for j in range(2)], 1)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    return profile_from_elements(torch.as_tensor(c), torch.as_tensor(n), torch.as_tensor(wsum), WHEEL_WIDTH)


# ---- 3-D: the wheels' meshes and each run's rigid motion (rft.contacts_3d) ------------------------------
MESHES = {"smooth": "smooth_wheel_125.mat", "grouser": "grousered_wheel_125.mat"}
# The meshes' own frame (x the axle, 0 to 60 mm across the width, y the heading, z up, axle centre at the
# origin) -> this package's wheel frame (heading +x, axle along y, z up): (x, y, z) -> (y, -x, z). Entries
# 0 and +-1, so the normals' round-off (which decides some contacts, reference/rft3d_facts.md) is kept.
MESH_TO_WHEEL = ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0))


def read_wheel_mesh(data_dir, wheel: str):
    """The wheel's 3-D surface mesh as the data's authors used it (``rft.Mesh``, m, m^2), turned into this
    package's wheel frame (``MESH_TO_WHEEL``): it rolls toward +x about the y axis, the axle at the origin.
    Smooth: 37,526 elements (rim and one sidewall); grousered: 59,092."""
    from ..rft.mesh import read_mesh

    if wheel not in MESHES:
        raise ValueError(f"wheel must be one of {sorted(MESHES)}, got {wheel!r}")
    data_dir = _data_dir(data_dir)
    f = data_dir / MESHES[wheel]
    if not f.is_file():
        raise FileNotFoundError(f"no {f.name} in {data_dir} (the rover-wheel data are not shipped)")
    return read_mesh(f, unit="mm").transformed(torch.tensor(MESH_TO_WHEEL, dtype=torch.float64))


def wheel_motion(runs: list[WheelRun], as_commanded: bool = False, dtype=torch.float64) -> dict:
    """Each run's rigid motion in the wheel frame (``read_wheel_mesh``), keyword arguments of
    ``rft.contacts_3d``: carriage velocity V (cos psi, sin psi, 0) at slip angle psi (the wheel heads +x and
    drifts toward +y, the side of the mesh's sidewall), spin (0, rim speed / radius, 0) (rolling forward),
    surface at sinkage - radius (axle at the origin). Measured speeds (``avg_Vx``, ``avg_Vry``) by default;
    ``as_commanded``: the authors' inputs (V = 10 mm/s and the commanded rim speed), with which their
    predictions ``rft_force`` / ``rft_lateral`` are reproduced. The sinkage is the measured one either way."""
    psi = torch.tensor([math.radians(r.slip_angle_deg) for r in runs], dtype=dtype)
    V = torch.tensor([0.010 if as_commanded else r.v for r in runs], dtype=dtype)
    rim = torch.tensor([r.commanded_rim_speed if as_commanded else r.rim_speed for r in runs], dtype=dtype)
    sink = torch.tensor([r.sinkage for r in runs], dtype=dtype)
    zero = torch.zeros_like(V)
    return {"velocity": torch.stack([V * torch.cos(psi), V * torch.sin(psi), zero], -1),
            "angular_velocity": torch.stack([zero, rim / WHEEL_RADIUS, zero], -1),
            "surface": sink - WHEEL_RADIUS}
