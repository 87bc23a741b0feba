"""The default fit (``InverseRFT(contacts, forces).fit()``: Li et al.'s term and the Laplace hyperparameter
posterior): the same predictions in two fresh processes, the same predictions whether Adam stops early or runs
every step (the polish goes to the mode either way), the Laplace Hessian against autograd's second derivatives,
warnings said once, and a progress bar that writes a few lines, not one per step, to a pipe."""

import subprocess
import sys
import warnings

import pytest
import torch

import irft_torch as irft
from irft_torch.gp import fit_control
from irft_torch.gp.hyper import posterior as hp_mod
from irft_torch.gp.hyper.guard import HyperPosteriorWarning, said_once

F64 = torch.float64

SCRIPT = """
import sys, torch
import irft_torch as irft
torch.set_default_dtype(torch.float64)
toe = irft.rft.CToe(radius=0.02, width=0.008, n_segments=6)
path = irft.rft.spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=50)
c = irft.rft.contacts(toe, path)
f = irft.rft.forces(irft.rft.FourierStressMap.generic(0.8, 0.6), c)
f = f * (1 + 0.03 * torch.randn(f.shape, generator=torch.Generator().manual_seed(3)))
torch.manual_seed(int(sys.argv[1]))  # the global stream differs between the two processes: nothing may use it
m = irft.InverseRFT(c, f)
m.fit(n_iter=150, progress=False)
b = torch.linspace(-1.4, 1.4, 9)
post = m.stress_map(b[:, None], b[None, :])
pred = m.predict_forces(c[::5])
torch.save({"map": post.mean, "map_var": post.variance, "f": pred.mean, "f_var": pred.variance}, sys.argv[2])
"""


def _data(T=60):
    toe = irft.rft.CToe(radius=0.02, width=0.008, n_segments=6)
    path = irft.rft.spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=T)
    c = irft.rft.contacts(toe, path).to(dtype=F64)
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(0.8, 0.6).to(dtype=F64), c)
    return c, f * (1 + 0.03 * torch.randn(f.shape, generator=torch.Generator().manual_seed(3), dtype=F64))


def test_the_defaults_are_li_basis_and_laplace():
    c, f = _data(30)
    m = irft.InverseRFT(c, f)
    assert m.hyper_method == "laplace" and m.hypers.li is not None
    assert irft.InverseRFT(c, f, surface_offset=True).hyper_method == "map"  # the offset has its own Laplace std
    assert irft.InverseRFT(c, f, priors=None).hyper_method == "map"  # a flat prior: an improper posterior


def test_two_fresh_processes_predict_exactly_the_same(tmp_path):
    out = []
    for seed in (0, 1):
        path = tmp_path / f"run{seed}.pt"
        subprocess.run([sys.executable, "-c", SCRIPT, str(seed), str(path)], check=True, capture_output=True)
        out.append(torch.load(path))
    for key in out[0]:
        assert torch.equal(out[0][key], out[1][key]), key


def test_stopping_adam_early_before_the_polish_predicts_as_a_full_fit(monkeypatch):
    c, f = _data()
    b = torch.linspace(-1.4, 1.4, 9, dtype=F64)
    early = irft.InverseRFT(c, f)
    steps_early = len(early.fit(n_iter=300, progress=False))
    monkeypatch.setattr(fit_control, "CONVERGED_NATS", -float("inf"))  # never converged: all 300 steps
    full = irft.InverseRFT(c, f)
    steps_full = len(full.fit(n_iter=300, progress=False))
    assert steps_full == 300 and steps_early < 300
    a, r = early.stress_map(b[:, None], b[None, :]), full.stress_map(b[:, None], b[None, :])
    assert ((a.mean - r.mean).abs() / r.stddev).max() < 1e-3
    assert ((a.stddev - r.stddev).abs() / r.stddev).max() < 1e-3


@pytest.mark.parametrize("method,chunked", [("auto", False), ("spectral", True)])
def test_laplace_hessian_by_differences_is_autograd_s(method, chunked, monkeypatch):
    """In one batch, and one point at a time (``GRADIENT_ELEMENTS`` at 1) with the spectral basis prepared once for
    every point (``backend.prepare`` called once, each chunk in that basis)."""
    c, f = _data(40)
    m = irft.InverseRFT(c, f, hyper_posterior="map", method=method)
    m.fit(n_iter=60, progress=False)
    m.train()
    spec = hp_mod.hyper_spec(m.hypers)
    theta = spec.theta(m.hypers)
    calls = []
    if chunked:
        from irft_torch.gp.hyper import density

        monkeypatch.setattr(density, "GRADIENT_ELEMENTS", 1)
        for name in ("prepare", "space_for"):
            real = getattr(m.backend, name)
            monkeypatch.setattr(m.backend, name, lambda *a, real=real, name=name: calls.append(name) or real(*a))
        evaluate = density.log_posterior_and_grad
        monkeypatch.setattr(density, "log_posterior_and_grad",
                            lambda *a, **k: calls.append(len(a[2])) or evaluate(*a, **k))
    lp, g, H = hp_mod._hessian_by_differences(m.backend, spec, theta)
    if chunked:
        assert calls == ["prepare"] + [1] * (2 * theta.numel() + 1), calls
    th = theta.clone().requires_grad_(True)
    ref = hp_mod.log_posterior(m.backend, spec, th, exact_graph=True)
    (g_ref,) = torch.autograd.grad(ref, th, create_graph=True)
    H_ref = -torch.stack([torch.autograd.grad(g_ref[i], th, retain_graph=True)[0] for i in range(th.numel())])
    assert float(lp) == pytest.approx(float(ref.detach()), rel=1e-12, abs=1e-9)
    torch.testing.assert_close(g, g_ref.detach(), rtol=1e-8, atol=1e-8)
    assert float((H - H_ref).abs().max() / H_ref.abs().max()) < 1e-6


def test_chunked_gradients_of_no_points_are_empty():
    from irft_torch.gp.hyper import density

    c, f = _data(40)
    m = irft.InverseRFT(c, f, hyper_posterior="map")
    m.fit(n_iter=5, progress=False)
    spec = hp_mod.hyper_spec(m.hypers)
    lp, g = density.log_posterior_and_grad_chunked(m.backend, spec, torch.zeros(0, spec.size, dtype=F64))
    assert lp.shape == (0,) and g.shape == (0, spec.size)


def test_many_draws_warnings_are_said_once():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with said_once():
            for ls in (0.11, 0.12, 0.13):
                warnings.warn(f"lengthscales [{ls}] need more than 30 harmonics per angle", UserWarning,
                              stacklevel=2)
            for _ in range(3):
                warnings.warn("weights rest on 2 proposals", HyperPosteriorWarning, stacklevel=2)
    messages = [str(w.message) for w in caught]
    assert len(messages) == 2, messages
    assert sum("3 hyperparameter draw(s)" in m and "[0.11]" in m for m in messages) == 1
    assert sum(issubclass(w.category, HyperPosteriorWarning) for w in caught) == 1


def test_a_default_fit_on_ordinary_data_warns_nothing():
    c, f = _data()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        irft.InverseRFT(c, f).fit(n_iter=300, progress=False)
    assert not [str(w.message) for w in caught]


def test_progress_to_a_pipe_is_a_few_lines_not_one_per_step(capsys):
    c, f = _data(30)
    irft.InverseRFT(c, f, hyper_posterior="map").fit(n_iter=300, progress=True)  # capsys: stderr is not a terminal
    err = capsys.readouterr().err
    assert 0 < err.count("\r") <= 4, err.count("\r")


def test_truncated_draws_go_to_the_diagnostics_not_to_a_warning():
    kept: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with said_once(kept):
            for ls in (0.11, 0.12):
                warnings.warn(f"lengthscales [{ls}] need more than 30 harmonics per angle", UserWarning, stacklevel=2)
    assert not caught and len(kept) == 2 and "[0.11]" in kept[0]
    c, f = _data(30)
    m = irft.InverseRFT(c, f)
    m.fit(n_iter=60, progress=False)
    m.hyper_posterior.extra["truncated"] = "2 of the draws' kernels are truncated (...)"  # as fit_hyper_posterior sets
    assert "Hyperparameter draws: 2 of the draws' kernels are truncated" in str(m.diagnostics(warn=False))
