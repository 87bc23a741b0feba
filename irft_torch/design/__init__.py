"""What to measure next: probe scores (information gain, integrated variance), greedy and
gradient-based gait/toe design, for the planar and the 3-D model alike. Uses ``gp`` through a backend's posterior
interface (``candidate_rows``, ``region_rows``, ``map_moments``, ``posterior_root``, ``condition``; like
botorch's acquisition/ and optim/ on a model's posterior) and ``make_backend`` to score in another
space; neither ``gp`` nor ``rft`` imports it."""

from .footholds import Stance, foothold_scores, force_field, plan_footholds, plan_stances
from .greedy import DesignStep, greedy_design
from .optimize import DesignedProbe, default_spec, optimize_probe
from .scoring import MixtureScorer, ProbeScorer, ProbeScorer3D, Region, force_relative

__all__ = ["ProbeScorer", "ProbeScorer3D", "MixtureScorer", "Region",
           "DesignStep", "greedy_design", "force_relative", "optimize_probe",
           "DesignedProbe", "default_spec", "Stance", "force_field", "foothold_scores", "plan_footholds",
           "plan_stances"]
