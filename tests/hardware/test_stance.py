"""Stance onset and end from the stated surface or the force, with the margin samples the contacts need."""

import numpy as np
import pytest

from irft_torch.hardware.live.stance import StanceDetector


def feed(det, z, fz=None, valid=None):
    out = []
    for k in range(len(z)):
        f = (0.0, 0.0 if fz is None else fz[k])
        out += det.push(k * 1e-3, (0.0, z[k]), f, True if valid is None else bool(valid[k]), arrival=float(k))
    return out


def test_surface_stances_are_the_runs_below_the_surface():
    z = np.array([0.01, 0.0, -0.01, -0.02, -0.01, 0.0, 0.02, 0.03, -0.005, -0.001, 0.01, 0.02])
    det = StanceDetector("surface", lowest=-0.005)  # the toe's lowest point 5 mm below its reference
    got = feed(det, z)
    in_contact = z - 0.005 < 0  # independent: where the lowest point is below z = 0
    runs = [(s, e) for s, e in zip(*[np.flatnonzero(np.diff(np.r_[0, in_contact.astype(int), 0]) == d)
                                      for d in (1, -1)])]
    assert [(int(round(s.start / 1e-3)), int(round(s.end / 1e-3)) + 1) for s in got] == runs
    for s, (a, b) in zip(got, runs):
        assert s.first == 1 and s.last - s.first == b - a  # one margin sample before, one after
        np.testing.assert_allclose(s.time, np.arange(a - 1, b + 1) * 1e-3)
        assert s.arrival[-1] == b  # the sample that closed it


def test_force_mode_hysteresis_and_masked_samples():
    fz = np.array([0, 0.5, 1.5, 0.8, 0.6, 0.4, 0.3, 2.0, 2.0, 0.1, 0.0])
    valid = np.ones(len(fz), bool)
    valid[3] = False
    det = StanceDetector("force", threshold=1.0)
    got = feed(det, np.zeros(len(fz)), fz, valid)
    # onset above 1 N, end below 0.5 N: samples 2..4 (3 masked, not in the arrays) and 7..8
    assert [(s.start, s.end, s.masked) for s in got] == [(2e-3, 4e-3, 1), (7e-3, 8e-3, 0)]


def test_reset_drops_the_stance_in_progress():
    det = StanceDetector("surface")
    feed(det, np.array([0.01, -0.01, -0.02]))
    assert det.in_stance
    s = det.reset()
    assert s is not None and s.n_samples == 2 and not det.in_stance
    with pytest.raises(ValueError, match="mode must be"):
        StanceDetector("depth")
