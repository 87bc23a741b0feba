"""Does I-RFT learn a real granular medium better than the generic RFT map? Leave-one-beta-out on
independent DEM plate-intrusion simulations.

    python experiments/dem_validation.py --data ../shared/data/dem_plate_intrusion [--out experiments/results]

For each of the 8 plate tilts, everything is fitted on the other tilts' runs only:
  1. the effective free surface (``dem_data.calibrate_surface_offset``: the depth below the DEM's
     z_top, the top of the highest grain, at which RFT's depth law explains the forces best);
  2. I-RFT on the force time series (the plate cut into 10 segments, every ``--stride`` ms; the
     default 200 ms is longer than the force residuals' integrated autocorrelation time, printed,
     so the samples are nearly independent as the likelihood assumes), zero mean (the paper's) and
     physics-informed mean (generic shape x learned scales);
  3. baselines: the generic Li et al. map with one least-squares scale per axis, fitted to the runs'
     stresses (the data README's recipe) and fitted to the forces (the usual RFT calibration); a
     plain GP on the per-run stresses (the README's second baseline; same angle kernel, zero mean).
The held-out runs' stress per depth is scored against each run's force/depth slope over the plate
area (the README's per-run stress) and against its RFT stress (through the origin, below the fold's
surface); their forces against the DEM's. Calibration: the share of held-out runs whose slope lies
inside the 95 % interval of the map plus the slope's own standard error.
Runs: gamma >= 45 degrees (the README's 6 directions x 8 tilts = 48); ``--all-gammas`` also trains
on the others. The data are read from --data and never copied.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

import irft_torch as irft
from irft_torch import dem_data, metrics
from irft_torch.rft import Contacts, FourierStressMap


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


README_BARS = {"generic x LS scales (README)": (0.0166, 0.0173), "plain GP on run stresses (README)": (0.0153, 0.0125)}
IRFT = ("I-RFT", "I-RFT + physics mean")
BASELINES = ("generic x LS scales, fit to run stresses", "generic x LS scales, fit to forces",
             "plain GP on run stresses")


class RunData:
    """One run's angles, per-run stresses and (for a given surface offset) contacts and forces."""

    def __init__(self, run, min_depth: float) -> None:
        self.run = run
        self.angles = dem_data.canonical_angles(run)
        self.slope = np.array(dem_data.run_stress(run, min_depth))
        self.slope_se = np.array(dem_data.run_stress_se(run, min_depth))
        self._cache = {}

    def contacts(self, offset: float, stride: int):
        key = (round(offset, 6), stride)
        if key not in self._cache:
            c, f = dem_data.run_contacts(self.run, stride=stride, surface_offset=offset)
            rft_stress = np.array(dem_data.run_stress_rft(self.run, min_depth=0.0, surface_offset=offset))
            self._cache[key] = (c, f, rft_stress)
        return self._cache[key]


def residual_time_ms(runs, offset: float) -> tuple[float, float]:
    """Median integrated autocorrelation time (ms) of the per-run RFT force residuals, per axis."""
    taus = []
    for r in runs:
        c, f = dem_data.run_contacts(r, surface_offset=offset)
        if len(c) < 50:
            continue
        w = c.weight_z.sum(-1)
        fit = torch.stack([(f[:, k] * w).sum() / (w * w).sum() * w for k in range(2)], -1)
        dt_ms = float(np.median(np.diff(r.t))) * 1000
        taus.append([metrics.integrated_autocorrelation_time(f[:, k] - fit[:, k]) * dt_ms for k in range(2)])
    return tuple(np.median(np.array(taus), 0))


def generic_scales(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares scale per axis: target ~ s * pred."""
    return (pred * target).sum(0) / (pred * pred).sum(0)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="dem_validation.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--data", required=True, default=argparse.SUPPRESS,
                    help="directory of the DEM csv files (read, never copied)")
    ap.add_argument("--out", default="experiments/results", help="where the report and figures go")
    ap.add_argument("--stride", type=int, default=200, help="use every n-th 1 ms sample")
    ap.add_argument("--min-depth", type=float, default=1.0, help="cm, for the per-run slopes (the data README's 1)")
    ap.add_argument("--offset", default="auto",
                    help="effective surface below z_top, cm, or 'auto' (calibrated per fold on its training runs)")
    ap.add_argument("--n-iter", type=int, default=150, help="Adam steps per I-RFT fit")
    ap.add_argument("--all-gammas", action="store_true", help="also train on runs with gamma < 45 degrees")
    return ap


def main(argv=None) -> None:
    a = build_parser().parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")  # this script only writes files; set here, never at import
    torch.set_default_dtype(torch.float64)
    t0 = time.perf_counter()
    runs, report = dem_data.read_runs(a.data)
    print(f"read {len(runs)} runs; {report.summary()}")
    usable = [r for r in runs if (r.depth > a.min_depth).sum() >= 3]
    data = [RunData(r, a.min_depth) for r in usable]
    evaluated = [d for d in data if d.run.gamma_deg >= 45]
    trainable = data if a.all_gammas else evaluated
    betas = sorted({d.run.beta_deg for d in evaluated})
    generic = FourierStressMap.generic()
    names = IRFT + BASELINES
    rows = {n: [] for n in names}  # per held-out run: (pred (2,), std (2,) or None, slope, slope se, rft)
    force_err = {n: [] for n in names}
    offsets = {}
    fig_fold = None
    for beta in betas:
        train = [d for d in trainable if d.run.beta_deg != beta]
        test = [d for d in evaluated if d.run.beta_deg == beta]
        off = (dem_data.calibrate_surface_offset([d.run for d in train])[0] if a.offset == "auto"
               else float(a.offset))
        offsets[beta] = off
        parts = [d.contacts(off, a.stride) for d in train]
        ctr, ftr = Contacts.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
        models = {}
        for n, pm in zip(IRFT, ("zero", "physics")):
            torch.manual_seed(0)
            m = irft.InverseRFT(ctr, ftr, prior_mean=pm)
            m.fit(n_iter=a.n_iter, lr=0.05, progress=False)
            models[n] = m
        th = torch.tensor([d.angles for d in train])
        shape_train = generic(th[:, 0], th[:, 1]).numpy()
        slopes = np.array([d.slope for d in train])
        models[BASELINES[0]] = generic.scaled(*generic_scales(shape_train, slopes).tolist())
        g = irft.rft.forces(generic, ctr)
        models[BASELINES[1]] = generic.scaled(*((g * ftr).sum(0) / g.pow(2).sum(0)).tolist())
        one = torch.ones(len(train), 1)
        plain = irft.InverseRFT(Contacts(th[:, :1], th[:, 1:], one, one), torch.tensor(slopes))
        plain.fit(n_iter=a.n_iter, lr=0.05, progress=False)
        models[BASELINES[2]] = plain
        for d in test:
            c, f, rft_stress = d.contacts(off, a.stride)
            b, gm = torch.tensor([d.angles[0]]), torch.tensor([d.angles[1]])
            for n, m in models.items():
                if isinstance(m, irft.InverseRFT):
                    post = m.stress_map(b, gm)
                    pred, std = post.mean[0].detach().numpy(), post.stddev[0].detach().numpy()
                else:
                    pred, std = m(b, gm)[0].numpy(), None
                rows[n].append((pred, std, d.slope, d.slope_se, rft_stress))
                with torch.no_grad():
                    fp = m.predict_forces(c).mean if n in IRFT else irft.rft.forces(m, c)
                force_err[n].append((fp - f).numpy())
        if beta == 45.0:
            fig_fold = (models["I-RFT + physics mean"], train, test, off)
        elapsed = time.perf_counter() - t0
        print(f"held out beta {beta:g}: surface {off:.1f} cm below z_top ({elapsed:.0f} s)", flush=True)

    tau = residual_time_ms([d.run for d in trainable], float(np.median(list(offsets.values()))))
    elapsed = time.perf_counter() - t0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# I-RFT on independent DEM plate-intrusion data (leave-one-beta-out)", "",
             f"`python experiments/dem_validation.py --data DIR`: {len(evaluated)} held-out runs (gamma >= 45 deg), "
             f"training on {'all gammas' if a.all_gammas else 'gamma >= 45 deg'}, {len(betas)} folds, every "
             f"{a.stride} ms (force residual autocorrelation time {tau[0]:.0f} ms in x, {tau[1]:.0f} ms in z), "
             f"{a.n_iter} Adam steps; {elapsed:.0f} s. Reader: {report.summary()}.", "",
             "Effective surface below z_top per held-out beta (cm, calibrated on the fold's training runs): "
             + ", ".join(f"{b:g}: {o:.1f}" for b, o in offsets.items()) + ".", "",
             "| model | stress RMSE x, slope (N/cm^3) | z, slope | x, RFT stress | z, RFT stress "
             "| force RMSE x (N) | z (N) | 95 % coverage x | z |",
             "|---|---|---|---|---|---|---|---|---|"]
    summary = {}
    for n in names:
        P = np.array([r[0] for r in rows[n]])
        S = np.array([r[2] for r in rows[n]])
        SE = np.array([r[3] for r in rows[n]])
        R = np.array([r[4] for r in rows[n]])
        slope_rmse = np.sqrt(((P - S) ** 2).mean(0))
        rft_rmse = np.sqrt(((P - R) ** 2).mean(0))
        fe = np.concatenate(force_err[n])
        f_rmse = np.sqrt((fe**2).mean(0))
        if rows[n][0][1] is not None:
            std = np.array([r[1] for r in rows[n]])
            inside = (np.abs(P - S) <= 1.96 * np.sqrt(std**2 + SE**2)).mean(0)
            cov = f"{100 * inside[0]:.0f} % | {100 * inside[1]:.0f} %"
        else:
            cov = "- | -"
        summary[n] = slope_rmse
        lines.append(f"| {n} | {slope_rmse[0]:.4f} | {slope_rmse[1]:.4f} | {rft_rmse[0]:.4f} | {rft_rmse[1]:.4f} "
                     f"| {f_rmse[0]:.3f} | {f_rmse[1]:.3f} | {cov} |")
        print(lines[-1])
    for n, (x, z) in README_BARS.items():
        lines.append(f"| {n} | {x:.4f} | {z:.4f} | | | | | | |")
    se = np.array([d.slope_se for d in evaluated])
    th_all = torch.tensor([d.angles for d in evaluated])
    s_runs = generic_scales(generic(th_all[:, 0], th_all[:, 1]).numpy(), np.array([d.slope for d in evaluated]))
    parts = [dem_data.run_contacts(d.run, stride=a.stride, min_depth=a.min_depth) for d in evaluated]
    g_all = irft.rft.forces(generic, Contacts.cat([p[0] for p in parts]))
    f_all = torch.cat([p[1] for p in parts])
    s_forces = ((g_all * f_all).sum(0) / g_all.pow(2).sum(0)).numpy()
    best = min(summary, key=lambda n: summary[n].sum())
    lines += [
        "",
        f"Lowest slope-target RMSE (sum of axes): **{best}**. The per-run slopes are themselves noisy: their "
        f"standard errors (residual autocorrelation included) are {np.sqrt((se**2).mean(0))[0]:.4f} (x) and "
        f"{np.sqrt((se**2).mean(0))[1]:.4f} (z) N/cm^3 rms, a floor under any model's slope RMSE.",
        "",
        "Targets: 'slope' is the README's per-run stress (force against centre depth, with an intercept, depth > "
        f"{a.min_depth:g} cm, over the plate area); 'RFT stress' is what an RFT map means, F = alpha x depth x area "
        "through the origin, with depth below the fold's effective surface. Force RMSE is over every held-out sample "
        "below that surface. Coverage: held-out runs whose slope lies within 1.96 sqrt(map variance + slope SE^2).",
        "",
        "The README rows are its published figures. Its recipe, rerun here (the 'fit to run stresses' and plain GP "
        f"rows), does not reproduce them: on all {len(evaluated)} runs it gives generic-map scales of "
        f"{s_runs[0]:.3f} (x) and {s_runs[1]:.3f} (z), not the README's 0.27 and 0.18; those are closer to the "
        f"scales fitted to the force time series with depth below z_top ({s_forces[0]:.3f}, {s_forces[1]:.3f}).",
        "",
        "Angle mapping (DEM -> DESIGN.md): `irft_torch/dem_data.py` (beta_c = beta, gamma_c = gamma, x contribution "
        "flipped for motion toward -x).",
    ]
    if fig_fold is not None:
        from irft_torch import plotting

        m, train, test, off = fig_fold
        points = ([d.angles[0] for d in train], [d.angles[1] for d in train]), \
                 ([d.angles[0] for d in test], [d.angles[1] for d in test])
        fig = plotting.plot_posterior_map(m, 48, "I-RFT + physics mean (beta 45 held out)", points=points)
        plotting.save(fig, out / "dem_maps.png")
        fig, axes = plotting.plt.subplots(len(test), 2, figsize=(11, 2.2 * len(test)), constrained_layout=True)
        for k, d in enumerate(test):
            c, f, _ = d.contacts(off, a.stride)
            with torch.no_grad():
                pred = m.predict_forces(c, include_noise=True)
            lo, hi = pred.interval(0.95)
            for i in range(2):
                ax = axes[k, i]
                ax.plot(f[:, i].numpy(), "k.-", lw=1, ms=3, label="DEM")
                ax.plot(pred.mean[:, i].numpy(), "C1-", lw=1, label="I-RFT (held out)")
                ax.fill_between(range(len(c)), lo[:, i].numpy(), hi[:, i].numpy(), color="C1", alpha=0.2)
                ax.set_title(f"{d.run.label}: F_{'xz'[i]} (N)", fontsize=8)
        axes[0, 0].legend(fontsize=7)
        for ax in axes[-1]:
            ax.set_xlabel(f"sample (every {a.stride} ms, centre below the effective surface)")
        plotting.save(fig, out / "dem_forces_heldout.png")
        lines += ["", "Figures: `dem_maps.png` (learned maps and their std, training angle pairs as dots, the "
                  "held-out beta = 45 runs as stars), `dem_forces_heldout.png` (held-out runs: DEM forces and I-RFT's "
                  "prediction with its 95 % band)."]
    (out / "dem_validation.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out}/dem_validation.md ({time.perf_counter() - t0:.0f} s)")
    _ = math


if __name__ == "__main__":
    main()
