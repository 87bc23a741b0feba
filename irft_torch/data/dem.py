"""Reader for the DEM plate-intrusion runs (Chrono::Granular, by others) and their RFT contacts.

The data are not part of this package (their authors state no licence); point the reader at a
copy, e.g. ``shared/data/dem_plate_intrusion``. Per tilt B (degrees) there are two files,
``beta_<B>_plate_forces.csv`` (t [s], F_x, F_y, F_z [N]: force of the grains on the plate) and
``beta_<B>_plate_positions.csv`` (t [s], x, y, z [cm] of the plate centre, z_top [cm] of the
grains). Each holds several runs, one per direction gamma, each starting with a header row
``gamma,beta`` (sometimes with trailing commas); numbers may be in scientific notation; some
blocks are truncated. Rows are matched across the two files by time; anything that cannot be
used is reported, never dropped silently.

Conventions (DEM -> DESIGN.md): the plate (3.81 cm long, 2.54 cm wide) moves with velocity
(v_x, v_z) ~ (-cos gamma, -sin gamma): toward -x and down. In the world frame its tangent is
(cos beta, -sin beta) (``TILT_SIGN = -1``: beta rotates the plate about +y, x toward -z), so its
DESIGN tilt is -beta; motion toward -x mirrors it into the canonical square: beta_c = +beta,
gamma_c = gamma, and the x contribution flips sign (weight_x = +depth x area). With this mapping
the per-run stresses correlate 0.95 with the generic Li et al. map (checked in the tests).

The free surface: ``z_top`` is the top of the highest grain, not the level where the plate starts
to feel the bed (the force stays ~0 for the first 1-1.5 cm of centre depth). RFT's force is
proportional to the depth below the *effective* surface, ``z_top - surface_offset``;
``calibrate_surface_offset`` estimates that offset from runs (about 1.8 cm here); with it a run's RFT
stress (fit through the origin) is within about the slopes' own noise of its force/depth slope (x: 1.0x,
z: 1.7x their standard error, rms), where below ``z_top`` itself the two differ by 4x their noise.

The data README's per-run target is the stress per depth *through the origin* below ``z_top``
(``run_stress_origin``); ``run_stress`` is the slope with an intercept. Both are linear functionals of
the force series (``stress_functional``), so a model that predicts forces predicts them exactly
through ``recipe_functional``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..metrics import integrated_autocorrelation_time
from ..rft.contacts import Contacts

__all__ = ["DEMRun", "DEMReadReport", "read_runs", "canonical_angles", "run_contacts", "run_stress", "run_stress_se",
           "run_stress_rft", "stress_functional", "run_stress_origin", "recipe_functional", "calibrate_surface_offset",
           "PLATE_LENGTH_CM", "PLATE_WIDTH_CM", "TILT_SIGN"]

PLATE_LENGTH_CM = 3.81
PLATE_WIDTH_CM = 2.54
TILT_SIGN = -1.0  # the plate's DESIGN tilt is TILT_SIGN x beta_DEM

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_ROW = re.compile(rf"^\s*({_NUMBER})(?:\s*,\s*({_NUMBER}))*\s*,*\s*$")


@dataclass
class DEMRun:
    """One intrusion: tilt and direction (degrees, DEM convention), and time series matched by
    time: t (n,) s, force (n, 3) N (F_x, F_y, F_z), centre (n, 3) cm (x, y, z), z_top (n,) cm."""

    beta_deg: float
    gamma_deg: float
    t: np.ndarray
    force: np.ndarray
    centre: np.ndarray
    z_top: np.ndarray

    @property
    def depth(self) -> np.ndarray:
        """Depth of the plate centre below the grains' top, cm (negative above)."""
        return self.z_top - self.centre[:, 2]

    @property
    def label(self) -> str:
        return f"beta {self.beta_deg:g}, gamma {self.gamma_deg:g}"


@dataclass
class DEMReadReport:
    """What the reader could not use, with file and line numbers."""

    skipped_rows: list = field(default_factory=list)  # (file, line, reason)
    unmatched: list = field(default_factory=list)  # (run label, n forces only, n positions only)
    runs_missing_a_file: list = field(default_factory=list)

    def summary(self) -> str:
        parts = []
        if self.skipped_rows:
            parts.append(f"{len(self.skipped_rows)} unparseable row(s), e.g. {self.skipped_rows[0]}")
        for label, nf, np_ in self.unmatched:
            if nf or np_:
                parts.append(f"{label}: {nf} force row(s) and {np_} position row(s) without a partner at the same time")
        parts += [f"no partner file/block for {r}" for r in self.runs_missing_a_file]
        return "; ".join(parts) if parts else "nothing skipped"


def _blocks(path: Path, width: int, report: DEMReadReport) -> dict[tuple[float, float], np.ndarray]:
    """Runs of one file keyed by (gamma, beta): rows of ``width`` numbers. A header row is two numbers
    whose beta is the file's (``beta_<B>_...``): a data row cut to two values is a damaged row, not
    the start of a run."""
    runs: dict[tuple[float, float], list] = {}
    key = None
    named = re.match(r"beta_(-?\d+(?:\.\d+)?)_", path.name)
    file_beta = float(named.group(1)) if named else None
    try:
        content = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text CSV file (byte {e.start} is not UTF-8 text): is it a DEM plate "
                         "file (beta_<B>_plate_forces.csv / _positions.csv)?") from None
    for line_no, line in enumerate(content.splitlines(), 1):
        text = line.strip().rstrip(",").strip()
        if not text:
            continue
        if not _ROW.match(line.strip()):
            report.skipped_rows.append((path.name, line_no, "not numbers"))
            continue
        values = [float(v) for v in text.split(",") if v.strip()]
        if len(values) == 2 and file_beta is not None and values[1] != file_beta:
            report.skipped_rows.append((path.name, line_no, f"2 values, expected {width} (not a header: beta "
                                                            f"{values[1]:g} is not the file's {file_beta:g})"))
            continue
        if len(values) == 2:  # a header row: gamma, beta
            key = (values[0], values[1])
            if key in runs:  # a repeated header continues the same run (a split block)
                continue
            runs[key] = []
            continue
        if key is None:
            report.skipped_rows.append((path.name, line_no, "data before any header"))
            continue
        if len(values) != width:
            report.skipped_rows.append((path.name, line_no, f"{len(values)} values, expected {width}"))
            continue
        if not all(math.isfinite(v) for v in values):
            report.skipped_rows.append((path.name, line_no, "non-finite value"))
            continue
        runs[key].append(values)
    if not runs:
        raise ValueError(f"{path}: no run in it (no 'gamma,beta' header row followed by rows of {width} numbers): is "
                         "it a DEM plate file (beta_<B>_plate_forces.csv / _positions.csv)?")
    return {k: np.asarray(v, dtype=np.float64).reshape(-1, width) for k, v in runs.items()}


def read_runs(directory) -> tuple[list[DEMRun], DEMReadReport]:
    """All runs under ``directory``, forces and positions matched by time (to the millisecond)."""
    directory = Path(directory)
    if directory.is_file():
        raise NotADirectoryError(f"{directory} is a file: read_runs takes the folder that holds the "
                                 f"beta_<B>_plate_forces.csv and _positions.csv files (e.g. {directory.parent})")
    if not directory.is_dir():
        raise FileNotFoundError(f"no DEM data directory at {directory}")
    report = DEMReadReport()
    runs = []
    force_files = sorted(directory.glob("beta_*_plate_forces.csv"))
    if not force_files:
        raise FileNotFoundError(f"{directory} holds no beta_<B>_plate_forces.csv files")
    for ff in force_files:
        pf = ff.with_name(ff.name.replace("_forces", "_positions"))
        if not pf.exists():
            report.runs_missing_a_file.append(pf.name)
            continue
        fb = _blocks(ff, 4, report)
        pb = _blocks(pf, 5, report)
        for key in sorted(set(fb) | set(pb)):
            gamma, beta = key
            if key not in fb or key not in pb:
                report.runs_missing_a_file.append(f"{ff.name} gamma {gamma:g}")
                continue
            f, p = fb[key], pb[key]
            tf = np.round(f[:, 0] * 1000).astype(np.int64)
            tp = np.round(p[:, 0] * 1000).astype(np.int64)
            common, i_f, i_p = np.intersect1d(tf, tp, assume_unique=False, return_indices=True)
            label = f"beta {beta:g}, gamma {gamma:g}"
            report.unmatched.append((label, len(tf) - len(common), len(tp) - len(common)))
            if len(common) < 2:
                continue
            runs.append(DEMRun(beta, gamma, f[i_f, 0], f[i_f, 1:4], p[i_p, 1:4], p[i_p, 4]))
    return runs, report


def canonical_angles(run: DEMRun) -> tuple[float, float]:
    """(beta_c, gamma_c) in rad, DESIGN.md's canonical square (see the module docstring)."""
    b, g = math.radians(run.beta_deg), math.radians(run.gamma_deg)
    vx, vz = -math.cos(g), -math.sin(g)
    tilt = TILT_SIGN * b  # DESIGN tilt of the plate
    gamma_c = math.atan2(-vz, abs(vx))
    beta_c = -tilt if vx < 0 else tilt
    beta_c = (beta_c + math.pi / 2) % math.pi - math.pi / 2
    return beta_c, gamma_c


def _sign_x(run: DEMRun) -> float:
    """weight_x = sign_x x depth x area: -sign(v_x), +1 for the DEM's motion toward -x. Taken from the
    direction of motion, never from a weight (a weight is 0 wherever a segment is above the surface)."""
    vx = -math.cos(math.radians(run.gamma_deg))
    return 1.0 if vx < 0 else -1.0


def _segment_depths(run: DEMRun, keep: np.ndarray, n_segments: int, surface_offset: float,
                    signed: bool = False) -> np.ndarray:
    """(len(keep), n_segments) depth of each segment centre below the effective surface, cm (>= 0;
    ``signed``: negative above it)."""
    tilt = TILT_SIGN * math.radians(run.beta_deg)
    s = (np.arange(n_segments) + 0.5) / n_segments * PLATE_LENGTH_CM - PLATE_LENGTH_CM / 2
    seg_z = run.centre[keep, 2][:, None] + s[None, :] * math.sin(tilt)
    depth = run.z_top[keep][:, None] - surface_offset - seg_z
    return depth if signed else np.clip(depth, 0.0, None)


def run_contacts(run: DEMRun, n_segments: int = 10, stride: int = 1, min_depth: float = 0.0,
                 surface_offset: float = 0.0, dtype=torch.float64) -> tuple[Contacts, torch.Tensor]:
    """Contacts (T, M) of the plate split into ``n_segments`` along its length, and the DEM forces
    (T, 2) = (F_x, F_z) [N], for every ``stride``-th sample whose centre is deeper than
    ``min_depth`` cm below the effective surface ``z_top - surface_offset`` [cm]. Segment depths
    follow the plate's tilt (z of segment = z_centre + s sin tilt). The contacts keep the signed
    segment depths and areas (``Contacts.depth``, ``area_x``, ``area_z``), so that a model can learn
    the surface (``InverseRFT(..., surface=True)``, ``Contacts.with_surface_offset``)."""
    _check_offset(surface_offset)
    beta_c, gamma_c = canonical_angles(run)
    keep = np.nonzero(run.depth - surface_offset > min_depth)[0][::stride]
    depth = torch.as_tensor(_segment_depths(run, keep, n_segments, surface_offset, signed=True), dtype=dtype)
    area = torch.full_like(depth, PLATE_LENGTH_CM / n_segments * PLATE_WIDTH_CM)  # cm^2
    w = torch.relu(depth) * area
    T = len(keep)
    sign = _sign_x(run)
    c = Contacts(torch.full((T, n_segments), beta_c, dtype=dtype), torch.full((T, n_segments), gamma_c, dtype=dtype),
                 sign * w, w, depth, sign * area, area)
    f = torch.as_tensor(run.force[keep][:, [0, 2]], dtype=dtype)
    return c, f


def _check_offset(surface_offset: float) -> None:
    """The effective surface lies between a plate length above z_top (heaped grains; a learned surface
    may end there) and three plate lengths below it."""
    lo, hi = -PLATE_LENGTH_CM, PLATE_LENGTH_CM * 3
    if not (math.isfinite(surface_offset) and lo < surface_offset < hi):
        raise ValueError(f"surface_offset must be a depth below z_top in cm in ({lo:g}, {hi:g}), got {surface_offset}")


def _depth_regression(run: DEMRun, min_depth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of (F_x, F_z) on [centre depth, 1] over samples deeper than min_depth cm:
    the design matrix (n, 2), the coefficients (2, 2) (slope row, intercept row) and residuals (n, 2)."""
    m = run.depth > min_depth
    if m.sum() < 3:
        raise ValueError(f"run {run.label}: fewer than 3 samples deeper than {min_depth} cm")
    d = run.depth[m]
    A = np.stack([d, np.ones_like(d)], 1)
    F = run.force[m][:, [0, 2]]
    coef, *_ = np.linalg.lstsq(A, F, rcond=None)
    return A, coef, F - A @ coef


def run_stress(run: DEMRun, min_depth: float = 1.0) -> tuple[float, float]:
    """Per-run stress per depth (alpha_x, alpha_z) in N/cm^3: the slope of force against centre depth
    (depth > min_depth cm, least squares with an intercept) divided by the plate area, in the
    canonical convention (the x force of motion toward -x flips sign). The data README's recipe."""
    _, coef, _ = _depth_regression(run, min_depth)
    area = PLATE_LENGTH_CM * PLATE_WIDTH_CM
    return _sign_x(run) * coef[0, 0] / area, coef[0, 1] / area


def run_stress_se(run: DEMRun, min_depth: float = 1.0) -> tuple[float, float]:
    """Standard errors (N/cm^3) of ``run_stress``: the least-squares slope's error with the residuals'
    autocorrelation accounted for (white-noise error x sqrt(integrated autocorrelation time))."""
    A, _, resid = _depth_regression(run, min_depth)
    cov00 = np.linalg.inv(A.T @ A)[0, 0]
    area = PLATE_LENGTH_CM * PLATE_WIDTH_CM
    out = []
    for k in range(2):
        var = float(resid[:, k] @ resid[:, k]) / (len(A) - 2)
        tau = integrated_autocorrelation_time(resid[:, k])
        out.append(math.sqrt(var * cov00 * tau) / area)
    return out[0], out[1]


def stress_functional(run: DEMRun, min_depth: float = 1.0, intercept: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The data README's per-run stress recipe as a linear functional of the force series.

    Over the samples whose centre depth below ``z_top`` exceeds ``min_depth`` cm (indices ``keep``),
    the least-squares slope of F against that depth d, divided by the plate area, is ``coef @ F[keep]``:
    through the origin (the README's target, ``intercept=False``) coef = d / (sum d^2 x area); with an
    intercept coef = (d - mean d) / (sum (d - mean d)^2 x area). The canonical x sign is not applied.

    Returns:
        (keep (n,) sample indices, coef (n,) in 1/cm^3).
    """
    keep = np.nonzero(run.depth > min_depth)[0]
    if len(keep) < 3:
        raise ValueError(f"run {run.label}: fewer than 3 samples deeper than {min_depth} cm")
    d = run.depth[keep]
    if intercept:
        d = d - d.mean()
    return keep, d / (float(d @ d) * PLATE_LENGTH_CM * PLATE_WIDTH_CM)


def run_stress_origin(run: DEMRun, min_depth: float = 1.0) -> tuple[float, float]:
    """The data README's per-run stress per depth (alpha_x, alpha_z), N/cm^3: F = s x depth with no
    intercept (s = sum(F d) / sum(d^2)) over samples whose centre is deeper than ``min_depth`` cm below
    ``z_top``, divided by the plate area; canonical convention (x flips for motion toward -x)."""
    keep, coef = stress_functional(run, min_depth)
    s = coef @ run.force[keep][:, [0, 2]]
    return _sign_x(run) * float(s[0]), float(s[1])


def recipe_functional(run: DEMRun, min_depth: float = 1.0, intercept: bool = False, surface_offset: float = 0.0,
                      n_segments: int = 10, dtype=torch.float64) -> Contacts:
    """One composite observation (1, n_segments) whose RFT force is the README's per-run stress of the
    forces RFT predicts for this run: for any map, ``rft.forces(map, c)`` (and a model's
    ``predict_forces(c)``, mean and exact variance) gives (alpha_x, alpha_z) of ``run_stress_origin``
    (or of ``run_stress`` with ``intercept``) computed on the predicted force series, canonical sign
    included. The contacts use the effective surface ``z_top - surface_offset``; the samples and the
    depth d of the recipe are those of ``z_top``, as in the README."""
    keep, coef = stress_functional(run, min_depth, intercept)
    depth = _segment_depths(run, keep, n_segments, surface_offset)
    area = PLATE_LENGTH_CM / n_segments * PLATE_WIDTH_CM
    w = torch.as_tensor(coef @ depth * area, dtype=dtype)[None]  # (1, M): sum_t coef_t weight_tm
    beta_c, gamma_c = canonical_angles(run)
    full = lambda v: torch.full((1, n_segments), v, dtype=dtype)  # noqa: E731
    # F_x = sign_x sum w alpha_x and the recipe applies sign_x again: weight_x = w (sign_x^2 = 1)
    return Contacts(full(beta_c), full(gamma_c), w.clone(), w)


def run_stress_rft(run: DEMRun, min_depth: float = 1.0, surface_offset: float = 0.0) -> tuple[float, float]:
    """The run's stress per depth as RFT defines it, F = alpha x sum_m depth_m x area_m (a fit
    through the origin over samples deeper than min_depth cm below the effective surface),
    canonical convention, N/cm^3.

    With ``surface_offset`` = 0 this differs from ``run_stress`` (slope with an intercept) by the
    force/depth intercept; with the calibrated offset the two agree to about the slope's noise."""
    c, f = run_contacts(run, min_depth=min_depth, surface_offset=surface_offset)
    w = c.weight_z.sum(-1)
    ww = float((w * w).sum())
    if len(c) < 3 or ww <= 0:
        raise ValueError(f"run {run.label}: fewer than 3 samples deeper than {min_depth} cm")
    return _sign_x(run) * float((f[:, 0] * w).sum()) / ww, float((f[:, 1] * w).sum()) / ww


def calibrate_surface_offset(runs: list[DEMRun], offsets=None, n_segments: int = 10) -> tuple[float, np.ndarray]:
    """The effective free surface: the ``surface_offset`` [cm] below ``z_top`` that best explains the
    forces with RFT's depth law, each run fitted with its own (alpha_x, alpha_z) through the origin.

    The score is the pooled residual sum of squares of both force axes over the same samples for
    every candidate offset (all samples whose centre is below ``z_top``), so offsets compare fairly.
    Uses only the runs passed (in a cross-validation, the training runs).

    Returns:
        (best offset in cm, array (K, 2) of [offset, residual sum of squares in N^2]).
    """
    offsets = np.arange(0.0, 3.01, 0.1) if offsets is None else np.asarray(offsets, dtype=np.float64)
    if offsets.ndim != 1 or offsets.size == 0:
        raise ValueError("offsets must be a non-empty 1-D sequence of depths in cm")
    for o in offsets:
        _check_offset(float(o))
    if not runs:
        raise ValueError("calibrate_surface_offset needs at least one run")
    sse = np.zeros(len(offsets))
    area = PLATE_LENGTH_CM / n_segments * PLATE_WIDTH_CM
    for run in runs:
        keep = np.nonzero(run.depth > 0)[0]
        F = run.force[keep][:, [0, 2]]
        for k, o in enumerate(offsets):
            w = _segment_depths(run, keep, n_segments, float(o)).sum(-1) * area
            ww = float(w @ w)
            fit = (F.T @ w) ** 2 / ww if ww > 0 else np.zeros(2)
            sse[k] += float((F * F).sum() - fit.sum())
    best = float(offsets[int(np.argmin(sse))])
    return best, np.stack([offsets, sse], 1)
