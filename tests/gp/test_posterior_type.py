"""One posterior type for every model (``gp.posterior.Posterior``): the planar model's (K = 2 axes) and the 3-D
model's (K = 3, with each point's axes' covariance), its mixture of covariances against a hand-computed one."""

import torch

from irft_torch.gp import Posterior
from irft_torch.gp.inverse3d import Posterior3D


def test_the_3d_posterior_is_the_one_posterior_type():
    assert Posterior3D is Posterior


def test_mixture_of_covariances_by_hand():
    """Two draws at one point, weights 0.25 / 0.75: mean = sum w m, covariance = sum w (C + (m - mean)(m - mean)^T),
    written out entry by entry."""
    m = torch.tensor([[[1.0, 2.0, 3.0]], [[3.0, 2.0, -1.0]]], dtype=torch.float64)  # (S=2, N=1, K=3)
    C = torch.stack([torch.diag(torch.tensor([1.0, 2.0, 3.0])), torch.tensor([[2.0, 0.5, 0.0], [0.5, 1.0, 0.0],
                                                                             [0.0, 0.0, 4.0]])]).double()[:, None]
    w = torch.tensor([0.25, 0.75], dtype=torch.float64)
    p = Posterior.of_covariances(m, C, w)
    mean = torch.tensor([2.5, 2.0, 0.0], dtype=torch.float64)  # 0.25 (1, 2, 3) + 0.75 (3, 2, -1)
    d0, d1 = m[0, 0] - mean, m[1, 0] - mean  # (-1.5, 0, 3), (0.5, 0, -1)
    cov = 0.25 * (C[0, 0] + torch.outer(d0, d0)) + 0.75 * (C[1, 0] + torch.outer(d1, d1))
    assert torch.allclose(p.mean[0], mean, atol=1e-15)
    assert torch.allclose(p.covariance[0], cov, atol=1e-14)
    assert torch.allclose(p.variance[0], torch.tensor([0.25 * 1 + 0.75 * 2 + 0.25 * 2.25 + 0.75 * 0.25,
                                                       0.25 * 2 + 0.75 * 1, 0.25 * 3 + 0.75 * 4 + 0.25 * 9 + 0.75 * 1],
                                                      dtype=torch.float64), atol=1e-14)
    lo, hi = p.interval(0.95)
    assert bool((lo < p.mean).all() and (p.mean < hi).all())
    one = Posterior.of_covariances(m[:1], C[:1], None)  # a plug-in: the plain Gaussian, no components
    assert one.components is None and torch.equal(one.variance[0], torch.tensor([1.0, 2.0, 3.0]).double())


def test_reshape_and_to_keep_every_part():
    m = torch.randn(3, 6, 3, dtype=torch.float64)
    A = torch.randn(3, 6, 3, 3, dtype=torch.float64)
    p = Posterior.of_covariances(m, A @ A.mT, torch.tensor([0.2, 0.3, 0.5], dtype=torch.float64))
    q = p.reshape(2, 3).to(torch.float32)
    assert q.mean.shape == (2, 3, 3) and q.covariance.shape == (2, 3, 3, 3) and q.components[0].shape == (3, 2, 3, 3)
    assert q.mean.dtype == q.covariance.dtype == q.components[1].dtype == torch.float32
    assert torch.allclose(q.covariance.double().reshape(6, 3, 3), p.covariance, rtol=1e-6)
