"""The rows of docs/faults.md that no other test covers, and a check that every row of that table
names a test that exists (one test per row)."""

import os
import re
import warnings
from pathlib import Path

import can
import numpy as np
import pytest
import torch

from irft_torch.hardware import (
    FiveBarLeg,
    ForceTrace,
    LogReadError,
    MotorModel,
    ResampledLog,
    encode,
    forces_from_log,
    read_log,
    subtract_air,
)

ROOT = Path(__file__).resolve().parents[2]


def _open_fds():
    return len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else None


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf", ".csv"])
@pytest.mark.parametrize("content, message", [
    (b"", r"is empty|not a BLF log"),
    (b"garbage" * 10, r"holds no CAN frames|damaged|not a BLF log"),
    (bytes(range(256)) * 3, r"damaged|not a BLF log|not text"),
])
def test_empty_and_garbage_files(tmp_path, suffix, content, message):
    """One clear LogReadError, never struct.error / BLFParseError / UnicodeDecodeError, and no file
    handle left open."""
    p = tmp_path / f"x{suffix}"
    p.write_bytes(content)
    before = _open_fds()
    with warnings.catch_warnings():
        warnings.simplefilter("error", ResourceWarning)
        with pytest.raises(LogReadError, match=message) as e:
            read_log(p)
    assert "\n" not in str(e.value) and e.value.partial.motors == {}
    assert _open_fds() == before


def test_unsupported_suffix_and_directory(tmp_path):
    (tmp_path / "x.trc").write_text("")
    with pytest.raises(ValueError, match=r"unsupported log format '.trc'; use one of .log, .asc, .blf, .csv"):
        read_log(tmp_path / "x.trc")
    (tmp_path / "d.log").mkdir()
    with pytest.raises(ValueError, match="is a directory"):
        read_log(tmp_path / "d.log")


def _blf(tmp_path):
    p = tmp_path / "x.blf"
    with can.Logger(str(p)) as log:
        for k in range(50):
            log.on_message_received(encode("get_iq", 0, timestamp=1.7e9 + k / 100, iq_setpoint=0, iq_measured=k))
    return p


def test_blf_header_that_disagrees_with_the_file(tmp_path):
    """The header's object count and file size are checked against what the file holds."""
    p = _blf(tmp_path)
    raw = bytearray(p.read_bytes())
    count_at = 4 + 4 + 8 + 8 + 8  # '<4sLBBBBBBBBQQL': signature, header size, 8 bytes, 2 x u64, then u32 count
    raw[count_at:count_at + 4] = (49).to_bytes(4, "little")
    (tmp_path / "c.blf").write_bytes(bytes(raw))
    with pytest.raises(LogReadError, match="the header lists 49 objects, the file holds 50"):
        read_log(tmp_path / "c.blf")
    # a recording that never stopped (the writer's header still says 144 bytes): all frames kept, and said
    w = can.BLFWriter(str(tmp_path / "u.blf"))
    for k in range(30):
        w.on_message_received(encode("get_iq", 0, timestamp=1.7e9 + k / 100, iq_setpoint=0, iq_measured=k))
    w._flush()
    w.file.flush()
    with pytest.raises(LogReadError, match="never finalized: the recording did not stop cleanly") as e:
        read_log(tmp_path / "u.blf")
    assert e.value.partial.motors[0].arrays("iq")[1][:, 1].tolist() == list(range(30))
    w.file.close()
    (tmp_path / "l.blf").write_bytes(p.read_bytes() + bytes(8))
    with pytest.raises(LogReadError, match="truncated inside container 1.*kept 50 sample"):  # 8 stray bytes
        read_log(tmp_path / "l.blf")


def test_unreachable_joint_angles_name_the_leg_options():
    """Encoder angles no five-bar with these links can reach: every sample -> an error naming the
    options; some samples -> masked and counted."""
    leg = FiveBarLeg(0.10, 0.20, hip_spacing=0.55)  # hips at x = -/+0.275 m
    motors = (MotorModel(0.1), MotorModel(0.1))
    T = 10
    pos = np.tile([0.25, -0.25], (T, 1))  # q = (pi/2, -pi/2): knees inward at x = -/+0.175, 0.35 m apart
    far = -pos  # knees outward at -/+0.375: 0.75 m apart, more than 2 l2 = 0.4 m
    log = ResampledLog(np.arange(T) * 0.01, far, np.zeros((T, 2)), np.zeros((T, 2)), np.ones(T, bool))
    with pytest.raises(ValueError, match=r"none of the 10 joint-angle samples is reachable.*check --l1/--l2"):
        forces_from_log(log, leg, motors)
    mixed = pos.copy()
    mixed[3] = far[3]
    trace = forces_from_log(ResampledLog(log.time, mixed, log.velocity, log.iq, log.valid), leg, motors)
    assert trace.why_masked == {"joint angles out of the leg's reach (check --l1/--l2)": 1}
    assert trace.valid.tolist() == [k != 3 for k in range(T)]


def _trace(x):
    T = len(x)
    toe = np.stack([x, np.full(T, -0.28)], -1)
    z = np.zeros((T, 2))
    return ForceTrace(np.arange(T) * 0.01, z, toe, z, np.ones((T, 2)), np.ones(T, bool))


def test_air_run_in_the_other_direction_is_an_error():
    x = np.linspace(-0.1, 0.1, 50)
    with pytest.raises(ValueError, match="the air run does not follow the reference path.*other direction"):
        subtract_air(_trace(x), _trace(x[::-1]))
    # the same direction is fine, and a shorter air run masks (and counts) what it does not cover
    out = subtract_air(_trace(x), _trace(x[:48]))
    assert (out.force[out.valid] == 0).all() and int((~out.valid).sum()) == 2
    assert list(out.why_masked.values()) == [2]
    torch.manual_seed(0)


def test_fault_table_rows_each_name_an_existing_test():
    text = (ROOT / "docs" / "faults.md").read_text()
    rows = [r for r in text.splitlines() if re.match(r"^\| F\d+ ", r)]
    assert len(rows) >= 30
    ids = [r.split("|")[1].strip() for r in rows]
    assert len(set(ids)) == len(ids), "duplicate row ids"
    for row in rows:
        refs = re.findall(r"`(tests/[\w/]+\.py)::(\w+)(?:\[([^\]]+)\])?`", row)
        assert refs, f"row without a test: {row[:60]}"
        for path, name, case in refs:
            src = (ROOT / path).read_text()
            assert re.search(rf"^def {name}\(", src, re.M), f"{path}::{name} does not exist ({row[:40]})"
            if case:
                assert case in src, f"{path}::{name}[{case}]: case not found"
