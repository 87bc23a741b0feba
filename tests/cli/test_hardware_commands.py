"""irft record / ingest / fit from the command line: the simulated leg end to end, and the live
recorder on python-can's virtual bus."""

import errno
import threading

import can
import matplotlib.image
import numpy as np
import pytest
import torch
from hardware.closed_form import ik_coaxial, torques_coaxial

import irft_torch as irft
from irft_torch.cli import main
from irft_torch.hardware import FakeODrive, SimulatedLeg, load_dataset, read_log

PLUG_IN = ["--hyper-posterior", "map", "--no-li-basis"]  # the pipeline, not the posterior (tests/gp test that)


def test_record_simulate_ingest_fit(tmp_path, capsys):
    """record --simulate -> ingest -> fit with no hardware. The logged currents are checked against
    the closed-form five-bar statics, and the dataset's forces against the forward RFT of a flat
    plate dragged at 5 cm (generic map x 1.5 in z: F = (-0.136, 0.375 x 1.5) x depth x area)."""
    out = tmp_path / "trial.log"
    rc = main(["record", "--simulate", "--out", str(out), "--toe", "I", "--length", "0.04", "--path", "rectangle",
               "--shear", "0.2", "--rate", "50", "--scale-z", "1.5"])
    assert rc == 0
    text = capsys.readouterr().out
    assert f"wrote {out}" in text and f"wrote {tmp_path / 'trial_air.log'}" in text
    # the logged currents are what the closed-form statics say (k_t 0.0973, l1 0.15, l2 0.30, hips 0.25 m up)
    data = read_log(out)
    t_iq, iq0 = data.motors[0].arrays("iq")
    _, enc0 = data.motors[0].arrays("encoder")
    _, iq1 = data.motors[1].arrays("iq")
    assert data.issues == [] and len(t_iq) > 100
    # toe (leg frame) from encoder angles via closed-form FK of the coaxial leg, then the currents
    _, enc1 = data.motors[1].arrays("encoder")
    q1, q2 = 2 * np.pi * enc0[:, 0], 2 * np.pi * enc1[:, 0]
    th, g = (q1 + q2) / 2, (q1 - q2) / 2
    L = 0.15 * np.cos(g) + np.sqrt(0.30**2 - 0.15**2 * np.sin(g) ** 2)
    x, z = L * np.sin(th), -L * np.cos(th)
    shear = np.abs(z + 0.25 + 0.05) < 1e-6  # toe 5 cm deep
    shear &= np.roll(shear, 1) & np.roll(shear, -1)  # not at the corners, where the motion turns
    assert shear.sum() > 100
    F = (-0.136 * 5 * 3.2, 0.375 * 1.5 * 5 * 3.2)  # flat 4 cm x 0.8 cm plate, 5 cm deep, moving +x
    want = np.array([torques_coaxial(xx, zz, F, 0.15, 0.30) for xx, zz in zip(x[shear], z[shear])]) / 0.0973
    np.testing.assert_allclose(np.stack([iq0[shear, 1], iq1[shear, 1]], -1), want, rtol=2e-3, atol=2e-3)
    assert ik_coaxial(x[0], z[0], 0.15, 0.30) == pytest.approx((q1[0], q2[0]), abs=1e-6)

    ds_path = tmp_path / "ds"
    rc = main(["ingest", str(out), "--air", str(tmp_path / "trial_air.log"), "--out", str(ds_path), "--toe", "I",
               "--length", "0.04", "--filter-window", "1"])
    assert rc == 0
    text = capsys.readouterr().out
    assert f"wrote {tmp_path / 'ds.npz'}:" in text and "masked: none" in text
    ds = load_dataset(tmp_path / "ds.npz")
    deep = ((ds.toe_position[:, 1] + 0.05).abs() < 1e-6).numpy()
    deep &= np.roll(deep, 1) & np.roll(deep, -1)
    np.testing.assert_allclose(ds.forces[deep].numpy(), np.tile(F, (int(deep.sum()), 1)), atol=2e-3)

    rc = main(["fit", str(tmp_path / "ds.npz"), "--out", str(tmp_path / "fit"), "--n-iter", "5",
               "--max-samples", "60", "--no-progress", *PLUG_IN])
    assert rc == 0
    for f in ("stress_map.png", "forces.png"):
        img = matplotlib.image.imread(tmp_path / "fit" / f)
        assert img.shape[0] > 200 and img.shape[1] > 200 and img.std() > 0.01  # a drawn figure, not blank
    model = irft.InverseRFT.load(tmp_path / "fit" / "model.pt")
    idx = torch.as_tensor(np.nonzero(deep)[0][::10])
    pred = model.predict_forces(ds.contacts[idx]).mean
    # the fitted model reproduces the drag and lift it was trained on (a zero map is 2.7 / 9 N off)
    assert pred.shape == (len(idx), 2) and bool(((pred - torch.tensor(F)).abs() < 1.0).all()), pred

    # two datasets fit together: the model holds both recordings' samples, on the backend asked for
    rc = main(["fit", str(tmp_path / "ds.npz"), str(tmp_path / "ds.npz"), "--out", str(tmp_path / "fit2"),
               "--n-iter", "3", "--method", "pairs", "--no-progress", *PLUG_IN])
    assert rc == 0 and "2 datasets, " in capsys.readouterr().out
    both = irft.InverseRFT.load(tmp_path / "fit2" / "model.pt")
    assert len(both.train_contacts) == 2 * len(ds) and both.method == "pairs"
    # MAP by default; --priors none is the paper's plain likelihood (no prior term in the loss)
    assert model.priors == "physical" and both.priors == "physical"
    rc = main(["fit", str(tmp_path / "ds.npz"), "--out", str(tmp_path / "fit3"), "--n-iter", "2",
               "--max-samples", "60", "--priors", "none", "--no-progress", *PLUG_IN])
    plain = irft.InverseRFT.load(tmp_path / "fit3" / "model.pt")
    assert rc == 0 and plain.priors is None and float(plain.backend.log_prior()) == 0.0


def test_ingest_truncated_log_is_a_clear_error(tmp_path, capsys):
    sim = SimulatedLeg(irft.rft.IToe(0.08, 0.008), irft.rft.FourierStressMap.generic(), rate=50)
    sim.run(irft.rft.rectangle_path(0.05, 0.30, 0.05, start=(-0.15, 0.0)), tmp_path / "t.log")
    text = (tmp_path / "t.log").read_text()
    kept = text[: len(text) // 2].rsplit("\n", 1)[0]
    last_t = float(kept.rsplit("\n", 1)[-1].split()[0].strip("()"))
    (tmp_path / "t.log").write_text(kept + "\n(17000")
    rc = main(["ingest", str(tmp_path / "t.log"), "--out", str(tmp_path / "ds.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "t.log: damaged or truncated: the last line has no line end" in err
    assert not (tmp_path / "ds.npz").exists() and err.count("\n") == 1
    rc = main(["ingest", str(tmp_path / "t.log"), "--out", str(tmp_path / "ds.npz"), "--on-error", "warn"])
    assert rc == 0
    ds = load_dataset(tmp_path / "ds.npz")
    full = read_log(tmp_path / "t.log", on_error="warn")
    # what was kept: everything up to the last complete line, nothing after it
    assert ds.time.max().item() <= last_t and ds.time.max().item() > last_t - 0.05
    assert len(full.motors[0].times["iq"]) > 100


def test_record_on_a_virtual_bus(tmp_path, capsys):
    threads_before = threading.active_count()
    drives = [FakeODrive(can.Bus(channel="irft-cli-rec", interface="virtual"), n) for n in (0, 1)]
    for d in drives:
        d.set_state(0.0, 0.0, 1.0 + d.node)
        d.start()
    try:
        rc = main(["record", "--interface", "virtual", "--channel", "irft-cli-rec", "--out",
                   str(tmp_path / "r.asc"), "--duration", "0.2", "--rate", "100"])
    finally:
        for d in drives:
            d.stop()
            d.bus.shutdown()
    assert rc == 0
    n = int(capsys.readouterr().out.split("wrote ")[1].split()[0])
    data = read_log(tmp_path / "r.asc")
    v0, v1 = data.motors[0].arrays("iq")[1], data.motors[1].arrays("iq")[1]
    assert n == len(v0) + len(v1) and len(v0) >= 3 and (v0[:, 1] == 1.0).all() and (v1[:, 1] == 2.0).all()
    assert threading.active_count() == threads_before


def test_record_warns_when_no_controller_answers(tmp_path, capsys):
    rc = main(["record", "--interface", "virtual", "--channel", "irft-nobody-here", "--out",
               str(tmp_path / "r.log"), "--duration", "0.1"])
    err = capsys.readouterr().err
    assert rc == 1 and "warning: no controller answered on virtual channel 'irft-nobody-here'" in err
    # one controller of two: named
    drive = FakeODrive(can.Bus(channel="irft-one-node", interface="virtual"), 0)
    drive.start()
    try:
        rc = main(["record", "--interface", "virtual", "--channel", "irft-one-node", "--out",
                   str(tmp_path / "r.log"), "--duration", "0.1"])
    finally:
        drive.stop()
        drive.bus.shutdown()
    assert rc == 1 and "node(s) [1] sent no frames (nodes heard: [0])" in capsys.readouterr().err


def test_socketcan_unavailable_gives_a_hint(tmp_path, capsys, monkeypatch):
    def no_socketcan(*a, **k):
        raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")

    monkeypatch.setattr(can, "Bus", no_socketcan)
    rc = main(["record", "--out", str(tmp_path / "r.log"), "--duration", "0.1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert "argument --interface: socketcan is not available on this machine" in err and "--simulate" in err
    assert not (tmp_path / "r.log").exists()


def test_record_help_exits_zero():
    with pytest.raises(SystemExit) as e:
        main(["record", "--help"])
    assert e.value.code == 0


def test_record_mit_mode_listens_and_ingest_reads_it(tmp_path, capsys):
    """MIT mode: record sends nothing (a poll would be a command) and logs the motors' replies; the
    values come back through read_log as sent (AK80-9 codes, within one code)."""
    from irft_torch.hardware import encode_mit_reply

    stop = threading.Event()
    sent = []
    motor_bus = can.Bus(channel="irft-mit-rec", interface="virtual")
    heard = []

    def motors():
        k = 0
        while not stop.is_set():
            for node, pos in ((1, 0.5), (2, -0.5)):
                motor_bus.send(encode_mit_reply(node, pos + 0.001 * k, 0.0, 1.0 * node))
                sent.append(node)
            while (m := motor_bus.recv(timeout=0)) is not None:
                heard.append(m)
            k += 1
            stop.wait(0.005)

    th = threading.Thread(target=motors, daemon=True)
    th.start()
    try:
        rc = main(["record", "--interface", "virtual", "--channel", "irft-mit-rec", "--protocol", "mit",
                   "--out", str(tmp_path / "m.log"), "--duration", "0.2"])
    finally:
        stop.set()
        th.join(1.0)
        motor_bus.shutdown()
    out = capsys.readouterr().out
    assert rc == 0 and "listening only" in out and heard == []  # nothing was sent to the motors
    data = read_log(tmp_path / "m.log", protocol="mit", mit_model="AK80-9")
    for node, torque in ((1, 1.0), (2, 2.0)):
        _, enc = data.motors[node].arrays("encoder")
        _, tq = data.motors[node].arrays("torque")
        assert len(tq) >= 5 and np.allclose(tq[:, 1], torque, atol=36 / 4095)
        assert np.all(np.abs(np.diff(enc[:, 0] * 2 * np.pi) - 0.001) < 0.0015)


def test_record_simulate_several_trials_then_ingest(tmp_path, capsys):
    rc = main(["record", "--simulate", "--trials", "2", "--out", str(tmp_path / "t.blf"), "--toe", "I", "--length",
               "0.04", "--path", "rectangle", "--shear", "0.04", "--penetration", "0.02", "--extraction", "0.02",
               "--rate", "40", "--current-noise", "0.05", "--seed", "3"])
    assert rc == 0, capsys.readouterr().err
    names = [tmp_path / "t_1.blf", tmp_path / "t_2.blf", tmp_path / "t_air.blf"]
    assert all(p.stat().st_size > 200 for p in names)
    capsys.readouterr()
    rc = main(["ingest", str(names[0]), str(names[1]), "--air", str(names[2]), "--out", str(tmp_path / "ds.npz"),
               "--toe", "I", "--length", "0.04"])
    assert rc == 0, capsys.readouterr().err
    ds = load_dataset(tmp_path / "ds.npz")
    # the plate at 2 cm: F_z = 0.375 x 2 x 3.2 = 2.4 N while dragged (two noisy trials averaged)
    deep = ((ds.toe_position[:, 1] + 0.02).abs() < 1e-4).numpy()
    assert deep.sum() > 10 and abs(float(ds.forces[deep, 1].mean()) - 2.4) < 0.1


def test_record_simulate_prints_an_ingest_command_that_matches_the_simulation(tmp_path, capsys, monkeypatch):
    """The 'next: irft ingest ...' line of record --simulate, run as printed, builds the dataset of
    the toe and nodes that were simulated. It used to leave out --width, --segments, --nodes (a
    2 cm wide plate ingested as the default 0.8 cm one: every contact area 2.5 times too small).
    By hand: a 4 cm x 2 cm plate 5 cm deep has depth x area = 5 x 4 x 2 = 40 cm^3 in its 6 segments."""
    monkeypatch.chdir(tmp_path)
    rc = main(["record", "--simulate", "--out", "t.log", "--toe", "I", "--length", "0.04", "--width", "0.02",
               "--segments", "6", "--nodes", "3", "5", "--path", "rectangle", "--shear", "0.1", "--rate", "50"])
    assert rc == 0
    hint = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("next: irft ingest "))
    assert main(hint.split()[2:] + ["--no-statistics"]) == 0, capsys.readouterr().err
    ds = load_dataset(tmp_path / "dataset.npz")
    deep = ((ds.toe_position[:, 1] + 0.05).abs() < 1e-6).numpy()
    assert deep.sum() > 10 and ds.contacts.n_segments == 6
    np.testing.assert_allclose(ds.contacts.weight_z[deep].sum(1).numpy(), 40.0, rtol=1e-6)
