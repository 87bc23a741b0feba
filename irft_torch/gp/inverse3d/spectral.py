"""The 3-D spectral backend: each map in a truncated Fourier basis on the (beta, gamma) torus (``gp.kernels.fourier``),
one basis per map sized for the kernel's relative truncation error <= ``tol`` at that map's lengthscales, in the
weight-space algebra of ``backends.WeightSpace3D``; the training rows' features come from a
``features.SpectralFeatureBank`` (cut from larger nested bases as the lengthscales shorten)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ..kernels.fourier import MAX_HARMONICS, FourierBasis
from ..kernels.li_basis import li_index, with_li_functions
from .backends import WeightSpace3D
from .features import BankRows, SpectralFeatureBank, union_basis
from .rows import BLOCKS

__all__ = ["Spectral3D"]


class Spectral3D(WeightSpace3D):
    """3-D I-RFT in a Fourier basis on the (beta, gamma) torus (``gp.kernels.fourier``), one per map, each sized for
    its kernel's relative truncation error <= ``tol`` at its own lengthscales (a map with long lengthscales keeps
    few features while another's shorten); each grows (``refresh``) when its lengthscales shrink."""

    name = "spectral"

    def __init__(self, hypers, contacts, forces, tol: float = 1e-7, features=None,
                 max_harmonics: int = MAX_HARMONICS) -> None:
        super().__init__(hypers, contacts, forces)
        if not 0 < tol < 1:
            raise ValueError(f"tol must be in (0, 1), got {tol}")
        if not 1 <= int(max_harmonics) <= MAX_HARMONICS:
            raise ValueError(f"max_harmonics must be an integer in [1, {MAX_HARMONICS}], got {max_harmonics}")
        self.max_harmonics = int(max_harmonics)
        if features is not None and not isinstance(features, BankRows):
            raise TypeError(f"features must be SpectralFeatureBank(...).rows(index), got {type(features).__name__}")
        self.tol = float(tol)
        # none passed: a bank of its own, so that a growing basis (and a hyperparameter draw's) is cut from one
        # larger pass over the data instead of a pass per size
        self._bank = features if features is not None else self._own_bank()
        self._queried: list[SpectralFeatureBank | None] = [None]  # the last contacts predicted at, their features
        self.bases = self._bases_for(hypers.lengthscale)
        self._set_features()

    def _data_changed(self, contacts, forces) -> None:
        self._merge_rows(contacts, forces)
        self._bank = self._own_bank()  # the old bank does not hold the new samples

    def _own_bank(self) -> BankRows:
        """A bank over all the training samples (lazy: nothing is computed until a basis is asked for)."""
        cap = getattr(self, "max_harmonics", MAX_HARMONICS)  # _data_changed runs before __init__ sets it
        return SpectralFeatureBank(self.train_contacts, ahead=cap).rows(None)

    def _maps_rbf(self) -> list[int]:
        return [c for c in range(3) if not self.hypers.constant_map(c)]

    @property
    def basis(self) -> FourierBasis:
        """The smallest basis holding every map's (what a single basis for all maps would be)."""
        return union_basis(self.bases)

    def _bases_for(self, lengthscale: Tensor, shrink: float = 1.0) -> tuple[FourierBasis | None, ...]:
        """Per map (3): the smallest basis for ``tol`` at its lengthscales (times ``shrink``), None for a constant."""
        out: list[FourierBasis | None] = [None] * 3
        for m in self._maps_rbf():
            ls = lengthscale.detach()[m:m + 1] * shrink
            basis = FourierBasis.for_lengthscale(ls, self.tol, self.max_harmonics)
            out[m] = basis if self.hypers.li is None else with_li_functions(basis)
        return tuple(out)

    def _block_bases(self, b: int) -> list[FourierBasis | None]:
        return [self.bases[m] for m in BLOCKS[b].maps]

    def describe(self) -> str:
        sizes = " / ".join("1" if x is None else str(x.size) for x in self.bases)
        return (f"spectral: T={self.n_samples}, {sizes} Fourier features (alpha_x / alpha_y / alpha_z), kernel "
                f"truncation error <= {self.truncation_error().max().item():.1e}")

    def truncation_error(self) -> Tensor:
        out = self.hypers.kernel.outputscale.detach().new_zeros(3)
        ls = self.hypers.lengthscale.detach()
        for m in self._maps_rbf():
            out[m] = self.bases[m].truncation_error(ls[m:m + 1])[0]
        return out

    def stale(self) -> bool:
        return bool((self.truncation_error() > self.tol).any())

    def refresh(self) -> bool:
        if not self.stale():
            return False
        need = self._bases_for(self.hypers.lengthscale, 0.85)
        stale = self.truncation_error() > self.tol
        grown = list(self.bases)
        for m in self._maps_rbf():
            if stale[m]:  # only the maps whose lengthscales left their basis behind
                old, new = self.bases[m], need[m]
                grown[m] = FourierBasis(min(max(new.n_beta, old.n_beta), self.max_harmonics),
                                        min(max(new.n_gamma, old.n_gamma), self.max_harmonics))
        if tuple(grown) == self.bases:
            return False
        old_bases, self.bases = self.bases, tuple(grown)
        try:
            self._set_features()
        except BaseException:  # (Ctrl-C included) the bases the factors are still of
            self.bases = old_bases
            raise
        return True

    def _features(self, c: Contacts3D, b: int) -> Tensor:
        bases = self._block_bases(b)
        if self._bank is not None and c is self.train_contacts:
            return self._bank.features(bases, b, self.hypers.constant_map(1))
        held = self._queried[0]  # shared with this backend's draws (``with_hypers``): asked of each in turn
        if held is None or held.contacts is not c:
            held = self._queried[0] = SpectralFeatureBank(c, ahead=self.max_harmonics)
        return held._full(bases, b, self.hypers.constant_map(1))

    def _sigma(self, b: int, X: Tensor, detach: bool) -> Tensor:
        block = BLOCKS[b]
        out, start = [], 0
        for m in block.maps:
            s = self.hypers.outputscale[m]
            s = s.detach() if detach else s
            if self.hypers.constant_map(m):
                out.append(X[:, start:start + 1] * s)
                start += 1
                continue
            basis = self.bases[m]
            ls = self.hypers.lengthscale[m:m + 1]
            Sb, Sg = basis.coefficients(ls.detach() if detach else ls)
            Fb, Fg = basis.sizes
            Y = X[:, start:start + Fb * Fg].reshape(-1, Fb, Fg)
            out.append(s * (Sb[0].mT @ Y @ Sg[0]).reshape(-1, Fb * Fg))
            v = self.hypers.li_of(m, detach)
            if v is not None:  # Li et al.'s term: v / 4 on its 9 weights
                idx = li_index(basis, X.device)
                out[-1] = out[-1].index_add(-1, idx, X[:, start + idx] * (v / 4))
            start += Fb * Fg
        return torch.cat(out, -1)
