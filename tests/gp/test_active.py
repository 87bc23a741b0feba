"""Active probing: information gain and integrated variance against a dense reference."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.active import Region, greedy_design, information_gain, integrated_variance, rank_candidates
from irft_torch.rft import Contacts, FourierStressMap

from .dense_reference import W_dense, k_dense
from .test_model_vs_dense import random_contacts, set_hypers


def dense_posterior_cov(model, train, star_blocks):
    """Per axis: the posterior covariance of the stacked functionals star_blocks = [(contacts, which
    weights: 'x'/'z'/'ones')], from explicit W and K."""
    ls, os = model.kernel.lengthscale.detach(), model.kernel.outputscale.detach()
    noise = model.likelihood.noise.detach()
    out = []
    for a, wname in enumerate(("weight_x", "weight_z")):
        th = torch.stack([train.beta.reshape(-1), train.gamma.reshape(-1)], -1)
        W = W_dense(getattr(train, wname))
        Ws, ths = [], []
        for c in star_blocks:
            Ws.append(W_dense(getattr(c, wname)))
            ths.append(torch.stack([c.beta.reshape(-1), c.gamma.reshape(-1)], -1))
        n_rows = [w.shape[0] for w in Ws]
        n_cols = [w.shape[1] for w in Ws]
        Wst = torch.zeros(sum(n_rows), sum(n_cols))
        r = q = 0
        for w, nr, nc in zip(Ws, n_rows, n_cols):
            Wst[r:r + nr, q:q + nc] = w
            r, q = r + nr, q + nc
        thst = torch.cat(ths)
        k = lambda A, B: k_dense(A, B, ls[a, 0], os[a])  # noqa: E731
        S = W @ k(th, th) @ W.T + noise[a] * torch.eye(W.shape[0])
        Kst = Wst @ k(thst, th) @ W.T
        out.append(Wst @ k(thst, thst) @ Wst.T - Kst @ torch.linalg.solve(S, Kst.T))
    return out


@pytest.fixture
def model():
    c = random_contacts(T=20, M=3, seed=21)
    m = irft.InverseRFT(c, irft.rft.forces(FourierStressMap.generic(), c), method="exact")
    set_hypers(m, seed=3)
    return m


def test_information_gain_matches_dense(model):
    cand = random_contacts(T=8, M=4, seed=22)
    covs = dense_posterior_cov(model, model.train_contacts, [cand])
    noise = model.likelihood.noise.detach()
    want = sum(0.5 * torch.logdet(torch.eye(8) + covs[a] / noise[a]) for a in range(2))
    assert information_gain(model, cand).item() == pytest.approx(want.item(), rel=1e-8)


def test_integrated_variance_matches_dense(model):
    cand = random_contacts(T=6, M=3, seed=23)
    region = Region.square(5)
    one = torch.ones_like(region.beta)[:, None]
    pts = Contacts(region.beta[:, None], region.gamma[:, None], one, one)
    covs = dense_posterior_cov(model, model.train_contacts, [pts, cand])
    noise, s = model.likelihood.noise.detach(), model.kernel.outputscale.detach()
    n = len(pts)
    want_now, want_after = 0.0, 0.0
    for a in range(2):
        S = covs[a]
        var = torch.diagonal(S[:n, :n])
        k = S[:n, n:]
        post = var - torch.diagonal(k @ torch.linalg.solve(S[n:, n:] + noise[a] * torch.eye(6), k.T))
        want_now += (region.weight * var).sum() / s[a]
        want_after += (region.weight * post).sum() / s[a]
    assert integrated_variance(model, None, region).item() == pytest.approx(want_now.item(), rel=1e-8)
    assert integrated_variance(model, cand, region).item() == pytest.approx(want_after.item(), rel=1e-8)
    assert want_after < want_now


def test_more_contact_teaches_more_and_greedy_conditions(model):
    cand = random_contacts(T=6, M=3, seed=24)
    weak = Contacts(cand.beta, cand.gamma, cand.weight_x * 0.01, cand.weight_z * 0.01)
    ranked = rank_candidates(model, [weak, cand], "eig")
    assert ranked[0][0] == 1
    ranked_v = rank_candidates(model, [weak, cand], "variance", Region.sign_change(6))
    assert ranked_v[0][0] == 1
    before = integrated_variance(model).item()
    steps = greedy_design(model, [weak, cand, cand], budget=2)
    assert steps[0].index in (1, 2)
    # the integrated variance keeps falling, by less the second time (the same probe again)
    assert steps[1].score < steps[0].score < before
    assert before - steps[0].score > steps[0].score - steps[1].score
    with pytest.raises(ValueError, match="criterion"):
        rank_candidates(model, [cand], "entropy")
    assert math.isfinite(information_gain(model, cand).item())
