"""Hyperparameter priors with a physical meaning (MAP fitting), registered the gpytorch way.

``InverseRFT(...)`` (``MapPrior(hyperpriors="physical")``, the default) registers three priors on the shared
hyperparameter modules (``register_prior``); every backend's ``loss`` then subtracts their log
density / T, as gpytorch's ``ExactMarginalLogLikelihood`` does. ``MapPrior(hyperpriors=None)`` is the paper's
plain marginal likelihood.

Each prior is a normal density on log(value / centre), i.e. a log-normal prior on the value with
MAP taken in log space (no Jacobian term, so the mode is the centre):

- **outputscale** sigma_c^2 of map c: centre max(zeta rms_c, s_c, 0.5 rms_c max_c' s_c' / rms_c')^2, s_c the
  data's own stress-per-depth scale of axis c (rms force over rms summed weight), log-sd ln 2 (sigma
  within a factor 2 at two standard deviations). The calibration harness (``studies.calibration``,
  issue 30) showed why the generic term alone is not enough: a medium whose map does not project on
  the generic shape (a smooth random map, coefficients of other signs) gets zeta ~ 0, the old narrow
  prior (a factor 1.5) pinned the map's variance near zero, and its intervals held the truth on 41 %
  of the square in one such case (``calibration_study.py --truth prior``: median 0.38, now 0.751).
  The rest of this paragraph explains the generic term, centre (zeta * rms_c)^2.
  Li et al. (Science 2013, Fig. 2 and the supplement's Table S2) found that the stress-per-depth
  maps of the granular media they measured share one generic shape and differ mainly by one scale
  factor zeta per medium; the media used in public code span about an order of magnitude (plastic pellets 0.11, poppy
  seeds 0.25 loose / 0.46 close, glass beads 0.33; the I-RFT paper's own glass-bead bed 1.0 (x) and 1.5
  (z)). So no fixed centre in N/cm^3 fits every medium; the medium's zeta is instead estimated from
  the forces themselves (least squares of the measured forces on the generic shape's forces, both
  axes together: one zeta per medium), and rms_c = (0.209, 0.381) is the root mean square of the
  generic map over the canonical square (x, z) per unit zeta. The width, sigma_c within a factor
  1.5 either way at two standard deviations (log-sd of sigma_c^2 ln 1.5), covers how far one axis
  of a real medium strays from the common zeta: the poppy-seed sets' map stds are 0.84-0.91 (x)
  and 0.96-0.97 (z) of the generic map's at their zeta, the I-RFT bed's scales 1.0 (x) and 1.5 (z)
  are 0.82 and 1.22 of their geometric mean. So an axis the forces do not inform (F_x during a
  vertical intrusion) keeps a prior of the size real media have, instead of collapsing to zero.
  With the physics mean (generic shape x learned scales) the GP models the residual, so the centre
  is 0.3 of that and the width a factor 10. When the model also learns the surface height, zeta
  (estimated at the stated surface) is not trusted and the width is a factor 10 too.
- **lengthscales** (dimensionless, on the embedding (sin 2beta, cos 2beta, sin gamma, cos gamma),
  each coordinate in [-1, 1]): centre ``LENGTHSCALE_CENTRE`` = 1.5, log-sd 1.5 (a factor 4.5 per
  standard deviation: where the forces inform a lengthscale, they decide it). An RBF fitted to the
  generic map itself, densely sampled, takes lengthscales 2.2-5.4 (a smooth, nearly bilinear map);
  DEM and measured maps have sharper features (steeper gamma dependence), so the centre sits
  below. Where the forces never vary a coordinate (an I-toe samples beta = 0 only), the lengthscale
  is the centre: the map keeps correlation exp(-4 / (2 * 1.5^2)) = 0.41 between beta = 0 and
  beta = +-pi/2 (exp(-1/4.5) = 0.80 at +-pi/4), so it extrapolates part of what it saw and reverts
  to the prior's variance beyond, and that is what the posterior std then says.
- **Li et al.'s term** (``kernel="li"``, ``gp.kernels.li_basis``): its variance per map has the outputscale's
  centre and width: the 9 functions are given as much prior variance as the RBF part.
- **with the generic shape as a term in a spatial model** (``kernel="li+generic"`` with places, the spatial
  default; ``residual_terms``): the shape's variance u (below) carries the medium, so the RBF and Li et al.'s 9
  functions model what the shape leaves, as the GP does with the physics mean: their centre is the physics mean's
  residual centre (the larger of 0.3 of the generic map at zeta and what the forces leave after the generic shape
  at its least-squares scale per axis), their width a factor 10. Each of the three terms at the whole map's size
  made the spatial model's intervals wider than needed (95 % coverage 0.98-1.00 at new places on walks over
  generic-like media, the errors' sd 0.2-0.6 of the posterior sd; with this rule 0.95-0.96 and 0.7-0.9,
  ``experiments/validation/walk_and_map.py``). Planar models keep the rule above (``residual_terms`` says why).
- **the generic shape's variance** u (``kernel="li+generic"``, ``gp.kernels.li_basis``): the variance of the shape's
  scale per map, centre the medium's zeta squared (the scale real media have, as above), log-sd ln 2. As for
  the outputscale: with the physics mean (which already carries the shape at a fitted scale) the centre is
  (0.3 zeta)^2 and the width a factor 10, and with a learned surface (zeta not trusted) the width is a factor 10.
- **mean scale** (with the physics mean, ``MapPrior(mean="physics")`` or ``"average"``): the generic shape's
  scale per axis, centre the medium's zeta (as above), log-sd ln 2. A proper prior, so that a model with
  the physics mean has a marginal likelihood (evidence) to weigh against the zero mean's.
- **noise** variance of each force axis: centre 1e-2 of the mean squared force of that axis (a noise
  std of 10 % of the force; the I-RFT paper's Table II studies relative noise variances of 0.05 and
  0.2, i.e. 22 % and 45 %), log-sd ln 10 (a factor 10 per standard deviation): a noise-free
  simulation can still push it to its floor, but a flat
  likelihood (few samples) no longer does.

The priors carry no state: their centres are recomputed from the training data whenever a model
is built (a model file rebuilds the model from its data and the option ``priors``), and their
buffers are left out of state dicts.

**3-D models** (``gp.inverse3d``, K = 3 maps: alpha_x, alpha_y, alpha_z): the same priors with the third map added
(``prior_centres_3d``): the outputscale centre as above with zeta the generic map's least-squares scale on all three
force axes (3-D RFT with alpha_y = alpha_x(0, 0), the rover-wheel authors' form) and rms_c (0.209, 0.136, 0.381)
(alpha_y's the constant's), s_c per map from ``data_scales_3d``; lengthscales, noise and Li et al.'s term as planar;
``register_physical_priors`` registers them for any K.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from gpytorch.priors import NormalPrior
from torch import Tensor

from ...rft.contacts import Contacts
from ...rft.contacts3d import Contacts3D
from ...rft.forces import forces as rft_forces
from ...rft.forces3d import forces_3d
from ...rft.stress_maps import FourierStressMap

__all__ = ["PRIORS", "GENERIC_RMS", "GENERIC_RMS_3D", "LENGTHSCALE_CENTRE", "CentreSums", "medium_scale",
           "prior_centres", "centres_of_sums", "data_scales_3d", "prior_centres_3d",
           "register_physical_priors", "register_spatial_priors", "residual_terms", "spatial_lengthscale_centre"]

PRIORS = ("physical", None)
GENERIC_RMS = (0.2088, 0.3805)  # rms of the generic Li et al. map over the square, (x, z), per unit zeta
LENGTHSCALE_CENTRE = 1.5
LENGTHSCALE_LOG_SD = 1.5
OUTPUTSCALE_LOG_SD = math.log(2.0)  # of sigma^2: sigma within a factor 2 at two standard deviations
JOINT_FRACTION = 0.5  # an axis' centre is at least this share of what the other axis' data scale implies
NOISE_RELATIVE = 1e-2
NOISE_LOG_SD = math.log(10.0)
GENERIC_LOG_SD = math.log(2.0)  # of u, the generic shape's variance, around zeta^2
MEAN_SCALE_LOG_SD = math.log(2.0)  # the physics mean's scale per axis, around the medium's zeta
SPATIAL_VARIANCE_START = 0.25  # v at the start and the centre of its prior: maps that vary by about 50 % (sd)
SPATIAL_VARIANCE_LOG_SD = math.log(4.0)  # v around SPATIAL_VARIANCE_START: 0.016 to 4 at two standard deviations
SPATIAL_LENGTHSCALE_LOG_SD = math.log(3.0)  # l around a quarter of the ground walked (a factor 9 at two sd)
PHYSICS_MEAN_RESIDUAL = 0.3  # residual GP's centre, relative, with the physics mean


def _generic_forces(contacts: Contacts) -> Tensor:
    """(T, 2) N: the generic shape's forces on the contacts, per unit zeta."""
    return rft_forces(FourierStressMap.generic().to(contacts.beta.dtype), contacts)


@dataclass(frozen=True)
class CentreSums:
    """The sums over samples that fix the priors' centres, each (2,) per axis: F.g, g.g, F.F, the squared
    summed weight (|weight| summed over segments) and the count n, g the generic shape's forces per unit zeta.
    Streamed data add theirs (``InverseRFT.add_data``): the centres of all the data in O(new samples)."""

    fg: Tensor
    gg: Tensor
    ff: Tensor
    ww: Tensor
    n: int

    @classmethod
    def of(cls, contacts: Contacts, forces: Tensor) -> CentreSums:
        g = _generic_forces(contacts)
        w = torch.stack([contacts.weight_x.abs().sum(-1), contacts.weight_z.abs().sum(-1)], -1)
        return cls((forces * g).sum(0), g.pow(2).sum(0), forces.pow(2).sum(0), w.pow(2).sum(0), len(forces))

    def __add__(self, other: CentreSums) -> CentreSums:
        return CentreSums(self.fg + other.fg, self.gg + other.gg, self.ff + other.ff, self.ww + other.ww,
                          self.n + other.n)

    def map_scale(self) -> Tensor:
        """(2,) N/cm^3: rms force over rms summed weight, per axis (``gp.inputs._data_scales``)."""
        n = max(self.n, 1)
        return (self.ff / n).sqrt().clamp_min(1e-300) / (self.ww / n).sqrt().clamp_min(1e-300)

    def medium_scale(self) -> float:
        """``medium_scale`` of the summed data."""
        den = float(self.gg.sum())
        return max(float(self.fg.sum()) / den, 0.0) if den > 0 else 0.0

    def residual_scale(self) -> Tensor:
        """``residual_scale`` of the summed data: sum (F - s g)^2 = F.F - 2 s F.g + s^2 g.g."""
        n = max(self.n, 1)
        s = (self.fg / self.gg.clamp_min(1e-300)).clamp_min(0)
        r2 = (self.ff - 2 * s * self.fg + s * s * self.gg).clamp_min(0)
        return (r2 / n).sqrt() / (self.ww / n).sqrt().clamp_min(1e-300)


def medium_scale(contacts: Contacts, forces: Tensor) -> float:
    """Least-squares zeta of the generic map on these forces, both axes together:
    zeta = sum_c F_c . g_c / sum_c g_c . g_c, g_c the generic shape's forces (N per unit zeta).
    Returns 0 where the forces do not project positively on the shape."""
    return CentreSums.of(contacts, forces).medium_scale()


def residual_scale(contacts: Contacts, forces: Tensor) -> Tensor:
    """(2,) N/cm^3: per axis, the rms of the forces less the generic shape's at its least-squares scale
    (>= 0), over the rms summed weight: the size of what a physics mean leaves to the GP."""
    return CentreSums.of(contacts, forces).residual_scale()


def prior_centres(contacts: Contacts, forces: Tensor, map_scale: Tensor, physics_mean: bool = False,
                  residual: bool = False) -> dict:
    """The centres (physical units) of the three priors for these (whitened) data: outputscale (2,)
    in (N/cm^3)^2, lengthscale (dimensionless), noise (2,) in N^2. ``residual``: as ``centres_of_sums``'
    (``residual_terms(hypers)`` says where a model uses it)."""
    return centres_of_sums(CentreSums.of(contacts, forces), map_scale, physics_mean, residual)


def centres_of_sums(sums: CentreSums, map_scale: Tensor | None = None, physics_mean: bool = False,
                    residual: bool = False) -> dict:
    """``prior_centres`` from the data's ``CentreSums`` (``map_scale`` None: the sums' own). ``residual``: the
    outputscale's centre is the residual's, as with ``physics_mean`` (where ``residual_terms(hypers)``: a spatial
    model with the generic shape as a kernel term, whose other terms model what it leaves)."""
    rms = torch.tensor(GENERIC_RMS, dtype=sums.ff.dtype, device=sums.ff.device)
    ms = (sums.map_scale() if map_scale is None else map_scale).to(rms)
    # a fallback where the forces do not project on the generic shape: the data's own map scale
    fallback = float((ms / rms).max())
    zeta = max(sums.medium_scale(), 0.1 * fallback)
    if physics_mean or residual:
        # the residual's size: a fraction of the medium's map (generic-like media), or what the forces
        # leave after the generic shape at its least-squares scale per axis (media of other shapes)
        resid = sums.residual_scale()
        sigma = torch.maximum(torch.maximum(zeta * rms * PHYSICS_MEAN_RESIDUAL, resid),
                              JOINT_FRACTION * float((resid / rms).max()) * rms)
    else:
        # the largest of three estimates of each map's size: the generic shape at the medium's zeta (right
        # for generic-like media, and for an axis the forces barely see), the axis' own stress per depth
        # (forces over weights: right for media of any shape, the data's own scale), and half of what the
        # other axis' data scale implies at the generic proportions (an axis whose forces are small along
        # this motion, in a medium that does not project on the generic shape)
        sigma = torch.maximum(torch.maximum(zeta * rms, ms), JOINT_FRACTION * fallback * rms)
    return {"zeta": zeta, "outputscale": sigma.pow(2), "lengthscale": LENGTHSCALE_CENTRE,
            "noise": NOISE_RELATIVE * sums.ff / max(sums.n, 1)}


def residual_terms(hypers) -> bool:
    """Whether the RBF and Li et al.'s term model what the generic shape leaves (centre and width of the physics
    mean's residual, ``centres_of_sums(..., residual=True)``): in a spatial model with the generic shape as a term
    (``kernel="li+generic"`` with places, the spatial default). There every term's variance is also the scale of
    its variation over the ground, and three terms each at the whole map's size made the intervals at new places
    wider than needed (module docstring). Planar models keep each term at the map's size: there the rule left
    the generic-shaped media as wide (scaled alpha_x 0.98 -> 1.00 on the harness, seed 0) and made one fit of six
    overconfident (perturbed alpha_z 0.95 -> 0.89)."""
    li = getattr(hypers, "li", None)
    return li is not None and li.generic and getattr(hypers, "spatial", None) is not None


def _stateless(prior):
    """A prior's buffers out of state dicts: a model's state is its hyperparameters, whatever its priors."""
    prior._non_persistent_buffers_set.update(prior._buffers.keys())
    return prior


def register_physical_priors(hypers, centres: dict, physics_mean: bool = False, learned_surface: bool = False) -> None:
    """Register the outputscale, lengthscale and noise priors on ``hypers`` (``RFTHyperparameters``)
    with gpytorch's ``register_prior``, each a ``NormalPrior`` on log(value / centre).

    ``learned_surface``: the surface height is fitted too, so the medium's scale zeta estimated at the
    stated surface is not trusted (a surface 2 cm off changes the depths, and zeta, by a factor of
    2-3 on a shallow stroke): the outputscale prior then has the physics mean's width (a factor 10
    per standard deviation), and the forces decide. Where ``residual_terms(hypers)`` (a spatial model with the
    generic shape as a term) the RBF and Li et al.'s term model what the shape leaves: ``centres`` are then the
    residual's (``centres_of_sums(..., residual=True)``) and the width is the physics mean's too."""
    dtype = hypers.kernel.raw_outputscale.dtype
    log_os = centres["outputscale"].to(dtype).log().detach().clone()
    log_ls = math.log(centres["lengthscale"])
    noise = centres["noise"].to(dtype)
    log_noise = (noise.mean().reshape(1) if hypers.tied else noise).log().detach().clone()
    os_sd = NOISE_LOG_SD if (physics_mean or learned_surface or residual_terms(hypers)) else OUTPUTSCALE_LOG_SD
    zero = torch.zeros((), dtype=dtype, device=hypers.kernel.raw_outputscale.device)
    # closures as partials of module-level functions, so that a model pickles (process pools, copies)
    hypers.kernel.register_prior("outputscale_prior", _stateless(NormalPrior(zero.clone(), os_sd)),
                                 functools.partial(_log_outputscale_ratio, c=log_os))
    hypers.kernel.base_kernel.register_prior("lengthscale_prior",
                                             _stateless(NormalPrior(zero.clone(), LENGTHSCALE_LOG_SD)),
                                             functools.partial(_log_lengthscale_ratio, c=log_ls))
    hypers.likelihood.noise_covar.register_prior("noise_prior", _stateless(NormalPrior(zero.clone(), NOISE_LOG_SD)),
                                                 functools.partial(_log_noise_ratio, c=log_noise))
    if getattr(hypers, "li", None) is not None:
        # Li et al.'s 9-function term (``gp.kernels.li_basis``): the same centre and width as the outputscale; the
        # evidence for this centre (x 0.25 to x 4 all raise coverage): docs/calibration.md
        hypers.li.register_prior("variance_prior", _stateless(NormalPrior(zero.clone(), os_sd)),
                                 functools.partial(_log_li_ratio, c=log_os))
        if hypers.li.generic:  # the generic shape's scale: real media's zeta (the module docstring)
            zeta = max(float(centres["zeta"]), 1e-300) * (PHYSICS_MEAN_RESIDUAL if physics_mean else 1.0)
            log_zeta2 = torch.full_like(log_os, 2 * math.log(zeta))
            sd = NOISE_LOG_SD if (physics_mean or learned_surface) else GENERIC_LOG_SD
            hypers.li.register_prior("generic_variance_prior", _stateless(NormalPrior(zero.clone(), sd)),
                                     functools.partial(_log_generic_ratio, c=log_zeta2))
    if physics_mean and hypers.mean is not None:
        # a proper prior on the generic shape's scale per axis (a model's evidence needs one: ``prior_mean=
        # "average"`` weighs the physics mean against the zero mean by it): around the medium's zeta, a factor 2
        # per standard deviation (real media's axes stray from one zeta by a factor 1.2-1.5, see above)
        hypers.mean.register_prior("scales_prior", _stateless(NormalPrior(zero.clone(), MEAN_SCALE_LOG_SD)),
                                   functools.partial(_log_scale_ratio, c=math.log(max(float(centres["zeta"]), 1e-300))))


def _log_outputscale_ratio(m, c):
    return m.outputscale.log() - c.to(m.outputscale)


def _log_li_ratio(m, c):
    return m.variance.log() - c.to(m.variance)


def _log_generic_ratio(m, c):
    return m.generic_variance.log() - c.to(m.generic_variance)


def _log_lengthscale_ratio(m, c):
    return m.lengthscale.log() - (c.to(m.lengthscale) if torch.is_tensor(c) else c)


def _log_scale_ratio(m, c):
    return m.scales.log() - c


def _log_noise_ratio(m, c):
    return m.noise.reshape(-1).log() - c.to(m.noise)


def spatial_lengthscale_centre(locations: Tensor) -> float:
    """The spatial lengthscale's prior centre, m: a quarter of the largest extent of the places (N, 2) walked
    (1 m where every place is the same)."""
    span = float((locations.max(0).values - locations.min(0).values).max()) if len(locations) else 0.0
    return span / 4 if span > 0 else 1.0


def register_spatial_priors(hypers, lengthscale_centre: float) -> None:
    """Priors of the spatial factor (``gp.kernels.spatial``), gpytorch ``NormalPrior`` on log(value / centre):
    the relative variance v around ``SPATIAL_VARIANCE_START`` (a proper prior: the hyperparameter posterior
    needs one, and v -> 0, one medium, stays reachable), the lengthscale around ``lengthscale_centre`` m."""
    k = hypers.spatial.kernel
    zero = torch.zeros((), dtype=k.raw_outputscale.dtype, device=k.raw_outputscale.device)
    k.register_prior("outputscale_prior", _stateless(NormalPrior(zero.clone(), SPATIAL_VARIANCE_LOG_SD)),
                     functools.partial(_log_spatial_variance_ratio, c=math.log(SPATIAL_VARIANCE_START)))
    k.base_kernel.register_prior("lengthscale_prior", _stateless(NormalPrior(zero.clone(), SPATIAL_LENGTHSCALE_LOG_SD)),
                                 functools.partial(_log_lengthscale_ratio, c=math.log(lengthscale_centre)))


def _log_spatial_variance_ratio(m, c):
    return m.outputscale.log() - c


# ---- 3-D models (K = 3 maps) ---------------------------------------------------------------------------------------
GENERIC_RMS_3D = (GENERIC_RMS[0], 0.136, GENERIC_RMS[1])  # alpha_x, alpha_y (= alpha_x(0, 0)), alpha_z


def data_scales_3d(c: Contacts3D, f: Tensor) -> tuple[Tensor, Tensor]:
    """The data's force scale (3,) N (rms per axis) and stress-per-depth scale (3,) N/cm^3 per map: the rms of
    the forces the map feeds over the rms of its summed |weights| (a map no force sees takes alpha_x's)."""
    fs = f.pow(2).mean(0).sqrt().clamp_min(1e-300)
    fxy = f[:, :2].pow(2).sum(-1).mean().sqrt()

    def per_map(w):
        s = w.abs().sum(1).pow(2).sum(-1).mean().sqrt() if w.ndim == 3 else w.abs().sum(1).pow(2).mean().sqrt()
        return s

    sx, sy, sz = per_map(c.weight_x), per_map(c.weight_y), per_map(c.weight_z)
    mx = fxy / sx.clamp_min(1e-300)
    my = fxy / sy if float(sy) > 0 else mx
    mz = fs[2] / sz.clamp_min(1e-300)
    return fs, torch.stack([mx, my, mz]).clamp_min(1e-300)


def medium_scale_3d(c: Contacts3D, f: Tensor) -> float:
    """Least-squares zeta of the generic map (alpha_y = alpha_x(0, 0)) on all three axes; 0 if it does not
    project positively."""
    g = forces_3d(FourierStressMap.generic().to(c.beta.dtype), c)
    den = float(g.pow(2).sum())
    return max(float((f * g).sum()) / den, 0.0) if den > 0 else 0.0


def prior_centres_3d(c: Contacts3D, f: Tensor, map_scale: Tensor, noise_floor: float) -> dict:
    rms = torch.tensor(GENERIC_RMS_3D, dtype=f.dtype, device=f.device)
    ms = map_scale.to(rms)
    fallback = float((ms / rms).max())
    zeta = max(medium_scale_3d(c, f), 0.1 * fallback)
    sigma = torch.maximum(torch.maximum(zeta * rms, ms), JOINT_FRACTION * fallback * rms)
    noise = (NOISE_RELATIVE * f.pow(2).mean(0)).clamp_min(noise_floor * 10)
    return {"zeta": zeta, "outputscale": sigma.pow(2), "lengthscale": LENGTHSCALE_CENTRE, "noise": noise}
