"""Record a CAN bus to a standard python-can log, and read logs back into per-motor time series.

Formats follow the file suffix, as python-can's ``can.Logger`` / ``can.LogReader`` choose them
(.log candump, .asc, .blf, .csv, ...). Reading never crashes on a bad frame and never drops good
data silently: malformed frames (wrong length, non-finite payload, unknown ids) are skipped and
counted in ``LogData.issues``; out-of-order timestamps are sorted and reported; gaps are reported
and masked when resampling; a truncated or corrupted file raises ``LogReadError`` naming the
frame, with everything read before it in ``.partial`` (or, with ``on_error="warn"``, returns it).
What a log holds once read is in ``hardware.bus.log_data``; the structural checks of a file in
``hardware.bus.log_checks``.
"""

from __future__ import annotations

import io
import math
import os
import time
import warnings
from collections import defaultdict
from pathlib import Path

import can
import numpy as np

from ..._files import checked_target, temp_name
from .log_checks import _blf_intact, _Fault, _text_checks
from .log_clock import clock_breaks
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
             mit_model="AK80-9", master_id: int = 0, channel=None) -> LogData:
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
        channel: read only the frames of this CAN channel (as the file names it: "can0" in a candump
            log, the channel number in .asc / .blf). Needed when the log holds several buses whose
            node ids collide (``candump -L any``): without it that is a ValueError naming the channels.
    Returns:
        LogData. Series groups: "encoder" (position [motor turns], velocity [turns/s]), "iq" (setpoint,
        measured [A]), "torque" (target, estimate [N m]), "heartbeat" (fault 0/1, ODrive axis state).
        For MIT replies the encoder values are at the output shaft (rad / 2 pi) and the third field
        goes to "torque" (both columns the reply) or "iq" per the model's ``quantity``.

    Every fault is reported, never passed over: malformed frames are skipped and counted in
    ``issues``; exact duplicates (same time, id and data) are dropped and counted; a file that is
    empty, not a log, cut short or damaged raises LogReadError (``.partial`` keeps every frame read
    before the fault). The logger's clock is read in file order (``log_clock``): a clock stepped back
    or ahead while the motors' positions continue is undone (the frames after it re-timed) and said
    so in ``issues``; a clock that restarts (two recordings appended) splits the log into recordings,
    ``LogData.segments``, each read on its own (``resample`` then asks for one). What cannot be
    detected: a .log/.csv cut exactly at a line end reads as a shorter recording (ingest's trial
    coverage check catches it), and a changed hex digit inside a text frame is a valid frame (text
    logs carry no checksum; BLF's compressed containers do).
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
        msg = f"{path.name} is not a readable {suffix} log: {type(e).__name__}: {e}"
        data.issues.append(msg)
        raise LogReadError(msg, data) from None
    records, fault = _decode_all(reader, path.name, suffix, data, protocol, firmware, mit_model, master_id,
                                 nodes, channel)
    if hasattr(reader, "stop"):
        reader.stop()
    kept = _assemble(data, records, path.name)
    if structural:
        where = f"kept {kept} sample(s) from {data.n_frames - data.duplicates} frame(s) read before the fault"
        text_fault = f"{path.name}: damaged or truncated: {'; '.join(structural)}; {where}"
        fault = f"{fault}; {text_fault}" if fault else text_fault
    if fault is None and data.n_frames == 0:
        fault = f"{path.name} holds no CAN frames"
    if fault:
        data.issues.append(fault)
        if on_error == "raise":
            raise LogReadError(fault, data)
        warnings.warn(fault, stacklevel=2)
    if channel is None:
        _refuse_mixed_channels(data, path.name)
    elif not data.motors:
        others = [f"{k.split(' (')[0][len('on CAN channel '):]} ({v} frames)" for k, v in data.skipped.items()
                  if k.startswith("on CAN channel ")]
        if others:
            raise ValueError(f"{path.name} holds no frames on CAN channel {channel!r}; its channels: "
                             f"{', '.join(others)}")
    return data


def _refuse_mixed_channels(data: LogData, name: str) -> None:
    """ValueError where one node id sends on several CAN channels within a recording: two buses logged
    together (``candump -L any``) whose node ids collide would be read as one motor."""
    for part in data.recordings():
        mixed = {node: c for node, c in part.channels.items() if len(c) > 1}
        if mixed:
            node, c = sorted(mixed.items())[0]
            where = ", ".join(f"{k}: {v} samples" for k, v in sorted(c.items(), key=str))
            pick = sorted(c, key=lambda k: -c[k])[0]
            raise ValueError(f"{name}: node {node} sends on {len(c)} CAN channels ({where}): the log holds several "
                             f"buses with the same node ids (candump -L any?), which would be read as one motor; pick "
                             f"the leg's channel: read_log(..., channel={pick!r}) (irft ingest --channel {pick})")


def _channel_name(msg: can.Message, suffix: str) -> str | None:
    """The frame's CAN channel as the file writes it: candump's interface name (.log), the channel
    number of .asc / .blf (python-can counts those from 0, the files from 1); None where the format
    has none (.csv)."""
    ch = msg.channel
    if ch is None:
        return None
    if suffix in (".asc", ".blf") and isinstance(ch, int):
        return str(ch + 1)
    return str(ch)


def _decode_all(reader, name: str, suffix: str, data: LogData, protocol: str, firmware: str, mit_model,
                master_id: int, nodes, channel) -> tuple[list, str | None]:
    """Every frame of the file in file order as a record (time, frame number, dedup key, channel, kind,
    payload): kind "data" (payload: [(node, group, values)]), "skip" (payload: the reason), "other"
    (payload: the id; MIT mode: a frame the host sent) or "none" (our own polls, replies outside the
    force series). Frames on another channel than ``channel`` and non-finite timestamps are counted
    in ``data.skipped`` here. Returns the records and the reader's fault (None: read to the end)."""
    records: list = []
    first_of_kind: dict[str, str] = {}
    it = iter(reader)
    index = 0
    last_t = None
    while True:
        try:
            msg = next(it)
        except StopIteration:
            return records, None
        except Exception as e:  # noqa: BLE001 - any reader fault means the file is damaged here
            return records, (f"{name}: truncated or corrupted after frame {index} "
                             f"(last good timestamp {last_t if last_t is not None else 'none'}): "
                             f"{type(e).__name__}: {e}")
        index += 1
        data.n_frames += 1
        if not math.isfinite(msg.timestamp):
            data.skipped["non-finite timestamp"] += 1
            continue
        ch = _channel_name(msg, suffix)
        if channel is not None and ch != str(channel):
            data.skipped[f"on CAN channel {ch} (reading channel {channel})"] += 1
            continue
        key = _frame_key(msg)
        payload: object  # a frame's data, or what the record says instead (see ``_decode_all``)
        kind, payload = "none", None
        if msg.is_error_frame:
            kind, payload = "skip", "error frame"
        elif protocol == "odrive" and msg.is_remote_frame:
            pass  # our own polling requests: not data
        else:
            try:
                frame = decode(msg, firmware) if protocol == "odrive" else decode_mit(msg, mit_model, master_id)
            except FrameError as e:
                if e.reason == "command frame":
                    kind, payload = "other", msg.arbitration_id  # the host's commands (or replies elsewhere)
                else:
                    kind, payload = "skip", first_of_kind.setdefault(
                        e.reason, f"{e.reason} (first at frame {index}: {e})")
            else:
                kind, payload = _payload(frame, protocol, mit_model, nodes)
        if kind == "data":
            last_t = msg.timestamp
        records.append((msg.timestamp, index, key, ch, kind, payload))


def _payload(frame, protocol: str, mit_model, nodes) -> tuple[str, object]:
    """(kind, payload) of a decoded frame (see ``_decode_all``)."""
    if nodes is not None and frame.node not in nodes:
        return "skip", "node not requested"
    if protocol == "mit":
        v = frame.values
        if v["saturated"]:
            return "skip", "saturated (a field at the end of its range)"
        third = "torque" if mit_model.quantity == "torque" else "iq"
        return "data", [(frame.node, "encoder", (v["position"] / (2 * math.pi), v["velocity"] / (2 * math.pi))),
                        (frame.node, third, (v[mit_model.quantity],) * 2)]
    if frame.command == "heartbeat":  # the motor's state: samples while it is not controlling are masked
        return "data", [(frame.node, "heartbeat", _heartbeat_status(frame.values))]
    if frame.command not in _FIELDS:
        return "none", None  # other replies: decoded and valid, not part of the force series
    group, names = _FIELDS[frame.command]
    return "data", [(frame.node, group, tuple(frame.values[n] for n in names))]


def _assemble(data: LogData, records: list, name: str) -> int:
    """Fill ``data`` from the records: the clock's breaks found (``log_clock``: steps undone, a new
    recording a segment of its own), then per recording exact duplicates dropped, skips counted,
    the series sorted by time, and what was found reported in ``issues``. Returns the number of
    samples kept."""
    if not records:
        _summarize(data, 0)
        return 0
    early = dict(data.skipped)  # counted while decoding (non-finite times, other channels): the whole file's
    times = np.array([r[0] for r in records])
    enc: dict = defaultdict(lambda: ([], []))
    for k, r in enumerate(records):
        if r[4] == "data":
            for node, group, vals in r[5]:
                if group == "encoder":
                    enc[node][0].append(k)
                    enc[node][1].append(vals[0])
    positions = {n: (np.asarray(i), np.asarray(p, dtype=float)) for n, (i, p) in enc.items()}
    ids = np.array([r[2][1] | r[2][2] << 29 | r[2][3] << 30 for r in records], dtype=np.int64)
    breaks = clock_breaks(times, positions, ids, np.array([r[1] for r in records]))
    parts = [LogData() for _ in range(breaks.n_segments)]
    kept = 0
    for seg, part in enumerate(parts):
        sel = np.nonzero(breaks.segment == seg)[0]
        kept += _fill(part, [records[k] for k in sel], times[sel] + breaks.offset[sel])
    data.issues.extend(breaks.notes)
    if len(parts) == 1:
        one = parts[0]
        data.motors, data.duplicates, data.other_ids = one.motors, one.duplicates, one.other_ids
        data.channels = one.channels
        for k, v in one.skipped.items():
            data.skipped[k] += v
        if data.duplicates:
            data.issues.append(f"dropped {data.duplicates} duplicate frame(s) (same time, id and data as an earlier "
                               "one)")
        _summarize(data, one.disorder)
        data.issues.extend(one.issues)
        return kept
    # several recordings: each its own LogData (``segments``); the whole holds their totals
    data.issues.extend(f"skipped {count} frame(s): {reason}" for reason, count in sorted(early.items()))
    for k, part in enumerate(parts):
        part.n_frames = int((breaks.segment == k).sum())
        _summarize(part, part.disorder)
        data.duplicates += part.duplicates
        for key, v in part.skipped.items():
            data.skipped[key] += v
        for key, v in part.other_ids.items():
            data.other_ids[key] += v
        for node, m in part.motors.items():
            whole = data.motors.setdefault(node, MotorSeries(node))
            for group in m.times:
                whole.times[group].extend(m.times[group])
                whole.values[group].extend(m.values[group])
        data.issues.extend(f"recording {k + 1}: {issue}" for issue in part.issues)
    data.segments = parts
    data.issues.append(f"{name} holds {len(parts)} recordings (the clock restarts between them); each is read "
                       "as a run of its own (LogData.segments)")
    return kept


def _fill(part: LogData, records: list, times: np.ndarray) -> int:
    """One recording's records (file order, re-timed ``times``) into ``part``."""
    seen: set = set()
    raw = []
    front = -math.inf
    channels: dict = defaultdict(lambda: defaultdict(int))
    for (t0, index, key, ch, kind, payload), t in zip(records, times):
        key = (round(float(t), 7), *key[1:])  # on the re-timed clock: a step back must not make two frames one
        if key in seen:
            part.duplicates += 1
            continue
        seen.add(key)
        if kind == "skip":
            part.skipped[payload] += 1
        elif kind == "other":
            part.other_ids[payload] += 1
        elif kind == "data":
            if t < front:
                part.disorder += 1
            front = max(front, t)
            for node, group, vals in payload:
                raw.append((float(t), node, group, vals))
                channels[node][ch] += 1
    part.channels = {node: dict(c) for node, c in channels.items()}
    raw.sort(key=lambda r: r[0])
    for t, node, group, vals in raw:
        m = part.motors.setdefault(node, MotorSeries(node))
        m.times[group].append(t)
        m.values[group].append(vals)
    return len(raw)


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
        the number of frames received and written (our own polls are not counted). The log is written
        to a temporary file beside ``path`` and renamed over it when recording ends (Ctrl-C and errors
        included: what was recorded is kept), so an older log at ``path`` is never half overwritten.
    """
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be positive seconds, got {duration}")
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be positive (Hz), got {rate}")
    if Path(path).suffix.lower() not in SUPPORTED_SUFFIXES:
        raise ValueError(f"log file {path}: the suffix picks the format; use one of {', '.join(SUPPORTED_SUFFIXES)}")
    requests = [request(command, node, firmware) for command, node in poll]
    counter = _Counter()
    path = checked_target(path, "log")
    tmp = temp_name(path)  # an older log at ``path`` stays whole until this recording is complete
    logger = can.Logger(str(tmp))
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
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)  # even after an error: what was recorded is a valid log, never thrown away
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
