"""The grid path: its likelihood against a dense reference, agreement with the exact path,
streaming equal to batch, and the automatic switch."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.grid import AngleGrid, GridRFT
from irft_torch.rft import Contacts, FourierStressMap

from .dense_reference import embed

P = math.pi
TRUTH = FourierStressMap.generic(0.452, 0.417)


def ctoe_gait2(n=150):
    toe = irft.rft.CToe(0.02, 0.008, 10, opening="left")
    path = irft.rft.spline_path([(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)], n_steps=n)
    c = irft.rft.contacts(toe, path)
    return c, irft.rft.forces(TRUTH, c)


def test_interpolation_is_exact_on_nodes_and_periodic_in_beta():
    grid = AngleGrid(8, 6)
    b, g = grid.nodes()
    B, G = torch.meshgrid(b, g, indexing="ij")
    idx, w = grid.interpolation(B.reshape(-1), G.reshape(-1))
    dense = torch.zeros(48, 48).scatter_add(1, idx, w)
    torch.testing.assert_close(dense, torch.eye(48))
    i1, w1 = grid.interpolation(torch.tensor([1.55]), torch.tensor([0.1]))
    i2, w2 = grid.interpolation(torch.tensor([1.55 - P]), torch.tensor([0.1]))
    torch.testing.assert_close(torch.zeros(48).scatter_add(0, i1[0], w1[0]),
                               torch.zeros(48).scatter_add(0, i2[0], w2[0]))


@pytest.mark.parametrize("physics", [False, True])
def test_grid_likelihood_matches_dense_phi_k_phi(physics):
    """Woodbury / determinant-lemma likelihood against Phi K Phi^T + noise written out densely."""
    c, f = ctoe_gait2(60)
    f = f + 0.01 * torch.randn(f.shape, generator=torch.Generator().manual_seed(0))
    gm = GridRFT(AngleGrid(10, 8), physics_mean=physics)
    gm.kernel.lengthscale = torch.tensor([[[0.7, 1.1, 0.9, 1.3]], [[1.2, 0.8, 0.6, 1.0]]])
    gm.kernel.outputscale = torch.tensor([0.02, 0.05])
    gm.likelihood.noise = torch.tensor([1e-3, 2e-3])
    if physics:
        gm.mean_module.scales = torch.tensor([0.4, 0.5])
    gm.set_data(c, f)
    ours = gm.log_marginal_likelihood()
    params = [p for p in gm.parameters() if p.requires_grad]
    g_ours = torch.autograd.grad(ours.sum(), params)

    def dense():
        b, g = gm.grid.nodes()
        B, G = torch.meshgrid(b, g, indexing="ij")
        phi = embed(B.reshape(-1), G.reshape(-1))  # grid in beta-major order
        out = []
        for a, w in enumerate((c.weight_x, c.weight_z)):
            x = phi / gm.kernel.lengthscale[a, 0]
            K = gm.kernel.outputscale[a] * torch.exp(-0.5 * ((x[:, None] - x[None]) ** 2).sum(-1))
            idx, iw = gm.grid.interpolation(c.beta, c.gamma)
            Phi = torch.zeros(len(c), gm.grid.size).scatter_add(1, idx.reshape(len(c), -1),
                                                                (w[..., None] * iw).reshape(len(c), -1))
            S = Phi @ K @ Phi.T + gm.likelihood.noise[a] * torch.eye(len(c))
            y = f[:, a]
            if physics:
                shape = FourierStressMap.generic()(c.beta, c.gamma)[..., a]
                y = y - gm.mean_module.scales[a] * (w * shape).sum(-1)
            L = torch.linalg.cholesky(S)
            al = torch.cholesky_solve(y[:, None], L)[:, 0]
            T = len(c)
            out.append((-0.5 * y @ al - torch.log(torch.diagonal(L)).sum() - 0.5 * T * math.log(2 * P)) / T)
        return torch.stack(out)

    ref = dense()
    g_ref = torch.autograd.grad(ref.sum(), params)
    # the grid factors carry a 1e-8 jitter: agreement to ~1e-6 relative
    torch.testing.assert_close(ours, ref, rtol=1e-6, atol=1e-8)
    for a, b in zip(g_ours, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_grid_map_agrees_with_exact_within_one_percent_of_range():
    c, f = ctoe_gait2(150)
    exact = irft.InverseRFT(c, f, method="exact")
    exact.fit(n_iter=60, progress=False)
    grid = irft.InverseRFT(c, f, method="grid", grid_size=(32, 32))
    grid.load_state_dict(exact.state_dict(), strict=False)  # same hyperparameters
    grid.kernel.load_state_dict(exact.kernel.state_dict())
    grid.likelihood.load_state_dict(exact.likelihood.state_dict())
    grid.grid_model._cache = None
    b, g = torch.meshgrid(torch.linspace(-1.5, 1.5, 30), torch.linspace(-1.5, 1.5, 30), indexing="ij")
    me, mg = exact.stress_map(b, g), grid.stress_map(b, g)
    rng = TRUTH(b, g).amax((0, 1)) - TRUTH(b, g).amin((0, 1))
    err = (me.mean - mg.mean).abs().amax((0, 1)) / rng
    assert (err < 0.01).all(), err


def test_streaming_equals_batch_and_is_what_auto_picks():
    c, f = ctoe_gait2(120)
    batch = irft.InverseRFT(c, f, method="grid", grid_size=(16, 16))
    stream = irft.InverseRFT(c[:40], f[:40], method="grid", grid_size=(16, 16))
    stream.load_state_dict(batch.state_dict())
    for i in range(40, 120, 20):
        stream.add_data(c[i:i + 20], f[i:i + 20])
    b = torch.linspace(-1.4, 1.4, 11)
    p1, p2 = batch.stress_map(b, b), stream.stress_map(b, b)
    torch.testing.assert_close(p1.mean, p2.mean, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(p1.variance, p2.variance, rtol=1e-9, atol=1e-12)
    # exact path streaming too (fixed hyperparameters, same posterior as a batch model)
    e1 = irft.InverseRFT(c, f, method="exact")
    e2 = irft.InverseRFT(c[:60], f[:60], method="exact")
    e2.load_state_dict(e1.state_dict())
    e2.add_data(c[60:], f[60:])
    torch.testing.assert_close(e1.stress_map(b, b).mean, e2.stress_map(b, b).mean)
    assert irft.InverseRFT(c, f, exact_max_segments=10).method == "grid"
    assert irft.InverseRFT(c, f).method == "exact"


def test_grid_fit_recovers_the_map_and_forces():
    c, f = ctoe_gait2(150)
    m = irft.InverseRFT(c, f, method="grid", grid_size=(24, 24))
    hist = m.fit(n_iter=100, progress=False)
    assert hist[-1] < hist[0]
    b, g = torch.meshgrid(torch.linspace(-1.5, 1.5, 30), torch.linspace(-1.5, 1.5, 30), indexing="ij")
    rmse = (m.stress_map(b, g).mean - TRUTH(b, g)).pow(2).mean((0, 1)).sqrt()
    assert (rmse < 0.03).all(), rmse
    pred = m.predict_forces(c)
    assert ((pred.mean - f).abs().amax(0) / (f.amax(0) - f.amin(0)) < 0.02).all()
    with pytest.raises(RuntimeError, match="grid path"):
        m.mll()
    assert isinstance(m.predict_forces(Contacts(c.beta[:3], c.gamma[:3], c.weight_x[:3], c.weight_z[:3]),
                                       variance="independent").variance, torch.Tensor)
