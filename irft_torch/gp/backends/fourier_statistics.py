"""The data in a Fourier basis on the angle torus: the features of weighted sums, their sufficient statistics in one
pass, and the statistics and data factor of a nested smaller basis cut from a larger one's (no pass over the data).
What the spectral backend (``spectral``), a fleet's workers (``gp.statistics``) and the draws' bases
(``draw_spaces``) share."""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts import Contacts
from ..kernels.fourier import FourierBasis
from .weight_space import FeatureStatistics, WeightSpaceBackend, _DataFactor, chunk_rows

__all__ = ["features", "spectral_statistics", "restrict_statistics", "cut_factor"]


def _axis_features(w: Tensor, pb: Tensor, pg: Tensor) -> Tensor:
    """sum_m w_nm psi_beta(beta_nm) kron psi_gamma(gamma_nm): w (N, M) -> (N, Fb Fg), one batched matmul."""
    return torch.bmm((w[..., None] * pb).mT, pg).reshape(w.shape[0], pb.shape[-1] * pg.shape[-1])


def features(c: Contacts, basis: FourierBasis, axes: tuple[int, ...] = (0, 1)) -> Tensor:
    """Phi (len(axes), N, F): the features of the weighted sums of contacts (N, M), x and z axes."""
    pb, pg = basis.features(c.beta, c.gamma)  # (N, M, Fb), (N, M, Fg)
    w = (c.weight_x, c.weight_z)
    return torch.stack([_axis_features(w[a], pb, pg) for a in axes])


def _meta(basis: FourierBasis) -> dict:
    return {"space": "spectral", "n_beta": basis.n_beta, "n_gamma": basis.n_gamma}


def spectral_statistics(c: Contacts, f: Tensor, basis: FourierBasis, mean=None, chunk: int | None = None
                        ) -> FeatureStatistics:
    """Sufficient statistics of one recording (contacts (T, M) and forces (T, 2), whitened if a
    noise scale applies) in ``basis``, one chunked pass, no model needed: what a worker computes in
    a map-reduce over a fleet's recordings. Statistics add up (``a + b``) to those of the union.

    Args:
        mean: the physics prior mean (``GenericShapeMean``) if the model will use one, else None.
    """
    F = basis.size
    stats = FeatureStatistics.zeros(F, dtype=f.dtype, device=f.device, meta=_meta(basis))
    shape = mean.shape_forces(c) if mean is not None else None
    chunk = chunk or chunk_rows(F, c.n_segments)
    with torch.no_grad():
        for i in range(0, len(c), chunk):
            part = c[i:i + chunk]
            y, g = f[i:i + chunk].T, None if shape is None else shape[:, i:i + chunk]
            sign = WeightSpaceBackend._row_sign(part)
            if sign is None:
                stats.accumulate(features(part, basis), y, g)
            else:
                stats.accumulate_shared(features(part, basis, axes=(1,))[0], sign, y, g)
    return stats


def restrict_statistics(stats: FeatureStatistics, basis: FourierBasis) -> FeatureStatistics:
    """The statistics in a smaller (nested) basis: the leading harmonics' blocks, exactly the
    statistics a pass over the data in ``basis`` gives. ValueError if ``basis`` is not inside the
    statistics' own."""
    meta = stats.meta
    if meta.get("space") != "spectral":
        raise ValueError(f"statistics of space {meta.get('space')!r} cannot serve a spectral basis")
    nb, ng = int(meta["n_beta"]), int(meta["n_gamma"])
    if basis.n_beta > nb or basis.n_gamma > ng:
        raise ValueError(f"statistics in FourierBasis({nb}, {ng}) cannot give the larger {basis}")
    if (basis.n_beta, basis.n_gamma) == (nb, ng):
        return stats
    Fb, Fg = basis.sizes
    full = (2 * nb + 1, 2 * ng + 1)
    out_meta = {**meta, **_meta(basis)}

    def cut(v: Tensor) -> Tensor:  # the leading Fb x Fg block of each (beta, gamma) feature axis: one strided copy
        lead = v.shape[:1]
        k = (v.ndim - 1)
        v = v.reshape(*lead, *(full * k))
        v = v[(slice(None), *([slice(0, Fb), slice(0, Fg)] * k))]
        return v.reshape(*lead, *([Fb * Fg] * k))

    return FeatureStatistics(cut(stats.P), cut(stats.b), stats.yy, cut(stats.bg), stats.yg, stats.gg, stats.n,
                             out_meta)


def cut_factor(factor: _DataFactor, big: FourierBasis, basis: FourierBasis) -> _DataFactor:
    """The data factor in a smaller (nested) ``basis`` from one in ``big``: R's columns of the leading harmonics'
    blocks (as ``restrict_statistics`` cuts P), c and rho unchanged (they are of the same orthonormal U)."""
    (Fb, Fg), full = basis.sizes, big.sizes
    R = factor.R
    R = R.reshape(*R.shape[:-1], *full)[..., :Fb, :Fg].reshape(*R.shape[:-1], Fb * Fg)
    return _DataFactor(R, factor.c_y, factor.c_g, factor.rho, factor.rank)
