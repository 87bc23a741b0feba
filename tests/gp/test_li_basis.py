"""Li et al.'s 9-function kernel term (``InverseRFT(..., li_basis=True)``, ``gp.kernels.li_basis``): each backend
against the model written densely with the term's closed form (1 + cos 2 dbeta)(1 + cos dgamma) / 4, the closed-form
gradient against autograd and finite differences, and the options around it."""

import math

import pytest
import torch

from irft_torch import InverseRFT
from irft_torch.gp.backends.closed_form import autograd_only
from irft_torch.gp.batch_fit import fit_together, shares_fit
from irft_torch.gp.kernels.li_basis import li_features
from irft_torch.gp.surface.offset import surface_loss
from irft_torch.rft import CToe, IToe, contacts, forces
from irft_torch.rft.paths import pose_path
from irft_torch.rft.stress_maps import FourierStressMap

from .dense_reference import W_dense, k_dense

F64 = torch.float64
LS = torch.tensor([[0.9, 1.3, 0.7, 2.0], [1.1, 0.8, 1.6, 0.6]], dtype=F64)
OS = torch.tensor([0.03, 0.2], dtype=F64)
LI = torch.tensor([0.05, 0.4], dtype=F64)


def _k_li(th1, th2, v):
    """v (1 + cos 2(b - b')) (1 + cos(g - g')) / 4, written from the angle differences (not from features)."""
    db = th1[:, None, 0] - th2[None, :, 0]
    dg = th1[:, None, 1] - th2[None, :, 1]
    return v * (1 + torch.cos(2 * db)) * (1 + torch.cos(dg)) / 4


def _data(kind: str, T: int = 30):
    t = torch.linspace(0, 1, T, dtype=F64)
    if kind == "rotating":  # a C-toe that turns while it dives: many distinct angle pairs
        c = contacts(CToe(0.02, 0.01, n_segments=6),
                     pose_path(t, -0.06 + 0.12 * t, 0.01 - 0.05 * torch.sin(math.pi * t), 0.6 * t))
    elif kind == "translating":  # a C-toe on a curve, not turning: the row-separable kernel
        c = contacts(CToe(0.02, 0.01, n_segments=6),
                     pose_path(t, -0.06 + 0.12 * t, 0.01 - 0.05 * torch.sin(math.pi * t), 0.0 * t))
    else:  # an I-toe at a fixed tilt on a straight line: few distinct pairs
        c = contacts(IToe(0.03, 0.02, n_segments=5), pose_path(t, -0.06 + 0.12 * t, 0.01 - 0.05 * t, 0.3 + 0 * t))
    f = forces(FourierStressMap.generic().double(), c)
    f = f + 0.02 * f.abs().amax(0) * torch.randn(f.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    return c, f


def _set(model, noise):
    model.hypers.lengthscale = LS[:, None, :]
    model.hypers.outputscale = OS
    model.hypers.noise = noise
    model.hypers.li.variance = LI


def _dense(c, f, a, noise, extra=None):
    """nll per sample, map posterior at th_star and force posterior of c_star, axis a, written densely;
    ``extra(t1, t2)``: one more kernel term of axis a's map (the generic shape's, ``test_generic_shape``)."""
    th = torch.stack([c.beta.reshape(-1), c.gamma.reshape(-1)], -1)
    w = (c.weight_x, c.weight_z)[a]
    W = W_dense(w)

    def k(t1, t2):
        out = k_dense(t1, t2, LS[a], OS[a]) + _k_li(t1, t2, LI[a])
        return out if extra is None else out + extra(t1, t2)

    S = W @ k(th, th) @ W.T + noise * torch.eye(len(f), dtype=F64)
    L = torch.linalg.cholesky(S)
    y = f[:, a]
    alpha = torch.cholesky_solve(y[:, None], L)[:, 0]
    nll = (0.5 * y @ alpha + L.diagonal().log().sum() + 0.5 * len(y) * math.log(2 * math.pi)) / len(y)

    def map_post(th_s):
        ks = k(th_s, th) @ W.T
        return ks @ alpha, k(th_s, th_s).diagonal() - (ks * torch.cholesky_solve(ks.T, L).T).sum(-1)

    def force_post(cs):
        ths = torch.stack([cs.beta.reshape(-1), cs.gamma.reshape(-1)], -1)
        Ws = W_dense((cs.weight_x, cs.weight_z)[a])
        Ksx = Ws @ k(ths, th) @ W.T
        Kss = Ws @ k(ths, ths) @ Ws.T
        return Ksx @ alpha, Kss.diagonal() - (Ksx * torch.cholesky_solve(Ksx.T, L).T).sum(-1)

    return nll, map_post, force_post


def test_li_features_are_the_first_harmonics_products():
    g = torch.Generator().manual_seed(0)
    th1 = (torch.rand(20, 2, generator=g, dtype=F64) - 0.5) * math.pi
    th2 = (torch.rand(15, 2, generator=g, dtype=F64) - 0.5) * math.pi
    f1, f2 = li_features(th1[:, 0], th1[:, 1]), li_features(th2[:, 0], th2[:, 1])
    assert f1.shape == (20, 9)
    assert torch.allclose(f1 @ f2.T, _k_li(th1, th2, 1.0), atol=1e-14)
    # Li et al.'s generic map lies in their span (least squares leaves nothing), a sharp tanh map does not
    A = FourierStressMap.generic().double()(th1[:, 0], th1[:, 1])
    coef = torch.linalg.lstsq(f1, A).solution
    assert float((f1 @ coef - A).abs().max()) < 1e-10
    sharp = torch.tanh(6 * th1[:, 1:])
    assert float((f1 @ torch.linalg.lstsq(f1, sharp).solution - sharp).abs().max()) > 1e-2


@pytest.mark.parametrize("kind,method,terms", [
    ("rotating", "observations", None), ("rotating", "pairs", ["PairsRBF", "LiBasisTerm"]),
    ("translating", "observations", ["RowSeparable", "LiBasisTerm"]),
    ("itoe", "observations", ["PairsRBF", "LiBasisTerm"]), ("itoe", "pairs", ["PairsRBF", "LiBasisTerm"]),
    ("rotating", "spectral", ["KroneckerFourier", "LiBasisTerm"]),
    ("translating", "spectral", ["KroneckerFourier", "LiBasisTerm"])])
def test_each_backend_is_the_dense_model_with_the_term(kind, method, terms):
    c, f = _data(kind)
    model = InverseRFT(c, f, method=method, li_basis=True, hyper_posterior="map")
    noise = torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0)
    _set(model, noise)
    cf = model.backend.closed_form()
    if terms is not None:
        assert [type(t).__name__ for t in cf.terms] == terms
    g = torch.Generator().manual_seed(4)
    th_s = (torch.rand(25, 2, generator=g, dtype=F64) - 0.5) * math.pi
    post = model.stress_map(th_s[:, 0], th_s[:, 1])
    fpost = model.predict_forces(c[::3])
    with torch.no_grad():
        nll = model.backend.negative_log_likelihood()
    # the spectral basis truncates the RBF part at a relative kernel error of 1e-7 (Li et al.'s term is exact in it)
    tol = 1e-5 if method == "spectral" else 1e-8
    if method == "spectral":
        assert float(model.backend.truncation_error().max()) < 1e-7
    for a in range(2):
        ref_nll, map_post, force_post = _dense(c, f, a, model.hypers.noise[a].detach())
        mean, var = map_post(th_s)
        scale = float(mean.abs().max())
        assert torch.allclose(post.mean[:, a], mean, rtol=tol, atol=tol * scale)
        assert torch.allclose(post.variance[:, a], var, rtol=10 * tol, atol=tol * float(var.max()))
        fm, fv = force_post(c[::3])
        assert torch.allclose(fpost.mean[:, a], fm, rtol=tol, atol=tol * float(fm.abs().max()))
        assert torch.allclose(fpost.variance[:, a], fv, rtol=100 * tol, atol=tol * float(fv.max()))
        assert abs(float(nll[a]) - float(ref_nll)) < (1e-6 if method == "spectral" else 1e-9)
    # the term matters here: without it the same hyperparameters give another posterior
    plain = InverseRFT(c, f, method=method, hyper_posterior="map", li_basis=False)
    plain.hypers.lengthscale, plain.hypers.outputscale, plain.hypers.noise = LS[:, None, :], OS, noise
    assert float((plain.stress_map(th_s[:, 0], th_s[:, 1]).variance - post.variance).abs().max()) > 1e-3


@pytest.mark.parametrize("kind,method", [("rotating", "pairs"), ("translating", "observations"),
                                         ("itoe", "observations"), ("rotating", "spectral")])
def test_closed_form_gradient_of_the_term_is_autograd_s_and_finite_differences(kind, method):
    c, f = _data(kind)
    model = InverseRFT(c, f, method=method, li_basis=True, hyper_posterior="map")
    _set(model, torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0))
    model.hypers.zero_grad()
    loss = model.backend.loss_and_grad()
    assert loss is not None
    closed = {n: p.grad.clone() for n, p in model.hypers.named_parameters()}
    model.hypers.zero_grad()
    with autograd_only():
        ref = model.backend.loss()
        ref.backward()
    assert abs(loss - float(ref.detach())) < 1e-8
    for n, p in model.hypers.named_parameters():
        assert torch.allclose(closed[n], p.grad, rtol=1e-6, atol=1e-9), n
    raw = model.hypers.li.raw_variance
    h = 1e-5
    for i in range(2):
        with torch.no_grad(), autograd_only():
            raw[i] += h
            up = float(model.backend.loss())
            raw[i] -= 2 * h
            down = float(model.backend.loss())
            raw[i] += h
        assert abs((up - down) / (2 * h) - float(closed["li.raw_variance"][i])) < 1e-6


def test_a_vanishing_term_gives_the_rbf_model():
    c, f = _data("rotating")
    noise = torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0)
    plain = InverseRFT(c, f, method="observations", hyper_posterior="map", li_basis=False)
    plain.hypers.lengthscale, plain.hypers.outputscale, plain.hypers.noise = LS[:, None, :], OS, noise
    li = InverseRFT(c, f, method="observations", li_basis=True, hyper_posterior="map")
    _set(li, noise)
    li.hypers.li.variance = torch.tensor([1e-14, 1e-14], dtype=F64)
    b = torch.linspace(-1.5, 1.5, 9, dtype=F64)
    p1, p2 = plain.stress_map(b, b.flip(0)), li.stress_map(b, b.flip(0))
    assert torch.allclose(p1.mean, p2.mean, rtol=1e-9, atol=1e-12)
    assert torch.allclose(p1.variance, p2.variance, rtol=1e-9, atol=1e-14)


def test_fit_laplace_and_save_load_keep_the_term(tmp_path):
    c, f = _data("rotating", T=40)
    model = InverseRFT(c, f, li_basis=True, hyper_posterior="laplace")
    assert model.method != "spectral"
    v0 = model.hypers.li_variance.detach().clone()
    model.fit(n_iter=60, progress=False)
    assert not torch.allclose(model.hypers.li_variance.detach(), v0)  # the term's variance is learned
    assert "li_variance" in model.hypers.as_dict()
    assert {"li_variance_x", "li_variance_z"} <= set(model.hyper_posterior.labels)
    b = torch.linspace(-1.2, 1.2, 7, dtype=F64)
    post = model.stress_map(b, b)
    path = tmp_path / "li.pt"
    model.save(path)
    back = InverseRFT.load(path)
    assert back.hypers.li is not None
    again = back.stress_map(b, b)
    assert torch.allclose(post.mean, again.mean, atol=1e-12) and torch.allclose(post.variance, again.variance,
                                                                                 atol=1e-12)


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_the_prior_variance_is_s_plus_v_in_scores_and_diagnostics(method):
    """k(theta, theta) = s + v (1 + 1)(1 + 1) / 4 = s + v at every angle pair (by hand): the prior map variance
    that the probe scores and the diagnostics divide by. With data that say nothing (noise 1e9 x the forces'
    power) the integrated variance is the prior's, 1 per map, and nothing is constrained; with the data, the
    diagnostics' constrained share is that of the posterior variance below (s + v) / 2 on their grid."""
    from irft_torch.design import ProbeScorer

    c, f = _data("rotating")
    model = InverseRFT(c, f, method=method, li_basis=True, hyper_posterior="map")
    _set(model, torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0))
    prior = OS + LI
    torch.testing.assert_close(model.hypers.prior_variance.detach(), prior, rtol=1e-12, atol=0)
    d = model.diagnostics()
    e = torch.linspace(-math.pi / 2, math.pi / 2, 25, dtype=F64)
    mid = (e[1:] + e[:-1]) / 2
    B, G = torch.meshgrid(mid, mid, indexing="ij")
    var = model.stress_map(B, G).variance.reshape(-1, 2)
    for a, m in enumerate(d.maps):
        assert m.constrained_fraction == pytest.approx(float((var[:, a] < prior[a] / 2).double().mean()), abs=1e-12)
        assert m.variance_ratio == pytest.approx(float((var[:, a] / prior[a]).clamp(0, 1).mean()), rel=1e-9)
    assert 0 < d.maps[1].constrained_fraction < 1
    with torch.no_grad():
        model.hypers.noise = 1e9 * f.pow(2).mean(0)
    tol = 1e-4 if method == "spectral" else 1e-7  # the data's residual information, and the scoring basis
    post = model.stress_map(B, G).variance
    torch.testing.assert_close(post, prior.expand_as(post), rtol=tol, atol=0)
    iv = ProbeScorer.from_model(model).integrated_variance(per_axis=True)
    torch.testing.assert_close(iv, torch.ones(2, dtype=F64), rtol=tol, atol=0)
    assert [m.constrained_fraction for m in model.diagnostics().maps] == [0.0, 0.0]


def test_options_that_do_not_carry_the_term_say_so():
    c, f = _data("rotating")
    from irft_torch.gp.backends.spectral import SpectralBackend
    from irft_torch.gp.kernels.fourier import FourierBasis

    model = InverseRFT(c, f, li_basis=True, hyper_posterior="map")
    with pytest.raises(ValueError, match="li_basis"):  # a basis without the first harmonics cannot hold the term
        SpectralBackend(model.hypers, c, f, basis=FourierBasis(0, 3))
    with pytest.raises(TypeError, match="li_basis"):
        InverseRFT(c, f, li_basis="yes", hyper_posterior="map")
    c2, f2 = _data("itoe")
    a = InverseRFT(c2, f2, method="pairs", li_basis=True, hyper_posterior="map")
    b = InverseRFT(c2, 1.1 * f2, method="pairs", hyper_posterior="map", li_basis=False)
    assert "li_basis" in shares_fit([a, b])  # the term in one model and not the other: not one batch


@pytest.mark.parametrize("tied", [False, True])
@pytest.mark.parametrize("generic", [False, True])
def test_fit_together_with_the_term_ends_where_each_fit_ends(tied, generic):
    """``gp.fit_together`` stacks the term's variance (and the generic shape's, with its prior's per-model centres)
    with the other hyperparameters: the same losses at every step and the same hyperparameters as each model's own
    fit."""
    c, f = _data("itoe")
    fs = [f, 1.3 * f * (1 + 0.05 * torch.randn(f.shape, generator=torch.Generator().manual_seed(1), dtype=F64))]
    opts = {"method": "pairs", "li_basis": True, "generic_shape": generic, "tied_noise": tied}
    alone = [InverseRFT(c, x, **opts, hyper_posterior="map") for x in fs]
    together = [InverseRFT(c, x, **opts, hyper_posterior="map") for x in fs]
    assert shares_fit(together) is None
    raw = ["raw_variance"] + (["raw_generic_variance"] if generic else [])
    start = [[getattr(m.hypers.li, n).detach().clone() for n in raw] for m in together]
    histories = [m.fit(n_iter=25, lr=0.1, progress=False) for m in alone]
    batch = fit_together(together, n_iter=25, lr=0.1)
    for a, b, ha, hb, v0 in zip(alone, together, histories, batch, start):
        torch.testing.assert_close(torch.tensor(hb), torch.tensor(ha), rtol=1e-9, atol=1e-9)
        for (name, pa), (_, pb) in zip(a.hypers.named_parameters(), b.hypers.named_parameters()):
            torch.testing.assert_close(pb, pa, rtol=1e-8, atol=1e-12, msg=name)
        for n, x0 in zip(raw, v0):  # the batch moved the term's variances
            assert float((getattr(b.hypers.li, n) - x0).abs().max()) > 1e-3, n


def test_the_learned_surface_carries_the_term():
    """The surface likelihood (``gp.surface.offset``, its own pairs algebra) with the term equals the dense model
    with it at the shifted contacts, and its offset gradient equals central differences."""
    check_learned_surface({}, _set, _dense)


def check_learned_surface(options: dict, set_hypers, dense) -> None:
    """A model with Li et al.'s term (and ``options``) learning the surface offset: its loss at two offsets against
    ``dense`` (the model written densely) at the shifted contacts, its offset gradient against central differences,
    and a fit whose rebuilt backend keeps the term. ``set_hypers(model, noise)`` sets the hyperparameters ``dense``
    assumes (``test_generic_shape`` passes its own pair)."""
    from .test_surface import TRUTH, assert_offset_gradient_is_central_differences, plates

    c = plates()
    f = forces(TRUTH, c.with_surface_offset(torch.tensor(-0.004)))
    f = f + 0.02 * f.abs().max() * torch.randn(f.shape, generator=torch.Generator().manual_seed(0))
    m = InverseRFT(c, f, surface_offset=True, li_basis=True, priors=None, **options, hyper_posterior="map")
    noise = torch.tensor([3e-3, 5e-3], dtype=F64) * f.pow(2).mean(0)
    set_hypers(m, noise)
    for delta in (-0.6, 0.2):  # cm
        with torch.no_grad():
            m.surface.offset.fill_(delta)
        loss = surface_loss(m)
        cd = c.with_surface_offset(torch.tensor(delta / 100))
        ref = sum(dense(cd, f, a, m.hypers.noise[a].detach())[0] for a in range(2))
        assert abs(float(loss.detach()) - float(ref)) < 1e-9
        assert_offset_gradient_is_central_differences(m, loss, delta)
    m.fit(n_iter=30, progress=False)  # the backend rebuilt at the fitted offset keeps the term
    assert m.backend.hypers.li is not None
    assert torch.isfinite(m.stress_map(c.beta[:3, 0], c.gamma[:3, 0]).variance).all()
