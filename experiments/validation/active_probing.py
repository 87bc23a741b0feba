"""Active probing: do designed probes teach the maps faster than the paper's four configurations?

Data: simulated (three media, forward RFT). Run time: --quick about 9 s; full about 8 min (487 s,
2 cores, 2026-12-03).

    python experiments/validation/active_probing.py [--out experiments/results] [--quick] [--seeds 0 1]

Starting from nothing, a robot runs probes one after another, refitting I-RFT after each, on three
media (the generic Li et al. map at the paper's truth scale, and the two poppy-seed maps), with
the paper's force noise (multiplicative, variance 0.05), which the model is told is relative
(``noise_scale``; with a homoscedastic noise model the fitted z lengthscales collapse under this
noise for every strategy). Strategies, all at equal probe length:
  - each of the paper's four configurations (I/C toe x gait 1/2), run again and again;
  - the four in turn;
  - designed: before each probe, score a library of random equal-length probes (both toes, random
    tilts, paths inside the leg's workspace) with ``ProbeScorer`` (the prior for the first probe,
    then the fitted model: the posterior variance does not depend on the forces), refine the best
    few by gradient descent on the expected integrated variance (``optimize_probe``), run the best.
A designed probe is as long as the paper's shortest configuration (gait 2), so after k probes its
total path length is never more than any baseline's. Map RMSE over a 50 x 50 grid of the square,
per axis, after every probe; mean (and spread) over noise seeds.
Writes active_probing.md / .csv and active_probing_<medium>.png, active_probing_paths.png.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch

import irft_torch as irft
from irft_torch.design import ProbeScorer, force_relative, optimize_probe
from irft_torch.rft import FourierStressMap, Probe, ProbeBounds, forces, random_probes
from irft_torch.studies import reproduce


@dataclass(frozen=True)
class Settings:
    n_probes: int = 5
    n_library: int = 40  # random candidates per toe, per probe
    n_refine: int = 3  # best candidates refined by gradient descent
    refine_iter: int = 25
    fit_iter: int = 100  # Adam steps after the first probe
    refit_iter: int = 50  # after each further probe (warm start)
    noise: float = 0.05  # variance of the multiplicative force noise (the paper's Table II)
    noise_floor: float = 0.1  # N: the relative noise scale is sqrt(F^2 + floor^2)
    eval_grid: int = 50
    prior_outputscale: float = 0.1  # the first design's guess: map std ~0.3 N/cm^3
    prior_noise: float = 0.1  # and force noise std ~0.3 N
    bounds: ProbeBounds = ProbeBounds(max_depth=0.06, max_height=0.02, x_range=(-0.25, 0.25))

    @classmethod
    def quick(cls) -> Settings:
        return cls(n_probes=2, n_library=6, n_refine=1, refine_iter=5, fit_iter=30, refit_iter=15)


MEDIA = {
    "generic": FourierStressMap.generic(*reproduce.StudySettings().truth_scale),
    "poppy seeds, loose": FourierStressMap.poppy_seeds_loose(),
    "poppy seeds, close": FourierStressMap.poppy_seeds_close(),
}


def paper_probes(study: reproduce.StudySettings) -> list[Probe]:
    return [Probe(*reproduce.configuration(name, study), name) for name in reproduce.CONFIGS]


def eval_points(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    e = torch.linspace(-math.pi / 2, math.pi / 2, n + 1, dtype=torch.float64)
    c = (e[1:] + e[:-1]) / 2
    return torch.meshgrid(c, c, indexing="ij")


def run_sequence(truth, next_probe, s: Settings, seed: int) -> list[dict]:
    """Run ``s.n_probes`` probes chosen by ``next_probe(k, model)``; the map RMSE after each."""
    B, G = eval_points(s.eval_grid)
    with torch.no_grad():
        want = truth(B, G)
    gen = torch.Generator().manual_seed(seed)
    model, total, out = None, 0.0, []
    for k in range(s.n_probes):
        probe = next_probe(k, model)
        c = probe.contacts()
        with torch.no_grad():
            f = forces(truth, c)
        f = f * (1 + math.sqrt(s.noise) * torch.randn(f.shape, generator=gen, dtype=f.dtype))
        # The noise is proportional to the force (a gain error): tell the model so (relative noise scale).
        scale = (f.pow(2) + s.noise_floor**2).sqrt()
        torch.manual_seed(seed)
        if model is None:
            # the design loop's plug-in (the study as measured; a mixture scorer costs a plug-in's x its draws)
            model = irft.InverseRFT(c, f, noise_scale=scale, hyper_posterior="map", prior=irft.MapPrior(kernel="rbf"))
            model.fit(n_iter=s.fit_iter, progress=False)
        else:
            model.add_data(c, f, noise_scale=scale)
            model.fit(n_iter=s.refit_iter, progress=False)
        with torch.no_grad():
            est = model.stress_map(B, G).mean
        total += probe.length
        rmse = (est - want).pow(2).mean((0, 1)).sqrt()
        out.append({"probe": k + 1, "name": probe.name, "length_m": probe.length, "total_length_m": total,
                    "rmse_x": float(rmse[0]), "rmse_z": float(rmse[1]), "probe_obj": probe})
    return out


def designer(s: Settings, toes: dict, length: float):
    def next_probe(k: int, model) -> Probe:
        if model is None:
            scorer = ProbeScorer.prior(1.0, s.prior_outputscale, s.prior_noise, method="spectral")
        else:  # candidates' noise is relative to their (predicted) force, as the fits assume
            scorer = ProbeScorer.from_model(model, noise_scale=force_relative(model, s.noise_floor))
        library = random_probes(toes, s.n_library, length, bounds=s.bounds, n_steps=100, seed=1000 + k)
        best = None
        for i, _ in scorer.rank(library, "variance")[: s.n_refine]:
            d = optimize_probe(scorer, init=library[i], bounds=s.bounds, n_iter=s.refine_iter, lr=0.05)
            if best is None or d.score < best.score:
                best, toe_name = d, library[i].name.split(" #")[0]
        tilt = math.degrees(float(best.probe.spec["heading"]))
        return replace(best.probe, name=f"{toe_name}-toe, tilt {tilt:.0f} deg")

    return next_probe


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="active_probing.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--out", default="experiments/results", help="where the report, CSV and figures go")
    ap.add_argument("--quick", action="store_true", help="a small version (for tests)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="noise seeds")
    ap.add_argument("--media", nargs="+", default=list(MEDIA), choices=list(MEDIA), help="media to run")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")  # this script only writes files; set here, never at import
    torch.set_default_dtype(torch.float64)
    s = Settings.quick() if a.quick else Settings()
    study = reproduce.StudySettings()
    paper = paper_probes(study)
    length = min(p.length for p in paper)
    toes = {"I": paper[0].toe, "C": paper[2].toe}
    t0 = time.perf_counter()
    strategies = {p.name: (lambda k, m, p=p: p) for p in paper}
    strategies["paper's four in turn"] = lambda k, m: paper[k % 4]
    strategies["designed"] = designer(s, toes, length)
    results = {}  # (medium, strategy, seed) -> rows
    for medium in a.media:
        for name, nxt in strategies.items():
            for seed in a.seeds:
                results[(medium, name, seed)] = run_sequence(MEDIA[medium], nxt, s, seed)
            print(f"{medium:20s} {name:22s} rmse x/z after {s.n_probes} probes: "
                  + ", ".join(f"{r[-1]['rmse_x']:.4f}/{r[-1]['rmse_z']:.4f}"
                              for r in (results[(medium, name, sd)] for sd in a.seeds))
                  + f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
    write_outputs(Path(a.out), results, a, s, length, paper, strategies, time.perf_counter() - t0)


def wins_sentence(wins) -> str:
    """Say after which probes (1-based) the designed sequence beat the best paper configuration in both axes."""
    after = [str(k + 1) for k, w in enumerate(wins) if w]
    if not after:
        return (f"The designed probes were not below the best of the paper's four configurations in both axes "
                f"after any of the {len(wins)} probes.")
    return (f"Designed below the best of the paper's four configurations in both axes after probe"
            f"{'s' if len(after) > 1 else ''} {', '.join(after)} (of {len(wins)}).")


def _mean(rows_by_seed, k, key):
    v = torch.tensor([rows[k][key] for rows in rows_by_seed])
    return float(v.mean()), float(v.std()) if len(v) > 1 else 0.0


def write_outputs(out: Path, results, a, s: Settings, length, paper, strategies, elapsed) -> None:
    from irft_torch import plotting

    out.mkdir(parents=True, exist_ok=True)
    with open(out / "active_probing.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["medium", "strategy", "seed", "probe", "probe_name", "length_m", "total_length_m", "rmse_x",
                    "rmse_z"])
        for (medium, name, seed), rows in results.items():
            for r in rows:
                w.writerow([medium, name, seed, r["probe"], r["name"], f"{r['length_m']:.4f}",
                            f"{r['total_length_m']:.4f}", f"{r['rmse_x']:.5f}", f"{r['rmse_z']:.5f}"])
    lines = ["# Active probing: designed probes vs the paper's configurations", "",
             f"`python experiments/validation/active_probing.py{' --quick' if a.quick else ''}`: "
             f"{s.n_probes} probes, noise "
             f"seeds {a.seeds}, multiplicative force noise of variance {s.noise} (the model told it is relative: "
             f"noise_scale = sqrt(F^2 + ({s.noise_floor} N)^2)); {elapsed:.0f} s. Designed probes are "
             f"{length:.3f} m long (the paper's gait 2; gait 1 is {paper[0].length:.3f} m), chosen from "
             f"{2 * s.n_library} random probes per step, best {s.n_refine} refined by {s.refine_iter} gradient steps, "
             f"inside depth {100 * s.bounds.max_depth:.0f} cm, height {100 * s.bounds.max_height:.0f} cm, "
             f"x in [{100 * s.bounds.x_range[0]:.0f}, {100 * s.bounds.x_range[1]:.0f}] cm. I-RFT on the "
             f"method='auto' backend, refitted after every probe. Map RMSE in N/cm^3 over a "
             f"{s.eval_grid} x {s.eval_grid} grid of the square (mean over seeds; +- their std).", ""]
    verdicts = []
    names = list(strategies)
    for medium in a.media:
        lines += [f"## {medium}", "", "| strategy | " + " | ".join(f"after {k + 1} (x / z)" for k in range(s.n_probes))
                  + " | total length after the last (m) |", "|---" * (s.n_probes + 2) + "|"]
        for name in names:
            rows = [results[(medium, name, sd)] for sd in a.seeds]
            cells = []
            for k in range(s.n_probes):
                (mx, sx), (mz, sz) = _mean(rows, k, "rmse_x"), _mean(rows, k, "rmse_z")
                cells.append(f"{mx:.4f} +- {sx:.4f} / {mz:.4f} +- {sz:.4f}")
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {rows[0][-1]['total_length_m']:.2f} |")
        wins = []
        for k in range(s.n_probes):
            d = [_mean([results[(medium, "designed", sd)] for sd in a.seeds], k, key)[0]
                 for key in ("rmse_x", "rmse_z")]
            best = [min(_mean([results[(medium, p.name, sd)] for sd in a.seeds], k, key)[0] for p in paper)
                    for key in ("rmse_x", "rmse_z")]
            wins.append(d[0] < best[0] and d[1] < best[1])
        verdicts.append((medium, wins))
        designed_names = [r["name"] for r in results[(medium, "designed", a.seeds[0])]]
        lines += ["", f"Designed probes (seed {a.seeds[0]}): " + "; ".join(designed_names) + ".",
                  wins_sentence(wins),
                  f"![{medium}](active_probing_{medium.replace(' ', '_').replace(',', '')}.png)", ""]
        fig, axes = plotting.plt.subplots(1, 2, figsize=(11, 3.8), constrained_layout=True)
        for name in names:
            rows = [results[(medium, name, sd)] for sd in a.seeds]
            xs = [r["total_length_m"] for r in rows[0]]
            for i, key in enumerate(("rmse_x", "rmse_z")):
                m = [_mean(rows, k, key)[0] for k in range(s.n_probes)]
                style = dict(lw=2.5, color="k") if name == "designed" else dict(lw=1.2)
                axes[i].plot(xs, m, "o-", label=name, ms=4, **style)
        for i, key in enumerate(("x", "z")):
            axes[i].set_xlabel("total path length (m)")
            axes[i].set_ylabel(f"map RMSE alpha_{key} (N/cm$^3$)")
            axes[i].set_yscale("log")
            axes[i].set_title(medium)
        axes[1].legend(fontsize=7)
        plotting.save(fig, out / f"active_probing_{medium.replace(' ', '_').replace(',', '')}.png")
    designed = [r["probe_obj"] for r in results[(a.media[0], "designed", a.seeds[0])]]
    fig, axes = plotting.plt.subplots(len(designed), 1, figsize=(8, 2.2 * len(designed)), constrained_layout=True)
    for ax, p in zip(axes if len(designed) > 1 else [axes], designed):
        plotting.plot_toe_path(p.toe, p.path, n_snapshots=8, ax=ax)
        ax.set_title(p.name, fontsize=9)
    plotting.save(fig, out / "active_probing_paths.png")
    lines += ["Designed probe paths (first medium, first seed): `active_probing_paths.png`.", "",
              "## Verdict", ""]
    for medium, wins in verdicts:
        lines.append(f"- {medium}: designed below the best paper configuration in both axes after "
                     f"{sum(wins)} of {len(wins)} probes" + (" (including the last)" if wins[-1] else "") + ".")
    (out / "active_probing.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out}/active_probing.md")


if __name__ == "__main__":
    main()
