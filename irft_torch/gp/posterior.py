"""Posterior marginals of the maps and the forces (``Posterior``), and how the front door forms them
from a backend: the forces of contacts with rows out of contact skipped (``_force_posterior``) and
the root of a positive semi-definite covariance for joint draws (``_psd_root``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rft.contacts import Contacts
from .backends import RFTBackend
from .hyper.mixture import mixture_covariance, mixture_moments, mixture_quantile

__all__ = ["Posterior"]


@dataclass
class Posterior:
    """Posterior marginals of K maps or force axes: ``mean`` and ``variance`` of the same shape (..., K), axis order
    (x, z) for the planar model (K = 2), (x, y, z) for the 3-D one (K = 3, ``gp.inverse3d``); there also
    ``covariance`` (..., K, K), each point's axes jointly (None where the axes are independent: the planar model).

    Averaged over hyperparameter draws (``InverseRFT(..., hyper_posterior="laplace")``) each marginal is a
    Gaussian mixture: ``mean``, ``variance`` (and ``covariance``) are its moments, ``components`` holds the
    draws' own means and variances (S, ..., K) and their weights (S,), and ``interval`` inverts the mixture's
    CDF (``gp.hyper.mixture``)."""

    mean: Tensor
    variance: Tensor
    components: tuple[Tensor, Tensor, Tensor] | None = None
    covariance: Tensor | None = None

    @property
    def stddev(self) -> Tensor:
        return self.variance.clamp_min(0).sqrt()

    def interval(self, level: float = 0.95) -> tuple[Tensor, Tensor]:
        """Central credible interval (lower, upper) of the marginals at ``level`` in (0, 1)."""
        return marginal_interval(self.mean, self.stddev, self.components, level)

    def to(self, *args, **kwargs) -> Posterior:
        """The same posterior with every tensor moved as ``Tensor.to(*args, **kwargs)`` moves it (a
        device, a dtype or both): ``model.stress_map(b, g).to("cpu")`` for plotting a GPU model's map."""
        comp = None
        if self.components is not None:
            means, variances, weights = self.components
            comp = (means.to(*args, **kwargs), variances.to(*args, **kwargs), weights.to(*args, **kwargs))
        cov = None if self.covariance is None else self.covariance.to(*args, **kwargs)
        return Posterior(self.mean.to(*args, **kwargs), self.variance.to(*args, **kwargs), comp, cov)

    def reshape(self, *shape: int) -> Posterior:
        """The points reshaped to ``shape`` (the axis dimension kept)."""
        K = self.mean.shape[-1]
        comp = None
        if self.components is not None:
            m, v, w = self.components
            comp = (m.reshape(m.shape[0], *shape, K), v.reshape(v.shape[0], *shape, K), w)
        cov = None if self.covariance is None else self.covariance.reshape(*shape, K, K)
        return Posterior(self.mean.reshape(*shape, K), self.variance.reshape(*shape, K), comp, cov)

    @classmethod
    def mixture(cls, means: Tensor, variances: Tensor, weights: Tensor) -> Posterior:
        """The mixture over draws: ``means``, ``variances`` (S, ..., 2), ``weights`` (S,); one draw is a
        plain Gaussian posterior (the same numbers, no components)."""
        if means.shape[0] == 1:
            return cls(means[0], variances[0])
        mean, var = mixture_moments(means, variances, weights)
        return cls(mean, var, (means, variances, weights))

    @classmethod
    def of_covariances(cls, means: Tensor, covariances: Tensor, weights: Tensor | None) -> Posterior:
        """The mixture over draws of ``means`` (S, ..., K) and each point's axes' ``covariances`` (S, ..., K, K) with
        ``weights`` (S,) (None: one plug-in draw, a plain Gaussian): ``covariance`` kept (the 3-D model's)."""
        if weights is None or means.shape[0] == 1:
            cov = covariances[0]
            return cls(means[0], torch.diagonal(cov, dim1=-2, dim2=-1).clone(), None, cov)
        mean, cov = mixture_covariance(means, covariances, weights)
        variances = torch.diagonal(covariances, dim1=-2, dim2=-1)
        return cls(mean, torch.diagonal(cov, dim1=-2, dim2=-1).clone(), (means, variances, weights), cov)


def _psd_root(cov: Tensor) -> Tensor:
    """L (..., N, N) with L L^T = cov for a positive semi-definite covariance (a smooth kernel's is
    rank-deficient on many points): Cholesky with a jitter of 1e-12, then 1e-10, of the largest
    variance (draws off by at most that), else the exact root from the eigendecomposition."""
    cov = 0.5 * (cov + cov.mT)
    top = cov.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(torch.finfo(cov.dtype).tiny)[..., None, None]
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    for rel in (1e-12, 1e-10):
        L, info = torch.linalg.cholesky_ex(cov + rel * top * eye)
        if not bool(info.any()):
            return L
    lam, V = torch.linalg.eigh(cov)
    return V * lam.clamp_min(0).sqrt()[..., None, :]


def _predict_chunk(backend: RFTBackend) -> int:
    """Rows of contacts predicted at a time: a backend's query costs memory in proportion to the rows
    times its training samples (a cross-covariance) or features, so 2^24 / T rows (256 to 8192) keep
    each piece to a few hundred MB whatever the number of rows asked for (T = 10^6: 1.2 GB in all
    instead of 10.7 GB at once)."""
    return max(256, min(8192, 2**24 // max(1, int(getattr(backend, "n_samples", 1)))))


def _force_posterior(backend: RFTBackend, flat: Contacts, rows: Tensor, variance: str,
                     chunk: int | None = None) -> tuple[Tensor, Tensor]:
    """Mean and variance (2, N) of the forces of contacts (N, M) from one backend; rows with no segment
    in contact (``rows`` False) have force exactly 0, mean and variance. With ``chunk``, the rows are
    predicted ``chunk`` at a time (the same numbers, bounded memory)."""
    N = flat.shape[0]
    if chunk is not None and N > chunk:
        parts = [_force_posterior(backend, flat[i:i + chunk], rows[i:i + chunk], variance) for i in range(0, N, chunk)]
        return torch.cat([p[0] for p in parts], -1), torch.cat([p[1] for p in parts], -1)
    mean = flat.beta.new_zeros(2, N)
    var = flat.beta.new_zeros(2, N)
    if rows.any():
        sub = flat[rows]
        post = backend.posterior(sub, variance=(variance == "exact"))
        v_sub = post.variance
        if variance == "independent":
            act = (sub.weight_x != 0) | (sub.weight_z != 0)
            b, g = sub.beta[act], sub.gamma[act]
            ones = torch.ones_like(b)[:, None]
            seg_var = backend.posterior(Contacts(b[:, None], g[:, None], ones, ones)).variance
            w2 = torch.stack([sub.weight_x[act], sub.weight_z[act]]).pow(2)  # (2, n_active)
            per_seg = torch.zeros(2, *sub.shape, dtype=w2.dtype, device=w2.device)
            per_seg = per_seg.masked_scatter(act.expand(2, *act.shape), w2 * seg_var)
            v_sub = per_seg.sum(-1)
        mean = mean.masked_scatter(rows.expand(2, N), post.mean)
        var = var.masked_scatter(rows.expand(2, N), v_sub)
    return mean, var


def _maps_from(backends: list[RFTBackend], counts: list[list[int]], c: Contacts, generator) -> Tensor:
    """Maps (2, N, n) drawn jointly over the N points of ``c``: ``counts[a][s]`` of map a's n draws from
    backend s (its posterior mean plus its root times normals), the order shuffled across backends."""
    out: list[list[Tensor]] = [[], []]
    for s, b in enumerate(backends):
        k = max(counts[0][s], counts[1][s])
        if k == 0:
            continue
        root = b.posterior_root(c)
        post = b.posterior(c, variance=False, covariance=root is None)
        if root is None:
            root = _psd_root(post.covariance)  # (2, N, N)
        eps = torch.randn(2, root.shape[-1], k, generator=generator, dtype=root.dtype, device=root.device)
        maps = post.mean[..., None] + root @ eps  # (2, N, k)
        for a in range(2):
            out[a].append(maps[a, :, :counts[a][s]])
    draws = torch.stack([torch.cat(o, -1) for o in out])  # (2, N, n)
    if sum(1 for k in counts[0] if k) > 1 or sum(1 for k in counts[1] if k) > 1:
        # interleave the backends' maps (each backend's block is otherwise contiguous)
        n = draws.shape[-1]
        draws = torch.stack([draws[a][:, torch.randperm(n, generator=generator, device=draws.device)]
                             for a in range(2)])
    return draws


def _mixture_maps(backends: list[RFTBackend], weights: Tensor | None, n: int, c: Contacts, generator) -> Tensor:
    """``n`` joint draws (2, N, n) of the maps at point contacts c (N, 1) from the mixture over ``backends`` with
    ``weights``: None (one backend), (S,) (hyperparameter draws: how many maps each supplies, picked by
    ``generator``) or (S, 2) (models averaged per map: each map's draws picked on its own)."""
    with torch.no_grad():
        if weights is None:
            return _maps_from(backends, [[n], [n]], c, generator)
        if weights.ndim == 1:
            pick = torch.multinomial(weights, n, replacement=True, generator=generator)
            counts = torch.bincount(pick, minlength=len(backends)).tolist()
            return _maps_from(backends, [counts, counts], c, generator)
        per_map = [torch.bincount(torch.multinomial(weights[:, a], n, replacement=True, generator=generator),
                                  minlength=len(backends)).tolist() for a in range(2)]
        return _maps_from(backends, per_map, c, generator)


def _check_level(level: float) -> None:
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")


def marginal_interval(mean: Tensor, stddev: Tensor, components: tuple[Tensor, Tensor, Tensor] | None,
                      level: float) -> tuple[Tensor, Tensor]:
    """Central interval (lower, upper) at ``level`` of each marginal: Gaussian (``normal_interval``), or, with
    ``components`` = (means, variances, weights) of a mixture over hyperparameter draws, the mixture CDF's
    quantiles (``gp.hyper.mixture``). What ``Posterior.interval`` and the 3-D posterior's ``interval`` return."""
    _check_level(level)
    if components is not None:
        means, variances, weights = components
        return (mixture_quantile(0.5 - level / 2, means, variances, weights),
                mixture_quantile(0.5 + level / 2, means, variances, weights))
    return normal_interval(mean, stddev, level)


def normal_interval(mean: Tensor, stddev: Tensor, level: float) -> tuple[Tensor, Tensor]:
    """Central interval (lower, upper) of independent Gaussian marginals at ``level`` in (0, 1):
    mean -+ sqrt(2) erfinv(level) stddev (what ``Posterior.interval`` and the 3-D posterior use)."""
    _check_level(level)
    z = math.sqrt(2) * torch.special.erfinv(torch.tensor(level, dtype=torch.float64)).item()
    return mean - z * stddev, mean + z * stddev
