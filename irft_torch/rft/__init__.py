"""Forward granular Resistive Force Theory: physics only, no inference.

Stress maps (``FourierStressMap``), toes (``IToe``, ``CToe``, ``PolylineToe``), paths
(``rectangle_path``, ``spline_path``, ``rotating_leg_path``, ``pose_path``), contact kinematics
(``contacts`` -> ``Contacts``), forward forces (``forces``) and probes (``Probe``, ``ProbeBounds``,
``random_probes``); over changing ground: fields of media (``TerrainField``) and a walk's stances
(``footholds``, ``walk`` -> ``Walk``);
in 3-D: bodies (``Mesh``, ``wheel_mesh``, ``read_mesh``), contacts (``contacts_3d`` ->
``Contacts3D``, ``planar_motion``) and forces (``forces_3d``).
"""

from .contacts import M_TO_CM, Contacts, SegmentKinematics, contacts, segment_kinematics
from .contacts3d import Contacts3D, contacts_3d, element_kinematics, planar_motion
from .forces import forces, segment_forces
from .forces3d import forces_3d
from .mesh import Mesh, read_mesh, wheel_mesh
from .paths import Path, course_path, pose_path, rectangle_path, rotating_leg_path, spline_path
from .probes import Probe, ProbeBounds, random_probes
from .stress_maps import FourierStressMap, mirror_to_canonical
from .terrain import TerrainField
from .toes import CToe, IToe, PolylineToe, Toe
from .walks import Walk, footholds, walk

__all__ = [
    "FourierStressMap", "mirror_to_canonical",
    "Toe", "IToe", "CToe", "PolylineToe",
    "Path", "rectangle_path", "spline_path", "course_path", "rotating_leg_path", "pose_path",
    "Contacts", "SegmentKinematics", "contacts", "segment_kinematics", "M_TO_CM",
    "forces", "segment_forces",
    "Probe", "ProbeBounds", "random_probes",
    "TerrainField", "Walk", "footholds", "walk",
    "Mesh", "wheel_mesh", "read_mesh", "Contacts3D", "contacts_3d", "element_kinematics", "planar_motion", "forces_3d",
]
