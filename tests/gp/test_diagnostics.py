"""model.diagnostics(): what the forces constrain, against cases whose answer is known by hand."""

import math
import warnings

import pytest
import torch

import irft_torch as irft

from .dense_reference import truncation_gaps

TRUTH = irft.rft.FourierStressMap.generic()


def vertical_intrusion():
    """A flat plate pushed straight down: every segment at beta = 0, gamma = pi/2, where alpha_x of
    the generic map is 0 by symmetry, so F_x is noise only and alpha_x cannot be learned."""
    toe = irft.rft.IToe(0.04, 0.008, n_segments=5)
    t = torch.linspace(0, 3, 120, dtype=torch.float64)
    c = irft.rft.contacts(toe, irft.rft.pose_path(t, torch.zeros(120), 0.01 - 0.02 * t))
    f = irft.rft.forces(TRUTH, c)
    return c, f + 0.02 * torch.randn(f.shape, generator=torch.Generator().manual_seed(0), dtype=f.dtype)


def test_vertical_intrusion_reports_alpha_x_unidentified():
    c, f = vertical_intrusion()
    assert float(TRUTH(torch.tensor(0.0), torch.tensor(math.pi / 2))[0]).__abs__() < 1e-12
    model = irft.InverseRFT(c, f, priors=None, hyper_posterior="map",
                            li_basis=False)  # the plain likelihood: alpha_x's variance collapses
    model.fit(n_iter=150, progress=False)
    with pytest.warns(UserWarning, match="alpha_x is not constrained by these forces"):
        report = model.diagnostics()
    x, z = report.maps
    assert report.unidentified == ["alpha_x"] and x.unidentified and not z.unidentified
    assert x.signal_to_noise < 1 < z.signal_to_noise
    # one angle pair: no embedding coordinate varies, so no lengthscale is informed
    assert x.uninformed_lengthscales == ["sin 2beta", "cos 2beta", "sin gamma", "cos gamma"]
    assert "posterior is the prior" in str(report)


def test_a_rotating_c_toe_informs_every_lengthscale_and_both_maps():
    toe = irft.rft.CToe(0.02, 0.008, n_segments=10)
    path = irft.rft.spline_path([(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)], n_steps=150)
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(TRUTH, c)
    f = f * (1 + 0.02 * torch.randn(f.shape, generator=torch.Generator().manual_seed(1), dtype=f.dtype))
    model = irft.InverseRFT(c, f, hyper_posterior="map", li_basis=False)
    model.fit(n_iter=100, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        report = model.diagnostics()
    assert report.unidentified == []
    for m in report.maps:
        assert m.uninformed_lengthscales == [] and m.signal_to_noise > 10
        assert 0.05 < m.constrained_fraction <= 1 and 0 < m.variance_ratio < 0.5


def test_an_approximate_kernel_is_reported_with_a_bound_that_holds():
    """The spectral basis is an approximation: diagnostics() states its error bound and the tolerance, and the
    bound holds against the exact kernel evaluated densely (RBF on the embedding, written out here) at random angle
    pairs. An exact backend adds no such note."""
    c, f = vertical_intrusion()
    model = irft.InverseRFT(c, f, method="spectral", tol=1e-3, hyper_posterior="map", li_basis=False)
    with torch.no_grad():
        model.hypers.lengthscale = torch.tensor([[[0.7, 1.1, 0.5, 0.9]], [[1.3, 0.6, 0.8, 0.4]]], dtype=torch.float64)
    model.backend.refresh()
    bound = model.truncation_error()
    note = model.diagnostics(warn=False).notes[0]
    assert note.startswith("Kernel: spectral") and f"<= {float(bound.max()):.1e}" in note and "within tol 1e-03" in note
    gap = truncation_gaps(model.backend.basis, model.hypers.lengthscale.detach())  # the exact RBF, written out
    assert (gap <= bound + 1e-12).all()
    exact_model = irft.InverseRFT(c, f, method="observations", hyper_posterior="map", li_basis=False)
    assert not any(n.startswith("Kernel") for n in exact_model.diagnostics(warn=False).notes)
