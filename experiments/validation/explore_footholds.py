"""Where to step next: greedy footholds (``design.plan_footholds``; with ``--gaits``, ``plan_stances``) against a
lawnmower path and random footholds.

Data: simulated (``rft.TerrainField.random_patches`` of media from the calibration study's families). Run time:
about 18 s per seed here (2 cores; 42 s with ``--refit-every 4``); the default run about 1.5 minutes.

    python experiments/validation/explore_footholds.py [--seeds 0 1 2 3 4] [--steps 12] [--reach 0.45]
        [--roi 9 5] [--refit-every 0] [--gaits 1] [--greedy-draws] [--out experiments/results]

A C-toe first walks a line of 8 footholds (x = 0 to 1.4 m, y = 0) over a 2 m x 1 m patch of ground; the spatial
model (``InverseRFT(..., locations=)``, defaults) is fitted there. Then each strategy takes ``--steps`` more
stances, one scoop each (with ``--gaits``, one stroke of the library each), 2 % noise, the model updated with the
forces measured (``add_data``, hyperparameters fixed; ``--refit-every K``: refitted after every K stances, every
strategy alike):

- greedy: ``design.plan_footholds`` one step at a time, within ``--reach`` (0.45 m) of the last foothold, from
  candidates on a 0.1 m grid, scoring the maps over a ``--roi`` grid of places (9 x 5, edges included) spanning
  the patch the error is measured over (before 2026-12-01's change: 5 x 3, 0.2 m inside the edges);
- lawnmower: three rows (y = -0.35, 0, 0.35 m) walked back and forth, spaced to fit the steps;
- random: footholds drawn uniformly over the patch;
- with ``--greedy-draws``, also greedy-draws: the greedy planner with its scores averaged over the hyperparameter
  draws (``draws=True``; about 2.5 minutes a seed with 3 gaits and ``--refit-every 4``).

``--gaits K`` (1, the default: the scoop alone; 2 or 3): a library of strokes (``GAITS``: the scoop, a steeper dive
with the toe tilted forward, a skim with it tilted back); greedy chooses each stance's stroke with its foothold
(``design.plan_stances``), the lawnmower walks the strokes in turn, the random footholds draw one each (about 55 s
per seed with 3 gaits and ``--refit-every 4``).

Reported: map RMSE (N/cm^3, both maps, a 9 x 9 grid of the canonical square) at 16 held-out random places in
the patch after every 4 steps, mean over seeds; and the same over the grid angles within 15 deg of the stroke's
segments (the angles a foothold can teach directly). Writes ``explore_footholds.csv`` (with ``--gaits K`` > 1,
``explore_footholds_K_gaits.csv``).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

F64 = torch.float64
X0, X1, Y0, Y1 = 0.0, 2.0, -0.5, 0.5


# the gait library (``--gaits K`` takes the first K): (course knots, rad from +x; toe heading, rad). The first is the
# scoop every strategy walks with one gait; the others dive steeper with the toe tilted forward, and skim with it
# tilted back (other angles of attack and of motion)
GAITS = (([-0.8, -0.3, 0.4], 0.0), ([-1.2, -0.6, 0.0], 0.6), ([-0.6, 0.2, 0.8], -0.6))


def strokes_and_field(seed: int, n_gaits: int = 1):
    """The first ``n_gaits`` strokes of ``GAITS`` (``design.Stance`` s of a C-toe) and the seed's field."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from walk_and_map import media

    from irft_torch.design import Stance
    from irft_torch.rft import CToe, TerrainField, course_path

    if not 1 <= n_gaits <= len(GAITS):
        raise ValueError(f"--gaits must be 1 to {len(GAITS)}, got {n_gaits}")
    toe = CToe(0.025, 0.02, n_segments=6)
    stances = [Stance.of_stroke(toe, course_path(course, 0.06, start=(0.0, 0.0), heading=tilt, n_steps=10))
               for course, tilt in GAITS[:n_gaits]]
    field = TerrainField.random_patches(media(seed, False), n_patches=6, extent=(X0, X1, Y0, Y1), edge=0.1,
                                        seed=seed)
    return stances, field


def measure(field, stance, feet: torch.Tensor, gen: torch.Generator):
    """Contacts with places, and forces with 2 % noise, of the stance at each foothold (N, 2)."""
    from irft_torch import rft
    from irft_torch.rft.contacts import Contacts

    c = Contacts.cat([stance.at(p) for p in feet])
    F = rft.forces(field, c, locations=c.locations)
    return c, F + 0.02 * F.abs().mean(0) * torch.randn(F.shape, generator=gen, dtype=F64)


def lawnmower(n: int) -> torch.Tensor:
    rows = (-0.35, 0.0, 0.35)
    per = math.ceil(n / len(rows))
    out = []
    for r, y in enumerate(rows):
        xs = np.linspace(X0 + 0.1, X1 - 0.1, per)
        out += [(float(x), y) for x in (xs if r % 2 == 0 else xs[::-1])]
    return torch.tensor(out[:n], dtype=F64)


def rmse(model, field, places, b, g, seen) -> tuple[float, float]:
    """Map RMSE (N/cm^3) at ``places`` over the angle grid (b, g), and over its angles ``seen`` by the stroke."""
    truth = torch.stack([field.at(p)(b, g) for p in places])
    err = (model.stress_map(b, g, locations=places).mean - truth).pow(2)  # (L, 9, 9, 2)
    return float(err.mean().sqrt()), float(err[:, seen].mean().sqrt())


def run(seed: int, steps: int, reach: float = 0.45, roi_grid: tuple[int, int] = (9, 5),
        refit_every: int = 0, n_gaits: int = 1, greedy: tuple[str, ...] = ("greedy",)
        ) -> dict[str, list[tuple[float, float]]]:
    import irft_torch as irft
    from irft_torch.design import plan_stances
    from irft_torch.rft.contacts import Contacts

    stances, field = strokes_and_field(seed, n_gaits)
    stance = stances[0]
    gen = torch.Generator().manual_seed(seed)
    line = torch.stack([torch.linspace(0.0, 1.4, 8, dtype=F64), torch.zeros(8, dtype=F64)], -1)
    c0, F0 = measure(field, stance, line, gen)
    base = irft.InverseRFT(c0, F0)  # c0 carries its places
    base.fit(progress=False)
    rng = np.random.default_rng(30_000 + seed)
    held = torch.tensor(np.stack([rng.uniform(X0, X1, 16), rng.uniform(Y0, Y1, 16)], -1), dtype=F64)
    b, g = torch.meshgrid(torch.linspace(-math.pi / 2, math.pi / 2, 9, dtype=F64),
                          torch.linspace(-math.pi / 2, math.pi / 2, 9, dtype=F64), indexing="ij")
    from walk_and_map import seen_angles

    every = Contacts.cat([s.at(torch.zeros(2, dtype=F64)) for s in stances])
    seen = seen_angles(every, b, g)  # the grid angles within 15 deg of a segment of a stroke (any foothold's)
    gx, gy = torch.meshgrid(torch.arange(X0, X1 + 1e-9, 0.1, dtype=F64), torch.arange(Y0, Y1 + 1e-9, 0.1, dtype=F64),
                            indexing="ij")
    candidates = torch.stack([gx.reshape(-1), gy.reshape(-1)], -1)
    nx, ny = roi_grid
    px, py = torch.meshgrid(torch.linspace(X0, X1, nx, dtype=F64), torch.linspace(Y0, Y1, ny, dtype=F64),
                            indexing="ij")  # the greedy planner's region: the patch the error is measured over
    roi = torch.stack([px.reshape(-1), py.reshape(-1)], -1)
    plans = {**{g: None for g in greedy}, "lawnmower": lawnmower(steps),
             "random": torch.tensor(np.stack([rng.uniform(X0, X1, steps), rng.uniform(Y0, Y1, steps)], -1), dtype=F64)}
    # with a gait library, the lawnmower walks the strokes in turn and the random footholds draw one each
    gaits = {"lawnmower": [k % n_gaits for k in range(steps)],
             "random": [0] * steps if n_gaits == 1 else
             np.random.default_rng(50_000 + seed).integers(n_gaits, size=steps).tolist()}
    out: dict[str, list[tuple[float, float]]] = {}
    for name, feet in plans.items():
        import copy

        m = copy.deepcopy(base)
        errs = [rmse(m, field, held, b, g, seen)]
        here = line[-1]
        g_meas = torch.Generator().manual_seed(40_000 + seed)
        for k in range(steps):
            if name in greedy:  # "greedy": at the mode's hyperparameters (the default); "greedy-draws": averaged
                where, which = plan_stances(m, stances, here, 1, reach, candidates, roi, draws=name == "greedy-draws")
                p, s = where[0], stances[int(which[0])]
            else:
                p, s = feet[k], stances[int(gaits[name][k])]
            c, F = measure(field, s, p[None], g_meas)
            m.add_data(c, F)
            here = p
            if refit_every and (k + 1) % refit_every == 0 and k + 1 < steps:
                m.fit(progress=False)  # the hyperparameters follow the data, as a walking robot's would
            if (k + 1) % 4 == 0:
                errs.append(rmse(m, field, held, b, g, seen))
        out[name] = errs
    return out


def seen_share(seed: int, n_gaits: int = 1) -> float:
    """The share of the 9 x 9 angle grid within 15 deg of the strokes' segments."""
    from walk_and_map import seen_angles

    from irft_torch.rft.contacts import Contacts

    stances, _ = strokes_and_field(seed, n_gaits)
    c = Contacts.cat([s.at(torch.zeros(2, dtype=F64)) for s in stances])
    b, g = torch.meshgrid(torch.linspace(-math.pi / 2, math.pi / 2, 9, dtype=F64),
                          torch.linspace(-math.pi / 2, math.pi / 2, 9, dtype=F64), indexing="ij")
    return float(seen_angles(c, b, g).double().mean())


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="explore_footholds.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--steps", type=int, default=12, help="stances each strategy takes after the first line")
    ap.add_argument("--reach", type=float, default=0.45, help="the greedy planner's longest step, m (the lawnmower's "
                    "steps along a row are 0.6 m at 12 steps, its first step from the line 1.35 m)")
    ap.add_argument("--roi", type=int, nargs=2, default=[9, 5], metavar=("NX", "NY"),
                    help="the greedy planner's places: an NX x NY grid over the whole patch, edges included")
    ap.add_argument("--refit-every", type=int, default=0, metavar="K",
                    help="refit the hyperparameters after every K stances, every strategy alike (0: fixed)")
    ap.add_argument("--gaits", type=int, default=1, metavar="K",
                    help=f"strokes to choose from (the first K of {len(GAITS)}): greedy picks the foothold and the "
                    "stroke (design.plan_stances), the lawnmower walks them in turn, random draws one per stance")
    ap.add_argument("--greedy-draws", action="store_true",
                    help="also a greedy planner whose scores are averaged over the hyperparameter draws (draws=True), "
                    "beside the default one at the mode's hyperparameters")
    ap.add_argument("--out", type=Path, default=Path("experiments/results"), help="where the CSV goes")
    args = ap.parse_args(argv)
    torch.set_default_dtype(F64)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, t0 = [], time.perf_counter()
    for seed in args.seeds:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the unit checks on simulated media far from the generic
            res = run(seed, args.steps, args.reach, tuple(args.roi), args.refit_every, args.gaits,
                      ("greedy", "greedy-draws") if args.greedy_draws else ("greedy",))
        for name, errs in res.items():
            rows.append([seed, name, *[f"{e[0]:.5f}" for e in errs], *[f"{e[1]:.5f}" for e in errs]])
            print(f"seed {seed} {name:11s}: map RMSE after 0, 4, 8, ... steps: "
                  + ", ".join(f"{e[0]:.4f}" for e in errs)
                  + "; at the stroke's angles " + ", ".join(f"{e[1]:.4f}" for e in errs), flush=True)
    n = (len(rows[0]) - 2) // 2
    print(f"\nmean over {len(args.seeds)} seeds ({time.perf_counter() - t0:.0f} s), over the square | at the angles "
          f"the stroke reaches ({int(seen_share(args.seeds[0], args.gaits) * 100)} % of the grid):")
    for name in dict.fromkeys(r[1] for r in rows):
        errs = np.mean([[float(v) for v in r[2:]] for r in rows if r[1] == name], 0)
        print(f"  {name:11s}: " + ", ".join(f"{e:.4f}" for e in errs[:n]) + " | "
              + ", ".join(f"{e:.4f}" for e in errs[n:]))
    csv_name = "explore_footholds.csv" if args.gaits == 1 else f"explore_footholds_{args.gaits}_gaits.csv"
    with open(args.out / csv_name, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["seed", "strategy", *[f"rmse_after_{4 * i}" for i in range(n)],
                    *[f"rmse_seen_after_{4 * i}" for i in range(n)]])
        w.writerows(rows)
    print(f"wrote {args.out / csv_name}")


if __name__ == "__main__":
    main()
