"""CubeMars / T-Motor AK actuators in "MIT mode" (the Mini Cheetah protocol): reply frames.

Reply frame (standard 11-bit id = the host's master id, default 0; 6 data bytes, or 8 on firmware
that appends temperature and an error code), big-endian bit fields:

    byte 0        driver (motor) id
    bytes 1-2     position, 16 bits            [P_min, P_max] rad at the output shaft
    byte 3, 4.hi  velocity, 12 bits            [V_min, V_max] rad/s at the output shaft
    byte 4.lo, 5  torque (or current), 12 bits [T_min, T_max] N m at the output (or A)
    byte 6        temperature, deg C (8-byte replies only)
    byte 7        error code (8-byte replies only; 0 = no fault)

An unsigned field u of b bits maps to x = u (max - min) / (2^b - 1) + min (the vendor's
``uint_to_float``); the encoder does x -> int((x - min) (2^b - 1) / (max - min)). The ranges
differ per model and firmware: ``MIT_MODELS`` holds the vendor manual's table; any other set is
an ``MitModel(...)``. Command frames (id = a motor id, 8 bytes) and the mode commands
(FF FF FF FF FF FF FF FC/FD/FE) are what the host sends, not measurements: ``decode_mit`` names
them with reason "command frame".

Values are saturated by construction (12 bits cannot hold 1e6 A); a reply at the end of its range
is flagged ``saturated``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import can

from .odrive_can import Frame, FrameError

__all__ = ["MitModel", "MIT_MODELS", "MIT_ERRORS", "decode_mit", "encode_mit_reply", "mit_model"]


@dataclass(frozen=True)
class MitModel:
    """Field ranges of one actuator model in MIT mode.

    Args:
        name: model name, e.g. "AK80-9".
        p_max: position range [-p_max, p_max], rad (output shaft).
        v_max: velocity range [-v_max, v_max], rad/s (output shaft).
        t_max: range of the third field [-t_max, t_max]: N m at the output when ``quantity`` is
            "torque", A of q-axis current when it is "current".
        quantity: what the third field carries on this firmware, "torque" or "current".
    """

    name: str
    p_max: float = 12.5
    v_max: float = 50.0
    t_max: float = 18.0
    quantity: str = "torque"

    def __post_init__(self) -> None:
        for k in ("p_max", "v_max", "t_max"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{k} of MIT model {self.name!r} must be a positive number, got {v}")
        if self.quantity not in ("torque", "current"):
            raise ValueError(f"quantity must be 'torque' or 'current', got {self.quantity!r}")


# CubeMars "AK Series Module Driver User Manual", MIT mode limits (P rad, V rad/s, T N m).
MIT_MODELS = {
    "AK10-9": MitModel("AK10-9", 12.5, 50.0, 65.0),
    "AK60-6": MitModel("AK60-6", 12.5, 45.0, 15.0),
    "AK70-10": MitModel("AK70-10", 12.5, 50.0, 25.0),
    "AK80-6": MitModel("AK80-6", 12.5, 76.0, 12.0),
    "AK80-8": MitModel("AK80-8", 12.5, 37.5, 32.0),
    "AK80-9": MitModel("AK80-9", 12.5, 50.0, 18.0),
    "AK80-64": MitModel("AK80-64", 12.5, 8.0, 144.0),
}

MIT_ERRORS = {0: "no fault", 1: "over temperature", 2: "over current", 3: "over voltage", 4: "under voltage",
              5: "encoder fault", 6: "phase current unbalance"}


def mit_model(name: str | MitModel) -> MitModel:
    """The ``MitModel`` for a name in ``MIT_MODELS`` (case-insensitive) or the model itself."""
    if isinstance(name, MitModel):
        return name
    for key, m in MIT_MODELS.items():
        if key.lower() == str(name).lower():
            return m
    raise ValueError(f"unknown MIT-mode motor model {name!r}; known: {', '.join(MIT_MODELS)} "
                     "(or pass MitModel(name, p_max, v_max, t_max))")


def _to_float(u: int, lo: float, hi: float, bits: int) -> float:
    return u * (hi - lo) / ((1 << bits) - 1) + lo


def _to_uint(x: float, lo: float, hi: float, bits: int) -> int:
    x = min(max(float(x), lo), hi)
    return int((x - lo) * ((1 << bits) - 1) / (hi - lo))


def decode_mit(msg: can.Message, model: str | MitModel = "AK80-9", master_id: int = 0) -> Frame:
    """Decode one MIT-mode reply frame.

    Returns:
        Frame with node = the driver id in byte 0, command "mit_reply" and values position [rad],
        velocity [rad/s], torque [N m] or current [A] (per ``model.quantity``), saturated (0/1: a
        field at the end of its range), and for 8-byte replies temperature [deg C] and error
        (the code; see ``MIT_ERRORS``).
    Raises:
        FrameError naming the fault, with reason "extended id", "remote frame", "command frame"
        (a frame the host sent: any id other than ``master_id``), "wrong length" or "motor error"
        (a reply with a non-zero error code; ``err.msg`` keeps the frame).
    """
    m = mit_model(model)
    if msg.is_extended_id:
        raise FrameError(f"extended id 0x{msg.arbitration_id:x} is not an MIT-mode reply", "extended id", msg)
    if msg.is_remote_frame:
        raise FrameError(f"remote frame on id 0x{msg.arbitration_id:03x}: MIT mode has no polling",
                         "remote frame", msg)
    if msg.arbitration_id != master_id:
        raise FrameError(f"id 0x{msg.arbitration_id:03x} is a command to a motor, not a reply to master id "
                         f"{master_id}", "command frame", msg)
    data = bytes(msg.data)
    if len(data) not in (6, 8):
        raise FrameError(f"MIT reply: {len(data)} data bytes, expected 6 or 8", "wrong length", msg)
    node = data[0]
    p_u = data[1] << 8 | data[2]
    v_u = data[3] << 4 | data[4] >> 4
    t_u = (data[4] & 0x0F) << 8 | data[5]
    values = {
        "position": _to_float(p_u, -m.p_max, m.p_max, 16),
        "velocity": _to_float(v_u, -m.v_max, m.v_max, 12),
        m.quantity: _to_float(t_u, -m.t_max, m.t_max, 12),
        "saturated": int(t_u in (0, 0xFFF) or v_u in (0, 0xFFF) or p_u in (0, 0xFFFF)),
    }
    if len(data) == 8:
        values["temperature"] = data[6]
        values["error"] = data[7]
        if data[7]:
            raise FrameError(f"motor {node} reports error {data[7]} "
                             f"({MIT_ERRORS.get(data[7], 'unknown code')})", "motor error", msg)
    return Frame(msg.timestamp, node, "mit_reply", values)


def encode_mit_reply(node: int, position: float, velocity: float, torque: float, model: str | MitModel = "AK80-9",
                     master_id: int = 0, temperature: int | None = None, error: int = 0,
                     timestamp: float = 0.0) -> can.Message:
    """The reply a motor would send (for simulation); finite values outside the ranges saturate.
    With ``temperature`` given, the 8-byte form (temperature [deg C], error code: one byte each,
    0..255) is built. Raises ValueError naming the argument for a non-finite position, velocity or
    torque, a temperature or error code outside 0..255, or an error code without a temperature
    (the 6-byte form has no place for it)."""
    m = mit_model(model)
    if not 0 <= int(node) < 256:
        raise ValueError(f"driver id must be 0..255, got {node}")
    for name, x in (("position", position), ("velocity", velocity), ("torque", torque)):
        if not math.isfinite(float(x)):
            raise ValueError(f"{name} = {float(x)} is not a finite number")
    if temperature is None and error:
        raise ValueError(f"error = {error} needs the 8-byte reply: give a temperature too")
    for name, x in (("temperature", temperature), ("error", error)):
        if x is not None and not (int(x) == x and 0 <= x <= 255):
            raise ValueError(f"{name} = {x} does not fit its reply byte (an integer 0..255)")
    p = _to_uint(position, -m.p_max, m.p_max, 16)
    v = _to_uint(velocity, -m.v_max, m.v_max, 12)
    t = _to_uint(torque, -m.t_max, m.t_max, 12)
    data = bytes([int(node), p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | t >> 8, t & 0xFF])
    if temperature is not None:
        data += bytes([int(temperature), int(error)])
    return can.Message(arbitration_id=master_id, data=data, is_extended_id=False, timestamp=timestamp)
