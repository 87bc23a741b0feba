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
        m = irft.InverseRFT(c, f, method=method, prior_mean=prior_mean, hyper_posterior="map", li_basis=False)
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
        m = irft.InverseRFT(c, f, hyper_posterior="map", li_basis=False)
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
        m = irft.InverseRFT(c, f, surface_offset=True, hyper_posterior="map", li_basis=False)
        m.init_surface([0.003])
        loss = m.loss()
        (g,) = torch.autograd.grad(loss, [m.surface.offset])
        losses.append((loss, g))
    close(losses[1][0], losses[0][0])
    close(losses[1][1], losses[0][1], rtol=1e-6)


def test_add_data_and_save_load_across_devices(tmp_path):
    c, f = recording(device=CUDA)
    c2, f2 = recording(device=CUDA, seed=5, toe=IToe(0.04, 0.02, tilt=0.3, n_segments=6))
    m = irft.InverseRFT(c, f, hyper_posterior="map", li_basis=False)
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
        m = irft.InverseRFT(c, f, hyper_posterior="map", li_basis=False)
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
        m = irft.InverseRFT(c, f, method="spectral", statistics=s, hyper_posterior="map", li_basis=False)
        out.append(m.loss())
    close(out[1], out[0])
    assert math.isfinite(float(out[1].detach()))


def test_fit_together_with_the_default_priors_on_cuda_matches_cpu():
    """The crash issue 33 reported: gp.fit_together with the physical priors compared a CPU lengthscale
    centre with CUDA lengthscales (gp.kernels.priors._log_lengthscale_ratio)."""
    from irft_torch.studies.reproduce import configuration

    toe, path = configuration("C-toe gait 1")
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    g = torch.Generator().manual_seed(3)
    sets = [f * (1 + 0.05 * (i + 1) * torch.randn(f.shape, generator=g, dtype=f.dtype)) for i in range(3)]
    out = []
    for dev in ("cpu", CUDA):
        models = [irft.InverseRFT(c.to(device=dev), fs.to(dev), tied_noise=True, hyper_posterior="map",
                                  li_basis=False) for fs in sets]
        assert irft.gp.shares_fit(models) is None
        irft.gp.fit_together(models, n_iter=20, lr=0.1)
        out.append(torch.stack([m.hypers.outputscale.detach() for m in models]))
    assert on_cuda(out[1])
    close(out[1], out[0], rtol=1e-6)


@pytest.mark.parametrize("li_basis", [False, True])
def test_terrain_filter_on_cuda_matches_cpu(li_basis):
    B = 6
    res = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        model = irft.InverseRFT(c, f, prior_mean="physics", li_basis=li_basis, hyper_posterior="map")
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


def test_terrain_filter_mixture_on_cuda_matches_cpu():
    """Each environment's mixture over Laplace draws, weighed by its own samples, on the GPU as on the CPU."""
    B = 5
    res = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        model = irft.InverseRFT(c, f, hyper_posterior="laplace", li_basis=False)
        torch.manual_seed(0)
        model.fit(n_iter=20, progress=False)
        filt = irft.gp.TerrainFilterMixture(model, B, window=4)
        idx = torch.arange(B * 6).reshape(6, B) % len(c)
        for t in range(6):
            filt.update(c[idx[t].to(c.beta.device)], f[idx[t].to(f.device)])
        b = torch.linspace(-1.2, 1.2, 5, device=dev)
        res.append((filt.weights, filt.stress_map(b, b.flip(0))))
    (w_cpu, p_cpu), (w_gpu, p_gpu) = res
    assert on_cuda(w_gpu) and on_cuda(p_gpu.mean)
    close(w_gpu, w_cpu, rtol=1e-5, atol=1e-8)
    close(p_gpu.mean, p_cpu.mean, rtol=1e-5, atol=1e-8)
    close(p_gpu.variance, p_cpu.variance, rtol=1e-4, atol=1e-10)


def test_learned_surface_estimate_on_cuda():
    c, f = recording(device=CUDA)
    m = irft.InverseRFT(c, f, surface_offset=True, hyper_posterior="map", li_basis=False)
    m.fit(n_iter=5, progress=False)
    est = m.surface_offset
    assert est.mean.device == est.std.device


def test_probe_design_by_gradient_on_cuda():
    """The design objective and its gradient in the course knots agree with the CPU; the optimiser then runs
    on the GPU scorer and improves its start. (Its trajectories are not compared: Adam's first step is about
    lr * sign(gradient) per knot, so a knot whose gradient is ~1e-17 may step either way on either device.)"""
    from irft_torch.design import optimize_probe
    from irft_torch.design.optimize import default_spec
    from irft_torch.rft import ProbeBounds, course_path

    toe = IToe(0.04, 0.02, n_segments=6)
    out = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        scorer = ProbeScorer.from_model(irft.InverseRFT(c, f, hyper_posterior="map", li_basis=False))
        spec = default_spec(0.2, ProbeBounds())
        course = spec.pop("course").clone().requires_grad_(True)
        value = scorer.integrated_variance(irft.rft.contacts(toe, course_path(course, **spec)))
        (grad,) = torch.autograd.grad(value, [course])
        out.append((value, grad, scorer))
    (v_cpu, g_cpu, _), (v_gpu, g_gpu, scorer) = out
    assert on_cuda(v_gpu)
    close(v_gpu, v_cpu, rtol=1e-7)
    close(g_gpu, g_cpu, rtol=1e-6, atol=1e-9 * float(g_cpu.abs().max()))
    designed = optimize_probe(scorer, toe, length=0.2, n_iter=3)
    assert math.isfinite(designed.score) and designed.score <= designed.initial_score


def test_hyper_posterior_laplace_on_cuda_matches_cpu():
    """The Laplace hyperparameter posterior (mode, Hessian, weighed proposals) on the GPU: the same mixture
    as on the CPU (the proposals drawn on the CPU generator's stream, so the same draws)."""
    out = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        torch.manual_seed(0)  # the proposals are drawn from the CPU's default generator on either device
        m = irft.InverseRFT(c, f, hyper_posterior="laplace", li_basis=False)
        m.fit(n_iter=20, lr=0.1, progress=False)
        b = torch.linspace(-1.2, 1.2, 5, device=dev)
        out.append((m, m.stress_map(b, b.flip(0))))
    (cpu, p_cpu), (gpu, p_gpu) = out
    assert on_cuda(p_gpu.mean) and p_gpu.components is not None and on_cuda(p_gpu.components[2])
    close(gpu.hyper_posterior.weights, cpu.hyper_posterior.weights, rtol=1e-4, atol=1e-8)
    close(p_gpu.mean, p_cpu.mean, rtol=1e-5, atol=1e-8)
    close(p_gpu.variance, p_cpu.variance, rtol=1e-4, atol=1e-10)
    lo_g, hi_g = p_gpu.interval(0.95)
    lo_c, hi_c = p_cpu.interval(0.95)
    close(lo_g, lo_c, rtol=1e-4, atol=1e-8)
    back = p_gpu.to("cpu")
    assert back.mean.device.type == "cpu" and back.components is not None


def test_average_prior_mean_on_cuda_matches_cpu():
    out = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        m = irft.InverseRFT(c, f, prior_mean="average", hyper_posterior="map", li_basis=False)
        m.fit(n_iter=15, lr=0.1, progress=False)
        b = torch.linspace(-1.0, 1.0, 4, device=dev)
        out.append(m.stress_map(b, b))
    assert on_cuda(out[1].mean)
    # 15 Adam steps on either device, then evidence weights (exponentials of the two means' evidences):
    # equal to the fit's own floating-point drift, about 1e-3 of the largest variance here
    close(out[1].mean, out[0].mean, rtol=1e-5, atol=1e-8)
    close(out[1].variance, out[0].variance, rtol=1e-3, atol=1e-3 * float(out[0].variance.max()))


@pytest.mark.parametrize("li_basis", [False, True])
@pytest.mark.parametrize("method", BACKENDS)
def test_inverse_3d_on_cuda_matches_cpu(method, li_basis):
    """3-D RFT forward (a turning C-toe mesh) and the 3-D inverse model (with Li et al.'s term or without) on the
    GPU against the CPU."""
    from irft_torch.rft import Mesh, contacts_3d, forces_3d

    T = 16
    t = torch.linspace(0, 1, T)
    yaw = 0.9 * t
    co, si, z, o = torch.cos(yaw), torch.sin(yaw), torch.zeros(T), torch.ones(T)
    R = torch.stack([torch.stack([co, -si, z], -1), torch.stack([si, co, z], -1), torch.stack([z, z, o], -1)], -2)
    v = torch.stack([0.02 * o, 0.01 * torch.sin(3 * t), -0.01 * torch.cos(2 * t)], -1)
    w = torch.stack([z, z, 0.9 * o], -1)
    x0 = torch.stack([0.02 * t, z, -0.015 - 0.01 * t], -1)
    mesh = Mesh.from_toe(CToe(0.02, 0.01, n_segments=4), n_across=2)
    out = []
    for dev in ("cpu", CUDA):
        cc = contacts_3d(mesh.to(device=dev), v.to(dev), w.to(dev), surface=0.0, position=x0.to(dev),
                         rotation=R.to(dev))
        f = forces_3d(FourierStressMap.generic(0.5, 0.6).to(dev), cc, alpha_y=0.1)
        f = f + 0.02 * torch.randn(f.shape, generator=torch.Generator().manual_seed(0), dtype=f.dtype).to(dev)
        m = irft.InverseRFT(cc, f, method=method, li_basis=li_basis, hyper_posterior="map")
        loss = m.loss()
        params = [p for p in m.hypers.parameters() if p.requires_grad]
        grads = torch.autograd.grad(loss, params)
        with torch.no_grad():
            pred = m.predict_forces(cc[:5])
            b = torch.linspace(-1.0, 1.0, 4, device=dev)
            sm = m.stress_map(b, b)
        out.append((f, loss, grads, pred, sm))
    (f_c, l_c, g_c, p_c, s_c), (f_g, l_g, g_g, p_g, s_g) = out
    assert on_cuda(f_g) and on_cuda(p_g.covariance) and on_cuda(s_g.mean)
    close(f_g, f_c)
    close(l_g, l_c)
    for a, b in zip(g_g, g_c):
        close(a, b, rtol=1e-6, atol=1e-10)
    close(p_g.mean, p_c.mean, rtol=1e-7)
    close(p_g.covariance, p_c.covariance, rtol=1e-6, atol=1e-10)
    close(s_g.mean, s_c.mean, rtol=1e-7)


def test_reproduce_fits_on_cuda_like_the_cpu():
    """``irft reproduce --device cuda``: one of the study's fits (quick settings) on the GPU gives the CPU's
    Table I metrics; the data, metrics and maps come back on the CPU."""
    from dataclasses import replace

    from irft_torch.studies.reproduce import StudySettings, _fit_one

    s = replace(StudySettings.quick_settings(), n_iter=30)
    truth = FourierStressMap.generic(*s.truth_scale)
    res = [_fit_one("C-toe gait 1", "physics", 0.05, 0, truth, "paper", replace(s, device=str(d)), keep_maps=True)
           for d in ("cpu", CUDA)]
    assert res[1].maps["mean"].device.type == "cpu"
    for axis in "XZ":
        for k, v in res[0].metrics[axis].items():
            assert res[1].metrics[axis][k] == pytest.approx(v, rel=1e-4, abs=1e-6), (axis, k)


def test_nuts_hyper_posterior_runs_on_cuda():
    """NUTS (pyro) on the GPU model's potential: draws and weights on the GPU, predictions a mixture there."""
    pytest.importorskip("pyro")
    c, f = recording(device=CUDA)
    m = irft.InverseRFT(c, f, method="pairs", hyper_posterior="map", li_basis=False)
    m.fit(n_iter=15, lr=0.1, progress=False)
    hp = m.fit_hyper_posterior("nuts", n_draws=8, free=["outputscale_z", "noise_z"], n_samples=40, warmup=40)
    assert on_cuda(hp.theta) and on_cuda(hp.weights)
    assert torch.isfinite(hp.theta).all() and float(hp.weights.sum()) == pytest.approx(1.0)
    b = torch.linspace(-1.0, 1.0, 4, device=CUDA)
    post = m.stress_map(b, b)
    assert on_cuda(post.mean) and torch.isfinite(post.variance).all()


def test_probe_scores_of_a_3d_model_on_cuda_match_cpu():
    from irft_torch.design import ProbeScorer3D
    from irft_torch.rft import Mesh, contacts_3d, forces_3d

    T = 12
    t = torch.linspace(0, 1, T, dtype=torch.float64)
    z, o = torch.zeros_like(t), torch.ones_like(t)
    v = torch.stack([0.02 * o, 0.01 * torch.sin(3 * t), -0.01 * torch.cos(2 * t)], -1)
    w = torch.stack([z, z, 0.9 * o], -1)
    x0 = torch.stack([0.02 * t, z, -0.015 - 0.01 * t], -1)
    mesh = Mesh.from_toe(CToe(0.02, 0.01, n_segments=4), n_across=2).to(dtype=torch.float64)
    out = []
    for dev in ("cpu", CUDA):
        cc = contacts_3d(mesh.to(device=dev), v.to(dev), w.to(dev), surface=0.0, position=x0.to(dev))
        f = forces_3d(FourierStressMap.generic(0.5, 0.6).to(dev), cc, alpha_y=0.1)
        scorer = ProbeScorer.from_model(irft.InverseRFT(cc[:8], f[:8], method="pairs", hyper_posterior="map",
                                                        li_basis=False))
        assert isinstance(scorer, ProbeScorer3D)
        out.append((scorer.score([cc[8:], cc[6:]], "eig"), scorer.score([cc[8:], cc[6:]], "variance")))
    assert on_cuda(out[1][0])
    close(out[1][0], out[0][0], rtol=1e-6)
    close(out[1][1], out[0][1], rtol=1e-6)


@pytest.mark.parametrize("method", BACKENDS)
def test_li_basis_on_cuda_matches_cpu(method):
    """Li et al.'s kernel term (``li_basis=True``) on each backend: likelihood, closed-form and autograd gradients,
    posterior maps and a short fit with its Laplace posterior, on the GPU as on the CPU."""
    models = []
    for dev in ("cpu", CUDA):
        c, f = recording(device=dev)
        m = irft.InverseRFT(c, f, method=method, li_basis=True, hyper_posterior="map")
        with torch.no_grad():
            m.hypers.lengthscale = torch.tensor([[[0.8, 1.1, 0.9, 1.3]], [[1.2, 0.7, 1.0, 0.9]]])
            m.hypers.li.variance = torch.tensor([0.05, 0.3])
        models.append(m)
    cpu, gpu = models
    assert gpu.method == cpu.method == method and on_cuda(gpu.hypers.li.raw_variance)
    losses = [m.loss() for m in models]
    close(losses[1], losses[0])
    grads = [torch.autograd.grad(loss, [m.hypers.li.raw_variance]) for loss, m in zip(losses, models)]
    close(grads[1][0], grads[0][0], rtol=1e-7, atol=1e-12)
    for m in models:
        m.hypers.zero_grad()
        assert m.backend.loss_and_grad() is not None
    close(gpu.hypers.li.raw_variance.grad, cpu.hypers.li.raw_variance.grad, rtol=1e-7, atol=1e-12)
    beta, gamma = torch.linspace(-1.4, 1.4, 7), torch.linspace(-1.5, 1.5, 7)
    p_cpu, p_gpu = cpu.stress_map(beta, gamma), gpu.stress_map(beta.to(CUDA), gamma.to(CUDA))
    assert on_cuda(p_gpu.mean)
    close(p_gpu.mean, p_cpu.mean, rtol=1e-7)
    close(p_gpu.variance, p_cpu.variance, rtol=1e-6)
    for m in models:
        torch.manual_seed(0)  # the proposals are drawn from the CPU's default generator on either device
        m.hyper_method = "laplace"
        m.fit(n_iter=20, lr=0.05, progress=False)
    assert {"li_variance_x", "li_variance_z"} <= set(gpu.hyper_posterior.labels)
    close(gpu.hyper_posterior.weights, cpu.hyper_posterior.weights, rtol=1e-4, atol=1e-8)
    p_cpu, p_gpu = cpu.stress_map(beta, gamma), gpu.stress_map(beta.to(CUDA), gamma.to(CUDA))
    close(p_gpu.mean, p_cpu.mean, rtol=1e-5, atol=1e-8)
    close(p_gpu.variance, p_cpu.variance, rtol=1e-4, atol=1e-10)
