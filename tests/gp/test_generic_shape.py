"""The generic shape with an uncertain scale (``InverseRFT(..., li_basis=True, generic_shape=True)``,
``gp.kernels.li_basis``): u_a g_a(theta) g_a(theta') added to the kernel, g_a Li et al.'s generic map. Each backend
against the model written densely, with g evaluated from the published coefficients (``FourierStressMap.generic``, not
from
the term's own coefficients); the closed-form gradient against autograd and finite differences; the term as a mean
of uncertain scale, by hand (Bayesian linear regression); the prior, the filter, save/load and the options."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch import InverseRFT
from irft_torch.gp.backends.closed_form import autograd_only
from irft_torch.gp.batch_fit import shares_fit
from irft_torch.gp.kernels.li_basis import generic_coefficients, li_features
from irft_torch.rft import Contacts, forces
from irft_torch.rft.stress_maps import FourierStressMap

from .test_li_basis import LI, LS, OS, _data, check_learned_surface
from .test_li_basis import _dense as _dense_li

F64 = torch.float64
U = torch.tensor([0.5, 1.7], dtype=F64)  # the generic shape's variance per map, (N/cm^3)^2
GENERIC = FourierStressMap.generic().double()


def _g(th: torch.Tensor, a: int) -> torch.Tensor:
    """The generic map of axis a at angle pairs (n, 2), from the published coefficients."""
    return GENERIC(th[:, 0], th[:, 1])[:, a]


def _set(model, noise, u=U):
    model.hypers.lengthscale = LS[:, None, :]
    model.hypers.outputscale = OS
    model.hypers.noise = noise
    model.hypers.li.variance = LI
    if u is not None:
        model.hypers.li.generic_variance = u


def _dense(c, f, a, noise, u=U):
    """``test_li_basis._dense`` (nll, map and force posteriors of axis a, written densely) with the generic shape's
    term u_a g_a(theta) g_a(theta'), g from the published coefficients."""
    return _dense_li(c, f, a, noise, extra=lambda t1, t2: u[a] * _g(t1, a)[:, None] * _g(t2, a)[None, :])


def test_the_coefficients_give_the_published_generic_map():
    g = torch.Generator().manual_seed(0)
    th = (torch.rand(200, 2, generator=g, dtype=F64) - 0.5) * torch.tensor([math.pi, 2 * math.pi], dtype=F64)
    c = generic_coefficients(F64)
    assert c.shape == (2, 9)
    torch.testing.assert_close(li_features(th[:, 0], th[:, 1]) @ c.T, GENERIC(th[:, 0], th[:, 1]), rtol=0, atol=1e-12)
    # alpha_z(0, pi/2) = 1: a horizontal plate pushed straight down, per unit zeta (Li et al.'s normalization)
    z = li_features(torch.zeros((), dtype=F64), torch.tensor(math.pi / 2, dtype=F64)) @ c[1]
    assert float(z) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("kind,method,terms", [
    ("rotating", "observations", None), ("rotating", "pairs", ["PairsRBF", "LiBasisTerm", "LiBasisTerm"]),
    ("translating", "observations", ["RowSeparable", "LiBasisTerm", "LiBasisTerm"]),
    ("itoe", "pairs", ["PairsRBF", "LiBasisTerm", "LiBasisTerm"]),
    ("rotating", "spectral", ["KroneckerFourier", "LiBasisTerm", "LiBasisTerm"])])
def test_each_backend_is_the_dense_model_with_the_generic_term(kind, method, terms):
    c, f = _data(kind)
    model = InverseRFT(c, f, method=method, li_basis=True, generic_shape=True, hyper_posterior="map")
    noise = torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0)
    _set(model, noise)
    cf = model.backend.closed_form()
    if terms is not None:
        assert [type(t).__name__ for t in cf.terms] == terms
    th_s = (torch.rand(25, 2, generator=torch.Generator().manual_seed(4), dtype=F64) - 0.5) * math.pi
    post = model.stress_map(th_s[:, 0], th_s[:, 1])
    fpost = model.predict_forces(c[::3])
    with torch.no_grad():
        nll = model.backend.negative_log_likelihood()
    tol = 1e-5 if method == "spectral" else 1e-8  # the spectral basis truncates the RBF part at 1e-7
    for a in range(2):
        ref_nll, map_post, force_post = _dense(c, f, a, model.hypers.noise[a].detach())
        mean, var = map_post(th_s)
        torch.testing.assert_close(post.mean[:, a], mean, rtol=tol, atol=tol * float(mean.abs().max()))
        torch.testing.assert_close(post.variance[:, a], var, rtol=10 * tol, atol=tol * float(var.max()))
        fm, fv = force_post(c[::3])
        torch.testing.assert_close(fpost.mean[:, a], fm, rtol=tol, atol=tol * float(fm.abs().max()))
        torch.testing.assert_close(fpost.variance[:, a], fv, rtol=100 * tol, atol=tol * float(fv.max()))
        assert abs(float(nll[a]) - float(ref_nll)) < (1e-6 if method == "spectral" else 1e-9)
    # the term matters: the Li term alone at the same hyperparameters gives another posterior
    li = InverseRFT(c, f, method=method, li_basis=True, hyper_posterior="map")
    li.hypers.lengthscale, li.hypers.outputscale, li.hypers.noise = LS[:, None, :], OS, noise
    li.hypers.li.variance = LI
    assert float((li.stress_map(th_s[:, 0], th_s[:, 1]).variance - post.variance).abs().max()) > 1e-3


@pytest.mark.parametrize("kind,method", [("rotating", "pairs"), ("translating", "observations"),
                                         ("rotating", "spectral")])
def test_closed_form_gradient_of_the_generic_term_is_autograd_s_and_finite_differences(kind, method):
    c, f = _data(kind)
    model = InverseRFT(c, f, method=method, li_basis=True, generic_shape=True, hyper_posterior="map")
    _set(model, torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0))
    model.hypers.zero_grad()
    loss = model.backend.loss_and_grad()
    assert loss is not None  # the closed form claims the new parameter (else autograd would serve)
    closed = {n: p.grad.clone() for n, p in model.hypers.named_parameters()}
    assert "li.raw_generic_variance" in closed
    model.hypers.zero_grad()
    with autograd_only():
        ref = model.backend.loss()
        ref.backward()
    assert abs(loss - float(ref.detach())) < 1e-8
    for n, p in model.hypers.named_parameters():
        torch.testing.assert_close(closed[n], p.grad, rtol=1e-6, atol=1e-9, msg=n)
    raw, h = model.hypers.li.raw_generic_variance, 1e-5
    for i in range(2):
        with torch.no_grad(), autograd_only():
            raw[i] += h
            up = float(model.backend.loss())
            raw[i] -= 2 * h
            down = float(model.backend.loss())
            raw[i] += h
        assert abs((up - down) / (2 * h) - float(closed["li.raw_generic_variance"][i])) < 1e-6


def test_the_term_is_the_generic_shape_with_its_scale_integrated_out():
    """With the RBF and Li's 9 functions switched off (variances 1e-14), the model is y = m G + noise, G the
    generic shape's forces, m ~ N(0, u): Bayesian linear regression in one coefficient, by hand. Its posterior of
    the map at theta is g(theta) times m's posterior, N(u G.y / (sigma^2 + u G.G), u sigma^2 / (sigma^2 + u G.G))."""
    c, f = _data("rotating")
    model = InverseRFT(c, f, method="observations", li_basis=True, generic_shape=True, hyper_posterior="map")
    noise = torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0)
    _set(model, noise)
    model.hypers.outputscale = torch.full((2,), 1e-14, dtype=F64)
    model.hypers.li.variance = torch.full((2,), 1e-14, dtype=F64)
    G = forces(GENERIC, c)  # (T, 2): the generic shape's forces per unit scale, from the forward model
    th = (torch.rand(9, 2, generator=torch.Generator().manual_seed(2), dtype=F64) - 0.5) * math.pi
    post = model.stress_map(th[:, 0], th[:, 1])
    for a in range(2):
        s2, u, Ga = float(model.hypers.noise[a].detach()), float(U[a]), G[:, a]
        den = s2 + u * float(Ga @ Ga)
        m_mean, m_var = u * float(Ga @ f[:, a]) / den, u * s2 / den
        g = _g(th, a)
        torch.testing.assert_close(post.mean[:, a], m_mean * g, rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(post.variance[:, a], m_var * g.pow(2), rtol=1e-5, atol=1e-9)


def test_the_prior_variance_averages_the_generic_shape_over_the_square():
    """k(theta, theta) = s + v + u g(theta)^2; the scores' and diagnostics' prior variance is its mean over the
    canonical square, s + v + u mean(g^2) (the mean by a dense midpoint grid of the published map)."""
    c, f = _data("rotating")
    model = InverseRFT(c, f, li_basis=True, generic_shape=True, hyper_posterior="map")
    noise = torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0)
    _set(model, noise)
    e = torch.linspace(-math.pi / 2, math.pi / 2, 201, dtype=F64)
    mid = (e[1:] + e[:-1]) / 2
    B, Gm = (t.reshape(-1) for t in torch.meshgrid(mid, mid, indexing="ij"))
    ms = GENERIC(B, Gm).pow(2).mean(0)
    torch.testing.assert_close(model.hypers.prior_variance.detach(), OS + LI + U * ms, rtol=2e-3, atol=0)
    with torch.no_grad():  # data that say nothing: the posterior is the prior, pointwise s + v + u g^2
        model.hypers.noise = 1e9 * f.pow(2).mean(0)
    th = torch.stack([B[::997], Gm[::997]], -1)
    var = model.stress_map(th[:, 0], th[:, 1]).variance
    for a in range(2):
        torch.testing.assert_close(var[:, a], OS[a] + LI[a] + U[a] * _g(th, a).pow(2), rtol=1e-6, atol=0)
    torch.testing.assert_close(model.hypers.prior_variance_at(th[:, 0], th[:, 1]).detach(), var, rtol=1e-6, atol=0)
    # the diagnostics compare each point with its own prior: nothing learned reads as nothing learned
    d = model.diagnostics()
    assert [m.constrained_fraction for m in d.maps] == [0.0, 0.0]
    assert [m.variance_ratio for m in d.maps] == pytest.approx([1.0, 1.0], abs=1e-5)
    # the probe scores divide a region's integrated variance by the prior's mean over that region: the prior
    # scores 1 per map on the square and on a corner where g is far from its mean square (alpha_z near gamma = pi/2)
    from irft_torch.design import ProbeScorer, Region

    scorer = ProbeScorer.from_model(model)
    corner = Region(torch.tensor([-0.2, 0.0, 0.3], dtype=F64), torch.tensor([1.2, 1.4, 1.5], dtype=F64),
                    torch.tensor([1.0, 2.0, 1.0], dtype=F64))
    for region in (None, corner):
        iv = scorer.integrated_variance(region=region, per_axis=True)
        torch.testing.assert_close(iv, torch.ones(2, dtype=F64), rtol=1e-5, atol=0)
    plain = (scorer.integrated_variance(region=corner, per_axis=True) * scorer._prior_over(corner)
             / model.hypers.prior_variance.detach())
    assert float((plain - 1).abs().max()) > 0.1  # the square's mean would not say "the prior" there


def test_the_prior_is_centred_on_the_medium_s_scale_squared_and_the_fit_learns_it(tmp_path):
    """u's prior: log-normal at zeta^2 (zeta the least-squares scale of the generic shape on the forces, here a
    medium 0.3 x generic), log-sd ln 2, where the fit starts; the fit moves u; Laplace labels it; save/load keep it."""
    c, f = _data("rotating", T=40)
    f = 0.3 * f
    model = InverseRFT(c, f, li_basis=True, generic_shape=True, hyper_posterior="laplace")
    G = forces(GENERIC, c)
    zeta = float((f * G).sum() / G.pow(2).sum())
    assert zeta == pytest.approx(0.3, rel=0.05)
    torch.testing.assert_close(model.hypers.generic_variance.detach(), torch.full((2,), zeta**2, dtype=F64),
                               rtol=1e-6, atol=0)
    prior, closure = model.hypers.li._priors["generic_variance_prior"][:2]
    assert float(prior.scale) == pytest.approx(math.log(2))
    assert float(prior.log_prob(closure(model.hypers.li)).sum().detach()) == pytest.approx(2 * -math.log(
        math.log(2) * math.sqrt(2 * math.pi)))  # at the centre
    u0 = model.hypers.generic_variance.detach().clone()
    model.fit(n_iter=60, progress=False)
    assert not torch.allclose(model.hypers.generic_variance.detach(), u0)
    assert "generic_variance" in model.hypers.as_dict()
    assert {"generic_variance_x", "generic_variance_z"} <= set(model.hyper_posterior.labels)
    b = torch.linspace(-1.2, 1.2, 7, dtype=F64)
    post = model.stress_map(b, b)
    path = tmp_path / "generic.pt"
    model.save(path)
    back = InverseRFT.load(path)
    assert back.hypers.li.generic
    again = back.stress_map(b, b)
    torch.testing.assert_close(again.mean, post.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(again.variance, post.variance, rtol=0, atol=1e-12)


def test_the_filter_carries_the_generic_term():
    """``TerrainFilter`` of a model with the term: each environment's posterior is its own InverseRFT's (which the
    dense test above checks), maps and forces."""
    c0, f0 = _data("rotating")
    model = InverseRFT(c0, f0, li_basis=True, generic_shape=True, hyper_posterior="map")
    _set(model, torch.tensor([2e-4, 5e-4], dtype=F64) * f0.pow(2).mean(0))
    envs = [_data(k, T=6) for k in ("rotating", "translating")]
    filt = irft.gp.TerrainFilter(model, 2, capacity=2)
    th = (torch.rand(6, 2, generator=torch.Generator().manual_seed(5), dtype=F64) - 0.5) * math.pi
    for t in range(6):
        cs = Contacts(*(torch.stack([getattr(e[0], k)[t] for e in envs])
                        for k in ("beta", "gamma", "weight_x", "weight_z")))
        filt.update(cs, torch.stack([e[1][t] for e in envs]))
    maps = filt.stress_map(th[:, 0], th[:, 1])
    for b, (c, f) in enumerate(envs):
        own = InverseRFT(c, f, li_basis=True, generic_shape=True, priors=None, method="observations",
                         hyper_posterior="map")
        _set(own, model.hypers.noise.detach())
        ref = own.stress_map(th[:, 0], th[:, 1])
        torch.testing.assert_close(maps.mean[b], ref.mean, rtol=1e-7, atol=1e-10)
        torch.testing.assert_close(maps.variance[b], ref.variance, rtol=1e-7, atol=1e-10)


def test_options_around_the_generic_term():
    c, f = _data("itoe")
    with pytest.raises(ValueError, match="li_basis"):
        InverseRFT(c, f, generic_shape=True, hyper_posterior="map",
                   li_basis=False)  # a rank-one update of Li et al.'s term: needs it
    with pytest.raises(TypeError, match="generic_shape"):
        InverseRFT(c, f, li_basis=True, generic_shape=1, hyper_posterior="map")
    a = InverseRFT(c, f, method="pairs", li_basis=True, generic_shape=True, hyper_posterior="map")
    b = InverseRFT(c, 1.1 * f, method="pairs", li_basis=True, hyper_posterior="map")
    assert "generic_shape" in shares_fit([a, b])  # the term in one model and not the other: not one batch


def test_the_learned_surface_carries_the_generic_term():
    """The surface likelihood (``gp.surface.offset``, its own pairs algebra) with the term equals the dense model
    with it at the shifted contacts; its offset gradient equals central differences (``test_li_basis``'s check with the
    generic shape's term)."""
    check_learned_surface({"generic_shape": True}, _set, _dense)


@pytest.mark.parametrize("opts,factor,width", [({}, 1.0, math.log(2)), ({"prior_mean": "physics"}, 0.3, math.log(10)),
                                               ({"surface_offset": True}, 1.0, math.log(10))])
def test_the_prior_follows_the_outputscale_s_logic(opts, factor, width):
    """u's prior: at zeta^2 (log-sd ln 2); with the physics mean, which carries the shape already, at (0.3 zeta)^2 and
    a factor 10 wide, as the residual outputscale; with a learned surface (zeta not trusted) a factor 10 wide."""
    from .test_surface import TRUTH, plates

    c = plates()
    f = forces(TRUTH, c)
    f = f + 0.02 * f.abs().max() * torch.randn(f.shape, generator=torch.Generator().manual_seed(0))
    model = InverseRFT(c, f, li_basis=True, generic_shape=True, **opts, hyper_posterior="map")
    G = forces(GENERIC, c)
    zeta = float((f * G).sum() / G.pow(2).sum())
    prior, closure = model.hypers.li._priors["generic_variance_prior"][:2]
    assert float(prior.scale) == pytest.approx(width)
    centre = model.hypers.generic_variance.detach() / closure(model.hypers.li).detach().exp()  # value / exp(log ratio)
    torch.testing.assert_close(centre, torch.full((2,), (factor * zeta) ** 2, dtype=F64), rtol=1e-6, atol=0)


def test_add_data_and_cross_validation_carry_the_term():
    """A model grown by ``add_data`` is the dense model on all its data; ``cross_validate`` predicts each group from
    the dense model on the other groups (the same hyperparameters, the term included)."""
    c, f = _data("rotating")
    noise = torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0)
    model = InverseRFT(c[:12], f[:12], method="observations", li_basis=True, generic_shape=True, hyper_posterior="map")
    _set(model, noise)
    model.add_data(c[12:], f[12:])
    th = (torch.rand(9, 2, generator=torch.Generator().manual_seed(6), dtype=F64) - 0.5) * math.pi
    post = model.stress_map(th[:, 0], th[:, 1])
    groups = torch.arange(len(f)) // 10
    cv = model.cross_validate(groups)
    for a in range(2):
        _, map_post, _ = _dense(c, f, a, noise[a])
        mean, var = map_post(th)
        torch.testing.assert_close(post.mean[:, a], mean, rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(post.variance[:, a], var, rtol=1e-7, atol=1e-12)
        for g in range(3):
            keep = groups != g
            _, _, force_post = _dense(c[keep], f[keep], a, noise[a])
            fm, fv = force_post(c[~keep])
            torch.testing.assert_close(cv.mean[~keep, a], fm, rtol=1e-7, atol=1e-9)
            torch.testing.assert_close(cv.variance[~keep, a], fv, rtol=1e-6, atol=1e-12)


def test_the_3d_model_says_it_has_no_generic_term():
    from .test_inverse3d import turning_toe

    c, f = turning_toe()
    with pytest.raises(TypeError, match="generic_shape"):
        InverseRFT(c, f, li_basis=True, generic_shape=True, hyper_posterior="map")


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
@pytest.mark.parametrize("generic", [False, True])
def test_predictions_stay_differentiable_in_the_contacts_through_the_term(method, generic):
    """The force posterior's mean and variance are differentiable in the query's weights (the hyperparameters
    held): their gradient through Li et al.'s term (and the generic shape's) equals central differences."""
    c, f = _data("rotating")
    model = InverseRFT(c, f, method=method, li_basis=True, generic_shape=generic, hyper_posterior="map")
    _set(model, torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0), U if generic else None)
    q = c[::7]

    def value(wz):
        p = model.predict_forces(Contacts(q.beta, q.gamma, q.weight_x, wz))
        return p.mean[:, 1].sum() + p.variance[:, 1].sum()

    wz = q.weight_z.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(value(wz), wz)
    h = 1e-6
    for k in q.weight_z.reshape(-1).topk(3).indices.tolist():  # segments in contact (a zero weight cannot go down)
        i, j = divmod(k, q.weight_z.shape[1])
        up, down = q.weight_z.clone(), q.weight_z.clone()
        up[i, j] += h
        down[i, j] -= h
        with torch.no_grad():
            fd = (value(up) - value(down)) / (2 * h)
        assert float(grad[i, j]) == pytest.approx(float(fd), rel=1e-5, abs=1e-8)
