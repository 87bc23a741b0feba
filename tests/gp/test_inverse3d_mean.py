"""The 3-D physics prior mean (gp.inverse3d.mean): scales recovered from forces made by the forward 3-D RFT with
known scales, mean maps against Li et al.'s generic maps, the posterior against the dense reference on the
residual forces plus the mean, the fallback to the scaled generic medium away from the data, files."""

import pytest
import torch
from gpytorch.constraints import GreaterThan

import irft_torch as irft
from irft_torch.gp.inverse3d import InverseRFT3D, point_contacts
from irft_torch.gp.inverse3d.mean import fit_mean_scales, shape_forces_3d
from irft_torch.rft import FourierStressMap, forces_3d

from .test_inverse3d import _set, dense, per_sample, turning_toe

F64 = torch.float64
GX00 = float(FourierStressMap.generic()(torch.zeros((), dtype=F64), torch.zeros((), dtype=F64))[0])


def test_scales_are_recovered_from_forces_of_a_scaled_generic_medium():
    c, _ = turning_toe(T=12)
    f = forces_3d(FourierStressMap.generic(0.5, 0.6), c, alpha_y=0.1)  # alpha_y = 0.1 = s_y * generic alpha_x(0, 0)
    s = fit_mean_scales(c, f)
    torch.testing.assert_close(s, torch.tensor([0.5, 0.1 / GX00, 0.6], dtype=F64), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(shape_forces_3d(c) @ s, f, rtol=1e-10, atol=1e-12)


def test_the_default_mean_scales_alpha_x_and_alpha_z_only():
    """prior_mean="physics" (the 3-D default): forces of a scaled generic medium whose alpha_y is zero give back
    its two scales exactly and s_y = 0, whatever the lateral forces; "physics_alpha_y" fits all three."""
    c, _ = turning_toe(T=12)
    f = forces_3d(FourierStressMap.generic(0.5, 0.6), c, alpha_y=0.0)
    m = InverseRFT3D(c, f)
    assert m.prior.mean == "physics"
    torch.testing.assert_close(m.mean_scales, torch.tensor([0.5, 0.0, 0.6], dtype=F64), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(m.mean_forces(c), f, rtol=1e-10, atol=1e-12)
    # with a lateral stress the two scales are still the least-squares fit of the x-z shapes alone (by hand)
    f2 = forces_3d(FourierStressMap.generic(0.5, 0.6), c, alpha_y=0.1)
    G = shape_forces_3d(c)[..., [0, 2]].reshape(-1, 2)
    want = torch.linalg.lstsq(G, f2.reshape(-1, 1)).solution[:, 0]
    s = InverseRFT3D(c, f2).mean_scales
    torch.testing.assert_close(s[[0, 2]], want, rtol=1e-9, atol=1e-12)
    assert float(s[1]) == 0.0
    s_all = InverseRFT3D(c, f2, prior_mean="physics_alpha_y").mean_scales
    torch.testing.assert_close(s_all, torch.tensor([0.5, 0.1 / GX00, 0.6], dtype=F64), rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="maps"):
        fit_mean_scales(c, f, maps=(0, 3))


def test_the_mean_map_is_the_scaled_generic_map():
    c, f = turning_toe(T=12)
    m = InverseRFT3D(c, f, prior_mean="physics_alpha_y")
    b = torch.linspace(-2.5, 2.5, 7, dtype=F64)  # outside the canonical square too: the mirror identity
    g = torch.linspace(-1.5, 1.5, 7, dtype=F64).flip(0)
    want = FourierStressMap.generic()(b, g)
    got = m.mean_forces(point_contacts(b, g))
    s = m.mean_scales
    torch.testing.assert_close(got[:, 0], s[0] * want[:, 0], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(got[:, 1], s[1] * GX00 * torch.ones_like(b), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(got[:, 2], s[2] * want[:, 1], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_posterior_is_the_dense_reference_on_the_residual_plus_the_mean(method):
    c, f = turning_toe(T=10)
    m = InverseRFT3D(c, f, method=method, prior_mean="physics_alpha_y", priors=None,
                     tol=1e-12 if method == "spectral" else 1e-7)
    ls = 0.8 + torch.rand(3, 1, 4, generator=torch.Generator().manual_seed(1), dtype=F64)
    os, noise = torch.tensor([0.09, 0.02, 0.2], dtype=F64), torch.tensor([4e-4, 3e-4, 5e-4], dtype=F64)
    _set(m, ls, os, noise)
    m.backend.refresh()
    G = shape_forces_3d(c)
    nll, post = dense(c, f - G @ m.mean_scales, ls, os, noise, False)
    rtol = 1e-8 if method != "spectral" else 1e-7
    torch.testing.assert_close(m.loss().detach(), nll, rtol=rtol, atol=0)
    q = turning_toe(T=6, seed=2)[0][1:5]
    mean, cov = post(q)
    p = m.predict_forces(q)
    torch.testing.assert_close(p.mean, mean + shape_forces_3d(q) @ m.mean_scales, rtol=rtol, atol=1e-10)
    torch.testing.assert_close(p.covariance, per_sample(cov, len(q)), rtol=1e-6, atol=1e-10)
    cv = m.cross_validate(torch.arange(len(c)) % 2)
    assert cv.mean.shape == (len(c), 3)


def test_away_from_the_data_the_maps_fall_back_on_the_scaled_generic_medium():
    """Short lengthscales and a corner of the square the stroke never reaches: the physics-mean model's map is its
    scaled generic map there, the zero-mean model's is zero."""
    c, f = turning_toe(T=12)
    out = {}
    for mean in ("zero", "physics"):
        m = InverseRFT3D(c, f, prior_mean=mean, priors=None)
        # below the 3-D floor (0.21), so that the data's reach vanishes at the corner: the former floor, 0.05
        m.hypers.kernel.base_kernel.register_constraint("raw_lengthscale", GreaterThan(0.05))
        with torch.no_grad():
            m.hypers.lengthscale = torch.full((3, 1, 4), 0.08, dtype=F64)
        m.backend.refresh()
        b = torch.tensor([-1.45, 1.45], dtype=F64)
        g = torch.tensor([1.5, -1.5], dtype=F64)
        out[mean] = (m.stress_map(b, g).mean, m.mean_forces(point_contacts(b, g)))
    assert out["zero"][0].abs().max() < 1e-6
    torch.testing.assert_close(out["physics"][0], out["physics"][1], rtol=1e-5, atol=1e-7)
    assert out["physics"][1].abs().max() > 0.01


def test_files_keep_the_scales_and_add_data_keeps_them_fixed(tmp_path):
    c, f = turning_toe(T=14)
    m = InverseRFT3D(c[:8], f[:8], prior_mean="physics")
    m.fit(n_iter=10, progress=False)
    scales = m.mean_scales.clone()
    m.add_data(c[8:], f[8:])
    torch.testing.assert_close(m.mean_scales, scales, rtol=0, atol=0)
    torch.testing.assert_close(m.train_forces, f, rtol=0, atol=0)  # as measured, not the residuals
    batch = InverseRFT3D(c, f, prior_mean="physics")  # all data at once: its own scales
    assert not torch.allclose(batch.mean_scales, scales)
    m.save(tmp_path / "m.pt")
    back = InverseRFT3D.load(tmp_path / "m.pt")
    torch.testing.assert_close(back.mean_scales, scales, rtol=0, atol=0)
    q = turning_toe(T=5, seed=7)[0]
    torch.testing.assert_close(back.predict_forces(q).mean, m.predict_forces(q).mean, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="prior_mean"):
        irft.InverseRFT(c, f, prior_mean="average", hyper_posterior="map", li_basis=False)
