"""The package's version: from the installed metadata (``importlib.metadata``) when that metadata is
of this copy of the package, else from the ``pyproject.toml`` of the source tree it was imported from
(a checkout run without installing it, or beside an editable install of another checkout)."""

from __future__ import annotations

import json
import re
from importlib import metadata
from pathlib import Path
from urllib.parse import unquote, urlparse

DISTRIBUTION = "irft-torch"
UNKNOWN = "0+unknown"


def _editable_root(dist: metadata.Distribution) -> Path | None:
    """The source tree an editable install points at (PEP 610 ``direct_url.json``), else None."""
    text = dist.read_text("direct_url.json")
    if not text:
        return None
    info = json.loads(text)
    if not info.get("dir_info", {}).get("editable"):
        return None
    url = urlparse(info.get("url", ""))
    return Path(unquote(url.path)) if url.scheme == "file" else None


def version_from_pyproject(pyproject: Path) -> str | None:
    """``[project] version`` of a ``pyproject.toml`` (None if the file or the field is missing)."""
    if not pyproject.is_file():
        return None
    text = pyproject.read_text()
    project = re.search(r"^\[project\]\s*$(.*?)(?=^\[|\Z)", text, re.M | re.S)
    found = re.search(r'^version\s*=\s*"([^"]+)"', project.group(1), re.M) if project else None
    return found.group(1) if found else None


def package_version(package_dir: Path) -> str:
    """The version of the package in ``package_dir`` (the folder holding its ``__init__.py``)."""
    source_root = package_dir.resolve().parent
    try:
        dist = metadata.distribution(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        dist = None
    if dist is not None:
        editable = _editable_root(dist)
        if editable is None or editable.resolve() == source_root:
            return dist.version
    return version_from_pyproject(source_root / "pyproject.toml") or UNKNOWN
