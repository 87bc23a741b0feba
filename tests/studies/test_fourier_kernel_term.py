"""experiments/calibration/fourier_kernel_term.py: its Li-basis kernel spans Li et al.'s fitting functions, and
its dense
zero-mean model is the library's (the same posterior at the same hyperparameters)."""

import math

import torch

from irft_torch import InverseRFT
from irft_torch.rft import CToe, contacts, forces
from irft_torch.rft.paths import pose_path
from irft_torch.rft.stress_maps import FourierStressMap
from irft_torch.studies.calibration import medium

from . import experiment

F64 = torch.float64


def _script():
    return experiment("fourier_kernel_term")


def _angles(n, seed):
    g = torch.Generator().manual_seed(seed)
    return tuple((torch.rand(n, generator=g, dtype=F64) - 0.5) * math.pi for _ in range(2))


def test_the_li_term_is_the_product_of_first_harmonics_and_spans_li_et_al_s_maps():
    fk = _script()
    b1, g1 = _angles(30, 0)
    b2, g2 = _angles(20, 1)
    p = {"ls": torch.zeros(4, dtype=F64), "os": torch.tensor(-80.0, dtype=F64), "li": torch.tensor(math.log(2.5))}
    k = fk.kernel(p, b1, g1, b2, g2, li=True)  # the RBF part at variance e^-80: the Li term alone

    def features(b, g):  # {1, cos 2b, sin 2b} x {1, cos g, sin g}, by hand
        fb = torch.stack([torch.ones_like(b), torch.cos(2 * b), torch.sin(2 * b)], -1)
        fg = torch.stack([torch.ones_like(g), torch.cos(g), torch.sin(g)], -1)
        return (fb[:, :, None] * fg[:, None, :]).reshape(len(b), 9)

    # sigma_L^2 / 4 times the features' inner product (1 + cos 2(b - b'))(1 + cos(g - g')) / 4
    ref = 2.5 / 4 * features(b1, g1) @ features(b2, g2).T
    assert torch.allclose(k, ref, atol=1e-12)
    # Li et al.'s generic map and both poppy-seed sets lie in that span over the canonical square: least squares
    # on the 9 features leaves nothing (the RBF alone has no such finite span)
    b, g = _angles(400, 2)
    Phi = features(b, g)
    for m in (FourierStressMap.generic().double(), FourierStressMap.poppy_seeds_loose().double(),
              FourierStressMap.poppy_seeds_close().double()):
        a = m(b, g)  # (400, 2)
        coef = torch.linalg.lstsq(Phi, a).solution
        assert float((Phi @ coef - a).abs().max()) < 1e-10 * float(a.abs().max())
    sharp, _ = medium("sharp", 0)  # the harness' tanh-shaped media are not: the check has power
    a = sharp(b, g)
    coef = torch.linalg.lstsq(Phi, a).solution
    assert float((Phi @ coef - a).abs().max()) > 1e-2 * float(a.abs().max())


def test_the_dense_zero_mean_model_is_the_library_s_at_the_same_hyperparameters():
    fk = _script()
    t = torch.linspace(0, 1, 30, dtype=F64)
    c = contacts(CToe(0.02, 0.01, n_segments=6), pose_path(t, -0.06 + 0.12 * t, 0.01 - 0.05 * torch.sin(math.pi * t),
                                                            0.6 * t))
    f = forces(FourierStressMap.generic().double(), c)
    f = f + 0.02 * f.abs().amax(0) * torch.randn(f.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    model = InverseRFT(c, f, method="observations", hyper_posterior="map", li_basis=False)
    ls = torch.tensor([[0.9, 1.3, 0.7, 2.0], [1.1, 0.8, 1.6, 0.6]], dtype=F64)
    os, noise = torch.tensor([0.03, 0.2], dtype=F64), torch.tensor([2e-4, 5e-4], dtype=F64) * f.pow(2).mean(0)
    model.hypers.lengthscale = ls[:, None, :]
    model.hypers.outputscale = os
    model.hypers.noise = noise
    b, g = _angles(25, 4)
    post = model.stress_map(b, g)
    for a, w in enumerate((c.weight_x, c.weight_z)):
        ax = fk.DenseAxis(c.beta, c.gamma, w, f[:, a], li=False)
        ax.p.update(ls=ls[a].log(), os=os[a].log(), noise=model.hypers.noise[a].log())
        mean, cov = ax.posterior(b, g)
        assert torch.allclose(mean, post.mean[:, a], rtol=1e-6, atol=1e-9)
        assert torch.allclose(cov.diagonal(), post.variance[:, a], rtol=1e-6, atol=1e-12)


def test_the_generic_term_is_a_scale_with_a_gaussian_prior_on_li_et_al_s_generic_shape():
    """rbf+li+generic: u g_a(theta) g_a(theta') per map; alone (RBF variance e^-80, no k_Li) it is Bayesian
    linear regression of the forces on the generic shape's forces, whose posterior is known by hand."""
    fk = _script()
    generic = FourierStressMap.generic().double()
    b1, g1 = _angles(30, 5)
    b2, g2 = _angles(20, 6)
    p = {"ls": torch.zeros(4, dtype=F64), "os": torch.tensor(-80.0, dtype=F64), "gen": torch.tensor(math.log(0.7))}
    for a in (0, 1):
        k = fk.kernel(p, b1, g1, b2, g2, li=False, generic=a)
        assert torch.allclose(k, 0.7 * generic(b1, g1)[:, a, None] * generic(b2, g2)[None, :, a], atol=1e-12)
    t = torch.linspace(0, 1, 25, dtype=F64)
    c = contacts(CToe(0.02, 0.01, n_segments=5), pose_path(t, -0.05 + 0.1 * t, 0.01 - 0.04 * torch.sin(math.pi * t),
                                                            0.8 * t))
    zeta, u, noise = 0.6, 0.5, 1e-3
    f = zeta * forces(generic, c)
    f = f + math.sqrt(noise) * torch.randn(f.shape, generator=torch.Generator().manual_seed(7), dtype=F64)
    b, g = _angles(15, 8)
    for a, w in enumerate((c.weight_x, c.weight_z)):
        ax = fk.DenseAxis(c.beta, c.gamma, w, f[:, a], li=False, generic=a, zeta=1.0)
        ax.p.update(os=torch.tensor(-80.0, dtype=F64), gen=torch.tensor(math.log(u), dtype=F64),
                    noise=torch.tensor(math.log(noise), dtype=F64))
        mean, cov = ax.posterior(b, g)
        h = (w * generic(c.beta, c.gamma)[..., a]).sum(-1)  # (T,) the generic shape's forces per unit scale
        post_var = 1 / (1 / u + h @ h / noise)  # the scale's posterior, by hand
        post_mean = post_var * (h @ f[:, a]) / noise
        shape = generic(b, g)[:, a]
        assert abs(post_mean - zeta) < 0.05  # the data recover the scale
        assert torch.allclose(mean, post_mean * shape, rtol=1e-8, atol=1e-10)
        assert torch.allclose(cov, post_var * shape[:, None] * shape[None, :], rtol=1e-6, atol=1e-12)
