"""Old import paths kept for one release: each old module is a small shim that warns once, at
import, and forwards every name to the module that now holds it (``moved``)."""

from __future__ import annotations

import warnings
from types import ModuleType

REMOVED_IN = "0.4"


def moved(old: str, new: ModuleType, **elsewhere):
    """Warn that module ``old`` moved to ``new`` (a ``DeprecationWarning`` attributed to the line that
    imported ``old``: ``warnings`` skips importlib's own frames, so Python shows it there by default)
    and return a module ``__getattr__`` and ``__dir__`` that forward to ``new`` (and the names in
    ``elsewhere``, which moved to another module, to the objects given)."""
    warnings.warn(f"{old} moved to {new.__name__}; import it from there ({old} goes in {REMOVED_IN})",
                  DeprecationWarning, stacklevel=3)  # 1: here, 2: the shim, 3: its importer

    def __getattr__(name: str):
        if name in elsewhere:
            return elsewhere[name]
        return getattr(new, name)

    def __dir__() -> list[str]:
        return sorted({*dir(new), *elsewhere})

    return __getattr__, __dir__
