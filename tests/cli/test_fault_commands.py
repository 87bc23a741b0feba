"""The second pass of real-world faults at the command line (docs/faults.md F62-): swapped or mis-signed
inputs, unit slips, options that would destroy data, outputs that would overwrite each other, fits
interrupted or worse than the one in place, warnings as one line."""

import pytest
from hardware.fault_logs import dump, ingest

from irft_torch.cli import main


def test_trial_and_air_run_swapped_is_named(capsys, tmp_path, sim_logs):
    """(was: F_z <= 0 throughout the intrusion, alpha_z fitted at -0.64 where the truth is +0.67, exit 0)"""
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["air"], sim_logs["trial"])
    assert rc == 2 and err.count("\n") == 1 and not (tmp_path / "t.npz").exists()
    assert "both axes have the wrong sign" in err and "were the trial and the air run swapped?" in err


def test_an_air_run_ingested_as_a_trial_is_named(capsys, tmp_path, sim_logs):
    """(was: fitted as a medium with alpha_z ~ 0) the forces are no medium's at the stated depths."""
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["air"], sim_logs["air"])
    assert rc == 2 and "F_z is zero in every sample in contact" in err and "a log in air given as a trial?" in err
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["air"], sim_logs["air"], "--any-medium")
    assert rc == 0  # the check can be skipped, said in the message


@pytest.mark.parametrize("option, value, expect", [
    ("--width", "0.8", "argument --width: is in m: 0.8 is above any plausible value (0.0005 to 0.3 m); did you mean "
                       "0.8 cm = 0.008 m"),
    ("--zero-offsets", "90 0", "argument --zero-offsets: are joint angles in rad, within a turn (|q| <= 2 pi); got 90 "
                               "0 (degrees? 90 deg = 1.571 rad)"),
    ("--path-tol", "1", "argument --path-tol: is in m: 1 is above any plausible value (0.0001 to 0.1 m)"),
    ("--hip-height", "25", "argument --hip-height: is in m: 25 is above"),
    ("--kt", "97.3", "argument --kt: is in N m/A: 97.3 is above any plausible value (0.001 to 10 N m/A); mN m/A?"),
    ("--kt", "0.0000973", "argument --kt: is in N m/A: 9.73e-05 is below"),
    ("--gear-ratio", "9000", "argument --gear-ratio: is in motor turns per joint turn"),
])
def test_unit_slips_in_options_are_refused_before_any_work(capsys, tmp_path, sim_logs, option, value, expect):
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"], option, *value.split())
    assert rc == 2 and expect in err and err.count("\n") == 1 and out == ""


def test_a_toe_deeper_than_stated_is_named(capsys, tmp_path, sim_logs):
    """Hips stated 5 cm too high: the contacts say 1 mm deep where the toe ran 5 cm deep, the forces are
    800x what any medium gives that shallow (was: a dataset, exit 0)."""
    rc, out, err, ds = ingest(capsys, tmp_path, sim_logs["trial"], sim_logs["air"], "--hip-height", "0.3")
    assert rc == 2 and "F_z is" in err and "x what the generic granular medium gives" in err and "--hip-height" in err


def test_record_simulate_refuses_an_air_log_that_is_the_trial(capsys, tmp_path):
    """(was: the air run overwrote the trial) --air-out X --out X, and the trials' numbered names."""
    out = tmp_path / "x.log"
    out.write_text("keep me\n")
    rc = main(["record", "--simulate", "--out", str(out), "--air-out", str(out), "--speed", "0.2"])
    err = capsys.readouterr().err
    assert rc == 2 and "argument --air-out" in err and "would overwrite it" in err
    assert out.read_text() == "keep me\n"
    rc = main(["record", "--simulate", "--out", str(out), "--trials", "2", "--air-out", str(tmp_path / "x_2.log"),
               "--speed", "0.2"])
    assert rc == 2 and "trial 2" in capsys.readouterr().err and not (tmp_path / "x_1.log").exists()


def test_warnings_are_one_line(capsys, tmp_path, sim_logs):
    """Python warnings inside a command print as 'irft CMD: warning: ...', never file, line and source."""
    trial = sim_logs["trial"]
    cut = trial[0][0] + 0.6 * (trial[-1][0] - trial[0][0])
    lines = [ln for ln in trial if not (ln[2].startswith("029#") and ln[0] > cut)]
    rc, out, err, ds = ingest(capsys, tmp_path, lines, sim_logs["air"])
    assert rc == 0 and err and all(ln.startswith("irft ingest: warning: ") for ln in err.splitlines())
    assert "UserWarning" not in err and ".py:" not in err


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, sim_logs):
    folder = tmp_path_factory.mktemp("fit")
    dump(sim_logs["trial"], folder / "t.log")
    dump(sim_logs["air"], folder / "a.log")
    assert main(["ingest", str(folder / "t.log"), "--air", str(folder / "a.log"), "--out", str(folder / "ds.npz")]) == 0
    return folder / "ds.npz"


@pytest.fixture
def cheap_figures(monkeypatch):
    """Small figures in place of the map and force plots (what is tested is which files change, not the
    drawing, which test_cli checks)."""
    import matplotlib.pyplot as plt

    from irft_torch import plotting

    drawn = []

    def tiny(*a, **k):  # each a different picture, as each run's figures are
        drawn.append(1)
        fig = plt.figure(figsize=(1, 1))
        fig.text(0.5, 0.5, str(len(drawn)))
        return fig

    monkeypatch.setattr(plotting, "plot_posterior_map", tiny)
    monkeypatch.setattr(plotting, "plot_forces", tiny)


def _files(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir() if not p.name.startswith(".")}


def test_fit_interrupted_before_its_first_step_writes_nothing(capsys, tmp_path, dataset, monkeypatch, cheap_figures):
    """(was: an unfitted model written over the previous one, exit 0) Ctrl-C in the first step: the
    folder is as it was, exit 130; after some steps: written (the steps taken), said, exit 130."""
    from irft_torch.gp.backends.base import RFTBackend

    out = tmp_path / "fit"
    assert main(["fit", str(dataset), "--out", str(out), "--n-iter", "3", "--max-samples", "80", "--no-progress"]) == 0
    before = _files(out)
    real, real_lg, calls = RFTBackend.loss, RFTBackend.loss_and_grad, {"n": 0}

    def loss(self, *a, **k):  # the autograd step
        calls["n"] += 1
        if calls["n"] > calls.get("stop", 0):
            raise KeyboardInterrupt
        return real(self, *a, **k)

    def loss_and_grad(self, *a, **k):  # the closed-form step (gp.backends.closed_form)
        calls["n"] += 1
        if calls["n"] > calls.get("stop", 0):
            raise KeyboardInterrupt
        return real_lg(self, *a, **k)

    monkeypatch.setattr(RFTBackend, "loss", loss)
    monkeypatch.setattr(RFTBackend, "loss_and_grad", loss_and_grad)
    capsys.readouterr()
    rc = main(["fit", str(dataset), "--out", str(out), "--n-iter", "5", "--max-samples", "80", "--no-progress",
               "--replace"])
    err = capsys.readouterr().err
    assert rc == 130 and "interrupted before the first step: nothing written" in err and _files(out) == before
    calls.update(n=0, stop=2)
    rc = main(["fit", str(dataset), "--out", str(out), "--n-iter", "5", "--max-samples", "80", "--no-progress",
               "--replace"])
    cap = capsys.readouterr()
    assert rc == 130 and "interrupted after 2 of 5 steps" in cap.out and _files(out)["model.pt"] != before["model.pt"]


def test_fit_keeps_a_better_model_and_never_mixes_two_runs(capsys, tmp_path, dataset, monkeypatch, cheap_figures):
    """A 2-step fit into a folder holding a 20-step fit of the same data and options keeps the better one
    (exit 1, said); --replace writes it. A fit that fails while drawing its figures leaves the folder's
    three files as they were (was: one run's model beside the other's figures)."""
    from irft_torch import plotting

    out = tmp_path / "fit"
    args = ["fit", str(dataset), "--out", str(out), "--max-samples", "80", "--no-progress", "--hyper-posterior", "map",
            "--no-li-basis"]  # the plug-in: a Laplace polish takes both fits to the same mode
    assert main([*args, "--n-iter", "20"]) == 0
    good = _files(out)
    assert set(good) == {"model.pt", "stress_map.png", "forces.png"}
    capsys.readouterr()
    assert main([*args, "--n-iter", "2"]) == 1
    err = capsys.readouterr().err
    assert "holds a better fit of these data with these options" in err and _files(out) == good
    drawing = plotting.plot_forces
    monkeypatch.setattr(plotting, "plot_forces", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("no display")))
    assert main([*args, "--n-iter", "2", "--replace"]) == 3
    assert _files(out) == good and not [p for p in out.iterdir() if ".tmp" in p.name]
    monkeypatch.setattr(plotting, "plot_forces", drawing)
    assert main([*args, "--n-iter", "2", "--replace"]) == 0
    assert all(_files(out)[k] != good[k] for k in good)
    # a 3-D model's file in the folder (InverseRFT.load reads it as the 3-D model): replaced, said (was: KeyError)
    import torch

    import irft_torch as irft
    from irft_torch.gp.inverse3d import InverseRFT3D
    from irft_torch.rft import CToe, FourierStressMap, Mesh, contacts_3d, forces_3d

    t = torch.linspace(0, 1, 8, dtype=torch.float64)
    o, z = torch.ones_like(t), torch.zeros_like(t)
    c3 = contacts_3d(Mesh.from_toe(CToe(0.02, 0.01, n_segments=4), n_across=2).to(dtype=torch.float64),
                     torch.stack([0.02 * o, 0.01 * o, -0.01 * o], -1), torch.stack([z, z, 0.5 * o], -1), surface=0.0,
                     position=torch.stack([0.02 * t, z, -0.015 - 0.01 * t], -1))
    irft.InverseRFT(c3, forces_3d(FourierStressMap.generic(0.5, 0.6), c3), hyper_posterior="map",
                    li_basis=False).save(out / "model.pt")
    capsys.readouterr()
    assert main([*args, "--n-iter", "2"]) == 0
    assert "(a fit of a 3-D model)" in capsys.readouterr().out
    assert not isinstance(irft.InverseRFT.load(out / "model.pt"), InverseRFT3D)
