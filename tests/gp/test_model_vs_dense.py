"""InverseRFT against the dense reference: likelihood, gradients, map and force posteriors."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.rft import Contacts, FourierStressMap

from .dense_reference import axis_reference

P = math.pi


def random_contacts(T=25, M=4, seed=0):
    """Random angles, zero-weight segments, mixed left/right motion (sign of weight_x)."""
    g = torch.Generator().manual_seed(seed)
    beta = (torch.rand(T, M, generator=g) - 0.5) * P
    gamma = (torch.rand(T, M, generator=g) - 0.5) * P
    w = torch.rand(T, M, generator=g) * 3
    w[torch.rand(T, M, generator=g) < 0.3] = 0.0  # above the surface / padding
    w[0] = 0.0  # one observation with no contact at all
    sign = torch.where(torch.rand(T, 1, generator=g) < 0.5, -1.0, 1.0)
    return Contacts(beta=beta, gamma=gamma, weight_x=-sign * w, weight_z=w)


def set_hypers(model, seed=1):
    g = torch.Generator().manual_seed(seed)
    k = model.kernel
    k.lengthscale = 0.4 + torch.rand(2, 1, 4, generator=g)
    k.outputscale = torch.tensor([0.05, 0.2])
    model.likelihood.noise = torch.tensor([0.03, 0.07])


def references(model, c, f):
    ls, os = model.kernel.lengthscale.detach(), model.kernel.outputscale.detach()
    noise = model.likelihood.noise.detach()
    out = []
    for a, w in enumerate((c.weight_x, c.weight_z)):
        mean = None
        if model.prior_mean_kind == "physics":
            shape = FourierStressMap.generic()(c.beta, c.gamma)[..., a]
            mean = model.gp.mean_module.scales.detach()[a] * (w * shape).sum(-1)
        out.append(axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], mean))
    return out


@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
def test_mll_and_every_gradient_match_dense(prior_mean):
    c = random_contacts()
    f = irft.rft.forces(FourierStressMap.generic(0.5, 0.4), c) + 0.05 * torch.randn(len(c), 2,
                                                                                      generator=torch.Generator().manual_seed(3))
    model = irft.InverseRFT(c, f, prior_mean=prior_mean)
    set_hypers(model)
    model.train()
    mll = model.mll()
    ours = mll(model.gp(*model.gp.train_inputs), model.gp.train_targets).sum()
    params = [p for _, p in model.gp.named_parameters()]
    g_ours = torch.autograd.grad(ours, params)

    # dense reference as a function of the same raw parameters
    def dense_mll():
        ls, os, noise = model.kernel.lengthscale, model.kernel.outputscale, model.likelihood.noise
        total = 0.0
        for a, w in enumerate((c.weight_x, c.weight_z)):
            mean = None
            if prior_mean == "physics":
                shape = FourierStressMap.generic()(c.beta, c.gamma)[..., a]
                mean = model.gp.mean_module.scales[a] * (w * shape).sum(-1)
            total = total + axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], mean)[0]
        return total

    ref = dense_mll()
    g_ref = torch.autograd.grad(ref, params, allow_unused=True)
    assert ours.item() == pytest.approx(ref.item(), rel=1e-8)
    for (name, _), a, b in zip(model.gp.named_parameters(), g_ours, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10, msg=f"gradient of {name}")


@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
def test_map_and_force_posteriors_match_dense(prior_mean):
    c = random_contacts(T=30, M=5, seed=4)
    f = irft.rft.forces(FourierStressMap.generic(0.5, 0.4), c)
    model = irft.InverseRFT(c, f, prior_mean=prior_mean)
    set_hypers(model, seed=2)
    refs = references(model, c, f)
    g = torch.Generator().manual_seed(9)
    th = (torch.rand(40, 2, generator=g) - 0.5) * P
    post = model.stress_map(th[:, 0], th[:, 1])
    for a in range(2):
        mean_star = None
        if prior_mean == "physics":
            mean_star = model.gp.mean_module.scales.detach()[a] * FourierStressMap.generic()(th[:, 0], th[:, 1])[:, a]
        mu, var = refs[a][1](th, mean_star)
        torch.testing.assert_close(post.mean[:, a], mu, rtol=1e-8, atol=1e-12)
        torch.testing.assert_close(post.variance[:, a], var, rtol=1e-8, atol=1e-12)
    # forces at new contacts (mixed directions, zero weights), exact variance w^T Sigma w
    cs = random_contacts(T=12, M=3, seed=7)
    pred = model.predict_forces(cs)
    for a, w in enumerate((cs.weight_x, cs.weight_z)):
        mean_star = None
        if prior_mean == "physics":
            shape = FourierStressMap.generic()(cs.beta, cs.gamma)[..., a]
            mean_star = model.gp.mean_module.scales.detach()[a] * (w * shape).sum(-1)
        mu, var = refs[a][2](cs, w, mean_star)
        torch.testing.assert_close(pred.mean[:, a], mu, rtol=1e-8, atol=1e-12)
        torch.testing.assert_close(pred.variance[:, a], var, rtol=1e-8, atol=1e-12)


def test_independent_segment_variance_is_the_papers_formula():
    c = random_contacts(T=20, M=4, seed=5)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    model = irft.InverseRFT(c, f)
    set_hypers(model)
    refs = references(model, c, f)
    cs = random_contacts(T=6, M=3, seed=8)
    pred = model.predict_forces(cs, variance="independent")
    th = torch.stack([cs.beta.reshape(-1), cs.gamma.reshape(-1)], -1)
    for a, w in enumerate((cs.weight_x, cs.weight_z)):
        _, var = refs[a][1](th)
        want = (w.pow(2) * var.reshape(w.shape)).sum(-1)
        torch.testing.assert_close(pred.variance[:, a], want, rtol=1e-8, atol=1e-12)
    noisy = model.predict_forces(cs, variance="independent", include_noise=True)
    torch.testing.assert_close(noisy.variance - pred.variance, model.likelihood.noise.detach().expand(6, 2))


def test_zero_weight_padding_changes_nothing():
    c = random_contacts(T=15, M=3, seed=11)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    m1 = irft.InverseRFT(c, f)
    m2 = irft.InverseRFT(c.pad_segments(7), f)
    for m in (m1, m2):
        set_hypers(m)
        m.train()
    l1 = m1.mll()(m1.gp(*m1.gp.train_inputs), m1.gp.train_targets).sum()
    l2 = m2.mll()(m2.gp(*m2.gp.train_inputs), m2.gp.train_targets).sum()
    assert l1.item() == pytest.approx(l2.item(), rel=1e-12)
    b = torch.linspace(-1, 1, 9)
    torch.testing.assert_close(m1.stress_map(b, b).mean, m2.stress_map(b, b).mean, rtol=1e-10, atol=1e-12)


def test_mirror_outside_canonical_square():
    c = random_contacts(T=15, M=3, seed=12)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    m = irft.InverseRFT(c, f)
    b, g = torch.tensor([0.3]), torch.tensor([2.5])  # motion with a -x component
    inside = m.stress_map(-b, P - g)
    outside = m.stress_map(b, g)
    torch.testing.assert_close(outside.mean, inside.mean * torch.tensor([-1.0, 1.0]))
    torch.testing.assert_close(outside.variance, inside.variance)


@pytest.mark.parametrize("method", ["exact", "grid"])
def test_relative_noise_scale_is_heteroscedastic_noise_exactly(method, tmp_path):
    """noise_scale s: noise variance sigma^2 s_t^2 per sample. Against a dense model with
    S = A K A^T + sigma^2 diag(s^2), no whitening in the reference (A = W for the exact path, the
    interpolation Phi over the grid's nodes for the grid path), and through save/load."""
    from .dense_reference import W_dense, k_dense

    c = random_contacts(T=24, M=3, seed=13)
    f = irft.rft.forces(FourierStressMap.generic(0.5, 0.4), c)
    s = 0.5 + torch.rand(24, 2, generator=torch.Generator().manual_seed(2))
    model = irft.InverseRFT(c, f, noise_scale=s, method=method, grid_size=(10, 9))
    set_hypers(model, seed=6)
    if method == "grid":
        model.grid_model._cache = None
        grid = model.grid_model.grid
        b, g = grid.nodes()
        B, G = torch.meshgrid(b, g, indexing="ij")
        th = torch.stack([B.reshape(-1), G.reshape(-1)], -1)
        idx, iw = grid.interpolation(c.beta, c.gamma)
        A = [torch.zeros(24, grid.size).scatter_add(1, idx.reshape(24, -1), (w[..., None] * iw).reshape(24, -1))
             for w in (c.weight_x, c.weight_z)]
    else:
        th = torch.stack([c.beta.reshape(-1), c.gamma.reshape(-1)], -1)
        A = [W_dense(c.weight_x), W_dense(c.weight_z)]
    ls, os = model.kernel.lengthscale.detach(), model.kernel.outputscale.detach()
    noise = model.likelihood.noise.detach()
    total = 0.0
    for a in range(2):
        S = A[a] @ k_dense(th, th, ls[a, 0], os[a]) @ A[a].T + noise[a] * torch.diag(s[:, a] ** 2)
        mll = torch.distributions.MultivariateNormal(torch.zeros(24), S).log_prob(f[:, a])
        total = total + (mll + torch.log(s[:, a]).sum()) / 24  # the whitened likelihood's Jacobian term
    # the grid factors carry a 1e-8 jitter: agreement to ~1e-6 there
    assert -model.loss().item() == pytest.approx(total.item(), rel=1e-8 if method == "exact" else 1e-6)
    thq = (torch.rand(15, 2, generator=torch.Generator().manual_seed(3)) - 0.5) * P
    post = model.stress_map(thq[:, 0], thq[:, 1])
    for a in range(2):
        S = A[a] @ k_dense(th, th, ls[a, 0], os[a]) @ A[a].T + noise[a] * torch.diag(s[:, a] ** 2)
        if method == "exact":
            ks = k_dense(thq, th, ls[a, 0], os[a]) @ A[a].T
            kss = os[a]
        else:
            iq, wq = grid.interpolation(thq[:, 0], thq[:, 1])
            E = torch.zeros(15, grid.size).scatter_add(1, iq, wq)
            Kn = k_dense(th, th, ls[a, 0], os[a])
            ks, kss = E @ Kn @ A[a].T, torch.diagonal(E @ Kn @ E.T)
        mu = ks @ torch.linalg.solve(S, f[:, a])
        var = kss - (ks * torch.linalg.solve(S, ks.T).T).sum(-1)
        tol = 1e-8 if method == "exact" else 1e-6
        torch.testing.assert_close(post.mean[:, a], mu, rtol=tol, atol=1e-10)
        torch.testing.assert_close(post.variance[:, a], var, rtol=tol, atol=1e-10)
    model.save(tmp_path / "m.pt")
    back = irft.InverseRFT.load(tmp_path / "m.pt")
    torch.testing.assert_close(back.noise_scale, s)
    assert back.loss().item() == pytest.approx(model.loss().item(), rel=1e-10)
    pred = model.predict_forces(c[:4], include_noise=True, noise_scale=s[:4])
    plain = model.predict_forces(c[:4])
    torch.testing.assert_close(pred.variance - plain.variance, noise * s[:4] ** 2)
    with pytest.raises(ValueError, match="noise_scale must be"):
        irft.InverseRFT(c, f, noise_scale=torch.ones(5))
    with pytest.raises(ValueError, match="positive"):
        irft.InverseRFT(c, f, noise_scale=-torch.ones(24))
