"""Would Li et al.'s own fitting basis, as a kernel term, fix the narrow-slice intervals? A dense test.

Data: simulated (the harness' cases). Run time: about 25 min for 24 cases.

The harness (``docs/calibration.md``) finds the zero-mean model overconfident on generic-shaped media seen
through a narrow slice of the square (40-sample strokes, the rotating leg), and NUTS shows that the
hyperparameter posterior is not what fails (``experiments/calibration/nuts_vs_laplace.py``): the kernel is. Its RBF on
the embedding (sin 2beta, cos 2beta, sin gamma, cos gamma) with the long lengthscales such smooth maps get
gives the second-order terms of the embedding (sin 2beta cos gamma, ...) almost no prior variance, and
those are half of the basis Li et al. (2013) fit every medium they measured with:

    {1, cos 2beta, sin 2beta} x {1, cos gamma, sin gamma}  (9 functions, = m in {-1, 0, 1}, n in {0, 1}),

whose kernel is  k_Li(theta, theta') = sigma_L^2 (1 + cos 2(beta - beta')) (1 + cos(gamma - gamma')) / 4.

This script fits, per axis and per harness case, two zero-mean GPs on the same forces by dense algebra
(every segment's angle pair; no lazy operator, no backend; the MAP of the hyperparameters by L-BFGS):

- ``rbf``: the library's model re-derived (RBF ARD on the embedding; log-normal priors on the lengthscales
  (centre 1.5, log-sd 1.5) and the outputscale (centre the data's stress per depth squared, log-sd 2 log 2);
  the noise free): a check that this dense version behaves as ``InverseRFT`` does (the ``map`` row, the
  library's own plug-in fit of the same case, is beside it);
- ``rbf+li``: the same plus the k_Li term, its sigma_L^2 under a log-normal prior at the same centre, log-sd
  log 2 (without a prior, the marginal likelihood took sigma_L^2 to 0 on the first case tried: the RBF explains
  the slice as well, with fewer effective dimensions);
- ``rbf+li+generic`` (``--generic``): the same plus Li et al.'s generic map g_a of each axis as a rank-one term,
  u_a g_a(theta) g_a(theta'): the generic shape with a scale of prior N(0, u_a), integrated out exactly (Rasmussen
  & Williams 2006, section 2.7: a mean with a Gaussian prior on its coefficient is a kernel term), u_a under a
  log-normal prior at the medium's zeta squared (``gp.kernels.priors.medium_scale``), log-sd log 2. Unlike the physics
  mean (``prior_mean="physics"``), whose scale is a fitted point, the scale's uncertainty is in every interval,
  and a medium of another shape keeps the zero mean.

Each is scored as the harness scores (``studies.calibration``): 95 % coverage of the truth over the 41 x 41
grid, and the percentile among 200 maps drawn from the fit's own posterior (overconfident beyond chance
below 0.025). By default the plug-in predictions; ``--laplace N`` adds each model's Laplace mixture (N
proposals from N(mode, 1.5 H^-1) in log-hyperparameters, H the autograd Hessian, self-normalised importance
weights; intervals from the mixture CDF, ``gp.hyper.mixture``) and the library's own Laplace posterior.

    python experiments/calibration/fourier_kernel_term.py [--motions short,rotating,turning] [--seeds 2]
        [--first-seed 0]
        [--held-out | --held-out-1] [--laplace N] [--generic] [--only-models rbf+li,...] [--no-library] [--out DIR]

Rows go to ``fourier_kernel_term[_laplace].csv`` under --out as each case finishes (a rerun skips those there).
Results and what they mean: docs/calibration.md, "The kernel, not the mean" and "Fresh seeds: the generic shape
with an uncertain scale".
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor

from irft_torch import InverseRFT, metrics
from irft_torch.gp.hyper.guard import proposal_covariance
from irft_torch.gp.hyper.mixture import mixture_moments, mixture_quantile
from irft_torch.gp.kernels.priors import medium_scale
from irft_torch.rft.stress_maps import FourierStressMap
from irft_torch.studies.calibration import grid, medium, motion, score, simulate

sys.path.insert(0, str(Path(__file__).parent))
from calibration_harness import cases, coverage_table, run_resumable  # noqa: E402

F64 = torch.float64
LS_CENTRE, LS_LOG_SD = math.log(1.5), 1.5
OS_LOG_SD = 2 * math.log(2.0)
LI_LOG_SD = math.log(2.0)
GEN_LOG_SD = math.log(2.0)
GENERIC = FourierStressMap.generic().to(F64)
MODELS = ("rbf", "rbf+li", "rbf+li+generic")


def embed(b, g):
    return torch.stack([torch.sin(2 * b), torch.cos(2 * b), torch.sin(g), torch.cos(g)], -1)


def kernel(p: dict, b1, g1, b2, g2, li: bool, generic: int | None = None):
    """Prior covariance of one map between angle sets (n1,), (n2,): (n1, n2), (N/cm^3)^2. ``generic``: the
    axis (0: x, 1: z) whose generic-shape term u g(theta) g(theta') is added (None: none)."""
    d = (embed(b1, g1)[:, None, :] - embed(b2, g2)[None]) / p["ls"].exp()
    k = p["os"].exp() * torch.exp(-0.5 * d.pow(2).sum(-1))
    if li:
        db, dg = b1[:, None] - b2[None], g1[:, None] - g2[None]
        k = k + p["li"].exp() / 4 * (1 + torch.cos(2 * db)) * (1 + torch.cos(dg))
    if generic is not None:
        k = k + p["gen"].exp() * GENERIC(b1, g1)[:, generic, None] * GENERIC(b2, g2)[None, :, generic]
    return k


class DenseAxis:
    """One map's zero-mean GP on the segments in contact: forces y (T,) = W alpha + noise."""

    def __init__(self, beta, gamma, weight, y, li: bool, li_prior: tuple[float, float] = (1.0, LI_LOG_SD),
                 generic: int | None = None, zeta: float = 1.0) -> None:
        """``li_prior``: the k_Li variance's log-normal prior, (its centre over the outputscale's, log-sd);
        ``generic``: add the generic-shape term of this axis (0: x, 1: z), its variance u under a log-normal
        prior at ``zeta`` squared (the medium's scale, ``gp.kernels.priors.medium_scale``), log-sd log 2."""
        T, M = weight.shape
        keep = weight.reshape(-1) != 0
        self.b, self.g = beta.reshape(-1)[keep], gamma.reshape(-1)[keep]
        rows = torch.nonzero(keep).squeeze(1) // M
        self.W = torch.zeros(T, len(self.b), dtype=F64)
        self.W[rows, torch.arange(len(self.b))] = weight.reshape(-1)[keep]
        self.y, self.li, self.generic = y, li, generic
        self.centre = float((y.pow(2).mean() / weight.abs().sum(-1).pow(2).mean()).log())
        self.p = {"ls": torch.full((4,), LS_CENTRE, dtype=F64), "os": torch.tensor(self.centre, dtype=F64),
                  "li": torch.tensor(self.centre + math.log(li_prior[0]), dtype=F64), "noise": (1e-2 * y.var()).log(),
                  "gen": torch.tensor(2 * math.log(max(zeta, 1e-3)), dtype=F64)}
        self.li_centre, self.li_log_sd = self.centre + math.log(li_prior[0]), li_prior[1]
        self.gen_centre = float(self.p["gen"])

    @property
    def names(self) -> list[str]:
        return ["ls", "os", "noise"] + (["li"] if self.li else []) + (["gen"] if self.generic is not None else [])

    def covariance(self, p: dict | None = None):
        p = self.p if p is None else p
        T = len(self.y)
        return self.W @ kernel(p, self.b, self.g, self.b, self.g, self.li, self.generic) @ self.W.T \
            + p["noise"].exp() * torch.eye(T, dtype=F64)

    def loss(self, p: dict):
        """-log p(theta | y) up to a constant: the marginal likelihood and the log-normal priors (theta = log value)."""
        L = torch.linalg.cholesky(self.covariance(p))
        a = torch.cholesky_solve(self.y[:, None], L)
        loss = 0.5 * (self.y[:, None] * a).sum() + L.diagonal().log().sum()
        loss = loss + 0.5 * ((p["ls"] - LS_CENTRE) / LS_LOG_SD).pow(2).sum()
        loss = loss + 0.5 * ((p["os"] - self.centre) / OS_LOG_SD).pow(2)
        if self.li:
            loss = loss + 0.5 * ((p["li"] - self.li_centre) / self.li_log_sd).pow(2)
        if self.generic is not None:
            loss = loss + 0.5 * ((p["gen"] - self.gen_centre) / GEN_LOG_SD).pow(2)
        return loss

    def unflatten(self, theta) -> dict:
        out, i = dict(self.p), 0
        for n in self.names:
            k = self.p[n].numel()
            out[n] = theta[i:i + k].reshape(self.p[n].shape)
            i += k
        return out

    def fit(self, iters: int = 150) -> None:
        for n in self.names:
            self.p[n] = self.p[n].clone().requires_grad_(True)
        opt = torch.optim.LBFGS([self.p[n] for n in self.names], max_iter=iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = self.loss(self.p)
            loss.backward()
            return loss

        opt.step(closure)
        self.p = {k: v.detach() for k, v in self.p.items()}

    def posterior(self, B, G, p: dict | None = None):
        """Mean (n,) and covariance (n, n) of the map at angles (n,) (at hyperparameters ``p``, default the fit)."""
        p = self.p if p is None else p
        L = torch.linalg.cholesky(self.covariance(p))
        ks = kernel(p, B, G, self.b, self.g, self.li, self.generic) @ self.W.T  # (n, T)
        mean = ks @ torch.cholesky_solve(self.y[:, None], L).squeeze(1)
        V = torch.linalg.solve_triangular(L, ks.T, upper=False)
        return mean, kernel(p, B, G, B, G, self.li, self.generic) - V.T @ V

    def laplace(self, n_proposals: int, gen: torch.Generator) -> tuple[list[dict], Tensor]:
        """Hyperparameter draws and their self-normalised importance weights: proposals from N(mode, 1.5 H^-1)
        in theta = log value (H the autograd Hessian of ``loss`` at the fit, ``laplace_guard.proposal_covariance``)."""
        mode = torch.cat([self.p[n].reshape(-1) for n in self.names])
        H = torch.autograd.functional.hessian(lambda t: self.loss(self.unflatten(t)), mode)
        cov = 1.5 * proposal_covariance(H)
        root = torch.linalg.cholesky(cov)
        z = torch.randn(n_proposals, len(mode), generator=gen, dtype=F64)
        thetas = mode + z @ root.T
        logq = -0.5 * z.pow(2).sum(-1)
        logp = []
        with torch.no_grad():
            for t in thetas:
                try:
                    logp.append(-self.loss(self.unflatten(t)))
                except torch.linalg.LinAlgError:
                    logp.append(torch.tensor(-math.inf, dtype=F64))
        logw = torch.stack(logp) - logq
        w = torch.softmax(torch.where(torch.isfinite(logw), logw, torch.full_like(logw, -math.inf)), 0)
        keep = w > 1e-4
        w = w[keep] / w[keep].sum()
        return [self.unflatten(t) for t in thetas[keep]], w


def dense_score(c, f, truth, li: bool, seed: int, laplace: int = 0, draws: int = 200,
                li_prior: tuple[float, float] = (1.0, LI_LOG_SD), generic: bool = False) -> list[dict]:
    """The plug-in's scores, and with ``laplace`` proposals the Laplace mixture's too (one dict each)."""
    B, G = (t.reshape(-1) for t in grid(41))
    true = truth(B, G)
    outs: list[dict] = [{}, {}] if laplace else [{}]
    gen = torch.Generator().manual_seed(10_000 + seed)
    zeta = medium_scale(c, f)
    for a, (name, w) in enumerate((("x", c.weight_x), ("z", c.weight_z))):
        ax = DenseAxis(c.beta, c.gamma, w, f[:, a], li, li_prior, a if generic else None, zeta)
        ax.fit()
        with torch.no_grad():
            mean, cov = ax.posterior(B, G)
        parts = [([mean], [cov], torch.ones(1, dtype=F64))]
        if laplace:
            ps, wts = ax.laplace(laplace, gen)
            with torch.no_grad():
                comps = [ax.posterior(B, G, p) for p in ps]
            parts.append(([m for m, _ in comps], [v for _, v in comps], wts))
        for out, (means, covs, wts) in zip(outs, parts):
            with torch.no_grad():
                M, V = torch.stack(means), torch.stack([v.diagonal().clamp_min(0) for v in covs])
                lo, hi = (mixture_quantile(q, M, V, wts) for q in (0.025, 0.975))
                inside = ((true[:, a] >= lo) & (true[:, a] <= hi)).double().mean()
                pick = torch.multinomial(wts, draws, replacement=True, generator=gen)
                roots = {int(k): psd_safe_cholesky(covs[int(k)]) for k in pick.unique()}  # the components drawn
                maps = torch.stack([M[k] + roots[int(k)] @ torch.randn(len(mean), generator=gen, dtype=F64)
                                    for k in pick])
                own = ((maps >= lo) & (maps <= hi)).double().mean(1)
                mmean, mvar = mixture_moments(M, V, wts)
            out[f"cover95_{name}"] = float(inside)
            out[f"pct95_{name}"] = float(metrics.percentile_among(inside, own))
            out[f"rmse_{name}"] = float((mmean - true[:, a]).pow(2).mean().sqrt())
            out[f"std_{name}"] = float(mvar.sqrt().mean())
            out[f"n_draws_{name}"] = len(means)
            out[f"sigma_L_{name}"] = float(ax.p["li"].exp().sqrt()) if li else float("nan")
            out[f"u_{name}"] = float(ax.p["gen"].exp()) if generic else float("nan")
            out[f"lengthscale_{name}"] = str([round(v, 2) for v in ax.p["ls"].exp().tolist()])
    for out in outs:
        for lv in (50, 90):  # the harness' summary reads them; this script scores the 95 % interval only
            out[f"cover{lv}_x"] = out[f"cover{lv}_z"] = float("nan")
    return outs


def run(case, library: bool, laplace: int, li_prior: tuple[float, float] = (1.0, LI_LOG_SD),
        models=MODELS[:2]) -> list[dict]:
    truth, label = medium(case.family, case.seed)
    c = motion(case.kind, case.seed)
    f = simulate(truth, c, case.noise, case.seed)
    base = {"family": case.family, "motion": case.kind, "seed": case.seed, "noise": case.noise, "medium": label}
    rows = []
    if library:
        m = InverseRFT(c, f, hyper_posterior="map")
        m.fit(n_iter=300, progress=False)
        rows.append({**base, "posterior": "map", **score(m, truth, 41, 200, case.seed)})
        if laplace:
            m.fit_hyper_posterior("laplace", generator=torch.Generator().manual_seed(case.seed))
            rows.append({**base, "posterior": "laplace", **score(m, truth, 41, 200, case.seed)})
    for name in models:
        li, generic = "+li" in name, "+generic" in name
        scored = dense_score(c, f, truth, li, case.seed, laplace, li_prior=li_prior, generic=generic)
        rows.append({**base, "posterior": name, **scored[0]})
        if laplace:
            rows.append({**base, "posterior": name + " laplace", **scored[1]})
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--motions", default=None, help="comma-separated harness motions (default short,rotating,turning; "
                   "every motion of a held-out set)")
    p.add_argument("--seeds", type=int, default=2, help="seeds per family x motion")
    p.add_argument("--held-out", action="store_true", help="the harness' second held-out set instead")
    p.add_argument("--held-out-1", action="store_true", help="the harness' first held-out set (sharp media, the "
                   "figure-eight) instead")
    p.add_argument("--no-library", action="store_true", help="skip the library's own plug-in fit (the map row)")
    p.add_argument("--laplace", type=int, default=0, metavar="N",
                   help="also score each model's Laplace mixture (N importance-weighted proposals; the library's "
                        "own Laplace row beside them)")
    p.add_argument("--li-prior", type=float, nargs=2, default=(1.0, LI_LOG_SD), metavar=("FACTOR", "LOG_SD"),
                   help="the k_Li variance's prior: its centre as a factor of the outputscale's, and its log-sd "
                        "(default 1 and log 2; a sensitivity check)")
    p.add_argument("--generic", action="store_true",
                   help="also fit rbf+li+generic: Li et al.'s generic map as a rank-one term u g g^T per map (the "
                        "generic shape with an uncertain scale), u under a log-normal prior at the medium's zeta "
                        "squared, log-sd log 2 (files get the suffix _generic)")
    p.add_argument("--first-seed", type=int, default=0, help="skip the seeds below this (fresh seeds: a run "
                   "with --seeds 6 --first-seed 2 scores seeds 2-5 only)")
    p.add_argument("--only-models", default=None, help="comma-separated subset of rbf,rbf+li,rbf+li+generic")
    p.add_argument("--limit", type=int, default=None, help="only the first N cases (a smoke run)")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "results")
    a = p.parse_args()
    torch.set_num_threads(2)
    held = a.held_out or a.held_out_1
    kinds = set((a.motions or ("" if held else "short,rotating,turning")).split(",")) - {""}
    todo = [c for c in cases(a.held_out_1, a.seeds, False, held_out_2=a.held_out, first_seed=a.first_seed)
            if not kinds or c.kind in kinds][:a.limit]
    models = MODELS if a.generic else MODELS[:2]
    if a.only_models:
        asked = a.only_models.split(",")
        if any(m not in models for m in asked):
            p.error(f"--only-models must name some of {', '.join(models)} (rbf+li+generic needs --generic), "
                    f"got {a.only_models!r}")
        models = tuple(m for m in models if m in asked)
    a.out.mkdir(parents=True, exist_ok=True)
    tag = "" if tuple(a.li_prior) == (1.0, LI_LOG_SD) else f"_prior{a.li_prior[0]:g}_{a.li_prior[1]:.3g}"
    tag += "_generic" if a.generic else ""
    tag += f"_seeds{a.first_seed}-{a.seeds - 1}" if a.first_seed else ""
    path = a.out / (f"fourier_kernel_term{tag}_laplace.csv" if a.laplace else f"fourier_kernel_term{tag}.csv")
    kept = run_resumable(todo, path, lambda case: run(case, not a.no_library, a.laplace, tuple(a.li_prior), models))
    order = ("map", "laplace", "rbf", "rbf laplace", "rbf+li", "rbf+li laplace", "rbf+li+generic",
             "rbf+li+generic laplace")
    posts = [hp for hp in order if any(r["posterior"] == hp for r in kept)]
    print("\n".join(coverage_table(kept, posts)))


if __name__ == "__main__":
    main()
