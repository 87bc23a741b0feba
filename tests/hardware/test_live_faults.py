"""Faults while live, each injected on the virtual bus while the simulated leg walks: what the estimator
does (its message, what it counts) and that nothing is lost (every frame the bus delivered is in the log,
the log and the last snapshot are readable)."""

import re
import threading
import uuid

import can
import numpy as np
import pytest
import torch

import irft_torch as irft
from irft_torch.gp import InverseRFT
from irft_torch.hardware import LiveEstimator, MotorModel, WalkingLeg, read_log, stride_path
from irft_torch.hardware.live import MAP_POINTS

TOE = irft.rft.CToe(0.02, 0.008, n_segments=8)
SAND = irft.rft.FourierStressMap.generic(1.0, 1.5)
# These run a simulated leg against the wall clock on a virtual bus: a loaded 2-core host can pause the worker
# past a stance or a staleness limit. A failure that repeats on rerun is a real one.
pytestmark = pytest.mark.flaky(reruns=2)

TICKS = 150  # per stride at 1 kHz: half the swing (25 ms), the stance (0.1 s), the other half


@pytest.fixture(scope="module")
def prior(tmp_path_factory):
    p = stride_path(TOE, 0.025, stance_time=0.1, swing_time=0.05, rate=300)
    c = irft.rft.contacts(TOE, p)
    f = irft.rft.forces(SAND, c)
    m = InverseRFT(c, f + 0.02 * torch.randn(f.shape, generator=torch.Generator().manual_seed(1)),
                   hyper_posterior="map", method="spectral")
    m.fit(30, progress=False)
    path = tmp_path_factory.mktemp("prior") / "prior.pt"
    m.save(path)
    return path


def walk(tmp_path, prior, strides=4, hook=None, bus_patch=None, leg_kw=None, **kw):
    leg = WalkingLeg(TOE, SAND, stance_time=0.1, swing_time=0.05, current_noise=0.02, hook=hook, **(leg_kw or {}))
    channel = f"irft-fault-{uuid.uuid4().hex}-bus"
    events = []
    opened = []

    def factory():
        b = can.Bus(channel=channel, interface="virtual")
        if bus_patch is not None and not opened:
            bus_patch(b)
        opened.append(b)
        return b

    opts = dict(leg=leg.leg, motors=leg.motors, toe=TOE, hip_height=leg.hip_height, firmware="0.6",
                out_dir=tmp_path / "out", stale_after=0.5)  # a loaded CI host pauses threads for 0.1 s and more
    opts.update(kw)
    est = LiveEstimator(None, model=InverseRFT.load(prior), callback=events.append, bus_factory=factory, **opts)
    with est:
        leg.walk(channel, strides)
        est.drain()
    for b in opened:
        b.shutdown()
    return leg, est, events


def messages(events):
    return [e.message for e in events if e.event == "status"]


def assert_nothing_lost(tmp_path, est, sent=None):
    assert est.intake.logged == est.intake.received
    if sent is not None:
        assert est.intake.received == sent
    assert read_log(tmp_path / "out" / "frames.blf", firmware="0.6").n_frames == est.intake.logged
    if est.n_updates:
        InverseRFT.load(tmp_path / "out" / "model.pt")


def final_map(est):
    with torch.no_grad():
        return est.model.stress_map(torch.as_tensor(MAP_POINTS[:, 0]), torch.as_tensor(MAP_POINTS[:, 1])).mean.numpy()


def test_motor_that_stops_sending_marks_the_estimate_stale(tmp_path, prior):
    # node 1 silent for 0.75 s (5 strides), from stride 2's stance into stride 7's: longer than stale_after, which is
    # longer than the pauses of a loaded host (at 0.15 s this test failed there: a pause read as a silence)
    silent = range(TICKS + 60, 6 * TICKS + 60)

    def hook(tick, msgs):
        return [m for m in msgs if not (tick in silent and m.arbitration_id >> 5 == 1)]

    leg, est, events = walk(tmp_path, prior, strides=8, hook=hook, stale_after=0.5)
    said = messages(events)
    # said when the worker, caught up, sees the silence, or when node 1's next frame shows the gap
    assert any(m.startswith("node 1 ") and m.endswith("the estimate is stale (not updated) until it sends again")
               for m in said), said
    assert "both motors are sending again: the estimate is live" in said
    stances = [e for e in events if e.event == "stance"]
    # stride 2's stance dropped, strides 3-6 never seen, stride 7's joined midway skipped: strides 1 and 8 used
    assert [e.why_unused for e in stances if not e.used] == ["node 1 fell silent during it"]
    assert sum(e.used for e in stances) == 2 and est.detector.n_skipped > 0
    assert_nothing_lost(tmp_path, est, leg.frames_sent)


def test_duplicate_and_out_of_order_frames_are_dropped_and_counted(tmp_path, prior):
    held = []

    def hook(tick, msgs):
        if tick % 100 == 0:  # ticks with heartbeats are left alone
            return msgs
        if tick % 50 == 7:
            return msgs + [m for m in msgs if m.arbitration_id & 0x1F == 0x14]  # the currents twice
        if tick % 50 == 30:
            held.extend(msgs)  # sent after the next tick's frames: out of order
            return []
        out = msgs + held
        held.clear()
        return out

    leg, est, events = walk(tmp_path, prior, strides=2, hook=hook)
    n_dup = sum(1 for t in range(2 * TICKS) if t % 100 and t % 50 == 7) * 2
    n_late = sum(1 for t in range(2 * TICKS) if t % 100 and t % 50 == 30) * 4
    assert est.resampler.counts["duplicate"] == n_dup
    assert est.resampler.counts["out of order"] == n_late
    assert events[-1].counts["duplicate"] == n_dup and events[-1].counts["out of order"] == n_late
    assert est.n_updates == 2
    assert_nothing_lost(tmp_path, est, leg.frames_sent)


def test_duplicates_change_nothing(tmp_path, prior):
    def dup(tick, msgs):
        return msgs + msgs if tick % 100 else msgs

    _, clean, _ = walk(tmp_path / "a", prior, strides=2)
    _, doubled, _ = walk(tmp_path / "b", prior, strides=2, hook=dup)
    np.testing.assert_allclose(final_map(doubled), final_map(clean), atol=1e-9)


def test_timestamp_jump_is_undone(tmp_path, prior):
    def hook(tick, msgs):
        if tick >= TICKS + 140:  # in the swing of stride 2: the logger's clock steps one hour ahead
            for m in msgs:
                m.timestamp += 3600.0
        return msgs

    leg, est, events = walk(tmp_path, prior, strides=3, hook=hook)
    said = messages(events)
    # the step is the frames' clock less the wall clock between two arrivals: a loaded host's pause (CI: 15 ms)
    # is in the wall clock's part, so the step is known to the host's jitter, not to the frame period
    steps = [float(re.search(r"clock jumped by ([+-][0-9.]+) s", m)[1]) for m in said if "clock jumped by" in m]
    assert len(steps) == 1 and abs(steps[0] - 3600.0) < 0.25, said
    assert est.n_updates == 3 and not est.unused
    assert_nothing_lost(tmp_path, est, leg.frames_sent)


def test_stance_with_no_contact_is_reported(tmp_path, prior):
    # the force says stance, but the stated hips are 6 cm higher: the toe never reaches the stated surface
    leg, est, events = walk(tmp_path, prior, strides=2, stance="force", force_threshold=0.2, hip_height=0.31)
    unused = [e.why_unused for e in events if e.event == "stance"]
    assert unused and all(w.startswith("no segment in contact at the stated surface") for w in unused), unused
    assert est.n_updates == 0
    assert_nothing_lost(tmp_path, est, leg.frames_sent)


def test_implausible_forces_are_masked_and_reported(tmp_path, prior):
    # k_t 100x the motors' (a unit slip): forces no granular medium gives at these depths
    wrong = (MotorModel(9.73), MotorModel(9.73))
    leg, est, events = walk(tmp_path, prior, strides=2, motors=wrong)
    unused = [e.why_unused for e in events if e.event == "stance"]
    assert len(unused) == 2 and all(w.startswith("forces implausible for a granular medium: F_") for w in unused)
    assert "1e+02x" in unused[0] or "100x" in unused[0] or "large" in unused[0] or "x what" in unused[0], unused[0]
    assert est.n_updates == 0
    assert_nothing_lost(tmp_path, est, leg.frames_sent)


def test_queue_falling_behind_is_bounded_and_reported(tmp_path, prior):
    slow = threading.Event()
    events = []

    def cb(e):
        events.append(e)
        if e.event == "stance":
            slow.wait(0.4)  # a callback slower than the stride

    leg = WalkingLeg(TOE, SAND, stance_time=0.1, swing_time=0.05)
    channel = f"irft-fault-{uuid.uuid4().hex}-bus"
    bus = can.Bus(channel=channel, interface="virtual")
    est = LiveEstimator(bus, leg.leg, leg.motors, TOE, leg.hip_height, model=InverseRFT.load(prior), firmware="0.6",
                        out_dir=tmp_path / "out", callback=cb, max_queue=200, stale_after=5.0)
    with est:
        leg.walk(channel, 4)
        est.drain()
    bus.shutdown()
    assert est.intake.dropped > 0 and est.intake.high_water <= 200
    said = messages(events)
    assert any(m.startswith("the queue fell behind:") and "(all logged)" in m for m in said), said
    assert est.n_updates < 4  # the stances whose frames were dropped did not update it
    assert_nothing_lost(tmp_path, est, leg.frames_sent)  # every frame still in the log


def test_bus_error_reconnects(tmp_path, prior):
    def patch(bus):
        orig = bus.recv
        t_fail = []

        def recv(timeout=None):
            msg = orig(timeout)
            if msg is not None and msg.timestamp and len(t_fail) < 1 and bus._n_seen > 700:
                t_fail.append(msg.timestamp)
            bus._n_seen += 1
            if t_fail:
                raise can.CanOperationError("bus-off (simulated)")
            return msg

        bus._n_seen = 0
        bus.recv = recv

    leg, est, events = walk(tmp_path, prior, strides=8, bus_patch=patch)  # 6 after the outage: a loaded host is slow
    said = messages(events)
    assert "bus error: CanOperationError: bus-off (simulated); reconnecting" in said, said
    assert "reconnected (1 so far)" in said
    assert est.reconnections == 1 and est.n_updates >= 2  # stances after the reconnection update the estimate
    assert_nothing_lost(tmp_path, est)  # what the bus delivered is logged (frames during the outage never arrived)


def test_log_rotated_by_size_keeps_every_frame(tmp_path, prior):
    leg, est, _ = walk(tmp_path, prior, strides=2, log_name="frames.asc", max_log_bytes=40_000)
    files = sorted((tmp_path / "out").glob("frames*.asc"))
    assert len(files) >= 2  # rotated (python-can's SizedRotatingLogger)
    assert sum(sum(1 for _ in can.LogReader(str(f))) for f in files) == leg.frames_sent == est.intake.logged
