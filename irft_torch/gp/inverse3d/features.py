"""Spectral features of 3-D contacts (the rows of a block in a Fourier basis on the angle torus), and a bank
of them for fits on subsets of one data set's samples (cross-validation folds)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ..fourier import FourierBasis
from .hyperparameters import BLOCKS
from .rows import block_rows

__all__ = ["spectral_features", "SpectralFeatureBank", "BankRows"]


def spectral_features(c: Contacts3D, b: int, basis: FourierBasis, constant_y: bool) -> Tensor:
    """Phi (n, F_b) of the block's rows: per map of the block, sum_k w psi_beta(beta_k) x psi_gamma(gamma_k) (a
    constant alpha_y: sum_k w), side by side."""
    block = BLOCKS[b]
    _, _, ws = block_rows(c, block)
    T, A = len(c), len(block.axes)
    out = []
    for i, m in enumerate(block.maps):
        if m == 1 and constant_y:
            out.append(ws[i].sum(-1, keepdim=True))
            continue
        out.append(_fourier_rows(c.beta, c.gamma, ws[i].reshape(A, T, -1), basis).reshape(A * T, -1))
    return torch.cat(out, -1)


class SpectralFeatureBank:
    """Spectral features of a data set's samples, computed once per basis (and cut from a larger nested basis
    where one is held), for fits on subsets of its samples (cross-validation folds):
    ``InverseRFT3D(contacts[idx], forces[idx], method="spectral", features=bank.rows(idx))``."""

    def __init__(self, contacts: Contacts3D) -> None:
        self.contacts = contacts
        self._held: dict = {}

    def _full(self, basis: FourierBasis, b: int, constant_y: bool) -> Tensor:
        key = (b, constant_y)
        for (nb, ng), store in self._held.items():
            if nb >= basis.n_beta and ng >= basis.n_gamma and key in store:
                return _restrict(store[key], FourierBasis(nb, ng), basis, b, constant_y)
        with torch.no_grad():
            phi = spectral_features(self.contacts, b, basis, constant_y)
        self._held.setdefault((basis.n_beta, basis.n_gamma), {})[key] = phi
        return phi

    def rows(self, index) -> BankRows:
        return BankRows(self, torch.as_tensor(index))


class BankRows:
    """The samples ``index`` of a ``SpectralFeatureBank`` (the training rows of one model)."""

    def __init__(self, bank: SpectralFeatureBank, index: Tensor) -> None:
        self.bank, self.index = bank, index

    def features(self, basis: FourierBasis, b: int, constant_y: bool) -> Tensor:
        phi = self.bank._full(basis, b, constant_y)
        T = len(self.bank.contacts)
        A = len(BLOCKS[b].axes)
        idx = self.index if self.index.dtype != torch.bool else self.index.nonzero()[:, 0]
        return phi[torch.cat([idx + a * T for a in range(A)])]


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
