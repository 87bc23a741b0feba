"""The RFT-weighted covariance W K W^T as a lazy linear_operator LinearOperator."""

from __future__ import annotations

import math

import torch
import torch.utils.checkpoint
from linear_operator.operators import LinearOperator
from torch import Tensor

from .embedding import embed_angles, rbf

__all__ = ["RFTKernelLinearOperator", "RowSeparableRFTOperator", "memory_budget", "unique_pairs", "row_separable"]


class memory_budget:
    """Bytes one dense block of kernel evaluations may take (default 256 MiB). Blocks are
    recomputed in the backward pass (activation checkpointing), so peak memory stays near this
    budget whatever the problem size.

    Use as a context manager (``with memory_budget(2**28): ...``) or read ``memory_budget.value()``.
    """

    _value = 2**28

    def __init__(self, nbytes: int) -> None:
        self.nbytes = int(nbytes)

    @classmethod
    def value(cls) -> int:
        return cls._value

    def __enter__(self):
        self._old, memory_budget._value = memory_budget._value, self.nbytes
        return self

    def __exit__(self, *exc) -> None:
        memory_budget._value = self._old


def _gather_rows(table: Tensor, index: Tensor) -> Tensor:
    """table (*B, U, k), index (*B, T, M) -> (*B, T, M, k): table rows picked per batch."""
    B = index.shape[:-2]
    U, k = table.shape[-2:]
    nb = math.prod(B)
    table = table.expand(*B, U, k).reshape(nb * U, k)
    offset = (torch.arange(nb, device=index.device) * U).view(nb, 1)
    flat = (index.reshape(nb, -1) + offset).reshape(-1)
    return table[flat].reshape(*index.shape, k)


def _scatter_rows(values: Tensor, index: Tensor, U: int) -> Tensor:
    """values (*B, T, M, k) summed into rows index (*B, T, M) of a (*B, U, k) zero table."""
    B = index.shape[:-2]
    k = values.shape[-1]
    nb = math.prod(B)
    offset = (torch.arange(nb, device=index.device) * U).view(nb, 1)
    flat = (index.reshape(nb, -1) + offset).reshape(-1)
    out = values.new_zeros(nb * U, k).index_add(0, flat, values.reshape(-1, k))
    return out.reshape(*B, U, k)


def unique_pairs(pairs: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.unique(pairs, dim=0, return_inverse=True)`` for (n, 2) float pairs, by three 1-D uniques
    of the columns' bit patterns (row-wise unique sorts rows generically and is ~10x slower). Rows
    equal bit for bit share an entry; the order of the distinct rows may differ from torch's."""
    if pairs.shape[0] == 0:
        return pairs, torch.zeros(0, dtype=torch.long, device=pairs.device)
    ints = {8: torch.int64, 4: torch.int32, 2: torch.int16}[pairs.element_size()]
    bits = pairs.contiguous().view(ints)
    _, ia = torch.unique(bits[:, 0], return_inverse=True)
    ub, ib = torch.unique(bits[:, 1], return_inverse=True)
    key, inverse = torch.unique(ia * ub.numel() + ib, return_inverse=True)
    first = torch.full((key.numel(),), pairs.shape[0], dtype=torch.long, device=pairs.device)
    first = first.scatter_reduce(0, inverse, torch.arange(pairs.shape[0], device=pairs.device), "amin")
    return pairs[first], inverse


def _compress(beta: Tensor, gamma: Tensor, weight: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Move each row's non-zero-weight segments first and drop columns that are zero everywhere."""
    active = weight != 0
    keep = max(int(active.sum(-1).max()) if active.numel() else 0, 1)
    if keep == weight.shape[-1] and bool(active.all()):
        return beta, gamma, weight
    order = torch.argsort((~active).to(torch.int8), dim=-1, stable=True)[..., :keep]
    pick = lambda v: torch.take_along_dim(v, order, dim=-1)  # noqa: E731
    return pick(beta), pick(gamma), pick(weight)


# When a side's table has at most this many rows per segment slot, the weights are scattered into a
# dense (T x U) matrix and the operator is evaluated as L K R^T with matrix products: repeated
# angle pairs (an I-toe, a plate at fixed tilt and direction) then cost O(T U^2 + T^2 U).
DENSE_WEIGHTS_MAX_RATIO = 64


def _dense_weights(index: Tensor, weight: Tensor, U: int) -> Tensor:
    """(*B, T, M) indices and weights -> dense (*B, T, U) with the weights summed per table row."""
    return torch.zeros(*index.shape[:-1], U, dtype=weight.dtype, device=weight.device).scatter_add(-1, index, weight)


def _use_dense_weights(U1: int, M1: int, U2: int, M2: int) -> bool:
    return U1 <= DENSE_WEIGHTS_MAX_RATIO * M1 and U2 <= DENSE_WEIGHTS_MAX_RATIO * M2


def _dense_rows(x1, x2, s, li, lw, ri, rw) -> Tensor:
    """Rows of L K R^T for the observations in li, lw (*B, c, M1): (*B, c, T2)."""
    B = li.shape[:-2]
    c, M1 = li.shape[-2:]
    U2 = x2.shape[-2]
    seg = _gather_rows(x1, li).reshape(*B, c * M1, -1)
    k = rbf(seg, x2, s).reshape(*B, c, M1, U2)
    g = (lw[..., None, :] @ k).squeeze(-2)  # (*B, c, U2): W_rows K, as one batched matmul
    cols = _gather_rows(g.mT, ri)  # (*B, T2, M2, c)
    return (rw[..., None] * cols).sum(-2).mT


def row_separable(b: Tensor, g: Tensor, w: Tensor) -> dict | None:
    """The row-separable structure of one side's segments (*B, T, M), or None.

    When every observation's segments in contact share one gamma (the body translates: every point has
    the same direction of motion) the kernel's product form k = s k_beta k_gamma gives
    sum_{m, m'} w_tm w_t'm' k(theta_tm, theta_t'm') = s k_gamma(gamma_t, gamma_t') (L_b K_beta L_b^T)_tt',
    with L_b (T, n_b) the weights summed per distinct beta: O(T^2 n_b) instead of O(S U) kernel
    evaluations. Returns the distinct betas (n_b,), L_b (*B, T, n_b) and the rows' gamma (*B, T)
    (0 where a row touches nothing; its weights are 0).
    """
    a = w != 0
    if not bool(a.any()):
        return None
    first = a.to(torch.int8).argmax(-1, keepdim=True)
    g_row = torch.take_along_dim(g, first, -1)
    if not bool(((g == g_row) | ~a).all()):
        return None
    g_row = torch.where(a.any(-1, keepdim=True), g_row, torch.zeros_like(g_row))[..., 0]
    betas, inverse = torch.unique(b[a], return_inverse=True)
    index = torch.zeros(w.shape, dtype=torch.long, device=w.device).masked_scatter(a, inverse)
    Lb = _dense_weights(index, w, betas.numel())  # zero weights add nothing wherever they point
    return {"betas": betas, "Lb": Lb, "gamma": g_row}


def _beta_gamma_embedding(betas: Tensor, gamma: Tensor, lengthscale: Tensor) -> tuple[Tensor, Tensor]:
    """The embedding's beta half (sin 2beta, cos 2beta) / l_beta (*B, n_b, 2) and gamma half
    (sin gamma, cos gamma) / l_gamma (*B, T, 2), from ``embed_angles``."""
    ls = lengthscale  # (*B, 1, 4)
    zb = embed_angles(betas, torch.zeros_like(betas))[..., :2] / ls[..., :2]
    zg = embed_angles(torch.zeros_like(gamma), gamma)[..., 2:] / ls[..., 2:]
    return zb, zg


def _paired_rbf(a: Tensor, b: Tensor, s: Tensor) -> Tensor:
    """s exp(-|a_i - b_i|^2 / 2) row by row, through ``rbf``: a, b (..., n, D), s broadcastable to
    (..., n) -> (..., n)."""
    return rbf(a[..., None, :], b[..., None, :], s.expand(a.shape[:-1])[..., None, None])[..., 0, 0]


class RowSeparableRFTOperator(LinearOperator):
    r"""Lazy :math:`s\,K_\gamma(\gamma_1, \gamma_2) \circ (L_1 K_\beta L_2^\top)`: the same W K W^T as
    :class:`RFTKernelLinearOperator` when each observation's segments share one gamma (a translating
    toe; see :func:`row_separable`), in O(T1 T2 n_b) with no per-segment kernel evaluation.

    Args:
        zb1: (*B, n1, 2) the first side's distinct betas' (sin 2beta, cos 2beta) / lengthscales.
        zb2: (*B, n2, 2) the same for the second side.
        zg1: (*B, T1, 2) each first-side row's (sin gamma, cos gamma) / lengthscales.
        zg2: (*B, T2, 2) the same for the second side.
        outputscale: (*B, 1, 1).
        L1: (*B, T1, n1) the first side's weights summed per distinct beta.
        L2: (*B, T2, n2) the same for the second side.
    """

    def __init__(self, zb1: Tensor, zb2: Tensor, zg1: Tensor, zg2: Tensor, outputscale: Tensor, L1: Tensor,
                 L2: Tensor) -> None:
        super().__init__(zb1, zb2, zg1, zg2, outputscale, L1, L2)
        self.zb1, self.zb2, self.zg1, self.zg2 = zb1, zb2, zg1, zg2
        self.outputscale, self.L1, self.L2 = outputscale, L1, L2

    def _size(self) -> torch.Size:
        return torch.Size((*self.L1.shape[:-1], self.L2.shape[-2]))

    def _transpose_nonbatch(self) -> RowSeparableRFTOperator:
        return self.__class__(self.zb2, self.zb1, self.zg2, self.zg1, self.outputscale, self.L2, self.L1)

    def _beta_block(self) -> Tensor:
        return rbf(self.zb1, self.zb2, torch.ones((), dtype=self.zb1.dtype, device=self.zb1.device))

    def _rows(self, i: int, j: int, Kb: Tensor) -> Tensor:
        return rbf(self.zg1[..., i:j, :], self.zg2, self.outputscale) * (self.L1[..., i:j, :] @ Kb @ self.L2.mT)

    def to_dense(self) -> Tensor:
        return self._rows(0, self.L1.shape[-2], self._beta_block())

    def _matmul(self, rhs: Tensor) -> Tensor:
        Kb = self._beta_block()
        T1, T2 = self.L1.shape[-2], self.L2.shape[-2]
        per_row = 2 * self.L1.element_size() * max(1, math.prod(self.batch_shape)) * T2
        chunk = max(1, memory_budget.value() // per_row)
        return torch.cat([self._rows(i, i + chunk, Kb) @ rhs for i in range(0, T1, chunk)], dim=-2)

    def _diagonal(self) -> Tensor:
        kg = _paired_rbf(self.zg1, self.zg2, self.outputscale[..., 0])
        return kg * ((self.L1 @ self._beta_block()) * self.L2).sum(-1)

    def _get_indices(self, row_index, col_index, *batch_indices) -> Tensor:
        Kb = self._beta_block()
        zg1, zg2 = self.zg1[(*batch_indices, row_index)], self.zg2[(*batch_indices, col_index)]
        s = self.outputscale[(*batch_indices,)][..., 0, 0] if batch_indices else self.outputscale[..., 0, 0]
        kg = _paired_rbf(zg1, zg2, s)
        left = (self.L1 @ Kb)[(*batch_indices, row_index)]
        right = self.L2[(*batch_indices, col_index)]
        return kg * (left * right).sum(-1)

    def _getitem(self, row_index, col_index, *batch_indices) -> LinearOperator:
        if any(torch.is_tensor(b) for b in batch_indices):
            return super()._getitem(row_index, col_index, *batch_indices)
        b = tuple(batch_indices)
        return self.__class__(self.zb1[b], self.zb2[b], self.zg1[(*b, row_index)], self.zg2[(*b, col_index)],
                              self.outputscale[b], self.L1[(*b, row_index)], self.L2[(*b, col_index)])

    def _expand_batch(self, batch_shape) -> RowSeparableRFTOperator:
        return self.__class__(*(a.expand(*batch_shape, *a.shape[-2:]) for a in self._args))


class RFTKernelLinearOperator(LinearOperator):
    r"""Lazy :math:`L\,K(X_1, X_2)\,R^\top` with :math:`K = s\,\exp(-\tfrac12\|x_1 - x_2\|^2)`.

    Row t of L holds weights ``left_weight[t, :]`` at table rows ``left_index[t, :]`` (and likewise
    R): for composite RFT observations the tables are the distinct segment angle pairs,
    embedded and divided by the lengthscales, and L, R are the segment weights (depth x area),
    so the operator is W K W^T (or the cross-covariance W_* K W^T). W is never formed.

    Args:
        x1: (*B, U1, D) left table, already divided by the lengthscales.
        x2: (*B, U2, D) right table.
        outputscale: (*B, 1, 1) signal variance s.
        left_index: (*B, T1, M1) long, rows of ``x1``.
        left_weight: (*B, T1, M1) weights (0 for padding).
        right_index: (*B, T2, M2).
        right_weight: (*B, T2, M2).

    Shape: (*B, T1, T2). Gradients reach ``x1``, ``x2``, ``outputscale`` and the weights.
    """

    def __init__(self, x1: Tensor, x2: Tensor, outputscale: Tensor, left_index: Tensor, left_weight: Tensor,
                 right_index: Tensor, right_weight: Tensor) -> None:
        super().__init__(x1, x2, outputscale, left_index, left_weight, right_index, right_weight)
        self.x1, self.x2, self.outputscale = x1, x2, outputscale
        self.left_index, self.left_weight = left_index, left_weight
        self.right_index, self.right_weight = right_index, right_weight

    # ---- construction from segments ------------------------------------------------------
    @staticmethod
    def segment_structure(b1: Tensor, g1: Tensor, w1: Tensor, b2: Tensor, g2: Tensor, w2: Tensor,
                          batch_shape: torch.Size, same_inputs: bool = False) -> dict:
        """Compressed segments and their distinct angle pairs; independent of hyperparameters.

        Inputs are per-row segment angles and weights (*batch, T, M). Zero-weight segments are
        dropped; when no input needs a gradient, equal angle pairs share one table row.
        """

        def expand(*v):
            return [t.expand(*batch_shape, *t.shape[-2:]) for t in v]

        b1, g1, w1 = _compress(*expand(b1, g1, w1))
        if same_inputs:
            b2, g2, w2 = b1, g1, w1
        else:
            b2, g2, w2 = _compress(*expand(b2, g2, w2))
        grad = any(t.requires_grad for t in (b1, g1, b2, g2))

        def table(b, g, w):
            """Distinct angle pairs of the non-zero-weight segments and each segment's row in them."""
            a = w != 0
            pairs = torch.stack([b[a], g[a]], -1)
            if pairs.shape[0] == 0:
                return b.new_zeros(1, 2), torch.zeros(w.shape, dtype=torch.long, device=w.device)
            if grad:
                inverse = torch.arange(pairs.shape[0], device=b.device)  # keep every entry's gradient
            else:
                pairs, inverse = unique_pairs(pairs)
            return pairs, torch.zeros(w.shape, dtype=torch.long, device=w.device).masked_scatter(a, inverse)

        # Each side gets its own table: a cross-covariance (test rows x training rows) then only
        # evaluates the kernel between the pairs each side actually uses.
        pairs1, i1 = table(b1, g1, w1)
        pairs2, i2 = (pairs1, i1) if same_inputs else table(b2, g2, w2)
        out = {"pairs1": pairs1, "pairs2": pairs2, "i1": i1, "w1": w1, "i2": i2, "w2": w2, "same": same_inputs}
        if not grad:  # a translating toe on both sides: the kernel's product form (no gradient through unique)
            sep1 = row_separable(b1, g1, w1)
            sep2 = sep1 if same_inputs or sep1 is None else row_separable(b2, g2, w2)
            if sep1 is not None and sep2 is not None:
                out["separable"] = (sep1, sep2)
        return out

    @classmethod
    def from_structure(cls, structure: dict, lengthscale: Tensor, outputscale: Tensor,
                       batch_shape: torch.Size) -> LinearOperator:
        """W1 K W2^T with the base kernel's ``lengthscale`` (*batch, 1, 4), ``outputscale`` (*batch,): an
        :class:`RFTKernelLinearOperator`, or a :class:`RowSeparableRFTOperator` (the same matrix) when
        both sides' toes translate."""
        if "separable" in structure:
            (s1, s2), s = structure["separable"], outputscale.expand(batch_shape)[..., None, None]
            zb1, zg1 = _beta_gamma_embedding(s1["betas"], s1["gamma"], lengthscale)
            zb2, zg2 = (zb1, zg1) if s2 is s1 else _beta_gamma_embedding(s2["betas"], s2["gamma"], lengthscale)
            ex = lambda t: t.expand(*batch_shape, *t.shape[-2:])  # noqa: E731
            return RowSeparableRFTOperator(ex(zb1), ex(zb2), ex(zg1), ex(zg2), s, s1["Lb"], s2["Lb"])
        def scaled(pairs):
            t = embed_angles(pairs[:, 0], pairs[:, 1]) / lengthscale  # (*batch, U, 4)
            return t.expand(*batch_shape, *t.shape[-2:])

        x1 = scaled(structure["pairs1"])
        x2 = x1 if structure["same"] else scaled(structure["pairs2"])
        s = outputscale.expand(batch_shape)[..., None, None]
        return cls(x1, x2, s, structure["i1"], structure["w1"], structure["i2"], structure["w2"])

    @classmethod
    def from_segments(cls, b1, g1, w1, b2, g2, w2, lengthscale, outputscale, batch_shape,
                      same_inputs: bool = False) -> RFTKernelLinearOperator:
        """Build W1 K W2^T from per-row segment angles and weights (each (*batch, T, M))."""
        structure = cls.segment_structure(b1, g1, w1, b2, g2, w2, batch_shape, same_inputs)
        return cls.from_structure(structure, lengthscale, outputscale, batch_shape)

    # ---- the LinearOperator contract -----------------------------------------------------
    def _size(self) -> torch.Size:
        return torch.Size((*self.left_index.shape[:-1], self.right_index.shape[-2]))

    def _transpose_nonbatch(self) -> RFTKernelLinearOperator:
        return self.__class__(self.x2, self.x1, self.outputscale, self.right_index, self.right_weight,
                              self.left_index, self.left_weight)

    def _row_chunk(self, per_row: int) -> int:
        """Rows per block so that a block of ``per_row`` elements per row fits the budget."""
        itemsize = self.x1.element_size()
        nb = max(1, math.prod(self.batch_shape))
        return max(1, memory_budget.value() // max(1, itemsize * nb * per_row))

    def _matmul(self, rhs: Tensor) -> Tensor:
        B = torch.broadcast_shapes(self.batch_shape, rhs.shape[:-2])
        if B != self.batch_shape:
            return self._expand_batch(B)._matmul(rhs)
        rhs = rhs.expand(*B, *rhs.shape[-2:]) if rhs.shape[:-2] != B else rhs
        U1, U2 = self.x1.shape[-2], self.x2.shape[-2]
        # R^T rhs: scatter each observation's weighted rhs row onto its segments' table rows
        v = _scatter_rows(self.right_weight[..., None] * rhs[..., :, None, :], self.right_index, U2)
        chunk = self._row_chunk(U2)
        kv = torch.cat([rbf(self.x1[..., i:i + chunk, :], self.x2, self.outputscale) @ v
                        for i in range(0, U1, chunk)], dim=-2)
        return (self.left_weight[..., None] * _gather_rows(kv, self.left_index)).sum(-2)

    def to_dense(self) -> Tensor:
        T1, M1 = self.left_index.shape[-2:]
        U1, U2 = self.x1.shape[-2], self.x2.shape[-2]
        T2, M2 = self.right_index.shape[-2:]
        if _use_dense_weights(U1, M1, U2, M2):
            K = rbf(self.x1, self.x2, self.outputscale)
            L = _dense_weights(self.left_index, self.left_weight, U1)
            R = _dense_weights(self.right_index, self.right_weight, U2)
            return L @ K @ R.mT
        chunk = self._row_chunk(M1 * U2 + T2 * M2)
        if chunk >= T1:
            return _dense_rows(self.x1, self.x2, self.outputscale, self.left_index, self.left_weight,
                               self.right_index, self.right_weight)
        needs_grad = torch.is_grad_enabled() and any(
            a.requires_grad for a in (self.x1, self.x2, self.outputscale, self.left_weight, self.right_weight))
        blocks = []
        for i in range(0, T1, chunk):
            args = (self.x1, self.x2, self.outputscale, self.left_index[..., i:i + chunk, :],
                    self.left_weight[..., i:i + chunk, :], self.right_index, self.right_weight)
            if needs_grad:
                blocks.append(torch.utils.checkpoint.checkpoint(_dense_rows, *args, use_reentrant=False))
            else:
                blocks.append(_dense_rows(*args))
        return torch.cat(blocks, dim=-2)

    def _segment_block(self, x1, x2, s, lw, rw) -> Tensor:
        """sum_{m, m'} lw_m k(x1_m, x2_m') rw_m' for rows of gathered segments (..., n, M, D)."""
        return (lw[..., :, None] * rbf(x1, x2, s) * rw[..., None, :]).sum((-1, -2))

    def _diagonal(self) -> Tensor:
        x1 = _gather_rows(self.x1, self.left_index)
        x2 = _gather_rows(self.x2, self.right_index)
        return self._segment_block(x1, x2, self.outputscale[..., None, :, :], self.left_weight, self.right_weight)

    def _get_indices(self, row_index, col_index, *batch_indices) -> Tensor:
        bl = tuple(b.unsqueeze(-1) for b in batch_indices)
        li = self.left_index[(*batch_indices, row_index)]
        ri = self.right_index[(*batch_indices, col_index)]
        lw = self.left_weight[(*batch_indices, row_index)]
        rw = self.right_weight[(*batch_indices, col_index)]
        x1 = self.x1[(*bl, li)]
        x2 = self.x2[(*bl, ri)]
        s = self.outputscale[(*batch_indices,)] if batch_indices else self.outputscale
        return self._segment_block(x1, x2, s, lw, rw)

    def _getitem(self, row_index, col_index, *batch_indices) -> LinearOperator:
        if any(torch.is_tensor(b) for b in batch_indices):
            return super()._getitem(row_index, col_index, *batch_indices)
        b = tuple(batch_indices)
        return self.__class__(
            self.x1[b], self.x2[b], self.outputscale[b],
            self.left_index[(*b, row_index)], self.left_weight[(*b, row_index)],
            self.right_index[(*b, col_index)], self.right_weight[(*b, col_index)],
        )

    def to(self, *args, **kwargs) -> RFTKernelLinearOperator:
        """Move to a device / floating dtype; the index tensors stay long."""
        from linear_operator.utils.generic import _to_helper

        device, dtype = _to_helper(*args, **kwargs)
        return self.__class__(*(a.to(device=device, dtype=dtype if a.dtype.is_floating_point else None)
                                for a in self._args))

    def _expand_batch(self, batch_shape) -> RFTKernelLinearOperator:
        return self.__class__(*(a.expand(*batch_shape, *a.shape[-2:]) for a in self._args))
