"""Old import paths kept for one release: each old module is a small shim that warns once, at
import, and forwards every name to the module that now holds it (``moved``)."""

from __future__ import annotations

import sys
import warnings
from types import ModuleType

REMOVED_IN = "0.4"


def moved(old: str, new: ModuleType, **elsewhere):
    """Warn that module ``old`` moved to ``new`` (a ``DeprecationWarning`` attributed to the line that
    imported ``old``, past importlib's frames, so that Python shows it there by default) and return a
    module ``__getattr__`` and ``__dir__`` that forward to ``new`` (and the names in ``elsewhere``, which
    moved to another module, to the objects given)."""
    frame, level = sys._getframe(2), 3  # 1: this function, 2: the shim's body, 3: whoever imported it
    while frame is not None and ("importlib" in frame.f_code.co_filename or frame.f_code.co_filename == "<frozen "
                                 "importlib._bootstrap>"):
        frame, level = frame.f_back, level + 1
    warnings.warn(f"{old} moved to {new.__name__}; import it from there ({old} goes in {REMOVED_IN})",
                  DeprecationWarning, stacklevel=level)

    def __getattr__(name: str):
        if name in elsewhere:
            return elsewhere[name]
        return getattr(new, name)

    def __dir__() -> list[str]:
        return sorted({*dir(new), *elsewhere})

    return __getattr__, __dir__
