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
    (b"garbage" * 10, r"holds no CAN frames|not a CAN log|not a BLF log"),
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


def _stroke(T=200, pause=(80, 120), jitter=0.0, seed=0, valid=None, air=False):
    """A toe going down 4 cm at constant speed with a pause (samples ``pause``), force (0, 10 N x
    depth fraction), or with ``air`` (0, 1 N + depth fraction); optional Gaussian toe jitter (m)."""
    moving = np.ones(T, bool)
    moving[pause[0]:pause[1]] = False
    frac = np.cumsum(moving) / moving.sum()
    toe = np.stack([np.zeros(T), -0.28 - 0.04 * frac], -1)
    if jitter:
        toe = toe + jitter * np.random.default_rng(seed).standard_normal(toe.shape)
    f = np.stack([np.zeros(T), (1 + frac) if air else 10 * frac], -1)
    v = np.ones(T, bool) if valid is None else valid
    f[~v] = np.nan
    q = np.zeros((T, 2))
    return ForceTrace(np.arange(T) * 0.001, q, toe, q, f, v)


def test_masked_stretches_are_never_filled_in_by_averaging_or_air_subtraction():
    """A stretch masked in every trial stays masked in their average (and is counted); a stretch
    masked in the air run masks the trial there: no linear bridge comes back as data."""
    from irft_torch.hardware import average_trials

    v = np.ones(200, bool)
    v[140:160] = False  # a frame gap in the moving part
    avg = average_trials([_stroke(valid=v), _stroke(valid=v)], n_points=200)
    s = avg.arc_length
    gap_s = _stroke().arc_length[[139, 160]]
    inside = (s > gap_s[0] + 1e-9) & (s < gap_s[1] - 1e-9)
    assert inside.sum() >= 15 and not avg.valid[inside].any() and np.isnan(avg.force[inside]).all()
    assert sum(avg.why_masked.values()) == int((~avg.valid).sum()) >= 15
    # one trial masked there, the other not: the average is the valid one's (10 N x depth), not a blend
    one = average_trials([_stroke(valid=v), _stroke()], n_points=200)
    ok = one.valid & inside
    assert ok.sum() >= 15
    np.testing.assert_allclose(one.force[ok, 1], 10 * (-0.28 - one.toe[ok, 1]) / 0.04, atol=1e-6)
    out = subtract_air(_stroke(), _stroke(air=True, valid=v))
    assert not out.valid[141:159].any() and out.valid[:140].all() and out.valid[160:].all()
    assert list(out.why_masked.values()) == [int((~out.valid).sum())]
    frac = _stroke().force[:, 1] / 10
    np.testing.assert_allclose(out.force[out.valid, 1], (10 * frac - (1 + frac))[out.valid], atol=1e-9)


def test_filter_keeps_edges_and_odd_windows_only():
    from irft_torch.hardware import zero_phase_filter

    v = np.ones(12, bool)
    v[:3] = v[-2:] = False
    t = ForceTrace(np.arange(12) * 0.001, np.zeros((12, 2)), np.zeros((12, 2)), np.zeros((12, 2)),
                   np.where(v[:, None], 10.0, np.nan) * np.ones((12, 2)), v)
    out = zero_phase_filter(t, window=5)
    np.testing.assert_allclose(out.force[v], 10.0)  # a constant stays constant up to the masked ends
    assert np.isnan(out.force[~v]).all()
    impulse = np.zeros((13, 2))
    impulse[6] = 1.0
    t = ForceTrace(np.arange(13) * 0.001, impulse * 0, impulse * 0, impulse * 0, impulse, np.ones(13, bool))
    out = zero_phase_filter(t, window=5)
    assert np.nonzero(out.force[:, 0])[0].tolist() == [4, 5, 6, 7, 8]  # centred on the impulse: no lag
    with pytest.raises(ValueError, match="odd"):
        zero_phase_filter(t, window=4)


def test_encoder_jitter_does_not_misalign_runs_with_arc_noise():
    """Toe jitter of 20 um while standing still adds centimetres of 'arc length' (5 cm on the
    Traveler's log); with arc_noise the air run of a jittery leg lines up with the trial (its pause
    later and longer) and the subtraction leaves the trial's ground force."""
    from irft_torch.hardware.pipeline import progress

    kw = dict(T=1000, jitter=2e-5)
    trial, air = _stroke(pause=(300, 700), seed=1, **kw), _stroke(pause=(350, 800), seed=2, air=True, **kw)
    truth = _stroke(pause=(300, 700), T=1000).force[:, 1]  # the ground force: 10 N x depth fraction
    trial.force[:, 1] += 1 + truth / 10  # plus the air run's force at the same place
    assert trial.arc_length[-1] > 0.055  # a 4 cm stroke read as more than 5.5 cm
    s = progress(trial.toe, trial.time, 2e-4)
    assert abs(s[-1] - 0.04) < 2e-3 and (np.diff(s) > 0).all()
    clean = _stroke(pause=(300, 700), T=1000)
    depth = abs(clean.toe[-1, 1] - clean.toe[0, 1])
    np.testing.assert_allclose(progress(clean.toe, clean.time, 0.0)[-1], depth, atol=1e-6)  # the plain path length
    errs = {}
    for noise in (0.0, 2e-4):
        trial.arc_noise = air.arc_noise = noise
        out = subtract_air(trial, air)
        errs[noise] = np.abs(out.force[out.valid, 1] - truth[out.valid])
        assert out.valid.mean() > 0.95
    assert np.median(errs[2e-4]) < 0.01 and errs[2e-4].max() < 0.1  # lined up by place
    assert errs[0.0].max() > 5 * errs[2e-4].max()  # by jitter-inflated distance they are not


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


def test_averaging_says_what_a_longer_trial_loses():
    """Trials within min_coverage of each other are averaged over the distance all covered; what the
    longer ones ran beyond it is named in a warning (data are never dropped silently)."""
    from irft_torch.hardware import average_trials

    long, short = _stroke(T=200), _stroke(T=200)
    short = short.masked(np.arange(200) < 194)  # 3 % shorter
    # by hand: 159 and 153 of the 160 moving 0.25 mm steps: 3.975 and 3.825 cm, 1.5 mm = 3.8 % beyond
    with pytest.warns(UserWarning, match=r"covers 0\.038 m.* the last 0\.00[12] m of the longest trial \(3\.8 %\)"):
        avg = average_trials([long, short])
    assert avg.arc_length[-1] <= short.arc_length[-1] + 1e-9
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        average_trials([long, _stroke(T=200)])  # equal trials: nothing to say


def _log_with_heartbeats(path, states, rate=200.0, duration=1.0, firmware="0.5"):
    """A hand-written CANSimple log: both nodes' encoder estimates and currents at ``rate`` Hz, and
    heartbeats every 0.1 s whose (axis_error, axis_state, motor_error_flag) for node 0 come from
    ``states(t)`` (node 1 always healthy, closed loop)."""
    from irft_torch.hardware import encode

    writer = can.CanutilsLogWriter(str(path))
    n = int(round(duration * rate)) + 1
    for k in range(n):
        t = k / rate
        for node in (0, 1):
            writer.on_message_received(encode("get_encoder_estimates", node, firmware, timestamp=t + 1e-4,
                                              pos_estimate=0.01 * t, vel_estimate=0.01))
            writer.on_message_received(encode("get_iq", node, firmware, timestamp=t + 2e-4,
                                              iq_setpoint=1.0, iq_measured=1.0))
    for k in range(int(round(duration * 10)) + 1):
        t = k / 10
        for node in (0, 1):
            err, state, flag = states(t) if node == 0 else (0, 8, 0)
            writer.on_message_received(encode("heartbeat", node, firmware, timestamp=t + 3e-4, axis_error=err,
                                              axis_state=state, motor_error_flag=flag, encoder_error_flag=0,
                                              controller_flags=0))
    writer.stop()


@pytest.mark.parametrize("bad", [(0, 1, 0), (0x40, 8, 0), (0, 8, 1)], ids=["idle", "axis-error", "motor-flag"])
def test_a_motor_that_stops_controlling_is_masked_from_the_last_good_heartbeat(tmp_path, bad):
    """Node 0's heartbeats at 0.5 and 0.6 s report it idle, an axis error, or (0.5 firmware) a motor
    error flag: every sample after the last good heartbeat (0.4 s) and before the next good one
    (0.7 s) is masked and counted under a reason that names the node and what the heartbeats said;
    the rest stays valid (counted by hand from the time base)."""
    from irft_torch.hardware import read_log

    path = tmp_path / "fault.log"
    _log_with_heartbeats(path, lambda t: bad if 0.45 < t < 0.65 else (0, 8, 0))
    log = read_log(path).resample()
    t = log.time - 3e-4  # the heartbeats' clock (they were written 0.3 ms after each 0.1 s mark)
    expect = (t > 0.4 + 1e-9) & (t < 0.7 - 1e-9)
    np.testing.assert_array_equal(~log.valid, expect)
    (reason, count), = log.masked.items()
    assert reason.startswith("node 0: motor not in closed-loop control or reporting an error") and count == expect.sum()
    assert ("axis_state 1" in reason) if bad[1] == 1 else ("with an error set" in reason)
    healthy = read_log(_log_with_heartbeats(tmp_path / "ok.log", lambda t: (0, 8, 0)) or tmp_path / "ok.log")
    assert healthy.resample().valid.all()
