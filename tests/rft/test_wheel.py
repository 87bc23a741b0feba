"""The rolling wheel: hand-derived cases (locked wheel = sliding plate, pure rolling, arc integrals)."""

import math

import pytest
import torch

from irft_torch.rft import FourierStressMap, forces
from irft_torch.rft.wheel import (
    average_rows,
    circle_profile,
    profile_from_elements,
    slip_ratio,
    wheel_contacts,
    wheel_kinematics,
    wheel_speeds,
)

R, W = 0.0625, 0.06


def generic_alpha(beta, gamma):
    """Li et al. 2013 generic coefficients, written out here (rft_facts.md) independently of the package."""
    az = (0.206 + 0.169 * math.cos(2 * beta) + 0.212 * math.sin(2 * beta + gamma) + 0.358 * math.sin(gamma)
          + 0.055 * math.sin(-2 * beta + gamma))
    ax = (-0.124 * math.cos(2 * beta + gamma) + 0.253 * math.cos(gamma) + 0.007 * math.cos(-2 * beta + gamma)
          + 0.088 * math.sin(2 * beta))
    return ax, az


def test_slip_ratio_and_speeds():
    assert slip_ratio(0.01, 0.01 / R, R).item() == pytest.approx(0.0)
    assert slip_ratio(0.01, 0.0, R).item() == pytest.approx(-1.0)  # locked
    assert slip_ratio(0.01, 0.1 / R, R).item() == pytest.approx(0.9)
    assert slip_ratio(0.01, 0.003 / R, R).item() == pytest.approx(-0.7)  # the data's skid branch
    assert slip_ratio(0.0, 1.0, R).item() == pytest.approx(1.0)  # spinning in place
    for s in (-0.7, 0.0, 0.5):
        v, om = wheel_speeds(s, R, v=0.01)
        assert slip_ratio(v, om, R).item() == pytest.approx(s)
    with pytest.raises(ValueError, match="at rest"):
        slip_ratio(0.0, 0.0, R)


def test_pure_rolling_contact_point_is_at_rest():
    """slip 0: the rim point touching the ground's level below the axle has zero velocity; every
    point moves as a rotation about it (instantaneous centre)."""
    prof = circle_profile(R, W, 720)
    v = 0.01
    k = wheel_kinematics(prof, v, v / R, R, sinkage=0.02)
    pos, vel = k.position[0], k.velocity[0]
    ic = torch.tensor([0.0, -0.02], dtype=torch.float64)  # the lowest point of the rim
    om = -v / R  # counter-clockwise rate
    rel = pos - ic
    want = torch.stack([-om * rel[:, 1], om * rel[:, 0]], -1)
    torch.testing.assert_close(vel, want)
    bottom = pos[:, 1].argmin()
    assert vel[bottom].norm() < v * 0.01  # the chord next to the contact point barely moves


def test_locked_wheel_is_a_plate_sliding():
    """omega = 0: every segment slides horizontally (gamma = 0); the leading (front) lower arc is a
    curved plate: F = sum over phi in [0, phi0] of alpha(beta = phi, 0) depth dA."""
    M, s, v = 720, 0.03, 0.01
    prof = circle_profile(R, W, M)
    c = wheel_contacts(prof, v, 0.0, R, s)
    F = forces(FourierStressMap.generic(), c)[0]
    want = torch.zeros(2, dtype=torch.float64)
    dphi = 2 * math.pi / M
    zc = R - s
    for m in range(M):
        phi = (m + 0.5) * dphi  # chord midpoints, counter-clockwise from the bottom
        if phi > math.pi:
            break  # only the front half leads
        depth = -(zc - R * math.cos(phi) * math.cos(dphi / 2))
        if depth <= 0:
            continue
        ax, az = generic_alpha(phi, 0.0)  # tangent (cos phi, sin phi): tilt phi, sliding toward +x
        w = (depth * 100) * (2 * R * math.sin(dphi / 2) * 100) * (W * 100)
        want += torch.tensor([-ax * w, az * w], dtype=torch.float64)  # drag opposes +x
    torch.testing.assert_close(F, want)
    assert F[0] < 0 and F[1] > 0
    assert (c.gamma[c.weight_z > 0] == 0).all()


def test_weights_against_the_arc_integral():
    """sum of weight_z = width x int depth ds over the contact arc: r w [r sin phi0 - (r - s) phi0]
    (front half) and twice that for the whole submerged arc."""
    s = 0.025
    phi0 = math.acos(1 - s / R)
    exact = W * R * (R * math.sin(phi0) - (R - s) * phi0) * 1e6  # m^3 -> cm^3
    prof = circle_profile(R, W, 4000)
    for omega in (0.0, 0.1, 0.3 / R):  # the leading arc does not depend on the spin
        lead = wheel_contacts(prof, 0.01, omega, R, s)
        assert lead.weight_z.sum().item() == pytest.approx(exact, rel=1e-4)
    sub = wheel_contacts(prof, 0.01, 0.1, R, s, contact="submerged")
    assert sub.weight_z.sum().item() == pytest.approx(2 * exact, rel=1e-4)


def test_motion_toward_minus_x_mirrors_the_force():
    prof = circle_profile(R, W, 360)
    smap = FourierStressMap.generic()
    for omega in (0.0, 0.5 * 0.01 / R, 0.02 / R):
        f_pos = forces(smap, wheel_contacts(prof, 0.01, omega, R, 0.03))[0]
        f_neg = forces(smap, wheel_contacts(prof, -0.01, -omega, R, 0.03))[0]
        torch.testing.assert_close(f_neg, f_pos * torch.tensor([-1.0, 1.0], dtype=torch.float64))


def test_phases_and_average_rows():
    prof = circle_profile(R, W, 360)
    phases = torch.linspace(0, 2 * math.pi / 360, 4)[:-1]
    c = wheel_contacts(prof, 0.01, 0.2, R, 0.03, phases=phases)
    assert c.shape[0] == 3
    smap = FourierStressMap.generic()
    per_pose = forces(smap, c)
    mean = forces(smap, average_rows(c))[0]
    torch.testing.assert_close(mean, per_pose.mean(0))


def test_profile_from_elements_matches_the_circle():
    prof = circle_profile(R, W, 500)
    n = torch.stack([prof.tangents[:, 1], -prof.tangents[:, 0]], -1)
    again = profile_from_elements(prof.centres, n, prof.lengths, W)
    torch.testing.assert_close(again.tangents, prof.tangents)
    smap = FourierStressMap.generic()
    a = forces(smap, wheel_contacts(prof, 0.01, 0.1, R, 0.02))
    b = forces(smap, wheel_contacts(again, 0.01, 0.1, R, 0.02))
    torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="sinkage"):
        wheel_contacts(prof, 0.01, 0.1, R, -0.01)
    with pytest.raises(ValueError, match="contact"):
        wheel_contacts(prof, 0.01, 0.1, R, 0.01, contact="all")
