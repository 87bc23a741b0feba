"""The Laplace posterior's second importance-sampling stage, on the calibration harness' cases.

Data: simulated (the harness' cases). Run time: not timed whole; its first 4 cases 67 s (--limit 4, 2 cores,
2026-12-03) of the 30 in the main set (6 held-out, 16 held-out-2).

Each case (``studies.calibration``: a medium, a motion, a noise level, a seed) is fitted once; the plug-in, the
Laplace posterior with its first stage only (``adapt=False``) and with the adaptive second stage (the default)
are each scored from that same fit and the same first-stage proposals (``studies.calibration.score``: 95 %
coverage of the truth over the canonical square, the percentile among the fit's own posterior draws). Rows go
to ``laplace_stages_<SET>.csv`` as each case finishes (a rerun skips the cases there); the summary per family
and per motion (mean 95 % coverage, share overconfident beyond chance, x / z), the fits where stage 2 was
drawn, k-hat above 0.7 and the median ESS are printed.

    python experiments/calibration/laplace_stages.py --set main|held-out|held-out-2 [--limit N] [--out DIR]

``main``: every family x motion at seed 0, and the generic-scaled family at seeds 0 and 1 (30 fits);
``held-out`` / ``held-out-2``: the harness' two held-out sets at seeds 0 and 1 (6 and 16 fits).
"""

from __future__ import annotations

import argparse
import copy
import csv
import statistics
import sys
import warnings
from pathlib import Path

import torch

from irft_torch import InverseRFT
from irft_torch.studies.calibration import medium, motion, score, simulate

sys.path.insert(0, str(Path(__file__).parent))
from calibration_harness import append_rows, cases, coverage_table  # noqa: E402


def case_list(which: str) -> list:
    if which == "main":
        return [c for c in cases(False, 2, False) if c.seed == 0 or c.family == "scaled"]
    return cases(which == "held-out", 2, False, held_out_2=which == "held-out-2")


def run(case) -> list[dict]:
    truth, _ = medium(case.family, case.seed)
    c = motion(case.kind, case.seed)
    f = simulate(truth, c, case.noise, case.seed)
    fitted = InverseRFT(c, f, hyper_posterior="map")
    fitted.fit(n_iter=300, progress=False)
    base = {"family": case.family, "motion": case.kind, "seed": case.seed, "noise": case.noise}
    rows = [{**base, "posterior": "map", "ess": "", "khat": "", "n": "", **score(fitted, truth, 41, 200, case.seed)}]
    for name, adapt in (("laplace_stage1", False), ("laplace", True)):
        m = copy.deepcopy(fitted)
        hp = m.fit_hyper_posterior("laplace", generator=torch.Generator().manual_seed(case.seed), adapt=adapt)
        rows.append({**base, "posterior": name, "ess": round(hp.ess, 2), "khat": round(hp.khat, 3),
                     "n": hp.n_proposals, **score(m, truth, 41, 200, case.seed)})
    return rows


def summary(rows: list[dict]) -> str:
    lines = coverage_table(rows, ("map", "laplace_stage1", "laplace"))
    one = [r for r in rows if r["posterior"] == "laplace_stage1"]
    two = [r for r in rows if r["posterior"] == "laplace"]
    lines += ["", f"stage 2 drawn in {sum(int(r['n']) > int(o['n']) for r, o in zip(two, one))} of {len(two)} fits; "
              f"k-hat > 0.7: {sum(float(r['khat']) > 0.7 for r in one)} -> {sum(float(r['khat']) > 0.7 for r in two)}; "
              f"median ESS {statistics.median(float(r['ess']) for r in one):.1f} -> "
              f"{statistics.median(float(r['ess']) for r in two):.1f}"]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--set", choices=("main", "held-out", "held-out-2"), default="main")
    p.add_argument("--limit", type=int, default=None, help="only the first N cases (a smoke run)")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "results")
    args = p.parse_args(argv)
    torch.set_default_dtype(torch.float64)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"laplace_stages_{args.set}.csv"
    rows = list(csv.DictReader(path.open())) if path.exists() else []
    done = {(r["family"], r["motion"], int(r["seed"])) for r in rows}
    todo = [c for c in case_list(args.set)[:args.limit] if (c.family, c.kind, c.seed) not in done]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the HyperPosteriorWarning of stage 1 alone is expected here
        for case in todo:
            new = run(case)
            append_rows(path, new)
            rows += [{k: str(v) for k, v in r.items()} for r in new]
            print(case.key, [(r["posterior"], r["khat"], round(float(r["cover95_x"]), 3),
                              round(float(r["cover95_z"]), 3)) for r in new], flush=True)
    print(summary(rows))


if __name__ == "__main__":
    main()
