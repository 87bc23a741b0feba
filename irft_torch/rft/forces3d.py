"""Forward 3-D RFT: the force of the medium on a rigid body from stress maps and ``Contacts3D``."""

from __future__ import annotations

import torch
from torch import Tensor

from .contacts3d import Contacts3D

__all__ = ["forces_3d", "alpha_values_3d"]


def alpha_values_3d(stress_map, contacts: Contacts3D, alpha_y=None) -> Tensor:
    """(T, K, 3): (alpha_x, alpha_y, alpha_z) at every contact element, N/cm^3.

    ``stress_map(beta, gamma)`` returns (..., 2) = (alpha_x, alpha_z) (a ``FourierStressMap``, a planar
    ``InverseRFT``) or (..., 3) = (alpha_x, alpha_y, alpha_z) (a 3-D model's mean map; then ``alpha_y`` must be
    None). ``alpha_y``: None (the map's alpha_x(0, 0), the rover-wheel authors' choice), a number (N/cm^3), or
    a callable (beta, gamma) -> (...) (a map of its own).
    """
    if not isinstance(contacts, Contacts3D):
        raise TypeError(f"contacts must be a Contacts3D (rft.contacts_3d), got {type(contacts).__name__}")
    a = stress_map(contacts.beta, contacts.gamma)
    if a.shape == (*contacts.shape, 3):
        if alpha_y is not None:
            raise ValueError("stress_map returns (alpha_x, alpha_y, alpha_z): alpha_y must be None")
        return a
    if a.shape != (*contacts.shape, 2):
        raise ValueError(f"stress_map(beta, gamma) returned shape {tuple(a.shape)}, want "
                         f"{tuple(contacts.shape) + (2,)} (alpha_x, alpha_z) or {tuple(contacts.shape) + (3,)}")
    if alpha_y is None:
        z = torch.zeros((), dtype=contacts.beta.dtype, device=contacts.beta.device)
        ay = stress_map(z, z)[..., 0].expand(contacts.shape)
    elif callable(alpha_y):
        ay = torch.as_tensor(alpha_y(contacts.beta, contacts.gamma), dtype=a.dtype, device=a.device)
        if ay.shape != contacts.shape:
            raise ValueError(f"alpha_y(beta, gamma) returned shape {tuple(ay.shape)}, want {tuple(contacts.shape)}")
    else:
        ay = torch.as_tensor(alpha_y, dtype=a.dtype, device=a.device)
        if ay.numel() != 1 or not torch.isfinite(ay).all():
            raise ValueError(f"alpha_y must be None, a finite number in N/cm^3 or a callable, got {alpha_y!r}")
        ay = ay.reshape(()).expand(contacts.shape)
    return torch.stack([a[..., 0], ay, a[..., 1]], -1)


def forces_3d(stress_map, contacts: Contacts3D, alpha_y=None) -> Tensor:
    """Net force of the medium on the body, (T, 3) = (F_x, F_y, F_z) in N, world frame.

    F_(x,y) = sum_k weight_x[k] alpha_x(b_k, g_k) + weight_y[k] alpha_y, F_z = sum_k weight_z[k] alpha_z(b_k, g_k)
    (``rft.contacts3d``); ``stress_map`` and ``alpha_y`` as in ``alpha_values_3d`` (default alpha_y = the
    map's alpha_x(0, 0)).

    Example:
        >>> forces_3d(FourierStressMap.generic(0.6, 0.6), contacts_3d(mesh, v, w, surface=0.0))
    """
    a = alpha_values_3d(stress_map, contacts, alpha_y)
    fxy = (contacts.weight_x * a[..., 0:1] + contacts.weight_y * a[..., 1:2]).sum(-2)
    fz = (contacts.weight_z * a[..., 2]).sum(-1)
    return torch.cat([fxy, fz[:, None]], -1)
