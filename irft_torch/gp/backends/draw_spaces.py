"""Where a batch of hyperparameter draws is evaluated (Laplace's proposals, NUTS' steps, a mixture's kept draws) for a
spectral fit: each draw in the Fourier basis its own lengthscales need within ``tol``, grouped so that few bases are
built, their statistics and data factors cut from one pass and one factor of the rows in the largest; draws no basis up
to ``MAX_HARMONICS`` holds, and those whose basis would cost more than it, in the exact space of the data's distinct
angle pairs (``pairs.PairsBackend``, evaluated through the segments). The functions take the spectral backend;
``SpectralBackend.draw_groups``, ``with_hypers``, ``exact_twin`` call them."""

from __future__ import annotations

import contextlib
import math
import warnings

import torch
from torch import Tensor

from ..kernels.fourier import MAX_HARMONICS, FourierBasis, truncation_errors
from ..kernels.li_basis import with_li_functions
from .base import RFTBackend
from .fourier_statistics import cut_factor, restrict_statistics, spectral_statistics
from .pairs import PairsBackend, distinct_pairs

__all__ = ["DRAW_HARMONICS", "DRAW_GROUPS", "EXACT_PAIRS", "EXACT_IF_CHEAPER", "draws_in_one_basis", "basis_cost",
           "group_draws", "cut_backend", "draw_backend", "exact_twin"]

DRAW_HARMONICS = 4  # a batch of hyperparameter draws is grouped by the basis each needs, rounded up to this step
DRAW_GROUPS = 4  # and those this backend's basis does not hold into at most this many groups
EXACT_PAIRS = 4096  # draws beyond every basis go to the exact pairs space up to this many distinct angle pairs
EXACT_IF_CHEAPER = 4.0  # and those whose basis costs this many times the fit's, where the pairs space is cheaper
_GROUPED = [True]  # False inside ``draws_in_one_basis``


@contextlib.contextmanager
def draws_in_one_basis():
    """Within this context a batch of hyperparameter draws is evaluated as before draws were grouped: one spectral
    basis grown to hold every draw (truncated beyond ``MAX_HARMONICS``), each kept draw's backend built from the fit's
    statistics in the basis it needs (``draw_groups`` and ``with_hypers`` stand aside). The reference of
    ``experiments/benchmarks/bench_inference.py``."""
    _GROUPED.append(False)
    try:
        yield
    finally:
        _GROUPED.pop()


def basis_cost(n_beta: Tensor, n_gamma: Tensor, T: int) -> Tensor:
    """About the multiply-adds of one draw's likelihood (both maps) in ``FourierBasis(n_beta, n_gamma)`` on T samples
    (r = min(T, F) rows of the data factor): 2 (r^2 F + r F (F_beta + F_gamma)), ``KroneckerFourier.forward``."""
    Fb, Fg = 2 * n_beta.double() + 1, 2 * n_gamma.double() + 1
    return _per_draw(Fb, Fg, (Fb * Fg).clamp_max(T))


def _per_draw(Fb, Fg, r):
    """2 (r^2 F + r F (F_beta + F_gamma)), F = F_beta F_gamma: numbers or tensors (``basis_cost``)."""
    F = Fb * Fg
    return 2 * (r * r * F + r * F * (Fb + Fg))


def _group_cost(nb: int, ng: int, draws: int, T: int, cap: float = math.inf) -> tuple[float, bool]:
    """What evaluating ``draws`` draws in one basis (nb, ng) costs (``basis_cost`` units), and whether the exact space
    (``cap`` per draw) is cheaper: with an exact space to choose, a basis of its own also costs its setting up (the
    statistics in it, 2 T F^2, and its data factor from the rows, counted as 8 T^2 F, or F^3 with more samples than
    features), which a few draws do not repay. (Its weights were tried lower with the factor's cheaper
    eigendecomposition, 2026-12-02: the turning scoop's default fit within 1 % of these.)"""
    Fb, Fg = 2 * nb + 1, 2 * ng + 1
    F = Fb * Fg
    own = draws * float(_per_draw(Fb, Fg, min(T, F)))
    if math.isinf(cap):
        return own, False
    own += 8.0 * T * T * F + 2.0 * T * F * F if T <= F else 10.0 * F ** 3
    return min(own, draws * cap), draws * cap < own


def _split_keys(keys: list[tuple[int, int]], counts: list[int], groups: int, T: int,
                cap: float = math.inf) -> list[int]:
    """Contiguous groups (their lengths) of (n_beta, n_gamma) keys sorted by size, at most ``groups`` of them,
    minimizing the sum over groups of what evaluating the group's draws in one basis that holds all of them (its
    largest n_beta by its largest n_gamma) costs, or in the exact space (``cap`` per draw) where less
    (``_group_cost``). ``counts``: draws per key."""
    n = len(keys)

    def cost(i: int, j: int) -> float:  # keys i..j-1 in one basis
        return _group_cost(max(k[0] for k in keys[i:j]), max(k[1] for k in keys[i:j]), sum(counts[i:j]), T, cap)[0]

    best: dict[tuple[int, int], tuple[float, list[int]]] = {(0, 0): (0.0, [])}  # (placed, groups) -> (cost, lengths)
    for g in range(1, groups + 1):
        for j in range(1, n + 1):
            options = [(best[i, g - 1][0] + cost(i, j), best[i, g - 1][1] + [j - i])
                       for i in range(j) if (i, g - 1) in best]
            if options:
                best[j, g] = min(options, key=lambda o: o[0])
    return min((best[n, g] for g in range(1, groups + 1) if (n, g) in best), key=lambda o: o[0])[1]


def group_draws(backend, lengthscale: Tensor) -> list[tuple[Tensor, RFTBackend]] | None:
    """A batch of hyperparameter settings (lengthscales (S, 2, 1, 4)) grouped by the basis each needs for
    ``tol``: [(mask (S,), a backend on these data in that basis)], this backend itself for those it holds, and
    for the others the basis their own lengthscales need (each angle's harmonics rounded up to a multiple of
    ``DRAW_HARMONICS``, at most ``MAX_HARMONICS``), cut from one pass over the data in the largest of them. So a
    batch costs what each setting needs, not what its shortest lengthscale needs, and this backend's basis
    stays the fit's. Settings that no basis up to ``MAX_HARMONICS`` holds within ``tol`` go to the exact space
    of the data's distinct angle pairs (``exact_twin``) where it is affordable, else stay in the largest basis
    with a warning (their kernel truncated). None where this backend does not keep all of its data (built from
    statistics, or statistics merged in) or its basis is held (``method="auto"`` on nearly noise-free data): the
    caller then grows this basis for the batch (``prepare``). Inside ``draws_in_one_basis()``: None."""
    data = backend._whole_data()
    if backend.held or not _GROUPED[-1] or data is None:
        return None
    c, f = data
    ls = lengthscale.detach().reshape(-1, 2, 4).double()
    eb, eg = truncation_errors(ls[..., 0:2]), truncation_errors(ls[..., 2:4])  # (S, 2, MAX_HARMONICS + 1)
    own = (eb[..., backend.basis.n_beta] + eg[..., backend.basis.n_gamma] <= backend.tol).all(-1)  # (S,)

    def need(e: Tensor) -> Tensor:  # the fewest harmonics with e_n <= tol / 2 in every map (the cap if none)
        ok = e <= backend.tol / 2
        n = torch.where(ok.any(-1), ok.int().argmax(-1), MAX_HARMONICS)
        step = DRAW_HARMONICS
        return ((n.amax(-1).clamp_min(1) + step - 1) // step * step).clamp_max(MAX_HARMONICS)

    nb, ng = need(eb), need(eg)
    capped = (eb[..., MAX_HARMONICS] + eg[..., MAX_HARMONICS] > backend.tol).any(-1)  # beyond any basis for tol
    dear = basis_cost(nb, ng, backend.n_samples) > EXACT_IF_CHEAPER * basis_cost(
        torch.tensor(backend.basis.n_beta), torch.tensor(backend.basis.n_gamma), backend.n_samples)
    built = backend.__dict__.get("_exact_twin")  # once built (a batch wanted it), it is there for every later batch
    ready = built is not None and built[0] is backend.stats and built[1] is not None
    exact = exact_twin(backend) if bool(((capped | dear) & ~own).any()) or (ready and not bool(own.all())) else None
    if exact is None:  # they stay in the largest basis, truncated there: said (a draw's kernel is not exact)
        own = own | ((nb <= backend.basis.n_beta) & (ng <= backend.basis.n_gamma))  # a larger basis would not help
        if bool(capped.any()):
            warnings.warn(f"the shortest lengthscale {float(ls[capped].min()):.3g} of a batch of {len(ls)} "
                          f"settings need more than {MAX_HARMONICS} harmonics per angle; the truncation error may "
                          f"exceed tol={backend.tol:.0e}", stacklevel=4)
    groups: list[tuple[Tensor, RFTBackend]] = [(own, backend)] if bool(own.any()) else []
    to_exact = torch.zeros_like(own)
    cap = math.inf
    if exact is not None:  # the exact space: no truncation, whatever the lengthscale; also where it is cheaper
        cap = exact.draw_cost()
        to_exact = capped & ~own
    rest = ~own & ~to_exact
    # at most DRAW_GROUPS groups of the others, by the bases they need (each group's basis holds all of its
    # draws), a group whose basis would cost more than the exact space going there: fewer backends to build, each
    # draw in a basis near its own
    need_keys = sorted({(int(a), int(b)) for a, b in zip(nb[rest].tolist(), ng[rest].tolist())},
                       key=lambda k: ((2 * k[0] + 1) * (2 * k[1] + 1), k))
    counts = [int((rest & (nb == a) & (ng == b)).sum()) for a, b in need_keys]
    start = 0
    for length in (_split_keys(need_keys, counts, DRAW_GROUPS, backend.n_samples, cap) if need_keys else []):
        part = need_keys[start:start + length]
        top = (max(k[0] for k in part), max(k[1] for k in part))
        to_twin = _group_cost(*top, sum(counts[start:start + length]), backend.n_samples, cap)[1]
        for a, b in part:
            at = rest & (nb == a) & (ng == b)
            if to_twin:
                to_exact = to_exact | at
            else:
                nb[at], ng[at] = top
        start += length
    if bool(to_exact.any()):
        groups.append((to_exact, exact))
    rest = rest & ~to_exact
    if not bool(rest.any()):
        return groups
    keys = sorted({(int(a), int(b)) for a, b in zip(nb[rest].tolist(), ng[rest].tolist())})
    bases = [with_li_functions(FourierBasis(a, b)) if backend.hypers.li is not None else FourierBasis(a, b)
             for a, b in keys]
    big = FourierBasis(max(b.n_beta for b in bases), max(b.n_gamma for b in bases))
    # kept while the data are: the statistics in the largest basis asked for so far and a backend per basis
    hit = backend.__dict__.get("_draw_cache")
    if hit is None or hit[0] is not backend.stats:
        hit = backend._draw_cache = [backend.stats, backend.stats, {}, None]
    if not backend._covers(hit[1], big):
        held = hit[1].meta
        grown = FourierBasis(max(big.n_beta, int(held["n_beta"])), max(big.n_gamma, int(held["n_gamma"])))
        stored = backend._stored
        hit[1] = (restrict_statistics(stored, grown) if stored is not None and backend._covers(stored, grown)
                  else spectral_statistics(c, f, grown, backend.hypers.mean))
        hit[3] = None
    for (a, b), basis in zip(keys, bases):
        if basis not in hit[2]:
            hit[2][basis] = cut_backend(backend, hit, backend.hypers, basis)
        groups.append((rest & (nb == a) & (ng == b), hit[2][basis]))
    return groups


def cut_backend(backend, hit: list, hypers, basis: FourierBasis) -> RFTBackend:
    """A backend on these data at ``hypers`` in ``basis``, its statistics and data factor cut from those of the
    batch's largest basis (``hit``: ``draw_groups``' cache): R's leading blocks of columns, c and rho as they are.
    Phi_sub = U R_sub with the larger basis' own U, so the likelihood and posterior in terms of R_sub, c, rho are
    exact; one factor of the rows for every group instead of one each. Where the larger factor has more rows than
    ``basis`` has features (a draw's step would then cost more than its own factor's), its own factor."""
    c, f = backend._whole_data()
    out = type(backend)(hypers, c, f, tol=backend.tol, basis=basis, statistics=hit[1])
    if not (0 < out.stats.n <= out.stats.n_features):
        return out
    if hit[3] is None:
        held = hit[1].meta
        parent = backend if hit[1] is backend.stats else type(backend)(
            backend.hypers, c, f, tol=backend.tol, basis=FourierBasis(int(held["n_beta"]), int(held["n_gamma"])),
            statistics=hit[1])
        hit[3] = (FourierBasis(int(held["n_beta"]), int(held["n_gamma"])), parent._factor())
    big, factor = hit[3]
    if factor.R.shape[-2] <= basis.size and factor.R.dtype == hypers.kernel.raw_outputscale.dtype:
        out._data_factor = cut_factor(factor, big, basis)
    return out


def draw_backend(backend, hypers) -> RFTBackend | None:
    """A draw's backend: for a draw whose lengthscales no basis up to ``MAX_HARMONICS`` holds within ``tol``, the
    exact pairs space (``exact_twin``, its statistics shared) where that is affordable; for another, a spectral
    backend in the basis it needs, cut from the statistics its batch was evaluated in (``draw_groups``) where
    they cover it; else None (the model builds one from its own statistics). Inside ``draws_in_one_basis()``:
    None."""
    if not _GROUPED[-1] or backend.held:
        return None
    ls = hypers.lengthscale.detach().reshape(-1, 2, 4).double()
    top = truncation_errors(ls[..., 0:2])[..., MAX_HARMONICS] + truncation_errors(ls[..., 2:4])[..., MAX_HARMONICS]
    twin = exact_twin(backend) if bool((top > backend.tol).any()) else None
    if twin is not None:
        return twin.with_hypers(hypers)
    hit, data = backend.__dict__.get("_draw_cache"), backend._whole_data()
    if hit is None or hit[0] is not backend.stats or data is None:
        return None
    basis = FourierBasis.for_lengthscale(hypers.lengthscale, backend.tol)
    basis = with_li_functions(basis) if hypers.li is not None else basis
    if not backend._covers(hit[1], basis):
        return None
    return cut_backend(backend, hit, hypers, basis)


def exact_twin(backend) -> PairsBackend | None:
    """The pairs backend on this backend's data and hyperparameters (exact at any lengthscale), built once, where
    the data have at most ``EXACT_PAIRS`` distinct angle pairs (the pairs space's step is O(U^2 T)); else None."""
    hit = backend.__dict__.get("_exact_twin")
    if hit is not None and hit[0] is backend.stats:
        return hit[1]
    twin, data = None, backend._whole_data()
    if data is not None and distinct_pairs(data[0])[0].shape[0] <= EXACT_PAIRS:
        twin = PairsBackend(backend.hypers, *data)
        twin.segments = True
    backend._exact_twin = (backend.stats, twin)
    return twin
