"""TerrainFilter on a spatial model (maps over the ground, many environments at once): each environment's posterior
against the dense reference with the explicit product covariance (``test_spatial._dense``, written by hand) on its
own samples, with and without a window, tracked and fresh queries, the shared medium and forces at places; bad
input refused by name."""

import pytest
import torch

from irft_torch import InverseRFT, MapPrior
from irft_torch.gp import TerrainFilter, TerrainFilterMixture
from irft_torch.rft.contacts import Contacts

from .test_spatial import _dense, _set, _walk

F64 = torch.float64
B = 3
OFFSETS = torch.tensor([[0.0, 0.0], [0.25, -0.1], [-0.3, 0.2]], dtype=F64)  # each environment's walk moved (m)


def _model(kernel="li"):
    c, F, s = _walk(n_stances=4)
    m = InverseRFT(c, F, locations=s, hyper_posterior="map", prior=MapPrior(kernel=kernel))
    _set(m)
    return m


def _envs(n_stances=3):
    """Each environment's own walk (its noise seed, its place): lists of (contacts, forces, places)."""
    out = []
    for b in range(B):
        c, F, s = _walk(n_stances=n_stances, seed=5 + b)
        out.append((c, F, s + OFFSETS[b]))
    return out


def _stack(parts, k):
    return Contacts(*(torch.stack([getattr(p[0], key)[k] for p in parts]) for key in
                      ("beta", "gamma", "weight_x", "weight_z")))


def _close(a, b, tol=1e-8):
    torch.testing.assert_close(a, b, rtol=tol, atol=tol * max(float(b.abs().max()), 1e-12))


@pytest.mark.parametrize("kernel,window,small", [("li+generic", None, True), ("li", 4, False), ("rbf", 5, False)])
def test_each_environment_is_the_dense_product_covariance_model(kernel, window, small):
    """``small``: room for 2 samples to start (the capacity doubles as samples come) and one environment per
    block (the per-block slices of places and tracked points)."""
    m = _model(kernel)
    envs = _envs()
    T = len(envs[0][0])
    sizes = {"capacity": 2, "block_bytes": 1} if small else {}
    filt = TerrainFilter(m, n_envs=B, window=window, **sizes)
    assert filt.spatial and "spatial=True" in repr(filt)
    beta = torch.tensor([0.2, -0.6, 1.0], dtype=F64)
    gamma = torch.tensor([1.1, -0.4, 2.2], dtype=F64)
    places = torch.stack([OFFSETS + torch.tensor([0.1, 0.0], dtype=F64),
                          OFFSETS + torch.tensor([0.45, 0.05], dtype=F64)], 1)  # (B, 2, 2): on and beside the walk
    half = T // 2
    for k in range(half):  # sample by sample, then the rest as one block
        filt.update(_stack(envs, k), torch.stack([e[1][k] for e in envs]),
                    locations=torch.stack([e[2][k] for e in envs]))
    filt.stress_map(beta, gamma, locations=places)  # tracked from here on
    rest = Contacts(*(torch.stack([getattr(e[0], key)[half:] for e in envs]) for key in
                      ("beta", "gamma", "weight_x", "weight_z")))
    filt.update(rest, torch.stack([e[1][half:] for e in envs]), locations=torch.stack([e[2][half:] for e in envs]))
    tracked = filt.stress_map(beta, gamma, locations=places)
    assert tracked.mean.shape == (B, 2, 3, 2)
    shared = filt.stress_map(beta, gamma)  # the medium shared by the site
    one = filt.stress_map(beta, gamma, locations=places[:, 0])  # one place each: (B, *S, 2)
    assert one.mean.shape == (B, 3, 2)
    for b, (c, F, s) in enumerate(envs):
        keep = slice(None) if window is None else slice(T - window, T)
        pts = Contacts.points(beta.repeat(2), gamma.repeat(2))
        mean, var, _ = _dense(m, c[keep], F[keep], s[keep], pts, places[b].repeat_interleave(3, 0))
        _close(tracked.mean[b].reshape(-1, 2), mean.T)
        _close(tracked.variance[b].reshape(-1, 2), var.T)
        mean1, var1, _ = _dense(m, c[keep], F[keep], s[keep], Contacts.points(beta, gamma), places[b, :1].expand(3, 2))
        _close(one.mean[b], mean1.T)
        _close(one.variance[b], var1.T)
        mean0, var0, _ = _dense(m, c[keep], F[keep], s[keep], Contacts.points(beta, gamma), None)
        _close(shared.mean[b], mean0.T)
        _close(shared.variance[b], var0.T)
    # forces of each environment's first three samples, at their own places and at the shared medium
    qc = Contacts(*(torch.stack([getattr(e[0], key)[:3] for e in envs]) for key in
                    ("beta", "gamma", "weight_x", "weight_z")))
    qs = torch.stack([e[2][:3] for e in envs])
    forces = filt.predict_forces(qc, locations=qs)
    forces0 = filt.predict_forces(qc)
    for b, (c, F, s) in enumerate(envs):
        keep = slice(None) if window is None else slice(T - window, T)
        mean, var, _ = _dense(m, c[keep], F[keep], s[keep], c[:3], s[:3])
        _close(forces.mean[b], mean.T)
        _close(forces.variance[b], var.T)
        mean0, var0, _ = _dense(m, c[keep], F[keep], s[keep], c[:3], None)
        _close(forces0.mean[b], mean0.T)
        _close(forces0.variance[b], var0.T)


def test_far_samples_weigh_less_and_a_reset_environment_is_the_prior():
    """A sample at the query's place shrinks the variance there more than the same sample 3 m away (by hand: the
    factor's correlation falls with distance); reset gives the prior at a place: k (1 + v)."""
    m = _model("rbf")
    c, F, s = _walk(n_stances=2)
    filt = TerrainFilter(m, n_envs=2)
    here = torch.zeros(2, 2, dtype=F64)
    away = torch.tensor([[0.0, 0.0], [3.0, 0.0]], dtype=F64)
    filt.update(Contacts(*(getattr(c, k)[:1].expand(2, -1) for k in ("beta", "gamma", "weight_x", "weight_z"))),
                F[:1].expand(2, 2), locations=away)
    post = filt.stress_map(c.beta[0, :1], c.gamma[0, :1], locations=here)
    assert bool((post.variance[0] < post.variance[1]).all())
    filt.reset([0])
    prior = filt.stress_map(c.beta[0, :1], c.gamma[0, :1], locations=here)
    v = m.hypers.spatial.variance.detach()
    _close(prior.variance[0, 0], m.hypers.outputscale.detach() * (1 + v))
    _close(prior.mean[0], torch.zeros(1, 2, dtype=F64))


def test_a_plug_in_mixture_is_the_filter():
    m = _model("rbf")
    envs = _envs(n_stances=2)
    filt, mix = TerrainFilter(m, n_envs=B), TerrainFilterMixture(m, n_envs=B)
    for f in (filt, mix):
        for k in range(4):
            f.update(_stack(envs, k), torch.stack([e[1][k] for e in envs]),
                     locations=torch.stack([e[2][k] for e in envs]))
    beta, gamma = torch.tensor([0.3], dtype=F64), torch.tensor([0.9], dtype=F64)
    _close(mix.stress_map(beta, gamma, OFFSETS).mean, filt.stress_map(beta, gamma, OFFSETS).mean, 1e-12)


def test_places_refused_by_name():
    m = _model("rbf")
    envs = _envs(n_stances=2)
    filt = TerrainFilter(m, n_envs=B)
    c0, f0 = _stack(envs, 0), torch.stack([e[1][0] for e in envs])
    with pytest.raises(ValueError, match="locations is required"):
        filt.update(c0, f0)
    with pytest.raises(ValueError, match=r"locations must have shape \(3, 2\)"):
        filt.update(c0, f0, locations=torch.zeros(B, 3, dtype=F64))
    with pytest.raises(ValueError, match="locations contains NaN"):
        filt.update(c0, f0, locations=torch.full((B, 2), float("nan"), dtype=F64))
    planar = InverseRFT(envs[0][0], envs[0][1], hyper_posterior="map")
    flat = TerrainFilter(planar, n_envs=B)
    assert not flat.spatial
    with pytest.raises(ValueError, match="no spatial factor"):
        flat.update(c0, f0, locations=torch.zeros(B, 2, dtype=F64))
    with pytest.raises(ValueError, match="no spatial factor"):
        flat.stress_map(torch.zeros(1), torch.zeros(1), locations=torch.zeros(B, 2))
