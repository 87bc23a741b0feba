import math
import pathlib
import struct

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from irft_torch.hardware import FrameError, decode, encode, request, split_id

SHARED = pathlib.Path(__file__).resolve().parents[3] / "shared" / "reference" / "odrive"
DBC = SHARED / "odrive-cansimple.dbc"


def test_real_frames_from_an_odrive_board():
    # mrniu_hw_validation_frames.txt: heartbeat with a watchdog error, and a bus voltage reply
    hb = decode(can.Message(arbitration_id=0x021, data=bytes.fromhex("0008000001000000"), is_extended_id=False))
    assert (hb.node, hb.command, hb.values["axis_error"], hb.values["axis_state"]) == (1, "heartbeat", 0x800, 1)
    v = decode(can.Message(arbitration_id=0x037, data=bytes.fromhex("e091404200000000"), is_extended_id=False))
    assert v.command == "get_bus_voltage_current" and v.values["bus_voltage"] == pytest.approx(48.142456, abs=1e-6)
    # the report's encoder position bit pattern 0xc0cebe99 = -6.460766315 turns, little-endian on the wire
    data = bytes.fromhex("99becec0") + struct.pack("<f", 0.5)
    e = decode(can.Message(arbitration_id=0x029, data=data, is_extended_id=False))
    assert e.values["pos_estimate"] == pytest.approx(-6.460766315, abs=1e-6)


@pytest.mark.skipif(not DBC.exists(), reason="shared/reference/odrive DBC not present")
def test_encode_matches_the_official_dbc():
    cantools = pytest.importorskip("cantools", reason="cantools (a dev extra) reads the official DBC")
    db = cantools.database.load_file(str(DBC))
    m = encode("set_input_pos", 3, input_pos=1.5, vel_ff=-0.25, torque_ff=0.123)
    assert db.decode_message(m.arbitration_id & 0x1F, m.data) == pytest.approx(
        {"Input_Pos": 1.5, "Vel_FF": -0.25, "Torque_FF": 0.123})
    m = encode("get_iq", 5, iq_setpoint=2.5, iq_measured=-1.25)
    assert split_id(m.arbitration_id) == (5, 0x14)
    assert db.decode_message(0x14, m.data) == {"Iq_Setpoint": 2.5, "Iq_Measured": -1.25}
    m = encode("heartbeat", 2, axis_error=0x800, axis_state=8, motor_error_flag=1, encoder_error_flag=0,
               controller_flags=0x81)
    d = db.decode_message(0x01, m.data, decode_choices=False)
    assert d == {"Axis_Error": 0x800, "Axis_State": 8, "Motor_Error_Flag": 1, "Encoder_Error_Flag": 0,
                 "Controller_Error_Flag": 1, "Trajectory_Done_Flag": 1}
    back = decode(m).values
    assert back["controller_error_flag"] == 1 and back["trajectory_done_flag"] == 1


def test_byte_layouts_by_hand_and_firmware_06():
    m = encode("get_encoder_estimates", 1, pos_estimate=2.0, vel_estimate=-3.0)
    assert m.arbitration_id == 0x029 and bytes(m.data) == struct.pack("<ff", 2.0, -3.0) and not m.is_extended_id
    t = encode("get_torques", 4, firmware="0.6", torque_target=0.5, torque_estimate=0.25)
    assert t.arbitration_id == (4 << 5 | 0x1C) and bytes(t.data) == struct.pack("<ff", 0.5, 0.25)
    assert decode(t, "0.6").values == {"torque_target": 0.5, "torque_estimate": 0.25}
    with pytest.raises(FrameError, match="unknown command 0x1c"):
        decode(t, "0.5")  # 0x1C is Get_ADC_Voltage in 0.5.x, not a torque
    hb6 = encode("heartbeat", 0, firmware="0.6", axis_error=0, axis_state=8, procedure_result=3,
                 trajectory_done_flag=1)
    assert bytes(hb6.data) == bytes([0, 0, 0, 0, 8, 3, 1, 0])
    r = request("get_iq", 1)
    assert r.is_remote_frame and r.arbitration_id == 0x034 and r.dlc == 8
    assert decode(r).values == {"remote": True}


def test_malformed_frames_are_named():
    with pytest.raises(FrameError, match="3 data bytes, expected 8") as e:
        decode(can.Message(arbitration_id=0x034, data=b"\x00\x01\x02", is_extended_id=False))
    assert e.value.reason == "wrong length"
    nan = struct.pack("<ff", 0.0, math.nan)
    with pytest.raises(FrameError, match="non-finite iq_measured"):
        decode(can.Message(arbitration_id=0x034, data=nan, is_extended_id=False))
    with pytest.raises(FrameError, match="extended id"):
        decode(can.Message(arbitration_id=0x034, data=bytes(8), is_extended_id=True))
    with pytest.raises(ValueError, match="firmware"):
        decode(can.Message(arbitration_id=0x034, data=bytes(8)), firmware="0.4")


def test_fuzz_10k_frames_never_crash():
    """10^4 random frames (fixed seed, all ids, lengths 0..8, RTR and extended ids, both firmwares):
    each decodes to finite values or raises FrameError with a known reason; both outcomes occur."""
    rng = np.random.default_rng(15)
    reasons = {"unknown id", "wrong length", "non-finite payload", "extended id"}
    n_ok = n_err = 0
    for _ in range(10_000):
        rtr = bool(rng.random() < 0.1)
        length = int(rng.choice([0, 3, 7, 8, 8, 8, 8]))
        msg = can.Message(arbitration_id=int(rng.integers(0, 0x800)), is_remote_frame=rtr,
                          data=None if rtr else rng.integers(0, 256, length, dtype=np.uint8).tobytes(),
                          is_extended_id=bool(rng.random() < 0.05), dlc=8 if rtr else length)
        try:
            f = decode(msg, str(rng.choice(["0.5", "0.6"])))
        except FrameError as e:
            assert e.reason in reasons, e.reason
            n_err += 1
            continue
        for v in f.values.values():
            assert not isinstance(v, float) or math.isfinite(v)
        n_ok += 1
    assert n_ok > 500 and n_err > 1000, (n_ok, n_err)


@settings(max_examples=300, deadline=None)
@given(node=st.integers(0, 63), a=st.floats(-1e6, 1e6, width=32), b=st.floats(-1e6, 1e6, width=32))
def test_float_roundtrip(node, a, b):
    for cmd, names in (("get_iq", ("iq_setpoint", "iq_measured")), ("get_encoder_estimates",
                                                                     ("pos_estimate", "vel_estimate"))):
        f = decode(encode(cmd, node, **dict(zip(names, (a, b)))))
        assert (f.node, f.command) == (node, cmd) and [f.values[n] for n in names] == [a, b]


def test_encode_refuses_values_the_frame_cannot_carry():
    """F52. The official DBC: Vel_FF and Torque_FF are signed 16-bit with factor 0.001, so they carry
    -32.768 .. 32.767 (rev/s, N m); Axis_Requested_State is an unsigned 32-bit integer; the floats
    are IEEE float32. A value outside is a ValueError naming the field (was struct.error,
    OverflowError, or a NaN / rounded value sent silently)."""
    # the ends of the range are sent exactly: raw 0x7FFF and 0x8000 (little-endian)
    m = encode("set_input_pos", 1, input_pos=0.0, vel_ff=32.767, torque_ff=-32.768)
    assert bytes(m.data)[4:] == bytes.fromhex("ff7f0080")
    for kw, field in ((dict(input_pos=0.0, vel_ff=40.0, torque_ff=0.0), "vel_ff"),
                      (dict(input_pos=0.0, vel_ff=0.0, torque_ff=-33.0), "torque_ff"),
                      (dict(input_pos=0.0, vel_ff=math.nan, torque_ff=0.0), "vel_ff"),
                      (dict(input_pos=math.nan, vel_ff=0.0, torque_ff=0.0), "input_pos"),
                      (dict(input_pos=1e39, vel_ff=0.0, torque_ff=0.0), "input_pos")):
        with pytest.raises(ValueError, match=f"set_input_pos: {field} ="):
            encode("set_input_pos", 1, **kw)
    with pytest.raises(ValueError, match="set_input_torque: input_torque = inf"):
        encode("set_input_torque", 1, input_torque=math.inf)
    with pytest.raises(ValueError, match="axis_requested_state = -1.*0 to 4294967295"):
        encode("set_axis_state", 1, axis_requested_state=-1)
    with pytest.raises(ValueError, match="axis_requested_state = 8.7.*an integer"):
        encode("set_axis_state", 1, axis_requested_state=8.7)
    with pytest.raises(ValueError, match="axis_state = 300.*0 to 255"):
        encode("heartbeat", 1, axis_error=0, axis_state=300, motor_error_flag=0, encoder_error_flag=0,
               controller_flags=0)
