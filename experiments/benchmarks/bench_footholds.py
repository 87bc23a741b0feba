"""How long a walking robot waits for its next foothold: ``design.plan_stances`` (one step, a gait library of 3
strokes, every candidate within reach) against the former scorer, one candidate at a time through
``backend.cross_covariance``, in the same run; and the same step averaged over the hyperparameter draws
(``draws=True``).

Data: simulated (``explore_footholds.py``'s field and strokes, seed 0). Run time: about 1 minute (2 cores).

    python experiments/benchmarks/bench_footholds.py [--stances 20] [--repeats 3]

The model (``InverseRFT(..., locations=)``, its defaults) is fitted on a line of 8 footholds, then takes
``--stances`` - 8 more on a lawnmower path (``add_data``). Printed: ms per planning step, the ratio to the
former scorer at the mode's hyperparameters, and the largest difference between the two's scores (they compute
the same numbers).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import torch

F64 = torch.float64


def former_scores(backend, queries, weights, stance, footholds) -> torch.Tensor:
    """The scorer before the batched one: each foothold's stance through ``cross_covariance`` (P,)."""
    out = []
    for p in footholds:
        c = stance.at(p).to(dtype=queries.beta.dtype)
        S_qc = backend.cross_covariance(queries, c)
        S_cc = backend.cross_covariance(c, c)
        noise = backend.hypers.noise.detach()
        eye = torch.eye(S_cc.shape[-1], dtype=S_cc.dtype)
        L = torch.linalg.cholesky(0.5 * (S_cc + S_cc.mT) + noise[:, None, None] * eye)
        fall = torch.linalg.solve_triangular(L, S_qc.mT, upper=False).pow(2).sum(-2)
        out.append(((fall * weights).sum(-1) / backend.hypers.prior_variance.detach()).mean())
    return torch.stack(out)


def best_of(fn, repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="bench_footholds.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stances", type=int, default=20, help="stances the model has seen (8 on the first line)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    torch.set_default_dtype(F64)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "validation"))
    import explore_footholds as ef

    import irft_torch as irft
    from irft_torch.design import Region, foothold_scores, plan_stances
    from irft_torch.design.footholds import _region_queries

    stances, field = ef.strokes_and_field(0, 3)
    gen = torch.Generator().manual_seed(0)
    line = torch.stack([torch.linspace(0.0, 1.4, 8, dtype=F64), torch.zeros(8, dtype=F64)], -1)
    c, F = ef.measure(field, stances[0], line, gen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # simulated media far from the generic: the unit checks
        model = irft.InverseRFT(c, F)
        model.fit(progress=False)
        for k, p in enumerate(ef.lawnmower(max(args.stances - 8, 0))):
            c, F = ef.measure(field, stances[k % 3], p[None], gen)
            model.add_data(c, F)
    gx, gy = torch.meshgrid(torch.arange(ef.X0, ef.X1 + 1e-9, 0.1), torch.arange(ef.Y0, ef.Y1 + 1e-9, 0.1),
                            indexing="ij")
    cand = torch.stack([gx.reshape(-1), gy.reshape(-1)], -1)
    px, py = torch.meshgrid(torch.linspace(ef.X0, ef.X1, 9), torch.linspace(ef.Y0, ef.Y1, 5), indexing="ij")
    roi = torch.stack([px.reshape(-1), py.reshape(-1)], -1)
    here = torch.tensor([1.0, 0.0])
    near = cand[(cand - here).norm(dim=-1) <= 0.45]
    region = Region.square(8)
    queries = _region_queries(region, roi)
    weights = region.weight.repeat(roi.shape[0]) / roi.shape[0]
    n_draws = len(model._weighted_backends()[0])
    print(f"{len(model.backend.train_contacts)} samples ({args.stances} stances), {len(near)} candidates in reach x "
          f"{len(stances)} strokes, {len(queries)} queries (8 x 8 angles x 45 places); {n_draws} hyperparameter draws")

    def former():
        with torch.no_grad():
            return torch.stack([former_scores(model.backend, queries, weights, s, near) for s in stances])

    t_old, s_old = best_of(former, args.repeats)
    t_new, s_new = best_of(lambda: torch.stack([foothold_scores(model, s, near, roi, region) for s in stances]),
                           args.repeats)
    t_plan, _ = best_of(lambda: plan_stances(model, stances, here, 1, 0.45, cand, roi, region), args.repeats)
    t_mix, _ = best_of(lambda: plan_stances(model, stances, here, 1, 0.45, cand, roi, region, draws=True),
                       args.repeats)
    diff = float((s_new - s_old).abs().max() / s_old.abs().max())
    print(f"| scorer | ms per step | against the former |\n|---|---|---|\n"
          f"| former, one candidate at a time (the mode) | {1e3 * t_old:.0f} | 1 |\n"
          f"| batched scores (the mode) | {1e3 * t_new:.0f} | {t_new / t_old:.3f}x |\n"
          f"| plan_stances, one step (the mode, the default) | {1e3 * t_plan:.0f} | {t_plan / t_old:.3f}x |\n"
          f"| plan_stances, one step, averaged over {n_draws} draws (`draws=True`) | {1e3 * t_mix:.0f} | "
          f"{t_mix / t_old:.3f}x |")
    print(f"largest score difference, batched against former, relative to the largest score: {diff:.1e}")


if __name__ == "__main__":
    main()
