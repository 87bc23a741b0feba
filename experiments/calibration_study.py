"""Calibration study: does the 95 % posterior interval of the maps hold 95 % of the truth?

The paper's four configurations (I/C toe x gait 1/2, ``irft_torch.reproduce.configuration``) x 2
axes, forces from forward RFT with the generic map at the paper's scale, multiplicative noise of
variance 0, 0.05 and 0.2 (the paper's Table II) x 3 noise seeds. For every fit: the share of the
evaluation grid whose truth lies inside the central 50 %, 90 % and 95 % posterior intervals. A
cell is (configuration, axis, noise), averaged over the seeds; the bar: 95 % coverage within
85-99 % in every cell and the median cell within 90-98 %.

    python experiments/calibration_study.py [--quick] [--priors physical|none] [--out DIR]

Writes ``calibration_study.md`` and ``calibration_study.csv`` (one row per fit) and
``calibration_reliability.png`` (nominal against observed coverage, per configuration).

``--truth prior`` replaces the generic map by maps drawn from the GP prior the physical priors are
centred on (each axis: variance (zeta rms)^2 at the paper's zeta, every embedding lengthscale at the
prior's centre 1.5; one draw per configuration and seed, exact in a Fourier basis with kernel
truncation error below 1e-7): where the prior is right, what coverage does the fit reach? It
separates the machinery's calibration from a mismatch between the prior and one particular truth.
Files get the suffix ``_prior``.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import time
from pathlib import Path

import torch

from irft_torch.gp.fourier import FourierBasis
from irft_torch.gp.priors import GENERIC_RMS, LENGTHSCALE_CENTRE
from irft_torch.reproduce import CONFIGS, LEVELS, StudySettings, _fit_one
from irft_torch.rft import FourierStressMap
from irft_torch.rft.stress_maps import mirror_to_canonical

NOISES = (0.0, 0.05, 0.2)
SEEDS = (0, 1, 2)
LOW, HIGH, MEDIAN_LOW, MEDIAN_HIGH = 0.85, 0.99, 0.90, 0.98


class PriorDraw:
    """A map drawn from the zero-mean GP prior of I-RFT (ARD RBF on the angle embedding): alpha_a(theta)
    = psi(theta)^T u_a with u_a ~ N(0, s_a Sigma_beta kron Sigma_gamma) in a Fourier basis (``gp.fourier``),
    callable like a ``FourierStressMap``: (beta, gamma) -> (..., 2) N/cm^3, any angles (mirrored into
    the canonical square, alpha_x changing sign)."""

    def __init__(self, outputscale, lengthscale: float, seed: int, tol: float = 1e-7) -> None:
        ls = torch.full((2, 1, 4), float(lengthscale), dtype=torch.float64)
        self.basis = FourierBasis.for_lengthscale(ls, tol)
        Sb, Sg = self.basis.coefficients(ls)
        g = torch.Generator().manual_seed(seed)
        u = []
        for a in range(2):
            Lb = torch.linalg.cholesky(Sb[a] + 1e-12 * torch.eye(Sb.shape[-1], dtype=Sb.dtype))
            Lg = torch.linalg.cholesky(Sg[a] + 1e-12 * torch.eye(Sg.shape[-1], dtype=Sg.dtype))
            z = torch.randn(Sb.shape[-1], Sg.shape[-1], generator=g, dtype=torch.float64)
            u.append(float(outputscale[a]) ** 0.5 * (Lb @ z @ Lg.mT))  # cov(vec u) = s Sb kron Sg
        self.u = torch.stack(u)  # (2, Fb, Fg)

    def __call__(self, beta, gamma):
        b, g, sign = mirror_to_canonical(torch.as_tensor(beta), torch.as_tensor(gamma))
        pb, pg = self.basis.features(b, g)
        alpha = torch.einsum("...i,aij,...j->...a", pb, self.u.to(pb), pg)
        return torch.stack([sign * alpha[..., 0], alpha[..., 1]], -1)


def run(out: Path, quick: bool = False, priors: str | None = "physical", progress: bool = True,
        truth: str = "generic") -> dict:
    """Fit every (configuration, noise, seed); returns {"rows": per-fit rows, "cells": {(config, axis,
    noise): mean coverage per level}, "elapsed_s"}, and writes the table, CSV and figure."""
    torch.set_default_dtype(torch.float64)
    s = StudySettings(priors=priors)
    noises, seeds = NOISES, SEEDS
    if quick:
        s = StudySettings(n_steps=60, grid=24, n_iter=100, priors=priors)
        noises, seeds = (0.0, 0.2), (0,)
    generic = FourierStressMap.generic(*s.truth_scale)
    zeta = sum(s.truth_scale) / 2
    out.mkdir(parents=True, exist_ok=True)
    rows, t0 = [], time.perf_counter()
    for k, config in enumerate(CONFIGS):
        for noise in noises:
            for seed in seeds if noise > 0 else seeds[:1]:  # noise 0: every seed is the same fit
                truth_map = generic
                if truth == "prior":  # one draw per configuration and seed (the same at every noise level)
                    truth_map = PriorDraw([(zeta * r) ** 2 for r in GENERIC_RMS], LENGTHSCALE_CENTRE, 100 * k + seed)
                r = _fit_one(config, "zero", noise, seed, truth_map, "paper scale", s)
                for axis in "XZ":
                    rows.append({"config": config, "axis": axis, "noise": noise, "seed": seed,
                                 **{f"cover{round(100 * lv)}": r.metrics[axis][f"calibration{round(100 * lv)}"]
                                    for lv in LEVELS},
                                 "rmse": r.metrics[axis]["rmse"]})
                if progress:
                    print(f"{config} noise {noise} seed {seed}: 95 % coverage X {rows[-2]['cover95']:.3f} "
                          f"Z {rows[-1]['cover95']:.3f}", flush=True)
    elapsed = time.perf_counter() - t0
    cells = {}
    for config in CONFIGS:
        for axis in "XZ":
            for noise in noises:
                rs = [r for r in rows if (r["config"], r["axis"], r["noise"]) == (config, axis, noise)]
                cells[(config, axis, noise)] = {lv: statistics.fmean(r[f"cover{round(100 * lv)}"] for r in rs)
                                                for lv in LEVELS}
    suffix = "_prior" if truth == "prior" else ""
    with open(out / f"calibration_study{suffix}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _report(out, cells, noises, seeds, elapsed, quick, priors, truth)
    _figure(out, cells, noises, suffix)
    return {"rows": rows, "cells": cells, "elapsed_s": elapsed}


def verdict(cells: dict) -> tuple[bool, bool, float]:
    """(every cell's 95 % coverage in [0.85, 0.99], median cell in [0.90, 0.98], median)."""
    c95 = [v[0.95] for v in cells.values()]
    med = statistics.median(c95)
    return all(LOW <= c <= HIGH for c in c95), MEDIAN_LOW <= med <= MEDIAN_HIGH, med


def _report(out, cells, noises, seeds, elapsed, quick, priors, truth="generic") -> None:
    every, median_ok, med = verdict(cells)
    c95 = [v[0.95] for v in cells.values()]
    lines = ["# Calibration of the map posterior over the canonical square", "",
             f"`python experiments/calibration_study.py{' --quick' if quick else ''}"
             f"{' --priors none' if priors is None else ''}{' --truth prior' if truth == 'prior' else ''}`: "
             f"{len(cells)} cells, seeds {list(seeds)} "
             f"(noise 0: one fit), {elapsed:.0f} s of fitting. Hyperparameter priors: {priors or 'none (plain ML)'}; "
             "zero mean, the paper's model otherwise; truth: "
             + ("maps drawn from the GP prior the physical priors are centred on (one per configuration and seed)"
                if truth == "prior" else "the generic map at the paper's scale") + ".", "",
             "Each cell: the share of the evaluation grid whose truth lies inside the central 50 % / 90 % / 95 % "
             "posterior interval (mean over seeds). Calibrated: 0.50 / 0.90 / 0.95.", "",
             "| config | axis | " + " | ".join(f"noise {n}" for n in noises) + " |",
             "|---|---|" + "---|" * len(noises)]
    for config in CONFIGS:
        for axis in "XZ":
            cellstr = [" / ".join(f"{cells[(config, axis, n)][lv]:.2f}" for lv in LEVELS) for n in noises]
            lines.append(f"| {config} | {axis} | " + " | ".join(cellstr) + " |")
    lines += ["", f"95 % coverage: min {min(c95):.3f}, median {med:.3f}, max {max(c95):.3f}. "
              f"Every cell within {LOW:.2f}-{HIGH:.2f}: {'yes' if every else 'no'}; median within "
              f"{MEDIAN_LOW:.2f}-{MEDIAN_HIGH:.2f}: {'yes' if median_ok else 'no'}."]
    bad = [f"{c} {a} noise {n} ({v[0.95]:.2f})" for (c, a, n), v in cells.items() if not LOW <= v[0.95] <= HIGH]
    if bad:
        lines.append(f"Cells outside the band: {', '.join(bad)}.")
    (out / f"calibration_study{'_prior' if truth == 'prior' else ''}.md").write_text("\n".join(lines) + "\n")


def _figure(out, cells, noises, suffix="") -> None:
    from irft_torch import plotting

    fig = plotting.plot_reliability(
        {f"{c} {a}, noise {n}": [cells[(c, a, n)][lv] for lv in LEVELS] for (c, a, n) in cells}, LEVELS,
        title="Calibration study: share of the truth inside the central posterior interval"
              + ("\n(truth: maps drawn from the GP prior)" if suffix else "\n(truth: the generic map, paper's scale)"))
    plotting.save(fig, out / f"calibration_reliability{suffix}.png")


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="experiments/results")
    p.add_argument("--quick", action="store_true", help="small sizes, noise 0 and 0.2, one seed (a check)")
    p.add_argument("--priors", default="physical", choices=("physical", "none"))
    p.add_argument("--truth", default="generic", choices=("generic", "prior"),
                   help="the generic map at the paper's scale, or maps drawn from the GP prior (see above)")
    a = p.parse_args(argv)
    res = run(Path(a.out), quick=a.quick, priors=None if a.priors == "none" else a.priors, truth=a.truth)
    every, median_ok, med = verdict(res["cells"])
    name = "calibration_study_prior.md" if a.truth == "prior" else "calibration_study.md"
    print(f"wrote {Path(a.out) / name} ({res['elapsed_s']:.0f} s); median 95 % coverage "
          f"{med:.3f}; every cell in band: {every}; median in band: {median_ok}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
