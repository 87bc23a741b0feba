"""The causal moving average against the offline zero-phase one (pipeline.zero_phase_filter, scipy's
uniform_filter1d): the same values, each published ``(window - 1) / 2`` samples late."""

import numpy as np
import pytest

from irft_torch.hardware.live.causal_filter import CausalMovingAverage
from irft_torch.hardware.pipeline import ForceTrace, zero_phase_filter


def offline(force, valid, window):
    T = len(force)
    f = force.copy()
    f[~valid] = np.nan
    trace = ForceTrace(np.arange(T) * 1e-3, np.zeros((T, 2)), np.zeros((T, 2)), np.zeros((T, 2)), f, valid.copy())
    return zero_phase_filter(trace, window).force


def live(force, valid, window):
    filt = CausalMovingAverage(window)
    out, lags = [], []
    for k in range(len(force)):
        for s in filt.push(k * 1e-3, force[k], bool(valid[k]), payload=k):
            out.append(s)
            lags.append(k - s.payload)
    tail = filt.flush()
    return out + tail, lags


@pytest.mark.parametrize("window", [1, 3, 5, 9])
def test_equals_zero_phase_filter_with_masked_stretches(window):
    rng = np.random.default_rng(window)
    T = 400
    force = np.cumsum(rng.normal(size=(T, 2)), 0)
    valid = np.ones(T, bool)
    valid[:3] = False  # masked at the start, inside (short and long stretches) and at the end
    valid[50:52] = False
    valid[200:260] = False
    valid[-4:] = False
    out, lags = live(force, valid, window)
    ref = offline(force, valid, window)
    assert [s.payload for s in out] == list(range(T))  # every sample once, in order
    got = np.array([s.value for s in out])
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    np.testing.assert_allclose(got[valid], ref[valid], atol=1e-12, rtol=0)
    assert not any(s.valid for s, v in zip(out, valid) if not v)
    # a valid sample's value comes (window - 1) / 2 samples after it, except next to a masked stretch
    h = (window - 1) // 2
    steady = [lag for lag, s in zip(lags, out) if 260 + window < s.payload < T - 10]
    assert set(steady) == {h}


def test_short_stream_and_nothing_valid():
    f = CausalMovingAverage(5)
    out = f.push(0.0, [1.0, 2.0]) + f.push(1e-3, [3.0, 4.0]) + f.flush()
    np.testing.assert_allclose([s.value for s in out], [[1.8, 2.8], [2.2, 3.2]])  # nearest padding both ends
    g = CausalMovingAverage(3)
    assert g.push(0.0, [0, 0], valid=False) == []
    (s,) = g.flush()
    assert not s.valid and np.isnan(s.value).all()


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="window must be an odd"):
        CausalMovingAverage(4)
    with pytest.raises(ValueError, match="value must be finite"):
        CausalMovingAverage(3).push(0.0, [np.nan, 0.0])
