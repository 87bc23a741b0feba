"""rft.force_checks: measured forces against the generic map's on the same contacts (units two-sided,
signs, swapped columns), each finding checked on forces made by hand from a known map."""

import pytest
import torch

from irft_torch import rft
from irft_torch.rft.force_checks import compare_with_generic, force_faults


@pytest.fixture(scope="module")
def gait():
    torch.set_default_dtype(torch.float64)
    c = rft.contacts(rft.CToe(0.02, 0.008), rft.spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)],
                                                            n_steps=200))
    return c, rft.forces(rft.FourierStressMap.generic(1.0, 1.5), c)


def test_a_scaled_generic_medium_is_its_scale(gait):
    """F = generic(1, 1.5) forces: scale (1, 1.5) and cosine 1 exactly; loose poppy seeds (a measured
    medium, a quarter of the generic map) pass too."""
    c, f = gait
    cmp = compare_with_generic(c, f)
    torch.testing.assert_close(cmp.scale, torch.tensor([1.0, 1.5]))
    torch.testing.assert_close(cmp.cos, torch.ones(2))
    assert force_faults(c, f) == []
    assert force_faults(c, rft.forces(rft.FourierStressMap.poppy_seeds_loose(), c)) == []


@pytest.mark.parametrize("change, kind, text", [
    (lambda f: -f, "sign", "both axes have the wrong sign"),
    (lambda f: f * torch.tensor([1.0, -1.0]), "sign", "F_z has the wrong sign"),
    (lambda f: f * torch.tensor([-1.0, 1.0]), "sign", "F_x has the wrong sign"),
    (lambda f: f.flip(-1), "swapped", "columns look swapped"),
    (lambda f: 1000 * f, "large", "1.5e+03x what the generic"),
    (lambda f: f / 1000, "small", "0.0015x what the generic"),
    (lambda f: 0 * f, "small", "zero in every sample in contact"),
], ids=["negated", "z-negated", "x-negated", "swapped", "mN", "kN", "zero"])
def test_each_slip_is_named(gait, change, kind, text):
    c, f = gait
    faults = force_faults(c, change(f))
    assert faults and faults[0].kind == kind and text in faults[0].finding, [str(x) for x in faults]


def test_weights_in_the_wrong_unit_are_named(gait):
    """cm^3 read as m^3 (1e-6x) makes the forces look 1e6x too large; as mm^3 (1000x) 1000x too small."""
    c, f = gait
    m3 = rft.Contacts(c.beta, c.gamma, c.weight_x * 1e-6, c.weight_z * 1e-6)
    mm3 = rft.Contacts(c.beta, c.gamma, c.weight_x * 1e3, c.weight_z * 1e3)
    (big,), (small,) = force_faults(m3, f), force_faults(mm3, f)
    assert big.kind == "large" and "1.5e+06x" in big.finding and "m^3" in big.guess
    assert small.kind == "small" and "0.0015x" in small.finding and "mm^3" in small.guess


def test_forces_where_the_toe_is_out_of_the_sand(gait):
    """A constant 5 N (gravity on the leg, no air run subtracted) where the stated toe is above the sand."""
    c, f = gait
    out = ~((c.weight_x != 0) | (c.weight_z != 0)).any(-1)
    assert out.sum() >= 3
    g = f.clone()
    g[out, 1] = 5.0
    assert any(x.kind == "outside" for x in force_faults(c, g))
