"""Hyperparameter priors (gp.kernels.priors): against the generic map as truth and hand-derived values."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.kernels.priors import GENERIC_RMS, medium_scale, prior_centres

from .test_diagnostics import TRUTH, vertical_intrusion

P = math.pi


def grid(n=24):
    e = torch.linspace(-P / 2, P / 2, n + 1, dtype=torch.float64)
    c = (e[1:] + e[:-1]) / 2
    return torch.meshgrid(c, c, indexing="ij")


def test_generic_rms_is_that_of_the_generic_map_over_the_square():
    B, G = grid(200)
    rms = TRUTH(B, G).pow(2).mean((0, 1)).sqrt()
    torch.testing.assert_close(rms, torch.tensor(GENERIC_RMS, dtype=torch.float64), atol=2e-4, rtol=0)


def test_medium_scale_recovers_zeta_of_a_scaled_generic_medium():
    toe = irft.rft.CToe(0.02, 0.008, n_segments=8)
    c = irft.rft.contacts(toe, irft.rft.rectangle_path(n_steps=60))
    for zeta in (0.111, 0.33, 1.5):
        f = irft.rft.forces(irft.rft.FourierStressMap.generic(zeta, zeta), c)
        assert medium_scale(c, f) == pytest.approx(zeta, rel=1e-9)
        # in mN the same medium reads 1000 x larger (the prior follows the data's units)
        assert medium_scale(c, 1000 * f) == pytest.approx(1000 * zeta, rel=1e-9)


def test_vertical_intrusion_alpha_x_interval_covers_the_generic_map():
    """F_x is zero up to noise: alpha_x is informed at (0, pi/2) only. With the physical priors its
    variance stays that of real media (the medium's zeta read from F_z, x the generic rms), so the
    95 % interval covers the generic map over >= 90 % of the square (it collapsed to 0 +- 1e-4
    with the plain marginal likelihood, covering only where alpha_x happens to be 0)."""
    c, f = vertical_intrusion()
    model = irft.InverseRFT(c, f, priors="physical", hyper_posterior="map", li_basis=False)
    model.fit(n_iter=150, progress=False)
    B, G = grid()
    post = model.stress_map(B, G)
    lo, hi = post.interval(0.95)
    truth = TRUTH(B, G)
    inside = ((truth >= lo) & (truth <= hi)).double().mean((0, 1))
    assert float(inside[0]) >= 0.90
    assert float(inside[1]) >= 0.90
    # the x prior is the size of the generic map's (zeta = 1 here: alpha_z(0, pi/2) = 1)
    assert float(model.hypers.outputscale[0].sqrt()) == pytest.approx(GENERIC_RMS[0], rel=0.5)
    plain = irft.InverseRFT(c, f, priors=None, hyper_posterior="map", li_basis=False)
    plain.fit(n_iter=150, progress=False)
    lo, hi = plain.stress_map(B, G).interval(0.95)
    assert float(((truth[..., 0] >= lo[..., 0]) & (truth[..., 0] <= hi[..., 0])).double().mean()) < 0.5


def test_loss_subtracts_the_log_prior_over_T():
    """loss(priors) - loss(None) at equal hyperparameters = -(sum of normal log densities of
    log(value / centre)) / T, computed by hand."""
    c, f = vertical_intrusion()
    a = irft.InverseRFT(c, f, method="observations", priors="physical", hyper_posterior="map", li_basis=False)
    b = irft.InverseRFT(c, f, method="observations", priors=None, hyper_posterior="map", li_basis=False)
    b.hypers.load_state_dict(a.hypers.state_dict())
    from irft_torch.gp.inputs import _data_scales

    cen = prior_centres(a.train_contacts, a.train_forces, _data_scales(a.train_contacts, a.train_forces)[1], False)
    h = a.hypers

    def lognormal(v, centre, sd):
        z = (v.log() - math.log(centre) if isinstance(centre, float) else v.log() - centre.log()) / sd
        return (-0.5 * z.pow(2) - math.log(sd * math.sqrt(2 * P))).sum()

    with torch.no_grad():
        logp = (lognormal(h.outputscale, cen["outputscale"], math.log(2.0))
                + lognormal(h.lengthscale, 1.5, 1.5)
                + lognormal(h.noise, cen["noise"], math.log(10.0)))
        diff = a.loss() - b.loss()
    assert float(diff) == pytest.approx(-float(logp) / len(c), rel=1e-9)


def test_priors_carry_no_state_and_files_keep_them(tmp_path):
    c, f = vertical_intrusion()
    a = irft.InverseRFT(c, f, priors="physical", hyper_posterior="map", li_basis=False)
    a.fit(n_iter=5, progress=False)
    plain = irft.InverseRFT(c, f, priors=None, hyper_posterior="map", li_basis=False)
    assert set(a.state_dict()) == set(plain.state_dict())  # no prior buffers in the state
    plain.load_state_dict(a.state_dict())
    a.save(tmp_path / "m.pt")
    back = irft.InverseRFT.load(tmp_path / "m.pt")
    assert back.priors == "physical"
    torch.testing.assert_close(back.loss(), a.loss())
    with pytest.raises(ValueError, match="priors must be"):
        irft.InverseRFT(c, f, priors="flat", hyper_posterior="map", li_basis=False)


@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
def test_a_model_grown_by_add_data_has_the_objective_of_one_built_on_all_its_data(tmp_path, prior_mean):
    """The priors' centres follow the data: after add_data the loss (likelihood and log prior) at
    the same hyperparameters is the batch model's, and a saved and loaded model's."""
    toe = irft.rft.CToe(0.02, 0.008, opening="left")
    c = irft.rft.contacts(toe, irft.rft.spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=70))
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(0.45, 0.42), c)
    scale = 1.0 + 0.5 * torch.rand(70, generator=torch.Generator().manual_seed(0))
    batch = irft.InverseRFT(c, f, prior_mean=prior_mean, noise_scale=scale, hyper_posterior="map", li_basis=False)
    grown = irft.InverseRFT(c[:40], f[:40], prior_mean=prior_mean, noise_scale=scale[:40], hyper_posterior="map",
                            li_basis=False)
    grown.add_data(c[40:], f[40:], noise_scale=scale[40:])
    grown.load_state_dict(batch.state_dict())  # the same hyperparameters
    with torch.no_grad():
        assert grown.backend.log_prior().item() == pytest.approx(batch.backend.log_prior().item(), rel=1e-12)
        assert grown.loss().item() == pytest.approx(batch.loss().item(), rel=1e-10)
        grown.save(tmp_path / "g.pt")
        back = irft.InverseRFT.load(tmp_path / "g.pt")
        assert back.loss().item() == pytest.approx(grown.loss().item(), rel=1e-10)


def test_centre_sums_of_two_parts_give_the_direct_formulas_on_all_the_data():
    """Streaming adds the parts' sums (O(new samples)); the centres equal the direct formulas on the joined data:
    zeta = sum F.g / sum g.g, residual rms(F - s g) / rms(sum |w|) per axis (hand-written here)."""
    from irft_torch.gp.kernels.priors import CentreSums, _generic_forces, centres_of_sums

    toe = irft.rft.CToe(0.02, 0.008, opening="left")
    c = irft.rft.contacts(toe, irft.rft.spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=70))
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(0.45, 0.42), c)
    f = f + 0.05 * torch.randn(f.shape, generator=torch.Generator().manual_seed(1))
    sums = CentreSums.of(c[:25], f[:25]) + CentreSums.of(c[25:], f[25:])
    g = _generic_forces(c)
    w = torch.stack([c.weight_x.abs().sum(-1), c.weight_z.abs().sum(-1)], -1)
    zeta = float((f * g).sum() / g.pow(2).sum())
    s = (f * g).sum(0) / g.pow(2).sum(0)
    resid = (f - s * g).pow(2).mean(0).sqrt() / w.pow(2).mean(0).sqrt()
    assert sums.n == 70 and sums.medium_scale() == pytest.approx(zeta, rel=1e-12)
    torch.testing.assert_close(sums.residual_scale(), resid, rtol=1e-9, atol=0)
    torch.testing.assert_close(sums.map_scale(), f.pow(2).mean(0).sqrt() / w.pow(2).mean(0).sqrt(), rtol=1e-12, atol=0)
    cen = centres_of_sums(sums)
    torch.testing.assert_close(cen["noise"], 1e-2 * f.pow(2).mean(0), rtol=1e-12, atol=0)


def test_a_spatial_model_with_the_generic_shape_centres_its_residual_terms_on_what_the_shape_leaves():
    """kernel="li+generic" with places: the generic shape's variance carries the medium (centre zeta^2, log-sd ln 2),
    so the RBF and Li et al.'s term are centred, as the physics mean's residual GP, on max(0.3 zeta rms, r,
    0.5 max(r / rms) rms)^2 with r the forces' rms residual after the generic shape at its least-squares scale per
    axis over the rms summed weight (written out here), log-sd ln 10; the model starts there. A planar model with
    the shape, and one without ("li"), keep the centre at the map's own size, log-sd ln 2."""
    from irft_torch.gp.kernels.priors import _generic_forces

    toe = irft.rft.CToe(0.02, 0.008, opening="left")
    c = irft.rft.contacts(toe, irft.rft.spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=70))
    truth = irft.rft.FourierStressMap.generic(0.45, 0.42)
    f = irft.rft.forces(truth, c) * torch.tensor([1.3, 0.8], dtype=torch.float64)  # off the shape: a residual
    places = torch.stack([torch.linspace(0.0, 1.0, 70, dtype=torch.float64), torch.zeros(70, dtype=torch.float64)], -1)
    g = _generic_forces(c)
    w = torch.stack([c.weight_x.abs().sum(-1), c.weight_z.abs().sum(-1)], -1)
    zeta = float((f * g).sum() / g.pow(2).sum())
    s = (f * g).sum(0) / g.pow(2).sum(0)
    r = (f - s * g).pow(2).mean(0).sqrt() / w.pow(2).mean(0).sqrt()
    rms = torch.tensor(GENERIC_RMS, dtype=torch.float64)
    sigma = torch.maximum(torch.maximum(0.3 * zeta * rms, r), 0.5 * float((r / rms).max()) * rms)
    own = f.pow(2).mean(0).sqrt() / w.pow(2).mean(0).sqrt()
    big = torch.maximum(torch.maximum(zeta * rms, own), 0.5 * float((own / rms).max()) * rms)
    assert float((sigma / big).max()) < 0.5  # the two rules differ here
    spatial = irft.InverseRFT(c, f, locations=places, hyper_posterior="map")
    spatial_li = irft.InverseRFT(c, f, locations=places, prior=irft.MapPrior(kernel="li"), hyper_posterior="map")
    planar = irft.InverseRFT(c, f, prior=irft.MapPrior(kernel="li+generic"), hyper_posterior="map")
    li = irft.InverseRFT(c, f, prior=irft.MapPrior(kernel="li"), hyper_posterior="map")
    for model, centre, sd in ((spatial, sigma, math.log(10.0)), (spatial_li, big, math.log(2.0)),
                              (planar, big, math.log(2.0)), (li, big, math.log(2.0))):
        h = model.hypers
        torch.testing.assert_close(h.outputscale.detach(), centre.pow(2), rtol=1e-9, atol=0)
        torch.testing.assert_close(h.li.variance.detach(), centre.pow(2), rtol=1e-9, atol=0)
        assert float(h.kernel.outputscale_prior.scale) == pytest.approx(sd)
        assert float(h.li.variance_prior.scale) == pytest.approx(sd)
        with torch.no_grad():  # the registered density: log(value / centre) ~ N(0, sd), here at value = 2 centre
            h.outputscale = 2 * centre.pow(2)
            h.li.variance = 2 * centre.pow(2)
            for module, name in ((h.kernel, "outputscale_prior"), (h.li, "variance_prior")):
                prior, closure = module._priors[name][0], module._priors[name][1]
                torch.testing.assert_close(closure(module), torch.full((2,), math.log(2.0), dtype=torch.float64),
                                           rtol=1e-9, atol=0)
                assert float(prior.loc) == 0.0
    for model in (spatial, planar):
        h = model.hypers
        assert float(h.li.generic_variance_prior.scale) == pytest.approx(math.log(2.0))
        torch.testing.assert_close(h.li.generic_variance.detach(), torch.full((2,), zeta**2, dtype=torch.float64),
                                   rtol=1e-9, atol=0)
