"""Where to step next: footholds scored by what a stance there would teach about the maps over a region of the
ground, and a greedy planner that picks the next footholds (and strokes, from a gait library) within a reach (a
model fitted with places, ``InverseRFT(..., locations=)``).

A candidate stance is one stroke (contacts (T, M) and each sample's offset (T, 2) m from its foothold) placed at a
candidate foothold p. Its score is the expected fall of the maps' posterior variance over the region of interest,
summed over the region's angles (a ``Region``) and places (L, 2) m, both maps, each divided by its prior variance:

    score(p) = sum_a sum_q [S_qc (S_cc + noise)^-1 S_cq]_qq / prior_a / (N_angles L),

exact at one set of hyperparameters (the backend's posterior covariances; a Gaussian's variance does not depend on
the forces measured, so a planned stance is conditioned on without them). 0: nothing learned; 1: the region known
exactly. A model with a hyperparameter posterior (``hyper_posterior="laplace"``, the default) is scored at its mode;
``draws=True`` scores the weighted average of its draws' scores instead, the weights held (as ``design.MixtureScorer``
and botorch's fully Bayesian acquisitions average), at S times the cost for S draws or more. Measured
(``explore_footholds.py --gaits 3 --refit-every 4 --greedy-draws``, seeds 0-4, 16 draws): held-out map RMSE 0.091 /
0.076 / 0.073 N/cm^3 after 4 / 8 / 12 stances averaged over the draws, 0.090 / 0.075 / 0.074 at the mode, so the mode
is the default (``experiments/benchmarks/bench_footholds.py``: 0.24 s a step against 4.4 s). Choose ``draws=True``
where the hyperparameters are not refitted as the walk goes on: held at the first fit (seeds 40-44, no refit)
0.095 / 0.108 / 0.101 against 0.116 / 0.112 / 0.125 at the mode.

One stroke's candidates are scored together (``SpatialBackend.placed_covariances``): a foothold moves the places
only, so the angles' part of every covariance is formed once per stroke (the candidates in chunks of
``SCORE_ELEMENTS`` numbers, memory bounded whatever their number).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..rft.contacts import Contacts, check_locations
from .belief import variance_fall
from .region import Region

__all__ = ["Stance", "force_field", "foothold_scores", "plan_footholds", "plan_stances"]


@dataclass(frozen=True)
class Stance:
    """One stroke to place at footholds: ``contacts`` (T, M) and each sample's ``offsets`` (T, 2) m from the
    foothold (a drag moves along the heading; ``rft.walk`` of one foothold at the origin gives both)."""

    contacts: Contacts
    offsets: Tensor

    def __post_init__(self) -> None:
        if tuple(self.offsets.shape) != (len(self.contacts), 2):
            raise ValueError(f"offsets must be (T, 2) m, one place per sample of the stroke's {len(self.contacts)}, "
                             f"got shape {tuple(self.offsets.shape)}")

    @classmethod
    def of_stroke(cls, toe, stroke, heading: float = 0.0) -> Stance:
        """The stroke of ``toe`` (``rft.Path``) walked at heading ``heading`` rad, samples out of contact dropped."""
        from ..rft.walks import walk

        w = walk(toe, stroke, torch.zeros(1, 2, dtype=torch.float64), torch.tensor([float(heading)]))
        keep = (w.contacts.weight_x != 0).any(-1) | (w.contacts.weight_z != 0).any(-1)
        return cls(w.contacts[keep], w.locations[keep])

    def at(self, foothold: Tensor) -> Contacts:
        """The stance's contacts placed at ``foothold`` (2,) m."""
        return self.contacts.with_locations(foothold.to(self.offsets) + self.offsets)


def force_field(model, stance: Stance, places, include_noise: bool = False):
    """A planner's field: the forces (N) of ``stance`` placed at each of ``places`` (L, 2) m, predicted by a
    model fitted with places: a ``Posterior`` with mean and variance (L, T, 2) (each sample of the stroke, F_x and
    F_z), ``.interval(0.95)`` its band. ``include_noise``: a measurement's spread rather than the force's."""
    if not getattr(model, "spatial", False):
        raise ValueError("model: a force field needs a model fitted with places (InverseRFT(..., locations=))")
    where = check_locations(places, name="places").to(model.dtype)
    if where.ndim != 2:
        raise ValueError(f"places must be (L, 2) m, got shape {tuple(where.shape)}")
    L = where.shape[0]
    c = Contacts(**{k: v.to(model.dtype).expand(L, *v.shape) for k, v in stance.contacts.as_dict().items()})
    return model.predict_forces(c, include_noise=include_noise,
                                locations=where[:, None, :] + stance.offsets.to(where)[None])


def _region_setup(model, places, region: Region | None) -> tuple[Tensor, Contacts, Tensor]:
    """(places (L, 2) m, the region's angles at each place as point queries, their weights (N L,)) on the model's
    device and dtype; ``region`` default ``Region.square(8)``."""
    where = check_locations(places, name="places").to(model._device, model.dtype)
    if where.ndim != 2:
        raise ValueError(f"places must be (L, 2) m, got shape {tuple(where.shape)}")
    region = region or Region.square(8, dtype=model.dtype)
    queries = _region_queries(region, where).to(dtype=model.dtype, device=model._device)
    weights = region.weight.to(model._device, model.dtype).repeat(where.shape[0]) / where.shape[0]
    return where, queries, weights


def _region_queries(region: Region, places: Tensor) -> Contacts:
    c = region.contacts()
    N, L = len(c), places.shape[0]
    return Contacts(**{k: v.repeat(L, 1) for k, v in c.as_dict().items()},
                    locations=places.to(c.beta).repeat_interleave(N, 0))


#: foothold scores are formed this many numbers (footholds x 2 maps x (queries + training samples) x stroke samples)
#: at a time: a planner's footholds in a few batches, its memory bounded whatever the number of candidates
SCORE_ELEMENTS = 2**21


def _belief(model, draws: bool = False) -> tuple[list, Tensor]:
    """The backends a score averages over and their weights (S,) or (S, 2) per map: the model's hyperparameter
    draws (``hyper_posterior="laplace"``, the default) where ``draws``, else its mode's backend with weight 1."""
    backends, weights = model._weighted_backends() if draws else ([model.backend], None)
    if weights is None:
        return backends, torch.ones(1, dtype=model.dtype, device=model._device)
    return backends, weights


def _scores(backend, queries: Contacts, weights: Tensor, stance: Stance, footholds: Tensor) -> Tensor:
    """(P, 2) each map's score of ``stance`` at each of ``footholds`` (P, 2) m, at one backend's hyperparameters."""
    c = stance.contacts.to(dtype=queries.beta.dtype, device=queries.beta.device)
    if len(c) == 0 or len(footholds) == 0:  # a stroke that never touches teaches nothing
        return queries.beta.new_zeros(len(footholds), 2)
    offsets = stance.offsets.to(queries.beta)
    noise = backend.hypers.noise.detach()
    prior = backend.hypers.prior_variance.detach()
    out = []
    for S_qc, S_cc in backend.placed_covariances(queries, c, offsets, footholds,
                                                 SCORE_ELEMENTS // (2 * (len(queries) + backend.n_samples) * len(c))):
        fall = variance_fall(S_qc.mT, S_cc, noise[:, None])  # (P, 2, Q)
        out.append((fall * weights).sum(-1) / prior)
    return torch.cat(out)


def _averaged(backends, draw_weights: Tensor, queries, weights, stance, footholds) -> Tensor:
    """(P,) the scores averaged over the backends (weights (S,) or (S, 2) per map), then over the two maps."""
    per_map = torch.stack([_scores(b, queries, weights, stance, footholds) for b in backends])  # (S, P, 2)
    w = draw_weights[:, None, None] if draw_weights.ndim == 1 else draw_weights[:, None, :]
    return (w.to(per_map) * per_map).sum(0).mean(-1)


def foothold_scores(model, stance: Stance, candidates, places, region: Region | None = None,
                    draws: bool = False) -> Tensor:
    """Scores (K,) of a stance at each candidate foothold (K, 2) m for the maps over ``places`` (L, 2) m and the
    angles of ``region`` (default ``Region.square(8)``) (module docstring). ``model``: a fitted ``InverseRFT``
    with places, scored at its mode's hyperparameters; ``draws=True``: averaged over its hyperparameter draws
    where it has them."""
    if not getattr(model, "spatial", False):
        raise ValueError("model: foothold scores need a model fitted with places (InverseRFT(..., locations=))")
    cand = check_locations(candidates, name="candidates").to(model._device, model.dtype)
    if cand.ndim != 2:
        raise ValueError(f"candidates must be (K, 2) places in m, got shape {tuple(cand.shape)}")
    _, queries, weights = _region_setup(model, places, region)
    backends, draw_weights = _belief(model, draws)
    with torch.no_grad():
        return _averaged(backends, draw_weights, queries, weights, stance, cand)


def plan_footholds(model, stance: Stance, start, n_steps: int, reach: float, candidates, places,
                   region: Region | None = None, draws: bool = False) -> Tensor:
    """The next ``n_steps`` footholds (n_steps, 2) m, greedily: from ``start`` (2,) m, each step the candidate
    (K, 2) m within ``reach`` m of the last foothold with the highest score (``foothold_scores``) given the
    stances planned before it (conditioned on, every draw's backend, with the hyperparameters fixed). A step with
    no candidate in reach raises ``ValueError`` naming ``reach``. ``draws``: as ``foothold_scores``.
    ``plan_stances`` also chooses among strokes."""
    return plan_stances(model, [stance], start, n_steps, reach, candidates, places, region, draws)[0]


def plan_stances(model, stances, start, n_steps: int, reach: float, candidates, places,
                 region: Region | None = None, draws: bool = False) -> tuple[Tensor, Tensor]:
    """``plan_footholds`` over a gait library: each step the (foothold, stroke) pair with the highest score, the
    footholds (K, 2) m within ``reach`` of the last, the strokes ``stances`` (a sequence of ``Stance``; a stroke
    that sees angles the maps are unsure of scores higher). Returns (footholds (n_steps, 2) m, the index of each
    step's stroke in ``stances`` (n_steps,))."""
    if int(n_steps) != n_steps or n_steps < 1:
        raise ValueError(f"n_steps must be a positive integer, got {n_steps!r}")
    if not (reach > 0):
        raise ValueError(f"reach must be a positive distance in m, got {reach}")
    if not getattr(model, "spatial", False):
        raise ValueError("model: planning footholds needs a model fitted with places (InverseRFT(..., locations=))")
    if isinstance(stances, Stance):
        raise TypeError("stances: a sequence of design.Stance (plan_footholds takes one)")
    stances = list(stances)
    if not stances or not all(isinstance(s, Stance) for s in stances):
        raise TypeError("stances: a non-empty sequence of design.Stance")
    cand = check_locations(candidates, name="candidates").to(model._device, model.dtype)
    _, queries, weights = _region_setup(model, places, region)
    here = check_locations(start, name="start").to(model._device, model.dtype).reshape(2)
    (backends, draw_weights), plan, chosen = _belief(model, draws), [], []
    with torch.no_grad():
        for step in range(int(n_steps)):
            near = ((cand - here).norm(dim=-1) <= reach).nonzero()[:, 0]
            if len(near) == 0:
                raise ValueError(f"reach: no candidate foothold within {reach} m of {here.tolist()}")
            scores = torch.stack([_averaged(backends, draw_weights, queries, weights, s, cand[near])
                                  for s in stances])  # (n_stances, n_near)
            best = int(scores.argmax())
            k, here = best // len(near), cand[near[best % len(near)]]
            plan.append(here)
            chosen.append(k)
            if step + 1 < n_steps:  # the next step knows this stance (any forces: the variance does not see them)
                placed = stances[k].at(here).to(dtype=model.dtype, device=model._device)
                backends = [b.condition(placed, placed.beta.new_zeros(len(placed), 2)) for b in backends]
    return torch.stack(plan), torch.tensor(chosen, device=plan[0].device)
