"""Leave-one-group-out predictions (gp.cross_validation) against the closed form on the dense
reference: with S = W K W^T + noise the full covariance of the training forces and a = S^-1 (y - m),
the samples I held out are predicted with mean y_I - (S^-1)_II^-1 a_I and covariance (S^-1)_II^-1
(Rasmussen & Williams 2006, eq. 5.12, for blocks). Independent of the backends: explicit W and K."""

import pytest
import torch

import irft_torch as irft
from irft_torch.rft import FourierStressMap

from .dense_reference import W_dense, k_dense
from .test_backends_vs_dense import BACKENDS, TOL, data, set_hypers


def dense_loo(model, c, f, groups, noise_scale=None):
    """Closed-form leave-one-group-out mean and variance (T, 2), measurement noise included."""
    ls, os, noise = model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach()
    th = torch.stack([c.beta.reshape(-1), c.gamma.reshape(-1)], -1)
    mean, var = torch.zeros_like(f), torch.zeros_like(f)
    for a, w in enumerate((c.weight_x, c.weight_z)):
        W = W_dense(w)
        scale2 = torch.ones(len(f)) if noise_scale is None else noise_scale[:, a] ** 2
        S = W @ k_dense(th, th, ls[a, 0], os[a]) @ W.T + noise[a] * torch.diag(scale2)
        m = torch.zeros(len(f))
        if model.prior_mean_kind == "physics":
            m = model.hypers.mean_scales.detach()[a] * (w * FourierStressMap.generic()(c.beta, c.gamma)[..., a]).sum(-1)
        Sinv = torch.linalg.inv(S)
        alpha = Sinv @ (f[:, a] - m)
        for g in groups.unique():
            idx = (groups == g).nonzero()[:, 0]
            C = torch.linalg.inv(Sinv[idx][:, idx])
            mean[idx, a] = f[idx, a] - C @ alpha[idx]
            var[idx, a] = torch.diagonal(C)
    return mean, var


@pytest.mark.parametrize("prior", ["zero", "physics"])
@pytest.mark.parametrize("method", BACKENDS)
def test_leave_one_out_matches_the_closed_form(method, prior):
    c, f = data(T=20, repeated=True)
    model = irft.InverseRFT(c, f, prior_mean=prior, method=method, priors=None, hyper_posterior="map", li_basis=False)
    set_hypers(model)
    groups = torch.arange(len(f))
    ours = model.cross_validate(groups, include_noise=True)
    mean, var = dense_loo(model, c, f, groups)
    tol = TOL[method]
    torch.testing.assert_close(ours.mean, mean, rtol=tol * 10, atol=tol * 10)
    torch.testing.assert_close(ours.variance, var, rtol=tol * 10, atol=tol * 10)
    torch.testing.assert_close(ours.forces, f)


@pytest.mark.parametrize("method", BACKENDS)
def test_leave_one_group_out_matches_the_closed_form_with_noise_scales(method):
    c, f = data(T=24, repeated=True)
    scale = 0.5 + torch.rand(len(f), 2, generator=torch.Generator().manual_seed(4))
    model = irft.InverseRFT(c, f, method=method, priors=None, noise_scale=scale, hyper_posterior="map", li_basis=False)
    set_hypers(model)
    groups = torch.arange(len(f)) % 5  # interleaved groups of 4-5 samples
    ours = model.cross_validate(groups.numpy() * 0.5, include_noise=True)  # any labels: floats here
    mean, var = dense_loo(model, c, f, groups, noise_scale=scale)
    tol = TOL[method] * 10
    torch.testing.assert_close(ours.mean, mean, rtol=tol, atol=tol)
    torch.testing.assert_close(ours.variance, var, rtol=tol, atol=tol)
    assert ours.labels == [0.0, 0.5, 1.0, 1.5, 2.0]
    torch.testing.assert_close(ours.groups, groups)
    # without the noise: the variance of the predicted force alone, smaller by the sample's noise
    bare = model.cross_validate(groups)
    torch.testing.assert_close(bare.variance + model.hypers.noise.detach() * scale**2, ours.variance)
    rmse = (mean - f).pow(2).mean(0).sqrt()
    torch.testing.assert_close(ours.rmse(), rmse, rtol=tol, atol=tol)
    lpd = torch.distributions.Normal(mean, var.sqrt()).log_prob(f).mean(0)
    torch.testing.assert_close(ours.log_predictive_density(), lpd, rtol=1e-6, atol=1e-6)
    # a measurement is scored with its noise either way (sample 0 touches nothing: variance 0 without it)
    assert (bare.variance[0] == 0).all()
    torch.testing.assert_close(bare.log_predictive_density(), lpd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("method", BACKENDS)
def test_tied_noise_float32_and_data_added_in_parts(method):
    c, f = data(T=24, repeated=True)
    scale = 0.5 + torch.rand(len(f), 2, generator=torch.Generator().manual_seed(5))
    model = irft.InverseRFT(c[:10], f[:10], method=method, priors=None, tied_noise=True, prior_mean="physics",
                            noise_scale=scale[:10], hyper_posterior="map", li_basis=False)
    model.add_data(c[10:17], f[10:17], noise_scale=scale[10:17])
    model.add_data(c[17:], f[17:], noise_scale=scale[17:])
    set_hypers(model)
    model.hypers.noise = torch.tensor([0.05, 0.05])
    groups = torch.arange(len(f)) // 6  # groups spanning the parts
    mean, var = dense_loo(model, c, f, groups, noise_scale=scale)
    ours = model.cross_validate(groups, include_noise=True)
    tol = TOL[method] * 10
    torch.testing.assert_close(ours.mean, mean, rtol=tol, atol=tol)
    torch.testing.assert_close(ours.variance, var, rtol=tol, atol=tol)
    single = irft.InverseRFT(c.to(dtype=torch.float32), f.float(), method=method, priors=None, dtype=torch.float32,
                             hyper_posterior="map", li_basis=False)
    set_hypers(single)
    mean, var = dense_loo(single, c, f, groups)
    ours = single.cross_validate(groups, include_noise=True)
    assert ours.mean.dtype == torch.float32
    torch.testing.assert_close(ours.mean.double(), mean, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours.variance.double(), var, rtol=1e-3, atol=1e-4)
    assert torch.isfinite(single.cross_validate(groups).log_predictive_density()).all()


@pytest.mark.parametrize("method", BACKENDS)
def test_the_model_is_unchanged(method):
    c, f = data(T=20)
    model = irft.InverseRFT(c, f, method=method, priors=None, hyper_posterior="map", li_basis=False)
    model.fit(n_iter=5, progress=False)
    backend = model.backend
    before = model.predict_forces(c)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    modes = [m.training for m in model.modules()]
    model.cross_validate(torch.arange(20) // 4)
    assert model.backend is backend
    assert [m.training for m in model.modules()] == modes
    after = model.predict_forces(c)
    torch.testing.assert_close(after.mean, before.mean, rtol=0, atol=0)
    torch.testing.assert_close(after.variance, before.variance, rtol=0, atol=0)
    for k, v in model.state_dict().items():
        torch.testing.assert_close(v, state[k], rtol=0, atol=0)


def test_bad_groups_are_refused():
    c, f = data(T=20)
    model = irft.InverseRFT(c, f, method="pairs", priors=None, hyper_posterior="map", li_basis=False)
    with pytest.raises(ValueError, match="groups must have one label per training sample"):
        model.cross_validate(torch.arange(19))
    with pytest.raises(ValueError, match="at least 2 distinct labels"):
        model.cross_validate(torch.zeros(20))
    with pytest.raises(ValueError, match="NaN"):
        model.cross_validate(torch.full((20,), float("nan")))


def test_a_learned_surface_is_cross_validated_at_its_offset():
    from .test_surface import TRUTH, plates

    c = plates()
    f = irft.rft.forces(TRUTH, c.with_surface_offset(torch.tensor(-0.004)))
    model = irft.InverseRFT(c, f, surface_offset=True, method="pairs", priors=None, hyper_posterior="map",
                            li_basis=False)
    set_hypers(model)
    with torch.no_grad():
        model.surface.offset.fill_(-0.4)  # cm
    groups = torch.arange(len(f)) // 60  # the three plates
    ours = model.cross_validate(groups, include_noise=True)
    mean, var = dense_loo(model, c.with_surface_offset(torch.tensor(-0.004)), f, groups)
    torch.testing.assert_close(ours.mean, mean, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(ours.variance, var, rtol=1e-7, atol=1e-7)


def test_a_custom_backend_class_is_not_silently_replaced():
    c, f = data(T=20)
    model = irft.InverseRFT(c, f, method="pairs", priors=None, hyper_posterior="map", li_basis=False)

    class Mine(type(model.backend)):
        pass

    model.backend.__class__ = Mine
    with pytest.raises(TypeError, match="Mine"):
        model.cross_validate(torch.arange(20) // 4)


@pytest.mark.parametrize("method", ["pairs", "spectral"])
def test_refit_is_a_model_fitted_without_each_group(method):
    c, f = data(T=24, repeated=True)
    scale = 0.5 + torch.rand(len(f), 2, generator=torch.Generator().manual_seed(6))
    kw = dict(prior_mean="physics", method=method, noise_scale=scale, lengthscale=0.8)
    model = irft.InverseRFT(c, f, **kw, hyper_posterior="map", li_basis=False)
    model.fit(n_iter=20, lr=0.1, progress=False)
    groups = torch.arange(len(f)) // 8
    ours = model.cross_validate(groups, refit=True, n_iter=20, lr=0.1)
    for g in range(3):
        held = groups == g
        alone = irft.InverseRFT(c[~held], f[~held], **{**kw, "noise_scale": scale[~held]}, hyper_posterior="map",
                                li_basis=False)
        alone.fit(n_iter=20, lr=0.1, progress=False)
        post = alone.predict_forces(c[held])
        torch.testing.assert_close(ours.mean[held], post.mean, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(ours.variance[held], post.variance, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(ours.noise[held], alone.hypers.noise.detach() * scale[held] ** 2)
    # the hyperparameters differ from the model's: refit is not the fixed-hyperparameter answer
    fixed = model.cross_validate(groups)
    assert (fixed.mean - ours.mean).abs().max() > 1e-6


def test_refit_with_a_learned_surface_is_refused():
    from .test_surface import TRUTH, plates

    c = plates()
    model = irft.InverseRFT(c, irft.rft.forces(TRUTH, c), surface_offset=True, method="pairs", hyper_posterior="map",
                            li_basis=False)
    with pytest.raises(NotImplementedError, match="learned surface"):
        model.cross_validate(torch.arange(len(c)) // 60, refit=True)


def test_coverage_counts_measurements_inside_the_interval_by_hand():
    """Four samples, variance 1 and noise 3 (sd 2): residuals 0, 3.9, 4.0 and -4.1 against 1.96 x 2 = 3.92."""
    from irft_torch.gp.cross_validation import GroupPredictions

    F64 = torch.float64
    res = torch.tensor([[0.0, 0.0], [3.9, 0.0], [4.0, 0.0], [-4.1, 10.0]], dtype=F64)
    pred = GroupPredictions(mean=res, variance=torch.ones(4, 2, dtype=F64), forces=torch.zeros(4, 2, dtype=F64),
                            groups=torch.arange(4), labels=[0, 1, 2, 3], noise=torch.full((4, 2), 3.0, dtype=F64),
                            include_noise=False)
    torch.testing.assert_close(pred.coverage(0.95), torch.tensor([0.5, 0.75], dtype=F64))
    torch.testing.assert_close(pred.coverage(0.5), torch.tensor([0.25, 0.75], dtype=F64))  # 0.674 x 2 = 1.35
    with pytest.raises(ValueError, match="level"):
        pred.coverage(95)
