"""Record a CAN bus to a standard python-can log, and read logs back into per-motor time series.

Formats follow the file suffix, as python-can's ``can.Logger`` / ``can.LogReader`` choose them
(.log candump, .asc, .blf, .csv, ...). Reading never crashes on a bad frame and never drops good
data silently: malformed frames (wrong length, non-finite payload, unknown ids) are skipped and
counted in ``LogData.issues``; out-of-order timestamps are sorted and reported; gaps are reported
and masked when resampling; a truncated or corrupted file raises ``LogReadError`` naming the
frame, with everything read before it in ``.partial`` (or, with ``on_error="warn"``, returns it).
"""

from __future__ import annotations

import math
import time
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from .odrive_can import FrameError, decode, request

__all__ = ["MotorSeries", "LogData", "ResampledLog", "LogReadError", "read_log", "record"]

_FIELDS = {
    "get_encoder_estimates": ("encoder", ("pos_estimate", "vel_estimate")),
    "get_iq": ("iq", ("iq_setpoint", "iq_measured")),
    "get_torques": ("torque", ("torque_target", "torque_estimate")),
}


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

    def resample(self, nodes=(0, 1), rate: float | None = None, max_gap: float | None = None) -> ResampledLog:
        """Both motors' encoder position/velocity and q-axis current on one time base.

        Args:
            nodes: the two controllers' node ids, in joint order (motor 1, motor 2).
            rate: samples per second of the common time base (default: the median rate of the
                sparsest current series).
            max_gap: a sample further than this [s] from a measured one on either side is masked
                (default 3 sampling intervals of the source).
        Returns:
            ResampledLog over the span all series share, with a ``valid`` mask.
        """
        series = []
        for node in nodes:
            if node not in self.motors:
                raise ValueError(f"node {node} sent no frames (nodes seen: {sorted(self.motors)})")
            m = self.motors[node]
            for group in ("encoder", "iq"):
                t, v = m.arrays(group)
                if len(t) < 2:
                    raise ValueError(f"node {node} has {len(t)} {group} samples; need at least 2")
                series.append((node, group, t, v))
        start = max(s[2][0] for s in series)
        stop = min(s[2][-1] for s in series)
        if stop <= start:
            raise ValueError("the motors' series do not overlap in time")
        if rate is None:
            rate = min(1.0 / np.median(np.diff(s[2])) for s in series if s[1] == "iq")
        n = int(math.floor((stop - start) * rate)) + 1
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
        return ResampledLog(
            time=tb,
            position=np.stack([out[(n_, "encoder")][:, 0] for n_ in nodes], -1),
            velocity=np.stack([out[(n_, "encoder")][:, 1] for n_ in nodes], -1),
            iq=np.stack([out[(n_, "iq")][:, 1] for n_ in nodes], -1),
            valid=valid,
        )


@dataclass
class ResampledLog:
    """Two motors on one time base: time (T,) s; position (T, 2) motor turns; velocity (T, 2)
    turns/s; iq (T, 2) measured q-axis current, A; valid (T,) False inside gaps."""

    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    iq: np.ndarray
    valid: np.ndarray


def _summarize(data: LogData, disorder: int) -> None:
    for reason, count in sorted(data.skipped.items()):
        data.issues.append(f"skipped {count} frame(s): {reason}")
    if disorder:
        data.issues.append(f"{disorder} frame(s) arrived with a timestamp earlier than the one before; sorted by time")
    for node, m in sorted(data.motors.items()):
        for group in list(m.times):
            t, v = m.arrays(group)
            if len(t) > 2:
                dt = np.diff(t)
                med = float(np.median(dt))
                big = np.nonzero(dt > 3 * med)[0]
                if len(big):
                    data.issues.append(
                        f"node {node} {group}: {len(big)} gap(s) longer than 3 sampling intervals "
                        f"({med * 1e3:.2f} ms), longest {dt.max() * 1e3:.1f} ms at t = {t[big[0]]:.4f} s")


def read_log(path, firmware: str = "0.5", nodes=None, on_error: str = "raise") -> LogData:
    """Read a python-can log file into per-motor series.

    Args:
        path: a .log / .asc / .blf / .csv / ... file (python-can chooses the reader by suffix).
        firmware: "0.5" or "0.6" CANSimple layouts.
        nodes: keep only these node ids (frames from others are counted as skipped).
        on_error: "raise" (LogReadError with ``.partial``) or "warn" (return the partial data) when
            the file is truncated or corrupted.
    """
    if on_error not in ("raise", "warn"):
        raise ValueError(f"on_error must be 'raise' or 'warn', got {on_error!r}")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no log file at {path}")
    data = LogData()
    raw: list[tuple[float, int, str, tuple]] = []
    last_t = -math.inf
    disorder = 0
    fault = None
    first_of_kind: dict[str, str] = {}
    reader = can.LogReader(str(path))
    it = iter(reader)
    index = 0
    while True:
        try:
            msg = next(it)
        except StopIteration:
            break
        except Exception as e:  # noqa: BLE001 - any reader fault means the file is damaged here
            fault = (f"{path.name}: truncated or corrupted after frame {index} "
                     f"(last good timestamp {last_t if raw else 'none'}): {type(e).__name__}: {e}")
            break
        index += 1
        data.n_frames += 1
        if msg.is_error_frame:
            data.skipped["error frame"] += 1
            continue
        if msg.is_remote_frame:
            continue  # our own polling requests: not data
        try:
            frame = decode(msg, firmware)
        except FrameError as e:
            key = first_of_kind.setdefault(e.reason, f"{e.reason} (first at frame {index}: {e})")
            data.skipped[key] += 1
            continue
        if nodes is not None and frame.node not in nodes:
            data.skipped["node not requested"] += 1
            continue
        if frame.command not in _FIELDS:
            continue  # heartbeats etc.: decoded and valid, not part of the force series
        if msg.timestamp < last_t:
            disorder += 1
        last_t = max(last_t, msg.timestamp)
        group, names = _FIELDS[frame.command]
        raw.append((msg.timestamp, frame.node, group, tuple(frame.values[n] for n in names)))
    if hasattr(reader, "stop"):
        reader.stop()
    raw.sort(key=lambda r: r[0])
    for t, node, group, vals in raw:
        m = data.motors.setdefault(node, MotorSeries(node))
        m.times[group].append(t)
        m.values[group].append(vals)
    _summarize(data, disorder)
    if fault:
        data.issues.append(fault)
        if on_error == "raise":
            raise LogReadError(fault, data)
        warnings.warn(fault, stacklevel=2)
    return data


def record(bus: can.BusABC, path, duration: float, poll: tuple = (("get_iq", 0), ("get_iq", 1)),
           rate: float = 200.0, firmware: str = "0.5", progress: bool = False) -> int:
    """Log every frame on ``bus`` to ``path`` for ``duration`` s while polling with RTR frames.

    Args:
        poll: (command, node) pairs requested at ``rate`` Hz (encoder estimates arrive cyclically
            from ODrives by default; add ("get_encoder_estimates", node) if yours do not send them).
    Returns:
        the number of frames written. The file is flushed and closed even on Ctrl-C.
    """
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be positive seconds, got {duration}")
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be positive (Hz), got {rate}")
    counter = _Counter()
    logger = can.Logger(str(path))
    notifier = can.Notifier(bus, [logger, counter])
    try:
        t_end = time.monotonic() + duration
        period = 1.0 / rate
        next_t = time.monotonic()
        while time.monotonic() < t_end:
            for command, node in poll:
                bus.send(request(command, node, firmware))
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
    except KeyboardInterrupt:
        pass
    finally:
        time.sleep(0.05)  # let the last replies arrive
        notifier.stop()
        logger.stop()
    return counter.n


class _Counter(can.Listener):
    def __init__(self) -> None:
        self.n = 0

    def on_message_received(self, msg: can.Message) -> None:
        self.n += 1
