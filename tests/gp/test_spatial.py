"""Maps over the ground (``InverseRFT(..., locations=)``, ``gp.kernels.spatial``, ``gp.backends.spatial``): the
posterior against a dense reference built by hand with the explicit product covariance, the planar model as the
special case, streaming against batch, and bad input refused by name."""

import math

import pytest
import torch

from irft_torch import InverseRFT, MapPrior, rft
from irft_torch.rft import CToe, FourierStressMap, TerrainField, course_path, walk
from irft_torch.rft.contacts import Contacts

F64 = torch.float64
LOOSE = FourierStressMap.poppy_seeds_loose()
CLOSE = FourierStressMap.poppy_seeds_close()


def _walk(n_stances=6, stride=0.15, seed=0, noise=0.02):
    """A C-toe's scoop repeated at footholds along x over two media (boundary at x = 0.4 m), forces with 2 %
    noise: (contacts, forces (T, 2) N, locations (T, 2) m)."""
    toe = CToe(0.025, 0.02, n_segments=5)
    stroke = course_path([-0.6, -0.2, 0.3], 0.06, start=(0.0, 0.0), n_steps=8)
    p = torch.stack([torch.arange(n_stances, dtype=F64) * stride, torch.zeros(n_stances, dtype=F64)], -1)
    w = walk(toe, stroke, p, torch.zeros(n_stances, dtype=F64))
    keep = (w.contacts.weight_z != 0).any(-1)
    c, s = w.contacts[keep], w.locations[keep]
    field = TerrainField.two_media(LOOSE, CLOSE, boundary=0.4, width=0.05)
    F = rft.forces(field, c, locations=s)
    g = torch.Generator().manual_seed(seed)
    F = F + noise * F.abs().mean(0) * torch.randn(F.shape, generator=g, dtype=F64)
    return c, F, s


def _set(model, v=(0.3, 0.5), ls=(0.25, 0.4)):
    with torch.no_grad():
        model.hypers.spatial.kernel.outputscale = torch.tensor(v, dtype=F64)
        model.hypers.spatial.kernel.base_kernel.lengthscale = torch.tensor(ls, dtype=F64).reshape(2, 1, 1)


def _embed(beta, gamma):
    return torch.stack([torch.sin(2 * beta), torch.cos(2 * beta), torch.sin(gamma), torch.cos(gamma)], -1)


def _angle_kernel(model, b1, g1, b2, g2):
    """(2, N1, N2) the angle kernel by hand: the RBF on (sin 2b, cos 2b, sin g, cos g) plus Li et al.'s nine
    functions {1, cos 2b, sin 2b} x {1, cos g, sin g} / 2 (``gp.kernels.li_basis``: |f|^2 = 1) with their
    variance."""
    h = model.hypers
    ls = h.lengthscale.detach()[:, 0, :]  # (2, 4)
    e1, e2 = _embed(b1, g1), _embed(b2, g2)
    d2 = ((e1[None, :, None, :] - e2[None, None, :, :]) / ls[:, None, None, :]).pow(2).sum(-1)
    K = h.outputscale.detach()[:, None, None] * torch.exp(-0.5 * d2)

    def li(b, g):
        a = torch.stack([torch.ones_like(b), torch.cos(2 * b), torch.sin(2 * b)], -1)
        c = torch.stack([torch.ones_like(g), torch.cos(g), torch.sin(g)], -1)
        return 0.5 * (a[:, :, None] * c[:, None, :]).reshape(len(b), 9)

    if h.li is not None:
        K = K + h.li.variance.detach()[:, None, None] * (li(b1, g1) @ li(b2, g2).T)[None]
    if h.li is not None and h.li.generic:  # the generic shape's term u_a g_a(theta) g_a(theta'), g: Li et al.'s map
        gen = FourierStressMap.generic().to(F64)
        a, b = gen(b1, g1).T, gen(b2, g2).T  # (2, N)
        K = K + h.li.generic_variance.detach()[:, None, None] * a[:, :, None] * b[:, None, :]
    return K


def _matern(model, s1, s2):
    """(2, N1, N2) v k_5/2(|s - s'| / l) by hand."""
    v = model.hypers.spatial.variance.detach()
    ls = model.hypers.spatial.lengthscale.detach()
    r = (s1[:, None, :] - s2[None, :, :]).norm(dim=-1)[None] / ls[:, None, None]
    return v[:, None, None] * (1 + math.sqrt(5) * r + 5 / 3 * r.pow(2)) * torch.exp(-math.sqrt(5) * r)


def _dense(model, c, F, s, qc, qs):
    """Posterior mean and variance (2, N) of the weighted sums of query contacts qc at places qs (None: the shared
    medium) from training (c, F, s), with the explicit product covariance (zero prior mean)."""
    def rows(x):
        keep = x.weight_z.reshape(-1) != 0
        b, g = x.beta.reshape(-1)[keep], x.gamma.reshape(-1)[keep]
        t = torch.arange(len(x))[:, None].expand(x.shape).reshape(-1)[keep]
        W = torch.zeros(2, len(x), int(keep.sum()), dtype=F64)
        W[0, t, torch.arange(len(t))] = x.weight_x.reshape(-1)[keep]
        W[1, t, torch.arange(len(t))] = x.weight_z.reshape(-1)[keep]
        return b, g, W

    b1, g1, W1 = rows(c)
    b2, g2, W2 = rows(qc)
    K11 = W1 @ _angle_kernel(model, b1, g1, b1, g1) @ W1.mT * (1 + _matern(model, s, s))
    f12 = 1.0 if qs is None else 1 + _matern(model, s, qs)
    f22 = 1.0 if qs is None else 1 + _matern(model, qs, qs)
    K12 = W1 @ _angle_kernel(model, b1, g1, b2, g2) @ W2.mT * f12
    K22 = W2 @ _angle_kernel(model, b2, g2, b2, g2) @ W2.mT * f22
    A = K11 + model.hypers.noise.detach()[:, None, None] * torch.eye(len(c), dtype=F64)
    mean = (K12.mT @ torch.linalg.solve(A, F.T[..., None]))[..., 0]
    var = torch.diagonal(K22 - K12.mT @ torch.linalg.solve(A, K12), dim1=-2, dim2=-1)
    return mean, var, K11


@pytest.mark.parametrize("li_basis", [False, True, "generic"])
def test_spatial_posterior_is_the_dense_product_covariance_model(li_basis):
    c, F, s = _walk()
    kernel = {False: "rbf", True: "li", "generic": "li+generic"}[li_basis]
    m = InverseRFT(c, F, locations=s, hyper_posterior="map", prior=MapPrior(kernel=kernel))
    _set(m)
    assert m.spatial and m.method == "spatial"
    # maps at places on and off the footholds
    beta = torch.tensor([0.1, -0.5, 0.9], dtype=F64)
    gamma = torch.tensor([1.2, -0.3, 2.0], dtype=F64)
    where = torch.tensor([[0.0, 0.0], [0.37, 0.1], [1.2, -0.2]], dtype=F64)
    post = m.stress_map(beta, gamma, locations=where)
    assert post.mean.shape == (3, 3, 2)
    qc = Contacts.points(beta.repeat(3), gamma.repeat(3))
    qs = where.repeat_interleave(3, 0)
    mean, var, K11 = _dense(m, c, F, s, qc, qs)
    torch.testing.assert_close(post.mean.reshape(-1, 2), mean.T, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(post.variance.reshape(-1, 2), var.T, rtol=1e-8, atol=1e-10)
    # the medium shared by the site (no places): factor 1 in every covariance with it
    shared = m.stress_map(beta, gamma)
    mean0, var0, _ = _dense(m, c, F, s, Contacts.points(beta, gamma), None)
    torch.testing.assert_close(shared.mean, mean0.T, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(shared.variance, var0.T, rtol=1e-8, atol=1e-10)
    # forces of new contacts, each at its own place
    qc2, qs2 = c[::7], s[::7] + torch.tensor([0.05, 0.02], dtype=F64)
    pred = m.predict_forces(qc2, locations=qs2)
    mean2, var2, _ = _dense(m, c, F, s, qc2, qs2)
    torch.testing.assert_close(pred.mean, mean2.T, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(pred.variance, var2.T, rtol=1e-8, atol=1e-8)
    # the marginal likelihood per sample
    A = K11 + m.hypers.noise.detach()[:, None, None] * torch.eye(len(c), dtype=F64)
    ref = -torch.distributions.MultivariateNormal(torch.zeros(len(c), dtype=F64), A).log_prob(F.T) / len(c)
    with torch.no_grad():
        torch.testing.assert_close(m.backend.negative_log_likelihood(), ref, rtol=1e-9, atol=1e-10)


def test_gpytorch_exact_gp_predicts_what_the_spatial_backend_does():
    """The backend's own Cholesky path against gpytorch's prediction from its ExactGP (inputs: places in front of
    the composite rows, the product kernel)."""
    c, F, s = _walk(n_stances=4)
    m = InverseRFT(c, F, locations=s, hyper_posterior="map", li_basis=False)
    _set(m)
    from irft_torch.gp.backends.spatial import encode_placed

    q = c[::5].with_locations(s[::5] + 0.03)
    m.gp.eval()
    import gpytorch

    with torch.no_grad(), gpytorch.settings.fast_pred_var(False), gpytorch.settings.max_cholesky_size(10**6):
        ref = m.gp(encode_placed(q, m.backend.n_segments))
        got = m.predict_forces(q)
    torch.testing.assert_close(got.mean, ref.mean.T, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(got.variance, ref.variance.T, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("kernel", ["li", "li+generic"])
def test_equal_places_are_the_planar_model_with_the_factor_in_its_variances(kernel):
    """Every sample at one place: the factor is 1 + v everywhere, so the spatial model is the planar one with its
    angle variances times 1 + v (to 1e-10), for the planar default's kernel and the spatial default's; with no
    places at all the planar model is built."""
    from irft_torch import MapPrior

    c, F, s = _walk(n_stances=4)
    here = torch.tensor([0.3, -0.1], dtype=F64)
    prior = MapPrior(kernel=kernel)
    sp = InverseRFT(c, F, locations=here.expand(len(c), 2), hyper_posterior="map", prior=prior)
    _set(sp)
    pl = InverseRFT(c, F, hyper_posterior="map", prior=prior)
    assert not pl.spatial and pl.method != "spatial"
    v = sp.hypers.spatial.variance.detach()
    with torch.no_grad():
        pl.hypers.lengthscale = sp.hypers.lengthscale.detach()
        pl.hypers.outputscale = sp.hypers.outputscale.detach() * (1 + v)
        pl.hypers.li.variance = sp.hypers.li.variance.detach() * (1 + v)
        if kernel == "li+generic":
            pl.hypers.li.generic_variance = sp.hypers.li.generic_variance.detach() * (1 + v)
        pl.hypers.noise = sp.hypers.noise.detach()
    beta, gamma = torch.meshgrid(torch.linspace(-1.4, 1.4, 7, dtype=F64), torch.linspace(-3, 3, 9, dtype=F64),
                                 indexing="ij")
    a = sp.stress_map(beta, gamma, locations=here[None])
    b = pl.stress_map(beta, gamma)
    torch.testing.assert_close(a.mean[0], b.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(a.variance[0], b.variance, rtol=1e-10, atol=1e-12)


def test_the_defaults_over_the_ground_add_the_generic_shape():
    """A model with places takes MapPrior(kernel="li+generic") by default (its scale then varies over the ground),
    one without keeps "li"; a kernel asked for is kept."""
    from irft_torch import MapPrior

    c, F, s = _walk(n_stances=3)
    assert InverseRFT(c, F, locations=s, hyper_posterior="map").prior.kernel == "li+generic"
    assert InverseRFT(c.with_locations(s), F, hyper_posterior="map").prior.kernel == "li+generic"
    assert InverseRFT(c, F, hyper_posterior="map").prior.kernel == "li"
    m = InverseRFT(c, F, locations=s, hyper_posterior="map", prior=MapPrior(kernel="li"))
    assert m.prior.kernel == "li" and not m.hypers.li.generic


def test_streaming_stances_equals_the_batch_model():
    c, F, s = _walk(n_stances=5)
    half = len(c) // 2
    batch = InverseRFT(c, F, locations=s, hyper_posterior="map")
    _set(batch)
    grown = InverseRFT(c[:half], F[:half], locations=s[:half], hyper_posterior="map")
    grown.hypers.load_state_dict(batch.hypers.state_dict())
    grown.add_data(c[half:], F[half:], locations=s[half:])
    where = torch.tensor([[0.1, 0.0], [0.5, 0.2]], dtype=F64)
    beta, gamma = torch.tensor([0.2, -0.7], dtype=F64), torch.tensor([1.0, 2.5], dtype=F64)
    a, b = grown.stress_map(beta, gamma, locations=where), batch.stress_map(beta, gamma, locations=where)
    torch.testing.assert_close(a.mean, b.mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(a.variance, b.variance, rtol=1e-9, atol=1e-11)


def test_places_are_refused_by_name_where_they_do_not_fit():
    c, F, s = _walk(n_stances=3)
    with pytest.raises(ValueError, match="locations"):
        InverseRFT(c, F, locations=s[:-1])
    with pytest.raises(ValueError, match="locations"):
        InverseRFT(c, F, locations=torch.full_like(s, math.nan))
    with pytest.raises(ValueError, match="method"):
        InverseRFT(c, F, locations=s, method="spectral")
    planar = InverseRFT(c, F, hyper_posterior="map")
    with pytest.raises(ValueError, match="locations"):
        planar.stress_map(torch.zeros(2), torch.zeros(2), locations=torch.zeros(1, 2))
    with pytest.raises(ValueError, match="locations"):
        planar.predict_forces(c, locations=s)
    sp = InverseRFT(c, F, locations=s, hyper_posterior="map")
    with pytest.raises(ValueError, match="locations"):
        sp.add_data(c[:3], F[:3])
    with pytest.raises(ValueError, match="locations"):
        sp.stress_map(torch.zeros(2), torch.zeros(2), locations=torch.zeros(2, 3))
    with pytest.raises(ValueError, match="locations"):
        Contacts.cat([c[:2].with_locations(s[:2]), c[2:4]])
    # places survive indexing, cat, to and the weight changes
    placed = c.with_locations(s)
    torch.testing.assert_close(Contacts.cat([placed[:3], placed[3:]]).locations, s)
    torch.testing.assert_close(placed.scale_weights(2.0, 3.0).locations, s)
    torch.testing.assert_close(placed.pad_segments(c.n_segments + 2).locations, s)


def test_a_saved_spatial_model_loads_with_its_places_and_predicts_the_same(tmp_path):
    c, F, s = _walk(n_stances=3)
    m = InverseRFT(c, F, locations=s, hyper_posterior="map")
    _set(m)
    m.save(tmp_path / "m.pt")
    back = InverseRFT.load(tmp_path / "m.pt")
    assert back.spatial
    torch.testing.assert_close(back.train_contacts.locations, s)
    where = torch.tensor([[0.2, 0.1]], dtype=F64)
    a = m.stress_map(torch.tensor([0.3]), torch.tensor([1.0]), locations=where)
    b = back.stress_map(torch.tensor([0.3]), torch.tensor([1.0]), locations=where)
    torch.testing.assert_close(a.mean, b.mean, rtol=1e-12, atol=1e-12)
