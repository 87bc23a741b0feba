r"""Parallel environments' terrain estimates averaged over a model's hyperparameter draws, each draw weighed
by each environment's own samples (``TerrainFilterMixture``).

A model fitted with ``hyper_posterior="laplace"`` (or ``"nuts"``, or ``MapPrior(mean="average")``) predicts with a
mixture over draws theta_s of weights w_s (``gp.hyper.mixture``). ``TerrainFilter`` keeps one environment's posterior at
one set of hyperparameters (the mode); this keeps one ``TerrainFilter`` per draw, and weighs the draws per
environment b by the evidence of that environment's samples y_b (its window's, with ``window``):

    w_{b,s} = w_s p(y_b | theta_s) / sum_s' w_s' p(y_b | theta_s'),
    log p(y_b | theta_s) = sum_a [ -|z_{b,a}|^2 / 2 + sum_i log U_{b,a,ii} - n_b log(2 pi) / 2 ]

with each draw's filter state z = U (y - m), U = L^{-1} (``terrain_filter``): the log marginal likelihood of the
samples held, exact at every step (also after the window forgets, since U and z are kept exactly). With weights
per map (S, 2) (an averaged prior mean) each map's weights are updated by that map's term alone. So an
environment whose sand is softer than the training data's moves its weight to the draws that explain it.

Each environment's ``stress_map`` and ``predict_forces`` are then its mixture: mean sum_s w_{b,s} mu_s, total
variance, and ``Posterior.interval`` from the mixture's CDF (``components`` with weights (S, B, 1, 2)).
``tests/gp/test_terrain_mixture.py`` checks it against each draw's dense posterior and evidence.

Cost: S filters (S = the model's draws, 16 by default): S times ``TerrainFilter``'s memory and time.
"""

from __future__ import annotations

import math
from typing import cast

import torch
from torch import Tensor, nn

from ...rft.contacts import Contacts
from ..model import InverseRFT
from ..posterior import Posterior
from .filter import TerrainFilter

__all__ = ["TerrainFilterMixture"]


class TerrainFilterMixture(nn.Module):
    r"""B streaming posteriors of the stress maps, one per environment, each a mixture over the model's
    hyperparameter draws weighed by the environment's own samples (module docstring).

    Args:
        model: a fitted ``InverseRFT``; its draws (``model.hyper_posterior``, or the averaged prior means) and
            their weights are copied. A plug-in model has one draw: the same numbers as ``TerrainFilter``.
        n_envs: B, the number of environments.
        window: keep each environment's last ``window`` samples (None: all since its last ``reset``).
        capacity: initial room for samples per environment without a window.
        block_bytes: CPU only: the working set per block of environments (``TerrainFilter``'s).

    Attributes:
        filters: one ``TerrainFilter`` per draw (S).
        prior_log_weights: (S, 2) log w_s, per map.

    Example:
        >>> model = irft.InverseRFT(c, f).fit()  # Li et al.'s term and the Laplace posterior: the default
        >>> filt = irft.gp.TerrainFilterMixture(model, n_envs=256, window=16)
        >>> filt.update(contacts, forces)                  # (B, M), (B, 2)
        >>> post = filt.stress_map(beta, gamma)            # mixture per environment; post.interval(0.95)
        >>> filt.weights                                   # (B, S, 2): each environment's weight of each draw
    """

    prior_log_weights: Tensor  # (S, 2), a buffer

    def __init__(self, model: InverseRFT, n_envs: int, window: int | None = None, capacity: int = 32,
                 block_bytes: int = 32 << 20) -> None:
        super().__init__()
        if not isinstance(model, InverseRFT):
            raise TypeError(f"model must be an irft_torch.InverseRFT (fitted), got {type(model).__name__}")
        backends, w = model._weighted_backends()
        S = len(backends)
        self.per_map = w is not None and w.ndim == 2  # weights per map (averaged prior means): updated per map
        w = torch.ones(1, 2) if w is None else w.detach()
        w = w[:, None].expand(S, 2) if w.ndim == 1 else w
        self.filters = nn.ModuleList([TerrainFilter(model, n_envs, window, capacity, block_bytes, hypers=b.hypers)
                                      for b in backends])
        ref = self._each()[0]
        self.register_buffer("prior_log_weights", w.to(dtype=ref.dtype, device=ref.device).clamp_min(0).log())
        self.n_envs, self.window, self.dtype, self.device = n_envs, window, ref.dtype, ref.device

    def _each(self) -> list[TerrainFilter]:
        return cast("list[TerrainFilter]", list(self.filters))

    @property
    def n_draws(self) -> int:
        return len(self.filters)

    def extra_repr(self) -> str:
        return f"n_draws={self.n_draws}, " + self._each()[0].extra_repr()

    # ---- the weights --------------------------------------------------------------------------------
    def log_evidence(self) -> Tensor:
        """(B, S, 2) log p(y_{b,a} | theta_s): each environment's samples held, per draw and map (0 for none)."""
        out = []
        for f in self._each():
            n = f.count.to(f.dtype)[:, None]  # (B, 1): the samples held (both maps)
            logdet = torch.diagonal(f.U, dim1=-2, dim2=-1).log().sum(-1)  # (B, 2): sum log U_ii (1 past them)
            out.append(-0.5 * f.z.pow(2).sum(-1) + logdet - 0.5 * n * math.log(2 * math.pi))
        return torch.stack(out, 1)

    @property
    def weights(self) -> Tensor:
        """(B, S, 2) each environment's posterior weight of each draw, per map (summing to 1 over S)."""
        with torch.no_grad():
            ev = self.log_evidence()
            if not self.per_map:  # one weight per draw: the maps' evidence together
                ev = ev.sum(-1, keepdim=True).expand_as(ev)
            return torch.softmax(self.prior_log_weights[None] + ev, dim=1)

    def _mixture(self, posts: list[Posterior]) -> Posterior:
        means = torch.stack([p.mean for p in posts])  # (S, B, ..., 2)
        variances = torch.stack([p.variance for p in posts])
        w = self.weights.permute(1, 0, 2)  # (S, B, 2)
        w = w.reshape(w.shape[0], w.shape[1], *([1] * (means.ndim - 3)), 2)
        return Posterior.mixture(means, variances, w)

    # ---- what a TerrainFilter does ---------------------------------------------------------------------
    @torch.no_grad()
    def update(self, contacts: Contacts, forces, mask=None, locations=None) -> TerrainFilterMixture:
        """Add samples to every draw's filter (``TerrainFilter.update``; ``locations`` for a spatial model). Returns
        self."""
        for f in self._each():
            f.update(contacts, forces, mask, locations)
        return self

    @torch.no_grad()
    def reset(self, env_ids=None) -> TerrainFilterMixture:
        """Return environments to the prior, and their draws to the model's weights. Returns self."""
        for f in self._each():
            f.reset(env_ids)
        return self

    def stress_map(self, beta, gamma, locations=None) -> Posterior:
        """Each environment's mixture posterior of (alpha_x, alpha_z) at angles of broadcast shape S (rad): mean
        and total variance (B, *S, 2) (a spatial model's ``locations``: as ``TerrainFilter.stress_map``),
        ``interval`` from the mixture's CDF."""
        return self._mixture([f.stress_map(beta, gamma, locations) for f in self._each()])

    def predict_forces(self, contacts: Contacts, include_noise: bool = False, locations=None) -> Posterior:
        """Each environment's mixture posterior of the forces on its own contacts (B, T, M) (at ``locations`` (B, T,
        2) m, a spatial model): (B, T, 2) in N."""
        return self._mixture([f.predict_forces(contacts, include_noise, locations) for f in self._each()])
