"""Hyperparameter posteriors (gp.hyper.posterior, gp.hyper.mixture): against brute-force numerical integration on
the dense reference, hand-derived mixtures, Monte Carlo and finite differences."""

import math

import pytest
import torch
from scipy.optimize import brentq
from scipy.stats import norm

import irft_torch as irft
from irft_torch.gp.hyper.importance import _student_t
from irft_torch.gp.hyper.mixture import mixture_moments, mixture_quantile
from irft_torch.gp.hyper.pareto import gpd_fit, gpd_shape, pareto_khat, psis_smooth
from irft_torch.gp.hyper.posterior import hyper_spec, log_posterior, point_mass
from irft_torch.gp.inputs import _data_scales
from irft_torch.gp.kernels.priors import (
    LENGTHSCALE_CENTRE,
    LENGTHSCALE_LOG_SD,
    NOISE_LOG_SD,
    OUTPUTSCALE_LOG_SD,
    prior_centres,
)

from .dense_reference import axis_reference

F64 = torch.float64


def small_problem(T=40, seed=0):
    toe = irft.rft.CToe(0.02, 0.008, n_segments=5)
    c = irft.rft.contacts(toe, irft.rft.spline_path([(-0.15, 0.0), (-0.05, -0.04), (0.08, -0.01), (0.15, -0.04)],
                                                    n_steps=T))
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(0.7, 1.1), c)
    g = torch.Generator().manual_seed(seed)
    f = f + 0.05 * f.std(0) * torch.randn(f.shape, generator=g, dtype=F64)
    return c, f


@pytest.fixture(scope="module")
def fitted():
    c, f = small_problem()
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.fit(n_iter=150, progress=False)
    return c, f, m


def query():
    b = torch.tensor([-1.2, -0.4, 0.0, 0.3, 1.0], dtype=F64)
    g = torch.tensor([-1.5, -0.3, 0.8, 1.2, 1.55], dtype=F64)  # the canonical square (the reference does not mirror)
    return b, g


# ---- mixtures ---------------------------------------------------------------------------------------
def test_mixture_moments_and_quantiles_against_scipy_and_monte_carlo():
    g = torch.Generator().manual_seed(3)
    means = torch.randn(6, 4, generator=g, dtype=F64) * 2
    variances = torch.rand(6, 4, generator=g, dtype=F64) + 0.05
    w = torch.rand(6, generator=g, dtype=F64)
    w = w / w.sum()
    mean, var = mixture_moments(means, variances, w)
    # hand formula: E[x] and E[x^2] - E[x]^2
    ex2 = (w[:, None] * (variances + means**2)).sum(0)
    torch.testing.assert_close(mean, (w[:, None] * means).sum(0), rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(var, ex2 - mean**2, rtol=1e-12, atol=1e-12)
    for q in (0.025, 0.5, 0.975):
        ours = mixture_quantile(q, means, variances, w)
        for j in range(4):  # scipy's root of the CDF written with scipy's normal
            def cdf(x):
                return float(sum(w[s] * norm.cdf(x, means[s, j], variances[s, j].sqrt()) for s in range(6))) - q
            ref = brentq(cdf, -50, 50, xtol=1e-13)
            assert float(ours[j]) == pytest.approx(ref, abs=1e-9)
    # Monte Carlo: draw a component by weight, then a normal
    n = 400_000
    comp = torch.multinomial(w, n, replacement=True, generator=g)
    x = means[comp] + variances[comp].sqrt() * torch.randn(n, 4, generator=g, dtype=F64)
    for q in (0.025, 0.975):
        torch.testing.assert_close(mixture_quantile(q, means, variances, w), torch.quantile(x, q, dim=0), atol=0.03,
                                   rtol=0)


def test_posterior_interval_of_a_mixture_is_not_the_moment_matched_one():
    means = torch.tensor([[0.0], [4.0]], dtype=F64)
    variances = torch.tensor([[1.0], [1.0]], dtype=F64)
    post = irft.Posterior.mixture(means, variances, torch.tensor([0.5, 0.5], dtype=F64))
    lo, hi = post.interval(0.95)
    # P(X <= hi) = 0.975 by the mixture CDF
    cdf = 0.5 * norm.cdf(float(hi), 0, 1) + 0.5 * norm.cdf(float(hi), 4, 1)
    assert cdf == pytest.approx(0.975, abs=1e-10)
    assert float(post.variance) == pytest.approx(1 + 4.0, rel=1e-12)  # 1 + (2^2)
    one = irft.Posterior.mixture(means[:1], variances[:1], torch.ones(1, dtype=F64))
    assert one.components is None and float(one.mean) == 0.0


# ---- the log posterior ------------------------------------------------------------------------------
def test_log_posterior_is_the_dense_marginal_likelihood_times_T_plus_the_log_prior(fitted):
    """n put back and no Jacobian: log p(theta | F) = sum_axes log N(F; 0, W K W^T + s^2 I) + sum of the normal
    log densities of log(value / centre), all by hand on the dense reference."""
    c, f, m = fitted
    h = m.hypers
    spec = hyper_spec(h)
    lp = float(log_posterior(m.backend, spec, spec.theta(h)))
    total = 0.0
    for a, w in enumerate((c.weight_x, c.weight_z)):
        mll, _, _ = axis_reference(c, f[:, a], w, h.lengthscale[a, 0].detach(), h.outputscale[a].detach(),
                                   h.noise[a].detach())
        total += float(mll) * len(f)
    cen = prior_centres(c, f, _data_scales(c, f)[1], False)

    def lognormal(v, centre, sd):
        z = (v.log() - torch.as_tensor(centre, dtype=F64).log()) / sd
        return float((-0.5 * z.pow(2) - math.log(sd * math.sqrt(2 * math.pi))).sum())

    total += lognormal(h.outputscale.detach(), cen["outputscale"], OUTPUTSCALE_LOG_SD)
    total += lognormal(h.lengthscale.detach(), LENGTHSCALE_CENTRE, LENGTHSCALE_LOG_SD)
    total += lognormal(h.noise.detach(), cen["noise"], NOISE_LOG_SD)
    assert lp == pytest.approx(total, rel=1e-9)
    # the model's own loss (autograd) against log_posterior (closed form): two summation orders, ~1e-10 apart
    assert lp == pytest.approx(-float(m.loss()) * len(f), rel=1e-9)


def test_log_posterior_gradient_against_finite_differences(fitted):
    c, f, m = fitted
    spec = hyper_spec(m.hypers)
    th = spec.theta(m.hypers).clone().requires_grad_(True)
    (g,) = torch.autograd.grad(log_posterior(m.backend, spec, th), th)
    eps = 1e-5
    for i in (0, 3, 9, 11):
        e = torch.zeros_like(th)
        e[i] = eps
        with torch.no_grad():
            fd = (log_posterior(m.backend, spec, th + e) - log_posterior(m.backend, spec, th - e)) / (2 * eps)
        assert float(g[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-6)


# ---- Laplace against brute force ---------------------------------------------------------------------
def _brute_force(m, c, f, free_axes_values, grid_1d, query_pts):
    """Mixture mean and variance of alpha_z at the query by trapezoidal integration over log outputscale_z
    (and optionally log noise_z) on a grid: dense reference likelihood + the prior written by hand."""
    h = m.hypers
    cen = prior_centres(c, f, _data_scales(c, f)[1], False)
    ls = h.lengthscale[1, 0].detach()
    b, g = query_pts
    th_star = torch.stack([b, g], -1)
    logps, means, variances = [], [], []
    for point in grid_1d:
        os = point[0].exp()
        noise = point[1].exp() if len(point) > 1 else h.noise[1].detach()
        mll, map_post, _ = axis_reference(c, f[:, 1], c.weight_z, ls, os, noise)
        lp = float(mll) * len(f) - 0.5 * float((point[0] - cen["outputscale"][1].log()) / OUTPUTSCALE_LOG_SD) ** 2
        if len(point) > 1:
            lp -= 0.5 * float((point[1] - cen["noise"][1].log()) / NOISE_LOG_SD) ** 2
        mu, var = map_post(th_star)
        logps.append(lp)
        means.append(mu)
        variances.append(var)
    lw = torch.tensor(logps, dtype=F64)
    w = (lw - lw.max()).exp()
    w = w / w.sum()
    return mixture_moments(torch.stack(means), torch.stack(variances), w)


def test_laplace_mixture_matches_brute_force_integration_over_one_hyperparameter(fitted):
    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    hp = m.fit_hyper_posterior("laplace", n_proposals=1024, n_draws=None, free=["outputscale_z"],
                               generator=torch.Generator().manual_seed(0))
    assert hp.khat < 0.5 and hp.ess > 500
    spec = hyper_spec(m.hypers)
    j = spec.labels.index("outputscale_z")
    mode, sd = float(hp.mode[j]), float(hp.covariance[j, j].sqrt())
    grid = torch.linspace(mode - 10 * sd, mode + 10 * sd, 201, dtype=F64)[:, None]  # trapezoid: exponentially accurate
    mean_ref, var_ref = _brute_force(m, c, f, None, grid, query())
    post = m.stress_map(*query())
    scale = float(mean_ref.abs().max())
    torch.testing.assert_close(post.mean[:, 1], mean_ref, atol=1e-3 * scale, rtol=0)
    torch.testing.assert_close(post.variance[:, 1], var_ref, rtol=1e-3, atol=0)
    # the integration mattered: the plug-in variance differs from the mixture's by more than the tolerance
    plug = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    plug.load_state_dict(m.state_dict())
    assert (plug.stress_map(*query()).variance[:, 1] / var_ref - 1).abs().max() > 3e-3


def test_laplace_mixture_matches_brute_force_integration_over_two_hyperparameters(fitted):
    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    hp = m.fit_hyper_posterior("laplace", n_proposals=1024, n_draws=None, free=["outputscale_z", "noise_z"],
                               generator=torch.Generator().manual_seed(1))
    spec = hyper_spec(m.hypers)
    i, j = spec.labels.index("outputscale_z"), spec.labels.index("noise_z")
    a = torch.linspace(float(hp.mode[i] - 8 * hp.covariance[i, i].sqrt()),
                       float(hp.mode[i] + 8 * hp.covariance[i, i].sqrt()), 41, dtype=F64)
    b = torch.linspace(float(hp.mode[j] - 8 * hp.covariance[j, j].sqrt()),
                       float(hp.mode[j] + 8 * hp.covariance[j, j].sqrt()), 41, dtype=F64)
    grid = torch.cartesian_prod(a, b)
    mean_ref, var_ref = _brute_force(m, c, f, None, grid, query())
    post = m.stress_map(*query())
    torch.testing.assert_close(post.mean[:, 1], mean_ref, atol=1e-3 * float(mean_ref.abs().max()), rtol=0)
    torch.testing.assert_close(post.variance[:, 1], var_ref, rtol=1e-3, atol=0)


def test_the_moment_matched_points_give_the_brute_force_mixture_with_few_draws(fitted):
    """The default draws (``points="moments"``: 2 P = 4 points over two free hyperparameters, out of 256 + 128
    weighed proposals) against trapezoidal integration: the mixture's mean and variance close to the exact
    integral, where a systematic resample of as many draws is further from it."""
    c, f, m0 = fitted
    free = ["outputscale_z", "noise_z"]
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    hp = m.fit_hyper_posterior("laplace", n_proposals=256, n_draws=4, free=free)
    assert hp.extra["points"] == "moments" and hp.n_draws == 4 and hp.extra["stages"] == 2
    spec = hyper_spec(m.hypers)
    i, j = spec.labels.index("outputscale_z"), spec.labels.index("noise_z")
    sd = hp.covariance.diagonal().sqrt()
    a = torch.linspace(float(hp.mode[i] - 8 * sd[i]), float(hp.mode[i] + 8 * sd[i]), 41, dtype=F64)
    b = torch.linspace(float(hp.mode[j] - 8 * sd[j]), float(hp.mode[j] + 8 * sd[j]), 41, dtype=F64)
    mean_ref, var_ref = _brute_force(m, c, f, None, torch.cartesian_prod(a, b), query())
    got = m.stress_map(*query())
    err_mean = float(((got.mean[:, 1] - mean_ref) / var_ref.sqrt()).abs().max())
    err_var = float((got.variance[:, 1] / var_ref - 1).abs().max())
    assert err_mean < 0.02 and err_var < 0.01
    r = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    r.load_state_dict(m0.state_dict())
    worse = 0
    for seed in range(4):
        r.fit_hyper_posterior("laplace", n_proposals=256, n_draws=4, free=free, points="resample",
                              generator=torch.Generator().manual_seed(seed))
        assert r.hyper_posterior.extra["points"] == "resample"
        e = float(((r.stress_map(*query()).mean[:, 1] - mean_ref) / var_ref.sqrt()).abs().max())
        worse += e > err_mean
    assert worse >= 3


def test_moment_points_fall_back_to_a_resample_where_too_few_draws_are_asked(fitted):
    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    hp = m.fit_hyper_posterior("laplace", n_proposals=64, n_draws=2, free=["outputscale_z", "noise_z"])
    assert hp.extra["points"] == "resample" and hp.n_draws <= 2
    with pytest.raises(ValueError, match="points"):
        m.fit_hyper_posterior("laplace", n_proposals=64, points="sigma")
    with pytest.raises(ValueError, match="adapt"):
        m.fit_hyper_posterior("laplace", n_proposals=64, adapt="sometimes")


def test_moment_points_reproduce_the_weighted_mean_and_covariance():
    from irft_torch.gp.hyper.importance import _moment_points

    g = torch.Generator().manual_seed(3)
    x = torch.randn(200, 5, generator=g, dtype=F64) @ torch.randn(5, 5, generator=g, dtype=F64)
    w = torch.rand(200, generator=g, dtype=F64)
    w = w / w.sum()
    mu = (w[:, None] * x).sum(0)
    C = ((x - mu).mT * w) @ (x - mu)
    for n_draws, n in ((16, 10), (8, 6)):  # the symmetric set 2 P, the simplex P + 1
        pts = _moment_points(x, w, n_draws, lambda p: torch.zeros(len(p), dtype=F64))
        assert pts.shape == (n, 5)
        torch.testing.assert_close(pts.mean(0), mu, rtol=0, atol=1e-12)
        torch.testing.assert_close(((pts - mu).mT @ (pts - mu)) / n, C, rtol=1e-10, atol=1e-12)
    assert _moment_points(x, w, 5, lambda p: torch.zeros(len(p), dtype=F64)) is None
    assert _moment_points(x, w, 16, lambda p: torch.full((len(p),), -math.inf, dtype=F64)) is None


def test_a_point_mass_gives_the_plug_in_predictions(fitted):
    """Exactly up to the round trip value -> log -> exp -> raw of the hyperparameters (a few ulps)."""
    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    ref_map = m.stress_map(*query())
    ref_f = m.predict_forces(c[:7], include_noise=True)
    m._set_hyper_posterior(point_mass(m.backend))
    assert m._draw_backends is not None and m._draw_backends[0] is not m.backend
    got = m.stress_map(*query())
    torch.testing.assert_close(got.mean, ref_map.mean, rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(got.variance, ref_map.variance, rtol=1e-11, atol=1e-15)
    gf = m.predict_forces(c[:7], include_noise=True)
    torch.testing.assert_close(gf.mean, ref_f.mean, rtol=1e-11, atol=1e-12)
    torch.testing.assert_close(gf.variance, ref_f.variance, rtol=1e-11, atol=1e-15)
    lo, hi = got.interval(0.9)
    rlo, rhi = ref_map.interval(0.9)
    torch.testing.assert_close(lo, rlo)
    torch.testing.assert_close(hi, rhi)


def test_laplace_end_to_end_predictions_are_mixtures_of_the_draws(fitted, tmp_path):
    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="laplace", li_basis=False)
    m.load_state_dict(m0.state_dict())
    m.fit(n_iter=0, progress=False)  # the posterior over hyperparameters at the loaded fit
    hp = m.hyper_posterior
    assert hp is not None and hp.n_draws >= 2 and abs(float(hp.weights.sum()) - 1) < 1e-12
    assert "outputscale_x" in hp.summary()
    # each prediction is the weighted mixture of the draws' own plug-in predictions
    per = []
    for th in hp.theta:
        d = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
        d.load_state_dict(m0.state_dict())
        hyper_spec(d.hypers).load(d.hypers, th)
        per.append(d.predict_forces(c[5:12]))
    mean, var = mixture_moments(torch.stack([p.mean for p in per]), torch.stack([p.variance for p in per]),
                                hp.weights)
    got = m.predict_forces(c[5:12])
    torch.testing.assert_close(got.mean, mean, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(got.variance, var, rtol=1e-10, atol=1e-14)
    # the mean map is the mixture mean; sample_maps draws from the mixture (its mean and variance, MC)
    b, g = query()
    torch.testing.assert_close(m(b, g), m.stress_map(b, g).mean)
    draws = m.sample_maps(b, g, 20_000, generator=torch.Generator().manual_seed(2))
    post = m.stress_map(b, g)
    torch.testing.assert_close(draws.mean(0), post.mean, atol=4 * float(post.stddev.max()) / 141, rtol=0)
    se = (draws - post.mean).pow(2).std(0) / math.sqrt(len(draws))  # the Monte Carlo error of a variance estimate
    assert bool(((draws.var(0) - post.variance).abs() <= 5 * se).all())
    # save and load keep the draws and the predictions
    m.save(tmp_path / "m.pt")
    back = irft.InverseRFT.load(tmp_path / "m.pt")
    assert back.hyper_posterior is not None and back.hyper_method == "laplace"
    torch.testing.assert_close(back.predict_forces(c[5:12]).variance, got.variance, rtol=1e-10, atol=1e-14)


def test_add_data_reweights_the_draws_by_the_new_samples_likelihood(fitted):
    c, f, m0 = fitted
    m = irft.InverseRFT(c[:30], f[:30], method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict(), strict=False)
    hp = m.fit_hyper_posterior("laplace", n_proposals=64, n_draws=8, generator=torch.Generator().manual_seed(4))
    w0, thetas = hp.weights.clone(), hp.theta.clone()
    m.add_data(c[30:], f[30:])
    # by hand: p(F_new | F_old, theta_s) from the dense reference on all and on the old samples
    logr = []
    for th in thetas:
        d = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
        hyper_spec(d.hypers).load(d.hypers, th)
        h = d.hypers
        tot = 0.0
        for a, w in enumerate((c.weight_x, c.weight_z)):
            args = (h.lengthscale[a, 0].detach(), h.outputscale[a].detach(), h.noise[a].detach())
            all_, _, _ = axis_reference(c, f[:, a], w, *args)
            old, _, _ = axis_reference(c[:30], f[:30, a], w[:30], *args)
            tot += float(all_) * len(f) - float(old) * 30
        logr.append(tot)
    lw = w0.log() + torch.tensor(logr, dtype=F64)
    ref = (lw - lw.max()).exp()
    torch.testing.assert_close(m.hyper_posterior.weights, ref / ref.sum(), rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("shape", [-0.2, 0.1, 0.5, 0.8])
def test_pareto_shape_recovers_known_shapes_and_agrees_with_scipys_maximum_likelihood(shape):
    """gpd_shape (Zhang & Stephens, as PSIS uses it) on 3000 draws of a generalized Pareto distribution of known
    shape: within sampling error of the truth (sd about 0.02-0.03 here), and within 0.02 of scipy's
    maximum-likelihood fit of the same draws (an independent estimator)."""
    from scipy.stats import genpareto

    x = genpareto.rvs(shape, scale=2.0, size=3000, random_state=3)
    k = gpd_shape(torch.tensor(x))
    assert abs(k - shape) < 0.08
    assert abs(k - genpareto.fit(x, floc=0)[0]) < 0.02


def test_pareto_shape_is_pyros_implementation_of_the_same_estimator():
    """pyro's fit_generalized_pareto (Zhang & Stephens with PSIS' shrinkage, written independently) on the same
    draws: the same k to rounding."""
    stats = pytest.importorskip("pyro.ops.stats", reason="pyro (the bayes extra) not installed")
    from scipy.stats import genpareto

    for shape, n in ((0.3, 25), (0.7, 500), (-0.1, 3000)):
        x = torch.tensor(genpareto.rvs(shape, scale=0.5, size=n, random_state=4))
        assert gpd_shape(x) == pytest.approx(stats.fit_generalized_pareto(x)[0], rel=1e-9, abs=1e-12)


def test_pareto_khat_of_importance_weights_tells_light_from_heavy_tails():
    """Importance weights p/q of a normal target: a wider normal proposal gives bounded weights (k-hat well below
    0.5), a narrower one weights with a Pareto tail of shape 1 - sigma_q^2 / sigma_p^2 = 0.75 here (the ratio of
    two normals' densities; PSIS paper, section 3); k-hat near it."""
    g = torch.Generator().manual_seed(0)
    n = 20000
    for sd_q, low, high in ((2.0, -math.inf, 0.3), (0.5, 0.6, 0.9)):  # bounded weights: any k <= 0
        x = sd_q * torch.randn(n, generator=g, dtype=F64)
        lw = -0.5 * x.pow(2) + 0.5 * (x / sd_q).pow(2)
        assert low < pareto_khat(lw) < high


def test_gpd_fit_recovers_a_known_scale():
    """gpd_fit's scale on 3000 draws of a generalized Pareto distribution of known shape and scale 2: within
    sampling error of the truth and of scipy's maximum-likelihood scale (an independent estimator)."""
    from scipy.stats import genpareto

    for shape in (0.1, 0.6):
        x = genpareto.rvs(shape, scale=2.0, size=3000, random_state=5)
        k, sigma = gpd_fit(torch.tensor(x))
        assert abs(sigma - 2.0) < 0.15
        assert abs(sigma - genpareto.fit(x, floc=0)[2]) < 0.1


def test_psis_smoothing_keeps_the_body_and_caps_the_tail():
    """Only the M = min(N / 5, 3 sqrt(N)) largest weights change; they stay above the largest unchanged one,
    ascending with the raw ones, and at most the largest raw weight; -inf stays -inf."""
    g = torch.Generator().manual_seed(1)
    x = 0.5 * torch.randn(200, generator=g, dtype=F64)
    lw = -0.5 * x.pow(2) + 0.5 * (x / 0.5).pow(2)
    lw[3] = -math.inf
    sm = psis_smooth(lw)
    M = int(min(199 / 5, 3 * math.sqrt(199)))
    order = torch.argsort(lw[torch.isfinite(lw)])
    raw, new = lw[torch.isfinite(lw)][order], sm[torch.isfinite(sm)][order]
    assert torch.isinf(sm[3])
    torch.testing.assert_close(new[:-M], raw[:-M], rtol=0, atol=0)
    assert (new[-M:] >= raw[-M - 1]).all() and (new[-M:].diff() >= 0).all() and new.max() <= raw.max() + 1e-12
    assert (new[-M:] != raw[-M:]).any()


def test_psis_estimates_vary_less_than_raw_importance_sampling_and_stay_accurate():
    """E[x^2] = 1 under a standard normal from 128 draws of a narrower normal proposal (sd 0.6: weights with a
    Pareto tail of shape 0.64), over 400 seeds: the Pareto-smoothed self-normalised estimate's error (against
    the exact 1) is smaller in root mean square than the raw weights' (Vehtari et al. 2024, figure 3's point)."""
    g = torch.Generator().manual_seed(2)
    err_raw, err_psis = [], []
    for _ in range(400):
        x = 0.6 * torch.randn(128, generator=g, dtype=F64)
        lw = -0.5 * x.pow(2) + 0.5 * (x / 0.6).pow(2)
        for lws, errs in ((lw, err_raw), (psis_smooth(lw), err_psis)):
            w = torch.softmax(lws, 0)
            errs.append(float((w * x.pow(2)).sum()) - 1.0)
    rms_raw, rms_psis = (torch.tensor(e).pow(2).mean().sqrt() for e in (err_raw, err_psis))
    assert rms_psis < 0.85 * rms_raw


def test_student_t_proposals_have_the_chi_square_quantiles_they_are_built_from():
    """The Sobol proposals' scale factors df / v: v from the chi-square inverse CDF (scipy.special's incomplete gamma
    inverse) must be the chi-square's quantiles: the proposals' log density integrates (Monte Carlo) to the
    Student-t's, checked by the radial distribution's median against scipy.stats' F distribution."""
    from scipy.stats import f as f_dist

    P, df, n = 3, 4.0, 4096
    mean, cov = torch.zeros(P, dtype=F64), torch.eye(P, dtype=F64)
    x, logq = _student_t(mean, cov, df, n, torch.Generator().manual_seed(1), qmc=True)
    r2 = x.pow(2).sum(-1) / P  # |x|^2 / P of a standard multivariate t: an F(P, df) variable
    for q in (0.25, 0.5, 0.75):
        assert abs(float(torch.quantile(r2, q)) - f_dist.ppf(q, P, df)) < 0.02 * f_dist.ppf(q, P, df) + 0.01


def test_bad_hyper_posterior_arguments_are_refused():
    c, f = small_problem(T=20)
    with pytest.raises(ValueError, match="hyper_posterior must be one of"):
        irft.InverseRFT(c, f, hyper_posterior="mcmc", li_basis=False)
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    with pytest.raises(ValueError, match="free: unknown"):
        m.fit_hyper_posterior("laplace", free=["lengthscale"])
    with pytest.raises(NotImplementedError, match="surface"):
        irft.InverseRFT(c, f, hyper_posterior="laplace", surface_offset=True, li_basis=False)


def test_nuts_agrees_with_brute_force_on_one_hyperparameter(fitted):
    pytest.importorskip("pyro")
    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    hp = m.fit_hyper_posterior("nuts", n_draws=400, free=["outputscale_z"], n_samples=400, warmup=200)
    spec = hyper_spec(m.hypers)
    j = spec.labels.index("outputscale_z")
    draws = hp.extra["all_draws"][:, 0]
    # brute force: the posterior mean and sd of log outputscale_z on a fine grid, by log_posterior's dense twin
    grid = torch.linspace(float(draws.mean() - 8 * draws.std()), float(draws.mean() + 8 * draws.std()), 801,
                          dtype=F64)
    h = m.hypers
    cen = prior_centres(c, f, _data_scales(c, f)[1], False)
    lps = []
    for t in grid:
        mll, _, _ = axis_reference(c, f[:, 1], c.weight_z, h.lengthscale[1, 0].detach(), t.exp(), h.noise[1].detach())
        lps.append(float(mll) * len(f) - 0.5 * float((t - cen["outputscale"][1].log()) / OUTPUTSCALE_LOG_SD) ** 2)
    lw = torch.tensor(lps, dtype=F64)
    w = (lw - lw.max()).exp()
    w = w / w.sum()
    mean = float((w * grid).sum())
    sd = float((w * (grid - mean) ** 2).sum().sqrt())
    assert hp.theta.shape[1] == spec.size and bool((hp.theta[:, j] != hp.mode[j]).any())
    # within 4 Monte Carlo standard errors at the chain's effective sample size
    assert abs(float(draws.mean()) - mean) < 4 * sd / math.sqrt(max(hp.ess, 1.0))
    assert float(draws.std()) == pytest.approx(sd, rel=0.25)


def _grid_moments(m, c, f, grid):
    """Posterior mean and sd (2,) of (log outputscale_z, log noise_z) by summation over a fine grid (P, 2):
    dense reference likelihood + the priors written by hand."""
    h = m.hypers
    cen = prior_centres(c, f, _data_scales(c, f)[1], False)
    lps = []
    for point in grid:
        mll, _, _ = axis_reference(c, f[:, 1], c.weight_z, h.lengthscale[1, 0].detach(), point[0].exp(),
                                   point[1].exp())
        lps.append(float(mll) * len(f) - 0.5 * float((point[0] - cen["outputscale"][1].log()) / OUTPUTSCALE_LOG_SD) ** 2
                   - 0.5 * float((point[1] - cen["noise"][1].log()) / NOISE_LOG_SD) ** 2)
    lw = torch.tensor(lps, dtype=F64)
    w = (lw - lw.max()).exp()
    w = w / w.sum()
    mean = (w[:, None] * grid).sum(0)
    return mean, (w[:, None] * (grid - mean) ** 2).sum(0).sqrt()


def test_nuts_with_the_laplace_metric_in_worker_processes_agrees_with_brute_force_on_two_hyperparameters(fitted):
    """Two chains in two worker processes, each from the polished mode with the Laplace covariance as its
    dense metric: the draws' moments against summation over a 61 x 61 grid."""
    pytest.importorskip("pyro")
    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    free = ["outputscale_z", "noise_z"]
    hp = m.fit_hyper_posterior("nuts", n_draws=16, free=free, n_samples=300, warmup=150, num_chains=2, processes=2)
    assert hp.extra["metric"] == "laplace" and len(hp.extra["gradient_evaluations"]) == 2
    spec = hyper_spec(m.hypers)
    cols = [spec.labels.index(k) for k in free]
    draws = hp.extra["all_draws"]  # (600, 2): the free coordinates
    assert draws.shape == (600, 2) and hp.theta.shape == (16, spec.size)
    held = [k for k in range(spec.size) if k not in cols]
    assert torch.equal(hp.theta[:, held], hp.mode[held].expand(16, -1))  # the rest stay at the fitted values
    lo, hi = draws.mean(0) - 8 * draws.std(0), draws.mean(0) + 8 * draws.std(0)
    grid = torch.cartesian_prod(*(torch.linspace(float(lo[k]), float(hi[k]), 61, dtype=F64) for k in range(2)))
    mean, sd = _grid_moments(m, c, f, grid)
    err = (draws.mean(0) - mean).abs() / (sd / math.sqrt(max(hp.ess, 1.0)))
    assert bool((err < 4).all()), err  # within 4 Monte Carlo standard errors
    torch.testing.assert_close(draws.std(0), sd, rtol=0.2, atol=0)
    # the chains started at the polished mode, not at the fitted point (Adam's last iterate)
    assert not torch.equal(hp.extra["start"][cols], hp.mode[cols])


def test_nuts_metric_and_processes_arguments_and_the_in_process_fallback(fitted, monkeypatch):
    pytest.importorskip("pyro")
    from concurrent.futures.process import BrokenProcessPool

    from irft_torch.gp.hyper import nuts as hyper_nuts

    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    with pytest.raises(ValueError, match="metric must be one of"):
        hyper_nuts.nuts(m.backend, metric="dense")
    with pytest.raises(ValueError, match="processes must be"):
        hyper_nuts.nuts(m.backend, processes=0)
    # pyro's own diagonal metric from the fitted point still runs
    hp = hyper_nuts.nuts(m.backend, n_samples=20, warmup=20, free=["outputscale_z"], metric="diagonal")
    assert hp.extra["metric"] == "diagonal" and torch.equal(hp.extra["start"], hp.mode)

    class Broken:  # workers that cannot start (a script without a main guard): the chains run here, with a warning
        def __init__(self, *a, **k):
            pass

        def __enter__(self):
            raise BrokenProcessPool("no workers")

        def __exit__(self, *a):
            return False

    monkeypatch.setattr("concurrent.futures.ProcessPoolExecutor", Broken)
    with pytest.warns(RuntimeWarning, match="main"):
        hp = hyper_nuts.nuts(m.backend, n_samples=10, warmup=10, num_chains=2, processes=2, free=["outputscale_z"])
    assert hp.extra["all_draws"].shape == (20, 1)
    # in a script the default is one process (its workers would import the script again)
    assert hyper_nuts._processes(None, 4, torch.device("cpu")) == 1


def test_nuts_says_when_pyro_does_not_take_the_laplace_metric(fitted, monkeypatch):
    """The metric is set through pyro's adapter (its internals): where that fails, the chain runs pyro's own
    metric and the posterior says so (``extra["metric"]``, a warning) instead of claiming the Laplace one."""
    pytest.importorskip("pyro")
    from pyro.infer.mcmc.adaptation import WarmupAdapter

    from irft_torch.gp.hyper import nuts as hyper_nuts

    c, f, m0 = fitted
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.load_state_dict(m0.state_dict())
    calls = []
    reset = WarmupAdapter.reset_step_size_adaptation

    def failing_second(self, z):  # pyro's own call passes; the one after the metric is set fails
        calls.append(1)
        if len(calls) == 2:
            raise AttributeError("no such adapter")
        return reset(self, z)

    monkeypatch.setattr(WarmupAdapter, "reset_step_size_adaptation", failing_second)
    with pytest.warns(RuntimeWarning, match="did not take the Laplace metric"):
        hp = hyper_nuts.nuts(m.backend, n_samples=10, warmup=10, free=["outputscale_z"], processes=1)
    assert hp.extra["metric"] == "diagonal" and len(calls) >= 3
    monkeypatch.undo()
    hp = hyper_nuts.nuts(m.backend, n_samples=10, warmup=10, free=["outputscale_z"], processes=1)
    assert hp.extra["metric"] == "laplace"


def test_weighted_moments_of_one_coordinate_are_a_one_by_one_covariance():
    """The importance stages' weighted mean and covariance (P,), (P, P), also for P = 1 (torch.cov returns 0-D
    there), against the weighted mean and variance written out."""
    from irft_torch.gp.hyper.importance import _weighted_moments

    g = torch.Generator().manual_seed(0)
    for P in (1, 3):
        x = torch.randn(50, P, generator=g, dtype=torch.float64)
        w = torch.rand(50, generator=g, dtype=torch.float64)
        mean, cov = _weighted_moments(x, w)
        wn = w / w.sum()
        want_mean = (wn[:, None] * x).sum(0)
        d = x - want_mean
        assert mean.shape == (P,) and cov.shape == (P, P)
        torch.testing.assert_close(mean, want_mean, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(cov, (wn[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0), rtol=1e-10,
                                   atol=1e-14)
