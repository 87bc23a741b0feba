"""The experiments' wall time against the engine of an earlier commit, in the same run: issue #12's
"dem_validation.py and irft reproduce at least 3x faster with the same tables".

Data: the DEM runs (--data DIR, not shipped; --only reproduce needs none) and a git checkout of the
reference commit. Run time: about 4 min.

    python experiments/benchmarks/bench_experiments.py --data ../shared/data/dem_plate_intrusion [--reference 25da515]
    python experiments/benchmarks/bench_experiments.py --only reproduce    # irft reproduce only (no data needed)

The reference commit (default 25da515: the engine when issue #12 was filed) is checked out into a
temporary git worktree (this needs the repository's history: a git clone, not an sdist). Each command
runs in a fresh process, one after the other (nothing else should run on the machine meanwhile):

  * DEM, the reference's own experiment script (8 leave-one-beta-out folds, I-RFT zero and physics
    mean, the plain GP, 150 Adam steps): on the reference engine as written (its ``method="exact"``,
    that engine's fastest), and on this engine with that argument replaced by ``priors=None`` (the
    library's default backend choice, ``method="auto"``, and the reference's model: the plain marginal
    likelihood, where this engine adds hyperparameter priors by default); the two tables are compared
    cell by cell;
  * ``irft reproduce``, the reference's (40 fits, one process) against this one's (52 fits, in one
    worker process per CPU: the same tables and more, with this engine's default priors, so other
    numbers), and against this one's ``--priors none`` (the reference's model, the plain marginal
    likelihood: the same tables, compared cell by cell); and the reference's study driver
    (``reproduce.py`` of that commit, serial, its fits given
    ``priors=None``: the same model) on this engine, which isolates the engine;
  * the current ``experiments/validation/dem_validation.py`` (17 folds, 6 models), for the record.

The data are read from --data and never copied.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


def run(cmd: list[str], pythonpath: Path, cwd: Path) -> float:
    """Wall seconds of ``cmd`` in a fresh process with ``irft_torch`` imported from ``pythonpath``."""
    env = {**os.environ, "PYTHONPATH": str(pythonpath), "PYTHONWARNINGS": "ignore"}
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}")
    return dt


def table_cells(path: Path) -> dict[tuple, float]:
    """Numeric cells of a CSV (key: the row's key columns (config, axis, noise, ...) and the column's
    name) or of a markdown file's table rows (key: row label, column index) -> value."""
    out = {}
    if path.suffix == ".csv":
        import csv

        rows = list(csv.reader(path.open()))
        head = rows[0]
        k = next(j for j, h in enumerate(head) if h not in ("config", "axis", "noise", "truth", "prior_mean"))
        for row in rows[1:]:
            for j in range(k, len(row)):
                try:
                    out[(*row[:k], head[j])] = float(row[j])
                except ValueError:
                    pass
        return out
    for line in path.read_text().splitlines():
        if not line.startswith("| ") or line.startswith("|---"):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        for j, c in enumerate(cells[1:], 1):
            m = re.fullmatch(r"(-?\d+(?:\.\d+)?)\s*%?", c)
            if m:
                out[(cells[0], j)] = float(m.group(1))
    return out


def compare(a: Path, b: Path) -> str:
    ca, cb = table_cells(a), table_cells(b)
    common = [k for k in ca if k in cb]
    if not common:
        return "no common table cells"
    rel = [abs(cb[k] - ca[k]) / max(abs(ca[k]), 1e-12) for k in common]
    worst = max(range(len(common)), key=rel.__getitem__)
    k = common[worst]
    return (f"{len(common)} common cells, median relative difference {sorted(rel)[len(rel) // 2]:.1%}, largest "
            f"{rel[worst]:.1%} ({', '.join(map(str, k))}: {ca[k]:g} vs {cb[k]:g})")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="bench_experiments.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--data", help="the DEM plate-intrusion folder (read, never copied; not needed with "
                                   "--only reproduce)")
    ap.add_argument("--reference", default="25da515", help="the commit whose engine is the reference")
    ap.add_argument("--skip-current-dem", action="store_true", help="do not time today's full DEM experiment")
    ap.add_argument("--only", choices=["all", "dem", "reproduce"], default="all",
                    help="time only the DEM experiments or only irft reproduce")
    a = ap.parse_args(argv)
    if a.data is None and a.only != "reproduce":
        ap.error("--data is needed (the DEM plate-intrusion folder) unless --only reproduce")
    data = str(Path(a.data).resolve()) if a.data else ""
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        wt = tmp / "reference"
        p = subprocess.run(["git", "worktree", "add", "--detach", str(wt), a.reference], cwd=ROOT,
                           capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"cannot check out {a.reference} (needs the git history): {p.stderr.strip()}")
        try:
            rows = []
            if a.only in ("all", "dem"):
                # DEM: the reference's script, on its engine and on this one (method: the library default)
                old_script = (wt / "experiments" / "dem_validation.py").read_text()
                # this engine's default backend choice; the reference's model: no hyperparameter priors
                new_script = old_script.replace(', method="exact")', ", priors=None)")
                if new_script.count("priors=None") != 2:
                    raise SystemExit("the reference's dem_validation.py does not fit as expected: compare by hand")
                (tmp / "dem_ref_on_this.py").write_text(new_script)
                t_old = run([py, "experiments/dem_validation.py", "--data", data, "--out", str(tmp / "dem_old")],
                            wt, wt)
                t_new = run([py, str(tmp / "dem_ref_on_this.py"), "--data", data, "--out", str(tmp / "dem_new")],
                            ROOT, tmp)
                rows.append((f"DEM, the reference's experiment (its tables): {a.reference} engine vs this one",
                             t_old, t_new, compare(tmp / "dem_old" / "dem_validation.md",
                                                   tmp / "dem_new" / "dem_validation.md")))
                print(rows[-1], flush=True)
            if a.only in ("all", "reproduce"):
                # irft reproduce: the reference's, this one's, and the reference's driver on this engine
                t_old = run([py, "-m", "irft_torch.cli", "reproduce", "--out", str(tmp / "rep_old"), "--no-progress"],
                            wt, wt)
                t_new = run([py, "-m", "irft_torch.cli", "reproduce", "--out", str(tmp / "rep_new"), "--no-progress"],
                            ROOT, tmp)
                tables = "; ".join(f"{t}: " + compare(tmp / "rep_old" / t, tmp / "rep_new" / t)
                                   for t in ("table1.csv", "table2.csv"))
                rows.append((f"irft reproduce: {a.reference} (40 fits, serial) vs this one (52 fits, workers)", t_old,
                             t_new, tables))
                print(rows[-1], flush=True)
                # the same model as the reference's: the plain marginal likelihood for every fit
                t_plain = run([py, "-m", "irft_torch.cli", "reproduce", "--priors", "none", "--out",
                               str(tmp / "rep_plain"), "--no-progress"], ROOT, tmp)
                tables = "; ".join(f"{t}: " + compare(tmp / "rep_old" / t, tmp / "rep_plain" / t)
                                   for t in ("table1.csv", "table2.csv"))
                rows.append((f"irft reproduce: {a.reference} vs this one with --priors none (the reference's model; "
                             "44 fits, workers)", t_old, t_plain, tables))
                print(rows[-1], flush=True)
                driver = (wt / "irft_torch" / "reproduce.py").read_text()
                # the package-relative imports made absolute: this engine's modules
                driver = re.sub(r"^(\s*)from \.([\w.]*) import",
                                lambda m: f"{m.group(1)}from irft_torch{'.' if m.group(2) else ''}{m.group(2)} import",
                                driver, flags=re.M)
                if driver.count("model = InverseRFT(c, f, ") != 1:
                    raise SystemExit("the reference's reproduce.py does not fit as expected: compare by hand")
                driver = driver.replace("model = InverseRFT(c, f, ", "model = InverseRFT(c, f, priors=None, ")
                (tmp / "ref_reproduce.py").write_text(driver)
                (tmp / "ref_driver.py").write_text(
                    "import sys, torch\nsys.path.insert(0, sys.argv[2])\ntorch.set_default_dtype(torch.float64)\n"
                    "import ref_reproduce as r\nr.run_study(sys.argv[1], r.StudySettings(), progress=False)\n")
                t_drv = run([py, str(tmp / "ref_driver.py"), str(tmp / "rep_drv"), str(tmp)], ROOT, tmp)
                tables = "; ".join(f"{t}: " + compare(tmp / "rep_old" / t, tmp / "rep_drv" / t)
                                   for t in ("table1.csv", "table2.csv"))
                rows.append((f"the reference's reproduce driver (40 fits, serial): {a.reference} engine vs this one",
                             t_old, t_drv, tables))
                print(rows[-1], flush=True)
            if not a.skip_current_dem and a.only in ("all", "dem"):
                t_cur = run([py, "experiments/validation/dem_validation.py", "--data", data,
                             "--out", str(tmp / "dem_cur")],
                            ROOT, ROOT)
                rows.append(("today's dem_validation.py (17 folds, 6 models) on this engine", None, t_cur, ""))
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(wt)], cwd=ROOT, capture_output=True)
    print(f"\n{os.cpu_count()} CPUs; wall clock of a fresh process each\n")
    print("| command | reference engine | this engine | ratio | tables |")
    print("|---|---|---|---|---|")
    for name, t_old, t_new, cmp in rows:
        ratio = f"{t_old / t_new:.1f}x" if t_old else "-"
        print(f"| {name} | {f'{t_old:.1f} s' if t_old else '-'} | {t_new:.1f} s | {ratio} | {cmp} |")


if __name__ == "__main__":
    main()
