import math
import subprocess
import sys

import numpy as np
import pytest

from irft_torch.cli import build_parser, main


def test_every_subcommand_has_help(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert "simulate" in sub.choices
    for name in sub.choices:
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0
        assert "usage: irft" in capsys.readouterr().out


def test_simulate_writes_npz_csv_and_pngs(tmp_path):
    out = tmp_path / "sim.npz"
    rc = main(["simulate", "--toe", "I", "--length", "0.02", "--path", "rectangle", "--n-steps", "50",
               "--out", str(out), "--csv", str(tmp_path / "sim.csv"), "--plot", str(tmp_path / "fig")])
    assert rc == 0
    d = np.load(out)
    # independent check: a flat plate 2 cm x 0.8 cm during the shear at 5 cm depth
    # feels F = (-0.136, 0.375) * 5 * 1.6 N (generic map)
    shear = (d["position"][:, 1] < -0.0499) & (np.abs(d["position"][:, 0]) < 0.15)
    np.testing.assert_allclose(d["forces"][shear], np.tile([-0.136 * 8, 0.375 * 8], (shear.sum(), 1)),
                               atol=1e-9)
    rows = (tmp_path / "sim.csv").read_text().splitlines()
    assert len(rows) == 51 and rows[0].startswith("time_s,x_m,z_m")
    for name in ("stress_map.png", "toe_path.png", "coverage.png", "forces.png"):
        assert (tmp_path / "fig" / name).stat().st_size > 1000


def test_simulate_output_is_a_dataset_fit_reads(tmp_path):
    # a newcomer simulates, then fits: irft simulate's .npz is a dataset (load_dataset reads it)
    from irft_torch.hardware import load_dataset

    out = tmp_path / "sim.npz"
    assert main(["simulate", "--toe", "I", "--length", "0.02", "--path", "rectangle", "--n-steps", "50",
                 "--out", str(out)]) == 0
    d, ds = np.load(out), load_dataset(out)
    np.testing.assert_array_equal(ds.toe_position.numpy(), d["position"])
    np.testing.assert_array_equal(ds.forces.numpy(), d["forces"])
    # independent: the shear samples' weights are the plate's 2 cm x 0.8 cm at 5 cm depth (8 cm^3)
    shear = (d["position"][:, 1] < -0.0499) & (np.abs(d["position"][:, 0]) < 0.15)
    np.testing.assert_allclose(ds.contacts.weight_z.numpy()[shear].sum(-1), 8.0, rtol=1e-9)
    assert main(["fit", str(out), "--out", str(tmp_path / "fit"), "--n-iter", "5", "--no-progress"]) == 0
    from irft_torch import InverseRFT

    # the default, as the library's: Li et al.'s term and a Laplace hyperparameter posterior, kept in the file
    m = InverseRFT.load(tmp_path / "fit" / "model.pt")
    assert m.hypers.li is not None and m.hyper_posterior is not None and m.hyper_posterior.method == "laplace"
    assert m.hyper_posterior.n_draws > 1 and "li_variance_x" in m.hyper_posterior.labels
    assert not m.hypers.li.generic
    # the plug-in RBF by name
    assert main(["fit", str(out), "--out", str(tmp_path / "fit2"), "--n-iter", "5", "--no-progress", "--no-li-basis",
                 "--hyper-posterior", "map"]) == 0
    m = InverseRFT.load(tmp_path / "fit2" / "model.pt")
    assert m.hypers.li is None and m.hyper_posterior is None and m.hyper_method == "map"
    # ... and the generic shape's uncertain scale (--generic-shape implies --li-basis)
    assert main(["fit", str(out), "--out", str(tmp_path / "fit3"), "--n-iter", "5", "--no-progress",
                 "--generic-shape", "--hyper-posterior", "map"]) == 0
    m = InverseRFT.load(tmp_path / "fit3" / "model.pt")
    assert m.hypers.li is not None and m.hypers.li.generic and "generic_variance" in m.hypers.as_dict()


def test_simulate_bad_input_is_a_clear_error(tmp_path, capsys):
    rc = main(["simulate", "--path", "spline", "--control-points", "0.1,0;0.0,-0.05",
               "--out", str(tmp_path / "x.npz")])
    assert rc == 2
    assert "strictly increasing x" in capsys.readouterr().err


def test_console_script_runs(tmp_path):
    r = subprocess.run([sys.executable, "-m", "irft_torch.cli", "--help"], capture_output=True, text=True)
    assert r.returncode == 0
    for name in ("simulate", "reproduce", "record", "ingest", "fit"):
        assert name in r.stdout
    # a user error through the real entry point: one line on stderr, no traceback
    r = subprocess.run([sys.executable, "-m", "irft_torch.cli", "fit", str(tmp_path / "missing.npz")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.count("\n") == 1
    assert r.stderr.startswith("irft fit: error: no dataset at")


def _shear(d):
    """Samples of the rectangle gait's shear stroke (toe 5 cm deep, away from the corners)."""
    z, x = d["position"][:, 1], d["position"][:, 0]
    return (z < -0.0499) & (np.abs(x) < 0.15)


def test_simulate_map_and_scale(tmp_path):
    """Poppy seeds, loosely packed (Li et al. 2013): a horizontal plate moving horizontally feels
    alpha_z = A00 + A10 = 0.051 + 0.047 = 0.098 and alpha_x = C11 + C01 + C-11 = -0.026 + 0.057 + 0
    = 0.031 N/cm^3 (drag opposes the motion); --scale-x 2 --scale-z 0.5 scale them; 2 cm x 0.8 cm
    at 5 cm deep: depth x area = 8 cm^3."""
    out = tmp_path / "p.npz"
    rc = main(["simulate", "--toe", "I", "--length", "0.02", "--path", "rectangle", "--n-steps", "100",
               "--map", "poppy-loose", "--scale-x", "2", "--scale-z", "0.5", "--out", str(out)])
    assert rc == 0
    d = np.load(out)
    s = _shear(d)
    assert s.sum() > 10 and str(d["map"]) == "poppy-loose" and d["scale"].tolist() == [2.0, 0.5]
    np.testing.assert_allclose(d["forces"][s], np.tile([-0.031 * 2 * 8, 0.098 * 0.5 * 8], (s.sum(), 1)), atol=1e-9)


@pytest.mark.parametrize("opening", ["up", "down"])
def test_simulate_c_toe_opening(tmp_path, opening):
    """C-toe of radius 2 cm, width 0.8 cm, M = 10 chords, its arc's mid-point on the path 5 cm deep:
    sum over chords of depth x chord x width, from the geometry of the docstring (the arc below the
    mid-point's level for "down", above it for "up")."""
    out = tmp_path / "c.npz"
    rc = main(["simulate", "--toe", "C", "--radius", "0.02", "--opening", opening, "--path", "rectangle",
               "--n-steps", "100", "--out", str(out)])
    assert rc == 0
    d = np.load(out)
    r, M = 2.0, 10  # cm
    mid = -math.pi / 2 if opening == "up" else math.pi / 2  # centre -> arc mid-point
    want = 0.0
    for k in range(M):
        phi = mid + ((k + 0.5) / M - 0.5) * math.pi
        z = r * math.cos(math.pi / (2 * M)) * math.sin(phi) - r * math.sin(mid)  # chord mid-point above the origin
        want += (5.0 - z) * 2 * r * math.sin(math.pi / (2 * M)) * 0.8
    assert want == pytest.approx(21.3389 if opening == "up" else 28.7201, abs=1e-4)
    np.testing.assert_allclose(d["weight_z"][_shear(d)].sum(1), want, rtol=1e-9)


@pytest.mark.parametrize("argv, arg", [
    (["fit", "DS", "--max-samples", "-5"], "argument --max-samples"),
    (["fit", "DS", "--n-iter", "0"], "argument --n-iter"),
    (["fit", "DS", "--lr", "-1"], "argument --lr"),
    (["fit", "DS", "--out", "AFILE"], "argument --out: AFILE exists and is a file"),
    (["fit", "TRUNC"], "is damaged or not an irft dataset"),
    (["fit", "MISSING"], "no dataset at"),
    (["ingest", "LOG", "--out", "OUT", "--nodes", "0", "0"], "argument --nodes: each motor needs its own node id"),
    (["ingest", "LOG", "--out", "OUT", "--nodes", "0", "64"], "argument --nodes: node ids must be in 0..63"),
    (["ingest", "LOG", "--out", "OUT", "--rate", "0"], "argument --rate: must be a positive number"),
    (["ingest", "LOG", "--out", "OUT", "--hip-height", "-0.25"], "argument --hip-height"),
    (["ingest", "LOG", "--out", "OUT", "--kt", "0.1", "--kv", "85"], "argument --kt: give --kt or --kv"),
    (["ingest", "LOG", "--out", "OUT", "--l1", "150"], "argument --l1: is in m: 150 is above any plausible value"),
    (["ingest", "LOG", "--out", "OUT", "--directions", "1", "2"], "argument --directions"),
    (["ingest", "LOG", "--out", "OUT", "--filter-window", "0"], "argument --filter-window"),
    (["ingest", "LOG", "--out", "OUT", "--filter-window", "4"], "argument --filter-window: must be odd"),
    (["ingest", "LOG", "--out", "OUT", "--arc-noise=-1e-4"], "argument --arc-noise: must be >= 0"),
    (["ingest", "LOG", "--out", "OUT", "--extension", "-0.05"], "argument --extension: must be >= 0"),
    (["ingest", "LOG", "--out", "AFILE/x.npz"], "argument --out: cannot create"),
    (["ingest", "LOG", "--out", "ADIR"], "argument --out: ADIR.npz is a directory"),
    (["ingest", "MISSING.log", "--out", "OUT"], "argument logs: no log file at"),
    (["ingest", "LOG", "--out", "OUT", "--heading", "north"], "argument --heading"),
    # angles passed in degrees (rad expected): 90 deg = pi/2 rad, 30 deg = pi/6 rad
    (["ingest", "LOG", "--out", "OUT", "--heading", "90"], "argument --heading: is an angle in rad"),
    (["ingest", "LOG", "--out", "OUT", "--heading", "90"], "90 deg = 1.571 rad"),
    (["simulate", "--toe", "I", "--tilt", "30"], "argument --tilt: is an angle in rad"),
    (["simulate", "--toe", "I", "--tilt", "-30"], "-30 deg = -0.5236 rad"),
    (["ingest", "LOG", "--out", "OUT", "--protocol", "mit", "--mit-model", "AK99"], "argument --mit-model"),
    (["record", "--out", "r.trc"], "argument --out: the suffix picks the log format"),
    (["record", "--out", "r.log", "--rate", "0"], "argument --rate"),
    (["record", "--out", "r.log", "--duration", "-1"], "argument --duration"),
    (["record", "--out", "r.log", "--interface", "nosuch"], "argument --interface: python-can cannot use 'nosuch'"),
    (["record", "--out", "r.log", "--interface", "virtual", "--poll", "get_nothing"], "argument --poll"),
    (["reproduce", "--out", "AFILE"], "argument --out: AFILE exists and is a file"),
    (["ingest", "LOG", "--out", "OUT", "--protocol", "mit", "--mit-master-id", "4096"], "argument --mit-master-id"),
    (["simulate", "--segments", "0"], "argument --segments"),
    (["simulate", "--radius", "0"], "argument --radius"),
    (["simulate", "--out", "ADIR"], "argument --out: ADIR.npz is a directory"),
    (["simulate", "--plot", "AFILE"], "argument --plot: AFILE exists and is a file"),
    (["simulate", "--n-steps", "x"], "argument --n-steps: invalid int value"),
])
def test_user_errors_are_one_line_naming_the_argument(tmp_path, capsys, argv, arg):
    (tmp_path / "AFILE").write_text("x")
    (tmp_path / "ADIR.npz").mkdir()
    (tmp_path / "LOG.log").write_text("(1.0) can0 014#0000000000000000\n")
    (tmp_path / "TRUNC.npz").write_bytes(b"PK\x03\x04" + bytes(50))
    sub = {"DS": "TRUNC.npz", "AFILE": "AFILE", "ADIR": "ADIR", "TRUNC": "TRUNC.npz", "MISSING": "none.npz",
           "LOG": "LOG.log", "OUT": "out.npz", "MISSING.log": "none.log"}

    def fix(a):
        for k, v in sub.items():
            if a == k or a.startswith(k + "/"):
                return str(tmp_path / (v + a[len(k):]))
        return str(tmp_path / a) if a.endswith((".log", ".trc")) else a

    try:
        rc = main([fix(a) for a in argv])
    except SystemExit as e:  # argparse's own type errors
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert arg.replace("AFILE", str(tmp_path / "AFILE")).replace("ADIR", str(tmp_path / "ADIR")) in err, err
    assert not (tmp_path / "out.npz").exists()


def test_simulate_terrain_walks_two_media_and_writes_each_sample_place(tmp_path, capsys):
    # a flat 2 cm x 0.8 cm plate in shear at 5 cm depth: 8 cm^3 times the medium's map at (beta 0, gamma 0), which
    # is generic (F = (-0.136, 0.375) x 8 N, as above) before the boundary (x = 3 m / 2) and poppy seeds (close)
    # beyond it. Stances 1 m apart; the shear drags the place 0.05..0.35 m past the foothold, so stance 0 is 23
    # boundary widths (0.05 m) before it, stance 2 eleven beyond (share 1.7e-5 of the other), stance 3 31 beyond
    from irft_torch import rft
    from irft_torch.hardware import load_dataset
    from irft_torch.rft import FourierStressMap

    out = tmp_path / "walk.npz"
    assert main(["simulate", "--toe", "I", "--length", "0.02", "--path", "rectangle", "--n-steps", "50",
                 "--terrain", "two-media", "--stances", "4", "--stride", "1.0", "--out", str(out),
                 "--plot", str(tmp_path / "fig")]) == 0
    d, ds = np.load(out), load_dataset(out)
    assert d["forces"].shape == (200, 2) and ds.locations.shape == (200, 2)
    np.testing.assert_array_equal(d["stance"], np.repeat(np.arange(4), 50))
    np.testing.assert_allclose(d["footholds"], [[0, 0], [1, 0], [2, 0], [3, 0]], atol=1e-12)
    shear = (d["position"][:, 1] < -0.0499) & (np.abs(d["position"][:, 0]) < 0.15)
    rows = shear & (d["stance"] == 0)
    np.testing.assert_allclose(d["forces"][rows], np.tile([-0.136 * 8, 0.375 * 8], (rows.sum(), 1)), atol=1e-6)
    close = rft.forces(FourierStressMap.poppy_seeds_close(), ds.contacts).numpy()  # the homogeneous bed of seeds
    for k, rtol in ((2, 1e-4), (3, 1e-12)):
        rows = shear & (d["stance"] == k)
        np.testing.assert_allclose(d["forces"][rows], close[rows], rtol=rtol, atol=1e-12)
        assert np.abs(close[rows] - np.array([-0.136 * 8, 0.375 * 8])).max() > 0.5  # the media differ here
    # each sample's place: its foothold plus the stroke's drag along x
    np.testing.assert_allclose(ds.locations.numpy()[:, 0], d["footholds"][d["stance"], 0]
                               + d["position"][:, 0] - d["position"][0, 0])
    assert (tmp_path / "fig" / "terrain.png").stat().st_size > 1000
    capsys.readouterr()
    # the homogeneous fit says what it does with the places (one medium for the whole walk)
    assert main(["fit", str(out), "--out", str(tmp_path / "fit"), "--n-iter", "3", "--no-progress",
                 "--hyper-posterior", "map"]) == 0
    assert "carry each sample's place" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["simulate", "--terrain", "patches", "--stances", "0", "--out", str(tmp_path / "x.npz")])
