"""The angle embedding and its RBF: the one place where the kernel's numbers are computed.

phi(beta, gamma) = (sin 2beta, cos 2beta, sin gamma, cos gamma): period pi in beta (a segment turned
by pi is the same segment), period 2 pi in gamma. The kernel of both maps is an ARD RBF on phi,

    k(theta, theta') = s exp(-1/2 sum_d (phi_d(theta) - phi_d(theta'))^2 / l_d^2),

held by a stock ``ScaleKernel(RBFKernel(ard_num_dims=4, batch_shape=[2]))`` (see ``kernels``); every
backend evaluates it through :func:`rbf` on embeddings divided by the lengthscales.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["embed_angles", "rbf"]


def embed_angles(beta: Tensor, gamma: Tensor) -> Tensor:
    """phi(beta, gamma) = (sin 2beta, cos 2beta, sin gamma, cos gamma): angles (...) in rad -> (..., 4)."""
    return torch.stack([torch.sin(2 * beta), torch.cos(2 * beta), torch.sin(gamma), torch.cos(gamma)], dim=-1)


def rbf(a: Tensor, b: Tensor, outputscale: Tensor, out: Tensor | None = None) -> Tensor:
    """outputscale * exp(-|a_i - b_j|^2 / 2) for inputs already divided by the lengthscales:
    a (..., n, D), b (..., m, D), outputscale broadcastable to (..., 1, 1) -> (..., n, m); written into ``out``
    (n, m) where given (a buffer reused over many kernels: no fresh block each, no autograd).

    One matmul of augmented vectors gives the exponent: [a, log s - |a|^2/2, 1] . [b, 1, -|b|^2/2]
    = log s - |a - b|^2 / 2, then one exp: two passes over the (n, m) block instead of six.
    """
    outputscale = torch.as_tensor(outputscale, dtype=a.dtype, device=a.device)
    log_s = torch.log(outputscale).expand(*a.shape[:-2], 1, 1).expand(*a.shape[:-1], 1)
    one_a = torch.ones_like(a[..., :1])
    one_b = torch.ones_like(b[..., :1])
    a_aug = torch.cat([a, log_s - 0.5 * a.pow(2).sum(-1, keepdim=True), one_a], dim=-1)
    b_aug = torch.cat([b, one_b, -0.5 * b.pow(2).sum(-1, keepdim=True)], dim=-1)
    if out is not None:
        return torch.matmul(a_aug, b_aug.mT, out=out).exp_()
    return (a_aug @ b_aug.mT).exp_()  # in place: no second (n, m) buffer (autograd keeps exp's result either way)
