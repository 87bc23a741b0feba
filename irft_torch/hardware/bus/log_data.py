"""What a CAN log holds once read: per-motor time series (``MotorSeries``, ``LogData``), the two
motors resampled onto one time base with gaps and non-controlling stretches masked
(``ResampledLog``), and ``LogReadError`` (a log read only up to a fault, with what was read)."""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

__all__ = ["MotorSeries", "LogData", "ResampledLog", "LogReadError", "CLOSED_LOOP_CONTROL"]

CLOSED_LOOP_CONTROL = 8  # ODrive AxisState: the only state in which the motor holds the torque it is asked for


class LogReadError(ValueError):
    """A log could not be read to its end. ``partial`` holds the LogData read before the fault."""

    def __init__(self, message: str, partial: LogData) -> None:
        super().__init__(message)
        self.partial = partial


@dataclass
class MotorSeries:
    """One controller's decoded samples: for each group ("encoder", "iq", "torque") the times (n,)
    [s] and values (n, 2) in the order of the protocol's fields."""

    node: int
    times: dict = field(default_factory=lambda: defaultdict(list))
    values: dict = field(default_factory=lambda: defaultdict(list))

    def arrays(self, group: str) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(self.times.get(group, []), dtype=np.float64)
        v = np.asarray(self.values.get(group, []), dtype=np.float64).reshape(-1, 2)
        return t, v


@dataclass
class LogData:
    """Decoded content of a log: per node series, frame counts and what was skipped and why."""

    motors: dict = field(default_factory=dict)
    n_frames: int = 0
    issues: list = field(default_factory=list)
    skipped: dict = field(default_factory=lambda: defaultdict(int))
    duplicates: int = 0
    other_ids: dict = field(default_factory=lambda: defaultdict(int))  # MIT: frames not sent to the master id, by id
    # node -> {CAN channel (as the file names it) -> samples}
    channels: dict = field(default_factory=dict)
    # the recordings of a log whose clock restarts (two or more, each a LogData); empty for one recording
    segments: list = field(default_factory=list)
    disorder: int = 0  # frames earlier than the one before (sorted)

    def recordings(self) -> list[LogData]:
        """The recordings this log holds: ``segments`` when its clock restarts, else [self]."""
        return list(self.segments) if self.segments else [self]

    def resample(self, nodes=(0, 1), rate: float | None = None, max_gap: float | None = None,
                 max_current: float | None = None, max_torque: float | None = None) -> ResampledLog:
        """Both motors' encoder position/velocity and q-axis current (or torque) on one time base.

        Args:
            nodes: the two controllers' node ids, in joint order (motor 1, motor 2); distinct.
            rate: samples per second of the common time base (default: the median rate of the
                sparsest current series).
            max_gap: a sample between two measured ones further apart than this [s] is masked, however
                near it is to either (interpolating across the gap would invent data; default 3 sampling
                intervals of the source). A sample at a measured one's time is kept.
            max_current: measured currents with |I| above this [A] are outliers (beyond what the
                motor can carry): dropped before interpolation and counted in ``masked``.
            max_torque: the same for torque series [N m] (MIT-mode replies, ODrive Get_Torques).
        Raises:
            ValueError: a log of several recordings (``segments``); a rate more than ``RATE_RANGE``
                times below or above the log's own; an encoder re-zeroed mid-recording (its position
                jumps between two samples, ``_check_no_rezero``).
        Returns:
            ResampledLog over the span all series share (a series that stops early or starts late
            is named in ``masked`` with the samples that cuts off), with a ``valid`` mask: False inside gaps and
            wherever a motor's heartbeats (ODrive) say it was not in closed-loop control or had an
            error, from its last good heartbeat to its next (counted in ``masked``). It carries ``iq``
            (T, 2) when both motors sent currents, else ``torque`` (T, 2) N m when they sent torques.
        """
        if self.segments:
            raise ValueError(f"this log holds {len(self.segments)} recordings (its clock restarts between them): "
                             "resample each of LogData.segments (irft ingest reads each as a run of its own)")
        nodes = tuple(nodes)
        if len(nodes) != 2 or nodes[0] == nodes[1]:
            raise ValueError(f"nodes must be two different node ids (motor 1, motor 2), got {list(nodes)}")
        if rate is not None and not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate must be a positive number of samples per second, got {rate}")
        if max_gap is not None and not (math.isfinite(max_gap) and max_gap > 0):
            raise ValueError(f"max_gap must be positive seconds, got {max_gap}")
        for node in nodes:
            if node not in self.motors:
                hint = ""
                if self.other_ids:  # MIT mode: every frame not addressed to the master id was taken for a command
                    ids = ", ".join(f"0x{i:03x} ({n})" for i, n in sorted(self.other_ids.items())[:8])
                    hint = (f"; the log also holds frames on other ids, read as the host's commands to the motors: "
                            f"{ids}: if the motors reply on one of these, pass it as the master id (--mit-master-id)")
                raise ValueError(f"node {node} sent no frames (nodes seen: {sorted(self.motors)}){hint}")
        have = [set(g for g in self.motors[n].times if len(self.motors[n].times[g])) for n in nodes]
        load = "iq" if all("iq" in h for h in have) else "torque" if all("torque" in h for h in have) else None
        if load is None:
            raise ValueError(f"nodes {list(nodes)} did not both send currents (Get_Iq) or torques "
                             f"(groups seen: {[sorted(h) for h in have]})")
        limit = max_current if load == "iq" else max_torque
        unit = "A" if load == "iq" else "N m"
        masked: dict = {}
        series = []
        for node in nodes:
            m = self.motors[node]
            for group in ("encoder", load):
                t, v = m.arrays(group)
                if group == load and limit is not None:
                    ok = np.abs(v[:, 1]) <= limit
                    if not ok.all():
                        masked[f"node {node}: |{'current' if load == 'iq' else 'torque'}| above {limit:g} {unit} "
                               f"(max {np.abs(v[:, 1]).max():.4g})"] = int((~ok).sum())
                        t, v = t[ok], v[ok]
                if len(t) < 2:
                    raise ValueError(f"node {node} has {len(t)} usable {group} samples; need at least 2")
                dt = np.diff(t)
                if not float(np.median(dt)) > 0:
                    raise ValueError(f"node {node} {group}: timestamps do not advance (median step 0 s)")
                if group == "encoder":
                    _check_no_rezero(node, t, v)
                series.append((node, group, t, v))
        start = max(s[2][0] for s in series)
        stop = min(s[2][-1] for s in series)
        if stop <= start:
            raise ValueError("the motors' series do not overlap in time")
        native = min(1.0 / np.median(np.diff(s[2])) for s in series if s[1] == load)
        if rate is None:
            rate = native
        elif not native / RATE_RANGE <= rate <= native * RATE_RANGE:
            raise ValueError(
                f"rate {rate:g} Hz is {'below' if rate < native else 'above'} the log's own {native:.4g} Hz by "
                f"{max(rate / native, native / rate):.3g}x: resampling by interpolation "
                + ("keeps one sample in that many and drops the rest (no anti-aliasing): the forces between them are "
                   "lost" if rate < native else "invents that many samples between two measured ones")
                + f"; use a rate within {RATE_RANGE:g}x of {native:.4g} Hz, or leave it out (the log's rate)")
        masked.update(_cropped(series, start, stop, rate))
        n = int(math.floor((stop - start) * rate)) + 1
        if n > 50_000_000:
            raise ValueError(f"the motors' series span {stop - start:.4g} s: at {rate:g} Hz that is {n} samples "
                             "(a clock jump inside the log?); split the log, or lower the rate")
        tb = start + np.arange(n) / rate
        valid = np.ones(n, dtype=bool)
        out = {}
        for node, group, t, v in series:
            gap = max_gap if max_gap is not None else 3 * float(np.median(np.diff(t)))
            j = np.clip(np.searchsorted(t, tb), 1, len(t) - 1)
            near = np.minimum(np.abs(tb - t[j - 1]), np.abs(t[j] - tb))
            span = t[j] - t[j - 1]
            valid &= (span <= gap) | (near <= 1e-3 * gap)  # at a measured sample (to clock resolution)
            out[(node, group)] = np.stack([np.interp(tb, t, v[:, k]) for k in range(2)], -1)
        for node in nodes:
            bad, why = _not_controlling(self.motors[node], tb)
            if bad.any():
                masked[f"node {node}: motor not in closed-loop control or reporting an error ({why})"] = \
                    int((bad & valid).sum())
                valid &= ~bad
        third = np.stack([out[(n_, load)][:, 1] for n_ in nodes], -1)
        return ResampledLog(
            time=tb,
            position=np.stack([out[(n_, "encoder")][:, 0] for n_ in nodes], -1),
            velocity=np.stack([out[(n_, "encoder")][:, 1] for n_ in nodes], -1),
            iq=third if load == "iq" else None,
            valid=valid,
            torque=third if load == "torque" else None,
            masked=masked,
        )


RATE_RANGE = 10.0  # resample within this factor of the log's own rate (interpolation, no anti-aliasing filter)
REZERO_MIN = 0.01  # turns: a jump between two samples smaller than this is not called a re-zero


def _cropped(series: list, start: float, stop: float, rate: float) -> dict:
    """Series that start or end well inside the others' span (an encoder that stopped early: a pulled
    connector, a controller that stopped sending): reason -> the samples lost at ``rate`` (the span
    kept is where every series has data). Within 5 sampling intervals of each other (or 50 ms) the
    series end together, as interleaved frames do."""
    first = min(s[2][0] for s in series)
    last = max(s[2][-1] for s in series)
    out = {}
    for node, group, t, _ in series:
        tol = max(5 * float(np.median(np.diff(t))), 0.05)
        what = "encoder" if group == "encoder" else "current" if group == "iq" else group
        if t[-1] == stop and last - stop > tol:
            out[f"node {node} {what} stops {last - stop:.3f} s before the other series end (a pulled connector, or "
                f"the controller stopped sending): the log is cut there"] = int(round((last - stop) * rate))
        if t[0] == start and start - first > tol:
            out[f"node {node} {what} starts {start - first:.3f} s after the other series: the log starts "
                "there"] = int(round((start - first) * rate))
    return out


def _check_no_rezero(node: int, t: np.ndarray, v: np.ndarray) -> None:
    """ValueError where an encoder position jumps between two consecutive samples (not across a gap)
    by more than its own motion explains: the encoder was re-zeroed mid-recording (an index search, a
    controller reboot), so the joint angles after it are off by the jump. A jump: at least
    ``REZERO_MIN`` turns, 10x the largest step among the 10 samples on either side, and 3x what the
    velocity estimate at its ends covers in that time."""
    p, vel = v[:, 0], v[:, 1]
    if len(p) < 4:
        return
    dt = np.diff(t)
    dp = np.diff(p)
    med = float(np.median(dt))
    big = np.nonzero((np.abs(dp) > REZERO_MIN) & (dt <= 3 * med))[0]
    for k in big:
        near = np.abs(np.concatenate([dp[max(0, k - 10):k], dp[k + 1:k + 11]]))
        moved = 3 * max(abs(vel[k]), abs(vel[k + 1])) * dt[k]
        if len(near) and abs(dp[k]) > 10 * near.max() and abs(dp[k]) > moved:
            raise ValueError(f"node {node}'s encoder jumps by {dp[k]:+.4f} turns between {t[k] - t[0]:.3f} and "
                             f"{t[k + 1] - t[0]:.3f} s into its series, where it moves at most {near.max():.4f} turns "
                             "per sample before and after: the encoder was re-zeroed mid-recording (an index search, "
                             "a controller reboot), so every joint angle after it is off by that much. Record the "
                             "run again, or cut the log at that time")


def _not_controlling(m: MotorSeries, tb: np.ndarray) -> tuple[np.ndarray, str]:
    """(T,) True where the motor's heartbeats say it was not holding its torque (an error, or a state
    other than closed-loop control) and what they said. A sample counts as such when the heartbeat
    before it or the one after it says so: the state changed somewhere between two heartbeats, so the
    stretch up to the first one that reports it is masked too. No heartbeats: nothing is known, nothing
    masked (a log with none is read as before)."""
    t, v = m.arrays("heartbeat")
    if len(t) == 0:
        return np.zeros(len(tb), dtype=bool), ""
    off = (v[:, 0] != 0) | (v[:, 1] != CLOSED_LOOP_CONTROL)
    before = np.searchsorted(t, tb, side="right") - 1  # the last heartbeat at or before each sample
    after = np.searchsorted(t, tb, side="left")  # the first at or after it
    bad = np.where(before >= 0, off[np.clip(before, 0, None)], False) | \
        np.where(after < len(t), off[np.clip(after, None, len(t) - 1)], False)
    states = sorted({int(s) for s in v[off, 1]})
    errors = int(v[off, 0].sum())
    why = (f"heartbeat axis_state {', '.join(map(str, states))} (closed loop is {CLOSED_LOOP_CONTROL})"
           + (f", {errors} heartbeat(s) with an error set" if errors else ""))
    return bad, why


@dataclass
class ResampledLog:
    """Two motors on one time base: time (T,) s; position (T, 2) motor turns; velocity (T, 2)
    turns/s; iq (T, 2) measured q-axis current, A (None when the motors reported torque); valid
    (T,) False inside gaps and while a motor was not controlling (its heartbeats); torque (T, 2) N m
    at the output shaft when the motors reported torque instead of current (MIT mode); masked: raw
    samples dropped as outliers and samples masked, reason -> count."""

    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    iq: np.ndarray | None
    valid: np.ndarray
    torque: np.ndarray | None = None
    masked: dict = field(default_factory=dict)
