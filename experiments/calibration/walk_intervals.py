"""How wide are the intervals on the walk-and-map walks, by model? Coverage and the spread of z beside map RMSE.

Data: simulated (``validation/walk_and_map.py``'s terrains and walks, our own seeds). Run time: about 2 minutes
here (2 cores).

    python experiments/calibration/walk_intervals.py [--seeds 0 1 2] [--kinds boundary gradient homogeneous]

For each walk, four fits on the same samples: the planar default (Li et al.'s term, Laplace), the planar plug-in
(``hyper_posterior="map"``), the planar RBF with Laplace, and the spatial plug-in (``locations=``, the spatial
default's kernel "li+generic"). At the walk's held-out places, on a 13 x 13 grid of the canonical square: the 95 %
coverage of mean +- 1.96 sd, the sd of z = (truth - mean) / sd (1 for honest intervals, below 1 for intervals
wider than needed) and the map RMSE (N/cm^3), each the mean over seeds. Notes: ``experiments/notes/
walk_and_map_coverage.md``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
import torch


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="walk_intervals.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--kinds", nargs="+", default=["boundary", "gradient", "homogeneous"])
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "validation"))
    import walk_and_map as wm

    import irft_torch as irft

    torch.set_default_dtype(torch.float64)
    models = {"planar default (li, Laplace)": {}, "planar plug-in (li)": {"hyper_posterior": "map"},
              "planar RBF + Laplace": {"prior": irft.MapPrior(kernel="rbf")},
              "spatial plug-in (li+generic)": {"hyper_posterior": "map", "spatial": True}}
    res: dict = {}
    for kind in args.kinds:
        for seed in args.seeds:
            field = wm.terrain(kind, seed, False)
            c, F, s, _, _ = wm.walk_over(field, 16, seed)
            places = wm.held_out_places(seed)
            b, g = wm.grid()
            truth = torch.stack([field.at(p)(b, g) for p in places])  # (L, 13, 13, 2)
            for name, opts in models.items():
                opts = dict(opts)
                spatial = opts.pop("spatial", False)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the unit checks on simulated media far from the generic
                    m = irft.InverseRFT(c, F, locations=s if spatial else None, **opts)
                    m.fit(progress=False)
                post = m.stress_map(b, g, locations=places) if spatial else m.stress_map(b, g)
                mean, sd = post.mean.expand_as(truth), post.variance.clamp_min(1e-30).sqrt().expand_as(truth)
                z = (truth - mean) / sd
                res.setdefault((kind, name), []).append([float((z.abs() < 1.96).double().mean()), float(z.std()),
                                                         float((truth - mean).pow(2).mean().sqrt())])
    for (kind, name), v in res.items():
        cov, zsd, rmse = np.mean(v, 0)
        print(f"{kind:12s} {name:30s} coverage {cov:.2f}  sd of z {zsd:.2f}  map RMSE {rmse:.4f} N/cm^3")


if __name__ == "__main__":
    main()
