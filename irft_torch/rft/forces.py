"""Forward RFT: the force of the medium on the toe from a stress map and contacts."""

from __future__ import annotations

import torch
from torch import Tensor

from .contacts import Contacts

__all__ = ["forces", "segment_forces"]


def segment_forces(stress_map, contacts: Contacts) -> Tensor:
    """Per-segment forces (..., T, M, 2) = (weight_x alpha_x, weight_z alpha_z), N."""
    if not isinstance(contacts, Contacts):
        raise TypeError(f"contacts must be a Contacts, got {type(contacts).__name__}")
    alpha = stress_map(contacts.beta, contacts.gamma)
    if alpha.shape != contacts.shape + (2,):
        raise ValueError(
            f"stress_map(beta, gamma) returned shape {tuple(alpha.shape)}, want {tuple(contacts.shape) + (2,)}"
        )
    return torch.stack([contacts.weight_x, contacts.weight_z], dim=-1) * alpha


def forces(stress_map, contacts: Contacts) -> Tensor:
    """Net force of the medium on the toe, (..., T, 2) = (F_x, F_z) in N.

    F_c[t] = sum_m weight_c[t, m] alpha_c(beta[t, m], gamma[t, m]) (Li et al. 2013, eq. of the
    I-RFT paper's Section II-A), with ``stress_map`` any callable (beta, gamma) -> (..., 2) in
    N/cm^3, e.g. a ``FourierStressMap`` or a fitted ``InverseRFT.stress_map_mean``.
    """
    if not isinstance(contacts, Contacts):
        raise TypeError(f"contacts must be a Contacts, got {type(contacts).__name__}")
    alpha = stress_map(contacts.beta, contacts.gamma)
    if alpha.shape != contacts.shape + (2,):
        raise ValueError(
            f"stress_map(beta, gamma) returned shape {tuple(alpha.shape)}, want {tuple(contacts.shape) + (2,)}"
        )
    f_x = (contacts.weight_x * alpha[..., 0]).sum(dim=-1)
    f_z = (contacts.weight_z * alpha[..., 1]).sum(dim=-1)
    return torch.stack([f_x, f_z], dim=-1)
