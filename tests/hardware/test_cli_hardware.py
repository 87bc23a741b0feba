"""irft record / ingest / fit on the simulated leg, from the command line."""

import threading

import can
import numpy as np
import pytest
import torch

import irft_torch as irft
from irft_torch.cli import main
from irft_torch.hardware import FakeODrive, SimulatedLeg, load_dataset


def test_ingest_and_fit(tmp_path):
    sim = SimulatedLeg(irft.rft.CToe(0.04, 0.008), irft.rft.FourierStressMap.generic(1.0, 1.5),
                       friction=0.05, cogging=0.02, rate=50)
    path = irft.rft.rectangle_path(0.05, 0.30, 0.05, start=(-0.15, 0.0))
    truth = sim.run(path, tmp_path / "t0.log")
    sim.run(path, tmp_path / "air.log", in_air=True)
    rc = main(["ingest", str(tmp_path / "t0.log"), "--air", str(tmp_path / "air.log"), "--out",
               str(tmp_path / "ds.npz"), "--toe", "C", "--radius", "0.04", "--filter-window", "1"])
    assert rc == 0
    ds = load_dataset(tmp_path / "ds.npz")
    t = (ds.time - ds.time[0]).numpy()
    want = np.stack([np.interp(t, truth.time, truth.force[:, k]) for k in range(2)], -1)
    rng = truth.force.max(0) - truth.force.min(0)
    assert (np.abs(ds.forces.numpy() - want).max(0) / rng < 0.01).all()
    rc = main(["fit", str(tmp_path / "ds.npz"), "--out", str(tmp_path / "fit"), "--n-iter", "20",
               "--max-samples", "80", "--no-progress"])
    assert rc == 0
    for f in ("model.pt", "stress_map.png", "forces.png"):
        assert (tmp_path / "fit" / f).exists()
    model = irft.InverseRFT.load(tmp_path / "fit" / "model.pt")
    assert len(model.train_contacts) == 80


def test_ingest_truncated_log_is_a_clear_error(tmp_path, capsys):
    sim = SimulatedLeg(irft.rft.IToe(0.08, 0.008), irft.rft.FourierStressMap.generic(), rate=50)
    sim.run(irft.rft.rectangle_path(0.05, 0.30, 0.05, start=(-0.15, 0.0)), tmp_path / "t.log")
    text = (tmp_path / "t.log").read_text()
    (tmp_path / "t.log").write_text(text[: len(text) // 2].rsplit("\n", 1)[0] + "\n(17000")
    rc = main(["ingest", str(tmp_path / "t.log"), "--out", str(tmp_path / "ds.npz")])
    assert rc == 2 and "t.log: damaged or truncated: the last line has no line end" in capsys.readouterr().err
    rc = main(["ingest", str(tmp_path / "t.log"), "--out", str(tmp_path / "ds.npz"), "--on-error", "warn"])
    assert rc == 0 and load_dataset(tmp_path / "ds.npz").forces.shape[1] == 2


def test_record_on_a_virtual_bus(tmp_path):
    drives = [FakeODrive(can.Bus(channel="irft-cli-rec", interface="virtual"), n) for n in (0, 1)]
    for d in drives:
        d.set_state(0.0, 0.0, 1.0)
        d.start()
    try:
        rc = main(["record", "--interface", "virtual", "--channel", "irft-cli-rec", "--out",
                   str(tmp_path / "r.asc"), "--duration", "0.2", "--rate", "100"])
    finally:
        for d in drives:
            d.stop()
            d.bus.shutdown()
    assert rc == 0 and (tmp_path / "r.asc").stat().st_size > 100
    assert threading.active_count() >= 1 and torch.is_tensor(torch.zeros(1))
    with pytest.raises(SystemExit):
        main(["record", "--help"])
