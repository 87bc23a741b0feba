r"""The "spectral" backend: the maps in a truncated Fourier basis on the angle torus.

alpha_a(theta) = psi(theta)^T u_a with psi = psi_beta(2 beta) kron psi_gamma(gamma) and
u_a ~ N(0, s_a Sigma_beta,a kron Sigma_gamma,a) (``gp.kernels.fourier``): the weight-space algebra
(``weight_space``) with F = (2 n_beta + 1)(2 n_gamma + 1) features. The sufficient statistics take
one pass over the data (O(T M F + T F^2)); each Adam step costs O(r^3 + r^2 F) with r <= min(T, F),
whatever T; streaming adds O(F^2) per sample. The basis is sized from the lengthscales and a
tolerance on the kernel's truncation error (reported by ``truncation_error``); when a lengthscale
shrinks during fitting, ``refresh`` grows the basis (recomputing the statistics from the data it
keeps).
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from ...rft.contacts import Contacts
from ..kernels.fourier import MAX_HARMONICS, FourierBasis, truncation_errors
from ..kernels.li_basis import li_index, with_li_functions
from . import draw_spaces
from .base import FunctionalPosterior, RFTBackend, split_blocks
from .draw_spaces import DRAW_GROUPS, DRAW_HARMONICS, EXACT_PAIRS, draws_in_one_basis
from .fourier_statistics import _meta, features, restrict_statistics, spectral_statistics
from .pairs import PairsBackend
from .weight_space import FeatureStatistics, WeightSpaceBackend

__all__ = ["SpectralBackend", "spectral_statistics", "restrict_statistics", "features", "DRAW_HARMONICS", "DRAW_GROUPS",
           "EXACT_PAIRS", "draws_in_one_basis"]

GROW_MARGIN = 0.85  # a basis grows (or shrinks) to hold lengthscales this much shorter than the current ones
SHRINK_FACTOR = 0.7  # a fit moves to a smaller basis when its step would cost under this much of the current one's


def step_flops(T: int, basis: FourierBasis) -> float:
    """The closed form's arithmetic per step in ``basis`` (r = min(T, F)): r^3 / 3 + 2 r^2 F + 2 r F (F_b + F_g)."""
    F, (Fb, Fg) = basis.size, basis.sizes
    r = min(T, F)
    return r**3 / 3 + 2 * r * r * F + 2 * r * F * (Fb + Fg)


class SpectralBackend(WeightSpaceBackend):
    """I-RFT in a Fourier basis on the (beta, gamma) torus; exact up to the reported truncation.

    Args:
        hypers: shared hyperparameters.
        contacts: whitened training contacts (T, M).
        forces: whitened training forces (T, 2), N.
        tol: bound on the kernel's relative truncation error used to size the basis (default 1e-7).
        basis: a fixed :class:`FourierBasis` instead (then ``tol`` only triggers a warning).
        keep_data: keep the training data so that the basis can grow (default True).
        statistics: precomputed statistics of exactly ``contacts`` and ``forces`` (``gp.statistics``) in a
            basis at least as large as the one needed: used instead of a pass over the data, here and
            whenever the basis grows within them.
    """

    name = "spectral"
    held = False  # True: the basis stays as it is (set by InverseRFT's method="auto" to hold a step's cost)
    _basis_key: Tensor | None  # the hyperparameters the basis was last sized for (``_ensure_basis``)

    def __init__(self, hypers, contacts: Contacts, forces: Tensor, tol: float = 1e-7,
                 basis: FourierBasis | None = None, keep_data: bool = True,
                 statistics: FeatureStatistics | None = None) -> None:
        super().__init__(hypers, contacts, forces)
        if not (0 < tol < 1):
            raise ValueError(f"tol must be in (0, 1), got {tol}")
        self.tol = float(tol)
        self.basis = basis or FourierBasis.for_lengthscale(hypers.lengthscale, self.tol)
        if getattr(hypers, "li", None) is not None and min(self.basis.n_beta, self.basis.n_gamma) < 1:
            if basis is not None:
                raise ValueError(f"basis {basis} has no first harmonic of 2 beta or gamma: Li et al.'s term "
                                 f"(li_basis: kernel='li') needs FourierBasis(n_beta >= 1, n_gamma >= 1)")
            self.basis = with_li_functions(self.basis)  # it never shrinks
        self._data = [(contacts, forces)] if keep_data else None
        self._stored = statistics if statistics is not None and self._covers(statistics, self.basis) else None
        self._set_stats(self._stored_or_pass(self.basis, [(contacts, forces)]))

    @staticmethod
    def _covers(stats: FeatureStatistics, basis: FourierBasis) -> bool:
        m = stats.meta
        return m.get("space") == "spectral" and basis.n_beta <= m["n_beta"] and basis.n_gamma <= m["n_gamma"]

    def _stored_or_pass(self, basis: FourierBasis, data=None) -> FeatureStatistics | None:
        """The training data's statistics in ``basis``: cut from the stored ones when they cover it,
        else one pass over ``data`` (default the kept data; None if there is none)."""
        if self._stored is not None and self._covers(self._stored, basis):
            return restrict_statistics(self._stored, basis)
        data = self._data if data is None else data
        if data is None:
            return None
        stats = None
        for c, f in data:
            part = self.statistics(c, f)
            stats = part if stats is None else stats + part
        return stats

    def describe(self) -> str:
        err = self.truncation_error().max().item()
        return (f"spectral: T={self.n_samples}, {self.basis.sizes[0]} x {self.basis.sizes[1]} = {self.basis.size} "
                f"Fourier features, kernel truncation error <= {err:.1e}")

    # ---- statistics ---------------------------------------------------------------------------
    def features(self, c: Contacts) -> Tensor:
        """Phi (2, N, F): the weighted sums' features, x and z axes."""
        return features(c, self.basis)

    def statistics(self, c: Contacts, f: Tensor) -> FeatureStatistics:
        """Sufficient statistics of (c, f) in this backend's basis, one chunked pass."""
        return spectral_statistics(c, f, self.basis, self.hypers.mean)

    def _rows(self):
        if not self._data:
            return None
        c = Contacts.cat([d[0] for d in self._data])
        y = torch.cat([d[1] for d in self._data]).T
        with torch.no_grad():
            g = self.hypers.mean.shape_forces(c) if self.hypers.mean is not None else None
            return self.features(c), y, g

    def _meta(self) -> dict:
        return _meta(self.basis)

    # ---- the weight-space pieces ------------------------------------------------------------
    def _sigma_factors(self, detach: bool = False) -> tuple[Tensor, Tensor, Tensor]:
        """Sigma_beta (2, Fb, Fb), Sigma_gamma (2, Fg, Fg), s (2,); the detached ones are cached
        while the hyperparameters and the basis stay the same (queries)."""
        ls, s = self.hypers.lengthscale, self.hypers.outputscale
        if not detach:
            return (*self.basis.coefficients(ls), s)
        key = self._hyper_key()
        hit = self.__dict__.get("_sigma_cache")
        if hit is None or hit[1] != self.basis or not torch.equal(hit[0], key):
            with torch.no_grad():
                hit = (key, self.basis, (*self.basis.coefficients(ls.detach()), s.detach()))
            self._sigma_cache = hit
        return hit[2]

    def _kron(self, X: Tensor, Sb: Tensor, Sg: Tensor, s: Tensor) -> Tensor:
        """X (2, k, F) -> X (s Sb kron Sg) (2, k, F), without forming the Kronecker product."""
        Fb, Fg = self.basis.sizes
        k = X.shape[-2]
        Y = X.reshape(2, k * Fb, Fg) @ Sg  # two large products instead of 2k small ones
        Y = Y.reshape(2, k, Fb, Fg).transpose(1, 2).reshape(2, Fb, k * Fg)
        Y = (Sb.mT @ Y).reshape(2, Fb, k, Fg).transpose(1, 2)
        return s[:, None, None] * Y.reshape(X.shape)

    def _li_index(self) -> Tensor:
        """(9,) the positions of Li et al.'s functions {1, cos 2beta, sin 2beta} x {1, cos gamma, sin gamma} in this
        basis (beta-major, as ``li_basis.li_features``): the term is diagonal here, v / 4 on those 9 weights."""
        return li_index(self.basis, self.stats.P.device)

    def _sigma_apply(self, X: Tensor, detach: bool) -> Tensor:
        """X (2, k, F) -> X Sigma, Sigma = s Sb kron Sg (+ Li et al.'s term on its 9 weights, P / 4,
        ``gp.kernels.li_basis``: diag(v) / 4, or with the generic shape the full 9 x 9 P / 4)."""
        Y = self._kron(X, *self._sigma_factors(detach=detach))
        li = self.hypers.li
        if li is None:
            return Y
        idx = self._li_index()
        return Y.index_add(-1, idx, li.weigh(X[..., idx], detach=detach) / 4)

    def _apply_sigma(self, X: Tensor) -> Tensor:
        return self._sigma_apply(X, detach=False)

    def _closed_form_terms(self, f) -> list:
        from .covariance_terms import KroneckerFourier, li_terms

        terms: list = [KroneckerFourier(self.basis, f.R)]
        if self.hypers.li is not None:  # H (F, 9): 1/2 at each function's own weight (li_features = psi / 2)
            H = f.R.new_zeros(self.basis.size, 9)
            H[self._li_index().to(H.device), torch.arange(9, device=H.device)] = 0.5
            terms += li_terms(self.hypers, H)
        return terms

    def _whole_data(self) -> tuple[Contacts, Tensor] | None:
        """The training contacts and forces, where this backend keeps all of them (None: built from statistics, or
        statistics merged in)."""
        if not self._data or sum(len(c) for c, _ in self._data) != self.n_samples:
            return None
        if len(self._data) == 1:
            return self._data[0]
        return Contacts.cat([d[0] for d in self._data]), torch.cat([d[1] for d in self._data])

    def draw_groups(self, lengthscale: Tensor) -> list[tuple[Tensor, RFTBackend]] | None:
        """A batch of hyperparameter settings (lengthscales (S, 2, 1, 4)) grouped by the space each is evaluated in:
        [(mask (S,), a backend on these data)], this backend itself for those its basis holds within ``tol``, a basis
        near each one's own for the others, the exact pairs space beyond every basis or where it is cheaper
        (``draw_spaces.group_draws``); None where this backend cannot choose (built from statistics, its basis held,
        or inside ``draws_in_one_basis()``): the caller then grows this basis for the batch (``prepare``)."""
        return draw_spaces.group_draws(self, lengthscale)

    def with_hypers(self, hypers) -> RFTBackend | None:
        """A kept draw's backend (``draw_spaces.draw_backend``): the exact pairs space beyond every basis, else the
        basis it needs cut from its batch's statistics; None where the model builds one from its own statistics."""
        return draw_spaces.draw_backend(self, hypers)

    def space_for(self, lengthscale: Tensor) -> RFTBackend:
        """The backend one hyperparameter setting (lengthscales (2, 1, 4)) is evaluated in: this one where its basis
        holds them within ``tol`` (the cheap check a step makes anyway), else ``draw_groups``' choice (the basis they
        need, or the exact pairs space beyond ``MAX_HARMONICS``); this one where it cannot choose. The last space
        chosen serves the next setting its basis holds too (L-BFGS' steps near the mode)."""
        ls = lengthscale.detach()
        flat = ls.reshape(-1, 2, 4).double()
        last = self.__dict__.get("_last_space")
        sizes = [self.basis] + ([last[1].basis] if last is not None and isinstance(last[1], SpectralBackend) else [])
        top = max([MAX_HARMONICS] + [max(b.n_beta, b.n_gamma) for b in sizes])  # a basis may hold more than the cap
        eb, eg = truncation_errors(flat[..., 0:2], top), truncation_errors(flat[..., 2:4], top)  # every n, remembered

        def holds(basis: FourierBasis) -> bool:
            return bool((eb[..., basis.n_beta] + eg[..., basis.n_gamma] <= self.tol).all())

        if holds(self.basis):
            return self
        if last is not None and last[0] is self.stats and isinstance(last[1], SpectralBackend) and holds(last[1].basis):
            return last[1]
        groups = self.draw_groups(ls[None])
        space = self if not groups else groups[0][1]
        self._last_space = (self.stats, space)
        return space

    def forget_draws(self) -> None:
        """Drop what evaluating a batch of draws kept (``draw_groups``: statistics in the largest basis a draw needed,
        up to 2 x 3721^2 numbers, and a backend per group): called once the draws' own backends are built."""
        self.__dict__.pop("_draw_cache", None)
        self.__dict__.pop("_last_space", None)

    def exact_twin(self) -> PairsBackend | None:
        """The pairs backend on these data and hyperparameters, exact at any lengthscale, built once
        (``draw_spaces.exact_twin``; None beyond ``EXACT_PAIRS`` distinct pairs)."""
        return draw_spaces.exact_twin(self)

    def prepare(self, values: dict) -> None:
        """Outside a fit loop, grow the basis so that its truncation error is below ``tol`` for every
        lengthscale in ``values`` (a batch of draws: one basis for all)."""
        if not self.in_fit:
            from .covariance_terms import LENGTHSCALE

            self.refresh(values[LENGTHSCALE])

    def _features_of(self, c: Contacts) -> Tensor:
        """features(c), remembered for the last few query objects that need no gradient."""
        if any(t.requires_grad for t in c.as_dict().values()):
            return self.features(c)
        cache = self.__dict__.setdefault("_feature_cache", {})
        hit = cache.get(id(c))
        if hit is not None and hit[0] is c and hit[1] == self.basis:
            return hit[2]
        Phi = self.features(c)
        if len(cache) >= 4:
            cache.pop(next(iter(cache)))
        cache[id(c)] = (c, self.basis, Phi)
        return Phi

    def _cross(self, c: Contacts) -> Tensor:
        return self._sigma_apply(self._features_of(c), detach=True)

    def _prior_cov(self, c: Contacts, full: bool) -> Tensor:
        C, _ = self._query(c)  # Phi Sigma, remembered
        Phi = self._features_of(c)
        return C @ Phi.mT if full else (C * Phi).sum(-1)

    def _prior_cross(self, c1: Contacts, c2: Contacts) -> Tensor:
        C1, _ = self._query(c1)
        return C1 @ self._features_of(c2).mT

    def truncation_error(self) -> Tensor:
        return self.basis.truncation_error(self.hypers.lengthscale)

    def _ensure_basis(self) -> None:
        """Refresh the basis once per new set of hyperparameter values (outside a fit loop)."""
        key = self._hyper_key()
        if getattr(self, "_basis_key", None) is None or not torch.equal(self._basis_key, key):
            self.refresh()
            self._basis_key = key

    def negative_log_likelihood(self) -> Tensor:
        if not self.in_fit:
            self._ensure_basis()
        return super().negative_log_likelihood()

    def _u_posterior(self) -> tuple[Tensor, Tensor]:
        """The posterior of the Fourier coefficients: mean m_u (2, F) and covariance
        A = Sigma - (H Sigma)^T (H Sigma) (2, F, F), cached while the hyperparameters and data stay."""
        H, v = self._posterior_terms()
        hit = self.__dict__.get("_u_cache")
        if hit is not None and hit[0] is H:
            return hit[1], hit[2]
        with torch.no_grad():
            F = self.basis.size
            eye = torch.eye(F, dtype=H.dtype, device=H.device).expand(2, F, F)
            Sigma = self._sigma_apply(eye, detach=True)
            HS = H @ Sigma
            A = Sigma - HS.mT @ HS
            A = 0.5 * (A + A.mT)
            m = (Sigma @ v[..., None])[..., 0]
        self._u_cache = (H, m, A)
        return m, A

    def _times_posterior(self, c: Contacts) -> Tensor:
        """Phi A (2, N, F), remembered for the last few query objects that need no gradient."""
        _, A = self._u_posterior()
        if any(t.requires_grad for t in c.as_dict().values()):
            return self._features_of(c) @ A
        cache = self.__dict__.setdefault("_phiA_cache", {})
        hit = cache.get(id(c))
        if hit is not None and hit[0] is c and hit[1] is A:
            return hit[2]
        X = self._features_of(c) @ A
        if len(cache) >= 4:
            cache.pop(next(iter(cache)))
        cache[id(c)] = (c, A, X)
        return X

    def posterior(self, contacts: Contacts, variance: bool = True, covariance: bool = False):
        """In coefficient space: mean Phi m_u, covariance Phi A Phi^T (the same numbers as the
        weight-space formulas, fewer products per query)."""
        self._ensure_basis()
        m, _ = self._u_posterior()
        Phi = self._features_of(contacts)
        mean = (Phi @ m[..., None])[..., 0]
        prior = self.hypers.mean_of(contacts, detach=True)
        if prior is not None:
            mean = mean + prior
        out = FunctionalPosterior(mean)
        if covariance or variance:
            X = self._times_posterior(contacts)
            if covariance:
                cov = X @ Phi.mT
                out.covariance = 0.5 * (cov + cov.mT)
                out.variance = torch.diagonal(out.covariance, dim1=-2, dim2=-1)
            else:
                out.variance = (X * Phi).sum(-1)
        return out

    def cross_covariance(self, c1: Contacts, c2: Contacts) -> Tensor:
        self._ensure_basis()
        return self._times_posterior(c1) @ self._features_of(c2).mT

    def root_size(self) -> int:
        self._ensure_basis()
        return self.basis.size

    def posterior_root(self, contacts: Contacts) -> Tensor:
        """Z = Phi R (2, N, F) with R R^T = A, so that Z Z^T is the posterior covariance of the
        contacts' weighted sums (noise not included): scoring works with it in F dimensions when a
        candidate has more samples than the basis has features."""
        self._ensure_basis()
        _, A = self._u_posterior()
        hit = self.__dict__.get("_root_cache")
        if hit is None or hit[0] is not A:
            lam, V = torch.linalg.eigh(A)
            hit = self._root_cache = (A, V * lam.clamp_min(0).sqrt()[..., None, :])
        return self._features_of(contacts) @ hit[1]

    def block_covariance(self, contacts: Contacts, sizes: list[int]) -> Tensor:
        """Diagonal blocks Phi_i A Phi_i^T (B, 2, T_max, T_max): one product Phi A over every block's rows,
        then one batched product of the blocks (zero-padded rows add zero rows and columns)."""
        self._ensure_basis()
        Phi = self._features_of(contacts)  # (2, N, F)
        X = self._times_posterior(contacts)
        cov = split_blocks(X, sizes) @ split_blocks(Phi, sizes).mT
        return 0.5 * (cov + cov.mT)

    # ---- more data and a growing basis --------------------------------------------------------
    def _with_data(self, c: Contacts, f: Tensor) -> SpectralBackend:
        new = SpectralBackend.__new__(SpectralBackend)
        WeightSpaceBackend.__init__(new, self.hypers, c, f)
        new.tol, new.basis = self.tol, self.basis
        new._data = None if self._data is None else self._data + [(c, f)]
        new._stored = None
        new._set_stats(self.stats + new.statistics(c, f))
        return new

    def add_data(self, contacts: Contacts, forces: Tensor) -> None:
        self._set_stats(self.stats + self.statistics(contacts, forces))
        self._stored = None  # they no longer describe all the data
        if self._data is not None:
            self._data.append((contacts, forces))

    def merge(self, stats: FeatureStatistics) -> None:
        """Add statistics computed elsewhere (another recording, another process) in this basis."""
        self._set_stats(self.stats + stats)
        self._data = None  # the raw data behind them is not here: the basis can no longer grow
        self._stored = None

    def stale(self) -> bool:
        if self.held:  # the basis is held (method="auto" on nearly noise-free data, gp.model): nothing to adapt
            return False
        return not bool((self.truncation_error() <= self.tol).all())

    def shrink(self) -> bool:
        """Called every few steps of a fit: move to the smaller basis the current lengthscales need (with the margin
        ``refresh`` grows by) where its step costs under ``SHRINK_FACTOR`` of this basis' (a fit whose lengthscales
        grew back after a short start: without it the last steps pay for the widest basis any step needed). The
        statistics are cut from this basis' (exact: ``restrict_statistics``), which are kept, so growing back
        within them needs no pass over the data. Returns whether the basis changed; never for a held basis."""
        if self.held:
            return False
        small = FourierBasis.for_lengthscale(self.hypers.lengthscale.detach() * GROW_MARGIN, self.tol)
        if getattr(self.hypers, "li", None) is not None:
            small = with_li_functions(small)
        small = FourierBasis(min(small.n_beta, self.basis.n_beta), min(small.n_gamma, self.basis.n_gamma))
        if step_flops(self.n_samples, small) >= SHRINK_FACTOR * step_flops(self.n_samples, self.basis):
            return False
        if self._stored is None or not self._covers(self._stored, self.basis):
            self._stored = self.stats  # the widest statistics of exactly these data: the basis may grow back
        self.basis = small
        self._set_stats(restrict_statistics(self._stored, small))
        return True

    def refresh(self, lengthscale: Tensor | None = None) -> bool:
        """Grow the basis if the current lengthscales (or ``lengthscale`` (*S, 2, 1, 4), every draw of a
        batch) need more harmonics than it has for ``tol`` (recomputing the statistics from the kept data).
        Returns whether it grew. A held basis (``held``) never grows."""
        ls = self.hypers.lengthscale if lengthscale is None else lengthscale.detach().reshape(-1, 1, 4)
        if self.held or bool((self.basis.truncation_error(ls) <= self.tol).all()):  # the cheap check: this basis
            return False
        need = FourierBasis.for_lengthscale(ls, self.tol)
        if need.n_beta <= self.basis.n_beta and need.n_gamma <= self.basis.n_gamma:
            return False
        ahead = FourierBasis.for_lengthscale(ls.detach() * GROW_MARGIN, self.tol)  # room to shrink
        grown = FourierBasis(max(ahead.n_beta, self.basis.n_beta), max(ahead.n_gamma, self.basis.n_gamma))
        fixed = self._data is None and not (self._stored is not None and self._covers(self._stored, grown))
        if grown == self.basis or fixed:
            if fixed:
                warnings.warn(f"the lengthscales need a larger Fourier basis ({need}) than the statistics were "
                              f"computed in ({self.basis}) and the raw data are not kept: the kernel truncation "
                              f"error is now {self.basis.truncation_error(ls).max().item():.1e} (tol {self.tol:.0e})",
                              stacklevel=2)
            return False
        if max(need.n_beta, need.n_gamma) >= MAX_HARMONICS:  # not just the margin: the tolerance is out of reach
            flat = ls.detach().reshape(-1)
            what = (f"lengthscales {flat.tolist()}" if flat.numel() <= 8 else  # one model's 8; a batch: its shortest
                    f"the shortest lengthscale {float(flat.min()):.3g} of a batch of {flat.numel() // 8} settings")
            warnings.warn(f"{what} need more than {MAX_HARMONICS} harmonics per angle; the truncation error may "
                          f"exceed tol={self.tol:.0e}", stacklevel=2)
        self.basis = grown
        self._set_stats(self._stored_or_pass(grown))
        return True
