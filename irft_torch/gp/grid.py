r"""The scalable path: the stress maps on a fixed (beta, gamma) grid, for recordings of any length.

Each map is represented by its values u on a Gb x Gg grid over the canonical square (periodic in
beta, whose period is pi) and read anywhere by bilinear interpolation, alpha(theta) ~ e(theta)^T u.
A force is then F = Phi u + noise with Phi = W x (interpolation), a fixed sparse matrix: its
sufficient statistics P = Phi^T Phi (U x U), b = Phi^T y and y^T y are accumulated in one pass over
the data. The embedding kernel factors exactly over beta and gamma, so the grid prior is
K = s (K_beta kron K_gamma) = s Lt Lt^T with Lt = L_beta kron L_gamma. With Z = Lt^T P Lt and
B = I + (s / sigma^2) Z (matrix determinant lemma and Woodbury):

    log|Phi K Phi^T + sigma^2 I| = T log sigma^2 + log|B|
    y^T (.)^-1 y = (y^T y - (s / sigma^2) r^T B^-1 r) / sigma^2,   r = Lt^T b

so each marginal-likelihood evaluation costs O(U^3) whatever the number of samples, and new
samples only add to (P, b, y^T y): streaming updates give exactly the posterior of a batch fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..rft.contacts import Contacts
from .kernels import AngleRBFKernel
from .likelihoods import ForceNoiseLikelihood

__all__ = ["AngleGrid", "GridStatistics", "GridRFT"]


@dataclass(frozen=True)
class AngleGrid:
    """Gb x Gg nodes: beta_j = -pi/2 + j pi / Gb (periodic), gamma_k = -pi/2 + k pi / (Gg - 1)."""

    n_beta: int = 32
    n_gamma: int = 32

    def __post_init__(self) -> None:
        if self.n_beta < 4 or self.n_gamma < 4:
            raise ValueError(f"grid needs at least 4 x 4 nodes, got {self.n_beta} x {self.n_gamma}")

    @property
    def size(self) -> int:
        return self.n_beta * self.n_gamma

    def nodes(self, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor]:
        b = -math.pi / 2 + torch.arange(self.n_beta, dtype=dtype, device=device) * math.pi / self.n_beta
        g = -math.pi / 2 + torch.arange(self.n_gamma, dtype=dtype, device=device) * math.pi / (self.n_gamma - 1)
        return b, g

    def interpolation(self, beta: Tensor, gamma: Tensor) -> tuple[Tensor, Tensor]:
        """Bilinear weights of canonical angles (...,): indices (..., 4) into the flattened grid
        (beta-major) and weights (..., 4), summing to 1."""
        fb = (beta + math.pi / 2) / (math.pi / self.n_beta)
        jb = torch.floor(fb)
        tb = fb - jb
        jb = jb.long().remainder(self.n_beta)
        jb1 = (jb + 1).remainder(self.n_beta)  # beta is periodic: the node after the last is the first
        fg = ((gamma + math.pi / 2) / (math.pi / (self.n_gamma - 1))).clamp(0, self.n_gamma - 1 - 1e-9)
        jg = torch.floor(fg)
        tg = fg - jg
        jg = jg.long()
        idx = torch.stack([jb * self.n_gamma + jg, jb * self.n_gamma + jg + 1,
                           jb1 * self.n_gamma + jg, jb1 * self.n_gamma + jg + 1], -1)
        w = torch.stack([(1 - tb) * (1 - tg), (1 - tb) * tg, tb * (1 - tg), tb * tg], -1)
        return idx, w


class GridStatistics:
    """Per-axis sufficient statistics of composite observations on a grid: P (2, U, U),
    b (2, U), yy (2,), n (number of force samples). Accumulate with ``add``; exact to round-off
    whatever the chunking."""

    def __init__(self, grid: AngleGrid, dtype=torch.float64, device=None, mean_shape=None) -> None:
        U = grid.size
        self.grid = grid
        self.P = torch.zeros(2, U, U, dtype=dtype, device=device)
        self.b = torch.zeros(2, U, dtype=dtype, device=device)
        self.yy = torch.zeros(2, dtype=dtype, device=device)
        self.n = 0
        # with a prior mean m_c = s_c g_c (g the generic shape's forces): Phi^T g, g^T g, y^T g
        self.mean_shape = mean_shape
        self.bg = torch.zeros(2, U, dtype=dtype, device=device)
        self.gg = torch.zeros(2, dtype=dtype, device=device)
        self.yg = torch.zeros(2, dtype=dtype, device=device)

    def rows(self, contacts: Contacts) -> tuple[Tensor, Tensor]:
        """Phi rows of contacts (T, M): indices (T, 4M) and values (2, T, 4M) for the x and z axes."""
        idx, w = self.grid.interpolation(contacts.beta, contacts.gamma)  # (T, M, 4)
        T = idx.shape[0]
        vx = (contacts.weight_x[..., None] * w).reshape(T, -1)
        vz = (contacts.weight_z[..., None] * w).reshape(T, -1)
        return idx.reshape(T, -1), torch.stack([vx, vz])

    def add(self, contacts: Contacts, forces: Tensor, chunk: int = 8192) -> GridStatistics:
        """Add force samples (T, 2) observed through contacts (T, M). O(T (4M)^2), chunked."""
        U = self.grid.size
        c = contacts.to(dtype=self.P.dtype, device=self.P.device)
        f = forces.to(dtype=self.P.dtype, device=self.P.device)
        for i in range(0, len(c), chunk):
            idx, val = self.rows(c[i:i + chunk])
            y = f[i:i + chunk].T  # (2, t)
            pair = (idx[:, :, None] * U + idx[:, None, :]).reshape(-1)
            # Rows whose x weights are the z weights up to one sign (any toe that does not turn)
            # give the same outer products for both axes: one pass serves both.
            same = bool(((val[0] == val[1]).all(-1) | (val[0] == -val[1]).all(-1)).all())
            flat_idx = idx.reshape(-1)
            bulk = pair.numel() > U * U  # a dense histogram pays off only when it is not mostly empty
            for a in range(2):
                if not (a == 1 and same):
                    outer = (val[a][:, :, None] * val[a][:, None, :]).reshape(-1)
                    inc = torch.bincount(pair, weights=outer, minlength=U * U) if bulk else None
                if bulk:
                    self.P[a] += inc.reshape(U, U)
                else:
                    self.P[a].view(-1).index_add_(0, pair, outer)  # cost ~ the row's nonzeros, not U^2
                self.b[a].index_add_(0, flat_idx, (val[a] * y[a][:, None]).reshape(-1))
            self.yy += y.pow(2).sum(-1)
            if self.mean_shape is not None:
                cc = c[i:i + chunk]
                a_ = self.mean_shape(cc.beta, cc.gamma)
                g = torch.stack([(cc.weight_x * a_[..., 0]).sum(-1), (cc.weight_z * a_[..., 1]).sum(-1)])
                for a in range(2):
                    self.bg[a].index_add_(0, flat_idx, (val[a] * g[a][:, None]).reshape(-1))
                self.gg += g.pow(2).sum(-1)
                self.yg += (g * y).sum(-1)
            self.n += idx.shape[0]
        return self

    def residual(self, scales: Tensor | None) -> tuple[Tensor, Tensor]:
        """(b, yy) of y - scales * g (the data minus the prior mean); plain (b, yy) without a mean."""
        if scales is None or self.mean_shape is None:
            return self.b, self.yy
        return self.b - scales[:, None] * self.bg, self.yy - 2 * scales * self.yg + scales.pow(2) * self.gg


class GridRFT(nn.Module):
    """I-RFT on a grid: same kernel and likelihood parameterization as the exact model
    (``AngleRBFKernel`` with batch (2,), ``ForceNoiseLikelihood``), marginal likelihood in O(U^3).

    Args:
        grid: the AngleGrid (default 32 x 32).
        tied_noise: one noise variance for both axes.
    """

    def __init__(self, grid: AngleGrid | None = None, tied_noise: bool = False, noise_floor: float = 1e-8,
                 dtype=torch.float64, physics_mean: bool = False) -> None:
        super().__init__()
        from gpytorch.constraints import GreaterThan

        from .means import GenericShapeMean

        self.grid = grid or AngleGrid()
        self.mean_module = GenericShapeMean() if physics_mean else None
        self.kernel = AngleRBFKernel(batch_shape=torch.Size([2]))
        self.likelihood = ForceNoiseLikelihood(tied=tied_noise, noise_constraint=GreaterThan(noise_floor))
        self.to(dtype)
        self.dtype = dtype
        self.stats: GridStatistics | None = None
        self._cache = None

    # ---- data --------------------------------------------------------------------------------
    def set_data(self, contacts: Contacts, forces: Tensor, chunk: int = 8192) -> GridRFT:
        device = self.kernel.raw_outputscale.device
        shape = self.mean_module.shape_map if self.mean_module is not None else None
        self.stats = GridStatistics(self.grid, self.dtype, device, mean_shape=shape).add(contacts, forces, chunk)
        self._cache = None
        return self

    def add_data(self, contacts: Contacts, forces: Tensor) -> GridRFT:
        """Streaming: add samples with the hyperparameters fixed; the posterior is then exactly that
        of a batch fit on all the data (same sufficient statistics)."""
        if self.stats is None:
            return self.set_data(contacts, forces)
        self.stats.add(contacts, forces)
        self._cache = None
        return self

    # ---- prior factors -----------------------------------------------------------------------
    def _factors(self) -> tuple[Tensor, Tensor]:
        """Cholesky factors of K_beta (2, Gb, Gb) and K_gamma (2, Gg, Gg), unit variance."""
        b, g = self.grid.nodes(self.dtype, self.kernel.raw_outputscale.device)
        ls = self.kernel.lengthscale[:, 0, :]  # (2, 4)

        def factor(x1, x2, l1, l2):
            f1, f2 = x1 / l1[:, None], x2 / l2[:, None]
            d2 = (f1[:, :, None] - f1[:, None, :]) ** 2 + (f2[:, :, None] - f2[:, None, :]) ** 2
            K = torch.exp(-0.5 * d2)
            jitter = 1e-8 if self.dtype == torch.float64 else 1e-5
            return torch.linalg.cholesky(K + jitter * torch.eye(K.shape[-1], dtype=K.dtype, device=K.device))

        Lb = factor(torch.sin(2 * b), torch.cos(2 * b), ls[:, 0], ls[:, 1])
        Lg = factor(torch.sin(g), torch.cos(g), ls[:, 2], ls[:, 3])
        return Lb, Lg

    def _kron_apply(self, Lb: Tensor, Lg: Tensor, X: Tensor, transpose: bool = False) -> Tensor:
        """(Lb kron Lg)^(T) X for X (2, U, k), without forming the Kronecker product."""
        Gb, Gg = self.grid.n_beta, self.grid.n_gamma
        k = X.shape[-1]
        A = Lb.mT if transpose else Lb  # (2, Gb, Gb)
        C = Lg.mT if transpose else Lg  # (2, Gg, Gg)
        Y = (A @ X.reshape(2, Gb, Gg * k)).reshape(2, Gb, Gg, k)  # beta factor on the first grid axis
        Y = C[:, None] @ Y  # gamma factor on the second, batched over beta
        return Y.reshape(2, Gb * Gg, k)

    def _posterior_terms(self):
        """B's Cholesky, r, and the factors: everything a likelihood or a prediction needs."""
        if self.stats is None:
            raise RuntimeError("no data: call set_data(contacts, forces) first")
        Lb, Lg = self._factors()
        s = self.kernel.outputscale  # (2,)
        noise = self.likelihood.noise  # (2,)
        P = self.stats.P
        bvec, yy = self.stats.residual(self.mean_module.scales if self.mean_module is not None else None)
        Z = self._kron_apply(Lb, Lg, P, transpose=True)  # Lt^T P
        Z = self._kron_apply(Lb, Lg, Z.mT, transpose=True)  # Lt^T P Lt (P symmetric)
        U = Z.shape[-1]
        B = torch.eye(U, dtype=Z.dtype, device=Z.device) + (s / noise)[:, None, None] * Z
        LB = torch.linalg.cholesky(0.5 * (B + B.mT))
        r = self._kron_apply(Lb, Lg, bvec[..., None], transpose=True)  # (2, U, 1)
        return Lb, Lg, LB, r, s, noise, yy

    def log_marginal_likelihood(self) -> Tensor:
        """log p(F) per axis (2,), divided by the number of samples (as gpytorch's ExactMLL)."""
        Lb, Lg, LB, r, s, noise, yy = self._posterior_terms()
        n = self.stats.n
        q = torch.cholesky_solve(r, LB)
        quad = (yy - (s / noise) * (r * q).sum((-1, -2))) / noise
        logdet = n * torch.log(noise) + 2 * torch.log(torch.diagonal(LB, dim1=-2, dim2=-1)).sum(-1)
        return -0.5 * (quad + logdet + n * math.log(2 * math.pi)) / n

    # ---- prediction --------------------------------------------------------------------------
    def _prediction_cache(self):
        if self._cache is None:
            with torch.no_grad():
                Lb, Lg, LB, r, s, noise, _ = self._posterior_terms()
                mean_v = (s / noise)[:, None, None] * torch.cholesky_solve(r, LB)  # (2, U, 1)
                mean_u = self._kron_apply(Lb, Lg, mean_v)[..., 0]  # grid values of the posterior mean
                # posterior covariance of u: s Lt B^-1 Lt^T = C C^T with C = sqrt(s) Lt LB^-T
                eye = torch.eye(LB.shape[-1], dtype=LB.dtype, device=LB.device).expand_as(LB)
                LBinvT = torch.linalg.solve_triangular(LB, eye, upper=False).mT
                C = s.sqrt()[:, None, None] * self._kron_apply(Lb, Lg, LBinvT)
            self._cache = (mean_u, C)
        return self._cache

    def predict_rows(self, idx: Tensor, val: Tensor, variance: bool = True,
                     mean_prior: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """Posterior of linear functionals val . u[idx] (plus the prior mean ``mean_prior`` (2, N) of
        the same functionals): idx (N, K), val (2, N, K) -> mean, var (2, N)."""
        mean_u, C = self._prediction_cache()
        mean = (val * mean_u[:, idx]).sum(-1)
        if mean_prior is not None:
            mean = mean + mean_prior
        if not variance:
            return mean, None
        N, K = idx.shape
        U = C.shape[-1]
        chunk = max(1, 2**24 // (2 * K * U))
        var = []
        for i in range(0, N, chunk):
            j = idx[i:i + chunk]
            rows = (val[:, i:i + chunk, :, None] * C[:, j.reshape(-1)].reshape(2, j.shape[0], K, U)).sum(-2)
            var.append(rows.pow(2).sum(-1))
        return mean, torch.cat(var, -1)
