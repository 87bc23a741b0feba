r"""Li et al.'s own basis as a kernel term (``MapPrior(kernel="li")``, ``InverseRFT``'s default; docs/calibration.md).

Li, Zhang & Goldman (Science 2013) fit the stress-per-depth maps of every medium they measured with the
9 functions {1, cos 2beta, sin 2beta} x {1, cos gamma, sin gamma}. The RBF on the embedding
(sin 2beta, cos 2beta, sin gamma, cos gamma) gives their products (sin 2beta cos gamma, ...) almost no prior
variance once its lengthscales are long (a smooth map), so a medium whose map differs from the data's
mostly in those directions is extrapolated with false confidence (``experiments/calibration/fourier_kernel_term.py``).
This term gives the 9 functions a prior variance of their own, one per map:

.. math::
    k_{Li}(\theta, \theta') = v \, \tfrac14 (1 + \cos 2(\beta - \beta')) (1 + \cos(\gamma - \gamma'))
                            = v \, f(\theta)^\top f(\theta'),

with f the 9 functions divided by 2 (``li_features``). It is a rank-9 kernel: every backend adds
(W f) diag(v) (W f)^T to the force covariance, W f (2, N, 9) the features summed with the contacts' weights
(``contact_li_features``). v (2,) is in (N/cm^3)^2, a hyperparameter like the outputscale, with a log-normal
prior at the outputscale's centre (``gp.kernels.priors``).

**The generic shape with an uncertain scale** (``InverseRFT(..., prior=MapPrior(kernel="li+generic"))``). Li et al.
found that the media they measured share one generic map g_a (``FourierStressMap.generic``) up to a scale per
medium. That shape is one direction in the span of the 9 functions, g_a(theta) = f(theta) . c_a
(``generic_coefficients``), and the term above gives it no more prior variance than any other direction. Adding
u_a g_a(theta) g_a(theta') is a mean m_a g_a with m_a ~ N(0, u_a) integrated out exactly (Rasmussen & Williams
2006, section 2.7): the 9 coefficients' prior covariance per map becomes

.. math::
    P_a = \operatorname{diag}(v_a) + u_a c_a c_a^\top,

so every backend adds (W f) P_a (W f)^T (``LiBasisVariance.weigh``). u (2,) in (N/cm^3)^2 has a log-normal prior at the
medium's zeta squared (``gp.kernels.priors``). docs/calibration.md has the evidence (the rotating leg's alpha_z).
"""

from __future__ import annotations

import functools

import torch
from gpytorch import Module
from torch import Tensor

from .constraints import ScaledGreaterThan
from .fourier import FourierBasis

__all__ = ["LI_VARIANCE", "LI_GENERIC", "LiBasisVariance", "li_features", "weighted_li_features",
           "contact_li_features", "generic_coefficients", "generic_features", "li_index", "with_li_functions"]

LI_VARIANCE = "li.raw_variance"  # the raw parameter's name in ``RFTHyperparameters``; value (*S, 2)
LI_GENERIC = "li.raw_generic_variance"  # the generic shape's variance u (``kernel="li+generic"``); value (*S, 2)


FIRST_HARMONICS = FourierBasis(1, 1)  # the spectral basis' own first harmonics: the same 9 functions, same order


def li_features(beta: Tensor, gamma: Tensor) -> Tensor:
    """The 9 functions {1, cos 2beta, sin 2beta} x {1, cos gamma, sin gamma} / 2 at angles (...,) in
    radians: (..., 9), ordered beta-major as the spectral basis (``FourierBasis(1, 1)``, the first 3 x 3 of
    any larger one). f(theta) . f(theta') = (1 + cos 2(dbeta)) (1 + cos dgamma) / 4."""
    b, g = FIRST_HARMONICS.features(beta, gamma)  # (..., 3) each: (1, cos x, sin x)
    return 0.5 * (b[..., :, None] * g[..., None, :]).flatten(-2)


def weighted_li_features(beta: Tensor, gamma: Tensor, weight: Tensor) -> Tensor:
    """(*batch, N, 9): sum_m w[t, m] f(beta[t, m], gamma[t, m]) for segments (N, M) (or with the batch of
    the weights, e.g. (2, N, M) for the x and z weights) (cm^3 per function): the term's features of each
    weighted sum (a force, or a map value)."""
    return torch.einsum("...nm,...nmk->...nk", weight, li_features(beta, gamma))


def contact_li_features(contacts) -> Tensor:
    """(2, N, 9): ``weighted_li_features`` of contacts (N, M) with their x and z weights."""
    return weighted_li_features(contacts.beta, contacts.gamma, torch.stack([contacts.weight_x, contacts.weight_z]))


def with_li_functions(basis: FourierBasis) -> FourierBasis:
    """``basis`` grown to hold the 9 functions (at least one harmonic of 2 beta and of gamma): where a model has
    the term, its spectral basis never drops them, however long its lengthscales."""
    return FourierBasis(max(basis.n_beta, 1), max(basis.n_gamma, 1))


def li_index(basis: FourierBasis, device=None) -> Tensor:
    """(9,) the positions of the 9 functions in a Fourier basis' beta-major features (``gp.kernels.fourier``; the basis
    needs n_beta, n_gamma >= 1): there the term is diagonal, v / 4 on those weights (f = the functions / 2)."""
    Fg = basis.sizes[1]
    return (torch.arange(3, device=device)[:, None] * Fg + torch.arange(3, device=device)[None, :]).reshape(-1)


@functools.cache
def _generic_coefficients_f64() -> Tensor:
    from ...rft.stress_maps import FourierStressMap

    x = torch.linspace(-torch.pi, torch.pi, 13, dtype=torch.float64)[:-1]
    beta, gamma = (t.reshape(-1) for t in torch.meshgrid(x / 2, x, indexing="ij"))
    F = li_features(beta, gamma)  # (144, 9): a full period of 2 beta and of gamma
    g = FourierStressMap.generic().to(torch.float64)(beta, gamma)  # (144, 2)
    c = torch.linalg.lstsq(F, g).solution  # (9, 2)
    if float((F @ c - g).abs().max()) > 1e-10:  # the generic map is in the span: exact
        raise AssertionError("the generic map is not a combination of Li et al.'s 9 functions")
    return c.T.contiguous()


def generic_coefficients(dtype=None, device=None) -> Tensor:
    """(2, 9) c_a with Li et al.'s generic map (``FourierStressMap.generic``, per unit zeta) g_a(theta) =
    ``li_features``(theta) . c_a, x then z (dimensionless; exact: the map is in the 9 functions' span)."""
    return _generic_coefficients_f64().to(dtype=dtype or torch.get_default_dtype(), device=device)


def generic_features(features: Tensor, n_maps: int = 2) -> Tensor:
    """(n_maps, ..., N, 1): the generic shape's value (or weighted sum) g_a = f . c_a per map, from features
    (n_maps, ..., N, 9) or (N, 9) (shared by every map): the generic term's one feature per map. ``n_maps``: 2 (x, z),
    or 2B for B models stacked (``gp.batch_fit``: x, z of model 0, then of model 1, ...)."""
    c = generic_coefficients(features.dtype, features.device).repeat(n_maps // 2, 1)  # (n_maps, 9)
    if features.dim() == 2:
        return (features @ c.T).mT[..., None]  # (n_maps, N, 1)
    return features @ c.reshape(n_maps, *([1] * (features.dim() - 3)), 9, 1)


class LiBasisVariance(Module):
    """The term's prior variance per map, v (2,) in (N/cm^3)^2, and with ``generic``, the generic shape's u (2,)
    too, each positive through ``ScaledGreaterThan`` (measured in the data's map scale, like the outputscale).
    A gpytorch ``Module``: its priors are registered on it (``gp.kernels.priors``) and it is saved in state dicts."""

    def __init__(self, scale=1.0, n_maps: int = 2, generic: bool = False) -> None:
        """``scale``: the data's map scale squared per map ((N/cm^3)^2); ``n_maps``: 2 (x, z), or 2B for B models
        stacked (``gp.batch_fit``; the 3-D model's 3 maps have no generic shape); ``generic``: add the generic
        shape's variance u (module docstring)."""
        super().__init__()
        if generic and n_maps % 2:
            raise ValueError(f"the generic shape has an x and a z map per model: n_maps must be even, got {n_maps}")
        scale = torch.as_tensor(scale, dtype=torch.get_default_dtype()).expand(n_maps).clone()
        self.register_parameter("raw_variance", torch.nn.Parameter(torch.zeros(n_maps)))
        self.register_constraint("raw_variance", ScaledGreaterThan(0.0, scale))
        self.generic = bool(generic)
        if self.generic:
            self.register_parameter("raw_generic_variance", torch.nn.Parameter(torch.zeros(n_maps)))
            self.register_constraint("raw_generic_variance", ScaledGreaterThan(0.0, scale.clone()))

    @property
    def generic_variance(self) -> Tensor | None:
        """(n_maps,) u_x, u_z (per model when stacked) in (N/cm^3)^2: the generic shape's prior variance, or None
        without it."""
        if not self.generic:
            return None
        return self.raw_generic_variance_constraint.transform(self.raw_generic_variance)

    @generic_variance.setter
    def generic_variance(self, value) -> None:
        if not self.generic:
            raise AttributeError("this term has no generic shape (MapPrior(kernel='li+generic') not chosen)")
        value = torch.as_tensor(value, dtype=self.raw_generic_variance.dtype,
                                device=self.raw_generic_variance.device).expand(self.raw_generic_variance.shape)
        self.initialize(raw_generic_variance=self.raw_generic_variance_constraint.inverse_transform(value))

    @property
    def covariance(self) -> Tensor:
        """(n_maps, 9, 9) the 9 coefficients' prior covariance per map, P = diag(v) + u c c^T (without the generic
        shape, diag(v)), (N/cm^3)^2."""
        v = self.variance
        P = torch.diag_embed(v[:, None].expand(-1, 9))
        if self.generic:
            c = generic_coefficients(v.dtype, v.device).repeat(v.shape[0] // 2, 1)  # (n_maps, 9)
            P = P + self.generic_variance[:, None, None] * (c[:, :, None] * c[:, None, :])
        return P

    def weigh(self, features: Tensor, detach: bool = False) -> Tensor:
        """features P per map: (..., 2, N, 9) (or (N, 9)) -> (..., 2, N, 9), f diag(v) without the generic shape
        (9 products per row instead of 81), f P with it; ``f1 P f2^T = weigh(f1) @ f2.mT``. ``detach``: P as a
        constant (a prediction: differentiable in the features, i.e. the contacts, not the hyperparameters)."""
        if not self.generic:
            v = self.variance
            return features * (v.detach() if detach else v)[:, None, None]
        P = self.covariance
        return features @ (P.detach() if detach else P)

    def mean_variance(self) -> Tensor:
        """(n_maps,) the term's prior variance of a map averaged over the canonical square, (N/cm^3)^2:
        v (|f(theta)|^2 = 1 everywhere) plus u times the mean square of the generic shape there
        (``gp.kernels.priors.GENERIC_RMS``)."""
        v = self.variance
        if not self.generic:
            return v
        from .priors import GENERIC_RMS

        rms2 = torch.tensor(GENERIC_RMS, dtype=v.dtype, device=v.device).pow(2).repeat(v.shape[0] // 2)
        return v + self.generic_variance * rms2

    @property
    def variance(self) -> Tensor:
        """(n_maps,) v_x, v_z (per model when stacked) in (N/cm^3)^2."""
        return self.raw_variance_constraint.transform(self.raw_variance)

    @variance.setter
    def variance(self, value) -> None:
        value = torch.as_tensor(value, dtype=self.raw_variance.dtype,
                                device=self.raw_variance.device).expand(self.raw_variance.shape)
        self.initialize(raw_variance=self.raw_variance_constraint.inverse_transform(value))
