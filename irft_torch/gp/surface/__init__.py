"""Where the free surface is: its height learned with the maps (``offset``: ``SurfaceOffset`` and the front
door's ``LearnedSurfaceMixin``, fitted by the marginal likelihood through the segment depths) and the
likelihood profiled over a range of heights (``profile``)."""

from .offset import LearnedSurfaceMixin, SurfaceOffset

__all__ = ["LearnedSurfaceMixin", "SurfaceOffset"]
