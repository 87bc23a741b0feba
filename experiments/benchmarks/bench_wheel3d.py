"""Case 13 of ``bench_inference.py`` (issue 52): one fold of the 3-D rover-wheel study with the constructor's defaults.

Measures: ``InverseRFT(contacts_3d, forces).fit()`` on the measured smooth wheel, one slip angle held out (its own
kinematics, as ``experiments/validation/wheel_validation_3d.py`` builds them): construction, the fit, the Adam
steps and L-BFGS evaluations it took, one likelihood + gradient step at the start and at the end, the basis it ended
in and its kernel error; against the engine before e2da7f5 emulated in the same run (300 Adam steps, one basis
sized for every map, features in one product per chunk). Each fit runs in a fresh
process. ``--before-tree`` times the commit before e2da7f5 itself (a checkout of it) instead of the emulation. Data:
the shared rover-wheel runs (``--wheel-data``; not shipped: no licence). Run time: about 40 s.

    git worktree add /tmp/before e2da7f5~1   # optional: the engine before, as it was
    python experiments/benchmarks/bench_wheel3d.py --wheel-data ../shared/data/rover_wheel [--before-tree /tmp/before]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path
from unittest import mock

import numpy as np
import torch

HERE = Path(__file__).resolve().parent


@contextlib.contextmanager
def engine_before():
    """The 3-D engine as it was before e2da7f5: Adam runs its 300 steps (no converged stop, so no L-BFGS), every map
    in the one basis the shortest lengthscale needs, and the features in one product per chunk of samples."""
    import irft_torch.gp.inverse3d.features as features
    import irft_torch.gp.inverse3d.model as model
    import irft_torch.gp.inverse3d.spectral as backends

    per_map = backends.Spectral3D._bases_for

    def one_basis(self, lengthscale, shrink=1.0):
        bases = per_map(self, lengthscale, shrink)
        union = features.union_basis(bases)
        return tuple(None if b is None else union for b in bases)

    def refresh(self):  # the one basis grows for the map that needs it most
        if not self.stale():
            return False
        need, old = one_basis(self, self.hypers.lengthscale, 0.85), self.basis
        union = next(b for b in need if b is not None)
        grown = backends.FourierBasis(min(max(union.n_beta, old.n_beta), self.max_harmonics),
                                      min(max(union.n_gamma, old.n_gamma), self.max_harmonics))
        if grown == old:
            return False
        self.bases = tuple(None if b is None else grown for b in self.bases)
        self._set_features()
        return True

    with mock.patch.object(model, "converged", lambda *a, **k: False), \
            mock.patch.object(features, "_beta_groups", lambda beta: None), \
            mock.patch.object(backends.Spectral3D, "_bases_for", one_basis), \
            mock.patch.object(backends.Spectral3D, "refresh", refresh):
        yield


def step_time(model, repeats: int = 5) -> float:
    """Seconds of one likelihood + gradient step at the model's hyperparameters (best of ``repeats``)."""
    best = float("inf")
    for _ in range(repeats):
        for p in model.hypers.parameters():
            p.grad = None
        t0 = time.perf_counter()
        model.backend.loss().backward()
        best = min(best, time.perf_counter() - t0)
    return best


def one_fold(data: Path, wheel: str = "smooth", held_out: int = 2) -> dict:
    """The fold's fit with the defaults: times (s), steps, final loss per sample, basis, kernel error, warnings."""
    sys.path.insert(0, str(HERE.parent / "validation"))
    import wheel_validation_3d as w

    from irft_torch.gp.inverse3d import InverseRFT3D

    d = w.wheel_data_3d(data, wheel)
    train = torch.as_tensor(np.nonzero(d["groups"]["slip angle"] != held_out)[0])
    c, f = d["c"][train], d["F"][train]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        model = InverseRFT3D(c, f)
        t1 = time.perf_counter()
        first = step_time(model, 3)
        t2 = time.perf_counter()
        history = model.fit(progress=False)
        t3 = time.perf_counter()
    last = step_time(model, 3)
    return {"build": t1 - t0, "fit": t3 - t2, "total": (t1 - t0) + (t3 - t2), "first": first, "last": last,
            "steps": len(history), "loss": float(model.loss().detach()), "describe": model.backend.describe(),
            "error": float(model.truncation_error().max()), "tol": model.tol, "T": len(c),
            "warnings": [str(x.message) for x in caught]}


def _child(data: Path, before: str | None) -> dict:
    """``one_fold`` in a fresh process (each pays its own imports): the library of this tree, or of ``before`` (a
    checkout of an earlier commit: ``git worktree add /tmp/before e2da7f5~1``), or "emulated"."""
    env = dict(os.environ)
    cmd = [sys.executable, __file__, "--wheel-data", str(data), "--json"]
    if before == "emulated":
        cmd.append("--emulate-before")
    elif before is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(Path(before).resolve()), env.get("PYTHONPATH", "")])
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def wheel_fold_case(data: Path | None, row, before: str | None = None) -> None:
    """13. The 3-D wheel fold with the defaults, against the engine before (same run; ``before``: a checkout of the
    commit before e2da7f5, else emulated); skipped without data."""
    if data is None or not Path(data).is_dir():
        row("13. 3-D wheel fold with the defaults", "skipped: no --wheel-data (the shared rover-wheel runs)", "-", "-",
            "< 10 s, kernel error within tol")
        return
    ours = _child(Path(data), None)
    ref = _child(Path(data), before or "emulated")
    name = "emulated" if before is None else f"the tree at {before}"
    row(f"13. 3-D wheel fold, smooth wheel, slip angle 2 held out (T = {ours['T']}), "
        f"`InverseRFT3D(contacts, forces).fit()` ({ours['describe']})",
        f"{ours['total']:.1f} s (build {ours['build']:.1f}, fit {ours['fit']:.1f}; {ours['steps']} losses in the "
        f"history, Adam's then L-BFGS's last; step {ours['first'] * 1e3:.0f} ms first, {ours['last'] * 1e3:.0f} ms "
        f"last); loss "
        f"{ours['loss']:.4f}; kernel error {ours['error']:.1e} (tol {ours['tol']:.0e}); {len(ours['warnings'])} "
        f"warnings",
        f"the engine before e2da7f5 ({name}): {ref['total']:.1f} s ({ref['steps']} Adam steps; step "
        f"{ref['first'] * 1e3:.0f} / {ref['last'] * 1e3:.0f} ms); loss {ref['loss']:.4f}",
        f"{ref['total'] / ours['total']:.1f}x", "< 10 s, kernel error within tol")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wheel-data", type=Path, required=True, help="the rover-wheel data folder")
    ap.add_argument("--before-tree", default=None,
                    help="a checkout of the commit before e2da7f5 to time as the reference (default: emulated)")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--emulate-before", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    torch.set_default_dtype(torch.float64)
    if a.json:
        with engine_before() if a.emulate_before else contextlib.nullcontext():
            print(json.dumps(one_fold(a.wheel_data)))
        return
    wheel_fold_case(a.wheel_data, lambda *cells: print("  ".join(cells), flush=True), a.before_tree)


if __name__ == "__main__":
    main()
