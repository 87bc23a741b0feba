"""The paper's signal pipeline: currents -> torques -> toe forces, minus the force measured in air
along the same path, zero-phase moving-average filtered, repeated trials aligned and averaged,
then contacts + forces written as a dataset for the inference model.

Trials and the air run are aligned by arc length along the toe's path (not by time), so runs at
slightly different speeds or start times line up at the same place.
"""

from __future__ import annotations

import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import uniform_filter1d

from ..rft.contacts import SURFACE_FIELDS, Contacts, contacts
from ..rft.toes import Toe
from .can_log import ResampledLog
from .five_bar import FiveBarLeg, SingularConfigurationWarning
from .motor import MotorModel

__all__ = ["ForceTrace", "forces_from_log", "subtract_air", "zero_phase_filter", "average_trials",
           "Dataset", "build_dataset", "dataset_summary", "save_dataset", "load_dataset"]


@dataclass
class ForceTrace:
    """One run: time (T,) s, joint angles q (T, 2) rad, toe position (T, 2) m (leg frame), motor
    torques tau (T, 2) N m, ground force on the toe (T, 2) N (NaN where masked), valid (T,);
    why_masked: why samples were masked, reason -> count (raw outliers dropped before resampling are
    counted here too)."""

    time: np.ndarray
    q: np.ndarray
    toe: np.ndarray
    tau: np.ndarray
    force: np.ndarray
    valid: np.ndarray
    why_masked: dict = field(default_factory=dict)

    @property
    def arc_length(self) -> np.ndarray:
        """Distance travelled by the toe, m (T,)."""
        step = np.linalg.norm(np.diff(self.toe, axis=0), axis=1)
        step[~np.isfinite(step)] = 0.0  # unreachable samples (masked) add no distance
        return np.concatenate([[0.0], np.cumsum(step)])

    def masked(self, keep: np.ndarray) -> ForceTrace:
        return ForceTrace(self.time[keep], self.q[keep], self.toe[keep], self.tau[keep], self.force[keep],
                          self.valid[keep], dict(self.why_masked))


def forces_from_log(log: ResampledLog, leg: FiveBarLeg, motors: tuple[MotorModel, MotorModel]) -> ForceTrace:
    """tau = k_t I per motor (or, when the log carries torques, direction x gear_ratio x the reported
    torque: ODrive Get_Torques is motor-side; MIT-mode replies are output-side, so use gear_ratio 1
    there, as for their output-side positions), q from the encoders, F = -J^-T tau (singular
    samples masked).
    Samples whose joint angles the leg cannot reach (wrong link lengths, offsets) are masked and
    counted; if none is reachable this raises ValueError naming the leg options."""
    q = torch.stack([motors[i].joint_angle(torch.as_tensor(log.position[:, i])) for i in range(2)], -1)
    if log.iq is not None:
        tau = torch.stack([motors[i].torque(torch.as_tensor(log.iq[:, i])) for i in range(2)], -1)
    elif log.torque is not None:
        tau = torch.stack([motors[i].direction * motors[i].gear_ratio * torch.as_tensor(log.torque[:, i])
                           for i in range(2)], -1)
    else:
        raise ValueError("the log carries neither currents nor torques")
    toe = leg.forward_kinematics(q)
    reach = torch.isfinite(toe).all(-1).numpy()
    masked = dict(getattr(log, "masked", {}) or {})
    if not reach.any():
        raise ValueError(f"none of the {len(reach)} joint-angle samples is reachable by a five-bar leg with "
                         f"l1 = {leg.l1} m, l2 = {leg.l2} m, hip spacing {leg.hip_spacing} m (first q = "
                         f"{np.round(q[0].numpy(), 3).tolist()} rad): check --l1/--l2/--hip-spacing, --zero-offsets, "
                         "--directions and --gear-ratio")
    if not reach.all():
        masked["joint angles out of the leg's reach (check --l1/--l2)"] = int((~reach).sum())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SingularConfigurationWarning)
        force, ok = leg.ground_force(q, tau, warn=False)
    ok = ok.numpy()
    sing = reach & ~ok
    if sing.any():
        warnings.warn(f"{int(sing.sum())} of {len(ok)} samples are near a singular leg configuration "
                      f"(condition number > {leg.max_condition}); their forces are masked (NaN)",
                      SingularConfigurationWarning, stacklevel=2)
        masked[f"near a singular leg configuration (cond(J) > {leg.max_condition:g})"] = int(sing.sum())
    gaps = ~np.asarray(log.valid)
    if gaps.any():
        masked["inside a gap in the log"] = int(gaps.sum())
    valid = np.asarray(log.valid) & ok
    force = force.numpy().copy()
    force[~valid] = np.nan
    return ForceTrace(np.asarray(log.time), q.numpy(), toe.numpy(), tau.numpy(), force, valid, masked)


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


def _path_mismatch(ref: ForceTrace, other: ForceTrace, n: int = 200) -> tuple[float, float, float]:
    """(RMS distance between the two toe paths at the same arc length, the same with ``other``
    reversed, the distance both cover), m."""
    span = min(ref.arc_length[-1], other.arc_length[-1])
    s = np.linspace(0.0, span, n)
    ones_r, ones_o = np.isfinite(ref.toe).all(1), np.isfinite(other.toe).all(1)
    a = _interp_valid(s, ref.arc_length, ref.toe, ones_r)
    b = _interp_valid(s, other.arc_length, other.toe, ones_o)
    b_rev = _interp_valid(other.arc_length[-1] - s, other.arc_length, other.toe, ones_o)
    rms = float(np.sqrt(np.nanmean(((a - b) ** 2).sum(1))))
    rms_rev = float(np.sqrt(np.nanmean(((a - b_rev) ** 2).sum(1))))
    return rms, rms_rev, float(span)


def _check_same_path(ref: ForceTrace, other: ForceTrace, what: str, path_tol: float | None) -> None:
    rms, rms_rev, span = _path_mismatch(ref, other)
    tol = path_tol if path_tol is not None else max(0.01, 0.05 * span)
    if not rms <= tol:
        hint = (" It runs the stroke in the other direction: record every run in the same direction "
                "(or drop it)." if rms_rev <= tol else " Check that it is a run of the same gait.")
        raise ValueError(f"{what} does not follow the reference path: RMS distance {rms * 100:.1f} cm between the "
                         f"toe paths at equal arc length (tolerance {tol * 100:.1f} cm).{hint}")


def subtract_air(trial: ForceTrace, air: ForceTrace, path_tol: float | None = None) -> ForceTrace:
    """Trial force minus the air run's force at the same arc length along the path (removes
    gravity, cogging and friction that repeat with position). Samples beyond the air run's reach
    are masked and counted.

    Raises ValueError when the air run does not follow the trial's path (RMS distance between the
    toe paths at equal arc length above ``path_tol`` m, default max(1 cm, 5 % of the path)), e.g.
    an air run recorded in the other direction."""
    _check_same_path(trial, air, "the air run", path_tol)
    air_f = _interp_valid(trial.arc_length, air.arc_length, air.force, air.valid)
    force = trial.force - air_f
    beyond = trial.valid & ~np.isfinite(air_f).all(1)
    valid = trial.valid & np.isfinite(force).all(1)
    force[~valid] = np.nan
    masked = dict(trial.why_masked)
    if beyond.any():
        masked["no air-run force at this arc length (the air run is shorter or masked there)"] = int(beyond.sum())
    return ForceTrace(trial.time, trial.q, trial.toe, trial.tau, force, valid, masked)


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
    return ForceTrace(trace.time, trace.q, trace.toe, trace.tau, smooth, trace.valid, dict(trace.why_masked))


def average_trials(trials: list[ForceTrace], n_points: int | None = None, coverage: str = "error",
                   min_coverage: float = 0.95, path_tol: float | None = None) -> ForceTrace:
    """Align trials by arc length and average their forces (and joint angles) on a common grid.

    Every trial must follow trial 0's path in the same direction (RMS distance between the toe
    paths at equal arc length at most ``path_tol`` m, default max(1 cm, 5 % of the path)):
    otherwise ValueError (a reversed stroke is never averaged). A trial that covers less than
    ``min_coverage`` of the longest one (cut short, a truncated log) is an error with
    ``coverage="error"`` (default); with ``coverage="crop"`` every trial is cropped to the distance
    all covered, and a warning says how much was dropped.
    """
    if not trials:
        raise ValueError("average_trials needs at least one trial")
    if coverage not in ("error", "crop"):
        raise ValueError(f"coverage must be 'error' or 'crop', got {coverage!r}")
    if not 0 < min_coverage <= 1:
        raise ValueError(f"min_coverage must be in (0, 1], got {min_coverage}")
    if len(trials) == 1:
        return trials[0]
    lengths = np.array([t.arc_length[-1] for t in trials])
    longest = float(lengths.max())
    short = np.nonzero(lengths < min_coverage * longest)[0]
    if len(short) and coverage == "error":
        k = int(short[0])
        raise ValueError(f"trial {k} covers {lengths[k]:.3f} m of the {longest:.3f} m path "
                         f"({100 * lengths[k] / longest:.0f} %, below {100 * min_coverage:.0f} %): it is shorter than "
                         "the others (cut short, or a truncated log). Drop it, or crop every trial to the distance all "
                         "covered (coverage='crop', irft ingest --crop-trials).")
    for k in range(1, len(trials)):
        _check_same_path(trials[0], trials[k], f"trial {k}", path_tol)
    span = float(lengths.min())
    if len(short):
        warnings.warn(f"cropping every trial to {span:.3f} m, the distance all covered; "
                      f"{longest - span:.3f} m of the longest trial is dropped", stacklevel=2)
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
    masked = {}
    if (~valid).any():
        masked["masked in every trial at this arc length"] = int((~valid).sum())
    return ForceTrace(time, q, toe, tau, force, valid, masked)


@dataclass
class Dataset:
    """What the inference model takes: contacts (T, M), forces (T, 2) N, time (T,) s, and the toe
    path (T, 2) m (world frame) for plots. ``statistics``: optional named arrays saved with the data
    (the inference side's sufficient statistics, ``gp.statistics``; opaque here)."""

    contacts: Contacts
    forces: torch.Tensor
    time: torch.Tensor
    toe_position: torch.Tensor
    statistics: dict | None = None

    def __len__(self) -> int:
        return len(self.contacts)


def build_dataset(trace: ForceTrace, leg: FiveBarLeg, toe: Toe, hip_height: float,
                  heading: str | float = 0.0, max_depth: float | None = None) -> Dataset:
    """Contacts of ``toe`` along the leg's toe path (hips ``hip_height`` m above the surface) and
    the trace's forces; masked samples are dropped (the count is in the returned length).

    Physical checks (ValueError naming the option to check): ``hip_height`` must be positive (the
    motor axes are above the sand); the toe must touch the sand at some sample; with ``max_depth``
    [m] given, the toe's reference point must stay within that depth.
    """
    if not (np.isfinite(hip_height) and hip_height > 0):
        raise ValueError(f"hip_height must be the (positive) height of the motor axes above the sand surface in m, "
                         f"got {hip_height}")
    keep = trace.valid & np.isfinite(trace.force).all(1)
    if keep.sum() < 2:
        raise ValueError(f"only {int(keep.sum())} valid samples: nothing to learn from")
    t = trace.masked(keep)
    path = leg.toe_path(t.time, t.q, heading=heading, hip_height=hip_height)
    z = path.position[:, 1].numpy()
    if max_depth is not None and -z.min() > max_depth:
        raise ValueError(f"the toe reaches {-z.min():.3f} m below the surface, deeper than max_depth = {max_depth} m "
                         f"(toe z from {z.min():.3f} to {z.max():.3f} m): check --hip-height (the motor axes' height "
                         "above the sand, positive) and --l1/--l2")
    c = contacts(toe, path)
    if not bool((c.weight_z != 0).any()):
        raise ValueError(f"the toe never touches the sand (toe z from {z.min():.3f} to {z.max():.3f} m with hips "
                         f"{hip_height} m above the surface): check --hip-height and --l1/--l2")
    return Dataset(c, torch.as_tensor(t.force), torch.as_tensor(t.time), path.position)


def dataset_summary(ds: Dataset, masked: dict | None = None, n_before: int | None = None) -> list[str]:
    """Short printable lines: duration [s], samples, time in contact, toe depth range [m], force
    range [N] per axis, and the masked samples with their reasons."""
    t = ds.time.numpy()
    f = ds.forces.numpy()
    z = ds.toe_position[:, 1].numpy()
    contact = (ds.contacts.weight_z != 0).any(1).numpy()
    dt = np.diff(t)
    dur = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    contact_s = float(np.sum(np.where(contact[1:] | contact[:-1], dt, 0.0))) if len(t) > 1 else 0.0
    lines = [
        f"duration {dur:.2f} s, {len(ds)} samples x {ds.contacts.n_segments} segments"
        + (f" (of {n_before})" if n_before is not None and n_before != len(ds) else ""),
        f"in contact {contact_s:.2f} s ({100 * contact.mean():.0f} % of samples), toe reference depth "
        f"{max(0.0, -z.max()):.3f} to {max(0.0, -z.min()):.3f} m",
        f"force F_x {f[:, 0].min():.3g} to {f[:, 0].max():.3g} N, F_z {f[:, 1].min():.3g} to {f[:, 1].max():.3g} N",
    ]
    if masked:
        lines.append("masked: " + "; ".join(f"{v} {k}" for k, v in masked.items()))
    else:
        lines.append("masked: none")
    return lines


STATISTICS_PREFIX = "statistics."


def save_dataset(path, ds: Dataset, **meta) -> Path:
    """npz with beta, gamma, weight_x, weight_z (T, M) (and depth, area_x, area_z where the contacts
    carry them), forces (T, 2), time, toe_position, meta, and ``ds.statistics`` (if any) as arrays
    named "statistics.<name>". ".npz" is appended when ``path`` lacks it; the file is written whole
    or not at all (a temporary file renamed into place). Returns the path written."""
    import os

    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    arrays = {k: v.detach().cpu().numpy() for k, v in ds.contacts.as_dict().items()}
    arrays.update({STATISTICS_PREFIX + k: np.asarray(v) for k, v in (ds.statistics or {}).items()})
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, forces=ds.forces.numpy(), time=ds.time.numpy(), toe_position=ds.toe_position.numpy(),
                     meta=np.array(repr(meta)), **arrays)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def load_dataset(path) -> Dataset:
    """Read a dataset written by ``save_dataset``; a damaged, truncated or foreign file raises
    ValueError saying so (never a zip or pickle traceback)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}")
    if path.is_dir():
        raise ValueError(f"{path} is a directory, not a dataset .npz")
    need = ("beta", "gamma", "weight_x", "weight_z", "forces", "time", "toe_position")
    try:
        with np.load(path, allow_pickle=False) as d:
            missing = set(need) - set(d.files)
            if missing:
                raise ValueError(f"{path} is not an irft dataset: missing {sorted(missing)}")
            arrays = {k: np.asarray(d[k]) for k in need}
            stats = {k[len(STATISTICS_PREFIX):]: np.asarray(d[k]) for k in d.files if k.startswith(STATISTICS_PREFIX)}
            # the signed depths and areas (a learned surface offset, docs/surface.md): optional, all three
            surface = [k for k in SURFACE_FIELDS if k in d.files]
            if surface and len(surface) != len(SURFACE_FIELDS):
                raise ValueError(f"{path} is damaged: it holds {surface} but not all of {list(SURFACE_FIELDS)}")
            arrays.update({k: np.asarray(d[k]) for k in surface})
    except ValueError as e:
        if "not an irft dataset" in str(e):
            raise
        raise ValueError(f"{path} is damaged or not an irft dataset (.npz from irft ingest): {e}") from None
    except (zipfile.BadZipFile, EOFError, OSError, KeyError) as e:
        raise ValueError(f"{path} is damaged or not an irft dataset (.npz from irft ingest): "
                         f"{type(e).__name__}: {e}") from None
    T = len(arrays["forces"])
    shapes = {k: v.shape for k, v in arrays.items()}
    ok = (arrays["forces"].shape == (T, 2) and arrays["time"].shape == (T,) and arrays["toe_position"].shape == (T, 2)
          and all(arrays[k].ndim == 2 and arrays[k].shape[0] == T for k in need[:4] + tuple(surface))
          and len({arrays[k].shape for k in need[:4] + tuple(surface)}) == 1)
    if not ok:
        raise ValueError(f"{path}: inconsistent array shapes {shapes}; the file is damaged")
    bad = [k for k, v in arrays.items() if not np.issubdtype(v.dtype, np.floating) or not np.isfinite(v).all()]
    if bad:
        raise ValueError(f"{path}: non-finite or non-numeric values in {bad}; the file is damaged")
    c = Contacts(**{k: torch.as_tensor(arrays[k]) for k in need[:4] + tuple(surface)})
    return Dataset(c, torch.as_tensor(arrays["forces"]), torch.as_tensor(arrays["time"]),
                   torch.as_tensor(arrays["toe_position"]), stats or None)
