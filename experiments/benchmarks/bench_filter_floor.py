"""What a TerrainFilter step cannot go below on this machine: the kernel row's exponentials, and the kernel row
itself, eager and compiled.

Data: random angles, weights and exponents (B x M = 4096 x 10), nothing to download. Run time: about 4 s
(2 cores, 2026-12-03); --compile not measured.

Issue 33 asks for 1e5 env-steps per second at B = 4096 environments, M = 10 segments, one update and a
16-point map query per step: 41 ms per step. An update must evaluate the new sample's kernel row against
the n samples held (n M^2 kernel values per map axis, each one exponential): at window n = 16 that is
2 x 16 x 10 x 10 x 4096 = 13.1 million exponentials per step, which no algebra avoids (each pair of samples
meets exactly once while both are in the window). This script times, each against the 41 ms budget in the
same run:

1. ``torch.exp`` of 13.1 M numbers, in cache-sized pieces into one buffer (the exponentials alone);
2. the kernel row as ``TerrainFilter`` computes it (one batched matmul for the exponents, the exponential,
   the weighted sums), in the filter's blocks;
3. with ``--compile``: the same row written for ``torch.compile`` (inductor, this machine's C++ compiler),
   the environments innermost so that every loop is vectorised over them: one fused kernel.

    python experiments/benchmarks/bench_filter_floor.py [--compile] [--envs 4096] [--window 16]

Prints ms per step for float64 and float32 and the share of the 41 ms budget.
"""

from __future__ import annotations

import argparse
import time

import torch

from irft_torch.gp.kernels.embedding import embed_angles
from irft_torch.gp.streaming.filter import TerrainFilter

BUDGET_MS = 4096 / 1e5 * 1e3  # 1e5 env-steps/s at B = 4096


def best_ms(fn, repeats: int = 5) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def sides(beta, gamma, lengthscale, outputscale):
    """The filter's kernel sides (``TerrainFilter._sides``) for angles (..., M)."""
    phi = embed_angles(beta, gamma)
    scaled = phi.unsqueeze(-3) / lengthscale.view(2, 1, 4)
    half = -0.5 * scaled.pow(2).sum(-1)
    left = torch.cat([scaled / lengthscale.view(2, 1, 4), (outputscale.log()[:, None] + half)[..., None]], -1)
    right = torch.cat([phi, torch.ones_like(phi[..., :1])], -1).mT
    return left, right, half.unsqueeze(-2)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, default=4096)
    p.add_argument("--window", type=int, default=16)
    p.add_argument("--segments", type=int, default=10)
    p.add_argument("--compile", action="store_true", help="also time the inductor-compiled kernel row")
    a = p.parse_args()
    B, N, M = a.envs, a.window, a.segments
    n_exp = 2 * N * M * M * B
    print(f"B = {B}, window {N}, M = {M}: {n_exp / 1e6:.1f} M kernel exponentials per step; budget "
          f"{BUDGET_MS:.1f} ms per step (1e5 env-steps/s at B = 4096)")
    g = torch.Generator().manual_seed(0)
    for dtype in (torch.float64, torch.float32):
        name = "float64" if dtype == torch.float64 else "float32"
        x = -torch.rand(n_exp, generator=g, dtype=torch.float64).to(dtype) * 5
        piece = 1 << 18
        buf = torch.empty(piece, dtype=dtype)

        def exps():
            for i in range(0, n_exp, piece):
                xi = x[i:i + piece]
                torch.exp(xi, out=buf[:len(xi)])  # into one cache-sized buffer: the exponentials alone

        t_exp = best_ms(exps)
        ls = torch.tensor([[0.8, 1.1, 0.9, 1.3], [0.7, 1.0, 1.2, 0.9]], dtype=dtype)
        os_ = torch.tensor([0.3, 0.5], dtype=dtype)
        ang = [torch.rand(B, k, generator=g, dtype=torch.float64).to(dtype) * 3 for k in (M, M, N * M, N * M)]
        left, _, _ = sides(ang[0], ang[1], ls, os_)
        _, right, c_right = sides(ang[2], ang[3], ls, os_)
        w = torch.rand(B, 2, 1, M, generator=g, dtype=torch.float64).to(dtype)
        wt = torch.rand(B, 2, N, M, generator=g, dtype=torch.float64).to(dtype)
        block = max(1, (32 << 20) // ((2 * (2 * N * N + 2 * M * N * M + 2 * N * 16) + 8 * N * M) * x.element_size()))

        def eager():
            return [TerrainFilter._kernel(left[i:i + block], w[i:i + block], right[i:i + block],
                                          c_right[i:i + block], wt[i:i + block]) for i in range(0, B, block)]

        t_eager = best_ms(eager)
        line = (f"{name}: exp of {n_exp / 1e6:.1f} M numbers {t_exp:.1f} ms = {t_exp / BUDGET_MS:.0%} of the "
                f"budget; the kernel row, eager (the filter's code) {t_eager:.1f} ms = "
                f"{t_eager / BUDGET_MS:.0%}")
        if a.compile:
            # environments innermost: (2, M, 5, B), (5, N M, B), (2, N M, B), (2, M, B), (2, N, M, B)
            L, Rt = left.permute(1, 2, 3, 0).contiguous(), right.permute(1, 2, 0).contiguous()
            C = c_right[:, :, 0].permute(1, 2, 0).contiguous()
            W, WT = w[:, :, 0].permute(1, 2, 0).contiguous(), wt.permute(1, 2, 3, 0).contiguous()

            def fused(L, Rt, C, W, WT):
                e = C[:, None] + L[:, :, 4:5]
                for k in range(4):
                    e = e + L[:, :, k:k + 1] * Rt[k][None, None]
                s = (e.exp() * W[:, :, None]).sum(1)
                return (s.view(2, N, M, -1) * WT).sum(2)

            compiled = torch.compile(fused, dynamic=False)
            t0 = time.perf_counter()
            out = compiled(L, Rt, C, W, WT)
            t_build = time.perf_counter() - t0
            ref = torch.cat([k.view(-1, 2, N) for k in eager()]).permute(1, 2, 0)
            err = float((out - ref).abs().max() / ref.abs().max())
            t_comp = best_ms(lambda: compiled(L, Rt, C, W, WT))
            line += (f"; compiled (inductor, one fused kernel, {t_build:.0f} s to build, relative difference "
                     f"{err:.1e}) {t_comp:.1f} ms = {t_comp / BUDGET_MS:.0%}")
        print(line, flush=True)


if __name__ == "__main__":
    main()
