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


def _direct_errors(ls: torch.Tensor, n: int) -> torch.Tensor:
    """e_n (rows,) written out for lengthscale rows (rows, 2): max over the grid and between its nodes."""
    x = torch.arange(GRID, dtype=torch.float64) * (2 * math.pi / GRID)
    x = torch.cat([x, x + math.pi / GRID])
    psi = fourier_features(x, n)
    return torch.stack([(1 - torch.einsum("pi,ij,pj->p", psi, factor_coefficients(r, n), psi)).abs().max()
                        for r in ls])


def test_remembered_errors_survive_a_full_store(monkeypatch):
    """The errors remembered by value: a batch mixing the oldest remembered row with new ones, once the store is full,
    gives each row's own errors (an entry evicted while its batch is answered would lose it), a smaller n_max is cut
    from a larger one, and a larger one is computed anew."""
    from irft_torch.gp.kernels import fourier

    monkeypatch.setattr(fourier, "_ERRORS_KEPT", 16)  # batches of up to 4 rows are remembered
    monkeypatch.setattr(fourier, "_ERRORS", type(fourier._ERRORS)())
    g = torch.Generator().manual_seed(0)
    rows = 0.2 + torch.rand(20, 2, generator=g, dtype=torch.float64)
    truncation_errors(rows[:1], 6)  # the oldest
    for i in range(1, 16, 4):  # the store is full
        truncation_errors(rows[i:min(i + 4, 16)], 6)
    assert len(fourier._ERRORS) == 16
    pick = [0, 16, 17, 18]  # the oldest again, with three new rows: three evicted
    got = truncation_errors(rows[pick], 6)
    torch.testing.assert_close(got[:, 6], _direct_errors(rows[pick], 6), rtol=1e-9, atol=1e-14)
    torch.testing.assert_close(truncation_errors(rows[[17]], 3)[:, 3], _direct_errors(rows[[17]], 3),
                               rtol=1e-9, atol=1e-14)
    torch.testing.assert_close(truncation_errors(rows[[17]], 9)[:, 9], _direct_errors(rows[[17]], 9),
                               rtol=1e-9, atol=1e-14)
    assert len(fourier._ERRORS) == 16
