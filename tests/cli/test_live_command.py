"""``irft live --simulate``: as a newcomer types it, and as scripts use it (--out DIR --json, Ctrl-C)."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import can

from irft_torch.cli import main
from irft_torch.gp import InverseRFT

FAST = ["--warmup", "2", "--n-iter", "20"]


def frames_in(path):
    return sum(1 for _ in can.LogReader(str(path)))


def test_live_simulate_json_writes_log_snapshots_and_a_line_per_stance(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["live", "--simulate", "--strides", "5", "--out", str(out), "--json", *FAST]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    stances = [x for x in lines if x["event"] == "stance"]
    assert [x["stance"] for x in stances] == [1, 2, 3, 4, 5]
    assert all(x["used"] for x in stances) and stances[-1]["updates"] == 4  # the start model on 2, then 3 updates
    # the walk's end is the source stopping on purpose, not a motor falling silent
    assert not any("stale" in x.get("message", "") for x in lines), [x for x in lines if x["event"] != "stance"]
    end = lines[-1]
    assert end["event"] == "end" and end["frames"] == frames_in(out / "frames.blf") == 5 * 300 * 4 + 2 * 15
    InverseRFT.load(out / "model.pt")


def test_live_simulate_prints_a_converging_estimate(tmp_path, capsys):
    # no --out: the snapshots due every 1 ms are not written (no file to write them to), and nothing fails
    assert main(["live", "--simulate", "--strides", "6", "--print-every", "2", "--quiet", "--snapshot-period", "0.001",
                 *FAST]) == 0
    printed = [x for x in capsys.readouterr().out.splitlines() if x.startswith("stance ")]
    assert printed[0].startswith("stance 2: map = generic x (") and len(printed) == 3
    z_std = [float(re.search(r"\(\S+ ± \S+, \S+ ± (\S+)\)", x)[1]) for x in printed]
    assert z_std[-1] < z_std[0]  # the interval narrows


def _interruptible() -> None:
    """The child's SIGINT as a terminal gives it: a suite started as a background job (``cmd &``, CI scripts)
    passes SIGINT on ignored, and Python then installs no KeyboardInterrupt handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_sigint_ends_it_cleanly_with_a_readable_log_and_snapshot(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "irft_torch.cli", "live", "--simulate", "--strides", "1000",
                             "--out", str(out), "--json", "--snapshot-period", "0.2", *FAST],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, preexec_fn=_interruptible)
    stances = 0
    deadline = time.monotonic() + 120
    while stances < 4 and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        stances += json.loads(line)["event"] == "stance"
    assert stances == 4, proc.stderr.read()
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rest, err = proc.communicate(timeout=30)
    assert time.monotonic() - sent < 10
    assert proc.returncode in (0, 130), err
    assert json.loads(rest.splitlines()[-1])["event"] == "end"
    assert frames_in(out / "frames.blf") > 4 * 300 * 4
    InverseRFT.load(out / "model.pt")


def test_live_with_a_stored_air_run(tmp_path, capsys):
    """--air LOG: a log of the same strides in air (made here by the simulated leg in no medium, with the
    command's own toe and leg) is read and subtracted; a missing one is an error naming --air."""
    import uuid

    from irft_torch.cli import build_parser
    from irft_torch.cli.arguments import make_toe
    from irft_torch.cli.ingest import _leg_and_motors
    from irft_torch.hardware import WalkingLeg
    from irft_torch.rft import FourierStressMap

    a = build_parser().parse_args(["live", "--simulate"])
    leg, motors = _leg_and_motors(a)
    walker = WalkingLeg(make_toe(a), FourierStressMap.generic(0.0, 0.0), leg=leg, motors=motors,
                        hip_height=a.hip_height, rate=a.rate, firmware=a.firmware)
    channel = f"irft-air-cli-{uuid.uuid4().hex}-bus"  # no trailing digits: BLF holds a channel number < 2^16
    bus = can.Bus(channel=channel, interface="virtual")
    writer = can.Logger(str(tmp_path / "air.blf"))
    walker.walk(channel, 3, realtime=False)
    while (msg := bus.recv(0.0)) is not None:
        writer.on_message_received(msg)
    writer.stop()
    bus.shutdown()
    assert main(["live", "--simulate", "--strides", "4", "--json", "--air", str(tmp_path / "air.blf"), *FAST]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    stances = [x for x in lines if x["event"] == "stance"]
    assert len(stances) == 4 and all(x["used"] for x in stances)
    assert "samples with no air-run force near the toe" not in lines[-1]["counts"]  # the air run covers the walk
    assert main(["live", "--simulate", "--air", str(tmp_path / "missing.blf")]) != 0
    assert "--air" in capsys.readouterr().err
