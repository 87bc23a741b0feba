"""Where the free surface is: its height learned with the maps (``offset``: ``SurfaceOffset`` and the front
functions the front door calls with itself, fitted by the marginal likelihood through the segment depths) and the
likelihood profiled over a range of heights (``profile``)."""

from .offset import SurfaceOffset

__all__ = ["SurfaceOffset"]
