"""The Fourier basis's truncation errors against the quantity they stand for, written out: the largest
gap k(x, x) - psi_n(x)^T C_n psi_n(x) over the grid and between its nodes, one n at a time."""

import math

import pytest
import torch

from irft_torch.gp.kernels.fourier import GRID, factor_coefficients, fourier_features, harmonics_for, truncation_errors


@pytest.mark.parametrize("ls", [(0.3, 0.5), (1.0, 1.0), (2.5, 0.8)])
def test_truncation_errors_are_the_leading_blocks_gaps(ls):
    ls = torch.tensor(ls, dtype=torch.float64)
    n_max = 14
    got = truncation_errors(ls, n_max)
    x = torch.arange(GRID, dtype=torch.float64) * (2 * math.pi / GRID)
    x = torch.cat([x, x + math.pi / GRID])
    C = factor_coefficients(ls, n_max)
    psi = fourier_features(x, n_max)
    for n in range(n_max + 1):
        k = 2 * n + 1
        q = torch.einsum("pi,ij,pj->p", psi[:, :k], C[:k, :k], psi[:, :k])
        assert got[n].item() == pytest.approx((1 - q).abs().max().item(), rel=1e-9, abs=1e-14)
    n, e = harmonics_for(ls[None], 1e-6)
    full = truncation_errors(ls)
    assert full[n] <= 1e-6 and (n == 1 or full[n - 1] > 1e-6) and e == pytest.approx(full[n].item())
