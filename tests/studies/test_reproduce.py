"""`irft reproduce --quick`: every output, the paper's columns, well-formed report tables, identical
tables on a rerun."""

import csv
import re
import sys

import pytest

from irft_torch.cli import main

from . import experiment_path


def read(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def markdown_tables(text):
    """Every table of a markdown document as (header cells, [row cells]); a table starts at a header
    line followed by a |---| separator."""
    lines, tables, i = text.splitlines(), [], 0
    split = lambda line: [c.strip() for c in line.strip().strip("|").split("|")]  # noqa: E731
    while i < len(lines) - 1:
        if lines[i].startswith("|") and re.fullmatch(r"\|(-+\|)+", lines[i + 1].strip()):
            header, rows, i = split(lines[i]), [], i + 2
            assert len(split(lines[i - 1])) == len(header), f"separator width differs from header {header}"
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(split(lines[i]))
                i += 1
            tables.append((header, rows))
        else:
            i += 1
    return tables


def test_reproduce_quick_writes_everything_and_is_deterministic(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["reproduce", "--quick", "--out", str(a), "--no-progress"]) == 0
    t1 = read(a / "table1.csv")
    assert list(t1[0]) == ["config", "axis", "rmse", "mae", "r2", "pearson", "acr_percent"]
    assert {(r["config"], r["axis"]) for r in t1} == {
        (c, ax) for c in ("I-toe gait 1", "I-toe gait 2", "C-toe gait 1", "C-toe gait 2") for ax in "XZ"}
    t2 = read(a / "table2.csv")
    assert list(t2[0])[:5] == ["config", "axis", "noise", "rmse_percent", "mae_percent"]
    report = (a / "report.md").read_text()
    assert "ours / paper" in report and "c_opening" in report and "physics" in report
    assert len(list(a.glob("fig5_*.png"))) == 4
    # the C-toe on gait 2 is the best-sampled configuration: its map must be recovered well
    c2 = {r["axis"]: r for r in t1 if r["config"] == "C-toe gait 2"}
    assert float(c2["Z"]["r2"]) > 0.9 and float(c2["X"]["r2"]) > 0.8
    # rerun: identical tables
    from irft_torch.studies.paper_study import run_study
    from irft_torch.studies.reproduce import StudySettings

    run_study(b, StudySettings.quick_settings(), progress=False, figures=False)
    assert (a / "table1.csv").read_text() == (b / "table1.csv").read_text()
    assert (a / "table2.csv").read_text() == (b / "table2.csv").read_text()


def test_report_tables_are_well_formed_and_define_their_metrics(tmp_path):
    from irft_torch.studies.paper_study import run_study
    from irft_torch.studies.reproduce import StudySettings

    s = StudySettings(n_steps=30, grid=16, n_iter=10, noise_levels=(0.0, 0.05, 0.2), noise_seeds=(0,),
                      lengthscale_sensitivity=(), quick=True)
    run_study(tmp_path, s, progress=False, figures=False)
    report = (tmp_path / "report.md").read_text()
    tables = markdown_tables(report)
    assert len(tables) >= 5
    for header, rows in tables:  # every row has exactly the header's cells (the old Table II had 8 under 5)
        assert rows and all(len(r) == len(header) for r in rows), header
    # Table II: the paper's cells sit under the paper's column for the same noise level.
    # Values typed from Table II of the paper (reference/irft_paper.tex), RMSE% / MAE%.
    (header, rows), = [t for t in tables if "paper, noise 0.05" in t[0]]
    assert header == ["config", "axis", "ours, noise 0.0", "paper, noise 0.0", "ours, noise 0.05",
                      "paper, noise 0.05", "ours, noise 0.2", "paper, noise 0.2"]
    row = {(r[0], r[1]): dict(zip(header, r)) for r in rows}
    assert row[("C-toe gait 2", "Z")]["paper, noise 0.0"] == "3.68 / 2.41"
    assert row[("C-toe gait 2", "Z")]["paper, noise 0.05"] == "16.18 / 13.50"
    assert row[("C-toe gait 2", "Z")]["paper, noise 0.2"] == "35.37 / 23.11"
    assert row[("I-toe gait 1", "X")]["paper, noise 0.05"] == "18.41 / 12.42"
    assert re.fullmatch(r"[\d.]+\+-[\d.]+ / [\d.]+\+-[\d.]+", row[("I-toe gait 1", "X")]["ours, noise 0.05"])
    # every metric the tables use is defined in the report
    (dh, drows), = [t for t in tables if dh_is(t[0])]
    defined = {r[0] for r in drows}
    for name in ("RMSE", "MAE", "R2", "Pearson", "ACR% (accurate-coverage ratio)", "95% calibration", "coverage",
                 "redundancy"):
        assert name in defined
    assert "5 % of range" in report and "1.96 posterior std" in report


def dh_is(header):
    return header == ["metric", "definition", "unit"]


# ---- the experiment scripts' own outputs ------------------------------------------------------
def _script(name):
    import importlib.util

    path = experiment_path(name)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_experiment_help_prints_the_whole_description_and_defaults(capsys):
    import pytest

    for name, last in (("dem_validation", "The data are read from --data and never copied."),
                       ("active_probing", "active_probing_paths.png."),
                       ("experimental_validation", "z = -5, 0, -3, -1 cm"),
                       ("mixture_spread", "how many runs are above 10 %."),
                       ("walk_and_map", "``walk_and_map.png``."),
                       ("explore_footholds", "``explore_footholds_K_gaits.csv``).")):
        mod = _script(name)
        with pytest.raises(SystemExit):
            mod.main(["--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert last in text, name  # the old --help stopped after the docstring's first line
        assert "(default: experiments/results)" in text, name
    mod = _script("dem_validation")
    with pytest.raises(SystemExit):
        mod.main(["--help"])
    assert "(default: auto)" in " ".join(capsys.readouterr().out.split())  # --stride, matched per fold


def test_active_probing_summary_names_the_probes_or_says_none():
    wins_sentence = _script("active_probing").wins_sentence
    none = wins_sentence([False, False, False])
    assert "(none)" not in none and "after any of the 3 probes" in none and "not below" in none
    assert wins_sentence([False, True, True]).endswith("after probes 2, 3 (of 3).")
    assert wins_sentence([True, False]).endswith("after probe 1 (of 2).")


def test_experimental_validation_says_its_errors_are_in_sample():
    import inspect

    src = inspect.getsource(_script("experimental_validation").main)
    # the report's table: in-sample errors on a simulated leg next to the paper's real-leg errors, said so
    assert "in-sample" in src and "physical leg in real sand" in src
    assert "I-RFT in-sample force RMSE %" in src and "paper's I-RFT % (real leg)" in src


def test_importing_the_experiments_keeps_the_matplotlib_backend():
    """The scripts select a headless backend in main(), never at import (nor through irft_torch.plotting)."""
    import subprocess
    import sys

    code = ("import matplotlib, importlib.util, pathlib, sys; matplotlib.use('svg')\n"
            "for n in ('dem_validation', 'active_probing', 'experimental_validation'):\n"
            "    p = pathlib.Path('experiments') / 'validation' / (n + '.py')\n"
            "    s = importlib.util.spec_from_file_location(n, p)\n"
            "    m = importlib.util.module_from_spec(s); sys.modules[n] = m; s.loader.exec_module(m)\n"
            "import irft_torch.studies.paper_study, irft_torch.plotting\n"
            "print(matplotlib.get_backend())")
    import os
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[2]
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=root)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().lower() == "svg"


def test_calibration_study_quick_writes_coverage_that_matches_its_csv(tmp_path):
    """experiments/calibration/calibration_study.py --quick: every cell's coverage is a share in [0, 1], the 95 %
    interval covers at least the 50 % one's share (nested intervals), and the report's median is the
    median of the CSV's 95 % column (recomputed here)."""
    import csv
    import statistics
    import subprocess
    import sys

    script = experiment_path("calibration_study")
    subprocess.run([sys.executable, str(script), "--quick", "--out", str(tmp_path)], check=True,
                   capture_output=True, text=True)
    rows = list(csv.DictReader(open(tmp_path / "calibration_study.csv")))
    assert rows
    for r in rows:  # nested intervals: a wider one covers at least as much
        assert 0 <= float(r["cover50"]) <= float(r["cover90"]) <= float(r["cover95"]) <= 1
    cells = {}
    for r in rows:
        cells.setdefault((r["config"], r["axis"], r["noise"]), []).append(float(r["cover95"]))
    median = statistics.median(sum(v) / len(v) for v in cells.values())
    report = (tmp_path / "calibration_study.md").read_text()
    assert f"median {median:.3f}" in report, report
    assert (tmp_path / "calibration_reliability.png").stat().st_size > 10_000


def test_sampling_statistics_match_the_hand_count():
    # an I-toe sample covers one (beta, gamma) cell (its segments share one angle pair), a C-toe sample
    # one per segment in contact (on gait 1 the whole C is submerged), so the gait-1 area ratio is
    # the C-toe's segment count; the I-toe's gait-1 samples repeat three pairs (down, across, up)
    import torch

    from irft_torch.rft import contacts
    from irft_torch.studies import reproduce as R
    from irft_torch.studies.report import _pinning_rows

    torch.set_default_dtype(torch.float64)
    for M in (6, 10):
        s = R.StudySettings(n_steps=40, n_segments=M)
        st = R.sampling_statistics(s)
        assert st["C/I gait 1"] == pytest.approx(M, rel=1e-12)
        c = contacts(*R.configuration("I-toe gait 1", s))
        n_total = int((c.weight_z != 0).sum())  # segment samples in contact
        assert st["I-toe gait 1 (1e-3 rad)"] == pytest.approx(1 - 3 / n_total, rel=1e-12)
    text = "\n".join(_pinning_rows(R.StudySettings()))
    assert "| paper | 10.0 | 18.1 | 5.1 | 0.97 | 0.68 | 0.11 |" in text and "| 100 (the study) |" in text
    # the turning hypothesis: the C-toe's heading follows the direction of motion, so its segments' beta
    # move with the path's slope (every segment's beta shifts by the heading's change) and gait 2's
    # distinct pairs can only grow
    import math

    s = R.StudySettings(n_steps=60)
    # by hand on the rectangle gait: down the first 5 cm (-pi/2), across (0), up the last 5 cm (+pi/2)
    h = R.tangent_heading(R.configuration("I-toe gait 1", s)[1]).heading
    assert torch.allclose(h[:5], torch.full((5,), -math.pi / 2)) and torch.allclose(h[25:35], torch.zeros(10))
    assert torch.allclose(h[-5:], torch.full((5,), math.pi / 2))
    s = R.StudySettings(n_steps=20)
    toe, path = R.configuration("C-toe gait 2", s)
    turned = R.tangent_heading(path)
    # on the cubic gait, the slope of the spline z(x) (finite differences of the positions, not the velocities)
    dx, dz = path.position.diff(dim=0).T
    mid = 0.5 * (turned.heading[1:] + turned.heading[:-1])
    torch.testing.assert_close(mid, torch.atan2(dz, dx), atol=0.05, rtol=0)
    fixed, turning = contacts(toe, path), contacts(toe, turned)
    assert turning.beta[turning.weight_z != 0].unique().numel() > fixed.beta[fixed.weight_z != 0].unique().numel()
    st = R.sampling_statistics(s, c_turns_on_gait_2=True)
    assert st["C/I gait 2"] > R.sampling_statistics(s)["C/I gait 2"]
    assert st["C/I gait 1"] == pytest.approx(10.0)  # gait 1 untouched


def test_bench_inference_quick_runs_and_checks_itself_against_the_dense_formula(tmp_path):
    # the benchmark asserts its paper-scale step equals the dense formula before timing it; a change
    # of defaults (priors, backends) must not break that check. No timing is asserted here.
    import subprocess

    bench = experiment_path("bench_inference")
    r = subprocess.run([sys.executable, str(bench), "--quick", "--repeats", "1",
                        "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    text = (tmp_path / "benchmarks.md").read_text()
    assert "1. paper scale" in text and "5. streaming" in text


def test_calibration_prior_draws_have_the_kernels_covariance():
    # maps drawn by the calibration study's --truth prior: their covariance across draws at three angle
    # pairs against the RBF on the embedding (sin 2b, cos 2b, sin g, cos g) / l, written out here
    import importlib.util

    import torch

    path = experiment_path("calibration_study")
    spec = importlib.util.spec_from_file_location("calibration_study_draws", path)
    cs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cs)
    torch.set_default_dtype(torch.float64)
    b, g = torch.tensor([0.0, 0.5, -1.0]), torch.tensor([0.3, -0.7, 1.2])
    vals = torch.stack([cs.PriorDraw([0.04, 0.09], 1.5, s)(b, g) for s in range(300)])  # (300, 3, 2)
    emb = torch.stack([torch.sin(2 * b), torch.cos(2 * b), torch.sin(g), torch.cos(g)], -1) / 1.5
    K = torch.exp(-0.5 * torch.cdist(emb, emb).pow(2))
    for a, s in ((0, 0.04), (1, 0.09)):
        C = torch.cov(vals[..., a].T) / s
        assert (C - K).abs().max() < 0.25, (C, K)  # 300 draws: sampling error about 0.1
    # the mirror identity: alpha_x flips sign, alpha_z does not, under (b, g) -> (-b, pi - g)
    d = cs.PriorDraw([0.04, 0.09], 1.5, 7)
    a1, a2 = d(b, g), d(-b, torch.pi - g)
    torch.testing.assert_close(a2[..., 0], -a1[..., 0])
    torch.testing.assert_close(a2[..., 1], a1[..., 1])


def _calibration_study():
    import importlib.util

    path = experiment_path("calibration_study")
    spec = importlib.util.spec_from_file_location("calibration_study_split", path)
    cs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cs)
    return cs


def test_calibration_split_and_prior_ceiling_by_hand():
    import torch

    from irft_torch.studies import reproduce as R

    cs = _calibration_study()
    torch.set_default_dtype(torch.float64)
    # split: 4 points, the first two with variance below half the prior's (1); errors 0.1, 3, 0.1, 3 at std 1
    maps = {"mean": torch.zeros(4, 2), "std": torch.tensor([[0.5, 1.0], [0.5, 1.0], [1.0, 1.0], [1.0, 1.0]]),
            "truth": torch.tensor([[0.1, 0.0], [3.0, 0.0], [0.1, 0.0], [3.0, 0.0]]), "prior_std": torch.ones(2)}
    x = cs.split_coverage(maps, 0)
    assert x["constrained"] == 0.5 and x["cover95_constrained"] == 0.5 and x["cover95_prior"] == 0.5
    z = cs.split_coverage(maps, 1)  # nothing constrained: that part is NaN, not a number
    assert z["constrained"] == 0.0 and z["cover95_constrained"] != z["cover95_constrained"] and z["cover95_prior"] == 1

    # ceiling: X = sign(beta) has |X| = rms everywhere (inside 1.96 rms: 1.0); Z = 10 on the cells with beta > 1.2
    # (a share f = 0.118 of a 50-cell grid: rms 10 sqrt(f) = 3.4, 10 > 1.96 x 3.4) and 0 elsewhere: 1 - f inside
    s = R.StudySettings()
    B, _ = R._grid(s)
    f = float((B > 1.2).double().mean())
    assert 0.1 < f < 0.13
    x, z = cs.prior_ceiling(lambda b, g: torch.stack([torch.sign(b), 10.0 * (b > 1.2)], -1), s)
    assert x == 1.0 and z == pytest.approx(1 - f)


def test_posterior_draws_are_covered_at_the_nominal_rate_on_average():
    # a map drawn from the fit's joint posterior is inside the marginal 95 % interval at 95 % of the points
    # on average over draws (for each point P(|N(0, s^2)| <= 1.96 s) = 0.95): a covariance inconsistent with
    # the variances (a missing or doubled term, a wrong jitter) moves that mean
    import torch

    from irft_torch.rft import FourierStressMap
    from irft_torch.studies import reproduce as R

    cs = _calibration_study()
    torch.set_default_dtype(torch.float64)
    s = R.StudySettings(n_steps=30, grid=16, n_iter=30)
    r = R._fit_one("C-toe gait 1", "zero", 0.05, 0, FourierStressMap.generic(*s.truth_scale), "t", s,
                   keep_maps=True, keep_model=True)
    cover = cs.posterior_draw_coverage(r.maps["model"], r.maps["B"], r.maps["G"], 4000, 0)
    assert cover.shape == (2, 4000)
    torch.testing.assert_close(cover.mean(-1), torch.full((2,), 0.95), atol=0.01, rtol=0)
    assert float(cover.std(-1).min()) > 0.02  # spatially correlated errors: one draw's coverage scatters


def test_itoe_alpha_x_is_as_covered_as_a_calibrated_model_would_be_with_the_priors_only():
    # the confidently-wrong case: an I-toe on gait 1 sees beta = 0 only. The share of the generic map
    # inside alpha_x's 95 % interval, against the shares that maps drawn from the fit's own posterior get (truths
    # it is calibrated for): within their central 95 % with the default priors (measured percentile 0.17), below
    # all of them with the paper's plain likelihood (measured 0.000: overconfident)
    import torch

    from irft_torch.rft import FourierStressMap
    from irft_torch.studies import reproduce as R

    cs = _calibration_study()
    torch.set_default_dtype(torch.float64)
    pits = {}
    for priors in ("physical", None):
        s = R.StudySettings(n_steps=60, grid=24, n_iter=100, priors=priors)
        r = R._fit_one("I-toe gait 1", "zero", 0.2, 0, FourierStressMap.generic(*s.truth_scale), "t", s,
                       keep_maps=True, keep_model=True)
        cover = cs.posterior_draw_coverage(r.maps["model"], r.maps["B"], r.maps["G"], 400, 0)[0]
        obs = r.metrics["X"]["calibration95"]
        pits[priors] = float((cover < obs).double().mean() + 0.5 * (cover == obs).double().mean())
    assert 0.025 <= pits["physical"] <= 0.975, pits
    assert pits[None] < 0.025, pits


def test_pinned_fits_use_the_paper_sampling():
    # Table I under the pinned sampling: PINNED_STEPS samples per path, the C-toe turning on gait 2 only
    import torch

    from irft_torch.rft import FourierStressMap
    from irft_torch.studies import reproduce as R

    torch.set_default_dtype(torch.float64)
    s = R.StudySettings(n_iter=2, grid=8)
    truth = FourierStressMap.generic(*s.truth_scale)
    for config in ("C-toe gait 1", "C-toe gait 2"):
        r = R._fit_one(config, "zero", 0.0, 0, truth, "paper scale", s, keep_maps=True, pinned=True)
        c = r.maps["contacts"]
        assert r.pinned and len(c) == R.PINNED_STEPS
        n_beta = c.beta[c.weight_z != 0].unique().numel()
        assert (n_beta > s.n_segments) == (config == "C-toe gait 2")  # only the turning toe's betas move


def test_bench_experiments_help_and_its_table_comparison(tmp_path, capsys):
    """bench_experiments.py's --help says what it runs; its cell-by-cell table comparison reads CSVs by
    their key columns and markdown tables by row label, checked on hand-made tables."""
    import pytest

    mod = _script("bench_experiments")
    with pytest.raises(SystemExit):
        mod.main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "The data are read from --data and never copied." in text and "(default: 25da515)" in text
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    a.write_text("config,axis,noise,rmse,acr\nC,X,0.0,0.10,50\nC,Z,0.0,0.20,40\nI,X,0.2,1.0,10\n")
    b.write_text("config,axis,noise,rmse,acr\nI,X,0.2,1.5,10\nC,Z,0.0,0.20,44\nC,X,0.0,0.11,50\n")  # rows reordered
    cells = mod.table_cells(a)
    assert cells[("C", "Z", "0.0", "rmse")] == 0.20 and ("C", "Z", "0.0", "noise") not in cells
    # relative differences: 0.1, 0, 0, 0.1, 0.5, 0 -> median (upper) 0.1, largest 0.5 at (I, X, 0.2, rmse)
    out = mod.compare(a, b)
    assert out.startswith("6 common cells, median relative difference 10.0%, largest 50.0% (I, X, 0.2, rmse")
    m1, m2 = tmp_path / "a.md", tmp_path / "b.md"
    m1.write_text("| model | x | z |\n|---|---|---|\n| A | 0.0100 | 2 % |\n| B | - | 0.5 |\n")
    m2.write_text("text\n| model | x | z |\n|---|---|---|\n| A | 0.0110 | 2 % |\n| B | 1 | 0.5 |\n")
    assert mod.table_cells(m1) == {("A", 1): 0.01, ("A", 2): 2.0, ("B", 2): 0.5}
    assert mod.compare(m1, m2).startswith("3 common cells, median relative difference 0.0%, largest 10.0% (A, 1")


def test_reproduce_priors_none_runs_every_fit_on_the_plain_likelihood(tmp_path, monkeypatch):
    """`irft reproduce --priors none`: the settings the study runs with have no priors (the paper's model);
    the default keeps the library's physical priors."""
    import irft_torch.studies.paper_study as P
    import irft_torch.studies.reproduce as R

    seen = []
    monkeypatch.setattr(P, "run_study", lambda out, s, **kw: seen.append(s) or {"out_dir": str(out), "elapsed_s": 0})
    assert main(["reproduce", "--priors", "none", "--out", str(tmp_path), "--no-progress"]) == 0
    assert main(["reproduce", "--quick", "--out", str(tmp_path), "--no-progress"]) == 0
    assert seen[0].priors is None and seen[0].n_iter == R.StudySettings().n_iter
    assert seen[1].priors == "physical" and seen[1].quick
    # the library's default fit instead of the paper's model; the paper's stays the study's default
    argv = ["reproduce", "--li-basis", "--hyper-posterior", "laplace", "--out", str(tmp_path), "--no-progress"]
    assert main(argv) == 0
    assert (seen[2].li_basis, seen[2].hyper_posterior) == (True, "laplace")
    assert (seen[0].li_basis, seen[0].hyper_posterior) == (False, "map")


def test_the_study_groups_only_fits_that_batch_and_batches_every_noise_study():
    """irft reproduce's grouping (``_groups``) against the batching's own rule (``gp.shares_fit``): every
    group of two or more is one that ``fit_together`` fits as one batch (none falls back, which would be
    slower, not wrong), and the noise levels x seeds of each configuration share one group."""
    import irft_torch.studies.reproduce as R
    from irft_torch.gp.batch_fit import shares_fit

    s = R.StudySettings()
    jobs = R.study_fits(s)
    groups = R._groups(jobs, s)
    assert sorted(i for g in groups for i in g) == list(range(len(jobs)))
    batched = [g for g in groups if len(g) > 1]
    assert batched
    for g in batched:
        models = []
        for i in g:
            config, prior_mean, noise, seed, truth_map, _, _, *rest = jobs[i]
            ls, priors, pinned = (rest + [None, "settings", False][len(rest):])[:3]
            models.append(R._build(config, prior_mean, noise, seed, truth_map, s, ls, priors, pinned)[0])
        assert shares_fit(models) is None, [jobs[i][:4] for i in g]
    for config in R.CONFIGS:  # where "auto" picks the pairs space, the noise study is one batch
        noisy = [i for i, j in enumerate(jobs) if j[0] == config and j[2] > 0]
        pairs = R._build(config, "zero", 0.0, 0, jobs[0][4], s)[0].method == "pairs"
        assert len(noisy) > 1 and any(set(noisy) <= set(g) for g in groups) == pairs, config
