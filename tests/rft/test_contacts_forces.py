import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from irft_torch.rft import (
    Contacts,
    CToe,
    FourierStressMap,
    IToe,
    PolylineToe,
    contacts,
    forces,
    pose_path,
    rectangle_path,
    rotating_leg_path,
    spline_path,
)
from irft_torch.rft.paths import Path

P = math.pi
GEN = FourierStressMap.generic()


def straight(v, depth=0.03, n=5):
    """A horizontal body at constant depth moving with velocity v."""
    t = torch.linspace(0, 1, n)
    pos = torch.stack([t * v[0], -depth + t * v[1]], -1)
    return Path(t, pos, torch.zeros(n), torch.tensor(v).expand(n, 2), torch.zeros(n))


def test_plate_pushed_down_by_hand():
    # plate 2 cm x 0.8 cm at 3 cm depth moving straight down: F = (0, 1.0 * 3 * 1.6) N
    toe = IToe(0.02, 0.008, n_segments=5)
    f = forces(GEN, contacts(toe, straight((0.0, -0.01), n=2)))
    torch.testing.assert_close(f[0], torch.tensor([0.0, 4.8]), atol=1e-12, rtol=0)


def test_plate_dragged_both_ways_by_hand():
    toe = IToe(0.02, 0.008, n_segments=5)
    zeta = 0.33
    smap = FourierStressMap.generic(zeta, zeta)
    w = 3.0 * 1.6
    right = forces(smap, contacts(toe, straight((0.02, 0.0))))
    left = forces(smap, contacts(toe, straight((-0.02, 0.0))))
    torch.testing.assert_close(right[0], torch.tensor([-0.136 * zeta * w, 0.375 * zeta * w]))
    torch.testing.assert_close(left[0], torch.tensor([+0.136 * zeta * w, 0.375 * zeta * w]))


def test_left_down_45_is_canonical_plus_quarter_pi():
    c = contacts(IToe(0.02, 0.008, tilt=0.3, n_segments=1), straight((-0.01, -0.01)))
    assert c.gamma[0, 0].item() == pytest.approx(P / 4)
    assert c.beta[0, 0].item() == pytest.approx(-0.3)
    assert c.weight_x[0, 0].item() > 0  # x contribution flipped


def test_mirrored_motion_equals_direct_formula():
    """Moving toward -x: the canonical-square force equals the uncanonical formula
    F = (-w alpha_x, w alpha_z) at the raw angles (beta, atan2(-v_z, v_x)) over the full circle."""
    toe = IToe(0.02, 0.008, tilt=0.4, n_segments=1)
    v = (-0.01, -0.004)
    c = contacts(toe, straight(v))
    a = GEN(torch.tensor(0.4), torch.tensor(math.atan2(-v[1], v[0])))  # raw (beta, gamma)
    w = c.weight_z[0, 0]
    torch.testing.assert_close(forces(GEN, c)[0], torch.stack([-w * a[0], w * a[1]]))


def test_segment_above_surface_adds_nothing():
    toe = IToe(0.02, 0.008, n_segments=4)
    c = contacts(toe, straight((0.01, 0.0), depth=-0.01))  # 1 cm above
    assert (c.weight_z == 0).all() and (forces(GEN, c) == 0).all()
    tilted = IToe(0.04, 0.008, tilt=P / 2, n_segments=4)  # vertical plate, half submerged
    c = contacts(tilted, straight((0.01, 0.0), depth=0.0))
    assert (c.weight_z[:, 2:] == 0).all() and (c.weight_z[:, :2] > 0).all()


def test_vertical_plate_beta_is_minus_half_pi_whatever_its_rounding():
    """A vertical plate is beta = -pi/2 (the interval [-pi/2, pi/2) is half-open), also when its tangent
    comes out of a rotation with a -1e-16 x component (tilt 3 pi/2, or tilt pi/2 at heading pi): same
    cell of the coverage grid, same angle pair, not +pi/2."""
    straight_d = straight((0.01, 0.0), n=2)
    turned = Path(straight_d.time, straight_d.position, torch.full((2,), P), straight_d.velocity,
                  straight_d.angular_velocity)
    for toe, path in ((IToe(0.02, 0.008, tilt=3 * P / 2, n_segments=1), straight_d),
                      (IToe(0.02, 0.008, tilt=P / 2, n_segments=1), turned),
                      (IToe(0.02, 0.008, tilt=-P / 2, n_segments=1), straight_d)):
        c = contacts(toe.to(torch.float64), path)
        torch.testing.assert_close(c.beta, torch.full_like(c.beta, -P / 2), atol=1e-15, rtol=0)


def test_ctoe_weights_sum_to_depth_times_area_by_hand():
    R, W, M, d0 = 0.02, 0.008, 2, 0.05
    toe = CToe(R, W, M)  # two chords from (-R, R) to (0, 0) to (R, R)
    c = contacts(toe, straight((0.0, -0.01), depth=d0, n=2))
    chord = math.sqrt(2) * R
    centre_depth = d0 - R / 2  # both chord mid-points are R/2 above the origin
    want = 2 * (centre_depth * 100) * (chord * W * 1e4)
    assert c.weight_z[0].sum().item() == pytest.approx(want, rel=1e-12)
    # many segments converge to the integral of depth over the arc (centre R above the origin):
    # W * int_{-pi}^{0} (d0 - R - R sin phi) R dphi = W * R * (pi d0 - pi R + 2 R)
    fine = contacts(CToe(R, W, 400), straight((0.0, -0.01), depth=d0, n=2))
    integral = (W * 1e2) * (R * 1e2) * (P * d0 * 1e2 - P * R * 1e2 + 2 * R * 1e2)
    assert fine.weight_z[0].sum().item() == pytest.approx(integral, rel=1e-4)


def test_canonical_square_on_all_path_kinds():
    toe = CToe(0.02, 0.008, 10)
    paths = [rectangle_path(), spline_path([(-0.2, 0), (-0.1, -0.05), (0.1, 0), (0.2, -0.05)]),
             rotating_leg_path(hip=(0.0, 0.02)), pose_path(torch.linspace(0, 1, 50),
                                                           torch.linspace(0.1, -0.1, 50),
                                                           -0.02 * torch.ones(50), torch.linspace(0, 3, 50))]
    for path in paths:
        c = contacts(toe.shifted(0, -0.03) if path.velocity.abs().sum() == 0 else toe, path)
        assert (c.beta >= -P / 2).all() and (c.beta < P / 2).all()
        assert (c.gamma.abs() <= P / 2 + 1e-12).all()
        assert (c.weight_z >= 0).all() and (c.weight_x.abs() == c.weight_z).all()
        assert c.weight_z.sum() > 0


def test_contacts_validation():
    z = torch.zeros(3, 2)
    with pytest.raises(ValueError, match="weight_z has shape"):
        Contacts(z, z, z, torch.zeros(3, 3))
    with pytest.raises(ValueError, match="gamma contains NaN"):
        Contacts(z, torch.full((3, 2), float("nan")), z, z)
    with pytest.raises(ValueError, match="weight_z must be >= 0"):
        Contacts(z, z, z, -torch.ones(3, 2))
    with pytest.raises(TypeError, match="toe must be a Toe"):
        contacts("C", rectangle_path())
    # a NaN min_speed made every segment "not moving": all forces silently 0; a negative one gave
    # segments at rest a direction (gamma 0) and a force
    for bad in (float("nan"), -1e-3):
        with pytest.raises(ValueError, match="min_speed"):
            contacts(IToe(0.02, 0.008), rectangle_path(), min_speed=bad)


def test_contacts_helpers():
    c = contacts(CToe(0.02, 0.008, 4), rectangle_path(n_steps=20))
    both = Contacts.cat([c, c[:5].pad_segments(6)])
    assert both.shape == (25, 6) and len(both) == 25
    torch.testing.assert_close(forces(GEN, both)[20:], forces(GEN, c)[:5])
    # .to: self when nothing changes (as Tensor.to), a converted copy otherwise, the original untouched
    assert c.to(c.beta.dtype) is c and c.to(device=c.beta.device) is c
    c32 = c.to(torch.float32)
    assert c32 is not c and c32.weight_z.dtype == torch.float32 and c.weight_z.dtype == torch.float64
    torch.testing.assert_close(c32.weight_z, c.weight_z.float())


@settings(max_examples=40, deadline=None)
@given(
    radius=st.floats(0.005, 0.1), n=st.integers(1, 12), scale=st.floats(0.05, 5.0),
    pts=st.lists(st.tuples(st.floats(-0.05, 0.05), st.floats(-0.06, 0.02)), min_size=2, max_size=5),
    kind=st.sampled_from(["C", "I", "poly"]),
)
def test_property_finite_nonnegative_and_linear_in_scale(radius, n, scale, pts, kind):
    xs = sorted({round(p[0], 4) for p in pts})
    if len(xs) < 2:
        xs = [-0.05, 0.05]
    cps = [(x, z) for x, (_, z) in zip(xs, pts + pts)]
    toe = {"C": lambda: CToe(radius, 0.01, n), "I": lambda: IToe(radius, 0.01, 0.3, n),
           "poly": lambda: PolylineToe([(0, 0), (radius, -radius / 2), (2 * radius, 0)], 0.01, n)}[kind]()
    c = contacts(toe, spline_path(cps, n_steps=30))
    for v in c.as_dict().values():
        assert torch.isfinite(v).all()
    assert (c.weight_z >= 0).all()
    f1 = forces(GEN, c)
    fs = forces(FourierStressMap.generic(scale, scale), c)
    torch.testing.assert_close(fs, scale * f1, atol=1e-10, rtol=1e-10)


def test_contacts_differentiable_in_toe_and_path():
    cps = torch.tensor([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], requires_grad=True)
    f = forces(GEN, contacts(CToe(0.02, 0.008, 10), spline_path(cps, n_steps=40)))
    f.sum().backward()
    assert torch.isfinite(cps.grad).all() and cps.grad.abs().sum() > 0
