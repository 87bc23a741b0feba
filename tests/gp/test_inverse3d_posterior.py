"""3-D I-RFT beyond the plug-in: the hyperparameter posterior (Laplace, against brute-force integration over one
free hyperparameter on the plain dense reference of test_inverse3d) and streaming ``add_data`` (against a batch
model on all the data, on every backend, and the dense reference)."""

import math

import pytest
import torch

from irft_torch.gp.hyper.posterior import hyper_spec
from irft_torch.gp.inverse3d import InverseRFT3D, point_contacts
from irft_torch.gp.kernels.priors import OUTPUTSCALE_LOG_SD, data_scales_3d, prior_centres_3d
from irft_torch.rft import Contacts3D

from .test_inverse3d import _set, dense, per_sample, turning_toe

F64 = torch.float64
HYPERS = (torch.tensor([[[1.1, 0.9, 1.3, 1.0]], [[0.8, 1.2, 1.0, 1.4]], [[1.0, 1.0, 0.9, 1.2]]], dtype=F64),
          torch.tensor([0.09, 0.02, 0.2], dtype=F64), torch.tensor([4e-4, 3e-4, 5e-4], dtype=F64))


def query():
    b = torch.tensor([-1.2, -0.4, 0.0, 0.3, 1.0], dtype=F64)
    g = torch.tensor([-1.5, -0.3, 0.8, 1.2, 1.55], dtype=F64)
    return b, g


@pytest.fixture(scope="module")
def problem():
    c, f = turning_toe(T=14, seed=3)
    return c, f


def test_laplace_mixture_matches_brute_force_integration_over_alpha_y_variance(problem):
    """outputscale_y (alpha_y's prior variance) free: alpha_x, alpha_y and the (F_x, F_y) covariance all move with
    it (one horizontal block). The model's mixture (Laplace, importance-reweighted) against the trapezoid rule on
    a grid of log s_y: the dense reference's marginal likelihood x T plus the prior's log density by hand."""
    c, f = problem
    m = InverseRFT3D(c, f, method="observations", prior_mean="zero")  # the dense reference's zero mean
    _set(m, *HYPERS)
    hp = m.fit_hyper_posterior("laplace", n_proposals=512, n_draws=None, free=["outputscale_y"],
                               generator=torch.Generator().manual_seed(0))
    assert len(hp.labels) == 18 and {"outputscale_x", "outputscale_y", "outputscale_z", "noise_x", "noise_y",
                                     "noise_z", "lengthscale_y[sin2b]", "lengthscale_z[cosg]"} <= set(hp.labels)
    assert hp.khat < 0.5 and hp.ess > 250
    j = hp.labels.index("outputscale_y")
    mode, sd = float(hp.mode[j]), float(hp.covariance[j, j].sqrt())
    centre = prior_centres_3d(c, f, data_scales_3d(c, f)[1], m._noise_floor)["outputscale"][1]
    ls, os, noise = (t.detach().clone() for t in (m.hypers.lengthscale, m.hypers.outputscale, m.hypers.noise))
    qm, qf = point_contacts(*query()), c[3:8]
    lps, maps, forces = [], [], []
    for th in torch.linspace(mode - 10 * sd, mode + 10 * sd, 161, dtype=F64):
        os[1] = th.exp()
        nll, post = dense(c, f, ls, os, noise, False)
        lps.append(-float(nll) * len(c) - 0.5 * float((th - centre.log()) / OUTPUTSCALE_LOG_SD) ** 2)
        mean, cov = post(qm)
        maps.append((mean, per_sample(cov, len(qm))))
        mean, cov = post(qf)
        forces.append((mean, per_sample(cov, len(qf))))
    lw = torch.tensor(lps, dtype=F64)
    w = (lw - lw.max()).exp()
    w = w / w.sum()

    def total(parts):  # law of total covariance, written out
        mu = sum(wi * p[0] for wi, p in zip(w, parts))
        cov = sum(wi * (p[1] + (p[0] - mu)[..., :, None] * (p[0] - mu)[..., None, :]) for wi, p in zip(w, parts))
        return mu, cov

    want_m, want_mc = total(maps)
    want_f, want_fc = total(forces)
    got = m.stress_map(*query())
    scale = float(want_m.abs().max())
    torch.testing.assert_close(got.mean, want_m, atol=1e-3 * scale, rtol=0)
    torch.testing.assert_close(got.covariance, want_mc, rtol=2e-3, atol=1e-3 * float(want_mc.abs().max()))
    gf = m.predict_forces(qf)
    torch.testing.assert_close(gf.mean, want_f, atol=1e-3 * float(want_f.abs().max()), rtol=0)
    torch.testing.assert_close(gf.covariance, want_fc, rtol=2e-3, atol=1e-3 * float(want_fc.abs().max()))
    # the integration mattered: the plug-in's alpha_y variance is off the mixture's by more than the tolerance
    plug = InverseRFT3D(c, f, method="observations", prior_mean="zero")
    plug.hypers.load_state_dict(m.hypers.state_dict())
    assert (plug.stress_map(*query()).variance[:, 1] / want_mc[:, 1, 1] - 1).abs().max() > 1e-2
    # the mixture's intervals are its CDF's quantiles: 2.5 % below the lower end, by the draws' own normals
    lo, _ = got.interval(0.95)
    means, variances, weights = got.components
    cdf = (weights[:, None, None] * 0.5 * torch.special.erfc(-(lo - means) / variances.sqrt() / math.sqrt(2))).sum(0)
    torch.testing.assert_close(cdf, torch.full_like(cdf, 0.025), rtol=0, atol=1e-9)


def test_laplace_end_to_end_on_every_backend_save_load_and_constant_alpha_y(problem, tmp_path):
    """fit(...) with hyper_posterior="laplace": each prediction is the weighted mixture of the draws' plug-in
    predictions (a model per draw, built and set by hand); alpha_y's lengthscales stay fixed for a constant alpha_y;
    save/load keeps the draws; sample_maps draws from the mixture."""
    c, f = problem
    for method, alpha_y in (("pairs", "map"), ("spectral", "constant")):
        m = InverseRFT3D(c, f, method=method, alpha_y=alpha_y, hyper_posterior="laplace", tol=1e-9)
        _set(m, *HYPERS)
        hp = m.fit_hyper_posterior(n_proposals=48, n_draws=6, generator=torch.Generator().manual_seed(1))
        assert hp is m.hyper_posterior and hp.n_draws >= 2 and abs(float(hp.weights.sum()) - 1) < 1e-12
        spec = hyper_spec(m.hypers)
        fixed = [spec.labels.index(f"lengthscale_y[{d}]") for d in ("sin2b", "cos2b", "sing", "cosg")]
        moved = (hp.theta[:, fixed] - hp.mode[fixed]).abs().max()
        assert (moved == 0) if alpha_y == "constant" else (moved > 0)
        means, covs = [], []
        for th in hp.theta:
            d = InverseRFT3D(c, f, method=method, alpha_y=alpha_y, tol=1e-9)
            spec.load(d.hypers, th)
            d.backend.refresh()
            p = d.predict_forces(c[2:9], include_noise=True)
            means.append(p.mean)
            covs.append(p.covariance)
        w = hp.weights
        mu = sum(wi * x for wi, x in zip(w, means))
        cov = sum(wi * (C + (x - mu)[:, :, None] * (x - mu)[:, None, :]) for wi, x, C in zip(w, means, covs))
        got = m.predict_forces(c[2:9], include_noise=True)
        # spectral: each draw's basis grows from the model's, a model built by hand from its own; draws at short
        # lengthscales reach the harmonics' cap (truncation_error() says by how much): equal within that
        rtol = 1e-9 if method != "spectral" else 1e-6
        torch.testing.assert_close(got.mean, mu, rtol=rtol, atol=1e-11)
        atol = 1e-12 if method != "spectral" else 1e-6 * float(cov.abs().max())
        torch.testing.assert_close(got.covariance, cov, rtol=10 * rtol, atol=atol)
        m.save(tmp_path / "m.pt")
        back = InverseRFT3D.load(tmp_path / "m.pt")
        assert back.hyper_posterior is not None and back.hyper_method == "laplace"
        torch.testing.assert_close(back.predict_forces(c[2:9], include_noise=True).covariance, got.covariance,
                                   rtol=1e-9, atol=1e-12)
    b, g = query()
    post = m.stress_map(b, g)
    draws = m.sample_maps(b, g, 4000, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(draws.mean(0), post.mean, atol=5 * float(post.stddev.max()) / 63, rtol=0)
    torch.testing.assert_close(draws.var(0), post.variance, rtol=0.12, atol=1e-12)


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_add_data_is_the_batch_posterior(problem, method):
    """Samples streamed in two parts (the second with more elements per sample: padding) give the batch model's
    loss, force and map posteriors at the same hyperparameters, and the dense reference's."""
    c, f = problem
    tol = 1e-12 if method == "spectral" else 1e-7
    batch = InverseRFT3D(c, f, method=method, tol=tol, prior_mean="zero")
    part = InverseRFT3D(c[:9], f[:9], method=method, tol=tol, prior_mean="zero")
    for m in (batch, part):
        _set(m, *HYPERS)
        m.backend.refresh()
    part.add_data(c[9:].pad_elements(c.n_elements + 3), f[9:])
    assert len(part.train_contacts) == len(c) and part.backend.n_samples == len(c)
    with torch.no_grad():
        torch.testing.assert_close(part.backend.negative_log_likelihood(), batch.backend.negative_log_likelihood(),
                                   rtol=1e-9, atol=0)
        nll, post = dense(c, f, *HYPERS, False)
        torch.testing.assert_close(part.backend.negative_log_likelihood().sum(), nll, rtol=1e-7, atol=0)
    q, _ = turning_toe(T=6, seed=5)
    for got, want in ((part.predict_forces(q), batch.predict_forces(q)),
                      (part.stress_map(*query()), batch.stress_map(*query()))):
        torch.testing.assert_close(got.mean, want.mean, rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(got.covariance, want.covariance, rtol=1e-7, atol=1e-11)
    mean, cov = post(q)
    torch.testing.assert_close(part.predict_forces(q).mean, mean, rtol=1e-7, atol=1e-10)
    # the priors' centres follow all the data: the loss is the batch model's, priors included
    torch.testing.assert_close(part.loss(), batch.loss(), rtol=1e-9, atol=0)


def test_add_data_reweights_the_draws_by_the_new_samples_likelihood(problem):
    c, f = problem
    m = InverseRFT3D(c[:9], f[:9], method="pairs", prior_mean="zero")
    _set(m, *HYPERS)
    hp = m.fit_hyper_posterior("laplace", n_proposals=32, n_draws=5, free=["outputscale_y", "noise_x"],
                               generator=torch.Generator().manual_seed(4))
    w0 = hp.weights.clone()
    # each draw's hyperparameter values (theta is log value in this model's own data scales: read the values
    # from the draws, not by loading theta into a model built on other data)
    values = [tuple(t.detach().clone() for t in (b.hypers.lengthscale, b.hypers.outputscale, b.hypers.noise))
              for b in m._draw_backends]
    m.add_data(c[9:], f[9:])
    logr = []
    for h in values:  # p(F_new | F_old, theta_s) by hand on the dense reference
        logr.append(-float(dense(c, f, *h, False)[0]) * len(c) + float(dense(c[:9], f[:9], *h, False)[0]) * 9)
    lw = w0.log() + torch.tensor(logr, dtype=F64)
    want = (lw - lw.max()).exp()
    torch.testing.assert_close(m.hyper_posterior.weights, want / want.sum(), rtol=1e-7, atol=1e-12)


def test_bad_arguments():
    c, f = turning_toe(T=4)
    with pytest.raises(ValueError, match="hyper_posterior"):
        InverseRFT3D(c, f, hyper_posterior="mcmc")
    m = InverseRFT3D(c, f)
    with pytest.raises(ValueError, match="method"):
        m.fit_hyper_posterior("hmc")
    with pytest.raises(TypeError, match="Contacts3D"):
        m.add_data(c.planar(), f)
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        m.add_data(c, f[:, :2])


def test_a_flat_hyperprior_is_said_to_make_the_posterior_improper_as_in_the_planar_model(problem):
    """The 3-D model shares the planar hyperparameter-posterior mixin: without hyperparameter priors a Laplace
    posterior warns that it is improper (the planar model's HyperPosteriorWarning), and its draws stay finite and
    in the guard's bounds."""
    from irft_torch.gp.hyper import guard
    from irft_torch.gp.options import MapPrior

    c, f = problem
    m = InverseRFT3D(c, f, prior=MapPrior(mean="zero", hyperpriors=None))
    _set(m, *HYPERS)
    with pytest.warns(guard.HyperPosteriorWarning, match="hyperpriors=None.*improper"):
        hp = m.fit_hyper_posterior("laplace", n_proposals=32, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(hp.theta.exp()).all()
    assert float(hp.covariance.diagonal().max()) <= guard.MAX_LOG_SD**2 * (1 + 1e-9)
    post = m.stress_map(*query())
    assert torch.isfinite(post.mean).all() and torch.isfinite(post.variance).all()


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_the_scoring_questions_match_the_dense_reference(problem, method):
    """What a probe scorer asks of a 3-D backend (``candidate_rows``, ``region_rows``, ``map_moments``,
    ``condition``), against the dense reference: each candidate's block rows' covariance, noise and covariance with
    the maps at a region's points; the maps' moments at angles; conditioning without forces leaves the mean where
    it was and gives the covariance of a dense model that has also seen the samples (whatever their forces)."""
    from types import SimpleNamespace

    c, f = problem
    m = InverseRFT3D(c, f, method=method, prior_mean="zero", priors=None, tol=1e-12 if method == "spectral" else 1e-7)
    _set(m, *HYPERS)
    m.backend.refresh()
    ls, os, noise = HYPERS
    _, post = dense(c, f, ls, os, noise, False)
    cands = [turning_toe(T=6, seed=8)[0][1:4], turning_toe(T=6, seed=9)[0][:5]]
    b, g = query()
    region = SimpleNamespace(beta=b, gamma=g)
    S, nz, cross = m.backend.candidate_rows(cands, m.backend.region_rows(region))
    pts = point_contacts(b, g)
    N, rtol = len(b), 1e-6 if method == "spectral" else 1e-8
    for i, cand in enumerate(cands):
        T = len(cand)
        _, P = post(Contacts3D.cat([cand, pts]))  # rows (x, y, z) x (T + N), axis-major
        idx = [torch.cat([a * (T + N) + torch.arange(T) for a in axes]) for axes in ((0, 1), (2,))]
        pidx = [torch.cat([a * (T + N) + T + torch.arange(N) for a in axes]) for axes in ((0, 1), (2,))]
        for blk in range(2):
            k = len(idx[blk])
            torch.testing.assert_close(S[i, blk, :k, :k], P[idx[blk]][:, idx[blk]], rtol=rtol, atol=1e-12)
            assert (S[i, blk, k:] == 0).all() and (nz[i, blk, k:] == 1).all()  # padding: noise only
            torch.testing.assert_close(nz[i, blk, :k], noise[[0, 1] if blk == 0 else [2]].repeat_interleave(T))
            torch.testing.assert_close(cross[i, blk, :k, :len(pidx[blk])], P[idx[blk]][:, pidx[blk]], rtol=rtol,
                                       atol=1e-12)
    mean, var = m.backend.map_moments(b, g)
    assert all(torch.equal(x, y) for x, y in zip(m.backend.map_moments(b.tolist(), g.tolist()), (mean, var)))
    want_mean, want_cov = post(pts)
    torch.testing.assert_close(mean, want_mean, rtol=rtol, atol=1e-10)
    torch.testing.assert_close(var, torch.diagonal(want_cov).reshape(3, N).T, rtol=rtol, atol=1e-12)
    after = m.backend.condition(cands[1])
    # (the spectral mean to ~1e-6 N/cm^3 of maps ~0.1: its I + A, ~3,000 features at noise 4e-4 N^2, is ill-conditioned)
    atol = 2e-6 if method == "spectral" else 1e-10
    torch.testing.assert_close(after.map_moments(b, g)[0], mean, rtol=rtol, atol=atol)
    both = Contacts3D.cat([c, cands[1]])
    _, post_after = dense(both, torch.cat([f, torch.randn(len(cands[1]), 3, dtype=F64)]), ls, os, noise, False)
    torch.testing.assert_close(after.map_moments(b, g)[1], torch.diagonal(post_after(pts)[1]).reshape(3, N).T,
                               rtol=rtol, atol=1e-12)



def test_bad_query_angles_are_clear_errors_as_in_the_planar_model(problem):
    """NaN angles, shapes that do not broadcast and angles in degrees: the 3-D model's map queries say so (they
    gave NaN maps, a bare broadcasting error and nothing)."""
    c, f = problem
    m = InverseRFT3D(c, f, method="pairs", hyper_posterior="map")
    b, g = query()
    with pytest.raises(ValueError, match="gamma contains NaN"):
        m.stress_map(b, g.clone().index_fill_(0, torch.tensor([1]), float("nan")))
    with pytest.raises(ValueError, match="do not broadcast"):
        m.sample_maps(b, g[:3])
    with pytest.warns(UserWarning, match="degrees"):
        m.stress_map(b * 60, g)


def test_cross_validation_groups_are_any_labels_checked_as_in_the_planar_model(problem):
    """Groups named by strings give the same held-out predictions as the same groups numbered (each sample
    predicted from the other groups, so the labels only group); one label, NaN labels or a wrong length: a
    ValueError naming groups."""
    c, f = problem
    m = InverseRFT3D(c, f, method="pairs", hyper_posterior="map")
    numbered = torch.arange(len(c)) // 5
    named = [f"run {int(k)}" for k in numbered]
    a, b = m.cross_validate(numbered), m.cross_validate(named)
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=0)
    torch.testing.assert_close(a.covariance, b.covariance, rtol=0, atol=0)
    for bad, match in ((torch.zeros(len(c)), "at least 2"), (torch.full((len(c),), float("nan")), "NaN"),
                       (numbered[:-1], "one label per training sample")):
        with pytest.raises(ValueError, match=match):
            m.cross_validate(bad)
