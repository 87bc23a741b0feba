"""FiveBarLeg's ``extension`` (a toe l3 beyond the distal joint along the leg axis, the Traveler's
0.05 m): closed-form kinematics and statics of the symmetric leg, finite differences, round trips."""

import math

import pytest
import torch

from irft_torch.hardware import FiveBarLeg


def test_extension_closed_form_symmetric_leg():
    """q1 = th + g, q2 = th - g: toe at (L + l3)(sin th, -cos th) with L(g) = l1 cos g +
    sqrt(l2^2 - l1^2 sin^2 g); F_radial = (tau1 - tau2) / L'(g), F_tangential = (tau1 + tau2) / (L + l3)."""
    l1, l2, l3, th, g = 0.1, 0.2, 0.05, -0.25, 1.1
    leg = FiveBarLeg(l1, l2, extension=l3)
    q = torch.tensor([th + g, th - g], dtype=torch.float64)
    root = math.sqrt(l2**2 - l1**2 * math.sin(g) ** 2)
    L = l1 * math.cos(g) + root
    dL = -l1 * math.sin(g) - l1**2 * math.sin(g) * math.cos(g) / root
    e_r = torch.tensor([math.sin(th), -math.cos(th)], dtype=torch.float64)
    e_t = torch.tensor([math.cos(th), math.sin(th)], dtype=torch.float64)
    torch.testing.assert_close(leg.forward_kinematics(q), (L + l3) * e_r)
    tau = torch.tensor([0.4, -0.9], dtype=torch.float64)
    want = -((tau[0] - tau[1]) / dL * e_r + (tau[0] + tau[1]) / (L + l3) * e_t)
    force, valid = leg.ground_force(q, tau)
    assert bool(valid)
    torch.testing.assert_close(force, want)


def test_traveler_at_rest_pose():
    """The Traveler (0.1 / 0.2 / 0.05 m) with both proximal links horizontal: toe sqrt(0.2^2 - 0.1^2)
    + 0.05 = 0.2232 m straight below the hip."""
    leg = FiveBarLeg(0.1, 0.2, extension=0.05)
    q = torch.tensor([math.pi / 2, -math.pi / 2], dtype=torch.float64)
    torch.testing.assert_close(leg.forward_kinematics(q),
                               torch.tensor([0.0, -(math.sqrt(0.03) + 0.05)], dtype=torch.float64))


@pytest.mark.parametrize("leg", [FiveBarLeg(0.1, 0.2, extension=0.05),
                                 FiveBarLeg(0.12, 0.25, hip_spacing=0.08, extension=0.03)])
def test_extension_round_trip(leg):
    """(The Jacobian of these legs against finite differences: tests/hardware/test_motor_five_bar.py.)"""
    q = torch.tensor([[0.5, -0.4], [0.9, 0.1], [1.6, -1.5]], dtype=torch.float64)
    on_branch = q[[0, 2]]  # knees out, the branch inverse_kinematics returns
    torch.testing.assert_close(leg.inverse_kinematics(leg.forward_kinematics(on_branch)), on_branch)
    # virtual work: the holding torques of a ground force give back that force
    F = torch.tensor([[1.0, 2.0], [-3.0, 0.5], [0.2, 9.0]], dtype=torch.float64)
    force, _ = leg.ground_force(q, leg.holding_torques(q, F))
    torch.testing.assert_close(force, F)


def test_zero_extension_is_the_plain_leg_and_bad_values_are_refused():
    q = torch.tensor([0.7, -0.3], dtype=torch.float64)
    tau = torch.tensor([0.3, 0.1], dtype=torch.float64)
    a, b = FiveBarLeg(0.1, 0.2), FiveBarLeg(0.1, 0.2, extension=0.0)
    torch.testing.assert_close(a.forward_kinematics(q), b.forward_kinematics(q))
    torch.testing.assert_close(a.ground_force(q, tau)[0], b.ground_force(q, tau)[0])
    with pytest.raises(ValueError, match="extension"):
        FiveBarLeg(0.1, 0.2, extension=-0.01)
