"""Spectral features of 3-D contacts (the rows of a block in a Fourier basis on the angle torus), and a bank
of them for fits on subsets of one data set's samples (cross-validation folds)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ..kernels.fourier import FourierBasis
from ..kernels.operators import unique_pairs
from .hyperparameters import BLOCKS
from .rows import block_rows

__all__ = ["spectral_features", "SpectralFeatureBank", "BankRows"]


def spectral_features(c: Contacts3D, b: int, basis: FourierBasis, constant_y: bool) -> Tensor:
    """Phi (n, F_b) of the block's rows: per map of the block, sum_k w psi_beta(beta_k) x psi_gamma(gamma_k) (a
    constant alpha_y: sum_k w), side by side."""
    block = BLOCKS[b]
    _, _, ws = block_rows(c, block)
    T, A = len(c), len(block.axes)
    ws = [w.reshape(A, T, -1) for w in ws]
    beta, gamma, merged = _distinct_pairs(c.beta, c.gamma, ws)
    out = []
    for i, m in enumerate(block.maps):
        if m == 1 and constant_y:
            out.append(ws[i].sum(-1).reshape(A * T, 1))
            continue
        out.append(_fourier_rows(beta, gamma, merged[i], basis).reshape(A * T, -1))
    return torch.cat(out, -1)


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
    keys, inv = torch.unique(t_of * n_pairs + pair, return_inverse=True)  # sorted: a sample's pairs side by side
    row = keys // n_pairs
    slot = torch.arange(len(keys), device=keys.device) - torch.searchsorted(keys, row * n_pairs)
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

    def _full(self, basis: FourierBasis, b: int, constant_y: bool) -> Tensor:
        key = (b, constant_y)
        for (nb, ng), store in self._held.items():
            if nb >= basis.n_beta and ng >= basis.n_gamma and key in store:
                return _restrict(store[key], FourierBasis(nb, ng), basis, b, constant_y)
        big = basis if self.ahead is None else FourierBasis(_rounded_up(basis.n_beta, self.ahead),
                                                            _rounded_up(basis.n_gamma, self.ahead))
        with torch.no_grad():
            phi = spectral_features(self.contacts, b, big, constant_y)
        self._held.setdefault((big.n_beta, big.n_gamma), {})[key] = phi
        return _restrict(phi, big, basis, b, constant_y)

    def rows(self, index) -> BankRows:
        """The samples ``index`` (indices or a bool mask; None: all, no copy)."""
        return BankRows(self, None if index is None else torch.as_tensor(index))


class BankRows:
    """The samples ``index`` of a ``SpectralFeatureBank`` (the training rows of one model)."""

    def __init__(self, bank: SpectralFeatureBank, index: Tensor | None) -> None:
        self.bank, self.index = bank, index

    def features(self, basis: FourierBasis, b: int, constant_y: bool) -> Tensor:
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


def _restrict(phi: Tensor, big: FourierBasis, small: FourierBasis, b: int, constant_y: bool) -> Tensor:
    """Features in a nested smaller basis: the leading harmonics' columns of each map's block."""
    if big == small:
        return phi
    Fb, Fg = big.sizes
    fb, fg = small.sizes
    sel = (torch.arange(fb, device=phi.device)[:, None] * Fg + torch.arange(fg, device=phi.device)[None, :]).reshape(-1)
    out, start = [], 0
    for m in BLOCKS[b].maps:
        if m == 1 and constant_y:
            out.append(phi[:, start:start + 1])
            start += 1
        else:
            out.append(phi[:, start + sel])
            start += Fb * Fg
    return torch.cat(out, -1)


def _fourier_rows(beta: Tensor, gamma: Tensor, w: Tensor, basis: FourierBasis, chunk: int = 2**22) -> Tensor:
    """Features of weighted sums: beta, gamma (T, K), weights (A, T, K) -> (A, T, F) = sum_k w psi_beta x psi_gamma,
    one batched product per chunk of samples."""
    A, T, K = w.shape
    Fb, Fg = basis.sizes
    out = w.new_zeros(A, T, Fb * Fg)
    step = max(1, chunk // max(1, K * (Fb + Fg + A * Fb)))
    for t0 in range(0, T, step):
        sl = slice(t0, min(T, t0 + step))
        pb, pg = basis.features(beta[sl], gamma[sl])  # (t, K, Fb), (t, K, Fg)
        left = (w[:, sl, :, None] * pb[None]).permute(1, 0, 3, 2).reshape(sl.stop - sl.start, A * Fb, K)
        prod = (left @ pg).reshape(-1, A, Fb * Fg)  # (t, A, F)
        out[:, sl] = prod.transpose(0, 1)
    return out
