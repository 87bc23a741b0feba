"""Scoring candidate probes on a model with T = 1,000 force samples: time, and agreement between
the two forms of the belief, against gpytorch's own exact predictive covariance in the same run.

    python experiments/bench_active_probing.py [--T 1000] [--candidates 100] [--steps 200]

The model: 5 random probes (I- and C-toe, 200 samples each: T = 1,000, about 9,000 segments in
contact), exact path, hyperparameters at their data-scaled initial values (the cost does not
depend on them). Candidates: random probes of 200 samples each, half of either toe.
  - ProbeScorer, grid form (what method="auto" picks for this model): the exact posterior at the
    32 x 32 nodes once, then each candidate by interpolation;
  - ProbeScorer, exact form: each candidate against every training segment (lazy W K W^T);
  - reference: gpytorch's exact predictive covariance of each candidate's forces
    (``model.gp(rows).covariance_matrix``, the training solve cached by gpytorch), then the
    log-determinant for the EIG; timed on a subset and scaled to all candidates.
"""

from __future__ import annotations

import argparse
import time

import gpytorch
import torch

import irft_torch as irft
from irft_torch.gp.active_probing import ProbeScorer
from irft_torch.gp.encoding import encode_contacts
from irft_torch.rft import CToe, IToe, random_probes


def ranks(v: torch.Tensor) -> torch.Tensor:
    return torch.argsort(torch.argsort(v)).double()


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.corrcoef(torch.stack([ranks(a), ranks(b)]))[0, 1])


def reference_eig(model, contacts) -> torch.Tensor:
    """EIG from gpytorch's exact predictive covariance (noise-free forces), as a user would write it."""
    M = max(model.n_segments, contacts.n_segments)
    model._ensure_width(M)
    with torch.no_grad(), gpytorch.settings.max_cholesky_size(2**31), gpytorch.settings.fast_pred_var(False):
        S = model.gp(encode_contacts(contacts, M)).covariance_matrix  # (2, T_c, T_c)
        noise = model.likelihood.noise
        eye = torch.eye(S.shape[-1], dtype=S.dtype)
        return 0.5 * torch.logdet(eye + S / noise[:, None, None]).sum()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", type=int, default=1000, help="training force samples (5 probes)")
    ap.add_argument("--candidates", type=int, default=100)
    ap.add_argument("--steps", type=int, default=200, help="samples per candidate probe")
    ap.add_argument("--reference", type=int, default=20, help="candidates timed with the gpytorch reference")
    a = ap.parse_args(argv)
    torch.set_default_dtype(torch.float64)
    toes = {"I": IToe(0.02, 0.008), "C": CToe(0.02, 0.008, opening="left")}
    train_probes = random_probes(toes, 3, 0.44, n_steps=a.T // 5, seed=1)[:5]
    train = irft.rft.Contacts.cat([p.contacts() for p in train_probes])
    smap = irft.rft.FourierStressMap.generic(0.452, 0.417)
    f = irft.rft.forces(smap, train)
    f = f + 0.02 * f.abs().max() * torch.randn(f.shape, generator=torch.Generator().manual_seed(0))
    model = irft.InverseRFT(train, f, method="exact")
    n_seg = int((train.weight_z > 0).sum())
    cands = random_probes(toes, a.candidates // 2, 0.44, n_steps=a.steps, seed=2)
    cand_c = [p.contacts() for p in cands]
    seg_c = sum(int((c.weight_z > 0).sum()) for c in cand_c) / len(cand_c)
    print(f"model: T = {len(train)} force samples, {n_seg} segments in contact; {len(cands)} candidates of "
          f"{a.steps} samples ({seg_c:.0f} segments in contact on average); {torch.get_num_threads()} threads")

    results = {}
    for method in ("grid", "exact"):
        t0 = time.perf_counter()
        scorer = ProbeScorer.from_model(model, method=method)
        t_setup = time.perf_counter() - t0
        with torch.no_grad():
            t0 = time.perf_counter()
            iv = scorer.score(cand_c, "variance")
            t_iv = time.perf_counter() - t0
            t0 = time.perf_counter()
            eig = scorer.score(cand_c, "eig")
            t_eig = time.perf_counter() - t0
        results[method] = (iv, eig)
        print(f"ProbeScorer {method:5s}: set-up {t_setup:6.2f} s, {len(cands)} candidates: integrated variance "
              f"{t_iv:6.2f} s, information gain {t_eig:6.2f} s; set-up + IV {t_setup + t_iv:6.2f} s")
        results[method + "_time"] = t_setup + t_iv, t_setup + t_eig
    n_ref = min(a.reference, len(cands))
    t0 = time.perf_counter()
    ref = torch.stack([reference_eig(model, c) for c in cand_c[:n_ref]])
    t_ref = (time.perf_counter() - t0) * len(cands) / n_ref
    print(f"reference (gpytorch exact predictive covariance): {t_ref:6.2f} s for {len(cands)} candidates "
          f"(timed on {n_ref}, scaled)")
    g_iv, g_eig = results["grid"]
    e_iv, e_eig = results["exact"]
    err_ref = float(((e_eig[:n_ref] - ref) / ref).abs().max())
    print(f"exact form vs gpytorch EIG: max relative difference {err_ref:.1e}")
    print(f"grid vs exact form: IV max relative difference {float(((g_iv - e_iv) / e_iv).abs().max()):.2%}, "
          f"EIG {float(((g_eig - e_eig) / e_eig).abs().max()):.2%}; rank correlation IV {spearman(g_iv, e_iv):.3f}, "
          f"EIG {spearman(g_eig, e_eig):.3f}; same best candidate: IV {int(g_iv.argmin()) == int(e_iv.argmin())}, "
          f"EIG {int(g_eig.argmax()) == int(e_eig.argmax())}")
    print(f"ratios (EIG, reference time / ours): grid form {t_ref / results['grid_time'][1]:.1f}x, "
          f"exact form {t_ref / results['exact_time'][1]:.1f}x")


if __name__ == "__main__":
    main()
