"""Where the Laplace approximation of the hyperparameter posterior fails (gp.hyper.guard): a noise driven to its
wall by noise-free forces, a direction the plain likelihood leaves flat, proposals that are all impossible; each
against a hand-derived case, the truth or the plug-in."""

import math
import warnings

import pytest
import torch

import irft_torch as irft
import irft_torch.gp.hyper.posterior as hyper_posterior
from irft_torch.gp.hyper import guard
from irft_torch.rft import FourierStressMap

from .test_backends_vs_dense import data

F64 = torch.float64
TRUTH = FourierStressMap.generic(0.452, 0.417)


# ---- the pieces, by hand ------------------------------------------------------------------------------
def test_proposal_covariance_floors_flat_and_convex_directions_by_hand():
    R = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(0), dtype=F64))[0]
    lam = torch.tensor([4.0, 1e-9, -2.0], dtype=F64)  # curved, flat, convex
    cov = guard.proposal_covariance(R @ torch.diag(lam) @ R.T)
    expected = R @ torch.diag(torch.tensor([0.25, guard.MAX_LOG_SD**2, guard.MAX_LOG_SD**2], dtype=F64)) @ R.T
    torch.testing.assert_close(cov, expected, rtol=1e-12, atol=1e-12)


def test_walls_are_the_coordinates_one_sd_from_an_impossible_setting():
    def log_p(x):  # a Gaussian, impossible below -1 in coordinate 0 and above 3 in coordinate 2
        lp = -0.5 * x.pow(2).sum(-1)
        return torch.where((x[:, 0] < -1) | (x[:, 2] > 3), torch.full_like(lp, -math.inf), lp)

    mode = torch.zeros(3, dtype=F64)
    assert guard.walls(log_p, mode, torch.tensor([2.0, 2.0, 2.0], dtype=F64)).tolist() == [True, False, False]
    assert guard.walls(log_p, mode, torch.tensor([0.5, 2.0, 4.0], dtype=F64)).tolist() == [False, False, True]


def test_possible_draws_are_finite_and_above_their_bounds():
    theta = torch.tensor([[0.0, 0.0], [800.0, 0.0], [0.0, math.log(0.5)], [-1.0, 1.0]], dtype=F64)
    lower = torch.tensor([0.0, 0.5], dtype=F64)
    assert guard.possible(theta, lower).tolist() == [True, False, False, True]


def test_the_warning_names_only_what_failed():
    assert guard.reliability_message(40.0, 0.3, 128, []) is None
    m = guard.reliability_message(40.0, 0.9, 128, [])
    assert "k-hat 0.90 > 0.7" in m and "effective sample size" not in m and "nuts" in m
    m = guard.reliability_message(1.0, 0.3, 128, ["noise_x"])
    assert "effective sample size 1.0 < 2" in m and "k-hat" not in m and "noise_x" in m


# ---- on models ----------------------------------------------------------------------------------------
def gait1_noise_free():
    toe = irft.rft.CToe(radius=0.02, width=0.008, n_segments=10)
    c = irft.rft.contacts(toe, irft.rft.rectangle_path(0.05, 0.40, 0.05, n_steps=100))
    return c, irft.rft.forces(TRUTH, c)


def coverage95(model):
    """(2,) the share of a 40 x 40 grid of the square whose truth lies in the 95 % interval."""
    g = torch.linspace(-math.pi / 2, math.pi / 2, 40, dtype=F64)
    B, G = torch.meshgrid(g, g, indexing="ij")
    with torch.no_grad():
        lo, hi = model.stress_map(B, G).interval(0.95)
    truth = TRUTH(B, G)
    return ((truth >= lo) & (truth <= hi)).double().mean((0, 1))


def test_noise_free_forces_hold_the_noise_at_its_wall_and_the_weights_stay_healthy():
    """Noise-free forces push the noise variance down until the kernel matrix is not positive definite: no
    mode, and a Gaussian in log-noise that is mostly impossible. Before the guard, the importance weights
    collapsed onto one proposal far from the fit (ESS 1.00, k-hat 9.3): the "posterior" was one random setting."""
    c, f = gait1_noise_free()
    model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    model.fit(n_iter=150, lr=0.05, progress=False)
    plug_in = coverage95(model)  # measured 0.614 (x) and 1.0 (z)
    with pytest.warns(guard.HyperPosteriorWarning, match="held at their fitted values.*noise_x"):
        hp = model.fit_hyper_posterior("laplace", generator=torch.Generator().manual_seed(0))
    assert {"noise_x", "noise_z"} <= set(hp.extra["held"])
    for lab in ("noise_x", "noise_z"):  # held: every draw at the polished value
        i = hp.labels.index(lab)
        assert torch.equal(hp.theta[:, i], hp.mode[i].expand(hp.n_draws))
    assert hp.ess >= 4 and hp.n_draws >= 4  # was 1.00: one proposal
    ours = coverage95(model)  # against the truth: measured 0.712 and 1.0
    assert (ours >= plug_in).all() and ours[0] > plug_in[0] + 0.05, (ours, plug_in)


def test_a_direction_the_plain_likelihood_leaves_flat_gets_finite_draws():
    """priors=None after 5 steps: a lengthscale the likelihood hardly constrains. Before, its Gaussian was 1000
    wide in log(lengthscale); a draw at theta = 906 (a lengthscale of e^906) was kept and loading it raised."""
    c, f = data(T=20)
    model = irft.InverseRFT(c, f, method="pairs", priors=None, hyper_posterior="map", li_basis=False)
    model.fit(n_iter=5, progress=False)
    with pytest.warns(guard.HyperPosteriorWarning, match="priors=None.*improper"):
        hp = model.fit_hyper_posterior("laplace", generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(hp.theta.exp()).all()
    assert float(hp.covariance.diagonal().max()) <= guard.MAX_LOG_SD**2 * (1 + 1e-9)
    B, G = torch.meshgrid(torch.linspace(-1.5, 1.5, 7, dtype=F64), torch.linspace(-1.5, 1.5, 7, dtype=F64),
                          indexing="ij")
    post = model.stress_map(B, G)
    assert torch.isfinite(post.mean).all() and torch.isfinite(post.variance).all()


def test_every_proposal_impossible_keeps_the_plug_in_and_says_so(monkeypatch):
    c, f = data(T=20)
    model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    model.fit(n_iter=30, progress=False)
    B, G = torch.meshgrid(torch.linspace(-1.5, 1.5, 5, dtype=F64), torch.linspace(-1.5, 1.5, 5, dtype=F64),
                          indexing="ij")
    real = hyper_posterior._log_posterior_many

    def proposals_impossible(backend, spec, x):  # the wall check (2P rows) sees the real density
        lp = real(backend, spec, x)
        return torch.full_like(lp, -math.inf) if x.shape[0] == 64 else lp

    monkeypatch.setattr(hyper_posterior, "_log_posterior_many", proposals_impossible)
    with pytest.warns(guard.HyperPosteriorWarning, match="every one of the 64 Laplace proposals.*plug-in"):
        hp = model.fit_hyper_posterior("laplace", n_proposals=64)
    assert hp.n_draws == 1 and torch.equal(hp.theta[0], hp.mode) and float(hp.weights[0]) == 1.0
    ours = model.stress_map(B, G)
    model.fit_hyper_posterior("map")  # the plug-in at the same (polished) hyperparameters
    plug = model.stress_map(B, G)
    torch.testing.assert_close(ours.mean, plug.mean, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(ours.variance, plug.variance, rtol=1e-12, atol=1e-14)


# ---- the adaptive second stage, on a target known in closed form -----------------------------------------
def misplaced_gaussian():
    """A 3-D Gaussian target N(m, S) and a start 2 target sds off in its first coordinate: m, S, the target, start."""
    m = torch.tensor([0.3, -1.0, 2.0], dtype=F64)
    A = torch.tensor([[1.0, 0.0, 0.0], [0.6, 0.8, 0.0], [-0.3, 0.2, 0.5]], dtype=F64)
    S = A @ A.T
    target = torch.distributions.MultivariateNormal(m, S)
    return m, S, target, m + torch.tensor([2.0, 0.0, 0.0], dtype=F64) * S.diagonal().sqrt()


def moments(x, lw):
    """Weighted mean (P,), covariance (P, P) and effective sample size of draws x (N, P) with log weights lw (N,)."""
    w = (lw - lw.max()).exp()
    w = w / w.sum()
    mu = (w[:, None] * x).sum(0)
    d = x - mu
    return mu, (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0), float(1 / w.pow(2).sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_misplaced_proposal_is_corrected_by_the_second_stage(seed):
    """Target N(m, S) in 3-D; the first proposal is centred 2 target sds off in one coordinate: its weights are
    unreliable (k-hat 1.3-1.5, ESS 5-10 of 256). With the second stage the weighted mean and covariance approach
    the target's (closed form) and the effective sample size grows (measured: mean error 0.3-0.7 -> 0.05-0.1,
    ESS -> 56-162 of 512)."""
    from irft_torch.gp.hyper.importance import first_stage, importance_sample
    from irft_torch.gp.hyper.pareto import pareto_khat

    m, S, target, start = misplaced_gaussian()

    g = torch.Generator().manual_seed(seed)
    first = first_stage(target.log_prob, start, S, 30.0, 256, g)
    x1, lp1, lw1, n1 = importance_sample(target.log_prob, first, start, S, 30.0, g)
    x2, lp2, lw2, n2 = importance_sample(target.log_prob, first, start, S, 30.0, g, adapt=guard.unreliable)
    assert n1 == 1 and n2 == 2 and x2.shape == (512, 3)
    torch.testing.assert_close(lp2, target.log_prob(x2))  # the log posterior of every draw is returned
    assert guard.unreliable(lw1) and pareto_khat(lw1) > 0.7
    mu1, C1, ess1 = moments(x1, lw1)
    mu2, C2, ess2 = moments(x2, lw2)
    assert ess2 > 3 * ess1
    assert (mu2 - m).abs().max() < min(0.12, 0.5 * float((mu1 - m).abs().max()))
    assert (C2 - S).abs().max() < 0.2


def test_held_coordinates_are_exactly_those_the_draws_keep_fixed(monkeypatch):
    """Some proposal always impossible and a new wall at every check: two rounds of holding, then the third round's
    proposals stand. Every coordinate reported held is constant across the draws, and the others are not."""
    c, f = data(T=20)
    model = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    model.fit(n_iter=30, progress=False)
    real = hyper_posterior._log_posterior_many

    def one_impossible(backend, spec, x):
        lp = real(backend, spec, x)
        return torch.cat([lp.new_full((1,), -math.inf), lp[1:]]) if x.shape[0] == 64 else lp

    def first_at_wall(log_p_many, mode, sd):
        out = torch.zeros(mode.numel(), dtype=torch.bool)
        out[0] = True
        return out

    monkeypatch.setattr(hyper_posterior, "_log_posterior_many", one_impossible)
    monkeypatch.setattr(guard, "walls", first_at_wall)
    with pytest.warns(guard.HyperPosteriorWarning, match="held at their fitted values"):
        hp = model.fit_hyper_posterior("laplace", n_proposals=64, n_draws=None)
    assert hp.extra["held"] == hp.labels[:2]
    spread = (hp.theta - hp.mode).abs().amax(0)
    assert (spread[:2] == 0).all() and (spread[2:] > 0).all()


def test_a_polish_that_runs_into_an_underflow_falls_back_to_the_fitted_point(monkeypatch):
    """With priors=None, L-BFGS can run along a flat direction until a variance underflows (e^-745 = 0) and the
    Hessian there is NaN (the wheel study's plain likelihood with the generic shape raised LinAlgError from eigh).
    The polish then keeps the fitted point, whose Hessian is finite; where even that one is not, the plug-in is
    kept and a HyperPosteriorWarning says why. The NaN is injected: a Hessian of NaN wherever the polish moved."""
    c, f = data(T=20)
    model = irft.InverseRFT(c, f, method="pairs", priors=None, hyper_posterior="map", li_basis=False)
    model.fit(n_iter=30, progress=False)
    start = hyper_posterior.hyper_spec(model.hypers).theta(model.hypers).clone()
    real = hyper_posterior._hessian

    def nan_where_moved(backend, spec, theta):
        lp, g, H = real(backend, spec, theta)
        moved = not torch.allclose(spec.full(theta), start, rtol=0, atol=1e-9)
        return (lp, g, torch.full_like(H, math.nan)) if moved else (lp, g, H)

    monkeypatch.setattr(hyper_posterior, "_hessian", nan_where_moved)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", guard.HyperPosteriorWarning)
        hp = model.fit_hyper_posterior("laplace", generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(hp.mode, start, rtol=0, atol=1e-9)  # the fitted point, not the polished one
    assert hp.n_draws > 1 and torch.isfinite(hp.theta).all()

    def nan_everywhere(backend, spec, theta):
        lp, g, H = real(backend, spec, theta)
        return lp, g, torch.full_like(H, math.nan)

    monkeypatch.setattr(hyper_posterior, "_hessian", nan_everywhere)
    with pytest.warns(guard.HyperPosteriorWarning, match="Hessian is not finite.*plug-in"):
        hp = model.fit_hyper_posterior("laplace", generator=torch.Generator().manual_seed(0))
    assert hp.n_draws == 1 and float(hp.weights[0]) == 1.0
