r"""Li et al.'s own basis as a kernel term (``InverseRFT(..., li_basis=True)``, docs/calibration.md).

Li, Zhang & Goldman (Science 2013) fit the stress-per-depth maps of every medium they measured with the
9 functions {1, cos 2beta, sin 2beta} x {1, cos gamma, sin gamma}. The RBF on the embedding
(sin 2beta, cos 2beta, sin gamma, cos gamma) gives their products (sin 2beta cos gamma, ...) almost no prior
variance once its lengthscales are long (a smooth map), so a medium whose map differs from the data's
mostly in those directions is extrapolated with false confidence (``experiments/fourier_kernel_term.py``).
This term gives the 9 functions a prior variance of their own, one per map:

.. math::
    k_{Li}(\theta, \theta') = v \, \tfrac14 (1 + \cos 2(\beta - \beta')) (1 + \cos(\gamma - \gamma'))
                            = v \, f(\theta)^\top f(\theta'),

with f the 9 functions divided by 2 (``li_features``). It is a rank-9 kernel: every backend adds
(W f) diag(v) (W f)^T to the force covariance, W f (2, N, 9) the features summed with the contacts' weights
(``contact_li_features``). v (2,) is in (N/cm^3)^2, a hyperparameter like the outputscale, with a log-normal
prior at the outputscale's centre (``gp.priors``).
"""

from __future__ import annotations

import torch
from gpytorch import Module
from torch import Tensor

from .constraints import ScaledGreaterThan
from .fourier import FourierBasis

__all__ = ["LI_VARIANCE", "LiBasisVariance", "li_features", "weighted_li_features", "contact_li_features",
           "li_covariance", "li_index", "with_li_functions"]

LI_VARIANCE = "li.raw_variance"  # the raw parameter's name in ``RFTHyperparameters``; value (*S, 2)


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
    """(9,) the positions of the 9 functions in a Fourier basis' beta-major features (``gp.fourier``; the basis
    needs n_beta, n_gamma >= 1): there the term is diagonal, v / 4 on those weights (f = the functions / 2)."""
    Fg = basis.sizes[1]
    return (torch.arange(3, device=device)[:, None] * Fg + torch.arange(3, device=device)[None, :]).reshape(-1)


def li_covariance(variance: Tensor, f1: Tensor, f2: Tensor) -> Tensor:
    """(*S, 2, N1, N2) = f1 diag(v) f2^T per map, for features (2, N, 9) (or (N, 9), shared by both maps)
    and v (*S, 2) in (N/cm^3)^2."""
    return (f1 * variance[..., None, None]) @ f2.mT


class LiBasisVariance(Module):
    """The term's prior variance per map, v (2,) in (N/cm^3)^2, positive through ``ScaledGreaterThan``
    (measured in the data's map scale, like the outputscale). A gpytorch ``Module``: its prior is
    registered on it (``gp.priors``) and it is saved in state dicts."""

    def __init__(self, scale=1.0, n_maps: int = 2) -> None:
        """``scale``: the data's map scale squared per map ((N/cm^3)^2); ``n_maps``: 2 (x, z), or 2B for B models
        stacked (``gp.batch_fit``)."""
        super().__init__()
        scale = torch.as_tensor(scale, dtype=torch.get_default_dtype()).expand(n_maps).clone()
        self.register_parameter("raw_variance", torch.nn.Parameter(torch.zeros(n_maps)))
        self.register_constraint("raw_variance", ScaledGreaterThan(0.0, scale))

    @property
    def variance(self) -> Tensor:
        """(n_maps,) v_x, v_z (per model when stacked) in (N/cm^3)^2."""
        return self.raw_variance_constraint.transform(self.raw_variance)

    @variance.setter
    def variance(self, value) -> None:
        value = torch.as_tensor(value, dtype=self.raw_variance.dtype,
                                device=self.raw_variance.device).expand(self.raw_variance.shape)
        self.initialize(raw_variance=self.raw_variance_constraint.inverse_transform(value))
