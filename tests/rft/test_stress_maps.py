import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from irft_torch.rft import FourierStressMap, mirror_to_canonical
from irft_torch.rft.stress_maps import GENERIC

P = math.pi


def generic_by_hand(b, g):
    """The expanded generic form of rft_facts.md, written out term by term (independent of the
    table-driven implementation)."""
    az = 0.206 + 0.169 * math.cos(2 * b) + 0.212 * math.sin(2 * b + g) + 0.358 * math.sin(g) \
        + 0.055 * math.sin(-2 * b + g)
    ax = -0.124 * math.cos(2 * b + g) + 0.253 * math.cos(g) + 0.007 * math.cos(-2 * b + g) \
        + 0.088 * math.sin(2 * b)
    return ax, az


@pytest.mark.parametrize(
    "b, g, want",
    [(0.0, P / 2, (0.0, 1.0)), (0.0, 0.0, (0.136, 0.375)), (0.0, -P / 2, (None, -0.25))],
)
def test_generic_check_values(b, g, want):
    a = FourierStressMap.generic()(torch.tensor(b), torch.tensor(g))
    if want[0] is not None:
        assert a[0].item() == pytest.approx(want[0], abs=1e-12)
    assert a[1].item() == pytest.approx(want[1], abs=1e-12)


def test_generic_equals_expanded_formula_on_grid():
    b, g = torch.meshgrid(torch.linspace(-P, P, 37), torch.linspace(-P, P, 41), indexing="ij")
    a = FourierStressMap.generic()(b, g)
    ref = torch.tensor([[generic_by_hand(bi, gi) for bi, gi in zip(rb, rg)]
                        for rb, rg in zip(b.tolist(), g.tolist())])
    torch.testing.assert_close(a, ref, atol=1e-12, rtol=0)


def test_regression_isaaclab_sin_cos_swap():
    # jnskkmhr/IsaacLab swapped sin and cos in alpha_x and got alpha_x(0, pi/2) = 0.224.
    ax = FourierStressMap.generic()(torch.tensor(0.0), torch.tensor(P / 2))[0].item()
    assert abs(ax) < 1e-12
    swapped = -0.124 * math.sin(P / 2) + 0.253 * math.sin(P / 2) + 0.007 * math.sin(P / 2) \
        + 0.088 * math.cos(0.0)
    assert swapped == pytest.approx(0.224)
    assert abs(ax - swapped) > 0.2


def test_regression_c_minus11_uses_cos():
    # qishuny/3D-RFT-wheel used sin for the C_-11 term. Only C_-11 nonzero: alpha_x = cos(-2b+g).
    smap = FourierStressMap({}, {}, {(-1, 1): 1.0}, {})
    b, g = torch.tensor(0.3), torch.tensor(0.2)
    assert smap(b, g)[0].item() == pytest.approx(math.cos(-0.6 + 0.2), abs=1e-14)


def test_scales_and_presets():
    b, g = torch.rand(50) * P - P / 2, torch.rand(50) * P - P / 2
    base = FourierStressMap.generic()(b, g)
    torch.testing.assert_close(FourierStressMap.generic(0.452, 0.417)(b, g),
                               base * torch.tensor([0.452, 0.417]))
    torch.testing.assert_close(FourierStressMap.generic().scaled(2.0, 3.0)(b, g),
                               base * torch.tensor([2.0, 3.0]))
    # zeta of the poppy-seed sets (rft_facts.md): alpha_z(0, pi/2) = 0.254 loose, 0.464 close
    z = lambda s: s(torch.tensor(0.0), torch.tensor(P / 2))[1].item()  # noqa: E731
    assert z(FourierStressMap.poppy_seeds_loose()) == pytest.approx(0.254, abs=1e-12)
    assert z(FourierStressMap.poppy_seeds_close()) == pytest.approx(0.464, abs=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.floats(-10, 10), st.floats(-10, 10))
def test_period_pi_in_beta_and_mirror_identity(b, g):
    smap = FourierStressMap.generic()
    a = smap(torch.tensor(b), torch.tensor(g))
    torch.testing.assert_close(smap(torch.tensor(b + P), torch.tensor(g)), a, atol=1e-12, rtol=0)
    m = smap(torch.tensor(-b), torch.tensor(P - g))
    torch.testing.assert_close(m * torch.tensor([-1.0, 1.0]), a, atol=1e-12, rtol=0)
    bc, gc, sx = mirror_to_canonical(torch.tensor(b), torch.tensor(g))
    assert -P / 2 <= bc.item() < P / 2 and abs(gc.item()) <= P / 2 + 1e-12
    torch.testing.assert_close(smap(bc, gc) * torch.stack([sx, torch.ones(())]), a, atol=1e-12, rtol=0)


def test_mirror_to_canonical_interval_ends():
    """beta lands in [-pi/2, pi/2) even one ulp below -pi/2 (where remainder rounds up to pi); gamma in
    [-pi/2, pi/2] closed: straight down (pi/2) and straight up (-pi/2) are kept, never wrapped or flipped;
    gamma = +-pi (moving toward -x) is canonical 0 with the x sign flipped."""
    below = math.nextafter(-P / 2, -4.0)
    bc, gc, sx = mirror_to_canonical(torch.tensor([below, P / 2, -P / 2, 0.3, 0.3, 0.3, 0.3], dtype=torch.float64),
                                     torch.tensor([0.0, 0.0, 0.0, P / 2, -P / 2, P, -P], dtype=torch.float64))
    assert ((bc >= -P / 2) & (bc < P / 2)).all(), bc.tolist()
    torch.testing.assert_close(bc, torch.tensor([-P / 2, -P / 2, -P / 2, 0.3, 0.3, -0.3, -0.3], dtype=torch.float64))
    torch.testing.assert_close(gc, torch.tensor([0.0, 0.0, 0.0, P / 2, -P / 2, 0.0, 0.0], dtype=torch.float64))
    assert sx.tolist() == [1.0, 1.0, 1.0, 1.0, 1.0, -1.0, -1.0]


def test_not_identities_are_not_claimed():
    # rft_facts.md: alpha_z(-b,-g) != alpha_z(b,g) in general; make sure the form is not symmetric.
    smap = FourierStressMap.generic()
    b, g = torch.tensor(0.4), torch.tensor(1.2)
    assert abs(smap(-b, -g)[1] - smap(b, g)[1]) > 0.1


def test_differentiable_and_broadcasting():
    b = torch.zeros(3, 1, requires_grad=True)
    g = torch.linspace(-1, 1, 4, requires_grad=True)
    a = FourierStressMap.generic()(b, g)
    assert a.shape == (3, 4, 2)
    a.sum().backward()
    # d alpha_z / d gamma at b=0 by hand: 0.212 cos g + 0.358 cos g + 0.055 cos g
    # d alpha_x / d gamma at b=0: 0.124 sin g - 0.253 sin g - 0.007 sin g
    want = (0.625 * torch.cos(g) - 0.136 * torch.sin(g)).detach() * 3
    torch.testing.assert_close(g.grad, want)


def test_float32_follows_input():
    a = FourierStressMap.generic()(torch.zeros(2, dtype=torch.float32), torch.zeros(2, dtype=torch.float32))
    assert a.dtype == torch.float32


def test_bad_coefficient_index():
    with pytest.raises(ValueError, match="m=2"):
        FourierStressMap({(2, 0): 1.0}, {}, {}, {})
    assert set(GENERIC) == {"A", "B", "C", "D"}


def test_non_finite_scales_and_coefficients_are_errors():
    # the constructor rejects a NaN scale; scaled() and the coefficient tables must too (a NaN map is no map)
    with pytest.raises(ValueError, match="scale_x"):
        FourierStressMap.generic().scaled(float("nan"), 1.0)
    with pytest.raises(ValueError, match="scale_z"):
        FourierStressMap.generic().scaled(1.0, float("inf"))
    with pytest.raises(ValueError, match=r"m=0, n=0"):
        FourierStressMap({(0, 0): float("nan")}, {}, {}, {})



def test_docstring_example_runs_as_written():
    """The class docstring's example, run under torch's own default dtype (float32, what a user sees); it
    showed float64 output for float32 inputs (the map follows the inputs' dtype)."""
    import doctest

    import irft_torch.rft.stress_maps as mod

    (test,) = [t for t in doctest.DocTestFinder().find(mod.FourierStressMap, module=mod)
               if t.name == "FourierStressMap"]
    report = []
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        result = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE).run(test, out=report.append)
    finally:
        torch.set_default_dtype(old)
    assert result.failed == 0 and result.attempted >= 3, "".join(report)
