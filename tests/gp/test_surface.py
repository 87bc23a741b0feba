"""The free surface's height learned with the maps (``gp.surface.offset``): contacts moved by an offset
equal contacts of the physically shifted path; the surface likelihood equals the dense reference at
every offset; its offset gradient equals finite differences; a 1 cm error in the stated surface is
recovered to 1 mm on simulated data and the map error returns to the correct surface's."""

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.surface.offset import surface_loss
from irft_torch.rft import FourierStressMap, IToe, contacts, rectangle_path

from .dense_reference import axis_reference

TRUTH = FourierStressMap.generic(0.2, 0.2)


def plates(shift_m: float = 0.0):
    """Three flat plates (tilts -0.5, 0, 0.5 rad) on the rectangle gait from 1.5 cm above the
    surface; ``shift_m``: the whole path moved up by this much (m)."""
    parts = []
    for tilt in (-0.5, 0.0, 0.5):
        path = rectangle_path(penetration=0.05, shear=0.10, extraction=0.05, start=(-0.05, 0.015 + shift_m),
                              n_steps=60)
        parts.append(contacts(IToe(0.04, 0.02, tilt, n_segments=4), path))
    return irft.rft.Contacts.cat(parts)


def test_offset_equals_the_shifted_path():
    c = plates()
    assert c.has_surface
    # a surface 1 cm higher than stated is the same as the path 1 cm lower
    moved = c.with_surface_offset(torch.tensor(0.01))  # m
    direct = plates(shift_m=-0.01)
    for k in ("weight_x", "weight_z", "beta", "gamma"):
        torch.testing.assert_close(getattr(moved, k), getattr(direct, k), rtol=1e-9, atol=1e-9)
    weights_only = irft.rft.Contacts(c.beta, c.gamma, c.weight_x, c.weight_z)
    with pytest.raises(ValueError, match="depth"):
        irft.InverseRFT(weights_only, irft.rft.forces(TRUTH, c), surface_offset=True, hyper_posterior="map",
                        li_basis=False)


def test_surface_likelihood_matches_dense_reference_and_its_gradient():
    c = plates()
    f = irft.rft.forces(TRUTH, c.with_surface_offset(torch.tensor(-0.004)))
    f = f + 0.02 * f.abs().max() * torch.randn(f.shape, generator=torch.Generator().manual_seed(0))
    m = irft.InverseRFT(c, f, surface_offset=True, method="observations", priors=None, hyper_posterior="map",
                        li_basis=False)
    for delta in (-0.7, -0.2, 0.3):  # cm, the unit the offset is learned in
        with torch.no_grad():
            m.surface.offset.fill_(delta)
        loss = surface_loss(m)
        cd = c.with_surface_offset(torch.tensor(delta / 100))
        hp = m.hypers
        ls, os, nz = hp.lengthscale.detach(), hp.outputscale.detach(), hp.noise.detach()
        ref = sum(-axis_reference(cd, f[:, a], w, ls[a, 0], os[a], nz[a])[0]
                  for a, w in enumerate((cd.weight_x, cd.weight_z)))
        torch.testing.assert_close(loss.detach(), ref, rtol=1e-8, atol=1e-10)
        assert_offset_gradient_is_central_differences(m, loss, delta)


def assert_offset_gradient_is_central_differences(m, loss, delta: float, h: float = 1e-5) -> None:
    """d loss / d offset by autograd (``loss``: ``surface_loss(m)`` at ``delta`` cm) against central differences."""
    (g,) = torch.autograd.grad(loss, m.surface.offset)
    with torch.no_grad():
        m.surface.offset.fill_(delta + h)
        up = surface_loss(m)
        m.surface.offset.fill_(delta - h)
        down = surface_loss(m)
    torch.testing.assert_close(g[0], (up - down) / (2 * h), rtol=1e-5, atol=1e-8)


def test_one_centimetre_error_is_recovered_to_a_millimetre():
    true_c = plates()
    f = irft.rft.forces(TRUTH, true_c)
    f = f + 0.02 * f.abs().max() * torch.randn(f.shape, generator=torch.Generator().manual_seed(1))
    stated = plates(shift_m=-0.01)  # the surface stated 1 cm too high: every depth 1 cm too large
    learned = irft.InverseRFT(stated, f, surface_offset=True, hyper_posterior="map", li_basis=False)
    learned.fit(300, progress=False)
    est = learned.surface_offset
    assert abs(float(est.mean[0]) + 0.01) < 0.001, est.mean  # m: within 1 mm of the truth, -1 cm
    assert 0 < float(est.std[0]) < 0.001
    lo, hi = est.interval(0.95)
    assert lo[0] < -0.01 < hi[0]
    torch.testing.assert_close(est.in_cm().mean, 100 * est.mean)
    ref = irft.InverseRFT(true_c, f, hyper_posterior="map", li_basis=False)
    ref.fit(300, progress=False)
    ignored = irft.InverseRFT(stated, f, hyper_posterior="map", li_basis=False)
    ignored.fit(300, progress=False)
    b, g = true_c.beta[true_c.weight_z > 0], true_c.gamma[true_c.weight_z > 0]  # the visited pairs
    truth = TRUTH(b, g)

    def rmse(model):
        with torch.no_grad():
            return (model.stress_map(b, g).mean - truth).pow(2).mean(0).sqrt()

    r_ref, r_learned, r_ignored = rmse(ref), rmse(learned), rmse(ignored)
    assert (r_learned <= 2 * r_ref + 1e-3).all(), (r_learned, r_ref)
    assert (r_ignored[1] > 5 * r_learned[1]), (r_ignored, r_learned)


def test_predictions_after_init_surface_are_at_the_chosen_offset(tmp_path):
    """init_surface moves the offset: the map, the force predictions and a saved and loaded copy are then
    those of the contacts at that offset (the dense reference on ``with_surface_offset(start)``)."""
    c = plates()
    f = irft.rft.forces(TRUTH, c.with_surface_offset(torch.tensor(-0.004)))
    f = f + 0.02 * f.abs().max() * torch.randn(f.shape, generator=torch.Generator().manual_seed(2))
    m = irft.InverseRFT(c, f, surface_offset=True, method="pairs", priors=None, hyper_posterior="map", li_basis=False)
    start = m.init_surface(torch.linspace(-0.01, 0.01, 5))
    assert float(start[0]) != 0.0
    cd = c.with_surface_offset(start)
    hp = m.hypers
    ls, os, nz = hp.lengthscale.detach(), hp.outputscale.detach(), hp.noise.detach()
    th = torch.tensor([[0.2, 1.0], [-0.4, 0.6]])
    q = cd[10:14]
    m.save(tmp_path / "m.pt")
    back = irft.InverseRFT.load(tmp_path / "m.pt")
    for model in (m, back):
        post, pred = model.stress_map(th[:, 0], th[:, 1]), model.predict_forces(q)
        for a, w in enumerate((cd.weight_x, cd.weight_z)):
            _, map_posterior, force_posterior = axis_reference(cd, f[:, a], w, ls[a, 0], os[a], nz[a])
            mu, var = map_posterior(th)
            torch.testing.assert_close(post.mean[:, a], mu, rtol=1e-7, atol=1e-9)
            torch.testing.assert_close(post.variance[:, a], var, rtol=1e-7, atol=1e-12)
            mu_f, _ = force_posterior(q, (q.weight_x, q.weight_z)[a])
            torch.testing.assert_close(pred.mean[:, a], mu_f, rtol=1e-7, atol=1e-9)


def test_module_apply_reaches_the_surface_offset():
    """``model.apply(fn)`` (torch's recursive visit) reaches the ``SurfaceOffset`` like any submodule;
    its own method was named ``apply`` and shadowed torch's, so the visit called it with ``fn``."""
    c = plates()
    m = irft.InverseRFT(c, irft.rft.forces(TRUTH, c), surface_offset=True, method="pairs", priors=None,
                        hyper_posterior="map", li_basis=False)
    seen = []
    m.apply(lambda module: seen.append(type(module).__name__))
    assert "SurfaceOffset" in seen and seen[-1] == "InverseRFT"
    with torch.no_grad():
        m.surface.offset.fill_(1.0)  # cm: the surface 1 cm higher than stated = the path 1 cm lower
    moved, direct = m.surface.shifted(c), plates(shift_m=-0.01)
    for k in ("weight_x", "weight_z"):
        torch.testing.assert_close(getattr(moved, k), getattr(direct, k), rtol=1e-9, atol=1e-9)
