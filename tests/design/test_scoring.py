"""Probe scoring: information gain and integrated variance against a dense reference (explicit W,
explicit K, torch Cholesky), for a fitted model on every backend and for the prior; heteroscedastic
candidates; conditioning, greedy design (the chain rule of information), and gradients."""

import math

import pytest
import torch
from gp.dense_reference import W_dense, k_dense
from gp.test_backends_vs_dense import random_contacts, set_hypers

import irft_torch as irft
from irft_torch.design import ProbeScorer, Region, force_relative, greedy_design
from irft_torch.rft import Contacts, FourierStressMap

TOL = {"observations": 1e-8, "pairs": 1e-8, "spectral": 1e-6}


def angles(c):
    return torch.stack([c.beta.reshape(-1), c.gamma.reshape(-1)], -1)


def dense_cov(ls, os, noise, train, blocks, interp=None):
    """Per axis: the posterior covariance of the stacked weighted sums of ``blocks`` (a list of
    Contacts) after observing ``train`` (None: the prior), from explicit W and K. With ``interp``
    (a function Contacts -> dense (2, T, U) interpolation rows and the node angles (U, 2)) the blocks
    are read from the map's posterior at the nodes instead."""
    out = []
    for a, wname in enumerate(("weight_x", "weight_z")):
        k = lambda A, B: k_dense(A, B, ls[a, 0], os[a])  # noqa: E731
        Ws = torch.block_diag(*[W_dense(getattr(c, wname)) for c in blocks])
        ths = torch.cat([angles(c) for c in blocks])
        if interp is not None:
            nodes = interp["nodes"]
            Ws = torch.cat([interp["phi"](c)[a] for c in blocks])
            ths = nodes
        Kss = k(ths, ths)
        if train is not None:
            W = W_dense(getattr(train, wname))
            th = angles(train)
            S = W @ k(th, th) @ W.T + noise[a] * torch.eye(W.shape[0])
            Kst = k(ths, th) @ W.T
            Kss = Kss - Kst @ torch.linalg.solve(S, Kst.T)
        out.append(Ws @ Kss @ Ws.T)
    return out


def eig_dense(covs, noise):
    return sum(0.5 * torch.logdet(torch.eye(S.shape[0]) + S / noise[a]) for a, S in enumerate(covs))


def iv_dense(covs, noise, os, region, n_cand):
    """covs over [region points, candidate]: integrated variance now and after the candidate."""
    now = after = 0.0
    n = region.beta.numel()
    for a, S in enumerate(covs):
        var = torch.diagonal(S[:n, :n])
        k = S[:n, n:]
        post = var - torch.diagonal(k @ torch.linalg.solve(S[n:, n:] + noise[a] * torch.eye(n_cand), k.T))
        now = now + (region.weight * var).sum() / os[a]
        after = after + (region.weight * post).sum() / os[a]
    return now, after


def hypers(model):
    return (model.hypers.lengthscale.detach(), model.hypers.outputscale.detach(), model.hypers.noise.detach())


def fitted(method="observations"):
    c = random_contacts(T=20, M=3, seed=21, repeated=(method == "pairs"))
    m = irft.InverseRFT(c, irft.rft.forces(FourierStressMap.generic(), c), method=method, hyper_posterior="map",
                        li_basis=False)
    set_hypers(m, seed=3)
    return m


@pytest.fixture
def model():
    return fitted()


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_information_gain_and_integrated_variance_match_dense(method):
    model = fitted(method)
    tol = TOL[method]
    ls, os, noise = hypers(model)
    scorer = ProbeScorer.from_model(model, tol=None)
    assert scorer.method == method
    cand = random_contacts(T=8, M=4, seed=22)  # more segments than the training rows: no padding needed
    want = eig_dense(dense_cov(ls, os, noise, model.train_contacts, [cand]), noise)
    assert scorer.information_gain(cand).item() == pytest.approx(want.item(), rel=tol)
    for region in (Region.square(5), Region.sign_change(6)):
        covs = dense_cov(ls, os, noise, model.train_contacts, [region.contacts(), cand])
        now, after = iv_dense(covs, noise, os, region, len(cand))
        assert scorer.integrated_variance(region=region).item() == pytest.approx(now.item(), rel=tol)
        assert scorer.integrated_variance(cand, region).item() == pytest.approx(after.item(), rel=tol)
        assert after < now
        # per map: the x map is seen only through F_x, so its share uses only the x block
        n = region.beta.numel()
        Sx = covs[0]
        kx = Sx[:n, n:]
        post_x = torch.diagonal(Sx[:n, :n]) - torch.diagonal(
            kx @ torch.linalg.solve(Sx[n:, n:] + noise[0] * torch.eye(len(cand)), kx.T))
        after_x = (region.weight * post_x).sum() / os[0]
        per = scorer.integrated_variance(cand, region, per_axis=True)
        assert per.shape == (2,) and per[0].item() == pytest.approx(after_x.item(), rel=tol)
        assert per.sum().item() == pytest.approx(after.item(), rel=tol)
    cov_x = dense_cov(ls, os, noise, model.train_contacts, [cand])[0]
    eig_x = 0.5 * torch.logdet(torch.eye(len(cand)) + cov_x / noise[0])
    assert scorer.information_gain(cand, per_axis=True)[0].item() == pytest.approx(eig_x.item(), rel=tol)
    want = torch.stack(dense_cov(ls, os, noise, model.train_contacts, [cand]))
    torch.testing.assert_close(scorer.covariance(cand), want, rtol=tol, atol=tol * want.abs().max().item())


@pytest.mark.parametrize("method", ["observations", "pairs", "spectral"])
def test_batched_scores_of_unequal_candidates_match_dense(method, monkeypatch):
    """``score`` stacks candidates of different lengths and segment counts into zero-padded blocks,
    a few rows at a time: each score is still that candidate's own (dense, one at a time)."""
    import irft_torch.design.scoring as scoring

    monkeypatch.setattr(scoring, "SCORE_ROWS", 12)  # several batches, some with one candidate
    model = fitted(method)
    tol = TOL[method]
    ls, os, noise = hypers(model)
    cands = [random_contacts(T=T, M=M, seed=30 + i) for i, (T, M) in enumerate([(8, 4), (3, 2), (8, 4), (11, 5),
                                                                                  (5, 3)])]
    region = Region.square(5)
    scorer = ProbeScorer.from_model(model, tol=None)
    eig = scorer.score(cands, "eig")
    iv = scorer.score(cands, "variance", region=region)
    assert eig.shape == iv.shape == (len(cands),)
    for i, cand in enumerate(cands):
        want = eig_dense(dense_cov(ls, os, noise, model.train_contacts, [cand]), noise)
        assert eig[i].item() == pytest.approx(want.item(), rel=tol)
        covs = dense_cov(ls, os, noise, model.train_contacts, [region.contacts(), cand])
        _, after = iv_dense(covs, noise, os, region, len(cand))
        assert iv[i].item() == pytest.approx(after.item(), rel=tol)


@pytest.mark.parametrize("method", ["observations", "spectral"])
def test_batches_pad_little_and_empty_candidates_teach_nothing(method, monkeypatch):
    """One long candidate among many short ones is not padded into their batch (memory B T_max^2), the
    scores come back in the candidates' order, and a candidate with no row at all scores EIG 0 and
    leaves the variance as it is."""
    import irft_torch.design.scoring as scoring

    model = fitted(method)
    scorer = ProbeScorer.from_model(model, tol=None)
    seen = []
    real = scoring.ProbeScorer._score_batch

    def spy(self, cands, criterion, region):
        seen.append((len(cands), max(len(c) for c in cands)))
        return real(self, cands, criterion, region)

    monkeypatch.setattr(scoring.ProbeScorer, "_score_batch", spy)
    short = [random_contacts(T=2, M=2, seed=50 + i) for i in range(30)]
    cands = short[:15] + [random_contacts(T=600, M=2, seed=49)] + short[15:]
    got = scorer.score(cands, "eig")
    assert all(b * t**2 <= scoring.SCORE_ROWS**2 // 10 or b == 1 for b, t in seen), seen
    one_by_one = torch.stack([scorer.information_gain(c) for c in cands])
    torch.testing.assert_close(got, one_by_one, rtol=1e-9, atol=1e-12)
    empty = random_contacts(T=3, M=2, seed=7)[:0]
    eig, iv = scorer.score([empty, short[0]], "eig"), scorer.score([empty, short[0]], "variance")
    assert eig[0].item() == 0.0 and iv[0].item() == pytest.approx(scorer.integrated_variance().item(), rel=1e-12)
    assert eig[1].item() > 0


def test_long_candidates_are_scored_in_the_spectral_root_space_exactly():
    """Candidates with more samples than the spectral basis has features are scored in F dimensions
    (Woodbury on the posterior root): the same numbers as the dense T x T computation."""
    model = fitted("spectral")
    with torch.no_grad():
        model.hypers.lengthscale = torch.full((2, 1, 4), 2.5)
    model.backend.refresh()
    ls, os, noise = hypers(model)
    scorer = ProbeScorer.from_model(model, tol=None)
    F = scorer.backend.posterior_root(random_contacts(T=2, M=2)).shape[-1]
    cands = [random_contacts(T=T, M=3, seed=40 + T) for T in (F + 20, F + 7)]
    assert all(len(c) > F for c in cands)  # the root path
    region = Region.sign_change(6)
    eig = scorer.score(cands, "eig")
    iv = scorer.score(cands, "variance", region=region)
    for i, cand in enumerate(cands):
        want = eig_dense(dense_cov(ls, os, noise, model.train_contacts, [cand]), noise)
        assert eig[i].item() == pytest.approx(want.item(), rel=1e-6)
        covs = dense_cov(ls, os, noise, model.train_contacts, [region.contacts(), cand])
        _, after = iv_dense(covs, noise, os, region, len(cand))
        assert iv[i].item() == pytest.approx(after.item(), rel=1e-6)
        assert iv[i].item() == pytest.approx(scorer.integrated_variance(cand, region).item(), rel=1e-6)


@pytest.mark.parametrize("method", ["observations", "spectral"])
def test_a_scorer_follows_its_model_after_add_data_and_a_refit(method):
    """A scorer shares its model's backend: after ``model.add_data`` (or a refit moving the shared
    hyperparameters) its cached region values must not describe the old belief."""
    model = fitted(method)
    if method == "spectral":
        with torch.no_grad():
            model.hypers.lengthscale = torch.full((2, 1, 4), 2.5)
        model.backend.refresh()
    scorer, region = ProbeScorer.from_model(model), Region.sign_change(6)
    long, short = random_contacts(T=140, M=3, seed=1), random_contacts(T=5, M=2, seed=2)
    scorer.score([long, short], "variance", region)  # fills the caches
    new = random_contacts(T=40, M=3, seed=9)
    model.add_data(new, irft.rft.forces(FourierStressMap.generic(), new))
    want = ProbeScorer.from_model(model).score([long, short], "variance", region)
    torch.testing.assert_close(scorer.score([long, short], "variance", region), want, rtol=1e-9, atol=0)
    with torch.no_grad():
        model.hypers.outputscale = model.hypers.outputscale * 1.7
    want = ProbeScorer.from_model(model).score([long, short], "variance", region)
    torch.testing.assert_close(scorer.score([long, short], "variance", region), want, rtol=1e-9, atol=0)


def test_a_scorer_forgets_its_region_values_when_the_model_rebuilds_at_a_moved_surface():
    """``init_surface`` rebuilds the model's backend at the new offset with the same sample count and
    hyperparameters: the scorer follows the new backend, and its region values (the current variance
    the expected variance is computed from) must be the new belief's, as in a dense computation on the
    model's training contacts at the moved surface (the bug: the cached values of the old surface stayed)."""
    toes = {"I": irft.rft.IToe(0.02, 0.008), "C": irft.rft.CToe(0.02, 0.008, opening="left")}
    probes = irft.rft.random_probes(toes, 2, 0.2, n_steps=15, seed=3)
    train = Contacts.cat([p.contacts() for p in probes[:2]])
    m = irft.InverseRFT(train, irft.rft.forces(FourierStressMap.generic(), train), method="observations",
                        surface_offset=True, hyper_posterior="map", li_basis=False)
    scorer, region, cand = ProbeScorer.from_model(m), Region.sign_change(6), probes[2].contacts()
    scorer.score([cand], "variance", region)  # fills the region cache at the stated surface
    m.init_surface([0.01])
    ls, os, noise = hypers(m)
    now, after = iv_dense(dense_cov(ls, os, noise, m.train_contacts, [region.contacts(), cand]), noise, os, region,
                          len(cand))
    assert scorer.integrated_variance(region=region).item() == pytest.approx(now.item(), rel=1e-8)
    assert scorer.score([cand], "variance", region).item() == pytest.approx(after.item(), rel=1e-8)


def test_candidates_noise_scale_is_heteroscedastic_noise_exactly():
    """A candidate sample t with noise scale s_t has noise variance sigma^2 s_t^2: the scores equal a
    dense computation with S + sigma^2 diag(s^2) (the bug: candidates were scored with unit noise)."""
    model = fitted()
    ls, os, noise = hypers(model)
    cand = random_contacts(T=6, M=3, seed=24)
    s = 0.3 + 2 * torch.rand(6, 2, generator=torch.Generator().manual_seed(1))
    scorer = ProbeScorer.from_model(model, tol=None, noise_scale=lambda c: s)
    region = Region.square(5)
    covs = dense_cov(ls, os, noise, model.train_contacts, [region.contacts(), cand])
    n = region.beta.numel()
    eig = after = 0.0
    for a, S in enumerate(covs):
        N = noise[a] * torch.diag(s[:, a] ** 2)
        Sc = S[n:, n:]
        eig = eig + 0.5 * torch.logdet(torch.eye(6) + torch.linalg.solve(N, Sc))
        k = S[:n, n:]
        post = torch.diagonal(S[:n, :n]) - torch.diagonal(k @ torch.linalg.solve(Sc + N, k.T))
        after = after + (region.weight * post).sum() / os[a]
    assert scorer.information_gain(cand).item() == pytest.approx(eig.item(), rel=1e-8)
    assert scorer.integrated_variance(cand, region).item() == pytest.approx(after.item(), rel=1e-8)
    plain = ProbeScorer.from_model(model, tol=None).information_gain(cand).item()
    assert abs(plain - eig.item()) > 1e-3  # the scale matters
    with pytest.warns(UserWarning, match="noise_scale"):
        heavy = irft.InverseRFT(model.train_contacts, irft.rft.forces(FourierStressMap.generic(), model.train_contacts),
                                noise_scale=torch.full((20,), 2.0), hyper_posterior="map", li_basis=False)
        ProbeScorer.from_model(heavy)


def test_prior_scorer_matches_dense():
    ls = 0.3 + torch.rand(2, 1, 4, generator=torch.Generator().manual_seed(5))
    os, noise = torch.tensor([0.05, 0.2]), torch.tensor([0.03, 0.07])
    scorer = ProbeScorer.prior(ls, os, noise)
    cand = random_contacts(T=7, M=3, seed=30)
    region = Region.square(4)
    assert scorer.information_gain(cand).item() == pytest.approx(eig_dense(dense_cov(ls, os, noise, None, [cand]),
                                                                           noise).item(), rel=1e-8)
    now, after = iv_dense(dense_cov(ls, os, noise, None, [region.contacts(), cand]), noise, os, region, len(cand))
    assert now.item() == pytest.approx(2.0, rel=1e-12)  # the prior: each axis' variance is its prior variance
    assert scorer.integrated_variance(cand, region).item() == pytest.approx(after.item(), rel=1e-8)


def test_conditioning_equals_refitting_with_the_probe_and_leaves_the_model_alone(model):
    ls, os, noise = hypers(model)
    scorer = ProbeScorer.from_model(model, method="exact")
    c1, c2 = random_contacts(T=6, M=3, seed=40), random_contacts(T=5, M=5, seed=41)
    after = scorer.condition(c1)
    both = Contacts.cat([model.train_contacts, c1])
    want = eig_dense(dense_cov(ls, os, noise, both, [c2]), noise)
    assert after.information_gain(c2).item() == pytest.approx(want.item(), rel=1e-8)
    assert len(model.train_contacts) == 20 and scorer.backend.n_samples == 20
    # from the prior too: conditioning the prior on data is the posterior given that data
    prior = ProbeScorer.prior(ls, os, noise).condition(model.train_contacts)
    assert prior.information_gain(c2).item() == pytest.approx(scorer.information_gain(c2).item(), rel=1e-8)


def test_greedy_information_adds_up_to_the_joint_information(model):
    """Chain rule: the EIG scores of a greedy sequence sum to the EIG of observing all of it."""
    ls, os, noise = hypers(model)
    cands = [random_contacts(T=5, M=3, seed=50 + i) for i in range(5)]
    steps = greedy_design(ProbeScorer.from_model(model, method="exact"), cands, budget=3, criterion="eig")
    chosen = [cands[s.index] for s in steps]
    joint = eig_dense(dense_cov(ls, os, noise, model.train_contacts, chosen), noise)
    assert sum(s.score for s in steps) == pytest.approx(joint.item(), rel=1e-8)
    assert len({s.index for s in steps}) == 3
    # the first pick is the single most informative candidate (checked against dense)
    single = [eig_dense(dense_cov(ls, os, noise, model.train_contacts, [c]), noise).item() for c in cands]
    assert steps[0].index == max(range(5), key=single.__getitem__)
    ivs = [s.integrated_variance for s in steps]
    assert ivs[0] > ivs[1] > ivs[2]


def test_spectral_and_exact_scores_agree_on_probes():
    toes = {"I": irft.rft.IToe(0.02, 0.008), "C": irft.rft.CToe(0.02, 0.008, opening="left")}
    probes = irft.rft.random_probes(toes, 6, 0.3, n_steps=60, seed=3)
    train = Contacts.cat([p.contacts() for p in probes[:2]])
    m = irft.InverseRFT(train, irft.rft.forces(FourierStressMap.generic(0.45, 0.42), train), method="observations",
                        hyper_posterior="map", li_basis=False)
    ex = ProbeScorer.from_model(m, method="observations").score(probes[2:])
    sp = ProbeScorer.from_model(m, method="spectral", tol=None).score(probes[2:])  # the model's 1e-7
    # IV is a difference (prior minus what the data explain): 1e-6 of its scale, 2 (the prior's IV)
    torch.testing.assert_close(sp, ex, rtol=1e-6, atol=2e-6)
    eig_ex = ProbeScorer.from_model(m, method="observations").score(probes[2:5], "eig")
    eig_sp = ProbeScorer.from_model(m, method="spectral", tol=None).score(probes[2:5], "eig")
    # EIG sums log(1 + lambda / sigma^2) over many eigenvalues: kernel errors of 1e-7 reach ~3e-6 here
    torch.testing.assert_close(eig_sp, eig_ex, rtol=1e-5, atol=0)


@pytest.mark.parametrize("method", ["exact", "spectral"])
def test_scores_are_differentiable_in_the_path(method):
    """d IV / d course knot against central finite differences, through path -> contacts -> score."""
    scorer = ProbeScorer.prior(0.8, (0.05, 0.1), (0.02, 0.05), method=method)
    toe = irft.rft.CToe(0.02, 0.008, n_segments=6, opening="left")
    base = torch.tensor([-1.2, -0.2, 0.1, 0.3])

    def iv(course):
        path = irft.rft.course_path(course, 0.2, start=(0.0, 0.0), heading=0.3, n_steps=40)
        return scorer.integrated_variance(irft.rft.contacts(toe, path), Region.square(6))

    course = base.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(iv(course), course)
    h = 1e-6
    for k in range(4):
        e = torch.zeros(4)
        e[k] = h
        fd = (iv(base + e) - iv(base - e)) / (2 * h)
        assert grad[k].item() == pytest.approx(fd.item(), rel=1e-4, abs=1e-8)


def test_no_contact_teaches_nothing_and_bad_input_is_named(model):
    scorer = ProbeScorer.from_model(model, method="exact")
    cand = random_contacts(T=5, M=3, seed=80)
    air = Contacts(cand.beta, cand.gamma, torch.zeros_like(cand.weight_x), torch.zeros_like(cand.weight_z))
    assert scorer.information_gain(air).item() == pytest.approx(0.0, abs=1e-12)
    assert scorer.integrated_variance(air).item() == pytest.approx(scorer.integrated_variance().item(), rel=1e-12)
    weak = Contacts(cand.beta, cand.gamma, cand.weight_x * 0.01, cand.weight_z * 0.01)
    assert scorer.rank([weak, cand], "eig")[0][0] == 1
    assert scorer.rank([weak, cand], "variance")[0][0] == 1
    with pytest.raises(ValueError, match="criterion"):
        scorer.score([cand], "entropy")
    with pytest.raises(TypeError, match="Contacts or have a contacts"):
        scorer.score(["not a probe"])
    with pytest.raises(ValueError, match="method"):
        ProbeScorer.from_model(model, method="fast")
    with pytest.raises(ValueError, match="noise must be positive"):
        ProbeScorer.prior(noise=-1.0)
    with pytest.raises(ValueError, match="weight must be >= 0"):
        Region(torch.zeros(3), torch.zeros(3), torch.tensor([1.0, -1.0, 0.5]))
    with pytest.raises(ValueError, match="one shape"):
        Region(torch.zeros(3), torch.zeros(2), torch.ones(3))
    with pytest.raises(ValueError, match="budget"):
        greedy_design(scorer, [cand], budget=-1)
    assert math.isfinite(scorer.information_gain(cand).item())


def test_a_spectral_model_is_scored_in_a_coarser_basis_by_default_and_ranked_the_same():
    """``from_model``'s default ``tol="auto"`` scores a spectral model in the basis that 1e-4 of the
    kernel variance needs, cut from the model's statistics: fewer features, scores within a few
    percent of the model's own (exact to 1e-6) basis, the same choice and order (up to near ties); it
    follows ``add_data``."""
    from irft_torch.design.scoring import SCORING_TOL

    toes = {"I": irft.rft.IToe(0.02, 0.008), "C": irft.rft.CToe(0.02, 0.008, opening="left")}
    probes = irft.rft.random_probes(toes, 8, 0.3, n_steps=60, seed=5)
    train = Contacts.cat([p.contacts() for p in probes[:3]])
    smap = FourierStressMap.generic(0.45, 0.42)
    m = irft.InverseRFT(train, irft.rft.forces(smap, train), method="spectral", hyper_posterior="map", li_basis=False)
    coarse, fine = ProbeScorer.from_model(m), ProbeScorer.from_model(m, tol=None)
    assert fine.backend is m.backend
    assert coarse.backend.basis.size < m.backend.basis.size
    assert float(coarse.backend.truncation_error().max()) <= SCORING_TOL
    cands = probes[3:]
    for criterion, rel in (("variance", 0.02), ("eig", 0.05)):
        c, f = coarse.score(cands, criterion), fine.score(cands, criterion)
        torch.testing.assert_close(c, f, rtol=rel, atol=0)
        assert int(c.argmax()) == int(f.argmax())  # the choice
        # the order, up to near ties (scores within 1 % of each other may swap)
        i, j = torch.triu_indices(len(c), len(c), 1)
        apart = (f[i] - f[j]).abs() > 0.01 * f[i].abs()
        assert torch.equal(torch.sign(c[i] - c[j])[apart], torch.sign(f[i] - f[j])[apart])
    # the coarse statistics are the model's cut, not a second pass: equal to a pass in that basis
    direct = irft.gp.backends.SpectralBackend(m.hypers, m.train_contacts, m.train_forces,
                                               basis=coarse.backend.basis)
    torch.testing.assert_close(coarse.backend.stats.P, direct.stats.P, rtol=1e-12, atol=1e-12)
    new = probes[1].contacts()
    m.add_data(new, irft.rft.forces(smap, new))
    assert coarse.backend.n_samples == m.backend.n_samples
    torch.testing.assert_close(coarse.score(cands), ProbeScorer.from_model(m).score(cands), rtol=1e-10, atol=0)
    with pytest.raises(ValueError, match="tol"):
        ProbeScorer.from_model(m, tol="coarse")


def test_a_scorer_follows_its_model_across_backend_switches_whatever_its_recipe(monkeypatch):
    """Every scorer from ``from_model`` (default, the model's own basis, a coarser or finer tolerance,
    another backend) scores the model's current data after a refit moves the model spectral ->
    observations -> spectral and after ``add_data``: the same scores as a scorer made afresh."""
    import irft_torch.gp.fit_control as gp_model  # where auto asks for the costs

    toes = {"I": irft.rft.IToe(0.02, 0.008), "C": irft.rft.CToe(0.02, 0.008, opening="left")}
    probes = irft.rft.random_probes(toes, 6, 0.3, n_steps=40, seed=7)
    train = Contacts.cat([p.contacts() for p in probes[:3]])
    smap = FourierStressMap.generic(0.45, 0.42)
    m = irft.InverseRFT(train, irft.rft.forces(smap, train), method="spectral", hyper_posterior="map", li_basis=False)
    m.auto = True  # let the fit move between backends, with costs we choose
    recipes = [{}, {"tol": None}, {"tol": 1e-3}, {"tol": 1e-9}, {"method": "pairs"}, {"method": "observations"}]
    scorers = [ProbeScorer.from_model(m, **r) for r in recipes]
    for cheapest in ("observations", "spectral"):
        monkeypatch.setattr(gp_model, "estimated_costs", lambda *a, c=cheapest, **k: {
            "observations": 1.0 if c == "observations" else 10.0, "pairs": 10.0,
            "spectral": 1.0 if c == "spectral" else 10.0})
        m.fit(n_iter=30, lr=0.01, progress=False)
        assert m.backend.name == cheapest
    new = probes[3].contacts()
    m.add_data(new, irft.rft.forces(smap, new))
    cands = probes[4:]
    for r, sc in zip(recipes, scorers):
        assert sc.backend.n_samples == m.backend.n_samples, r
        torch.testing.assert_close(sc.score(cands), ProbeScorer.from_model(m, **r).score(cands), rtol=1e-9, atol=0)
    assert scorers[1].backend is m.backend and scorers[0].backend.basis.size < m.backend.basis.size


def test_force_relative_scorers_pickle_regions_keep_their_dtype_and_retired_arguments_warn():
    import pickle

    model = fitted("observations")
    scorer = ProbeScorer.from_model(model, noise_scale=force_relative(model, floor=0.1))
    cand = random_contacts(T=8, M=4, seed=22)
    back = pickle.loads(pickle.dumps(scorer))
    assert back.information_gain(cand).item() == pytest.approx(scorer.information_gain(cand).item(), rel=1e-12)
    with pytest.raises(ValueError, match="floor"):
        force_relative(model, floor=0.0)
    assert Region.square(4, dtype=torch.float32).beta.dtype == torch.float32
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        assert Region.square(4, dtype=torch.float64).weight.dtype == torch.float64
    finally:
        torch.set_default_dtype(old)
    with pytest.warns(FutureWarning, match="grid_size"):
        ProbeScorer.prior(grid_size=8)


def test_a_region_with_eig_and_a_budget_beyond_the_candidates_are_said():
    """'eig' has no region (it was ignored silently): a ValueError naming region, in score, rank, greedy_design and
    optimize_probe; a budget larger than the candidates picks them all and warns."""
    from irft_torch.design.optimize import optimize_probe
    from irft_torch.rft import IToe, contacts, rectangle_path

    scorer = ProbeScorer.prior()
    toe = IToe(0.02, 0.008, n_segments=4)
    cands = [contacts(toe, rectangle_path(0.02, 0.05, 0.02, n_steps=8))]
    region = Region.square(6)
    for call in (lambda: scorer.score(cands, "eig", region), lambda: scorer.rank(cands, "eig", region),
                 lambda: greedy_design(scorer, cands, 1, "eig", region),
                 lambda: optimize_probe(scorer, toe, length=0.1, n_iter=1, criterion="eig", region=region)):
        with pytest.raises(ValueError, match="region applies to criterion 'variance'"):
            call()
    with pytest.warns(UserWarning, match="budget 3 is more than the 1 candidate"):
        steps = greedy_design(scorer, cands, 3)
    assert len(steps) == 1


def test_a_derived_scorer_tells_a_new_backend_from_a_freed_one():
    """The belief a derived scorer uses is tied to its model's backend object by a weak reference, not
    its id: when the model's backend is replaced, the scorer derives again (an id can be reused by a
    new object once the old one is freed); a pickled copy keeps following its own model."""
    import gc
    import pickle

    toes = {"I": irft.rft.IToe(0.02, 0.008), "C": irft.rft.CToe(0.02, 0.008, opening="left")}
    probes = irft.rft.random_probes(toes, 3, 0.2, n_steps=15, seed=3)
    train, cand = Contacts.cat([p.contacts() for p in probes[:2]]), probes[2].contacts()
    m = irft.InverseRFT(train, irft.rft.forces(FourierStressMap.generic(), train), method="observations",
                        hyper_posterior="map", li_basis=False)
    s = ProbeScorer.from_model(m, method="pairs")
    first = s.backend
    assert s.backend is first  # unchanged model: the same derived belief
    state = s._derived_from
    m.backend = type(m.backend)(m.hypers, m.train_contacts, m.train_forces)  # rebuilt; the old one freed
    gc.collect()
    assert state[0]() is None  # the old backend is gone: its id may be reused, the weak reference says so
    assert s.backend is not first
    copy = pickle.loads(pickle.dumps(s))
    assert copy._same_state(copy._recipe[0].backend, copy._derived_from)  # follows its own model, no rebuild
    torch.testing.assert_close(copy.score([cand]), s.score([cand]))
