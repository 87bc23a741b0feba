"""The air baseline live (``hardware.AirBaseline``): a leg that draws current in air (the links' weight), a
stored air run of the same stride subtracted causally. Judged against the same walk by a leg that draws
nothing in air (the truth the subtraction should recover) and against the walk with nothing subtracted."""

import uuid

import can
import numpy as np
import pytest
import torch

import irft_torch as irft
from irft_torch.gp import InverseRFT
from irft_torch.hardware import AirBaseline, LiveEstimator, WalkingLeg
from irft_torch.hardware.live import MAP_POINTS
from irft_torch.hardware.walking_leg import stride_path

TOE = irft.rft.CToe(0.02, 0.008, n_segments=8)
SAND = irft.rft.FourierStressMap.generic(1.0, 1.5)
AIR = irft.rft.FourierStressMap.generic(0.0, 0.0)  # no medium: the leg in air
N_STRIDES = 6


def weight(q):
    """A current the leg draws in air, A (n, 2) from joint angles (n, 2): the links' weight, cos q."""
    return 1.5 * np.cos(q) + 0.5


def leg(medium, air_current=None):
    return WalkingLeg(TOE, medium, stance_time=0.15, swing_time=0.1, air_current=air_current)


def record(walker, path, n_strides=3):
    """Every frame of ``n_strides`` strides (each of the walk's depths once) into a log at ``path``, as fast as the
    bus takes them."""
    channel = f"irft-air-{uuid.uuid4().hex}-bus"  # no trailing digits: BLF holds a channel number < 2^16
    bus = can.Bus(channel=channel, interface="virtual")
    writer = can.Logger(str(path))
    walker.walk(channel, n_strides, realtime=False)
    while (msg := bus.recv(0.0)) is not None:
        writer.on_message_received(msg)
    writer.stop()
    bus.shutdown()
    return path


@pytest.fixture(scope="module")
def start(tmp_path_factory):
    d = tmp_path_factory.mktemp("air")
    p = stride_path(TOE, 0.025, rate=200)
    c = irft.rft.contacts(TOE, p)
    m = InverseRFT(c, irft.rft.forces(SAND, c), hyper_posterior="map", method="spectral")
    m.fit(40, progress=False)
    m.save(d / "prior.pt")
    return d


def live_map(walker, prior, air=None):
    channel = f"irft-air-live-{uuid.uuid4().hex}-bus"
    bus = can.Bus(channel=channel, interface="virtual")
    est = LiveEstimator(bus, walker.leg, walker.motors, TOE, walker.hip_height, model=InverseRFT.load(prior),
                        firmware="0.6", air=air, stale_after=30.0)
    with est:
        walker.walk(channel, N_STRIDES, realtime=False)
        est.drain(60.0, ended=True)
    bus.shutdown()
    assert est.error is None and est.n_updates == N_STRIDES, (est.error, est.n_updates, est.unused,
                                                              est.resampler.counts)
    b, g = torch.as_tensor(MAP_POINTS[:, 0]), torch.as_tensor(MAP_POINTS[:, 1])
    with torch.no_grad():
        return est.model.stress_map(b, g).mean.numpy(), est


def test_a_stored_air_run_subtracted_live_recovers_the_walk_of_a_leg_that_draws_nothing_in_air(start):
    air_log = record(leg(AIR, weight), start / "air.blf")
    baseline = AirBaseline.from_log(air_log, leg(AIR).leg, leg(AIR).motors, firmware="0.6")
    truth, _ = live_map(leg(SAND), start / "prior.pt")
    subtracted, est = live_map(leg(SAND, weight), start / "prior.pt", air=baseline)
    raw, _ = live_map(leg(SAND, weight), start / "prior.pt")
    scale = np.abs(truth).max()
    err_sub, err_raw = np.abs(subtracted - truth).max() / scale, np.abs(raw - truth).max() / scale
    assert err_raw > 0.2, err_raw  # the weight matters: unsubtracted, the map is off by a fifth or more
    # subtracted: the weightless walk's map (measured 1.6e-4 of the map's largest value; an air run that missed
    # one of the walk's three depths left 4.7e-2, the nearest positions then at another pose)
    assert err_sub < 2e-3, (err_sub, err_raw)
    assert "samples with no air-run force near the toe" not in est.last.counts


def test_where_the_air_run_never_was_samples_are_masked_and_counted(start):
    air_log = record(leg(AIR, weight), start / "air_half.blf")
    full = AirBaseline.from_log(air_log, leg(AIR).leg, leg(AIR).motors, firmware="0.6")
    front = full.toe[:, 0] > np.median(full.toe[:, 0])  # half the stride's positions only
    half = AirBaseline(full.toe[front], full.force[front])
    _, est = live_map(leg(SAND, weight), start / "prior.pt", air=half)
    assert est.last.counts["samples with no air-run force near the toe"] > 0


def test_air_baseline_lookup_and_bad_input():
    toe = np.array([[0.0, -0.2], [0.01, -0.2], [0.02, -0.21]])
    force = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    air = AirBaseline(toe, force, max_distance=0.004)
    got = air(np.array([[0.0011, -0.2], [0.0195, -0.2095], [0.05, -0.2], [np.nan, 0.0]]))
    np.testing.assert_array_equal(got[:2], [[1.0, 2.0], [5.0, 6.0]])  # the nearest air-run sample's force
    assert np.isnan(got[2:]).all()  # 3 cm from any air-run sample, and a NaN toe: no baseline there
    with pytest.raises(ValueError, match="max_distance"):
        AirBaseline(toe, force, max_distance=5.0)  # mm given for m
    with pytest.raises(ValueError, match=r"\(n, 2\)"):
        AirBaseline(toe, force[:, :1])
    with pytest.raises(ValueError, match="valid sample"):
        AirBaseline(toe[:1], force[:1])
    with pytest.raises(FileNotFoundError, match="air-run log"):
        AirBaseline.from_log("no/such/air.blf", irft.hardware.FiveBarLeg(0.15, 0.30),
                             (irft.hardware.MotorModel.u8_ii(),) * 2)
