"""Forward RFT: the force of the medium on the toe from a stress map and contacts."""

from __future__ import annotations

import torch
from torch import Tensor

from .contacts import Contacts
from .terrain import TerrainField, check_locations

__all__ = ["forces", "segment_forces"]


def _alpha(stress_map, contacts: Contacts, locations) -> Tensor:
    """The map at every segment (..., T, M, 2): ``stress_map(beta, gamma)``, or with ``locations`` (T, 2) m
    ``stress_map(beta, gamma, s)``, each sample's segments at its own place (a ``TerrainField``)."""
    if not isinstance(contacts, Contacts):
        raise TypeError(f"contacts must be a Contacts, got {type(contacts).__name__}")
    if locations is None:
        if isinstance(stress_map, TerrainField):
            raise ValueError(f"stress_map is a TerrainField ({stress_map.name}): pass locations (T, 2), each "
                             f"sample's place in m, or one medium (field.at(place))")
        return stress_map(contacts.beta, contacts.gamma)
    T = contacts.shape[-2]
    s = check_locations(locations, name="locations")
    if s.shape[-2:] != (T, 2):
        raise ValueError(f"locations must be ({T}, 2), one place per sample, got shape {tuple(s.shape)}")
    return stress_map(contacts.beta, contacts.gamma, s.to(contacts.beta)[..., :, None, :])


def segment_forces(stress_map, contacts: Contacts, locations=None) -> Tensor:
    """Per-segment forces (..., T, M, 2) = (weight_x alpha_x, weight_z alpha_z), N; ``locations`` as in
    ``forces``."""
    alpha = _alpha(stress_map, contacts, locations)
    if alpha.shape != contacts.shape + (2,):
        raise ValueError(
            f"stress_map(beta, gamma) returned shape {tuple(alpha.shape)}, want {tuple(contacts.shape) + (2,)}"
        )
    return torch.stack([contacts.weight_x, contacts.weight_z], dim=-1) * alpha


def forces(stress_map, contacts: Contacts, locations=None) -> Tensor:
    """Net force of the medium on the toe, (..., T, 2) = (F_x, F_z) in N.

    F_c[t] = sum_m weight_c[t, m] alpha_c(beta[t, m], gamma[t, m]) (Li et al. 2013, eq. of the
    I-RFT paper's Section II-A), with ``stress_map`` any callable (beta, gamma) -> (..., 2) in
    N/cm^3, e.g. a ``FourierStressMap`` or a fitted ``InverseRFT.stress_map_mean``. Over changing ground
    (``rft.terrain.TerrainField``), ``locations`` (T, 2) m gives each sample's place and the map is taken
    there: alpha(beta[t, m], gamma[t, m]; s[t]).
    """
    alpha = _alpha(stress_map, contacts, locations)
    if alpha.shape != contacts.shape + (2,):
        raise ValueError(
            f"stress_map(beta, gamma) returned shape {tuple(alpha.shape)}, want {tuple(contacts.shape) + (2,)}"
        )
    f_x = (contacts.weight_x * alpha[..., 0]).sum(dim=-1)
    f_z = (contacts.weight_z * alpha[..., 1]).sum(dim=-1)
    return torch.stack([f_x, f_z], dim=-1)
