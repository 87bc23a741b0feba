"""The profile likelihood of one surface offset: an ``InverseRFT`` refitted at each offset of a grid.

Independent of the Laplace approximation of ``gp.surface.offset`` (which the front door composes while it
fits the offset with the maps), so it checks that one; it builds models, so it sits above the front
door (``gp.model``), never imported by it.
"""

from __future__ import annotations

import math

import torch

from ...rft.contacts import Contacts
from ..model import InverseRFT

__all__ = ["profile_surface"]


def profile_surface(contacts: Contacts, forces, offsets, n_iter: int = 300, lr: float = 0.05,
                    level: float = 0.95, **kwargs) -> dict:
    """Profile likelihood of one surface offset: at each offset (m) on a grid, an ``InverseRFT`` on
    ``contacts.with_surface_offset(offset)`` (hyperparameters refitted, ``n_iter`` Adam steps, other
    constructor arguments in ``kwargs``) and its total negative log likelihood (T x loss).

    Returns a dict: ``offsets`` (n,), ``nll`` (n,) minus its minimum (NaN where no segment touches),
    ``best`` (the grid's
    minimizer) and ``interval`` (lower, upper): the grid points where 2 x nll <= the chi-square(1)
    quantile at ``level`` (the grid's own resolution; an end of the grid means the interval reaches
    at least that far). Independent of the Laplace approximation, and of the model's own offset.
    """
    offsets = torch.as_tensor(offsets, dtype=torch.float64).reshape(-1)
    kwargs = {"hyper_posterior": "map", **kwargs}  # the fitted loss is what is profiled: no draws needed
    losses = []
    for d in offsets.tolist():
        c = contacts.with_surface_offset(d)
        if not bool((c.weight_z != 0).any()):
            losses.append(math.nan)  # nothing in contact at this offset: no map to fit (left out)
            continue
        m = InverseRFT(c, forces, **kwargs)
        m.fit(n_iter, lr, progress=False)
        with torch.no_grad():
            losses.append(float(m.loss()) * len(m.train_forces))
    nll = torch.tensor(losses, dtype=torch.float64)
    if not torch.isfinite(nll).any():
        raise ValueError("profile_surface: no offset of the grid puts any segment in contact")
    nll = nll - nll[torch.isfinite(nll)].min()
    q = 2 * torch.special.erfinv(torch.tensor(level, dtype=torch.float64)).item() ** 2  # chi2(1) quantile
    inside = offsets[2 * nll <= q]
    return {"offsets": offsets, "nll": nll, "best": float(offsets[int(torch.nan_to_num(nll, math.inf).argmin())]),
            "interval": (float(inside.min()), float(inside.max()))}
