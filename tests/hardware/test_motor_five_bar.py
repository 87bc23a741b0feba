import math
import warnings

import numpy as np
import pytest
import torch

from irft_torch.hardware import FiveBarLeg, MotorModel, SingularConfigurationWarning, kt_from_kv


def test_torque_constant_conventions():
    assert kt_from_kv(85) == pytest.approx(0.0973, abs=1e-4)  # the paper's U8-II
    assert kt_from_kv(85, "si") / kt_from_kv(85) == pytest.approx(60 / (2 * math.pi) / 8.27)
    assert kt_from_kv(85) / kt_from_kv(85, "si") == pytest.approx(0.866, abs=1e-3)  # ODrive's = 0.866 x SI
    m = MotorModel(0.0973, direction=-1, gear_ratio=6.0, zero_offset=0.2)
    assert m.torque(2.0).item() == pytest.approx(-2 * 6 * 0.0973)
    assert m.current(m.torque(1.5)).item() == pytest.approx(1.5)
    assert m.joint_angle(m.encoder_turns(0.7)).item() == pytest.approx(0.7)
    assert m.joint_angle(6.0).item() == pytest.approx(-2 * math.pi + 0.2)  # 6 motor turns = 1 joint turn
    with pytest.raises(ValueError, match="direction"):
        MotorModel(0.1, direction=2)
    with pytest.raises(ValueError, match="torque_constant"):
        MotorModel(97.3)  # N m per mA would be a unit slip


LEGS = [FiveBarLeg(0.1, 0.2), FiveBarLeg(0.12, 0.25, hip_spacing=0.08),
        FiveBarLeg(0.1, 0.2, extension=0.05), FiveBarLeg(0.12, 0.25, hip_spacing=0.08, extension=0.03)]


@pytest.mark.parametrize("leg", LEGS)
def test_jacobian_against_finite_differences(leg):
    q = torch.tensor([[0.5, -0.4], [0.9, 0.1], [0.2, -0.9]], dtype=torch.float64)
    J = leg.jacobian(q)
    eps = 1e-6
    for j in range(2):
        dq = torch.zeros(2, dtype=torch.float64)
        dq[j] = eps
        fd = (leg.forward_kinematics(q + dq) - leg.forward_kinematics(q - dq)) / (2 * eps)
        torch.testing.assert_close(J[..., :, j], fd, atol=1e-8, rtol=1e-7)


def test_symmetric_leg_hand_derived_statics():
    """Coaxial five-bar: q1 = th + g, q2 = th - g, L(g) = l1 cos g + sqrt(l2^2 - l1^2 sin^2 g);
    F_radial = (tau1 - tau2) / L'(g), F_tangential = (tau1 + tau2) / L (hardware_facts.md)."""
    l1, l2, th, g = 0.1, 0.2, 0.3, 0.8
    leg = FiveBarLeg(l1, l2)
    q = torch.tensor([th + g, th - g], dtype=torch.float64)
    L = l1 * math.cos(g) + math.sqrt(l2**2 - l1**2 * math.sin(g) ** 2)
    dL = -l1 * math.sin(g) - l1**2 * math.sin(g) * math.cos(g) / math.sqrt(l2**2 - l1**2 * math.sin(g) ** 2)
    torch.testing.assert_close(leg.forward_kinematics(q), torch.tensor([L * math.sin(th), -L * math.cos(th)]))
    tau = torch.tensor([0.7, -0.2], dtype=torch.float64)
    # J^-T tau in radial/tangential components (radial = along the leg, away from the hip)
    radial = (tau[0] - tau[1]) / dL
    tangential = (tau[0] + tau[1]) / L
    e_r = torch.tensor([math.sin(th), -math.cos(th)])
    e_t = torch.tensor([math.cos(th), math.sin(th)])  # d/d th of the toe direction
    want = -(radial * e_r + tangential * e_t)  # ground force is -J^-T tau
    force, valid = leg.ground_force(q, tau)
    assert bool(valid)
    torch.testing.assert_close(force, want)


@pytest.mark.parametrize("leg", LEGS)
def test_ground_force_against_numpy_solve_and_roundtrip(leg):
    rng = np.random.default_rng(0)
    q = torch.as_tensor(np.stack([rng.uniform(0.3, 0.9, 20), rng.uniform(-0.9, -0.3, 20)], -1))
    tau = torch.as_tensor(rng.normal(size=(20, 2)))
    force, valid = leg.ground_force(q, tau)
    J = leg.jacobian(q).numpy()
    for i in range(20):
        if valid[i]:
            np.testing.assert_allclose(force[i].numpy(), -np.linalg.solve(J[i].T, tau[i].numpy()), rtol=1e-9)
    # a known static load through torques and back
    load = torch.tensor([3.0, 25.0], dtype=torch.float64).expand(20, 2)
    back, ok = leg.ground_force(q, leg.holding_torques(q, load))
    torch.testing.assert_close(back[ok], load[ok])


def test_ik_inverts_fk_and_names_unreachable_points():
    leg = FiveBarLeg(0.15, 0.3, hip_spacing=0.05)
    p = torch.tensor([[0.05, -0.3], [-0.1, -0.25], [0.12, -0.35]], dtype=torch.float64)
    torch.testing.assert_close(leg.forward_kinematics(leg.inverse_kinematics(p)), p)
    with pytest.raises(ValueError, match=r"p\[1\].*outside the leg's workspace"):
        leg.inverse_kinematics(torch.tensor([[0.0, -0.3], [0.0, -0.9]], dtype=torch.float64))


def test_singular_configurations_are_masked_not_huge():
    leg = FiveBarLeg(0.1, 0.2)
    q = torch.tensor([[0.6, -0.6], [1e-7, -1e-7], [0.4, -0.2]], dtype=torch.float64)  # row 1: stretched
    with pytest.warns(SingularConfigurationWarning, match="1 of 3"):
        force, valid = leg.ground_force(q, torch.ones(3, 2, dtype=torch.float64))
    assert valid.tolist() == [True, False, True]
    assert torch.isnan(force[1]).all() and torch.isfinite(force[[0, 2]]).all()
    assert leg.condition_number(q)[1] > 1e3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        leg.ground_force(q[[0, 2]], torch.ones(2, 2, dtype=torch.float64))


def test_ik_refuses_toes_forward_kinematics_puts_elsewhere():
    """F54. Hips 0.1 m apart, l1 = 0.1, l2 = 0.2, toe p = (-0.08, -0.27) m. By hand (law of cosines,
    knee 1 on the +x side of its hip-to-toe line, knee 2 on the -x side): q1 = atan2(-0.03, 0.27) +
    acos((l1^2 + r1^2 - l2^2) / (2 l1 r1)), r1 = |p - hip1|, likewise q2 with a minus. Both knees
    are then l2 from p, but knee 1 ends up 0.8 mm left of knee 2 (the knees have crossed past each
    other), so forward_kinematics, which keeps the toe on one side of the knee line, puts the toe
    at p's mirror image across that line, 0.1 m above the hips. inverse_kinematics returned these
    angles silently (a simulated leg logged joint angles whose toe was elsewhere)."""
    l1, l2, s = 0.1, 0.2, 0.1
    leg = FiveBarLeg(l1, l2, hip_spacing=s)
    p = np.array([-0.08, -0.27])
    hips = np.array([[-s / 2, 0.0], [s / 2, 0.0]])
    q = []
    for i, sign in ((0, 1), (1, -1)):
        rel = p - hips[i]
        r = math.hypot(*rel)
        q.append(math.atan2(rel[0], -rel[1]) + sign * math.acos((l1**2 + r**2 - l2**2) / (2 * l1 * r)))
    knees = hips + l1 * np.stack([np.sin(q), -np.cos(q)], -1)
    np.testing.assert_allclose(np.linalg.norm(p - knees, axis=1), [l2, l2], atol=1e-12)
    assert knees[0, 0] < knees[1, 0]  # crossed
    d = knees[1] - knees[0]
    mid = knees.mean(0)
    mirror = p - 2 * np.dot(p - mid, [-d[1], d[0]]) / np.dot(d, d) * np.array([-d[1], d[0]])
    np.testing.assert_allclose(leg.forward_kinematics(torch.tensor(q)).numpy(), mirror, atol=1e-9)
    assert mirror[1] > 0.09
    with pytest.raises(ValueError, match=r"p\[1\] = \[-0.08, -0.27\].*knees"):
        leg.inverse_kinematics(torch.tensor([[0.0, -0.25], p.tolist()], dtype=torch.float64))
    # toes the leg reaches in its assembly still round-trip (hips apart, and coaxial above the hips)
    for leg_, pts in ((leg, [[0.0, -0.25], [0.05, -0.2], [-0.1, -0.15]]),
                      (FiveBarLeg(l1, l2), [[0.0, 0.2], [0.1, -0.2]])):
        pts = torch.tensor(pts, dtype=torch.float64)
        torch.testing.assert_close(leg_.forward_kinematics(leg_.inverse_kinematics(pts)), pts)


def test_jacobian_at_a_singular_configuration_is_a_clear_error():
    """F55. Singular configurations by hand. (a) Coaxial leg, q1 = q2 = 0.3: both knees at
    l1 (sin 0.3, -cos 0.3), so the toe can be anywhere on the circle of radius l2 around them (the
    forward kinematics is undetermined: NaN, not the knee point 0 m from the knees as before). (b)
    Hips 2 m apart, l1 = 0.5, l2 = 1.5, q = (-pi/2, pi/2): knees at (-1.5, 0) and (1.5, 0), 2 l2
    apart, the toe at the origin between them: all four links on the x axis. jacobian and
    holding_torques raised torch's bare 'linalg.solve: ... the input matrix is singular'; now a
    ValueError names q[i]. (c) Knees 0.5 m > 2 l2 apart (unreachable): a NaN Jacobian is refused
    too. ground_force still masks such samples (NaN force, a warning)."""
    l1, l2 = 0.1, 0.2
    coax = FiveBarLeg(l1, l2)
    q = torch.tensor([[0.5, -0.5], [0.3, 0.3]], dtype=torch.float64)
    knee = l1 * np.array([math.sin(0.3), -math.cos(0.3)])
    np.testing.assert_allclose(coax._knees(q[1])[0].numpy(), [knee, knee], atol=1e-15)
    p = coax.forward_kinematics(q)
    assert torch.isfinite(p[0]).all() and torch.isnan(p[1]).all()
    with pytest.raises(ValueError, match=r"q\[1\] = \[0.3, 0.3\] rad.*singular"):
        coax.jacobian(q)
    with pytest.raises(ValueError, match=r"q\[1\].*singular"):
        coax.holding_torques(q, torch.zeros(2, 2, dtype=torch.float64))
    line = FiveBarLeg(0.5, 1.5, hip_spacing=2.0)
    q = torch.tensor([-math.pi / 2, math.pi / 2], dtype=torch.float64)
    np.testing.assert_allclose(line._knees(q)[0].numpy(), [[-1.5, 0.0], [1.5, 0.0]], atol=1e-15)
    np.testing.assert_allclose(line.forward_kinematics(q).numpy(), [0.0, 0.0], atol=1e-15)
    with pytest.raises(ValueError, match=r"q\[0\] = \[-1.5708, 1.5708\] rad.*singular"):
        line.holding_torques(q, torch.tensor([0.0, 10.0], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"q\[0\].*cannot reach"):
        FiveBarLeg(l1, l2, hip_spacing=0.5).jacobian(torch.zeros(2, dtype=torch.float64))
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        force, valid = line.ground_force(q, torch.ones(2, dtype=torch.float64))
    assert not bool(valid) and torch.isnan(force).all()
