"""Maps over the ground online: the cost of one step (a stance's forces in, the maps at the robot's place out)
as the walk grows, ``SpatialTiles`` against the exact spatial model, and the tiles' difference from it.

Data: simulated (a C-toe's scoop every 0.2 m along a straight walk over a boundary and patches). Run time: about
2 minutes here (2 cores).

    python experiments/benchmarks/bench_walk_online.py [--stances 2000] [--exact-upto 150] [--tile 1.0] [--margin 1.0]

The spatial model is fitted on the first 12 stances; then each step adds one stance (``add_data``, hyperparameters
fixed) and asks for the maps at the new foothold over an 8 x 8 grid of angles. Reported: ms per step at steps 100
and ``--stances`` (the mean of 10 steps around each) and their ratio, for the tiles and, up to ``--exact-upto``
stances, the exact model (whose step grows with the walk); and the largest difference between the two models'
map means, in units of the exact model's sd, at 20 places off the footholds within the first ``--exact-upto``
stances. Writes nothing.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import torch

F64 = torch.float64


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="bench_walk_online.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stances", type=int, default=2000, help="stances walked (default 2000)")
    ap.add_argument("--exact-upto", type=int, default=150, help="stances the exact model is timed to (default 150)")
    ap.add_argument("--tile", type=float, default=1.0, help="tile side, m (default 1.0)")
    ap.add_argument("--margin", type=float, default=1.0, help="how far beyond its square a tile takes samples, m "
                                                              "(default 1.0)")
    args = ap.parse_args(argv)
    torch.set_default_dtype(F64)
    warnings.simplefilter("ignore")

    import irft_torch as irft
    from irft_torch.design import Stance
    from irft_torch.gp import SpatialTiles
    from irft_torch.rft import CToe, FourierStressMap, TerrainField, course_path

    stance = Stance.of_stroke(CToe(0.025, 0.02, n_segments=6),
                              course_path([-0.8, -0.3, 0.4], 0.06, start=(0.0, 0.0), n_steps=10))
    length = 0.2 * args.stances
    loose, close = FourierStressMap.poppy_seeds_loose(), FourierStressMap.poppy_seeds_close()
    field = TerrainField.random_patches([loose, close], n_patches=max(4, args.stances // 10),
                                        extent=(0.0, length, -1.0, 1.0), edge=0.1, seed=0)
    gen = torch.Generator().manual_seed(0)

    def measure(p):
        c = stance.at(p)
        F = irft.rft.forces(field, c, locations=c.locations)
        return c, F + 0.02 * F.abs().mean(0) * torch.randn(F.shape, generator=gen, dtype=F64)

    feet = torch.stack([torch.arange(args.stances, dtype=F64) * 0.2, torch.zeros(args.stances, dtype=F64)], -1)
    data = [measure(p) for p in feet]
    from irft_torch.rft.contacts import Contacts

    c0 = Contacts.cat([d[0] for d in data[:12]])
    F0 = torch.cat([d[1] for d in data[:12]])
    model = irft.InverseRFT(c0, F0, hyper_posterior="map")
    model.fit(progress=False)
    b, g = torch.meshgrid(torch.linspace(-math.pi / 2, math.pi / 2, 8), torch.linspace(-math.pi / 2, math.pi / 2, 8),
                          indexing="ij")
    marks = [100, args.stances - 5]

    def run(kind: str, upto: int) -> dict[int, float]:
        import copy

        holder = SpatialTiles(model, tile=args.tile, margin=args.margin) if kind == "tiles" else copy.deepcopy(model)
        times: dict[int, list[float]] = {m: [] for m in marks}
        for k in range(12, upto):
            t0 = time.perf_counter()
            c, F = data[k]
            holder.add_data(c, F)
            if kind == "tiles":
                holder.stress_map(b, g, feet[k:k + 1])
            else:
                holder.stress_map(b, g, locations=feet[k:k + 1])
            dt = time.perf_counter() - t0
            for m in marks:
                if abs(k - m) < 5:
                    times[m].append(dt)
        return {m: 1e3 * sum(v) / len(v) for m, v in times.items() if v}

    tiles = run("tiles", args.stances)
    print(f"spatial lengthscale (x, z) {model.hypers.spatial.lengthscale.tolist()} m")
    print(f"tiles ({args.tile:g} m, margin {args.margin:g} m): {tiles[marks[0]]:.1f} ms per step at step {marks[0]}, "
          f"{tiles[marks[1]]:.1f} ms at step {marks[1]}: ratio {tiles[marks[1]] / tiles[marks[0]]:.2f}")
    upto = min(args.exact_upto, args.stances)
    exact_marks = [100, upto - 5]
    marks[:] = exact_marks
    exact = run("exact", upto)
    print(f"exact model: {exact[exact_marks[0]]:.1f} ms per step at step {exact_marks[0]}, "
          f"{exact[exact_marks[1]]:.1f} ms at step {exact_marks[1]}: ratio "
          f"{exact[exact_marks[1]] / exact[exact_marks[0]]:.2f}")
    # the tiles' difference from the exact model over the first `upto` stances
    cs = Contacts.cat([d[0] for d in data[:upto]])
    Fs = torch.cat([d[1] for d in data[:upto]])
    full = irft.InverseRFT(cs, Fs, hyper_posterior="map")
    full.hypers.load_state_dict(model.hypers.state_dict())
    t = SpatialTiles(full, tile=args.tile, margin=args.margin)
    x = torch.rand(20, generator=gen, dtype=F64) * 0.2 * (upto - 1)
    y = (torch.rand(20, generator=gen, dtype=F64) - 0.5) * 0.4
    where = torch.stack([x, y], -1)
    a, e = t.stress_map(b, g, where), full.stress_map(b, g, locations=where)
    gap = ((a.mean - e.mean).abs() / e.variance.sqrt()).max()
    ratio = (a.variance / e.variance).max()
    print(f"tiles against the exact model over {upto} stances, 20 places: largest |mean difference| "
          f"{float(gap):.3f} sd, largest variance ratio {float(ratio):.3f}")


if __name__ == "__main__":
    main()
