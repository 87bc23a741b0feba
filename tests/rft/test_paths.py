import math

import pytest
import torch

from irft_torch.rft import CToe, pose_path, rectangle_path, rotating_leg_path, segment_kinematics, spline_path
from irft_torch.rft.paths import Path


def test_rectangle_path_corners_and_speed():
    p = rectangle_path(0.05, 0.4, 0.05, start=(-0.2, 0.0), n_steps=501, speed=0.02)
    torch.testing.assert_close(p.position[0], torch.tensor([-0.2, 0.0]))
    torch.testing.assert_close(p.position[-1], torch.tensor([0.2, 0.0]))
    assert p.position[:, 1].min().item() == pytest.approx(-0.05)
    torch.testing.assert_close(p.velocity.norm(dim=1), torch.full((501,), 0.02))
    assert p.length.item() == pytest.approx(0.5)
    assert p.time[-1].item() == pytest.approx(0.5 / 0.02)


def test_spline_passes_through_control_points_and_is_natural():
    cps = [(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)]
    p = spline_path(cps, n_steps=4001)
    for x, z in cps:
        i = (p.position[:, 0] - x).abs().argmin()
        assert p.position[i, 1].item() == pytest.approx(z, abs=1e-5)
    # independent reference: scipy's natural cubic spline
    from scipy.interpolate import CubicSpline

    cs = CubicSpline([c[0] for c in cps], [c[1] for c in cps], bc_type="natural")
    xs = p.position[:, 0].numpy()
    torch.testing.assert_close(p.position[:, 1], torch.tensor(cs(xs)), atol=1e-12, rtol=0)
    slope = torch.tensor(cs(xs, 1))
    torch.testing.assert_close(p.velocity[:, 1] / p.velocity[:, 0], slope, atol=1e-10, rtol=0)
    # evenly spaced in arc length (to the dense parametrization's accuracy)
    steps = p.position.diff(dim=0).norm(dim=1)
    assert (steps.max() - steps.min()) / steps.mean() < 1e-3


def test_spline_differentiable_in_control_points():
    cps = torch.tensor([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], requires_grad=True)
    p = spline_path(cps, n_steps=50)
    p.position[:, 1].sum().backward()
    assert torch.isfinite(cps.grad).all() and cps.grad[:, 1].abs().sum() > 0


def test_velocity_finite_differences_match_rigid_body():
    """Segment velocity v + omega x r against finite differences of segment positions."""
    toe = CToe(0.03, 0.01, 8).shifted(0.0, -0.06)
    t = torch.linspace(0, 2, 2001)
    x, z, h = 0.05 * torch.sin(t), -0.02 * t**2, 0.7 * t + 0.3 * torch.sin(3 * t)
    paths = [
        Path(t, torch.stack([x, z], -1), h,
             torch.stack([0.05 * torch.cos(t), -0.04 * t], -1), 0.7 + 0.9 * torch.cos(3 * t)),
        rotating_leg_path(hip=(0.0, 0.05), sweep=2.0, angular_speed=1.0, n_steps=2001),
    ]
    for path in paths:
        k = segment_kinematics(toe, path)
        dt = path.time.diff()[:, None, None]
        fd = (k.position[2:] - k.position[:-2]) / (dt[1:] + dt[:-1])
        torch.testing.assert_close(k.velocity[1:-1], fd, atol=1e-6, rtol=1e-5)


def test_pose_path_rates():
    t = torch.linspace(0, 1, 1001) ** 1.5  # non-uniform steps
    p = pose_path(t, torch.sin(t), t**2, heading=torch.remainder(2 * t + 3.0, 2 * math.pi) - math.pi)
    torch.testing.assert_close(p.velocity[1:-1, 0], torch.cos(t)[1:-1], atol=1e-5, rtol=0)
    torch.testing.assert_close(p.velocity[1:-1, 1], 2 * t[1:-1], atol=1e-5, rtol=0)
    torch.testing.assert_close(p.angular_velocity, torch.full_like(t, 2.0), atol=1e-6, rtol=0)


def test_rotating_leg_direction():
    # clockwise: a toe below the hip sweeps toward -x
    toe = CToe(0.02, 0.01, 4).shifted(0.0, -0.05)
    k = segment_kinematics(toe, rotating_leg_path(direction="cw", n_steps=3))
    assert (k.velocity[0, :, 0] < 0).all()
    k = segment_kinematics(toe, rotating_leg_path(direction="ccw", n_steps=3))
    assert (k.velocity[0, :, 0] > 0).all()


def test_bad_paths():
    with pytest.raises(ValueError, match="at least 2 poses"):
        pose_path([0.0], [0.0], [0.0])
    with pytest.raises(ValueError, match="x contains NaN"):
        pose_path([0.0, 1.0], [0.0, float("nan")], [0.0, 0.0])
    with pytest.raises(ValueError, match="strictly increasing x"):
        spline_path([(0.1, 0.0), (0.0, -0.05)])
    with pytest.raises(ValueError, match="metres"):
        spline_path([(-20, 0), (-10, -5), (10, 0), (20, -5)])  # centimetres
    with pytest.raises(ValueError, match="penetration"):
        rectangle_path(penetration=float("inf"))
    with pytest.raises(ValueError, match="n_steps"):
        rectangle_path(n_steps=1)
    with pytest.raises(ValueError, match="direction"):
        rotating_leg_path(direction="left")


def test_course_path_straight_and_circular_against_closed_forms():
    from irft_torch.rft import course_path

    p = course_path(-math.pi / 4, 0.3, start=(0.1, 0.0), n_steps=31, speed=0.05)
    torch.testing.assert_close(p.position[-1], torch.tensor([0.1 + 0.3 / math.sqrt(2), -0.3 / math.sqrt(2)]))
    torch.testing.assert_close(p.velocity.norm(dim=1), torch.full((31,), 0.05))
    assert p.time[-1].item() == pytest.approx(0.3 / 0.05)
    # a course turning at a constant rate (two knots: a linear spline) is a circle of radius 1/kappa
    psi0, kappa, L = -math.pi / 2, 8.0, 0.35
    p = course_path([psi0, psi0 + kappa * L], L, start=(0.0, 0.0), n_steps=71, substeps=16)
    s = torch.linspace(0, L, 71)
    x = (torch.sin(psi0 + kappa * s) - math.sin(psi0)) / kappa
    z = -(torch.cos(psi0 + kappa * s) - math.cos(psi0)) / kappa
    torch.testing.assert_close(p.position, torch.stack([x, z], -1), atol=1e-6, rtol=0)
    assert p.length.item() == pytest.approx(L, rel=1e-3)  # chords of an arc, 70 of them


def test_course_path_heading_rate_and_gradient():
    from irft_torch.rft import course_path

    heading = torch.tensor([0.0, 0.4, -0.2])
    p = course_path([-1.0, 0.0, 0.5], 0.4, heading=heading, n_steps=401, speed=0.02)
    fd = pose_path(p.time, p.position[:, 0], p.position[:, 1], p.heading)  # finite differences in time
    torch.testing.assert_close(p.angular_velocity[5:-5], fd.angular_velocity[5:-5], atol=2e-5, rtol=1e-3)
    torch.testing.assert_close(p.velocity[5:-5], fd.velocity[5:-5], atol=1e-6, rtol=1e-4)
    course = torch.tensor([-1.0, 0.0, 0.5], requires_grad=True)
    end = course_path(course, 0.4, n_steps=21).position[-1, 1]
    (g,) = torch.autograd.grad(end, course)
    h = 1e-6
    for k in range(3):
        e = torch.zeros(3)
        e[k] = h
        fd_k = (course_path(course.detach() + e, 0.4, n_steps=21).position[-1, 1]
                - course_path(course.detach() - e, 0.4, n_steps=21).position[-1, 1]) / (2 * h)
        assert g[k].item() == pytest.approx(fd_k.item(), rel=1e-6)
    with pytest.raises(ValueError, match="length"):
        course_path([0.0], 40.0)
    with pytest.raises(ValueError, match="course contains NaN"):
        course_path([0.0, float("nan")], 0.2)


def test_rotating_leg_angles_in_degrees_warn():
    with pytest.warns(UserWarning, match="start_angle=90.0 rad"):
        rotating_leg_path(start_angle=90.0)
    with pytest.warns(UserWarning, match="sweep=180.0 rad"):
        rotating_leg_path(sweep=180.0)
    with pytest.raises(ValueError, match="start_angle must be a finite angle"):
        rotating_leg_path(start_angle=float("inf"))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = rotating_leg_path(start_angle=-math.pi / 2, sweep=6 * math.pi, n_steps=50)  # three turns: a leg's strides
    assert p.heading[-1].item() == pytest.approx(-math.pi / 2 - 6 * math.pi)
