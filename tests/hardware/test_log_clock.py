"""The logger's clock read in file order (hardware.bus.log_clock): restarts split a log into recordings,
steps and jumps are undone; every dataset is checked against the oracle (RFT of its own contacts in
the simulated leg's known sand: clean logs are 6e-5 N off)."""

import numpy as np
import pytest

from irft_torch.hardware import read_log
from irft_torch.hardware.bus.log_clock import clock_breaks

from .fault_logs import dump, ingest, shifted

TOL = 0.05  # N


def test_clean_logs_match_the_oracle(capsys, tmp_path, sim_logs):
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"])
    assert rc == 0 and err == "" and "clock" not in out
    assert sim_logs["oracle"](ds) < 1e-3 and len(ds) > 250


@pytest.mark.parametrize("start", [0.0, 0.7, 3600.0], ids=["relative-from-0", "relative-from-0.7", "an-hour-later"])
def test_a_restarted_clock_splits_the_log_into_recordings(capsys, tmp_path, sim_logs, start):
    """Two recordings appended (was: interleaved by the sort, 3973 of 4345 samples off by > 0.5 N): each
    is a run of its own, both go into the dataset, the dataset matches the oracle."""
    trial = sim_logs["trial"]
    t0 = trial[0][0]
    if start < 100:  # relative times: both recordings start near 0
        lines = shifted(trial, -t0 + 2.0) + shifted(trial, -t0 + start)
    else:  # absolute times: the next recording an hour after the first ended
        lines = trial + shifted(trial, trial[-1][0] - t0 + start)
    data = read_log(dump(lines, tmp_path / "two.log"))
    assert len(data.segments) == 2 and ("the clock restarts" in data.issues[0] or "clock jumps" in data.issues[0])
    for seg in data.segments:  # each recording whole and in order: the same samples as the clean log
        t, v = seg.motors[0].arrays("iq")
        assert len(t) == len(read_log(dump(trial, tmp_path / "one.log")).motors[0].arrays("iq")[0])
        assert (np.diff(t) > 0).all()
    with pytest.raises(ValueError, match="holds 2 recordings.*resample each of LogData.segments"):
        data.resample()
    rc, out, err, ds = ingest(capsys, tmp_path, lines, sim_logs["air"])
    assert rc == 0 and "holds 2 recordings" in out and "from 2 run(s) in sand" in out
    assert sim_logs["oracle"](ds) < TOL


def test_a_restart_in_the_air_run_is_split_too(capsys, tmp_path, sim_logs):
    """(was: the trial blamed on the air run) two air runs appended: averaged as two air runs."""
    air = sim_logs["air"]
    lines = shifted(air, -air[0][0] + 1.0) + shifted(air, -air[0][0])
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], lines)
    assert rc == 0 and "holds 2 recordings" in out and sim_logs["oracle"](ds) < TOL


@pytest.mark.parametrize("step", [-2.0, -0.3, -30.0, 2.5, 86400.0, "absolute"])
def test_a_clock_set_mid_log_is_undone(capsys, tmp_path, sim_logs, step):
    """An NTP step back of 2 s (was: the overlap merged, errors up to 3.3 N), a step back longer than
    the recording, a jump ahead of 2.5 s or a day (was: 199 s and 6 GB, the gap counted as contact), from
    relative to absolute time (was: "lower the rate"): the motors' positions continue across it, so
    the frames after it are re-timed to follow on; every sample is kept, the dataset matches the oracle
    and lasts what the clean one does."""
    trial = sim_logs["trial"]
    k = len(trial) // 2 + 3  # inside a burst of one instant's frames
    if step == "absolute":
        lines = shifted(trial[:k], -trial[0][0]) + trial[k:]
    else:
        lines = shifted(trial, step, k)
    data = read_log(dump(lines, tmp_path / "c.log"))
    clean = read_log(dump(trial, tmp_path / "clean.log"))
    assert not data.segments and any("clock" in i and "re-timed" in i for i in data.issues)
    for node in (0, 1):
        for group in ("encoder", "iq"):
            t, v = data.motors[node].arrays(group)
            tc, vc = clean.motors[node].arrays(group)
            np.testing.assert_array_equal(v, vc)  # every sample, in its order
            np.testing.assert_allclose(np.diff(t), np.diff(tc), atol=1e-5)  # each series' spacing kept
    rc, out, err, ds = ingest(capsys, tmp_path, lines, sim_logs["air"])
    assert rc == 0 and sim_logs["oracle"](ds) < TOL
    duration = float(out.split("duration ")[1].split(" s")[0])
    assert abs(duration - (trial[-1][0] - trial[0][0])) < 0.02


def test_late_frames_and_a_short_pause_are_not_clock_breaks(tmp_path, sim_logs):
    """One frame 0.3 s late is disorder (sorted, reported as before), not a restart; a pause under a
    second while the leg moves stays a gap (masked), not a recording of its own."""
    trial = [list(x) for x in sim_logs["trial"]]
    trial[400][0] -= 0.3
    data = read_log(dump(trial, tmp_path / "late.log"))
    assert not data.segments and any("sorted by time" in i for i in data.issues)
    k = len(sim_logs["trial"]) // 2
    gap = sim_logs["trial"][:k] + sim_logs["trial"][k + 60:]  # 60 frames, about 0.12 s, missing
    data = read_log(dump(gap, tmp_path / "gap.log"))
    assert not data.segments and any("gap" in i for i in data.issues)
    assert not data.resample().valid.all()


def test_clock_breaks_by_hand():
    """Four series sampled every 10 ms, positions moving 1e-3 turn a sample; the clock set back 5 s at
    frame 22 (positions continue: a step, re-timed to follow on by each series' own 10 ms), then at
    frame 42 back to 0 with the positions 0.3 turn away (a restart: a second recording)."""
    ids = np.tile(np.arange(4), 15)
    inst = np.repeat(np.arange(15), 4) * 0.01 + ids * 1e-4
    t = 100.0 + inst
    t[22:] -= 5.0
    t[42:] = inst[42:] - inst[42]
    pos_rec = np.repeat(np.arange(15), 4) * 1e-3
    pos_rec[42:] += 0.3
    positions = {n: (np.nonzero(ids == n)[0], pos_rec[ids == n]) for n in range(2)}  # two of the ids: encoders
    b = clock_breaks(t, positions, ids)
    assert b.segment.tolist() == [0] * 42 + [1] * 18
    np.testing.assert_allclose((t + b.offset)[:42], 100.0 + inst[:42], atol=1e-9)  # the step undone exactly
    assert "steps back 5.000 s at frame 23" in b.notes[0] and "restarts at frame 43" in b.notes[1]
