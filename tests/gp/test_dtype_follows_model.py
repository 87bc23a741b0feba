"""Every public path keeps a float32 model in float32 under torch's float64 default: a tensor made without
the model's dtype promotes a result to float64 here, or fails a matmul, which the CPU catches. (A tensor
made without the model's *device* is the same mistake, but only a GPU shows it: issue 33's crash in
``fit_together``'s priors made its centres in the right dtype, on the CPU; tests/test_gpu.py covers it.)"""

import torch

import irft_torch as irft
from irft_torch.design import ProbeScorer
from irft_torch.rft import CToe, FourierStressMap, IToe, spline_path

F32 = torch.float32


def recording(toe=None, n=80):
    toe = toe or CToe(0.02, 0.008, n_segments=8)
    path = spline_path([(-0.15, 0.0), (-0.05, -0.04), (0.05, -0.03), (0.15, 0.0)], n_steps=n)
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    return c, f + 0.02 * torch.randn(f.shape, generator=torch.Generator().manual_seed(0), dtype=f.dtype)


def test_a_float32_model_stays_float32_on_every_path():
    assert torch.get_default_dtype() == torch.float64
    c, f = recording()
    model = irft.InverseRFT(c, f, dtype=F32, prior_mean="physics", hyper_posterior="map", li_basis=False)
    assert model.loss().dtype == F32  # the physical priors' centres and locs
    model.fit(n_iter=3, progress=False)
    filt = irft.TerrainFilter(model, 4, window=3)
    for t in range(5):
        filt.update(c[t * 4:t * 4 + 4], f[t * 4:t * 4 + 4])
    b = torch.linspace(-1.0, 1.0, 3)
    per_env = irft.rft.Contacts(*(v[:12].reshape(4, 3, -1) for v in (c.beta, c.gamma, c.weight_x, c.weight_z)))
    for post in (filt.stress_map(b, b), filt.predict_forces(per_env)):
        assert post.mean.dtype == post.variance.dtype == F32
    scorer = ProbeScorer.from_model(model)
    assert scorer.score([recording(IToe(0.04, 0.02, n_segments=4), n=30)[0]]).dtype == F32
    surf = irft.InverseRFT(c, f, dtype=F32, surface_offset=True, hyper_posterior="map", li_basis=False)
    surf.fit(n_iter=2, progress=False)
    est = surf.surface_offset
    assert est.mean.dtype == est.std.dtype == F32


def test_fit_together_keeps_float32_models_in_float32(monkeypatch):
    """Its stacked prior centres are in the models' dtype and on their device: every prior term is checked as
    it is evaluated (the closures are looked up when the models are built)."""
    from irft_torch.gp.kernels import priors
    from irft_torch.studies.reproduce import configuration

    def checked(name):
        original = getattr(priors, name)

        def ratio(m, c):
            value = original(m, c)
            if torch.is_tensor(c):
                assert c.dtype == value.dtype == F32 and c.device == value.device, (name, c.dtype, value.dtype)
            return value

        monkeypatch.setattr(priors, name, ratio)

    for name in ("_log_outputscale_ratio", "_log_lengthscale_ratio", "_log_noise_ratio"):
        checked(name)

    toe, path = configuration("C-toe gait 1")
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(FourierStressMap.generic(), c)
    models = [irft.InverseRFT(c, f * s, dtype=F32, tied_noise=True, hyper_posterior="map",
                              li_basis=False) for s in (1.0, 1.1)]
    assert irft.gp.shares_fit(models) is None
    losses = irft.gp.fit_together(models, n_iter=3, lr=0.1)
    assert all(m.hypers.outputscale.dtype == F32 and m.loss().dtype == F32 for m in models)
    assert losses is not None
