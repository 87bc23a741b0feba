"""The interface every inference backend implements, and what its posterior returns.

A backend holds training data (already whitened by the noise scales and mapped into the canonical
square) and the shared :class:`RFTHyperparameters`. It computes one covariance, W K W^T + noise,
in whatever space is smallest, and answers four questions:

- ``loss()``: the negative log marginal likelihood per force sample, summed over the two axes
  (gpytorch's ``ExactMarginalLogLikelihood`` normalization, registered hyperparameter priors
  included), differentiable in the hyperparameters;
- ``posterior(contacts)``: the posterior of the weighted sums of any contacts (a composite force,
  or a map value: a one-segment functional, ``Contacts.points``), marginal or joint;
- ``condition(contacts, forces=None)``: a new backend that has also seen these observations
  (without forces: as if they equalled their posterior mean, which leaves the mean unchanged and
  gives the exact posterior covariance; the covariance never depends on the values);
- ``add_data(contacts, forces)``: the same, in place (streaming).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor, nn

from ...rft.contacts import Contacts
from ..kernels.hyperparameters import RFTHyperparameters

__all__ = ["FunctionalPosterior", "RFTBackend", "touching"]


@dataclass
class FunctionalPosterior:
    """Posterior of N linear functionals of each map, axis order (x, z).

    Attributes:
        mean: (2, N).
        variance: (2, N), or None when not asked for.
        covariance: (2, N, N) joint covariance, or None when not asked for.
    """

    mean: Tensor
    variance: Tensor | None = None
    covariance: Tensor | None = None


def touching(c: Contacts) -> Tensor:
    """(T,) bool: rows with at least one segment of non-zero weight on either axis."""
    return ((c.weight_x != 0) | (c.weight_z != 0)).any(-1)


def split_blocks(x: Tensor, sizes: list[int], dim: int = -2) -> Tensor:
    """x (..., sum(sizes), ...) cut along ``dim`` into consecutive blocks of ``sizes``, stacked in front
    and zero-padded to the longest: (B, ..., max(sizes), ...). A view when the blocks are equal."""
    dim = dim % x.ndim
    B, T = len(sizes), max(sizes)
    if all(n == T for n in sizes):
        return x.unflatten(dim, (B, T)).movedim(dim, 0)
    out = x.new_zeros(B, *x.shape[:dim], T, *x.shape[dim + 1:])
    start = 0
    for i, n in enumerate(sizes):
        out[i].narrow(dim, 0, n).copy_(x.narrow(dim, start, n))
        start += n
    return out


class RFTBackend(nn.Module):
    """Base class of the exact backends ("observations", "pairs", "spectral").

    Args:
        hypers: the shared hyperparameters (a submodule: it is trained through the backend).
        contacts: training contacts (T, M), whitened and canonical.
        forces: (T, 2) whitened forces in N.
    """

    name = "base"

    def __init__(self, hypers: RFTHyperparameters, contacts: Contacts, forces: Tensor) -> None:
        super().__init__()
        self.hypers = hypers
        self.n_samples = len(contacts)
        self.in_fit = False  # set by a fit loop that calls ``refresh`` itself every few steps

    # ---- to implement ------------------------------------------------------------------------
    def negative_log_likelihood(self) -> Tensor:
        """-log p(F | hyperparameters) / T per axis, (2,)."""
        raise NotImplementedError

    def posterior(self, contacts: Contacts, variance: bool = True, covariance: bool = False) -> FunctionalPosterior:
        raise NotImplementedError

    def cross_covariance(self, c1: Contacts, c2: Contacts) -> Tensor:
        """Posterior covariance (2, N1, N2) between the weighted sums of two sets of contacts."""
        raise NotImplementedError

    def condition(self, contacts: Contacts, forces: Tensor | None = None) -> RFTBackend:
        raise NotImplementedError

    def root_size(self) -> int | None:
        """The width F of ``posterior_root`` (None where there is no finite root)."""
        return None

    def posterior_root(self, contacts: Contacts) -> Tensor | None:
        """Z (2, N, F) with Z Z^T the posterior covariance of the contacts' weighted sums, where the
        backend has a finite root (the spectral one: F Fourier features), else None."""
        return None

    def block_covariance(self, contacts: Contacts, sizes: list[int]) -> Tensor:
        """The diagonal blocks of the posterior covariance of ``contacts`` (sum(sizes), M) split along
        time into consecutive blocks of ``sizes``: (B, 2, T_max, T_max), each block zero-padded to the
        longest (noise not included). What scoring B candidates at once needs: each one's own
        covariance, not the ones between them. This default asks ``posterior`` once per block."""
        out = contacts.beta.new_zeros(len(sizes), 2, max(sizes), max(sizes))
        start = 0
        for i, n in enumerate(sizes):
            out[i, :, :n, :n] = self.posterior(contacts[start:start + n], covariance=True).covariance
            start += n
        return out

    def add_data(self, contacts: Contacts, forces: Tensor) -> None:
        raise NotImplementedError

    def with_hypers(self, hypers: RFTHyperparameters) -> RFTBackend | None:
        """A backend on the same data at other hyperparameters that shares what does not depend on them
        (a hyperparameter posterior's draws), or None where there is nothing to share (build a new one)."""
        return None

    def closed_form(self):
        """The likelihood of this backend's data in closed form (``closed_form.ClosedForm``: one loss and
        its gradient without autograd, over a batch of hyperparameter draws too), or None where there is
        none (then ``loss()`` and autograd serve)."""
        return None

    def draw_groups(self, lengthscale: Tensor) -> list | None:
        """A batch of hyperparameter settings (lengthscales (S, 2, 1, 4)) split by the backend each is evaluated in
        at least cost: [(mask (S,), backend)] (the spectral backend: by the basis each needs), or None: every
        setting here (the exact spaces' cost does not depend on them)."""
        return None

    def space_for(self, lengthscale: Tensor) -> RFTBackend:
        """The backend one hyperparameter setting (lengthscales (2, 1, 4)) is evaluated in at least cost: this one
        (the spectral backend: the basis the setting needs, ``draw_groups``)."""
        return self

    def forget_draws(self) -> None:
        """Drop what evaluating a batch of hyperparameter draws kept (nothing by default)."""

    def prepare(self, values: dict) -> None:
        """Adapt to hyperparameter values about to be evaluated by ``closed_form()`` (name -> (*S, *shape);
        the spectral basis grows to hold their lengthscales). Nothing by default."""

    # ---- shared ------------------------------------------------------------------------------
    def loss_and_grad(self) -> float | None:
        """``loss()`` and its gradient in closed form (``closed_form.loss_and_grad``): sets ``.grad`` of the
        raw hyperparameters and returns the loss, or None (use ``loss()`` and autograd)."""
        from .closed_form import loss_and_grad

        return loss_and_grad(self)

    def loss(self) -> Tensor:
        """Negative log marginal likelihood per force sample summed over both axes, minus the log
        density of any registered hyperparameter prior divided by T (MAP), as gpytorch's
        ``ExactMarginalLogLikelihood`` does."""
        return self.negative_log_likelihood().sum() - self.log_prior() / max(self.n_samples, 1)

    def log_prior(self) -> Tensor:
        """Sum of the log densities of the hyperparameter priors registered on the shared modules."""
        return self.hypers.log_prior()

    def stale(self) -> bool:
        """Whether the current hyperparameters need ``refresh`` (the spectral basis too small)."""
        return False

    def refresh(self) -> bool:
        """Called during fitting: adapt to the current hyperparameters if needed (the spectral basis
        grows when a lengthscale shrinks). Returns whether anything changed."""
        return False

    def shrink(self) -> bool:
        """Called every few steps of a fit: move to a cheaper space the current hyperparameters allow (the spectral
        basis, once the lengthscales grew back). Returns whether anything changed."""
        return False

    def truncation_error(self) -> Tensor:
        """(2,) bound on |k - k_used| / outputscale, per map: 0 for the exact-arithmetic backends."""
        return self.hypers.kernel.outputscale.detach().new_zeros(2)

    # ---- what a probe scorer asks (``design.ProbeScorer``); a 3-D backend answers the same (``gp.inverse3d``) ------
    contacts_type = Contacts
    n_blocks = 2  # independent blocks of the force covariance: the x rows (alpha_x), the z rows (alpha_z)

    def region_rows(self, region) -> Contacts:
        """A region's points (``design.Region``) as point evaluations of both maps (``region.contacts()``), on the
        hyperparameters' dtype and device."""
        dt = self.hypers.noise
        return region.contacts().to(dtype=dt.dtype, device=dt.device)

    def region_variance(self, rows: Contacts) -> Tensor:
        """(2, N) the maps' posterior variance at ``region_rows``' points, (N/cm^3)^2."""
        return self.posterior(rows).variance

    def candidate_rows(self, cands: list[Contacts], rows: Contacts | None = None) -> tuple:
        """Each candidate's force rows per axis, zero-padded to the longest (``block_covariance``): S (B, 2, T, T)
        their posterior covariance (noise not included), the rows' noise variances (2, 1), and their posterior
        covariance (B, 2, T, N) with ``rows`` (``region_rows``), or None. Differentiable in the candidates."""
        sizes = [len(c) for c in cands]
        both = Contacts.cat(cands)
        S = self.block_covariance(both, sizes)
        cross = None if rows is None else split_blocks(self.cross_covariance(rows, both), sizes, dim=-1).mT
        return S, self.hypers.noise.detach()[:, None], cross

    @staticmethod
    def fold_maps(x: Tensor) -> Tensor:
        """(..., 2, N) values of ``region_rows``' rows per map: already (alpha_x, alpha_z)."""
        return x

    def map_moments(self, beta, gamma) -> tuple[Tensor, Tensor]:
        """Posterior mean and variance (N, 2) of (alpha_x, alpha_z) at angles of any broadcast shape (N of them)."""
        dt = self.hypers.noise
        post = self.posterior(Contacts.points(beta, gamma, dtype=dt.dtype, device=dt.device))
        return post.mean.T, post.variance.T

    def describe(self) -> str:
        return f"{self.name}: T={self.n_samples}"

    @staticmethod
    def _gaussian_nll(quad: Tensor, logdet: Tensor, n: int) -> Tensor:
        """0.5 (quad + logdet + n log 2 pi) / n."""
        return 0.5 * (quad + logdet + n * math.log(2 * math.pi)) / n

