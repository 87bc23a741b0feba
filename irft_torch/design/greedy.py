"""Sequential design: pick probes one after another, each the best given the ones before (planar candidates
with a planar model's ``ProbeScorer`` or ``MixtureScorer``, ``rft.Contacts3D`` candidates with a 3-D model's)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from .region import Region, _as_contacts
from .scoring import MixtureScorer, ProbeScorer

__all__ = ["DesignStep", "greedy_design"]


@dataclass
class DesignStep:
    """One pick of ``greedy_design``: the candidate's index, its score when picked, and the
    integrated variance over the region once it is observed (the prior: 2 planar, 3 in 3-D; 0 = known)."""

    index: int
    score: float
    integrated_variance: float


def greedy_design(scorer: ProbeScorer | MixtureScorer, candidates: Sequence, budget: int,
                  criterion: str = "variance",
                  region: Region | None = None) -> list[DesignStep]:
    """Pick ``budget`` probes one after another, each the best given the ones before (the belief is
    conditioned on every pick; the posterior variance does not depend on the values). Neither the
    scorer nor any model is changed.

    With criterion "eig", the scores add up to the information of the whole sequence (chain rule).
    With fewer candidates than ``budget``, every candidate is picked (a warning says so).
    """
    if int(budget) != budget or budget < 0:
        raise ValueError(f"budget must be an integer >= 0, got {budget}")
    cands = [_as_contacts(c, scorer.three_d) for c in candidates]
    if budget > len(cands):
        warnings.warn(f"budget {budget} is more than the {len(cands)} candidate(s): the design has {len(cands)} "
                      f"step(s)", stacklevel=2)
    left = list(range(len(cands)))
    steps: list[DesignStep] = []
    current = scorer
    for _ in range(min(int(budget), len(cands))):
        j, score = current.rank([cands[i] for i in left], criterion, region)[0]
        idx = left.pop(j)
        current = current.condition(cands[idx])
        with torch.no_grad():
            iv = float(current.integrated_variance(region=region))
        steps.append(DesignStep(idx, score, iv))
    return steps
