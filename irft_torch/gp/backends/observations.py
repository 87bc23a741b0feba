"""The "observations" backend: a gpytorch ExactGP over composite force observations, its kernel
returning the lazy W K W^T (``RFTKernelLinearOperator``). The reference implementation, and the
choice for few samples with many distinct angle pairs (a rotating toe, short recordings)."""

from __future__ import annotations

import contextlib
import math

import gpytorch
import torch
from gpytorch.distributions import MultivariateNormal
from gpytorch.mlls import ExactMarginalLogLikelihood
from linear_operator.utils.cholesky import psd_safe_cholesky
from linear_operator.utils.errors import NotPSDError
from torch import Tensor

from ...rft.contacts import Contacts
from ..kernels.angle import BATCH, RFTCompositeKernel, composite_covariance
from ..kernels.encoding import encode_contacts
from ..kernels.li_basis import contact_li_features, li_features
from ..kernels.operators import RFTKernelLinearOperator, _dense_weights, _use_dense_weights
from .base import FunctionalPosterior, RFTBackend

__all__ = ["CompositeExactGP", "ObservationsBackend", "PriorBackend"]


class CompositeExactGP(gpytorch.models.ExactGP):
    """A batch of two exact GPs (x and z maps) observed through RFT-weighted sums.

    Inputs are composite rows (2, T, 3M) (see ``gp.kernels.encoding``), targets the forces (2, T).
    """

    def __init__(self, train_inputs: Tensor, train_targets: Tensor, likelihood, mean_module, covar_module) -> None:
        super().__init__(train_inputs, train_targets, likelihood)
        self.mean_module = mean_module
        self.covar_module = covar_module

    def forward(self, x: Tensor) -> MultivariateNormal:
        return MultivariateNormal(self.mean_module(x), self.covar_module(x))


class ObservationsBackend(RFTBackend):
    """Exact I-RFT in the T-dimensional space of the observations (gpytorch's ExactGP).

    Args:
        hypers: shared hyperparameters (their kernel, likelihood and mean become the GP's).
        contacts: whitened training contacts (T, M).
        forces: whitened training forces (T, 2), N.
        solver: "cholesky" (exact, the default) or "gpytorch" (gpytorch's own settings: CG/Lanczos
            above ``gpytorch.settings.max_cholesky_size``).
    """

    name = "observations"

    def __init__(self, hypers, contacts: Contacts, forces: Tensor, solver: str = "cholesky") -> None:
        super().__init__(hypers, contacts, forces)
        if solver not in ("cholesky", "gpytorch"):
            raise ValueError(f"solver must be 'cholesky' or 'gpytorch', got {solver!r}")
        self.solver = solver
        self.train_contacts, self.train_forces = contacts, forces
        self.n_segments = contacts.n_segments
        mean = hypers.mean if hypers.mean is not None else gpytorch.means.ZeroMean(batch_shape=BATCH)
        self.gp = CompositeExactGP(self._encode(contacts), forces.T.contiguous(), hypers.likelihood,
                                   *self._gp_parts(mean))

    def _encode(self, contacts: Contacts, M: int | None = None) -> Tensor:
        """The ExactGP's input rows of ``contacts`` (``gp.kernels.encoding``), padded to M segments."""
        return encode_contacts(contacts, M)

    def _gp_parts(self, mean) -> tuple:
        """The ExactGP's mean and kernel modules over ``_encode``'s rows."""
        return mean, RFTCompositeKernel(self.hypers.kernel, self.hypers.li)

    def _settings(self):
        stack = contextlib.ExitStack()
        if self.solver == "cholesky":
            stack.enter_context(gpytorch.settings.max_cholesky_size(2**31))
        return stack

    def mll(self) -> ExactMarginalLogLikelihood:
        """gpytorch's exact marginal log likelihood object for this GP."""
        return ExactMarginalLogLikelihood(self.hypers.likelihood, self.gp)

    def negative_log_likelihood(self) -> Tensor:
        self.gp.train()
        if self.solver == "cholesky":
            return self._cholesky_nll()
        with self._settings():
            out = self.gp(*self.gp.train_inputs)
            return -self.hypers.likelihood(out).log_prob(self.gp.train_targets) / self.n_samples

    def _cholesky_nll(self) -> Tensor:
        """-log p(F) / T per axis (2,) of this ExactGP, by one Cholesky of its own lazy W K W^T (the
        kernel's operator, made dense) plus the noise: what ``likelihood(gp(x)).log_prob(y)`` computes
        with ``max_cholesky_size`` above T, without gpytorch's per-call bookkeeping (a third of a step
        on the paper's T = 100 problems). ``tests/test_backends.py`` checks the two agree, gradients too."""
        x = self.gp.train_inputs[0]
        K = self.gp.covar_module.forward(x, x).to_dense()
        r = self.gp.train_targets - self.gp.mean_module(x)
        n = K.shape[-1]
        eye = torch.eye(n, dtype=K.dtype, device=K.device)
        L = psd_safe_cholesky(K + self.hypers.noise[:, None, None] * eye)
        z = torch.linalg.solve_triangular(L, r[..., None], upper=False)[..., 0]
        logdet = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
        return 0.5 * (z.pow(2).sum(-1) + logdet + n * math.log(2 * math.pi)) / self.n_samples

    def closed_form(self):
        """``closed_form.ClosedForm`` in the observations' space (R = I, A = W K W^T) where W K W^T has a
        cheap exact form: a translating toe (``RowSeparable``) or few distinct angle pairs (weights summed
        per pair, ``PairsRBF`` with R = W_U, the operator's own dense-weights case); else None (autograd).
        Only with the Cholesky solver."""
        from .closed_form import ClosedForm
        from .covariance_terms import PairsRBF, RowSeparable, li_terms

        if self.solver != "cholesky":
            return None
        hit = self.__dict__.get("_closed_form_cache")
        if hit is not None and hit[0] is self.train_contacts and hit[1] is self.train_forces:
            return hit[2]
        c, y = self.train_contacts, self.train_forces.T
        with torch.no_grad():
            side = self._side(c)
            g = self.hypers.mean.shape_forces(c) if self.hypers.mean is not None else None
        R = None
        if "separable" in side:
            terms: list = [RowSeparable(side["separable"][0])]
            if self.hypers.li is not None:
                terms += li_terms(self.hypers, side["li"])
        else:
            U, M = side["pairs1"].shape[0], side["i1"].shape[-1]
            if not _use_dense_weights(U, M, U, M):
                self._closed_form_cache = (c, self.train_forces, None)
                return None
            R = _dense_weights(side["i1"].expand(2, *side["i1"].shape[-2:]), side["w1"], U)
            terms = [PairsRBF(side["pairs1"])]
            if self.hypers.li is not None:
                terms += li_terms(self.hypers, li_features(side["pairs1"][:, 0], side["pairs1"][:, 1]))
        cf = ClosedForm(R, y, g, y.new_zeros(2, 3), self.n_samples, terms, symmetrize=False)
        self._closed_form_cache = (c, self.train_forces, cf)
        return cf

    def _ensure_width(self, M: int) -> None:
        """Widen the training rows with zero-weight padding so test rows with M segments fit."""
        if M > self.n_segments:
            self.gp.set_train_data(inputs=self._encode(self.train_contacts, M), strict=False)
            self.n_segments = M

    # ---- prediction: the training covariance factored once per set of hyperparameters --------
    def _side(self, c: Contacts) -> dict:
        """One side of a W1 K W2^T: the contacts' non-zero segments and their distinct angle pairs (and, with
        Li et al.'s term, the features summed with the weights, "li" (2, N, 9))."""
        w = torch.stack([c.weight_x, c.weight_z])
        side = RFTKernelLinearOperator.segment_structure(c.beta[None], c.gamma[None], w, c.beta[None], c.gamma[None],
                                                         w, BATCH, same_inputs=True)
        if self.hypers.li is not None:
            side["li"] = contact_li_features(c)
        return side

    def _block(self, side1: dict, side2: dict) -> Tensor:
        """Prior covariance (2, N1, N2) of two sets of weighted sums (the lazy operator, made dense)."""
        structure = {"pairs1": side1["pairs1"], "i1": side1["i1"], "w1": side1["w1"], "pairs2": side2["pairs1"],
                     "i2": side2["i1"], "w2": side2["w1"], "same": side1 is side2}
        if "separable" in side1 and "separable" in side2:  # both toes translate: the product form
            structure["separable"] = (side1["separable"][0], side2["separable"][0])
        k = self.hypers.kernel
        K = RFTKernelLinearOperator.from_structure(structure, k.lengthscale.detach(), k.outputscale.detach(),
                                                   BATCH).to_dense()
        if self.hypers.li is not None:
            K = K + self.hypers.li.weigh(side1["li"], detach=True) @ side2["li"].mT
        return K

    def _factor(self):
        """(train side, L (2, T, T) with L L^T = W K W^T + noise, alpha = (.)^-1 (y - m)), cached by value."""
        key = torch.cat([p.detach().reshape(-1) for p in self.hypers.parameters()])
        hit = self.__dict__.get("_factor_cache")
        if hit is not None and hit[0] is self.train_contacts and torch.equal(hit[1], key):
            return hit[2]
        with torch.no_grad():
            side = self._side(self.train_contacts)
            K = self._block(side, side)
            noise = self.hypers.noise.detach()
            eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
            try:
                L = psd_safe_cholesky(0.5 * (K + K.mT) + noise[:, None, None] * eye)
            except NotPSDError as e:
                raise NotPSDError(f"training covariance not positive definite; hyperparameters: "
                                  f"{self.hypers.as_dict()}") from e
            r = self.train_forces.T
            m = self.hypers.mean_of(self.train_contacts)
            if m is not None:
                r = r - m
            alpha = torch.cholesky_solve(r[..., None], L)[..., 0]
        value = (side, L, alpha)
        self._factor_cache = (self.train_contacts, key, value)
        return value

    def _query(self, c: Contacts):
        """(side, K_tq (2, T, N), A = L^-1 K_tq), remembered for the last few query objects that need
        no gradient (a design scores one region against many candidates)."""
        side_t, L, _ = self._factor()
        grad = any(t.requires_grad for t in c.as_dict().values())
        cache = self.__dict__.setdefault("_query_cache", {})
        hit = cache.get(id(c))
        if not grad and hit is not None and hit[0] is c and hit[1] is L:
            return hit[2]
        side = self._side(c)
        Ktq = self._block(side_t, side)
        A = torch.linalg.solve_triangular(L, Ktq, upper=False)
        value = (side, Ktq, A)
        if not grad:
            if len(cache) >= 4:
                cache.pop(next(iter(cache)))
            cache[id(c)] = (c, L, value)
        return value

    def posterior(self, contacts: Contacts, variance: bool = True, covariance: bool = False) -> FunctionalPosterior:
        """Exact posterior of the weighted sums of ``contacts`` (N, M) (the same numbers as gpytorch's
        prediction from ``self.gp``, which the tests check; the training factor is computed once)."""
        _, _, alpha = self._factor()
        side, Ktq, A = self._query(contacts)
        mean = (Ktq.mT @ alpha[..., None])[..., 0]
        prior = self.hypers.mean_of(contacts, detach=True)
        if prior is not None:
            mean = mean + prior
        out = FunctionalPosterior(mean)
        if covariance:
            cov = self._block(side, side) - A.mT @ A
            out.covariance = 0.5 * (cov + cov.mT)
            out.variance = torch.diagonal(out.covariance, dim1=-2, dim2=-1)
        elif variance:
            out.variance = composite_covariance(self.hypers.kernel, contacts, li=self.hypers.li).diagonal() - A.pow(
                2).sum(-2)
        return out

    def cross_covariance(self, c1: Contacts, c2: Contacts) -> Tensor:
        s1, _, A1 = self._query(c1)
        s2, _, A2 = self._query(c2)
        return self._block(s1, s2) - A1.mT @ A2

    def _with_data(self, c: Contacts, f: Tensor) -> ObservationsBackend:
        return type(self)(self.hypers, Contacts.cat([self.train_contacts, c]),
                                   torch.cat([self.train_forces, f.to(self.train_forces)]), self.solver)

    def condition(self, contacts: Contacts, forces: Tensor | None = None) -> ObservationsBackend:
        if forces is None:
            with torch.no_grad():
                forces = self.posterior(contacts, variance=False).mean.T
        return self._with_data(contacts, forces)

    def add_data(self, contacts: Contacts, forces: Tensor) -> None:
        self.train_contacts = Contacts.cat([self.train_contacts, contacts])
        self.train_forces = torch.cat([self.train_forces, forces.to(self.train_forces)])
        self.n_segments = max(self.n_segments, contacts.n_segments)
        self.n_samples = len(self.train_contacts)
        self.gp.set_train_data(inputs=self._encode(self.train_contacts, self.n_segments),
                               targets=self.train_forces.T.contiguous(), strict=False)


class PriorBackend(RFTBackend):
    """No data yet: the prior of the maps (exact, through the lazy W K W^T). ``condition`` turns it
    into an :class:`ObservationsBackend`. For designing the first probes."""

    name = "prior"

    def __init__(self, hypers) -> None:
        nn_init = RFTBackend.__init__
        empty = Contacts(*(torch.zeros(0, 1, dtype=hypers.kernel.raw_outputscale.dtype,
                                       device=hypers.kernel.raw_outputscale.device) for _ in range(4)))
        nn_init(self, hypers, empty, empty.beta.new_zeros(0, 2))

    def _op(self, c1: Contacts, c2: Contacts | None):
        return composite_covariance(self.hypers.kernel, c1, c2, li=self.hypers.li)

    def posterior(self, contacts: Contacts, variance: bool = True, covariance: bool = False) -> FunctionalPosterior:
        mean = self.hypers.mean_of(contacts, detach=True)
        if mean is None:
            mean = contacts.beta.new_zeros(2, len(contacts))
        out = FunctionalPosterior(mean)
        if covariance:
            out.covariance = self._op(contacts, None).to_dense()
            out.variance = torch.diagonal(out.covariance, dim1=-2, dim2=-1)
        elif variance:
            out.variance = self._op(contacts, None).diagonal()
        return out

    def cross_covariance(self, c1: Contacts, c2: Contacts) -> Tensor:
        return self._op(c1, c2).to_dense()

    def condition(self, contacts: Contacts, forces: Tensor | None = None) -> ObservationsBackend:
        if forces is None:
            forces = self.posterior(contacts, variance=False).mean.T
        return ObservationsBackend(self.hypers, contacts, forces.detach())

    def add_data(self, contacts: Contacts, forces: Tensor) -> None:
        raise TypeError("a PriorBackend holds no data: use condition(), or build InverseRFT(contacts, forces)")

    def negative_log_likelihood(self) -> Tensor:
        raise TypeError("a PriorBackend holds no data: there is no likelihood to evaluate")
