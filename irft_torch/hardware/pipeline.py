"""The paper's signal pipeline: currents -> torques -> toe forces, minus the force measured in air
along the same path, zero-phase moving-average filtered, repeated trials aligned and averaged,
then contacts + forces written as a dataset for the inference model.

Trials and the air run are aligned by arc length along the toe's path (not by time), so runs at
slightly different speeds or start times line up at the same place.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import uniform_filter1d

from ..rft.contacts import Contacts, contacts
from ..rft.toes import Toe
from .can_log import ResampledLog
from .five_bar import FiveBarLeg
from .motor import MotorModel

__all__ = ["ForceTrace", "forces_from_log", "subtract_air", "zero_phase_filter", "average_trials",
           "Dataset", "build_dataset", "save_dataset", "load_dataset"]


@dataclass
class ForceTrace:
    """One run: time (T,) s, joint angles q (T, 2) rad, toe position (T, 2) m (leg frame), motor
    torques tau (T, 2) N m, ground force on the toe (T, 2) N (NaN where masked), valid (T,)."""

    time: np.ndarray
    q: np.ndarray
    toe: np.ndarray
    tau: np.ndarray
    force: np.ndarray
    valid: np.ndarray

    @property
    def arc_length(self) -> np.ndarray:
        """Distance travelled by the toe, m (T,)."""
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.toe, axis=0), axis=1))])

    def masked(self, keep: np.ndarray) -> ForceTrace:
        return ForceTrace(self.time[keep], self.q[keep], self.toe[keep], self.tau[keep], self.force[keep],
                          self.valid[keep])


def forces_from_log(log: ResampledLog, leg: FiveBarLeg, motors: tuple[MotorModel, MotorModel]) -> ForceTrace:
    """tau = k_t I per motor, q from the encoders, F = -J^-T tau (singular samples masked)."""
    q = torch.stack([motors[i].joint_angle(torch.as_tensor(log.position[:, i])) for i in range(2)], -1)
    tau = torch.stack([motors[i].torque(torch.as_tensor(log.iq[:, i])) for i in range(2)], -1)
    force, ok = leg.ground_force(q, tau)
    toe = leg.forward_kinematics(q)
    valid = np.asarray(log.valid) & ok.numpy()
    force = force.numpy().copy()
    force[~valid] = np.nan
    return ForceTrace(np.asarray(log.time), q.numpy(), toe.numpy(), tau.numpy(), force, valid)


def _interp_valid(x_new: np.ndarray, x: np.ndarray, y: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Interpolate y (n, 2) at x_new over valid samples; NaN outside their span."""
    xv, yv = x[valid], y[valid]
    if len(xv) < 2:
        return np.full((len(x_new), y.shape[1]), np.nan)
    order = np.argsort(xv, kind="stable")
    xv, yv = xv[order], yv[order]
    out = np.stack([np.interp(x_new, xv, yv[:, k]) for k in range(y.shape[1])], -1)
    out[(x_new < xv[0]) | (x_new > xv[-1])] = np.nan
    return out


def subtract_air(trial: ForceTrace, air: ForceTrace) -> ForceTrace:
    """Trial force minus the air run's force at the same arc length along the path (removes
    gravity, cogging and friction that repeat with position). Samples beyond the air run's reach
    are masked."""
    air_f = _interp_valid(trial.arc_length, air.arc_length, air.force, air.valid)
    force = trial.force - air_f
    valid = trial.valid & np.isfinite(force).all(1)
    force[~valid] = np.nan
    return ForceTrace(trial.time, trial.q, trial.toe, trial.tau, force, valid)


def zero_phase_filter(trace: ForceTrace, window: int = 5) -> ForceTrace:
    """Centred moving average of ``window`` samples (no lag); masked samples are bridged by linear
    interpolation for the filter and stay masked."""
    if int(window) != window or window < 1:
        raise ValueError(f"window must be a positive integer (samples), got {window}")
    if window == 1:
        return trace
    idx = np.arange(len(trace.time))
    filled = _interp_valid(idx.astype(float), idx.astype(float), np.nan_to_num(trace.force), trace.valid)
    filled = np.where(np.isnan(filled), 0.0, filled)
    smooth = uniform_filter1d(filled, size=int(window), axis=0, mode="nearest")
    smooth[~trace.valid] = np.nan
    return ForceTrace(trace.time, trace.q, trace.toe, trace.tau, smooth, trace.valid)


def average_trials(trials: list[ForceTrace], n_points: int | None = None) -> ForceTrace:
    """Align trials by arc length and average their forces (and joint angles) on a common grid
    spanning the distance all trials covered."""
    if not trials:
        raise ValueError("average_trials needs at least one trial")
    if len(trials) == 1:
        return trials[0]
    span = min(t.arc_length[-1] for t in trials)
    n = n_points or int(np.median([len(t.time) for t in trials]))
    s = np.linspace(0.0, span, n)
    ref = trials[0]
    forces = np.stack([_interp_valid(s, t.arc_length, t.force, t.valid) for t in trials])
    qs = np.stack([_interp_valid(s, t.arc_length, t.q, np.ones(len(t.time), bool)) for t in trials])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all trials masked at a point: stays NaN
        force = np.nanmean(forces, axis=0)
    valid = np.isfinite(force).all(1)
    q = qs.mean(0)
    time = np.interp(s, ref.arc_length, ref.time)
    toe = np.stack([np.interp(s, ref.arc_length, ref.toe[:, k]) for k in range(2)], -1)
    tau = np.stack([np.interp(s, ref.arc_length, ref.tau[:, k]) for k in range(2)], -1)
    return ForceTrace(time, q, toe, tau, force, valid)


@dataclass
class Dataset:
    """What the inference model takes: contacts (T, M), forces (T, 2) N, time (T,) s, and the toe
    path (T, 2) m (world frame) for plots."""

    contacts: Contacts
    forces: torch.Tensor
    time: torch.Tensor
    toe_position: torch.Tensor

    def __len__(self) -> int:
        return len(self.contacts)


def build_dataset(trace: ForceTrace, leg: FiveBarLeg, toe: Toe, hip_height: float,
                  heading: str | float = 0.0) -> Dataset:
    """Contacts of ``toe`` along the leg's toe path (hips ``hip_height`` m above the surface) and
    the trace's forces; masked samples are dropped (the count is in the returned length)."""
    keep = trace.valid & np.isfinite(trace.force).all(1)
    if keep.sum() < 2:
        raise ValueError(f"only {int(keep.sum())} valid samples: nothing to learn from")
    t = trace.masked(keep)
    path = leg.toe_path(t.time, t.q, heading=heading, hip_height=hip_height)
    c = contacts(toe, path)
    return Dataset(c, torch.as_tensor(t.force), torch.as_tensor(t.time), path.position)


def save_dataset(path, ds: Dataset, **meta) -> None:
    """npz with beta, gamma, weight_x, weight_z (T, M), forces (T, 2), time, toe_position, meta."""
    arrays = {k: v.detach().cpu().numpy() for k, v in ds.contacts.as_dict().items()}
    np.savez(path, forces=ds.forces.numpy(), time=ds.time.numpy(), toe_position=ds.toe_position.numpy(),
             meta=np.array(repr(meta)), **arrays)


def load_dataset(path) -> Dataset:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}")
    d = np.load(path)
    need = {"beta", "gamma", "weight_x", "weight_z", "forces", "time", "toe_position"}
    missing = need - set(d.files)
    if missing:
        raise ValueError(f"{path} is not an irft dataset: missing {sorted(missing)}")
    c = Contacts(*(torch.as_tensor(d[k]) for k in ("beta", "gamma", "weight_x", "weight_z")))
    return Dataset(c, torch.as_tensor(d["forces"]), torch.as_tensor(d["time"]), torch.as_tensor(d["toe_position"]))

