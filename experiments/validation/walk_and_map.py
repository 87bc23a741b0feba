"""Walk and map: stress maps over the ground learned from a walk's leg forces, against three baselines.

Data: simulated (``rft.TerrainField``: a boundary between two media, a compaction gradient, random patches; and a
homogeneous bed), media from the calibration study's families (``irft_torch.studies.calibration.medium``:
generic-like, sharp and preset media for our seeds; blends, sloped beds and GP draws for the held-out ones).
Run time: about 6 s per terrain and seed here (2 cores, 2026-12-01); the default run about 2 minutes.

    python experiments/validation/walk_and_map.py [--seeds 0 1 2] [--held-out 100 101] [--stances 16]
        [--prior-mean zero|physics] [--kernel li|li+generic|rbf] [--out experiments/results] [--plot]

A C-toe walks 3 m along x, one stroke per foothold (two strokes alternating: a shallow scoop and a steep one),
0.2 m apart, with 2 % force noise. The maps are then asked for at 12 places off the footholds (x along the
walk, up to 0.2 m to either side) over a 13 x 13 grid of the canonical square (beta, gamma in [-90, 90] deg),
against the truth there. Methods:

- spatial: ``InverseRFT(contacts, forces, locations=places)``, the library's defaults (``gp.spatial``);
- homogeneous: ``InverseRFT(contacts, forces)``, one medium for the whole walk;
- filter: ``TerrainFilter`` (the homogeneous fit's hyperparameters) with a sliding window of three stances,
  fed sample by sample; a place gets the filter's map as it stood when the robot was at the nearest foothold;
- scalar GP: the field's current practice, one number per step: the least-squares scale of Li et al.'s generic
  map to the stance's forces, regressed over the footholds by a gpytorch exact GP (Matern 5/2, fitted), the map
  at a place = its predicted scale times the generic map.

Per terrain and seed: map RMSE (N/cm^3, both maps) at the held-out places, and the 95 % coverage of the spatial
model's intervals there (the homogeneous model's beside it), over the whole square and split into the angles the
walk's segments came within 15 degrees of ("seen") and the others, with the spread of the errors in units of the
model's sd there (1 for honest intervals, below 1 for intervals wider than needed). Seeds ``--seeds`` are our own;
``--held-out`` were written down before any run and are reported apart. Writes ``walk_and_map.csv`` and, with
``--plot``, ``walk_and_map.png``.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch

F64 = torch.float64
KINDS = ("boundary", "gradient", "patches", "homogeneous")
EXTENT = (0.0, 3.0)


OWN_FAMILIES = ("perturbed", "sharp", "presets")  # the calibration study's media (irft_torch.studies.calibration)
HELD_OUT_FAMILIES = ("blend", "tilted", "gp")  # chosen before any run, for the held-out seeds only


class Scaled:
    """A medium (a callable (beta, gamma) -> (..., 2) N/cm^3) times (sx, sz)."""

    def __init__(self, medium, sx: float = 1.0, sz: float = 1.0) -> None:
        self.medium, self.sx, self.sz = medium, sx, sz

    def __call__(self, beta, gamma):
        out = self.medium(beta, gamma)
        return torch.stack([self.sx * out[..., 0], self.sz * out[..., 1]], -1)

    def scaled(self, sx: float, sz: float) -> Scaled:
        return Scaled(self.medium, self.sx * sx, self.sz * sz)


def media(seed: int, held_out: bool) -> list:
    """Three media for one terrain, each from a family of the calibration study's (``--held-out`` seeds: families
    no fit here was tuned on), at 0.5-1.5 times its size."""
    from irft_torch.studies.calibration import medium

    rng = np.random.default_rng(seed)
    fams = HELD_OUT_FAMILIES if held_out else OWN_FAMILIES
    out = []
    for j in range(3):
        fam = fams[int(rng.integers(len(fams)))]
        k = float(rng.uniform(0.5, 1.5))
        out.append(Scaled(medium(fam, 1000 * seed + j)[0], k, k))
    return out


def terrain(kind: str, seed: int, held_out: bool = False):
    from irft_torch.rft import TerrainField

    rng = np.random.default_rng(seed + 7)
    a, b, c = media(seed, held_out)
    if kind == "boundary":
        return TerrainField.two_media(a, b, boundary=float(rng.uniform(1.0, 2.0)), width=0.05,
                                      angle=float(rng.uniform(-0.3, 0.3)))
    if kind == "gradient":
        lo, hi = sorted(rng.uniform(0.4, 1.6, size=2))
        return TerrainField.compaction_gradient(a, scales=(float(lo), float(hi)), span=(0.3, 2.7))
    if kind == "patches":
        return TerrainField.random_patches([a, b, c], n_patches=8, extent=(0.0, 3.0, -0.6, 0.6), edge=0.1,
                                           seed=seed)
    return TerrainField.uniform(a)


def walk_over(field, n_stances: int, seed: int, noise: float = 0.02):
    """(contacts, forces (T, 2) N, places (T, 2) m, stance (T,), footholds (N, 2) m) of the walk (docstring)."""
    from irft_torch import rft
    from irft_torch.rft import CToe, course_path, walk

    toe = CToe(0.025, 0.02, n_segments=6)
    strokes = [course_path([-0.6, -0.2, 0.3], 0.06, start=(0.0, 0.0), n_steps=10),
               course_path([-1.0, -0.5, 0.6], 0.05, start=(0.0, 0.0), n_steps=10)]
    x = torch.linspace(0.0, EXTENT[1], n_stances, dtype=F64)
    feet = torch.stack([x, torch.zeros_like(x)], -1)
    parts = [walk(toe, strokes[k % 2], feet[k:k + 1], torch.zeros(1, dtype=F64)) for k in range(n_stances)]
    from irft_torch.rft.contacts import Contacts

    c = Contacts.cat([p.contacts for p in parts])
    s = torch.cat([p.locations for p in parts])
    stance = torch.cat([torch.full((len(p),), k) for k, p in enumerate(parts)])
    keep = (c.weight_z != 0).any(-1)
    c, s, stance = c[keep], s[keep], stance[keep]
    F = rft.forces(field, c, locations=s)
    g = torch.Generator().manual_seed(10_000 + seed)
    F = F + noise * F.abs().mean(0) * torch.randn(F.shape, generator=g, dtype=F64)
    return c, F, s, stance, feet


def held_out_places(seed: int, n: int = 12) -> torch.Tensor:
    rng = np.random.default_rng(20_000 + seed)
    x = rng.uniform(0.1, EXTENT[1] - 0.1, n)
    y = rng.uniform(-0.2, 0.2, n)
    return torch.tensor(np.stack([x, y], -1), dtype=F64)


def grid():
    b, g = torch.meshgrid(torch.linspace(-math.pi / 2, math.pi / 2, 13, dtype=F64),
                          torch.linspace(-math.pi / 2, math.pi / 2, 13, dtype=F64), indexing="ij")
    return b, g


def seen_angles(c, b, g, within: float = math.radians(15.0)):
    """(13, 13) bool: grid angle pairs within ``within`` rad (in both angles) of a segment in contact."""
    keep = c.weight_z != 0
    from irft_torch.rft.stress_maps import mirror_to_canonical

    cb, cg, _ = mirror_to_canonical(c.beta[keep], c.gamma[keep])
    near = ((b.reshape(-1, 1) - cb).abs() < within) & ((g.reshape(-1, 1) - cg).abs() < within)
    return near.any(-1).reshape(b.shape)


def scalar_gp(c, F, stance, feet, places):
    """The scalar baseline: each stance's least-squares scale of the generic map, a GP over the footholds."""
    import gpytorch

    from irft_torch import rft
    from irft_torch.rft import FourierStressMap

    G = rft.forces(FourierStressMap.generic(), c)
    k = torch.stack([(F[stance == j] * G[stance == j]).sum() / G[stance == j].pow(2).sum()
                     for j in range(len(feet))])

    class GP(gpytorch.models.ExactGP):
        def __init__(self, x, y, lik):
            super().__init__(x, y, lik)
            self.mean = gpytorch.means.ConstantMean()
            self.cov = gpytorch.kernels.ScaleKernel(gpytorch.kernels.MaternKernel(nu=2.5))

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean(x), self.cov(x))

    lik = gpytorch.likelihoods.GaussianLikelihood().double()
    gp = GP(feet, k, lik).double()
    gp.mean.constant.data.fill_(float(k.mean()))
    gp.train()
    opt = torch.optim.Adam(gp.parameters(), lr=0.05)
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, gp)
    for _ in range(200):
        opt.zero_grad()
        loss = -mll(gp(feet), k)
        loss.backward()
        opt.step()
    gp.eval()
    with torch.no_grad():
        return gp(places).mean  # (L,)


def filter_maps(model, c, F, stance, feet, places, window_stances: int = 3):
    """The sliding-window filter's map at each place: as it stood after the stance nearest to the place."""
    from irft_torch import TerrainFilter

    per = int(np.bincount(stance.numpy()).max())
    filt = TerrainFilter(model, n_envs=1, window=window_stances * per)
    b, g = grid()
    snaps = []
    for j in range(len(feet)):
        for t in torch.nonzero(stance == j)[:, 0]:
            filt.update(c[int(t):int(t) + 1], F[int(t):int(t) + 1])
        snaps.append(filt.stress_map(b, g).mean[0])  # (13, 13, 2)
    near = torch.cdist(places, feet).argmin(-1)
    return torch.stack([snaps[int(i)] for i in near])


def run_one(kind: str, seed: int, n_stances: int, held_out: bool = False, prior_mean: str = "zero",
            kernel: str | None = None) -> dict:
    import irft_torch as irft
    from irft_torch.rft import FourierStressMap

    field = terrain(kind, seed, held_out)
    c, F, s, stance, feet = walk_over(field, n_stances, seed)
    places = held_out_places(seed)
    b, g = grid()
    truth = torch.stack([field.at(p)(b, g) for p in places])  # (L, 13, 13, 2)
    out: dict = {"kind": kind, "seed": seed, "samples": len(c)}
    t0 = time.perf_counter()
    spatial = irft.InverseRFT(c, F, locations=s, prior=irft.MapPrior(mean=prior_mean, kernel=kernel))
    spatial.fit(progress=False)
    out["spatial_s"] = time.perf_counter() - t0
    post = spatial.stress_map(b, g, locations=places)
    homog = irft.InverseRFT(c, F)
    homog.fit(progress=False)
    hp = homog.stress_map(b, g)
    plug = irft.InverseRFT(c, F, hyper_posterior="map")
    plug.fit(progress=False)
    maps = {"spatial": post.mean, "homogeneous": hp.mean.expand_as(truth),
            "filter": filter_maps(plug, c, F, stance, feet, places),
            "scalar_gp": scalar_gp(c, F, stance, feet, places)[:, None, None, None]
            * FourierStressMap.generic()(b, g)[None]}
    seen = seen_angles(c, b, g)  # (13, 13): where the walk's segments have been
    out["seen_share"] = float(seen.double().mean())
    for name, m in maps.items():
        out[f"rmse_{name}"] = float((m - truth).pow(2).mean().sqrt())
        out[f"rmse_seen_{name}"] = float((m - truth)[:, seen].pow(2).mean().sqrt())
    for name, p in (("spatial", post), ("homogeneous", hp)):
        z = (truth - p.mean) / p.variance.clamp_min(1e-30).sqrt()
        inside = (z.abs() < 1.96).double()
        out[f"coverage_{name}"] = float(inside.mean())
        out[f"coverage_seen_{name}"] = float(inside[:, seen].mean())  # where the walk's segments have been
        out[f"coverage_unseen_{name}"] = float(inside[:, ~seen].mean()) if bool((~seen).any()) else float("nan")
    z = (truth - post.mean) / post.variance.clamp_min(1e-30).sqrt()  # the spread of z says how wide the intervals are
    out["z_sd_seen"], out["z_sd_unseen"] = float(z[:, seen].std()), float(z[:, ~seen].std())
    sp = spatial.hypers.as_dict()
    out["spatial_variance"] = sp["spatial_variance"]
    out["spatial_lengthscale_m"] = sp["spatial_lengthscale_m"]
    out["_plot"] = (field, spatial, feet, places, truth, post)
    return out


def plot(res: dict, path: Path) -> None:
    """One spatial run's field at one angle pair over the ground: truth, estimate, sd, footholds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    field, model, feet, places, _, _ = res["_plot"]
    xs, ys = torch.linspace(-0.1, 3.1, 65, dtype=F64), torch.linspace(-0.5, 0.5, 21, dtype=F64)
    X, Y = torch.meshgrid(xs, ys, indexing="ij")
    loc = torch.stack([X.reshape(-1), Y.reshape(-1)], -1)
    beta, gamma = torch.tensor(0.0, dtype=F64), torch.tensor(math.pi / 2, dtype=F64)  # a plate pushed down
    true = torch.stack([field.at(p)(beta, gamma)[1] for p in loc]).reshape(X.shape)
    post = model.stress_map(beta, gamma, locations=loc)
    mean, sd = post.mean[:, 1].reshape(X.shape), post.variance[:, 1].sqrt().reshape(X.shape)
    fig, axes = plt.subplots(3, 1, figsize=(8, 7.5), sharex=True, constrained_layout=True)
    lo, hi = float(min(true.min(), mean.min())), float(max(true.max(), mean.max()))
    for ax, z, title, kw in ((axes[0], true, "truth", {"vmin": lo, "vmax": hi}),
                             (axes[1], mean, "spatial model: posterior mean", {"vmin": lo, "vmax": hi}),
                             (axes[2], sd, "spatial model: posterior sd", {"cmap": "magma"})):
        im = ax.pcolormesh(X.numpy(), Y.numpy(), z.detach().numpy(), shading="auto", **kw)
        ax.plot(feet[:, 0], feet[:, 1], "^", color="k", mec="w", ms=6, label="footholds")
        ax.plot(places[:, 0], places[:, 1], "wo", mec="k", ms=5, label="held-out places")
        ax.set_title(f"{res['kind']} (seed {res['seed']}): alpha_z at a plate pushed down (beta 0, gamma 90 deg), "
                     f"{title}", fontsize=9)
        ax.set_ylabel("y [m]")
        fig.colorbar(im, ax=ax, label="N/cm^3")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("x along the walk [m]")
    fig.savefig(path, dpi=110)
    plt.close(fig)


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="walk_and_map.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="our own seeds")
    ap.add_argument("--held-out", type=int, nargs="*", default=[100, 101],
                    help="seeds written down before any run, reported apart")
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    ap.add_argument("--stances", type=int, default=16, help="footholds along the 3 m walk")
    ap.add_argument("--out", type=Path, default=Path("experiments/results"), help="where the CSV (and PNG) go")
    ap.add_argument("--plot", action="store_true", help="also write walk_and_map.png")
    ap.add_argument("--prior-mean", default="zero", choices=["zero", "physics"],
                    help="the spatial model's prior mean (the library's default: zero)")
    ap.add_argument("--kernel", default=None, choices=["li", "li+generic", "rbf"],
                    help="the spatial model's angle kernel (default: the library's, li+generic with places)")
    args = ap.parse_args(argv)
    torch.set_default_dtype(F64)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, last = [], None
    for group, seeds in (("own", args.seeds), ("held-out", args.held_out)):
        for kind in args.kinds:
            for seed in seeds:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the unit checks on simulated media far from the generic
                    r = run_one(kind, seed, args.stances, group == "held-out", args.prior_mean, args.kernel)
                r["group"] = group
                if last is None or (last["kind"] != "boundary" and kind == "boundary"):
                    last = r  # the figure: the first boundary walk
                rows.append(r)
                print(f"{group:8s} {kind:11s} seed {seed:3d}: map RMSE [N/cm^3] spatial {r['rmse_spatial']:.4f}, "
                      f"homogeneous {r['rmse_homogeneous']:.4f}, filter {r['rmse_filter']:.4f}, scalar GP "
                      f"{r['rmse_scalar_gp']:.4f}; at seen angles ({r['seen_share']:.0%}) {r['rmse_seen_spatial']:.4f}"
                      f" / {r['rmse_seen_homogeneous']:.4f} / {r['rmse_seen_filter']:.4f} / "
                      f"{r['rmse_seen_scalar_gp']:.4f}; 95 % coverage spatial {r['coverage_spatial']:.2f} (homogeneous "
                      f"{r['coverage_homogeneous']:.2f}); fit {r['spatial_s']:.1f} s", flush=True)
    for where, pre in (("the whole canonical square", "rmse_"), ("the angles the walk saw", "rmse_seen_")):
        print(f"\nmean over seeds, map RMSE N/cm^3 over {where}; the spatial model's 95 % coverage (whole square):")
        for group in ("own", "held-out"):
            for kind in args.kinds:
                sel = [r for r in rows if r["group"] == group and r["kind"] == kind]
                if not sel:
                    continue
                m = {k: np.mean([r[pre + k] for r in sel]) for k in ("spatial", "homogeneous", "filter", "scalar_gp")}
                cov = np.mean([r["coverage_spatial"] for r in sel])
                cs, cu = (np.mean([r[f"coverage_{w}_spatial"] for r in sel]) for w in ("seen", "unseen"))
                zs, zu = (np.mean([r[f"z_sd_{w}"] for r in sel]) for w in ("seen", "unseen"))
                best = min(("homogeneous", "filter", "scalar_gp"), key=lambda n: m[n])
                print(f"  {group:8s} {kind:11s}: spatial {m['spatial']:.4f} | homogeneous {m['homogeneous']:.4f} | "
                      f"filter {m['filter']:.4f} | scalar GP {m['scalar_gp']:.4f} | best baseline {best}; "
                      f"spatial / best {m['spatial'] / m[best]:.2f}; coverage {cov:.2f} (seen angles {cs:.2f}, "
                      f"unseen {cu:.2f}; sd of z {zs:.2f} / {zu:.2f})")
    keys = [k for k in rows[0] if not k.startswith("_")]
    with open(args.out / "walk_and_map.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {args.out / 'walk_and_map.csv'}")
    if args.plot and last is not None:
        plot(last, args.out / "walk_and_map.png")
        print(f"wrote {args.out / 'walk_and_map.png'}")


if __name__ == "__main__":
    main()
