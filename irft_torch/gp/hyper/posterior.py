r"""A posterior over the hyperparameters: Laplace with importance reweighting, or NUTS.

A point estimate (MAP or ML-II) of the lengthscales, outputscales and noise is one plausible
setting among many; where the forces say little about a lengthscale, predictions made at one value
extrapolate with a confidence nothing supports. Here every positive hyperparameter is written as
theta = log(value), and

    log p(theta | F) = log p(F | theta) + log p(theta) + const,

with log p(F | theta) = -T * (the backend's negative log likelihood per sample, summed over the two
axes): gpytorch's ``ExactMarginalLogLikelihood`` (and ``RFTBackend.loss``) divides by T, which is put
back. The physical priors (``gp.kernels.priors``) are normal densities of log(value / centre), i.e. densities
in theta already: no change-of-variables term is needed in these coordinates (a prior stated on the
value itself would add sum(theta)). Without priors (``MapPrior(hyperpriors=None)``) the prior is flat in theta.

- ``laplace``: the mode theta_hat (the fitted hyperparameters, polished by a few Newton steps on the
  exact Hessian), the Gaussian N(theta_hat, H^-1) with H the Hessian of -log p(theta | F) by autograd,
  then importance sampling: proposals from a multivariate Student-t (30 degrees of freedom) on that
  Gaussian, split along its axes where the log posterior falls more slowly on one side than the curvature says
  (Geweke's split-t, ``gp.hyper.importance.split_axes``), weights p(theta | F) / q(theta), self-normalised.
  Reported: the effective sample size (sum w)^2 / sum w^2 and Pareto k-hat of the largest weights (Vehtari et al.,
  PSIS: k-hat < 0.7 means the weights are reliable). A second stage of proposals, moved to the first stage's
  weighted draws, is always drawn, and more while the weights stay unreliable (up to four stages); all are weighed
  together. The draws kept for prediction are a small equally weighted point
  set with the weighted proposals' mean and covariance (``points="moments"``): it carries no resampling noise.
  Where the approximation does not hold (a hyperparameter at a wall, a flat direction, unreliable weights)
  ``gp.hyper.guard`` holds, caps or warns (``HyperPosteriorWarning``) instead of a silently wrong mixture.
- ``nuts`` (``gp.hyper.nuts``): pyro's NUTS on the same potential -log p(theta | F) (optional: ``pip install
  pyro-ppl``), started at the mode with the Laplace covariance as its metric, chains in worker processes;
  the reference and the fallback when the Laplace weights are unreliable.

Predictions are then the mixture over the draws (``gp.hyper.mixture``).
"""

from __future__ import annotations

import contextlib
import copy
import math
import warnings
from dataclasses import dataclass, field

import torch
from gpytorch.priors import Prior
from linear_operator.utils.errors import NotPSDError
from torch import Tensor

from . import guard
from .density import closed_form_log_posterior, log_posterior_and_grad_chunked, log_posterior_batch
from .importance import _always, _merge, _moment_points, _systematic, first_stage, importance_sample, split_axes
from .pareto import pareto_khat, psis_smooth

__all__ = ["HyperPosterior", "HyperSpec", "add_data_to_draws", "hyper_spec", "log_posterior", "laplace",
           "point_mass", "log_evidence", "HYPER_POSTERIORS"]

HYPER_POSTERIORS = ("map", "laplace", "nuts")
NEWTON_DONE = 1e-2  # Newton decrement g^T H^-1 g (nats x 2) below which the polish takes its last step
HESSIAN_STEP = 1e-4  # central-difference step of the Laplace Hessian, in log(value)
POLISH_CHANGE = 1e-9  # L-BFGS' tolerance_change: log p (nats) and step size; Newton's steps finish
DRAW_SEED = 0  # the Laplace proposals' seed where no generator is passed: a refit gives the same predictions


@dataclass
class HyperSpec:
    """Where each free hyperparameter lives: raw parameter names in ``RFTHyperparameters``, their
    shapes, constraints (value = constraint.transform(raw)) and readable labels per coordinate."""

    names: list[str]
    shapes: list[torch.Size]
    constraints: list
    labels: list[str]

    @property
    def size(self) -> int:
        return len(self.labels)

    def full(self, theta: Tensor) -> Tensor:
        """theta of every coordinate (*S, P) from this spec's own (*S, P_free) (the same here)."""
        return theta

    def free_part(self, g: Tensor) -> Tensor:
        """This spec's own coordinates (*S, P_free) of a gradient over every coordinate (*S, P)."""
        return g

    def theta(self, hypers) -> Tensor:
        """theta = log(value) (P,) of the hyperparameters' current values."""
        params = dict(hypers.named_parameters())
        return torch.cat([c.transform(params[n]).detach().reshape(-1).log()
                          for n, c in zip(self.names, self.constraints)])

    def raw(self, theta: Tensor) -> dict[str, Tensor]:
        """Raw parameters for theta (differentiable); NaN where a value is at or below its constraint's
        lower bound (an impossible setting)."""
        out, i = {}, 0
        for n, s, c in zip(self.names, self.shapes, self.constraints):
            k = s.numel()
            value = theta[i:i + k].exp().reshape(s)
            lower = c.lower_bound.to(value)
            raw = c.inverse_transform(torch.where(value > lower, value, torch.full_like(value, float("nan"))))
            out[n] = raw
            i += k
        return out

    def load(self, hypers, theta: Tensor) -> None:
        """Write theta into ``hypers`` (in place, no gradient)."""
        params = dict(hypers.named_parameters())
        with torch.no_grad():
            for n, raw in self.raw(theta.to(params[self.names[0]])).items():
                if not torch.isfinite(raw).all():
                    raise ValueError(f"hyperparameter {n} at or below its lower bound")
                params[n].copy_(raw)


def _label(name: str, shape: torch.Size) -> list[str]:
    base = {"kernel.base_kernel.raw_lengthscale": "lengthscale", "kernel.raw_outputscale": "outputscale",
            "likelihood.noise_covar.raw_noise": "noise", "mean.raw_scales": "mean_scale",
            "li.raw_variance": "li_variance", "li.raw_generic_variance": "generic_variance",
            "spatial.kernel.raw_outputscale": "spatial_variance",
            "spatial.kernel.base_kernel.raw_lengthscale": "spatial_lengthscale"}.get(name, name)
    n = shape.numel()
    if base == "lengthscale":
        dims = ("sin2b", "cos2b", "sing", "cosg")
        return [f"lengthscale_{'xz'[i // 4]}[{dims[i % 4]}]" for i in range(n)]
    if n == 2:
        return [f"{base}_x", f"{base}_z"]
    return [base] if n == 1 else [f"{base}[{i}]" for i in range(n)]


def hyper_spec(hypers) -> HyperSpec:
    """The free (``requires_grad``) hyperparameters of an ``RFTHyperparameters`` or any module whose
    ``hyper_labels(name, shape)`` names its coordinates (the 3-D one), each positive through its constraint."""
    names, shapes, cons, labels = [], [], [], list[str]()
    label_of = getattr(hypers, "hyper_labels", _label)
    for name, p, c in hypers.named_parameters_and_constraints():
        if not p.requires_grad:
            continue
        if c is None:
            raise ValueError(f"hyperparameter {name} has no constraint: its value is not known to be positive")
        names.append(name)
        shapes.append(p.shape)
        cons.append(c)
        labels += label_of(name, p.shape)
    return HyperSpec(names, shapes, cons, labels)


@contextlib.contextmanager
def _swapped(hypers, raw: dict[str, Tensor]):
    """The hyperparameter module's raw parameters replaced by the tensors ``raw`` (name -> tensor) for the
    duration, restored on exit whatever happens (what ``torch.func.functional_call`` does, done on the one
    shared module so that the model, its backend and gpytorch's parts all see the swap)."""
    saved = []
    try:
        for name, t in raw.items():
            owner, _, leaf = name.rpartition(".")
            module = hypers.get_submodule(owner) if owner else hypers
            saved.append((module, leaf, module._parameters[leaf]))
            module._parameters[leaf] = t
        yield
    finally:
        for module, leaf, p in reversed(saved):
            module._parameters[leaf] = p


def log_posterior(backend, spec: HyperSpec, theta: Tensor, exact_graph: bool = False) -> Tensor:
    """Unnormalised log p(theta | F) at theta (P,) (differentiable): -T x the backend's negative log
    likelihood per sample (both axes) plus the log prior; -inf where theta is impossible (a value below its
    bound, a covariance that is not positive definite). In closed form where the backend has one (``gp.hyper.density``:
    first derivatives only); ``exact_graph``: through autograd, differentiable twice (the Laplace Hessian)."""
    if not exact_graph:
        fast = closed_form_log_posterior(backend, spec, theta)
        if fast is not None:
            return fast
    raw = spec.raw(theta)
    if not all(torch.isfinite(r).all() for r in raw.values()):
        return theta.new_tensor(-math.inf)
    was = backend.training
    backend.train()
    try:
        with _swapped(backend.hypers, raw):
            return -(backend.negative_log_likelihood().sum() * backend.n_samples) + backend.log_prior()
    except (torch.linalg.LinAlgError, NotPSDError):  # not positive definite at an extreme draw
        return theta.new_tensor(-math.inf)
    finally:
        backend.train(was)


@dataclass
class HyperPosterior:
    """Draws of the hyperparameters and their weights.

    Attributes:
        method: "map" (a point mass), "laplace" or "nuts".
        labels: the P coordinates' names (``lengthscale_x[sin2b]``, ``outputscale_z``, ``noise_x``, ...).
        theta: (S, P) draws of log(value).
        weights: (S,) summing to 1.
        mode: (P,) theta at the mode (the fitted, polished hyperparameters).
        covariance: (P, P) Laplace covariance H^-1 (None for NUTS and a point mass).
        ess: effective sample size of the importance weights (Laplace) or the draws (NUTS).
        khat: Pareto k-hat of the importance weights (NaN where not computed).
        n_proposals: how many proposals were weighed.
    """

    method: str
    labels: list[str]
    theta: Tensor
    weights: Tensor
    mode: Tensor
    covariance: Tensor | None = None
    ess: float = float("nan")
    khat: float = float("nan")
    n_proposals: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def n_draws(self) -> int:
        return self.theta.shape[0]

    def values(self) -> dict[str, Tensor]:
        """Each hyperparameter's draws as values (S,) (exp of theta)."""
        return {lab: self.theta[:, i].exp() for i, lab in enumerate(self.labels)}

    def summary(self) -> str:
        """One line per hyperparameter: mode and 95 % interval of the weighted draws (values)."""
        lines = [f"hyperparameter posterior ({self.method}): {self.n_draws} draws, ESS {self.ess:.1f} of "
                 f"{self.n_proposals}, Pareto k-hat {self.khat:.2f}"]
        order = self.theta.argsort(0)
        for i, lab in enumerate(self.labels):
            v, w = self.theta[order[:, i], i], self.weights[order[:, i]]
            cw = w.cumsum(0)
            lo = v[int((cw < 0.025).sum().clamp_max(len(v) - 1))].exp().item()
            hi = v[int((cw < 0.975).sum().clamp_max(len(v) - 1))].exp().item()
            lines.append(f"  {lab:22s} mode {self.mode[i].exp().item():.4g}   95 % [{lo:.4g}, {hi:.4g}]")
        return "\n".join(lines)

    def state(self) -> dict:
        """Tensors and metadata for a model file."""
        return {"method": self.method, "labels": list(self.labels), "theta": self.theta.detach().cpu(),
                "weights": self.weights.detach().cpu(), "mode": self.mode.detach().cpu(),
                "covariance": None if self.covariance is None else self.covariance.detach().cpu(),
                "ess": self.ess, "khat": self.khat, "n_proposals": self.n_proposals}

    @classmethod
    def from_state(cls, d: dict) -> HyperPosterior:
        return cls(d["method"], list(d["labels"]), d["theta"], d["weights"], d["mode"], d.get("covariance"),
                   float(d["ess"]), float(d["khat"]), int(d["n_proposals"]))


def point_mass(backend) -> HyperPosterior:
    """The hyperparameters as they are, weight 1: predictions equal the plug-in (MAP) ones."""
    spec = hyper_spec(backend.hypers)
    th = spec.theta(backend.hypers)
    return HyperPosterior("map", spec.labels, th[None], th.new_ones(1), th, n_proposals=1, ess=1.0)


def _hessian(backend, spec: HyperSpec, theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """log p, its gradient (P,) and the Hessian (P, P) of -log p at theta: central differences of the closed-form
    gradient (``gp.hyper.density``; 2 P + 1 points in one space, step ``HESSIAN_STEP`` in log(value), error ~1e-8
    relative) where the backend has one and every point is possible, else autograd's second derivatives."""
    fd = _hessian_by_differences(backend, spec, theta)
    if fd is not None:
        return fd
    th = theta.detach().clone().requires_grad_(True)
    lp = log_posterior(backend, spec, th, exact_graph=True)
    (g,) = torch.autograd.grad(lp, th, create_graph=True)
    rows = [torch.autograd.grad(g[i], th, retain_graph=True)[0] for i in range(th.numel())]
    H = -torch.stack(rows)
    return lp.detach(), g.detach(), 0.5 * (H + H.mT).detach()


def _hessian_by_differences(backend, spec: HyperSpec, theta: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
    """``_hessian`` from the closed-form gradient at theta and theta +- h e_i (one space); None without a closed
    form or where a point is impossible (then autograd's)."""
    P, h = theta.numel(), HESSIAN_STEP
    eye = torch.eye(P, dtype=theta.dtype, device=theta.device) * h
    points = torch.cat([theta.detach()[None], theta.detach() + eye, theta.detach() - eye])
    with torch.no_grad():
        res = log_posterior_and_grad_chunked(backend, spec, points)
    if res is None or res[1] is None or not bool(torch.isfinite(res[0]).all()):
        return None
    lp, g = res
    H = -(g[1:P + 1] - g[P + 1:]) / (2 * h)
    return lp[0], g[0], 0.5 * (H + H.mT)


def _polish(backend, spec: HyperSpec, theta: Tensor, max_iter: int) -> tuple[Tensor, Tensor, Tensor]:
    """The mode of log p(theta | F) from theta: L-BFGS (strong Wolfe line search, torch.optim) to a gradient below
    1e-6 or a step changing log p by under ``POLISH_CHANGE``, then Newton steps on the exact Hessian while the posterior
    still rises. Adam's last iterate is near, not at, the mode, and the Laplace Gaussian belongs at the mode."""
    x = theta.detach().clone().requires_grad_(True)
    opt = torch.optim.LBFGS([x], lr=1.0, max_iter=int(max_iter), tolerance_grad=1e-6, tolerance_change=POLISH_CHANGE,
                            history_size=20, line_search_fn="strong_wolfe")
    start = log_posterior(backend, spec, x.detach())

    def closure():
        opt.zero_grad()
        lp = log_posterior(backend, spec, x)
        loss = -lp if torch.isfinite(lp) else x.sum() * 0 + 1e30
        loss.backward()
        return loss

    if max_iter > 0:
        try:
            opt.step(closure)
        except (torch.linalg.LinAlgError, NotPSDError):  # a line-search probe too far: keep the start
            x = theta.detach().clone()
    cand = x.detach()
    with torch.no_grad():
        lp_c = log_posterior(backend, spec, cand)
    start_theta = theta.detach()
    theta = cand if torch.isfinite(lp_c) and lp_c >= start else start_theta
    lp, g, H = _hessian(backend, spec, theta)
    if not _finite(g, H) and theta is not start_theta:
        # L-BFGS ran along a direction the posterior is flat in (priors=None) until a value under- or overflowed
        # (a variance of e^-745 is 0): no Gaussian there; the fit's own point has one
        theta = start_theta
        lp, g, H = _hessian(backend, spec, theta)
    for _ in range(3):  # Newton on the exact Hessian: quadratic convergence near the mode
        if not _finite(g, H) or float(g.abs().max()) < 1e-6:
            break
        step = torch.linalg.solve(guard.positive_definite(H), g)
        step = step / max(1.0, float(step.abs().max()))
        with torch.no_grad():
            lp_c = log_posterior(backend, spec, theta + step)
        if not (torch.isfinite(lp_c) and lp_c > lp):
            break
        if float(g @ step) < NEWTON_DONE:  # the mode is this close: H there is H here to the step's size
            theta, lp = (theta + step).detach(), lp_c
            break
        lp_n, g_n, H_n = _hessian(backend, spec, (theta + step).detach())
        if not _finite(g_n, H_n):
            break
        theta, lp, g, H = (theta + step).detach(), lp_n, g_n, H_n
    return theta, H, lp


def _finite(*tensors: Tensor) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def laplace(backend, n_proposals: int = 128, n_draws: int | None = 16, free=None, max_iter: int = 100,
            df: float = 30.0, inflate: float = 1.5, qmc: bool = True,
            generator: torch.Generator | None = None, adapt: bool | str = "always", smooth: bool = True,
            points: str = "moments", split: bool = True, max_stages: int = 4) -> HyperPosterior:
    """The Laplace approximation at the mode, importance-reweighted (module docstring).

    Args:
        backend: a fitted model's backend (``InverseRFT.backend``); its hyperparameters are moved to
            the polished mode.
        n_proposals: proposals weighed (one marginal likelihood each).
        n_draws: at most this many draws kept for prediction (``points``); None keeps every proposal with its
            weight.
        free: labels (or a bool mask (P,)) of the hyperparameters to marginalise; the others stay at the
            mode (default: all).
        max_iter: L-BFGS iterations polishing the mode before the Hessian is taken.
        df: the proposal is a Student-t with ``df`` degrees of freedom and scale ``inflate`` x H^-1: wider than
            the Laplace Gaussian, so the weights stay bounded where the posterior's tails are heavier.
        qmc: proposals from a scrambled Sobol sequence (``_student_t``) rather than pseudo-random.
        generator: a ``torch.Generator`` for the proposals' scrambling and the resample; None (default): one seeded
            with ``DRAW_SEED``, so that the same data give the same draws and predictions in any process.
        adapt: "always" (default): a second stage of ``n_proposals`` / 2 proposals, from a Student-t moved to the
            first stage's weighted draws, both weighed together (``gp.hyper.importance.importance_sample``);
            "unreliable" (or True): a second stage of ``n_proposals`` only where the first stage's weights are
            unreliable (Pareto k-hat above 0.7 or ESS below 2); False: one stage.
        smooth: Pareto-smoothed weights (``gp.hyper.pareto.psis_smooth``): the few largest weights, which set
            most of the Monte Carlo error, replaced by a fitted tail; False: the raw weights.
        points: the draws kept. "moments" (default): P + 1 equally weighted points (2 P where ``n_draws``
            allows) with the weighted proposals' mean and covariance over the P free coordinates
            (``_moment_points``): no resampling noise, and the mixture's mean exact where a prediction is
            quadratic in theta. "resample": a systematic resample of ``n_draws`` proposals (identical ones
            merged), the fallback where ``n_draws`` < P + 1 or a point is an impossible setting.
        split: the first stage's Student-t is split along the Laplace covariance's Cholesky axes
            (``gp.hyper.importance.split_axes``, Geweke 1989): each side as wide as the log posterior's fall there
            says (4 P + 1 more evaluations), so a direction the data bound on one side only is covered. False: the
            symmetric Student-t.
        max_stages: with ``adapt``, stages of the second's size, each moved to all the weighted draws so far, are
            added while the weights stay unreliable (``guard.unreliable``), up to this many stages in all (2: never
            more than the second). With ``split``, on the planar wheels' 54 held-out runs, a prediction's centre
            moves by under 0.1 of its sd between point sets (docs/calibration.md).
    """
    spec = hyper_spec(backend.hypers)
    P = spec.size
    mask = _free_mask(spec, free).clone()
    if generator is None:
        generator = torch.Generator().manual_seed(DRAW_SEED)
    theta0 = spec.theta(backend.hypers)
    held: list[str] = []
    lower = guard.lower_bounds(spec)
    for attempt in range(3):  # polish and propose; coordinates at a wall are held there and the rest done again
        idx = mask.nonzero()[:, 0].to(theta0.device)
        sub_spec = _SubSpec(spec, theta0, idx)
        mode_sub, H, lp_mode = _polish(backend, sub_spec, theta0[idx], max_iter)
        theta0 = sub_spec.full(mode_sub)
        if not _finite(H):
            spec.load(backend.hypers, theta0)
            return _kept_plug_in(spec, theta0, held, "the log posterior's Hessian is not finite at the fitted "
                                                     "hyperparameters (a value under- or overflows there)")
        cov = guard.proposal_covariance(H)

        def log_p_many(x: Tensor, sub_spec=sub_spec) -> Tensor:  # -inf where impossible (overflow, below a bound)
            lp = _log_posterior_many(backend, sub_spec, x)
            return torch.where(guard.possible(sub_spec.full(x), lower), lp, torch.full_like(lp, -math.inf))

        axes = split_axes(log_p_many, mode_sub, cov, float(inflate)) if split else None
        first = first_stage(log_p_many, mode_sub, float(inflate) * cov, df, int(n_proposals), generator, qmc, axes)
        if bool(torch.isfinite(first[2]).all()):
            break
        if attempt == 2:  # the proposals drawn stand (impossible ones weigh nothing)
            break
        at_wall = guard.walls(log_p_many, mode_sub, cov.diagonal().sqrt())  # only where some are impossible
        if not at_wall.any():
            break
        held += [sub_spec.labels[int(i)] for i in at_wall.nonzero()[:, 0]]
        mask[idx[at_wall].cpu()] = False
        if not mask.any():
            break
    mode = theta0
    spec.load(backend.hypers, mode)
    if not mask.any():  # every coordinate at a wall: nothing to marginalise
        return _kept_plug_in(spec, mode, held, "every hyperparameter is at a wall")
    if adapt not in (True, False, "always", "unreliable"):
        raise ValueError(f"adapt must be 'always', 'unreliable' (True) or False, got {adapt!r}")
    if points not in ("moments", "resample"):
        raise ValueError(f"points must be 'moments' or 'resample', got {points!r}")
    when = {"always": _always, "unreliable": guard.unreliable, True: guard.unreliable, False: None}[adapt]
    x, logp, logw, n_stages = importance_sample(log_p_many, first, mode_sub, float(inflate) * cov, df, generator, qmc,
                                         when, max(1, int(n_proposals) // 2) if adapt == "always" else None, axes,
                                         guard.unreliable, int(max_stages))
    spec.load(backend.hypers, mode)  # functional_call restores, but be explicit about where we leave them
    khat = pareto_khat(logw)  # of the raw weights: how far they could be trusted before smoothing
    if smooth:
        logw = psis_smooth(logw)
    ok = torch.isfinite(logw)
    if not ok.any():
        return _kept_plug_in(spec, mode, held, f"every one of the {int(n_proposals)} Laplace proposals is an "
                                               f"impossible setting")
    lw = torch.where(ok, logw - logw[ok].max(), torch.full_like(logw, -math.inf))
    w = lw.exp()
    w = w / w.sum()
    ess = guard.effective_size(lw)
    message = guard.reliability_message(ess, khat, x.shape[0], held)
    if message:
        warnings.warn(message, guard.HyperPosteriorWarning, stacklevel=3)
    thetas = sub_spec.full(x)
    kept = _moment_points(x, w, n_draws, log_p_many) if points == "moments" else None
    if kept is not None:
        thetas, w = sub_spec.full(kept), kept.new_full((kept.shape[0],), 1 / kept.shape[0])
    elif n_draws is not None and n_draws < len(w):
        pick = _systematic(w, int(n_draws), generator)
        thetas, w = _merge(thetas[pick], torch.full((len(pick),), 1 / len(pick), dtype=w.dtype, device=w.device))
    else:
        keep = w > 0
        thetas, w = thetas[keep], w[keep]
    full_cov = theta0.new_zeros(P, P)
    full_cov[idx[:, None], idx[None, :]] = cov
    return HyperPosterior("laplace", spec.labels, thetas.detach(), w.detach(), mode.detach(), full_cov, ess, khat,
                          x.shape[0], {"log_posterior_mode": float(lp_mode), "held": held,
                                             "stages": n_stages,
                                             "points": "moments" if kept is not None else "resample",
                                             "hessian": H.detach() if bool(mask.all()) else None})


def _log_posterior_many(backend, spec: HyperSpec, x: Tensor) -> Tensor:
    """log p at each row of x (n, P): one call where the backend has the closed form, else one by one."""
    with torch.no_grad():
        logp = log_posterior_batch(backend, spec, x)
        return torch.stack([log_posterior(backend, spec, xi) for xi in x]) if logp is None else logp


def _kept_plug_in(spec: HyperSpec, mode: Tensor, held: list[str], why: str) -> HyperPosterior:
    """A point mass at the polished hyperparameters (the plug-in), with a ``HyperPosteriorWarning`` saying why."""
    warnings.warn(f"{why}: the hyperparameter posterior is far from Gaussian here; predictions use the fitted "
                  f"hyperparameters (the plug-in). hyper_posterior='nuts' samples it (pip install pyro-ppl)",
                  guard.HyperPosteriorWarning, stacklevel=4)
    return HyperPosterior("laplace", spec.labels, mode.detach()[None], mode.new_ones(1), mode.detach(), None,
                          1.0, float("nan"), 0, {"held": held or list(spec.labels), "plug_in": why})


class _SubSpec(HyperSpec):
    """A spec over some coordinates of another, the rest held at ``base``."""

    def __init__(self, spec: HyperSpec, base: Tensor, idx: Tensor) -> None:
        super().__init__(spec.names, spec.shapes, spec.constraints, [spec.labels[int(i)] for i in idx])
        self.full_spec, self.base, self.idx = spec, base.detach(), idx

    def raw(self, theta: Tensor) -> dict[str, Tensor]:
        return self.full_spec.raw(self.base.index_put((self.idx,), theta))

    def full(self, theta: Tensor) -> Tensor:
        out = self.base.to(theta).expand(*theta.shape[:-1], self.base.shape[-1]).clone()
        out[..., self.idx] = theta
        return out

    def free_part(self, g: Tensor) -> Tensor:
        return g[..., self.idx]


def _free_mask(spec: HyperSpec, free) -> Tensor:
    P = spec.size
    if free is None:
        mask = torch.ones(P, dtype=torch.bool)
    elif isinstance(free, Tensor):
        mask = free.to(torch.bool).reshape(-1)
    else:
        unknown = [f for f in free if f not in spec.labels]
        if unknown:
            raise ValueError(f"free: unknown hyperparameter(s) {unknown}; known: {spec.labels}")
        mask = torch.tensor([lab in set(free) for lab in spec.labels])
    if mask.numel() != P or not mask.any():
        raise ValueError(f"free must select some of the {P} hyperparameters {spec.labels}")
    return mask


def label_axis(label: str) -> int | None:
    """The map (0: x, 1: z) a hyperparameter label belongs to, or None (shared by both: tied noise)."""
    if label.startswith("lengthscale_"):
        return "xz".index(label[len("lengthscale_")])
    if label.endswith("_x"):
        return 0
    if label.endswith("_z"):
        return 1
    return None


def log_prior_per_axis(hypers) -> Tensor:
    """(2,) the log densities of the registered hyperparameter priors, summed per map (a prior on a
    hyperparameter both maps share, a tied noise, is split evenly)."""
    out = hypers.kernel.raw_outputscale.new_zeros(2)
    for _, module, prior, closure, _ in hypers.named_priors():
        lp = prior.log_prob(closure(module))
        if lp.ndim >= 1 and lp.shape[0] == 2:
            out = out + lp.reshape(2, -1).sum(-1)
        else:
            out = out + lp.sum() / 2
    return out


def log_evidence(backend, hessian: Tensor | None = None) -> Tensor:
    r"""(2,) the log marginal likelihood of each map's model, log p(F_c | model) (its hyperparameters
    integrated out), by the Laplace approximation at the backend's current hyperparameters, which must be
    the mode of their posterior (``laplace`` polishes them there):

        log p(F_c) ~ log p(F_c | theta_c) + log p(theta_c) + (d_c / 2) log 2 pi - 1/2 log |H_c|

    with theta_c the d_c log-hyperparameters of map c and H_c their block of the Hessian of
    -log p(theta | F). The two maps' models are independent (each its own hyperparameters and force
    axis), so the evidence factorises over them; where a hyperparameter is shared (tied noise) the two
    entries are both the joint evidence / 2. The priors must be proper (``MapPrior(hyperpriors="physical")``, the
    default): a flat prior has no evidence (ValueError). ``hessian``: H at these hyperparameters if already known (P, P)
    (``laplace`` keeps it in ``extra["hessian"]``), else computed by autograd."""
    hypers = backend.hypers
    if not any(True for _ in hypers.named_priors()):
        raise ValueError("the evidence needs proper hyperparameter priors (MapPrior(hyperpriors='physical')); these "
                         "have none")
    spec = hyper_spec(hypers)
    theta = spec.theta(hypers)
    H = _hessian(backend, spec, theta)[2] if hessian is None else hessian.to(theta)
    was = backend.training
    backend.train()
    try:
        with torch.no_grad():
            log_lik = -backend.negative_log_likelihood() * backend.n_samples
            lp = log_lik + log_prior_per_axis(hypers)
    finally:
        backend.train(was)
    axes = [label_axis(lab) for lab in spec.labels]
    if any(a is None for a in axes):  # a shared hyperparameter: one joint evidence
        d = len(axes)
        joint = lp.sum() + 0.5 * d * math.log(2 * math.pi) - 0.5 * torch.linalg.slogdet(guard.positive_definite(H))[1]
        return (joint / 2).expand(2).clone()
    out = []
    for c in range(2):
        idx = torch.tensor([i for i, a in enumerate(axes) if a == c], device=H.device)
        Hc = guard.positive_definite(H[idx][:, idx])
        out.append(lp[c] + 0.5 * len(idx) * math.log(2 * math.pi) - 0.5 * torch.linalg.slogdet(Hc)[1])
    return torch.stack(out)


def draw_hypers(hypers, spec: HyperSpec, theta: Tensor):
    """A copy of ``hypers`` set to theta, its priors shared with ``hypers`` (they do not depend on theta and are kept
    out of state dicts; copying them was most of a copy's time)."""
    h = copy.deepcopy(hypers, {id(m): m for m in hypers.modules() if isinstance(m, Prior)})
    spec.load(h, theta)
    return h


def add_data_to_draws(hp: HyperPosterior, backends: list, contacts, forces: Tensor) -> None:
    """Stream samples into each draw's backend and reweight the draw by their likelihood given the old
    samples, p(F_new | F_old, theta_s) = p(F_all | theta_s) / p(F_old | theta_s): the importance weights a
    fit on all the data would give these draws (the draws themselves stay; ``hp.extra["draws_ess"]`` says
    how far the new data moved the weights)."""
    log_lik = []
    with torch.no_grad():
        for b in backends:
            before = -b.negative_log_likelihood().sum() * b.n_samples
            b.add_data(contacts, forces)
            log_lik.append(-b.negative_log_likelihood().sum() * b.n_samples - before)
    logw = hp.weights.log().to(forces) + torch.stack(log_lik)
    w = (logw - logw.max()).exp()
    hp.weights = (w / w.sum()).to(hp.weights)
    hp.extra["draws_ess"] = float(1 / hp.weights.pow(2).sum())
