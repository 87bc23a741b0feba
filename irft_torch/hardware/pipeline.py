"""The paper's signal pipeline: currents -> torques -> toe forces, minus the force measured in air
along the same path, zero-phase moving-average filtered, repeated trials aligned and averaged,
then contacts + forces built into a dataset for the inference model (its file format:
``data.dataset``).

Trials and the air run are aligned by arc length along the toe's path (not by time), so runs at
slightly different speeds or start times line up at the same place.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.ndimage import uniform_filter1d

from ..data.dataset import Dataset, dataset_summary, load_dataset, save_dataset
from ..rft.contacts import contacts
from ..rft.toes import Toe
from .bus.log_data import ResampledLog
from .five_bar import FiveBarLeg, SingularConfigurationWarning
from .motor import MotorModel

# Dataset, dataset_summary, save_dataset and load_dataset: the dataset format (data.dataset), built here
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
    arc_noise: float = 0.0

    @property
    def arc_length(self) -> np.ndarray:
        """Distance travelled by the toe along its path, m (T,), ignoring toe moves below
        ``arc_noise`` m (encoder jitter while standing still; see ``progress``): the coordinate
        trials and the air run are aligned by."""
        return progress(self.toe, self.time, self.arc_noise)

    def masked(self, keep: np.ndarray) -> ForceTrace:
        return ForceTrace(self.time[keep], self.q[keep], self.toe[keep], self.tau[keep], self.force[keep],
                          self.valid[keep], dict(self.why_masked), self.arc_noise)


def progress(toe: np.ndarray, time: np.ndarray, noise: float = 0.0) -> np.ndarray:
    """Distance travelled along a toe path, m (T,), for aligning runs by place rather than time.

    With ``noise`` > 0 a move counts once the toe is more than ``noise`` m from where the last
    counted move ended, so encoder jitter while the toe stands still adds nothing (summing every
    1 ms step of the Traveler leg's log gives 0.25 m for a 0.17 m stroke, 5 cm of it over a 3 s
    pause; 0.19 m with noise = 2e-4). Between two counted moves the distance is spread in proportion
    to the raw step lengths (a pause about linearly in time: two runs pausing at one place line up by
    how much of the pause has passed). The distance between counted moves is their chord, so a
    corner is cut by up to ~noise / 3: keep noise at the jitter's size (0 for noise-free positions,
    where this is the plain path length). A creep of 1 nm/s makes the coordinate strictly increasing
    (never a visible distance), so runs that stand still line up by time instead of picking one
    sample of a repeated distance. Unreachable samples (NaN toe) add nothing.

    Args:
        toe: (T, 2) toe positions, m. time: (T,) increasing sample times, s.
        noise: the jitter to ignore, m (0: every step counts, the plain path length).
    """
    toe, time = np.asarray(toe, dtype=float), np.asarray(time, dtype=float)
    T = len(time)
    ok = np.nonzero(np.isfinite(toe).all(1))[0]
    if T == 0 or len(ok) == 0:
        return np.zeros(T)
    step = np.linalg.norm(np.diff(toe, axis=0), axis=1)
    raw = np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(step), step, 0.0))])
    moves, lengths = [int(ok[0])], [0.0]
    anchor = toe[ok[0]]
    for i in ok[1:]:
        d = float(np.hypot(*(toe[i] - anchor)))
        if d > noise:
            moves.append(int(i))
            lengths.append(lengths[-1] + d)
            anchor = toe[i]
    at, dist = np.array(moves), np.array(lengths)
    k = np.clip(np.searchsorted(at, np.arange(T), side="right") - 1, 0, len(at) - 1)  # last counted move <= i
    s = dist[k].copy()
    inside = k < len(at) - 1
    kk = k[inside]
    span = raw[at[kk + 1]] - raw[at[kk]]
    frac = np.where(span > 0, (raw[inside] - raw[at[kk]]) / np.where(span > 0, span, 1.0), 0.0)
    s[inside] += (dist[kk + 1] - dist[kk]) * np.clip(frac, 0.0, 1.0)
    return s + 1e-9 * (time - time[0])


def forces_from_log(log: ResampledLog, leg: FiveBarLeg, motors: tuple[MotorModel, MotorModel],
                    arc_noise: float = 0.0) -> ForceTrace:
    """tau = k_t I per motor (or, when the log carries torques, direction x gear_ratio x the reported
    torque: ODrive Get_Torques is motor-side; MIT-mode replies are output-side, so use gear_ratio 1
    there, as for their output-side positions), q from the encoders, F = -J^-T tau (singular
    samples masked).
    Samples whose joint angles the leg cannot reach (wrong link lengths, offsets) are masked and
    counted; if none is reachable this raises ValueError naming the leg options. ``arc_noise``: see
    ``ForceTrace`` (m)."""
    if not (np.isfinite(arc_noise) and 0 <= arc_noise < 0.01):
        raise ValueError(f"arc_noise must be a toe-position jitter in m in [0, 0.01), got {arc_noise}")
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
        ground, ok_t = leg.ground_force(q, tau, warn=False)
    ok = ok_t.numpy()
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
    force = ground.numpy().copy()
    force[~valid] = np.nan
    return ForceTrace(np.asarray(log.time), q.numpy(), toe.numpy(), tau.numpy(), force, valid, masked, float(arc_noise))


def _interp_valid(x_new: np.ndarray, x: np.ndarray, y: np.ndarray, valid: np.ndarray,
                  bridge: bool = False) -> np.ndarray:
    """Interpolate y (n, k) at x_new over the valid samples; NaN outside their span and, unless
    ``bridge``, inside a masked stretch (between two valid samples with masked ones between them:
    a masked sample is never filled in and returned as data)."""
    idx = np.nonzero(valid)[0]
    xv, yv = x[idx], y[idx]
    if len(xv) < 2:
        return np.full((len(x_new), y.shape[1]), np.nan)
    order = np.argsort(xv, kind="stable")
    xv, yv, idx = xv[order], yv[order], idx[order]
    out = np.stack([np.interp(x_new, xv, yv[:, k]) for k in range(y.shape[1])], -1)
    out[(x_new < xv[0]) | (x_new > xv[-1])] = np.nan
    if not bridge:
        gap = np.abs(np.diff(idx)) > 1  # (n_valid - 1,): masked samples between these two neighbours
        if gap.any():
            j = np.clip(np.searchsorted(xv, x_new, side="left"), 1, len(xv) - 1)  # xv[j-1] < x_new <= xv[j]
            out[gap[j - 1] & (x_new > xv[j - 1]) & (x_new < xv[j])] = np.nan
    return out


def _path_mismatch(ref: ForceTrace, other: ForceTrace, n: int = 200) -> tuple[float, float, float]:
    """(RMS distance between the two toe paths at the same arc length, the same with ``other``
    reversed, the distance both cover), m."""
    span = min(ref.arc_length[-1], other.arc_length[-1])
    s = np.linspace(0.0, span, n)
    ones_r, ones_o = np.isfinite(ref.toe).all(1), np.isfinite(other.toe).all(1)
    a = _interp_valid(s, ref.arc_length, ref.toe, ones_r, bridge=True)
    b = _interp_valid(s, other.arc_length, other.toe, ones_o, bridge=True)
    b_rev = _interp_valid(other.arc_length[-1] - s, other.arc_length, other.toe, ones_o, bridge=True)
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
    return replace(trial, force=force, valid=valid, why_masked=masked)


def zero_phase_filter(trace: ForceTrace, window: int = 5) -> ForceTrace:
    """Centred moving average of ``window`` samples (odd: no lag); masked samples are bridged by
    linear interpolation for the filter (masked ends hold the nearest valid value) and stay masked."""
    if int(window) != window or window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd positive integer (samples; an even one shifts the force by half a "
                         f"sample), got {window}")
    if window == 1 or trace.valid.sum() < 2:
        return trace
    idx = np.arange(len(trace.time)).astype(float)
    filled = _interp_valid(idx, idx, np.nan_to_num(trace.force), trace.valid, bridge=True)  # finite first..last
    first, last = np.nonzero(trace.valid)[0][[0, -1]]
    filled[:first], filled[last + 1:] = filled[first], filled[last]
    smooth = uniform_filter1d(filled, size=int(window), axis=0, mode="nearest")
    smooth[~trace.valid] = np.nan
    return replace(trace, force=smooth, why_masked=dict(trace.why_masked))


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
    elif longest - span > 0.01 * longest:  # within min_coverage, but data are dropped: say so
        warnings.warn(f"the average covers {span:.3f} m, the distance every trial covered; the last "
                      f"{longest - span:.3f} m of the longest trial ({100 * (longest - span) / longest:.1f} %) is not "
                      "in it", stacklevel=2)
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
    return ForceTrace(time, q, toe, tau, force, valid, masked, ref.arc_noise)


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
