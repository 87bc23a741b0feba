"""Every backend against the dense reference (explicit W, explicit K, torch Cholesky): likelihood,
the gradient of every hyperparameter, map and force posteriors (marginal and joint), conditioning,
heteroscedastic noise. Observations and pairs: 1e-8 relative; spectral: within 1e-6 at the default
tolerance (its reported kernel truncation bound is 1e-7). The reference is the paper's plain marginal
likelihood, so the models here are built with ``priors=None`` (the priors' term is checked in
test_priors.py)."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.rft import Contacts, FourierStressMap

from .dense_reference import W_dense, axis_reference, k_dense

P = math.pi
BACKENDS = ["observations", "pairs", "spectral"]
TOL = {"observations": 1e-8, "pairs": 1e-8, "spectral": 1e-6}


def random_contacts(T=25, M=4, seed=0, repeated=False):
    """Random angles, zero-weight segments, mixed left/right motion (sign of weight_x); with
    ``repeated`` the angles come from a few values (many segments share a pair); with
    ``repeated="translating"`` a translating toe: one gamma per row, one beta per segment slot (its
    sign flipped on some rows, as the canonical mirror does)."""
    g = torch.Generator().manual_seed(seed)
    beta = (torch.rand(T, M, generator=g) - 0.5) * P
    gamma = (torch.rand(T, M, generator=g) - 0.5) * P
    if repeated == "translating":
        flip = torch.where(torch.rand(T, 1, generator=g) < 0.3, -1.0, 1.0)
        beta = flip * beta[:1].expand(T, M)
        gamma = gamma[:, :1].expand(T, M).clone()
    elif repeated:
        beta, gamma = (beta * 1.3).round() / 1.3, (gamma * 1.3).round() / 1.3
    w = torch.rand(T, M, generator=g) * 3
    w[torch.rand(T, M, generator=g) < 0.3] = 0.0  # above the surface / padding
    w[0] = 0.0  # one observation with no contact at all
    sign = torch.where(torch.rand(T, 1, generator=g) < 0.5, -1.0, 1.0)
    return Contacts(beta=beta, gamma=gamma, weight_x=-sign * w, weight_z=w)


def set_hypers(model, seed=1, low=0.4):
    g = torch.Generator().manual_seed(seed)
    model.hypers.lengthscale = low + torch.rand(2, 1, 4, generator=g)
    model.hypers.outputscale = torch.tensor([0.05, 0.2])
    model.hypers.noise = torch.tensor([0.03, 0.07])


def data(T=25, M=4, seed=0, repeated=False):
    c = random_contacts(T, M, seed, repeated)
    f = irft.rft.forces(FourierStressMap.generic(0.5, 0.4), c)
    f = f + 0.05 * torch.randn(len(c), 2, generator=torch.Generator().manual_seed(seed + 3))
    return c, f


def prior_mean(model, c, a, w):
    if model.prior_mean_kind != "physics":
        return None
    shape = FourierStressMap.generic()(c.beta, c.gamma)[..., a]
    return model.hypers.mean_scales.detach()[a] * (w * shape).sum(-1)


def references(model, c, f):
    ls, os, noise = model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach()
    return [axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], prior_mean(model, c, a, w))
            for a, w in enumerate((c.weight_x, c.weight_z))]


@pytest.mark.parametrize("repeated", [False, True, "translating"])
@pytest.mark.parametrize("prior", ["zero", "physics"])
@pytest.mark.parametrize("method", BACKENDS)
def test_likelihood_and_every_gradient_match_dense(method, prior, repeated):
    c, f = data(repeated=repeated)
    model = irft.InverseRFT(c, f, prior_mean=prior, method=method, priors=None, hyper_posterior="map", li_basis=False)
    assert model.method == method
    set_hypers(model)
    params = dict(model.hypers.named_parameters())
    ours = model.loss()
    g_ours = torch.autograd.grad(ours, list(params.values()))

    def dense():
        ls, os, noise = model.hypers.lengthscale, model.hypers.outputscale, model.hypers.noise
        total = 0.0
        for a, w in enumerate((c.weight_x, c.weight_z)):
            mean = None
            if prior == "physics":
                mean = model.hypers.mean_scales[a] * (w * FourierStressMap.generic()(c.beta, c.gamma)[..., a]).sum(-1)
            total = total - axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], mean)[0]
        return total

    ref = dense()
    g_ref = torch.autograd.grad(ref, list(params.values()))
    tol = TOL[method]
    assert ours.item() == pytest.approx(ref.item(), rel=tol)
    for name, a, b in zip(params, g_ours, g_ref):
        torch.testing.assert_close(a, b, rtol=tol * 10, atol=tol * b.abs().max().item() + 1e-12,
                                   msg=f"gradient of {name}")


@pytest.mark.parametrize("prior", ["zero", "physics"])
@pytest.mark.parametrize("method", BACKENDS)
def test_map_and_force_posteriors_match_dense(method, prior):
    c, f = data(T=30, M=5, seed=4, repeated=(method == "pairs"))
    model = irft.InverseRFT(c, f, prior_mean=prior, method=method, priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=2)
    refs = references(model, c, f)
    tol = TOL[method]
    th = (torch.rand(40, 2, generator=torch.Generator().manual_seed(9)) - 0.5) * P
    post = model.stress_map(th[:, 0], th[:, 1])
    for a in range(2):
        ms = None
        if prior == "physics":
            ms = model.hypers.mean_scales.detach()[a] * FourierStressMap.generic()(th[:, 0], th[:, 1])[:, a]
        mu, var = refs[a][1](th, ms)
        torch.testing.assert_close(post.mean[:, a], mu, rtol=tol, atol=tol * mu.abs().max().item())
        torch.testing.assert_close(post.variance[:, a], var, rtol=tol, atol=tol * var.abs().max().item())
    cs = random_contacts(T=12, M=3, seed=7)
    pred = model.predict_forces(cs)
    for a, w in enumerate((cs.weight_x, cs.weight_z)):
        mu, var = refs[a][2](cs, w, prior_mean(model, cs, a, w))
        torch.testing.assert_close(pred.mean[:, a], mu, rtol=tol, atol=tol * mu.abs().max().item())
        torch.testing.assert_close(pred.variance[:, a], var, rtol=tol, atol=tol * var.abs().max().item())


@pytest.mark.parametrize("method", BACKENDS)
def test_translating_toe_posteriors_match_dense(method):
    """A translating toe (one gamma per row): the observations backend's kernel takes its product form
    (``RowSeparableRFTOperator``); posteriors of translating and of general queries match dense."""
    from irft_torch.gp import RowSeparableRFTOperator

    c, f = data(T=30, M=4, seed=5, repeated="translating")
    model = irft.InverseRFT(c, f, prior_mean="physics", method=method, priors=None, hyper_posterior="map",
                            li_basis=False)
    set_hypers(model, seed=4)
    if method == "observations":
        gp = model.backend.gp
        assert isinstance(gp.covar_module.forward(*gp.train_inputs * 2), RowSeparableRFTOperator)
    refs = references(model, c, f)
    tol = TOL[method]
    for cs in (random_contacts(T=9, M=3, seed=6, repeated="translating"), random_contacts(T=7, M=5, seed=8)):
        pred = model.predict_forces(cs)
        for a, w in enumerate((cs.weight_x, cs.weight_z)):
            mu, var = refs[a][2](cs, w, prior_mean(model, cs, a, w))
            torch.testing.assert_close(pred.mean[:, a], mu, rtol=tol, atol=tol * mu.abs().max().item())
            torch.testing.assert_close(pred.variance[:, a], var, rtol=tol, atol=tol * var.abs().max().item())


@pytest.mark.parametrize("method", BACKENDS)
def test_joint_covariance_and_cross_covariance_match_dense(method):
    c, f = data(T=20, M=3, seed=21)
    model = irft.InverseRFT(c, f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=3)
    ls, os, noise = model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach()
    q1, q2 = random_contacts(T=6, M=2, seed=22), random_contacts(T=4, M=4, seed=23)
    joint = model.backend.posterior(q1, covariance=True).covariance
    cross = model.backend.cross_covariance(q1, q2)
    th = torch.stack([c.beta.reshape(-1), c.gamma.reshape(-1)], -1)
    tol = TOL[method]
    for a, key in enumerate(("weight_x", "weight_z")):
        W = W_dense(getattr(c, key))
        K = k_dense(th, th, ls[a, 0], os[a])
        S = W @ K @ W.T + noise[a] * torch.eye(len(c))

        def prior_cov(qa, qb):
            ta = torch.stack([qa.beta.reshape(-1), qa.gamma.reshape(-1)], -1)
            tb = torch.stack([qb.beta.reshape(-1), qb.gamma.reshape(-1)], -1)
            Wa, Wb = W_dense(getattr(qa, key)), W_dense(getattr(qb, key))
            return Wa @ k_dense(ta, tb, ls[a, 0], os[a]) @ Wb.T, Wa @ k_dense(ta, th, ls[a, 0], os[a]) @ W.T, \
                Wb @ k_dense(tb, th, ls[a, 0], os[a]) @ W.T

        kab, ka, kb = prior_cov(q1, q1)
        want = kab - ka @ torch.linalg.solve(S, kb.T)
        torch.testing.assert_close(joint[a], want, rtol=tol, atol=tol * want.abs().max().item())
        kab, ka, kb = prior_cov(q1, q2)
        want = kab - ka @ torch.linalg.solve(S, kb.T)
        torch.testing.assert_close(cross[a], want, rtol=tol, atol=tol * want.abs().max().item())


@pytest.mark.parametrize("with_forces", [True, False])
@pytest.mark.parametrize("method", BACKENDS)
def test_conditioning_equals_a_batch_posterior(method, with_forces):
    """condition(c2, f2) gives the posterior of a model on (c1 + c2, f1 + f2) at the same
    hyperparameters; without forces the covariance is the same and the mean does not move."""
    c, f = data(T=30, M=4, seed=31, repeated=(method == "pairs"))
    c1, f1, c2, f2 = c[:18], f[:18], c[18:], f[18:]
    base = irft.InverseRFT(c1, f1, method=method, priors=None, hyper_posterior="map", li_basis=False)
    full = irft.InverseRFT(c, f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    for m in (base, full):
        set_hypers(m, seed=5)
    q = random_contacts(T=8, M=3, seed=33)
    before = base.backend.posterior(q, covariance=True)
    cond = base.backend.condition(c2, f2 if with_forces else None)
    got = cond.posterior(q, covariance=True)
    want = full.backend.posterior(q, covariance=True)
    tol = TOL[method]
    torch.testing.assert_close(got.covariance, want.covariance, rtol=tol, atol=tol * want.covariance.abs().max())
    target = want.mean if with_forces else before.mean
    torch.testing.assert_close(got.mean, target, rtol=tol, atol=tol * target.abs().max())
    # the original backend is untouched
    torch.testing.assert_close(base.backend.posterior(q, covariance=True).covariance, before.covariance)


@pytest.mark.parametrize("method", BACKENDS)
def test_streaming_equals_batch(method):
    c, f = data(T=40, M=3, seed=41, repeated=(method == "pairs"))
    batch = irft.InverseRFT(c, f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    stream = irft.InverseRFT(c[:15], f[:15], method=method, priors=None, hyper_posterior="map", li_basis=False)
    for m in (batch, stream):
        set_hypers(m, seed=7)
    stream.add_data(c[15:30], f[15:30])
    stream.add_data(c[30:], f[30:])
    b = torch.linspace(-1.4, 1.4, 11)
    pb, ps = batch.stress_map(b, b.flip(0)), stream.stress_map(b, b.flip(0))
    tol = TOL[method]
    torch.testing.assert_close(ps.mean, pb.mean, rtol=tol, atol=tol * pb.mean.abs().max())
    torch.testing.assert_close(ps.variance, pb.variance, rtol=tol, atol=tol * pb.variance.abs().max())
    assert stream.loss().item() == pytest.approx(batch.loss().item(), rel=tol)


@pytest.mark.parametrize("method", BACKENDS)
def test_relative_noise_scale_is_heteroscedastic_noise_exactly(method, tmp_path):
    """noise_scale s: noise variance sigma^2 s_t^2 per sample, against a dense model with
    S = W K W^T + sigma^2 diag(s^2) (no whitening in the reference), and through save/load."""
    c, f = data(T=24, M=3, seed=13, repeated=(method == "pairs"))
    s = 0.5 + torch.rand(24, 2, generator=torch.Generator().manual_seed(2))
    model = irft.InverseRFT(c, f, noise_scale=s, method=method, priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=6)
    th = torch.stack([c.beta.reshape(-1), c.gamma.reshape(-1)], -1)
    A = [W_dense(c.weight_x), W_dense(c.weight_z)]
    ls, os, noise = model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach()
    tol = TOL[method]
    total = 0.0
    covs = []
    for a in range(2):
        S = A[a] @ k_dense(th, th, ls[a, 0], os[a]) @ A[a].T + noise[a] * torch.diag(s[:, a] ** 2)
        covs.append(S)
        mll = torch.distributions.MultivariateNormal(torch.zeros(24), S).log_prob(f[:, a])
        total = total + (mll + torch.log(s[:, a]).sum()) / 24  # the whitened likelihood's Jacobian term
    assert -model.loss().item() == pytest.approx(total.item(), rel=tol)
    thq = (torch.rand(15, 2, generator=torch.Generator().manual_seed(3)) - 0.5) * P
    post = model.stress_map(thq[:, 0], thq[:, 1])
    for a in range(2):
        ks = k_dense(thq, th, ls[a, 0], os[a]) @ A[a].T
        mu = ks @ torch.linalg.solve(covs[a], f[:, a])
        var = os[a] - (ks * torch.linalg.solve(covs[a], ks.T).T).sum(-1)
        torch.testing.assert_close(post.mean[:, a], mu, rtol=tol, atol=tol * mu.abs().max())
        torch.testing.assert_close(post.variance[:, a], var, rtol=tol, atol=tol * var.abs().max())
    model.save(tmp_path / "m.pt")
    back = irft.InverseRFT.load(tmp_path / "m.pt")
    assert back.method == method
    torch.testing.assert_close(back.noise_scale, s)
    assert back.loss().item() == pytest.approx(model.loss().item(), rel=1e-10)
    pred = model.predict_forces(c[:4], include_noise=True, noise_scale=s[:4])
    plain = model.predict_forces(c[:4])
    torch.testing.assert_close(pred.variance - plain.variance, noise * s[:4] ** 2)


@pytest.mark.parametrize("length", [0.2, 0.5, 1.0, 2.0, 4.0])
def test_spectral_within_its_truncation_bound_for_lengthscales_02_to_4(length):
    c, f = data(T=20, M=3, seed=51)
    model = irft.InverseRFT(c, f, method="spectral", lengthscale=length, priors=None, hyper_posterior="map",
                            li_basis=False)
    ref = irft.InverseRFT(c, f, method="observations", lengthscale=length, priors=None, hyper_posterior="map",
                          li_basis=False)
    bound = model.truncation_error()
    assert (bound <= 1e-7).all() and (bound >= 0).all()
    assert ref.truncation_error().abs().max() == 0
    assert model.loss().item() == pytest.approx(ref.loss().item(), rel=1e-6)
    b = torch.linspace(-1.5, 1.5, 13)
    pm, pr = model.stress_map(b[:, None], b[None, :]), ref.stress_map(b[:, None], b[None, :])
    torch.testing.assert_close(pm.mean, pr.mean, rtol=1e-6, atol=1e-6 * pr.mean.abs().max())
    torch.testing.assert_close(pm.variance, pr.variance, rtol=1e-6, atol=1e-6 * pr.variance.abs().max())


def test_float32_spectral_basis_is_sized_by_the_kernel_not_by_float32_round_off():
    """The Fourier basis is a property of the kernel (lengthscales and tol), not of the storage dtype:
    a float32 model gets the basis a float64 one gets, reports a truncation error within tol, and its
    likelihood and map match the dense float64 reference to float32 precision."""
    c, f = data(T=20, M=3, seed=51)
    m32 = irft.InverseRFT(c, f, method="spectral", dtype=torch.float32, priors=None, hyper_posterior="map",
                          li_basis=False)
    m64 = irft.InverseRFT(c, f, method="spectral", priors=None, hyper_posterior="map", li_basis=False)
    for m in (m32, m64):
        set_hypers(m)
        m.loss()  # the basis follows the new lengthscales
    assert (m32.truncation_error() <= 1e-7).all()
    assert m32.backend.basis == m64.backend.basis
    c64, f64 = c.to(dtype=torch.float64), f.double()
    refs = references(m64, c64, f64)
    assert m32.loss().item() == pytest.approx(-(refs[0][0] + refs[1][0]).item(), rel=1e-4)
    th = torch.tensor([[0.3, -0.2], [-1.1, 0.9]], dtype=torch.float64)
    post = m32.stress_map(th[:, 0].float(), th[:, 1].float())
    for a in range(2):
        mu, var = refs[a][1](th)
        torch.testing.assert_close(post.mean[:, a].double(), mu, rtol=1e-4, atol=1e-4 * mu.abs().max())
        torch.testing.assert_close(post.variance[:, a].double(), var, rtol=1e-3, atol=1e-3 * var.abs().max())


def test_spectral_basis_grows_when_a_lengthscale_shrinks():
    c, f = data(T=20, M=3, seed=52)
    model = irft.InverseRFT(c, f, method="spectral", lengthscale=2.0, priors=None, hyper_posterior="map",
                            li_basis=False)
    small = model.backend.basis.size
    model.hypers.lengthscale = torch.full((2, 1, 4), 0.3)
    assert model.truncation_error().max() > 1e-5  # the old basis cannot represent it
    model.loss()  # outside a fit loop every evaluation checks the basis
    assert model.backend.basis.size > small and model.truncation_error().max() <= 1e-7
    ref = irft.InverseRFT(c, f, method="observations", priors=None, hyper_posterior="map", li_basis=False)
    ref.hypers.load_state_dict(model.hypers.state_dict())
    assert model.loss().item() == pytest.approx(ref.loss().item(), rel=1e-6)


def test_spectral_basis_shrinks_when_the_lengthscales_grow_back():
    """A fit whose lengthscales grew back after a short start moves to the smaller basis they need (``shrink``): the
    likelihood and its gradient then match the observations space within the spectral tolerance, and growing back
    cuts the statistics kept from the wider basis (no second pass over the data)."""
    from unittest import mock

    from irft_torch.gp.backends import spectral

    c, f = data(T=40, M=3, seed=53)
    model = irft.InverseRFT(c, f, method="spectral", lengthscale=0.3, priors=None, hyper_posterior="map",
                            li_basis=False)
    wide = model.backend.basis
    assert not model.backend.shrink()  # the basis is what these lengthscales need
    model.hypers.lengthscale = torch.full((2, 1, 4), 2.0)
    assert model.backend.shrink()
    small = model.backend.basis
    assert small.n_beta < wide.n_beta and small.n_gamma < wide.n_gamma
    assert model.truncation_error().max() <= 1e-7
    ref = irft.InverseRFT(c, f, method="observations", priors=None, hyper_posterior="map", li_basis=False)
    ref.hypers.load_state_dict(model.hypers.state_dict())
    for m in (model, ref):
        m.hypers.zero_grad()
        m.loss().backward()
    assert model.loss().item() == pytest.approx(ref.loss().item(), rel=1e-6)
    for (name, p), q in zip(model.hypers.named_parameters(), ref.hypers.parameters()):
        torch.testing.assert_close(p.grad, q.grad, rtol=1e-5, atol=1e-7, msg=name)
    model.hypers.lengthscale = torch.full((2, 1, 4), 0.36)  # with refresh's margin, within the wide basis
    with mock.patch.object(spectral.SpectralBackend, "statistics", side_effect=AssertionError("a pass")):
        assert model.backend.refresh()
    assert small.size < model.backend.basis.size <= wide.size
    ref.hypers.load_state_dict(model.hypers.state_dict())
    assert model.loss().item() == pytest.approx(ref.loss().item(), rel=1e-6)


def test_a_fit_ends_in_the_basis_its_last_lengthscales_need():
    """Adam from short lengthscales on a smooth medium: the basis the start needed is not kept to the end."""
    c, f = data(T=60, M=3, seed=54)
    model = irft.InverseRFT(c, f, method="spectral", lengthscale=0.25, hyper_posterior="map", li_basis=False)
    start = model.backend.basis.size
    model.fit(n_iter=120, progress=False)
    from irft_torch.gp.backends.spectral import SHRINK_FACTOR, step_flops
    from irft_torch.gp.kernels.fourier import FourierBasis

    need = FourierBasis.for_lengthscale(model.hypers.lengthscale * 0.85, 1e-7)
    assert model.hypers.lengthscale.min() > 0.4  # the case: the lengthscales grew
    assert model.backend.basis.size < start
    assert step_flops(60, model.backend.basis) < step_flops(60, need) / SHRINK_FACTOR  # within the rule's hysteresis
    assert model.truncation_error().max() <= 1e-7


def test_independent_segment_variance_is_the_papers_formula():
    c, f = data(T=20, M=4, seed=5)
    model = irft.InverseRFT(c, f, method="observations", priors=None, hyper_posterior="map", li_basis=False)
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
    torch.testing.assert_close(noisy.variance - pred.variance, torch.tensor([0.03, 0.07]).expand(6, 2))


@pytest.mark.parametrize("method", BACKENDS)
def test_zero_weight_padding_changes_nothing(method):
    c, f = data(T=15, M=3, seed=11, repeated=(method == "pairs"))
    m1 = irft.InverseRFT(c, f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    m2 = irft.InverseRFT(c.pad_segments(7), f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    for m in (m1, m2):
        set_hypers(m)
    assert m1.loss().item() == pytest.approx(m2.loss().item(), rel=1e-10)
    b = torch.linspace(-1, 1, 9)
    torch.testing.assert_close(m1.stress_map(b, b).mean, m2.stress_map(b, b).mean, rtol=1e-9, atol=1e-12)


def test_mirror_outside_canonical_square():
    c, f = data(T=15, M=3, seed=12)
    m = irft.InverseRFT(c, f, priors=None, hyper_posterior="map", li_basis=False)
    b, g = torch.tensor([0.3]), torch.tensor([2.5])  # motion with a -x component
    inside = m.stress_map(-b, P - g)
    outside = m.stress_map(b, g)
    torch.testing.assert_close(outside.mean, inside.mean * torch.tensor([-1.0, 1.0]))
    torch.testing.assert_close(outside.variance, inside.variance)


def test_contacts_points_are_one_segment_functionals():
    b = torch.tensor([[0.3, -0.2], [1.0, 0.1]])
    g = torch.tensor([2.5, 0.4])
    pts = Contacts.points(b, g)
    assert pts.shape == (4, 1)
    smap = FourierStressMap.generic()
    torch.testing.assert_close(irft.rft.forces(smap, pts), smap(*torch.broadcast_tensors(b, g)).reshape(4, 2))
    with pytest.raises(ValueError, match="beta contains NaN"):
        Contacts.points(torch.tensor([float("nan")]), torch.tensor([0.0]))


def test_statistics_of_two_recordings_add_up_to_one_pass_over_both():
    from irft_torch.gp.backends.spectral import spectral_statistics
    from irft_torch.gp.kernels.fourier import FourierBasis

    c, f = data(T=50, M=4, seed=61)
    basis = FourierBasis(8, 9)  # more than lengthscales >= 1.5 need at the default tolerance
    a = spectral_statistics(c[:20], f[:20], basis, chunk=7)
    b = spectral_statistics(c[20:], f[20:], basis, chunk=13)
    both = spectral_statistics(c, f, basis)
    merged = a + b
    assert merged.n == both.n == 50
    for k in ("P", "b", "yy", "bg", "yg", "gg"):
        torch.testing.assert_close(getattr(merged, k), getattr(both, k), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="different feature spaces"):
        a + spectral_statistics(c[:5], f[:5], FourierBasis(8, 8))
    # a backend that merges statistics computed elsewhere has the posterior of one fit on everything
    full = irft.InverseRFT(c, f, method="spectral", priors=None, hyper_posterior="map", li_basis=False)
    part = irft.InverseRFT(c[:20], f[:20], method="spectral", priors=None, hyper_posterior="map", li_basis=False)
    for m in (full, part):
        set_hypers(m, seed=9, low=1.5)
    part.backend.basis = full.backend.basis = basis
    full.backend._set_stats(spectral_statistics(c, f, basis))
    part.backend._set_stats(spectral_statistics(c[:20], f[:20], basis))
    part.backend.merge(spectral_statistics(c[20:], f[20:], basis))
    q = random_contacts(T=5, M=3, seed=62)
    torch.testing.assert_close(part.backend.posterior(q).mean, full.backend.posterior(q).mean, rtol=1e-9, atol=1e-12)
    assert part.backend.negative_log_likelihood().sum().item() == pytest.approx(
        full.backend.negative_log_likelihood().sum().item(), rel=1e-10)


@pytest.mark.parametrize("method", ["pairs", "spectral"])
def test_segments_moving_both_ways_in_one_sample_match_dense(method):
    """A turning toe: within one sample some segments move toward +x and some toward -x (weight_x
    signs differ along the row), so the x and z feature rows differ: the general accumulation."""
    c = random_contacts(T=25, M=4, seed=71, repeated=(method == "pairs"))
    sign = torch.where(torch.rand(25, 4, generator=torch.Generator().manual_seed(72)) < 0.5, -1.0, 1.0)
    c = Contacts(c.beta, c.gamma, sign * c.weight_z, c.weight_z)
    f = irft.rft.forces(FourierStressMap.generic(0.5, 0.4), c) + 0.05 * torch.randn(25, 2)
    model = irft.InverseRFT(c, f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=4)
    ref = sum(-r[0] for r in references(model, c, f))
    assert model.loss().item() == pytest.approx(ref.item(), rel=TOL[method])


def test_many_queries_in_a_row_never_reuse_another_querys_structure():
    """Regression: the composite kernel cached its segment structure by the inputs' ids; a freed
    query's id reused by the next one gave that one the old structure (a wrong, non-PSD covariance).
    Twenty fresh queries under no_grad, each against the pairs backend (exact, no such cache)."""
    c, f = data(T=20, M=3, seed=81, repeated=True)
    obs = irft.InverseRFT(c, f, method="observations", priors=None, hyper_posterior="map", li_basis=False)
    pairs = irft.InverseRFT(c, f, method="pairs", priors=None, hyper_posterior="map", li_basis=False)
    for m in (obs, pairs):
        set_hypers(m, seed=8)
    with torch.no_grad():
        for k in range(20):
            q = random_contacts(T=6, M=3, seed=100 + k)  # one shape: the freed tensors' ids come back
            a = obs.backend.posterior(q, covariance=True).covariance
            b = pairs.backend.posterior(q, covariance=True).covariance
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10 * b.abs().max().item())


def test_composite_kernel_cache_never_serves_another_tensor():
    from irft_torch.gp.kernels.angle import AngleKernel, RFTCompositeKernel
    from irft_torch.gp.kernels.encoding import encode_contacts

    kern = RFTCompositeKernel(AngleKernel())
    ids = set()
    for k in range(30):
        rows = encode_contacts(random_contacts(T=6, M=3, seed=200 + k))  # freed each round: ids come back
        ids.add(id(rows))
        got = kern(rows).to_dense()
        want = RFTCompositeKernel(AngleKernel())(rows).to_dense()  # a fresh kernel, no cache
        torch.testing.assert_close(got, want)
        # the cache holds the tensor it was built for, so no later tensor can take its id
        assert kern._structure_key[0] is rows


def test_the_one_rbf_is_gpytorchs_scalekernel_rbf():
    """Every backend evaluates the kernel through gp.kernels.embedding.rbf with the stock
    ScaleKernel(RBFKernel)'s hyperparameters: it equals that module's own forward."""
    from irft_torch.gp.kernels.angle import AngleKernel, angle_covariance
    from irft_torch.gp.kernels.embedding import embed_angles

    k = AngleKernel()
    k.lengthscale = 0.3 + torch.rand(2, 1, 4, generator=torch.Generator().manual_seed(1))
    k.outputscale = torch.tensor([0.3, 2.0])
    g = torch.Generator().manual_seed(2)
    b1, g1, b2, g2 = ((torch.rand(n, generator=g) - 0.5) * P for n in (7, 7, 5, 5))
    ours = angle_covariance(k, b1, g1, b2, g2)
    stock = k(embed_angles(b1, g1), embed_angles(b2, g2)).to_dense()
    torch.testing.assert_close(ours, stock, rtol=1e-12, atol=1e-14)


def test_observations_posterior_is_gpytorchs_own_prediction():
    """The observations backend factors the training covariance once; its posterior equals what
    gpytorch's ExactGP predicts from the same lazy W K W^T."""
    import gpytorch

    from irft_torch.gp.kernels.encoding import encode_contacts

    c, f = data(T=20, M=3, seed=91)
    model = irft.InverseRFT(c, f, method="observations", prior_mean="physics", priors=None, hyper_posterior="map",
                            li_basis=False)
    set_hypers(model, seed=10)
    q = random_contacts(T=6, M=3, seed=92)
    ours = model.backend.posterior(q, covariance=True)
    model.gp.eval()
    with torch.no_grad(), gpytorch.settings.max_cholesky_size(2**31), gpytorch.settings.fast_pred_var(False):
        out = model.gp(encode_contacts(q, model.backend.n_segments))
        want_mean, want_cov = out.mean, out.covariance_matrix
    torch.testing.assert_close(ours.mean, want_mean, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(ours.covariance, want_cov, rtol=1e-7, atol=1e-9 * want_cov.abs().max().item())


@pytest.mark.parametrize("prior", ["zero", "physics"])
def test_observations_likelihood_is_gpytorchs_exact_marginal_likelihood(prior):
    """The observations backend's training loss (one Cholesky of the kernel's own lazy W K W^T) equals
    gpytorch's ExactMarginalLogLikelihood of its ExactGP, value and every gradient, tied noise too."""
    import gpytorch

    c, f = data(T=20, M=3, seed=93, repeated=True)
    for tied in (False, True):
        model = irft.InverseRFT(c, f, method="observations", prior_mean=prior, priors=None, tied_noise=tied,
                                hyper_posterior="map", li_basis=False)
        set_hypers(model, seed=11)
        params = [p for p in model.hypers.parameters() if p.requires_grad]
        ours = model.backend.negative_log_likelihood()
        g_ours = torch.autograd.grad(ours.sum(), params)
        model.gp.train()
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(model.hypers.likelihood, model.gp)
        with gpytorch.settings.max_cholesky_size(2**31):
            theirs = -mll(model.gp(*model.gp.train_inputs), model.gp.train_targets)
        g_theirs = torch.autograd.grad(theirs.sum(), params)
        torch.testing.assert_close(ours, theirs, rtol=1e-10, atol=1e-12)
        for a, b in zip(g_ours, g_theirs):
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("method", BACKENDS)
def test_sampled_maps_have_the_dense_posterior_mean_and_covariance(method):
    # 20000 maps drawn at 5 angle pairs (one outside the canonical square: alpha_x's mirror sign) against
    # the dense posterior written out here: mean and joint covariance within Monte-Carlo error
    c, f = data(T=20, M=3, seed=31)
    model = irft.InverseRFT(c, f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=5)
    beta = torch.tensor([[0.0, 0.3, -1.2], [0.9, 1.2, 2.0]])  # (2, 3): 6 points, beta = 2.0 mirrored in
    gamma = torch.tensor([[0.1, -0.8, 0.5], [1.3, -0.2, 0.4]])
    n = 20000
    draws = model.sample_maps(beta, gamma, n, generator=torch.Generator().manual_seed(0))
    assert draws.shape == (n, 2, 3, 2)
    q = Contacts.points(beta, gamma)  # the mirror's sign on weight_x, written by the contacts
    for a, (ref, key) in enumerate(zip(references(model, c, f), ("weight_x", "weight_z"))):
        mean, cov = ref[2](q, getattr(q, key), full=True)
        x = draws[..., a].reshape(n, -1)
        sd = cov.diagonal().sqrt()
        assert ((x.mean(0) - mean).abs() < 5 * sd / n**0.5 + 1e-9).all(), (x.mean(0), mean)
        emp = torch.cov(x.T)
        # sampling error of a covariance entry: sd_i sd_j sqrt((1 + rho^2) / n) < 1.5 sd_i sd_j / sqrt(n)
        assert ((emp - cov).abs() < 5 * 1.5 * torch.outer(sd, sd) / n**0.5 + 1e-9).all(), (emp, cov)
    with pytest.raises(ValueError, match="n must be a positive integer"):
        model.sample_maps(beta, gamma, 0)


def test_psd_root_of_rank_deficient_and_slightly_indefinite_covariances():
    from irft_torch.gp.posterior import _psd_root

    g = torch.Generator().manual_seed(0)
    A = torch.randn(50, 5, generator=g)
    low = A @ A.T  # rank 5 of 50: Cholesky needs the tiny jitter
    L = _psd_root(low)
    torch.testing.assert_close(L @ L.T, low, rtol=0, atol=1e-9 * low.diagonal().max().item())
    # rounding made it indefinite (eigenvalue -1e-6 of the largest): no jitter tried suffices, the
    # eigendecomposition's root clamps it; L L^T is then within that eigenvalue of the matrix
    Q, _ = torch.linalg.qr(torch.randn(50, 50, generator=g))
    lam = torch.linspace(0, 1, 50)
    lam[0] = -1e-6
    bad = Q @ torch.diag(lam) @ Q.T
    L = _psd_root(bad)
    assert torch.isfinite(L).all()
    torch.testing.assert_close(L @ L.T, bad, rtol=0, atol=2e-6)
