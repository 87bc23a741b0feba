"""Which 3-D backend (``make_backend_3d``): observations while the element-pair count is small, else pairs where the
data hold few distinct angle pairs, else spectral (docs/inverse3d.md)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ..kernels.fourier import MAX_HARMONICS
from ..kernels.operators import unique_pairs
from .backends import Backend3D, Observations3D, Pairs3D
from .spectral import Spectral3D

__all__ = ["make_backend_3d", "METHODS_3D"]

METHODS_3D = ("auto", "observations", "pairs", "spectral")


def make_backend_3d(method: str, hypers, contacts: Contacts3D, forces: Tensor, tol: float = 1e-7,
                    features=None, max_harmonics: int = MAX_HARMONICS) -> Backend3D:
    """The backend for ``method``; "auto": observations while the element-pair count is small, else pairs where
    the data hold few distinct angle pairs, else spectral."""
    if method not in METHODS_3D:
        raise ValueError(f"method must be one of {METHODS_3D}, got {method!r}")
    if features is not None and method == "auto":
        method = "spectral"
    if method == "auto":
        n = int(contacts.in_contact().sum())
        live = contacts.in_contact()
        U = unique_pairs(torch.stack([contacts.beta[live], contacts.gamma[live]], -1).detach())[0].shape[0] if n else 1
        if n <= 1500:
            method = "observations"
        elif U <= 1500:
            method = "pairs"
        else:
            method = "spectral"
    if method == "observations":
        return Observations3D(hypers, contacts, forces)
    if method == "pairs":
        return Pairs3D(hypers, contacts, forces)
    return Spectral3D(hypers, contacts, forces, tol=tol, features=features, max_harmonics=max_harmonics)
