"""The CUDA path against the CPU path (itself checked against the dense reference in tests/gp): the same
data on the GPU gives the same likelihood, gradients, fits, posteriors, forces, probe scores and
sufficient statistics, and everything a model returns stays on the data's device. Skipped where no
GPU is visible (CI has none); run with ``pytest tests/test_gpu.py`` on a machine with one."""

import math
import os

import pytest
import torch

import irft_torch as irft
from irft_torch.design import ProbeScorer, Region
from irft_torch.gp.statistics import recording_statistics
from irft_torch.rft import CToe, FourierStressMap, IToe, rectangle_path, spline_path

# IRFT_GPU_TEST_DEVICE=cpu runs this module on the CPU against itself (a dry run of the test code only).
CUDA = torch.device(os.environ.get("IRFT_GPU_TEST_DEVICE", "cuda"))
pytestmark = pytest.mark.skipif(CUDA.type == "cuda" and not torch.cuda.is_available(),
                                reason="no CUDA device visible (CI has none)")
BACKENDS = ["observations", "pairs", "spectral"]


def close(a, b, rtol=1e-8, atol=1e-10):
    torch.testing.assert_close(a.detach().cpu(), b.detach().cpu(), rtol=rtol, atol=atol)


def recording(toe=None, device="cpu", n=120, seed=0):
    toe = toe or CToe(0.02, 0.008, n_segments=10)
    path = spline_path([(-0.15, 0.0), (-0.05, -0.04), (0.05, -0.03), (0.15, 0.0)], n_steps=n)
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    f = f + 0.02 * torch.randn(f.shape, generator=torch.Generator().manual_seed(seed), dtype=f.dtype)
    return c.to(device=device), f.to(device)


def on_cuda(x):
    return x.device.type == CUDA.type


def test_forward_rft_on_cuda_matches_cpu():
    toe, path = CToe(0.02, 0.008), rectangle_path(n_steps=80)
    c_cpu = irft.rft.contacts(toe, path)
    path_gpu = type(path)(**{k: (v.to(CUDA) if torch.is_tensor(v) else v) for k, v in vars(path).items()})
    c_gpu = irft.rft.contacts(toe, path_gpu)
    assert on_cuda(c_gpu.beta)
    for name in ("beta", "gamma", "weight_x", "weight_z"):
        close(getattr(c_gpu, name), getattr(c_cpu, name))
    smap = FourierStressMap.generic()
    close(irft.rft.forces(smap.to(CUDA), c_gpu), irft.rft.forces(smap, c_cpu))


@pytest.mark.parametrize("prior_mean", ["zero", "physics"])
@pytest.mark.parametrize("method", BACKENDS)
def test_loss_gradients_and_posteriors_match_cpu(method, prior_mean):
    models = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        m = irft.InverseRFT(c, f, method=method, prior_mean=prior_mean)
        with torch.no_grad():
            m.hypers.lengthscale = torch.tensor([[[0.8, 1.1, 0.9, 1.3]], [[1.2, 0.7, 1.0, 0.9]]])
        models.append(m)
    cpu, gpu = models
    assert gpu.method == cpu.method == method
    params = [dict(m.hypers.named_parameters()) for m in models]
    assert params[0].keys() == params[1].keys()
    losses = [m.loss() for m in models]
    close(losses[1], losses[0])
    grads = [torch.autograd.grad(loss, list(p.values())) for loss, p in zip(losses, params)]
    for name, g_cpu, g_gpu in zip(params[0], *grads):
        assert on_cuda(g_gpu), name
        close(g_gpu, g_cpu, rtol=1e-7, atol=1e-12)
    beta = torch.linspace(-1.4, 1.4, 7)
    gamma = torch.linspace(-1.5, 1.5, 7)
    p_cpu, p_gpu = cpu.stress_map(beta, gamma), gpu.stress_map(beta.to(CUDA), gamma.to(CUDA))
    assert on_cuda(p_gpu.mean) and on_cuda(p_gpu.variance)
    close(p_gpu.mean, p_cpu.mean, rtol=1e-7)
    close(p_gpu.variance, p_cpu.variance, rtol=1e-6)
    new, _ = recording(toe=IToe(0.04, 0.02, n_segments=6), n=60)
    f_cpu, f_gpu = cpu.predict_forces(new), gpu.predict_forces(new.to(device=CUDA))
    assert on_cuda(f_gpu.mean)
    close(f_gpu.mean, f_cpu.mean, rtol=1e-7)
    close(f_gpu.variance, f_cpu.variance, rtol=1e-6)


def test_fit_on_cuda_follows_cpu_and_stays_on_device():
    runs = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        m = irft.InverseRFT(c, f)
        runs.append((m, m.fit(n_iter=25, lr=0.1, progress=False)))
    (cpu, h_cpu), (gpu, h_gpu) = runs
    assert all(on_cuda(p) for p in gpu.parameters())
    torch.testing.assert_close(torch.tensor(h_gpu), torch.tensor(h_cpu), rtol=1e-6, atol=1e-8)
    b = torch.zeros(3, device=CUDA)
    close(gpu.stress_map(b, b).mean, cpu.stress_map(b.cpu(), b.cpu()).mean, rtol=1e-5, atol=1e-8)
    d = gpu.diagnostics(warn=False)
    assert d is not None


def test_learned_surface_on_cuda_matches_cpu():
    losses = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        m = irft.InverseRFT(c, f, surface_offset=True)
        m.init_surface([0.003])
        loss = m.loss()
        (g,) = torch.autograd.grad(loss, [m.surface.offset])
        losses.append((loss, g))
    close(losses[1][0], losses[0][0])
    close(losses[1][1], losses[0][1], rtol=1e-6)


def test_add_data_and_save_load_across_devices(tmp_path):
    c, f = recording(device=CUDA)
    c2, f2 = recording(device=CUDA, seed=5, toe=IToe(0.04, 0.02, tilt=0.3, n_segments=6))
    m = irft.InverseRFT(c, f)
    m.fit(n_iter=10, progress=False)
    m.add_data(c2, f2)
    b = torch.linspace(-1.0, 1.0, 5, device=CUDA)
    before = m.stress_map(b, b)
    path = tmp_path / "model.pt"
    m.save(path)
    back = irft.InverseRFT.load(path, map_location="cpu")
    after = back.stress_map(b.cpu(), b.cpu())
    close(after.mean, before.mean)
    close(after.variance, before.variance, rtol=1e-6)


def test_probe_scores_on_cuda_match_cpu():
    scores = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        m = irft.InverseRFT(c, f)
        scorer = ProbeScorer.from_model(m)
        toes = [IToe(0.04, 0.02, tilt=t, n_segments=6) for t in (-0.5, 0.0, 0.7)]
        cands = [recording(toe=toe, n=40)[0].to(device=dev) for toe in toes]
        region = Region.square(8)
        scores.append((scorer.score(cands, "eig"), scorer.score(cands, "variance", region=region)))
    close(scores[1][0], scores[0][0], rtol=1e-6)
    close(scores[1][1], scores[0][1], rtol=1e-6)


def test_sufficient_statistics_on_cuda_match_cpu():
    out = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        s = recording_statistics(c, f.cpu().numpy())  # forces as a user may pass them: numpy, on the host
        m = irft.InverseRFT(c, f, method="spectral", statistics=s)
        out.append(m.loss())
    close(out[1], out[0])
    assert math.isfinite(float(out[1].detach()))


def test_fit_together_with_the_default_priors_on_cuda_matches_cpu():
    """The crash issue 33 reported: gp.fit_together with the physical priors compared a CPU lengthscale
    centre with CUDA lengthscales (gp.priors._log_lengthscale_ratio)."""
    from irft_torch.studies.reproduce import configuration

    toe, path = configuration("C-toe gait 1")
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    g = torch.Generator().manual_seed(3)
    sets = [f * (1 + 0.05 * (i + 1) * torch.randn(f.shape, generator=g, dtype=f.dtype)) for i in range(3)]
    out = []
    for dev in ("cpu", CUDA):
        models = [irft.InverseRFT(c.to(device=dev), fs.to(dev), tied_noise=True) for fs in sets]
        assert irft.gp.shares_fit(models) is None
        irft.gp.fit_together(models, n_iter=20, lr=0.1)
        out.append(torch.stack([m.hypers.outputscale.detach() for m in models]))
    assert on_cuda(out[1])
    close(out[1], out[0], rtol=1e-6)


def test_terrain_filter_on_cuda_matches_cpu():
    B = 6
    res = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        model = irft.InverseRFT(c, f, prior_mean="physics")
        filt = irft.TerrainFilter(model, B, window=5)
        idx = torch.arange(B * 8).reshape(8, B) % len(c)
        for t in range(8):
            filt.update(c[idx[t].to(c.beta.device)], f[idx[t].to(f.device)], mask=(idx[t] % 5 != 0).to(f.device))
        b = torch.linspace(-1.2, 1.2, 5, device=dev)
        post = filt.stress_map(b, b.flip(0))
        filt.reset([1])
        pred = filt.predict_forces(c[idx[:3].T.to(c.beta.device)])
        res.append((post, pred))
    (p_cpu, f_cpu), (p_gpu, f_gpu) = res
    assert on_cuda(p_gpu.mean) and on_cuda(f_gpu.variance)
    close(p_gpu.mean, p_cpu.mean, rtol=1e-7)
    close(p_gpu.variance, p_cpu.variance, rtol=1e-6)
    close(f_gpu.mean, f_cpu.mean, rtol=1e-7)
    close(f_gpu.variance, f_cpu.variance, rtol=1e-6)


def test_learned_surface_estimate_on_cuda():
    c, f = recording(device=CUDA)
    m = irft.InverseRFT(c, f, surface_offset=True)
    m.fit(n_iter=5, progress=False)
    est = m.surface_offset
    assert est.mean.device == est.std.device


def test_probe_design_by_gradient_on_cuda():
    from irft_torch.design import optimize_probe

    scores = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        scorer = ProbeScorer.from_model(irft.InverseRFT(c, f))
        out = optimize_probe(scorer, IToe(0.04, 0.02, n_segments=6), length=0.2, n_iter=3)
        scores.append(scorer.score([out.probe], "variance"))
    assert on_cuda(scores[1])
    close(scores[1], scores[0], rtol=1e-6)
