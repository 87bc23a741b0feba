"""The scorers' shared algebra (design.belief) against the dense formulas: the information gain from
slogdet(I + D^-1/2 S D^-1/2) and the variance after an observation from the explicit Gaussian conditional
(C^T (S + D)^-1 C by a dense solve), batched and with one noise per row; and the criterion check."""

import pytest
import torch

from irft_torch.design.belief import check_criterion, information_nats, variance_after, variance_fall

F64 = torch.float64


def _problem(seed=0, batch=(3,), n=5, N=4):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(*batch, n + N, n + N + 2, generator=g, dtype=F64)
    joint = A @ A.mT  # a joint covariance of the candidate's rows and the points
    S, C, V = joint[..., :n, :n], joint[..., :n, n:], joint[..., n:, n:]
    noise = 0.1 + torch.rand(*batch, n, generator=g, dtype=F64)
    return S, C, torch.diagonal(V, dim1=-2, dim2=-1), noise


def test_information_gain_is_the_log_determinant_with_a_noise_per_row():
    S, _, _, noise = _problem()
    d = noise.rsqrt()
    eye = torch.eye(S.shape[-1], dtype=F64)
    want = 0.5 * torch.linalg.slogdet(eye + d[..., :, None] * S * d[..., None, :])[1]
    torch.testing.assert_close(information_nats(S, noise), want, rtol=1e-12, atol=1e-12)
    # one noise for all rows broadcasts: the same as repeating it
    one = noise[..., :1]
    torch.testing.assert_close(information_nats(S, one), information_nats(S, one.expand_as(noise)), rtol=0, atol=0)


def test_variance_after_is_the_gaussian_conditional():
    S, C, v, noise = _problem(seed=1, batch=(2, 3))
    want = v - torch.diagonal(C.mT @ torch.linalg.solve(S + torch.diag_embed(noise), C), dim1=-2, dim2=-1)
    torch.testing.assert_close(variance_after(v, C, S, noise), want, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(variance_fall(C, S, noise), v - want, rtol=1e-10, atol=1e-12)
    assert (variance_fall(C, S, noise) > 0).all()  # an observation never adds variance


def test_the_criterion_is_checked_by_name():
    check_criterion("variance", None)
    check_criterion("eig", None)
    with pytest.raises(ValueError, match="criterion must be 'variance' or 'eig'"):
        check_criterion("entropy", None)
    with pytest.raises(ValueError, match="region applies to criterion 'variance'"):
        check_criterion("eig", object())
