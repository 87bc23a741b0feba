"""InverseRFT: infer the stress maps alpha_x, alpha_z from composite force observations."""

from __future__ import annotations

import contextlib
import math
import warnings
from dataclasses import dataclass

import gpytorch
import torch
from gpytorch.constraints import GreaterThan
from gpytorch.distributions import MultivariateNormal
from gpytorch.mlls import ExactMarginalLogLikelihood
from linear_operator.utils.errors import NotPSDError
from torch import Tensor, nn
from tqdm.auto import tqdm

from ..rft.contacts import Contacts
from ..rft.stress_maps import mirror_to_canonical
from .encoding import encode_contacts
from .grid import AngleGrid, GridRFT
from .kernels import AngleRBFKernel, RFTCompositeKernel
from .likelihoods import ForceNoiseLikelihood
from .means import GenericShapeMean

__all__ = ["Posterior", "CompositeExactGP", "InverseRFT"]


@dataclass
class Posterior:
    """Posterior marginals: ``mean`` and ``variance`` of the same shape (..., 2), axis order (x, z)."""

    mean: Tensor
    variance: Tensor

    @property
    def stddev(self) -> Tensor:
        return self.variance.clamp_min(0).sqrt()

    def interval(self, level: float = 0.95) -> tuple[Tensor, Tensor]:
        """Central credible interval of the marginals."""
        z = math.sqrt(2) * torch.special.erfinv(torch.tensor(level, dtype=torch.float64)).item()
        return self.mean - z * self.stddev, self.mean + z * self.stddev


class CompositeExactGP(gpytorch.models.ExactGP):
    """A batch of two exact GPs (x and z maps) observed through RFT-weighted sums.

    Inputs are composite rows (2, T, 3M) (see ``gp.encoding``), targets the forces (2, T).
    """

    def __init__(self, train_inputs: Tensor, train_targets: Tensor, likelihood: ForceNoiseLikelihood,
                 mean_module: gpytorch.means.Mean, covar_module: RFTCompositeKernel) -> None:
        super().__init__(train_inputs, train_targets, likelihood)
        self.mean_module = mean_module
        self.covar_module = covar_module

    def forward(self, x: Tensor) -> MultivariateNormal:
        return MultivariateNormal(self.mean_module(x), self.covar_module(x))


def _as_forces(forces, T: int, dtype, device) -> Tensor:
    f = torch.as_tensor(forces, dtype=dtype, device=device)
    if f.ndim != 2 or f.shape[-1] != 2:
        raise ValueError(f"forces must be (T, 2) = (F_x, F_z) in N, got shape {tuple(f.shape)}")
    if f.shape[0] != T:
        raise ValueError(f"forces has {f.shape[0]} samples but contacts has {T} time steps")
    bad = ~torch.isfinite(f)
    if bad.any():
        i = int(bad.any(-1).nonzero()[0])
        raise ValueError(f"forces contains NaN or inf (first at sample {i}); mask or drop those samples")
    return f


def _as_noise_scale(noise_scale, T: int, dtype, device) -> Tensor:
    """(T, 2) relative noise standard deviations; ones when ``noise_scale`` is None."""
    if noise_scale is None:
        return torch.ones(T, 2, dtype=dtype, device=device)
    s = torch.as_tensor(noise_scale, dtype=dtype, device=device)
    if s.ndim == 1 and s.shape[0] == T:
        s = s[:, None].expand(T, 2)
    if s.shape != (T, 2):
        raise ValueError(f"noise_scale must be (T,) or (T, 2) with T = {T}, got shape {tuple(s.shape)}")
    if not (torch.isfinite(s).all() and (s > 0).all()):
        raise ValueError("noise_scale must be positive and finite (a relative noise standard deviation per sample)")
    return s.contiguous()


def _whiten(c: Contacts, f: Tensor, s: Tensor) -> tuple[Contacts, Tensor]:
    """Divide each composite observation (its force and its segment weights) by its noise scale:
    F_t / s_t = sum_m (w_tm / s_t) alpha(theta_tm) + eps_t, eps_t ~ N(0, sigma^2), exactly."""
    return Contacts(c.beta, c.gamma, c.weight_x / s[:, :1], c.weight_z / s[:, 1:]), f / s


class InverseRFT(nn.Module):
    r"""Inverse RFT (Liu, Xue et al.): GP posteriors of alpha_x(beta, gamma), alpha_z(beta, gamma)
    from forces F_c[t] = sum_m w_c[t, m] alpha_c(theta[t, m]) + noise.

    Holds a real ``gpytorch.models.ExactGP`` (``.gp``, a batch of two GPs for x and z) whose
    kernel returns the lazy ``W K W^T`` and a ``ForceNoiseLikelihood`` (``.likelihood``); both work
    with gpytorch's own ``ExactMarginalLogLikelihood``.

    Args:
        contacts: training ``Contacts`` (T, M) (canonical angles, weights in cm^3).
        forces: (T, 2) measured (F_x, F_z) in N.
        prior_mean: "zero" (the paper) or "physics" (generic Li et al. shape x learned scales).
        tied_noise: one noise variance for both axes (the paper) instead of one per axis.
        dtype: inference dtype (float64 by default; float32 works).
        solver: "cholesky" (exact, the default) or "gpytorch" (use gpytorch's own settings, e.g.
            CG/Lanczos above ``gpytorch.settings.max_cholesky_size``).
        method: "exact" (gpytorch ExactGP, the lazy W K W^T), "grid" (the maps on a grid_size
            (beta, gamma) grid with bilinear interpolation: cost per step independent of the number of
            samples), or "auto": grid once more than ``exact_max_segments`` segment samples touch
            the ground (a long recording never runs out of memory).
        lengthscale: initial lengthscale of every embedding dimension. Where the data never vary an
            angle (an I-toe samples beta = 0 only) the likelihood cannot move it, so it sets how far
            the map extrapolates.
        noise_scale: (T,) or (T, 2) positive relative noise standard deviations per sample (and
            axis): the noise of sample t has variance ``noise * noise_scale[t]**2``. For noise
            proportional to the force (e.g. a current sensor's gain error), pass
            ``sqrt(forces**2 + floor**2)``. Applied exactly by whitening each observation (its force
            and weights divided by its scale), so every path (exact, grid, streaming) supports it;
            ``train_contacts`` and ``train_forces`` hold the whitened data. Default: homoscedastic.

    Example:
        >>> model = InverseRFT(contacts, forces)
        >>> model.fit(n_iter=300, lr=0.05)
        >>> post = model.stress_map(beta, gamma)        # .mean, .variance: (..., 2) in N/cm^3
        >>> pred = model.predict_forces(new_contacts)   # .mean, .variance: (T', 2) in N
    """

    def __init__(self, contacts: Contacts, forces, *, prior_mean: str = "zero", tied_noise: bool = False,
                 dtype: torch.dtype = torch.float64, solver: str = "cholesky",
                 lengthscale: float = 1.0, method: str = "auto", grid_size: tuple[int, int] = (32, 32),
                 exact_max_segments: int = 6_000, noise_scale=None) -> None:
        super().__init__()
        if not isinstance(contacts, Contacts):
            raise TypeError(f"contacts must be an irft_torch.rft.Contacts, got {type(contacts).__name__}")
        if contacts.beta.ndim != 2:
            raise ValueError(f"contacts must be (T, M) for training, got {tuple(contacts.shape)}")
        if prior_mean not in ("zero", "physics"):
            raise ValueError(f"prior_mean must be 'zero' or 'physics', got {prior_mean!r}")
        if not (math.isfinite(lengthscale) and lengthscale > 0.05):
            raise ValueError(f"lengthscale must be a finite value > 0.05, got {lengthscale}")
        if method not in ("auto", "exact", "grid"):
            raise ValueError(f"method must be 'auto', 'exact' or 'grid', got {method!r}")
        if solver not in ("cholesky", "gpytorch"):
            raise ValueError(f"solver must be 'cholesky' or 'gpytorch', got {solver!r}")
        T = len(contacts)
        if T < 2:
            raise ValueError(f"need at least 2 force observations, got {T}")
        device = contacts.beta.device
        c = contacts.to(dtype=dtype, device=device)
        f = _as_forces(forces, T, dtype, device)
        self.noise_scale = _as_noise_scale(noise_scale, T, dtype, device)
        c, f = _whiten(c, f, self.noise_scale)
        for axis, w in (("weight_x", c.weight_x), ("weight_z", c.weight_z)):
            if not (w != 0).any():
                raise ValueError(f"contacts.{axis} is zero everywhere: no segment is in contact, nothing to learn")
        self.prior_mean_kind, self.solver, self.dtype = prior_mean, solver, dtype
        self.init_lengthscale = float(lengthscale)
        self.train_contacts, self.train_forces = c, f
        self.n_segments = c.n_segments
        x, y = encode_contacts(c), f.T.contiguous()

        # Data-scaled initial values and bounds (forces in N, maps in N/cm^3).
        s = torch.stack([c.weight_x.abs().sum(-1), c.weight_z.abs().sum(-1)])  # (2, T)
        power = y.pow(2).mean(-1)
        rel_floor = 1e-8 if dtype == torch.float64 else 1e-5
        noise_floor = max(float(power.min()) * rel_floor, 1e-12)
        n_segments = int(((c.weight_x != 0) | (c.weight_z != 0)).sum())
        if method == "auto":
            method = "grid" if n_segments > exact_max_segments else "exact"
        self.method = method
        if method == "exact":
            self.likelihood = ForceNoiseLikelihood(tied=tied_noise, noise_constraint=GreaterThan(noise_floor))
            base = AngleRBFKernel(batch_shape=torch.Size([2]))
            kernel = RFTCompositeKernel(base)
            mean = (GenericShapeMean() if prior_mean == "physics"
                    else gpytorch.means.ZeroMean(batch_shape=torch.Size([2])))
            self.gp = CompositeExactGP(x, y, self.likelihood, mean, kernel)
            self.grid_model = None
        else:
            self.gp = None
            self.grid_model = GridRFT(AngleGrid(*grid_size), tied_noise=tied_noise, noise_floor=noise_floor,
                                      dtype=dtype, physics_mean=(prior_mean == "physics"))
            self.likelihood = self.grid_model.likelihood
            base = self.grid_model.kernel
            mean = self.grid_model.mean_module
        self.to(device=device, dtype=dtype)
        with torch.no_grad():
            resid = y
            if prior_mean == "physics":
                g = mean.shape_map.to(dtype)(c.beta, c.gamma)
                shape_f = torch.stack([(c.weight_x * g[..., 0]).sum(-1), (c.weight_z * g[..., 1]).sum(-1)])
                scales = ((y * shape_f).sum(-1) / shape_f.pow(2).sum(-1).clamp_min(1e-300)).clamp_min(1e-3)
                mean.scales = scales
                resid = y - scales[:, None] * shape_f
            base.outputscale = (resid.pow(2).mean(-1) / s.pow(2).mean(-1).clamp_min(1e-300)).clamp_min(1e-6)
            base.lengthscale = torch.full((2, 1, 4), float(lengthscale), dtype=dtype)
            self.likelihood.noise = (1e-2 * power).clamp_min(noise_floor * 10)
        self._appended: list = []
        if self.grid_model is not None:
            self.grid_model.set_data(c, f)
        self.loss_history: list[float] = []
        self.eval()

    # ---- convenience views ---------------------------------------------------------------
    @property
    def kernel(self) -> AngleRBFKernel:
        """The angle kernel holding the hyperparameters (lengthscale (2, 1, 4), outputscale (2,))."""
        return self.grid_model.kernel if self.gp is None else self.gp.covar_module.base_kernel

    @property
    def mean_module(self):
        return self.grid_model.mean_module if self.gp is None else self.gp.mean_module

    def hyperparameters(self) -> dict[str, list]:
        """Current hyperparameters, readable (lengthscales per embedding dim, variances). ``noise`` is
        the force noise variance per axis in N^2 (with ``noise_scale``, that of a sample of scale 1)."""
        out = {
            "lengthscale_x": self.kernel.lengthscale[0, 0].tolist(),
            "lengthscale_z": self.kernel.lengthscale[1, 0].tolist(),
            "outputscale": self.kernel.outputscale.tolist(),
            "noise": self.likelihood.noise.tolist(),
        }
        if self.prior_mean_kind == "physics":
            out["mean_scales"] = self.mean_module.scales.tolist()
        return out

    def _settings(self):
        stack = contextlib.ExitStack()
        if self.solver == "cholesky":
            stack.enter_context(gpytorch.settings.max_cholesky_size(2**31))
        return stack

    # ---- training ------------------------------------------------------------------------
    def mll(self) -> ExactMarginalLogLikelihood:
        """gpytorch's exact marginal log likelihood of this model (exact path only)."""
        if self.gp is None:
            raise RuntimeError("the grid path has no gpytorch ExactGP; use model.loss()")
        return ExactMarginalLogLikelihood(self.likelihood, self.gp)

    def loss(self) -> Tensor:
        """Negative log marginal likelihood per force sample, summed over the two axes."""
        if self.gp is None:
            return -self.grid_model.log_marginal_likelihood().sum()
        self.train()
        with self._settings():
            out = self.gp(*self.gp.train_inputs)
            return -self.mll()(out, self.gp.train_targets).sum()

    def fit(self, n_iter: int = 300, lr: float = 0.05, progress: bool = True) -> list[float]:
        """Adam on the exact marginal likelihood. Returns the loss per step (the negative log
        likelihood per force sample, summed over the two axes). Ctrl-C stops early and keeps
        what was learned."""
        if int(n_iter) < 0 or not math.isfinite(lr) or lr <= 0:
            raise ValueError(f"need n_iter >= 0 and lr > 0, got n_iter={n_iter}, lr={lr}")
        self.train()
        params = self.gp.parameters() if self.gp is not None else self.grid_model.parameters()
        opt = torch.optim.Adam(params, lr=lr)
        history: list[float] = []
        bar = tqdm(range(int(n_iter)), desc=f"I-RFT fit ({self.method})", disable=not progress, leave=False)
        step = 0
        try:
            for step in bar:
                opt.zero_grad(set_to_none=True)
                loss = self.loss()
                loss.backward()
                opt.step()
                history.append(loss.item())
                if progress:
                    bar.set_postfix(loss=f"{history[-1]:.4g}")
        except KeyboardInterrupt:
            warnings.warn(f"fit interrupted after {len(history)} steps; the model keeps those steps",
                          stacklevel=2)
        except (NotPSDError, torch.linalg.LinAlgError) as e:
            raise NotPSDError(
                f"the force covariance W K W^T + noise is not positive definite even with gpytorch's jitter "
                f"(step {step}); hyperparameters then: {self.hyperparameters()}. Try a lower lr, a larger noise "
                f"floor, or float64."
            ) from e
        finally:
            bar.close()
            self.eval()
            if self.grid_model is not None:
                self.grid_model._cache = None
        self.loss_history.extend(history)
        return history

    def add_data(self, contacts: Contacts, forces, noise_scale=None) -> InverseRFT:
        """Streaming: add force samples with the hyperparameters fixed (no refit). On the grid path
        this only adds to the sufficient statistics; the posterior equals a batch fit's.
        ``noise_scale``: as in the constructor, for the new samples."""
        if not isinstance(contacts, Contacts) or contacts.beta.ndim != 2:
            raise ValueError("contacts must be a Contacts of shape (T, M)")
        device = self.train_forces.device
        c = contacts.to(dtype=self.dtype, device=device)
        f = _as_forces(forces, len(c), self.dtype, device)
        scale = _as_noise_scale(noise_scale, len(c), self.dtype, device)
        c, f = _whiten(c, f, scale)
        self.noise_scale = torch.cat([self.noise_scale, scale])
        if self.grid_model is not None:
            self.grid_model.add_data(c, f)
            self._appended.append((c, f))
            return self
        self.train_contacts = Contacts.cat([self.train_contacts, c])
        self.train_forces = torch.cat([self.train_forces, f])
        M = max(self.n_segments, c.n_segments)
        self.n_segments = M
        self.gp.set_train_data(inputs=encode_contacts(self.train_contacts, M),
                               targets=self.train_forces.T.contiguous(), strict=False)
        return self

    # ---- prediction ----------------------------------------------------------------------
    def _ensure_width(self, M: int) -> None:
        """Widen the training rows with zero-weight padding so test rows with M segments fit."""
        if self.gp is not None and M > self.n_segments:
            self.gp.set_train_data(inputs=encode_contacts(self.train_contacts, M), strict=False)
            self.n_segments = M

    def _predict_rows(self, rows: Tensor, variance: bool = True, chunk: int = 4096) -> tuple[Tensor, Tensor | None]:
        """Exact path: posterior of composite rows (2, N, 3M): mean (2, N), variance (2, N) or None."""
        self.eval()
        grad = rows.requires_grad
        means, variances = [], []
        ctx = contextlib.nullcontext() if grad else torch.no_grad()
        with ctx, self._settings(), gpytorch.settings.skip_posterior_variances(not variance), \
                warnings.catch_warnings():
            warnings.simplefilter("ignore", gpytorch.utils.warnings.GPInputWarning)
            for i in range(0, rows.shape[-2], chunk):
                try:
                    out = self.gp(rows[..., i:i + chunk, :])
                except NotPSDError as e:
                    raise NotPSDError(f"training covariance not positive definite; hyperparameters: "
                                      f"{self.hyperparameters()}") from e
                means.append(out.mean)
                if variance:
                    variances.append(out.variance)
        return torch.cat(means, -1), (torch.cat(variances, -1) if variance else None)

    def _posterior_of(self, c: Contacts, variance: bool = True) -> tuple[Tensor, Tensor | None]:
        """Posterior of the weighted sums of contacts c (N, M): mean, variance (2, N)."""
        if self.gp is not None:
            self._ensure_width(c.n_segments)
            return self._predict_rows(encode_contacts(c, self.n_segments), variance)
        gm = self.grid_model
        idx, w = gm.grid.interpolation(c.beta, c.gamma)  # (N, M, 4)
        N = idx.shape[0]
        val = torch.stack([(c.weight_x[..., None] * w).reshape(N, -1), (c.weight_z[..., None] * w).reshape(N, -1)])
        prior = None
        if gm.mean_module is not None:
            a = gm.mean_module.shape_map(c.beta, c.gamma)
            prior = gm.mean_module.scales[:, None] * torch.stack(
                [(c.weight_x * a[..., 0]).sum(-1), (c.weight_z * a[..., 1]).sum(-1)])
        return gm.predict_rows(idx.reshape(N, -1), val, variance, prior)

    def _points(self, beta, gamma) -> tuple[Contacts, torch.Size]:
        beta = torch.as_tensor(beta, dtype=self.dtype, device=self.train_forces.device)
        gamma = torch.as_tensor(gamma, dtype=self.dtype, device=self.train_forces.device)
        beta, gamma = torch.broadcast_tensors(beta, gamma)
        for name, v in (("beta", beta), ("gamma", gamma)):
            if not torch.isfinite(v).all():
                raise ValueError(f"{name} contains NaN or inf")
        bc, gc, sx = mirror_to_canonical(beta.reshape(-1), gamma.reshape(-1))
        return Contacts(bc[:, None], gc[:, None], sx[:, None], torch.ones_like(bc)[:, None]), beta.shape

    def stress_map(self, beta, gamma) -> Posterior:
        """Posterior of (alpha_x, alpha_z) at angles of any broadcast shape S (rad).

        Angles outside the canonical square are mapped in by the mirror identity. Returns mean and
        variance of shape S + (2,), in N/cm^3 and (N/cm^3)^2 (paper eqs. for mu and sigma^2).
        """
        pts, S = self._points(beta, gamma)
        mean, var = self._posterior_of(pts)
        return Posterior(mean.T.reshape(*S, 2), var.T.reshape(*S, 2))

    def forward(self, beta: Tensor, gamma: Tensor) -> Tensor:
        """Posterior mean map (..., 2): a fitted model is a stress map (``rft.forces(model, c)``)."""
        pts, S = self._points(beta, gamma)
        mean, _ = self._posterior_of(pts, variance=False)
        return mean.T.reshape(*S, 2)

    def predict_forces(self, contacts: Contacts, variance: str = "exact", include_noise: bool = False,
                       noise_scale=None) -> Posterior:
        """Posterior of the forces (F_x, F_z) for contacts of shape (..., T, M).

        Args:
            variance: "exact" (w^T Sigma w, segments correlated) or "independent" (the paper's
                sum_m w_m^2 sigma^2(theta_m)).
            include_noise: add the learned observation noise (predict a measurement).
            noise_scale: with ``include_noise``, the new samples' relative noise scales (..., T) or
                (..., T, 2), as in the constructor (default 1).

        Returns:
            Posterior with mean and variance (..., T, 2) in N and N^2. Differentiable in the
            contact angles and weights.
        """
        if not isinstance(contacts, Contacts):
            raise TypeError(f"contacts must be a Contacts, got {type(contacts).__name__}")
        if variance not in ("exact", "independent"):
            raise ValueError(f"variance must be 'exact' or 'independent', got {variance!r}")
        c = contacts.to(dtype=self.dtype, device=self.train_forces.device)
        lead, M = c.shape[:-1], c.n_segments
        flat = Contacts(*(v.reshape(-1, M) for v in c.as_dict().values()))
        # Rows with no segment in contact have force exactly 0 (mean and variance): skip them.
        touching = ((flat.weight_x != 0) | (flat.weight_z != 0)).any(-1)
        N = flat.shape[0]
        mean = flat.beta.new_zeros(2, N)
        var = flat.beta.new_zeros(2, N)
        if touching.any():
            sub = flat[touching]
            m_sub, v_sub = self._posterior_of(sub, variance=(variance == "exact"))
            if variance == "independent":
                act = (sub.weight_x != 0) | (sub.weight_z != 0)
                b, g = sub.beta[act], sub.gamma[act]
                ones = torch.ones_like(b)[:, None]
                _, seg_var = self._posterior_of(Contacts(b[:, None], g[:, None], ones, ones))
                w2 = torch.stack([sub.weight_x[act], sub.weight_z[act]]).pow(2)  # (2, n_active)
                per_seg = torch.zeros(2, *sub.shape, dtype=w2.dtype, device=w2.device)
                per_seg = per_seg.masked_scatter(act.expand(2, *act.shape), w2 * seg_var)
                v_sub = per_seg.sum(-1)
            mean = mean.masked_scatter(touching.expand(2, N), m_sub)
            var = var.masked_scatter(touching.expand(2, N), v_sub)
        var = var.T.reshape(*lead, 2)
        if include_noise:
            scale = torch.ones((), dtype=var.dtype, device=var.device) if noise_scale is None else \
                torch.as_tensor(noise_scale, dtype=var.dtype, device=var.device)
            if scale.ndim == len(lead):
                scale = scale[..., None]
            if not (torch.isfinite(scale).all() and (scale > 0).all()):
                raise ValueError("noise_scale must be positive and finite")
            var = var + self.likelihood.noise * scale.pow(2)
        return Posterior(mean.T.reshape(*lead, 2), var)

    # ---- persistence ---------------------------------------------------------------------
    def save(self, path) -> None:
        """Write training data, options and the state dict to one file (torch.save)."""
        contacts, forces = self.train_contacts, self.train_forces
        if self._appended:  # grid path: samples streamed in after construction
            contacts = Contacts.cat([contacts] + [c for c, _ in self._appended])
            forces = torch.cat([forces] + [f for _, f in self._appended])
        s = self.noise_scale  # undo the whitening: the file holds the measured forces
        contacts = Contacts(contacts.beta, contacts.gamma, contacts.weight_x * s[:, :1], contacts.weight_z * s[:, 1:])
        torch.save({
            "contacts": {k: v.cpu() for k, v in contacts.as_dict().items()},
            "forces": (forces * s).cpu(),
            "noise_scale": s.cpu(),
            "options": {"prior_mean": self.prior_mean_kind, "tied_noise": self.likelihood.tied,
                        "lengthscale": self.init_lengthscale, "method": self.method,
                        "grid_size": (self.grid_model.grid.n_beta, self.grid_model.grid.n_gamma)
                        if self.grid_model is not None else (32, 32),
                        "solver": self.solver, "dtype": str(self.dtype).replace("torch.", "")},
            "state_dict": self.state_dict(),
            "loss_history": self.loss_history,
        }, path)

    @classmethod
    def load(cls, path, map_location=None) -> InverseRFT:
        """Rebuild a model written by ``save``."""
        d = torch.load(path, map_location=map_location, weights_only=True)
        opts = dict(d["options"])
        opts["dtype"] = getattr(torch, opts["dtype"])
        model = cls(Contacts(**d["contacts"]), d["forces"], noise_scale=d.get("noise_scale"), **opts)
        model.load_state_dict(d["state_dict"])
        model.loss_history = list(d.get("loss_history", []))
        return model

    def extra_repr(self) -> str:
        return (f"T={len(self.train_contacts)}, M={self.n_segments}, prior_mean={self.prior_mean_kind!r}, "
                f"method={self.method!r}")
