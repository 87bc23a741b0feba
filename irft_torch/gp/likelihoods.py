"""Gaussian force-noise likelihood for the (x, z) batch of composite observations."""

from __future__ import annotations

import torch
from gpytorch.constraints import GreaterThan, Interval
from gpytorch.likelihoods import _GaussianLikelihoodBase
from gpytorch.likelihoods.noise_models import Noise
from linear_operator.operators import DiagLinearOperator
from torch import Tensor

__all__ = ["ForceNoise", "ForceNoiseLikelihood"]


class ForceNoise(Noise):
    """Homoskedastic noise variance per force axis (N^2), or one shared by both (``tied``).

    ``noise`` has shape (2,) = (sigma_x^2, sigma_z^2) either way; tied, both are one parameter.
    """

    def __init__(self, tied: bool = False, noise_constraint: Interval | None = None) -> None:
        super().__init__()
        self.tied = bool(tied)
        self.register_parameter("raw_noise", torch.nn.Parameter(torch.zeros(1 if tied else 2)))
        self.register_constraint("raw_noise", noise_constraint or GreaterThan(1e-6))

    @property
    def noise(self) -> Tensor:
        return self.raw_noise_constraint.transform(self.raw_noise).expand(2)

    @noise.setter
    def noise(self, value) -> None:
        value = torch.as_tensor(value, dtype=self.raw_noise.dtype, device=self.raw_noise.device)
        value = value.expand(2).mean(0, keepdim=True) if self.tied else value.expand(2)
        lower = getattr(self.raw_noise_constraint, "lower_bound", torch.tensor(0.0))
        value = torch.maximum(value, lower.to(value) * 1.0001)
        self.initialize(raw_noise=self.raw_noise_constraint.inverse_transform(value))

    def forward(self, *params, shape: torch.Size | None = None, **kwargs) -> DiagLinearOperator:
        if shape is None or len(shape) < 2 or shape[-2] != 2:
            raise ValueError(f"ForceNoise expects the (x, z) batch shape (..., 2, T), got {shape}")
        return DiagLinearOperator(self.noise[:, None].expand(*shape))


class ForceNoiseLikelihood(_GaussianLikelihoodBase):
    r"""F_c = (W_c alpha_c) + eps_c, eps_c ~ N(0, sigma_c^2), c in (x, z).

    Per-axis noise by default; ``tied=True`` shares one variance as the I-RFT paper does.
    Works with gpytorch's ``ExactMarginalLogLikelihood``.

    Example:
        >>> lik = ForceNoiseLikelihood(tied=True)
        >>> lik.noise            # (2,), N^2
    """

    def __init__(self, tied: bool = False, noise_constraint: Interval | None = None) -> None:
        super().__init__(noise_covar=ForceNoise(tied=tied, noise_constraint=noise_constraint))

    @property
    def noise(self) -> Tensor:
        return self.noise_covar.noise

    @noise.setter
    def noise(self, value) -> None:
        self.noise_covar.noise = value

    @property
    def tied(self) -> bool:
        return self.noise_covar.tied

    def forward(self, function_samples: Tensor, *params, **kwargs):
        noise = self._shaped_noise_covar(function_samples.shape, *params, **kwargs).diagonal(dim1=-1, dim2=-2)
        return torch.distributions.Normal(function_samples, noise.sqrt())
