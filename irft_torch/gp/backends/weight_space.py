r"""Weight-space inference shared by the "pairs" and "spectral" backends.

Both write each map as a linear model in F fixed features, alpha_a(theta) = psi(theta)^T u_a with
u_a ~ N(0, Sigma_a(hyperparameters)), so a force is F_a = Phi_a u_a + eps, eps ~ N(0, sigma_a^2 I),
with Phi_a (T x F) fixed by the data. The pairs backend's u are the map values at the recording's
distinct angle pairs (Sigma = K_UU, exact); the spectral backend's u are Fourier coefficients on the
angle torus (Sigma = s Sigma_beta kron Sigma_gamma, exact to a reported truncation error).

Everything the likelihood and the posterior need of the data is the Gram matrix of
[Phi | y | g] (g: the physics mean's shape forces), accumulated in one pass and additive over
recordings (:class:`FeatureStatistics`). From it, once per data set (no hyperparameter enters):
P = Phi^T Phi = V D V^T, R = D^{1/2} V^T (r x F, r = rank), c = D^{-1/2} V^T Phi^T y = Q^T y
(Q the orthonormal basis of Phi's range) and the residual rho = y^T y - |c|^2. Then, exactly,

    log |sigma^2 I_T + Phi Sigma Phi^T| = (T - r) log sigma^2 + log |sigma^2 I_r + A|,   A = R Sigma R^T
    y^T (sigma^2 I_T + Phi Sigma Phi^T)^{-1} y = rho / sigma^2 + c^T (sigma^2 I_r + A)^{-1} c

(Q^T (sigma^2 I + Q A Q^T)^{-1} Q = (sigma^2 I + A)^{-1}): each Adam step costs O(r^3 + r^2 F)
whatever T, with no inverse or factor of Sigma (no jitter). The posterior of any functional q with
prior cross-covariance C_qu = Cov(q, u) is

    mean = m_q + C_qu R^T (sigma^2 I + A)^{-1} c,    cov = C_qq - (H C_uq)^T (H C_uq),  H = L^{-1} R,

with L L^T = sigma^2 I + A.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from ...rft.contacts import Contacts
from .base import FunctionalPosterior, RFTBackend

__all__ = ["FeatureStatistics", "WeightSpaceBackend"]


@dataclass
class FeatureStatistics:
    """Sufficient statistics of composite observations in a feature space, per axis (x, z).

    Attributes:
        P: (2, F, F) Phi^T Phi (cm^6).
        b: (2, F) Phi^T y.
        yy: (2,) y^T y (N^2).
        bg, yg, gg: (2, F), (2,), (2,): Phi^T g, y^T g, g^T g for the physics mean's shape forces g
            (zeros without one).
        n: number of force samples.

    Statistics of two recordings add up to those of their union (``a + b``), exactly.
    """

    P: Tensor
    b: Tensor
    yy: Tensor
    bg: Tensor
    yg: Tensor
    gg: Tensor
    n: int = 0
    meta: dict = field(default_factory=dict)

    @classmethod
    def zeros(cls, F: int, dtype=torch.float64, device=None, meta: dict | None = None) -> FeatureStatistics:
        z = lambda *s: torch.zeros(*s, dtype=dtype, device=device)  # noqa: E731
        return cls(z(2, F, F), z(2, F), z(2), z(2, F), z(2), z(2), 0, dict(meta or {}))

    @property
    def n_features(self) -> int:
        return self.P.shape[-1]

    def accumulate(self, Phi: Tensor, y: Tensor, g: Tensor | None = None, same_gram: bool = False) -> None:
        """Add rows: Phi (2, t, F), y (2, t), g (2, t) or None. ``same_gram``: Phi_x^T Phi_x equals
        Phi_z^T Phi_z (rows equal up to a sign per row): one product serves both axes."""
        if same_gram:
            G = Phi[1].mT @ Phi[1]
            self.P += G.expand(2, *G.shape)
        else:
            self.P += Phi.mT @ Phi
        self.b += (Phi.mT @ y[..., None])[..., 0]
        self.yy += y.pow(2).sum(-1)
        if g is not None:
            self.bg += (Phi.mT @ g[..., None])[..., 0]
            self.yg += (y * g).sum(-1)
            self.gg += g.pow(2).sum(-1)
        self.n += y.shape[-1]

    def accumulate_shared(self, Phi: Tensor, sign: Tensor, y: Tensor, g: Tensor | None = None) -> None:
        """Add rows whose x features are the z features times a sign per row (a toe that does not
        turn: weight_x = sign_t weight_z): Phi (t, F) of the z axis, sign (t,), y and g (2, t). One
        product serves both axes."""
        G = Phi.mT @ Phi
        self.P += G.expand(2, *G.shape)
        ys = torch.stack([sign * y[0], y[1]])  # (2, t): Phi_x^T y_x = Phi_z^T (sign y_x)
        self.b += (ys @ Phi)
        self.yy += y.pow(2).sum(-1)
        if g is not None:
            gs = torch.stack([sign * g[0], g[1]])
            self.bg += gs @ Phi
            self.yg += (y * g).sum(-1)
            self.gg += g.pow(2).sum(-1)
        self.n += y.shape[-1]

    def __add__(self, other: FeatureStatistics) -> FeatureStatistics:
        if not isinstance(other, FeatureStatistics):
            return NotImplemented
        if other.P.shape != self.P.shape or other.meta != self.meta:
            raise ValueError(f"cannot merge statistics of different feature spaces: {self.meta} "
                             f"(F={self.n_features}) and {other.meta} (F={other.n_features})")
        return FeatureStatistics(self.P + other.P, self.b + other.b, self.yy + other.yy, self.bg + other.bg,
                                 self.yg + other.yg, self.gg + other.gg, self.n + other.n, dict(self.meta))

    def state(self) -> dict:
        """Tensors and metadata for torch.save (with a dataset)."""
        return {"P": self.P, "b": self.b, "yy": self.yy, "bg": self.bg, "yg": self.yg, "gg": self.gg,
                "n": self.n, "meta": self.meta}

    @classmethod
    def from_state(cls, d: dict) -> FeatureStatistics:
        return cls(d["P"], d["b"], d["yy"], d["bg"], d["yg"], d["gg"], int(d["n"]), dict(d["meta"]))


@dataclass
class _DataFactor:
    """What the likelihood needs of the data, hyperparameter-free: R (2, r, F), c (2, r) for y and
    for g, and the residual Gram (2, 3) = (rho_yy, rho_yg, rho_gg) outside Phi's range."""

    R: Tensor
    c_y: Tensor
    c_g: Tensor
    rho: Tensor
    rank: Tensor  # (2,) per-axis rank


def data_factor(stats: FeatureStatistics, dtype) -> _DataFactor:
    """Eigendecomposition of P in float64 (once per data set); eigenvalues below ``F eps`` of the
    largest are the null space of Phi (contributions of order eps: exactly zero in the model)."""
    P = stats.P.double()
    P = 0.5 * (P + P.mT)
    D, V = torch.linalg.eigh(P)  # ascending
    tol = P.shape[-1] * torch.finfo(torch.float64).eps * 10 * D[..., -1:].clamp_min(1e-300)
    keep = D > tol  # (2, F)
    r = max(int(keep.sum(-1).max()), 1)
    D, V, keep = D[..., -r:], V[..., -r:], keep[..., -r:]  # the r largest per axis
    sq = torch.where(keep, D.clamp_min(0).sqrt(), torch.zeros_like(D))
    inv_sq = torch.where(keep, 1 / sq.clamp_min(1e-300), torch.zeros_like(D))
    R = (sq[..., :, None] * V.mT)  # (2, r, F)
    c_y = inv_sq * (V.mT @ stats.b.double()[..., None])[..., 0]
    c_g = inv_sq * (V.mT @ stats.bg.double()[..., None])[..., 0]
    rho = torch.stack([stats.yy.double() - c_y.pow(2).sum(-1), stats.yg.double() - (c_y * c_g).sum(-1),
                       stats.gg.double() - c_g.pow(2).sum(-1)], -1)
    rho[..., 0] = rho[..., 0].clamp_min(0)
    rho[..., 2] = rho[..., 2].clamp_min(0)
    return _DataFactor(R.to(dtype), c_y.to(dtype), c_g.to(dtype), rho.to(dtype), keep.sum(-1))


def data_factor_from_rows(Phi: Tensor, y: Tensor, g: Tensor | None, dtype, trim: bool | None = None) -> _DataFactor:
    """The same factor from the rows themselves, Phi (2, T, F) = U S V^T: R = S V^T, c = U^T y. With T <= F
    (fewer rows than features: where the planar backends use it) from the rows' Gram Phi Phi^T = U S^2 U^T
    (T x T, float64) and R = U^T Phi, 2-3x cheaper than the thin SVD (measured at T = 1,000, F = 1,037-1,525:
    0.17-0.20 s against 0.35-0.67 s); R^T R = Phi^T Phi to rounding whatever the accuracy of single eigenvectors (U
    is orthogonal), and the Gram's rounding (about T eps of the largest S^2) stays below the cut (10 F eps) since
    T <= F: a very uneven Phi can keep a few more near-zero rows than the SVD, which costs time, not accuracy.
    With more rows than features (a 3-D backend's long recordings) the thin SVD, whose cost grows with T F^2, not
    T^3. Directions with S^2 below ``F eps`` of the largest are Phi's null space (zero in the
    model, as in ``data_factor``), and the rows of R beyond the largest rank of the two axes are dropped
    (``trim``; default: unless inside ``closed_form.autograd_only``, the engine as it was): zero rows of R only
    add sigma^2 to the diagonal, which the (n - r) log sigma^2 term counts anyway. A turning toe's 200 x 289 rows
    have rank 64."""
    from .closed_form import closed_form_enabled

    Phi, y = Phi.double(), y.double()
    if Phi.shape[-2] <= Phi.shape[-1]:
        S2, U = torch.linalg.eigh(Phi @ Phi.mT)
        S2, U = S2.flip(-1).clamp_min(0), U.flip(-1)  # descending
        Vh = None
    else:  # on CUDA the default Jacobi driver can fail to converge on rank-deficient rows; QR-based gesvd does not
        U, S, Vh = torch.linalg.svd(Phi, full_matrices=False, driver="gesvd" if Phi.is_cuda else None)
        S2 = S.pow(2)
    tol = Phi.shape[-1] * torch.finfo(torch.float64).eps * 10 * S2[..., :1].clamp_min(1e-300)
    keep = S2 > tol
    if closed_form_enabled() if trim is None else trim:
        r = max(int(keep.sum(-1).max()), 1)  # S descends: the kept directions come first
        U, S2, keep = U[..., :r], S2[..., :r], keep[..., :r]
        Vh = None if Vh is None else Vh[..., :r, :]
    R = U.mT @ Phi if Vh is None else S2.sqrt()[..., :, None] * Vh
    R = torch.where(keep[..., :, None], R, torch.zeros((), dtype=Phi.dtype, device=Phi.device))
    S = S2.sqrt()
    c_y = torch.where(keep, (U.mT @ y[..., None])[..., 0], torch.zeros_like(S))
    g = torch.zeros_like(y) if g is None else g.double()
    c_g = torch.where(keep, (U.mT @ g[..., None])[..., 0], torch.zeros_like(S))
    rho = torch.stack([y.pow(2).sum(-1) - c_y.pow(2).sum(-1), (y * g).sum(-1) - (c_y * c_g).sum(-1),
                       g.pow(2).sum(-1) - c_g.pow(2).sum(-1)], -1)
    rho[..., 0] = rho[..., 0].clamp_min(0)
    rho[..., 2] = rho[..., 2].clamp_min(0)
    return _DataFactor(R.to(dtype), c_y.to(dtype), c_g.to(dtype), rho.to(dtype), keep.sum(-1))


def chunk_rows(F: int, M: int) -> int:
    """Rows per pass of a statistics accumulation with F features and M segments (about 256 MB)."""
    return max(256, min(16384, int(2**25 // max(1, F * (M + 4)))))


class WeightSpaceBackend(RFTBackend):
    """Shared algebra of the weight-space backends. Subclasses provide the features and Sigma:

    - ``_apply_sigma(X)``: X (2, k, F) -> X Sigma (2, k, F), differentiable in the hyperparameters;
    - ``_cross(contacts)``: prior cross-covariance C_qu (2, N, F) of the contacts' weighted sums
      with u (no gradient needed in the hyperparameters, differentiable in the contacts);
    - ``_prior_cov(contacts, full)``: prior variance (2, N) or covariance (2, N, N) of the sums;
    - ``_with_data(contacts, forces)``: a copy with more observations (``condition``).
    """

    def __init__(self, hypers, contacts: Contacts, forces: Tensor) -> None:
        super().__init__(hypers, contacts, forces)
        self.stats: FeatureStatistics | None = None
        self._data_factor: _DataFactor | None = None
        self._post_cache: tuple | None = None

    def _with_data(self, c: Contacts, f: Tensor) -> WeightSpaceBackend:
        """A copy with more observations (each subclass's own)."""
        raise NotImplementedError

    # ---- statistics -----------------------------------------------------------------------------
    def _set_stats(self, stats: FeatureStatistics) -> None:
        self.stats = stats
        self.n_samples = stats.n
        self._data_factor = None
        self._post_cache = None

    def _factor(self) -> _DataFactor:
        if self._data_factor is None:
            dtype = self.hypers.kernel.raw_outputscale.dtype
            rows = self._rows() if 0 < self.stats.n <= self.stats.n_features else None
            self._data_factor = data_factor(self.stats, dtype) if rows is None else data_factor_from_rows(*rows, dtype)
        return self._data_factor

    def _rows(self) -> tuple[Tensor, Tensor, Tensor | None] | None:
        """The feature rows Phi (2, T, F), forces y (2, T) and mean shape g (2, T) or None, when the
        backend keeps its data (used when T <= F); None otherwise."""
        return None

    def _apply_sigma(self, X: Tensor) -> Tensor:
        raise NotImplementedError

    def _closed_form_terms(self, f: _DataFactor) -> list:
        """The ``closed_form.CovarianceTerm`` s of Sigma (summed), or None (no closed form)."""
        return None

    def closed_form(self):
        """``closed_form.ClosedForm`` on this backend's data factor (R, c, rho) and Sigma's terms, rebuilt
        when the data factor changes (new data, a grown basis)."""
        from .closed_form import ClosedForm

        f = self._factor()
        hit = self.__dict__.get("_closed_form_cache")
        if hit is not None and hit[0] is f:
            return hit[1]
        terms = self._closed_form_terms(f)
        cf = None if terms is None else ClosedForm(f.R, f.c_y, f.c_g if self.hypers.mean is not None else None,
                                                    f.rho, self.stats.n, terms)
        self._closed_form_cache = (f, cf)
        return cf

    def _cross(self, contacts: Contacts) -> Tensor:
        raise NotImplementedError

    def _prior_cov(self, contacts: Contacts, full: bool) -> Tensor:
        raise NotImplementedError

    def _system(self):
        """L (2, r, r) with L L^T = sigma^2 I + R Sigma R^T, the mean-adjusted c (2, r) and rho (2,)."""
        f = self._factor()
        noise = self.hypers.noise
        A = self._apply_sigma(f.R) @ f.R.mT
        A = 0.5 * (A + A.mT)
        eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
        L = torch.linalg.cholesky(A + noise[:, None, None] * eye)
        m = self.hypers.mean_scales
        if m is None:
            c, rho = f.c_y, f.rho[..., 0]
        else:
            c = f.c_y - m[:, None] * f.c_g
            rho = (f.rho[..., 0] - 2 * m * f.rho[..., 1] + m.pow(2) * f.rho[..., 2]).clamp_min(0)
        return L, c, rho, noise, f

    def negative_log_likelihood(self) -> Tensor:
        L, c, rho, noise, f = self._system()
        n = self.stats.n
        r = L.shape[-1]
        z = torch.linalg.solve_triangular(L, c[..., None], upper=False)[..., 0]
        quad = rho / noise + z.pow(2).sum(-1)
        logdet = (n - r) * torch.log(noise) + 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
        return self._gaussian_nll(quad, logdet, n)

    # ---- posterior ------------------------------------------------------------------------------
    def _hyper_key(self) -> Tensor:
        """The hyperparameters' current values, flattened (a cache key: ``.data`` writes do not bump
        a tensor's version counter, so values are compared)."""
        return torch.cat([p.detach().reshape(-1) for p in self.hypers.parameters()]).clone()

    def _posterior_terms(self):
        """H = L^{-1} R (2, r, F) and v = R^T L^{-T} L^{-1} c (2, F), cached while the
        hyperparameters and the data stay the same (no gradient in the hyperparameters)."""
        key = self._hyper_key()
        if self._post_cache is None or not torch.equal(self._post_cache[0], key):
            with torch.no_grad():
                L, c, _, _, f = self._system()
                H = torch.linalg.solve_triangular(L, f.R, upper=False)
                z = torch.linalg.solve_triangular(L, c[..., None], upper=False)
                v = (H.mT @ z)[..., 0]
            self._post_cache = (key, H, v)
        return self._post_cache[1], self._post_cache[2]

    def _prior_cross(self, c1: Contacts, c2: Contacts) -> Tensor:
        """Prior covariance (2, N1, N2) of two sets of weighted sums."""
        raise NotImplementedError

    def _query(self, contacts: Contacts) -> tuple[Tensor, Tensor]:
        """C_qu (2, N, F) and G = H C_uq (2, r, N) of a query; remembered for the last few query
        objects that need no gradient (a design scores one region against many candidates)."""
        H, _ = self._posterior_terms()
        grad = any(t.requires_grad for t in contacts.as_dict().values())
        key = id(contacts)
        cache = self.__dict__.setdefault("_query_cache", {})
        hit = cache.get(key)
        if not grad and hit is not None and hit[0] is contacts and hit[1] is H:
            return hit[2], hit[3]
        C = self._cross(contacts)
        G = H @ C.mT
        if not grad:
            if len(cache) >= 4:
                cache.pop(next(iter(cache)))
            cache[key] = (contacts, H, C, G)
        return C, G

    def posterior(self, contacts: Contacts, variance: bool = True, covariance: bool = False) -> FunctionalPosterior:
        _, v = self._posterior_terms()
        C, G = self._query(contacts)
        mean = (C @ v[..., None])[..., 0]
        prior = self.hypers.mean_of(contacts, detach=True)
        if prior is not None:
            mean = mean + prior
        out = FunctionalPosterior(mean)
        if covariance:
            cov = self._prior_cov(contacts, full=True) - G.mT @ G
            out.covariance = 0.5 * (cov + cov.mT)
            out.variance = torch.diagonal(out.covariance, dim1=-2, dim2=-1)
        elif variance:
            out.variance = self._prior_cov(contacts, full=False) - G.pow(2).sum(-2)
        return out

    def cross_covariance(self, c1: Contacts, c2: Contacts) -> Tensor:
        _, G1 = self._query(c1)
        _, G2 = self._query(c2)
        return self._prior_cross(c1, c2) - G1.mT @ G2

    def condition(self, contacts: Contacts, forces: Tensor | None = None) -> WeightSpaceBackend:
        if forces is None:
            with torch.no_grad():
                forces = self.posterior(contacts, variance=False).mean.T
        return self._with_data(contacts, forces)

    @staticmethod
    def _row_sign(c: Contacts) -> Tensor | None:
        """(T,) sign_t with weight_x = sign_t weight_z for every row (a toe that does not turn), or None."""
        if not torch.equal(c.weight_x.abs(), c.weight_z):
            return None
        s = torch.sign(c.weight_x)
        nz = s != 0
        first = torch.where(nz.any(-1), s.masked_fill(~nz, 0).sum(-1).sign(), torch.ones_like(s[..., 0]))
        return first if bool(((s == first[..., None]) | ~nz).all()) else None

    @classmethod
    def _same_gram(cls, c: Contacts) -> bool:
        """Whether weight_x = +-weight_z with one sign per row (a toe that does not turn)."""
        return cls._row_sign(c) is not None

