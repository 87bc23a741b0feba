r"""Joint posteriors of several row sets of one block, on any 3-D backend (what design/ scores candidates with).

A backend's ``posterior`` answers for one ``Contacts3D``. Scoring a candidate probe needs the covariance between
the maps at a region's points and the candidate's forces, two row sets with different element counts (a point
evaluation has one element, a wheel tens of thousands), so they cannot share one padded ``Contacts3D`` cheaply.
Every backend writes the posterior covariance of two row sets q_i, q_j of a block as

    Cov(q_i, q_j | F) = P(q_i, q_j) - G_i^T G_j,       E[q_i | F] = m_i

with P the prior covariance and G_i (r x n_i) the data's part: observations G = L^{-1} K(train, q) (L the
training rows' Cholesky); weight space G = H Sigma Phi_q^T with P = Phi_i Sigma Phi_j^T (``backends`` module
doc); pairs at angles off its table G = H Cov(u, q) with P from the kernel. ``BlockRows`` holds those parts (each
backend gives its own, ``Backend3D._part_rows``).
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D

__all__ = ["BlockRows"]


class BlockRows:
    """The rows of block ``b`` (0 horizontal: F_x rows then F_y rows; 1 vertical: F_z rows) of several
    ``Contacts3D`` parts under a backend's posterior: ``mean(i)`` (n_i,) and ``cov(i, j)`` (n_i, n_j), N and N^2
    (a point evaluation's rows read the maps, ``model.point_contacts``). Hyperparameters fixed, no gradient."""

    def __init__(self, backend, b: int, parts: list[Contacts3D]) -> None:
        self.backend, self.b = backend, b
        self.rows: list[tuple] = []
        self._means: list[Tensor] = []
        self._G: list[Tensor] = []
        self._feat: list[tuple[Tensor, Tensor] | None] = []  # (Phi Sigma, Phi) where the prior is in features
        for p in parts:
            self._append(p)

    def extended(self, parts: list[Contacts3D]) -> BlockRows:
        """These rows and more (the new parts' indices follow): what is computed is shared, not recomputed."""
        new = copy.copy(self)
        new.rows, new._means, new._G, new._feat = list(self.rows), list(self._means), list(self._G), list(self._feat)
        for p in parts:
            new._append(p)
        return new

    def _append(self, part: Contacts3D) -> None:
        with torch.no_grad():
            q, mean, G, feat = self.backend._part_rows(self.b, part)
        self.rows.append(q)
        self._means.append(mean)
        self._G.append(G)
        self._feat.append(feat)

    def mean(self, i: int) -> Tensor:
        return self._means[i]

    def prior(self, i: int, j: int) -> Tensor:
        fi, fj = self._feat[i], self._feat[j]
        with torch.no_grad():
            if fi is not None and fj is not None:
                return fi[0] @ fj[1].mT
            return self.backend._cross(self.b, self.rows[i], self.rows[j], same=i == j)

    def cov(self, i: int, j: int) -> Tensor:
        out = self.prior(i, j) - self._G[i].mT @ self._G[j]
        return 0.5 * (out + out.mT) if i == j else out

    def variance(self, i: int) -> Tensor:
        """The diagonal of ``cov(i, i)`` without forming it where the prior is in features."""
        f = self._feat[i]
        if f is None:
            return torch.diagonal(self.cov(i, i))
        return (f[0] * f[1]).sum(-1) - self._G[i].pow(2).sum(0)

