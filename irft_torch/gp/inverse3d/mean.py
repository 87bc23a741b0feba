r"""A physics prior mean for 3-D models: Li et al.'s generic maps, one scale per map fitted to the training forces.

With ``InverseRFT(contacts_3d, forces, prior_mean="physics")`` the GPs model what the generic medium does not
explain: the prior mean of the maps is

    mu_x(beta, gamma) = s_x g_x(beta, gamma),   mu_y = s_y g_x(0, 0),   mu_z(beta, gamma) = s_z g_z(beta, gamma)

with g the generic maps of Li et al. 2013 (``rft.FourierStressMap.generic()``, unscaled; alpha_y the generic
alpha_x(0, 0), as the rover-wheel authors take it) and s = (s_x, s_y, s_z) the least-squares scales of the
training forces on the forces those maps make (``shape_forces_3d``: each map's contribution at unit scale,
(T, 3 axes, 3 maps)). The scales are fixed when the model is built (an empirical-Bayes mean; the minimum-norm
solution where a map is not seen: a planar motion leaves s_y = 0) and kept in the model's file. Where the forces
constrain the maps, the posterior follows the data whatever the mean; where they do not (a held-out kinematics,
a locked wheel), it falls back on the scaled generic medium instead of zero.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ...rft.stress_maps import FourierStressMap

__all__ = ["shape_forces_3d", "fit_mean_scales"]

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


def fit_mean_scales(contacts: Contacts3D, forces: Tensor, shape_forces: Tensor | None = None) -> Tensor:
    """(3,) least-squares scales of (alpha_x, alpha_y, alpha_z)'s generic shapes on ``forces`` (T, 3) in N:
    min |G s - F|^2 over every sample and axis (minimum norm where a map is not seen). ``shape_forces``:
    ``shape_forces_3d(contacts)`` if already computed."""
    G = shape_forces_3d(contacts) if shape_forces is None else shape_forces
    return torch.linalg.pinv(G.reshape(-1, 3)) @ forces.reshape(-1)
