"""Two motors' frames, as they arrive, onto one time base: the live counterpart of
``LogData.resample``.

Grid sample k sits at ``start + k / rate`` (``start``: the first instant every series has reached, as
offline). It is published once every series has a sample at or after it, linearly interpolated as
``np.interp`` does, and marked invalid where its bracketing samples are more than ``max_gap`` s apart
(interpolating across a gap would invent data) or while a motor's last heartbeat reported an error or
a state other than closed-loop control. Given the offline rate and gap (``irft ingest --rate``), the
samples equal offline ones (``tests/hardware/test_live.py``).

What arrives wrong is dropped and counted, never used: a frame older than the newest one of its series
(out of order: the grid has moved past it), an exact repeat (a duplicate), a current beyond
``max_current`` A (an outlier, as offline). A logger clock that jumps (its timestamps move by more than
``jump`` s beyond the wall-clock time between two arrivals; an NTP step) is undone: the frames after
it are re-timed by the jump, as ``log_clock`` undoes it offline, and it is reported.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..bus.log_data import CLOSED_LOOP_CONTROL

__all__ = ["LiveResampler", "GridSamples"]


@dataclass
class GridSamples:
    """Samples on the common time base: time (n,) s, position (n, 2) motor turns, current (n, 2) A
    (motor 1, motor 2), valid (n,), arrival (n,) the wall-clock instant (``time.monotonic``) the last
    frame they needed had arrived."""

    time: np.ndarray
    position: np.ndarray
    current: np.ndarray
    valid: np.ndarray
    arrival: np.ndarray

    def __len__(self) -> int:
        return len(self.time)


@dataclass
class _Series:
    t: deque = field(default_factory=deque)
    v: deque = field(default_factory=deque)
    first: float = math.nan


class LiveResampler:
    """Args:
        nodes: the controllers' node ids (motor 1, motor 2).
        rate: the common time base's samples per second (Hz; the controllers' message rate).
        max_gap: bracketing samples further apart than this are a gap, s (default 3 / rate).
        max_current: |current| above this, A, is an outlier (dropped and counted; None: no limit).
        jump: a clock step larger than this, s, is undone (default 0.5).
        max_buffer: samples kept per series while the other series lag (memory bound; beyond it the
            oldest are dropped and counted).
    """

    def __init__(self, nodes=(0, 1), rate: float = 1000.0, max_gap: float | None = None,
                 max_current: float | None = 80.0, jump: float = 0.5, max_buffer: int = 20_000) -> None:
        nodes = tuple(int(n) for n in nodes)
        if len(nodes) != 2 or nodes[0] == nodes[1]:
            raise ValueError(f"nodes must be two different node ids (motor 1, motor 2), got {list(nodes)}")
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate must be positive samples per second, got {rate}")
        if max_gap is not None and not (math.isfinite(max_gap) and max_gap > 0):
            raise ValueError(f"max_gap must be positive seconds, got {max_gap}")
        if not (math.isfinite(jump) and jump > 0):
            raise ValueError(f"jump must be positive seconds, got {jump}")
        self.nodes, self.rate = nodes, float(rate)
        self.max_gap = 3.0 / rate if max_gap is None else float(max_gap)
        self.max_current, self.jump, self.max_buffer = max_current, float(jump), int(max_buffer)
        self.counts: dict[str, int] = {"out of order": 0, "duplicate": 0, "outlier": 0, "overflow": 0,
                                       "not controlling": 0, "gap": 0}
        self.notes: list[str] = []  # what happened, in words (clock jumps)
        self.offset = 0.0  # subtracted from every timestamp (clock steps undone), s
        self._last_raw: tuple[float, float] | None = None  # (raw timestamp, arrival) of the newest frame
        self.restart()

    def restart(self) -> None:
        """Forget every series and start a new time base when all have spoken again (after a motor
        fell silent, or a reconnection). Counts and the clock offset are kept."""
        self._series = {(n, g): _Series() for n in self.nodes for g in ("encoder", "iq")}
        self._bad_since: dict[int, float | None] = {n: None for n in self.nodes}
        self._hb: dict[int, list] = {n: [] for n in self.nodes}  # (time, bad) heartbeats not yet passed
        self.start: float | None = None
        self.k = 0
        self._arrival = math.nan

    def retime(self, timestamp: float, arrival: float) -> float:
        """The frame's time on the undone clock, s; a step beyond ``jump`` is undone and noted."""
        if self._last_raw is not None:
            raw_dt = timestamp - self._last_raw[0]
            wall_dt = arrival - self._last_raw[1]
            if raw_dt > wall_dt + self.jump or raw_dt < -self.jump:
                step = raw_dt - max(wall_dt, 0.0)
                self.offset += step
                self.notes.append(f"the frames' clock jumped by {step:+.3f} s at t = {timestamp:.3f} (the wall clock "
                                  f"moved {max(wall_dt, 0.0):.3f} s): re-timed by {-step:+.3f} s")
        self._last_raw = (timestamp, arrival)
        return timestamp - self.offset

    def add(self, node: int, group: str, t: float, values, arrival: float) -> None:
        """One decoded sample: ``group`` "encoder" (position turns, velocity turns/s), "iq" (setpoint,
        measured A) or "heartbeat" (fault 0/1, axis state); ``t`` already re-timed (``retime``)."""
        if node not in self._bad_since:
            return
        self._arrival = arrival if not math.isfinite(self._arrival) else max(self._arrival, arrival)
        if group == "heartbeat":
            self._hb[node].append((t, bool(values[0]) or int(values[1]) != CLOSED_LOOP_CONTROL))
            return
        s = self._series.get((node, group))
        if s is None:
            return
        v = (float(values[0]), float(values[1]))
        if group == "iq" and self.max_current is not None and abs(v[1]) > self.max_current:
            self.counts["outlier"] += 1
            return
        if s.t:
            if t < s.t[-1]:
                self.counts["out of order"] += 1
                return
            if t == s.t[-1]:
                self.counts["duplicate"] += 1
                return
        else:
            s.first = t
        s.t.append(t)
        s.v.append(v)
        if len(s.t) > self.max_buffer:
            s.t.popleft()
            s.v.popleft()
            self.counts["overflow"] += 1

    def ready(self) -> GridSamples:
        """The grid samples every series has now reached (possibly none), in order."""
        series = list(self._series.values())
        if self.start is None:
            if any(not s.t for s in series):
                return _empty()
            self.start = max(s.t[0] for s in series)
        reached = min(s.t[-1] for s in series)
        n = int(math.floor((reached - self.start) * self.rate + 1e-9)) + 1 - self.k
        if n <= 0:
            return _empty()
        tb = self.start + (self.k + np.arange(n)) / self.rate
        tb = tb[tb <= reached]
        n = len(tb)
        if n == 0:
            return _empty()
        self.k += n
        valid = np.ones(n, dtype=bool)
        out = {}
        for key, s in self._series.items():
            t = np.fromiter(s.t, dtype=float, count=len(s.t))
            v = np.asarray(s.v, dtype=float).reshape(-1, 2)
            i = np.clip(np.searchsorted(t, tb, side="right") - 1, 0, len(t) - 1)  # last sample at or before
            j = np.minimum(i + 1, len(t) - 1)
            exact = t[i] == tb
            span = t[j] - t[i]
            w = np.where(exact | (span <= 0), 0.0, (tb - t[i]) / np.where(span > 0, span, 1.0))
            out[key] = np.where(exact[:, None], v[i], v[i] + w[:, None] * (v[j] - v[i]))
            near = np.minimum(np.abs(tb - t[i]), np.abs(t[j] - tb))
            ok = exact | (span <= self.max_gap) | (near <= 1e-3 * self.max_gap)
            self.counts["gap"] += int((valid & ~ok).sum())
            valid &= ok
            keep = max(0, int(i[-1]))  # the samples before the last bracket are never needed again
            for _ in range(keep):
                s.t.popleft()
                s.v.popleft()
        for node in self.nodes:
            bad = self._not_controlling(node, tb)
            self.counts["not controlling"] += int((valid & bad).sum())
            valid &= ~bad
        return GridSamples(tb, np.stack([out[(nd, "encoder")][:, 0] for nd in self.nodes], -1),
                           np.stack([out[(nd, "iq")][:, 1] for nd in self.nodes], -1), valid,
                           np.full(n, self._arrival))

    def _not_controlling(self, node: int, tb: np.ndarray) -> np.ndarray:
        """(n,) True from a heartbeat that reports an error (or a state other than closed loop) to the
        next good one."""
        bad = np.zeros(len(tb), dtype=bool)
        hb = self._hb[node]
        since = self._bad_since[node]
        k = 0
        for i, t in enumerate(tb):
            while k < len(hb) and hb[k][0] <= t:
                since = hb[k][0] if hb[k][1] else None
                k += 1
            bad[i] = since is not None
        del hb[:k]
        self._bad_since[node] = since
        return bad


def _empty() -> GridSamples:
    z = np.zeros(0)
    return GridSamples(z, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=bool), z)
