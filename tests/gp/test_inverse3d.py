"""3-D I-RFT (gp.inverse3d) against a dense reference written plainly (explicit W over every element, explicit K,
torch Cholesky), against the planar model (its special case), and on what a user sees (errors, save/load)."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.gp.inverse3d import InverseRFT3D
from irft_torch.rft import (
    Contacts3D,
    CToe,
    FourierStressMap,
    Mesh,
    contacts,
    contacts_3d,
    forces,
    forces_3d,
    planar_motion,
    spline_path,
)


# ---- the dense reference ------------------------------------------------------------------------------------------
def _embed(b, g):
    return torch.stack([torch.sin(2 * b), torch.cos(2 * b), torch.sin(g), torch.cos(g)], -1)


def _k_map(b1, g1, b2, g2, ls, s, constant, v=None):
    """The RBF on the embedding (+ Li et al.'s term v (1 + cos 2 dbeta)(1 + cos dgamma) / 4, from the angle
    differences); a constant map: s."""
    if constant:
        return s * torch.ones(b1.shape[0], b2.shape[0], dtype=b1.dtype)
    a, c = _embed(b1, g1) / ls, _embed(b2, g2) / ls
    k = s * torch.exp(-0.5 * ((a[:, None] - c[None]) ** 2).sum(-1))
    if v is not None:
        db, dg = b1[:, None] - b2[None], g1[:, None] - g2[None]
        k = k + v * (1 + torch.cos(2 * db)) * (1 + torch.cos(dg)) / 4
    return k


def _W(w):
    """(T, K) -> (T, T*K) block rows."""
    T, K = w.shape
    out = torch.zeros(T, T * K, dtype=w.dtype)
    for t in range(T):
        out[t, t * K:(t + 1) * K] = w[t]
    return out


def _rows(c):
    """Per map, the explicit (3T, T K) weight matrix over the rows (F_x, F_y, F_z) x T."""
    T, K = c.shape
    z = torch.zeros(T, T * K, dtype=c.beta.dtype)
    Wx = torch.cat([_W(c.weight_x[..., 0]), _W(c.weight_x[..., 1]), z])
    Wy = torch.cat([_W(c.weight_y[..., 0]), _W(c.weight_y[..., 1]), z])
    Wz = torch.cat([z, z, _W(c.weight_z)])
    return (Wx, Wy, Wz), c.beta.reshape(-1), c.gamma.reshape(-1)


def dense(c, f, ls, os, noise, constant_y, li=None):
    """(nll / T summed, posterior function of (contacts) -> mean (T, 3), full covariance (3T, 3T)); ``li`` (3,):
    Li et al.'s term's variance per map."""
    Ws, b, g = _rows(c)
    T = len(c)

    def _k(b1, g1, b2, g2, ls_m, s, constant, m=None):
        return _k_map(b1, g1, b2, g2, ls_m, s, constant, None if li is None or m is None else li[m])

    Ks = [_k(b, g, b, g, ls[m, 0], os[m], constant_y and m == 1, m) for m in range(3)]
    C = sum(W @ K @ W.T for W, K in zip(Ws, Ks)) + torch.diag(noise.repeat_interleave(T))
    y = f.T.reshape(-1)
    L = torch.linalg.cholesky(C)
    alpha = torch.cholesky_solve(y[:, None], L)[:, 0]
    nll = 0.5 * (y @ alpha + 2 * torch.log(torch.diagonal(L)).sum() + 3 * T * math.log(2 * math.pi)) / T

    def post(q):
        Wq, bq, gq = _rows(q)
        Kqt = sum(Wa @ _k(bq, gq, b, g, ls[m, 0], os[m], constant_y and m == 1, m) @ Wt.T
                  for m, (Wa, Wt) in enumerate(zip(Wq, Ws)))
        Kqq = sum(Wa @ _k(bq, gq, bq, gq, ls[m, 0], os[m], constant_y and m == 1, m) @ Wa.T
                  for m, Wa in enumerate(Wq))
        mean = Kqt @ alpha
        cov = Kqq - Kqt @ torch.cholesky_solve(Kqt.T, L)
        return mean.reshape(3, -1).T, cov

    return nll, post


def per_sample(cov, T):
    return cov.reshape(3, T, 3, T).diagonal(dim1=1, dim2=3).permute(2, 0, 1)


# ---- data: a C-toe turning about the vertical while it strokes and drifts sideways --------------------------------
def turning_toe(T=10, seed=0):
    gen = torch.Generator().manual_seed(seed)
    mesh = Mesh.from_toe(CToe(0.02, 0.01, n_segments=4), n_across=2).to(dtype=torch.float64)
    t = torch.linspace(0, 1, T, dtype=torch.float64)  # float64 whatever torch's default (a module fixture runs first)
    yaw = 0.9 * t
    c, s, z, o = torch.cos(yaw), torch.sin(yaw), torch.zeros_like(t), torch.ones_like(t)
    R = torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)
    v = torch.stack([0.02 * o, 0.01 * torch.sin(3 * t), -0.01 * torch.cos(2 * t)], -1)
    w = torch.stack([z, z, 0.9 * o], -1)
    x0 = torch.stack([0.02 * t, z, -0.015 - 0.01 * t], -1)
    cc = contacts_3d(mesh, v, w, surface=0.0, position=x0, rotation=R)
    f = forces_3d(FourierStressMap.generic(0.5, 0.6), cc, alpha_y=0.1)
    return cc, f + 0.02 * torch.randn(f.shape, generator=gen, dtype=f.dtype)


def _set(model, ls, os, noise):
    with torch.no_grad():
        model.hypers.lengthscale = ls
        model.hypers.outputscale = os
        model.hypers.noise = noise


CASES = [(m, a) for m in ("observations", "pairs", "spectral") for a in ("map", "constant")]


@pytest.mark.parametrize("method,alpha_y", CASES)
def test_backends_match_the_dense_reference(method, alpha_y):
    c, f = turning_toe()
    tol = 1e-12 if method == "spectral" else 1e-7
    model = InverseRFT3D(c, f, method=method, alpha_y=alpha_y, priors=None, tol=tol, prior_mean="zero")
    gen = torch.Generator().manual_seed(1)
    ls = (0.8 + torch.rand(3, 1, 4, generator=gen))
    _set(model, ls, torch.tensor([0.09, 0.02, 0.2]), torch.tensor([4e-4, 3e-4, 5e-4]))
    model.backend.refresh()
    if method == "spectral":  # each map in a basis of its own (sized for its lengthscales), not all the same
        assert len({b for b in model.backend.bases if b is not None}) > 1
    # spectral: exact to its truncation (basis sized for 1e-12 relative kernel error); the others: arithmetic
    rtol = 1e-8 if method != "spectral" else 1e-7
    loss = model.loss()
    loss.backward()
    raw = [p for p in model.hypers.parameters() if p.requires_grad]
    grads = [p.grad.clone() for p in raw]
    for p in raw:
        p.grad = None
    ref, post = dense(c, f, model.hypers.lengthscale, model.hypers.outputscale, model.hypers.noise,
                      alpha_y == "constant")
    ref.backward()
    torch.testing.assert_close(loss, ref, rtol=rtol, atol=0)
    for g, p in zip(grads, raw):
        torch.testing.assert_close(g, p.grad, rtol=1e-6 if method != "spectral" else 1e-5, atol=1e-9)
    assert_predictions_match(model, post, rtol)


def assert_predictions_match(model, post, rtol):
    """Forces of new contacts (mean, each sample's 3 x 3 covariance, the joint block covariances) and map
    posteriors at points off the data (alpha_x with its mirror sign, alpha_y, alpha_z) against the dense
    posterior ``post``; returns the stress map's posterior at those points."""
    from irft_torch.gp.inverse3d import point_contacts

    q, _ = turning_toe(T=6, seed=2)
    q = q[1:5]
    b = torch.tensor([-1.2, 0.3, 1.0, 0.1], dtype=torch.float64)
    gm = torch.tensor([0.4, -1.1, 2.5, 0.0], dtype=torch.float64)
    with torch.no_grad():
        mean_ref, cov_ref = post(q)
        pred = model.predict_forces(q)
        torch.testing.assert_close(pred.mean, mean_ref, rtol=rtol, atol=1e-10)
        torch.testing.assert_close(pred.covariance, per_sample(cov_ref, len(q)), rtol=1e-6, atol=1e-10)
        _, _, joints = model.backend.posterior(q, joint=True)
        T = len(q)
        torch.testing.assert_close(joints[0], cov_ref[:2 * T, :2 * T], rtol=1e-6, atol=1e-10)
        torch.testing.assert_close(joints[1], cov_ref[2 * T:, 2 * T:], rtol=1e-6, atol=1e-10)
        sm = model.stress_map(b, gm)
        pm, pc = post(point_contacts(b, gm))
        torch.testing.assert_close(sm.mean, pm, rtol=rtol, atol=1e-10)
        torch.testing.assert_close(sm.covariance, per_sample(pc, 4), rtol=1e-6, atol=1e-10)
    return sm, point_contacts(b, gm)


def test_planar_motion_is_the_planar_model():
    """A C-toe in the x-z plane: alpha_x and alpha_z posteriors, forces and the loss are the planar model's, the
    F_y rows adding only their own noise term (F_y here pure noise); on every backend."""
    toe = CToe(0.02, 0.008, n_segments=6)
    path = spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=30)
    c2 = contacts(toe, path)
    f2 = forces(FourierStressMap.generic(), c2)
    c3 = contacts_3d(Mesh.from_toe(toe), surface=0.0, **planar_motion(path))
    fy = 0.01 * torch.randn(len(c2), generator=torch.Generator().manual_seed(0))
    f3 = torch.stack([f2[:, 0], fy, f2[:, 1]], -1)
    for method in ("observations", "pairs", "spectral"):
        m2 = irft.InverseRFT(c2, f2, method=method, priors=None, hyper_posterior="map", li_basis=False)
        m3 = irft.InverseRFT(c3, f3, method=method, priors=None, prior_mean="zero", hyper_posterior="map",
                             li_basis=False)  # the planar default
        assert isinstance(m3, InverseRFT3D)
        ls, os, nz = m2.hypers.lengthscale, m2.hypers.outputscale, m2.hypers.noise
        _set(m3, torch.stack([ls[0], ls[0] * 1.3, ls[1]]), torch.stack([os[0], os[0], os[1]]),
             torch.stack([nz[0], torch.tensor(2e-4), nz[1]]))
        sy = m3.hypers.noise[1]
        own = 0.5 * (fy.pow(2).sum() / sy + len(fy) * torch.log(sy) + len(fy) * math.log(2 * math.pi)) / len(fy)
        torch.testing.assert_close(m3.loss().detach(), (m2.loss() + own).detach(), rtol=1e-12, atol=1e-12)
        b = torch.linspace(-1.5, 1.5, 9)
        p3, p2 = m3.stress_map(b, b.flip(0)), m2.stress_map(b, b.flip(0))
        torch.testing.assert_close(p3.mean[:, [0, 2]], p2.mean, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(p3.variance[:, [0, 2]], p2.variance, rtol=1e-10, atol=1e-12)
        q3, q2 = m3.predict_forces(c3), m2.predict_forces(c2)
        torch.testing.assert_close(q3.mean[:, [0, 2]], q2.mean, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(q3.variance[:, [0, 2]], q2.variance, rtol=1e-10, atol=1e-10)
        assert q3.covariance[:, 2, :2].abs().max() == 0  # F_z independent of (F_x, F_y)


def test_fit_recovers_the_medium_and_round_trips(tmp_path):
    c, f = turning_toe(T=24)
    model = irft.InverseRFT(c, f, alpha_y="constant", hyper_posterior="map", li_basis=False)
    model.fit(n_iter=60, lr=0.05, progress=False)
    pred = model.predict_forces(c)
    assert ((pred.mean - f).pow(2).mean(0).sqrt() < 0.15 * f.pow(2).mean(0).sqrt() + 0.05).all()
    draws = model.sample_maps(torch.zeros(3), torch.tensor([0.0, 0.5, 1.0]), n=4,
                              generator=torch.Generator().manual_seed(0))
    assert draws.shape == (4, 3, 3)
    assert (draws[:, :, 1] - draws[:, :1, 1]).abs().max() < 1e-6  # a constant alpha_y: one value per draw (jitter)
    assert draws[:, 0, 1].std() > 0
    model.save(tmp_path / "m3.pt")
    back = InverseRFT3D.load(tmp_path / "m3.pt")
    torch.testing.assert_close(back.predict_forces(c).mean, pred.mean, rtol=1e-10, atol=1e-12)
    # the front door reads the file it wrote (as it builds the 3-D model from Contacts3D); a damaged file: named
    front = irft.InverseRFT.load(tmp_path / "m3.pt")
    assert isinstance(front, InverseRFT3D) and front.alpha_y == "constant"
    torch.testing.assert_close(front.predict_forces(c).covariance, pred.covariance, rtol=1e-10, atol=1e-12)
    (tmp_path / "bad.pt").write_bytes((tmp_path / "m3.pt").read_bytes()[:200])
    from irft_torch.gp.model_file import ModelFileError

    for load in (irft.InverseRFT.load, InverseRFT3D.load):
        with pytest.raises(ModelFileError, match="bad.pt"):
            load(tmp_path / "bad.pt")
    cv = model.cross_validate(torch.arange(len(c)) // 6)
    assert cv.mean.shape == (len(c), 3) and (cv.variance > 0).all()


def test_bad_input():
    c, f = turning_toe(T=4)
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        irft.InverseRFT(c, f[:, :2], hyper_posterior="map", li_basis=False)
    with pytest.raises(ValueError, match="alpha_y"):
        InverseRFT3D(c, f, alpha_y="field")
    with pytest.raises(ValueError, match="NaN"):
        InverseRFT3D(c, f * float("nan"))
    with pytest.raises(ValueError, match="method"):
        InverseRFT3D(c, f, method="grid")
    with pytest.raises(TypeError, match="Contacts3D"):
        InverseRFT3D(c, f).predict_forces(c.planar())
    empty = Contacts3D(c.beta, c.gamma, c.weight_x * 0, c.weight_y * 0, c.weight_z * 0)
    with pytest.raises(ValueError, match="no element"):
        InverseRFT3D(empty, f)
    for key, value in (("locations", torch.zeros(4, 2)), ("surface", True), ("noise_scale", torch.ones(4)),
                       ("statistics", object())):  # the planar model's options, refused by name (None: not asked)
        with pytest.raises(TypeError, match=f"no {key}=: .* planar only"):
            irft.InverseRFT(c, f, **{key: value})
        InverseRFT3D(c, f, **{key: None})


def test_a_diverging_3d_fit_keeps_its_best_iterate_and_says_so():
    """lr far too large: the loss climbs; the model ends at the best step's hyperparameters (its loss is the history's
    minimum), with a FitDivergedWarning naming a smaller lr. A NaN loss stops the fit at once, best iterate kept."""
    from irft_torch.gp.fit_control import FitDivergedWarning

    c, f = turning_toe(T=12)
    m = InverseRFT3D(c, f, method="pairs")
    with pytest.warns(FitDivergedWarning, match="try lr = 0.5"):
        hist = m.fit(n_iter=40, lr=5.0, progress=False)
    assert max(hist) > min(hist) + 0.1
    torch.testing.assert_close(m.loss().detach(), torch.tensor(min(hist), dtype=torch.float64), rtol=1e-9, atol=1e-12)

    m = InverseRFT3D(c, f, method="pairs")
    real, calls = m.backend.loss, []

    def poisoned():
        calls.append(1)
        out = real()
        return out * float("nan") if len(calls) == 6 else out

    m.backend.loss = poisoned
    with pytest.warns(FitDivergedWarning, match="to nan"):
        hist = m.fit(n_iter=20, lr=0.05, progress=False)
    assert len(hist) == 6 and math.isnan(hist[-1])
    m.backend.loss = real
    torch.testing.assert_close(m.loss().detach(), torch.tensor(min(hist[:5]), dtype=torch.float64), rtol=1e-9,
                               atol=1e-12)


def test_a_converged_3d_fit_ends_at_the_mode():
    """Adam stops where it has converged and L-BFGS finishes: the fit ends where central finite differences of the
    log posterior (T x the loss) vanish along every raw hyperparameter, below the last Adam step's loss."""
    c, f = turning_toe(T=24)
    m = InverseRFT3D(c, f, method="pairs")
    hist = m.fit(n_iter=300, progress=False)
    assert len(hist) < 300  # stopped on convergence (then the polished loss appended)
    assert hist[-1] <= min(hist[:-1])
    T, h = len(c), 1e-4
    with torch.no_grad():
        torch.testing.assert_close(m.loss(), torch.tensor(hist[-1], dtype=torch.float64), rtol=1e-12, atol=0)
        for p in m.hypers.parameters():
            for i in range(p.numel()):
                flat = p.view(-1)
                x = float(flat[i])
                flat[i] = x + h
                up = float(m.loss())
                flat[i] = x - h
                down = float(m.loss())
                flat[i] = x
                assert abs(T * (up - down) / (2 * h)) < 0.05, (i, T * (up - down) / (2 * h))


def test_a_map_whose_lengthscales_shorten_grows_its_own_basis_only():
    """The spectral backend keeps a basis per map: shortening alpha_z's lengthscales grows alpha_z's basis (to one
    that holds the exact RBF, written out, within tol there, where the old one did not) and leaves the others' as
    they were."""
    from .dense_reference import truncation_gaps

    c, f = turning_toe()
    model = InverseRFT3D(c, f, method="spectral", tol=1e-7)
    before = model.backend.bases
    with torch.no_grad():
        ls = model.hypers.lengthscale.clone()
        ls[2] = torch.tensor([[0.3, 0.4, 0.5, 0.6]], dtype=ls.dtype)
        model.hypers.lengthscale = ls
    assert model.backend.stale() and model.backend.refresh()
    after = model.backend.bases
    assert after[0] == before[0] and after[1] == before[1] and after[2] != before[2]
    ls_z = model.hypers.lengthscale.detach()[2:3]
    assert float(truncation_gaps(after[2], ls_z)[0]) <= 1e-7 < float(truncation_gaps(before[2], ls_z)[0])
    assert float(model.backend.truncation_error().max()) <= 1e-7


def test_ctrl_c_in_the_polish_keeps_the_values_before_it_and_says_so():
    """Ctrl-C while L-BFGS probes: the model keeps the values the polish started from (not a line-search probe's),
    with a warning: its loss is the one the polish evaluated first."""
    c, f = turning_toe(T=24)
    m = InverseRFT3D(c, f, method="pairs")
    real, calls = m.backend.loss, []
    adam_steps = []

    start = []

    def interrupted():
        calls.append(1)
        if adam_steps and len(calls) == adam_steps[0] + 4:  # the polish's third evaluation
            raise KeyboardInterrupt
        out = real()
        if adam_steps and len(calls) == adam_steps[0] + 1:  # the polish's first: where it starts
            start.append(float(out))
        return out

    import irft_torch.gp.fit_control as model_module  # the fit's loop (the planar one)

    converged = model_module.converged

    def seen(history, n):
        done = converged(history, n)
        if done:
            adam_steps.append(len(history))
        return done

    m.backend.loss = interrupted
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(model_module, "converged", seen)
        with pytest.warns(UserWarning, match="interrupted in its L-BFGS polish"):
            hist = m.fit(n_iter=300, progress=False)
    m.backend.loss = real
    assert adam_steps and len(hist) == adam_steps[0]  # no polished loss appended
    assert len(calls) == adam_steps[0] + 4  # the interrupt came inside the polish
    torch.testing.assert_close(m.loss().detach(), torch.tensor(start[0], dtype=torch.float64), rtol=1e-12, atol=0)


def test_an_interrupted_basis_growth_leaves_the_backend_as_it_was():
    """Ctrl-C while the spectral backend recomputes its features for a grown basis: the bases and the data factors
    stay those before it, so the loss is what it was (the grown basis is asked for again by the next refresh)."""
    c, f = turning_toe()
    model = InverseRFT3D(c, f, method="spectral")
    before, loss = model.backend.bases, float(model.loss())
    with torch.no_grad():
        ls = model.hypers.lengthscale.clone()
        ls[2] = torch.tensor([[0.3, 0.4, 0.5, 0.6]], dtype=ls.dtype)
        model.hypers.lengthscale = ls
    stale_loss = float(model.loss())
    real, calls = model.backend._features, []

    def interrupted(contacts, b):
        calls.append(b)
        if b == 1:  # the second block, after the first block's factor was made
            raise KeyboardInterrupt
        return real(contacts, b)

    model.backend._features = interrupted
    with pytest.raises(KeyboardInterrupt):
        model.backend.refresh()
    model.backend._features = real
    assert calls == [0, 1] and model.backend.bases == before
    assert float(model.loss()) == stale_loss and stale_loss != loss
    assert model.backend.refresh() and model.backend.bases[2] != before[2]
