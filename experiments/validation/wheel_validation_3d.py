"""The rover wheels in 3-D: every run of both wheels at every slip angle (``wheel_validation.py --study 3d``).

Data: the rover-wheel runs and meshes (via wheel_validation.py --data DIR). Run time: 22 min for
both wheels with the defaults.

Each run (smooth: 190, grousered: 197; slip angle 0-90 deg, slip -1..0.9, 1-3 trials) is one observation
of its mean (longitudinal, lateral, vertical) force, with the 3-D contacts (``rft.contacts_3d``) of the wheel's
mesh from the data folder at the run's measured carriage speed, rim speed and sinkage (the authors' contact
rule: leading elements below the flat surface; docs/rft3d.md). Two held-out schemes, everything fitted on the
other levels (all trials):

- leave-one-slip-angle-out (7 folds: 0, 15, ..., 90 deg);
- leave-one-slip-out (9 folds: the commanded rim speeds 0 ... 100 mm/s, slip -1 ... 0.9).

Predictors of the held-out runs:

  I-RFT                     ``irft.InverseRFT(contacts_3d, forces)`` with its defaults (spectral backend here,
                            physical priors, MAP): alpha_y a third map over (beta, gamma), ``prior_mean="physics"``
                            (alpha_x and alpha_z's prior means Li et al.'s generic maps, one least-squares scale
                            each fitted on the training runs, alpha_y's zero: away from the training kinematics
                            the maps fall back on that scaled generic medium, not zero)
  ``--variants`` adds rows:
    zero                    every map zero-mean (``prior_mean="zero"``, the planar model's default)
    constant                alpha_y one constant (a rank-one term), the default mean
    physics_alpha_y         alpha_y's mean the scaled generic alpha_x(0, 0) too (``prior_mean="physics_alpha_y"``)
  generic x LS per axis     the generic Li et al. map in the same 3-D RFT (alpha_y = alpha_x(0, 0)) with one
                            least-squares scale per force axis fitted on the training runs
  others' RFT (files)       the data authors' 3-D RFT prediction (generic x 0.6, commanded speeds)
  trivial                   the training runs' mean force

RMSE [N] per axis (longitudinal / lateral / vertical), per held-out level and over all runs, 95 % coverage of
I-RFT's held-out intervals (measurement noise included). Figures: each force vs slip angle and vs slip with the
held-out I-RFT intervals, and the maps learned from all runs with their posterior std.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from irft_torch.data import wheel as wd
from irft_torch.gp import Engine, MapPrior
from irft_torch.gp.inverse3d import InverseRFT3D
from irft_torch.gp.inverse3d.features import SpectralFeatureBank
from irft_torch.gp.kernels.fourier import MAX_HARMONICS
from irft_torch.rft import FourierStressMap, contacts_3d, forces_3d

AXES = ("longitudinal", "lateral", "vertical")
IRFT, IRFT_Z, IRFT_C, IRFT_PY = ("I-RFT", "I-RFT (zero mean)", "I-RFT (alpha_y constant)",
                                 "I-RFT (alpha_y mean too)")
GEN, AUTH, MEAN = "generic x LS per axis", "others' RFT (files)", "trivial (training mean)"
ALL_VARIANTS = {"default": (IRFT, "map", "physics"), "zero": (IRFT_Z, "map", "zero"),
                "constant": (IRFT_C, "constant", "physics"),
                "physics_alpha_y": (IRFT_PY, "map", "physics_alpha_y")}  # --variants: row, alpha_y, prior mean
VARIANTS = {IRFT: ("map", "physics")}  # the rows run (set from --variants by ``run``)
ROWS = (*VARIANTS, GEN, AUTH, MEAN)


def _choose_variants(names: str) -> None:
    """--variants "zero,constant" -> the I-RFT rows of this run, the default row first (module-wide: a script)."""
    global VARIANTS, ROWS
    keys = ["default"] + [k.strip() for k in names.split(",") if k.strip() and k.strip() != "default"]
    bad = [k for k in keys if k not in ALL_VARIANTS]
    if bad:
        raise SystemExit(f"--variants {names!r}: choose from {sorted(set(ALL_VARIANTS) - {'default'})}")
    VARIANTS = {ALL_VARIANTS[k][0]: ALL_VARIANTS[k][1:] for k in keys}
    ROWS = (*VARIANTS, GEN, AUTH, MEAN)
SCHEMES = ("slip angle", "slip")


def wheel_data_3d(data: Path, wheel: str) -> dict:
    runs = wd.read_wheel_runs(data, wheel, None)
    mesh = wd.read_wheel_mesh(data, wheel)
    c = contacts_3d(mesh, **wd.wheel_motion(runs))
    F = torch.tensor([[r.force[0], r.lateral, r.force[1]] for r in runs])
    A = torch.tensor([[r.rft_force[0], r.rft_lateral, r.rft_force[1]] for r in runs])
    G = forces_3d(FourierStressMap.generic(), c)  # unit zeta, alpha_y = alpha_x(0, 0)
    psi = np.array([r.slip_angle_deg for r in runs])
    levels = sorted({r.commanded_rim_speed for r in runs})
    groups = {"slip angle": np.searchsorted(np.unique(psi), psi),
              "slip": np.array([levels.index(r.commanded_rim_speed) for r in runs])}
    return dict(runs=runs, c=c, F=F, authors=A, G=G, psi=psi, slip=np.array([r.slip for r in runs]), groups=groups,
                bank=SpectralFeatureBank(c, ahead=MAX_HARMONICS))


def model_options(args) -> tuple[dict, dict]:
    """The constructor's and fit's options this run passes: none but those given on the command line (the study
    runs with the library's defaults; ``--method``, ``--tol``, ``--harmonics``, ``--n-iter``, ``--lr``,
    ``--li-basis``, ``--hyper-posterior`` to ask for others)."""
    engine = {k: getattr(args, a, None) for k, a in (("method", "method"), ("tol", "tol"),
                                                     ("max_harmonics", "harmonics"))}
    engine = {k: v for k, v in engine.items() if v is not None}
    given = {"hyper_posterior": getattr(args, "hyper_posterior", None), "engine": Engine(**engine) if engine else None}
    if getattr(args, "li_basis", None) is not None:
        given["kernel"] = "li" if args.li_basis else "rbf"
    fit_given = {k: getattr(args, k, None) for k in ("n_iter", "lr")}
    return ({k: v for k, v in given.items() if v is not None}, {k: v for k, v in fit_given.items() if v is not None})


def fit(d: dict, idx: np.ndarray, alpha_y: str, args, prior_mean: str = "physics") -> InverseRFT3D:
    i = torch.as_tensor(idx)
    options, fit_options = model_options(args)
    options = dict(options)
    prior = MapPrior(kernel=options.pop("kernel", None), mean=prior_mean)
    model = InverseRFT3D(d["c"][i], d["F"][i], alpha_y=alpha_y, features=d["bank"].rows(i), prior=prior,
                         **options)  # features: the folds' spectral features cut from one pass (the same numbers)
    model.fit(progress=False, **fit_options)
    return model


def evaluate(d: dict, scheme: str, args) -> dict:
    """Held-out predictions of every row for one scheme: mean (n, 3) and, for I-RFT, variance with noise."""
    F, G, group = d["F"], d["G"], d["groups"][scheme]
    pred = {k: torch.full_like(F, math.nan) for k in ROWS}
    var = {k: torch.full_like(F, math.nan) for k in VARIANTS}
    pred[AUTH] = d["authors"].clone()
    for g in range(int(group.max()) + 1):
        test, train = np.nonzero(group == g)[0], np.nonzero(group != g)[0]
        tr, te = torch.as_tensor(train), torch.as_tensor(test)
        scale = (F[tr] * G[tr]).sum(0) / G[tr].pow(2).sum(0).clamp_min(1e-300)
        pred[GEN][te] = scale * G[te]
        pred[MEAN][te] = F[tr].mean(0)
        for name, (ay, mean) in VARIANTS.items():
            model = fit(d, train, ay, args, mean)
            p = model.predict_forces(d["c"][te], include_noise=True)
            pred[name][te], var[name][te] = p.mean, p.variance
    return {"pred": pred, "var": var}


def rmse(err: torch.Tensor) -> list[float]:
    return err.pow(2).mean(0).sqrt().tolist()


def tables(d: dict, res: dict, scheme: str) -> tuple[dict, dict, dict]:
    """Per level and overall RMSE (N, per axis) of every row, and I-RFT's 95 % coverage overall."""
    F, group = d["F"], d["groups"][scheme]
    per_level, overall, coverage = {}, {}, {}
    for k in ROWS:
        e = res["pred"][k] - F
        overall[k] = rmse(e)
        per_level[k] = [rmse(e[torch.as_tensor(group == g)]) for g in range(int(group.max()) + 1)]
    for k in VARIANTS:
        z = (res["pred"][k] - F).abs() / res["var"][k].sqrt()
        coverage[k] = (z < 1.96).double().mean(0).tolist()
    return per_level, overall, coverage


def level_names(d: dict, scheme: str) -> list[str]:
    group = d["groups"][scheme]
    key = d["psi"] if scheme == "slip angle" else d["slip"]
    unit = " deg" if scheme == "slip angle" else ""
    return [f"{key[group == g].mean():+.2f}{unit}" if unit == "" else f"{key[group == g].mean():.0f}{unit}"
            for g in range(int(group.max()) + 1)]


def plot_forces(d: dict, results: dict, wheel: str, out: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5), constrained_layout=True)
    for row, scheme in enumerate(SCHEMES):
        res = results[scheme]
        x = d["psi"] if scheme == "slip angle" else d["slip"]
        width = 2.5 if scheme == "slip angle" else 0.025
        for a, ax in enumerate(axes[row]):
            off = {"measured": 0.0, IRFT: -1.0, AUTH: 1.0, GEN: 2.0}
            ax.plot(x, d["F"][:, a], "k.", ms=5, label="measured", zorder=3)
            m, s = res["pred"][IRFT][:, a], res["var"][IRFT][:, a].sqrt()
            ax.errorbar(x + off[IRFT] * width, m, yerr=1.96 * s, fmt="o", ms=3, color="C0", elinewidth=0.8, alpha=0.8,
                        label="I-RFT held out, 95 % interval")
            ax.plot(x + off[AUTH] * width, res["pred"][AUTH][:, a], "x", ms=4, color="C3", label=AUTH)
            ax.plot(x + off[GEN] * width, res["pred"][GEN][:, a], "+", ms=5, color="C2", label=GEN)
            ax.set_xlabel("slip angle [deg]" if scheme == "slip angle" else "slip")
            ax.set_ylabel(f"{AXES[a]} force [N]")
            ax.set_title(f"{AXES[a]}, leave-one-{scheme}-out")
            ax.grid(alpha=0.3)
        axes[row, 0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{wheel} wheel: held-out forces of every run (3-D)")
    fig.savefig(out / f"wheel3d_forces_{wheel}.png", dpi=110)
    plt.close(fig)


def plot_maps(models: dict, out: Path) -> None:
    import matplotlib.pyplot as plt

    n = 61
    b = torch.linspace(-math.pi / 2, math.pi / 2, n)
    g = torch.linspace(-math.pi / 2, math.pi / 2, n)
    B, Gm = torch.meshgrid(b, g, indexing="ij")
    fig, axes = plt.subplots(2 * len(models), 3, figsize=(13, 4.2 * len(models)), constrained_layout=True)
    for w, (wheel, model) in enumerate(models.items()):
        post = model.stress_map(B, Gm)
        for i, name in enumerate(("alpha_x", "alpha_y", "alpha_z")):
            for r, (what, val) in enumerate((("mean", post.mean[..., i]), ("posterior std", post.stddev[..., i]))):
                ax = axes[2 * w + r, i]
                im = ax.pcolormesh(np.degrees(b), np.degrees(g), val.T.numpy(), shading="auto",
                                   cmap="RdBu_r" if what == "mean" else "viridis")
                if what == "mean":
                    lim = float(val.abs().max())
                    im.set_clim(-lim, lim)
                fig.colorbar(im, ax=ax, label="N/cm^3")
                ax.set_title(f"{wheel}: {name} {what}")
                ax.set_xlabel("beta [deg]")
                ax.set_ylabel("gamma [deg]")
    means = "; ".join(f"{w}: generic x ({', '.join(f'{v:.2f}' for v in m.mean_scales.tolist())})"
                      for w, m in models.items() if m.mean_scales is not None)
    fig.suptitle("Posterior of the maps from all runs (the GP plus its prior mean" +
                 (f";\nscales of the generic maps (s_x, s_y, s_z) = {means})" if means else ")"))
    fig.savefig(out / "wheel3d_maps.png", dpi=100)
    plt.close(fig)


def run(data: Path, out: Path, args, wheels=("smooth", "grouser")) -> str:
    _choose_variants(getattr(args, "variants", ""))
    t0 = time.perf_counter()
    lines = ["## 3-D: every run, every slip angle (issue 31)", ""]
    options, fit_options = model_options(args)
    shown = {("prior" if k == "kernel" else k): (f"MapPrior(kernel={v!r})" if k == "kernel" else repr(v))
             for k, v in options.items()}
    lines += [f"I-RFT: `InverseRFT(contacts_3d, forces{''.join(f', {k}={v}' for k, v in shown.items())})"
              f".fit({', '.join(f'{k}={v!r}' for k, v in fit_options.items())})`"
              + (" (the constructor's defaults)" if not options and not fit_options else ""), ""]
    models, summary = {}, {}
    for wheel in wheels:
        print(f"3-D {wheel} wheel ...", flush=True)
        d = wheel_data_3d(data, wheel)
        results = {s: evaluate(d, s, args) for s in SCHEMES}
        plot_forces(d, results, wheel, out)
        alpha_y, mean = VARIANTS[IRFT]  # the default row's
        models[wheel] = fit(d, np.arange(len(d["runs"])), alpha_y, args, mean)
        lines += [f"### {wheel} wheel ({len(d['runs'])} runs, {d['c'].n_elements} contact elements at most per run)",
                  ""]
        for scheme in SCHEMES:
            per_level, overall, cov = tables(d, results[scheme], scheme)
            summary[(wheel, scheme)] = overall
            names = level_names(d, scheme)
            lines += [f"Leave-one-{scheme}-out, RMSE [N] longitudinal / lateral / vertical:", "",
                      "| held out | " + " | ".join(ROWS) + " |", "|---" * (len(ROWS) + 1) + "|"]
            for i, nm in enumerate(names):
                lines.append(f"| {nm} | " + " | ".join("{:.2f} / {:.2f} / {:.2f}".format(*per_level[k][i])
                                                       for k in ROWS) + " |")
            lines.append("| **all** | " + " | ".join("**{:.2f} / {:.2f} / {:.2f}**".format(*overall[k])
                                                     for k in ROWS) + " |")
            lines += ["", "95 % coverage held out (noise included): " + "; ".join(
                f"{k} {100 * cov[k][0]:.0f} / {100 * cov[k][1]:.0f} / {100 * cov[k][2]:.0f} %" for k in VARIANTS), ""]
    plot_maps(models, out)
    lines += _bars(summary, IRFT), ""
    lines += ["Kernel truncation of the all-runs fits (relative, per map; tolerance "
              f"{next(iter(models.values())).tol:.0e}): " + "; ".join(
                  f"{w}: {', '.join(f'{v:.1e}' for v in m.truncation_error().tolist())}"
                  for w, m in models.items()), ""]
    lines += [f"Fitted hyperparameters (all runs, alpha_y={VARIANTS[IRFT][0]!r}, prior_mean={VARIANTS[IRFT][1]!r}): "
              + "; ".join(
        f"{w}: {m.hyperparameters()}" for w, m in models.items()), "",
        "Prior mean scales of the generic maps (s_x, s_y, s_z), all runs: " + "; ".join(
            f"{w}: {', '.join(f'{v:.3f}' for v in m.mean_scales.tolist())}" for w, m in models.items()
            if m.mean_scales is not None), "",
        f"Time: {time.perf_counter() - t0:.0f} s (2 CPU cores). Figures: wheel3d_forces_{{smooth,grouser}}.png, "
        "wheel3d_maps.png."]
    return "\n".join(lines)


def _bars(summary: dict, row: str) -> str:
    """The issue's bars, overall per wheel and scheme: I-RFT (the default row) below the others' RFT and the scaled
    generic map on all axes, below the training mean on longitudinal and lateral."""
    out = [f"The issue's bars (overall RMSE, the row {row}):", ""]
    for (wheel, scheme), o in summary.items():
        best = o[row]
        checks = [all(best[a] < o[AUTH][a] for a in range(3)), all(best[a] < o[GEN][a] for a in range(3)),
                  all(best[a] < o[MEAN][a] for a in range(2)), best[2] < o[MEAN][2]]
        out.append(f"- {wheel}, leave-one-{scheme}-out: below others' RFT on all axes: {checks[0]}; below generic x LS "
                   f"on all axes: {checks[1]}; below the training mean, longitudinal and lateral: {checks[2]}; "
                   f"vertical below the training mean: {checks[3]} ({best[2]:.2f} vs {o[MEAN][2]:.2f} N)")
    return "\n".join(out)
