"""The DEM plate-intrusion reader and its angle mapping (skipped where the shared data are absent)."""

import math
import pathlib
import re

import numpy as np
import pytest
import torch

from irft_torch.data import dem as D
from irft_torch.rft import FourierStressMap

DATA = pathlib.Path(__file__).resolve().parents[3] / "shared" / "data" / "dem_plate_intrusion"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"DEM data not found at {DATA} (not shipped: no licence)")


def write(path, text):
    path.write_text(text)
    return path


def test_reader_quirks_on_a_hand_made_file(tmp_path):
    write(tmp_path / "beta_30_plate_forces.csv",
          "90,30,,\n0,0,0,0\n0.001,1.5e-01,0,2E+00\n0.002,0.2,0,2.5,\n0.003,0.3,0\n"  # truncated last row
          "81,30\n0,0,0,0\n0.001,0.1,0,1\nbad,row,x,y\n")
    write(tmp_path / "beta_30_plate_positions.csv",
          "90,30,,,\n0,0,0,15,9\n0.001,0,0,14.9,9\n0.002,0,0,14.8,9\n0.003,0,0,14.7,9\n"
          "81,30,,,\n0,0,0,15,9\n0.001,0,0,14.9,9\n")
    runs, rep = D.read_runs(tmp_path)
    assert [(r.gamma_deg, len(r.t)) for r in runs] == [(81.0, 2), (90.0, 3)]
    r90 = runs[1]
    np.testing.assert_allclose(r90.force[1], [0.15, 0.0, 2.0])  # scientific notation, trailing comma
    reasons = {x[2] for x in rep.skipped_rows}
    assert "3 values, expected 4" in reasons and "not numbers" in reasons
    assert ("beta 30, gamma 90", 0, 1) in rep.unmatched  # t = 3 ms: its force row was truncated
    assert "unparseable" in rep.summary()
    with pytest.raises(FileNotFoundError, match="no DEM data directory"):
        D.read_runs(tmp_path / "nope")


def test_a_data_row_cut_to_two_values_is_damage_not_a_new_run(tmp_path):
    # two numbers are a header only with the file's beta: "0.002,0.2" (a force row cut after x) must not open a
    # run "gamma 0.002" and take the rows after it from run (90, 30)
    write(tmp_path / "beta_30_plate_forces.csv", "90,30\n0,0,0,0\n0.001,0.1,0,1\n0.002,0.2\n0.003,0.3,0,3\n")
    write(tmp_path / "beta_30_plate_positions.csv",
          "90,30\n0,0,0,15,9\n0.001,0,0,14.9,9\n0.002,0,0,14.8,9\n0.003,0,0,14.7,9\n")
    runs, rep = D.read_runs(tmp_path)
    assert [(r.gamma_deg, r.beta_deg, len(r.t)) for r in runs] == [(90.0, 30.0, 3)]  # t = 0, 1, 3 ms
    assert any(x[1] == 4 and x[2].startswith("2 values, expected 4") for x in rep.skipped_rows), rep.skipped_rows


def test_contacts_of_a_tilted_plate_by_hand():
    run = D.DEMRun(30.0, 90.0, np.array([0.0, 0.1]), np.array([[1.0, 0, 2.0], [1.0, 0, 2.0]]),
                   np.array([[0, 0, 5.0], [0, 0, 4.0]]), np.array([9.0, 9.0]))
    c, f = D.run_contacts(run, n_segments=2)
    # segment centres at s = -/+ 3.81/4 along a plate tilted by -30 deg (DESIGN): z = zc -/+ s sin(-30)
    s = 3.81 / 4
    depth0 = np.array([9 - (5 + s * 0.5), 9 - (5 - s * 0.5)])
    area = 3.81 / 2 * 2.54
    torch.testing.assert_close(c.weight_z[0], torch.tensor(depth0 * area))
    assert c.beta[0, 0].item() == pytest.approx(math.radians(30)) and c.gamma[0, 0].item() == pytest.approx(math.pi / 2)
    assert (c.weight_x == c.weight_z).all()  # motion toward -x: the x contribution flips sign
    torch.testing.assert_close(f[0], torch.tensor([1.0, 2.0], dtype=torch.float64))


@needs_data
def test_real_data_mapping_correlates_with_the_generic_map():
    runs, rep = D.read_runs(DATA)
    runs = [r for r in runs if r.gamma_deg >= 45]
    assert len(runs) == 48
    gen = FourierStressMap.generic()
    meas = np.array([D.run_stress(r) for r in runs])
    pred = np.array([gen(*map(torch.tensor, D.canonical_angles(r))).tolist() for r in runs])
    corr = [np.corrcoef(meas[:, k], pred[:, k])[0, 1] for k in range(2)]
    assert corr[0] > 0.94 and corr[1] > 0.93, corr  # README: about 0.95 for both axes
    # the other tilt sign would be wrong: x correlation collapses
    D.TILT_SIGN, old = 1.0, D.TILT_SIGN
    try:
        wrong = np.array([gen(*map(torch.tensor, D.canonical_angles(r))).tolist() for r in runs])
    finally:
        D.TILT_SIGN = old
    assert np.corrcoef(meas[:, 0], wrong[:, 0])[0, 1] < 0.5


def _ramp_run(beta_deg, gamma_deg, alpha, offset, noise=0.0, n=3000, seed=0):
    """A synthetic run: the centre goes from 3 cm above z_top to 9 cm below it; forces from RFT's law
    written out by hand for the plate cut into 10 equal segments, depth below z_top - offset."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 1e-3
    z_top = np.full(n, 9.0)
    zc = 12.0 - 12.0 * t / t[-1]
    tilt = -math.radians(beta_deg)
    offsets = [-3.81 / 2 + (k + 0.5) * 3.81 / 10 for k in range(10)]  # segment centres along the plate
    area = 3.81 / 10 * 2.54
    w = sum(np.clip(z_top - offset - (zc + s * math.sin(tilt)), 0, None) * area for s in offsets)
    sign = 1.0 if -math.cos(math.radians(gamma_deg)) < 0 else -1.0
    force = np.stack([sign * alpha[0] * w, np.zeros(n), alpha[1] * w], 1) + noise * rng.standard_normal((n, 3))
    centre = np.stack([np.zeros(n), np.zeros(n), zc], 1)
    return D.DEMRun(beta_deg, gamma_deg, t, force, centre, z_top)


def test_rft_stress_keeps_the_x_sign_when_the_first_segment_is_above_the_surface():
    # a plate tilted 45 deg: its upper half is still in the air when the centre is 1 cm deep, so the
    # first kept sample has weight_x[0, 0] = 0 (the sign once read from it, which zeroed alpha_x)
    run = _ramp_run(45.0, 63.0, (0.11, 0.15), offset=0.0)
    c, _ = D.run_contacts(run, min_depth=0.5)
    assert c.weight_x[0, 0] == 0 and c.weight_x[0, -1] > 0
    ax, az = D.run_stress_rft(run, min_depth=0.5)
    assert ax == pytest.approx(0.11, rel=1e-9) and az == pytest.approx(0.15, rel=1e-9)
    # motion toward +x (gamma > 90 deg in the DEM's convention): the canonical sign flips back
    run = _ramp_run(45.0, 120.0, (0.07, 0.2), offset=0.0)
    ax, az = D.run_stress_rft(run, min_depth=0.5)
    assert ax == pytest.approx(0.07, rel=1e-9) and az == pytest.approx(0.2, rel=1e-9)


def test_surface_offset_is_recovered_and_makes_slope_and_rft_stress_agree():
    runs = [_ramp_run(b, g, (0.05 + 0.001 * b, 0.2), offset=1.3, noise=0.05, seed=i)
            for i, (b, g) in enumerate([(0, 90), (30, 63), (-45, 72), (60, 81)])]
    best, curve = D.calibrate_surface_offset(runs)
    assert best == pytest.approx(1.3, abs=1e-9)
    assert curve.shape == (31, 2) and curve[:, 1].argmin() == 13
    for r in runs:
        slope = np.array(D.run_stress(r, min_depth=3.0))  # fully submerged: the slope is alpha exactly
        naive = np.array(D.run_stress_rft(r, min_depth=3.0))
        fixed = np.array(D.run_stress_rft(r, min_depth=0.0, surface_offset=best))
        np.testing.assert_allclose(fixed, slope, atol=3e-3)
        assert abs(naive[1] - slope[1]) > 0.02  # through the origin below z_top, the intercept biases it
    with pytest.raises(ValueError, match="surface_offset"):
        D.run_contacts(runs[0], surface_offset=-10.0)  # a surface 10 cm above the top grain
    with pytest.raises(ValueError, match="at least one run"):
        D.calibrate_surface_offset([])


def test_slope_standard_error_matches_the_white_noise_formula():
    run = _ramp_run(0.0, 90.0, (0.0, 0.2), offset=0.0, noise=0.5, n=4000, seed=3)
    se_x, se_z = D.run_stress_se(run, min_depth=1.0)
    d = run.depth[run.depth > 1.0]
    want = 0.5 / math.sqrt(((d - d.mean()) ** 2).sum()) / (3.81 * 2.54)  # OLS slope error / area
    assert se_z == pytest.approx(want, rel=0.1) and se_x == pytest.approx(want, rel=0.1)


@needs_data
def test_real_data_surface_calibration_and_slopes_within_their_noise():
    runs, _ = D.read_runs(DATA)
    runs = [r for r in runs if r.gamma_deg >= 45]
    best, _ = D.calibrate_surface_offset(runs)
    assert 1.2 <= best <= 2.4, best  # a grain diameter or two below the highest grain's top
    slope = np.array([D.run_stress(r) for r in runs])
    se = np.array([D.run_stress_se(r) for r in runs])
    naive = np.array([D.run_stress_rft(r, min_depth=0.0) for r in runs])
    fixed = np.array([D.run_stress_rft(r, min_depth=0.0, surface_offset=best) for r in runs])
    rms = lambda v: np.sqrt((v**2).mean(0))  # noqa: E731
    assert (rms(fixed - slope) < 2 * rms(se)).all(), (rms(fixed - slope), rms(se))
    assert (rms(fixed - slope) < 0.5 * rms(naive - slope)).all(), (rms(fixed - slope), rms(naive - slope))


def test_through_origin_stress_by_hand():
    # F_z = 0.3 d + 0.5 and F_x = -0.2 d + 0.1 (N) against centre depth d below z_top: the README's recipe
    # (no intercept, d > 1 cm, over the plate area) by numpy's least squares, and with an intercept by polyfit
    run = _ramp_run(0.0, 72.0, (0.0, 0.0), offset=0.0)
    d = run.depth
    run.force[:, 2] = 0.3 * d + 0.5
    run.force[:, 0] = -0.2 * d + 0.1
    m = d > 1.0
    area = 3.81 * 2.54
    want = [np.linalg.lstsq(d[m, None], run.force[m, k], rcond=None)[0][0] / area for k in (0, 2)]
    ax, az = D.run_stress_origin(run)
    assert az == pytest.approx(want[1], rel=1e-12) and az != pytest.approx(0.3 / area, rel=1e-3)
    assert ax == pytest.approx(want[0], rel=1e-12)  # motion toward -x: canonical sign +1
    slope = [np.polyfit(d[m], run.force[m, k], 1)[0] / area for k in (0, 2)]
    np.testing.assert_allclose(D.run_stress(run), slope, rtol=1e-9)
    keep, coef = D.stress_functional(run, intercept=True)
    assert coef @ run.force[keep, 2] == pytest.approx(slope[1], rel=1e-9)
    with pytest.raises(ValueError, match="fewer than 3"):
        D.stress_functional(run, min_depth=50.0)


@pytest.mark.parametrize("offset", [0.0, 1.3])
@pytest.mark.parametrize("intercept", [False, True])
def test_recipe_functional_is_the_recipe_on_rft_forces(offset, intercept):
    # an RFT map's forces on every sample, then the recipe by hand, equal the map's force on the functional
    run = _ramp_run(30.0, 63.0, (0.0, 0.0), offset=0.0)
    smap = FourierStressMap.generic(scale_x=0.4, scale_z=0.2)
    c, _ = D.run_contacts(run, min_depth=1.0 - offset, surface_offset=offset)
    f = irft_forces(smap, c).numpy()
    d = run.depth[run.depth > 1.0]
    assert len(d) == len(f)
    A = np.stack([d, np.ones_like(d)], 1) if intercept else d[:, None]
    want = np.linalg.lstsq(A, f, rcond=None)[0][0] / (3.81 * 2.54)  # F_x of motion toward -x: sign +1
    got = irft_forces(smap, D.recipe_functional(run, intercept=intercept, surface_offset=offset))[0].numpy()
    np.testing.assert_allclose(got, want, rtol=1e-9)
    if offset == 0.0 and not intercept:
        # below z_top and past the depth where the tilted plate is all under: the functional is the map itself
        deep = D.recipe_functional(run, min_depth=3.0)
        alpha = smap(*map(torch.tensor, D.canonical_angles(run)))
        torch.testing.assert_close(irft_forces(smap, deep)[0], alpha)


def irft_forces(smap, c):
    from irft_torch.rft import forces

    return forces(smap, c)


@needs_data
def test_real_data_reproduces_the_readme_through_origin_figures():
    # the README's figures, recomputed here by numpy from the library's recipe: 54 runs, correlations with the
    # generic map 0.949 / 0.948, scales 0.266 / 0.178, leave-one-beta-out RMSE 0.0166 / 0.0173 N/cm^3
    runs, _ = D.read_runs(DATA)
    runs = [r for r in runs if (r.depth > 1.0).sum() >= 3]
    assert len(runs) == 54
    S = np.array([D.run_stress_origin(r) for r in runs])
    gen = FourierStressMap.generic()
    g = np.array([gen(*map(torch.tensor, D.canonical_angles(r))).tolist() for r in runs])
    corr = [np.corrcoef(S[:, k], g[:, k])[0, 1] for k in range(2)]
    np.testing.assert_allclose(corr, [0.949, 0.948], atol=6e-4)
    np.testing.assert_allclose((g * S).sum(0) / (g * g).sum(0), [0.266, 0.178], atol=6e-4)
    betas = np.array([r.beta_deg for r in runs])
    err = []
    for b in np.unique(betas):
        tr = betas != b
        err.append(g[~tr] * (g[tr] * S[tr]).sum(0) / (g[tr] ** 2).sum(0) - S[~tr])
    np.testing.assert_allclose(np.sqrt((np.concatenate(err) ** 2).mean(0)), [0.0166, 0.0173], atol=6e-5)


@needs_data
def test_dem_validation_experiment_runs_small(tmp_path, monkeypatch):
    import importlib

    # importable by name, as when run as a script: the fold workers (spawned processes) import it
    monkeypatch.syspath_prepend(str(pathlib.Path(__file__).resolve().parents[2] / "experiments" / "validation"))
    mod = importlib.import_module("dem_validation")
    small = ["--data", str(DATA), "--stride", "1000", "--eval-stride", "200", "--n-iter", "3", "--plain-iter", "3",
             "--no-li-basis", "--hyper-posterior", "map"]  # the script's machinery; the default's fit is tests/gp's
    res = mod.main([*small, "--out", str(tmp_path), "--jobs", "2"])
    text = (tmp_path / "dem_validation.md").read_text()
    serial = mod.main([*small, "--out", str(tmp_path / "serial"), "--jobs", "1"])  # the folds in this process
    tables = lambda t: [ln for ln in t.splitlines() if ln.startswith("|")]  # noqa: E731
    assert tables((tmp_path / "serial" / "dem_validation.md").read_text()) == tables(text)
    assert serial.keys() == res.keys()
    for name in mod.IRFT + mod.BASELINES:
        assert f"| {name}" in text
    assert "leave-one-beta-out" in text and "leave-one-gamma-out" in text and "the README's figure" in text
    for f in ("dem_maps.png", "dem_forces_heldout.png", "dem_stresses.png"):
        assert (tmp_path / f).exists(), f
    # the generic x LS row is the README's recipe: its leave-one-beta-out figures, to the printed digits
    np.testing.assert_allclose(res["beta"]["generic x LS scales"]["rmse_origin"], [0.0166, 0.0173], atol=6e-5)
    assert res["beta"]["I-RFT"]["pred_origin"].shape == (54, 2)
    # the row whose mean is chosen per axis by grouped cross-validation: each axis is one of the two fits'
    for split in res:
        r = res[split]
        cv, zero, phys = (r[n]["pred_origin"] for n in (mod.CV, "I-RFT", "I-RFT + physics mean"))
        assert np.all((cv == zero) | (cv == phys)), split
    # the 55th run is named where it is left out (the data README: beta 45, gamma 9 stays above 1 cm)
    assert "left out: beta 45, gamma 9 (deepest 0.61 cm)" in text
    # the learned surface: within a cm of the README's effective surface (1.8 cm below the top grain) after
    # 3 steps on every 1000th sample (a Laplace std may then be inf)
    learned = [float(v) for v in re.findall(r"(-?[0-9.]+) \+- (?:[0-9.]+|inf) cm / 1000 ms", text)]
    assert len(learned) == 17 and all(0.8 < v < 2.8 for v in learned), learned


def test_run_effect_variant_matches_the_dense_likelihood():
    # the experiment's per-run random stress: loss = dense Gaussian NLL with covariance W (K + tau^2 I) W^T + noise,
    # K from gpytorch's own ScaleKernel(RBFKernel) on the embedding (sin 2b, cos 2b, sin g, cos g)
    import importlib.util

    path = pathlib.Path(__file__).resolve().parents[2] / "experiments" / "validation" / "dem_validation.py"
    spec = importlib.util.spec_from_file_location("dem_validation_re", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    runs = [_ramp_run(b, g, (0.05 + 0.001 * b, 0.2), offset=0.0, noise=0.3, n=600, seed=i)
            for i, (b, g) in enumerate([(0, 90), (30, 63), (-45, 72), (60, 81)])]
    parts = [D.run_contacts(r, stride=60, min_depth=1.0) for r in runs]
    from irft_torch.rft import Contacts

    c = Contacts.cat([p[0] for p in parts])
    f = torch.cat([p[1] for p in parts])
    m = mod.fit_run_effect(c, f, "zero", 5)
    with torch.no_grad():
        m.hypers.raw_run_effect.fill_(0.3)
        got = float(m.loss() + m.backend.log_prior() / len(c))  # the likelihood part (priors checked elsewhere)
        tau2 = mod.run_effect_variance(m.hypers)
        pairs = torch.tensor([D.canonical_angles(r) for r in runs], dtype=torch.float64)
        X = torch.stack([torch.sin(2 * pairs[:, 0]), torch.cos(2 * pairs[:, 0]), torch.sin(pairs[:, 1]),
                         torch.cos(pairs[:, 1])], -1)
        K = m.kernel(X, X).to_dense()  # (2, U, U)
        run_of = torch.cat([torch.full((len(p[0]),), i) for i, p in enumerate(parts)])
        total = 0.0
        for k, w in enumerate((c.weight_x, c.weight_z)):
            Phi = torch.zeros(len(c), len(runs), dtype=torch.float64)
            Phi[torch.arange(len(c)), run_of] = w.sum(-1)
            C = Phi @ (K[k] + tau2[k] * torch.eye(len(runs))) @ Phi.T + m.hypers.noise[k] * torch.eye(len(c))
            y = f[:, k]
            total += float(0.5 * y @ torch.linalg.solve(C, y) + 0.5 * torch.logdet(C)
                           + 0.5 * len(c) * math.log(2 * math.pi)) / len(c)
    assert got == pytest.approx(total, rel=1e-8)


def test_run_contacts_keep_signed_depths_so_the_surface_can_move():
    # the same samples (centre deeper than 3 cm below z_top) built against two surfaces 0.5 cm apart:
    # moving the first one's surface down by 0.5 cm (Contacts.with_surface_offset, m) gives the second
    run = _ramp_run(30.0, 63.0, (0.06, 0.2), offset=0.0)
    c0, f0 = D.run_contacts(run, min_depth=2.0, surface_offset=1.0)
    c1, f1 = D.run_contacts(run, min_depth=1.5, surface_offset=1.5)
    assert c0.has_surface and len(c0) == len(c1) > 10
    torch.testing.assert_close(f0, f1)
    moved = c0.with_surface_offset(torch.tensor(-0.005))
    torch.testing.assert_close(moved.weight_z, c1.weight_z, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(moved.weight_x, c1.weight_x, rtol=1e-12, atol=1e-12)
    # the weights are relu(depth) x area of the plate's 10 strips (3.81 / 10 x 2.54 cm^2)
    torch.testing.assert_close(c0.area_z, torch.full_like(c0.area_z, 3.81 / 10 * 2.54))


def test_force_bootstrap_resamples_whole_runs_by_hand():
    """Two held-out runs, errors 1 N (1 sample) and 3 N (3 samples), against a perfect model: a resample is
    (1, 1) -> 1 N, (3, 3) -> 3 N, or mixed -> sqrt((1 + 27) / 4) N pooled, with chances 1/4, 1/4, 1/2; the 95 %
    interval of RMSE(perfect) - RMSE(b) is then [-3, -1] N. Resampling samples one by one would not give it."""
    import importlib.util

    path = pathlib.Path(__file__).resolve().parents[2] / "experiments" / "validation" / "dem_validation.py"
    spec = importlib.util.spec_from_file_location("dem_validation_bs", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    b = [np.ones((1, 2)), 3 * np.ones((3, 2))]
    a = [np.zeros((1, 2)), np.zeros((3, 2))]
    ci = mod.paired_bootstrap(a, b, n=4000)
    np.testing.assert_allclose(ci, [[-3.0, -3.0], [-1.0, -1.0]])
    same = mod.paired_bootstrap(b, b)
    np.testing.assert_allclose(same, 0.0)
