"""One marginal-likelihood-plus-gradient step: InverseRFT's lazy W K W^T vs the paper's dense formula.

    python experiments/bench_inference.py [--T 200] [--M 10] [--repeats 5] [--no-memory]

Both run in this process on the same contacts (the paper's C-toe on gait 2 and random contacts),
float64; the ratio is printed. Then the exact path's peak memory is measured in fresh
subprocesses for a few T (M = 10, random contacts: no repeated angle pairs) and extrapolated
(power law) to the largest T that fits in 8 GB.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time

import torch

import irft_torch as irft


def random_contacts(T, M, seed=0):
    g = torch.Generator().manual_seed(seed)
    b = (torch.rand(T, M, generator=g) - 0.5) * math.pi
    gm = (torch.rand(T, M, generator=g) - 0.5) * math.pi
    w = torch.rand(T, M, generator=g)
    return irft.rft.Contacts(b, gm, -w, w)


def paper_contacts(T, M):
    toe = irft.rft.CToe(0.02, 0.008, M)
    path = irft.rft.spline_path([(-0.20, 0.0), (-0.10, -0.05), (0.10, 0.0), (0.20, -0.05)], n_steps=T)
    return irft.rft.contacts(toe, path)


def ours_step(model):
    model.train()
    mll = model.mll()
    for p in model.parameters():
        p.grad = None
    with model._settings():
        loss = -mll(model.gp(*model.gp.train_inputs), model.gp.train_targets).sum()
    loss.backward()
    return loss.item()


def dense_step(model, c, f):
    """The paper's formula: dense W (T x TM), dense K (TM x TM), per axis, Cholesky."""
    for p in model.parameters():
        p.grad = None
    ls, os, noise = model.kernel.lengthscale, model.kernel.outputscale, model.likelihood.noise
    T, M = c.shape
    th_b, th_g = c.beta.reshape(-1), c.gamma.reshape(-1)
    phi = torch.stack([torch.sin(2 * th_b), torch.cos(2 * th_b), torch.sin(th_g), torch.cos(th_g)], -1)
    total = 0.0
    rows = torch.arange(T).repeat_interleave(M)
    cols = torch.arange(T * M)
    for a, w in enumerate((c.weight_x, c.weight_z)):
        W = torch.zeros(T, T * M)
        W[rows, cols] = w.reshape(-1)
        x = phi / ls[a, 0]
        K = os[a] * torch.exp(-0.5 * ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1))
        S = W @ K @ W.T + noise[a] * torch.eye(T)
        L = torch.linalg.cholesky(S)
        y = f[:, a]
        alpha = torch.cholesky_solve(y[:, None], L)[:, 0]
        total = total + (0.5 * y @ alpha + torch.log(torch.diagonal(L)).sum() + 0.5 * T * math.log(2 * math.pi)) / T
    total.backward()
    return total.item()


def best_time(fn, repeats):
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def peak_memory_child(T, M):
    torch.set_default_dtype(torch.float64)
    c = random_contacts(T, M)
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(), c)
    model = irft.InverseRFT(c, f)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    ours_step(model)
    dt = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"T": T, "peak_gb": peak / 2**20, "step_gb": (peak - base) / 2**20, "seconds": dt}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", type=int, default=200)
    ap.add_argument("--M", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--no-memory", action="store_true", help="skip the subprocess memory sweep")
    ap.add_argument("--_child", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._child:
        return peak_memory_child(a._child, a.M)
    torch.set_default_dtype(torch.float64)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, T = {a.T}, M = {a.M}, float64")
    smap = irft.rft.FourierStressMap.generic(0.452, 0.417)
    for name, c in (("C-toe, gait 2", paper_contacts(a.T, a.M)), ("random contacts", random_contacts(a.T, a.M))):
        f = irft.rft.forces(smap, c)
        model = irft.InverseRFT(c, f)
        l1, l2 = ours_step(model), dense_step(model, c, f)
        assert abs(l1 - l2) < 1e-8 * abs(l2), (l1, l2)
        t_ours = best_time(lambda: ours_step(model), a.repeats)
        t_dense = best_time(lambda: dense_step(model, c, f), a.repeats)
        print(f"  {name:16s}: ours {t_ours * 1e3:8.1f} ms   dense W K W^T {t_dense * 1e3:8.1f} ms   "
              f"ratio {t_dense / t_ours:6.1f}x  (same loss to 1e-8)")
    if a.no_memory:
        return
    print("exact path peak memory, one step, random contacts (fresh process each):")
    pts = []
    for T in (250, 500, 1000):
        out = subprocess.run([sys.executable, __file__, "--_child", str(T), "--M", str(a.M)],
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        pts.append((T, r["step_gb"]))
        print(f"  T = {T:5d}: +{r['step_gb']:.2f} GB over the process baseline, {r['seconds']:.2f} s")
    (t1, m1), (t2, m2) = pts[-2], pts[-1]
    slope = math.log(m2 / m1) / math.log(t2 / t1)
    t_max = t2 * (8.0 / m2) ** (1 / slope)
    print(f"  memory ~ T^{slope:.2f}; largest T in 8 GB with M = {a.M}: about {t_max:,.0f} "
          f"(random angles; repeated angle pairs, e.g. an I-toe, go much further)")


if __name__ == "__main__":
    main()
