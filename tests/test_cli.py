import subprocess
import sys

import numpy as np
import pytest
import torch

import irft_torch as irft
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


def test_simulate_bad_input_is_a_clear_error(tmp_path, capsys):
    rc = main(["simulate", "--path", "spline", "--control-points", "0.1,0;0.0,-0.05",
               "--out", str(tmp_path / "x.npz")])
    assert rc == 2
    assert "strictly increasing x" in capsys.readouterr().err


def test_console_script_runs():
    r = subprocess.run([sys.executable, "-m", "irft_torch.cli", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "simulate" in r.stdout
    assert isinstance(irft.rft.FourierStressMap.generic(), torch.nn.Module)
