"""Spectral features of 3-D contacts (the rows of a block in a Fourier basis on the angle torus), and a bank
of them for fits on subsets of one data set's samples (cross-validation folds)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ..kernels.fourier import FourierBasis
from ..kernels.operators import unique_pairs
from .rows import BLOCKS, block_rows

__all__ = ["spectral_features", "merged_rows", "MergedRows", "SpectralFeatureBank", "BankRows", "union_basis"]


def spectral_features(c: Contacts3D, b: int, basis: FourierBasis, constant_y: bool,
                      merged: MergedRows | None = None) -> Tensor:
    """Phi (n, F_b) of the block's rows: per map of the block, sum_k w psi_beta(beta_k) x psi_gamma(gamma_k) (a
    constant alpha_y: sum_k w), side by side. ``merged``: ``merged_rows(c)`` where already at hand."""
    block = BLOCKS[b]
    T, A = len(c), len(block.axes)
    m_rows = merged_rows(c) if merged is None else merged
    out = []
    for i, m in enumerate(block.maps):
        w = m_rows.weights[b][i]  # (A, T, K')
        if m == 1 and constant_y:
            out.append(w.sum(-1).reshape(A * T, 1))
            continue
        out.append(_fourier_rows(m_rows.beta, m_rows.gamma, w, basis, groups=m_rows.groups).reshape(A * T, -1))
    return torch.cat(out, -1)


@dataclass(frozen=True)
class MergedRows:
    """Every block's rows with each sample's equal angle pairs merged (``_distinct_pairs``), hyperparameter- and
    basis-free: beta, gamma (T, K'); ``weights[b][i]`` (A, T, K') of block b's i-th map; ``groups``: each
    sample's distinct betas (``_beta_groups``) or None."""

    beta: Tensor
    gamma: Tensor
    weights: list[list[Tensor]]
    groups: tuple[Tensor, Tensor] | None


def merged_rows(c: Contacts3D) -> MergedRows:
    """``MergedRows`` of contacts (T, K): one pass over the elements for all blocks."""
    T = len(c)
    per_block = [[w.reshape(len(block.axes), T, -1) for w in block_rows(c, block)[2]] for block in BLOCKS]
    flat = [w for ws in per_block for w in ws]
    beta, gamma, merged = _distinct_pairs(c.beta, c.gamma, flat)
    weights, start = [], 0
    for ws in per_block:
        weights.append(merged[start:start + len(ws)])
        start += len(ws)
    return MergedRows(beta, gamma, weights, _beta_groups(beta))


def _per_sample_slots(sample: Tensor, value: Tensor, n_values: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each sample's distinct values side by side: for entries (sample (n,), value id (n,) < ``n_values``), the
    distinct (sample, value) keys (sorted), each entry's key, and each key's sample (row) and place among its
    sample's (slot)."""
    keys, inv = torch.unique(sample * n_values + value, return_inverse=True)
    row = keys // n_values
    slot = torch.arange(len(keys), device=keys.device) - torch.searchsorted(keys, row * n_values)
    return keys, inv, row, slot


def _distinct_pairs(beta: Tensor, gamma: Tensor, ws: list[Tensor]) -> tuple[Tensor, Tensor, list[Tensor]]:
    """Each sample's segments merged where their angle pairs are equal (their weights summed) and those with no
    weight dropped: beta, gamma (T, K'), the weights (A, T, K'), K' the most distinct pairs of a sample, padded
    with zero weight. The same weighted sums (to rounding); a wheel's rim repeats each pair across its width and
    half of it is out of the sand, so K' is 3-6x below K on the rover wheels."""
    T = beta.shape[0]
    active = torch.stack([(w != 0).any(0) for w in ws]).any(0)  # (T, K)
    t_of, k_of = active.nonzero(as_tuple=True)
    pair = unique_pairs(torch.stack([beta[t_of, k_of], gamma[t_of, k_of]], -1))[1]  # (n,) id of each angle pair
    n_pairs = int(pair.max()) + 1 if len(pair) else 1
    keys, inv, row, slot = _per_sample_slots(t_of, pair, n_pairs)
    k = max(1, int(slot.max()) + 1 if len(slot) else 1)
    if k >= beta.shape[1]:
        return beta, gamma, ws
    b2, g2 = beta.new_zeros(T, k), gamma.new_zeros(T, k)
    where = row * k + slot  # (U,) flat position of each distinct pair
    b2.view(-1)[where[inv]] = beta[t_of, k_of]
    g2.view(-1)[where[inv]] = gamma[t_of, k_of]
    out = []
    for w in ws:
        o = w.new_zeros(w.shape[0], T * k)
        o.index_add_(1, where[inv], w[:, t_of, k_of])
        out.append(o.reshape(w.shape[0], T, k))
    return b2, g2, out


class SpectralFeatureBank:
    """Spectral features of a data set's samples, computed once per basis (and cut from a larger nested basis
    where one is held), for fits on subsets of its samples (cross-validation folds):
    ``InverseRFT3D(contacts[idx], forces[idx], engine="spectral", features=bank.rows(idx))``.

    Args:
        contacts: the data set's contacts (T, K).
        ahead: None computes each basis asked for; an int ``cap`` computes a larger one when it must compute
            (each angle's harmonics rounded up to 8, 16, 32, at most ``cap``) and cuts the smaller ones asked
            for later from it: a fit whose basis grows step by step pays a few passes over the data, not one per
            size (a backend's own bank: 3 passes at most where there were a dozen or more).
    """

    def __init__(self, contacts: Contacts3D, ahead: int | None = None) -> None:
        self.contacts = contacts
        self.ahead = ahead
        self._held: dict = {}
        self._merged: MergedRows | None = None  # ``merged_rows`` of the contacts, once asked for

    def _full(self, basis: FourierBasis | Sequence[FourierBasis | None], b: int, constant_y: bool) -> Tensor:
        """Block b's features in ``basis``: one for every map, or one per map of the block (None: a constant)."""
        key = (b, constant_y)
        union = union_basis(basis)
        for (nb, ng), store in self._held.items():
            if nb >= union.n_beta and ng >= union.n_gamma and key in store:
                return _restrict(store[key], FourierBasis(nb, ng), basis, b, constant_y)
        big = union if self.ahead is None else FourierBasis(_rounded_up(union.n_beta, self.ahead),
                                                            _rounded_up(union.n_gamma, self.ahead))
        with torch.no_grad():
            if self._merged is None:
                self._merged = merged_rows(self.contacts)
            phi = spectral_features(self.contacts, b, big, constant_y, self._merged)
        self._held.setdefault((big.n_beta, big.n_gamma), {})[key] = phi
        return _restrict(phi, big, basis, b, constant_y)

    def rows(self, index) -> BankRows:
        """The samples ``index`` (indices or a bool mask; None: all, no copy)."""
        return BankRows(self, None if index is None else torch.as_tensor(index))


class BankRows:
    """The samples ``index`` of a ``SpectralFeatureBank`` (the training rows of one model)."""

    def __init__(self, bank: SpectralFeatureBank, index: Tensor | None) -> None:
        self.bank, self.index = bank, index

    def features(self, basis: FourierBasis | Sequence[FourierBasis | None], b: int, constant_y: bool) -> Tensor:
        """Block b's features of these samples in ``basis`` (one, or one per map of the block)."""
        phi = self.bank._full(basis, b, constant_y)
        if self.index is None:
            return phi
        T = len(self.bank.contacts)
        A = len(BLOCKS[b].axes)
        idx = self.index if self.index.dtype != torch.bool else self.index.nonzero()[:, 0]
        return phi[torch.cat([idx + a * T for a in range(A)])]


def _rounded_up(n: int, cap: int) -> int:
    """n harmonics rounded up to 8, 16, 32, ... and capped at ``cap`` (never below n)."""
    return max(n, min(cap, max(8, 1 << max(0, n - 1).bit_length())))


def union_basis(basis: FourierBasis | Sequence[FourierBasis | None]) -> FourierBasis:
    """The smallest basis holding every one given (None entries: constant maps, no basis)."""
    if isinstance(basis, FourierBasis):
        return basis
    held = [x for x in basis if x is not None]
    return FourierBasis(max((x.n_beta for x in held), default=0), max((x.n_gamma for x in held), default=0))


def _restrict(phi: Tensor, big: FourierBasis, small: FourierBasis | Sequence[FourierBasis | None], b: int,
              constant_y: bool) -> Tensor:
    """Features in nested smaller bases (one, or one per map of the block): the leading harmonics' columns of each
    map's block."""
    maps = BLOCKS[b].maps
    smalls = [small] * len(maps) if isinstance(small, FourierBasis) else list(small)
    Fb, Fg = big.sizes
    out, start = [], 0
    for m, sm in zip(maps, smalls):
        if m == 1 and constant_y:
            out.append(phi[:, start:start + 1])
            start += 1
            continue
        if sm is None or sm == big:
            out.append(phi[:, start:start + Fb * Fg])
        else:
            fb, fg = sm.sizes
            sel = (torch.arange(fb, device=phi.device)[:, None] * Fg
                   + torch.arange(fg, device=phi.device)[None, :]).reshape(-1)
            out.append(phi[:, start + sel])
        start += Fb * Fg
    return out[0] if len(out) == 1 else torch.cat(out, -1)


def _fourier_rows(beta: Tensor, gamma: Tensor, w: Tensor, basis: FourierBasis, chunk: int = 2**22,
                  groups: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Features of weighted sums: beta, gamma (T, K), weights (A, T, K) -> (A, T, F) = sum_k w psi_beta x psi_gamma,
    per chunk of samples. Where a sample's elements share few beta values (``groups``, from ``_beta_groups``; a
    wheel's rim: some 300 among 3,000 pairs), the sum is taken in two stages, sum_beta psi_beta(beta) x
    (sum_{k: beta_k = beta} w_k psi_gamma(gamma_k)): the same sum reordered, with K / U fewer products."""
    A, T, K = w.shape
    Fb, Fg = basis.sizes
    out = w.new_zeros(A, T, Fb * Fg)
    if groups is None:  # per sample: the features of K elements and their weighted products
        step = max(1, chunk // max(1, K * (Fb + Fg + A * Fb)))
    else:  # per sample: K elements' gamma features and weighted products, U betas' features and sums
        U = groups[1].shape[1]
        step = max(1, chunk // max(1, K * Fg * (A + 1) + U * (Fb + A * Fg)))
    for t0 in range(0, T, step):
        sl = slice(t0, min(T, t0 + step))
        t = sl.stop - sl.start
        if groups is None:  # one batched product
            pb, pg = basis.features(beta[sl], gamma[sl])  # (t, K, Fb), (t, K, Fg)
            left = (w[:, sl, :, None] * pb[None]).permute(1, 0, 3, 2).reshape(t, A * Fb, K)
            out[:, sl] = (left @ pg).reshape(t, A, Fb * Fg).transpose(0, 1)
            continue
        slot, b_pad = groups  # (T K,) slot of each element in the (T, U) layout, (T, U) the distinct betas
        U = b_pad.shape[1]
        pb, pg = basis.features(b_pad[sl], gamma[sl])  # (t, U, Fb), (t, K, Fg)
        wpg = (w[:, sl].permute(1, 2, 0)[..., None] * pg[:, :, None, :]).reshape(t * K, A * Fg)  # (t K, A Fg)
        G = wpg.new_zeros(t * U, A * Fg).index_add_(0, slot[t0 * K:sl.stop * K] - t0 * U, wpg)
        prod = pb.mT @ G.reshape(t, U, A * Fg)  # (t, Fb, A Fg)
        out[:, sl] = prod.reshape(t, Fb, A, Fg).permute(2, 0, 1, 3).reshape(A, t, Fb * Fg)
    return out


def _beta_groups(beta: Tensor) -> tuple[Tensor, Tensor] | None:
    """Each sample's distinct beta values: (the slot of each element in a (T, U) layout, flat (T K,); the
    values (T, U), padded with a value of the sample's own), or None where U is more than half of K."""
    T, K = beta.shape
    if T == 0 or K == 0:
        return None
    values, inv = torch.unique(beta, return_inverse=True)
    sample = torch.arange(T, device=beta.device)[:, None].expand(T, K)
    keys, ginv, row, slot = _per_sample_slots(sample.reshape(-1), inv.reshape(-1), len(values))
    U = int(slot.max()) + 1
    if 2 * U > K:
        return None
    b_pad = beta[:, :1].expand(T, U).clone()  # padding: never weighted
    b_pad[row, slot] = values[keys % len(values)]
    return row[ginv] * U + slot[ginv], b_pad
