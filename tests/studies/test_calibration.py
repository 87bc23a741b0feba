"""The calibration harness (studies.calibration): its media against published coefficients, its motions,
its percentile statistic on truths the model is calibrated for by construction, and one fast case."""

import math

import pytest
import torch

import irft_torch as irft
from irft_torch.studies import calibration as cal

F64 = torch.float64


def test_fourier_medium_of_li_equals_the_published_generic_map_and_mirrors():
    g = torch.Generator().manual_seed(0)
    b = (torch.rand(200, generator=g, dtype=F64) - 0.5) * 2 * math.pi
    gm = (torch.rand(200, generator=g, dtype=F64) - 0.5) * 2 * math.pi
    ours = cal.FourierMedium.from_li(irft.rft.stress_maps.GENERIC, 0.7, 1.3)(b, gm)
    ref = irft.rft.FourierStressMap.generic(0.7, 1.3).double()(b, gm)
    torch.testing.assert_close(ours, ref, rtol=1e-12, atol=1e-12)
    # hand value: a horizontal plate pushed straight down, alpha_z(0, pi/2) = scale_z (Li et al.)
    assert float(cal.FourierMedium.from_li(irft.rft.stress_maps.GENERIC, 1.0, 1.3)(0.0, math.pi / 2)[1]) == \
        pytest.approx(1.3, rel=1e-12)


@pytest.mark.parametrize("family", cal.MEDIA + cal.HELD_OUT_MEDIA + cal.HELD_OUT_MEDIA_2)
def test_every_medium_is_finite_reproducible_and_mirror_consistent(family):
    truth, label = cal.medium(family, 3)
    again, _ = cal.medium(family, 3)
    B, G = cal.grid(11)
    a = truth(B, G)
    assert a.shape == (11, 11, 2) and torch.isfinite(a).all() and isinstance(label, str)
    torch.testing.assert_close(a, again(B, G))
    # motion toward -x is the mirror image: alpha_x(b, g) = -alpha_x(-b, pi - g), alpha_z equal (inside the
    # square: on its edge gamma = +-pi/2, straight down or up, a map outside Li's form need not be symmetric)
    B, G, a = B[:, 1:-1], G[:, 1:-1], a[:, 1:-1]
    m = truth(-B, math.pi - G)
    torch.testing.assert_close(m[..., 0], -a[..., 0], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(m[..., 1], a[..., 1], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kind", cal.MOTIONS + cal.HELD_OUT_MOTIONS + cal.HELD_OUT_MOTIONS_2)
def test_every_motion_touches_the_medium(kind):
    c = cal.motion(kind, 0)
    T = {"short": 40, "long": 400}.get(kind)
    if T is not None:
        assert len(c) == T
    assert ((c.weight_z != 0).any(-1)).double().mean() > 0.3
    f = cal.simulate(cal.medium("presets", 2)[0], c, 0.02, 0)
    assert torch.isfinite(f).all() and (f[:, 1].abs().max() > 0)


def test_simulated_noise_is_the_stated_share_of_each_axis_range():
    c = cal.motion("turning", 1)
    truth = cal.medium("scaled", 1)[0]
    clean = irft.rft.forces(truth, c)
    noisy = cal.simulate(truth, c, 0.05, 7)
    rng = clean.amax(0) - clean.amin(0)
    std = (noisy - clean).std(0)
    torch.testing.assert_close(std / rng, torch.full((2,), 0.05, dtype=F64), rtol=0.2, atol=0)


def test_the_percentile_statistic_is_uniform_on_truths_drawn_from_the_model_itself():
    """Simulation-based calibration of the statistic: a map drawn from the fit's own posterior is a truth the
    model is calibrated for, so its 95 % coverage's percentile among the model's draws is uniform."""
    c = cal.motion("short", 0)
    f = cal.simulate(cal.medium("presets", 2)[0], c, 0.05, 0)
    model = irft.InverseRFT(c, f, hyper_posterior="map")
    model.fit(n_iter=60, progress=False)
    B, G = cal.grid(15)
    truths = model.sample_maps(B, G, 60, generator=torch.Generator().manual_seed(123))
    pct = []
    for k in range(60):
        table = truths[k]

        def truth(beta, gamma, table=table):
            assert beta.shape == table.shape[:-1]
            return table

        pct.append(cal.score(model, truth, n_grid=15, draws=100, seed=k)["pct95_z"])
    pct = torch.tensor(pct)
    assert 0.35 < float(pct.mean()) < 0.65  # uniform: mean 1/2, sd of the mean 0.037
    assert float((pct < 0.025).double().mean()) <= 0.1


def test_one_case_scores_the_plug_in_the_laplace_mixture_and_the_average_from_one_fit():
    rows = cal.run_case(cal.Case("gp", "short", 0.05, 0), ("map", "laplace", "average"), n_iter=80, n_grid=15,
                        draws=60)
    assert [r["posterior"] for r in rows] == ["map", "laplace", "average"]
    assert rows[0]["fit_s"] == rows[1]["fit_s"] == rows[2]["fit_s"]  # one fit of the zero mean, three predictions
    assert 0 <= rows[2]["w_physics_x"] <= 1 and 0 <= rows[2]["w_physics_z"] <= 1
    for r in rows:
        for k in ("cover50_x", "cover90_z", "cover95_x", "pct95_z"):
            assert 0.0 <= r[k] <= 1.0
        assert r["cover50_x"] <= r["cover90_x"] <= r["cover95_x"]
    assert rows[1]["n_draws"] >= 2 and rows[1]["ess"] > 1
