"""3-D I-RFT (issue 31): alpha_x, alpha_y and alpha_z learned from (F_x, F_y, F_z) through ``rft.contacts_3d``.

``InverseRFT3D`` (built by ``irft.InverseRFT`` when given a ``Contacts3D``), its block structure (``rows``), the
backends (``backends``: observations, pairs; ``spectral``; chosen by ``select``). Its hyperparameters and physical
priors are the planar modules' for K = 3 maps (``gp.kernels.hyperparameters.RFT3DHyperparameters``,
``gp.kernels.priors``). docs/inverse3d.md.
"""

from ..kernels.hyperparameters import RFT3DHyperparameters
from .backends import Backend3D, Observations3D, Pairs3D
from .model import InverseRFT3D, Posterior3D, point_contacts
from .rows import BLOCKS
from .select import make_backend_3d
from .spectral import Spectral3D

__all__ = ["InverseRFT3D", "Posterior3D", "point_contacts", "RFT3DHyperparameters", "BLOCKS", "Backend3D",
           "Observations3D", "Pairs3D", "Spectral3D", "make_backend_3d"]
