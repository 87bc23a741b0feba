"""CubeMars / T-Motor AK MIT-mode replies, checked against frames built here from the vendor's
published layout (AK Series Module Driver User Manual, MIT mode): byte 0 driver id; position 16
bits (bytes 1-2, big-endian); velocity 12 bits (byte 3, high nibble of byte 4); torque 12 bits (low
nibble of byte 4, byte 5); optional byte 6 temperature and byte 7 error code;
x = u (max - min) / (2^bits - 1) + min."""

import math

import can
import numpy as np
import pytest

from irft_torch.hardware import MIT_MODELS, FrameError, MitModel, decode_mit, encode_mit_reply


def vendor_frame(node, p_u, v_u, t_u, extra=b""):
    """The reply bytes for raw field values, written from the manual's bit layout."""
    assert 0 <= p_u < 2**16 and 0 <= v_u < 2**12 and 0 <= t_u < 2**12
    data = bytes([node, p_u >> 8, p_u & 0xFF, v_u >> 4, ((v_u & 0xF) << 4) | (t_u >> 8), t_u & 0xFF]) + extra
    return can.Message(arbitration_id=0, data=data, is_extended_id=False)


def test_literal_frames_decode_to_hand_values():
    # AK80-9: P +-12.5 rad, V +-50 rad/s, T +-18 N m
    f = decode_mit(can.Message(arbitration_id=0, data=bytes.fromhex("03A000C00800"), is_extended_id=False), "AK80-9")
    # p_u = 0xA000 = 40960, v_u = 0xC00 = 3072, t_u = 0x800 = 2048
    assert f.node == 3 and f.command == "mit_reply"
    assert f.values["position"] == pytest.approx(40960 * 25 / 65535 - 12.5, abs=1e-12)  # 3.12524 rad
    assert f.values["position"] == pytest.approx(3.125238, abs=1e-6)
    assert f.values["velocity"] == pytest.approx(3072 * 100 / 4095 - 50, abs=1e-12)  # 25.0183 rad/s
    assert f.values["velocity"] == pytest.approx(25.018315, abs=1e-6)
    assert f.values["torque"] == pytest.approx(2048 * 36 / 4095 - 18, abs=1e-12)  # 0.0043956 N m
    assert f.values["saturated"] == 0
    # the same raw fields for an AK10-9 (T +-65 N m): only the scale changes
    f = decode_mit(can.Message(arbitration_id=0, data=bytes.fromhex("03A000C00800"), is_extended_id=False), "ak10-9")
    assert f.values["torque"] == pytest.approx(2048 * 130 / 4095 - 65, abs=1e-12)


def test_zero_encodes_to_mid_codes_and_ends_are_flagged_saturated():
    # x = 0: int(12.5 * 65535 / 25) = 32767 = 0x7FFF; int(50 * 4095 / 100) = 2047 = 0x7FF; torque the same
    m = encode_mit_reply(1, 0.0, 0.0, 0.0, "AK80-9")
    assert bytes(m.data) == bytes.fromhex("017FFF7FF7FF") and m.arbitration_id == 0 and not m.is_extended_id
    f = decode_mit(vendor_frame(2, 0xFFFF, 0, 0xFFF))
    assert (f.values["position"], f.values["velocity"], f.values["torque"]) == (12.5, -50.0, 18.0)
    assert f.values["saturated"] == 1
    # 1e6 N m cannot be sent: the 12-bit field saturates at +T_max
    assert decode_mit(encode_mit_reply(1, 0.0, 0.0, 1e6)).values["torque"] == 18.0


@pytest.mark.parametrize("name", sorted(MIT_MODELS))
def test_roundtrip_within_one_code(name):
    m = MIT_MODELS[name]
    rng = np.random.default_rng(1)
    for _ in range(50):
        p, v, t = rng.uniform(-1, 1, 3) * (m.p_max, m.v_max, m.t_max) * 0.99
        f = decode_mit(encode_mit_reply(7, p, v, t, name), name)
        # the encoder truncates: the decoded value lies within one code below the true one
        assert 0 <= p - f.values["position"] <= 2 * m.p_max / 65535 + 1e-12
        assert 0 <= v - f.values["velocity"] <= 2 * m.v_max / 4095 + 1e-12
        assert 0 <= t - f.values["torque"] <= 2 * m.t_max / 4095 + 1e-12


def test_eight_byte_reply_temperature_error_and_current_models():
    f = decode_mit(vendor_frame(5, 0x8000, 0x800, 0x800, bytes([41, 0])))
    assert f.values["temperature"] == 41 and f.values["error"] == 0
    with pytest.raises(FrameError, match="error 2 \\(over current\\)") as e:
        decode_mit(vendor_frame(5, 0x8000, 0x800, 0x800, bytes([41, 2])))
    assert e.value.reason == "motor error"
    cur = MitModel("old-firmware", 12.5, 50.0, 40.0, quantity="current")
    f = decode_mit(vendor_frame(1, 0x8000, 0x800, 0xC00), cur)
    assert f.values["current"] == pytest.approx(3072 * 80 / 4095 - 40) and "torque" not in f.values


def test_non_replies_are_named():
    cmd = can.Message(arbitration_id=1, data=bytes.fromhex("FFFFFFFFFFFFFFFC"), is_extended_id=False)
    with pytest.raises(FrameError, match="command to a motor") as e:
        decode_mit(cmd)
    assert e.value.reason == "command frame"
    assert decode_mit(can.Message(arbitration_id=5, data=bytes(6), is_extended_id=False), master_id=5).node == 0
    for msg, reason in (
        (can.Message(arbitration_id=0, data=bytes(7), is_extended_id=False), "wrong length"),
        (can.Message(arbitration_id=0, data=bytes(6), is_extended_id=True), "extended id"),
        (can.Message(arbitration_id=0, is_remote_frame=True, dlc=6, is_extended_id=False), "remote frame"),
    ):
        with pytest.raises(FrameError) as e:
            decode_mit(msg)
        assert e.value.reason == reason
    with pytest.raises(ValueError, match="unknown MIT-mode motor model 'AK99'"):
        decode_mit(vendor_frame(1, 0, 0, 0), "AK99")
    with pytest.raises(ValueError, match="t_max"):
        MitModel("x", 12.5, 50.0, -1.0)


def test_fuzz_10k_frames_never_crash_never_out_of_range():
    """10^4 random frames (fixed seed): each decodes to finite values inside the model's ranges
    or raises FrameError; a measurable share of both outcomes occurs."""
    rng = np.random.default_rng(20261122)
    model = MIT_MODELS["AK80-9"]
    n_ok = n_err = 0
    for _ in range(10_000):
        length = int(rng.choice([0, 1, 5, 6, 6, 6, 7, 8, 8]))
        msg = can.Message(arbitration_id=int(rng.choice([0, 0, 0, int(rng.integers(0, 0x800))])),
                          data=rng.integers(0, 256, length, dtype=np.uint8).tobytes(),
                          is_extended_id=bool(rng.random() < 0.05), dlc=length)
        try:
            f = decode_mit(msg, model)
        except FrameError as e:
            assert e.reason in ("wrong length", "extended id", "command frame", "motor error")
            n_err += 1
            continue
        v = f.values
        assert abs(v["position"]) <= model.p_max and abs(v["velocity"]) <= model.v_max
        assert abs(v["torque"]) <= model.t_max and all(math.isfinite(x) for x in v.values())
        n_ok += 1
    assert n_ok > 1000 and n_err > 1000, (n_ok, n_err)


def test_reply_encoder_refuses_what_the_frame_cannot_carry():
    """F53. Bytes 6 and 7 of the reply (temperature, error code) are single bytes (0..255) in the
    vendor's layout: 300 deg C was sent as 44, error 256 as 0 (no fault). A NaN field has no code
    (was a bare 'cannot convert float NaN to integer'). Finite values beyond a range still saturate,
    as documented."""
    m = encode_mit_reply(1, 0.0, 0.0, 0.0, temperature=255, error=6)
    assert bytes(m.data)[6:] == bytes([255, 6])
    for kw, name in ((dict(temperature=300), "temperature"), (dict(temperature=-5), "temperature"),
                     (dict(temperature=40, error=256), "error"), (dict(temperature=40, error=-1), "error"),
                     (dict(error=3), "error")):
        with pytest.raises(ValueError, match=name):
            encode_mit_reply(1, 0.0, 0.0, 0.0, **kw)
    for i, name in enumerate(("position", "velocity", "torque")):
        args = [0.0, 0.0, 0.0]
        args[i] = math.nan
        with pytest.raises(ValueError, match=f"{name} = nan"):
            encode_mit_reply(1, *args)


def test_replies_on_another_id_are_named_when_a_node_has_no_frames(tmp_path):
    """Motors that reply on id 0x005 while the host's id is given as 0: every reply is taken for a
    command to a motor; the error then names the ids seen and the option that fixes it, and with the
    right master id the same log reads (was: only 'node 1 sent no frames')."""
    from irft_torch.hardware import read_log

    path = tmp_path / "mit.log"
    writer = can.CanutilsLogWriter(str(path))
    for k in range(20):
        for node in (1, 2):
            writer.on_message_received(encode_mit_reply(node, 0.01 * k, 0.0, 0.5, "AK80-9", master_id=5,
                                                        timestamp=k / 100 + node * 1e-4))
    writer.stop()
    with pytest.raises(ValueError, match=r"node 1 sent no frames.*0x005 \(40\).*--mit-master-id"):
        read_log(path, protocol="mit", mit_model="AK80-9", master_id=0).resample(nodes=(1, 2))
    ok = read_log(path, protocol="mit", mit_model="AK80-9", master_id=5).resample(nodes=(1, 2))
    assert ok.valid.all() and np.allclose(ok.torque, 0.5, atol=0.01)
