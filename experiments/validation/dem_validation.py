"""Does I-RFT learn a real granular medium better than the generic RFT map and a plain GP? Leave-one-beta-out
and leave-one-gamma-out on independent DEM plate-intrusion simulations.

Data: the DEM plate-intrusion runs (--data DIR, e.g. ../shared/data/dem_plate_intrusion; not shipped).
Run time: about 2 min (123 s on 2 cores, 2026-12-03, with the default model since 2026-11-28: Li et al.'s term and
the Laplace posterior; 38-40 s on 2026-11-25 before it); --cv-refit 109 s on 2026-11-25, not measured since.

    python experiments/validation/dem_validation.py --data ../shared/data/dem_plate_intrusion
        [--out experiments/results]

The target is the data README's, exactly: each run's stress per depth *through the origin*
(F = s x depth, no intercept, over the samples whose centre is deeper than 1 cm below z_top, s over
the plate area), for F_x and F_z, all 54 runs. The README's other target (the slope with an
intercept) is reported beside it. For each held-out tilt (LOBO, 8 folds) and each held-out
direction (LOGO, 9 folds), everything is fitted on the other runs only:

  * generic x LS scales: the Li et al. generic map with one least-squares scale per axis, fitted to
    the training runs' stresses of the target being scored (the README's first baseline);
  * generic x LS scales, fit to forces: the same scales fitted to the force time series (the usual
    RFT calibration);
  * plain GP on run stresses: an exact GP (ARD RBF on the angle embedding, learned noise, 300 Adam
    steps, the plain marginal likelihood: ``priors=None``) on the training runs' stresses of the
    target being scored (the README's second baseline);
  * I-RFT (zero mean, the paper's model: the default) and I-RFT + physics mean, fitted to the force
    time series of the training runs (the plate cut into 10 segments, centre deeper than 1 cm below
    z_top, the free surface at z_top: the surface the target is defined with; the library's default
    physical hyperparameter priors). Their prediction of a held-out run's target is the README's
    recipe applied to the forces they predict for that run (``data.dem.recipe_functional``: one
    linear functional, so its posterior mean and variance are exact);
  * I-RFT, learned surface: zero mean, the free surface learned with the maps (``gp.surface.offset``: one
    offset for the bed per fold, started at the best of a grid), on every tau-th sample, tau the
    training runs' median force-residual autocorrelation time; its prediction of a held-out run
    uses the recipe on the forces it predicts at its learned surface;
  * I-RFT, mean per axis by grouped CV: per axis, the zero-mean or the physics-mean fit, whichever
    predicts the training runs' stresses better with each training tilt (LOBO) or direction (LOGO)
    left out in turn (``model.cross_validate``, no refit): the choice made on the training runs alone.

The force noise of I-RFT is white; the DEM's is not (force chains: slow, run-long fluctuations), so
the sampling stride sets how much one run's stress is trusted. ``--stride auto`` (default) picks it per
fold from the training runs alone: the stride at which the noise I-RFT sees on a run's stress
(pooled force residual variance / sum of squared weights) equals the scatter of the training runs'
stresses about a smooth map (the plain GP's learned noise on them). Held-out forces are scored on
every ``--eval-stride`` ms of the held-out runs (centre deeper than 1 cm below z_top). Coverage: the
share of held-out runs whose target lies inside the 95 % predictive interval (the map's posterior on
the target plus the run's own noise). The data are read from --data and never copied.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

import irft_torch as irft
from irft_torch import metrics
from irft_torch.data import dem
from irft_torch.gp.backends.pairs import PairsBackend
from irft_torch.rft import Contacts, FourierStressMap
from irft_torch.studies.workers import worker_context


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


TARGETS = {"origin": "through the origin (README)", "intercept": "slope with an intercept"}
LEARNED = "I-RFT, learned surface"
CV = "I-RFT, mean per axis by grouped CV"
FITTED = ("I-RFT", "I-RFT + physics mean", LEARNED)  # each its own fit; the CV row takes each axis from one of
IRFT = FITTED + (CV,)                                # the first two
DEFAULT = "I-RFT"
BASELINES = ("generic x LS scales", "generic x LS scales, fit to forces", "plain GP on run stresses")
SPLITS = {"beta": "leave-one-beta-out", "gamma": "leave-one-gamma-out"}
# The data README's figures (its recipe, leave-one-beta-out, all 54 runs), per target: (x, z) N/cm^3.
README_FIGURES = {"origin": {"generic x LS scales": (0.0166, 0.0173), "plain GP on run stresses": (0.0149, 0.0120)},
                  "intercept": {"plain GP on run stresses": (0.0468, 0.0213)}}


class RunData:
    """One run: its canonical angles, its two per-run stress targets, and cached contacts."""

    def __init__(self, run, min_depth: float) -> None:
        self.run = run
        self.min_depth = min_depth
        self.angles = dem.canonical_angles(run)
        self.target = {"origin": np.array(dem.run_stress_origin(run, min_depth)),
                       "intercept": np.array(dem.run_stress(run, min_depth))}
        self._cache = {}

    def contacts(self, offset: float, stride: int):
        """(contacts, forces) of every ``stride``-th sample whose centre is deeper than min_depth below z_top,
        the depths of the segments measured from the surface ``z_top - offset``."""
        key = ("c", round(offset, 6), stride)
        if key not in self._cache:
            self._cache[key] = dem.run_contacts(self.run, stride=stride, min_depth=self.min_depth - offset,
                                                     surface_offset=offset)
        return self._cache[key]

    def functional(self, target: str, offset: float) -> Contacts:
        key = ("f", target, round(offset, 6))
        if key not in self._cache:
            self._cache[key] = dem.recipe_functional(self.run, self.min_depth, target == "intercept", offset)
        return self._cache[key]

    def coef_sq(self, target: str) -> float:
        """sum_t coef_t^2 of the recipe (1/cm^6): the recipe's variance per unit of white 1 ms force noise."""
        _, coef = dem.stress_functional(self.run, self.min_depth, target == "intercept")
        return float(coef @ coef)


class _RunEffectPairs(PairsBackend):
    """The pairs backend with a per-run random stress: F_t = sum_m w_tm (alpha(theta_tm) + delta_run), delta ~
    N(0, tau^2) per axis, independent between runs. Each DEM run has its own angle pair, so this is
    Sigma = K_UU + tau^2 I (a nugget on the map at the training pairs); tau^2 is learned with the rest by the
    marginal likelihood (``hypers.raw_run_effect``, registered by ``fit_run_effect``). An experiment-only
    variant (``--run-effect``): no backend of the library has this hyperparameter yet."""

    def _apply_sigma(self, X):
        return X @ self._K() + run_effect_variance(self.hypers)[:, None, None] * X


LI_FLAG = {True: " --li-basis", False: " --no-li-basis", None: ""}  # how a run's li_basis choice is written


def run_effect_variance(hypers) -> torch.Tensor:
    """tau^2 (2,) in (N/cm^3)^2: softplus of the raw parameter times the map's prior variance scale."""
    return torch.nn.functional.softplus(hypers.raw_run_effect) * hypers.run_effect_scale


def fit_run_effect(c: Contacts, f: torch.Tensor, prior_mean: str, n_iter: int) -> irft.InverseRFT:
    """I-RFT in the pairs space with a per-run random stress (see ``_RunEffectPairs``)."""
    m = irft.InverseRFT(c, f, prior=irft.MapPrior(kernel="rbf", mean=prior_mean), engine="pairs", hyper_posterior="map")
    h = m.hypers
    h.register_parameter("raw_run_effect", torch.nn.Parameter(torch.zeros(2, dtype=h.outputscale.dtype)))
    h.run_effect_scale = h.outputscale.detach().clone()
    m.backend.__class__ = _RunEffectPairs
    m.backend._post_cache = None
    m.fit(n_iter=n_iter, lr=0.05, progress=False)
    return m


def generic_scales(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares scale per axis: target ~ s * pred."""
    return (pred * target).sum(0) / (pred * pred).sum(0)


def plain_gp(train: list[RunData], target: str, n_iter: int) -> irft.InverseRFT:
    """Exact GP on the training runs' stresses: each run one observation of the map at its angles."""
    th = torch.tensor([d.angles for d in train])
    one = torch.ones(len(train), 1)
    y = torch.tensor(np.array([d.target[target] for d in train]))
    # the README's plain exact GP: ML-II on the plain marginal likelihood (no hyperparameter priors)
    m = irft.InverseRFT(Contacts(th[:, :1], th[:, 1:], one, one), y,
                        prior=irft.MapPrior(kernel="rbf", hyperpriors=None), hyper_posterior="map")
    torch.manual_seed(0)
    m.fit(n_iter=n_iter, lr=0.05, progress=False)
    return m


def matched_stride(train: list[RunData], scatter: np.ndarray, offset: float) -> tuple[int, np.ndarray]:
    """The stride (ms) at which white force noise puts as much noise on a run's stress as the runs' scatter.

    A run's least-squares stress on n samples with weights W_t has noise variance sigma^2 / sum W_t^2;
    thinning the 1 ms series by s divides sum W^2 by s. With sigma^2 the pooled residual variance of
    per-run fits through the origin, s = scatter / (sigma^2 mean_r 1 / sum_t W_rt^2), per axis; one
    stride for both axes (geometric mean), between 5 and 1000 ms. Training runs only."""
    rss, n, inv = np.zeros(2), 0, []
    for d in train:
        c, f = d.contacts(offset, 1)
        w = c.weight_z.sum(-1).numpy()
        F = f.numpy()
        a = (F * w[:, None]).sum(0) / (w @ w)
        rss += ((F - a * w[:, None]) ** 2).sum(0)
        n += len(w)
        inv.append(1.0 / (w @ w))
    per_axis = scatter / (rss / n * np.mean(inv))
    return int(np.clip(round(float(np.sqrt(np.prod(per_axis)))), 5, 1000)), per_axis


def residual_time_ms(data: list[RunData], offset: float) -> tuple[float, float]:
    """Median integrated autocorrelation time (ms) of the per-run through-origin force residuals, per axis."""
    taus = []
    for d in data:
        c, f = d.contacts(offset, 1)
        w = c.weight_z.sum(-1)
        fit = torch.stack([(f[:, k] * w).sum() / (w * w).sum() * w for k in range(2)], -1)
        taus.append([metrics.integrated_autocorrelation_time(f[:, k] - fit[:, k]) for k in range(2)])
    return tuple(np.median(np.array(taus), 0))


def mean_by_cross_validation(models: dict, train: list[RunData], parts: list, split: str, refit: bool = False,
                             n_iter: int = 300) -> tuple[np.ndarray, ...]:
    """Per axis, the prior mean (zero or physics) whose fitted model predicts the training runs better
    when each training ``split`` value (a tilt or a direction) is left out in turn (``gp.cross_validate``,
    at the fitted hyperparameters: no refit), the question the outer fold asks, on the training runs
    alone (``refit``: each candidate refitted without the left-out value, ``n_iter`` Adam steps at 0.05, as
    the fits; ``--cv-refit``). Criterion: the RMSE over the training runs of each run's least-squares stress through the
    origin (sum_t w_t F_t / sum_t w_t^2 on its samples, w_t the weight sum: the scored target's recipe on
    the fit's samples) from the held-out predicted forces, each run counted once. Reported beside it,
    the held-out force RMSE pooled over samples (the criterion tried first: the large forces of the
    flat plate, beta = 0, decide it). Returns (choice (2,) 0 zero / 1 physics, stress RMSE (2, 2) N/cm^3,
    force RMSE (2, 2) N), rows (zero, physics)."""
    key = [d.run.beta_deg if split == "beta" else d.run.gamma_deg for d in train]
    groups = np.concatenate([np.full(len(p[1]), k) for k, p in zip(key, parts)])
    cvs = [models[n].cross_validate(groups, refit=refit, n_iter=n_iter, lr=0.05) for n in IRFT[:2]]
    stress = np.zeros((2, 2))
    for i, cv in enumerate(cvs):
        err, start = [], 0
        for c, f in parts:
            w = torch.stack([c.weight_x.sum(-1), c.weight_z.sum(-1)], -1)  # (T_run, 2) cm^3
            sl = slice(start, start + len(f))
            err.append(((w * cv.residual[sl]).sum(0) / w.pow(2).sum(0)).numpy())
            start += len(f)
        stress[i] = np.sqrt((np.array(err) ** 2).mean(0))
    force = np.stack([cv.rmse().numpy() for cv in cvs])
    return stress.argmin(0), stress, force


def run_fold(train: list[RunData], test: list[RunData], a, split: str = "beta") -> tuple[dict, dict]:
    """Fit every model on ``train``; predict the held-out runs' targets and forces.

    Returns (predictions: model -> target -> list of (mean (2,), var (2,) or None) per test run,
    info: offset, stride, models)."""
    generic = FourierStressMap.generic()
    off = (dem.calibrate_surface_offset([d.run for d in train])[0] if a.offset == "auto" else float(a.offset))
    th = torch.tensor([d.angles for d in train])
    shape = generic(th[:, 0], th[:, 1]).numpy()
    out = {n: {t: [] for t in TARGETS} for n in IRFT + BASELINES}
    forces = {n: [] for n in IRFT + BASELINES}
    plains = {t: plain_gp(train, t, a.plain_iter) for t in TARGETS}
    scatter = plains["origin"].hypers.noise.detach().numpy()
    stride, _ = matched_stride(train, scatter, off) if a.stride == "auto" else (int(a.stride), None)
    parts = [d.contacts(off, stride) for d in train]
    ctr, ftr = Contacts.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    models, offs, off_std = {}, {n: off for n in IRFT}, {n: None for n in IRFT}
    for n, pm in zip(IRFT[:2], ("zero", "physics")):
        torch.manual_seed(getattr(a, "seed", 0))  # each fit's own stream: the same numbers whichever worker runs it
        if a.run_effect:
            models[n] = fit_run_effect(ctr, ftr, pm, a.n_iter)
            continue
        with_shape = bool(getattr(a, "generic_shape", False))
        kernel = "li+generic" if with_shape else ("rbf" if getattr(a, "li_basis", None) is False else "li")
        m = irft.InverseRFT(ctr, ftr, prior=irft.MapPrior(kernel=kernel, mean=pm),  # the rest: the defaults
                            hyper_posterior=getattr(a, "hyper_posterior", None))
        m.fit(n_iter=a.n_iter, lr=0.05, progress=False)
        models[n] = m
    # The learned surface (gp.surface.offset): one offset for the bed, fitted with the maps. Its force residuals are
    # smaller than at z_top, so the stride matched at z_top does not apply; it takes every tau-th sample, tau the
    # training runs' median integrated autocorrelation time of the force residuals (nearly independent samples
    # for the white-noise model), and starts the offset at the best of a grid (the likelihood has shoulders).
    n = LEARNED
    if a.stride == "auto":
        stride_l = int(np.clip(round(float(np.mean(residual_time_ms(train, off)))), 5, 1000))
    else:
        stride_l = int(a.stride)
    parts_l = [d.contacts(off, stride_l) for d in train]
    c_l, f_l = Contacts.cat([p[0] for p in parts_l]), torch.cat([p[1] for p in parts_l])
    torch.manual_seed(0)
    m = irft.InverseRFT(c_l, f_l, surface=True)
    m.init_surface(torch.linspace(-0.03, 0.01, 17))
    m.fit(n_iter=a.n_iter, lr=0.05, progress=False)
    est = m.surface_offset.in_cm()  # cm, positive when the surface is above the stated one
    offs[n], off_std[n] = off - float(est.mean[0]), float(est.std[0])
    models[n] = m
    g = irft.rft.forces(generic, ctr)
    fitted = generic.scaled(*((g * ftr).sum(0) / g.pow(2).sum(0)).tolist())
    scaled = {t: generic.scaled(*generic_scales(shape, np.array([d.target[t] for d in train])).tolist())
              for t in TARGETS}
    if a.run_effect:  # the run effect lives in the backend class; cross-validation would drop it
        choice, cv_rmse, cv_force = np.zeros(2, dtype=int), None, None
    else:
        choice, cv_rmse, cv_force = mean_by_cross_validation(models, train, parts, split, a.cv_refit, a.n_iter)
    for d in test:
        b, gm = torch.tensor([d.angles[0]]), torch.tensor([d.angles[1]])
        c_eval, f_eval = d.contacts(off, a.eval_stride)
        c_top, _ = d.contacts(0.0, a.eval_stride)  # the target's own law: F = s x depth below z_top
        w_top = torch.stack([c_top.weight_x.sum(-1), c_top.weight_z.sum(-1)], -1)
        for t in TARGETS:
            with torch.no_grad():
                for n in FITTED:
                    m = models[n]
                    fn = d.functional(t, offs[n])  # the recipe on forces predicted at the model's surface
                    p = m.predict_forces(fn)
                    # the run's own noise on its stress: white noise of variance sigma^2 every `stride` ms
                    noise = m.hypers.noise.detach().numpy() * (stride_l if n == LEARNED else stride) * d.coef_sq(t)
                    if a.run_effect and n != LEARNED:  # the held-out run's own random stress, through the recipe
                        k = torch.stack([fn.weight_x.sum(), fn.weight_z.sum()])
                        noise = noise + (run_effect_variance(m.hypers) * k**2).detach().numpy()
                    out[n][t].append((p.mean[0].numpy(), p.variance[0].numpy() + noise))
                out[BASELINES[0]][t].append((scaled[t](b, gm)[0].numpy(), None))
                out[BASELINES[1]][t].append((irft.rft.forces(fitted, d.functional(t, off))[0].numpy(), None))
                post = plains[t].stress_map(b, gm)
                out[BASELINES[2]][t].append((post.mean[0].detach().numpy(),
                                             (post.variance[0] + plains[t].hypers.noise).detach().numpy()))
        with torch.no_grad():
            for n in FITTED:
                c_n, f_n = d.contacts(offs[n], a.eval_stride) if offs[n] != off else (c_eval, f_eval)
                forces[n].append((models[n].predict_forces(c_n).mean - f_n).numpy())
            forces[BASELINES[0]].append((irft.rft.forces(scaled["origin"], c_top) - f_eval).numpy())
            forces[BASELINES[1]].append((irft.rft.forces(fitted, c_eval) - f_eval).numpy())
            s = plains["origin"].stress_map(b, gm).mean[0].detach()
            forces[BASELINES[2]].append((w_top * s - f_eval).numpy())
    # the two maps are independent GPs (own hyperparameters, noise not tied): each axis from the chosen model
    for t in TARGETS:
        out[CV][t] = [tuple(np.where(choice == 1, p, z) for z, p in zip(rz, rp))
                      for rz, rp in zip(out[IRFT[0]][t], out[IRFT[1]][t])]
    forces[CV] = [np.where(choice == 1, p, z) for z, p in zip(forces[IRFT[0]], forces[IRFT[1]])]
    return out, {"offset": off, "learned": (offs[LEARNED], off_std[LEARNED], stride_l), "stride": stride,
                 "models": models, "forces": forces, "cv": (choice, cv_rmse, cv_force)}


def score(data: list[RunData], folds: list[tuple[float, list[int]]], preds: dict, force_err: dict) -> dict:
    """Per model: RMSE per target (2,), coverage per target (2,) or None, force RMSE (2,)."""
    res = {}
    for n in preds:
        r = {}
        for t in TARGETS:
            flat = [x for fold in preds[n][t] for x in fold]
            S = np.array([data[i].target[t] for _, idx in folds for i in idx])
            P = np.array([x[0] for x in flat])
            r[f"rmse_{t}"] = np.sqrt(((P - S) ** 2).mean(0))
            if flat[0][1] is not None:
                V = np.array([x[1] for x in flat])
                r[f"cover_{t}"] = (np.abs(P - S) <= 1.96 * np.sqrt(V)).mean(0)
            else:
                r[f"cover_{t}"] = None
            r[f"pred_{t}"], r[f"var_{t}"] = P, (None if flat[0][1] is None else V)
        r["force_runs"] = [e for fold in force_err[n] for e in fold]  # per held-out run (T_i, 2) N
        fe = np.concatenate(r["force_runs"])
        r["force"] = np.sqrt((fe**2).mean(0))
        res[n] = r
    return res


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="dem_validation.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--data", required=True, default=argparse.SUPPRESS,
                    help="directory of the DEM csv files (read, never copied)")
    ap.add_argument("--out", default="experiments/results", help="where the report and figures go")
    ap.add_argument("--stride", default="auto",
                    help="I-RFT: use every n-th 1 ms sample, or 'auto' (matched per fold on its training runs)")
    ap.add_argument("--eval-stride", type=int, default=10, help="held-out force samples: every n-th 1 ms sample")
    ap.add_argument("--min-depth", type=float, default=1.0, help="cm below z_top: the data README's 1")
    ap.add_argument("--offset", default="0",
                    help="I-RFT's free surface below z_top, cm, or 'auto' (calibrated per fold on its training runs)")
    ap.add_argument("--n-iter", type=int, default=300, help="Adam steps per I-RFT fit")
    ap.add_argument("--run-effect", action="store_true",
                    help="I-RFT with a per-run random stress learned by the marginal likelihood (experimental)")
    ap.add_argument("--li-basis", action=argparse.BooleanOptionalAction, default=None,
                    help="the I-RFT rows (zero and physics mean) with or without Li et al.'s basis as a kernel term "
                         "(default: the constructor's, with); the learned-surface row is left as it is")
    ap.add_argument("--generic-shape", action="store_true",
                    help="the same rows with the generic shape's uncertain scale too (MapPrior(kernel="
                         "'li+generic'))")
    ap.add_argument("--hyper-posterior", default=None, choices=("map", "laplace"),
                    help="the same rows' hyperparameter posterior (InverseRFT(..., hyper_posterior=...); default: the "
                         "constructor's, laplace): map, the plug-in (the earlier default, with --no-li-basis)")
    ap.add_argument("--seed", type=int, default=0,
                    help="the seed set before each I-RFT fit (the Laplace rows' proposals; the plug-in rows do not "
                         "depend on it): a rerun with another seed measures the run-to-run spread")
    ap.add_argument("--cv-refit", action="store_true",
                    help="the grouped-CV row refits both candidates without each left-out value (nested "
                         "cross-validation; about 2x the time) instead of using the fitted hyperparameters")
    ap.add_argument("--plain-iter", type=int, default=300, help="Adam steps per plain-GP fit (the README's 300)")
    ap.add_argument("--splits", default="beta,gamma", help="which held-out splits: beta, gamma or both")
    ap.add_argument("--jobs", type=int, default=0,
                    help="worker processes for the folds (0: one per CPU, at most 8; 1: this process)")
    return ap


_WORKER: dict = {}


def _init_worker(a, data: list[RunData]) -> None:
    """A fold worker: one torch thread (the fits are small), the parsed runs sent once (parsing the
    files again would take longer than the pickle)."""
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    _WORKER["data"] = data
    _WORKER["a"] = a


def _fold_task(split: str, idx: list[int], keep_models: bool):
    """One fold in a worker: run_fold on its data; the fitted models only where the figures need them."""
    data, a = _WORKER["data"], _WORKER["a"]
    train = [d for i, d in enumerate(data) if i not in idx]
    out, info = run_fold(train, [data[i] for i in idx], a, split)
    if not keep_models:
        info["models"] = None
    return out, info


def main(argv=None) -> dict:
    a = build_parser().parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")  # this script only writes files; set here, never at import
    torch.set_default_dtype(torch.float64)
    t0 = time.perf_counter()
    runs, report = dem.read_runs(a.data)
    print(f"read {len(runs)} runs; {report.summary()}")
    deep_enough = [(r.depth > a.min_depth).sum() >= 3 for r in runs]
    usable = [r for r, ok in zip(runs, deep_enough) if ok]
    too_shallow = [f"{r.label} (deepest {r.depth.max():.2f} cm)" for r, ok in zip(runs, deep_enough) if not ok]
    if too_shallow:
        print(f"left out, fewer than 3 samples deeper than {a.min_depth:g} cm: {', '.join(too_shallow)}")
    data = [RunData(r, a.min_depth) for r in usable]
    splits = [s.strip() for s in a.splits.split(",") if s.strip()]
    for s in splits:
        if s not in SPLITS:
            raise SystemExit(f"--splits: expected beta and/or gamma, got {s!r}")
    results, fold_info, fig_fold = {}, {}, None
    all_folds = {}
    for split in splits:
        key = [d.run.beta_deg if split == "beta" else d.run.gamma_deg for d in data]
        all_folds[split] = [(v, [i for i, k in enumerate(key) if k == v]) for v in sorted(set(key))]
    jobs = a.jobs or min(8, os.cpu_count() or 1)
    figure_fold = ("beta", 45.0)  # the held-out force figure's fold: its models come back from the worker
    if jobs > 1:  # folds are independent: one per worker process, the data read once per worker
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs, mp_context=worker_context(), initializer=_init_worker,
                                 initargs=(a, data)) as pool:
            futures = {(split, v): pool.submit(_fold_task, split, idx, (split, v) == figure_fold)
                       for split in splits for v, idx in all_folds[split]}
            fold_results = {k: f.result() for k, f in futures.items()}
    else:
        fold_results = None
    for split in splits:
        folds = all_folds[split]
        preds = {n: {t: [] for t in TARGETS} for n in IRFT + BASELINES}
        force_err = {n: [] for n in IRFT + BASELINES}
        fold_info[split] = []
        for v, idx in folds:
            train = [d for i, d in enumerate(data) if i not in idx]
            test = [data[i] for i in idx]
            out, info = fold_results[(split, v)] if fold_results else run_fold(train, test, a, split)
            for n in out:
                for t in TARGETS:
                    preds[n][t].append(out[n][t])
                force_err[n].append(info["forces"][n])
            fold_info[split].append((v, info["offset"], info["stride"], *info["learned"], info["cv"]))
            if (split, v) == figure_fold:
                fig_fold = (info["models"][DEFAULT], train, test, info["offset"], info["models"][LEARNED],
                            info["learned"][0])
            lo, lsd, ls = info["learned"]
            print(f"{SPLITS[split]}: held out {split} {v:g} ({len(test)} runs): surface {info['offset']:.1f} cm below "
                  f"z_top, stride {info['stride']} ms; learned surface {lo:.2f} +- {lsd:.2f} cm below z_top, stride "
                  f"{ls} ms ({time.perf_counter() - t0:.0f} s)", flush=True)
        results[split] = (folds, score(data, folds, preds, force_err))
    tau = residual_time_ms(data, 0.0)
    elapsed = time.perf_counter() - t0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = write_report(a, data, report, results, fold_info, tau, elapsed, too_shallow)
    if fig_fold is not None or results:
        lines += figures(a, out, data, results, fig_fold)
    (out / "dem_validation.md").write_text("\n".join(lines) + "\n")
    write_predictions(out / "dem_predictions.csv", data, results)
    print(f"wrote {out}/dem_validation.md ({time.perf_counter() - t0:.0f} s)")
    return {s: r for s, (_, r) in results.items()}


def _pair(v, fmt="{:.4f}") -> str:
    return "- | -" if v is None else f"{fmt.format(v[0])} | {fmt.format(v[1])}"


def write_report(a, data, report, results, fold_info, tau, elapsed, too_shallow=()) -> list[str]:
    names = IRFT + BASELINES
    lines = ["# I-RFT on independent DEM plate-intrusion data", "",
             f"`python experiments/validation/dem_validation.py --data DIR"
             f"{'' if a.stride == 'auto' else f' --stride {a.stride}'}"
             f"{'' if a.offset == '0' else f' --offset {a.offset}'}{' --cv-refit' if a.cv_refit else ''}"
             f"{LI_FLAG[getattr(a, 'li_basis', None)]}"
             f"{' --generic-shape' if getattr(a, 'generic_shape', False) else ''}"
             f"{'' if getattr(a, 'hyper_posterior', None) is None else ' --hyper-posterior ' + a.hyper_posterior}`: "
             f"{len(data)} runs (every run with at least 3 "
             f"samples deeper than {a.min_depth:g} cm"
             f"{'; left out: ' + ', '.join(too_shallow) if too_shallow else ''}), "
             f"{a.n_iter} Adam steps per I-RFT fit; {elapsed:.0f} s. "
             f"Reader: {report.summary()}.", "",
             f"Targets: **origin** = the data README's per-run stress per depth, F = s x depth through the origin over "
             f"the samples whose centre is deeper than {a.min_depth:g} cm below z_top, over the plate area (the bar); "
             "**intercept** = the slope of the same fit with an intercept. Each baseline is fitted to the target it is "
             "scored on; I-RFT is fitted once, to the forces, and scored on both through the recipe applied to its "
             "predicted forces. Force RMSE: held-out samples every "
             f"{a.eval_stride} ms, centre deeper than {a.min_depth:g} cm below z_top. Coverage: held-out runs inside "
             "the 95 % predictive interval (posterior of the target + the run's own noise). Force residual "
             f"autocorrelation time (per-run through-origin fits, median): {tau[0]:.0f} ms (x), {tau[1]:.0f} ms (z).",
             ""]
    for split, (folds, res) in results.items():
        lines += [f"## {SPLITS[split]} ({len(folds)} folds)", "",
                  f"Per held-out {split} (deg): I-RFT's surface below z_top / its stride: "
                  + "; ".join(f"{v:g}: {o:.1f} cm / {s} ms" for v, o, s, *_ in fold_info[split]) + ".",
                  f"{LEARNED}: the surface it learned (cm below z_top, Laplace std) / its stride: "
                  + "; ".join(f"{v:g}: {lo:.2f} +- {lsd:.2f} cm / {ls} ms"
                              for v, _, _, lo, lsd, ls, _ in fold_info[split]) + ".",
                  cv_choices(split, fold_info[split], a.cv_refit), "",
                  "| model | origin RMSE x (N/cm^3) | origin z | intercept RMSE x | intercept z | force RMSE x (N) "
                  "| force z (N) | 95 % coverage, origin x | z |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for n in names:
            r = res[n]
            cov = "- | -" if r["cover_origin"] is None else \
                f"{100 * r['cover_origin'][0]:.0f} % | {100 * r['cover_origin'][1]:.0f} %"
            lines.append(f"| {n}{' (default)' if n == DEFAULT else ''} | {_pair(r['rmse_origin'])} | "
                         f"{_pair(r['rmse_intercept'])} | {_pair(r['force'], '{:.3f}')} | {cov} |")
            print(f"{split}: {lines[-1]}")
        if split == "beta":
            for n in BASELINES:
                o = README_FIGURES["origin"].get(n)
                i = README_FIGURES["intercept"].get(n)
                if o or i:
                    lines.append(f"| {n}: the README's figure | {_pair(o) if o else '| '} | {_pair(i) if i else '| '} "
                                 "| | | | |")
        target = np.array([data[i].target["origin"] for _, idx in folds for i in idx])
        lines += [""] + bars(res, target) + bars(res, target, LEARNED) + bars(res, target, CV) + [""]
    return lines


def cv_choices(split: str, info: list, refit: bool = False) -> str:
    """The prior mean each fold's grouped cross-validation chose per axis, with its RMSEs."""
    if info[0][-1][1] is None:
        return f"{CV}: not computed with --run-effect (zero mean used)."
    words = []
    for v, *_, (choice, stress, force) in info:
        per = [f"{ax} {('zero', 'physics')[choice[k]]} ({stress[0, k]:.4f} / {stress[1, k]:.4f} N/cm^3; by force "
               f"RMSE {('zero', 'physics')[int(force[:, k].argmin())]})" for k, ax in enumerate("xz")]
        words.append(f"{v:g}: {', '.join(per)}")
    how = "each candidate refitted without it" if refit else "at the fitted hyperparameters"
    return (f"{CV}: per held-out {split}, the prior mean chosen per axis by leaving each training {split} out in "
            f"turn, {how} (training runs' stress RMSE, zero / physics mean; the choice the pooled force RMSE "
            f"would make): "
            + "; ".join(words) + ".")


def paired_bootstrap(runs_a, runs_b, n: int = 2000, seed: int = 0) -> np.ndarray:
    """95 % interval (2, 2) of RMSE(a) - RMSE(b) per axis, the held-out runs resampled with replacement
    (``metrics.rmse_difference``): how much of a difference the choice of runs alone could make. ``runs_a[i]``,
    ``runs_b[i]``: the same run's errors under each model, (2,) (one value per run: its stress) or (T_i, 2) (its
    force samples, which move together: the RMSE pools the samples of the runs drawn)."""
    sse = lambda runs: np.stack([(np.atleast_2d(e) ** 2).sum(0) for e in runs])  # noqa: E731 (R, 2)
    count = np.array([len(np.atleast_2d(e)) for e in runs_a], dtype=float)
    d = metrics.rmse_difference(sse(runs_a), sse(runs_b), count=count, n_boot=n, seed=seed)
    return np.stack([d.low.numpy(), d.high.numpy()])


def write_predictions(path: Path, data: list, results: dict) -> None:
    """Every held-out run's target, prediction, predictive variance and force errors, per split and row
    (one CSV line per split x row x target x run): what ``compare_predictions.py`` pairs between two runs of
    this script."""
    import csv

    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["split", "fold", "run", "model", "target", "truth_x", "truth_z", "pred_x", "pred_z", "var_x",
                    "var_z", "force_sse_x", "force_sse_z", "force_n"])
        for split, (folds, res) in results.items():
            order = [(v, i) for v, idx in folds for i in idx]
            for model, r in res.items():
                for t in TARGETS:
                    for k, (v, i) in enumerate(order):
                        e = np.atleast_2d(r["force_runs"][k])
                        var = r[f"var_{t}"]
                        w.writerow([split, f"{v:g}", data[i].run.label, model, t, *data[i].target[t],
                                    *r[f"pred_{t}"][k], *(var[k] if var is not None else ("", "")),
                                    *(e**2).sum(0), len(e)])


def bars(res: dict, target: np.ndarray, model: str = DEFAULT) -> list[str]:
    """Issue #14's bars for an I-RFT row (the default), in words; ``target`` (N, 2) the held-out runs' origin
    stresses."""
    r = res[model]
    out = []
    for n in ("generic x LS scales", "plain GP on run stresses"):
        b = res[n]
        stress = ["x", "z"]
        wins = [f"{ax} {r['rmse_origin'][k]:.4f} {'<' if r['rmse_origin'][k] < b['rmse_origin'][k] else '>='} "
                f"{b['rmse_origin'][k]:.4f}" for k, ax in enumerate(stress)]
        fw = [f"{ax} {r['force'][k]:.3f} {'<' if r['force'][k] < b['force'][k] else '>='} {b['force'][k]:.3f}"
              for k, ax in enumerate(stress)]
        ok = (r["rmse_origin"] < b["rmse_origin"]).all() and (r["force"] < b["force"]).all()
        ci = paired_bootstrap(r["pred_origin"] - target, b["pred_origin"] - target)
        cf = paired_bootstrap(r["force_runs"], b["force_runs"])
        out.append(f"- {model} vs {n}: origin stresses {', '.join(wins)}; forces {', '.join(fw)} N: "
                   f"**{'beats it' if ok else 'does not beat it everywhere'}**. RMSE difference, 95 % paired "
                   f"bootstrap over the held-out runs: x [{ci[0, 0]:+.4f}, {ci[1, 0]:+.4f}], "
                   f"z [{ci[0, 1]:+.4f}, {ci[1, 1]:+.4f}] N/cm^3; forces (runs resampled whole) x "
                   f"[{cf[0, 0]:+.3f}, {cf[1, 0]:+.3f}], z [{cf[0, 1]:+.3f}, {cf[1, 1]:+.3f}] N.")
    c = r["cover_origin"]
    ok = ((c >= 0.85) & (c <= 0.99)).all()
    out.append(f"- {model}: 95 % coverage of held-out runs (origin target): {100 * c[0]:.0f} % (x), "
               f"{100 * c[1]:.0f} % (z): "
               f"**{'within' if ok else 'outside'} 85-99 %**.")
    return out


def figures(a, out: Path, data, results, fig_fold) -> list[str]:
    from irft_torch import plotting

    plt = plotting.plt
    lines = ["## Figures", ""]
    fig, axes = plt.subplots(len(results), 2, figsize=(11, 4.8 * len(results)), squeeze=False, constrained_layout=True)
    markers = {"generic x LS scales": ("s", "C2"), "plain GP on run stresses": ("^", "C0")}
    for row, (split, (folds, res)) in enumerate(results.items()):
        S = np.array([data[i].target["origin"] for _, idx in folds for i in idx])
        for k, ax in enumerate(axes[row]):
            lo, hi = S[:, k].min(), S[:, k].max()
            pad = 0.1 * (hi - lo)
            ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=0.8, label="prediction = target")
            for n, (mk, col) in markers.items():
                ax.plot(S[:, k], res[n]["pred_origin"][:, k], mk, color=col, ms=4, mfc="none",
                        label=f"{n} (RMSE {res[n]['rmse_origin'][k]:.4f})")
            r = res[DEFAULT]
            ax.errorbar(S[:, k], r["pred_origin"][:, k], yerr=1.96 * np.sqrt(r["var_origin"][:, k]), fmt="o",
                        color="C1", ms=4, elinewidth=0.8, capsize=0,
                        label=f"{DEFAULT} with its 95 % interval (RMSE {r['rmse_origin'][k]:.4f})")
            ax.set_xlabel(rf"held-out run's stress per depth $\alpha_{'xz'[k]}$, through the origin (N/cm$^3$)")
            ax.set_ylabel(r"prediction (N/cm$^3$)")
            ax.set_title(f"{SPLITS[split]}: {'xz'[k]} axis", fontsize=10)
            ax.legend(fontsize=7, loc="upper left")
    plotting.save(fig, out / "dem_stresses.png")
    lines.append("`dem_stresses.png`: every held-out run's through-origin stress (x axis) against each model's "
                 "prediction of it, per split and axis, I-RFT with its 95 % interval.")
    if fig_fold is not None:
        m, train, test, off, m_l, off_l = fig_fold
        points = ([d.angles[0] for d in train], [d.angles[1] for d in train]), \
                 ([d.angles[0] for d in test], [d.angles[1] for d in test])
        fig = plotting.plot_posterior_map(m, 48, f"{DEFAULT} (beta 45 held out)", points=points)
        plotting.save(fig, out / "dem_maps.png")
        fig, axes = plt.subplots(len(test), 2, figsize=(11, 1.9 * len(test)), constrained_layout=True, squeeze=False)
        for k, d in enumerate(test):
            c, f = d.contacts(off, a.eval_stride)
            depth = d.run.depth[d.run.depth > a.min_depth][::a.eval_stride]
            c_l, _ = d.contacts(off_l, a.eval_stride)  # the same samples, depths below the learned surface
            with torch.no_grad():
                pred = m.predict_forces(c, include_noise=True)
                pred_l = m_l.predict_forces(c_l).mean
            lo, hi = pred.interval(0.95)
            for i in range(2):
                ax = axes[k, i]
                ax.plot(depth, f[:, i].numpy(), "k.", ms=2, label="DEM (held out)")
                ax.plot(depth, pred.mean[:, i].numpy(), "C1-", lw=1, label=f"{DEFAULT}, trained on the other tilts")
                ax.fill_between(depth, lo[:, i].numpy(), hi[:, i].numpy(), color="C1", alpha=0.2,
                                label="95 % band of a measurement")
                ax.plot(depth, pred_l[:, i].numpy(), "C0--", lw=1,
                        label=f"{LEARNED} ({off_l:.2f} cm below z_top), mean")
                ax.axvline(off_l, color="C0", lw=0.6, ls=":")
                ax.set_title(f"{d.run.label}: F_{'xz'[i]} (N)", fontsize=8)
        axes[0, 0].legend(fontsize=7)
        for ax in axes[-1]:
            ax.set_xlabel("plate centre depth below z_top (cm)")
        plotting.save(fig, out / "dem_forces_heldout.png")
        lines.append("`dem_maps.png`: the default I-RFT's maps and their std with beta = 45 held out (training "
                     "angle pairs as dots, the held-out runs as stars); `dem_forces_heldout.png`: the held-out "
                     "beta = 45 runs' forces against depth, DEM and I-RFT's prediction with the 95 % band of a "
                     "measurement, and the learned-surface I-RFT's mean (its surface dotted).")
    return lines


if __name__ == "__main__":
    main()
