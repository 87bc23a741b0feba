"""irft_torch: Inverse Resistive Force Theory in PyTorch / GPyTorch.

    import irft_torch as irft
    smap = irft.rft.FourierStressMap.generic()
    contacts = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path())
    forces = irft.rft.forces(smap, contacts)

The subpackages load on first use (PEP 562), so ``import irft_torch`` and the ``irft`` command's
parsing do not import torch before they need it (``irft reproduce`` starts its worker processes'
imports first, beside its own).
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING

from ._version import package_version

__version__ = package_version(Path(__file__).parent)
__all__ = ["rft", "gp", "hardware", "data", "design", "studies", "metrics", "InverseRFT", "MapPrior", "Engine",
           "Posterior", "TerrainFilter", "__version__"]

_SUBMODULES = ("rft", "gp", "hardware", "data", "design", "studies", "metrics")
_FROM_GP = ("InverseRFT", "MapPrior", "Engine", "Posterior", "TerrainFilter")

if TYPE_CHECKING:  # what static tools and IDEs see
    from . import data, design, gp, hardware, metrics, rft, studies
    from .gp import Engine, InverseRFT, MapPrior, Posterior, TerrainFilter


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    if name in _FROM_GP:
        return getattr(importlib.import_module(".gp", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
