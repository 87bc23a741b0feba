"""Averaging over the prior mean (gp.mean_average): the evidence against the Laplace formula written by hand on
the dense reference (finite-difference Hessian), predictions against the two models' own predictions mixed by
hand, streaming against the dense likelihood ratio, files, per-map mixture weights against per-map mixtures."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.hyper.mixture import mixture_moments, mixture_quantile
from irft_torch.gp.hyper.posterior import hyper_spec, log_evidence
from irft_torch.gp.inputs import _data_scales
from irft_torch.gp.kernels.priors import (
    LENGTHSCALE_CENTRE,
    LENGTHSCALE_LOG_SD,
    NOISE_LOG_SD,
    OUTPUTSCALE_LOG_SD,
    prior_centres,
)
from irft_torch.gp.mean_average import MeanAverage, _polish_to_mode

from .dense_reference import axis_reference
from .test_hyper_posterior import query, small_problem

F64 = torch.float64


@pytest.fixture(scope="module")
def averaged():
    c, f = small_problem(T=36, seed=4)
    m = irft.InverseRFT(c, f, method="pairs", prior_mean="average", hyper_posterior="map", li_basis=False)
    m.fit(n_iter=120, progress=False)
    return c, f, m


def _lognormal(v, centre, sd):
    z = (torch.as_tensor(v, dtype=F64).log() - torch.as_tensor(centre, dtype=F64).log()) / sd
    return (-0.5 * z.pow(2) - math.log(sd * math.sqrt(2 * math.pi))).sum()


def test_log_evidence_is_the_laplace_formula_on_the_dense_reference():
    """Per map: log p(F_c | theta_c) + log p(theta_c) + d/2 log 2 pi - 1/2 log |H_c|, with the likelihood from the
    dense reference, the normal priors of log(value / centre) written by hand, and H_c by autograd through that
    dense reference (central differences of it, the first version, agree to their own error of a few 1e-4)."""
    c, f = small_problem(T=30, seed=2)
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.fit(n_iter=100, progress=False)
    _polish_to_mode(m.backend)
    m.train()
    ours = log_evidence(m.backend)
    m.eval()
    cen = prior_centres(c, f, _data_scales(c, f)[1], False)
    h = m.hypers
    for a, w in enumerate((c.weight_x, c.weight_z)):
        theta0 = torch.cat([h.lengthscale[a, 0].detach().log(), h.outputscale[a].detach().log().reshape(1),
                            h.noise[a].detach().log().reshape(1)])

        def logp(th):
            ls, os, noise = th[:4].exp(), th[4].exp(), th[5].exp()
            mll, _, _ = axis_reference(c, f[:, a], w, ls, os, noise)
            return (mll * len(f) + _lognormal(ls, LENGTHSCALE_CENTRE, LENGTHSCALE_LOG_SD)
                    + _lognormal(os, cen["outputscale"][a], OUTPUTSCALE_LOG_SD)
                    + _lognormal(noise, cen["noise"][a], NOISE_LOG_SD))

        d = len(theta0)
        H = -torch.autograd.functional.hessian(logp, theta0)  # exact, through the dense reference (not the library)
        H = 0.5 * (H + H.T)
        want = logp(theta0) + 0.5 * d * math.log(2 * math.pi) - 0.5 * torch.linalg.slogdet(H)[1]
        assert float(ours[a]) == pytest.approx(float(want), abs=1e-7)


def test_evidence_needs_proper_priors():
    c, f = small_problem(T=20)
    with pytest.raises(ValueError, match="priors='physical'"):
        irft.InverseRFT(c, f, prior_mean="average", priors=None, hyper_posterior="map", li_basis=False)
    with pytest.raises(NotImplementedError, match="surface"):
        irft.InverseRFT(c, f, prior_mean="average", surface_offset=True, hyper_posterior="map", li_basis=False)
    m = irft.InverseRFT(c, f, priors=None, hyper_posterior="map", li_basis=False)
    with pytest.raises(ValueError, match="proper hyperparameter priors"):
        log_evidence(m.backend)


def test_averaged_predictions_are_the_two_models_mixed_by_their_evidence(averaged):
    c, f, m = averaged
    ma = m.mean_average
    assert isinstance(ma, MeanAverage) and m.companion.prior_mean_kind == "physics"
    # the weights: a softmax of each model's own evidence, per map
    le = torch.stack([log_evidence(m.backend), log_evidence(m.companion.backend)]).detach()
    torch.testing.assert_close(ma.log_evidence, le.double(), rtol=0, atol=1e-8)
    torch.testing.assert_close(ma.weights, torch.softmax(le.double(), 0), rtol=0, atol=1e-10)
    b, g = query()
    post = m.stress_map(b, g)
    parts = [irft.InverseRFT.stress_map(x, b, g) for x in (_plug_in(m), _plug_in(m.companion))]
    pi = ma.weights
    mean = pi[0] * parts[0].mean + pi[1] * parts[1].mean
    second = pi[0] * (parts[0].variance + parts[0].mean**2) + pi[1] * (parts[1].variance + parts[1].mean**2)
    torch.testing.assert_close(post.mean, mean, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(post.variance, second - mean**2, rtol=1e-8, atol=1e-12)
    torch.testing.assert_close(m(b, g), mean, rtol=1e-10, atol=1e-12)
    pf = m.predict_forces(c[10:20])
    fp = [x.predict_forces(c[10:20]) for x in (_plug_in(m), _plug_in(m.companion))]
    torch.testing.assert_close(pf.mean, pi[0] * fp[0].mean + pi[1] * fp[1].mean, rtol=1e-10, atol=1e-12)
    # each map's 95 % interval from its own mixture (weights differ between the maps)
    lo, hi = post.interval(0.95)
    for a in range(2):
        means = torch.stack([p.mean[..., a] for p in parts])
        variances = torch.stack([p.variance[..., a] for p in parts])
        torch.testing.assert_close(lo[..., a], mixture_quantile(0.025, means, variances, pi[:, a]), rtol=0, atol=1e-9)
        torch.testing.assert_close(hi[..., a], mixture_quantile(0.975, means, variances, pi[:, a]), rtol=0, atol=1e-9)


def _plug_in(model):
    """A plain plug-in model with ``model``'s fitted hyperparameters (no draws, no average)."""
    c, f = model._measured()
    p = irft.InverseRFT(c, f, method=model.method, prior_mean=model.prior_mean_kind
                        if model.prior_mean_kind != "average" else "zero", hyper_posterior="map", li_basis=False)
    p.hypers.load_state_dict(model.hypers.state_dict())
    return p


def test_sample_maps_draw_each_map_from_its_own_mixture(averaged):
    c, f, m = averaged
    b, g = query()
    post = m.stress_map(b, g)
    s = m.sample_maps(b, g, n=20000, generator=torch.Generator().manual_seed(1))
    assert s.shape == (20000, 5, 2)
    torch.testing.assert_close(s.mean(0), post.mean, rtol=0, atol=4 * float(post.stddev.max()) / math.sqrt(20000))
    # the empirical CDF at each map's own mixture quantiles (binomial spread: 4 sigma)
    for q in (0.1, 0.5, 0.9):
        x = mixture_quantile(q, *post.components)
        frac = (s <= x).double().mean(0)
        assert (frac - q).abs().max() < 4 * math.sqrt(q * (1 - q) / 20000), (q, frac)


def test_files_keep_the_companion_and_the_weights(averaged, tmp_path):
    c, f, m = averaged
    m.save(tmp_path / "avg.pt")
    back = irft.InverseRFT.load(tmp_path / "avg.pt")
    b, g = query()
    torch.testing.assert_close(back.mean_average.weights, m.mean_average.weights, rtol=0, atol=0)
    torch.testing.assert_close(back.stress_map(b, g).mean, m.stress_map(b, g).mean, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(back.stress_map(b, g).variance, m.stress_map(b, g).variance, rtol=1e-10, atol=1e-14)


def test_add_data_moves_the_weights_by_the_new_samples_likelihood():
    """log pi_mc += log p(F_new,c | F_old,c, M_m) at each model's hyperparameters: the dense likelihood of all the
    samples minus that of the old ones, per map."""
    c, f = small_problem(T=40, seed=6)
    m = irft.InverseRFT(c[:30], f[:30], method="pairs", prior_mean="average", hyper_posterior="map", li_basis=False)
    m.fit(n_iter=80, progress=False)
    le0 = m.mean_average.log_evidence.clone()
    gains = []
    for model in (m, m.companion):
        h = model.hypers
        g = []
        for a, w in enumerate((c.weight_x, c.weight_z)):
            ls, os, noise = h.lengthscale[a, 0].detach(), h.outputscale[a].detach(), h.noise[a].detach()
            mean_all = mean_old = None
            if h.mean is not None:
                shape = h.mean.shape_forces(c)[a].detach() * h.mean.scales[a].detach()
                mean_all, mean_old = shape, shape[:30]
            all_, _, _ = axis_reference(c, f[:, a], w, ls, os, noise, mean_all)
            old, _, _ = axis_reference(c[:30], f[:30, a], w[:30], ls, os, noise, mean_old)
            g.append(float(all_) * 40 - float(old) * 30)
        gains.append(g)
    m.add_data(c[30:], f[30:])
    want = le0 + torch.tensor(gains, dtype=F64)
    torch.testing.assert_close(m.mean_average.log_evidence, want, rtol=0, atol=1e-7)
    assert len(m.companion.train_forces) == 40


def test_per_map_mixture_weights_are_a_mixture_per_map():
    g = torch.Generator().manual_seed(8)
    means = torch.randn(5, 3, 2, generator=g, dtype=F64)
    variances = torch.rand(5, 3, 2, generator=g, dtype=F64) + 0.1
    w = torch.rand(5, 2, generator=g, dtype=F64)
    w = w / w.sum(0)
    mean, var = mixture_moments(means, variances, w)
    for a in range(2):
        ma, va = mixture_moments(means[..., a], variances[..., a], w[:, a])
        torch.testing.assert_close(mean[..., a], ma, rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(var[..., a], va, rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(mixture_quantile(0.9, means, variances, w)[..., a],
                                   mixture_quantile(0.9, means[..., a], variances[..., a], w[:, a]), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="weights must be"):
        mixture_moments(means, variances, torch.ones(5, 3, dtype=F64))


def test_a_medium_of_the_generic_shape_seen_through_a_slice_takes_the_physics_mean():
    """A rotating I-toe sees a diagonal line of the square; in a generic-shaped medium the physics mean explains
    the forces with far fewer degrees of freedom, and the average puts its weight there."""
    from irft_torch.studies.calibration import medium, motion, simulate

    truth, _ = medium("scaled", 0)
    c = motion("rotating", 0)[::3]  # every third sample: the same slice of the square, a third of the cost
    f = simulate(truth, c, 0.01, 0)
    m = irft.InverseRFT(c, f, prior_mean="average", hyper_posterior="map", li_basis=False)
    m.fit(n_iter=100, progress=False)
    assert (m.mean_average.weights[1] > 0.9).all()
    assert hyper_spec(m.companion.hypers).labels[-2:] == ["mean_scale_x", "mean_scale_z"]
