"""How much do the default intervals' centres move with the hyperparameter draws' random stream? The
mixture's Monte Carlo spread at every held-out planar wheel run.

Data: the measured rover-wheel runs (--data DIR, e.g. ../shared/data/rover_wheel; not shipped). Run time: about
3-4 minutes per wheel and setting at five streams here (2 cores, 2026-12-01).

    python experiments/calibration/mixture_spread.py --data ../shared/data/rover_wheel [--streams 5]
        [--wheels smooth grouser] [--draws 16 64] [--weights psis raw] [--points moments resample]
        [--proposals 128] [--out experiments/results]

For each wheel and held-out slip level (the planar study's folds: ``validation/wheel_validation.py --study
planar``, its fit settings), the mode is fitted once with the plug-in; then the Laplace posterior over the
hyperparameters is fitted ``--streams`` times, stream 0 the library's fixed point set and the others seeded
generators, each keeping at most ``--draws`` draws ("all": every weighted proposal; ``--points``: the default's
moment-matched points or a systematic resample of the proposals), and the held-out runs' forces are
predicted (with noise, as the study does). Per run and axis, the spread is the standard deviation of the
predicted mean over the streams divided by the mean predictive sd: the share of its interval that the mixture's
Monte Carlo error moves the centre by. The issue's bar is below 10 % at every run. Writes
``mixture_spread.csv`` (one row per wheel, setting, run) and prints the median, the largest and how many runs
are above 10 %.
"""

from __future__ import annotations

import argparse
import copy
import csv
import sys
import time
from pathlib import Path

import numpy as np
import torch


def spreads(data: Path, wheel: str, draws, proposals: int, streams: int,
            smooth: bool = True, points: str = "moments") -> tuple[np.ndarray, float, float]:
    """(runs, 2) spread per held-out run and axis, seconds per fold and posterior fit, mean draws kept."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "validation"))
    import wheel_validation as wv

    import irft_torch as irft
    from irft_torch.rft.contacts import Contacts

    runs = wv.wd.read_wheel_runs(data, wheel)
    profile, K = wv.contact_profile(data, wheel, "envelope")
    c_all = [wv.run_contacts(profile, r, K) for r in runs]
    F = torch.tensor([r.force for r in runs], dtype=torch.float64)
    levels = sorted({r.commanded_rim_speed for r in runs})
    group = np.array([levels.index(r.commanded_rim_speed) for r in runs])
    settings = wv.PLANAR_DEFAULTS
    means = np.full((streams, len(runs), 2), np.nan)
    sds = np.full((streams, len(runs), 2), np.nan)
    seconds, kept = [], []
    for g in range(len(levels)):
        test, train = np.nonzero(group == g)[0], np.nonzero(group != g)[0]
        c_train = Contacts.cat([c_all[i] for i in train])
        c_test = Contacts.cat([c_all[i] for i in test])
        base = irft.InverseRFT(c_train, F[train], prior=irft.MapPrior(mean="zero", hyperpriors="physical"),
                               engine=irft.Engine(method=settings["method"], tol=settings["tol"]),
                               hyper_posterior="map")
        base.fit(n_iter=settings["n_iter"], lr=settings["lr"], progress=False)
        for s in range(streams):
            m = copy.deepcopy(base)
            t0 = time.perf_counter()
            m.fit_hyper_posterior("laplace", n_proposals=proposals, n_draws=draws, smooth=smooth, points=points,
                                  generator=None if s == 0 else torch.Generator().manual_seed(s))
            with torch.no_grad():
                post = m.predict_forces(c_test, include_noise=True)
            seconds.append(time.perf_counter() - t0)
            kept.append(m.hyper_posterior.n_draws)
            means[s, test] = post.mean.numpy()
            sds[s, test] = post.variance.clamp_min(0).sqrt().numpy()
        print(f"  {wheel}: held-out slip level {g + 1}/{len(levels)} done", flush=True)
    return means.std(0, ddof=1) / sds.mean(0), float(np.mean(seconds)), float(np.mean(kept))


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="mixture_spread.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="the rover-wheel .mat files (read, never copied)")
    ap.add_argument("--streams", type=int, default=3, help="random streams (point sets) per fold, >= 2 (default 3)")
    ap.add_argument("--wheels", nargs="+", default=["smooth", "grouser"], choices=["smooth", "grouser"])
    ap.add_argument("--draws", nargs="+", default=["16"],
                    help="settings of n_draws to compare: numbers, or all (every weighted proposal: each draw is a "
                         "backend of its own, over 12 GB on a wheel fold)")
    ap.add_argument("--proposals", type=int, default=128, help="Laplace proposals per stage (default 128)")
    ap.add_argument("--weights", nargs="+", default=["psis"], choices=["psis", "raw"],
                    help="importance weights to compare: Pareto-smoothed (the default) or raw")
    ap.add_argument("--points", nargs="+", default=["moments"], choices=["moments", "resample"],
                    help="the draws kept: the moment-matched point set (the default) or a systematic resample")
    ap.add_argument("--out", type=Path, default="experiments/results", help="where the CSV goes")
    args = ap.parse_args(argv)
    if args.streams < 2:
        ap.error("--streams must be at least 2 (a spread needs two)")
    if not args.data.is_dir():
        raise SystemExit(f"--data {args.data}: no such directory (the rover-wheel data are not shipped)")
    torch.set_default_dtype(torch.float64)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for wheel in args.wheels:
        for d, weights, points in [(d, wt, pt) for d in args.draws for wt in args.weights for pt in args.points]:
            draws = None if d == "all" else int(d)
            ratio, sec, kept = spreads(args.data, wheel, draws, args.proposals, args.streams, weights == "psis",
                                       points)
            med, top, over = np.median(ratio, 0), ratio.max(0), (ratio > 0.1).sum(0)
            print(f"{wheel}, n_draws={d}, {weights} weights, {points}, {args.proposals} proposals: "
                  f"spread / sd median {med[0]:.3f} / {med[1]:.3f}, "
                  f"max {top[0]:.3f} / {top[1]:.3f}, above 0.1: {over[0]} / {over[1]} of {len(ratio)} (x / z); "
                  f"{kept:.0f} draws kept, {sec:.1f} s per posterior fit and prediction")
            rows += [[wheel, d, weights, points, args.proposals, i, f"{r[0]:.4f}", f"{r[1]:.4f}"]
                     for i, r in enumerate(ratio)]
    with open(args.out / "mixture_spread.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["wheel", "n_draws", "weights", "points", "n_proposals", "run", "spread_x", "spread_z"])
        w.writerows(rows)
    print(f"wrote {args.out / 'mixture_spread.csv'}")


if __name__ == "__main__":
    main()
