"""Probe scores of a model with a hyperparameter posterior: the weighted average, over its draws, of the
dense reference scores at each draw's hyperparameters (explicit W and K per draw); greedy design and
gradient design take the averaged scorer; one draw of weight 1 scores as the plug-in."""

import pytest
import torch
from gp.test_backends_vs_dense import random_contacts

from design.test_scoring import dense_cov, eig_dense, fitted, iv_dense
from irft_torch.design import MixtureScorer, ProbeScorer, Region, greedy_design
from irft_torch.gp.hyper.posterior import HyperPosterior, hyper_spec

TOL = {"observations": 1e-8, "pairs": 1e-8, "spectral": 1e-6}


def with_draws(model, shifts, weights):
    """The model with a hand-made hyperparameter posterior: its current theta shifted by each of ``shifts``."""
    spec = hyper_spec(model.hypers)
    th = spec.theta(model.hypers)
    g = torch.Generator().manual_seed(5)
    thetas = torch.stack([th + s * torch.randn(th.shape, generator=g, dtype=th.dtype) for s in shifts])
    w = torch.tensor(weights, dtype=th.dtype)
    model._set_hyper_posterior(HyperPosterior("laplace", spec.labels, thetas, w / w.sum(), th))
    return thetas, w / w.sum(), spec


def draw_hypers(spec, theta):
    vals = {lab: float(v) for lab, v in zip(spec.labels, theta.exp())}
    ls = torch.tensor([[[vals[f"lengthscale_{a}[{d}]"] for d in ("sin2b", "cos2b", "sing", "cosg")]] for a in "xz"])
    return ls, torch.tensor([vals["outputscale_x"], vals["outputscale_z"]]), \
        torch.tensor([vals["noise_x"], vals["noise_z"]])


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_mixture_scores_are_the_weighted_dense_scores(method):
    model = fitted(method)
    thetas, w, spec = with_draws(model, [0.0, 0.3, 0.6], [0.5, 0.3, 0.2])
    scorer = ProbeScorer.from_model(model, tol=None)
    assert isinstance(scorer, MixtureScorer) and scorer.n_draws == 3
    cand = random_contacts(T=8, M=4, seed=22)
    region = Region.square(5)
    eig = iv = iv_now = 0.0
    for th, wi in zip(thetas, w):
        ls, os, noise = draw_hypers(spec, th)
        eig = eig + wi * eig_dense(dense_cov(ls, os, noise, model.train_contacts, [cand]), noise)
        now, after = iv_dense(dense_cov(ls, os, noise, model.train_contacts, [region.contacts(), cand]), noise, os,
                              region, len(cand))
        iv, iv_now = iv + wi * after, iv_now + wi * now
    tol = TOL[method]
    assert scorer.information_gain(cand).item() == pytest.approx(eig.item(), rel=tol)
    assert scorer.integrated_variance(cand, region).item() == pytest.approx(iv.item(), rel=tol)
    assert scorer.integrated_variance(region=region).item() == pytest.approx(iv_now.item(), rel=tol)
    both = scorer.score([cand, random_contacts(T=5, M=3, seed=23)], "variance", region)
    assert both[0].item() == pytest.approx(iv.item(), rel=tol)


def test_one_draw_scores_as_the_plug_in_and_designs_run():
    model = fitted("observations")
    plug = ProbeScorer.from_model(model)
    cands = [random_contacts(T=6, M=3, seed=40 + i) for i in range(4)]
    want = plug.score(cands, "eig")
    with_draws(model, [0.0], [1.0])
    mix = ProbeScorer.from_model(model)
    assert isinstance(mix, MixtureScorer)
    torch.testing.assert_close(mix.score(cands, "eig"), want, rtol=1e-10, atol=0)
    # greedy design on the averaged belief: each pick conditions every draw; the chain rule of information
    with_draws(model, [0.0, 0.5], [0.6, 0.4])
    mix = ProbeScorer.from_model(model)
    steps = greedy_design(mix, cands, budget=2, criterion="variance")
    assert len(steps) == 2 and steps[1].integrated_variance < steps[0].integrated_variance
    after = mix.condition(cands[steps[0].index])
    assert isinstance(after, MixtureScorer)
    assert after.integrated_variance().item() == pytest.approx(steps[0].integrated_variance, rel=1e-10)


def test_map_variance_is_the_mixture_total_variance():
    model = fitted("observations")
    with_draws(model, [0.0, 0.5], [0.7, 0.3])
    b, g = torch.tensor([0.1, -0.4]), torch.tensor([0.3, 1.0])
    want = model.stress_map(b, g).variance
    torch.testing.assert_close(ProbeScorer.from_model(model).map_variance(b, g), want, rtol=1e-9, atol=1e-12)


def test_the_scorer_follows_the_models_draws():
    model = fitted("observations")
    with_draws(model, [0.0, 0.5], [0.5, 0.5])
    mix = ProbeScorer.from_model(model)
    cand = random_contacts(T=6, M=3, seed=50)
    before = mix.information_gain(cand).item()
    with_draws(model, [0.0, 0.4, 0.7], [0.2, 0.3, 0.5])
    assert mix.n_draws == 3
    assert mix.information_gain(cand).item() != pytest.approx(before, rel=1e-6)


def test_bad_weights_are_refused():
    model = fitted("observations")
    s = ProbeScorer.from_model(model)
    with pytest.raises(ValueError, match="weights"):
        MixtureScorer([s, s], [1.0, -1.0])
    with pytest.raises(ValueError, match="at least one"):
        MixtureScorer([], [])
