"""ODrive CANSimple frames: encode and decode, firmware 0.5.x (ODrive v3.6) and 0.6.x (Pro/S1).

arbitration_id = node_id << 5 | cmd_id (6-bit node, 5-bit command, 11-bit standard id); payloads
are little-endian, floats are IEEE-754 float32, always 8 bytes. Layouts follow ODrive's
``can-protocol.csv`` and official DBC (firmware 0.5.6) and the 0.6 documentation.

Get_* values arrive cyclically or in answer to a remote (RTR) frame with the same id:
``request("get_iq", node)`` builds one.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import can

__all__ = ["COMMANDS", "Frame", "FrameError", "arbitration_id", "split_id", "encode", "decode", "request"]

# name -> (cmd id, struct format of the 8-byte payload, field names, scale of each field)
_COMMON = {
    "estop": (0x02, None, (), ()),
    "set_axis_state": (0x07, "<I4x", ("axis_requested_state",), (1,)),
    "get_encoder_estimates": (0x09, "<ff", ("pos_estimate", "vel_estimate"), (1, 1)),  # turns, turns/s
    "set_input_pos": (0x0C, "<fhh", ("input_pos", "vel_ff", "torque_ff"), (1, 0.001, 0.001)),
    "set_input_vel": (0x0D, "<ff", ("input_vel", "input_torque_ff"), (1, 1)),
    "set_input_torque": (0x0E, "<f4x", ("input_torque",), (1,)),
    "get_iq": (0x14, "<ff", ("iq_setpoint", "iq_measured"), (1, 1)),  # A
    "get_bus_voltage_current": (0x17, "<ff", ("bus_voltage", "bus_current"), (1, 1)),
    "clear_errors": (0x18, None, (), ()),
}
COMMANDS = {
    "0.5": {
        **_COMMON,
        # u32 axis error, u8 state, flags: motor (byte 5 bit 0), encoder (6.0), controller (7.0),
        # trajectory done (7.7)
        "heartbeat": (0x01, "<IBBBB", ("axis_error", "axis_state", "motor_error_flag", "encoder_error_flag",
                                        "controller_flags"), (1, 1, 1, 1, 1)),
    },
    "0.6": {
        **_COMMON,
        # u32 axis error, u8 state, u8 procedure result, u8 trajectory done flag, reserved
        "heartbeat": (0x01, "<IBBBx", ("axis_error", "axis_state", "procedure_result", "trajectory_done_flag"),
                      (1, 1, 1, 1)),
        "get_torques": (0x1C, "<ff", ("torque_target", "torque_estimate"), (1, 1)),  # N m
    },
}
_BY_ID = {fw: {spec[0]: name for name, spec in cmds.items()} for fw, cmds in COMMANDS.items()}


class FrameError(ValueError):
    """A frame that cannot be decoded; ``reason`` is one of "unknown id", "wrong length",
    "non-finite payload", "extended id", "remote frame"."""

    def __init__(self, message: str, reason: str, msg: can.Message | None = None) -> None:
        super().__init__(message)
        self.reason, self.msg = reason, msg


@dataclass
class Frame:
    """A decoded frame: time [s], node id, command name, values (SI where the protocol is: A, N m,
    V; positions in motor turns)."""

    timestamp: float
    node: int
    command: str
    values: dict = field(default_factory=dict)


def _firmware(fw: str) -> str:
    key = str(fw)[:3]
    if key not in COMMANDS:
        raise ValueError(f"firmware must be '0.5' or '0.6' (0.5.x, 0.6.x), got {fw!r}")
    return key


def arbitration_id(node: int, cmd: int) -> int:
    if not 0 <= int(node) < 64:
        raise ValueError(f"node id must be in 0..63, got {node}")
    if not 0 <= int(cmd) < 32:
        raise ValueError(f"command id must be in 0..31, got {cmd}")
    return int(node) << 5 | int(cmd)


def split_id(arb_id: int) -> tuple[int, int]:
    """(node, cmd) of an 11-bit CANSimple id."""
    return arb_id >> 5, arb_id & 0x1F


_INT_RANGE = {"I": (0, 2**32 - 1), "B": (0, 255), "h": (-(2**15), 2**15 - 1)}
_F32_MAX = 3.4028234663852886e38


def encode(command: str, node: int, firmware: str = "0.5", timestamp: float = 0.0, **values) -> can.Message:
    """A data frame for ``command`` with the given field values (all fields required).

    Raises ValueError naming the field when a value does not fit its slot: non-finite, beyond
    float32, or outside an integer field's range (e.g. ``vel_ff`` / ``torque_ff`` of Set_Input_Pos,
    int16 x 0.001: -32.768 .. 32.767 rev/s, N m); unscaled integer fields (states, flags, error
    bits) must be whole numbers. Nothing is clipped, wrapped or rounded silently (scaled fields are
    rounded to their resolution)."""
    fw = _firmware(firmware)
    if command not in COMMANDS[fw]:
        raise ValueError(f"unknown command {command!r} for firmware {fw}.x; known: {sorted(COMMANDS[fw])}")
    cmd, fmt, names, scales = COMMANDS[fw][command]
    if fmt is None:
        data = bytes(8)
    else:
        missing = set(names) - set(values)
        extra = set(values) - set(names)
        if missing or extra:
            raise ValueError(f"{command} takes fields {names}; missing {sorted(missing)}, unexpected {sorted(extra)}")
        raw = []
        for name, scale, code in zip(names, scales, fmt.replace("<", "").replace("x", "")):
            v = float(values[name])
            if not math.isfinite(v):
                raise ValueError(f"{command}: {name} = {v} is not a finite number")
            if code == "f":
                if abs(v) > _F32_MAX:
                    raise ValueError(f"{command}: {name} = {v:g} does not fit a float32 (|x| <= {_F32_MAX:.4g})")
                raw.append(v)
                continue
            lo, hi = _INT_RANGE[code]
            if scale == 1 and v != int(v):
                raise ValueError(f"{command}: {name} = {v:g} must be an integer ({lo} to {hi})")
            r = int(round(v / scale))
            if not lo <= r <= hi:
                span = f"{lo} to {hi}" if scale == 1 else f"{lo * scale:g} to {hi * scale:g}"
                raise ValueError(f"{command}: {name} = {v:g} is outside what the frame carries ({span})")
            raw.append(r)
        data = struct.pack(fmt, *raw)
    return can.Message(arbitration_id=arbitration_id(node, cmd), data=data, is_extended_id=False,
                       timestamp=timestamp)


def request(command: str, node: int, firmware: str = "0.5", timestamp: float = 0.0) -> can.Message:
    """An RTR frame asking node ``node`` for ``command`` (a Get_* message)."""
    fw = _firmware(firmware)
    if command not in COMMANDS[fw]:
        raise ValueError(f"unknown command {command!r} for firmware {fw}.x")
    return can.Message(arbitration_id=arbitration_id(node, COMMANDS[fw][command][0]), is_remote_frame=True,
                       dlc=8, is_extended_id=False, timestamp=timestamp)


def decode(msg: can.Message, firmware: str = "0.5") -> Frame:
    """Decode one frame; raises FrameError naming what is wrong (never returns garbage)."""
    fw = _firmware(firmware)
    if msg.is_extended_id:
        raise FrameError(f"extended id 0x{msg.arbitration_id:x} is not CANSimple", "extended id", msg)
    node, cmd = split_id(msg.arbitration_id)
    name = _BY_ID[fw].get(cmd)
    if name is None:
        raise FrameError(f"unknown command 0x{cmd:02x} (id 0x{msg.arbitration_id:03x}) for firmware {fw}.x",
                         "unknown id", msg)
    if msg.is_remote_frame:
        return Frame(msg.timestamp, node, name, {"remote": True})
    _, fmt, names, scales = COMMANDS[fw][name]
    if fmt is None:
        return Frame(msg.timestamp, node, name, {})
    if len(msg.data) != 8:
        raise FrameError(f"{name} from node {node}: {len(msg.data)} data bytes, expected 8", "wrong length", msg)
    raw = struct.unpack(fmt, bytes(msg.data))
    values = {n: r * s if s != 1 else r for n, r, s in zip(names, raw, scales)}
    if name == "heartbeat" and fw == "0.5":
        flags = values.pop("controller_flags")
        values["controller_error_flag"] = flags & 1
        values["trajectory_done_flag"] = flags >> 7 & 1
        values["motor_error_flag"] &= 1
        values["encoder_error_flag"] &= 1
    if name == "heartbeat" and fw == "0.6":
        values["trajectory_done_flag"] &= 1
    bad = [n for n, v in values.items() if isinstance(v, float) and not math.isfinite(v)]
    if bad:
        raise FrameError(f"{name} from node {node}: non-finite {', '.join(bad)}", "non-finite payload", msg)
    return Frame(msg.timestamp, node, name, values)
