"""Is a change worse than the reference beyond what the choice of held-out runs alone could make? Two runs of a
real-data study, paired run by run.

Data: two output folders of dem_validation.py or wheel_validation.py --study planar. Run time: about 3 s on two
dem_validation.py outputs (2 cores, 2026-12-03).

    python experiments/validation/compare_predictions.py REFERENCE CANDIDATE [--unit fold|run] [--models "I-RFT,..."]

REFERENCE and CANDIDATE are output folders (or the CSV files) of ``dem_validation.py`` (``dem_predictions.csv``)
or ``wheel_validation.py --study planar`` (``wheel_predictions.csv``), run with different settings on the same
data: e.g. the library's defaults against ``--li-basis --hyper-posterior laplace``. For every row (predictor)
both runs have (rows with the same errors in both, such as the baselines, are listed and left out), per split
or wheel, quantity and axis, it prints the two RMSEs, their difference (candidate -
reference: positive is worse) and its 95 % paired bootstrap interval (``irft_torch.metrics.rmse_difference``),
resampling whole held-out folds (``--unit fold``, the default: a fold's runs share one fit and their errors move
together; 8-9 folds here, so read an interval that barely excludes 0 as a hint) or single runs (``--unit
run``). "worse" marks a difference whose whole interval is above 0; "better" one wholly below.

Quantities: the DEM's held-out stress per depth through the origin (N/cm^3, one value per run) and its held-out
force samples (N, each run's samples pooled); the wheels' mean force per run (N). Nothing is refitted: the
CSVs hold each run's prediction and the measured value.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from irft_torch.metrics import rmse_difference

FILES = ("dem_predictions.csv", "wheel_predictions.csv")


def locate(path: Path) -> Path:
    """The predictions CSV in an output folder (or the file itself)."""
    if path.is_file():
        return path
    found = [path / f for f in FILES if (path / f).is_file()]
    if len(found) != 1:
        raise SystemExit(f"{path}: expected one of {', '.join(FILES)} there (run dem_validation.py or "
                         f"wheel_validation.py --study planar with --out {path}), found {len(found)}")
    return found[0]


def read_units(path: Path) -> dict:
    """{(split or wheel, model, quantity): {run: (fold, sse (2,), count)}} from one predictions CSV."""
    units: dict = defaultdict(dict)
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            f = lambda k: float(row[k])  # noqa: E731
            if "split" in row:  # DEM: the origin stress (one value per run) and the run's force samples
                if row["target"] != "origin":
                    continue
                key = (f"DEM {row['split']}-out", row["model"])
                err = np.array([f("pred_x") - f("truth_x"), f("pred_z") - f("truth_z")])
                units[key + ("stress [N/cm^3]",)][row["run"]] = (row["fold"], err**2, 1.0)
                units[key + ("force [N]",)][row["run"]] = (row["fold"], np.array([f("force_sse_x"),
                                                                               f("force_sse_z")]), f("force_n"))
            else:  # wheels: the run's mean force
                err = np.array([f("pred_x") - f("truth_x"), f("pred_z") - f("truth_z")])
                units[(f"{row['wheel']} wheel", row["model"], "force [N]")][row["run"]] = (row["fold"], err**2, 1.0)
    return units


def compare(reference: dict, candidate: dict, unit: str, models: list[str] | None) -> list[str]:
    lines = ["| set | row | quantity | axis | RMSE reference | RMSE candidate | difference (95 % interval) | |",
             "|---|---|---|---|---|---|---|---|"]
    same: list[str] = []
    for key in reference:
        if key not in candidate or (models and key[1] not in models):
            continue
        ref, cand = reference[key], candidate[key]
        runs = [r for r in ref if r in cand]
        if len(runs) != len(ref) or len(runs) != len(cand):
            raise SystemExit(f"{key}: the two runs held out different runs ({len(ref)} and {len(cand)}, "
                             f"{len(runs)} in common): not the same study")
        if not all(np.isfinite(ref[r][1]).all() and np.isfinite(cand[r][1]).all() for r in runs):
            continue  # a row one of the runs did not compute (NaN)
        sse_r = np.stack([ref[r][1] for r in runs])
        sse_c = np.stack([cand[r][1] for r in runs])
        if np.array_equal(sse_r, sse_c):
            same.append(f"{key[0]} {key[1]} ({key[2]})")
            continue
        count = np.array([ref[r][2] for r in runs])
        groups = [ref[r][0] for r in runs] if unit == "fold" else None
        d = rmse_difference(sse_c, sse_r, count=count, groups=groups)
        rr = np.sqrt(sse_r.sum(0) / count.sum())
        rc = np.sqrt(sse_c.sum(0) / count.sum())
        for a, axis in enumerate("xz"):
            lo, hi = float(d.low[a]), float(d.high[a])
            word = "worse" if lo > 0 else ("better" if hi < 0 else "")
            lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {axis} | {rr[a]:.4g} | {rc[a]:.4g} | "
                         f"{float(d.difference[a]):+.3g} ({lo:+.3g} .. {hi:+.3g}) | {word} |")
    if same:  # rows neither setting touches (the baselines): no difference to test
        lines += ["", "The same errors in both runs, left out: " + "; ".join(same) + "."]
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="compare_predictions.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reference", type=Path, help="output folder (or CSV) of the reference run")
    ap.add_argument("candidate", type=Path, help="output folder (or CSV) of the candidate run")
    ap.add_argument("--unit", default="fold", choices=("fold", "run"),
                    help="resample whole held-out folds (default) or single runs")
    ap.add_argument("--models", default="", help="comma-separated rows to compare (default: every row both have)")
    a = ap.parse_args(argv)
    ref, cand = locate(a.reference), locate(a.candidate)
    if ref.name != cand.name:
        raise SystemExit(f"{ref} and {cand} are predictions of different studies")
    models = [m.strip() for m in a.models.split(",") if m.strip()] or None
    lines = compare(read_units(ref), read_units(cand), a.unit, models)
    print(f"reference {ref}, candidate {cand}; resampled: whole {a.unit}s\n")
    print("\n".join(lines))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
