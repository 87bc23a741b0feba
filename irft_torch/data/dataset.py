"""The dataset file format: what the inference takes (``Dataset``: contacts, forces, time, the toe
path) and its ``.npz`` file (``save_dataset``, ``load_dataset``; ``irft ingest`` and ``irft
simulate`` write it, ``irft fit`` reads it), with a short printable summary.

It sits below ``hardware`` and ``gp`` (it imports only ``rft``): the hardware pipeline builds a
``Dataset`` (``hardware.build_dataset``), the command line fits one; ``hardware`` re-exports these
names.
"""

from __future__ import annotations

import threading
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._files import atomic_write
from ..rft.contacts import SURFACE_FIELDS, Contacts

# numpy reads each array's header with ast.literal_eval, which CPython 3.11 can get wrong when two threads parse
# at once ("SystemError: AST constructor recursion depth mismatch", python/cpython#106905): Dask's threaded
# workers load several datasets at a time (studies.fleet). One file is read at a time in a process.
_NPY_LOCK = threading.Lock()

__all__ = ["Dataset", "dataset_summary", "save_dataset", "load_dataset", "STATISTICS_PREFIX"]


@dataclass
class Dataset:
    """What the inference model takes: contacts (T, M), forces (T, 2) N, time (T,) s, and the toe
    path (T, 2) m (world frame) for plots. ``statistics``: optional named arrays saved with the data
    (the inference side's sufficient statistics, ``gp.statistics``; opaque here). ``locations``: optional
    (T, 2) m, each sample's horizontal place on the ground (a walk over changing terrain: ``rft.walks``)."""

    contacts: Contacts
    forces: torch.Tensor
    time: torch.Tensor
    toe_position: torch.Tensor
    statistics: dict | None = None
    locations: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.contacts)


def dataset_summary(ds: Dataset, masked: dict | None = None, n_before: int | None = None) -> list[str]:
    """Short printable lines: duration [s], samples, time in contact (steps over masked stretches
    longer than 3 sampling intervals count 3: a gap is not contact), toe depth range [m], force range
    [N] per axis, and the masked samples with their reasons."""
    t = ds.time.numpy()
    f = ds.forces.numpy()
    z = ds.toe_position[:, 1].numpy()
    contact = (ds.contacts.weight_z != 0).any(1).numpy()
    dt = np.diff(t)
    dur = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    # a step longer than 3 sampling intervals spans masked samples (a gap): what happened there is not known
    dt = np.minimum(dt, 3 * float(np.median(dt))) if len(dt) else dt
    contact_s = float(np.sum(np.where(contact[1:] | contact[:-1], dt, 0.0))) if len(t) > 1 else 0.0
    lines = [
        f"duration {dur:.2f} s, {len(ds)} samples x {ds.contacts.n_segments} segments"
        + (f" (of {n_before})" if n_before is not None and n_before != len(ds) else ""),
        f"in contact {contact_s:.2f} s ({100 * contact.mean():.0f} % of samples), toe reference depth "
        f"{max(0.0, -z.max()):.3f} to {max(0.0, -z.min()):.3f} m",
        f"force F_x {f[:, 0].min():.3g} to {f[:, 0].max():.3g} N, F_z {f[:, 1].min():.3g} to {f[:, 1].max():.3g} N",
    ]
    if masked:
        lines.append("masked: " + "; ".join(f"{v} {k}" for k, v in masked.items()))
    else:
        lines.append("masked: none")
    return lines


STATISTICS_PREFIX = "statistics."


def save_dataset(path, ds: Dataset, **meta) -> Path:
    """npz with beta, gamma, weight_x, weight_z (T, M) (and depth, area_x, area_z where the contacts
    carry them), forces (T, 2), time, toe_position, locations (T, 2) where the dataset has them, meta,
    and ``ds.statistics`` (if any) as arrays
    named "statistics.<name>". ".npz" is appended when ``path`` lacks it; the file is written whole
    or not at all (a temporary file, fsynced, renamed into place: ``_files.atomic_write``). Returns the
    path written."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    arrays: dict[str, Any] = {k: v.detach().cpu().numpy() for k, v in ds.contacts.as_dict().items()}
    arrays.update({STATISTICS_PREFIX + k: np.asarray(v) for k, v in (ds.statistics or {}).items()})
    if ds.locations is not None:
        if tuple(ds.locations.shape) != (len(ds), 2):
            raise ValueError(f"locations must be ({len(ds)}, 2), one place per sample, got {tuple(ds.locations.shape)}")
        arrays["locations"] = ds.locations.detach().cpu().numpy()
    atomic_write(path, lambda fh: np.savez(fh, forces=ds.forces.numpy(), time=ds.time.numpy(),
                                          toe_position=ds.toe_position.numpy(), meta=np.array(repr(meta)), **arrays),
                 "dataset")
    return path


def load_dataset(path) -> Dataset:
    """Read a dataset written by ``save_dataset``; a damaged, truncated or foreign file raises
    ValueError saying so (never a zip or pickle traceback)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}")
    if path.is_dir():
        raise ValueError(f"{path} is a directory, not a dataset .npz")
    need = ("beta", "gamma", "weight_x", "weight_z", "forces", "time", "toe_position")
    with open(path, "rb") as fh:
        head = fh.read(30)
    if not head.startswith(b"PK"):  # not a zip: np.load would read it as a .npy or a pickle and say so
        raise ValueError(f"{path} is damaged or not an irft dataset (.npz from irft ingest): not an .npz (zip) "
                         f"archive; it starts with {head.decode('latin-1')[:30]!r}")
    try:
        with _NPY_LOCK, np.load(path, allow_pickle=False) as d:
            missing = set(need) - set(d.files)
            if missing:
                raise ValueError(f"{path} is not an irft dataset: missing {sorted(missing)}")
            arrays = {k: np.asarray(d[k]) for k in need}
            stats = {k[len(STATISTICS_PREFIX):]: np.asarray(d[k]) for k in d.files if k.startswith(STATISTICS_PREFIX)}
            # the signed depths and areas (a learned surface offset, docs/surface.md): optional, all three
            surface = [k for k in SURFACE_FIELDS if k in d.files]
            if surface and len(surface) != len(SURFACE_FIELDS):
                raise ValueError(f"{path} is damaged: it holds {surface} but not all of {list(SURFACE_FIELDS)}")
            arrays.update({k: np.asarray(d[k]) for k in surface})
            if "locations" in d.files:
                arrays["locations"] = np.asarray(d["locations"])
    except ValueError as e:
        if "not an irft dataset" in str(e):
            raise
        raise ValueError(f"{path} is damaged or not an irft dataset (.npz from irft ingest): {e}") from None
    except (zipfile.BadZipFile, EOFError, OSError, KeyError) as e:
        raise ValueError(f"{path} is damaged or not an irft dataset (.npz from irft ingest): "
                         f"{type(e).__name__}: {e}") from None
    T = len(arrays["forces"])
    shapes = {k: v.shape for k, v in arrays.items()}
    ok = (arrays["forces"].shape == (T, 2) and arrays["time"].shape == (T,) and arrays["toe_position"].shape == (T, 2)
          and all(arrays[k].ndim == 2 and arrays[k].shape[0] == T for k in need[:4] + tuple(surface))
          and len({arrays[k].shape for k in need[:4] + tuple(surface)}) == 1
          and ("locations" not in arrays or arrays["locations"].shape == (T, 2)))
    if not ok:
        raise ValueError(f"{path}: inconsistent array shapes {shapes}; the file is damaged")
    bad = [k for k, v in arrays.items() if not np.issubdtype(v.dtype, np.floating) or not np.isfinite(v).all()]
    if bad:
        raise ValueError(f"{path}: non-finite or non-numeric values in {bad}; the file is damaged")
    c = Contacts(**{k: torch.as_tensor(arrays[k]) for k in need[:4] + tuple(surface)})
    loc = torch.as_tensor(arrays["locations"]) if "locations" in arrays else None
    return Dataset(c, torch.as_tensor(arrays["forces"]), torch.as_tensor(arrays["time"]),
                   torch.as_tensor(arrays["toe_position"]), stats or None, loc)
