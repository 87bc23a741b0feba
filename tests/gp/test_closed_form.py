"""The closed-form loss and gradient (``gp.backends.closed_form``) and the batched log posterior over
hyperparameter draws (``gp.hyper.density``), each against two independent references: autograd through the
backends' own ``loss`` (the code that existed before) and the dense reference (explicit W, explicit K,
torch Cholesky; ``dense_reference``). float64 to 1e-8 (the spectral backend against the dense reference:
1e-6, its truncation); float32 against float64."""

import math

import pytest
import torch
from gpytorch.constraints import GreaterThan
from gpytorch.priors import GammaPrior

import irft_torch as irft
from irft_torch.gp.backends.closed_form import ClosedForm, autograd_only, current_values
from irft_torch.gp.backends.covariance_terms import LENGTHSCALE, OUTPUTSCALE, CovarianceTerm, PairsRBF
from irft_torch.gp.hyper.density import log_posterior_and_grad, log_posterior_batch
from irft_torch.gp.hyper.posterior import _SubSpec, hyper_spec, log_posterior
from irft_torch.rft import FourierStressMap

from .dense_reference import axis_reference
from .test_backends_vs_dense import data, set_hypers

# (backend, contacts): which closed form each case exercises
CASES = [("observations", "translating"),  # RowSeparable
         ("observations", True),  # few distinct pairs: PairsRBF with R = W_U
         ("observations", False),  # every pair distinct: the same, more pairs than samples
         ("pairs", True),  # PairsRBF on the weight-space factor (from P's eigenvectors or from the rows)
         ("pairs", False),  # fewer samples than pairs: the factor from the rows (a thin SVD)
         ("spectral", False)]  # KroneckerFourier


def autograd_grads(model):
    params = list(model.hypers.parameters())
    loss = model.backend.loss()
    return loss.item(), torch.autograd.grad(loss, params)


def closed_form_grads(model):
    params = list(model.hypers.parameters())
    for p in params:
        p.grad = None
    loss = model.backend.loss_and_grad()
    assert loss is not None, f"{model.method} has no closed form here"
    out = [p.grad.clone() for p in params]
    for p in params:
        p.grad = None
    return loss, out


def assert_grads_close(got, want, tol, names):
    for name, a, b in zip(names, got, want):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol * b.abs().max().item() + 1e-300, msg=f"gradient of {name}")


def assert_closed_form_is_autograd(model):
    """The closed form's loss and every raw gradient against autograd through the backend's own loss."""
    names = [n for n, _ in model.hypers.named_parameters()]
    want_loss, want = autograd_grads(model)
    got_loss, got = closed_form_grads(model)
    assert got_loss == pytest.approx(want_loss, rel=1e-12)
    assert_grads_close(got, want, 1e-9, names)


@pytest.mark.parametrize("tied", [False, True])
@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
@pytest.mark.parametrize("method, repeated", CASES)
def test_loss_and_every_gradient_equal_autograd_of_the_backends_loss(method, repeated, prior_mean, tied):
    """With the physical priors (their closed form too), at hyperparameters away from the initial ones."""
    c, f = data(T=30, M=4, seed=2, repeated=repeated)
    model = irft.InverseRFT(c, f, method=method, prior_mean=prior_mean, tied_noise=tied, hyper_posterior="map",
                            li_basis=False)
    set_hypers(model, seed=3)
    assert_closed_form_is_autograd(model)


@pytest.mark.parametrize("method, repeated", [c for c in CASES if c[0] != "spectral"])
def test_li_basis_terms_equal_autograd(method, repeated):
    """Li et al.'s term (kernel="li") in each exact closed form: loss and gradients against autograd through the
    backend's own loss."""
    c, f = data(T=30, M=4, seed=7, repeated=repeated)
    model = irft.InverseRFT(c, f, method=method, prior_mean="physics", hyper_posterior="map")
    set_hypers(model, seed=8)
    assert_closed_form_is_autograd(model)


@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
@pytest.mark.parametrize("method, repeated", CASES)
def test_loss_and_every_gradient_equal_the_dense_reference(method, repeated, prior_mean):
    """The paper's plain likelihood (no priors), differentiated by autograd through the explicit dense
    formula; the closed form's raw-parameter gradients against it."""
    c, f = data(T=25, M=4, seed=0, repeated=repeated)
    model = irft.InverseRFT(c, f, method=method, prior_mean=prior_mean, priors=None, hyper_posterior="map",
                            li_basis=False)
    set_hypers(model, seed=1)
    params = dict(model.hypers.named_parameters())
    ls, os, noise = model.hypers.lengthscale, model.hypers.outputscale, model.hypers.noise
    total = 0.0
    for a, w in enumerate((c.weight_x, c.weight_z)):
        mean = None
        if prior_mean == "physics":
            mean = model.hypers.mean_scales[a] * (w * FourierStressMap.generic()(c.beta, c.gamma)[..., a]).sum(-1)
        total = total - axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], mean)[0]
    want = torch.autograd.grad(total, list(params.values()))
    got_loss, got = closed_form_grads(model)
    tol = 1e-6 if method == "spectral" else 1e-8
    assert got_loss == pytest.approx(total.item(), rel=tol)
    assert_grads_close(got, want, tol * 10, list(params))


def _segments_model(T: int, seed: int, **options):
    """A pairs model on a turning toe with more distinct pairs than samples, evaluated through the segments (the
    spectral backend's exact twin's form, ``PairsBackend.segments``)."""
    from irft_torch.gp.backends.covariance_terms import SegmentPairsRBF

    c, f = data(T=T, M=4, seed=seed, repeated=False)
    model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", **options)
    set_hypers(model, seed=seed + 1)
    model.backend.segments = True
    assert model.backend.n_pairs > T and isinstance(model.backend.closed_form().terms[0], SegmentPairsRBF)
    return c, f, model


@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
def test_the_segment_form_equals_the_dense_reference(prior_mean):
    """W_U K_UU W_U^T through sparse products and the Gram of the scaled embedding, its gradient without W^T G W:
    the loss and every raw gradient against autograd through the dense reference (explicit W and K); a batch of
    draws in one call against the dense reference at each."""
    c, f, model = _segments_model(25, 20, prior_mean=prior_mean, priors=None, li_basis=False)
    params = dict(model.hypers.named_parameters())
    ls, os, noise = model.hypers.lengthscale, model.hypers.outputscale, model.hypers.noise

    def reference(ls, os, noise, scales):
        total = 0.0
        for a, w in enumerate((c.weight_x, c.weight_z)):
            shape = (w * FourierStressMap.generic()(c.beta, c.gamma)[..., a]).sum(-1)
            mean = None if scales is None else scales[a] * shape
            total = total - axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], mean)[0]
        return total

    total = reference(ls, os, noise, model.hypers.mean_scales)
    want = torch.autograd.grad(total, list(params.values()))
    got_loss, got = closed_form_grads(model)
    assert got_loss == pytest.approx(total.item(), rel=1e-10)
    assert_grads_close(got, want, 1e-8, list(params))
    base = current_values(model.hypers)
    g = torch.Generator().manual_seed(22)
    values = {n: v * torch.exp(0.3 * torch.randn(4, *v.shape, generator=g)) for n, v in base.items()}
    values[LENGTHSCALE] = values[LENGTHSCALE] * torch.tensor([1.0, 0.5, 0.2, 0.1])[:, None, None, None]  # short too
    nll, grads, ok = model.backend.closed_form().evaluate(values)
    assert ok.all()
    for s in range(4):
        one = {n: v[s] for n, v in values.items()}
        noise_s = one["likelihood.noise_covar.raw_noise"][..., 0] if "likelihood.noise_covar.raw_noise" in one else None
        scales = one.get("mean.raw_scales") if prior_mean == "physics" else None
        ref = reference(one[LENGTHSCALE], one[OUTPUTSCALE], noise_s.expand(2), scales)
        assert nll[s].sum().item() == pytest.approx(ref.item(), rel=1e-10)


def test_the_segment_form_with_li_basis_equals_autograd():
    """Li et al.'s term and the generic shape's, summed per sample, in the segments' closed form (physics mean,
    priors): the loss and every raw gradient against autograd through the backend's own weight-space loss."""
    _, _, model = _segments_model(30, 23, prior=irft.MapPrior(mean="physics", kernel="li+generic"))
    assert_closed_form_is_autograd(model)


@pytest.mark.parametrize("method, repeated", CASES)
def test_a_batch_of_draws_equals_each_draw_alone_and_the_dense_reference(method, repeated):
    """ClosedForm.evaluate over S draws in one call: each draw's nll and gradients equal a call with that
    draw alone and the dense reference's at that draw (physics mean, tied noise)."""
    c, f = data(T=25, M=4, seed=4, repeated=repeated)
    model = irft.InverseRFT(c, f, method=method, prior_mean="physics", tied_noise=True, priors=None,
                            hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=5)
    base = current_values(model.hypers)
    g = torch.Generator().manual_seed(6)
    S = 5
    values = {n: v * torch.exp(0.2 * torch.randn(S, *v.shape, generator=g)) for n, v in base.items()}
    model.backend.prepare(values)
    cf = model.backend.closed_form()
    nll, grads, ok = cf.evaluate(values)
    assert ok.all() and nll.shape == (S, 2)
    tol = 1e-6 if method == "spectral" else 1e-8
    for s in range(S):
        one = {n: v[s] for n, v in values.items()}
        nll1, grads1, _ = cf.evaluate(one)
        torch.testing.assert_close(nll[s], nll1, rtol=1e-12, atol=0)
        for n in grads:
            torch.testing.assert_close(grads[n][s], grads1[n], rtol=1e-10, atol=1e-12 * grads1[n].abs().max())
        ls, os = one[LENGTHSCALE], one[OUTPUTSCALE]
        noise = one["likelihood.noise_covar.raw_noise"].expand(2)
        for a, w in enumerate((c.weight_x, c.weight_z)):
            m = one["mean.raw_scales"][a] * (w * FourierStressMap.generic()(c.beta, c.gamma)[..., a]).sum(-1)
            ref = -axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], m)[0]
            assert nll[s, a].item() == pytest.approx(ref.item(), rel=tol)


@pytest.mark.parametrize("method, repeated", CASES)
def test_log_posterior_in_closed_form_equals_autograd_one_by_one(method, repeated):
    """What Laplace and NUTS use: the batched log posterior (128 proposals: one call) and the single one
    with its gradient, against the autograd path (``exact_graph``), over all and over some coordinates."""
    c, f = data(T=30, M=4, seed=7, repeated=repeated)
    model = irft.InverseRFT(c, f, method=method, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=8)
    spec = hyper_spec(model.hypers)
    theta = spec.theta(model.hypers)
    x = theta + 0.15 * torch.randn(6, theta.numel(), generator=torch.Generator().manual_seed(9))
    for sp, pts in ((spec, x), (_SubSpec(spec, theta, torch.tensor([0, 3, 9])), x[:, [0, 3, 9]])):
        batch = log_posterior_batch(model.backend, sp, pts, grouped=False)  # one basis, grown for all draws first
        with autograd_only():
            one_by_one = torch.stack([log_posterior(model.backend, sp, p) for p in pts])
        torch.testing.assert_close(batch, one_by_one, rtol=1e-9, atol=0)  # summation order differs
        for p in pts[:2]:
            t = p.clone().requires_grad_(True)
            (g,) = torch.autograd.grad(log_posterior(model.backend, sp, t), t)
            t = p.clone().requires_grad_(True)
            (want,) = torch.autograd.grad(log_posterior(model.backend, sp, t, exact_graph=True), t)
            torch.testing.assert_close(g, want, rtol=1e-9, atol=1e-9 * want.abs().max())


@pytest.mark.parametrize("kernel", ["rbf", "li"])
def test_draws_are_evaluated_in_the_bases_their_own_lengthscales_need(kernel, monkeypatch):
    """A batch of draws, some with lengthscales far shorter than the fit's: the spectral backend evaluates them in
    groups, each in the basis its draws need (more than one group here, with the exact pairs space made to look dear),
    its own basis unchanged; every value against the exact pairs space (the RBF itself at the distinct angle pairs)
    within what the kernel's tolerance allows, and against one basis grown for all of them. With the pairs space at
    its own cost (120 pairs: cheaper than any larger basis), it takes every draw the fit's basis does not hold."""
    import math

    from irft_torch.gp.backends import make_backend
    from irft_torch.gp.backends.covariance_terms import LENGTHSCALE as LS
    from irft_torch.gp.backends.pairs import PairsBackend

    monkeypatch.setattr(PairsBackend, "draw_cost", lambda self: math.inf)

    c, f = data(T=30, M=4, seed=7)
    model = irft.InverseRFT(c, f, engine="spectral", hyper_posterior="map", prior=irft.MapPrior(kernel=kernel))
    set_hypers(model, seed=8, low=1.5)
    backend = model.backend
    before = backend.basis
    spec = hyper_spec(model.hypers)
    theta = spec.theta(model.hypers)
    x = theta + 0.1 * torch.randn(12, theta.numel(), generator=torch.Generator().manual_seed(3), dtype=theta.dtype)
    ls = [i for i, name in enumerate(spec.labels) if name.startswith("lengthscale")]
    x[6:, ls] -= torch.linspace(0.5, 2.5, 6, dtype=theta.dtype)[:, None]  # down to e^-2.5 of the fit's
    from irft_torch.gp.hyper.density import _values
    values, _ = _values(backend, spec, x)
    groups = backend.draw_groups(values[LS])
    assert len(groups) >= 3 and sum(int(m.sum()) for m, _ in groups) == 12
    # the two shortest settings need more than MAX_HARMONICS per angle for tol: the exact pairs space takes them
    beyond = [m for m, b in groups if b.name == "pairs"]
    assert len(beyond) == 1 and beyond[0].nonzero()[:, 0].tolist() == [10, 11]
    grouped = log_posterior_batch(backend, spec, x)
    assert backend.basis == before  # the fit's own basis is kept
    exact = make_backend("pairs", model.hypers, model.train_contacts, model.train_forces)
    want = log_posterior_batch(exact, spec, x)
    torch.testing.assert_close(grouped, want, rtol=1e-8, atol=1e-7)
    # one setting at a time with its gradient (L-BFGS, NUTS): the same spaces, this backend's basis unchanged
    for k in (8, 11):
        lp, g = log_posterior_and_grad(backend, spec, x[k])
        lp_exact, g_exact = log_posterior_and_grad(exact, spec, x[k])
        torch.testing.assert_close(lp, lp_exact, rtol=1e-8, atol=1e-7)
        torch.testing.assert_close(g, g_exact, rtol=1e-6, atol=1e-6 * float(g_exact.abs().max()))
    assert backend.basis == before
    # a kept draw that short predicts in the exact space too; a shorter one than the fit's in the basis it needs
    import copy

    short = copy.deepcopy(model.hypers)
    short.lengthscale = values[LS][11]
    assert backend.with_hypers(short).name == "pairs"
    mid = copy.deepcopy(model.hypers)
    mid.lengthscale = values[LS][8]  # a longer basis than the fit's: cut from the batch's statistics, no pass
    from irft_torch.gp.kernels.fourier import FourierBasis

    got = backend.with_hypers(mid)
    assert got.name == "spectral" and got.basis == FourierBasis.for_lengthscale(mid.lengthscale, backend.tol)
    fresh = make_backend("spectral", mid, model.train_contacts, model.train_forces)  # its own pass over the data
    torch.testing.assert_close(got.loss(), fresh.loss(), rtol=1e-12, atol=0)
    backend.forget_draws()
    assert backend.with_hypers(mid) is None  # the model builds it from its own statistics
    monkeypatch.undo()
    groups = backend.draw_groups(values[LS])
    own = [m for m, b in groups if b is backend]
    assert [b.name for _, b in groups] == ["spectral", "pairs"] and own[0].nonzero()[:, 0].tolist() == list(range(6))
    torch.testing.assert_close(log_posterior_batch(backend, spec, x), want, rtol=1e-8, atol=1e-7)
    with pytest.warns(UserWarning, match="need more than 30 harmonics"):  # one basis for all: truncated, and said
        one = log_posterior_batch(backend, spec, x, grouped=False)
    torch.testing.assert_close(grouped[:10], one[:10], rtol=1e-8, atol=1e-7)
    assert abs(float(one[11] - want[11])) > 1e-4  # the truncated kernel's value, 1.3e-3 off


def test_a_basis_beyond_the_cap_places_one_setting_in_itself():
    """A spectral backend in a basis of more harmonics than the draws' cap (32 of beta) holds a long-lengthscale setting
    itself (``space_for`` reads the errors up to the basis' own harmonics, not only up to the cap)."""
    from irft_torch.gp.backends.spectral import SpectralBackend
    from irft_torch.gp.kernels.fourier import FourierBasis

    c, f = data(T=30, M=4, seed=7)
    model = irft.InverseRFT(c, f, engine="spectral", hyper_posterior="map", li_basis=False)
    model.hypers.lengthscale = torch.full_like(model.hypers.lengthscale, 3.0)
    wide = SpectralBackend(model.hypers, model.train_contacts, model.train_forces, basis=FourierBasis(32, 4))
    assert bool((wide.basis.truncation_error(model.hypers.lengthscale) <= wide.tol).all())
    assert wide.space_for(model.hypers.lengthscale) is wide


def test_draw_groups_partition_by_hand():
    """The grouping's partition of (n_beta, n_gamma) keys by hand, T = 100 samples (fewer than any basis' features,
    so a draw costs 2 T F (T + F_beta + F_gamma)): [(8, 24) x 10, (12, 16) x 10, (30, 30) x 1] in two groups: the
    first two share (12, 24) (20 x 42.6M + 165.2M = 1.02G) rather than (8, 24) alone and the rest in (30, 30)
    (10 x 27.7M + 11 x 165.2M = 2.09G) or one group (21 x 165.2M); (4, 28) and (28, 4) stay apart (10 x 17.0M;
    their union would be (28, 28), 10 x 139M); one key, one group."""
    from irft_torch.gp.backends.draw_spaces import _split_keys, basis_cost

    assert float(basis_cost(torch.tensor(12), torch.tensor(24), 100)) == 2 * 100 * 1225 * (100 + 25 + 49)
    assert _split_keys([(8, 24), (12, 16), (30, 30)], [10, 10, 1], 2, 100) == [2, 1]
    assert _split_keys([(4, 28), (28, 4)], [5, 5], 2, 100) == [1, 1]
    assert _split_keys([(8, 8)], [3], 4, 100) == [1]


def test_impossible_draws_get_minus_infinity_and_no_gradient():
    c, f = data(T=20, M=3, seed=10, repeated=True)
    model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    spec = hyper_spec(model.hypers)
    theta = spec.theta(model.hypers)
    bad = theta.clone()
    bad[spec.labels.index("noise_x")] = -80.0  # below the noise floor
    lp, g = log_posterior_and_grad(model.backend, spec, torch.stack([theta, bad]))
    assert torch.isfinite(lp[0]) and lp[1] == -math.inf
    assert torch.equal(g[1], torch.zeros_like(g[1]))


def test_float32_agrees_with_float64():
    c, f = data(T=30, M=4, seed=11, repeated=True)
    grads = {}
    for dtype in (torch.float32, torch.float64):
        model = irft.InverseRFT(c, f, method="pairs", dtype=dtype, hyper_posterior="map", li_basis=False)
        set_hypers(model, seed=12)
        loss, g = closed_form_grads(model)
        grads[dtype] = (loss, g)
        assert all(x.dtype == dtype for x in g)
    assert grads[torch.float32][0] == pytest.approx(grads[torch.float64][0], rel=1e-4)
    for a, b in zip(grads[torch.float32][1], grads[torch.float64][1]):
        torch.testing.assert_close(a.double(), b, rtol=1e-3, atol=1e-3 * b.abs().max())


@pytest.mark.parametrize("method, repeated", [("pairs", True), ("spectral", False), ("observations", "translating")])
def test_a_fit_follows_the_autograd_fit(method, repeated):
    """The same Adam steps give the same hyperparameters (and losses) as before, to round-off."""
    c, f = data(T=40, M=4, seed=13, repeated=repeated)
    fast, slow = (irft.InverseRFT(c, f, method=method, prior_mean="physics", hyper_posterior="map",
                                  li_basis=False) for _ in range(2))
    h_fast = fast.fit(40, lr=0.05, progress=False)
    with autograd_only():
        h_slow = slow.fit(40, lr=0.05, progress=False)
    assert h_fast == pytest.approx(h_slow, rel=1e-9)
    for (n, a), b in zip(fast.hypers.named_parameters(), slow.hypers.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9, msg=n)


def test_a_prior_registered_by_hand_takes_autograd_and_an_uncovered_parameter_falls_back():
    c, f = data(T=25, M=3, seed=14, repeated=True)
    model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    model.hypers.kernel.register_prior("extra_prior", GammaPrior(2.0, 3.0), lambda m: m.outputscale)
    names = [n for n, _ in model.hypers.named_parameters()]
    want_loss, want = autograd_grads(model)
    got_loss, got = closed_form_grads(model)
    assert got_loss == pytest.approx(want_loss, rel=1e-12)
    assert_grads_close(got, want, 1e-9, names)
    # a parameter no closed-form term knows: never a silent zero gradient, autograd serves
    model.hypers.register_parameter("raw_other", torch.nn.Parameter(torch.zeros(1)))
    model.hypers.register_constraint("raw_other", GreaterThan(0.0))
    assert model.backend.loss_and_grad() is None


class _DeviationTerm(CovarianceTerm):
    """A toy finite-rank term v_k h_k(theta) h_k(theta') with fixed h_k (K, U) at the pairs and variances
    v (a raw parameter of the hyperparameters): what an additive kernel term plugs in as."""

    names = ("raw_dev",)

    def __init__(self, H):
        self.H = H  # (K, U)

    def forward(self, values, R):
        RH = R @ self.H.mT  # (2, r, K)
        v = values["raw_dev"]  # (*S, K)
        return (RH * v[..., None, None, :]) @ RH.mT, RH

    def backward(self, values, adj, RH):
        return {"raw_dev": ((RH.mT @ adj.G) * RH.mT).sum(-1).sum(-2)}


def test_an_additive_term_plugs_in():
    """Sigma = K_UU + H^T diag(v) H: the closed form with the toy term against autograd through a direct
    evaluation of the same likelihood (the weight-space formula written with torch.logdet and solve)."""
    c, f = data(T=30, M=4, seed=15, repeated=True)
    model = irft.InverseRFT(c, f, method="pairs", priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(model, seed=16)
    model.hypers.register_parameter("raw_dev", torch.nn.Parameter(torch.tensor([0.1, -0.4])))
    model.hypers.register_constraint("raw_dev", GreaterThan(0.0))
    table = model.backend.table
    H = torch.stack([torch.cos(2 * table[:, 0]), torch.sin(table[:, 1])])  # (2, U): two fixed Fourier functions
    backend = model.backend
    f0 = backend._factor()
    backend._closed_form_cache = (f0, ClosedForm(f0.R, f0.c_y, None, f0.rho, backend.stats.n,
                                                 [PairsRBF(table), _DeviationTerm(H)]))
    params = list(model.hypers.parameters())
    got_loss, got = closed_form_grads(model)

    K = backend._K() + H.mT @ torch.diag_embed(model.hypers.raw_dev_constraint.transform(model.hypers.raw_dev)) @ H
    A = f0.R @ K @ f0.R.mT
    noise = model.hypers.noise
    n, r = backend.stats.n, A.shape[-1]
    S = A + noise[:, None, None] * torch.eye(r)
    quad = f0.rho[:, 0] / noise + (f0.c_y[..., None, :] @ torch.linalg.solve(S, f0.c_y[..., None]))[..., 0, 0]
    logdet = (n - r) * noise.log() + torch.logdet(S)
    want_loss = (0.5 * (quad + logdet + n * math.log(2 * math.pi)) / n).sum()
    want = torch.autograd.grad(want_loss, params)
    assert got_loss == pytest.approx(want_loss.item(), rel=1e-12)
    assert_grads_close(got, want, 1e-9, [n for n, _ in model.hypers.named_parameters()])


def test_laplace_is_the_same_posterior_as_before():
    """The Laplace posterior (polish, Hessian, 128 weighted proposals in one call) with the same generator
    equals the one computed through autograd, proposal by proposal (to the Hessian's accuracy: here central
    differences of the closed-form gradient, 2e-8 relative, against autograd's second derivatives; the split
    proposal's sides are read from log-posterior differences along the Hessian's Cholesky factor, which carry
    that error a few times over into the draws: 4e-8 here)."""
    c, f = data(T=40, M=4, seed=17, repeated=True)
    posts = []
    for ctx in (autograd_only, None):
        model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
        model.fit(30, progress=False)
        g = torch.Generator().manual_seed(18)
        if ctx is None:
            posts.append(model.fit_hyper_posterior("laplace", generator=g))
        else:
            with ctx():
                posts.append(model.fit_hyper_posterior("laplace", generator=g))
    a, b = posts
    torch.testing.assert_close(a.mode, b.mode, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(a.theta, b.theta, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(a.weights, b.weights, rtol=1e-7, atol=1e-9)
    assert a.ess == pytest.approx(b.ess, rel=1e-7)


@pytest.mark.parametrize("method, repeated", CASES)
def test_the_one_vector_step_serves_the_default_model_and_follows_a_changed_bound(method, repeated):
    """``loss_and_grad`` on the default model goes through the one-vector form (``_Flat``: values, priors and
    the chain rule on all raw hyperparameters at once), equal to autograd; a noise floor changed in place
    rebuilds it (a stale lower bound would give other values), and the gradients still equal autograd."""
    from irft_torch.gp.backends.closed_form import _plan

    c, f = data(T=30, M=4, seed=2, repeated=repeated)
    model = irft.InverseRFT(c, f, method=method, li_basis=True, hyper_posterior="map")
    set_hypers(model, seed=3)
    names = [n for n, _ in model.hypers.named_parameters()]
    flat = _plan(model.hypers).flat()
    assert flat is not None and {n for n, _, _ in flat.entries} == set(names)
    for _ in range(2):
        want_loss, want = autograd_grads(model)
        got_loss, got = closed_form_grads(model)
        assert got_loss == pytest.approx(want_loss, rel=1e-12)
        assert_grads_close(got, want, 1e-9, names)
        bound = model.hypers.likelihood.noise_covar.raw_noise_constraint.lower_bound
        bound.fill_(float(model.hypers.noise.min()) * 0.5)  # a floor near the noise: values move
    assert _plan(model.hypers).flat() is not flat


def test_the_one_vector_step_follows_a_replaced_buffer():
    """A constraint's scale replaced by a new tensor (as ``module.to`` / ``.double()`` replace buffers, keeping the
    parameters) makes the one-vector form stale; the step rebuilds it and still equals autograd."""
    from irft_torch.gp.backends.closed_form import _plan

    c, f = data(T=30, M=4, seed=2, repeated=True)
    model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    flat = _plan(model.hypers).flat()
    constraint = model.hypers.kernel.raw_outputscale_constraint
    constraint.scale = constraint.scale * 2  # replaced, not changed in place: the values double
    assert not flat.valid()
    names = [n for n, _ in model.hypers.named_parameters()]
    want_loss, want = autograd_grads(model)
    got_loss, got = closed_form_grads(model)
    assert got_loss == pytest.approx(want_loss, rel=1e-12)
    assert_grads_close(got, want, 1e-9, names)
    assert _plan(model.hypers).flat() is not flat
