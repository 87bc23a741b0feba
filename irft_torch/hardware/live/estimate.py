"""What the live estimator publishes after each stance (and on each status change): ``LiveEstimate``, one JSON
line each (``as_json``), and where its map summary is taken (``MAP_POINTS``)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = ["LiveEstimate", "MAP_POINTS", "SCALE_DRAWS", "UNNAMED", "NO_AIR"]

# where the map is summarised: a 9 x 9 grid over the canonical square (beta, gamma), rad
_B, _G = np.meshgrid(np.linspace(-np.pi / 2, np.pi / 2, 9, endpoint=False) + np.pi / 18,
                     np.linspace(-np.pi / 2, np.pi / 2, 9), indexing="ij")
MAP_POINTS = np.stack([_B.ravel(), _G.ravel()], -1)  # (81, 2)


@dataclass
class LiveEstimate:
    """What is published after each stance (and on each status change).

    Attributes:
        event: "stance" (a stance was processed), "status" (a fault or a recovery; ``message`` says
            what), "end" (the estimator stopped).
        stance: stances seen so far (1-based number of this one). used: whether it updated the model;
            why_unused: the reason when not.
        t_start, t_end: the stance's first and last sample, s (the bus's clock). samples: its samples.
        latency: wall-clock s from the arrival of the frames that closed the stance to this estimate.
        residual_rms: (2,) RMS of the stance's forces minus the model's prediction before the update, N.
        residual_z: RMS of those residuals over the predicted std (measurement noise included): ~1 when
            the model's intervals are right.
        scale, scale_std: (2,) the map as a multiple of Li et al.'s generic map (alpha_x, alpha_z): the
            average of map / generic map over ``MAP_POINTS``, each point weighted by its posterior precision,
            and that average's posterior std (exact for a plug-in model; a model averaging over hyperparameters:
            from ``SCALE_DRAWS`` maps drawn jointly, a fixed stream).
        map_mean, map_std: (81, 2) posterior mean and std at ``MAP_POINTS``, N/cm^3 (in the callback;
            the JSON line carries the summary).
        stale: True while a motor has sent nothing for ``stale_after`` s; staleness: the longest silence
            of the two motors now, s.
        frames, dropped: frames received, and frames the queue could not take (still logged).
        counts: what was dropped or masked, reason -> count. message: status text.
    """

    event: str
    stance: int = 0
    used: bool = False
    why_unused: str | None = None
    t_start: float = math.nan
    t_end: float = math.nan
    samples: int = 0
    latency: float = math.nan
    residual_rms: list = field(default_factory=lambda: [math.nan, math.nan])
    residual_z: float = math.nan
    scale: list = field(default_factory=lambda: [math.nan, math.nan])
    scale_std: list = field(default_factory=lambda: [math.nan, math.nan])
    map_mean: np.ndarray | None = None
    map_std: np.ndarray | None = None
    stale: bool = False
    staleness: float = 0.0
    frames: int = 0
    dropped: int = 0
    updates: int = 0
    counts: dict = field(default_factory=dict)
    message: str = ""

    def as_json(self) -> str:
        """One JSON object on one line (the map arrays left out; NaN written as null)."""
        d = {k: v for k, v in asdict(self).items() if k not in ("map_mean", "map_std")}
        return json.dumps(_finite(d), separators=(",", ":"))


def _finite(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


SCALE_DRAWS = 200  # joint map draws behind a mixture model's ``LiveEstimate.scale_std`` (Monte Carlo error ~5 %)
UNNAMED = "frames logged without their channel (the log format cannot hold it)"  # ``LiveEstimate.counts``
NO_AIR = "samples with no air-run force near the toe"  # the count's name in ``LiveEstimate.counts``
