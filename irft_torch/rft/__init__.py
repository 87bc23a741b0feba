"""Forward granular Resistive Force Theory: physics only, no inference.

Stress maps (``FourierStressMap``), toes (``IToe``, ``CToe``, ``PolylineToe``), paths
(``rectangle_path``, ``spline_path``, ``rotating_leg_path``, ``pose_path``), contact kinematics
(``contacts`` -> ``Contacts``), forward forces (``forces``) and probes (``Probe``, ``ProbeBounds``,
``random_probes``).
"""

from .contacts import M_TO_CM, Contacts, SegmentKinematics, contacts, segment_kinematics
from .forces import forces, segment_forces
from .paths import Path, course_path, pose_path, rectangle_path, rotating_leg_path, spline_path
from .probes import Probe, ProbeBounds, random_probes
from .stress_maps import FourierStressMap, mirror_to_canonical
from .toes import CToe, IToe, PolylineToe, Toe

__all__ = [
    "FourierStressMap", "mirror_to_canonical",
    "Toe", "IToe", "CToe", "PolylineToe",
    "Path", "rectangle_path", "spline_path", "course_path", "rotating_leg_path", "pose_path",
    "Contacts", "SegmentKinematics", "contacts", "segment_kinematics", "M_TO_CM",
    "forces", "segment_forces",
    "Probe", "ProbeBounds", "random_probes",
]
