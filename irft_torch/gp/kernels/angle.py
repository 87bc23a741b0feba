"""The kernel over stress-map angles (a stock gpytorch ScaleKernel(RBFKernel) on the embedding) and the
composite kernel over RFT-weighted observations (a lazy W K W^T)."""

from __future__ import annotations

import torch
from gpytorch.constraints import GreaterThan, Interval
from gpytorch.kernels import Kernel, RBFKernel, ScaleKernel
from linear_operator.operators import MatmulLinearOperator
from torch import Tensor

from .embedding import embed_angles, rbf
from .encoding import decode_rows
from .li_basis import contact_li_features, weighted_li_features
from .operators import RFTKernelLinearOperator

__all__ = ["embed_angles", "AngleKernel", "RFTCompositeKernel", "angle_covariance", "composite_covariance"]

BATCH = torch.Size([2])  # the (x, z) maps: a batch of two independent GPs


class AngleKernel(ScaleKernel):
    r"""``ScaleKernel(RBFKernel(ard_num_dims=4, batch_shape=[2]))`` on the angle embedding
    phi = (sin 2beta, cos 2beta, sin gamma, cos gamma): the stock gpytorch parts, so that priors,
    constraints and state dicts are gpytorch's own.

    .. math::
        k(\theta, \theta') = \sigma_f^2 \exp\Big(-\tfrac12 \sum_{d=1}^{4}
            (\phi_d(\theta) - \phi_d(\theta'))^2 / \ell_d^2\Big)

    Called on embeddings (..., n, 4) it is gpytorch's RBF. The backends evaluate it on angle
    pairs through :func:`irft_torch.gp.kernels.embedding.rbf` (one fused matmul), with this module's
    ``lengthscale`` (2, 1, 4) and ``outputscale`` (2,) ((N/cm^3)^2); a test checks the two agree.

    Args:
        batch_shape: default (2,) = the x and z maps.
        lengthscale_constraint: default ``GreaterThan(0.05)``.

    Example:
        >>> k = AngleKernel()
        >>> k.lengthscale.shape, k.outputscale.shape
        (torch.Size([2, 1, 4]), torch.Size([2]))
    """

    def __init__(self, batch_shape: torch.Size = BATCH, lengthscale_constraint: Interval | None = None,
                 lengthscale_prior=None, outputscale_prior=None,
                 outputscale_constraint: Interval | None = None) -> None:
        base = RBFKernel(ard_num_dims=4, batch_shape=batch_shape,
                         lengthscale_constraint=lengthscale_constraint or GreaterThan(0.05),
                         lengthscale_prior=lengthscale_prior)
        super().__init__(base, batch_shape=batch_shape, outputscale_prior=outputscale_prior,
                         outputscale_constraint=outputscale_constraint)

    @property
    def lengthscale(self) -> Tensor:
        """(*batch, 1, 4): lengthscales of (sin 2beta, cos 2beta, sin gamma, cos gamma), dimensionless."""
        return self.base_kernel.lengthscale

    @lengthscale.setter
    def lengthscale(self, value) -> None:
        value = torch.as_tensor(value, dtype=self.raw_outputscale.dtype, device=self.raw_outputscale.device)
        self.base_kernel.lengthscale = value.expand_as(self.base_kernel.raw_lengthscale)

    def scaled_embedding(self, beta: Tensor, gamma: Tensor) -> Tensor:
        """phi / lengthscale: angles (n,) -> (*batch, n, 4)."""
        return embed_angles(beta, gamma) / self.lengthscale


def angle_covariance(kernel: AngleKernel, beta1: Tensor, gamma1: Tensor, beta2: Tensor, gamma2: Tensor) -> Tensor:
    """Prior covariance of the two maps between angle pairs (n1,) and (n2,): (2, n1, n2)."""
    return rbf(kernel.scaled_embedding(beta1, gamma1), kernel.scaled_embedding(beta2, gamma2),
               kernel.outputscale[..., None, None])


def composite_covariance(kernel: AngleKernel, c1, c2=None, li=None):
    """Lazy prior covariance (2, N1, N2) of the weighted sums of two sets of contacts (N, M) (c2 None:
    of c1 with itself), x and z axes, at the kernel's current hyperparameters (no gradient in them;
    differentiable in the contacts). ``li``: a ``LiBasisVariance`` whose rank-9 term (``gp.kernels.li_basis``, with the
    generic shape where it has one: (W f) P (W f)^T) is added (the sum of the two operators), or None."""
    ls, os = kernel.lengthscale.detach(), kernel.outputscale.detach()
    w1 = torch.stack([c1.weight_x, c1.weight_z])
    if c2 is None:
        op = RFTKernelLinearOperator.from_segments(c1.beta[None], c1.gamma[None], w1, c1.beta[None], c1.gamma[None],
                                                   w1, ls, os, BATCH, same_inputs=True)
    else:
        w2 = torch.stack([c2.weight_x, c2.weight_z])
        op = RFTKernelLinearOperator.from_segments(c1.beta[None], c1.gamma[None], w1, c2.beta[None], c2.gamma[None],
                                                   w2, ls, os, BATCH)
    if li is None:
        return op
    f1 = contact_li_features(c1)
    f2 = f1 if c2 is None else contact_li_features(c2)
    return op + MatmulLinearOperator(li.weigh(f1, detach=True), f2.mT)


class RFTCompositeKernel(Kernel):
    r"""Covariance of RFT-weighted sums of a GP map: rows of ``(beta_1..M, gamma_1..M, w_1..M)``.

    For rows i, j:  k(i, j) = sum_{m, m'} w_im w_jm' k_base(theta_im, theta_jm').  Stacked, this is
    :math:`W K W^\top`, returned lazily as an :class:`RFTKernelLinearOperator` that never forms W
    nor the segment-by-segment product with it. Zero-weight segments (above the surface,
    padding) are dropped before any kernel evaluation; repeated angle pairs (e.g. an I-toe's
    segments) are evaluated once when no input needs a gradient.

    Args:
        base_kernel: the :class:`AngleKernel` (its hyperparameters are this kernel's).
        li: a ``LiBasisVariance``: Li et al.'s rank-9 term (``gp.kernels.li_basis``) is added, (W f) P (W f)^T with
            P = diag(v) (+ u c c^T, the generic shape),
            differentiable in its variance; None (default): the RBF alone.

    Example:
        >>> kern = RFTCompositeKernel(AngleKernel())
        >>> rows = encode_rows(beta, gamma, weight)          # (T, 3M)
        >>> K = kern(rows)                                   # lazy (2, T, T)
    """

    def __init__(self, base_kernel: AngleKernel, li=None, **kwargs) -> None:
        super().__init__(batch_shape=base_kernel.batch_shape, **kwargs)
        self.base_kernel = base_kernel
        self.li = li
        self._structure_key: tuple | None = None
        self._structure: dict | None = None

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, last_dim_is_batch: bool = False, **params):
        if last_dim_is_batch:
            raise NotImplementedError("RFTCompositeKernel does not support last_dim_is_batch")
        b1, g1, w1 = decode_rows(x1)
        b2, g2, w2 = decode_rows(x2)
        if diag:
            out = _composite_diag(self.base_kernel, b1, g1, w1, b2, g2, w2)
            if self.li is not None:
                f1, f2 = weighted_li_features(b1, g1, w1), weighted_li_features(b2, g2, w2)
                out = out + (self.li.weigh(f1) * f2).sum(-1)
            return out
        batch = torch.broadcast_shapes(x1.shape[:-2], x2.shape[:-2], self.batch_shape)
        # The index structure (compressed segments, distinct angle pairs) depends only on the
        # inputs, not on the hyperparameters: reuse it while the same input tensors come back
        # (every training step).
        # The key holds the input tensors themselves (not their ids, which a freed tensor's successor
        # may reuse) and their versions.
        key = (x1, x1._version, x2, x2._version, batch)
        old = self._structure_key
        hit = old is not None and old[0] is x1 and old[2] is x2 and old[1:2] == key[1:2] and old[3:] == key[3:]
        if not hit or x1.requires_grad or x2.requires_grad:
            structure = RFTKernelLinearOperator.segment_structure(
                b1, g1, w1, b2, g2, w2, batch, same_inputs=x1 is x2 or (x1.shape == x2.shape and torch.equal(x1, x2)))
            if not (x1.requires_grad or x2.requires_grad):
                self._structure_key, self._structure = key, structure
        else:
            structure = self._structure
        op = RFTKernelLinearOperator.from_structure(
            structure, self.base_kernel.lengthscale, self.base_kernel.outputscale, batch)
        if self.li is None:
            return op
        f1, f2 = weighted_li_features(b1, g1, w1), weighted_li_features(b2, g2, w2)
        return op + MatmulLinearOperator(self.li.weigh(f1), f2.mT)

    def num_outputs_per_input(self, x1: Tensor, x2: Tensor) -> int:
        return 1


def _composite_diag(base: AngleKernel, b1, g1, w1, b2, g2, w2) -> Tensor:
    """Row-wise sum_{m, m'} w1_m w2_m' k(theta1_m, theta2_m'), shape (*batch, T)."""
    ls = base.lengthscale.unsqueeze(-2)  # (*batch, 1, 1, 4)
    a = embed_angles(b1, g1) / ls
    b = embed_angles(b2, g2) / ls
    k = rbf(a, b, base.outputscale[..., None, None, None])  # (*batch, T, M, M)
    return (w1[..., :, None] * k * w2[..., None, :]).sum((-1, -2))

