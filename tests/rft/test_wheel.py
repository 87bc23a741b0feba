"""The rolling wheel: hand-derived cases (locked wheel = sliding plate, pure rolling, arc integrals)."""

import math

import pytest
import torch

from irft_torch.rft import Contacts, FourierStressMap, forces
from irft_torch.rft.wheel import (
    average_rows,
    circle_profile,
    envelope_profile,
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
    # float64 inputs stay float64 whatever the default dtype: pure rolling is slip 0, not 1e-7
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        d = torch.tensor([0.01], dtype=torch.float64)
        s0 = slip_ratio(d, d / R, R)
        assert s0.dtype == torch.float64 and abs(s0.item()) < 1e-15
        v, om = wheel_speeds(torch.tensor([0.3], dtype=torch.float64), R, v=0.01)
        assert v.dtype == om.dtype == torch.float64
        assert slip_ratio(0.01, 0.01 / R, R).dtype == torch.float32  # numbers: the default dtype
    finally:
        torch.set_default_dtype(old)


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


def test_average_rows_keeps_the_surface():
    """The average keeps depths and areas: moving the surface of the average (1 cm up, 1 cm down) gives the
    mean force of the poses moved by as much, segments above the sand that a higher surface reaches
    included (the unaveraged poses, forces summed by hand, are the reference)."""
    prof = circle_profile(R, W, 120)
    phases = torch.linspace(0, 2 * math.pi / 120, 4)[:-1]
    c = wheel_contacts(prof, 0.01, 0.2, R, 0.02, phases=phases)
    avg = average_rows(c)
    assert avg.has_surface and avg.shape[0] == 1
    assert int((avg.weight_z == 0).sum()) > 0  # zero-weight segments that face the sand are kept
    smap = FourierStressMap.generic()
    for delta in (0.01, -0.01):
        moved = c.with_surface_offset(delta)
        a = smap(moved.beta, moved.gamma)
        by_hand = torch.stack([(moved.weight_x * a[..., 0]).sum(-1), (moved.weight_z * a[..., 1]).sum(-1)], -1).mean(0)
        torch.testing.assert_close(forces(smap, avg.with_surface_offset(delta))[0], by_hand)
    assert forces(smap, c.with_surface_offset(0.01)).abs().sum() > 1.2 * forces(smap, c).abs().sum()  # it matters
    bare = average_rows(Contacts(c.beta, c.gamma, c.weight_x, c.weight_z))
    assert not bare.has_surface and int((bare.weight_z == 0).sum()) == 0  # without areas: zero weights dropped


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


def _polygon_toe(vertices, width):
    """A closed polygon (counter-clockwise vertices) as a Toe, built here from the vertices directly."""
    from irft_torch.rft.toes import Toe

    v = torch.as_tensor(vertices, dtype=torch.float64)
    a, b = v, torch.roll(v, -1, 0)
    d = b - a
    L = d.norm(dim=-1)
    return Toe((a + b) / 2, d / L[:, None], L, width)


def test_envelope_of_a_toothed_rim_is_the_polygon_through_the_tips():
    """A 12-point star (tips at R, notches at R/2 between them): the hull is the regular hexagon
    through the 6 tips, side R, perimeter 6 R, area 3 sqrt(3) / 2 R^2, every normal outward."""
    k = torch.arange(12, dtype=torch.float64)
    rad = torch.where(k % 2 == 0, torch.full_like(k, R), torch.full_like(k, R / 2))
    ang = -math.pi / 2 + 2 * math.pi * k / 12
    star = _polygon_toe(torch.stack([rad * torch.cos(ang), rad * torch.sin(ang)], -1), W)
    hull = envelope_profile(star)
    assert hull.n_segments == 6 and hull.width == W
    torch.testing.assert_close(hull.lengths, torch.full((6,), R, dtype=torch.float64))
    normal = torch.stack([hull.tangents[:, 1], -hull.tangents[:, 0]], -1)
    # each edge's outward normal points from the centre to the edge's midpoint (apothem R cos 30 deg)
    torch.testing.assert_close(normal, hull.centres / hull.centres.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(hull.centres.norm(dim=-1), torch.full((6,), R * math.cos(math.pi / 6),
                                                                         dtype=torch.float64))
    start = hull.centres - hull.tangents * (hull.lengths / 2)[:, None]
    x, z = start[:, 0], start[:, 1]
    area = 0.5 * (x * torch.roll(z, -1) - torch.roll(x, -1) * z).sum()  # shoelace: > 0 counter-clockwise
    assert area.item() == pytest.approx(3 * math.sqrt(3) / 2 * R**2)


def test_envelope_of_a_convex_rim_is_the_rim():
    prof = circle_profile(R, W, 360)
    hull = envelope_profile(prof)
    assert hull.n_segments == 360
    assert hull.lengths.sum().item() == pytest.approx(prof.lengths.sum().item(), rel=1e-12)
    smap = FourierStressMap.generic()
    for v, om, s in ((0.01, 0.0, 0.03), (0.01, 0.1 / R, 0.02)):
        torch.testing.assert_close(forces(smap, average_rows(wheel_contacts(hull, v, om, R, s))),
                                   forces(smap, average_rows(wheel_contacts(prof, v, om, R, s))))
    with pytest.raises(TypeError, match="Toe"):
        envelope_profile(prof.centres)


def _arc_quadrature(v, omega, sinkage, n=20001):
    """(F_x, F_z) of the circular rim's leading arc by the trapezoidal rule over phi (the rim point at
    angle phi from the bottom, toward +x): depth r cos phi - (r - s), tangent (cos phi, sin phi), velocity
    (v - omega r cos phi, -omega r sin phi); raw angles mirrored by hand for motion toward -x."""
    phi0 = math.acos(1 - sinkage / R)
    lo, hi = (0.0, phi0) if v > 0 else (-phi0, 0.0)
    fx = fz = 0.0
    dphi = (hi - lo) / (n - 1)
    for i in range(n):
        phi = lo + i * dphi
        depth = (R * math.cos(phi) - (R - sinkage)) * 100
        vx, vz = v - omega * R * math.cos(phi), -omega * R * math.sin(phi)
        beta, gamma, sign = phi, math.atan2(-vz, vx), 1.0
        if vx < 0:
            beta, gamma, sign = -phi, math.atan2(-vz, -vx), -1.0
        ax, az = generic_alpha(beta, gamma)
        dA = (W * 100) * (R * 100) * dphi * (0.5 if i in (0, n - 1) else 1.0)
        fx += -sign * ax * depth * dA
        fz += az * depth * dA
    return torch.tensor([fx, fz], dtype=torch.float64)


def test_wheel_contacts_keep_signed_depths_for_a_surface_offset():
    """The signed depths and areas are kept (as rft.contacts keeps them, trailing segments at area 0), so a
    surface 1 cm higher than stated is the wheel 1 cm deeper: both equal the arc quadrature at the deeper
    sinkage, for a locked, a slipping and a skidding wheel and one rolling toward -x."""
    prof = circle_profile(R, W, 2000)
    smap = FourierStressMap.generic()
    for v, omega in ((0.01, 0.0), (0.01, 0.02 / R), (0.01, 0.005 / R), (-0.01, -0.03 / R)):
        c = wheel_contacts(prof, v, omega, R, 0.015)
        assert c.has_surface
        assert (c.depth < 0).any()  # the rim above the sand keeps its (negative) depth
        up = forces(smap, c.with_surface_offset(0.01))[0]
        want = _arc_quadrature(v, omega, 0.025)
        torch.testing.assert_close(up, want, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(up, forces(smap, wheel_contacts(prof, v, omega, R, 0.025))[0])
        torch.testing.assert_close(forces(smap, c)[0], _arc_quadrature(v, omega, 0.015), rtol=1e-4, atol=1e-4)


def test_clockwise_profile_is_an_error_not_the_trailing_arc():
    """The leading arc is found from the outward normal, the tangent rotated by -90 degrees, which is
    outward only for a counter-clockwise profile: the same rim given clockwise would silently keep the
    trailing half. It is a ValueError; the counter-clockwise polyline gives the arc quadrature."""
    from irft_torch.rft import PolylineToe

    phi = -math.pi / 2 + 2 * math.pi * torch.arange(2001, dtype=torch.float64) / 2000
    pts = R * torch.stack([torch.cos(phi), torch.sin(phi)], -1)
    smap = FourierStressMap.generic()
    F = forces(smap, wheel_contacts(PolylineToe(pts, W), 0.01, 0.005 / R, R, 0.02))[0]
    torch.testing.assert_close(F, _arc_quadrature(0.01, 0.005 / R, 0.02), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="counter-clockwise"):
        wheel_contacts(PolylineToe(pts.flip(0), W), 0.01, 0.005 / R, R, 0.02)
    # contact="submerged" does not use the normals: either order is the same rim
    a = forces(smap, wheel_contacts(PolylineToe(pts, W), 0.01, 0.0, R, 0.02, contact="submerged"))
    b = forces(smap, wheel_contacts(PolylineToe(pts.flip(0), W), 0.01, 0.0, R, 0.02, contact="submerged"))
    torch.testing.assert_close(a, b)
