"""Terrain that changes over the ground: stress maps alpha(beta, gamma; s) that depend on where the toe is.

A ``TerrainField`` holds J media (stress maps, N/cm^3) and their share w_j(s) >= 0 (sum 1) at every horizontal
place s = (x, y) in m, world frame:

    alpha(beta, gamma; s) = sum_j w_j(s) alpha_j(beta, gamma).

RFT is linear in the map, so a blend of media is a medium: a boundary between two sands, a compaction
gradient (one sand between two scales) and patches are all this form. ``rft.forces(field, contacts,
locations=s)`` gives a walk's forces, each sample's map taken at its own place (``rft.walks`` makes the
footholds and their locations).

Example:
    >>> loose, packed = FourierStressMap.poppy_seeds_loose(), FourierStressMap.poppy_seeds_close()
    >>> field = TerrainField.two_media(loose, packed, boundary=1.0, width=0.05)   # packed beyond x = 1 m
    >>> field(beta, gamma, torch.tensor([2.0, 0.0]))    # (..., 2): packed sand's map there
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from .contacts import check_locations
from .stress_maps import FourierStressMap

__all__ = ["TerrainField", "check_locations"]

StressMap = Callable[[Tensor, Tensor], Tensor]


def _direction(angle: float) -> Tensor:
    return torch.tensor([math.cos(angle), math.sin(angle)], dtype=torch.float64)


class TerrainField(nn.Module):
    """Stress maps over the ground: J media and their shares w(s) (module docstring).

    Args:
        media: J stress maps, each a callable (beta, gamma) -> (..., 2) N/cm^3 (``FourierStressMap``, a fitted
            model's ``stress_map_mean``, ...).
        shares: s (..., 2) m -> w (..., J), non-negative and summing to 1 over J (checked on every call).
        name: what the field is, for reports and figures.

    Calling the field with ``beta``, ``gamma`` (radians) and ``locations`` (m, last dimension 2), all broadcast
    against one another, returns (..., 2): (alpha_x, alpha_z) at each place. The constructors below build the
    common kinds; ``at(s)`` is the homogeneous map at one place.
    """

    def __init__(self, media: Sequence[StressMap], shares: Callable[[Tensor], Tensor], name: str = "terrain") -> None:
        super().__init__()
        if len(media) == 0:
            raise ValueError("media must hold at least one stress map")
        for j, m in enumerate(media):
            if not callable(m):
                raise TypeError(f"media[{j}] must be a stress map (beta, gamma) -> (..., 2), got {type(m).__name__}")
        self.media = list(media)
        self._modules_list = nn.ModuleList([m for m in media if isinstance(m, nn.Module)])  # follow .to()
        self.shares_fn = shares
        self.name = name

    @property
    def n_media(self) -> int:
        return len(self.media)

    def shares(self, locations) -> Tensor:
        """w (..., J): each medium's share at ``locations`` (..., 2) m; non-negative, summing to 1."""
        s = check_locations(locations)
        w = self.shares_fn(s)
        if w.shape != s.shape[:-1] + (self.n_media,):
            want = tuple(s.shape[:-1]) + (self.n_media,)
            raise ValueError(f"shares(locations) returned {tuple(w.shape)}, want {want}")
        if bool((w < -1e-12).any()) or not torch.allclose(w.sum(-1), torch.ones_like(w[..., 0]), atol=1e-9):
            raise ValueError("shares(locations) must be non-negative and sum to 1 over the media")
        return w

    def forward(self, beta: Tensor, gamma: Tensor, locations) -> Tensor:
        """(alpha_x, alpha_z) (..., 2) N/cm^3 at angles ``beta``, ``gamma`` (rad) and places ``locations``
        (..., 2) m, broadcast together."""
        s = check_locations(locations).to(beta)
        w = self.shares(s)  # (..., J)
        beta, gamma = torch.broadcast_tensors(beta, gamma)
        out = None
        for j, m in enumerate(self.media):
            a = m(beta, gamma) * w[..., j, None]
            out = a if out is None else out + a
        assert out is not None
        return out

    def at(self, location) -> StressMap:
        """The homogeneous stress map (beta, gamma) -> (..., 2) at one place ``location`` (2,) m."""
        s = check_locations(location)
        if s.shape != (2,):
            raise ValueError(f"location must be one place (2,), got shape {tuple(s.shape)}")
        return lambda beta, gamma: self(beta, gamma, s.to(beta))

    def extra_repr(self) -> str:
        return f"{self.name!r}, {self.n_media} media"

    # ---- the common kinds ------------------------------------------------------------------------------------
    @classmethod
    def uniform(cls, medium: StressMap) -> TerrainField:
        """One medium everywhere: the homogeneous bed every planar model assumes."""
        return cls([medium], lambda s: torch.ones(*s.shape[:-1], 1, dtype=s.dtype, device=s.device),
                   name=f"uniform {getattr(medium, 'name', 'medium')}")

    @classmethod
    def two_media(cls, first: StressMap, second: StressMap, boundary: float = 0.0, width: float = 0.05,
                  angle: float = 0.0) -> TerrainField:
        """``first`` before a straight boundary, ``second`` beyond it: the boundary is the line where
        s . (cos angle, sin angle) = ``boundary`` (m); across it the share of ``second`` rises as a logistic of
        ``width`` (m: 10 % to 90 % over 4.4 width). ``angle`` in rad (0: the boundary is across x)."""
        if not (math.isfinite(width) and width > 0):
            raise ValueError(f"width must be a positive length in m, got {width}")
        d = _direction(angle)

        def shares(s: Tensor) -> Tensor:
            u = torch.sigmoid(((s * d.to(s)).sum(-1) - boundary) / width)
            return torch.stack([1 - u, u], dim=-1)

        return cls([first, second], shares, name=f"two media, boundary at {boundary:g} m")

    @classmethod
    def compaction_gradient(cls, medium: FourierStressMap, scales: tuple[float, float] = (0.5, 1.5),
                            span: tuple[float, float] = (0.0, 2.0), angle: float = 0.0) -> TerrainField:
        """One medium whose stiffness grows along a direction: ``medium`` scaled by ``scales[0]`` at
        s . (cos angle, sin angle) <= ``span[0]`` (m), by ``scales[1]`` at >= ``span[1]``, linearly between
        (both maps, alpha_x and alpha_z alike: looser to more compact)."""
        lo, hi = (float(v) for v in scales)
        a, b = (float(v) for v in span)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo >= 0 and hi >= 0):
            raise ValueError(f"scales must be two non-negative numbers, got {scales}")
        if not (math.isfinite(a) and math.isfinite(b) and b > a):
            raise ValueError(f"span must be (start, end) in m with end > start, got {span}")
        d = _direction(angle)

        def shares(s: Tensor) -> Tensor:
            u = (((s * d.to(s)).sum(-1) - a) / (b - a)).clamp(0, 1)
            return torch.stack([1 - u, u], dim=-1)

        return cls([medium.scaled(lo, lo), medium.scaled(hi, hi)], shares,
                   name=f"{getattr(medium, 'name', 'medium')} x {lo:g}..{hi:g} over {a:g}..{b:g} m")

    @classmethod
    def random_patches(cls, media: Sequence[StressMap], n_patches: int = 12,
                       extent: tuple[float, float, float, float] = (0.0, 3.0, -1.0, 1.0), edge: float = 0.05,
                       seed: int = 0) -> TerrainField:
        """Patches of ``media`` over the rectangle ``extent`` = (x_min, x_max, y_min, y_max) m: ``n_patches``
        centres drawn uniformly in it, each given one of the media in turn (so every medium has patches), and
        each place belongs to its nearest centre, with soft edges: the shares are softmax(-d_k^2 / (2 edge L))
        over the centres (d_k: distance to centre k, L the mean spacing sqrt(area / n_patches)), summed per
        medium. ``edge`` (m): the width of the blend between patches. Same ``seed``, same field."""
        J = len(media)
        if J < 1 or n_patches < J:
            raise ValueError(f"need at least one medium and n_patches >= len(media), got {J} media, {n_patches}")
        x0, x1, y0, y1 = (float(v) for v in extent)
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"extent must be (x_min, x_max, y_min, y_max) with max > min, got {extent}")
        if not (math.isfinite(edge) and edge > 0):
            raise ValueError(f"edge must be a positive length in m, got {edge}")
        g = torch.Generator().manual_seed(int(seed))
        u = torch.rand(n_patches, 2, generator=g, dtype=torch.float64)
        centres = torch.stack([x0 + (x1 - x0) * u[:, 0], y0 + (y1 - y0) * u[:, 1]], dim=-1)  # (P, 2)
        owner = torch.arange(n_patches) % J  # (P,) every medium owns patches
        onehot = torch.nn.functional.one_hot(owner, J).to(torch.float64)  # (P, J)
        spacing = math.sqrt((x1 - x0) * (y1 - y0) / n_patches)

        def shares(s: Tensor) -> Tensor:
            d2 = (s[..., None, :] - centres.to(s)).pow(2).sum(-1)  # (..., P)
            r = torch.softmax(-d2 / (2 * edge * spacing), dim=-1)
            return r @ onehot.to(s)

        field = cls(list(media), shares, name=f"{n_patches} patches of {J} media")
        field.register_buffer("centres", centres)
        field.register_buffer("owner", owner)
        return field
