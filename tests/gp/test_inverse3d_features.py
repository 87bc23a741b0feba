"""The 3-D spectral features (``gp.inverse3d.features``) against the sums written plainly: each sample's
sum_k w_k psi(2 beta_k) x psi(gamma_k) element by element, with repeated angle pairs and elements out of contact
(what the merging of equal pairs and the bank's larger pass must leave unchanged)."""

import torch

from irft_torch.gp.inverse3d.features import SpectralFeatureBank, _distinct_pairs, merged_rows, spectral_features
from irft_torch.gp.inverse3d.rows import BLOCKS, block_rows
from irft_torch.gp.kernels.fourier import FourierBasis, fourier_features
from irft_torch.rft import Contacts3D


def _contacts(T=5, K=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    pool_b = torch.rand(7, generator=g, dtype=torch.float64) * 3 - 1.5  # few angles: pairs repeat in a sample
    pool_g = torch.rand(5, generator=g, dtype=torch.float64) * 6 - 3
    beta = pool_b[torch.randint(0, 7, (T, K), generator=g)]
    gamma = pool_g[torch.randint(0, 5, (T, K), generator=g)]
    out = torch.rand(T, K, generator=g) < 0.4  # out of the sand: no weight on any map
    wx = torch.randn(T, K, 2, generator=g, dtype=torch.float64).masked_fill(out[..., None], 0)
    wy = torch.randn(T, K, 2, generator=g, dtype=torch.float64).masked_fill(out[..., None], 0)
    wz = torch.rand(T, K, generator=g, dtype=torch.float64).masked_fill(out, 0)
    return Contacts3D(beta, gamma, wx, wy, wz)


def _plain(c, b, basis):
    """The block's features element by element: rows axis-major (block.axes), maps side by side."""
    block = BLOCKS[b]
    weights = {0: c.weight_x, 1: c.weight_y}
    rows = []
    for a in block.axes:
        for t in range(len(c)):
            row = []
            for m in block.maps:
                w = c.weight_z[t] if m == 2 else weights[m][t, :, a]
                f = sum(w[k] * torch.outer(fourier_features(2 * c.beta[t, k], basis.n_beta),
                                           fourier_features(c.gamma[t, k], basis.n_gamma)).reshape(-1)
                        for k in range(c.shape[1]))
                row.append(f)
            rows.append(torch.cat(row))
    return torch.stack(rows)


def test_features_with_repeated_pairs_equal_the_plain_sums():
    c = _contacts()
    basis = FourierBasis(3, 2)
    for b in range(len(BLOCKS)):
        ref = _plain(c, b, basis)
        got = spectral_features(c, b, basis, constant_y=False)
        assert got.shape == ref.shape
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))
    _, _, ws = block_rows(c, BLOCKS[0])
    beta, _, _ = _distinct_pairs(c.beta, c.gamma, [w.reshape(2, len(c), -1) for w in ws])
    assert beta.shape[1] < c.shape[1]  # the sums above ran over the merged pairs
    assert merged_rows(c).groups is not None  # ... and in two stages over each sample's few betas


def test_features_with_every_beta_distinct_equal_the_plain_sums():
    c = _contacts(seed=2)
    g = torch.Generator().manual_seed(3)
    c = Contacts3D(torch.rand(c.beta.shape, generator=g, dtype=torch.float64) * 3 - 1.5, c.gamma, c.weight_x,
                   c.weight_y, c.weight_z)
    assert merged_rows(c).groups is None  # no beta repeats: one product per chunk
    basis = FourierBasis(2, 3)
    for b in range(len(BLOCKS)):
        ref = _plain(c, b, basis)
        torch.testing.assert_close(spectral_features(c, b, basis, constant_y=False), ref, rtol=0,
                                   atol=1e-12 * float(ref.abs().max()))


def test_a_bank_computing_ahead_cuts_what_is_asked():
    c = _contacts(T=6, seed=1)
    bank = SpectralFeatureBank(c, ahead=12)
    idx = torch.tensor([4, 0, 2])
    for n_beta, n_gamma in ((1, 2), (3, 3), (9, 5)):  # within one pass (8 harmonics), then a second (12)
        basis = FourierBasis(n_beta, n_gamma)
        for b in range(len(BLOCKS)):
            got = bank.rows(idx).features(basis, b, False)
            ref = _plain(c[idx], b, basis)
            torch.testing.assert_close(got, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))
    assert sorted(bank._held) == [(8, 8), (12, 8)]  # two passes over the data (each angle rounded up), not three
