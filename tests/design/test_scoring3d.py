"""Probe scores of 3-D models (design.ProbeScorer3D) against the dense 3-D reference of tests/gp/test_inverse3d: the
information gain from the candidate's explicit posterior force covariance, the integrated variance from the dense
posterior of a model that has also seen the candidate (its forces do not matter), on every backend and both forms
of alpha_y."""

import pytest
import torch
from gp.test_inverse3d import _set, dense, turning_toe

import irft_torch as irft
from irft_torch.design import ProbeScorer, ProbeScorer3D, Region, greedy_design
from irft_torch.gp.inverse3d import InverseRFT3D, point_contacts
from irft_torch.rft import Contacts3D

F64 = torch.float64
CASES = [(m, a) for m in ("observations", "pairs", "spectral") for a in ("map", "constant")]
LS = 0.8 + torch.rand(3, 1, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
OS = torch.tensor([0.09, 0.02, 0.2], dtype=torch.float64)
NOISE = torch.tensor([4e-4, 3e-4, 5e-4], dtype=torch.float64)


def _model(method, alpha_y, T=10):
    c, f = turning_toe(T=T)
    m = InverseRFT3D(c, f, method=method, alpha_y=alpha_y, priors=None,
                     tol=1e-12 if method == "spectral" else 1e-7)
    _set(m, LS, OS, NOISE)
    m.backend.refresh()
    return c, f, m


@pytest.mark.parametrize("method,alpha_y", CASES)
def test_scores_match_the_dense_reference(method, alpha_y):
    c, f, model = _model(method, alpha_y)
    scorer = ProbeScorer.from_model(model)
    assert isinstance(scorer, ProbeScorer3D)
    constant = alpha_y == "constant"
    ls, os, noise = model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach()
    cand = turning_toe(T=8, seed=3)[0][2:7]
    T = len(cand)
    # information gain: 1/2 log |I + D^-1/2 S D^-1/2| of the candidate's rows (F_x, F_y, F_z) x T
    _, post = dense(c, f, ls, os, noise, constant)
    _, S = post(cand)
    d = noise.repeat_interleave(T).rsqrt()
    want = 0.5 * torch.linalg.slogdet(torch.eye(3 * T, dtype=S.dtype) + d[:, None] * S * d[None, :])[1]
    rtol = 1e-6 if method != "spectral" else 1e-5
    torch.testing.assert_close(scorer.information_gain(cand), want, rtol=rtol, atol=1e-9)
    # integrated variance, now and after the candidate: the dense posterior of the maps at the region's points
    region = Region.square(5)
    pts = point_contacts(region.beta, region.gamma)
    N = region.beta.numel()

    def iv(post_fn):
        _, P = post_fn(pts)
        var = torch.diagonal(P).reshape(3, N)
        return (var * region.weight).sum(-1) / os

    torch.testing.assert_close(scorer.integrated_variance(None, region, per_map=True), iv(post), rtol=rtol, atol=1e-9)
    both = Contacts3D.cat([c, cand])
    _, post_after = dense(both, torch.cat([f, torch.zeros(T, 3, dtype=f.dtype)]), ls, os, noise, constant)
    after = iv(post_after)
    torch.testing.assert_close(scorer.integrated_variance(cand, region, per_map=True), after, rtol=rtol, atol=1e-9)
    torch.testing.assert_close(scorer.condition(cand).integrated_variance(None, region, per_map=True), after,
                               rtol=rtol, atol=1e-9)
    # the map variance at points: the dense posterior's diagonal
    mv = scorer.map_variance(region.beta[:4], region.gamma[:4])
    _, P4 = post(point_contacts(region.beta[:4], region.gamma[:4]))
    torch.testing.assert_close(mv, torch.diagonal(P4).reshape(3, 4).T, rtol=rtol, atol=1e-10)


def test_more_of_a_probe_is_worth_more_and_ranking_follows_the_scores():
    c, f, model = _model("pairs", "map")
    scorer = ProbeScorer3D.from_model(model)
    long, _ = turning_toe(T=8, seed=3)
    short = long[:3]
    eig = scorer.score([short, long], "eig")
    iv = scorer.score([short, long], "variance")
    assert eig[1] > eig[0] > 0  # more rows of the same probe: more information (log det is monotone)
    assert iv[1] < iv[0] < scorer.integrated_variance()
    assert [i for i, _ in scorer.rank([short, long], "eig")] == [1, 0]
    assert [i for i, _ in scorer.rank([short, long], "variance")] == [1, 0]
    per_block = scorer.information_gain(long, per_block=True)
    torch.testing.assert_close(per_block.sum(), eig[1])


def test_greedy_design_in_3d_follows_the_chain_rule_and_picks_the_best_each_time():
    """greedy_design with a ProbeScorer3D: each pick is the best candidate given the ones before (checked by scoring
    every remaining one on the conditioned scorer), and the EIG steps add up to the joint EIG of the picks taken as
    one probe (the chain rule; the joint score does not go through the sequence)."""
    c, f, model = _model("pairs", "map")
    scorer = ProbeScorer3D.from_model(model)
    cands = [turning_toe(T=4, seed=s)[0] for s in (11, 12, 13, 14)]
    steps = greedy_design(scorer, cands, budget=3, criterion="eig")
    assert len({s.index for s in steps}) == 3
    current = scorer
    for s in steps:
        left = [i for i in range(4) if i not in [t.index for t in steps[:steps.index(s)]]]
        scores = current.score([cands[i] for i in left], "eig")
        assert left[int(scores.argmax())] == s.index
        torch.testing.assert_close(torch.tensor(s.score, dtype=F64), scores.max().to(F64), rtol=1e-9, atol=1e-12)
        current = current.condition(cands[s.index])
        assert abs(s.integrated_variance - float(current.integrated_variance())) < 1e-9
    joint = scorer.score([Contacts3D.cat([cands[s.index] for s in steps])], "eig")[0]
    torch.testing.assert_close(torch.tensor(sum(s.score for s in steps), dtype=F64), joint.to(F64), rtol=1e-7,
                               atol=1e-10)
    with pytest.raises(TypeError, match="Contacts3D"):
        greedy_design(scorer, [_planar()[0]], budget=1)


def test_the_scorer_follows_the_model_and_refuses_what_does_not_apply():
    c, f, model = _model("observations", "map")
    scorer = ProbeScorer.from_model(model)
    before = scorer.integrated_variance()
    extra, fe = turning_toe(T=6, seed=5)
    model.add_data(extra, fe)
    assert scorer.integrated_variance() < before  # it scores the model's current belief
    with pytest.raises(TypeError, match="Contacts3D"):
        scorer.information_gain(irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path(n_steps=20)))
    with pytest.raises(ValueError, match="criterion"):
        scorer.score([extra], "entropy")
    with pytest.raises(ValueError, match="3-D model"):
        ProbeScorer.from_model(model, method="spectral")
    with pytest.raises(TypeError, match="InverseRFT3D"):
        ProbeScorer3D.from_model(irft.InverseRFT(*_planar(), hyper_posterior="map", li_basis=False))


def _planar():
    c = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path(n_steps=20))
    return c, irft.rft.forces(irft.rft.FourierStressMap.generic(), c)


def _laplace_model():
    """A pairs 3-D model at the fixed hyperparameters above with a Laplace posterior over them (4 draws)."""
    c, f = turning_toe(T=10)
    model = InverseRFT3D(c, f, method="pairs")
    _set(model, LS, OS, NOISE)
    model.backend.refresh()
    model.fit_hyper_posterior("laplace", n_proposals=32, n_draws=4, generator=torch.Generator().manual_seed(0))
    return c, f, model


def test_a_model_with_a_hyperparameter_posterior_is_scored_over_its_draws():
    """ProbeScorer.from_model of a 3-D model with a Laplace posterior: a MixtureScorer whose scores are the draws'
    weighted averages, each draw's computed from the dense reference at that draw's hyperparameters (information
    gain from the candidate's explicit covariance, integrated variance from a dense model that has also seen it;
    the map variance is the mixture's total variance, the spread of the draws' means included)."""
    from irft_torch.design import MixtureScorer

    c, f, model = _laplace_model()
    scorer = ProbeScorer.from_model(model)
    assert isinstance(scorer, MixtureScorer) and scorer.n_draws == len(model._draw_backends) > 1
    cand = turning_toe(T=8, seed=3)[0][2:7]
    T = len(cand)
    region = Region.square(4)
    pts = point_contacts(region.beta, region.gamma)
    N = region.beta.numel()
    both = Contacts3D.cat([c, cand])
    residual = model._residual(model.train_contacts, model.train_forces)  # what the backends are fitted on
    eig = iv_now = iv_after = 0
    means, variances = [], []
    weights = model.hyper_posterior.weights.to(F64)
    for w, backend in zip(weights, model._draw_backends):
        h = backend.hypers
        ls, os, noise = h.lengthscale.detach(), h.outputscale.detach(), h.noise.detach()
        _, post = dense(c, residual, ls, os, noise, False)
        _, S = post(cand)
        d = noise.repeat_interleave(T).rsqrt()
        eig = eig + w * 0.5 * torch.linalg.slogdet(torch.eye(3 * T, dtype=F64) + d[:, None] * S * d[None, :])[1]
        mean, P = post(pts)
        var = torch.diagonal(P).reshape(3, N)
        means.append(mean)
        variances.append(var.T)
        iv_now = iv_now + w * (var * region.weight).sum(-1) / os
        _, after = dense(both, torch.cat([residual, torch.zeros(T, 3, dtype=F64)]), ls, os, noise, False)
        iv_after = iv_after + w * (torch.diagonal(after(pts)[1]).reshape(3, N) * region.weight).sum(-1) / os
    mode = ProbeScorer3D(model.backend)  # the fitted hyperparameters alone: a different number (the draws matter)
    assert (mode.integrated_variance(cand, region, per_map=True) - iv_after).abs().max() > 1e-2
    torch.testing.assert_close(scorer.information_gain(cand), eig, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(scorer.integrated_variance(None, region, per_axis=True), iv_now, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(scorer.integrated_variance(cand, region, per_axis=True), iv_after, rtol=1e-6,
                               atol=1e-9)
    torch.testing.assert_close(scorer.score([cand, cand[:2]], "variance", region)[0], iv_after.sum(), rtol=1e-6,
                               atol=1e-9)
    m, v = torch.stack(means), torch.stack(variances)  # (S, N, 3)
    wm = weights[:, None, None]
    total = (wm * (v + m.pow(2))).sum(0) - (wm * m).sum(0).pow(2)
    torch.testing.assert_close(scorer.map_variance(region.beta, region.gamma), total, rtol=1e-6, atol=1e-10)
    assert [i for i, _ in scorer.rank([cand[:2], cand], "eig")] == [1, 0]


def test_greedy_design_takes_a_3d_model_over_its_draws():
    """greedy_design with the MixtureScorer of a 3-D model with a Laplace posterior: 3-D candidates accepted (they
    were sent down the planar path), each pick the best on the conditioned mixture, and the picks' information
    gains adding up to the mixture's joint gain (each draw's chain rule, the weights held)."""
    c, f, model = _laplace_model()
    scorer = ProbeScorer.from_model(model)
    assert scorer.three_d
    cands = [turning_toe(T=4, seed=s)[0] for s in (11, 12, 13)]
    steps = greedy_design(scorer, cands, budget=2, criterion="eig")
    current = scorer
    for k, s in enumerate(steps):
        left = [i for i in range(3) if i not in [t.index for t in steps[:k]]]
        scores = current.score([cands[i] for i in left], "eig")
        assert left[int(scores.argmax())] == s.index
        current = current.condition(cands[s.index])
    joint = scorer.score([Contacts3D.cat([cands[s.index] for s in steps])], "eig")[0]
    torch.testing.assert_close(torch.tensor(sum(s.score for s in steps), dtype=F64), joint.to(F64), rtol=1e-7,
                               atol=1e-10)
    with pytest.raises(ValueError, match="3-D model's draws take one weight each"):
        type(scorer)(scorer.scorers, torch.ones(len(scorer.scorers), 2))


def test_the_3d_diagnostics_count_the_draws_whose_kernel_is_truncated():
    """diagnostics()["kernel"]["draws_truncated"]: every draw of a spectral model capped at 2 harmonics per angle
    is truncated beyond tol (each draw's own bound says so), none with the default cap."""
    from irft_torch.gp.options import Engine

    c, f = turning_toe(T=10)
    for cap, expect_all in ((2, True), (30, False)):
        model = InverseRFT3D(c, f, engine=Engine("spectral", tol=1e-7, max_harmonics=cap))
        _set(model, LS, OS, NOISE)
        model.backend.refresh()
        model.fit_hyper_posterior("laplace", n_proposals=16, n_draws=4, generator=torch.Generator().manual_seed(0))
        S = len(model._draw_backends)
        bounds = [float(b.truncation_error().max()) for b in model._draw_backends]
        assert all(e > 1e-7 for e in bounds) if expect_all else all(e <= 1e-7 for e in bounds)
        got = model.diagnostics()["kernel"]["draws_truncated"]
        assert got == (f"{S} of {S}" if expect_all else f"0 of {S}")


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_an_empty_candidate_teaches_nothing(method):
    """A candidate of no samples beside one with samples: information gain exactly 0 and the integrated variance
    unchanged (it was an error on the observations backend), the other scored as alone."""
    c, f, model = _model(method, "map")
    scorer = ProbeScorer.from_model(model)
    cand = turning_toe(T=6, seed=4)[0]
    eig = scorer.score([cand[:0], cand], "eig")
    iv = scorer.score([cand[:0], cand], "variance")
    assert float(eig[0]) == 0.0
    torch.testing.assert_close(iv[0], scorer.integrated_variance(), rtol=1e-12, atol=0)
    torch.testing.assert_close(eig[1], scorer.information_gain(cand), rtol=1e-12, atol=0)
    torch.testing.assert_close(iv[1], scorer.integrated_variance(cand), rtol=1e-12, atol=0)
