"""What steers an ``InverseRFT`` fit beyond Adam's step: the backend following the hyperparameters
(``method="auto"`` moving to a cheaper space, the spectral basis growing, and held when nearly
noise-free data would make each step many times dearer) and the best iterate kept when the loss
diverges. A mixin of ``InverseRFT``; ``fit`` itself is in ``gp.model``."""

from __future__ import annotations

import math
import sys
import warnings
from typing import TYPE_CHECKING, cast

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .backends import RFTBackend, make_backend
from .backends.select import cheaper_space, estimate_pairs, estimated_costs, pairs_may_move, spectral_step_cost
from .kernels.fourier import FourierBasis

if TYPE_CHECKING:
    from ..rft.contacts import Contacts
    from .backends.spectral import SpectralBackend
    from .backends.weight_space import FeatureStatistics
    from .kernels.hyperparameters import RFTHyperparameters
    from .surface.offset import SurfaceOffset

__all__ = ["FitControlMixin", "FitDivergedWarning", "FitInterruptedWarning", "NOISE_FREE", "HOLD_FACTOR", "adam",
           "converged", "copy_into", "divergence", "progress_bar", "CONVERGED_NATS"]

NOISE_FREE = 1e-6  # noise variance / force power below which data are nearly noise-free (std < 0.1 % of rms)
HOLD_FACTOR = 4.0  # with nearly noise-free data, "auto" holds a step within this factor of the step then


CONVERGED_NATS = 2.0  # a fit followed by the Laplace polish stops when 25 Adam steps gain less log posterior than this
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
    (``gp.hyper.posterior._polish``) gets there in a few iterations where Adam would take hundreds."""
    if len(history) < 2 * window or len(history) % window:
        return False
    before, last = min(history[-2 * window:-window]), min(history[-window:])
    return n_samples * (before - last) < CONVERGED_NATS


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


class FitControlMixin:
    """The fit's adaptation and guards (see the module); needs an ``InverseRFT``'s hypers, backend, data."""

    _held_cost: float | None  # the step cost "auto" holds with nearly noise-free data (_adapt)
    _hold_said: bool  # the hold's warning was given
    _leave_pairs: tuple  # (the training contacts, whether "auto" could ever leave the pairs space) (_may_leave_pairs)
    _n_pairs: int | None  # the training contacts' distinct angle pairs (_pair_count)

    if TYPE_CHECKING:  # what the front door provides (gp.model)
        hypers: RFTHyperparameters
        backend: RFTBackend
        surface: SurfaceOffset | None
        _statistics: FeatureStatistics | None
        auto: bool
        solver: str
        tol: float

        @property
        def method(self) -> str: ...
        @property
        def train_contacts(self) -> Contacts: ...
        @property
        def train_forces(self) -> Tensor: ...
        def truncation_error(self) -> Tensor: ...
        def _rebuild_backend(self) -> None: ...

    def _snapshot(self) -> dict:
        """The fitted parameters' values (hyperparameters, the surface offset): a copy."""
        out = {k: v.detach().clone() for k, v in self.hypers.state_dict().items()}
        if self.surface is not None:
            out["surface.offset"] = self.surface.offset.detach().clone()
        return out

    def _kept_state(self, best: tuple[float, int], named: list, kept: list) -> tuple:
        """(loss, step) of a fit loop that copied the best iterate's parameter values into ``kept`` (in the order
        of ``named``: (name, parameter)) -> (loss, state, step) with the state in ``_snapshot``'s form (the
        hyperparameters' full state dict, their parameters at the best iterate; None before any step)."""
        value, step = best
        if step < 0:
            return value, None, step
        full = {k: v.detach().clone() for k, v in self.hypers.state_dict().items()}
        full.update((name, v) for (name, _), v in zip(named, kept))
        return value, full, step

    def _keep_best(self, best: tuple, history: list[float], lr: float, quiet: bool = False) -> None:
        """Restore the best iterate (loss, state, step) where the loss ended above it and warn where it diverged
        (``divergence``)."""
        value, state, step = best
        restore, message = divergence(value, step if state is not None else -1, history, lr)
        if not restore:
            return
        with torch.no_grad():
            self.hypers.load_state_dict({k: v for k, v in state.items() if k != "surface.offset"})
            if "surface.offset" in state:
                self.surface.offset.copy_(state["surface.offset"])
        if self.surface is not None:
            self._rebuild_backend()
        if message is not None and not quiet:
            warnings.warn(message, FitDivergedWarning, stacklevel=3)

    def _adapt(self) -> None:
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
        bound = self._step_bound()
        if self.auto and (self.method != "pairs" or self._may_leave_pairs()):
            costs = estimated_costs(self.train_contacts, self.hypers, self.tol, self._pair_count())
            best = cheaper_space(costs, self.method)
            if best is not None and (bound is None or costs[best] <= bound):
                self.backend = make_backend(best, self.hypers, self.train_contacts, self.train_forces,
                                            solver=self.solver, tol=self.tol, statistics=self._statistics)
                self.backend.in_fit = True
                return
        if bound is not None and self.method == "spectral":
            need = FourierBasis.for_lengthscale(self.hypers.lengthscale, self.tol)
            basis = cast("SpectralBackend", self.backend).basis
            grown = FourierBasis(max(need.n_beta, basis.n_beta), max(need.n_gamma, basis.n_gamma))
            cost = spectral_step_cost(self.train_contacts, grown)
            if cost > bound:
                cast("SpectralBackend", self.backend).held = True  # predictions after the fit keep it too
                if not self._hold_said:
                    self._hold_said = True
                    noise = [f"{v:.2g}" for v in self.hypers.noise.detach().tolist()]
                    warnings.warn(
                        f"the force noise fell to {noise} N^2, below {NOISE_FREE:g} of the force power (nearly "
                        "noise-free data), and the lengthscales shrink to fit what is left: engine 'auto' holds the "
                        f"spectral basis at {basis.size} features (kernel truncation error now "
                        f"{self.truncation_error().max().item():.1e}; {grown.size} features would cost "
                        f"{cost / self._held_cost:.0f}x a step). method='spectral' grows it anyway", stacklevel=3)
                return
        self.backend.refresh()

    def _step_bound(self) -> float | None:
        """With "auto" and nearly noise-free data (see ``_adapt``), the most a step may cost (in
        ``estimated_costs``' units): ``HOLD_FACTOR`` x the step when the noise first fell that low; else None."""
        if not self.auto or self.surface is not None:
            return None
        power = self.train_forces.pow(2).mean(0)
        if not bool((self.hypers.noise.detach() < NOISE_FREE * power).any()):
            self._held_cost = None
            if getattr(self.backend, "held", False):
                cast("SpectralBackend", self.backend).held = False  # the noise came back: the basis may grow again
            return None
        if self._held_cost is None:
            if self.method == "spectral":
                self._held_cost = spectral_step_cost(self.train_contacts, cast("SpectralBackend", self.backend).basis)
            else:
                self._held_cost = estimated_costs(self.train_contacts, self.hypers, self.tol,
                                                  self._pair_count())[self.method]
        return HOLD_FACTOR * self._held_cost

    def _may_leave_pairs(self) -> bool:
        """``select.pairs_may_move`` for the training contacts, kept while they are the same object (``add_data``
        joins new ones)."""
        c = self.train_contacts
        hit = getattr(self, "_leave_pairs", None)
        if hit is None or hit[0] is not c:
            hit = self._leave_pairs = (c, pairs_may_move(c, self.tol, self._pair_count()))
        return hit[1]

    def _pair_count(self) -> int:
        """The training contacts' number of distinct angle pairs (``select.estimate_pairs``), kept until
        ``add_data`` changes the data."""
        if getattr(self, "_n_pairs", None) is None:
            self._n_pairs = estimate_pairs(self.train_contacts)
        return self._n_pairs
