"""Probes, workspace bounds and the random equal-length library."""

import math

import pytest
import torch

from irft_torch.rft import CToe, IToe, Probe, ProbeBounds, course_path, random_probes


def test_bounds_violation_by_hand():
    b = ProbeBounds(max_depth=0.05, max_height=0.01, x_range=(-0.1, 0.1), tilt_range=(-0.5, 0.5))
    inside = course_path(-math.pi / 2, 0.04, start=(0.0, 0.0), n_steps=5)
    assert b.contains(inside) and b.violation(inside).item() == 0.0
    deep = course_path(-math.pi / 2, 0.07, start=(0.0, 0.0), n_steps=8)  # z = 0, -0.01, ..., -0.07
    want = sum(max(0.0, 0.01 * k - 0.05) ** 2 for k in range(8))
    assert not b.contains(deep)
    assert b.violation(deep).item() == pytest.approx(want, rel=1e-9)
    tilted = course_path(0.0, 0.05, start=(0.0, -0.01), heading=0.8, n_steps=3)
    assert b.violation(tilted).item() == pytest.approx(3 * 0.3**2, rel=1e-9)
    with pytest.raises(ValueError, match="max_depth"):
        ProbeBounds(max_depth=-0.1)
    with pytest.raises(ValueError, match="x_range"):
        ProbeBounds(x_range=(0.2, -0.2))


def test_random_probes_are_equal_length_inside_bounds_and_reproducible():
    toes = {"I": IToe(0.02, 0.008), "C": CToe(0.02, 0.008, opening="left")}
    b = ProbeBounds(max_depth=0.05, x_range=(-0.2, 0.2))
    probes = random_probes(toes, 4, 0.3, bounds=b, n_steps=80, seed=7)
    assert len(probes) == 8 and probes[0].name.startswith("I #0") and probes[4].name.startswith("C #0")
    for p in probes:
        assert b.contains(p.path)
        assert p.length == pytest.approx(0.3, rel=2e-3)  # the chord length of samples of a 0.3 m path
        assert (p.path.position[:, 1] < 0).double().mean() >= 0.6
        assert p.contacts().shape == (80, 10)
        rebuilt = Probe.from_course(p.toe, **p.spec)
        torch.testing.assert_close(rebuilt.path.position, p.path.position)
    again = random_probes(toes, 4, 0.3, bounds=b, n_steps=80, seed=7)
    torch.testing.assert_close(again[5].path.position, probes[5].path.position)
    with pytest.raises(RuntimeError, match="widen the bounds"):
        random_probes(toes, 1, 0.3, bounds=ProbeBounds(max_depth=0.001, x_range=(-0.01, 0.01)), max_tries=5)
