"""The 3-D lengthscale floor (``gp.kernels.hyperparameters.LENGTHSCALE_FLOOR_3D``): at the floor the default
spectral kernel is the dense RBF to its tolerance (no truncation by the harmonics cap), and a model file written
with the former floor (0.05) loads with the lengthscales it was saved with."""

from __future__ import annotations

import math

import torch

from irft_torch.gp.inverse3d import InverseRFT3D
from irft_torch.gp.kernels.hyperparameters import LENGTHSCALE_FLOOR_3D

from .test_inverse3d import dense, turning_toe


def test_at_the_floor_the_default_spectral_kernel_is_the_dense_one():
    c, f = turning_toe(T=12)
    model = InverseRFT3D(c, f, priors=None, prior_mean="zero", method="spectral")  # default tol, harmonics cap
    assert model.tol == 1e-7 and model.max_harmonics == 30
    with torch.no_grad():  # sin 2beta and sin gamma pulled onto the floor, as the wheels' fits pull alpha_x's; their
        raw = model.hypers.kernel.base_kernel.raw_lengthscale  # partners long: the truncation bound's worst case
        raw.fill_(-40.0)
        model.hypers.outputscale = torch.tensor([0.09, 0.02, 0.2])
        model.hypers.noise = torch.tensor([4e-4, 3e-4, 5e-4])
        ls = model.hypers.lengthscale.clone()
        ls[..., 1::2] = 30.0
        model.hypers.lengthscale = ls
    ls = model.hypers.lengthscale
    torch.testing.assert_close(ls[..., ::2], torch.full_like(ls[..., ::2], LENGTHSCALE_FLOOR_3D), rtol=0, atol=1e-15)
    model.backend.refresh()
    assert float(model.truncation_error().max()) <= model.tol
    ref, _ = dense(c, f, ls, model.hypers.outputscale, model.hypers.noise, False)
    # a kernel error of 1e-8 of the outputscale, amplified by signal over noise (about 1e3 here)
    torch.testing.assert_close(model.loss().detach(), ref.detach(), rtol=1e-5, atol=0)


def test_a_file_from_the_former_floor_keeps_its_lengthscales(tmp_path):
    c, f = turning_toe(T=10)
    model = InverseRFT3D(c, f, prior_mean="zero", hyper_posterior="map")
    model.save(tmp_path / "new.pt")
    d = torch.load(tmp_path / "new.pt", weights_only=True)
    floor = "kernel.base_kernel.raw_lengthscale_constraint.lower_bound"
    assert float(d["hypers"][floor]) == LENGTHSCALE_FLOOR_3D
    # a file as the former version wrote it: its constraint's floor 0.05, raw values measured from it, and an
    # initial lengthscale below today's floor
    d["hypers"][floor] = torch.tensor(0.05, dtype=torch.float64)
    d["options"]["lengthscale"] = 0.1
    raw = torch.linspace(-3.0, 1.0, 12, dtype=torch.float64).reshape(3, 1, 4)
    d["hypers"]["kernel.base_kernel.raw_lengthscale"] = raw
    torch.save(d, tmp_path / "old.pt")
    back = InverseRFT3D.load(tmp_path / "old.pt")
    expect = torch.tensor([math.log1p(math.exp(r)) + 0.05 for r in raw.reshape(-1).tolist()],
                          dtype=torch.float64).reshape(3, 1, 4)
    torch.testing.assert_close(back.hypers.lengthscale.detach(), expect, rtol=1e-12, atol=0)
    assert float(expect.min()) < LENGTHSCALE_FLOOR_3D  # below today's floor, and kept
    assert back.hypers.lengthscale_floor == 0.05
    # and a file written now reads back as written
    again = InverseRFT3D.load(tmp_path / "new.pt")
    torch.testing.assert_close(again.hypers.lengthscale.detach(), model.hypers.lengthscale.detach(), rtol=0, atol=0)
