"""The hyperparameters every backend shares, for K maps: the angle kernel, the force noise, the prior mean.

They live in stock gpytorch modules (``AngleKernel`` = ``ScaleKernel(RBFKernel)``, a batched
``GaussianLikelihood``), so priors, constraints and state dicts follow gpytorch. A backend only
reads them; swapping the backend keeps them. ``MapHyperparameters`` holds what every K shares;
``RFTHyperparameters`` is the planar model's (K = 2: alpha_x, alpha_z), ``RFT3DHyperparameters`` the 3-D
model's (K = 3: alpha_x, alpha_y, alpha_z; alpha_y a map over (beta, gamma) or a constant with a zero-mean
normal prior of variance s_y, a rank-one kernel term s_y (W_y 1)(W_y 1)^T; ``gp.inverse3d``, docs/inverse3d.md).
"""

from __future__ import annotations

import torch
from gpytorch import Module
from gpytorch.constraints import GreaterThan
from gpytorch.likelihoods import GaussianLikelihood
from torch import Tensor

from .angle import BATCH, AngleKernel
from .constraints import ScaledGreaterThan
from .li_basis import LiBasisVariance, generic_coefficients, li_features
from .means import GenericShapeMean
from .spatial import SpatialFactor

__all__ = ["MapHyperparameters", "RFTHyperparameters", "RFT3DHyperparameters", "force_likelihood", "MAPS_3D", "AXES_3D",
           "ALPHA_Y", "LENGTHSCALE_FLOOR_3D"]

MAPS_3D = ("alpha_x", "alpha_y", "alpha_z")
AXES_3D = ("F_x", "F_y", "F_z")
ALPHA_Y = ("map", "constant")
# The shortest lengthscale a 3-D map may take (embedding units; the planar model's floor is 0.05). Two reasons,
# neither from the wheels: an ARD RBF fitted to the DEM plate intrusion's 54 measured stresses (an independent
# granular simulation) takes 0.23-2.9, Li et al.'s generic map 2.2-5.4, so no medium measured has finer features;
# and above 0.21 the spectral basis's 30 harmonics per angle hold the RBF within tol 1e-7 whatever the other
# lengthscales (the bound, ``kernels.fourier``: 9.3e-8 at the worst), so the default fit is never truncated by the
# cap. Without it, the wheels' aggregate forces drive alpha_x's sin 2beta lengthscale onto 0.05
# (experiments/notes/wheel3d_lengthscales.md).
LENGTHSCALE_FLOOR_3D = 0.21


def force_likelihood(tied: bool = False, noise_floor: float = 1e-6, scale=1.0) -> GaussianLikelihood:
    """gpytorch's ``GaussianLikelihood`` for the (x, z) batch of force axes: one noise variance per
    axis (batch shape (2,), noise (2, 1)) or one shared (``tied``, the I-RFT paper; noise (1,)), N^2,
    bounded below by ``noise_floor``; ``scale``: the force variance that makes its raw value unit-free."""
    scale = torch.as_tensor(scale, dtype=torch.get_default_dtype())
    scale = scale.mean().reshape(1) if tied else scale.expand(2).reshape(2, 1)
    return GaussianLikelihood(batch_shape=torch.Size() if tied else BATCH,
                              noise_constraint=ScaledGreaterThan(noise_floor, scale))


class MapHyperparameters(Module):
    """What the planar and the 3-D model's hyperparameters share, for K maps over (beta, gamma): ``kernel`` (an
    ``AngleKernel`` with batch (K,): lengthscale (K, 1, 4), outputscale (K,) in (N/cm^3)^2), ``likelihood`` (a
    batched gpytorch ``GaussianLikelihood``: one force-noise variance per axis, N^2, or one shared), ``li`` (Li et
    al.'s term per map, ``gp.kernels.li_basis``, or None), and their readable views. ``RFTHyperparameters`` is K = 2
    (alpha_x, alpha_z), ``gp.inverse3d.RFT3DHyperparameters`` K = 3 (alpha_x, alpha_y, alpha_z)."""

    n_maps = 2
    kernel: AngleKernel
    likelihood: GaussianLikelihood
    li: LiBasisVariance | None

    @property
    def tied(self) -> bool:
        """Whether one noise variance serves every force axis (the I-RFT paper's)."""
        return self.likelihood.noise.numel() == 1

    @property
    def lengthscale(self) -> Tensor:
        """(K, 1, 4), dimensionless (the embedding's units)."""
        return self.kernel.lengthscale

    @lengthscale.setter
    def lengthscale(self, value) -> None:
        self.kernel.lengthscale = value

    @property
    def outputscale(self) -> Tensor:
        """(K,) the RBF part's prior variance of each map, (N/cm^3)^2."""
        return self.kernel.outputscale

    @outputscale.setter
    def outputscale(self, value) -> None:
        self.kernel.outputscale = torch.as_tensor(value, dtype=self.kernel.raw_outputscale.dtype).expand(self.n_maps)

    @property
    def noise(self) -> Tensor:
        """(K,) force noise variances, one per axis, N^2 (equal when tied)."""
        return self.likelihood.noise.reshape(-1).expand(self.n_maps)

    @noise.setter
    def noise(self, value) -> None:
        raw = self.likelihood.noise_covar.raw_noise
        value = torch.as_tensor(value, dtype=raw.dtype, device=raw.device).reshape(-1).expand(self.n_maps)
        value = value.mean(0, keepdim=True) if self.tied else value
        lower = self.likelihood.noise_covar.raw_noise_constraint.lower_bound.to(value).reshape(-1)
        self.likelihood.noise = torch.maximum(value, lower * 1.0001).reshape(raw.shape)

    @property
    def li_variance(self) -> Tensor | None:
        """(K,) prior variances of Li et al.'s 9-function term per map, (N/cm^3)^2, or None without it."""
        return None if self.li is None else self.li.variance

    def log_prior(self) -> Tensor:
        """Sum of the log densities of the hyperparameter priors registered on these modules (0 without any)."""
        total = self.kernel.raw_outputscale.new_zeros(())
        for _, module, prior, closure, _ in self.named_priors():
            total = total + prior.log_prob(closure(module)).sum()
        return total

    def fixed_labels(self) -> list[str]:
        """Labels of the coordinates no likelihood sees (a hyperparameter posterior leaves them where they are):
        none here; a 3-D model's constant alpha_y has some."""
        return []


class RFTHyperparameters(MapHyperparameters):
    """Kernel, likelihood and (optional) physics mean of the two maps, with readable views.

    Attributes:
        kernel: :class:`AngleKernel` (lengthscale (2, 1, 4), outputscale (2,) in (N/cm^3)^2).
        likelihood: gpytorch ``GaussianLikelihood`` (noise in N^2).
        mean: ``GenericShapeMean`` (scales (2,) of the generic Li et al. shape) or None (zero mean).
        li: ``LiBasisVariance`` (variance (2,) of Li et al.'s 9-function kernel term, ``gp.kernels.li_basis``, and with
            ``generic_shape`` the generic shape's variance (2,) too) or None (the RBF alone).
        spatial: ``SpatialFactor`` (maps that change over the ground, ``gp.kernels.spatial``: variance (2,) relative
            to the shared medium, lengthscale (2,) m) or None (one homogeneous medium).
    """

    def __init__(self, tied_noise: bool = False, physics_mean: bool = False, noise_floor: float = 1e-6,
                 force_scale=1.0, map_scale=1.0, li_basis: bool = False, generic_shape: bool = False,
                 spatial_lengthscale: float | None = None) -> None:
        """``force_scale`` (2,) N and ``map_scale`` (2,) N/cm^3: the data's typical force and stress per
        depth per axis; the raw parameters are measured in them (``ScaledGreaterThan``), so a fit does
        not depend on the units the data come in. ``spatial_lengthscale`` (m): maps over the ground, the
        spatial factor starting at this lengthscale; None: one medium."""
        super().__init__()
        fs = torch.as_tensor(force_scale, dtype=torch.get_default_dtype()).expand(2)
        ms = torch.as_tensor(map_scale, dtype=torch.get_default_dtype()).expand(2)
        self.kernel = AngleKernel(outputscale_constraint=ScaledGreaterThan(0.0, ms.pow(2)))
        self.likelihood = force_likelihood(tied_noise, noise_floor, fs.pow(2))
        self.mean = GenericShapeMean(scale=ms) if physics_mean else None
        if generic_shape and not li_basis:
            raise ValueError("generic_shape=True needs li_basis=True: the generic shape is a rank-one update of Li et "
                             "al.'s 9-function term (gp.kernels.li_basis)")
        self.li = LiBasisVariance(scale=ms.pow(2), generic=generic_shape) if li_basis else None
        self.spatial = None if spatial_lengthscale is None else SpatialFactor(float(spatial_lengthscale))

    def start_li(self, zeta: float) -> None:
        """Start Li et al.'s term at the RBF part's variance and the generic shape's at zeta^2 (the centres of their
        priors, ``gp.kernels.priors``; zeta the medium's scale, ``priors.prior_centres``)."""
        with torch.no_grad():
            self.li.variance = self.outputscale
            if self.li.generic:
                self.li.generic_variance = torch.as_tensor(float(zeta) ** 2).to(self.outputscale).clamp_min(
                    1e-6 * float(self.li.raw_generic_variance_constraint.scale.max()))

    @property
    def generic_variance(self) -> Tensor | None:
        """(2,) prior variances u of the generic shape's scale per map, (N/cm^3)^2, or None without the term."""
        return None if self.li is None else self.li.generic_variance

    @property
    def prior_variance(self) -> Tensor:
        """(2,) the prior variance of each map, (N/cm^3)^2: the outputscale, plus Li et al.'s v where the model has
        the term (its 9 functions have |f(theta)|^2 = 1 at every theta, ``gp.kernels.li_basis``); with the generic
        shape, plus u times its mean square over the canonical square (the one part that varies with the angles)."""
        s = self.outputscale
        return s if self.li is None else s + self.li.mean_variance()

    def prior_variance_at(self, beta: Tensor, gamma: Tensor) -> Tensor:
        """(..., 2) the prior variance of each map at angle pairs (...,) in radians, (N/cm^3)^2: ``prior_variance``
        everywhere, except with the generic shape, whose part is u g(theta)^2 (``gp.kernels.li_basis``)."""
        s = self.outputscale if self.li is None else self.outputscale + self.li.variance
        beta, gamma = torch.broadcast_tensors(beta, gamma)
        if self.li is None or not self.li.generic:
            return s.expand(*beta.shape, 2)
        g = li_features(beta, gamma) @ generic_coefficients(s.dtype, s.device).T  # (..., 2)
        return s + self.li.generic_variance * g.pow(2)

    @property
    def mean_scales(self) -> Tensor | None:
        """(2,) scales of the generic shape in the physics mean, or None for the zero mean."""
        return None if self.mean is None else self.mean.scales

    def mean_of(self, contacts, detach: bool = False) -> Tensor | None:
        """Prior mean of the weighted sums of ``contacts`` (N, M): (2, N) in N, or None (zero mean).
        ``detach``: the scales as constants (a prediction: differentiable in the contacts only, like
        the rest of the posterior, whose hyperparameters are fixed)."""
        if self.mean is None:
            return None
        scales = self.mean.scales.detach() if detach else self.mean.scales
        return scales[:, None] * self.mean.shape_forces(contacts)

    def as_dict(self) -> dict[str, list]:
        out = {"lengthscale_x": self.lengthscale[0, 0].tolist(), "lengthscale_z": self.lengthscale[1, 0].tolist(),
               "outputscale": self.outputscale.tolist(), "noise": self.noise.tolist()}
        if self.mean is not None:
            out["mean_scales"] = self.mean.scales.tolist()
        if self.li is not None:
            out["li_variance"] = self.li.variance.tolist()
            if self.li.generic:
                out["generic_variance"] = self.li.generic_variance.tolist()
        if self.spatial is not None:
            out["spatial_variance"] = self.spatial.variance.tolist()
            out["spatial_lengthscale_m"] = self.spatial.lengthscale.tolist()
        return out


class RFT3DHyperparameters(MapHyperparameters):
    """Kernel of the three maps (``AngleKernel`` with batch (3,): lengthscale (3, 1, 4), outputscale (3,) in
    (N/cm^3)^2) and the noise of the three force axes (a batched gpytorch ``GaussianLikelihood``, (3,) N^2).

    With ``alpha_y="constant"`` only the alpha_y outputscale is used for that map (the prior variance of the
    constant); its lengthscale has no gradient and stays where it is. ``li_basis``: ``li``, a
    ``LiBasisVariance`` (3,) (N/cm^3)^2 of Li et al.'s term per map (alpha_y's unused when it is a constant).
    ``lengthscale_floor``: every lengthscale is above it (``LENGTHSCALE_FLOOR_3D``; the constraint's buffer, so a model
    file from before it was raised loads with its own, 0.05).
    """

    n_maps = 3

    def __init__(self, alpha_y: str = "map", noise_floor: float = 1e-6, force_scale=1.0, map_scale=1.0,
                 li_basis: bool = False, lengthscale_floor: float = LENGTHSCALE_FLOOR_3D) -> None:
        super().__init__()
        if alpha_y not in ALPHA_Y:
            raise ValueError(f"alpha_y must be one of {ALPHA_Y}, got {alpha_y!r}")
        self.alpha_y = alpha_y
        fs = torch.as_tensor(force_scale, dtype=torch.get_default_dtype()).expand(3)
        ms = torch.as_tensor(map_scale, dtype=torch.get_default_dtype()).expand(3)
        self.kernel = AngleKernel(batch_shape=torch.Size([3]), lengthscale_constraint=GreaterThan(lengthscale_floor),
                                  outputscale_constraint=ScaledGreaterThan(0.0, ms.pow(2)))
        self.likelihood = GaussianLikelihood(batch_shape=torch.Size([3]),
                                             noise_constraint=ScaledGreaterThan(noise_floor, fs.pow(2).reshape(3, 1)))
        self.li = LiBasisVariance(scale=ms.pow(2), n_maps=3) if li_basis else None

    @property
    def lengthscale_floor(self) -> float:
        """The lengthscales' lower bound (the constraint's buffer: a state dict, hence a model file, carries it)."""
        return float(self.kernel.base_kernel.raw_lengthscale_constraint.lower_bound)

    def li_of(self, c: int, detach: bool) -> Tensor | None:
        """() map c's Li et al.'s variance, or None (no term, or a constant alpha_y)."""
        if self.li is None or self.constant_map(c):
            return None
        v = self.li.variance[c]
        return v.detach() if detach else v

    @property
    def prior_variance(self) -> Tensor:
        """(3,) each map's prior variance at any angle pair, (N/cm^3)^2: the outputscale, plus Li et al.'s v where
        the map has the term (|f(theta)|^2 = 1, ``gp.kernels.li_basis``)."""
        s = self.outputscale
        if self.li is None:
            return s
        keep = torch.tensor([not self.constant_map(c) for c in range(3)], device=s.device)
        return s + torch.where(keep, self.li.variance, torch.zeros_like(s))

    def constant_map(self, c: int) -> bool:
        """Whether map c is a constant (alpha_y with ``alpha_y="constant"``)."""
        return c == 1 and self.alpha_y == "constant"

    def hyper_labels(self, name: str, shape: torch.Size) -> list[str]:
        """Readable names of a raw parameter's coordinates (``gp.hyper.posterior.hyper_spec``):
        ``lengthscale_{x,y,z}[sin2b|cos2b|sing|cosg]``, ``outputscale_{x,y,z}`` (the maps alpha_x, alpha_y,
        alpha_z) and ``noise_{x,y,z}`` (the force axes F_x, F_y, F_z)."""
        base = {"kernel.base_kernel.raw_lengthscale": "lengthscale", "kernel.raw_outputscale": "outputscale",
                "likelihood.noise_covar.raw_noise": "noise", "li.raw_variance": "li_variance"}.get(name)
        if base is None:
            raise ValueError(f"no label for the 3-D hyperparameter {name!r}")
        if base == "lengthscale":
            dims = ("sin2b", "cos2b", "sing", "cosg")
            return [f"lengthscale_{'xyz'[i // 4]}[{dims[i % 4]}]" for i in range(shape.numel())]
        return [f"{base}_{a}" for a in "xyz"]

    def fixed_labels(self) -> list[str]:
        """Coordinates no likelihood sees: alpha_y's lengthscales when alpha_y is a constant (a hyperparameter
        posterior leaves them where they are), and its Li et al.'s variance."""
        if self.alpha_y != "constant":
            return []
        return self.hyper_labels("kernel.base_kernel.raw_lengthscale", torch.Size([12]))[4:8] + \
            (["li_variance_y"] if self.li is not None else [])

    def as_dict(self) -> dict[str, list | str]:
        ls = self.lengthscale.detach()
        out: dict[str, list | str] = {"lengthscale_x": ls[0, 0].tolist(), "lengthscale_z": ls[2, 0].tolist(),
               "outputscale": self.outputscale.tolist(), "noise": self.noise.tolist(), "alpha_y": self.alpha_y}
        if self.alpha_y == "map":
            out["lengthscale_y"] = ls[1, 0].tolist()
        if self.li is not None:  # a constant alpha_y has no term: its entry (unused) is left out
            v = self.li.variance.tolist()
            out["li_variance"] = [v[0], v[2]] if self.alpha_y == "constant" else v
        return out
