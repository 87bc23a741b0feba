"""How a 3-D model's covariance splits into two independent blocks, and the rows of a block: each block's force
axes stacked axis-major, with the weights of its maps.

The blocks (docs/inverse3d.md): F_z sees alpha_z only; F_x and F_y both see alpha_x (through the element's
in-plane direction u) and alpha_y (through e1). So the force covariance is block diagonal,

    horizontal (rows F_x then F_y, 2T):  sum_{c in x, y} W_hc K_c W_hc^T + diag(sigma_x^2 I, sigma_y^2 I)
    vertical   (rows F_z, T):            W_z K_z W_z^T + sigma_z^2 I

and the planar model is the special case where the F_y rows see no map (they add only their own noise term).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ...rft.stress_maps import mirror_to_canonical

__all__ = ["Block", "BLOCKS", "block_rows", "block_targets", "point_contacts"]


@dataclass(frozen=True)
class Block:
    """One independent block of the force covariance: the maps it sees and the force axes of its rows (each
    axis a group of T rows, in this order, with its own noise variance)."""

    name: str
    maps: tuple[int, ...]
    axes: tuple[int, ...]


BLOCKS = (Block("horizontal", (0, 1), (0, 1)), Block("vertical", (2,), (2,)))


def point_contacts(beta: Tensor, gamma: Tensor) -> Contacts3D:
    """Map evaluations as one-element functionals (N, 1): the F_x row reads alpha_x (times the mirror sign of
    angles outside the canonical square), the F_y row alpha_y, the F_z row alpha_z."""
    bc, gc, sx = mirror_to_canonical(beta.reshape(-1), gamma.reshape(-1))
    one, zero = torch.ones_like(bc), torch.zeros_like(bc)
    return Contacts3D(bc[:, None], gc[:, None], torch.stack([sx, zero], -1)[:, None],
                      torch.stack([zero, one], -1)[:, None], one[:, None])


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
