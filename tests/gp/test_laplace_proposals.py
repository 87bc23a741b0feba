"""The Laplace posterior's proposals (``gp.hyper.importance``): the split Student-t (``split_axes``, Geweke 1989)
and the stages added while the weights are unreliable or few, checked against closed forms: a split normal's sides,
the density's normalisation, and the moments of targets that importance sampling must recover."""

import math

import pytest
import torch

from irft_torch.gp.hyper import guard
from irft_torch.gp.hyper.importance import (
    SplitAxes,
    _split_t,
    _split_t_log_density,
    first_stage,
    importance_sample,
    split_axes,
)
from irft_torch.gp.hyper.pareto import pareto_khat

from .test_laplace_guard import misplaced_gaussian, moments

F64 = torch.float64


def split_normal_log_prob(x: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """A split normal in the first coordinate (sd ``lo`` below 0, ``hi`` above, unnormalised; both sides meet at
    0), a unit normal in the others."""
    s = torch.where(x[:, 0] > 0, torch.full_like(x[:, 0], hi), torch.full_like(x[:, 0], lo))
    return -0.5 * (x[:, 0] / s).pow(2) - 0.5 * x[:, 1:].pow(2).sum(-1)


def test_split_axes_reads_each_sides_width():
    """Along the wide side of a split normal (sd 2 against the Laplace 1) the log posterior falls by delta^2 / 8
    at delta sds, so the side's factor is delta / sqrt(delta^2 / 4) = 2 at every step; every other side is
    Gaussian with unit sd and keeps the Laplace width (factor 1, the scale sqrt(inflate))."""
    mode = torch.zeros(3, dtype=F64)
    axes = split_axes(lambda x: split_normal_log_prob(x, 1.0, 2.0), mode, torch.eye(3, dtype=F64), inflate=1.5)
    torch.testing.assert_close(axes.L, math.sqrt(1.5) * torch.eye(3, dtype=F64))
    torch.testing.assert_close(axes.hi, torch.tensor([2.0, 1.0, 1.0], dtype=F64))
    torch.testing.assert_close(axes.lo, torch.ones(3, dtype=F64))


def test_split_axes_follow_the_cholesky_factor():
    """With a correlated Laplace covariance C = L L^T the axes are L's columns: a Gaussian target of covariance
    (2 L) (2 L)^T falls by delta^2 / 8 along each, so every side's factor is 2."""
    L = torch.tensor([[1.0, 0.0], [0.6, 0.8]], dtype=F64)
    target = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=F64), scale_tril=2 * L)
    axes = split_axes(target.log_prob, torch.zeros(2, dtype=F64), L @ L.T, most=3.0)
    torch.testing.assert_close(axes.L, L)
    torch.testing.assert_close(axes.lo, torch.full((2,), 2.0, dtype=F64))
    torch.testing.assert_close(axes.hi, torch.full((2,), 2.0, dtype=F64))


def test_split_axes_keep_the_laplace_width_where_a_side_is_impossible_and_cap_a_flat_one():
    """A side whose probes are impossible (-inf) keeps the Laplace width; a side along which the log posterior does
    not fall at all is widened only to ``most``."""
    def log_p(x):
        lp = -0.5 * x.pow(2).sum(-1)
        lp = torch.where(x[:, 0] < -1.0, torch.full_like(lp, -math.inf), lp)  # a wall below -1 in coordinate 0
        return torch.where(x[:, 1] > 0, -0.5 * x[:, 0].pow(2), lp)  # flat above 0 in coordinate 1

    axes = split_axes(log_p, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), most=3.0)
    assert float(axes.lo[0]) == pytest.approx(1.0)
    assert float(axes.hi[1]) == pytest.approx(3.0)


def test_split_t_density_integrates_to_one_and_matches_its_draws():
    """The split-t's density over a 2-D grid sums to 1 (to the grid's error); its draws' mean is the density's mean
    on the grid; and they put the share hi / (lo + hi) of their mass on each axis' positive side, with the sides'
    mean distances in the ratio of their factors (a split normal's, per axis)."""
    L = torch.tensor([[1.0, 0.0], [0.5, 0.8]], dtype=F64)
    axes = SplitAxes(L, torch.tensor([0.5, 1.0], dtype=F64), torch.tensor([1.5, 0.7], dtype=F64))
    mean = torch.tensor([0.3, -0.2], dtype=F64)
    g = torch.linspace(-40, 40, 1601, dtype=F64)
    X = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    total = float(_split_t_log_density(X, mean, axes, 5.0).exp().sum() * (g[1] - g[0]) ** 2)
    assert total == pytest.approx(1.0, abs=2e-3)
    x, _ = _split_t(mean, axes, 30.0, 4096, torch.Generator().manual_seed(3), qmc=True)
    q30 = _split_t_log_density(X, mean, axes, 30.0).exp() * (g[1] - g[0]) ** 2
    torch.testing.assert_close(x.mean(0), (q30[:, None] * X).sum(0) / q30.sum(), rtol=0, atol=0.01)
    y = torch.linalg.solve_triangular(L, (x - mean).T, upper=False).T
    share = axes.hi / (axes.lo + axes.hi)
    assert float(((y > 0).double().mean(0) - share).abs().max()) < 0.02
    ratio = (y.clamp_min(0).sum(0) / (y > 0).sum(0)) / ((-y).clamp_min(0).sum(0) / (y < 0).sum(0))
    torch.testing.assert_close(ratio, axes.hi / axes.lo, rtol=0.05, atol=0)


def test_importance_sampling_of_a_skewed_target_is_better_with_the_split_proposal():
    """A split normal (sd 1 below, 2.5 above its mode) with the Laplace Gaussian at the mode (unit sd): the
    symmetric Student-t's weights are heavy-tailed; the split-t's are not, and its weighted mean and variance are
    those of the split normal in closed form (mean sqrt(2 / pi) (s2 - s1), variance (1 - 2 / pi) (s2 - s1)^2 +
    s1 s2)."""
    lo, hi = 1.0, 2.5
    log_p = lambda x: split_normal_log_prob(x, lo, hi)  # noqa: E731
    mode, cov = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    mean_true = math.sqrt(2 / math.pi) * (hi - lo)
    var_true = (1 - 2 / math.pi) * (hi - lo) ** 2 + lo * hi
    out = {}
    for name, axes in (("symmetric", None), ("split", split_axes(log_p, mode, cov, 1.5))):
        g = torch.Generator().manual_seed(7)
        first = first_stage(log_p, mode, 1.5 * cov, 30.0, 256, g, axes=axes)
        x, _, lw, _ = importance_sample(log_p, first, mode, 1.5 * cov, 30.0, g, axes=axes)
        w = (lw - lw.max()).exp()
        w = w / w.sum()
        mu = float((w * x[:, 0]).sum())
        var = float((w * (x[:, 0] - mu).pow(2)).sum())
        out[name] = (mu, var, float(1 / w.pow(2).sum()), pareto_khat(lw))
    mu, var, ess, khat = out["split"]
    assert khat < 0.5 < out["symmetric"][3]
    assert ess > 1.25 * out["symmetric"][2]
    assert mu == pytest.approx(mean_true, abs=0.05)
    assert var == pytest.approx(var_true, rel=0.05)


def test_stages_are_added_while_asked_and_weighed_together():
    """A Gaussian target (closed-form moments) with the proposal started 2 sd off in one coordinate: asking for
    stages while the effective sample size is below 400 adds them up to ``max_stages``, each of the second's size;
    every draw's log posterior is returned, and the weighted mean and covariance of all four stages are nearer the
    target's than those of two."""
    m, S, target, start = misplaced_gaussian()

    def run(max_stages):
        g = torch.Generator().manual_seed(5)
        first = first_stage(target.log_prob, start, S, 30.0, 256, g)
        return importance_sample(target.log_prob, first, start, S, 30.0, g, adapt=lambda lw: True, n2=128,
                                 more=lambda lw: guard.effective_size(lw) < 400, max_stages=max_stages)

    x2, lp2, lw2, n2 = run(2)
    x4, lp4, lw4, n4 = run(4)
    assert (n2, n4) == (2, 4) and x2.shape == (384, 3) and x4.shape == (640, 3)
    torch.testing.assert_close(lp4, target.log_prob(x4))
    torch.testing.assert_close(x4[:384], x2)  # the first two stages are the same draws
    mu2, C2, ess2 = moments(x2, lw2)
    mu4, C4, ess4 = moments(x4, lw4)
    assert ess4 > ess2
    assert float((mu4 - m).abs().max()) < float((mu2 - m).abs().max())
    assert float((C4 - S).abs().max()) < 0.1
