"""Stance detection on a live stream of toe samples: where a stance starts and ends, from the stated
surface (the toe below it) or from the force (its vertical component above a threshold).

A stance is a maximal run of valid samples in contact. The detector keeps one valid sample before the
onset and waits for one after the end (``margin``), so that the toe's velocity at every stance sample
is the same central difference the offline pipeline takes over the whole run (``rft.pose_path``):
the contacts of a stance computed alone equal those of the whole recording at its samples. Masked
samples are not part of any stance (the offline dataset drops them too); they are counted. A stance
is counted only from an onset seen: one in progress when the stream starts (or after ``reset``) is
skipped (``n_skipped``), never used cut.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Stance", "StanceDetector"]


@dataclass
class Stance:
    """One stance: its valid samples with ``margin`` neighbours on each side (not part of it).

    Attributes:
        time: (n,) s. toe: (n, 2) toe reference point, (x, z) m in the world frame (z = 0 the
            surface). force: (n, 2) (F_x, F_z) N, filtered. arrival: (n,) wall-clock instant
            (``time.monotonic``) the frames behind each sample had all arrived.
        first, last: the stance is ``[first, last)`` of these arrays (the rest is margin).
        masked: masked samples inside the stance (not in the arrays).
    """

    time: np.ndarray
    toe: np.ndarray
    force: np.ndarray
    arrival: np.ndarray
    first: int
    last: int
    masked: int = 0
    notes: list = field(default_factory=list)

    @property
    def n_samples(self) -> int:
        return self.last - self.first

    @property
    def start(self) -> float:
        """Time of the first stance sample, s."""
        return float(self.time[self.first])

    @property
    def end(self) -> float:
        """Time of the last stance sample, s."""
        return float(self.time[self.last - 1])


class StanceDetector:
    """Onset and end of each stance in a stream of filtered samples.

    Args:
        mode: "surface": in contact while the toe's lowest segment is below the stated surface
            (``lowest`` m below the toe's reference point: ``min(toe.centres[:, 1])`` for a fixed
            heading 0); "force": in contact while F_z exceeds ``threshold`` N (and until it falls
            below half of it: hysteresis against noise).
        lowest: see ``mode`` (m, <= 0 for a toe whose segments reach below its reference point).
        threshold: see ``mode`` (N, positive).
        margin: valid samples kept on each side of a stance (1: the central difference's neighbours).
        max_samples: a stance longer than this is cut and reported (a toe resting in the sand: the
            memory of one stance stays bounded).

    Example:
        >>> det = StanceDetector("surface", lowest=-0.02)
        >>> for t, x, z, fx, fz in samples:          # toe (x, z) m, force N
        ...     for stance in det.push(t, (x, z), (fx, fz), True, arrival=time.monotonic()):
        ...         update(stance)
    """

    def __init__(self, mode: str = "surface", lowest: float = 0.0, threshold: float = 1.0, margin: int = 1,
                 max_samples: int = 100_000) -> None:
        if mode not in ("surface", "force"):
            raise ValueError(f"mode must be 'surface' or 'force', got {mode!r}")
        if not math.isfinite(lowest):
            raise ValueError(f"lowest must be a finite offset in m, got {lowest}")
        if not (math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold must be a positive force in N, got {threshold}")
        if int(margin) != margin or margin < 1:
            raise ValueError(f"margin must be a positive integer (samples), got {margin}")
        if int(max_samples) != max_samples or max_samples < 3:
            raise ValueError(f"max_samples must be an integer >= 3, got {max_samples}")
        self.mode, self.lowest, self.threshold = mode, float(lowest), float(threshold)
        self.margin, self.max_samples = int(margin), int(max_samples)
        self._before: deque = deque(maxlen=self.margin)  # the last valid samples out of contact
        self._rows: list = []  # the stance in progress (margin before it included)
        self._after = 0  # margin samples collected after its end
        self._in = False
        self._masked = 0
        self.n_masked_outside = 0
        self._armed = False  # a stance counts only once the toe was seen out of contact (not one joined midway)
        self.n_skipped = 0  # samples of a stance joined midway (the stream's start, after a reset)

    def in_contact(self, toe, force) -> bool:
        if self.mode == "surface":
            return bool(toe[1] + self.lowest < 0)
        fz = float(force[1])
        return fz > (self.threshold / 2 if self._in else self.threshold)

    @property
    def in_stance(self) -> bool:
        return self._in

    def push(self, time: float, toe, force, valid: bool, arrival: float = math.nan) -> list[Stance]:
        """One sample (time s, toe (x, z) m, force (F_x, F_z) N, valid). Returns the stances that
        ended with it (usually none, at most one)."""
        if not valid:
            if self._in:
                self._masked += 1
            else:
                self.n_masked_outside += 1
            return []
        row = (float(time), float(toe[0]), float(toe[1]), float(force[0]), float(force[1]), float(arrival))
        out: list[Stance] = []
        if self._rows and not self._in:  # collecting the margin after a stance
            self._rows.append(row)
            self._after += 1
            if self._after >= self.margin:
                out.append(self._close())
            self._before.append(row)
            return out  # a new onset within the margin starts with the next sample
        contact = self.in_contact(row[1:3], row[3:5])
        if not self._armed:
            if contact:
                self.n_skipped += 1
                return out
            self._armed = True
        if contact and not self._in:
            self._in = True
            self._rows = list(self._before)
            self._first = len(self._rows)
            self._masked = 0
        if self._in and contact:
            self._rows.append(row)
            if len(self._rows) - self._first >= self.max_samples:
                self._last = len(self._rows)
                self._in = False
                stance = self._close(note=f"cut at {self.max_samples} samples (max_samples): the toe stayed in "
                                          "contact; the rest is the next stance")
                return [stance]
        elif self._in:  # the first sample out of contact: the stance ended before it
            self._in = False
            self._last = len(self._rows)
            self._rows.append(row)
            self._after = 1
            if self._after >= self.margin:
                out.append(self._close())
        self._before.append(row)
        return out

    def _close(self, note: str | None = None) -> Stance:
        a = np.asarray(self._rows, dtype=float)
        s = Stance(a[:, 0], a[:, 1:3], a[:, 3:5], a[:, 5], self._first, self._last, self._masked,
                   [note] if note else [])
        self._rows, self._after, self._masked = [], 0, 0
        return s

    def reset(self) -> Stance | None:
        """Drop the stance in progress (a fault: frames lost, a motor silent) and return it (its
        margin after may be short), or None."""
        self._armed = False
        if not self._rows:
            self._before.clear()
            return None
        if self._in:
            self._last = len(self._rows)
            self._in = False
        s = self._close()
        self._before.clear()
        self._armed = False
        return s
