r"""NUTS (pyro) on the hyperparameters' log posterior, the reference for the Laplace mixture.

The target is ``hyper_posterior.log_posterior`` (the exact marginal likelihood times n, the Jacobian of
log coordinates and the priors) over theta = log(value) of the free hyperparameters; its gradient is the
closed form where the backend has one (``gp.hyper.density``).

**The metric.** NUTS is correct with any positive-definite metric (the inverse mass matrix), but how many
leapfrog steps a draw takes depends on it. By default (``metric="laplace"``) each chain starts at the
posterior's mode (``hyper_posterior._polish``: L-BFGS then Newton, as ``laplace`` does) with the Laplace
covariance H^-1 there as a dense metric (``laplace_guard.proposal_covariance``: eigenvalues floored, no
direction wider than 5 in log), and only the step size is adapted in warm-up. ``metric="diagonal"`` is
pyro's default: an identity start, the diagonal adapted in warm-up windows. On C-toe gait 2 (11
hyperparameters, 500 + 500 per chain): 7.3 gradient evaluations per draw against 14.8, minimum effective
sample size 211 against 235 of 500, median 710 against 342 (``docs/calibration.md``).

**Chains in parallel.** With ``num_chains`` > 1 the chains can run in worker processes (a forkserver,
``processes`` of them, one thread each where that divides the cores): by default in a notebook or a
shell on the CPU; a script asks with ``processes=`` (and keeps its work under ``if __name__ ==
"__main__":``, as every start method but fork needs). Chain c is seeded with ``seed + c`` wherever it runs.
A backend that cannot be pickled, or workers that cannot start, run the chains in this process.
"""

from __future__ import annotations

import math
import os
import pickle
import sys
import warnings

import torch
from torch import Tensor

from . import guard
from .posterior import HyperPosterior, _free_mask, _polish, _SubSpec, hyper_spec, log_posterior

__all__ = ["nuts", "METRICS"]

METRICS = ("laplace", "diagonal")


def _kernel(potential, inverse_mass: Tensor | None, adapt_mass: bool):
    """A pyro NUTS kernel whose metric starts at ``inverse_mass`` (dense) if given."""
    from pyro.infer.mcmc import NUTS

    if inverse_mass is None:
        return NUTS(potential_fn=potential, adapt_step_size=True, adapt_mass_matrix=True, full_mass=False)

    class _FromLaplace(NUTS):
        metric_set = False  # whether pyro took the metric (its adapter is pyro's internals, 1.9)

        def _initialize_adapter(self):  # pyro sets an identity metric here: replace it, then find a step size
            super()._initialize_adapter()
            adapter = getattr(self._adapter, "mass_matrix_adapter", None)
            before = getattr(adapter, "inverse_mass_matrix", None)
            try:
                (sites,) = before.keys()
                adapter.inverse_mass_matrix = {sites: inverse_mass}
                self._adapter.reset_step_size_adaptation(self._initial_params)
                self.metric_set = True
            except (AttributeError, ValueError, RuntimeError):  # another pyro: its own metric (``_chain`` says so)
                if before is not None:
                    adapter.inverse_mass_matrix = before
                    self._adapter.reset_step_size_adaptation(self._initial_params)

    return _FromLaplace(potential_fn=potential, adapt_step_size=True, adapt_mass_matrix=adapt_mass, full_mass=True)


def _chain(backend, idx: Tensor, base: Tensor, start: Tensor, inverse_mass: Tensor | None, adapt_mass: bool,
           seed: int, n_samples: int, warmup: int, progress: bool,
           threads: int | None = None) -> tuple[Tensor, int, bool]:
    """One chain: its draws (n_samples, P_free), the number of gradient evaluations it took and whether it
    ran with the Laplace metric."""
    from pyro.infer.mcmc import MCMC

    if threads is not None:
        torch.set_num_threads(threads)
    sub = _SubSpec(hyper_spec(backend.hypers), base, idx)
    calls = [0]

    def potential(params):
        calls[0] += 1
        lp = log_posterior(backend, sub, params["theta"])
        return -lp if torch.isfinite(lp) else params["theta"].sum() * 0 + 1e30

    torch.manual_seed(seed)
    kernel = _kernel(potential, inverse_mass, adapt_mass)
    mcmc = MCMC(kernel, num_samples=int(n_samples), warmup_steps=int(warmup),
                initial_params={"theta": start.detach().clone()}, disable_progbar=not progress)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pyro's and the extreme draws' numerical warnings
        mcmc.run()
    taken = bool(getattr(kernel, "metric_set", False))
    if inverse_mass is not None and not taken:
        warnings.warn("NUTS: this pyro did not take the Laplace metric (its adapter's internals differ from pyro "
                      "1.9's); the chain ran with pyro's identity metric", RuntimeWarning,
                      stacklevel=2)
    return mcmc.get_samples()["theta"].detach().reshape(-1, len(idx)), calls[0], taken


def _chain_from_bytes(payload: bytes, *args) -> tuple[Tensor, int, bool]:
    return _chain(pickle.loads(payload), *args)


def _processes(processes: int | None, num_chains: int, device: torch.device) -> int:
    """How many worker processes run the chains: ``processes`` if given, else one per core (at most
    ``num_chains``) where that is safe without the caller's help (an interactive session: a notebook or a
    shell, whose workers need not import a script), else 1."""
    if processes is not None:
        if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
            raise ValueError(f"processes must be None or a positive integer, got {processes!r}")
        return min(processes, num_chains)
    interactive = getattr(sys.modules.get("__main__"), "__file__", None) is None
    if device.type != "cpu" or not interactive:
        return 1
    return max(1, min(num_chains, os.cpu_count() or 1, 8))


def _run_chains(backend, args: list[tuple], processes: int) -> list[tuple[Tensor, int, bool]]:
    """Each chain's (draws, gradient evaluations, Laplace metric taken), in worker processes where ``processes`` > 1."""
    if processes > 1:
        try:
            payload = pickle.dumps(backend)
        except Exception:  # noqa: BLE001 - any reason it cannot travel: run here instead
            payload = None
        if payload is not None:
            from concurrent.futures import ProcessPoolExecutor
            from concurrent.futures.process import BrokenProcessPool
            from multiprocessing import get_all_start_methods, get_context
            from multiprocessing.context import BaseContext

            if "forkserver" in get_all_start_methods():
                server = get_context("forkserver")
                server.set_forkserver_preload(["irft_torch", "pyro"])
                ctx: BaseContext = server
            else:
                ctx = get_context("spawn")
            threads = max(1, (os.cpu_count() or 1) // processes)
            try:
                with ProcessPoolExecutor(max_workers=processes, mp_context=ctx) as pool:
                    futures = [pool.submit(_chain_from_bytes, payload, *a, threads) for a in args]
                    return [f.result() for f in futures]
            except BrokenProcessPool:  # a worker could not start (a script without a main guard): run here
                warnings.warn("NUTS: the chains' worker processes could not start (a script that starts processes "
                              "needs `if __name__ == \"__main__\":` around its work); running the chains in this "
                              "process, one after the other", RuntimeWarning, stacklevel=3)
    return [_chain(backend, *a) for a in args]


def nuts(backend, n_samples: int = 256, warmup: int = 512, n_draws: int = 16, num_chains: int = 1, free=None,
         seed: int = 0, progress: bool = False, metric: str = "laplace", adapt_mass: bool = False,
         processes: int | None = None) -> HyperPosterior:
    """NUTS (pyro) on -log p(theta | F): ``n_samples`` after ``warmup`` per chain, all draws thinned evenly
    to ``n_draws`` equal-weight draws (botorch's ``fit_fully_bayesian_model_nuts`` defaults: 512 warm-up,
    256 draws, 16 kept). Needs pyro-ppl (``pip install pyro-ppl``, or the ``bayes`` extra).

    Args:
        free: the hyperparameters sampled (labels or a bool mask (P,)); the rest held at their fitted values.
        metric: ``"laplace"`` (default): chains start at the polished mode with the Laplace covariance as a
            dense metric (the module docstring); ``"diagonal"``: start at the fitted hyperparameters, pyro's
            identity metric with its diagonal adapted.
        adapt_mass: with ``metric="laplace"``, adapt the dense metric in warm-up too (pyro's windows).
        processes: worker processes for the chains (1: one after the other in this process). Default: one per
            core, at most ``num_chains``, in a notebook or shell on the CPU; 1 in a script, whose workers would
            import it again: a script passes ``processes`` itself, with its work under
            ``if __name__ == "__main__":``.

    Returns:
        a ``HyperPosterior`` ("nuts"): ``mode`` the fitted hyperparameters, ``covariance`` the draws',
        ``ess`` the smallest effective sample size over the free coordinates, ``extra``: ``all_draws``
        (C * n_samples, P_free), ``gradient_evaluations`` per chain, ``start`` (P,), ``metric``.
    """
    try:
        from pyro.ops.stats import effective_sample_size
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("hyper_posterior='nuts' needs pyro: pip install pyro-ppl (or irft-torch[bayes])") from e
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    for name, v in (("n_samples", n_samples), ("num_chains", num_chains), ("n_draws", n_draws)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name} must be a positive integer, got {v!r}")
    spec = hyper_spec(backend.hypers)
    theta0 = spec.theta(backend.hypers)
    mask = _free_mask(spec, free)
    idx = mask.nonzero()[:, 0].to(theta0.device)
    sub = _SubSpec(spec, theta0, idx)
    start, inverse_mass = theta0[idx].detach().clone(), None
    if metric == "laplace":
        try:
            mode, H, lp = _polish(backend, sub, start, 100)
            if torch.isfinite(lp) and bool(torch.isfinite(H).all()):
                start, inverse_mass = mode.detach().clone(), guard.proposal_covariance(H).to(theta0)
        except (torch.linalg.LinAlgError, RuntimeError, ValueError):  # no usable mode: pyro's own start
            pass
        finally:
            spec.load(backend.hypers, theta0)
    args = [(idx, theta0.detach(), start, inverse_mass, adapt_mass or inverse_mass is None, seed + c, n_samples,
             warmup, progress) for c in range(num_chains)]
    results = _run_chains(backend, args, _processes(processes, num_chains, theta0.device))
    spec.load(backend.hypers, theta0)
    by_chain = torch.stack([r[0].to(theta0) for r in results])  # (C, n, P_free)
    draws = by_chain.reshape(-1, len(idx))
    S = draws.shape[0]
    pick = torch.linspace(0, S - 1, min(int(n_draws), S)).round().long().to(draws.device)
    full = theta0.detach().expand(len(pick), -1).clone()
    full[:, idx] = draws[pick]
    w = torch.full((len(pick),), 1 / len(pick), dtype=full.dtype, device=full.device)
    c = draws - draws.mean(0)
    cov = theta0.new_zeros(spec.size, spec.size)
    cov[idx[:, None], idx[None, :]] = c.mT @ c / max(S - 1, 1)
    ess = float(effective_sample_size(by_chain, chain_dim=0, sample_dim=1).min())
    start_full = theta0.detach().clone()
    start_full[idx] = start
    return HyperPosterior("nuts", spec.labels, full, w, theta0.detach(), cov, ess if math.isfinite(ess) else 0.0,
                          float("nan"), S, {"all_draws": draws, "gradient_evaluations": [r[1] for r in results],
                                            "start": start_full,
                                            "metric": "laplace" if all(r[2] for r in results) else "diagonal"})
