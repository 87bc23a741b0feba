"""The bookkeeping of ``TerrainFilter``'s sample windows: environment indices, room for more samples (slots), and
forgetting the oldest sample of a window by a rank-one update of the inverse Cholesky factor (the filter's module
docstring derives it)."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["env_index", "pad_slots", "forget_oldest"]


def env_index(env_ids, B: int, device) -> Tensor:
    """Environment indices (k,) from a bool mask (B,), integer indices, a list or None (all)."""
    if env_ids is None:
        return torch.arange(B, device=device)
    ids = torch.as_tensor(env_ids, device=device)
    if ids.dtype == torch.bool:
        if ids.shape != (B,):
            raise ValueError(f"env_ids as a mask must have shape ({B},), got {tuple(ids.shape)}")
        return ids.nonzero()[:, 0]
    if ids.dtype.is_floating_point or ids.dtype.is_complex:
        raise ValueError(f"env_ids must be integer indices or a bool mask, got {ids.dtype}")
    ids = ids.reshape(-1).long()
    if ids.numel() and (int(ids.min()) < -B or int(ids.max()) >= B):
        raise ValueError(f"env_ids must be in [-{B}, {B}), got values from {int(ids.min())} to {int(ids.max())}")
    return ids % B


def pad_slots(t: Tensor, N: int, M: int, N2: int, M2: int) -> Tensor:
    """(..., N * M) slot-major columns -> (..., N2 * M2), zeros in the new slots and segments."""
    lead = t.shape[:-1]
    t = t.reshape(*lead, N, M)
    return torch.nn.functional.pad(t, (0, M2 - M, 0, N2 - N)).reshape(*lead, N2 * M2)


def forget_oldest(U: Tensor, z: Tensor, At: Tensor, full: Tensor) -> None:
    """Remove the oldest sample of the environments ``full`` (b,) of a block, in place (U: U^T (b, 2, n, n),
    z, A^T): the module docstring's rank-one update of the remaining factor, as a prefix sum."""
    p = -U[..., 0, 1:] / U[..., 0, :1]  # (b, 2, n - 1): L22^{-1} c
    p2 = p.pow(2)
    t = 1 + p2.cumsum(-1)
    t_prev = t - p2
    d = (t / t_prev).sqrt()
    coef = p / (t_prev * d)

    def solve(X: Tensor) -> Tensor:
        """Lt^{-1} X along the last (sample) axis: X d - coef cumsum(p X) (1 / d + coef p = d)."""
        extra = X.ndim - p.ndim
        pp, dd, cc = (v.view(*v.shape[:-1], *[1] * extra, v.shape[-1]) for v in (p, d, coef))
        return (X * dd).addcmul_(cc, (X * pp).cumsum_(-1), value=-1)

    f3, f4 = full.view(-1, 1, 1), full.view(-1, 1, 1, 1)
    U_new = torch.nn.functional.pad(solve(U[..., 1:, 1:]), (0, 1, 0, 1))
    U_new[..., -1, -1] = 1.0  # the freed last position: an identity row and column
    U.copy_(torch.where(f4, U_new, U))
    z.copy_(torch.where(f3, torch.nn.functional.pad(solve(torch.addcmul(z[..., 1:], p, z[..., :1])), (0, 1)), z))
    if At.shape[-2]:
        A_new = solve(torch.addcmul(At[..., 1:], At[..., :1], p[..., None, :]))
        At.copy_(torch.where(f4, torch.nn.functional.pad(A_new, (0, 1)), At))
