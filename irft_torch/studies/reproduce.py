"""The I-RFT paper's numerical validation (Section V-A, Tables I and II, Fig. 5), rerun: its
settings (``StudySettings``, every choice the paper leaves open), its four configurations, the
paper's own numbers, and the fits (``study_fits``, ``fit_study``), handed back as ``FitResult``s.

The report (``studies.report``) reads them; ``studies.paper_study.run_study`` (``irft reproduce``)
runs both. This module never imports the report: the figures its workers draw come in as a function.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from tqdm.auto import tqdm

from .. import metrics
from ..gp.batch_fit import fit_together
from ..gp.model import InverseRFT
from ..gp.options import grouped
from ..rft import CToe, FourierStressMap, IToe, contacts, forces, rectangle_path, spline_path

__all__ = ["StudySettings", "FitResult", "PAPER_TABLE1", "PAPER_TABLE2", "CONFIGS", "LEVELS", "configuration",
           "study_fits", "fit_study", "sampling_statistics", "tangent_heading"]

CONFIGS = ("I-toe gait 1", "I-toe gait 2", "C-toe gait 1", "C-toe gait 2")

# The paper's Table I: (rmse, mae, r2, pearson, acr%) per (config, axis).
PAPER_TABLE1 = {
    ("I-toe gait 1", "X"): (0.0552, 0.0356, 0.1652, 0.6757, 49.59),
    ("I-toe gait 1", "Z"): (0.1301, 0.0797, 0.0525, 0.4348, 35.28),
    ("I-toe gait 2", "X"): (0.0369, 0.0275, 0.6271, 0.8562, 41.72),
    ("I-toe gait 2", "Z"): (0.0385, 0.0254, 0.9169, 0.9841, 66.20),
    ("C-toe gait 1", "X"): (0.0236, 0.0186, 0.8477, 0.9246, 49.67),
    ("C-toe gait 1", "Z"): (0.0305, 0.0242, 0.9480, 0.9753, 54.86),
    ("C-toe gait 2", "X"): (0.0332, 0.0232, 0.6983, 0.8364, 47.18),
    ("C-toe gait 2", "Z"): (0.0201, 0.0133, 0.9772, 0.9906, 87.05),
}
# The paper's Table II: RMSE% and MAE% at noise variance 0 / 0.05 / 0.2.
PAPER_TABLE2 = {
    ("I-toe gait 1", "X"): ((18.26, 18.41, 19.33), (11.63, 12.42, 13.40)),
    ("I-toe gait 1", "Z"): ((28.97, 28.11, 22.65), (17.30, 20.71, 16.95)),
    ("I-toe gait 2", "X"): ((11.79, 14.42, 15.31), (8.79, 10.81, 11.56)),
    ("I-toe gait 2", "Z"): ((8.89, 10.03, 16.62), (5.73, 6.04, 10.76)),
    ("C-toe gait 1", "X"): ((6.95, 9.36, 25.42), (5.49, 7.61, 21.21)),
    ("C-toe gait 1", "Z"): ((7.53, 11.95, 16.97), (5.79, 9.75, 12.44)),
    ("C-toe gait 2", "X"): ((10.72, 12.86, 14.55), (7.64, 9.44, 10.54)),
    ("C-toe gait 2", "Z"): ((3.68, 16.18, 35.37), (2.41, 13.50, 23.11)),
}


@dataclass
class StudySettings:
    """Every choice of the study; the paper's where it states one, ours (documented) elsewhere."""

    toe_length: float = 0.020  # I-toe, m (paper)
    toe_radius: float = 0.020  # C-toe, m (paper)
    toe_width: float = 0.008  # m (paper)
    n_segments: int = 10  # (paper)
    c_opening: str = "left"  # ours: the C's open side faces -x, its convex side leads the motion
    rectangle: tuple[float, float, float] = (0.05, 0.40, 0.05)  # penetration, shear, extraction (paper)
    rectangle_start: tuple[float, float] = (-0.20, 0.0)  # ours: the toe starts at the surface
    spline_points: tuple = ((-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05))  # (paper), m
    n_steps: int = 100  # ours: samples per path, evenly spaced in arc length (fixed rate, 0.02 m/s)
    truth_scale: tuple[float, float] = (0.452, 0.417)  # implied by the paper's Table I (rft_facts.md)
    grid: int = 50  # ours: evaluation grid of grid x grid cell centres over [-pi/2, pi/2]^2
    n_iter: int = 150  # ours: Adam steps
    lr: float = 0.1  # ours (150 steps at 0.1 reach what 300 at 0.05 do: C-toe gait 2 converged)
    tied_noise: bool = True  # the paper's single noise variance
    noise_levels: tuple[float, ...] = (0.0, 0.05, 0.2)  # variance of the multiplicative factor (paper)
    noise_seeds: tuple[int, ...] = (0, 1, 2)  # ours
    lengthscale: float = 1.0  # ours: initial lengthscale of every embedding dimension
    lengthscale_sensitivity: tuple[float, ...] = (2.0, 4.0)  # extra I-toe fits in the report
    priors: str | None = "physical"  # ours: hyperparameter priors (gp.kernels.priors); None: the plain likelihood
    hyper_posterior: str = "map"  # ours: "laplace" predicts with the hyperparameter posterior (gp.hyper.posterior)
    li_basis: bool = False  # ours: Li et al.'s basis as a kernel term (gp.kernels.li_basis); the paper: the RBF alone
    generic_shape: bool = False  # ours: with li_basis, the generic shape's uncertain scale too (gp.kernels.li_basis)
    device: str = "cpu"  # where the models are fitted ("cuda": the GPU); data, metrics and figures stay on the CPU
    seed: int = 0
    quick: bool = False

    @classmethod
    def quick_settings(cls) -> StudySettings:
        return cls(n_steps=60, grid=30, n_iter=100, noise_levels=(0.0, 0.2), noise_seeds=(0,),
                   lengthscale_sensitivity=(), quick=True)


@dataclass
class FitResult:
    config: str
    prior_mean: str
    noise: float
    seed: int
    truth: str
    lengthscale: float = 1.0
    priors: str | None = "physical"
    pinned: bool = False  # the paper's sampling as pinned by its statistics (``PINNED_STEPS``, C-toe turning on gait 2)
    metrics: dict = field(default_factory=dict)  # axis -> metrics dict
    maps: dict = field(default_factory=dict)


def _toe(config: str, s: StudySettings):
    if config.startswith("I"):
        return IToe(s.toe_length, s.toe_width, n_segments=s.n_segments)
    return CToe(s.toe_radius, s.toe_width, n_segments=s.n_segments, opening=s.c_opening)


def _path(config: str, s: StudySettings):
    if config.endswith("1"):
        return rectangle_path(*s.rectangle, start=s.rectangle_start, n_steps=s.n_steps)
    return spline_path(s.spline_points, n_steps=s.n_steps)


def configuration(config: str, settings: StudySettings | None = None):
    """The toe and path of one of the paper's four configurations (``CONFIGS``), as the study runs them."""
    if config not in CONFIGS:
        raise ValueError(f"config must be one of {CONFIGS}, got {config!r}")
    s = settings or StudySettings()
    return _toe(config, s), _path(config, s)


def _grid(s: StudySettings) -> tuple[torch.Tensor, torch.Tensor]:
    edges = torch.linspace(-math.pi / 2, math.pi / 2, s.grid + 1, dtype=torch.float64)
    c = (edges[1:] + edges[:-1]) / 2
    B, G = torch.meshgrid(c, c, indexing="ij")
    return B, G


LEVELS = (0.5, 0.9, 0.95)  # central posterior intervals whose coverage of the truth is reported


def _build(config, prior_mean, noise, seed, truth_map, s, lengthscale=None, priors="settings", pinned=False):
    """The model of one fit of the study, not yet fitted, with its toe, path and contacts."""
    if pinned:
        s = replace(s, n_steps=PINNED_STEPS)
    toe, path = _toe(config, s), _path(config, s)
    if pinned and config == "C-toe gait 2":
        path = tangent_heading(path)
    c = contacts(toe, path)
    f = forces(truth_map, c)
    if noise > 0:
        g = torch.Generator().manual_seed(1000 * seed + int(noise * 1000))
        f = f * (1 + math.sqrt(noise) * torch.randn(f.shape, generator=g, dtype=f.dtype))
    torch.manual_seed(s.seed)
    ls = s.lengthscale if lengthscale is None else lengthscale
    priors = s.priors if priors == "settings" else priors
    dev = torch.device(s.device)
    model = InverseRFT(c.to(device=dev), f.to(dev), hyper_posterior=s.hyper_posterior,
                       **grouped(dict(prior_mean=prior_mean, tied_noise=s.tied_noise, lengthscale=ls, priors=priors,
                                      li_basis=s.li_basis, generic_shape=s.generic_shape)))
    return model, toe, path, c


def _evaluate(model, toe, path, c, config, prior_mean, noise, seed, truth_map, truth_name, s, lengthscale, priors,
              keep_maps=False, pinned=False, keep_model=False) -> FitResult:
    """The fitted model's map against the truth on the study's grid (Table I / II metrics, calibration)."""
    B, G = _grid(s)
    with torch.no_grad():
        post = model.stress_map(B, G).to("cpu")
        true = truth_map(B, G)
        h = model.hypers  # the map prior's sd per grid point (*B.shape, 2), N/cm^3: uniform but for the generic shape
        prior_std = h.prior_variance_at(*(x.to(h.outputscale) for x in (B, G))).sqrt().cpu()
    res = FitResult(config, prior_mean, noise, seed, truth_name, lengthscale, priors, pinned)
    for a, axis in enumerate("XZ"):
        m = metrics.map_metrics(post.mean[..., a], true[..., a])
        for level in LEVELS:
            m[f"calibration{round(100 * level)}"] = metrics.calibration(post.mean[..., a], post.stddev[..., a],
                                                                        true[..., a], level)
        res.metrics[axis] = m
    if keep_maps:
        res.maps = {"contacts": c, "toe": toe, "path": path, "mean": post.mean, "std": post.stddev,
                    "truth": true, "B": B, "G": G, "coverage": metrics.coverage_area(c),
                    "prior_std": prior_std,
                    "redundancy": metrics.redundancy(c)}
    if keep_model:  # in this process only (a fitted model is not sent back from a worker)
        res.maps["model"] = model
    return res


def _fit_group(specs: list, s: StudySettings, keep_model: bool = False) -> list[FitResult]:
    """Several fits of the study on the same contacts, fitted as one batch (``gp.fit_together``: the
    same result as fitting each, in a fraction of the time; fits it cannot batch are fitted one by one).
    ``specs``: (config, prior_mean, noise, seed, truth_map, truth_name, keep_maps, lengthscale, priors,
    pinned), the last three optional."""
    built = []
    for spec in specs:
        config, prior_mean, noise, seed, truth_map, truth_name, keep_maps, *rest = spec
        ls, priors, pinned = (rest + [None, "settings", False][len(rest):])[:3]
        model, toe, path, c = _build(config, prior_mean, noise, seed, truth_map, s, ls, priors, pinned)
        ls = s.lengthscale if ls is None else ls
        priors = s.priors if priors == "settings" else priors
        built.append((model, toe, path, c, spec, ls, priors, keep_maps, pinned))
    fit_together([b[0] for b in built], n_iter=s.n_iter, lr=s.lr)
    return [_evaluate(model, toe, path, c, spec[0], spec[1], spec[2], spec[3], spec[4], spec[5], s, ls, priors,
                      keep_maps=keep_maps, pinned=pinned, keep_model=keep_model)
            for model, toe, path, c, spec, ls, priors, keep_maps, pinned in built]


def _fit_one(config, prior_mean, noise, seed, truth_map, truth_name, s, keep_maps=False, lengthscale=None,
             priors="settings", pinned=False, keep_model=False) -> FitResult:
    """One fit of the study and its metrics."""
    spec = (config, prior_mean, noise, seed, truth_map, truth_name, keep_maps, lengthscale, priors, pinned)
    return _fit_group([spec], s, keep_model=keep_model)[0]


# The paper's sampling statistics (Section V-A): C-toe / I-toe (beta, gamma) area on gait 1 and 2,
# C-toe gait 2 / gait 1 area, and its redundancy 1 - N_unique / N_total for I-toe gait 1, C-toe gait 1
# and C-toe gait 2.
PAPER_SAMPLING = {"C/I gait 1": 10.0, "C/I gait 2": 18.1, "C gait 2/1": 5.1,
                  "I-toe gait 1": 0.97, "C-toe gait 1": 0.68, "C-toe gait 2": 0.11}
PINNED_STEPS = 10  # samples per path the paper's gait-1 redundancies imply (see _pinning_rows)
PINNING_STEPS = (10, 20, 50)  # samples per path tried against the paper's statistics (besides the study's)


def tangent_heading(path):
    """The same positions with the body turned along the direction of motion (heading = the velocity's
    angle): a toe that follows the path's slope, as a toe on a leg turns with the leg."""
    from ..rft import pose_path

    v = path.velocity
    return pose_path(path.time, path.position[:, 0], path.position[:, 1], heading=torch.atan2(v[:, 1], v[:, 0]))


def sampling_statistics(s: StudySettings, n_cells: int = 50, c_turns_on_gait_2: bool = False) -> dict[str, float]:
    """The paper's sampling statistics for the study's toes and paths (no fit): area ratios of the
    cells of an n_cells x n_cells grid holding a segment in contact, and redundancies on that grid and
    on a 3600 x 3600 one (angles equal to 1e-3 rad: the paper's 'distinct samples').
    ``c_turns_on_gait_2``: the C-toe follows the cubic path's slope (``tangent_heading``)."""
    area, red, exact = {}, {}, {}
    for config in CONFIGS:
        path = _path(config, s)
        if c_turns_on_gait_2 and config == "C-toe gait 2":
            path = tangent_heading(path)
        c = contacts(_toe(config, s), path)
        area[config] = metrics.coverage_area(c, n_cells)
        red[config] = metrics.redundancy(c, n_cells)
        exact[config] = metrics.redundancy(c, 3600)
    out = {"C/I gait 1": area["C-toe gait 1"] / area["I-toe gait 1"],
           "C/I gait 2": area["C-toe gait 2"] / area["I-toe gait 2"],
           "C gait 2/1": area["C-toe gait 2"] / area["C-toe gait 1"]}
    for config in ("I-toe gait 1", "C-toe gait 1", "C-toe gait 2"):
        out[config] = red[config]
        out[config + " (1e-3 rad)"] = exact[config]
    return out


def _fit_job(job: list, s: StudySettings, threads: int = 0, figure_dir: Path | None = None,
             draw: Callable | None = None) -> list[FitResult]:
    """One group of fits of the study (a worker process's task; ``threads``: torch threads there, 0 = keep).
    ``figure_dir``, ``draw``: ``draw(figure_dir, [result])`` for the fits that keep their maps right here
    (Fig. 5: a second or more each, side by side with the other worker's fits instead of after them), and
    mark them drawn."""
    if threads:
        torch.set_num_threads(threads)
    torch.set_default_dtype(torch.float64)
    results = _fit_group(job, s)
    if figure_dir is not None and draw is not None:
        for r in results:
            if r.maps:
                draw(figure_dir, [r])
                r.maps["figure_drawn"] = True
    return results


def _groups(jobs: list, s: StudySettings) -> list[list[int]]:
    """The fits that share contacts, zero mean and priors (noise levels, seeds, the unscaled truth, starting
    lengthscales) as one group each where their backend fits them as one batch (``gp.fit_together``);
    every other fit alone."""
    keys: dict = {}
    batchable: dict = {}
    out: list[list[int]] = []
    for i, job in enumerate(jobs):
        config, prior_mean, *_ = job
        priors = job[8] if len(job) > 8 else "settings"
        pinned = job[9] if len(job) > 9 else False
        if prior_mean != "zero":
            out.append([i])
            continue
        where = (config, pinned)
        if where not in batchable:  # the backend "auto" picks for these contacts
            model = _build(config, "zero", 0.0, 0, FourierStressMap.generic(), s, pinned=pinned)[0]
            batchable[where] = model.method == "pairs"
        if not batchable[where]:
            out.append([i])
            continue
        key = (config, priors, pinned)
        if key not in keys:
            keys[key] = len(out)
            out.append([])
        out[keys[key]].append(i)
    return out


def fit_study(jobs: list, s: StudySettings, progress: bool = True, pool=None, workers: int = 1,
              figure_dir: Path | None = None, draw: Callable | None = None) -> list[FitResult]:
    """Every fit of ``jobs`` (``study_fits``), in order, fitted in groups (``_groups``); in ``pool`` (a
    process pool of ``workers``) when given (each fit is seeded on its own, so the results do not depend
    on where or in which order it runs). Large groups first. ``figure_dir``, ``draw``: the pool's workers
    draw Fig. 5 (``draw(figure_dir, [result])``, e.g. ``studies.report.draw_fig5``) as its fit ends."""
    groups = _groups(jobs, s)
    bar = tqdm(total=len(jobs), desc="irft reproduce", disable=not progress)
    out: list = [None] * len(jobs)
    try:
        if pool is None:
            for g in groups:
                for i, r in zip(g, _fit_job([jobs[i] for i in g], s)):
                    out[i] = r
                bar.update(len(g))
            return out
        from concurrent.futures import as_completed

        # C-toe gait 2 the dearest fit (observations backend); a batch of B costs about 1 + B / 4 fits
        cost = {c: (4 if c.startswith("C") and c.endswith("2") else 1) for c in CONFIGS}
        order = sorted(groups, key=lambda g: -cost.get(jobs[g[0]][0], 1) * (1 + (len(g) - 1) / 4))
        threads = max(1, (os.cpu_count() or 1) // workers)
        futures = {pool.submit(_fit_job, [jobs[i] for i in g], s, threads, figure_dir, draw): g for g in order}
        for fut in as_completed(futures):
            g = futures[fut]
            for i, r in zip(g, fut.result()):
                out[i] = r
            bar.update(len(g))
        return out
    finally:
        bar.close()


def study_fits(s: StudySettings) -> list:
    """The fits of the study, one job each for ``fit_study``: Table I (zero and physics prior means, the
    paper's scale and the unscaled generic map, with and without the hyperparameter priors, and under the
    paper's pinned sampling) and the Table II noise study. A job is (config, prior_mean, noise, seed,
    truth_map, truth_name, keep_maps[, lengthscale, priors, pinned])."""
    paper_truth = FourierStressMap.generic(*s.truth_scale)
    unscaled = FourierStressMap.generic()
    jobs: list[tuple] = []
    for config in CONFIGS:
        jobs.append((config, "zero", 0.0, 0, paper_truth, "paper scale", True))
        jobs.append((config, "physics", 0.0, 0, paper_truth, "paper scale", False))
        jobs.append((config, "zero", 0.0, 0, unscaled, "unscaled", False))
        if s.priors is not None:  # the paper's plain marginal likelihood, for Table I
            jobs.append((config, "zero", 0.0, 0, paper_truth, "paper scale", False, None, None))
        for noise in s.noise_levels:
            if noise == 0:
                continue
            for seed in s.noise_seeds:
                jobs.append((config, "zero", noise, seed, paper_truth, "paper scale", False))
        if config.startswith("I"):
            for ls in s.lengthscale_sensitivity:
                jobs.append((config, "zero", 0.0, 0, paper_truth, "paper scale", False, ls, None))
        if not s.quick:  # Table I under the paper's sampling, as its statistics pin it
            for priors in dict.fromkeys((s.priors, None)):
                jobs.append((config, "zero", 0.0, 0, paper_truth, "paper scale", False, None, priors, True))
    return jobs
