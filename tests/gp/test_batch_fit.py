"""gp.fit_together: models that share their contacts, fitted as one batch, end where each model's own
fit (InverseRFT.fit) ends: the same hyperparameters and the same loss at every step."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.batch_fit import fit_together, shares_fit
from irft_torch.rft import FourierStressMap

from .test_backends_vs_dense import random_contacts

PLUG_IN = dict(hyper_posterior="map", li_basis=False)  # what these tests test: the batched MAP fit


def noisy_forces(c, n, seed=0):
    """n force sets on the same contacts: the generic map at other scales, with 0-30 % multiplicative noise."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n):
        f = irft.rft.forces(FourierStressMap.generic(0.3 + 0.2 * i, 0.5), c)
        out.append(f * (1 + 0.1 * i * torch.randn(f.shape, generator=g, dtype=f.dtype)))
    return out


def build(c, forces, **kw):
    return [irft.InverseRFT(c, f, **kw, **PLUG_IN) for f in forces]


def hyper_vector(model):
    d = model.hypers.as_dict()
    return torch.tensor(d["lengthscale_x"] + d["lengthscale_z"] + d["outputscale"] + d["noise"], dtype=torch.float64)


def assert_each_ends_as_its_own_fit(together, alone, n_iter, lr, histories=None, rtol=1e-10, atol=0.0):
    """Fit each of ``alone`` (twins of ``together``, unfitted) on its own with InverseRFT.fit and compare
    the hyperparameters ``together`` ended at (and, given, the batch's loss histories) with them."""
    for i, (a, b) in enumerate(zip(alone, together)):
        ha = a.fit(n_iter=n_iter, lr=lr, progress=False)
        if histories is not None:
            torch.testing.assert_close(torch.tensor(histories[i]), torch.tensor(ha), rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(hyper_vector(b), hyper_vector(a), rtol=rtol, atol=atol)


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
        "different contacts": [irft.InverseRFT(c, f1, method="pairs", **PLUG_IN),
                               irft.InverseRFT(other, noisy_forces(other, 1)[0], method="pairs", **PLUG_IN)],
        "backend": [irft.InverseRFT(c, f1, method="observations", **PLUG_IN),
                    irft.InverseRFT(c, f2, method="observations", **PLUG_IN)],
        "physics mean": [irft.InverseRFT(c, f1, method="pairs", prior_mean="physics", **PLUG_IN),
                         irft.InverseRFT(c, f2, method="pairs", prior_mean="physics", **PLUG_IN)],
        "priors": [irft.InverseRFT(c, f1, method="pairs", **PLUG_IN),
                   irft.InverseRFT(c, f2, method="pairs", priors=None, **PLUG_IN)],
    }
    from gpytorch.priors import NormalPrior

    extra = [irft.InverseRFT(c, f, method="pairs", **PLUG_IN) for f in (f1, f2)]
    for m in extra:  # a user's own prior: not one this batching stacks
        m.hypers.kernel.register_prior("my_prior", NormalPrior(0.0, 1.0), lambda k: k.outputscale)
    cases["prior this batching does not know"] = extra
    frozen = [irft.InverseRFT(c, f, method="pairs", **PLUG_IN) for f in (f1, f2)]
    frozen[1].hypers.kernel.raw_outputscale.requires_grad_(False)
    cases["held fixed"] = frozen
    for why, models in cases.items():
        reason = shares_fit(models)
        assert reason is not None and why.split()[-1] in reason, (why, reason)
        twins = [irft.InverseRFT(m.train_contacts, m.train_forces, method=m.method, priors=m.priors,
                                 prior_mean=m.prior_mean_kind, **PLUG_IN) for m in models]
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


def test_auto_models_that_could_leave_the_pairs_space_are_fitted_one_by_one():
    """With method="auto", InverseRFT.fit moves to a space that became 2x cheaper (every 30 steps). 300
    distinct pairs in 600 samples: pairs at construction (lengthscale 1), but with long lengthscales the
    spectral basis is small enough to win. A batch cannot follow that move, so these models go one by
    one, and end where their own fits end, in the spectral space; the same models pinned to "pairs" batch."""
    g = torch.Generator().manual_seed(3)
    U, T = 300, 600
    pb, pg = torch.rand(U, generator=g) * 3 - 1.5, torch.rand(U, generator=g) * 3 - 1.5
    idx = torch.randint(0, U, (T,), generator=g)
    c = irft.rft.Contacts(pb[idx, None], pg[idx, None], torch.ones(T, 1), torch.ones(T, 1))
    forces = noisy_forces(c, 2)
    alone, together = build(c, forces), build(c, forces)
    assert all(m.method == "pairs" for m in alone + together)
    for m in alone + together:  # then set long (a user's starting values, or a refit of a fitted model)
        m.hypers.lengthscale = 10.0
    why = shares_fit(together)
    assert why is not None and "auto" in why
    histories = [m.fit(n_iter=30, lr=0.01, progress=False) for m in alone]
    assert all(m.method == "spectral" for m in alone)  # the move the batch could not have made
    batch = fit_together(together, n_iter=30, lr=0.01)
    for a, b, ha, hb in zip(alone, together, histories, batch):
        assert b.method == a.method == "spectral"
        torch.testing.assert_close(torch.tensor(hb), torch.tensor(ha), rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(hyper_vector(b), hyper_vector(a), rtol=1e-8, atol=1e-12)
    assert shares_fit(build(c, forces, method="pairs")) is None


def test_rows_out_of_contact_count_so_a_longer_recording_is_not_batched():
    """Rows with no segment in contact leave the angle pairs and weights as they are but count as force
    samples in the likelihood (T): a recording with them and one without must each end as their own fit."""
    c = random_contacts(T=30, M=4, seed=9, repeated=True)
    f1, f2 = noisy_forces(c, 2)
    idle = irft.rft.Contacts(torch.zeros(5, 4), torch.zeros(5, 4), torch.zeros(5, 4), torch.zeros(5, 4))
    c_long, f2_long = irft.rft.Contacts.cat([c, idle]), torch.cat([f2, torch.zeros(5, 2)])
    make = lambda: [irft.InverseRFT(c, f1, method="pairs", **PLUG_IN),  # noqa: E731
                    irft.InverseRFT(c_long, f2_long, method="pairs", **PLUG_IN)]
    together, alone = make(), make()
    assert "samples" in shares_fit(together)
    fit_together(together, n_iter=20, lr=0.1)
    assert_each_ends_as_its_own_fit(together, alone, n_iter=20, lr=0.1)


def test_the_same_model_twice_is_fitted_twice_in_a_row():
    c = random_contacts(T=20, M=3, seed=10, repeated=True)
    f = noisy_forces(c, 1)[0]
    m, ref = irft.InverseRFT(c, f, method="pairs", **PLUG_IN), irft.InverseRFT(c, f, method="pairs", **PLUG_IN)
    assert "twice" in shares_fit([m, m])
    fit_together([m, m], n_iter=10, lr=0.1)
    ref.fit(n_iter=10, lr=0.1, progress=False)
    ref.fit(n_iter=10, lr=0.1, progress=False)
    torch.testing.assert_close(hyper_vector(m), hyper_vector(ref), rtol=1e-10, atol=0)
    assert len(m.loss_history) == 20


@pytest.mark.parametrize("built_under", [torch.float32, torch.float64])
def test_float64_models_batch_exactly_under_torchs_float32_default(built_under):
    """torch's default dtype is float32 outside this test suite: the stacked hyperparameters of float64
    models (their constraints' floors and scales, the priors' centres) must not pass through it."""
    c = random_contacts(T=30, M=4, seed=11, repeated=True)
    forces = noisy_forces(c, 3)
    try:
        torch.set_default_dtype(built_under)
        together, alone = build(c, forces, method="pairs"), build(c, forces, method="pairs")
        torch.set_default_dtype(torch.float32)
        assert shares_fit(together) is None
        fit_together(together, n_iter=30, lr=0.1)
        # under the float32 default too; the batch's autograd step and a lone fit's closed-form step
        # (gp.backends.closed_form) differ in summation order, ~1e-9 after 30 steps; a float32 leak is 1e-7
        assert_each_ends_as_its_own_fit(together, alone, n_iter=30, lr=0.1, rtol=1e-8)
    finally:
        torch.set_default_dtype(torch.float64)
    assert all(b.hypers.kernel.raw_outputscale.dtype == torch.float64 for b in together)


def test_a_batch_that_breaks_down_leaves_each_model_to_its_own_fit(monkeypatch):
    """One model's covariance breaking down mid-batch must not move the others to that step: each model
    goes back to its start and is fitted on its own (the breaking one would raise its own error)."""
    from linear_operator.utils.errors import NotPSDError

    from irft_torch.gp.backends.pairs import PairsBackend
    from irft_torch.gp.batch_fit import _StackedHyperparameters

    c = random_contacts(T=30, M=4, seed=12, repeated=True)
    forces = noisy_forces(c, 3)
    together, alone = build(c, forces, method="pairs"), build(c, forces, method="pairs")
    calls = {"n": 0}
    nll = PairsBackend.negative_log_likelihood

    def breaks_in_the_batch(self, *args, **kwargs):
        if isinstance(self.hypers, _StackedHyperparameters):
            calls["n"] += 1
            if calls["n"] == 7:
                raise NotPSDError("simulated breakdown of one model in the batch")
        return nll(self, *args, **kwargs)

    monkeypatch.setattr(PairsBackend, "negative_log_likelihood", breaks_in_the_batch)
    batch = fit_together(together, n_iter=20, lr=0.1)
    assert calls["n"] == 7
    for a, b, hb in zip(alone, together, batch):
        ha = a.fit(n_iter=20, lr=0.1, progress=False)
        assert len(hb) == 20 and b.loss_history == hb
        torch.testing.assert_close(torch.tensor(hb), torch.tensor(ha), rtol=1e-10, atol=0)
        torch.testing.assert_close(hyper_vector(b), hyper_vector(a), rtol=1e-10, atol=0)


def test_a_mixed_list_is_batched_in_the_groups_that_can_share_and_each_ends_as_its_own_fit(monkeypatch):
    """Models on two sets of contacts and one in another space, interleaved: the two pairs-space groups are
    each one batch, the other model is fitted alone, and every model ends where its own fit ends."""
    import irft_torch.gp.batch_fit as bf

    c, other = random_contacts(T=30, M=4, seed=13, repeated=True), random_contacts(T=30, M=4, seed=14, repeated=True)
    fc, fo = noisy_forces(c, 3), noisy_forces(other, 2, seed=1)

    def make():
        return [irft.InverseRFT(c, fc[0], method="pairs", **PLUG_IN),
                irft.InverseRFT(other, fo[0], method="pairs", **PLUG_IN),
                irft.InverseRFT(c, fc[1], method="observations", **PLUG_IN),
                irft.InverseRFT(c, fc[2], method="pairs", **PLUG_IN),
                irft.InverseRFT(other, fo[1], method="pairs", **PLUG_IN),
                irft.InverseRFT(c, fc[1], method="pairs", **PLUG_IN)]

    together, alone = make(), make()
    sizes = []
    batch_fit = bf._fit_batch
    monkeypatch.setattr(bf, "_fit_batch", lambda ms, *a: sizes.append(len(ms)) or batch_fit(ms, *a))
    histories = fit_together(together, n_iter=20, lr=0.1)
    assert sorted(sizes) == [2, 3]  # (0, 3, 5) on c and (1, 4) on the other contacts; model 2 alone
    assert_each_ends_as_its_own_fit(together, alone, n_iter=20, lr=0.1, histories=histories, rtol=1e-8, atol=1e-12)
