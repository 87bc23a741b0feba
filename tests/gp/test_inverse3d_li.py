"""Li et al.'s 9-function kernel term in the 3-D model (``InverseRFT3D(..., li_basis=True)``): every backend
against the dense model written from the angle differences, v (1 + cos 2 dbeta)(1 + cos dgamma) / 4 added to each
map over (beta, gamma) (not to a constant alpha_y); gradients by autograd through both; the prior variance s + v in
the diagnostics and the probe scores; files, add_data and the hyperparameter posterior's labels."""

import pytest
import torch

from irft_torch.design import ProbeScorer3D
from irft_torch.gp.hyper.posterior import hyper_spec
from irft_torch.gp.inverse3d import InverseRFT3D, point_contacts

from .test_inverse3d import CASES, _set, assert_predictions_match, dense, per_sample, turning_toe

LI = torch.tensor([0.05, 0.03, 0.3], dtype=torch.float64)
OS = torch.tensor([0.09, 0.02, 0.2], dtype=torch.float64)
NOISE = torch.tensor([4e-4, 3e-4, 5e-4], dtype=torch.float64)


def _model(method, alpha_y, li=LI, **kw):
    c, f = turning_toe()
    tol = 1e-12 if method == "spectral" else 1e-7
    model = InverseRFT3D(c, f, method=method, alpha_y=alpha_y, priors=None, tol=tol, prior_mean="zero",
                         li_basis=True, **kw)
    ls = 0.8 + torch.rand(3, 1, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    _set(model, ls, OS, NOISE)
    with torch.no_grad():
        model.hypers.li.variance = li
    model.backend.refresh()
    return model, c, f


@pytest.mark.parametrize("method,alpha_y", CASES)
def test_backends_match_the_dense_reference_with_the_term(method, alpha_y):
    model, c, f = _model(method, alpha_y)
    rtol = 1e-8 if method != "spectral" else 1e-7
    loss = model.loss()
    loss.backward()
    raw = [p for p in model.hypers.parameters() if p.requires_grad]
    grads = [p.grad.clone() for p in raw]
    for p in raw:
        p.grad = None
    h = model.hypers
    ref, post = dense(c, f, h.lengthscale, h.outputscale, h.noise, alpha_y == "constant", li=h.li_variance)
    ref.backward()
    torch.testing.assert_close(loss, ref, rtol=rtol, atol=0)
    for g, p in zip(grads, raw):  # the term's variance included (a constant alpha_y's: no gradient either way)
        torch.testing.assert_close(g, p.grad, rtol=1e-6 if method != "spectral" else 1e-5, atol=1e-9)
    assert float(h.li.raw_variance.grad.abs()[[0, 2]].min()) > 0
    sm, pts = assert_predictions_match(model, post, rtol)
    with torch.no_grad():
        # the term matters here: the model without it (the same other hyperparameters) differs
        _, post0 = dense(c, f, h.lengthscale, h.outputscale, h.noise, alpha_y == "constant")
        assert float((per_sample(post0(pts)[1], 4) - sm.covariance).abs().max()) > 1e-3


def test_prior_variance_is_s_plus_v_in_diagnostics_scores_and_far_from_the_data():
    model, c, f = _model("observations", "constant")
    prior = OS + LI * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)  # a constant alpha_y has no term
    torch.testing.assert_close(model.hypers.prior_variance.detach(), prior, rtol=1e-12, atol=0)
    with torch.no_grad():
        model.hypers.noise = 1e9 * f.pow(2).mean(0)  # data that say nothing: the prior everywhere
    b = torch.linspace(-1.4, 1.4, 5, dtype=torch.float64)
    post = model.stress_map(b, b.flip(0))
    torch.testing.assert_close(post.variance, prior.expand(5, 3), rtol=1e-6, atol=0)
    iv = ProbeScorer3D.from_model(model).integrated_variance(per_map=True)
    torch.testing.assert_close(iv, torch.ones(3, dtype=torch.float64), rtol=1e-6, atol=0)
    with pytest.warns(UserWarning, match="not constrained"):
        d = model.diagnostics()
    assert d["alpha_x"]["prior_std"] == pytest.approx(float(prior[0].sqrt()), rel=1e-12)


def test_files_add_data_and_hyperparameter_labels_keep_the_term(tmp_path):
    model, c, f = _model("pairs", "constant")
    path = tmp_path / "m.pt"
    model.save(path)
    back = InverseRFT3D.load(path)
    torch.testing.assert_close(back.hypers.li_variance, model.hypers.li_variance, rtol=0, atol=0)
    b = torch.tensor([0.2, -0.7], dtype=torch.float64)
    torch.testing.assert_close(back.stress_map(b, b).variance, model.stress_map(b, b).variance, rtol=1e-12, atol=0)
    labels = hyper_spec(model.hypers).labels
    assert {"li_variance_x", "li_variance_y", "li_variance_z"} <= set(labels)
    assert "li_variance_y" in model.hypers.fixed_labels()  # a constant alpha_y: no term to marginalise
    q, fq = turning_toe(T=6, seed=3)
    model.add_data(q, fq)
    h = model.hypers
    _, post = dense(model.train_contacts, model.train_forces, h.lengthscale, h.outputscale, h.noise, True,
                    li=h.li_variance)
    with torch.no_grad():
        torch.testing.assert_close(model.stress_map(b, b).mean, post(point_contacts(b, b))[0], rtol=1e-8, atol=1e-10)


def test_fit_with_the_default_priors_moves_the_term_and_refuses_a_non_bool():
    c, f = turning_toe(T=12)
    model = InverseRFT3D(c, f, li_basis=True)
    v0 = model.hypers.li_variance.detach().clone()
    torch.testing.assert_close(v0, model.hypers.outputscale.detach())  # initialised at its prior's centre
    model.fit(n_iter=20, progress=False)
    assert torch.isfinite(model.loss()) and float((model.hypers.li_variance - v0).abs().max()) > 0
    with pytest.raises(TypeError, match="li_basis"):
        InverseRFT3D(c, f, li_basis="yes")


def test_diagnostics_report_the_kernels_error_bound_and_it_holds():
    """Issue 52: a 3-D spectral model capped below its tol says so in diagnostics() (bound per map, tol, whether
    within), and the bound holds against the exact RBF on the embedding, written out here, at random angle
    pairs; an exact backend reports zero."""
    import warnings

    from irft_torch.gp.options import Engine, MapPrior

    from .dense_reference import truncation_gaps

    c, f = turning_toe()
    model = InverseRFT3D(c, f, prior=MapPrior(mean="zero"), engine=Engine("spectral", tol=1e-3, max_harmonics=4))
    with torch.no_grad():
        model.hypers.lengthscale = torch.tensor([[[0.7, 1.1, 0.5, 0.9]], [[1.3, 0.6, 0.8, 0.4]],
                                                 [[0.9, 0.9, 0.6, 0.7]]], dtype=torch.float64)
    model.backend.refresh()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # maps the 10 samples leave unconstrained: not this test's
        d = model.diagnostics()["kernel"]
    bound = torch.tensor(d["truncation_error"], dtype=torch.float64)
    assert d["tol"] == 1e-3 and not d["within_tol"] and bool((bound > 1e-3).any())
    ls = model.hypers.lengthscale.detach()
    gap = torch.cat([truncation_gaps(basis, ls[m:m + 1])  # each map in its own basis; the exact RBF written out
                     for m, basis in enumerate(model.backend.bases)])
    assert (gap <= bound + 1e-12).all() and bool((gap > 0.2 * bound).all())  # a bound, and not a loose one
    exact_model = InverseRFT3D(c, f, prior=MapPrior(mean="zero"), engine="pairs")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        k = exact_model.diagnostics()["kernel"]
    assert k["truncation_error"] == [0.0, 0.0, 0.0] and k["within_tol"]
