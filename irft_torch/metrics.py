"""Map and force metrics, sampling coverage and redundancy, calibration.

All functions take tensors of equal shape (an estimate and the ground truth over an evaluation
grid or a time series; shapes that differ beyond dimensions of size 1, such as (H, W, 2) against
(2, H, W), are a ValueError: flattened they would be compared out of order) and return Python floats
(``percentile_among``: a tensor of percentiles).
Percentages are in percent (0-100).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .rft.contacts import Contacts

__all__ = [
    "rmse", "mae", "r2", "pearson", "acr_percent", "rmse_percent", "mae_percent", "calibration",
    "percentile_among", "coverage_area", "redundancy", "map_metrics", "integrated_autocorrelation_time",
    "RMSEDifference", "rmse_difference",
]


def _same_layout(e: Tensor, t: Tensor) -> None:
    """ValueError where two tensors of one size hold their values in different layouts ((H, W, 2) and
    (2, H, W)): flattened, they would be compared element by element out of order. Shapes that differ
    only by dimensions of size 1 ((N,) and (N, 1)) are one layout."""
    se = tuple(d for d in e.shape if d != 1)
    st = tuple(d for d in t.shape if d != 1)
    if se == st:
        return
    hint = ""
    if sorted(se) == sorted(st) and len(set(st)) == len(st):
        hint = f" (truth.permute{tuple(st.index(d) for d in se)} has the estimate's)"
    raise ValueError(f"estimate has shape {tuple(e.shape)} but truth {tuple(t.shape)}: the same number of values in "
                     f"another layout, which would be compared out of order; give both in one layout{hint}")


def _pair(estimate: Tensor, truth: Tensor) -> tuple[Tensor, Tensor]:
    e0 = torch.as_tensor(estimate, dtype=torch.float64)
    t0 = torch.as_tensor(truth, dtype=torch.float64)
    e, t = e0.reshape(-1), t0.reshape(-1)
    if e.shape != t.shape:
        raise ValueError(f"estimate has {e.numel()} values, truth has {t.numel()}")
    _same_layout(e0, t0)
    if e.numel() == 0:
        raise ValueError("empty estimate")
    if not (torch.isfinite(e).all() and torch.isfinite(t).all()):
        raise ValueError("estimate or truth contains NaN or inf")
    return e, t


def _range(t: Tensor) -> float:
    r = float(t.max() - t.min())
    if r <= 0:
        raise ValueError("the ground truth is constant: a range-normalized metric is undefined")
    return r


def rmse(estimate, truth) -> float:
    """sqrt(mean((estimate - truth)^2))."""
    e, t = _pair(estimate, truth)
    return float((e - t).pow(2).mean().sqrt())


def mae(estimate, truth) -> float:
    """mean(|estimate - truth|)."""
    e, t = _pair(estimate, truth)
    return float((e - t).abs().mean())


def r2(estimate, truth) -> float:
    """Coefficient of determination 1 - SS_res / SS_tot (can be negative)."""
    e, t = _pair(estimate, truth)
    ss_tot = float((t - t.mean()).pow(2).sum())
    if ss_tot <= 0:
        raise ValueError("the ground truth is constant: R^2 is undefined")
    return 1.0 - float((e - t).pow(2).sum()) / ss_tot


def pearson(estimate, truth) -> float:
    """Pearson correlation coefficient (nan if either is constant)."""
    e, t = _pair(estimate, truth)
    ec, tc = e - e.mean(), t - t.mean()
    den = float(ec.norm() * tc.norm())
    return float((ec * tc).sum()) / den if den > 0 else math.nan


def acr_percent(estimate, truth, tolerance: float = 0.05) -> float:
    """Accurate-coverage ratio: % of points whose |error| <= tolerance x range(truth) (paper's ACR%).

    ``tolerance`` is a share in (0, 1) of the range (0.05, not 5); anything else is a ValueError.
    """
    if not 0.0 < float(tolerance) < 1.0:
        raise ValueError(f"tolerance must be a share of the range, in (0, 1) (0.05, not 5), got {tolerance}")
    e, t = _pair(estimate, truth)
    return 100.0 * float(((e - t).abs() <= tolerance * _range(t)).double().mean())


def rmse_percent(estimate, truth) -> float:
    """RMSE as % of range(truth)."""
    e, t = _pair(estimate, truth)
    return 100.0 * rmse(e, t) / _range(t)


def mae_percent(estimate, truth) -> float:
    """MAE as % of range(truth)."""
    e, t = _pair(estimate, truth)
    return 100.0 * mae(e, t) / _range(t)


def calibration(mean, stddev, truth, level: float = 0.95) -> float:
    """Share (0-1) of points whose truth lies in the central ``level`` posterior interval
    (mean +- z stddev, z the standard normal quantile of (1 + level) / 2).

    ``level`` is a share in (0, 1) (0.95, not 95) and ``stddev`` >= 0; anything else is a ValueError.
    """
    if not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must be a share in (0, 1), e.g. 0.95 (not a percent), got {level}")
    m, t = _pair(mean, truth)
    s, _ = _pair(stddev, truth)
    if (s < 0).any():
        raise ValueError("stddev must be >= 0 (a standard deviation, not a variance or a signed error)")
    z = math.sqrt(2) * float(torch.special.erfinv(torch.tensor(level, dtype=torch.float64)))
    return float(((m - t).abs() <= z * s).double().mean())


def percentile_among(observed, samples) -> Tensor:
    """Where ``observed`` (...) falls among ``samples`` (..., n) of what it should be distributed as: the
    share of samples below it, ties counted half (0-1). Uniform over repeated checks when observed is
    such a draw; near 0 or 1, it is not (e.g. a coverage against a calibrated model's coverages)."""
    obs = torch.as_tensor(observed, dtype=torch.float64)[..., None]
    smp = torch.as_tensor(samples, dtype=torch.float64)
    for name, v in (("observed", obs), ("samples", smp)):
        if torch.isnan(v).any():  # NaN compares false: it would count as a share of 0 (observed) or as above
            raise ValueError(f"{name} contains NaN")
    if smp.ndim == 0 or smp.shape[-1] == 0:
        raise ValueError(f"samples must be (..., n) with n >= 1, got shape {tuple(smp.shape)}")
    return (smp < obs).double().mean(-1) + 0.5 * (smp == obs).double().mean(-1)


class RMSEDifference(NamedTuple):
    """RMSE(candidate) - RMSE(reference) per column (D,), in the errors' unit, and its bootstrap interval."""

    difference: Tensor  # (D,) on every unit
    low: Tensor  # (D,) the interval's lower end
    high: Tensor  # (D,) its upper end

    def beyond_spread(self) -> Tensor:
        """(D,) bool: the candidate worse than the reference beyond the resampling spread (low > 0)."""
        return self.low > 0


def rmse_difference(candidate, reference, count=None, groups=None, level: float = 0.95, n_boot: int = 2000,
                    seed: int = 0) -> RMSEDifference:
    """How much worse (positive) or better (negative) a candidate's RMSE is than a reference's on the same
    held-out units, and how much of that the choice of units alone could make: a paired percentile bootstrap.

    Args:
        candidate: (R, D) sums of squared errors per unit under the candidate (a held-out run: one squared
            error per column, or the sum over its samples).
        reference: (R, D) the same under the reference, the same units in the same order.
        count: (R,) samples per unit (default 1 each). The RMSE pools samples: sqrt(sum SSE / sum count).
        groups: (R,) labels (integers or strings): resample whole groups (e.g. the held-out fold each run
            belongs to, whose errors share one fit and move together) instead of single units. Default: each unit
            its own.
        level: the interval's central share in (0, 1).
        n_boot: bootstrap resamples; ``seed`` their generator's seed (numpy ``default_rng``).

    With few groups (fewer than about 10) a percentile bootstrap is narrower than the spread it estimates
    (by about sqrt((G - 1) / G) and more in the tails): read an interval that barely excludes 0 as a hint.
    """
    c = np.asarray(torch.as_tensor(candidate, dtype=torch.float64).cpu(), dtype=float)
    r = np.asarray(torch.as_tensor(reference, dtype=torch.float64).cpu(), dtype=float)
    c, r = (v[:, None] if v.ndim == 1 else v for v in (c, r))  # one column: (R,) is (R, 1)
    if c.ndim != 2 or c.shape != r.shape or c.shape[0] == 0:
        raise ValueError(f"candidate and reference must be (R, D) with R >= 1 and one shape, got "
                         f"{tuple(c.shape)} and {tuple(r.shape)}")
    for name, v in (("candidate", c), ("reference", r)):
        if not np.isfinite(v).all() or (v < 0).any():
            raise ValueError(f"{name} must hold finite sums of squared errors (>= 0), not errors or NaN")
    n = np.ones(len(c)) if count is None else np.asarray(count, dtype=float).reshape(-1)
    if n.shape != (len(c),) or not np.isfinite(n).all() or (n <= 0).any():
        raise ValueError(f"count must be (R,) = ({len(c)},) positive sample counts, got {np.shape(count)}")
    if not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must be a share in (0, 1), e.g. 0.95 (not a percent), got {level}")
    if isinstance(n_boot, bool) or int(n_boot) != n_boot or n_boot < 1:
        raise ValueError(f"n_boot must be a positive integer, got {n_boot}")
    if groups is not None:  # one unit per group: its sums and counts (resampled together)
        g = np.asarray(groups).reshape(-1)
        if g.shape != (len(c),):
            raise ValueError(f"groups must be (R,) = ({len(c)},) labels, got {np.shape(groups)}")
        _, inv = np.unique(g, return_inverse=True)
        G = int(inv.max()) + 1
        c, r, n = (np.stack([v[inv == k].sum(0) for k in range(G)]) for v in (c, r, n))
    rmse_of = lambda s, k: np.sqrt(s / k[..., None])  # noqa: E731
    diff = rmse_of(c.sum(0), n.sum()) - rmse_of(r.sum(0), n.sum())
    idx = np.random.default_rng(seed).integers(0, len(c), (int(n_boot), len(c)))
    tot = n[idx].sum(1)
    d = rmse_of(c[idx].sum(1), tot) - rmse_of(r[idx].sum(1), tot)  # (n_boot, D)
    q = np.quantile(d, [(1 - level) / 2, (1 + level) / 2], axis=0)
    t = lambda v: torch.as_tensor(np.asarray(v, dtype=float))  # noqa: E731
    return RMSEDifference(t(diff), t(q[0]), t(q[1]))


def _cells(contacts: Contacts, n_cells: int) -> Tensor:
    """Flat indices of the (beta, gamma) cells of every segment in contact."""
    if isinstance(n_cells, bool) or int(n_cells) != n_cells or n_cells < 1:
        raise ValueError(f"n_cells must be a positive integer (cells per side of the grid), got {n_cells}")
    n_cells = int(n_cells)
    on = (contacts.weight_z != 0) | (contacts.weight_x != 0)
    b, g = contacts.beta[on].double(), contacts.gamma[on].double()
    ib = ((b + math.pi / 2) / math.pi * n_cells).floor().clamp(0, n_cells - 1).long()
    ig = ((g + math.pi / 2) / math.pi * n_cells).floor().clamp(0, n_cells - 1).long()
    return ib * n_cells + ig


def coverage_area(contacts: Contacts, n_cells: int = 50) -> float:
    """Share (0-1) of an n_cells x n_cells grid over the canonical square holding at least one
    segment in contact (the sampled area of the paper's coverage figure)."""
    cells = _cells(contacts, n_cells)
    return cells.unique().numel() / n_cells**2


def redundancy(contacts: Contacts, n_cells: int = 50) -> float:
    """1 - N_unique / N_total over segments in contact, N_unique counting distinct cells of an
    n_cells x n_cells grid (so that angles equal to round-off count as one)."""
    cells = _cells(contacts, n_cells)
    if cells.numel() == 0:
        raise ValueError("no segment is in contact")
    return 1.0 - cells.unique().numel() / cells.numel()


def map_metrics(estimate, truth) -> dict[str, float]:
    """The paper's Table I row: rmse, mae, r2, pearson, acr_percent (and rmse/mae percent)."""
    return {
        "rmse": rmse(estimate, truth), "mae": mae(estimate, truth), "r2": r2(estimate, truth),
        "pearson": pearson(estimate, truth), "acr_percent": acr_percent(estimate, truth),
        "rmse_percent": rmse_percent(estimate, truth), "mae_percent": mae_percent(estimate, truth),
    }


def integrated_autocorrelation_time(x, window: float = 5.0) -> float:
    """tau = 1 + 2 sum_{k>=1} rho(k), in samples, of a series (n,) (e.g. force residuals).

    The variance of a mean of n correlated samples is tau times that of n independent ones, so
    n / tau is the effective sample size and thinning by tau gives nearly independent samples.
    The sum stops at the first lag k >= ``window`` x tau(k) (Sokal's automatic window).
    For an AR(1) series with coefficient phi, tau = (1 + phi) / (1 - phi).
    """
    v = torch.as_tensor(x, dtype=torch.float64)
    if v.ndim != 1:  # flattening (T, 2) residuals would interleave the two axes into one series
        raise ValueError(f"x must be one series (n,), got shape {tuple(v.shape)} (pass one column at a time)")
    if not (math.isfinite(window) and window > 0):
        raise ValueError(f"window must be a positive number (Sokal's c, e.g. 5), got {window}")
    if v.numel() < 4:
        raise ValueError(f"need at least 4 samples, got {v.numel()}")
    if not torch.isfinite(v).all():
        raise ValueError("x contains NaN or inf")
    v = v - v.mean()
    n = v.numel()
    size = 1 << (2 * n - 1).bit_length()
    spec = torch.fft.rfft(v, size)
    acf = torch.fft.irfft(spec * spec.conj(), size)[:n]
    if acf[0] <= 0:
        return 1.0
    rho = (acf / acf[0]).tolist()
    tau = 1.0
    for k in range(1, n):
        tau += 2.0 * rho[k]
        if k >= window * tau:
            break
    return max(tau, 1.0)
