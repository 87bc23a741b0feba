"""Live on the robot: CAN frames in, an updated terrain estimate out after every stance, every frame logged
(``estimator.LiveEstimator``). Its pieces: the CAN intake (``intake``), the frames on one time base
(``resample``), the offline moving average done causally (``causal_filter``), stance onset and end (``stance``) and
what each stance publishes (``estimate``)."""

from .estimate import MAP_POINTS, NO_AIR, SCALE_DRAWS, UNNAMED, LiveEstimate
from .estimator import LiveEstimator

__all__ = ["LiveEstimator", "LiveEstimate", "MAP_POINTS", "UNNAMED", "NO_AIR", "SCALE_DRAWS"]
