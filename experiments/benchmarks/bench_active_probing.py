"""Scoring candidate probes on a model with T = 1,000 force samples: time and agreement, against
gpytorch's own exact predictive covariance in the same run.

Data: simulated (random I- and C-toe probes, forward RFT). Run time: about 9 s with the defaults (2 cores, 2026-12-03).

    python experiments/benchmarks/bench_active_probing.py [--T 1000] [--candidates 100] [--steps 200] [--device cuda]

The model: 5 random probes (I- and C-toe, 200 samples each: T = 1,000, about 9,000 segments in
contact), hyperparameters at their data-scaled initial values (the cost does not depend on them).
Candidates: random probes of 200 samples each, half of either toe.
  - ProbeScorer.from_model(model), the default: the model's backend (what method="auto" picked:
    spectral here) in the basis that 1e-4 of the kernel variance needs (``tol="auto"``);
  - the same in the model's own basis (``tol=None``, 1e-7) and at tol 1e-5: time, and the scores'
    difference and rank correlation with the model's basis;
  - ProbeScorer on the observations backend (each candidate against every training segment);
  - reference: gpytorch's exact predictive covariance of each candidate's forces
    (``model.gp(rows).covariance_matrix`` on an observations model, the training solve cached by
    gpytorch), then the log-determinant for the EIG; timed on a subset and scaled to all.
"""

from __future__ import annotations

import argparse
import time

import gpytorch
import torch

import irft_torch as irft
from irft_torch.design import ProbeScorer
from irft_torch.gp.kernels.encoding import encode_contacts
from irft_torch.rft import CToe, IToe, random_probes


def ranks(v: torch.Tensor) -> torch.Tensor:
    return torch.argsort(torch.argsort(v)).double()


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.corrcoef(torch.stack([ranks(a), ranks(b)]))[0, 1])


def reference_eig(model, contacts) -> torch.Tensor:
    """EIG from gpytorch's exact predictive covariance (noise-free forces), as a user would write it."""
    backend = model.backend
    M = max(backend.n_segments, contacts.n_segments)
    backend._ensure_width(M)
    with torch.no_grad(), gpytorch.settings.max_cholesky_size(2**31), gpytorch.settings.fast_pred_var(False):
        S = model.gp(encode_contacts(contacts, M)).covariance_matrix  # (2, T_c, T_c)
        noise = model.hypers.noise
        eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
        return 0.5 * torch.logdet(eye + S / noise[:, None, None]).sum()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", type=int, default=1000, help="training force samples (5 probes)")
    ap.add_argument("--candidates", type=int, default=100)
    ap.add_argument("--steps", type=int, default=200, help="samples per candidate probe")
    ap.add_argument("--reference", type=int, default=10, help="candidates timed with the gpytorch reference")
    ap.add_argument("--observations", type=int, default=10,
                    help="candidates scored on the observations backend (its time is scaled to all)")
    ap.add_argument("--device", default="cpu", help="cpu (default) or cuda: model, candidates and reference there")
    a = ap.parse_args(argv)
    dev = torch.device(a.device)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    torch.set_default_dtype(torch.float64)
    toes = {"I": IToe(0.02, 0.008), "C": CToe(0.02, 0.008, opening="left")}
    train_probes = random_probes(toes, 3, 0.44, n_steps=a.T // 5, seed=1)[:5]
    train = irft.rft.Contacts.cat([p.contacts() for p in train_probes])
    smap = irft.rft.FourierStressMap.generic(0.452, 0.417)
    f = irft.rft.forces(smap, train)
    f = f + 0.02 * f.abs().max() * torch.randn(f.shape, generator=torch.Generator().manual_seed(0))
    train, f = train.to(device=dev), f.to(dev)
    # the scorer's speed: one plug-in
    model = irft.InverseRFT(train, f, hyper_posterior="map", prior=irft.MapPrior(kernel="rbf"))
    exact = irft.InverseRFT(train, f, prior=irft.MapPrior(kernel="rbf"), engine="observations", hyper_posterior="map")
    n_seg = int((train.weight_z > 0).sum())
    cands = random_probes(toes, a.candidates // 2, 0.44, n_steps=a.steps, seed=2)
    cand_c = [p.contacts().to(device=dev) for p in cands]
    seg_c = sum(int((c.weight_z > 0).sum()) for c in cand_c) / len(cand_c)
    print(f"model: T = {len(train)} force samples, {n_seg} segments in contact, backend {model.backend.describe()}; "
          f"{len(cands)} candidates of {a.steps} samples ({seg_c:.0f} segments in contact on average); "
          f"{torch.get_num_threads()} threads, device {a.device}")
    results = {}
    for name, m, tol in (("default", model, "auto"), ("model", model, None), ("1e-5", model, 1e-5),
                         ("observations", exact, None)):
        n = len(cand_c) if name != "observations" else min(a.observations, len(cand_c))
        sync()
        t0 = time.perf_counter()
        scorer = ProbeScorer.from_model(m, tol=tol)
        with torch.no_grad():
            scorer.integrated_variance()  # the region's current variance: part of the set-up
            sync()
            t_setup = time.perf_counter() - t0
            t0 = time.perf_counter()
            iv = scorer.score(cand_c[:n], "variance")
            sync()
            t_iv = (time.perf_counter() - t0) * len(cand_c) / n
            t0 = time.perf_counter()
            eig = scorer.score(cand_c[:n], "eig")
            sync()
            t_eig = (time.perf_counter() - t0) * len(cand_c) / n
        results[name] = (iv, eig, t_setup + t_iv, t_setup + t_eig)
        label = {"default": "default (tol auto)", "model": "model's basis", "1e-5": "tol 1e-5"}.get(name, name)
        print(f"ProbeScorer, {label:18s} ({scorer.backend.describe()}): set-up {t_setup:5.2f} s, {len(cands)} "
              f"candidates: integrated variance {t_iv:5.2f} s, information gain {t_eig:5.2f} s"
              + ("" if n == len(cand_c) else f" (timed on {n}, scaled)"), flush=True)
    for name in ("default", "1e-5"):
        iv, eig = results[name][:2]
        m_iv, m_eig = results["model"][:2]
        print(f"{name} vs the model's basis: IV max relative difference {float(((iv - m_iv) / m_iv).abs().max()):.1e} "
              f"(Spearman {spearman(iv, m_iv):.4f}, same best: {int(iv.argmin()) == int(m_iv.argmin())}), EIG "
              f"{float(((eig - m_eig) / m_eig).abs().max()):.1e} (Spearman {spearman(eig, m_eig):.4f}, same best: "
              f"{int(eig.argmax()) == int(m_eig.argmax())})")
    n_ref = min(a.reference, len(cands))
    t0 = time.perf_counter()
    ref = torch.stack([reference_eig(exact, c) for c in cand_c[:n_ref]])
    sync()
    t_ref = (time.perf_counter() - t0) * len(cands) / n_ref
    print(f"reference (gpytorch exact predictive covariance): {t_ref:6.2f} s for {len(cands)} candidates "
          f"(timed on {n_ref}, scaled)")
    a_iv, a_eig, a_t_iv, a_t_eig = results["model"]
    e_iv, e_eig, e_t_iv, e_t_eig = results["observations"]
    n_cmp = min(n_ref, len(e_eig))
    print(f"observations-backend EIG vs gpytorch: max relative difference "
          f"{float(((e_eig[:n_cmp] - ref[:n_cmp]) / ref[:n_cmp]).abs().max()):.1e}")
    k = len(e_iv)
    print(f"{model.method} vs observations (first {k}): IV max relative difference "
          f"{float(((a_iv[:k] - e_iv) / e_iv).abs().max()):.1e}, "
          f"EIG {float(((a_eig[:k] - e_eig) / e_eig).abs().max()):.1e}")
    d_t_iv, d_t_eig = results["default"][2:]
    print(f"ratios (reference EIG time / ours): default {t_ref / d_t_eig:.1f}x, {model.method} in the model's basis "
          f"{t_ref / a_t_eig:.1f}x, observations {t_ref / e_t_eig:.1f}x (EIG); set-up + {len(cands)} scores, default: "
          f"IV {d_t_iv:.2f} s, EIG {d_t_eig:.2f} s (target <= 0.2 s); model's basis: IV {a_t_iv:.2f} s, EIG "
          f"{a_t_eig:.2f} s")


if __name__ == "__main__":
    main()
