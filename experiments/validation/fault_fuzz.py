"""Real-world log faults against an oracle: 10^3 edited logs per class through ``irft ingest``.

Data: simulated leg logs, edited. Run time: about 9 min (538 s, 2 cores, 2026-12-03; `--n 100`: 58 s).

    python experiments/validation/fault_fuzz.py [--n 1000] [--seed 0] [--out experiments/results]

A simulated leg (``hardware.SimulatedLeg``, C-toe, the paper's cubic gait, noise-free, 100 Hz) runs a
trial in sand and a run in air; its sand is known (the generic map), so every force ``irft ingest``
writes can be checked against RFT of the dataset's own contacts (``rft.forces(generic, contacts)``;
the clean logs: 6e-5 N off, with ``--filter-window 1``). Each case edits the candump text of the
trial or of the air run the way a lab's logs go wrong, then ingests it:

- clock restart: a second recording appended, its clock started again (relative times from 0 to
  5 s), or with absolute times 2 s to an hour later (the leg back at the start); sometimes cut short;
- clock step back: the clock set back by 0.15 s to 10 s mid-log (an NTP step);
- clock jump ahead: set ahead by 2 s to a day mid-log, or from relative to absolute time;
- channel mix: another leg's log on another CAN channel with the same node ids merged in by time
  (``candump -L any``), with ``--channel`` given or not; or with other node ids (no clash);
- series cut short: one node's encoder or current frames end early (a pulled connector);
- encoder re-zero: one node's encoder positions shifted by 0.02 to 0.5 turns from some time on.

Outcomes: **correct** (a dataset within 0.05 N of the oracle everywhere, the edit reported, every
recording used, no sample dropped unsaid), **refused** (exit 2, one line naming the real cause),
and the failures: **silent-wrong** (a dataset off the oracle), **lost** (a recording or samples
dropped without a word), **wrong cause** (refused, blaming something else), **traceback** (exit 3 or
an exception). Writes fault_fuzz.md under --out.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import struct
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

CLASSES = ("clock restart", "clock step back", "clock jump ahead", "channel mix", "series cut short",
           "encoder re-zero")
FAILURES = ("silent-wrong", "lost", "wrong cause", "traceback")
TOL = 0.05  # N: the oracle's bound on a correct dataset
# what a refusal must name for each class (the real cause), and what a handled case must have said
CAUSE = {"clock restart": r"recording|covers", "clock step back": r"clock", "clock jump ahead": r"clock",
         "channel mix": r"CAN channel", "series cut short": r"stops|covers|usable|node \d",
         "encoder re-zero": r"re-zeroed"}
SAID = {"clock restart": r"holds \d+ recordings", "clock step back": r"clock steps back",
        "clock jump ahead": r"clock jumps", "channel mix": r"", "series cut short": r"stops .* before",
        "encoder re-zero": r""}


@dataclass
class Case:
    cls: str
    trial: list  # candump lines [t, channel, rest] of each trial log
    air: list
    args: list = field(default_factory=list)
    recordings: int = 1  # trials in sand the dataset must be built from (nothing lost)
    what: str = ""


def _lines(path: Path, channel: str = "can0") -> list:
    out = []
    for ln in path.read_text().splitlines():
        m = re.match(r"\((\S+)\) (\S+) (.*)", ln)
        out.append([float(m[1]), channel, m[3]])
    return out


def _dump(lines: list, path: Path) -> None:
    path.write_text("".join(f"({t:.6f}) {ch} {rest}\n" for t, ch, rest in lines))


def base_logs(folder: Path) -> dict:
    """The clean trial and air run (channel can0), and another leg's trial in looser sand (for mixes)."""
    from irft_torch import rft
    from irft_torch.hardware import SimulatedLeg

    torch.set_default_dtype(torch.float64)
    path = rft.spline_path([(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)], n_steps=200, speed=0.15)
    out = {}
    for name, medium, air in (("trial", rft.FourierStressMap.generic(), False),
                              ("air", rft.FourierStressMap.generic(), True),
                              ("other", rft.FourierStressMap.poppy_seeds_loose(), False)):
        sim = SimulatedLeg(rft.CToe(0.02, 0.008), medium, rate=100)
        sim.run(path, folder / f"{name}.log", in_air=air)
        out[name] = _lines(folder / f"{name}.log")
    return out


def _shift_pos(rest: str, d: float) -> str:
    ident, data = rest.split("#", 1)
    data, *flag = data.split(" ")
    p, v = struct.unpack("<ff", bytes.fromhex(data))
    return f"{ident}#{struct.pack('<ff', p + d, v).hex().upper()}" + (f" {flag[0]}" if flag else "")


def edit(cls: str, rng: np.random.Generator, base: dict) -> Case:
    trial, air, other = ([list(x) for x in base[k]] for k in ("trial", "air", "other"))
    t0 = trial[0][0]
    target = "trial" if rng.random() < 0.6 else "air"
    logs = {"trial": trial, "air": air}
    lines = logs[target]
    n = len(lines)
    k = int(rng.integers(n // 5, 4 * n // 5))
    case = Case(cls, trial, air, what=target)
    if cls == "clock restart":
        if rng.random() < 0.6:  # relative times: each recording's clock starts near 0
            begin = rng.uniform(0, 5)
            first = [[x - lines[0][0] + begin, c, r] for x, c, r in lines]
            start = rng.uniform(0, 1)
        else:  # absolute times: the next recording starts later, the leg back at its start
            first = lines
            start = lines[-1][0] + rng.uniform(2, 3600)
        second = [[x - lines[0][0] + start, c, r] for x, c, r in lines]
        if rng.random() < 0.3:  # the second recording cut short
            second = second[: int(rng.integers(n // 10, n))]
        logs[target] = first + second
        case.recordings = 2 if target == "trial" else 1
        case.what += f", second recording of {len(second)} frames"
    elif cls == "clock step back":
        d = float(rng.uniform(0.15, 10.0))
        logs[target] = lines[:k] + [[x - d, c, r] for x, c, r in lines[k:]]
        case.what += f", {d:.2f} s at frame {k}"
    elif cls == "clock jump ahead":
        kind = rng.integers(3)
        if kind == 0:
            d = float(rng.uniform(2.0, 600.0))
            logs[target] = lines[:k] + [[x + d, c, r] for x, c, r in lines[k:]]
        elif kind == 1:
            logs[target] = lines[:k] + [[x + 86400.0, c, r] for x, c, r in lines[k:]]
        else:  # relative times, then absolute ones
            logs[target] = [[x - t0, c, r] for x, c, r in lines[:k]] + [[x, c, r] for x, c, r in lines[k:]]
        case.what += f", kind {kind} at frame {k}"
    elif cls == "channel mix":
        mode = rng.integers(3)
        other_ids = mode == 2
        extra = []
        lag = rng.uniform(-0.5, 0.5)
        for x, c, r in other:
            if other_ids:  # the other leg's nodes 2 and 3: no clash with nodes 0 and 1
                ident, rest = r.split("#", 1)
                r = f"{(int(ident, 16) + (2 << 5)):03X}#{rest}"
            extra.append([x - other[0][0] + lines[0][0] + lag, "can1", r])
        logs[target] = sorted(lines + extra, key=lambda ln: ln[0])
        if mode == 1:
            case.args = ["--channel", "can0"]
        case.what += ["", ", --channel can0", ", other node ids"][mode]
    elif cls == "series cut short":
        node, group = int(rng.integers(2)), ("009", "014")[int(rng.integers(2))]
        ident = f"{int(group, 16) + (node << 5):03X}#"
        cut = lines[k][0]
        logs[target] = [ln for ln in lines if not (ln[2].startswith(ident) and ln[0] > cut)]
        case.what += f", id {ident} after frame {k}"
    elif cls == "encoder re-zero":
        node = int(rng.integers(2))
        d = float(rng.uniform(0.02, 0.5)) * (1 if rng.random() < 0.5 else -1)
        ident = f"{0x09 + (node << 5):03X}#"
        cut = lines[k][0]
        logs[target] = [[x, c, _shift_pos(r, d) if r.startswith(ident) and x > cut else r] for x, c, r in lines]
        case.what += f", node {node} by {d:+.3f} turns after frame {k}"
    case.trial, case.air = logs["trial"], logs["air"]
    return case


def run_case(case: Case, folder: Path, medium) -> tuple[str, str]:
    """(outcome, the command's output) of ingesting one edited case."""
    from irft_torch import rft
    from irft_torch.cli import main
    from irft_torch.hardware import load_dataset

    _dump(case.trial, folder / "t.log")
    _dump(case.air, folder / "a.log")
    out = folder / "ds.npz"
    out.unlink(missing_ok=True)
    so, se = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
            rc = main(["ingest", str(folder / "t.log"), "--air", str(folder / "a.log"), "--out", str(out),
                       "--filter-window", "1", "--no-statistics", *case.args])
    except BaseException as e:  # noqa: BLE001 - anything escaping main is a failure of this library
        return "traceback", f"{type(e).__name__}: {e}"
    text = so.getvalue() + se.getvalue()
    if rc == 3 or "Traceback" in text:
        return "traceback", text
    if rc != 0:
        err = [ln for ln in se.getvalue().splitlines() if ": error: " in ln]
        ok = len(err) == 1 and re.search(CAUSE[case.cls], err[0])
        return ("refused" if ok else "wrong cause"), text
    ds = load_dataset(out)
    truth = rft.forces(medium, ds.contacts)
    if not float((ds.forces - truth).abs().max()) <= TOL:
        return "silent-wrong", text
    m = re.search(r"from (\d+) run\(s\) in sand", text)
    used = int(m[1]) if m else 1
    if used < case.recordings or (SAID[case.cls] and not re.search(SAID[case.cls], text)):
        return "lost", text
    return "correct", text


def run(n: int, seed: int = 0, folder: Path | None = None, classes=CLASSES, verbose: bool = False,
        base: dict | None = None) -> dict:
    """{class: Counter(outcome)} over ``n`` edited logs per class (``seed`` fixes the edits; ``base``: the
    clean logs, default ``base_logs``)."""
    from irft_torch import rft

    torch.set_default_dtype(torch.float64)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(folder or tmp)
        base = base or base_logs(folder)
        medium = rft.FourierStressMap.generic()
        counts = {}
        for c_i, cls in enumerate(classes):
            rng = np.random.default_rng([seed, c_i])
            counts[cls] = Counter()
            for _ in range(n):
                case = edit(cls, rng, base)
                outcome, text = run_case(case, folder, medium)
                counts[cls][outcome] += 1
                if verbose and outcome in FAILURES:
                    print(f"{cls} ({case.what}): {outcome}\n{text[-800:]}")
        return counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1000, help="edited logs per class (default 1000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="experiments/results")
    ap.add_argument("--verbose", action="store_true", help="print every failure's output")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    counts = run(a.n, a.seed, verbose=a.verbose)
    took = time.perf_counter() - t0
    cols = ("correct", "refused", *FAILURES)
    rows = [f"| {cls} | " + " | ".join(str(counts[cls][c]) for c in cols) + " |" for cls in counts]
    text = "\n".join([
        "# Real-world log faults against the oracle (experiments/validation/fault_fuzz.py)", "",
        f"`python experiments/validation/fault_fuzz.py --n {a.n} --seed {a.seed}`: {a.n} edited logs per class through "
        f"`irft ingest`, {took:.0f} s. Correct: within {TOL} N of RFT of the dataset's own contacts in the known "
        "sand, the edit reported, nothing dropped unsaid; refused: one line naming the real cause.", "",
        "| class | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|", *rows, ""])
    print(text)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fault_fuzz.md").write_text(text)
    bad = sum(counts[cls][f] for cls in counts for f in FAILURES)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
