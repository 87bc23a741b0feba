"""Forward RFT throughput: segment evaluations per second, batched, against a per-segment loop.

Data: random segments. Run time: about 3 s at the default 10^6 segments (2 cores, 2026-12-03).

    python experiments/benchmarks/bench_forward.py [--n 1000000]

Prints segments/s for ``irft.rft.forces`` on n random segments (float64 and float32) and, as a
same-run reference, a plain Python loop over the expanded Li et al. formula on a small sample.
"""

from __future__ import annotations

import argparse
import math
import time

import torch

import irft_torch as irft


def best_of(fn, repeats=5):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="segments (default 10^6)")
    a = ap.parse_args()
    torch.manual_seed(0)
    T, M = a.n // 10, 10
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {T} x {M} segments")
    smap = irft.rft.FourierStressMap.generic()
    results = {}
    for dtype in (torch.float64, torch.float32):
        b = (torch.rand(T, M, dtype=dtype) - 0.5) * math.pi
        g = (torch.rand(T, M, dtype=dtype) - 0.5) * math.pi
        w = torch.rand(T, M, dtype=dtype)
        c = irft.rft.Contacts(b, g, -w, w)
        irft.rft.forces(smap, c)
        dt = best_of(lambda: irft.rft.forces(smap, c))
        results[dtype] = T * M / dt
        print(f"  batched {str(dtype):14s}: {T * M / dt:.3e} segments/s ({dt * 1e3:.1f} ms)")
    n_loop = 20_000
    bl, gl = b.double().flatten()[:n_loop].tolist(), g.double().flatten()[:n_loop].tolist()

    def loop():
        for bi, gi in zip(bl, gl):
            0.206 + 0.169 * math.cos(2 * bi) + 0.212 * math.sin(2 * bi + gi) + 0.358 * math.sin(gi) \
                + 0.055 * math.sin(-2 * bi + gi)
            -0.124 * math.cos(2 * bi + gi) + 0.253 * math.cos(gi) + 0.007 * math.cos(-2 * bi + gi) \
                + 0.088 * math.sin(2 * bi)

    loop_rate = n_loop / best_of(loop, 3)
    print(f"  python loop reference : {loop_rate:.3e} segments/s")
    print(f"ratio batched float64 / loop: {results[torch.float64] / loop_rate:.0f}x; "
          f"target >= 1e7 segments/s: {'met' if results[torch.float64] >= 1e7 else 'NOT met'}")


if __name__ == "__main__":
    main()
