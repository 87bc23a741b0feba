"""A walking robot's stances over the ground: footholds along a route, one stroke per stance, and each
sample's place in the world (what ``rft.forces(field, contacts, locations=...)`` and a spatial model read).

The stroke is a planar ``Path`` in the leg's plane (x forward, z up, m). At stance k the leg plane stands at
foothold p_k (x, y) m, its x axis along the heading psi_k (rad, world frame); sample t of the stroke is at

    s[k, t] = p_k + (x_t - x_0) (cos psi_k, sin psi_k),

so a long drag moves its place with the toe, and a stance that only pushes down stays at its foothold.

Example:
    >>> p, psi = footholds([(0.0, 0.0), (3.0, 0.0), (3.0, 2.0)], stride=0.25)   # an L-shaped route
    >>> w = walk(IToe(), rectangle_path(...), p, psi)
    >>> F = forces(field, w.contacts, locations=w.locations)                     # (N T, 2) N
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .contacts import Contacts, contacts
from .paths import Path
from .terrain import check_locations
from .toes import Toe

__all__ = ["Walk", "footholds", "walk"]


@dataclass(frozen=True)
class Walk:
    """A walk's samples, stance after stance.

    Attributes:
        contacts: (N T, M) every stance's stroke, in order.
        locations: (N T, 2) m, each sample's place (module docstring).
        stance: (N T,) int64, the stance each sample belongs to (0..N-1).
        footholds: (N, 2) m, where each stance stands.
        headings: (N,) rad, each stance's walking direction.
    """

    contacts: Contacts
    locations: Tensor
    stance: Tensor
    footholds: Tensor
    headings: Tensor

    def __len__(self) -> int:
        return int(self.locations.shape[0])

    @property
    def n_stances(self) -> int:
        return int(self.footholds.shape[0])


def footholds(route, stride: float, start: float = 0.0) -> tuple[Tensor, Tensor]:
    """Footholds every ``stride`` m along the polyline ``route`` (P, 2) m, from ``start`` m along it to its
    end, and the heading (rad) of the leg at each: the direction of the route's piece it lies on.
    Returns ((N, 2), (N,)) in float64."""
    r = check_locations(route, name="route").to(torch.float64)
    if r.ndim != 2 or r.shape[0] < 2:
        raise ValueError(f"route must be (P, 2) with P >= 2 points, got shape {tuple(r.shape)}")
    if not (math.isfinite(stride) and stride > 0):
        raise ValueError(f"stride must be a positive length in m, got {stride}")
    seg = r.diff(dim=0)
    length = torch.linalg.vector_norm(seg, dim=-1)
    if bool((length <= 0).any()):
        raise ValueError("route has repeated consecutive points (a piece of zero length)")
    cum = torch.cat([length.new_zeros(1), length.cumsum(0)])
    total = float(cum[-1])
    if not (0 <= start <= total):
        raise ValueError(f"start must be within the route's length 0..{total:.3g} m, got {start}")
    d = torch.arange(start, total + 1e-12, stride, dtype=torch.float64)
    piece = (torch.searchsorted(cum, d, right=True) - 1).clamp(0, len(seg) - 1)
    u = (d - cum[piece]) / length[piece]
    points = r[piece] + u[:, None] * seg[piece]
    headings = torch.atan2(seg[piece, 1], seg[piece, 0])
    return points, headings


def walk(toe: Toe, stroke: Path, footholds, headings) -> Walk:
    """One ``stroke`` of ``toe`` at each foothold (N, 2) m with heading (N,) rad: contacts, places and stance
    indices of every sample (``Walk``; the module docstring has the geometry)."""
    p = check_locations(footholds, name="footholds").to(torch.float64)
    if p.ndim != 2:
        raise ValueError(f"footholds must be (N, 2), got shape {tuple(p.shape)}")
    N = p.shape[0]
    psi = torch.as_tensor(headings, dtype=torch.float64)
    if psi.shape != (N,):
        raise ValueError(f"headings must be ({N},), one per foothold, got shape {tuple(psi.shape)}")
    if not bool(torch.isfinite(psi).all()):
        raise ValueError("headings has NaN or infinite entries")
    c = contacts(toe, stroke)
    T = len(stroke)
    dx = (stroke.position[:, 0] - stroke.position[0, 0]).to(torch.float64)  # (T,) m along the heading
    direction = torch.stack([psi.cos(), psi.sin()], dim=-1)  # (N, 2)
    places = p[:, None, :] + dx[None, :, None] * direction[:, None, :]  # (N, T, 2)
    return Walk(contacts=Contacts.cat([c] * N), locations=places.reshape(N * T, 2),
                stance=torch.arange(N).repeat_interleave(T), footholds=p, headings=psi)
