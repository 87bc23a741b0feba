r"""Sufficient statistics of a recording: computed once, saved with it, merged across recordings.

A spectral model needs of its data only the Gram matrix of [Phi | y | g] in its Fourier basis
(``backends.weight_space.FeatureStatistics``; Phi the features of the composite rows, y the forces,
g the generic shape's forces for the physics mean). Those statistics

- add up over recordings (the statistics of a union are the sum), so a fleet's files are reduced
  one by one, in parallel processes (``irft fit --jobs``) or on other machines (docs/backends.md);
- are nested: the statistics in a basis of n harmonics contain those of every smaller basis
  (``restrict``), so one saved set serves every fit whose lengthscales need no more harmonics;
- are tied to the data they came from by a sha256 digest of the contacts and forces, checked when
  they are read back (statistics of other data are refused, never used).

Example:
    >>> stats = recording_statistics(ds.contacts, ds.forces)          # one pass, O(T M F + T F^2)
    >>> arrays = statistics_arrays(stats, ds.contacts, ds.forces)     # numpy arrays, e.g. for an .npz
    >>> back = statistics_from_arrays(arrays, ds.contacts, ds.forces) # None if they do not match
    >>> model = InverseRFT(ds.contacts, ds.forces, statistics=back)   # no pass over the data
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import torch
from torch import Tensor

from ..rft.contacts import Contacts
from .backends.spectral import restrict_statistics, spectral_statistics
from .backends.weight_space import FeatureStatistics
from .kernels.fourier import FourierBasis
from .kernels.means import GenericShapeMean
from .model_file import digest

__all__ = ["initial_basis", "recording_statistics", "restrict_statistics", "statistics_arrays",
           "statistics_from_arrays", "data_fingerprint", "FORMAT"]

FORMAT = 1  # version of the saved arrays
_KEYS = ("P", "b", "yy", "bg", "yg", "gg")


def initial_basis(lengthscale: float = 1.0, tol: float = 1e-7) -> FourierBasis:
    """The Fourier basis an ``InverseRFT(..., prior=MapPrior(lengthscale=...), engine=Engine(tol=...))`` starts
    its spectral backend in: the smallest whose kernel truncation error is <= ``tol`` at that lengthscale on every
    embedding dimension."""
    return FourierBasis.for_lengthscale(torch.full((2, 1, 4), float(lengthscale), dtype=torch.float64), tol)


def recording_statistics(contacts: Contacts, forces: Tensor, basis: FourierBasis | None = None,
                         lengthscale: float = 1.0, tol: float = 1e-7) -> FeatureStatistics:
    """Spectral sufficient statistics of one recording (contacts (T, M), forces (T, 2) in N, unit
    noise scale), with the generic shape's forces included so that they serve a zero-mean and a
    physics-mean model alike.

    Args:
        basis: the Fourier basis; default ``initial_basis(lengthscale, tol)``.
    """
    if not isinstance(contacts, Contacts) or contacts.beta.ndim != 2:
        raise ValueError("contacts must be an rft.Contacts of shape (T, M)")
    f = torch.as_tensor(forces, dtype=contacts.beta.dtype, device=contacts.beta.device)
    if f.shape != (len(contacts), 2):
        raise ValueError(f"forces must be (T, 2) = ({len(contacts)}, 2), got {tuple(f.shape)}")
    basis = basis or initial_basis(lengthscale, tol)
    mean = GenericShapeMean().to(dtype=contacts.beta.dtype, device=contacts.beta.device)
    stats = spectral_statistics(contacts, f, basis, mean)
    stats.meta["mean"] = "generic shape"
    return stats


def data_fingerprint(contacts: Contacts, forces: Tensor) -> str:
    """sha256 of the contacts and forces as float64 (hex): what saved statistics are checked against."""
    c = {k: v.to(torch.float64) for k, v in contacts.as_dict().items()}
    return digest({"contacts": c, "forces": torch.as_tensor(forces).to(torch.float64)})


def statistics_arrays(stats: FeatureStatistics, contacts: Contacts, forces: Tensor) -> dict[str, np.ndarray]:
    """The statistics as named numpy arrays (for an .npz beside the data they came from), with the
    data's fingerprint and the basis."""
    out = {k: getattr(stats, k).detach().cpu().numpy() for k in _KEYS}
    out["n"] = np.array(stats.n)
    out["meta"] = np.array(json.dumps({**stats.meta, "format": FORMAT,
                                       "data_sha256": data_fingerprint(contacts, forces)}))
    return out


def statistics_from_arrays(arrays: dict, contacts: Contacts | None = None, forces: Tensor | None = None,
                           source: str = "the saved statistics") -> FeatureStatistics | None:
    """Statistics back from ``statistics_arrays``. With ``contacts`` and ``forces`` given, statistics
    of other data (the arrays were edited, or the statistics belong to another file) are refused:
    a warning naming ``source`` and None (recompute them); a damaged set raises ValueError."""
    try:
        meta = json.loads(str(np.asarray(arrays["meta"])))
        t = {k: torch.as_tensor(np.asarray(arrays[k])) for k in _KEYS}
        n = int(np.asarray(arrays["n"]))
    except (KeyError, ValueError, TypeError) as e:
        raise ValueError(f"{source} are damaged or not irft statistics: {type(e).__name__}: {e}") from None
    if meta.get("format") != FORMAT or meta.get("space") != "spectral":
        raise ValueError(f"{source} have format {meta.get('format')!r} / space {meta.get('space')!r}; this "
                         f"version reads format {FORMAT}, spectral")
    F = (2 * int(meta["n_beta"]) + 1) * (2 * int(meta["n_gamma"]) + 1)
    shapes = {"P": (2, F, F), "b": (2, F), "yy": (2,), "bg": (2, F), "yg": (2,), "gg": (2,)}
    if any(tuple(t[k].shape) != s for k, s in shapes.items()) or not all(torch.isfinite(v).all() for v in t.values()):
        raise ValueError(f"{source} are damaged: shapes {({k: tuple(v.shape) for k, v in t.items()})} for "
                         f"{F} features, or non-finite values")
    fingerprint = meta.pop("data_sha256", None)
    meta.pop("format")
    if contacts is not None and forces is not None and fingerprint != data_fingerprint(contacts, forces):
        warnings.warn(f"{source} do not belong to these contacts and forces (their data fingerprint differs): "
                      "they are ignored and recomputed", stacklevel=2)
        return None
    return FeatureStatistics(**t, n=n, meta=meta)
