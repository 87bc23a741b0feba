"""Scale and speed of I-RFT: exact vs grid path, long recordings, streaming. Writes
experiments/results/benchmarks.md and scaling.png.

    python experiments/bench_scaling.py [--out experiments/results] [--quick]

Every size runs in a fresh subprocess, so its peak memory (ru_maxrss) is its own. Contacts are the
C-toe on the paper's cubic gait, repeated with small random jitter (each repeat a new trial), M = 10.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

import irft_torch as irft

TRUTH = irft.rft.FourierStressMap.generic(0.452, 0.417)


def recording(T: int, seed: int = 0):
    """T samples: repeats of the C-toe gait-2 run (1,000 samples each), angles and forces jittered."""
    toe = irft.rft.CToe(0.02, 0.008, 10, opening="left")
    base = irft.rft.contacts(toe, irft.rft.spline_path([(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)],
                                                       n_steps=1000))
    reps = math.ceil(T / 1000)
    g = torch.Generator().manual_seed(seed)
    parts = [torch.cat([v] * reps)[:T] for v in (base.beta, base.gamma, base.weight_x, base.weight_z)]
    jit = lambda v: v + 1e-3 * torch.randn(v.shape, generator=g)  # noqa: E731
    c = irft.rft.Contacts(jit(parts[0]).clamp(-math.pi / 2, math.pi / 2 - 1e-9), jit(parts[1]).clamp(-1.5, 1.5),
                          parts[2], parts[3])
    f = irft.rft.forces(TRUTH, c)
    return c, f + 0.01 * f.abs().amax(0) * torch.randn(f.shape, generator=g)


def child(kind: str, T: int, n_iter: int) -> dict:
    torch.set_default_dtype(torch.float64)
    c, f = recording(T)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    model = irft.InverseRFT(c, f, method=kind)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    model.fit(n_iter=n_iter, progress=False)
    t_fit = time.perf_counter() - t0
    b, g = torch.meshgrid(torch.linspace(-1.5, 1.5, 50), torch.linspace(-1.5, 1.5, 50), indexing="ij")
    t0 = time.perf_counter()
    model.stress_map(b, g)
    t_map = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"kind": kind, "T": T, "n_iter": n_iter, "build_s": t_build, "fit_s": t_fit, "map_s": t_map,
            "total_s": t_build + t_fit + t_map, "peak_gb": peak / 2**20, "added_gb": (peak - base) / 2**20}


def run_child(kind, T, n_iter, timeout=900):
    out = subprocess.run([sys.executable, __file__, "--_child", kind, str(T), str(n_iter)], capture_output=True,
                         text=True, timeout=timeout)
    if out.returncode != 0:
        return {"kind": kind, "T": T, "error": out.stderr.strip().splitlines()[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def best_time(fn, repeats=3):
    fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def paper_scale(lines):
    import gpytorch

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_inference import dense_step, ours_step, paper_contacts

    T, M = 200, 10
    c = paper_contacts(T, M)
    f = irft.rft.forces(TRUTH, c)
    model = irft.InverseRFT(c, f, method="exact")
    t_ours = best_time(lambda: ours_step(model))
    t_dense = best_time(lambda: dense_step(model, c, f))

    class Plain(gpytorch.models.ExactGP):
        def __init__(self, x, y, lik):
            super().__init__(x, y, lik)
            self.mean = gpytorch.means.ZeroMean(batch_shape=torch.Size([2]))
            self.cov = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=4, batch_shape=torch.Size(
                [2])), batch_shape=torch.Size([2]))

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean(x), self.cov(x))

    x = torch.randn(2, T, 4)
    y = torch.randn(2, T)
    lik = gpytorch.likelihoods.GaussianLikelihood(batch_shape=torch.Size([2]))
    plain = Plain(x, y, lik)
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, plain)

    def plain_step():
        plain.zero_grad()
        with gpytorch.settings.max_cholesky_size(10**6):
            (-mll(plain(x), y).sum()).backward()

    t_plain = best_time(plain_step)
    lines += ["## Paper scale (T = 200 force samples, M = 10 segments), one likelihood + gradient step", "",
              "| model | time | ratio to ours |", "|---|---|---|",
              f"| InverseRFT exact (lazy W K W^T) | {t_ours * 1e3:.1f} ms | 1.0 |",
              f"| the paper's formula, dense W and dense K | {t_dense * 1e3:.1f} ms | {t_dense / t_ours:.1f} |",
              f"| plain gpytorch ExactGP, {T} direct observations per axis | {t_plain * 1e3:.1f} ms | "
              f"{t_plain / t_ours:.2f} |", ""]
    print("\n".join(lines[-7:]), flush=True)


def agreement(lines, sizes):
    """Exact and grid posteriors with the same hyperparameters (fitted once, exact path, T = 300)."""
    c0, f0 = recording(300, seed=1)
    ref = irft.InverseRFT(c0, f0, method="exact")
    ref.fit(n_iter=40, progress=False)
    rows = ["## Grid (32 x 32) vs exact map, same hyperparameters (fitted on 300 samples, exact path)", "",
            "| T | max abs difference / range, x | z |", "|---|---|---|"]
    b, g = torch.meshgrid(torch.linspace(-1.5, 1.5, 40), torch.linspace(-1.5, 1.5, 40), indexing="ij")
    rng = TRUTH(b, g).amax((0, 1)) - TRUTH(b, g).amin((0, 1))
    for T in sizes:
        c, f = recording(T, seed=T)
        models = [irft.InverseRFT(c, f, method=m) for m in ("exact", "grid")]
        for m in models:
            m.kernel.load_state_dict(ref.kernel.state_dict())
            m.likelihood.load_state_dict(ref.likelihood.state_dict())
        models[1].grid_model._cache = None
        ex, gr = (m.stress_map(b, g).mean for m in models)
        err = ((ex - gr).abs().amax((0, 1)) / rng * 100).tolist()
        rows.append(f"| {T} | {err[0]:.2f} % | {err[1]:.2f} % |")
        print(rows[-1], flush=True)
    lines += rows + [""]


def streaming(lines, n_base=10_000, n_add=2_000):
    c, f = recording(n_base + n_add, seed=5)
    model = irft.InverseRFT(c[:n_base], f[:n_base], method="grid")
    model.fit(n_iter=30, progress=False)
    b = torch.linspace(-1.4, 1.4, 25)
    model.stress_map(b, b)
    t0 = time.perf_counter()
    for i in range(n_base, n_base + n_add):
        model.add_data(c[i:i + 1], f[i:i + 1])
    per_sample = (time.perf_counter() - t0) / n_add
    t0 = time.perf_counter()
    post = model.stress_map(b, b)
    t_query = time.perf_counter() - t0
    batch = irft.InverseRFT(c, f, method="grid")
    batch.kernel.load_state_dict(model.kernel.state_dict())
    batch.likelihood.load_state_dict(model.likelihood.state_dict())
    ref = batch.stress_map(b, b)
    diff = (post.mean - ref.mean).abs().max().item()
    lines += ["## Streaming (grid path, hyperparameters fixed)", "",
              f"Adding {n_add} samples one at a time to a model of {n_base}: {per_sample * 1e3:.3f} ms per sample; "
              f"the next posterior query (refactorization) {t_query * 1e3:.0f} ms, i.e. "
              f"{(per_sample + t_query / n_add) * 1e3:.3f} ms per sample amortized over the {n_add}. Posterior "
              f"mean vs a batch model on the same data and hyperparameters: max difference {diff:.1e}.", ""]
    print(lines[-2], flush=True)


def slope(points):
    xs = [math.log(p[0]) for p in points]
    ys = [math.log(p[1]) for p in points]
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="experiments/results")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--_child", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._child:
        print(json.dumps(child(a._child[0], int(a._child[1]), int(a._child[2]))))
        return
    torch.set_default_dtype(torch.float64)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# Benchmarks: scale and speed", "",
             f"`python experiments/bench_scaling.py{' --quick' if a.quick else ''}`; torch {torch.__version__}, "
             f"{torch.get_num_threads()} threads, float64. Ratios are measured in the same run.", ""]
    paper_scale(lines)
    agreement(lines, [300, 600] if a.quick else [300, 600, 1200])
    streaming(lines)
    exact_T = [250, 500] if a.quick else [250, 500, 1000]
    grid_T = [1_000, 10_000, 100_000] if a.quick else [1_000, 10_000, 100_000, 1_000_000]
    n_iter = 50
    res = [run_child("exact", T, 3) for T in exact_T] + [run_child("grid", T, n_iter) for T in grid_T]
    lines += ["## Time and peak memory against the number of force samples (M = 10)", "",
              "exact: construction + 3 Adam steps + a 50 x 50 map; grid (32 x 32): construction (one pass "
              f"over the data) + {n_iter} Adam steps + a 50 x 50 map.", "",
              "| path | T | build s | fit s | map s | total s | peak GB |", "|---|---|---|---|---|---|---|"]
    for r in res:
        if "error" in r:
            lines.append(f"| {r['kind']} | {r['T']} | failed: {r['error']} | | | | |")
        else:
            lines.append(f"| {r['kind']} | {r['T']:,} | {r['build_s']:.2f} | {r['fit_s']:.2f} | {r['map_s']:.2f} | "
                         f"{r['total_s']:.2f} | {r['peak_gb']:.2f} |")
        print(lines[-1], flush=True)
    ok = {k: [r for r in res if r["kind"] == k and "error" not in r] for k in ("exact", "grid")}
    from irft_torch import plotting

    fig, axes = plotting.plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for k, rs in ok.items():
        if len(rs) >= 2:
            ts = [(r["T"], r["total_s"]) for r in rs]
            ms = [(r["T"], r["peak_gb"]) for r in rs]
            axes[0].loglog(*zip(*ts), "o-", label=f"{k}: slope {slope(ts):.2f}")
            axes[1].loglog(*zip(*ms), "o-", label=f"{k}: slope {slope(ms):.2f}")
            lines.append(f"- {k}: time ~ T^{slope(ts):.2f}, peak memory ~ T^{slope(ms):.2f} "
                         f"(log-log least squares over T = {', '.join(str(t) for t, _ in ts)})")
    for ax, label in zip(axes, ("seconds", "peak memory (GB)")):
        ax.set_xlabel("force samples T")
        ax.set_ylabel(label)
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
    plotting.save(fig, out / "scaling.png")
    lines += ["", "Figure: `scaling.png` (log-log). The grid path's time is one pass over the data (linear in T) "
              "plus a per-step cost independent of T; its memory is the data itself plus O(U^2)."]
    (out / "benchmarks.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out}/benchmarks.md and scaling.png")


if __name__ == "__main__":
    main()
