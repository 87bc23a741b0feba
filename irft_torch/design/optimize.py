"""Gradient-based probe design: the path (and toe tilt) that teaches the most about the ground.

Contacts are differentiable in a ``course_path``'s knots (its direction of motion along the arc
length, and the toe's heading), and ``ProbeScorer`` scores are differentiable in the contacts, so
a probe of fixed length can be improved by gradient descent on its expected integrated map
variance (or its negative information gain). The workspace (``ProbeBounds``: depth, height, x
range, tilt) is a quadratic penalty during the descent; a step that raises the objective is undone
and the step size halved (so ``lr`` is an upper bound, not a setting to tune); the probe returned
is the best iterate that lies inside the workspace.

    from irft_torch.design import optimize_probe
    designed = optimize_probe(scorer, init=probe, bounds=ProbeBounds(max_depth=0.05))
    designed.probe, designed.score, designed.history

This package joins physics (``rft``) and inference (``gp``); neither imports it.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..rft.contacts import contacts
from ..rft.paths import course_path
from ..rft.probes import Probe, ProbeBounds
from ..rft.toes import Toe
from .scoring import ProbeScorer, Region

__all__ = ["DesignedProbe", "optimize_probe", "default_spec"]

_PENALTY_SCALE = 0.01  # m: an excursion of 1 cm outside the bounds costs `penalty` per sample (rms)


@dataclass
class DesignedProbe:
    """The result of ``optimize_probe``.

    Attributes:
        probe: the best probe found inside the bounds (its ``spec`` rebuilds it).
        score: its criterion value: integrated variance (lower is better) or information gain (nats).
        initial_score: the starting probe's.
        history: the objective (criterion + penalty, minimized) at every step.
        inside: whether ``probe`` lies inside the bounds (False only if no iterate did).
    """

    probe: Probe
    score: float
    initial_score: float
    history: list[float] = field(default_factory=list)
    inside: bool = True


def default_spec(length: float, bounds: ProbeBounds, n_knots: int = 8, n_steps: int = 100,
                 speed: float = 0.02) -> dict:
    """A plain starting probe: enter steeply near x_min, sweep toward +x half-way down the workspace."""
    lo, _ = bounds.x_range
    down = math.atan2(-bounds.max_depth / 2, 0.02)
    course = torch.zeros(n_knots, dtype=torch.float64)
    course[0] = down
    return dict(course=course, length=length, start=(lo + 0.02, 0.0), heading=0.0, n_steps=n_steps, speed=speed)


def optimize_probe(scorer: ProbeScorer, toe: Toe | None = None, init: Probe | None = None, *,
                   length: float | None = None, bounds: ProbeBounds | None = None, optimize_tilt: bool = True,
                   n_iter: int = 40, lr: float = 0.05, criterion: str = "variance", region: Region | None = None,
                   penalty: float = 10.0, name: str = "designed", progress: bool = False) -> DesignedProbe:
    """Improve a probe's course and tilt by Adam on its score, with fixed length and start.

    Args:
        scorer: the current belief (``ProbeScorer.from_model`` or ``.prior``).
        toe: the toe; default ``init.toe``.
        init: a starting probe made by ``Probe.from_course`` (e.g. the best of ``random_probes``);
            default ``default_spec(length, bounds)`` with ``toe``.
        length: path length, m (only without ``init``; a design keeps its start's length).
        bounds: the workspace (default ``ProbeBounds()``).
        optimize_tilt: also move the toe's heading knots.
        criterion: "variance" (integrated variance over ``region``) or "eig".
        penalty: weight of the bounds penalty (per 1 cm rms excursion).

    Returns:
        A ``DesignedProbe``; the best iterate inside the bounds (a warning if none was).
    """
    if criterion not in ("variance", "eig"):
        raise ValueError(f"criterion must be 'variance' or 'eig', got {criterion!r}")
    if criterion == "eig" and region is not None:
        raise ValueError("region applies to criterion 'variance' (the variance integrated over it); 'eig' is the "
                         "information about the probe's own forces: pass region=None")
    if int(n_iter) != n_iter or n_iter < 0 or not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"need n_iter >= 0 and lr > 0, got n_iter={n_iter}, lr={lr}")
    bounds = bounds or ProbeBounds()
    if init is not None:
        if init.spec is None:
            raise ValueError("init must be a probe made by Probe.from_course (it needs a spec to vary)")
        spec = dict(init.spec)
        toe = toe or init.toe
    else:
        if toe is None or length is None:
            raise ValueError("give init (a Probe), or toe and length")
        spec = default_spec(length, bounds)
    dtype = scorer.noise.dtype
    course = torch.as_tensor(spec.pop("course"), dtype=dtype).reshape(-1).clone().requires_grad_(True)
    heading = torch.as_tensor(spec.pop("heading", 0.0), dtype=dtype).reshape(-1).clone()
    heading.requires_grad_(optimize_tilt)
    params = [course] + ([heading] if optimize_tilt else [])

    def evaluate() -> tuple[Tensor, Tensor, Probe]:
        path = course_path(course, heading=heading, **spec)
        c = contacts(toe, path)
        value = scorer.integrated_variance(c, region) if criterion == "variance" else -scorer.information_gain(c)
        excess = bounds.violation(path) / (len(path) * _PENALTY_SCALE**2)
        return value, value + penalty * excess, Probe(toe, path, name)

    opt = torch.optim.Adam(params, lr=lr)
    history: list[float] = []
    best: tuple | None = None  # (value, course, heading, gradients) of the best iterate inside the bounds
    bar = tqdm(range(int(n_iter) + 1), desc="probe design", disable=not progress, leave=False)
    for step in bar:
        opt.zero_grad(set_to_none=True)
        value, objective, probe = evaluate()
        history.append(float(objective.detach()))
        if step == 0:
            initial = float(value.detach())
        better = bounds.contains(probe.path) and (best is None or float(value.detach()) < best[0])
        if not better and best is not None:
            # the step left the workspace or did not improve (Adam's first steps are ~lr per knot
            # whatever the gradient, and its momentum overshoots): from the best point again, with
            # half the step and fresh moments
            if step == n_iter:
                break
            with torch.no_grad():
                for p, v, g in zip(params, best[1], best[3]):
                    p.copy_(v)
                    p.grad = g.clone()
            for group in opt.param_groups:
                group["lr"] *= 0.5
            opt.state.clear()
            opt.step()
            continue
        if step == n_iter:
            if better:
                best = (float(value.detach()), [p.detach().clone() for p in params], None, None)
            break
        objective.backward()
        if better:
            best = (float(value.detach()), [p.detach().clone() for p in params], None,
                    [p.grad.detach().clone() for p in params])
        opt.step()
    bar.close()
    inside = best is not None
    if not inside:
        warnings.warn(f"no iterate of the design stayed inside {bounds}; returning the last one", stacklevel=2)
        best = (float(value.detach()), [p.detach().clone() for p in params])
    found = dict(zip(("course", "heading"), best[1]))
    found_heading = found.get("heading", heading.detach())
    final_spec = dict(spec, course=found["course"],
                      heading=found_heading if found_heading.numel() > 1 else float(found_heading))
    probe = Probe.from_course(toe, name, **final_spec)
    sign = 1.0 if criterion == "variance" else -1.0
    return DesignedProbe(probe, sign * best[0], sign * initial, history, inside)
