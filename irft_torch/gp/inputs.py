"""The front door's input checks and whitening: forces (T, 2) in N, relative noise scales, units
that look off by 1000 or in degrees, precomputed statistics of other data, the data's own force and
stress-per-depth scales. Every bad input is a ValueError (or TypeError) naming the argument."""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from ..rft.contacts import Contacts

__all__: list[str] = []


def _as_forces(forces, T: int, dtype, device, axes: tuple[str, ...] = ("F_x", "F_z")) -> Tensor:
    """(T, K) forces in N, one column per force axis named in ``axes`` (the 3-D model's: F_x, F_y, F_z)."""
    f = torch.as_tensor(forces, dtype=dtype, device=device)
    K = len(axes)
    if f.ndim != 2 or f.shape[-1] != K:
        where = " for Contacts3D" if K == 3 else ""
        raise ValueError(f"forces must be (T, {K}) = ({', '.join(axes)}) in N{where}, got shape {tuple(f.shape)}")
    if f.shape[0] != T:
        raise ValueError(f"forces has {f.shape[0]} samples but contacts has {T} time steps")
    bad = ~torch.isfinite(f)
    if bad.any():
        i = int(bad.any(-1).nonzero()[0])
        raise ValueError(f"forces contains NaN or inf (first at sample {i}); mask or drop those samples")
    return f


def _as_noise_scale(noise_scale, T: int, dtype, device) -> Tensor:
    """(T, 2) relative noise standard deviations of T training samples; ones when ``noise_scale`` is None."""
    if noise_scale is None:
        return torch.ones(T, 2, dtype=dtype, device=device)
    return _noise_scale(noise_scale, (T,), dtype, device).expand(T, 2).contiguous()


def _noise_scale(noise_scale, lead: tuple, dtype, device) -> Tensor:
    """``noise_scale`` of samples (*lead) = (..., T) as a tensor that broadcasts to exactly (*lead, 2):
    per sample (a shape ending in T, or a 0-d scalar) or per sample and axis (ending in (T, 2)); anything
    else is a ValueError (a (T,) scale must never line up with the two force axes)."""
    s = torch.as_tensor(noise_scale, dtype=dtype, device=device)
    given, T = tuple(s.shape), (lead[-1] if lead else 1)
    if s.ndim >= 2 and s.shape[-2:] == (T, 2):
        pass  # per sample and axis
    elif s.ndim == 0 or s.shape[-1] == T:
        s = s[..., None]  # per sample, both axes
    else:
        raise ValueError(f"noise_scale must end in T = {T} (per sample) or in (T, 2) (per sample and axis) for "
                         f"samples of shape {tuple(lead)}, got shape {given}")
    try:
        fits = torch.broadcast_shapes(s.shape, (*lead, 2)) == (*lead, 2)
    except RuntimeError:
        fits = False
    if not fits:
        raise ValueError(f"noise_scale of shape {given} does not broadcast to the samples {tuple(lead)}")
    if not (torch.isfinite(s).all() and (s > 0).all()):
        raise ValueError("noise_scale must be positive and finite (a relative noise standard deviation per sample)")
    return s


def _whiten(c: Contacts, f: Tensor, s: Tensor) -> tuple[Contacts, Tensor]:
    """Divide each composite observation (its force and its segment weights) by its noise scale:
    F_t / s_t = sum_m (w_tm / s_t) alpha(theta_tm) + eps_t, eps_t ~ N(0, sigma^2), exactly."""
    return c.scale_weights(1 / s[:, :1], 1 / s[:, 1:]), f / s


def _check_units(c: Contacts, f: Tensor) -> None:
    """Warn where the data look off by a unit, in degrees, or not like a granular medium's forces at
    these contacts (``rft.force_checks``: the generic map's forces as the yardstick, two-sided: mN or
    kN, weights in mm^3 or m^3, a flipped sign, swapped columns). The fit itself is unit-free."""
    from ..rft.force_checks import force_faults

    amax = float(torch.maximum(c.beta.abs().max(), c.gamma.abs().max()))
    if amax > math.pi + 1e-6:
        warnings.warn(f"angles reach {amax:.3g}: outside [-pi, pi]; are they in degrees? (angles are in rad)",
                      stacklevel=3)
        return  # in degrees the generic map's forces say nothing
    for fault in force_faults(c, f):
        if fault.kind == "outside":
            continue  # rows out of contact carry noise only: the model reads them as such
        warnings.warn(f"{fault} (forces (T, 2) = (F_x, F_z) in N on the toe; weights depth [cm] x area [cm^2])",
                      stacklevel=3)


def _check_query(c: Contacts, train: Contacts) -> None:
    """Warn where contacts to predict at look like another unit than the training ones: angles in
    degrees, or weights 100x larger or 1e4x smaller than any training sample's (mm^3, m^3)."""
    amax = float(torch.maximum(c.beta.abs().max(), c.gamma.abs().max())) if c.beta.numel() else 0.0
    if amax > 2 * math.pi + 1e-6:
        warnings.warn(f"contact angles reach {amax:.3g}: more than a turn; are they in degrees? (angles are in rad)",
                      stacklevel=3)
    w_new = float((c.weight_x.abs() + c.weight_z.abs()).sum(-1).max()) if c.beta.numel() else 0.0
    w_old = float((train.weight_x.abs() + train.weight_z.abs()).sum(-1).max())
    if w_new > 0 and w_old > 0 and not 1e-4 <= w_new / w_old <= 100:
        warnings.warn(f"the contacts' weights reach {w_new:.3g}, {w_new / w_old:.3g}x the training data's largest "
                      f"({w_old:.3g}): another unit? (weights are depth [cm] x area [cm^2]: mm^3 read 1000x, m^3 "
                      "1e-6x)", stacklevel=3)


def _check_angles(beta: Tensor, gamma: Tensor, where: str) -> tuple[int, ...]:
    """The broadcast shape of map-query angles (rad); ValueError naming both shapes when they do not
    broadcast, a warning when an angle is more than a turn (degrees?)."""
    try:
        S = torch.broadcast_shapes(beta.shape, gamma.shape)
    except RuntimeError:
        raise ValueError(f"{where}: beta of shape {tuple(beta.shape)} and gamma of shape {tuple(gamma.shape)} do not "
                         "broadcast: give angles of one shape, or a grid (torch.meshgrid(beta, gamma, "
                         "indexing='ij'))") from None
    amax = max(float(beta.abs().max()) if beta.numel() else 0.0, float(gamma.abs().max()) if gamma.numel() else 0.0)
    if amax > 2 * math.pi + 1e-6:
        warnings.warn(f"{where}: angles reach {amax:.3g}, more than a turn: are they in degrees? (angles are in rad: "
                      f"{amax:.3g} deg = {math.radians(amax):.4g} rad)", stacklevel=3)
    return tuple(S)


def _check_statistics(stats, f: Tensor, noise_scale, prior_mean: str):
    """Precomputed statistics, checked to be of these forces (count and power per axis)."""
    if stats is None:
        return None
    from .backends.weight_space import FeatureStatistics

    if not isinstance(stats, FeatureStatistics):
        raise TypeError(f"statistics must be a FeatureStatistics (gp.statistics), got {type(stats).__name__}")
    if noise_scale is not None:
        raise ValueError("statistics are computed with unit noise scale: drop noise_scale or statistics")
    if prior_mean == "physics" and stats.meta.get("mean") != "generic shape":
        raise ValueError("statistics lack the generic shape's forces a physics mean needs: compute them with "
                         "gp.statistics.recording_statistics")
    # float32 on either side (a float32 model given statistics of the float64 data) rounds the power at ~1e-7
    rtol = 1e-9 if f.dtype == stats.yy.dtype == torch.float64 else 1e-5
    power = f.double().pow(2).sum(0).to(stats.yy.device)
    if stats.n != len(f) or not torch.allclose(stats.yy.double(), power, rtol=rtol, atol=1e-300):
        raise ValueError(f"statistics are not of these forces: {stats.n} samples with power {stats.yy.tolist()} "
                         f"vs {len(f)} samples with power {power.tolist()}")
    return stats


def _check_dtype(dtype) -> None:
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float64 (default) or torch.float32, got {dtype}")


def _data_scales(c: Contacts, f: Tensor) -> tuple[Tensor, Tensor]:
    """The data's force scale (2,) N (rms force per axis) and stress-per-depth scale (2,) N/cm^3
    (that over the rms summed weight)."""
    s = torch.stack([c.weight_x.abs().sum(-1), c.weight_z.abs().sum(-1)])  # (2, T)
    force_scale = f.T.pow(2).mean(-1).sqrt().clamp_min(1e-300)
    return force_scale, force_scale / s.pow(2).mean(-1).sqrt().clamp_min(1e-300)


def _check_options(prior_mean: str, priors, method: str, hyper_posterior, solver: str, lengthscale: float,
                   surface: bool, tied_noise: bool, li_terms: tuple[bool, bool], retired_grid: bool) -> tuple[str, str]:
    """``InverseRFT``'s options checked (ValueError naming the argument, NotImplementedError for a combination
    that is not built); returns (method, hyper_posterior) with the retired and default values resolved."""
    from .hyper.posterior import HYPER_POSTERIORS
    from .kernels.priors import PRIORS
    from .mean_average import check_average_options

    if prior_mean not in ("zero", "physics", "average"):
        raise ValueError(f"MapPrior(mean=...) (formerly prior_mean) must be 'zero', 'physics' or 'average', "
                         f"got {prior_mean!r}")
    if prior_mean == "average":
        check_average_options(priors, surface, tied_noise)
    if not (math.isfinite(lengthscale) and lengthscale > 0.05):
        raise ValueError(f"lengthscale must be a finite value > 0.05, got {lengthscale}")
    if method == "grid":
        warnings.warn("method='grid' (bilinear interpolation) was retired in 0.2; using 'spectral', which is "
                      "exact to a reported truncation error", FutureWarning, stacklevel=3)
        method = "spectral"
    if method not in ("auto", "exact", "observations", "pairs", "spectral"):
        raise ValueError(f"method must be 'auto', 'observations' (or 'exact'), 'pairs' or 'spectral', got {method!r}")
    if priors not in PRIORS:
        raise ValueError(f"priors must be 'physical' or None (the plain marginal likelihood), got {priors!r}")
    if hyper_posterior is None:  # the default: the honest one (InverseRFT's docstring, docs/calibration.md); but a
        # learned surface has its own Laplace std (gp.surface.offset), and without priors the posterior is improper
        hyper_posterior = "map" if surface or priors is None else "laplace"
    if hyper_posterior not in HYPER_POSTERIORS:
        raise ValueError(f"hyper_posterior must be one of {HYPER_POSTERIORS}, got {hyper_posterior!r}")
    if hyper_posterior != "map" and surface:
        raise NotImplementedError("hyper_posterior with a learned surface offset: the offset has its own Laplace "
                                  "std (model.surface_offset); use hyper_posterior='map' with surface=...")
    if solver not in ("cholesky", "gpytorch"):
        raise ValueError(f"solver must be 'cholesky' or 'gpytorch', got {solver!r}")
    for name, flag in zip(("li_basis", "generic_shape"), li_terms):
        if not isinstance(flag, bool):
            raise TypeError(f"{name} must be True or False, got {flag!r}")
    if li_terms[1] and not li_terms[0]:
        raise ValueError("generic_shape=True needs li_basis=True: the generic shape is a rank-one update of Li et "
                         "al.'s 9-function term (gp.kernels.li_basis)")
    if retired_grid:
        warnings.warn("grid_size and exact_max_segments belong to the retired grid path and are ignored",
                      FutureWarning, stacklevel=3)
    return method, hyper_posterior


NOISE_FLOOR = 1e-8  # the force noise variance is at least this share of the force power (float64; float32: 1e-5)


def initial_hyperparameters(c: Contacts, f: Tensor, dtype, tied_noise: bool, prior_mean: str, li_basis: bool,
                            generic_shape: bool, lengthscale: float, spatial: bool):
    """``RFTHyperparameters`` started from the (whitened) data c (T, M), f (T, 2) N, and the data's map scale (2,)
    N/cm^3: bounds and raw units from the data's own force and stress-per-depth scales (a fit does not depend on
    the units, N or mN, cm^3 or mm^3); the outputscale from the force power per squared weight (after the physics
    mean's least-squares scale with ``MapPrior(mean="physics")``), the noise at 1 % of the force power."""
    from .kernels.hyperparameters import RFTHyperparameters
    from .kernels.priors import spatial_lengthscale_centre

    y = f.T
    s = torch.stack([c.weight_x.abs().sum(-1), c.weight_z.abs().sum(-1)])  # (2, T)
    power = y.pow(2).mean(-1)
    rel_floor = NOISE_FLOOR if dtype == torch.float64 else max(NOISE_FLOOR, 1e-5)
    noise_floor = max(float(power.min()) * rel_floor, 1e-12)
    force_scale, map_scale = _data_scales(c, f)
    hypers = RFTHyperparameters(tied_noise, prior_mean == "physics", noise_floor, force_scale.cpu(), map_scale.cpu(),
                                li_basis, generic_shape, spatial_lengthscale_centre(c.locations) if spatial else None
                                ).to(device=c.beta.device, dtype=dtype)
    with torch.no_grad():
        resid = y
        if prior_mean == "physics":
            shape_f = hypers.mean.shape_forces(c)
            scales = (y * shape_f).sum(-1) / shape_f.pow(2).sum(-1).clamp_min(1e-300)
            scales = torch.maximum(scales, 1e-3 * map_scale.to(scales))
            hypers.mean.scales = scales
            resid = y - scales[:, None] * shape_f
        hypers.outputscale = torch.maximum(resid.pow(2).mean(-1) / s.pow(2).mean(-1).clamp_min(1e-300),
                                           1e-6 * map_scale.to(resid).pow(2))
        hypers.lengthscale = torch.full((2, 1, 4), float(lengthscale), dtype=dtype)
        hypers.noise = (1e-2 * power).clamp_min(noise_floor * 10)
    return hypers, map_scale
