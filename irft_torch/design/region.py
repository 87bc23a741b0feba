"""Regions of the (beta, gamma) square over which a design integrates the map variance."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rft.contacts import Contacts
from ..rft.contacts3d import Contacts3D
from ..rft.stress_maps import mirror_to_canonical

__all__ = ["Region"]


@dataclass
class Region:
    """Points of the (beta, gamma) square with weights, over which the map variance is integrated.

    Attributes:
        beta, gamma: (N,) angles in rad (mapped into the canonical square on construction).
        weight: (N,) non-negative weights, normalized to sum to 1 on construction.
    The dtype is that of the first floating tensor given (else torch's default).
    """

    beta: Tensor
    gamma: Tensor
    weight: Tensor

    def __post_init__(self) -> None:
        dtype = next((v.dtype for v in (self.beta, self.gamma, self.weight)
                      if isinstance(v, Tensor) and v.dtype.is_floating_point), torch.get_default_dtype())
        b, g, w = (torch.as_tensor(v, dtype=dtype) for v in (self.beta, self.gamma, self.weight))
        if b.ndim != 1 or b.shape != g.shape or b.shape != w.shape or b.numel() == 0:
            raise ValueError(f"Region needs beta, gamma, weight of one shape (N,), got {tuple(b.shape)}, "
                             f"{tuple(g.shape)}, {tuple(w.shape)}")
        for name, v in (("beta", b), ("gamma", g), ("weight", w)):
            if not torch.isfinite(v).all():
                raise ValueError(f"Region.{name} contains NaN or inf")
        if (w < 0).any() or w.sum() <= 0:
            raise ValueError("Region.weight must be >= 0 with a positive sum")
        self.beta, self.gamma, _ = mirror_to_canonical(b, g)
        self.weight = w / w.sum()

    @classmethod
    def square(cls, n: int = 16, dtype=torch.float64) -> Region:
        """An n x n grid of cell centres over the canonical square, equal weights."""
        e = torch.linspace(-math.pi / 2, math.pi / 2, n + 1, dtype=dtype)
        c = (e[1:] + e[:-1]) / 2
        B, G = torch.meshgrid(c, c, indexing="ij")
        return cls(B.reshape(-1), G.reshape(-1), torch.ones(n * n, dtype=dtype))

    @classmethod
    def sign_change(cls, n: int = 16, gamma_min: float = math.pi / 3, dtype=torch.float64) -> Region:
        """The region the I-RFT paper calls informative: gamma > ``gamma_min`` (default pi/3), where
        alpha_x changes sign with beta."""
        sq = cls.square(n, dtype)
        return cls(sq.beta, sq.gamma, (sq.gamma > gamma_min).to(dtype))

    def contacts(self) -> Contacts:
        """The region's points as (N, 1) point evaluations (weight 1 on both axes)."""
        one = torch.ones_like(self.beta)[:, None]
        return Contacts(self.beta[:, None], self.gamma[:, None], one, one)


def _as_contacts(c, three_d: bool = False) -> Contacts | Contacts3D:
    """A Contacts, or anything with a ``contacts()`` method (an ``rft.Probe``); ``three_d``: an ``rft.Contacts3D``."""
    if three_d:
        if not isinstance(c, Contacts3D):
            raise TypeError(f"a 3-D candidate must be an rft.Contacts3D (rft.contacts_3d), got {type(c).__name__}")
        return c
    if isinstance(c, Contacts):
        out = c
    elif hasattr(c, "contacts"):
        out = c.contacts()
    else:
        raise TypeError(f"a candidate must be a Contacts or have a contacts() method (a Probe), got {type(c).__name__}")
    if out.beta.ndim != 2:
        raise ValueError(f"a candidate's contacts must be (T, M), got {tuple(out.shape)}")
    return out
