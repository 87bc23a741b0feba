"""What steers an ``InverseRFT`` fit beyond Adam's step: the backend following the hyperparameters
(``method="auto"`` moving to a cheaper space, the spectral basis growing, and held when nearly
noise-free data would make each step many times dearer) and the best iterate kept when the loss
diverges: ``FitControl``, an object each ``InverseRFT`` and ``InverseRFT3D`` holds (``model.fit_control``), whose
``run`` is the fit's Adam loop."""

from __future__ import annotations

import math
import sys
import warnings
from typing import TYPE_CHECKING, cast

import torch
from linear_operator.utils.errors import NotPSDError
from torch import Tensor
from tqdm.auto import tqdm

from .backends import make_backend
from .backends.select import cheaper_space, estimate_pairs, estimated_costs, pairs_may_move, spectral_step_cost
from .kernels.fourier import FourierBasis
from .surface.offset import surface_loss

if TYPE_CHECKING:
    from .backends.spectral import SpectralBackend

__all__ = ["FitControl", "FitDivergedWarning", "FitInterruptedWarning", "NOISE_FREE", "HOLD_FACTOR", "adam",
           "converged", "copy_into", "divergence", "progress_bar", "CONVERGED_NATS", "lbfgs_polish", "POLISH_EVALS",
           "POLISH_NATS"]

NOISE_FREE = 1e-6  # noise variance / force power below which data are nearly noise-free (std < 0.1 % of rms)
HOLD_FACTOR = 4.0  # with nearly noise-free data, "auto" holds a step within this factor of the step then


# a fit followed by a polish (Laplace's; a 3-D fit's L-BFGS) stops when 25 Adam steps gain less log posterior than this
CONVERGED_NATS = 2.0
PIPED_INTERVAL = 15.0  # s between progress lines where stderr is a pipe or a file (a live bar on a terminal)


def progress_bar(total: int, desc: str, enabled: bool = True) -> tqdm:
    """tqdm's bar over ``range(total)`` for a fit: the live bar in a terminal or notebook (``tqdm.auto``); where
    stderr is a pipe or a log file, a line at the start, every ``PIPED_INTERVAL`` seconds and at the end instead
    of one per refresh."""
    from tqdm.notebook import tqdm as notebook_bar

    piped = not issubclass(tqdm, notebook_bar) and not (hasattr(sys.stderr, "isatty") and sys.stderr.isatty())
    return tqdm(range(total), desc=desc, disable=not enabled, leave=False,
                **({"mininterval": PIPED_INTERVAL, "maxinterval": PIPED_INTERVAL} if piped else {}))


def converged(history: list[float], n_samples: int, window: int = 25) -> bool:
    """Whether the last ``window`` steps of a fit (losses per sample) raised the log posterior by less than
    ``CONVERGED_NATS`` over the best of the ``window`` before them: Adam is then near the mode, and L-BFGS
    (``gp.hyper.posterior._polish``, ``lbfgs_polish``) gets there in a few iterations where Adam would take
    hundreds."""
    if len(history) < 2 * window or len(history) % window:
        return False
    before, last = min(history[-2 * window:-window]), min(history[-window:])
    return n_samples * (before - last) < CONVERGED_NATS


POLISH_EVALS = 100  # loss evaluations L-BFGS may take per round of ``lbfgs_polish``
POLISH_NATS = 0.01  # ``lbfgs_polish`` stops where a step changes the log posterior by less than this


def lbfgs_polish(params: list[Tensor], loss_fn, n_samples: int, refresh=None, max_evals: int = POLISH_EVALS,
                 rounds: int = 5) -> tuple[float, int]:
    """From Adam's converged iterate to the mode of ``loss_fn`` (a per-sample loss of ``params`` over
    ``n_samples``): torch's L-BFGS with a strong Wolfe line search, stopped where a step changes the log posterior
    by less than ``POLISH_NATS`` or its gradient is below 1e-3 nats per unit (or after ``max_evals``
    evaluations); then ``refresh()`` (the backend following the new values, True where that changed the
    objective, e.g. a grown basis) and on with the same curvature history while it does, at most ``rounds``
    rounds. A probe that fails (a Cholesky, NaN), a round that ends higher, or Ctrl-C in a round (then re-raised)
    restores the values before that round. Returns (the loss at the values it ends at, the evaluations taken);
    where the start itself has no finite loss, (that value, 0) with nothing changed. A loss that is not finite is
    the caller's to act on (``InverseRFT3D.fit`` goes back to Adam's best iterate)."""
    evals, n = 0, max(int(n_samples), 1)
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=int(max_evals), max_eval=int(max_evals),
                            tolerance_grad=1e-3 / n, tolerance_change=POLISH_NATS / n, history_size=20,
                            line_search_fn="strong_wolfe")

    def closure():
        nonlocal evals
        evals += 1
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        if not torch.isfinite(loss):
            raise FloatingPointError("the loss is not finite")
        loss.backward()
        return loss

    def value_now() -> float:
        try:
            with torch.no_grad():
                return float(loss_fn())
        except (torch.linalg.LinAlgError, NotPSDError):
            return math.nan

    value = value_now()
    if not math.isfinite(value):
        return value, 0
    for _ in range(rounds):
        start = [p.detach().clone() for p in params]
        try:
            opt.step(closure)
            new = value_now()
        except (torch.linalg.LinAlgError, NotPSDError, FloatingPointError):
            new = math.inf
        except KeyboardInterrupt:  # Ctrl-C in a line search: the round's start, not a probe's values
            copy_into(params, start)
            raise
        if not new <= value:  # a failed probe, or higher (NaN included): this round's start
            copy_into(params, start)
            break
        value = new
        if refresh is None or not refresh():
            break
        value = value_now()
    return value, evals


def adam(params: list[Tensor], lr: float) -> torch.optim.Adam:
    """torch's Adam for a fit's few small hyperparameter tensors: the fused kernel where the device has one (one
    call per step instead of a dozen per tensor: 0.19 against 0.50 ms per step for an ``InverseRFT``'s five
    tensors on this project's CPU; the same steps to about 1 ulp), else the default implementation."""
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, ValueError):
        return torch.optim.Adam(params, lr=lr)


def copy_into(kept: list[Tensor], params: list[Tensor]) -> None:
    """The fit loop's best iterate: the parameters' values copied into ``kept`` in place (no allocation per step)."""
    with torch.no_grad():
        for k, p in zip(kept, params):
            k.copy_(p)


def divergence(best: float, step: int, history: list[float], lr: float) -> tuple[bool, str | None]:
    """A fit that ended above its best iterate (loss ``best`` at ``step``, 0-based): (restore the best iterate?,
    the ``FitDivergedWarning`` message or None). Restore where the last loss is above the best by more than 1e-3
    of it, or NaN / inf; warn where it rose by more than 0.1 (or 10 %): the lr was too large. The planar and the
    3-D fit share it."""
    if step < 0 or not history:
        return False, None
    last = history[-1]
    if math.isfinite(last) and last <= best + 1e-3 * max(1.0, abs(best)):
        return False, None
    if math.isfinite(last) and last - best <= max(0.1, 0.1 * abs(best)):
        return True, None
    return True, (f"the fit diverged: the loss rose from {best:.4g} (step {step + 1}) to {last:.4g} (step "
                  f"{len(history)}); the model keeps step {step + 1}'s hyperparameters. lr = {lr:g} is too large "
                  f"for these data: try lr = {lr / 10:g}")


class FitDivergedWarning(UserWarning):
    """``InverseRFT.fit``'s loss rose well above its best (or turned NaN): the best iterate was kept."""


class FitInterruptedWarning(UserWarning):
    """``InverseRFT.fit`` was stopped by Ctrl-C; the model keeps the steps taken."""


class FitControl:
    """The fit's adaptation and guards for one model (see the module): an object ``InverseRFT`` (and
    ``InverseRFT3D``) holds as ``fit_control``, each call given the model. Its own state: the step cost held with
    nearly noise-free data and whether that was said, the training contacts' distinct angle pairs (kept until
    ``forget_data``), and what the last ``run`` ended with (``converged_stop``, ``diverged``, ``best_state``: what
    a polish after it needs)."""

    def __init__(self) -> None:
        self.converged_stop = False  # the last ``run`` stopped on convergence (a polish may follow)
        self.diverged = False  # the last ``run`` ended with a FitDivergedWarning
        self.best_state: tuple | None = None  # the last ``run``'s best iterate, ``kept_state``'s (loss, state, step)
        self.held_cost: float | None = None  # the step cost "auto" holds with nearly noise-free data (adapt)
        self.hold_said = False  # the hold's warning was given
        self._n_pairs: int | None = None  # the training contacts' distinct angle pairs (pair_count)
        self._leave_pairs: tuple | None = None  # (the training contacts, whether "auto" could leave the pairs space)

    def forget_data(self) -> None:
        """The training data changed (``add_data``, a moved surface): the pair count is counted again."""
        self._n_pairs = None

    def run(self, model, n_iter: int, lr: float, progress: bool, stop_at_convergence: bool | None = None
            ) -> list[float]:
        """``InverseRFT.fit``'s Adam loop (its docstring; ``InverseRFT3D.fit``'s too): the losses per step; the model
        left at the best iterate, its backend adapted. ``stop_at_convergence``: stop once 25 steps gain less than
        ``CONVERGED_NATS`` (a polish follows; default: with the Laplace posterior and no learned surface)."""
        self.converged_stop = self.diverged = False
        model.train()
        surface = [] if model.surface is None else [("surface.offset", model.surface.offset)]
        named = [*model.hypers.named_parameters(), *surface]
        params = [p for _, p in named]
        opt, history, kept = adam(params, lr), [], [p.detach().clone() for p in params]  # kept: the best iterate
        best: tuple[float, int] = (math.inf, -1)  # loss, step of the values in ``kept``
        bar = progress_bar(int(n_iter), f"{type(model).__name__} fit ({model.method})", progress)
        polish_follows = (model.hyper_method == "laplace" and model.surface is None) if stop_at_convergence is None \
            else stop_at_convergence
        step = 0
        model.backend.in_fit = True
        try:
            for step in bar:
                opt.zero_grad(set_to_none=True)
                # closed form where the backend has one (``backends.closed_form``), else autograd
                value = model.backend.loss_and_grad() if model.surface is None else None
                loss = None
                if value is None:
                    loss = model.backend.loss() if model.surface is None else surface_loss(model)
                    value = loss.item()
                if not math.isfinite(value):
                    history.append(value)
                    break  # NaN or inf: no step from here leads anywhere; the best iterate is restored below
                if value < best[0]:
                    copy_into(kept, params)
                    best = (value, step)
                if loss is not None:
                    loss.backward()
                opt.step()
                history.append(value)
                if model.surface is None and step % 10 == 9:
                    if model.backend.stale() or (model.auto and step % 30 == 29):
                        self.adapt(model)  # with "auto", every 30 steps: a cheaper space may have opened up
                    else:
                        model.backend.shrink()  # lengthscales grown back: a smaller spectral basis holds them
                if progress:
                    bar.set_postfix(loss=f"{history[-1]:.4g}", refresh=False)
                if polish_follows and converged(history, model.backend.n_samples):
                    self.converged_stop = True
                    break  # the polish (Laplace's, L-BFGS) goes to the mode from here
        except KeyboardInterrupt:
            warnings.warn(f"fit interrupted after {len(history)} steps; the model keeps those steps",
                          FitInterruptedWarning, stacklevel=3)
        except (NotPSDError, torch.linalg.LinAlgError) as e:
            self.best_state = self.kept_state(model, best, named, kept)
            self.keep_best(model, self.best_state, history, lr, quiet=True)
            if model.surface is None:
                model.backend.refresh()  # the restored hyperparameters' basis
            raise NotPSDError(
                f"the force covariance W K W^T + noise is not positive definite (step {step}); hyperparameters "
                f"then: {model.hyperparameters()}. Try a lower lr, a larger noise floor, or float64 (the model holds "
                f"the best step's hyperparameters)."
            ) from e
        finally:
            model.backend.in_fit = False
            if model.surface is not None:
                model._rebuild_backend()
            bar.close()
            model.eval()
        self.best_state = self.kept_state(model, best, named, kept)
        self.diverged = self.keep_best(model, self.best_state, history, lr)
        if model.surface is None and model.backend.stale():
            self.adapt(model)
        return history

    @staticmethod
    def snapshot(model) -> dict:
        """The fitted parameters' values (hyperparameters, the surface offset): a copy."""
        out = {k: v.detach().clone() for k, v in model.hypers.state_dict().items()}
        if model.surface is not None:
            out["surface.offset"] = model.surface.offset.detach().clone()
        return out

    @staticmethod
    def kept_state(model, best: tuple[float, int], named: list, kept: list) -> tuple:
        """(loss, step) of a fit loop that copied the best iterate's parameter values into ``kept`` (in the order
        of ``named``: (name, parameter)) -> (loss, state, step) with the state in ``snapshot``'s form (the
        hyperparameters' full state dict, their parameters at the best iterate; None before any step)."""
        value, step = best
        if step < 0:
            return value, None, step
        full = {k: v.detach().clone() for k, v in model.hypers.state_dict().items()}
        full.update((name, v) for (name, _), v in zip(named, kept))
        return value, full, step

    @staticmethod
    def keep_best(model, best: tuple, history: list[float], lr: float, quiet: bool = False, stacklevel: int = 4
                  ) -> bool:
        """Restore the best iterate (loss, state, step) where the loss ended above it and warn where it diverged
        (``divergence``; ``stacklevel``: the warning's, at the user's call by default from ``run``). Returns whether
        it diverged."""
        value, state, step = best
        restore, message = divergence(value, step if state is not None else -1, history, lr)
        if not restore:
            return False
        with torch.no_grad():
            model.hypers.load_state_dict({k: v for k, v in state.items() if k != "surface.offset"})
            if "surface.offset" in state:
                model.surface.offset.copy_(state["surface.offset"])
        if model.surface is not None:
            model._rebuild_backend()
        if message is not None and not quiet:
            warnings.warn(message, FitDivergedWarning, stacklevel=stacklevel)
        return message is not None

    def adapt(self, model) -> None:
        """The hyperparameters moved so that the backend must adapt (the spectral basis must grow), or
        (``method="auto"``, every 30 steps) may have made another space cheaper: with "auto", first ask
        whether another backend is now cheaper (by more than 2x) and move there instead (the
        hyperparameters are shared, nothing is lost; a lengthscale that dips below what the spectral
        basis can hold and recovers brings the fit back to spectral); else refresh.

        Nearly noise-free data (an axis's noise below ``NOISE_FREE`` of its force power) let the noise
        collapse and the lengthscales shrink to fit what little is left (a simulated leg: at ~step 270
        the basis grows 4x and "auto" moved to the observations space at T = 4344, each step 30x the
        one before). From there "auto" holds the step cost within ``HOLD_FACTOR`` of the step then: no
        move to a costlier space, the spectral basis grown only that far and then held (``held``: the
        predictions after the fit keep it; its truncation error is reported and said once in a
        warning)."""
        bound = self.step_bound(model)
        if model.auto and (model.method != "pairs" or self.may_leave_pairs(model)):
            costs = estimated_costs(model.train_contacts, model.hypers, model.tol, self.pair_count(model))
            best = cheaper_space(costs, model.method)
            if best is not None and (bound is None or costs[best] <= bound):
                model.backend = make_backend(best, model.hypers, model.train_contacts, model.train_forces,
                                             solver=model.solver, tol=model.tol, statistics=model._statistics)
                model.backend.in_fit = True
                return
        if bound is not None and model.method == "spectral":
            need = FourierBasis.for_lengthscale(model.hypers.lengthscale, model.tol)
            basis = cast("SpectralBackend", model.backend).basis
            grown = FourierBasis(max(need.n_beta, basis.n_beta), max(need.n_gamma, basis.n_gamma))
            cost = spectral_step_cost(model.train_contacts, grown)
            if cost > bound:
                cast("SpectralBackend", model.backend).held = True  # predictions after the fit keep it too
                if not self.hold_said:
                    self.hold_said = True
                    noise = [f"{v:.2g}" for v in model.hypers.noise.detach().tolist()]
                    warnings.warn(
                        f"the force noise fell to {noise} N^2, below {NOISE_FREE:g} of the force power (nearly "
                        "noise-free data), and the lengthscales shrink to fit what is left: engine 'auto' holds the "
                        f"spectral basis at {basis.size} features (kernel truncation error now "
                        f"{model.truncation_error().max().item():.1e}; {grown.size} features would cost "
                        f"{cost / self.held_cost:.0f}x a step). method='spectral' grows it anyway", stacklevel=4)
                return
        model.backend.refresh()

    def step_bound(self, model) -> float | None:
        """With "auto" and nearly noise-free data (see ``adapt``), the most a step may cost (in
        ``estimated_costs``' units): ``HOLD_FACTOR`` x the step when the noise first fell that low; else None."""
        if not model.auto or model.surface is not None:
            return None
        power = model.train_forces.pow(2).mean(0)
        if not bool((model.hypers.noise.detach() < NOISE_FREE * power).any()):
            self.held_cost = None
            if getattr(model.backend, "held", False):
                cast("SpectralBackend", model.backend).held = False  # the noise came back: the basis may grow again
            return None
        if self.held_cost is None:
            if model.method == "spectral":
                self.held_cost = spectral_step_cost(model.train_contacts,
                                                    cast("SpectralBackend", model.backend).basis)
            else:
                self.held_cost = estimated_costs(model.train_contacts, model.hypers, model.tol,
                                                 self.pair_count(model))[model.method]
        return HOLD_FACTOR * self.held_cost

    def may_leave_pairs(self, model) -> bool:
        """``select.pairs_may_move`` for the training contacts, kept while they are the same object (``add_data``
        joins new ones)."""
        c = model.train_contacts
        hit = self._leave_pairs
        if hit is None or hit[0] is not c:
            hit = self._leave_pairs = (c, pairs_may_move(c, model.tol, self.pair_count(model)))
        return hit[1]

    def pair_count(self, model) -> int:
        """The training contacts' number of distinct angle pairs (``select.estimate_pairs``), kept until
        ``forget_data``."""
        if self._n_pairs is None:
            self._n_pairs = estimate_pairs(model.train_contacts)
        return self._n_pairs
