"""What to measure next: probe scores (information gain, integrated variance), greedy and
gradient-based gait/toe design. Uses ``gp`` through a backend's posterior interface
(``posterior``, ``cross_covariance``, ``block_covariance``, ``posterior_root``, ``condition``; like
botorch's acquisition/ and optim/ on a model's posterior) and ``make_backend`` to score in another
space; neither ``gp`` nor ``rft`` imports it."""

from .footholds import Stance, foothold_scores, force_field, plan_footholds, plan_stances
from .greedy import DesignStep, greedy_design
from .optimize import DesignedProbe, default_spec, optimize_probe
from .scoring import MixtureScorer, ProbeScorer, Region, force_relative
from .scoring3d import ProbeScorer3D

__all__ = ["ProbeScorer", "ProbeScorer3D", "MixtureScorer", "Region",
           "DesignStep", "greedy_design", "force_relative", "optimize_probe",
           "DesignedProbe", "default_spec", "Stance", "force_field", "foothold_scores", "plan_footholds",
           "plan_stances"]
