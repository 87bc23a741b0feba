"""Edited candump logs of the simulated leg (the ``sim_logs`` fixture) and ``irft ingest`` run on them:
what the fault tests share."""

import struct

from irft_torch.cli import main
from irft_torch.hardware import load_dataset


def dump(lines, path):
    """Write candump lines [t, channel, rest] to ``path``."""
    path.write_text("".join(f"({t:.6f}) {ch} {rest}\n" for t, ch, rest in lines))
    return path


def shifted(lines, dt, start=0):
    """The lines with dt added to every timestamp from index ``start`` on."""
    return [[t + dt if k >= start else t, c, r] for k, (t, c, r) in enumerate(lines)]


def shift_position(rest: str, d: float) -> str:
    """A Get_Encoder_Estimates frame's text with d turns added to its position."""
    ident, data = rest.split("#", 1)
    data, *flag = data.split(" ")
    p, v = struct.unpack("<ff", bytes.fromhex(data))
    return f"{ident}#{struct.pack('<ff', p + d, v).hex().upper()}" + (f" {flag[0]}" if flag else "")


def ingest(capsys, tmp_path, trial, air, *args, name="t"):
    """``irft ingest`` of the trial lines (a list of line lists: one log each) and the air lines, with
    --filter-window 1 (the oracle's setting). Returns (exit status, stdout, stderr, dataset or None)."""
    trials = [trial] if trial and isinstance(trial[0][0], float) else trial
    paths = [str(dump(t, tmp_path / f"{name}{k}.log")) for k, t in enumerate(trials)]
    air_path = dump(air, tmp_path / f"{name}_air.log")
    out = tmp_path / f"{name}.npz"
    out.unlink(missing_ok=True)
    capsys.readouterr()
    rc = main(["ingest", *paths, "--air", str(air_path), "--out", str(out), "--filter-window", "1",
               "--no-statistics", *args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err, (load_dataset(out) if rc == 0 else None)
