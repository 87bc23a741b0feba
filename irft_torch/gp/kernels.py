"""Kernels over the stress-map angles and over composite (RFT-weighted) observations."""

from __future__ import annotations

import torch
from gpytorch.constraints import GreaterThan, Interval, Positive
from gpytorch.kernels import Kernel
from torch import Tensor

from .encoding import decode_rows
from .operators import RFTKernelLinearOperator, rbf

__all__ = ["embed_angles", "AngleRBFKernel", "RFTCompositeKernel"]


def embed_angles(beta: Tensor, gamma: Tensor) -> Tensor:
    """phi(beta, gamma) = (sin 2beta, cos 2beta, sin gamma, cos gamma), shape S + (4,).

    Period pi in beta (a segment is the same segment turned by pi), period 2 pi in gamma.
    """
    return torch.stack([torch.sin(2 * beta), torch.cos(2 * beta), torch.sin(gamma), torch.cos(gamma)], dim=-1)


class AngleRBFKernel(Kernel):
    r"""ARD RBF on the angle embedding, with its own signal variance:

    .. math::
        k(\theta, \theta') = \sigma_f^2 \exp\Big(-\tfrac12 \sum_{d=1}^{4}
            (\phi_d(\theta) - \phi_d(\theta'))^2 / \ell_d^2\Big)

    Inputs are angle pairs ``(..., n, 2)`` = (beta, gamma) in rad. Hyperparameters: ``lengthscale``
    (*batch, 1, 4) (>= 0.05 by default) and ``outputscale`` (*batch,) in (N/cm^3)^2.

    Example:
        >>> k = AngleRBFKernel(batch_shape=torch.Size([2]))
        >>> k(torch.zeros(5, 2), torch.ones(3, 2)).shape
        torch.Size([2, 5, 3])
    """

    has_lengthscale = True

    def __init__(self, batch_shape: torch.Size = torch.Size(), lengthscale_constraint: Interval | None = None,
                 outputscale_constraint: Interval | None = None, **kwargs) -> None:
        super().__init__(ard_num_dims=4, batch_shape=batch_shape,
                         lengthscale_constraint=lengthscale_constraint or GreaterThan(0.05), **kwargs)
        self.register_parameter("raw_outputscale", torch.nn.Parameter(torch.zeros(*batch_shape)))
        self.register_constraint("raw_outputscale", outputscale_constraint or Positive())
        self.outputscale = 1.0

    @property
    def outputscale(self) -> Tensor:
        return self.raw_outputscale_constraint.transform(self.raw_outputscale)

    @outputscale.setter
    def outputscale(self, value) -> None:
        value = torch.as_tensor(value, dtype=self.raw_outputscale.dtype, device=self.raw_outputscale.device)
        self.initialize(raw_outputscale=self.raw_outputscale_constraint.inverse_transform(value))

    def scaled_embedding(self, beta: Tensor, gamma: Tensor) -> Tensor:
        """phi / lengthscale, shape (*batch, n, 4) for angles (..., n)."""
        return embed_angles(beta, gamma) / self.lengthscale

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, last_dim_is_batch: bool = False, **params):
        if last_dim_is_batch:
            raise NotImplementedError("AngleRBFKernel does not support last_dim_is_batch")
        a = self.scaled_embedding(x1[..., 0], x1[..., 1])
        b = self.scaled_embedding(x2[..., 0], x2[..., 1])
        os = self.outputscale[..., None]
        if diag:
            return os * torch.exp(-0.5 * (a - b).pow(2).sum(-1))
        return rbf(a, b, os[..., None])


class RFTCompositeKernel(Kernel):
    r"""Covariance of RFT-weighted sums of a GP map: rows of ``(beta_1..M, gamma_1..M, w_1..M)``.

    For rows i, j:  k(i, j) = sum_{m, m'} w_im w_jm' k_base(theta_im, theta_jm').  Stacked, this is
    :math:`W K W^\top`, returned lazily as an :class:`RFTKernelLinearOperator` that never forms W
    nor the segment-by-segment product with it. Zero-weight segments (above the surface,
    padding) are dropped before any kernel evaluation; repeated angle pairs (e.g. an I-toe's
    segments) are evaluated once when no input needs a gradient.

    Args:
        base_kernel: the kernel over angles, an :class:`AngleRBFKernel` (its hyperparameters are
            this kernel's hyperparameters).

    Example:
        >>> kern = RFTCompositeKernel(AngleRBFKernel())
        >>> rows = encode_rows(beta, gamma, weight)          # (T, 3M)
        >>> K = kern(rows)                                   # lazy (T, T)
    """

    def __init__(self, base_kernel: AngleRBFKernel, **kwargs) -> None:
        super().__init__(batch_shape=base_kernel.batch_shape, **kwargs)
        self.base_kernel = base_kernel
        self._structure_key, self._structure = None, None

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, last_dim_is_batch: bool = False, **params):
        if last_dim_is_batch:
            raise NotImplementedError("RFTCompositeKernel does not support last_dim_is_batch")
        b1, g1, w1 = decode_rows(x1)
        b2, g2, w2 = decode_rows(x2)
        if diag:
            return _composite_diag(self.base_kernel, b1, g1, w1, b2, g2, w2)
        batch = torch.broadcast_shapes(x1.shape[:-2], x2.shape[:-2], self.batch_shape)
        # The index structure (compressed segments, distinct angle pairs) depends only on the
        # inputs, not on the hyperparameters: reuse it while the same input tensors come back
        # (every training step).
        key = (id(x1), x1._version, id(x2), x2._version, tuple(x1.shape), tuple(x2.shape), batch,
               x1.requires_grad or x2.requires_grad)
        if self._structure_key != key or x1.requires_grad or x2.requires_grad:
            structure = RFTKernelLinearOperator.segment_structure(
                b1, g1, w1, b2, g2, w2, batch, same_inputs=x1 is x2 or (x1.shape == x2.shape and torch.equal(x1, x2)))
            if not (x1.requires_grad or x2.requires_grad):
                self._structure_key, self._structure = key, structure
        else:
            structure = self._structure
        return RFTKernelLinearOperator.from_structure(
            structure, self.base_kernel.lengthscale, self.base_kernel.outputscale, batch)

    def num_outputs_per_input(self, x1: Tensor, x2: Tensor) -> int:
        return 1


def _composite_diag(base: AngleRBFKernel, b1, g1, w1, b2, g2, w2) -> Tensor:
    """Row-wise sum_{m, m'} w1_m w2_m' k(theta1_m, theta2_m'), shape (*batch, T)."""
    ls = base.lengthscale.unsqueeze(-2)  # (*batch, 1, 1, 4)
    a = embed_angles(b1, g1) / ls
    b = embed_angles(b2, g2) / ls
    d2 = (a[..., :, None, :] - b[..., None, :, :]).pow(2).sum(-1)  # (*batch, T, M, M)
    k = base.outputscale[..., None, None, None] * torch.exp(-0.5 * d2)
    return (w1[..., :, None] * k * w2[..., None, :]).sum((-1, -2))
