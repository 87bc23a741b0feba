r"""What every probe scorer shares, planar (K = 2 maps) or 3-D (K = 3; ``design.scoring``): the two criteria's
algebra over a candidate's force rows, the belief's readable numbers, checking a criterion, ranking, following the
model a scorer was derived from.

For a candidate whose n force rows have posterior covariance S (noise not included, N^2) and noise variances D =
diag(sigma_i^2), and a region's map points with current variance v_j and covariance C (n x N) with those rows:

    EIG = 1/2 log | I + D^{-1/2} S D^{-1/2} |                      (``information_nats``, nats)
    v_j after the candidate = v_j - [C^T (S + D)^{-1} C]_jj        (``variance_after``, ``variance_fall``)

A planar model's rows are one force axis per map (a batch of K = 2); a 3-D model's are two blocks, (F_x; F_y) seeing
alpha_x and alpha_y, F_z seeing alpha_z. Each backend gives S and C in one layout (``candidate_rows``: a batch of
blocks, zero-padded); the scorer (``design.ProbeScorer``) and the foothold planner (``design.footholds``) call these.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence

import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor

from .region import Region

__all__ = ["BeliefScorer", "FollowingScorer", "information_nats", "variance_fall", "variance_after", "check_criterion"]

CRITERIA = ("variance", "eig")


def information_nats(S: Tensor, noise: Tensor) -> Tensor:
    """(...,) the information gain, nats, of observing rows with posterior covariance ``S`` (..., n, n) and noise
    variances ``noise`` of each row, (..., n) or a shape that expands to it (one per batch item: (..., 1))."""
    d = noise.rsqrt().expand(S.shape[:-1])
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    L = psd_safe_cholesky(eye + 0.5 * (S + S.mT) * d[..., :, None] * d[..., None, :])
    return torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)


def variance_fall(cross: Tensor, S: Tensor, noise: Tensor) -> Tensor:
    """(..., N) how much the points' variance falls on observing the rows, diag(C^T (S + D)^{-1} C): ``cross``
    (..., n, N) the rows' posterior covariance C with the points, ``S`` (..., n, n) the rows' own, ``noise`` (..., n)
    their noise variances."""
    nz = noise.expand(S.shape[:-1])
    L = psd_safe_cholesky(0.5 * (S + S.mT) + torch.diag_embed(nz))
    return torch.linalg.solve_triangular(L, cross, upper=False).pow(2).sum(-2)


def variance_after(variance: Tensor, cross: Tensor, S: Tensor, noise: Tensor) -> Tensor:
    """(..., N) the points' variance after observing the rows: ``variance`` (..., N) now, less ``variance_fall``."""
    return variance - variance_fall(cross, S, noise)


def check_criterion(criterion: str, region: Region | None) -> None:
    """Refuse an unknown criterion, and a region with "eig" (the information is about the probe's own forces)."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be 'variance' or 'eig', got {criterion!r}")
    if criterion == "eig" and region is not None:
        raise ValueError("region applies to criterion 'variance' (the variance integrated over it); 'eig' is the "
                         "information about the forces of the probe itself: pass region=None")


class BeliefScorer:
    """The part of a probe scorer that does not depend on the model's form: its belief's numbers (from
    ``backend.hypers``, detached) and ``rank``. A subclass gives ``backend`` and ``score``."""

    @property
    def backend(self):
        raise NotImplementedError

    @property
    def method(self) -> str:
        """The belief's backend ("observations", "pairs", "spectral", ...)."""
        return self.backend.name

    @property
    def outputscale(self) -> Tensor:
        """(K,) the RBF kernel's variance of each map, (N/cm^3)^2."""
        return self.backend.hypers.outputscale.detach()

    @property
    def prior_variance(self) -> Tensor:
        """(K,) each map's prior variance, (N/cm^3)^2 (with Li et al.'s term, where the model has it)."""
        return self.backend.hypers.prior_variance.detach()

    @property
    def noise(self) -> Tensor:
        """(K,) the force noise variance of each axis, N^2."""
        return self.backend.hypers.noise.detach()

    def score(self, candidates: Sequence, criterion: str = "variance", region: Region | None = None) -> Tensor:
        raise NotImplementedError

    def rank(self, candidates: Sequence, criterion: str = "variance",
             region: Region | None = None) -> list[tuple[int, float]]:
        """(index, score) pairs, best first (the lowest integrated variance, or the highest information gain)."""
        with torch.no_grad():
            s = self.score(candidates, criterion, region).tolist()
        order = sorted(range(len(s)), key=(lambda i: s[i]) if criterion == "variance" else (lambda i: -s[i]))
        return [(i, s[i]) for i in order]


class FollowingScorer(BeliefScorer):
    """A scorer of one backend that follows the model it was derived from (``ProbeScorer.from_model``): whenever the
    model's backend changes (``add_data``, a refit that grows the basis or moves to another backend) the scorer's is
    derived again (``_derive(*recipe)``, the subclass's) from it in the same way. Pickles with its model."""

    def __init__(self, backend) -> None:
        self._backend = backend
        self._recipe: tuple | None = None  # (model, method, tol) of ``from_model``: follow the model
        self._derived_from: tuple | None = None

    @staticmethod
    def _derive(model, method, tol, own=None):
        raise NotImplementedError

    @property
    def backend(self):
        """The belief scored (derived again from the model's whenever that changed). The hyperparameters are shared
        with the model."""
        if self._recipe is not None and not self._same_state(self._recipe[0].backend, self._derived_from):
            self._backend = self._derive(*self._recipe)
            self._derived_from = self._state_of(self._recipe[0].backend)
        return self._backend

    @staticmethod
    def _state_of(backend) -> tuple:
        """What a derived belief depends on: which backend object, its sample count and statistics, the
        objects held by weak references (an id could be reused by a later object once one is freed; a
        weak reference to a freed object answers None)."""
        stats = getattr(backend, "stats", None)
        return weakref.ref(backend), backend.n_samples, None if stats is None else weakref.ref(stats)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        if state.get("_derived_from") is not None:  # weak references do not pickle; the model comes along
            current = self._same_state(self._recipe[0].backend, self._derived_from)
            state["_derived_from"] = ("current",) if current else None  # None: derived again on first use
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self._derived_from == ("current",):
            self._derived_from = self._state_of(self._recipe[0].backend)

    @staticmethod
    def _same_state(backend, state: tuple | None) -> bool:
        """Whether ``backend`` is still the one (with the same sample count and statistics) of ``state``."""
        if state is None:
            return False
        stats = getattr(backend, "stats", None)
        return (state[0]() is backend and state[1] == backend.n_samples
                and (stats is None if state[2] is None else state[2]() is stats))
