"""Record a CAN bus to a standard python-can log, and read logs back into per-motor time series.

Formats follow the file suffix, as python-can's ``can.Logger`` / ``can.LogReader`` choose them
(.log candump, .asc, .blf, .csv, ...). Reading never crashes on a bad frame and never drops good
data silently: malformed frames (wrong length, non-finite payload, unknown ids) are skipped and
counted in ``LogData.issues``; out-of-order timestamps are sorted and reported; gaps are reported
and masked when resampling; a truncated or corrupted file raises ``LogReadError`` naming the
frame, with everything read before it in ``.partial`` (or, with ``on_error="warn"``, returns it).
What a log holds once read is in ``hardware.log_data``; the structural checks of a file in
``hardware.log_checks``.
"""

from __future__ import annotations

import io
import math
import time
import warnings
from collections import defaultdict
from pathlib import Path

import can
import numpy as np

from .log_checks import _blf_intact, _Fault, _text_checks
from .log_data import LogData, LogReadError, MotorSeries, ResampledLog
from .mit_can import decode_mit
from .mit_can import mit_model as _mit_model
from .odrive_can import FrameError, decode, request

__all__ = ["MotorSeries", "LogData", "ResampledLog", "LogReadError", "read_log", "record"]  # the first four: log_data

_FIELDS = {
    "get_encoder_estimates": ("encoder", ("pos_estimate", "vel_estimate")),
    "get_iq": ("iq", ("iq_setpoint", "iq_measured")),
    "get_torques": ("torque", ("torque_target", "torque_estimate")),
}


def _heartbeat_status(values: dict) -> tuple[float, float]:
    """(fault, axis_state) of an ODrive heartbeat: fault 1 when the axis error or (firmware 0.5) the
    motor, encoder or controller error flag is set, else 0."""
    fault = values["axis_error"] != 0 or any(values.get(k, 0) & 1 for k in
                                              ("motor_error_flag", "encoder_error_flag", "controller_flags"))
    return float(fault), float(values["axis_state"])



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


SUPPORTED_SUFFIXES = (".log", ".asc", ".blf", ".csv")
_TEXT_READERS = {".log": can.CanutilsLogReader, ".asc": can.ASCReader, ".csv": can.CSVReader}


def _frame_key(msg: can.Message) -> tuple:
    return (round(msg.timestamp, 7), msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
            bytes(msg.data) if not msg.is_remote_frame else msg.dlc)


def read_log(path, firmware: str = "0.5", nodes=None, on_error: str = "raise", protocol: str = "odrive",
             mit_model="AK80-9", master_id: int = 0) -> LogData:
    """Read a python-can log file into per-motor series.

    Args:
        path: a .log (candump -L), .asc, .blf or .csv file (the suffix picks the reader).
        firmware: "0.5" or "0.6" CANSimple layouts (``protocol="odrive"``).
        nodes: keep only these node ids (frames from others are counted as skipped).
        on_error: "raise" (LogReadError with ``.partial``) or "warn" (return the partial data) when
            the file is truncated or damaged.
        protocol: "odrive" (CANSimple) or "mit" (CubeMars / T-Motor AK MIT-mode replies).
        mit_model: the AK model, a name in ``MIT_MODELS`` or a ``MitModel`` (``protocol="mit"``).
        master_id: the host's id that replies are sent to (``protocol="mit"``).
    Returns:
        LogData. Series groups: "encoder" (position [motor turns], velocity [turns/s]), "iq" (setpoint,
        measured [A]), "torque" (target, estimate [N m]), "heartbeat" (fault 0/1, ODrive axis state).
        For MIT replies the encoder values are at the output shaft (rad / 2 pi) and the third field
        goes to "torque" (both columns the reply) or "iq" per the model's ``quantity``.

    Every fault is reported, never passed over: malformed frames are skipped and counted in
    ``issues``; exact duplicates (same time, id and data) are dropped and counted; a file that is
    empty, not a log, cut short or damaged raises LogReadError (``.partial`` keeps every frame read
    before the fault). What cannot be detected: a .log/.csv cut exactly at a line end reads as a
    shorter recording (ingest's trial coverage check catches it), and a changed hex digit inside a
    text frame is a valid frame (text logs carry no checksum; BLF's compressed containers do).
    """
    if on_error not in ("raise", "warn"):
        raise ValueError(f"on_error must be 'raise' or 'warn', got {on_error!r}")
    if protocol not in ("odrive", "mit"):
        raise ValueError(f"protocol must be 'odrive' or 'mit', got {protocol!r}")
    if protocol == "odrive":
        from .odrive_can import _firmware

        _firmware(firmware)
    else:
        mit_model = _mit_model(mit_model)
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no log file at {path}")
    if path.is_dir():
        raise ValueError(f"{path} is a directory, not a log file")
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise ValueError(f"{path.name}: unsupported log format {suffix!r}; use one of {', '.join(SUPPORTED_SUFFIXES)}")
    data = LogData()
    raw_bytes = path.read_bytes()
    structural: list[str] = []
    try:
        if suffix == ".blf":
            blob, blf_fault = _blf_intact(raw_bytes, path.name)
            if blf_fault:
                structural.append(blf_fault)
            reader = can.BLFReader(io.BytesIO(blob))
        else:
            text = raw_bytes.decode("utf-8", errors="replace")
            if not text.strip():
                raise _Fault(f"{path.name} is empty: no frames")
            faults, readable = _text_checks(text, suffix, data.issues, path.name)
            structural += faults
            reader = _TEXT_READERS[suffix](io.StringIO(readable))
    except _Fault as e:
        data.issues.append(str(e))
        raise LogReadError(str(e), data) from None
    except Exception as e:  # noqa: BLE001 - a header python-can cannot parse
        why = f"{path.name} is not a readable {suffix} log: {type(e).__name__}: {e}"
        data.issues.append(why)
        raise LogReadError(why, data) from None
    raw: list[tuple[float, int, str, tuple]] = []
    seen: set = set()
    duplicates = 0
    last_t = -math.inf
    disorder = 0
    fault = None
    first_of_kind: dict[str, str] = {}
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
        if not math.isfinite(msg.timestamp):
            data.skipped["non-finite timestamp"] += 1
            continue
        key = _frame_key(msg)
        if key in seen:
            duplicates += 1
            continue
        seen.add(key)
        if msg.is_error_frame:
            data.skipped["error frame"] += 1
            continue
        if protocol == "odrive" and msg.is_remote_frame:
            continue  # our own polling requests: not data
        try:
            if protocol == "odrive":
                frame = decode(msg, firmware)
            else:
                frame = decode_mit(msg, mit_model, master_id)
        except FrameError as e:
            if e.reason == "command frame":
                data.other_ids[msg.arbitration_id] += 1  # the host's commands to the motors (or replies elsewhere)
                continue
            key_ = first_of_kind.setdefault(e.reason, f"{e.reason} (first at frame {index}: {e})")
            data.skipped[key_] += 1
            continue
        if nodes is not None and frame.node not in nodes:
            data.skipped["node not requested"] += 1
            continue
        if protocol == "mit":
            if frame.values["saturated"]:
                data.skipped["saturated (a field at the end of its range)"] += 1
                continue
            v = frame.values
            group_values = [("encoder", (v["position"] / (2 * math.pi), v["velocity"] / (2 * math.pi)))]
            third = "torque" if mit_model.quantity == "torque" else "iq"
            group_values.append((third, (v[mit_model.quantity],) * 2))
        else:
            if frame.command == "heartbeat":  # the motor's state: samples while it is not controlling are masked
                group_values = [("heartbeat", _heartbeat_status(frame.values))]
            elif frame.command not in _FIELDS:
                continue  # other replies: decoded and valid, not part of the force series
            else:
                group, names = _FIELDS[frame.command]
                group_values = [(group, tuple(frame.values[n] for n in names))]
        if msg.timestamp < last_t:
            disorder += 1
        last_t = max(last_t, msg.timestamp)
        for group, vals in group_values:
            raw.append((msg.timestamp, frame.node, group, vals))
    if hasattr(reader, "stop"):
        reader.stop()
    data.duplicates = duplicates
    raw.sort(key=lambda r: r[0])
    for t, node, group, vals in raw:
        m = data.motors.setdefault(node, MotorSeries(node))
        m.times[group].append(t)
        m.values[group].append(vals)
    if duplicates:
        data.issues.append(f"dropped {duplicates} duplicate frame(s) (same time, id and data as an earlier one)")
    _summarize(data, disorder)
    if structural:
        kept = f"kept {len(raw)} sample(s) from {data.n_frames - duplicates} frame(s) read before the fault"
        text_fault = f"{path.name}: damaged or truncated: {'; '.join(structural)}; {kept}"
        fault = f"{fault}; {text_fault}" if fault else text_fault
    if fault is None and data.n_frames == 0:
        fault = f"{path.name} holds no CAN frames"
    if fault:
        data.issues.append(fault)
        if on_error == "raise":
            raise LogReadError(fault, data)
        warnings.warn(fault, stacklevel=2)
    return data


def record(bus: can.BusABC, path, duration: float, poll: tuple = (("get_iq", 0), ("get_iq", 1)),
           rate: float = 200.0, firmware: str = "0.5", progress: bool = False,
           stats: dict | None = None) -> int:
    """Log every frame on ``bus`` to ``path`` for ``duration`` s while polling with RTR frames.

    Args:
        poll: (command, node) pairs requested at ``rate`` Hz (encoder estimates arrive cyclically
            from ODrives by default; add ("get_encoder_estimates", node) if yours do not send them).
            Empty: listen only (MIT-mode motors answer their controller's commands; a poll would be
            a command).
        stats: if given, filled with ``frames_by_id`` (arbitration id -> frames received).
    Returns:
        the number of frames received and written (our own polls are not counted). The file is
        flushed and closed even on Ctrl-C.
    """
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be positive seconds, got {duration}")
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be positive (Hz), got {rate}")
    if Path(path).suffix.lower() not in SUPPORTED_SUFFIXES:
        raise ValueError(f"log file {path}: the suffix picks the format; use one of {', '.join(SUPPORTED_SUFFIXES)}")
    requests = [request(command, node, firmware) for command, node in poll]
    counter = _Counter()
    logger = can.Logger(str(path))
    notifier = can.Notifier(bus, [logger, counter])
    try:
        t_end = time.monotonic() + duration
        period = 1.0 / rate
        next_t = time.monotonic()
        while time.monotonic() < t_end:
            for r in requests:
                bus.send(r)
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
    except KeyboardInterrupt:
        pass
    finally:
        time.sleep(0.05)  # let the last replies arrive
        notifier.stop()
        logger.stop()
    if stats is not None:
        stats["frames_by_id"] = dict(counter.by_id)
    return counter.n


class _Counter(can.Listener):
    def __init__(self) -> None:
        self.n = 0
        self.by_id: dict = defaultdict(int)

    def on_message_received(self, msg: can.Message) -> None:
        self.n += 1
        self.by_id[msg.arbitration_id] += 1
