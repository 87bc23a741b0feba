"""The calibration harness (studies.calibration): its media against published coefficients, its motions,
its percentile statistic on truths the model is calibrated for by construction, and one fast case."""

import csv
import math

import pytest
import torch

import irft_torch as irft
from irft_torch.studies import calibration as cal

from . import experiment

F64 = torch.float64


def harness():
    """experiments/calibration/calibration_harness.py as a module."""
    return experiment("calibration_harness")


def test_fourier_medium_of_li_equals_the_published_generic_map_and_mirrors():
    g = torch.Generator().manual_seed(0)
    b = (torch.rand(200, generator=g, dtype=F64) - 0.5) * 2 * math.pi
    gm = (torch.rand(200, generator=g, dtype=F64) - 0.5) * 2 * math.pi
    ours = cal.FourierMedium.from_li(irft.rft.stress_maps.GENERIC, 0.7, 1.3)(b, gm)
    ref = irft.rft.FourierStressMap.generic(0.7, 1.3).double()(b, gm)
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=1e-12)
    # hand value: a horizontal plate pushed straight down, alpha_z(0, pi/2) = scale_z (Li et al.)
    assert float(cal.FourierMedium.from_li(irft.rft.stress_maps.GENERIC, 1.0, 1.3)(0.0, math.pi / 2)[1]) == \
        pytest.approx(1.3, rel=1e-12)


@pytest.mark.parametrize("family", cal.MEDIA + cal.HELD_OUT_MEDIA + cal.HELD_OUT_MEDIA_2)
def test_every_medium_is_finite_reproducible_and_mirror_consistent(family):
    truth, label = cal.medium(family, 3)
    again, _ = cal.medium(family, 3)
    B, G = cal.grid(11)
    a = truth(B, G)
    assert a.shape == (11, 11, 2) and torch.isfinite(a).all() and isinstance(label, str)
    torch.testing.assert_close(a, again(B, G))
    # motion toward -x is the mirror image: alpha_x(b, g) = -alpha_x(-b, pi - g), alpha_z equal (inside the
    # square: on its edge gamma = +-pi/2, straight down or up, a map outside Li's form need not be symmetric)
    B, G, a = B[:, 1:-1], G[:, 1:-1], a[:, 1:-1]
    m = truth(-B, math.pi - G)
    torch.testing.assert_close(m[..., 0], -a[..., 0], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(m[..., 1], a[..., 1], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kind", cal.MOTIONS + cal.HELD_OUT_MOTIONS + cal.HELD_OUT_MOTIONS_2)
def test_every_motion_touches_the_medium(kind):
    c = cal.motion(kind, 0)
    T = {"short": 40, "long": 400}.get(kind)
    if T is not None:
        assert len(c) == T
    assert ((c.weight_z != 0).any(-1)).double().mean() > 0.3
    f = cal.simulate(cal.medium("presets", 2)[0], c, 0.02, 0)
    assert torch.isfinite(f).all() and (f[:, 1].abs().max() > 0)


def test_simulated_noise_is_the_stated_share_of_each_axis_range():
    c = cal.motion("turning", 1)
    truth = cal.medium("scaled", 1)[0]
    clean = irft.rft.forces(truth, c)
    noisy = cal.simulate(truth, c, 0.05, 7)
    rng = clean.amax(0) - clean.amin(0)
    std = (noisy - clean).std(0)
    torch.testing.assert_close(std / rng, torch.full((2,), 0.05, dtype=F64), rtol=0.2, atol=0)


def test_the_percentile_statistic_is_uniform_on_truths_drawn_from_the_model_itself():
    """Simulation-based calibration of the statistic: a map drawn from the fit's own posterior is a truth the
    model is calibrated for, so its 95 % coverage's percentile among the model's draws is uniform; the coverages of
    those truths have the mean and spread the score reports from the model's own draws (``own95_*``, other draws of
    another generator), and their mean falls in the harness' calibrated band."""
    c = cal.motion("short", 0)
    f = cal.simulate(cal.medium("presets", 2)[0], c, 0.05, 0)
    model = irft.InverseRFT(c, f, hyper_posterior="map", li_basis=False)
    model.fit(n_iter=60, progress=False)
    B, G = cal.grid(15)
    truths = model.sample_maps(B, G, 60, generator=torch.Generator().manual_seed(123))
    pct, rows = [], []
    for k in range(60):
        table = truths[k]

        def truth(beta, gamma, table=table):
            assert beta.shape == table.shape[:-1]
            return table

        rows.append(cal.score(model, truth, n_grid=15, draws=100, seed=k))
        pct.append(rows[-1]["pct95_z"])
    pct = torch.tensor(pct)
    assert 0.35 < float(pct.mean()) < 0.65  # uniform: mean 1/2, sd of the mean 0.037
    assert float((pct < 0.025).double().mean()) <= 0.1
    for a in "xz":
        observed = torch.tensor([r[f"cover95_{a}"] for r in rows])
        own_mean = torch.tensor([r[f"own95_mean_{a}"] for r in rows])
        own_sd = torch.tensor([r[f"own95_sd_{a}"] for r in rows])
        se = float(own_sd.pow(2).mean().sqrt()) / math.sqrt(len(rows))
        assert abs(float(observed.mean() - own_mean.mean())) < 4 * se + 1e-3
        assert 0.5 < float(observed.std() / own_sd.pow(2).mean().sqrt()) < 2.0
        lo, hi = harness().calibrated_band(rows, a)
        assert lo <= float(observed.mean()) <= hi
        half = 1.96 * float(own_sd.pow(2).sum().sqrt()) / len(rows)  # the normal approximation of a mean of 60 fits
        centre = float(own_mean.mean())
        assert (lo, hi) == pytest.approx((centre - half, min(1.0, centre + half)), abs=0.01)


def test_the_calibrated_band_of_a_mean_coverage_against_hand_cases():
    """The harness' band for the mean of n fits' coverages: fits whose own coverage is always 1 (a posterior that
    covers all or nothing, here all) give [1, 1], which a mean of 1.000 is inside; own coverages uniform on [0, 1]
    give the mean of n uniforms, 1/2 +- 1.96 sqrt(1 / (12 n)) (central limit theorem, n = 48: +-0.0817); rows
    scored before the quantiles existed fall back to the normal approximation, and rows without either give None."""
    band = harness().calibrated_band
    ones = ";".join(["1.00000"] * 21)
    assert band([{"own95_q_x": ones}] * 12, "x") == (1.0, 1.0)
    uniform = ";".join(f"{k / 20:.5f}" for k in range(21))
    lo, hi = band([{"own95_q_z": uniform}] * 48, "z")
    half = 1.96 * math.sqrt(1 / (12 * 48))
    assert lo == pytest.approx(0.5 - half, abs=0.004) and hi == pytest.approx(0.5 + half, abs=0.004)
    lo, hi = band([{"own95_mean_x": "0.9", "own95_sd_x": "0.2", "own95_q_x": ""}] * 16, "x")
    assert (lo, hi) == pytest.approx((0.9 - 1.96 * 0.2 / 4, 0.9 + 1.96 * 0.2 / 4), rel=1e-12)
    assert band([{"cover95_x": "0.9"}] * 3, "x") is None


def test_the_overconfident_limit_is_the_binomial_quantile():
    """By hand: P(X <= 1) for X ~ Binomial(8, 0.025) is 0.9842 (>= 0.975), P(X <= 0) 0.8167; for 12 fits P(X <= 1) is
    0.9651 and P(X <= 2) 0.9971; for 48, P(X <= 3) 0.9682 and P(X <= 4) 0.9932."""
    limit = harness().overconfident_limit
    assert limit(8) == 1 and limit(12) == 2 and limit(48) == 4 and limit(1) == 0


def test_one_case_scores_the_plug_in_the_laplace_mixture_and_the_average_from_one_fit():
    rows = cal.run_case(cal.Case("gp", "short", 0.05, 0), ("map", "laplace", "average"), n_iter=80, n_grid=15,
                        draws=60)
    assert [r["posterior"] for r in rows] == ["map", "laplace", "average"]
    assert rows[0]["fit_s"] == rows[1]["fit_s"] == rows[2]["fit_s"]  # one fit of the zero mean, three predictions
    assert 0 <= rows[2]["w_physics_x"] <= 1 and 0 <= rows[2]["w_physics_z"] <= 1
    for r in rows:
        for k in ("cover50_x", "cover90_z", "cover95_x", "pct95_z"):
            assert 0.0 <= r[k] <= 1.0
        assert r["cover50_x"] <= r["cover90_x"] <= r["cover95_x"]
    assert rows[1]["n_draws"] >= 2 and rows[1]["ess"] > 1


def test_resumed_rows_with_more_columns_keep_their_headings(tmp_path):
    """A CSV from before a column existed, resumed with rows that have it: every value stays under its own heading
    (was: appended under the old header, each later column one place off) and the old rows read "nan" there."""
    path = tmp_path / "rows.csv"
    path.write_text("family,cover95_x,rmse_x\nscaled,0.9,0.01\n")
    harness().append_rows(path, [{"family": "gp", "cover95_x": 0.8, "own95_mean_x": 0.95, "rmse_x": 0.02}])
    rows = list(csv.DictReader(path.open()))
    assert rows[0] == {"family": "scaled", "cover95_x": "0.9", "rmse_x": "0.01", "own95_mean_x": "nan"}
    assert rows[1] == {"family": "gp", "cover95_x": "0.8", "rmse_x": "0.02", "own95_mean_x": "0.95"}
    assert harness().calibrated_band(rows, "x") is None  # one row without the own coverages: no band


def test_the_limits_scan_scales_the_residual_terms_prior_and_nothing_else():
    """experiments/calibration/calibration_limits.py's refit: the RBF outputscale's and Li et al.'s prior centres x
    factor against
    the library's model on the same data, the generic shape's and the lengthscales' priors unchanged."""
    limits = experiment("calibration_limits")
    truth, _ = cal.medium("perturbed", 1)
    c = cal.motion("short", 1)
    f = cal.simulate(truth, c, 0.05, 1)
    base = irft.InverseRFT(c, f, li_basis=True, generic_shape=True, hyper_posterior="map")
    scaled = limits.build_scaled(c, f, 0.01)

    def centre(module, name):
        return torch.as_tensor(module._priors[name][1].keywords["c"])

    for get, name, shift in ((lambda m: m.hypers.kernel, "outputscale_prior", math.log(0.01)),
                             (lambda m: m.hypers.li, "variance_prior", math.log(0.01)),
                             (lambda m: m.hypers.li, "generic_variance_prior", 0.0),
                             (lambda m: m.hypers.kernel.base_kernel, "lengthscale_prior", 0.0)):
        torch.testing.assert_close(centre(get(scaled), name), centre(get(base), name) + shift, rtol=0, atol=1e-12)


def test_the_limits_terms_drop_only_the_residual_and_leave_regression_on_the_generic_shape():
    """experiments/calibration/calibration_limits.py --terms: ``shrunk`` scales the RBF's and Li et al.'s variances
    and nothing
    else, and with them switched off the posterior is Bayesian linear regression of each force axis on the generic
    shape's forces (by hand), so on a scaled generic truth z^2 = (w - s)^2 / var(w) on every cell of the square."""
    limits = experiment("calibration_limits")
    truth, _ = cal.medium("scaled", 2)
    c = cal.motion("short", 2)
    f = cal.simulate(truth, c, 0.05, 2)
    model = irft.InverseRFT(c, f, li_basis=True, generic_shape=True,
                            hyper_posterior="map")  # not fitted: any hyperparameters do
    dropped = limits.shrunk(model, 1e-8)
    h, d = model.hypers, dropped.hypers
    torch.testing.assert_close(d.outputscale, h.outputscale * 1e-8, rtol=1e-12, atol=0)
    torch.testing.assert_close(d.li.variance, h.li.variance * 1e-8, rtol=1e-12, atol=0)
    for get in (lambda m: m.li.generic_variance, lambda m: m.noise, lambda m: m.lengthscale):
        torch.testing.assert_close(get(d), get(h), rtol=0, atol=0)
    # by hand: F_a = w_a g_a + noise, w_a ~ N(0, u_a), g_a the generic shape's forces per unit scale
    g = irft.rft.forces(irft.rft.FourierStressMap.generic().double(), c)  # (T, 2) N
    u, noise = h.li.generic_variance.detach(), h.noise.detach().reshape(-1)
    precision = g.pow(2).sum(0) / noise + 1 / u
    w = (g * f).sum(0) / noise / precision
    B, G = cal.grid(41)
    shape = irft.rft.FourierStressMap.generic().double()(B, G).reshape(-1, 2)
    t = truth(B, G).reshape(-1, 2)
    s = (t * shape).sum(0) / shape.pow(2).sum(0)  # the truth's scale per map
    torch.testing.assert_close(t, s * shape, rtol=1e-12, atol=1e-12)  # the truth is the shape, scaled
    z2_hand = (w - s).pow(2) * precision
    cover, z2 = limits.z_statistics(limits.shrunk(model, 1e-14), truth)
    for a in range(2):
        assert z2[a] == pytest.approx(float(z2_hand[a]), rel=5e-3)  # cells where g ~ 0 keep a trace
        assert cover[a] == (1.0 if float(z2_hand[a]) < 1.959964**2 else 0.0)
    # with the residual terms the same truth sits at their prior's centre: errors well inside the intervals
    _, z2_fitted = limits.z_statistics(model, truth)
    assert max(z2_fitted) < 1.0


def test_generic_residual_share_by_hand():
    """0 for the generic map at any positive scale; 1 where its least-squares scale is negative (clamped to 0: the
    whole map is residual); for generic + h with h orthogonal to the shape over the grid, rms(h) / rms(generic + h)."""
    shape = irft.rft.FourierStressMap.generic().double()
    torch.testing.assert_close(cal.generic_residual_share(lambda b, g: 0.37 * shape(b, g)),
                               torch.zeros(2, dtype=F64), rtol=0, atol=1e-12)
    torch.testing.assert_close(cal.generic_residual_share(lambda b, g: -shape(b, g)), torch.ones(2, dtype=F64))
    B, G = cal.grid(41)
    s = shape(B, G).reshape(-1, 2)
    bump = torch.stack([torch.cos(B) * torch.sin(2 * G), torch.cos(3 * G) + 0.0 * B], -1).reshape(-1, 2)
    k = (bump * s).sum(0) / s.pow(2).sum(0)  # h = bump - k shape: orthogonal to the shape on the grid

    def truth(b, g):
        h = torch.stack([torch.cos(b) * torch.sin(2 * g), torch.cos(3 * g) + 0.0 * b], -1) - k * shape(b, g)
        return shape(b, g) + h

    h = bump - k * s
    want = h.pow(2).mean(0).sqrt() / (s + h).pow(2).mean(0).sqrt()
    assert float(want.min()) > 0.2  # a case with a residual worth measuring
    torch.testing.assert_close(cal.generic_residual_share(truth), want, rtol=1e-10, atol=0)


def test_restated_reading_judges_nearly_generic_families_on_the_low_side_only():
    """Hand-made rows (own coverages with mean 0.95, sd 0.03: the normal band): a one-sided family covering
    everything is not flagged, the same coverage on a family with a residual is (high); a fit below its own 2.5th
    percentile twice in 4 is flagged low anywhere; the motion row leaves the one-sided family's fits out."""
    h = harness()
    assert h.one_sided_families(cal.MEDIA) == {"scaled", "presets"}
    assert h.one_sided_families(cal.HELD_OUT_MEDIA + cal.HELD_OUT_MEDIA_2) == set()

    def row(family, cover, pct):
        return {"family": family, "motion": "turning", "posterior": "map", "cover50_x": 0.5, "cover50_z": 0.5,
                "cover90_x": 0.9, "cover90_z": 0.9, "cover95_x": cover, "cover95_z": 0.95,
                "pct95_x": pct, "pct95_z": 0.5, "own95_mean_x": 0.95, "own95_sd_x": 0.03, "own95_mean_z": 0.95,
                "own95_sd_z": 0.03}

    rows = [row("scaled", 1.0, 0.9) for _ in range(4)] + [row("gp", 1.0, 0.9) for _ in range(4)]
    lines = h.restated_reading(rows)
    assert lines[0] == "One-sided (nearly the generic shape): scaled."
    verdict = lines[-1]  # | map | cells | low | high |
    assert "| map | 6 | 0: - |" in verdict  # scaled x, z; gp x, z; turning (gp only) x, z
    assert "gp x 1.000" in verdict and "turning x 1.000" in verdict and "scaled" not in verdict
    rows = [row("scaled", 0.9, 0.01) if i < 2 else row("scaled", 0.95, 0.5) for i in range(4)]
    verdict = h.restated_reading(rows)[-1]
    assert "| 1: scaled x 0.925 (0.92-0.98), 2/4 |" in verdict  # the motion row has no fits left: not a cell
