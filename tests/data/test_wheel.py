"""The rover-wheel reader and its axis mapping (skipped where the shared data are absent)."""

import math
import pathlib

import numpy as np
import pytest
import torch

from irft_torch.data import wheel as wd
from irft_torch.rft import FourierStressMap, forces
from irft_torch.rft.wheel import wheel_contacts

DATA = pathlib.Path(__file__).resolve().parents[3] / "shared" / "data" / "rover_wheel"
needs_data = pytest.mark.skipif(not DATA.is_dir(),
                                reason=f"rover-wheel data not found at {DATA} (not shipped: no licence)")


def test_reader_errors_without_data(tmp_path):
    with pytest.raises(FileNotFoundError, match="no rover-wheel data directory"):
        wd.read_wheel_runs(tmp_path / "nope", "smooth")
    with pytest.raises(FileNotFoundError, match="not shipped"):
        wd.read_wheel_runs(tmp_path, "smooth")
    with pytest.raises(ValueError, match="wheel must be"):
        wd.read_wheel_runs(tmp_path, "tracked")


@needs_data
@pytest.mark.parametrize("wheel", ["smooth", "grouser"])
def test_runs_at_slip_angle_zero_and_axis_mapping(wheel):
    runs = wd.read_wheel_runs(DATA, wheel)
    assert all(r.slip_angle_deg == 0 for r in runs)
    levels = sorted({r.commanded_rim_speed for r in runs})
    assert len(levels) == 9 and levels[0] == 0.0
    assert min(r.slip for r in runs) == pytest.approx(-1.0)
    assert max(r.slip for r in runs) == pytest.approx(0.9, abs=0.01)
    locked = [r for r in runs if r.slip < -0.99]
    fast = [r for r in runs if r.slip > 0.85]
    # the README's mapping: a locked wheel resists the motion (F_x < 0), the lift carries the load
    assert all(r.force[0] < 0 and r.force[1] > 0 for r in locked)
    assert np.mean([r.force[0] for r in fast]) > np.mean([r.force[0] for r in locked])
    assert all(0 < r.sinkage < 2 * wd.WHEEL_RADIUS for r in runs)
    assert all(r.rim_speed == pytest.approx(0.0, abs=1e-6) for r in locked)
    # the authors' RFT has the same sign pattern
    assert all(r.rft_force[0] < 0 < r.rft_force[1] for r in locked)
    assert len(wd.read_wheel_runs(DATA, wheel, slip_angle_deg=None)) > len(runs)


@needs_data
@pytest.mark.parametrize("wheel", ["smooth", "grouser"])
def test_profiles_are_closed_counter_clockwise_rims(wheel):
    prof = wd.read_profile(DATA, wheel)
    r = prof.centres.norm(dim=-1)
    assert r.max() <= wd.WHEEL_RADIUS * 1.01
    normal = torch.stack([prof.tangents[:, 1], -prof.tangents[:, 0]], -1)
    outward = ((normal * prof.centres).sum(-1) > 0).to(prof.lengths.dtype)
    assert (prof.lengths * outward).sum() / prof.lengths.sum() > 0.99
    if wheel == "smooth":
        assert prof.lengths.sum().item() == pytest.approx(2 * math.pi * wd.WHEEL_RADIUS, rel=1e-3)
    else:  # rim + grouser faces: longer than the tips' circle
        assert prof.lengths.sum().item() > 2 * math.pi * wd.WHEEL_RADIUS
    # a locked wheel at 3 cm sinkage under the generic map: drag against the motion, lift up
    F = forces(FourierStressMap.generic(), wheel_contacts(prof, 0.01, 0.0, wd.WHEEL_RADIUS, 0.03))[0]
    assert F[0] < 0 < F[1]


@needs_data
def test_grousered_envelope_is_the_tips_circle():
    """The grousered rim's convex hull: every vertex at a grouser tip (radius 62.2-62.8 mm: the
    mesh's tips, whose merged segments' ends stick out a little), a polygon of perimeter 2 pi r_tip
    to 0.1 %, shorter than the rim with its grouser faces."""
    from irft_torch.rft.wheel import envelope_profile

    prof = wd.read_profile(DATA, "grouser")
    hull = envelope_profile(prof)
    half = hull.tangents * (hull.lengths / 2)[:, None]
    r = (hull.centres - half).norm(dim=-1)
    assert 0.0622 < r.min().item() and r.max().item() < 0.0628
    assert hull.lengths.sum().item() == pytest.approx(2 * math.pi * r.mean().item(), rel=1e-3)
    assert hull.lengths.sum() < prof.lengths.sum()
