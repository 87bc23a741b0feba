r"""A physics prior mean for 3-D models: Li et al.'s generic maps, one scale per map fitted to the training forces.

With ``InverseRFT(contacts_3d, forces, prior=MapPrior(mean=...))`` the GPs model what the generic medium does not
explain: the prior mean of the maps is

    mu_x(beta, gamma) = s_x g_x(beta, gamma),   mu_y = s_y g_x(0, 0),   mu_z(beta, gamma) = s_z g_z(beta, gamma)

with g the generic maps of Li et al. 2013 (``rft.FourierStressMap.generic()``, unscaled; alpha_y's shape the
generic alpha_x(0, 0), as the rover-wheel authors take it) and s = (s_x, s_y, s_z) the least-squares scales of the
training forces on the forces those maps make (``shape_forces_3d``: each map's contribution at unit scale,
(T, 3 axes, 3 maps)). Which maps have a mean (``MEAN_MAPS``):

- ``"physics"`` (the 3-D default): alpha_x and alpha_z, the two maps Li et al. measured; alpha_y keeps a zero
  mean (s_y = 0: no experiment measured an out-of-plane stress map, and alpha_x(0, 0) is a convention);
- ``"physics_alpha_y"``: all three, alpha_y's mean the scaled generic alpha_x(0, 0).

The scales are fixed when the model is built (an empirical-Bayes mean; the minimum-norm solution where a map is
not seen: a planar motion leaves s_y = 0) and kept in the model's file. Where the forces constrain the maps, the
posterior follows the data whatever the mean; where they do not (a held-out kinematics, a locked wheel), it falls
back on the scaled generic medium instead of zero.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ...rft.stress_maps import FourierStressMap

__all__ = ["MEAN_MAPS", "shape_forces_3d", "fit_mean_scales"]

#: prior_mean -> the maps (0: alpha_x, 1: alpha_y, 2: alpha_z) whose mean is their scaled generic shape
MEAN_MAPS: dict[str, tuple[int, ...]] = {"physics": (0, 2), "physics_alpha_y": (0, 1, 2)}


def shape_forces_3d(contacts: Contacts3D) -> Tensor:
    """(T, 3, 3): the force on axis a (F_x, F_y, F_z; N) of map c (alpha_x, alpha_y, alpha_z) at unit scale of
    the generic shapes, so that the mean forces are ``shape_forces_3d(c) @ scales``."""
    c = contacts
    g = FourierStressMap.generic().to(dtype=c.beta.dtype, device=c.beta.device)  # a fresh module: .to is in place
    a = g(c.beta, c.gamma)  # (T, K, 2): generic alpha_x, alpha_z at each element
    zero = torch.zeros((), dtype=c.beta.dtype, device=c.beta.device)
    ay = g(zero, zero)[0]
    gx = (c.weight_x * a[..., 0:1]).sum(-2)  # (T, 2): alpha_x's part of (F_x, F_y)
    gy = c.weight_y.sum(-2) * ay  # (T, 2)
    gz = (c.weight_z * a[..., 1]).sum(-1)  # (T,)
    z = torch.zeros_like(gz)
    return torch.stack([torch.stack([gx[:, 0], gy[:, 0], z], -1), torch.stack([gx[:, 1], gy[:, 1], z], -1),
                        torch.stack([z, z, gz], -1)], -2)


def fit_mean_scales(contacts: Contacts3D, forces: Tensor, shape_forces: Tensor | None = None,
                    maps: tuple[int, ...] = (0, 1, 2)) -> Tensor:
    """(3,) least-squares scales of (alpha_x, alpha_y, alpha_z)'s generic shapes on ``forces`` (T, 3) in N:
    min |G s - F|^2 over every sample and axis, s nonzero only on ``maps`` (``MEAN_MAPS[prior_mean]``; minimum
    norm where a map is not seen). ``shape_forces``: ``shape_forces_3d(contacts)`` if already computed."""
    G = shape_forces_3d(contacts) if shape_forces is None else shape_forces
    idx = list(maps)
    if not idx or any(i not in (0, 1, 2) for i in idx) or len(set(idx)) != len(idx):
        raise ValueError(f"maps must be distinct map indices in (0, 1, 2), got {maps!r}")
    s = G.new_zeros(3)
    s[idx] = torch.linalg.pinv(G[..., idx].reshape(-1, len(idx))) @ forces.reshape(-1)
    return s
