"""irft_torch: Inverse Resistive Force Theory in PyTorch / GPyTorch.

    import irft_torch as irft
    smap = irft.rft.FourierStressMap.generic()
    contacts = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path())
    forces = irft.rft.forces(smap, contacts)
"""

from . import gp, hardware, metrics, rft
from .gp import InverseRFT, Posterior

__version__ = "0.1.0"
__all__ = ["rft", "gp", "hardware", "metrics", "InverseRFT", "Posterior", "__version__"]
