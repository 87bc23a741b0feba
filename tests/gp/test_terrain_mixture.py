"""TerrainFilterMixture: each environment's mixture over a model's hyperparameter draws, every draw weighed by the
environment's own samples, against the dense formula per draw (explicit W, K, Cholesky): the draw's posterior and
the log evidence of the samples held (window included), the weights w_s p(y | theta_s) normalised, the mixture's
moments and its interval from the mixture CDF."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp import TerrainFilter, TerrainFilterMixture
from irft_torch.rft import Contacts

from .dense_reference import axis_reference
from .test_terrain_filter import B, env_data, stack


def _model(prior_mean="zero"):
    c, f = env_data(0, T=20)
    model = irft.InverseRFT(c, f, prior_mean=prior_mean, hyper_posterior="laplace", li_basis=False)
    torch.manual_seed(0)
    model.fit(n_iter=30, progress=False)
    return model


def _dense(hypers, c, f, th, a):
    """Map posterior (mean, var) at th and log p(y_a | theta) of the samples (c, f), axis a, written densely."""
    ls, os, noise = hypers.lengthscale.detach(), hypers.outputscale.detach(), hypers.noise.detach()
    w = (c.weight_x, c.weight_z)[a]
    mean = None
    if hypers.mean is not None:
        s = hypers.mean_scales.detach()[a]
        mean = s * hypers.mean.shape_forces(c)[a]
    mll, map_post, _ = axis_reference(c, f[:, a], w, ls[a, 0], os[a], noise[a], mean)
    m_th = None
    if hypers.mean is not None:
        pts = Contacts.points(th[:, 0], th[:, 1])
        m_th = hypers.mean_scales.detach()[a] * hypers.mean.shape_forces(pts)[a] * (pts.weight_x[:, 0] if a == 0 else 1)
    mu, var = map_post(th, m_th)
    return mu, var, mll * len(f)


@pytest.mark.parametrize("window", [None, 3])
def test_each_environment_is_the_draws_mixture_weighed_by_its_own_evidence(window):
    model = _model()
    backends, w0 = model._weighted_backends()
    assert len(backends) > 1 and w0.ndim == 1
    data = [env_data(b) for b in range(B)]
    filt = TerrainFilterMixture(model, B, window=window)
    th = (torch.rand(5, 2, generator=torch.Generator().manual_seed(7), dtype=torch.float64) - 0.5) * math.pi
    prior = filt.stress_map(th[:, 0], th[:, 1])
    for t in range(6):
        filt.update(stack([d[0] for d in data], t), torch.stack([d[1][t] for d in data]),
                    mask=torch.tensor([True, t != 2, True]))
    filt.reset([2])  # environment 2 back to the prior and the model's weights
    post = filt.stress_map(th[:, 0], th[:, 1])
    lo, hi = post.interval(0.95)
    kept = [list(range(6)), [t for t in range(6) if t != 2]]
    for b in range(2):
        idx = torch.tensor(kept[b][-window:] if window else kept[b])
        c, f = data[b][0][idx], data[b][1][idx]
        mus, vars_, logw = [], [], []
        for s, bk in enumerate(backends):
            per_axis = [_dense(bk.hypers, c, f, th, a) for a in range(2)]
            mus.append(torch.stack([p[0] for p in per_axis], -1))
            vars_.append(torch.stack([p[1] for p in per_axis], -1))
            logw.append(math.log(float(w0[s])) + sum(float(p[2]) for p in per_axis))
        wts = torch.softmax(torch.tensor(logw, dtype=torch.float64), 0)  # one weight per draw, both maps
        torch.testing.assert_close(filt.weights[b, :, 0], wts, rtol=1e-8, atol=1e-12)
        mu, var = torch.stack(mus), torch.stack(vars_)  # (S, Q, 2)
        mean = (wts[:, None, None] * mu).sum(0)
        total = (wts[:, None, None] * (var + (mu - mean).pow(2))).sum(0)
        torch.testing.assert_close(post.mean[b], mean, rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(post.variance[b], total, rtol=1e-8, atol=1e-12)
        # the interval inverts the mixture's CDF (checked by its CDF at the ends: 2.5 % and 97.5 %)
        for x, q in ((lo[b], 0.025), (hi[b], 0.975)):
            cdf = (wts[:, None, None] * 0.5 * torch.special.erfc(-(x - mu) / var.sqrt() / math.sqrt(2))).sum(0)
            torch.testing.assert_close(cdf, torch.full_like(cdf, q), rtol=0, atol=1e-9)
    # the reset environment: the prior under the model's own weights, exactly
    torch.testing.assert_close(filt.weights[2, :, 0], w0.to(torch.float64), rtol=1e-12, atol=0)
    torch.testing.assert_close(post.mean[2], prior.mean[2], rtol=0, atol=1e-15)
    # the data move the weights (the evidence differs between draws)
    assert float((filt.weights[0, :, 0] - w0).abs().max()) > 1e-3


def test_a_plug_in_model_is_the_terrain_filter_and_forces_are_mixtures_too():
    c, f = env_data(0, T=20)
    plug = irft.InverseRFT(c, f, hyper_posterior="map", li_basis=False)
    plug.fit(n_iter=20, progress=False)
    data = [env_data(b) for b in range(B)]
    one, mix = TerrainFilter(plug, B, window=4), TerrainFilterMixture(plug, B, window=4)
    for t in range(5):
        ct, ft = stack([d[0] for d in data], t), torch.stack([d[1][t] for d in data])
        one.update(ct, ft)
        mix.update(ct, ft)
    th = torch.linspace(-1.2, 1.2, 4, dtype=torch.float64)
    a, b = one.stress_map(th, th), mix.stress_map(th, th)
    assert mix.n_draws == 1 and b.components is None
    torch.testing.assert_close(b.mean, a.mean, rtol=0, atol=0)
    cq = Contacts(*(torch.stack([getattr(d[0], k)[:3] for d in data]) for k in ("beta", "gamma", "weight_x",
                                                                                 "weight_z")))
    torch.testing.assert_close(mix.predict_forces(cq, include_noise=True).variance,
                               one.predict_forces(cq, include_noise=True).variance, rtol=0, atol=0)
    model = _model("physics")  # draws: each filter with its own draw's hyperparameters and mean scales
    m = TerrainFilterMixture(model, B, window=4)
    for t in range(5):
        m.update(stack([d[0] for d in data], t), torch.stack([d[1][t] for d in data]))
    p = m.predict_forces(cq)
    assert p.mean.shape == (B, 3, 2) and p.components[2].shape == (m.n_draws, B, 1, 2)
    with pytest.raises(TypeError, match="model"):
        TerrainFilterMixture("not a model", B)
