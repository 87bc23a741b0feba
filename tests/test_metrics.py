"""Metrics on hand-made cases."""

import math

import pytest
import torch

from irft_torch import metrics as M
from irft_torch.rft import Contacts


def test_perfect_estimate():
    t = torch.linspace(0, 1, 11)
    assert M.rmse(t, t) == 0 and M.mae(t, t) == 0
    assert M.r2(t, t) == 1 and M.pearson(t, t) == pytest.approx(1)
    assert M.acr_percent(t, t) == 100 and M.rmse_percent(t, t) == 0


def test_constant_offset():
    t = torch.linspace(0, 2, 5)  # range 2, values 0, .5, 1, 1.5, 2; var (ss_tot) = 2.5
    e = t + 0.3
    assert M.rmse(e, t) == pytest.approx(0.3) and M.mae(e, t) == pytest.approx(0.3)
    assert M.r2(e, t) == pytest.approx(1 - 5 * 0.09 / 2.5)
    assert M.pearson(e, t) == pytest.approx(1.0)  # an offset keeps the correlation
    assert M.rmse_percent(e, t) == pytest.approx(15.0) and M.mae_percent(e, t) == pytest.approx(15.0)
    assert M.acr_percent(e, t) == 0.0  # 0.3 > 5 % of range 2 = 0.1
    assert M.acr_percent(t + 0.05, t) == 100.0


def test_known_correlation_and_sign():
    t = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert M.pearson(-t, t) == pytest.approx(-1.0)
    e = torch.tensor([1.0, 3.0, 2.0, 4.0])  # by hand: sum of products 4, norms sqrt 5 each: r = 0.8
    assert M.pearson(e, t) == pytest.approx(0.8)
    assert M.r2(torch.full((4,), 2.5), t) == pytest.approx(0.0)  # predicting the mean


def test_calibration():
    truth = torch.zeros(1000)
    mean = torch.linspace(-3, 3, 1000)
    want = (mean.abs() <= 1.959964).double().mean().item()
    assert M.calibration(mean, torch.ones(1000), truth) == pytest.approx(want)


def test_coverage_and_redundancy_by_hand():
    b = torch.tensor([[0.0, 0.0], [0.0, 1.0], [0.001, 0.0]])
    g = torch.tensor([[0.0, 0.0], [0.5, 0.5], [0.0, -1.0]])
    w = torch.tensor([[1.0, 1.0], [1.0, 0.0], [1.0, 1.0]])  # one segment out of contact
    c = Contacts(b, g, -w, w)
    # in contact: (0,0) x2, (0,.5), (.001,0) [same cell as (0,0)], (0,-1): 3 distinct cells of 5
    assert M.redundancy(c, n_cells=10) == pytest.approx(1 - 3 / 5)
    assert M.coverage_area(c, n_cells=10) == pytest.approx(3 / 100)


def test_bad_metric_input():
    with pytest.raises(ValueError, match="constant"):
        M.r2(torch.ones(3), torch.ones(3))
    with pytest.raises(ValueError, match="NaN"):
        M.rmse(torch.tensor([math.nan]), torch.tensor([0.0]))
    with pytest.raises(ValueError, match="estimate has 2 values, truth has 3"):
        M.mae(torch.ones(2), torch.ones(3))


def test_integrated_autocorrelation_time_of_ar1():
    import numpy as np

    rng = np.random.default_rng(0)
    for phi in (0.0, 0.8):
        e = rng.standard_normal(100_000)
        x = np.empty_like(e)
        x[0] = e[0]
        for i in range(1, len(e)):  # AR(1): tau = (1 + phi) / (1 - phi)
            x[i] = phi * x[i - 1] + e[i]
        want = (1 + phi) / (1 - phi)
        assert M.integrated_autocorrelation_time(x) == pytest.approx(want, rel=0.1)
    with pytest.raises(ValueError, match="at least 4"):
        M.integrated_autocorrelation_time([1.0, 2.0])
    with pytest.raises(ValueError, match="NaN"):
        M.integrated_autocorrelation_time([1.0, float("nan"), 2.0, 3.0, 4.0])
    # (T, 2) residuals are two series: flattened they interleaved x and z into one (a silent number);
    # a window <= 0 or NaN stopped the sum at lag 1 or never (tau 1): both are errors now
    two = np.stack([x, rng.standard_normal(len(x))], -1)
    with pytest.raises(ValueError, match="one series"):
        M.integrated_autocorrelation_time(two)
    for window in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="window"):
            M.integrated_autocorrelation_time(x, window=window)


def test_bad_cell_count_is_an_error():
    """n_cells is the grid's cells per side: -2 gave coverage 0.25 and 2.5 gave 0.16 (by hand: one segment
    in a 2.5 x 2.5 "grid"), silently; 0 was a ZeroDivisionError naming nothing."""
    b = torch.tensor([[0.0, 0.5]])
    c = Contacts(b, b.clone(), torch.ones(1, 2), torch.ones(1, 2))
    assert M.coverage_area(c, 2) == pytest.approx(1 / 4)  # (0, 0) and (0.5, 0.5) share the cell [0, pi/2)^2
    for n in (-2, 0, 2.5):
        for f in (M.coverage_area, M.redundancy):
            with pytest.raises(ValueError, match="n_cells"):
                f(c, n)


def test_definitions_written_beside_the_tables():
    """The report and docs/metrics.md define ACR% as |e| <= 5 % of the truth's range (inclusive),
    calibration with mean +- 1.96 std, coverage over 50 x 50 cells; check those exact edges by hand."""
    t = torch.tensor([0.0, 10.0])  # range 10: the ACR tolerance is 0.5
    assert M.acr_percent(t + torch.tensor([0.5, 0.0]), t) == 100.0  # exactly on the edge counts
    assert M.acr_percent(t + torch.tensor([0.5001, 0.0]), t) == 50.0
    assert M.calibration(torch.tensor([1.95, 1.97]), torch.ones(2), torch.zeros(2)) == 0.5  # 1.96 std
    b = torch.tensor([[-math.pi / 2 + 1e-9, math.pi / 2 - 1e-9]])  # opposite corners of the square
    c = Contacts(b, b.clone(), torch.ones(1, 2), torch.ones(1, 2))
    assert M.coverage_area(c) == pytest.approx(2 / 2500)  # default grid: 50 x 50 cells
    assert M.redundancy(c) == 0.0


def test_calibration_bad_level_or_stddev_is_an_error():
    """A level outside (0, 1) (e.g. 95, a percent, as the module's other metrics report) has no central
    interval, and a negative stddev none either: both were a silent share of 0.0 (truth 0.1 sd from the
    mean lies inside any central interval wider than 8 %)."""
    mean, truth = torch.zeros(3), torch.tensor([0.1, -0.1, 0.05])
    assert M.calibration(mean, torch.ones(3), truth, 0.95) == 1.0
    for level in (95.0, 1.5, 0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="level"):
            M.calibration(mean, torch.ones(3), truth, level)
    with pytest.raises(ValueError, match="stddev"):
        M.calibration(mean, -torch.ones(3), truth)


def test_acr_bad_tolerance_is_an_error():
    """ACR%'s tolerance is a share of the truth's range: 5 (a percent, as the metric reports) covered 500 % of
    the range and every point counted (100 %, silently); a negative or NaN one counted none (0 %)."""
    t = torch.tensor([0.0, 5.0, 10.0])
    e = torch.tensor([0.0, 3.0, 10.0])  # errors 0, 2, 0 of range 10: 2/3 within 5 %, all within 20 %
    assert M.acr_percent(e, t, 0.05) == pytest.approx(100 * 2 / 3) and M.acr_percent(e, t, 0.2) == 100.0
    for tol in (5.0, 1.0, 0.0, -0.05, float("nan")):
        with pytest.raises(ValueError, match="tolerance"):
            M.acr_percent(e, t, tol)


def test_percentile_among_counts_ties_half():
    # among 1, 2, 2, 3: 2 has one sample below and two equal -> (1 + 0.5 x 2) / 4 = 0.5; 0 -> 0; 4 -> 1
    s = torch.tensor([1.0, 2.0, 2.0, 3.0])
    assert M.percentile_among(2.0, s).item() == 0.5
    torch.testing.assert_close(M.percentile_among(torch.tensor([0.0, 4.0]), s.expand(2, 4)),
                               torch.tensor([0.0, 1.0], dtype=torch.float64))
    # NaN compares false: a NaN observed was at the 0th percentile and a NaN sample counted as above
    # everything (2.5 among 1, NaN, 3 gave 1/3); no sample gave NaN. All errors now
    with pytest.raises(ValueError, match="observed"):
        M.percentile_among(float("nan"), s)
    with pytest.raises(ValueError, match="samples"):
        M.percentile_among(2.5, torch.tensor([1.0, float("nan"), 3.0]))
    with pytest.raises(ValueError, match="samples"):
        M.percentile_among(2.5, torch.zeros(0))


def test_two_layouts_of_one_size_are_refused():
    """(was: rmse of an (H, W, 2) mean against a (2, H, W) truth compared out of order: 0.29 for 0.10)
    a constant error of 0.1 by hand; (N,) against (N, 1) is one layout."""
    truth = torch.linspace(-1, 1, 5 * 7 * 2).reshape(5, 7, 2)
    est = truth + 0.1
    assert M.rmse(est, truth) == pytest.approx(0.1)
    with pytest.raises(ValueError, match=r"estimate has shape \(5, 7, 2\) but truth \(2, 5, 7\).*"
                                         r"truth.permute\(1, 2, 0\) has the estimate's"):
        M.rmse(est, truth.permute(2, 0, 1))
    assert M.mae(torch.ones(4, 1), torch.zeros(4)) == pytest.approx(1.0)


def _exact_bootstrap(c, r, count):
    """Every resample of R units with replacement (R^R, equally likely): the exact bootstrap distribution of
    RMSE(c) - RMSE(r), one column, as its distinct values (sorted) and the CDF at each."""
    import itertools

    R = len(c)
    vals = []
    for idx in itertools.product(range(R), repeat=R):
        n = sum(count[i] for i in idx)
        vals.append(math.sqrt(sum(c[i] for i in idx) / n) - math.sqrt(sum(r[i] for i in idx) / n))
    vals.sort()
    support, cdf = [], []
    for k, v in enumerate(vals):
        if support and abs(v - support[-1]) < 1e-12:
            cdf[-1] = (k + 1) / len(vals)
        else:
            support.append(v)
            cdf.append((k + 1) / len(vals))
    return support, cdf


def test_rmse_difference_against_the_exact_bootstrap():
    # four runs, one column: sums of squared errors and sample counts; 4^4 = 256 resamples enumerated
    c, r, count = [4.0, 1.0, 9.0, 2.5], [1.0, 2.0, 4.0, 0.5], [2, 1, 3, 1]
    one = lambda level: M.rmse_difference(torch.tensor(c)[:, None], torch.tensor(r)[:, None],  # noqa: E731
                                          count=count, level=level, n_boot=200_000, seed=1)
    d, e = one(0.57), one(0.6)
    assert float(d.difference[0]) == pytest.approx(math.sqrt(sum(c) / 7) - math.sqrt(sum(r) / 7), abs=1e-15)
    support, cdf = _exact_bootstrap(c, r, count)
    for p, got in ((0.215, d.low), (0.8, e.high)):
        k = next(i for i, q in enumerate(cdf) if q >= p)
        # the CDF jumps more than 0.01 away from p on both sides of the exact quantile, so 200 000 resamples
        # put the empirical quantile on that support point
        assert cdf[k] - p > 0.01 and (k == 0 or p - cdf[k - 1] > 0.01)
        assert float(got[0]) == pytest.approx(support[k], abs=1e-12)


def test_rmse_difference_resamples_whole_groups():
    # two groups of two runs: a resample holds group A twice, A and B, or B twice (1/4, 1/2, 1/4), so a 90 %
    # interval runs from the smallest of the three differences to the largest (written out by hand)
    c = torch.tensor([[1.0], [3.0], [8.0], [10.0]])
    r = torch.tensor([[2.0], [2.0], [1.0], [1.0]])
    aa = math.sqrt(4 / 2) - math.sqrt(4 / 2)  # group A: SSE 4 and 4 over 2 samples
    bb = math.sqrt(18 / 2) - math.sqrt(2 / 2)
    ab = math.sqrt(22 / 4) - math.sqrt(6 / 4)
    d = M.rmse_difference(c, r, groups=["A", "A", "B", "B"], level=0.9, n_boot=20_000)
    assert float(d.low[0]) == pytest.approx(min(aa, ab, bb), abs=1e-12)
    assert float(d.high[0]) == pytest.approx(max(aa, ab, bb), abs=1e-12)
    assert bool(d.beyond_spread()[0]) is (min(aa, ab, bb) > 0)
    # each run its own unit: other resamples, another interval
    e = M.rmse_difference(c, r, level=0.9, n_boot=20_000)
    assert (float(e.low[0]), float(e.high[0])) != pytest.approx((min(aa, ab, bb), max(aa, ab, bb)), abs=1e-3)


def test_rmse_difference_of_one_model_with_itself_is_zero():
    sse = torch.rand(9, 2) + 0.1
    d = M.rmse_difference(sse, sse.clone())
    assert torch.equal(d.difference, torch.zeros(2)) and torch.equal(d.low, torch.zeros(2))
    assert torch.equal(d.high, torch.zeros(2)) and not d.beyond_spread().any()


def test_rmse_difference_bad_input_names_the_argument():
    good = torch.ones(5, 2)
    for kwargs, word in (
        (dict(candidate=torch.ones(5, 3), reference=good), "one shape"),
        (dict(candidate=good * float("nan"), reference=good), "candidate"),
        (dict(candidate=good, reference=-good), "reference"),  # signed errors, not their squares
        (dict(candidate=good, reference=good, count=[1, 1]), "count"),
        (dict(candidate=good, reference=good, groups=[0, 1]), "groups"),
        (dict(candidate=good, reference=good, level=95), "level"),
        (dict(candidate=good, reference=good, n_boot=0), "n_boot"),
    ):
        with pytest.raises(ValueError, match=word):
            M.rmse_difference(**kwargs)
