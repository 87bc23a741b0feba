"""Which backend: the cheapest exact space for the data (``method="auto"``)."""

from __future__ import annotations

import types

import torch

from ...rft.contacts import Contacts
from ..kernels.fourier import MAX_HARMONICS, FourierBasis
from ..kernels.operators import row_separable, unique_pairs
from .base import RFTBackend, touching
from .observations import ObservationsBackend
from .pairs import PairsBackend, distinct_pairs
from .spectral import SpectralBackend

__all__ = ["METHODS", "choose_method", "make_backend", "estimated_costs", "estimate_pairs", "pairs_may_move",
           "spectral_step_cost"]

METHODS = ("observations", "pairs", "spectral")
ALIASES = {"exact": "observations"}
N_ITER = 300  # Adam steps the one-time costs are spread over
SPECTRAL_PENALTY = 1.5  # prefer the arithmetic-exact spaces when costs are close
# Per kernel-block element of the observations backend: the exp, its gradient, gathers and index
# arithmetic. Calibrated so that all three estimates are in the same units of time: one likelihood +
# gradient step of the paper's C-toe gait 2 (T = 100 / 200, 750 / 1500 distinct pairs, one thread)
# takes 22-24 / 142-147 ms in observations, 3.4-7.4 / 8-19 ms in spectral (F = 289-1037) and
# 19-28 / 200 ms in pairs: about 3 Gflop/s of the pairs and spectral estimates, and of this one
# only with 120 flops per element (the former 40 made observations look 3x cheaper than it is).
KERNEL_FLOPS = 120.0
# Each backend's floor per step, whatever the size (Python, autograd and gpytorch's bookkeeping), in
# the same units (about 3 Mflop per ms): measured on the paper's four configurations (T = 100, one
# thread) at 2.4 ms (observations), 1.0 ms (pairs) and 3.5 ms (spectral) per likelihood + gradient step.
SWITCH_FACTOR = 0.5  # a fit moves to another space when it is estimated this much cheaper (cheaper_space)
STEP_OVERHEAD = {"observations": 7e6, "pairs": 3e6, "spectral": 10e6}


def estimated_costs(contacts: Contacts, hypers, tol: float = 1e-7, n_pairs: int | None = None) -> dict[str, float]:
    """Rough flop counts of one likelihood + gradient step (the one-time work spread over N_ITER steps)
    in each space, plus each backend's fixed floor per step (``STEP_OVERHEAD``).

    T: samples in contact, U: distinct angle pairs, S: segments in contact, F: Fourier features for the
    current lengthscales. Observations: T^3 / 3 per step plus the kernel block (``KERNEL_FLOPS`` per
    element for the exp, its gradient and the gathers, over S x min(U, S) elements; for a translating
    toe, ``operators.row_separable``, T^2 (n_b + KERNEL_FLOPS / 10): one exp per pair of rows); pairs:
    O(min(T, U)^3 + U^2 (10 + min(T, U))); spectral: O(r^3 + r^2 F + r F (F_beta + F_gamma)),
    r = min(T, F), plus the one pass T F^2.
    """
    rows = touching(contacts)
    T = int(rows.sum())
    S = int(((contacts.weight_x != 0) | (contacts.weight_z != 0)).sum())
    U = estimate_pairs(contacts) if n_pairs is None else int(n_pairs)
    basis = FourierBasis.for_lengthscale(hypers.lengthscale, tol)
    F, (Fb, Fg) = basis.size, basis.sizes
    capped = max(basis.n_beta, basis.n_gamma) >= MAX_HARMONICS  # the tolerance is out of reach: not exact
    sep = row_separable(contacts.beta, contacts.gamma, contacts.weight_x.abs() + contacts.weight_z.abs())
    if sep is not None:  # a translating toe: the kernel's product form, no exp per segment
        obs = T**3 / 3 + T**2 * (sep["betas"].numel() + KERNEL_FLOPS / 10)
    else:
        obs = T**3 / 3 + KERNEL_FLOPS * S * min(U, S)
    pairs = _pairs_flops(T, U)
    spectral = _spectral_flops(T, F, Fb, Fg)
    spectral = float("inf") if capped else float(spectral * SPECTRAL_PENALTY)
    costs = {"observations": float(obs), "pairs": float(pairs), "spectral": spectral}
    return {m: v + STEP_OVERHEAD[m] for m, v in costs.items()}


def pairs_may_move(contacts: Contacts, tol: float = 1e-7, n_pairs: int | None = None) -> bool:
    """Whether ``cheaper_space`` could ever move a fit with ``method="auto"`` out of the pairs space, whatever its
    hyperparameters do. The observations and pairs costs do not depend on them; the spectral cost falls as the
    lengthscales grow, to its cost for the smallest basis (lengthscales without bound), which is what is checked:
    if even that is not 2x cheaper, the fit stays in pairs. Depends on the contacts only (a fit asks once, not every
    30 steps: the basis for a lengthscale costs about 1 ms here)."""
    widest = types.SimpleNamespace(lengthscale=torch.full((2, 1, 4), 1e6, dtype=torch.float64))
    return cheaper_space(estimated_costs(contacts, widest, tol, n_pairs), "pairs") is not None


def _pairs_flops(T: int, U: int) -> float:
    r = min(T, U)
    return r**3 / 3 + U**2 * (10 + r) + r**2 * U + (T * U**2 + U**3) / N_ITER


def _spectral_flops(T: int, F: int, Fb: int, Fg: int) -> float:
    r = min(T, F)
    return (r**3 / 3 + r**2 * F + r * F * (Fb + Fg)) + (T * F**2 + F**3) / N_ITER


def spectral_step_cost(contacts: Contacts, basis: FourierBasis) -> float:
    """The spectral backend's estimated step cost in ``basis`` (``estimated_costs``' units), finite even
    where the basis is capped below the tolerance (what a fit held in that basis pays per step)."""
    T = int(touching(contacts).sum())
    return float(_spectral_flops(T, basis.size, *basis.sizes) * SPECTRAL_PENALTY + STEP_OVERHEAD["spectral"])


def estimate_pairs(c: Contacts, sample: int = 50_000) -> int:
    """The number of distinct angle pairs, or (above ``sample`` segments in contact, when an evenly
    spaced sample of that many is mostly distinct) an estimate scaled from the sample: exact where
    it decides anything (few pairs), cheap where it cannot (a rotating toe on a long recording)."""
    active = (c.weight_x != 0) | (c.weight_z != 0)
    n = int(active.sum())
    if n > sample:
        pairs = torch.stack([c.beta[active], c.gamma[active]], -1)
        idx = torch.linspace(0, n - 1, sample, device=pairs.device).long()
        u = unique_pairs(pairs[idx])[0].shape[0]
        if u > sample // 2:
            return int(u * n / sample)
    return distinct_pairs(c)[0].shape[0]


def cheaper_space(costs: dict[str, float], current: str) -> str | None:
    """The space a fit with ``method="auto"`` moves to from ``current`` (the cheapest, when it costs
    less than half of ``current``: moving rebuilds the backend, so small gains are not worth it), or None."""
    best = min(costs, key=costs.get)
    return best if best != current and costs[best] < SWITCH_FACTOR * costs[current] else None


def choose_method(contacts: Contacts, hypers, tol: float = 1e-7) -> str:
    costs = estimated_costs(contacts, hypers, tol)
    return min(METHODS, key=lambda m: costs[m])


def make_backend(method: str, hypers, contacts: Contacts, forces, solver: str = "cholesky",
                 tol: float = 1e-7, statistics=None) -> RFTBackend:
    """Build the backend named ``method`` ("auto", "observations" (alias "exact"), "pairs", "spectral").
    ``statistics``: precomputed spectral statistics of exactly this data (``gp.statistics``), used by
    the spectral backend instead of a pass over the data and ignored by the others."""
    method = ALIASES.get(method, method)
    if method == "auto":
        method = choose_method(contacts, hypers, tol)
    if method == "observations":
        return ObservationsBackend(hypers, contacts, forces, solver=solver)
    if method == "pairs":
        return PairsBackend(hypers, contacts, forces)
    if method == "spectral":
        return SpectralBackend(hypers, contacts, forces, tol=tol, statistics=statistics)
    raise ValueError(f"method must be 'auto', 'observations' (or 'exact'), 'pairs' or 'spectral', got {method!r}")
