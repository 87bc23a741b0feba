"""The rows of a 3-D block: each block's force axes stacked axis-major, with the weights of its maps."""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from .hyperparameters import Block

__all__ = ["block_rows", "block_targets"]


def block_rows(c: Contacts3D, block: Block) -> tuple[Tensor, Tensor, list[Tensor]]:
    """The block's rows of contacts (T, K): beta, gamma (n, K) and, per map of the block, the weights (n, K);
    n = T x the block's axes, axis-major (all F_x rows, then all F_y rows)."""
    A = len(block.axes)
    beta, gamma = c.beta.repeat(A, 1), c.gamma.repeat(A, 1)
    per_map = {0: c.weight_x, 1: c.weight_y}
    weights = []
    for m in block.maps:
        if m == 2:
            weights.append(c.weight_z)
        else:
            weights.append(torch.cat([per_map[m][..., a] for a in block.axes]))
    return beta, gamma, weights


def block_targets(forces: Tensor, block: Block) -> Tensor:
    """(n,) the block's forces, axis-major."""
    return torch.cat([forces[:, a] for a in block.axes])
