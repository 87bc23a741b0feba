"""Logs, the signal pipeline and the simulated leg, end to end."""

import math
import struct
import threading

import can
import numpy as np
import pytest
import torch

import irft_torch as irft
from irft_torch.hardware import (
    FakeODrive,
    FiveBarLeg,
    LogReadError,
    SimulatedLeg,
    average_trials,
    build_dataset,
    encode,
    forces_from_log,
    load_dataset,
    read_log,
    record,
    save_dataset,
    subtract_air,
    zero_phase_filter,
)

from .closed_form import ik_coaxial, torques_coaxial

MEDIUM = irft.rft.FourierStressMap.generic(1.0, 1.5)
PATH = irft.rft.rectangle_path(0.05, 0.30, 0.05, start=(-0.15, 0.0), n_steps=200)


def closed_form_currents(truth, l1, l2, hip_height, kt):
    """Currents (T, 2) A that hold the simulated leg against its ground force, from the coaxial
    five-bar's closed forms (hardware_facts.md), and its joint angles (T, 2) rad: a reference
    independent of FiveBarLeg, which the simulated leg and ingest both use."""
    q = np.array([ik_coaxial(x, z, l1, l2) for x, z in truth.toe])
    tau = np.array([torques_coaxial(x, z, f, l1, l2) for (x, z), f in zip(truth.toe, truth.force)])
    return q, tau / kt


def assert_simulation_matches_closed_form(sim, truth):
    assert (sim.friction, sim.cogging) == (0.0, 0.0)
    q, current = closed_form_currents(truth, sim.leg.l1, sim.leg.l2, sim.hip_height, sim.motors[0].torque_constant)
    np.testing.assert_allclose(truth.q, q, atol=1e-9)
    np.testing.assert_allclose(truth.current, current, atol=1e-7)
    assert np.abs(current).max() > 1.0  # the check has something to check


def run(tmp_path, name="sand.log", in_air=False, **kw):
    sim = SimulatedLeg(irft.rft.IToe(0.08, 0.008), MEDIUM, **kw)
    truth = sim.run(PATH, tmp_path / name, in_air=in_air)
    return sim, truth


def truth_at(trace, truth):
    """Truth at the trace's samples, by time since the first frame (.asc stores relative times)."""
    t = trace.time - trace.time[0] + (0.0 if trace.time[0] < 1e6 else trace.time[0] - 1.7e9)
    return np.stack([np.interp(t, truth.time, truth.force[:, k]) for k in range(2)], -1)


def test_blf_roundtrip_is_exact(tmp_path):
    """Binary BLF logs: every frame, value and timestamp (to 1 us) comes back."""
    sent = []
    with can.Logger(str(tmp_path / "x.blf")) as log:
        for k in range(500):
            for node in (0, 1):
                m = encode("get_iq", node, timestamp=1.7e9 + k / 200, iq_setpoint=0.5 * k, iq_measured=-0.25 * k)
                log.on_message_received(m)
                sent.append((m.timestamp, node, -0.25 * k))
    data = read_log(tmp_path / "x.blf")
    assert data.issues == [] and data.n_frames == len(sent)
    for node in (0, 1):
        t, v = data.motors[node].arrays("iq")
        want = [(ts, val) for ts, n, val in sent if n == node]
        np.testing.assert_allclose(t, [w[0] for w in want], rtol=0, atol=1e-6)
        np.testing.assert_allclose(v[:, 1], [w[1] for w in want], rtol=0, atol=0)


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_end_to_end_noise_off_recovers_forces(tmp_path, suffix):
    sim, truth = run(tmp_path, "sand" + suffix)
    assert_simulation_matches_closed_form(sim, truth)
    data = read_log(tmp_path / ("sand" + suffix))
    assert data.issues == [] and sorted(data.motors) == [0, 1]
    trace = forces_from_log(data.resample(rate=sim.rate), sim.leg, sim.motors)
    rng = truth.force.max(0) - truth.force.min(0)
    err = np.abs(trace.force - truth_at(trace, truth)).max(0)
    assert (err / rng < 0.01).all(), err / rng  # measured: ~1e-5 of the range (float32 payloads)


def test_air_subtraction_removes_friction_and_cogging(tmp_path):
    kw = dict(friction=0.08, cogging=0.03)
    sim, truth = run(tmp_path, **kw)
    run(tmp_path, "air.log", in_air=True, **kw)
    t = forces_from_log(read_log(tmp_path / "sand.log").resample(rate=200), sim.leg, sim.motors)
    a = forces_from_log(read_log(tmp_path / "air.log").resample(rate=200), sim.leg, sim.motors)
    rng = truth.force.max(0) - truth.force.min(0)
    raw_err = np.abs(t.force - truth_at(t, truth)).max(0) / rng
    fixed = subtract_air(t, a)
    err = np.abs(fixed.force - truth_at(fixed, truth))[fixed.valid].max(0) / rng
    assert (raw_err > 0.05).any() and (err < 0.01).all(), (raw_err, err)


def test_noise_frame_drops_filter_and_trial_average(tmp_path):
    kw = dict(friction=0.05, cogging=0.02, current_noise=0.2, frame_drop=0.05)
    traces = []
    for seed in range(3):
        sim, truth = run(tmp_path, f"sand{seed}.log", seed=seed, **kw)
        run(tmp_path, f"air{seed}.log", in_air=True, seed=seed, **kw)
        t = forces_from_log(read_log(tmp_path / f"sand{seed}.log").resample(rate=200), sim.leg, sim.motors)
        a = forces_from_log(read_log(tmp_path / f"air{seed}.log").resample(rate=200), sim.leg, sim.motors)
        traces.append(zero_phase_filter(subtract_air(t, a), window=9))
    avg = average_trials(traces)
    rng = truth.force.max(0) - truth.force.min(0)
    one = np.sqrt(np.nanmean((traces[0].force - truth_at(traces[0], truth)) ** 2, 0)) / rng
    three = np.sqrt(np.nanmean((avg.force - truth_at(avg, truth)) ** 2, 0)) / rng
    assert (three < 0.03).all() and (three < one).all(), (one, three)  # reported in the closing note


def test_dataset_roundtrip_and_contacts(tmp_path):
    sim, truth = run(tmp_path)
    trace = forces_from_log(read_log(tmp_path / "sand.log").resample(rate=200), sim.leg, sim.motors)
    ds = build_dataset(trace, sim.leg, sim.toe, sim.hip_height)
    save_dataset(tmp_path / "ds.npz", ds, source="test")
    back = load_dataset(tmp_path / "ds.npz")
    torch.testing.assert_close(back.forces, ds.forces)
    torch.testing.assert_close(back.contacts.weight_z, ds.contacts.weight_z)
    # forward RFT on the dataset's contacts reproduces the measured forces (same medium)
    f = irft.rft.forces(MEDIUM, back.contacts)
    rng = back.forces.amax(0) - back.forces.amin(0)
    assert ((f - back.forces).abs().amax(0)[1] / rng[1]) < 0.02


def test_corrupted_and_truncated_logs(tmp_path):
    sim, truth = run(tmp_path)
    lines = (tmp_path / "sand.log").read_text().splitlines()
    n = len(lines)
    bad = list(lines)
    bad.insert(50, "(1700000000.100000) vcan0 034#0000")  # wrong length
    bad.insert(60, "(1700000000.200000) vcan0 7E1#0000000000000000")  # unknown command 0x01 of node 63? valid
    bad.insert(70, "(1700000000.300000) vcan0 03F#0000000000000000")  # unknown command 0x1f
    nan = "0000c07f0000c07f"  # two float32 NaNs
    bad.insert(80, f"(1700000000.400000) vcan0 034#{nan}")
    bad.append(lines[-1][:18])  # a truncated last line
    (tmp_path / "bad.log").write_text("\n".join(bad) + "\n")
    with pytest.raises(LogReadError, match=r"bad.log: damaged or truncated: 1 damaged line\(s\) \(first") as e:
        read_log(tmp_path / "bad.log")
    assert f"from {n + 4} frame(s) read before the fault" in str(e.value)
    part = e.value.partial
    issues = "\n".join(part.issues)
    assert "wrong length" in issues and "unknown id" in issues and "non-finite" in issues
    good = read_log(tmp_path / "sand.log")
    for node in (0, 1):
        assert len(part.motors[node].times["iq"]) == len(good.motors[node].times["iq"])  # nothing good lost
    with pytest.warns(UserWarning, match="truncated"):
        read_log(tmp_path / "bad.log", on_error="warn")


def test_out_of_order_and_gaps_are_reported_and_masked(tmp_path):
    path = tmp_path / "odd.log"
    with can.Logger(str(path)) as log:
        ts = [0.0, 0.01, 0.02, 0.015, 0.03, 0.04, 0.2, 0.21, 0.22, 0.23]
        for t in ts:
            for node in (0, 1):
                log.on_message_received(encode("get_iq", node, timestamp=1e9 + t, iq_setpoint=0, iq_measured=t))
                log.on_message_received(encode("get_encoder_estimates", node, timestamp=1e9 + t,
                                               pos_estimate=t, vel_estimate=0))
    data = read_log(path)
    text = "\n".join(data.issues)
    assert "earlier than the one before; sorted by time" in text and "gap" in text
    t, v = data.motors[0].arrays("iq")
    assert (np.diff(t) >= 0).all() and len(t) == len(ts)
    r = data.resample(rate=100)
    inside = (r.time - 1e9 > 0.045) & (r.time - 1e9 < 0.195)
    assert not r.valid[inside].any() and r.valid[~inside].all()


def test_record_live_bus_against_fake_controllers(tmp_path):
    threads_before = threading.active_count()
    channel = "irft-record-test"
    host = can.Bus(channel=channel, interface="virtual")
    drives = [FakeODrive(can.Bus(channel=channel, interface="virtual"), n) for n in (0, 1)]
    for i, d in enumerate(drives):
        d.set_state(0.1 * i, 0.0, 1.5 + i)
        d.start()
    try:
        n = record(host, tmp_path / "live.log", duration=0.3, rate=100)
    finally:
        for d in drives:
            d.stop()
            d.bus.shutdown()
        host.shutdown()
    data = read_log(tmp_path / "live.log")
    _, v0 = data.motors[0].arrays("iq")
    _, v1 = data.motors[1].arrays("iq")
    # every frame counted is in the file, each an answer with the state the controller was given
    assert n == len(v0) + len(v1) and len(v0) >= 5 and len(v1) >= 5
    assert (v0[:, 1] == 1.5).all() and (v1[:, 1] == 2.5).all()
    assert threading.active_count() == threads_before  # the notifier and both fake controllers stopped


def test_bad_inputs(tmp_path):
    with pytest.raises(FileNotFoundError, match="no log file"):
        read_log(tmp_path / "missing.log")
    with pytest.raises(ValueError, match="on_error"):
        read_log(tmp_path / "missing.log", on_error="ignore")
    with pytest.raises(ValueError, match="window"):
        zero_phase_filter(None, window=0)


@pytest.mark.parametrize("content", [b"time_s,x_m,z_m\n0,-0.2,0\n", b"\x80\x04K\x01.", b"\x93NUMPY\x01\x00"])
def test_load_dataset_of_a_file_that_is_no_npz_says_so(tmp_path, content):
    # a CSV (irft simulate --csv), a pickle, a .npy renamed .npz: none is a zip archive
    path = tmp_path / "sim.npz"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=r"not an irft dataset \(\.npz from irft ingest\): not an \.npz") as e:
        load_dataset(path)
    assert "pickle" not in str(e.value)  # numpy's advice to load it unsafely is not shown


def test_read_log_nodes_filter_counts_the_rest(tmp_path):
    path = tmp_path / "three.log"
    with can.Logger(str(path)) as log:
        for k in range(10):
            for node in (0, 1, 2):
                log.on_message_received(encode("get_iq", node, timestamp=1e9 + k / 100, iq_setpoint=0,
                                               iq_measured=10 * node + k))
    data = read_log(path, nodes={0, 2})
    assert sorted(data.motors) == [0, 2] and data.skipped["node not requested"] == 10
    assert data.motors[2].arrays("iq")[1][:, 1].tolist() == [20.0 + k for k in range(10)]
    assert "skipped 10 frame(s): node not requested" in data.issues


def test_firmware_06_torques_and_heartbeats(tmp_path):
    """0.6.x: Get_Torques (0x1C, f32 target, f32 estimate in N m) is read into the "torque" group;
    read as 0.5.x, 0x1C is not a known command and the frames are skipped as unknown ids."""
    path = tmp_path / "fw06.log"
    lines = []
    for k in range(5):
        t = 1e9 + k / 100
        data = struct.pack("<ff", 0.5 * k, -0.25 * k)
        lines.append(f"({t:.6f}) can0 {1 << 5 | 0x1C:03X}#{data.hex().upper()}")
        hb = bytes([0, 0, 0, 0, 8, 0, 1, 0])  # u32 error, state 8, procedure result 0, trajectory done
        lines.append(f"({t:.6f}) can0 {1 << 5 | 0x01:03X}#{hb.hex().upper()}")
    path.write_text("\n".join(lines) + "\n")
    data = read_log(path, firmware="0.6")
    t, v = data.motors[1].arrays("torque")
    assert data.issues == [] and v.tolist() == [[0.5 * k, -0.25 * k] for k in range(5)]
    old = read_log(path, firmware="0.5")
    assert {n: set(m.times) for n, m in old.motors.items()} == {1: {"heartbeat"}}  # the motor's state only
    assert sum(old.skipped.values()) == 5
    assert any("unknown id" in i and "skipped 5" in i for i in old.issues)
    with pytest.raises(ValueError, match="firmware"):
        read_log(path, firmware="0.4")


def test_toe_path_heading():
    """Straight down at q = (g, -g), l1 = 0.1, l2 = 0.2, g = pi/3: distal link 1 runs from the knee
    at (l1 sin g, -l1 cos g) to the toe (0, -L), tilted clockwise from straight down by
    asin(l1 sin g / l2) = asin(0.4330127) = 0.4478324 rad; link 2 is its mirror image."""
    leg = FiveBarLeg(0.1, 0.2)
    g = math.pi / 3
    q = torch.tensor([[g, -g], [g, -g]], dtype=torch.float64)
    t = torch.tensor([0.0, 0.1], dtype=torch.float64)
    assert leg.toe_path(t, q, heading="link1").heading.tolist() == pytest.approx([-0.4478324] * 2, abs=1e-7)
    assert leg.toe_path(t, q, heading="link2").heading.tolist() == pytest.approx([0.4478324] * 2, abs=1e-7)
    p = leg.toe_path(t, q, heading=0.3, hip_height=0.25)
    assert p.heading.tolist() == [0.3, 0.3]
    np.testing.assert_allclose(p.position.numpy(), [[0.0, 0.25 - 0.2302776]] * 2, atol=1e-7)
    with pytest.raises(ValueError, match="heading must be a number or 'link1'/'link2'"):
        leg.toe_path(t, q, heading="link3")


def test_simulated_leg_writes_blf_whatever_its_channel_name(tmp_path, monkeypatch):
    """The virtual channel's name used to end in uuid hex digits, which the BLF writer read as a
    16-bit channel number (struct.error about 1 run in 6); a name ending in digits is now harmless."""
    import irft_torch.hardware.simulated_leg as sl

    class FakeUUID:
        hex = "0123456789"

    monkeypatch.setattr(sl.uuid, "uuid4", lambda: FakeUUID())
    sim = SimulatedLeg(irft.rft.IToe(0.04, 0.008), MEDIUM, rate=40)
    sim.run(irft.rft.rectangle_path(0.02, 0.04, 0.02, start=(-0.02, 0.0)), tmp_path / "s.blf")
    data = read_log(tmp_path / "s.blf")
    assert data.issues == [] and len(data.motors[0].times["iq"]) > 20


def test_a_file_with_no_can_frame_says_it_is_not_a_can_log(tmp_path):
    # e.g. irft simulate's CSV renamed or passed as a log: not a single line is a frame
    p = tmp_path / "sim.log"
    p.write_text("time_s,x_m,z_m\n" + "".join(f"{0.01 * i},0.0,-0.01\n" for i in range(20)))
    with pytest.raises(LogReadError, match=r"sim.log is not a CAN log in python-can's \.log format: no line is a "
                                           r"CAN frame \(first line: 'time_s,x_m,z_m'\)"):
        read_log(p)
