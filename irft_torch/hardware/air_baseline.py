"""The force a leg needs in air, looked up by where the toe is: the live estimator's air baseline.

Offline, ``pipeline.subtract_air`` lines a trial up with its air run by arc length along one path. A leg
that walks repeats a stride instead, and the live estimator sees one sample at a time, so here the air
run's force is taken at the air-run sample nearest the toe's position (leg frame, m). What it removes is
what repeats with the pose: the links' weight, cogging, friction along the stride. A toe farther than
``max_distance`` from every air-run sample gets NaN (the live estimator masks that sample and counts it):
the stride changed since the air run, and an old baseline would be a silent error there. Down- and
up-strokes through the same point are told apart only by position: a stride whose stance and swing
cross (a figure of eight) needs its air force as a function of more than position.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .five_bar import FiveBarLeg
from .motor import MotorModel
from .pipeline import ForceTrace, forces_from_log, zero_phase_filter

__all__ = ["AirBaseline"]


class AirBaseline:
    """``air(toe) -> (n, 2)`` N: the air run's force at the nearest of its toe positions.

    Args:
        toe: (n, 2) m, the air run's toe positions (leg frame).
        force: (n, 2) N, the force ``forces_from_log`` reads there (filtered; what the leg needs in air).
        max_distance: m; a toe farther than this from every air-run sample gets NaN (default 5 mm).
    """

    def __init__(self, toe, force, max_distance: float = 0.005) -> None:
        from scipy.spatial import cKDTree

        toe, force = np.asarray(toe, dtype=float), np.asarray(force, dtype=float)
        if toe.ndim != 2 or toe.shape[1] != 2 or force.shape != toe.shape:
            raise ValueError(f"toe and force must both be (n, 2) (m, N), got {toe.shape} and {force.shape}")
        keep = np.isfinite(toe).all(1) & np.isfinite(force).all(1)
        if keep.sum() < 2:
            raise ValueError(f"the air run has {int(keep.sum())} valid sample(s): nothing to subtract (is it "
                             "the right log, with both motors' currents and encoders?)")
        if not (np.isfinite(max_distance) and 0 < max_distance < 0.1):
            raise ValueError(f"max_distance must be in (0, 0.1) m, got {max_distance} (in m, not mm?)")
        self.toe, self.force, self.max_distance = toe[keep], force[keep], float(max_distance)
        self._tree = cKDTree(self.toe)

    @classmethod
    def from_trace(cls, trace: ForceTrace, max_distance: float = 0.005) -> AirBaseline:
        """From an air run's ``ForceTrace`` (its valid samples)."""
        return cls(trace.toe[trace.valid], trace.force[trace.valid], max_distance)

    @classmethod
    def from_log(cls, path, leg: FiveBarLeg, motors: tuple[MotorModel, MotorModel], firmware: str = "0.5",
                 nodes: tuple[int, int] = (0, 1), rate: float = 1000.0, filter_window: int = 5,
                 max_distance: float = 0.005) -> AirBaseline:
        """From an air run's CAN log (``irft record``'s air run, or any log of the same stride in air): read,
        resampled at ``rate`` Hz, forces from the leg's statics, zero-phase filtered with ``filter_window``
        samples (the whole run is known: no lag)."""
        from .bus.can_log import read_log

        if not Path(path).is_file():
            raise FileNotFoundError(f"no air-run log at {path}")
        log = read_log(path, firmware=firmware).resample(tuple(nodes), rate=rate)
        return cls.from_trace(zero_phase_filter(forces_from_log(log, leg, motors), filter_window), max_distance)

    def __call__(self, toe) -> np.ndarray:
        """(n, 2) N at toe positions (n, 2) m; NaN rows where no air-run sample is within ``max_distance``."""
        toe = np.asarray(toe, dtype=float)
        out = np.full(toe.shape, np.nan)
        ok = np.isfinite(toe).all(1)
        if ok.any():
            dist, idx = self._tree.query(toe[ok], distance_upper_bound=self.max_distance)
            near = np.isfinite(dist)
            rows = np.flatnonzero(ok)[near]
            out[rows] = self.force[idx[near]]
        return out
