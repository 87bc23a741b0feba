"""Why the calibration harness' last rows fail (issue 30): four measurements, no tuning.

Data: simulated (the harness' cases). Run time: about 1 min without options; --scan 8 min 36 s; --nuts about
4 min; --terms about 1 min.

1. **The outputscale prior's centre against the truth** (no fits). The prior on each map's variance is
   centred on an estimate from the forces (``gp.kernels.priors.prior_centres``: the generic shape at the medium's
   zeta, the data's own stress per depth, half the other axis'). Printed per family and motion over
   ``--seeds`` seeds: log10(centre / the true map's mean square over the canonical square), median and range.
   Where the forces see little of the map, the posterior there is this prior.
2. **The residual terms' prior size against coverage** (``--scan``). The model with the generic shape as a
   rank-one term (``InverseRFT(..., prior=MapPrior(kernel="li+generic"))``) is refitted with the centre of
   its residual terms' priors (the RBF outputscale and Li et al.'s variance) scaled by each of
   ``--factors`` (1 is the library's), every family x motion at the seeds ``--first-seed`` ..
   ``--first-seed + --scan-seeds - 1``; the plug-in's 95 % coverage per family (``studies.calibration.score``)
   and, per fit, how many nats the forces gain when those two variances shrink 1000x at the fitted
   hyperparameters (the marginal likelihood alone, no hyperprior): does the generic-shaped families'
   over-coverage follow the residual terms' prior size, and what would shrinking it cost the other families?
3. ``--nuts``: one GP-drawn case (``gp/long/4``, a lengthscale 0.85 map) with the default model scored as the
   plug-in, Laplace and NUTS (one chain of 256 after 256, about 4 minutes here): does the exact hyperparameter
   posterior cover what the approximations miss?
4. ``--terms``: the generic-shape model's plug-in, every family x motion at the seeds of ``--scan``, scored as
   fitted and with its residual terms (the RBF, Li et al.'s 9 functions) switched off (variances x 1e-8, nothing
   refitted): how many nats the forces gain by dropping them, and the 95 % coverage and median z^2 (squared error
   over posterior variance; 1 for a truth drawn from the posterior) both ways. Do the generic-shaped media
   over-cover because the model keeps a residual they do not have, and could the forces be left to choose?

    python experiments/calibration/calibration_limits.py [--seeds 8] [--scan] [--factors 1,0.1,0.01] [--first-seed 4]
        [--scan-seeds 2] [--nuts] [--terms] [--out experiments/results]

Writes ``calibration_limits.md`` (and ``calibration_limits_scan.csv`` with ``--scan``,
``calibration_limits_terms.csv`` with ``--terms``) under ``--out``.
"""

from __future__ import annotations

import argparse
import copy
import csv
import statistics
import time
import warnings
from pathlib import Path
from typing import Any
from unittest import mock

import torch

import irft_torch.gp.model as front_door
from irft_torch import InverseRFT, MapPrior
from irft_torch.studies.calibration import MEDIA, MOTIONS, grid, medium, motion, score, simulate

GENERIC_SHAPED = ("scaled", "presets")


def _data(family: str, kind: str, seed: int):
    truth, label = medium(family, seed)
    c = motion(kind, seed)
    return truth, label, c, simulate(truth, c, 0.01 if seed % 2 == 0 else 0.05, seed)


def _os_centre(model: InverseRFT) -> torch.Tensor:
    """The outputscale prior's centre (2,) (N/cm^3)^2 as registered on the model."""
    closure = model.hypers.kernel._priors["outputscale_prior"][1]
    return torch.as_tensor(closure.keywords["c"]).exp()


def centre_table(seeds: int) -> list[str]:
    """Claim 1: log10(outputscale prior centre / truth mean square) per family x motion, seeds 0 .. seeds - 1."""
    B, G = grid(41)
    lines = ["| family | motion | x: median (min .. max) | z: median (min .. max) |", "|---|---|---|---|"]
    for family in MEDIA:
        for kind in MOTIONS:
            logs = []
            for seed in range(seeds):
                truth, _, c, f = _data(family, kind, seed)
                truth_ms = truth(B, G).reshape(-1, 2).pow(2).mean(0)
                fitted = InverseRFT(c, f, hyper_posterior="map", prior=MapPrior(kernel="rbf"))
                logs.append((_os_centre(fitted) / truth_ms).log10())
            v = torch.stack(logs)
            cells = [f"{float(v[:, a].median()):+.2f} ({float(v[:, a].min()):+.2f} .. {float(v[:, a].max()):+.2f})"
                     for a in range(2)]
            lines.append(f"| {family} | {kind} | {cells[0]} | {cells[1]} |")
            print(lines[-1], flush=True)
    return lines


def _fit_scaled(c, f, factor: float) -> InverseRFT:
    """``build_scaled`` fitted (300 Adam steps, the library's default)."""
    model = build_scaled(c, f, factor)
    model.fit(300, progress=False)
    return model


def build_scaled(c, f, factor: float) -> InverseRFT:
    """The generic-shape model with its residual terms' prior centre (outputscale, Li et al.'s variance) x factor;
    the generic shape's own prior (at zeta^2) as the library has it."""
    real = front_door.centres_of_sums  # what the model registers its priors from (gp.kernels.priors.CentreSums)

    def scaled(*args, **kwargs):
        out = dict(real(*args, **kwargs))
        out["outputscale"] = out["outputscale"] * factor
        return out

    with mock.patch.object(front_door, "centres_of_sums", scaled):
        return InverseRFT(c, f, prior=MapPrior(kernel="li+generic"), hyper_posterior="map")


def shrunk(model: InverseRFT, shrink: float) -> InverseRFT:
    """A copy of a generic-shape model with its residual terms' variances (the RBF outputscale, Li et al.'s
    variance) x ``shrink``, every other hyperparameter as fitted (no refit)."""
    m = copy.deepcopy(model)
    with torch.no_grad():
        m.hypers.outputscale = m.hypers.outputscale * shrink
        m.hypers.li.variance = m.hypers.li.variance * shrink
    return m


def _gain_nats(model: InverseRFT, shrink: float = 1e-3) -> tuple[float, float]:
    """Per axis, log p(F | residual variances x shrink) - log p(F | fitted), all else at the fit (nats)."""
    with torch.no_grad():
        before = model.backend.negative_log_likelihood().detach() * model.backend.n_samples
        m = shrunk(model, shrink)
        after = m.backend.negative_log_likelihood().detach() * m.backend.n_samples
    d = before - after
    return float(d[0]), float(d[1])


def z_statistics(model: InverseRFT, truth, n_grid: int = 41) -> tuple[list[float], list[float]]:
    """Per map: the share of a ``n_grid`` x ``n_grid`` grid whose 95 % interval holds the truth, and the mean of
    z^2 = (posterior mean - truth)^2 / posterior variance over it (1 where the truth is a draw of the posterior;
    below 1, intervals wider than this truth needs)."""
    B, G = grid(n_grid)
    with torch.no_grad():
        post = model.stress_map(B, G)
        z2 = ((post.mean - truth(B, G)).pow(2) / post.variance).reshape(-1, 2)
    return [float(v) for v in (z2 < 1.959964**2).double().mean(0)], [float(v) for v in z2.mean(0)]


def residual_terms(first_seed: int, n_seeds: int, out: Path) -> list[str]:
    """Claim 4: the generic-shape plug-in with and without its residual terms (x 1e-8, no refit), per family."""
    rows: list[dict[str, Any]] = []
    for seed in range(first_seed, first_seed + n_seeds):
        for family in MEDIA:
            for kind in MOTIONS:
                truth, _, c, f = _data(family, kind, seed)
                model = InverseRFT(c, f, prior=MapPrior(kernel="li+generic"), hyper_posterior="map")
                model.fit(300, progress=False)
                cov, z2 = z_statistics(model, truth)
                cov0, z20 = z_statistics(shrunk(model, 1e-8), truth)
                gain = _gain_nats(model, 1e-8)
                row = {"family": family, "motion": kind, "seed": seed}
                for a, name in enumerate("xz"):
                    row.update({f"gain_{name}": gain[a], f"cover95_{name}": cov[a], f"z2_{name}": z2[a],
                                f"cover95_dropped_{name}": cov0[a], f"z2_dropped_{name}": z20[a]})
                rows.append(row)
                print(f"{family}/{kind}/{seed}: gain {gain[0]:+.1f} / {gain[1]:+.1f} nats; 95 % {cov[0]:.3f} / "
                      f"{cov[1]:.3f}, z^2 {z2[0]:.2f} / {z2[1]:.2f}; dropped {cov0[0]:.3f} / {cov0[1]:.3f}, "
                      f"z^2 {z20[0]:.3g} / {z20[1]:.3g}", flush=True)
    with (out / "calibration_limits_terms.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = ["| family | nats gained by dropping the residual terms, x / z (median; min .. max) | fitted: 95 % "
             "coverage x / z | fitted: median z^2 x / z | dropped: 95 % coverage x / z | dropped: median z^2 x / z |",
             "|---|---|---|---|---|---|"]
    for family in MEDIA:
        rs = [r for r in rows if r["family"] == family]

        def both(key: str, fn, fmt: str, rs=rs) -> str:
            return " / ".join(format(fn([r[f"{key}_{a}"] for r in rs]), fmt) for a in "xz")

        gains = " / ".join(f"{statistics.median(v):+.1f} ({min(v):+.0f} .. {max(v):+.0f})"
                           for v in ([r[f"gain_{a}"] for r in rs] for a in "xz"))
        lines.append(f"| {family} ({len(rs)}) | {gains} | {both('cover95', statistics.mean, '.3f')} | "
                     f"{both('z2', statistics.median, '.2f')} | {both('cover95_dropped', statistics.mean, '.3f')} | "
                     f"{both('z2_dropped', statistics.median, '.3g')} |")
    return lines


def residual_scan(factors: list[float], first_seed: int, n_seeds: int, out: Path) -> list[str]:
    """Claim 2: coverage per family at each prior-centre factor, and the forces' gain for shrinking the terms."""
    rows = []
    for seed in range(first_seed, first_seed + n_seeds):
        for family in MEDIA:
            for kind in MOTIONS:
                truth, _, c, f = _data(family, kind, seed)
                for factor in factors:
                    t0 = time.perf_counter()
                    model = _fit_scaled(c, f, factor)
                    s = score(model, truth, 41, 200, seed)
                    gx, gz = _gain_nats(model)
                    rows.append({"family": family, "motion": kind, "seed": seed, "factor": factor,
                                 "cover95_x": s["cover95_x"], "cover95_z": s["cover95_z"],
                                 "pct95_x": s["pct95_x"], "pct95_z": s["pct95_z"], "gain_x": gx, "gain_z": gz,
                                 "os_x": float(model.hypers.outputscale[0]), "os_z": float(model.hypers.outputscale[1]),
                                 "seconds": time.perf_counter() - t0})
                    print(f"{family}/{kind}/{seed} x{factor:g}: 95 % coverage {s['cover95_x']:.3f} / "
                          f"{s['cover95_z']:.3f}, gain for shrinking {gx:.1f} / {gz:.1f} nats", flush=True)
    with (out / "calibration_limits_scan.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = ["| family | " + " | ".join(f"x {k:g}: 95 % x / z, overconfident" for k in factors) +
             " | gain for shrinking (nats, median x / z at x 1) |",
             "|---|" + "---|" * (len(factors) + 1)]
    for family in MEDIA:
        cells = []
        for k in factors:
            rs = [r for r in rows if r["family"] == family and r["factor"] == k]
            cx, cz = (statistics.mean(r[f"cover95_{a}"] for r in rs) for a in "xz")
            ox, oz = (100 * statistics.mean(r[f"pct95_{a}"] < 0.025 for r in rs) for a in "xz")
            cells.append(f"{cx:.3f} / {cz:.3f}, {ox:.0f} % / {oz:.0f} %")
        base = [r for r in rows if r["family"] == family and r["factor"] == factors[0]]
        gx, gz = (statistics.median(r[f"gain_{a}"] for r in base) for a in "xz")
        gains = f"{gx:.1f} / {gz:.1f}"
        lines.append(f"| {family} | " + " | ".join(cells) + f" | {gains} |")
    return lines


def nuts_case() -> list[str]:
    """Claim 3: gp/long/4 with the default model, plug-in, Laplace and NUTS from the same fit."""
    truth, label, c, f = _data("gp", "long", 4)
    fitted = InverseRFT(c, f, hyper_posterior="map", prior=MapPrior(kernel="rbf"))
    fitted.fit(300, progress=False)
    lines = [f"gp/long/4 ({label}), default model ({fitted.method}):", "",
             "| posterior | 95 % coverage x / z | RMSE / mean std x / z | seconds |", "|---|---|---|---|"]
    for name, opts in (("map", {}), ("laplace", {}),
                       ("nuts", {"n_samples": 256, "warmup": 256, "num_chains": 1, "processes": 1})):
        m = copy.deepcopy(fitted)
        t0 = time.perf_counter()
        m.fit_hyper_posterior(name, generator=torch.Generator().manual_seed(0), **opts)
        s = score(m, truth, 41, 200, 4)
        lines.append(f"| {name} | {s['cover95_x']:.3f} / {s['cover95_z']:.3f} | {s['rmse_x'] / s['std_x']:.2f} / "
                     f"{s['rmse_z'] / s['std_z']:.2f} | {time.perf_counter() - t0:.0f} |")
        print(lines[-1], flush=True)
    return lines


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=8, help="seeds per family x motion for the centre table")
    p.add_argument("--scan", action="store_true", help="refit with the residual terms' prior centre scaled")
    p.add_argument("--factors", default="1,0.1,0.01", help="comma-separated factors for --scan (1 first)")
    p.add_argument("--first-seed", type=int, default=4, help="--scan: the first seed")
    p.add_argument("--scan-seeds", type=int, default=2, help="--scan: seeds per family x motion")
    p.add_argument("--nuts", action="store_true", help="the gp/long/4 case with NUTS (slow)")
    p.add_argument("--terms", action="store_true",
                   help="the generic-shape plug-in with and without its residual terms, seeds --first-seed ..")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "results")
    a = p.parse_args(argv)
    torch.set_default_dtype(torch.float64)
    a.out.mkdir(parents=True, exist_ok=True)
    md = ["# Why the calibration harness' last rows fail (`python experiments/calibration/calibration_limits.py`)", "",
          "## The outputscale prior's centre against the truth: log10(centre / truth mean square), seeds "
          f"0-{a.seeds - 1}",
          ""]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        md += centre_table(a.seeds)
        if a.scan:
            factors = [float(x) for x in a.factors.split(",")]
            md += ["", f"## The residual terms' prior centre x factor: the generic-shape model refitted, seeds "
                   f"{a.first_seed}-{a.first_seed + a.scan_seeds - 1}, every motion", ""]
            md += residual_scan(factors, a.first_seed, a.scan_seeds, a.out)
        if a.terms:
            md += ["", f"## The generic-shape plug-in with and without its residual terms, seeds {a.first_seed}-"
                   f"{a.first_seed + a.scan_seeds - 1}, every motion", ""]
            md += residual_terms(a.first_seed, a.scan_seeds, a.out)
        if a.nuts:
            md += ["", "## NUTS on a GP-drawn map", ""] + nuts_case()
    (a.out / "calibration_limits.md").write_text("\n".join(md) + "\n")
    print(f"wrote {a.out / 'calibration_limits.md'}")


if __name__ == "__main__":
    main()
