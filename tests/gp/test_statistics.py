"""Sufficient statistics saved with a recording and merged across recordings (``gp.statistics``):
a smaller basis cut from a larger one equals a pass in the smaller basis; a model given statistics
equals the model that makes its own pass (and the dense reference); saved statistics of other data
are refused; ``irft fit`` reduces datasets in worker processes to the same sums."""

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.backends.spectral import spectral_statistics
from irft_torch.gp.kernels.fourier import FourierBasis
from irft_torch.gp.kernels.means import GenericShapeMean
from irft_torch.gp.statistics import (
    initial_basis,
    recording_statistics,
    restrict_statistics,
    statistics_arrays,
    statistics_from_arrays,
)

from .dense_reference import axis_reference
from .test_backends_vs_dense import data, set_hypers


def test_restrict_equals_a_pass_in_the_smaller_basis():
    c, f = data(T=30, seed=4)
    big = recording_statistics(c, f, FourierBasis(6, 5))
    small = FourierBasis(3, 4)
    direct = spectral_statistics(c, f, small, GenericShapeMean().double())
    cut = restrict_statistics(big, small)
    for k in ("P", "b", "yy", "bg", "yg", "gg"):
        torch.testing.assert_close(getattr(cut, k), getattr(direct, k), rtol=1e-12, atol=1e-12)
    assert cut.meta["n_beta"] == 3 and cut.meta["n_gamma"] == 4 and cut.n == 30
    with pytest.raises(ValueError, match="cannot give the larger"):
        restrict_statistics(big, FourierBasis(7, 5))


@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
def test_model_from_statistics_equals_its_own_pass_and_the_dense_reference(prior_mean):
    c, f = data(T=60, M=3, seed=2)
    stats = recording_statistics(c, f, FourierBasis(12, 12))  # larger than needed: cut to size
    models = [irft.InverseRFT(c, f, method="spectral", prior_mean=prior_mean, statistics=s, hyper_posterior="map",
                              li_basis=False) for s in (None, stats)]
    for m in models:
        set_hypers(m, low=0.6)
    losses = [m.loss() for m in models]
    grads = [torch.autograd.grad(v, list(m.hypers.parameters())) for v, m in zip(losses, models)]
    torch.testing.assert_close(losses[1], losses[0], rtol=1e-10, atol=0)
    for g0, g1 in zip(*grads):
        torch.testing.assert_close(g1, g0, rtol=1e-8, atol=1e-12)
    # the posterior of a map point against the dense reference (explicit W, K, Cholesky)
    m = models[1]
    m.eval()
    b, g = torch.tensor([0.3]), torch.tensor([1.1])
    post = m.stress_map(b, g)
    ls, os, nz = (m.hypers.lengthscale.detach(), m.hypers.outputscale.detach(), m.hypers.noise.detach())
    for a, w in enumerate((c.weight_x, c.weight_z)):
        mean0 = None
        if prior_mean == "physics":
            shape = irft.rft.FourierStressMap.generic()(c.beta, c.gamma)[..., a]
            mean0 = m.hypers.mean_scales.detach()[a] * (w * shape).sum(-1)
        _, map_posterior, _ = axis_reference(c, f[:, a], w, ls[a, 0], os[a], nz[a], mean0)
        mean_star = None
        if prior_mean == "physics":
            mean_star = m.hypers.mean_scales.detach()[a] * irft.rft.FourierStressMap.generic()(b, g)[..., a]
        pm, pv = map_posterior(torch.stack([b, g], -1), mean_star)
        torch.testing.assert_close(post.mean[..., a], pm, rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(post.variance[..., a], pv, rtol=1e-6, atol=1e-12)


def test_a_float32_model_takes_the_float64_statistics_of_its_data():
    """Statistics are computed once, in the data's dtype; a float32 model of the same data takes them
    (rounding its forces to float32 moves their power by ~1e-8, far less than other data would) and
    matches the dense float64 reference; statistics of other forces are still refused."""
    c, f = data(T=40, M=3, seed=2)
    assert c.beta.dtype == f.dtype == torch.float64
    stats = recording_statistics(c, f, FourierBasis(12, 12))
    m = irft.InverseRFT(c, f, method="spectral", dtype=torch.float32, statistics=stats, priors=None,
                        hyper_posterior="map", li_basis=False)
    set_hypers(m, low=0.6)
    m.loss()
    assert m.backend._stored is stats  # used, not recomputed
    ls, os, nz = (m.hypers.lengthscale.detach().double(), m.hypers.outputscale.detach().double(),
                  m.hypers.noise.detach().double())
    ref = sum(axis_reference(c, f[:, a], w, ls[a, 0], os[a], nz[a])[0] for a, w in enumerate((c.weight_x, c.weight_z)))
    assert m.loss().item() == pytest.approx(-ref.item(), rel=1e-4)
    with pytest.raises(ValueError, match="statistics are not of these forces"):
        irft.InverseRFT(c, f * 1.001, method="spectral", dtype=torch.float32, statistics=stats, hyper_posterior="map",
                        li_basis=False)


def test_basis_growth_is_cut_from_the_stored_statistics():
    c, f = data(T=80, M=3, seed=5)
    stats = recording_statistics(c, f, FourierBasis(20, 20))
    m = irft.InverseRFT(c, f, method="spectral", statistics=stats, hyper_posterior="map", li_basis=False)
    m.backend._data = None  # the raw data gone: the basis can only grow within the stored statistics
    start = m.backend.basis
    with torch.no_grad():
        m.hypers.lengthscale = torch.full((2, 1, 4), 0.5)
    assert m.backend.refresh()
    grown = m.backend.basis
    assert grown.size > start.size and grown.n_beta <= 20
    direct = spectral_statistics(c, f, grown, None)
    torch.testing.assert_close(m.backend.stats.P, direct.P, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(m.backend.stats.b, direct.b, rtol=1e-12, atol=1e-10)


def test_merged_statistics_of_two_recordings_serve_their_union():
    (c1, f1), (c2, f2) = data(T=40, seed=7), data(T=35, seed=8)
    basis = initial_basis()
    total = recording_statistics(c1, f1, basis) + recording_statistics(c2, f2, basis)
    c = irft.rft.Contacts.cat([c1, c2])
    f = torch.cat([f1, f2])
    a = irft.InverseRFT(c, f, method="spectral", hyper_posterior="map", li_basis=False)
    b = irft.InverseRFT(c, f, method="spectral", statistics=total, hyper_posterior="map", li_basis=False)
    torch.testing.assert_close(b.loss(), a.loss(), rtol=1e-10, atol=0)


def test_statistics_of_other_data_are_refused():
    c, f = data(T=30, seed=9)
    stats = recording_statistics(c, f)
    with pytest.raises(ValueError, match="statistics are not of these forces"):
        irft.InverseRFT(c, f * 1.01, method="spectral", statistics=stats, hyper_posterior="map", li_basis=False)
    with pytest.raises(ValueError, match="noise_scale"):
        irft.InverseRFT(c, f, method="spectral", statistics=stats, noise_scale=torch.ones(30), hyper_posterior="map",
                        li_basis=False)
    no_shape = spectral_statistics(c, f, initial_basis(), None)
    with pytest.raises(ValueError, match="generic shape"):
        irft.InverseRFT(c, f, method="spectral", prior_mean="physics", statistics=no_shape, hyper_posterior="map",
                        li_basis=False)
    arrays = statistics_arrays(stats, c, f)
    back = statistics_from_arrays(arrays, c, f)
    torch.testing.assert_close(back.P, stats.P)
    assert back.meta == stats.meta and back.n == stats.n
    f2 = f.clone()
    f2[3, 1] += 1e-9  # the data were edited after the statistics were saved
    with pytest.warns(UserWarning, match="do not belong to these contacts and forces"):
        assert statistics_from_arrays(arrays, c, f2) is None
    damaged = dict(arrays, P=arrays["P"][:, :5])
    with pytest.raises(ValueError, match="damaged"):
        statistics_from_arrays(damaged, c, f)
    with pytest.raises(ValueError, match="damaged"):
        statistics_from_arrays({k: v for k, v in arrays.items() if k != "b"}, c, f)


def test_fit_reduces_datasets_in_worker_processes(tmp_path):
    from irft_torch.cli.fit import _reduce_statistics
    from irft_torch.data import Dataset, load_dataset, save_dataset

    paths, parts = [], []
    for i, seed in enumerate((11, 12, 13)):
        c, f = data(T=30 + i, seed=seed)
        ds = Dataset(c, f, torch.arange(len(c), dtype=torch.float64), torch.zeros(len(c), 2))
        if i == 0:  # one file carries its statistics (a larger basis), the others not
            ds.statistics = statistics_arrays(recording_statistics(c, f, FourierBasis(9, 9)), c, f)
        paths.append(save_dataset(tmp_path / f"d{i}.npz", ds))
        parts.append((c, f))
    assert load_dataset(paths[0]).statistics is not None and load_dataset(paths[1]).statistics is None
    basis = initial_basis()
    want = sum((recording_statistics(c, f, basis) for c, f in parts[1:]), recording_statistics(*parts[0], basis))
    for jobs in (1, 2):
        got = _reduce_statistics(paths, basis, jobs=jobs)
        assert got.n == want.n
        for k in ("P", "b", "yy", "bg", "yg", "gg"):
            torch.testing.assert_close(getattr(got, k), getattr(want, k), rtol=1e-12, atol=1e-10)


@pytest.mark.parametrize("trim", [True, False])
@pytest.mark.parametrize("T,F", [(20, 33), (33, 20)])
def test_the_data_factor_from_rows_against_numpy(trim, T, F):
    """``data_factor_from_rows`` on rank-deficient rows (rank 7 and 11; fewer rows than features, the rows' Gram,
    and more, the thin SVD): R^T R = Phi^T Phi and R^T c = Phi^T y, c^T c = |proj y|^2 and the residuals outside the
    rows' range, checked against numpy's least squares; the rank against ``numpy.linalg.matrix_rank``."""
    import numpy as np

    from irft_torch.gp.backends.weight_space import data_factor_from_rows

    g = torch.Generator().manual_seed(5)
    Phi = torch.stack([torch.randn(T, k, generator=g, dtype=torch.float64)
                       @ torch.randn(k, F, generator=g, dtype=torch.float64) for k in (7, 11)])
    y, m = torch.randn(2, T, generator=g, dtype=torch.float64), torch.randn(2, T, generator=g, dtype=torch.float64)
    f = data_factor_from_rows(Phi, y, m, torch.float64, trim=trim)
    for a in range(2):
        P, Yv, Mv = Phi[a].numpy(), y[a].numpy(), m[a].numpy()
        R, cy, cg = f.R[a].numpy(), f.c_y[a].numpy(), f.c_g[a].numpy()
        assert int(f.rank[a]) == np.linalg.matrix_rank(P)
        assert R.shape[0] == (11 if trim else min(T, F))
        np.testing.assert_allclose(R.T @ R, P.T @ P, atol=1e-11 * np.abs(P.T @ P).max())
        np.testing.assert_allclose(R.T @ cy, P.T @ Yv, atol=1e-11 * np.abs(P.T @ Yv).max())
        proj_y = P @ np.linalg.lstsq(P, Yv, rcond=None)[0]  # y's part in the rows' range
        proj_m = P @ np.linalg.lstsq(P, Mv, rcond=None)[0]
        np.testing.assert_allclose(cy @ cy, proj_y @ proj_y, rtol=1e-10)
        np.testing.assert_allclose(cy @ cg, proj_y @ proj_m, rtol=1e-10)
        np.testing.assert_allclose(f.rho[a].numpy(), [Yv @ Yv - proj_y @ proj_y, Yv @ Mv - proj_y @ proj_m,
                                                    Mv @ Mv - proj_m @ proj_m], rtol=1e-9)
