"""How composite observations are laid out as GPyTorch inputs.

One force observation on one axis is one input row of width 3M:
``[beta_1..beta_M, gamma_1..gamma_M, w_1..w_M]`` (rad, rad, cm^3). A point evaluation of the map
alpha(beta, gamma) is the row with one segment of weight 1 and the rest padding (weight 0).
The batch of two GPs stacks the x axis (weights ``weight_x``) and the z axis (``weight_z``):
inputs (2, T, 3M), targets (2, T).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts import Contacts

__all__ = ["encode_rows", "decode_rows", "encode_contacts", "encode_points", "AXES"]

AXES = ("x", "z")


def encode_rows(beta: Tensor, gamma: Tensor, weight: Tensor) -> Tensor:
    """(..., T, M) x 3 -> (..., T, 3M)."""
    return torch.cat([beta, gamma, weight], dim=-1)


def decode_rows(rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(..., T, 3M) -> beta, gamma, weight, each (..., T, M)."""
    if rows.shape[-1] % 3:
        raise ValueError(f"composite rows must have width 3M, got {rows.shape[-1]}")
    beta, gamma, weight = rows.tensor_split(3, dim=-1)
    return beta, gamma, weight


def encode_contacts(contacts: Contacts, M: int | None = None) -> Tensor:
    """Contacts (T, M') -> rows (2, T, 3M) for the (x, z) batch, padded to M segments."""
    c = contacts.pad_segments(M) if M is not None else contacts
    return torch.stack([encode_rows(c.beta, c.gamma, c.weight_x), encode_rows(c.beta, c.gamma, c.weight_z)])


def encode_points(beta: Tensor, gamma: Tensor, sign_x: Tensor, M: int) -> Tensor:
    """Point evaluations at canonical angles (N,) -> rows (2, N, 3M): weight ``sign_x`` on the x
    axis (the mirror identity's sign), 1 on the z axis, padding elsewhere."""
    N = beta.shape[0]
    pad = beta.new_zeros(N, M - 1)
    b = torch.cat([beta[:, None], pad], -1)
    g = torch.cat([gamma[:, None], pad], -1)
    wx = torch.cat([sign_x[:, None], pad], -1)
    wz = torch.cat([torch.ones_like(beta)[:, None], pad], -1)
    return torch.stack([encode_rows(b, g, wx), encode_rows(b, g, wz)])
