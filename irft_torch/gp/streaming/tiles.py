"""Maps over the ground, online at a bounded cost: the ground cut into square tiles, each an exact spatial model of
the samples within its square widened by a margin (``gp.backends.spatial``, the fitted model's hyperparameters).

A walk's per-step cost then depends on how many samples a tile holds, not on how long the walk has been: a new
stance goes into the (at most four) tiles whose widened squares it falls in, and a query is answered by the tile
its place lies in. Each tile keeps at most ``max_samples`` samples (the oldest dropped first), and with
``max_tiles`` at most that many tiles are kept (the least recently used dropped: added to or asked about), so memory
is bounded by ``max_tiles`` x ``max_samples`` samples however far the robot walks; a place in a dropped tile gets
the prior again until new samples fall near it. Without ``max_tiles`` memory grows
with the ground covered.

The approximation: a place's maps are conditioned on the samples within the margin of its tile only. With the
margin at least three spatial lengthscales the variation around the site's medium is barely correlated beyond it;
what is lost is what far samples say about the medium shared by the whole site. ``experiments/benchmarks/
bench_walk_online.py`` measures the difference against the exact model and the cost per step.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import torch
from torch import Tensor

from ...rft.contacts import Contacts, check_locations
from ..backends.spatial import SpatialBackend
from ..posterior import Posterior

__all__ = ["SpatialTiles"]


class SpatialTiles:
    """Online maps over the ground with a bounded cost per step (module docstring).

    Args:
        model: a fitted ``InverseRFT`` with places (``locations=``): its hyperparameters (the plug-in, at the mode)
            are used and never changed.
        tile: the tiles' side, m.
        margin: how far beyond its square a tile takes samples, m (default: three times the longer spatial
            lengthscale, at least ``tile`` / 4).
        max_samples: the most samples a tile keeps (the oldest dropped first).
        max_tiles: the most tiles kept (the least recently used dropped first); None (default): no bound. At
            least 4: a new stance can fall in the margins of four tiles.

    Example:
        >>> tiles = SpatialTiles(model, tile=1.0)
        >>> tiles.add_data(stance_contacts, stance_forces, locations=stance_places)   # one stance at a time
        >>> tiles.stress_map(beta, gamma, locations=places).mean                      # (L, *beta.shape, 2)
    """

    def __init__(self, model, tile: float = 1.0, margin: float | None = None, max_samples: int = 400,
                 max_tiles: int | None = None) -> None:
        if not getattr(model, "spatial", False):
            raise ValueError("model: SpatialTiles needs a model fitted with places (InverseRFT(..., locations=))")
        if not (math.isfinite(tile) and tile > 0):
            raise ValueError(f"tile must be a positive length in m, got {tile}")
        if int(max_samples) != max_samples or max_samples < 2:
            raise ValueError(f"max_samples must be an integer >= 2, got {max_samples!r}")
        self.hypers = model.hypers
        self.dtype, self.device = model.dtype, model._device
        self.tile = float(tile)
        ls = float(self.hypers.spatial.lengthscale.detach().max())
        self.margin = float(max(3 * ls, tile / 4)) if margin is None else float(margin)
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"margin must be a non-negative length in m, got {margin}")
        if max_tiles is not None and (int(max_tiles) != max_tiles or max_tiles < 4):
            raise ValueError(f"max_tiles must be None or an integer >= 4, got {max_tiles!r}")
        self.max_samples = int(max_samples)
        self.max_tiles = None if max_tiles is None else int(max_tiles)
        self.n_dropped = 0  # tiles dropped to keep within max_tiles
        self._data: OrderedDict[tuple[int, int], tuple[Contacts, Tensor]] = OrderedDict()
        self._backends: dict[tuple[int, int], SpatialBackend] = {}
        c, f, _ = model._join()
        self.add_data(c, f)  # the model's own samples (already whitened: noise scale 1 assumed for new ones)

    @property
    def n_tiles(self) -> int:
        return len(self._data)

    def samples_in(self, key: tuple[int, int]) -> int:
        return len(self._data[key][0]) if key in self._data else 0

    def _key(self, s: Tensor) -> Tensor:
        return torch.floor(s / self.tile).long()

    def add_data(self, contacts: Contacts, forces, locations=None) -> SpatialTiles:
        """Add samples (T, M) with forces (T, 2) N and places (T, 2) m (or ``contacts.locations``); each goes into
        every tile whose widened square holds it. Cost: the tiles touched are refactored at their next query."""
        if locations is not None:
            contacts = contacts.with_locations(check_locations(locations, len(contacts)))
        if contacts.locations is None:
            raise ValueError("locations: SpatialTiles needs each sample's place (T, 2) m")
        c = contacts.to(dtype=self.dtype, device=self.device)
        f = torch.as_tensor(forces, dtype=self.dtype, device=self.device)
        if f.shape != (len(c), 2) or not bool(torch.isfinite(f).all()):
            raise ValueError(f"forces must be ({len(c)}, 2) finite N, got shape {tuple(f.shape)}")
        s = c.locations
        lo = torch.floor((s - self.margin) / self.tile).long().min(0).values
        hi = torch.floor((s + self.margin) / self.tile).long().max(0).values
        for i in range(int(lo[0]), int(hi[0]) + 1):
            for j in range(int(lo[1]), int(hi[1]) + 1):
                x0, y0 = i * self.tile - self.margin, j * self.tile - self.margin
                x1, y1 = (i + 1) * self.tile + self.margin, (j + 1) * self.tile + self.margin
                inside = (s[:, 0] >= x0) & (s[:, 0] < x1) & (s[:, 1] >= y0) & (s[:, 1] < y1)
                if not inside.any():
                    continue
                key = (i, j)
                new_c, new_f = c[inside], f[inside]
                if key in self._data:
                    old_c, old_f = self._data[key]
                    new_c, new_f = Contacts.cat([old_c, new_c]), torch.cat([old_f, new_f])
                if len(new_c) > self.max_samples:
                    new_c, new_f = new_c[-self.max_samples:], new_f[-self.max_samples:]
                self._data[key] = (new_c, new_f)
                self._data.move_to_end(key)
                self._backends.pop(key, None)
        self._drop_oldest()
        return self

    def _drop_oldest(self) -> None:
        """Drop the least recently used tiles beyond ``max_tiles``."""
        while self.max_tiles is not None and len(self._data) > self.max_tiles:
            key, _ = self._data.popitem(last=False)
            self._backends.pop(key, None)
            self.n_dropped += 1

    def _backend(self, key: tuple[int, int]) -> SpatialBackend | None:
        if key not in self._data:
            return None
        self._data.move_to_end(key)  # asked about: recently used
        if key not in self._backends:
            self._backends[key] = SpatialBackend(self.hypers, *self._data[key])
        return self._backends[key]

    def _posterior(self, c: Contacts) -> tuple[Tensor, Tensor]:
        """(mean, variance) (2, N) of the weighted sums of placed contacts (N, M), each from its place's tile."""
        keys = self._key(c.locations)
        mean = c.beta.new_zeros(2, len(c))
        var = c.beta.new_zeros(2, len(c))
        for key in {tuple(k) for k in keys.tolist()}:
            rows = (keys == torch.tensor(key, device=keys.device)).all(-1)
            part = c[rows]
            b = self._backend(key)
            if b is None:  # nothing measured near: the prior
                from ..kernels.angle import composite_covariance

                m = self.hypers.mean_of(part, detach=True)
                mean[:, rows] = 0.0 if m is None else m
                var[:, rows] = composite_covariance(self.hypers.kernel, part, li=self.hypers.li).diagonal() \
                    * self.hypers.spatial.diagonal(detach=True)[:, None]
                continue
            with torch.no_grad():
                post = b.posterior(part)
            mean[:, rows], var[:, rows] = post.mean, post.variance
        return mean, var

    def stress_map(self, beta, gamma, locations) -> Posterior:
        """The maps at angles (shape S, rad) at each of ``locations`` (L, 2) m: mean and variance (L, *S, 2)."""
        beta = torch.as_tensor(beta, dtype=self.dtype, device=self.device)
        gamma = torch.as_tensor(gamma, dtype=self.dtype, device=self.device)
        beta, gamma = torch.broadcast_tensors(beta, gamma)
        where = check_locations(locations, name="locations").to(self.dtype)
        if where.ndim != 2:
            raise ValueError(f"locations must be (L, 2) m, got shape {tuple(where.shape)}")
        pts = Contacts.points(beta, gamma)
        N, L = len(pts), where.shape[0]
        c = Contacts(**{k: v.repeat(L, 1) for k, v in pts.as_dict().items()},
                     locations=where.repeat_interleave(N, 0))
        mean, var = self._posterior(c)
        shape = (L, *beta.shape, 2)
        return Posterior(mean.T.reshape(shape), var.T.clamp_min(0).reshape(shape))
