"""gp.fit_together: models that share their contacts, fitted as one batch, end where each model's own
fit (InverseRFT.fit) ends: the same hyperparameters and the same loss at every step."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.batch_fit import fit_together, shares_fit
from irft_torch.rft import FourierStressMap

from .test_backends_vs_dense import random_contacts


def noisy_forces(c, n, seed=0):
    """n force sets on the same contacts: the generic map at other scales, with 0-30 % multiplicative noise."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n):
        f = irft.rft.forces(FourierStressMap.generic(0.3 + 0.2 * i, 0.5), c)
        out.append(f * (1 + 0.1 * i * torch.randn(f.shape, generator=g, dtype=f.dtype)))
    return out


def build(c, forces, **kw):
    return [irft.InverseRFT(c, f, **kw) for f in forces]


def hyper_vector(model):
    d = model.hypers.as_dict()
    return torch.tensor(d["lengthscale_x"] + d["lengthscale_z"] + d["outputscale"] + d["noise"], dtype=torch.float64)


@pytest.mark.parametrize("tied", [True, False])
@pytest.mark.parametrize("priors", ["physical", None])
def test_a_batch_ends_where_each_fit_ends(tied, priors):
    c = random_contacts(T=40, M=4, seed=5, repeated=True)
    forces = noisy_forces(c, 3)
    kw = dict(method="pairs", tied_noise=tied, priors=priors)
    alone = build(c, forces, **kw)
    together = build(c, forces, **kw)
    if priors is None:  # other starting lengthscales, as a sensitivity study has
        for i, (a, b) in enumerate(zip(alone, together)):
            a.hypers.lengthscale = b.hypers.lengthscale = 0.5 + 0.5 * i
    assert shares_fit(together) is None
    histories = [m.fit(n_iter=30, lr=0.1, progress=False) for m in alone]
    batch = fit_together(together, n_iter=30, lr=0.1)
    for a, b, ha, hb in zip(alone, together, histories, batch):
        torch.testing.assert_close(torch.tensor(hb), torch.tensor(ha), rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(hyper_vector(b), hyper_vector(a), rtol=1e-8, atol=1e-12)
        assert b.loss_history == hb
        pa, pb = a.stress_map(torch.tensor([0.3]), torch.tensor([-0.4])), b.stress_map(torch.tensor([0.3]),
                                                                                       torch.tensor([-0.4]))
        torch.testing.assert_close(pb.mean, pa.mean, rtol=1e-8, atol=1e-12)
        torch.testing.assert_close(pb.variance, pa.variance, rtol=1e-7, atol=1e-12)


def test_models_that_cannot_share_a_batch_are_fitted_one_by_one():
    c = random_contacts(T=30, M=4, seed=6, repeated=True)
    other = random_contacts(T=30, M=4, seed=7, repeated=True)
    f1, f2 = noisy_forces(c, 2)
    cases = {
        "different contacts": [irft.InverseRFT(c, f1, method="pairs"),
                               irft.InverseRFT(other, noisy_forces(other, 1)[0], method="pairs")],
        "backend": [irft.InverseRFT(c, f1, method="observations"), irft.InverseRFT(c, f2, method="observations")],
        "physics mean": [irft.InverseRFT(c, f1, method="pairs", prior_mean="physics"),
                         irft.InverseRFT(c, f2, method="pairs", prior_mean="physics")],
        "priors": [irft.InverseRFT(c, f1, method="pairs"), irft.InverseRFT(c, f2, method="pairs", priors=None)],
    }
    from gpytorch.priors import NormalPrior

    extra = [irft.InverseRFT(c, f, method="pairs") for f in (f1, f2)]
    for m in extra:  # a user's own prior: not one this batching stacks
        m.hypers.kernel.register_prior("my_prior", NormalPrior(0.0, 1.0), lambda k: k.outputscale)
    cases["prior this batching does not know"] = extra
    frozen = [irft.InverseRFT(c, f, method="pairs") for f in (f1, f2)]
    frozen[1].hypers.kernel.raw_outputscale.requires_grad_(False)
    cases["held fixed"] = frozen
    for why, models in cases.items():
        reason = shares_fit(models)
        assert reason is not None and why.split()[-1] in reason, (why, reason)
        twins = [irft.InverseRFT(m.train_contacts, m.train_forces, method=m.method, priors=m.priors,
                                 prior_mean=m.prior_mean_kind) for m in models]
        for m, t in zip(models, twins):
            for name, module, prior, closure, _ in m.hypers.named_priors():
                if "my_prior" in name:
                    t.hypers.kernel.register_prior("my_prior", prior, closure)
            for q, r in zip(m.hypers.parameters(), t.hypers.parameters()):
                r.requires_grad_(q.requires_grad)
        fit_together(models, n_iter=10, lr=0.1)
        for m, t in zip(models, twins):
            t.fit(n_iter=10, lr=0.1, progress=False)
            torch.testing.assert_close(hyper_vector(m), hyper_vector(t), rtol=1e-10, atol=0)


def test_fit_together_checks_its_arguments():
    c = random_contacts(T=20, M=3, seed=8, repeated=True)
    models = build(c, noisy_forces(c, 2), method="pairs")
    for bad in (dict(n_iter=-1), dict(n_iter=2.5), dict(lr=0.0), dict(lr=math.nan)):
        with pytest.raises(ValueError, match="n_iter"):
            fit_together(models, **{"n_iter": 5, "lr": 0.1, **bad})


def test_float32_models_batch_in_float32():
    c = random_contacts(T=30, M=4, seed=9, repeated=True)
    forces = [f.float() for f in noisy_forces(c, 2)]
    c32 = c.to(dtype=torch.float32)
    alone = build(c32, forces, method="pairs", dtype=torch.float32)
    together = build(c32, forces, method="pairs", dtype=torch.float32)
    assert shares_fit(together) is None
    for m in alone:
        m.fit(n_iter=15, lr=0.1, progress=False)
    fit_together(together, n_iter=15, lr=0.1)
    for a, b in zip(alone, together):
        assert b.hypers.outputscale.dtype == torch.float32
        torch.testing.assert_close(b.hypers.outputscale, a.hypers.outputscale, rtol=1e-4, atol=0)
