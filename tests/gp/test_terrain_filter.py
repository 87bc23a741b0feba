"""TerrainFilter: B streaming posteriors sharing one model's hyperparameters, each checked against that
environment's own InverseRFT (same hyperparameters, its samples given through add_data) and against the
dense formula (explicit W, explicit K, Cholesky) at 1e-8; windows and masks against a hand-derived
conjugate update; reset against the prior, exactly; bad input."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp import TerrainFilter
from irft_torch.rft import Contacts, FourierStressMap

from .dense_reference import W_dense, axis_reference, k_dense
from .test_backends_vs_dense import random_contacts, set_hypers

P = math.pi
B, M = 3, 4


def fitted(prior_mean="zero", dtype=torch.float64):
    """A model whose hyperparameters are set by hand (its own data are not part of any filter)."""
    c, f = env_data(0, T=20)
    model = irft.InverseRFT(c, f, prior_mean=prior_mean, dtype=dtype, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=1)
    if prior_mean == "physics":
        model.hypers.mean.scales = torch.tensor([0.6, 0.3])
    return model


def env_data(b, T=9):
    c = random_contacts(T=T, M=M, seed=10 + b)
    f = irft.rft.forces(FourierStressMap.generic(0.5, 0.4), c)
    return c, f + 0.05 * torch.randn(T, 2, generator=torch.Generator().manual_seed(20 + b))


def stack(cs, t):
    """The t-th sample of each environment: Contacts (B, M)."""
    return Contacts(*(torch.stack([getattr(c, k)[t] for c in cs]) for k in ("beta", "gamma", "weight_x", "weight_z")))


def own_model(model, c, f, method):
    """An environment's own InverseRFT at the shared hyperparameters, its samples given by add_data."""
    m = irft.InverseRFT(c[:2], f[:2], method=method, prior_mean=model.prior_mean_kind, priors=None,
                        hyper_posterior="map", li_basis=False)
    m.hypers.lengthscale = model.hypers.lengthscale.detach()
    m.hypers.outputscale = model.hypers.outputscale.detach()
    m.hypers.noise = model.hypers.noise.detach()
    if model.hypers.mean is not None:
        m.hypers.mean.scales = model.hypers.mean.scales.detach()
    torch.testing.assert_close(m.hypers.noise, model.hypers.noise.detach(), rtol=1e-10, atol=0)  # not at its floor
    if len(c) > 2:
        m.add_data(c[2:], f[2:])
    return m


def dense(model, c, f, th, cq):
    """The dense formula per axis: the map at th (Q, 2) and the forces of contacts cq (T, M)."""
    ls, os, noise = model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach()
    gen = FourierStressMap.generic()
    out = []
    for a, (w, wq) in enumerate(((c.weight_x, cq.weight_x), (c.weight_z, cq.weight_z))):
        s = None if model.hypers.mean is None else model.hypers.mean.scales.detach()[a]
        mean = None if s is None else s * (w * gen(c.beta, c.gamma)[..., a]).sum(-1)
        _, map_post, force_post = axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], mean)
        m_th = None if s is None else s * gen(th[:, 0], th[:, 1])[:, a]
        m_q = None if s is None else s * (wq * gen(cq.beta, cq.gamma)[..., a]).sum(-1)
        out.append((map_post(th, m_th), force_post(cq, wq, m_q)))
    return out


def close(a, b, tol=1e-8):
    a, b = a.detach(), b.detach()
    torch.testing.assert_close(a, b, rtol=tol, atol=tol * max(float(b.abs().max()), 1e-12))


@pytest.mark.parametrize("window", [None, 4])
@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
def test_each_environment_is_its_own_inverse_rft_and_the_dense_formula(prior_mean, window):
    model = fitted(prior_mean)
    data = [env_data(b) for b in range(B)]
    # env 1 skips samples 3 and 6 (masked), env 2 sends its samples two at a time (a (B, t, M) block)
    filt = TerrainFilter(model, B, window=window, capacity=2)  # no window: the capacity doubles twice
    kept = [list(range(9)), [t for t in range(9) if t not in (3, 6)], list(range(9))]
    th = (torch.rand(7, 2, generator=torch.Generator().manual_seed(3)) - 0.5) * P
    for t in range(0, 8, 2):
        block = Contacts(*(torch.stack([getattr(d[0], k)[t:t + 2] for d in data])
                           for k in ("beta", "gamma", "weight_x", "weight_z")))
        mask = torch.tensor([[True, True], [t != 6, t + 1 != 3], [True, True]])
        filt.update(block, torch.stack([d[1][t:t + 2] for d in data]), mask=mask)
        if t == 2:
            filt.stress_map(th[:, 0], th[:, 1])  # tracked from here on through the later updates
    filt.update(stack([d[0] for d in data], 8), torch.stack([d[1][8] for d in data]))
    post = filt.stress_map(th[:, 0], th[:, 1])
    cq = Contacts(*(torch.stack([getattr(d[0], k)[:5] for d in data])
                    for k in ("beta", "gamma", "weight_x", "weight_z")))
    pred = filt.predict_forces(cq, include_noise=True)
    assert post.mean.shape == (B, 7, 2) and pred.variance.shape == (B, 5, 2)
    for b in range(B):
        idx = torch.tensor(kept[b][-window:] if window else kept[b])
        c, f = data[b][0][idx], data[b][1][idx]
        assert int(filt.count[b]) == len(idx)
        for method in ("observations", "pairs"):
            own = own_model(model, c, f, method)
            ref_map, ref_forces = own.stress_map(th[:, 0], th[:, 1]), own.predict_forces(data[b][0][:5],
                                                                                          include_noise=True)
            close(post.mean[b], ref_map.mean)
            close(post.variance[b], ref_map.variance)
            close(pred.mean[b], ref_forces.mean)
            close(pred.variance[b], ref_forces.variance)
        for a, ((mu, var), (fmu, fvar)) in enumerate(dense(model, c, f, th, data[b][0][:5])):
            close(post.mean[b, :, a], mu)
            close(post.variance[b, :, a], var)
            close(pred.mean[b, :, a], fmu)
            close(pred.variance[b, :, a], fvar + model.hypers.noise.detach()[a])


def li_dense(model, c, f, th, cq):
    """The dense formula with Li et al.'s term written from angle differences (not from the features):
    k = RBF + v (1 + cos 2 dbeta)(1 + cos dgamma) / 4, per axis; zero prior mean."""
    ls, os, noise = model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach()
    v = model.hypers.li_variance.detach()

    def flat(x):
        return torch.stack([x.beta.reshape(-1), x.gamma.reshape(-1)], -1)

    out = []
    for a, (w, wq) in enumerate(((c.weight_x, cq.weight_x), (c.weight_z, cq.weight_z))):
        def k(t1, t2):
            db, dg = t1[:, None, 0] - t2[None, :, 0], t1[:, None, 1] - t2[None, :, 1]
            return k_dense(t1, t2, ls[a, 0], os[a]) + v[a] * (1 + torch.cos(2 * db)) * (1 + torch.cos(dg)) / 4

        th_c, th_q = flat(c), flat(cq)
        W, Wq = W_dense(w), W_dense(wq)
        L = torch.linalg.cholesky(W @ k(th_c, th_c) @ W.T + noise[a] * torch.eye(len(f), dtype=torch.float64))
        alpha = torch.cholesky_solve(f[:, a:a + 1], L)[:, 0]
        ks = k(th, th_c) @ W.T
        kf = Wq @ k(th_q, th_c) @ W.T
        out.append(((ks @ alpha, k(th, th).diagonal() - (ks * torch.cholesky_solve(ks.T, L).T).sum(-1)),
                    (kf @ alpha, (Wq @ k(th_q, th_q) @ Wq.T).diagonal()
                     - (kf * torch.cholesky_solve(kf.T, L).T).sum(-1))))
    return out


@pytest.mark.parametrize("window", [None, 3])
def test_li_basis_term_each_environment_is_its_own_inverse_rft_and_the_dense_formula(window):
    """A model with ``li_basis=True``: the filter carries v (W f) . (W' f) in every covariance (appends, the
    window's forgetting, tracked and fresh map points, forces), checked against each environment's own
    InverseRFT with the term and the dense formula written from angle differences."""
    c0, f0 = env_data(0, T=20)
    model = irft.InverseRFT(c0, f0, li_basis=True, hyper_posterior="map")
    set_hypers(model, seed=1)
    model.hypers.li.variance = torch.tensor([0.04, 0.3])
    data = [env_data(b) for b in range(B)]
    filt = TerrainFilter(model, B, window=window, capacity=2)
    th = (torch.rand(6, 2, generator=torch.Generator().manual_seed(5)) - 0.5) * P
    prior = filt.stress_map(th[:, 0], th[:, 1])  # tracked from the prior on
    k_prior = model.hypers.outputscale.detach() + model.hypers.li_variance.detach()  # k(theta, theta), w = +-1
    close(prior.variance, k_prior.expand(B, 6, 2), 1e-12)
    kept = [list(range(7)), [t for t in range(7) if t != 2], list(range(7))]
    for t in range(7):
        filt.update(stack([d[0] for d in data], t), torch.stack([d[1][t] for d in data]),
                    mask=torch.tensor([True, t != 2, True]))
    tracked = filt.stress_map(th[:, 0], th[:, 1])
    fresh = filt.stress_map(th[:, 0].clone().requires_grad_(True), th[:, 1])  # computed afresh (autograd path)
    cq = Contacts(*(torch.stack([getattr(d[0], k)[:4] for d in data])
                    for k in ("beta", "gamma", "weight_x", "weight_z")))
    pred = filt.predict_forces(cq)
    for b in range(B):
        idx = torch.tensor(kept[b][-window:] if window else kept[b])
        c, f = data[b][0][idx], data[b][1][idx]
        own = irft.InverseRFT(c[:2], f[:2], li_basis=True, priors=None, hyper_posterior="map")
        for name in ("lengthscale", "outputscale", "noise"):
            setattr(own.hypers, name, getattr(model.hypers, name).detach())
        own.hypers.li.variance = model.hypers.li_variance.detach()
        if len(c) > 2:
            own.add_data(c[2:], f[2:])
        ref_map, ref_forces = own.stress_map(th[:, 0], th[:, 1]), own.predict_forces(data[b][0][:4])
        for post in (tracked, fresh):
            close(post.mean[b], ref_map.mean)
            close(post.variance[b], ref_map.variance)
        close(pred.mean[b], ref_forces.mean)
        close(pred.variance[b], ref_forces.variance)
        for a, ((mu, var), (fmu, fvar)) in enumerate(li_dense(model, c, f, th, data[b][0][:4])):
            close(tracked.mean[b, :, a], mu)
            close(tracked.variance[b, :, a], var)
            close(pred.mean[b, :, a], fmu)
            close(pred.variance[b, :, a], fvar)
    # the term matters here: the same samples without it give another posterior
    plain = irft.InverseRFT(c0, f0, hyper_posterior="map", li_basis=False)
    set_hypers(plain, seed=1)
    other = TerrainFilter(plain, B, window=window, capacity=2)
    for t in range(7):
        other.update(stack([d[0] for d in data], t), torch.stack([d[1][t] for d in data]),
                     mask=torch.tensor([True, t != 2, True]))
    assert float((other.stress_map(th[:, 0], th[:, 1]).variance - tracked.variance).abs().max()) > 1e-3
    filt.reset([1])
    close(filt.stress_map(th[:, 0], th[:, 1]).variance[1], k_prior.expand(6, 2), 1e-12)


def test_spectral_model_within_its_truncation():
    """A spectral model's own posterior uses the truncated kernel; the filter the exact one: they agree to
    the backends' spectral tolerance (tests/gp/test_backends_vs_dense.py: 1e-6 at tol 1e-7)."""
    model = fitted()
    c, f = env_data(0)
    filt = TerrainFilter(model, 1)
    filt.update(Contacts(c.beta[None], c.gamma[None], c.weight_x[None], c.weight_z[None]), f[None])
    own = irft.InverseRFT(c, f, method="spectral", priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(own, seed=1)
    th = torch.linspace(-1.4, 1.4, 9)
    ours, theirs = filt.stress_map(th, th.flip(0)), own.stress_map(th, th.flip(0))  # (its basis grows first)
    assert own.method == "spectral" and float(own.truncation_error().max()) <= 1e-7
    close(ours.mean[0], theirs.mean, 1e-6)
    close(ours.variance[0], theirs.variance, 1e-6)


def point_samples(w, y, theta=(0.3, -0.4)):
    """One-segment samples at one angle: y_i = w_i alpha(theta) + noise on both axes."""
    n = len(w)
    w = torch.tensor(w, dtype=torch.float64)
    c = Contacts(torch.full((n, 1), theta[0]), torch.full((n, 1), theta[1]), -w[:, None], w[:, None])
    return c, torch.tensor(y, dtype=torch.float64)[:, None].expand(n, 2) * torch.tensor([-1.0, 1.0])


def conjugate(s, noise, w, y):
    """The hand-derived posterior of alpha(theta) from y_i = w_i alpha + eps, alpha ~ N(0, s): precision
    1/s + sum w_i^2 / noise, mean sum w_i y_i / noise / precision."""
    prec = 1 / s + sum(wi * wi for wi in w) / noise
    return sum(wi * yi for wi, yi in zip(w, y)) / noise / prec, 1 / prec


def test_window_and_mask_by_hand():
    model = fitted()
    s, noise = model.hypers.outputscale.detach(), model.hypers.noise.detach()
    w, y = [1.0, 2.0, 0.5, 1.5, 3.0], [0.4, 1.1, 0.2, 0.9, 1.6]
    c, f = point_samples(w, y)
    filt = TerrainFilter(model, 2, window=2)
    for t in range(5):  # env 1 misses sample 4 (index 3): its window then holds samples 2 and 4 (0-based 2, 4)
        ct = Contacts(*(v[t].expand(2, 1) for v in (c.beta, c.gamma, c.weight_x, c.weight_z)))
        filt.update(ct, f[t].expand(2, 2), mask=torch.tensor([True, t != 3]))
    post = filt.stress_map(torch.tensor([0.3]), torch.tensor([-0.4]))
    for b, kept in ((0, [3, 4]), (1, [2, 4])):
        for a in range(2):  # the x axis sees -w and -y: the same posterior of alpha_x
            mu, var = conjugate(float(s[a]), float(noise[a]), [w[i] for i in kept], [y[i] for i in kept])
            assert float(post.mean[b, 0, a]) == pytest.approx(mu, rel=1e-12)
            assert float(post.variance[b, 0, a]) == pytest.approx(var, rel=1e-12)
    assert filt.count.tolist() == [2, 2]


def test_masked_environment_is_unchanged_and_reset_gives_the_prior_exactly():
    for prior_mean in ("zero", "physics"):
        model = fitted(prior_mean)
        data = [env_data(b) for b in range(B)]
        filt = TerrainFilter(model, B, window=3)
        th = torch.linspace(-1.2, 1.2, 5)
        prior = TerrainFilter(model, B).stress_map(th, th)
        assert torch.equal(prior.variance, model.hypers.outputscale.detach().expand(B, 5, 2))
        if prior_mean == "zero":
            assert torch.equal(prior.mean, torch.zeros(B, 5, 2, dtype=torch.float64))
        for t in range(4):
            filt.update(stack([d[0] for d in data], t), torch.stack([d[1][t] for d in data]))
            filt.stress_map(th, th)
        before = filt.stress_map(th, th)
        filt.update(stack([d[0] for d in data], 4), torch.stack([d[1][4] for d in data]),
                    mask=torch.tensor([True, False, True]))
        after = filt.stress_map(th, th)
        assert torch.equal(after.mean[1], before.mean[1]) and torch.equal(after.variance[1], before.variance[1])
        assert not torch.equal(after.mean[0], before.mean[0])
        filt.reset(torch.tensor([False, True, True]))
        post = filt.stress_map(th, th)
        assert torch.equal(post.mean[1:], prior.mean[1:]) and torch.equal(post.variance[1:], prior.variance[1:])
        assert torch.equal(post.mean[0], after.mean[0])
        assert filt.count.tolist() == [3, 0, 0]
        other = filt.stress_map(th + 0.1, th)  # untracked points after a reset: the prior as well
        ref = TerrainFilter(model, B).stress_map(th + 0.1, th)
        close(other.mean[1:], ref.mean[1:], 1e-15)
        close(other.variance[1:], ref.variance[1:], 1e-15)


def test_gradients_in_a_policy_forward_pass_and_no_grad():
    model = fitted("physics")
    data = [env_data(b) for b in range(B)]
    filt = TerrainFilter(model, B, window=3)
    for t in range(4):
        filt.update(stack([d[0] for d in data], t), torch.stack([d[1][t] for d in data]))
    beta = torch.tensor([0.2, -0.5], dtype=torch.float64, requires_grad=True)
    gamma = torch.tensor([0.1, 0.7], dtype=torch.float64, requires_grad=True)

    def features(b, g):
        p = filt.stress_map(b, g)
        return torch.cat([p.mean, p.variance], -1)

    assert torch.autograd.gradcheck(features, (beta, gamma), eps=1e-6, atol=1e-6)
    loss = features(beta, gamma).sum()
    # an update between the forward and the backward pass (a rollout step) does not break the graph
    filt.update(stack([d[0] for d in data], 4), torch.stack([d[1][4] for d in data]))
    loss.backward()
    assert torch.isfinite(beta.grad).all()
    cq = Contacts(*(torch.stack([getattr(d[0], k)[:3] for d in data]).requires_grad_()
                    for k in ("beta", "gamma", "weight_x", "weight_z")))
    pred = filt.predict_forces(cq)
    pred.mean.sum().backward()
    assert cq.beta.grad is not None and torch.isfinite(cq.weight_x.grad).all()
    with torch.no_grad():
        post = filt.stress_map(beta, gamma)
    assert not post.mean.requires_grad
    close(post.mean, features(beta, gamma)[..., :2].detach(), 1e-12)


def test_bad_input_names_the_argument():
    model = fitted()
    filt = TerrainFilter(model, B)
    c, f = env_data(0)
    one = stack([c] * B, 0)
    with pytest.raises(TypeError, match="model"):
        TerrainFilter(object(), 4)
    for kwargs, word in (({"n_envs": 0}, "n_envs"), ({"n_envs": 2, "window": 0}, "window"),
                         ({"n_envs": 2.5}, "n_envs")):
        with pytest.raises(ValueError, match=word):
            TerrainFilter(model, **kwargs)
    with pytest.raises(ValueError, match="contacts"):
        filt.update(stack([c] * 2, 0), f[:2])
    with pytest.raises(ValueError, match="forces"):
        filt.update(one, f[:B, :1])
    with pytest.raises(ValueError, match="NaN"):
        filt.update(one, torch.full((B, 2), math.nan))
    with pytest.raises(ValueError, match="mask"):
        filt.update(one, f[:B], mask=torch.ones(B))
    with pytest.raises(ValueError, match="env_ids"):
        filt.reset([B])
    with pytest.raises(TypeError, match="contacts"):
        filt.predict_forces(f)
    assert filt.count.tolist() == [0] * B  # nothing was half-applied
