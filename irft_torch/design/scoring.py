r"""Score a candidate probe (toe + path) by what it would teach, before running it.

A GP's posterior covariance does not depend on the measured values, so the information a probe
would bring follows from its contacts alone. For a candidate with contacts c (T_c rows), per map
axis a in (x, z), let S_a be the current posterior covariance of its forces (T_c x T_c, segments
correlated: w^T Sigma w) and sigma_a^2 the force noise. Then

    EIG = sum_a 1/2 log | I + S_a / sigma_a^2 |            (nats: the mutual information between
                                                            the maps and the probe's forces)
    IV  = sum_a sum_j r_j [ v_a(theta_j) - k_aj^T (S_a + sigma_a^2 I)^-1 k_aj ] / s_a
                                                           (the expected integrated variance of the
                                                            maps over a region after the probe)

with v_a(theta_j) the current map variance at the region's points theta_j, k_aj the posterior
covariance between the map there and the probe's forces, r_j the region's weights (summing to 1)
and s_a the prior variance, so IV is 2 for the prior and 0 for maps known exactly.

Every posterior number comes from the belief's backend (``candidate_rows``, ``region_rows``,
``posterior_root``, ``condition``: a planar or a 3-D one, ``ProbeScorer3D``), as botorch's
``qNegIntegratedPosteriorVariance`` sits on a model's ``posterior`` and ``fantasize``; the scorer factors only
each candidate's own small matrix (S_a + sigma_a^2 I, or its F x F Woodbury form). Heteroscedastic noise: a
candidate's samples are whitened by their ``noise_scale`` exactly as ``InverseRFT`` whitens training samples.

Example:
    >>> scorer = ProbeScorer.from_model(model)              # or ProbeScorer.prior(...)
    >>> scores = scorer.score([p.contacts() for p in probes], criterion="variance")
    >>> steps = greedy_design(scorer, probes, budget=3)    # a hyperparameter posterior: a MixtureScorer
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, cast

import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor

from ..gp.backends import RFTBackend, make_backend
from ..gp.backends.base import split_blocks
from ..gp.backends.observations import PriorBackend
from ..gp.backends.select import ALIASES
from ..gp.hyper.mixture import mixture_moments
from ..gp.kernels.hyperparameters import RFTHyperparameters
from ..rft.contacts import Contacts
from .belief import BeliefScorer, FollowingScorer, check_criterion, information_nats, variance_after
from .force_noise import force_relative
from .region import Region, _as_contacts

if TYPE_CHECKING:
    from ..gp.backends.spectral import SpectralBackend

__all__ = ["Region", "ProbeScorer", "ProbeScorer3D", "MixtureScorer", "force_relative", "SCORING_TOL"]


NoiseScale = Callable[[Contacts], Tensor] | Tensor | None
SCORING_TOL = 1e-4  # kernel truncation error a spectral model's scorer is sized for by default (ranking, not a fit)
SCORE_ROWS = 2_000  # candidate force samples scored at once (best measured: 1,000-2,000; memory B T^2 + N T per axis)


# ---- the scorer --------------------------------------------------------------------------------
class ProbeScorer(FollowingScorer):
    """The current belief over alpha_x, alpha_z (a backend with fixed hyperparameters), to score many
    candidate probes.

    Build it with ``ProbeScorer.from_model(model)`` (a fitted ``InverseRFT``) or
    ``ProbeScorer.prior(...)`` (nothing measured yet). Candidates are ``Contacts`` (T, M) or
    ``rft.Probe``s. Scores are differentiable in the candidates' contact tensors.

    Args:
        backend: the belief.
        noise_scale: relative noise standard deviation of a candidate's samples, as ``InverseRFT``'s
            ``noise_scale``: None (1), or a function of the candidate's raw (not whitened) contacts
            returning (T,) or (T, 2) (e.g. from the predicted force: see ``force_relative``).

    Attributes:
        method: the backend's name.
        outputscale: (2,) the RBF kernel's variances s_a of the maps, (N/cm^3)^2.
        prior_variance: (2,) the maps' prior variances, (N/cm^3)^2: s_a, plus Li et al.'s v_a where the model
            has that term (``kernel="li"``), plus u_a times the generic shape's mean square over the square
            with ``kernel="li+generic"``. The integrated variances over a region are divided by the prior's mean
            over that region (this, but for the generic shape's part, which varies with the angles).
        noise: (2,) force noise variances sigma_a^2 of a sample of scale 1, N^2.
    """

    def __init__(self, backend: RFTBackend, noise_scale: NoiseScale = None) -> None:
        super().__init__(backend)
        self.noise_scale = noise_scale
        self._regions: dict[int, tuple[Region, object, Tensor]] = {}
        self._square: Region | None = None

    @staticmethod
    def _derive(model, method: str | None, tol, own: RFTBackend | None = None) -> RFTBackend:
        """The backend a scorer of ``model`` uses (see ``from_model``), from the model's current one (or from
        ``own``, one of its hyperparameter draws' backends, on the model's data)."""
        own = model.backend if own is None else own
        own_tol = cast("SpectralBackend", own).tol if own.name == "spectral" else float(getattr(model, "tol", 1e-7))
        target = "spectral" if isinstance(tol, float) else ALIASES.get(method or own.name, method or own.name)
        if tol == "auto":
            tol = max(own_tol, SCORING_TOL)
        elif tol is None:
            tol = own_tol
        if target == own.name and (target != "spectral" or tol == own.tol):
            return own
        # a spectral model's statistics serve any basis they cover (a coarser one: no pass over the data)
        stats = own.stats if own.name == "spectral" else None
        return make_backend(target, own.hypers, model.train_contacts, model.train_forces, tol=tol, statistics=stats)

    # ---- construction ----------------------------------------------------------------------
    @classmethod
    def from_model(cls, model, method: str | None = None, noise_scale: NoiseScale = None,
                   grid_size=None, tol: float | str | None = "auto") -> ProbeScorer | MixtureScorer | ProbeScorer3D:
        """The posterior of a (fitted) ``InverseRFT``, with its hyperparameters fixed.

        Args:
            method: None (the model's own backend) or a backend to rebuild on the model's data with
                its hyperparameters: "observations" (alias "exact"), "pairs", "spectral" (alias
                "grid"), "auto".
            noise_scale: as the constructor's. A model fitted with a ``noise_scale`` scores with unit
                scale (and warns) unless one is given.
            tol: the kernel truncation error of the spectral basis, wherever the scores are computed
                in one (the model's backend is spectral, or ``method="spectral"``).
                "auto" (default): ``SCORING_TOL`` = 1e-4 of the kernel variance (or the model's
                own tolerance, if coarser). Ranking candidates does not need the fit's 1e-7: at 1e-4
                the basis has about 40 % of the features (11 x 11 instead of 17 x 17 harmonics at
                T = 1,000) and scoring is 2.5-3.5x faster, the scores within 2 % of the model's basis
                and ranked the same (``experiments/benchmarks/bench_active_probing.py`` prints both; a test checks
                the choice and the order). Cut from a spectral model's statistics: no pass over the data.
                None: the model's own tolerance (a spectral model: its own backend and basis, exactly).
                A float: a spectral basis sized for this truncation error (``method`` becomes
                "spectral"). The bound reached is ``scorer.backend.truncation_error()``.

        A model with a hyperparameter posterior (``InverseRFT(..., hyper_posterior="laplace")``) gives a
        ``design.MixtureScorer``: every score is the weighted average of the scores at its draws.

        The scorer follows the model: after ``model.add_data`` or a refit (which may grow the basis or
        move to another backend) it scores the model's current belief, derived the same way. Its
        current map variance (``map_variance``, ``integrated_variance()``) is that of its own basis,
        within the truncation error of the model's (6e-4 relative at 1e-4 in one check).
        """
        from ..gp.inverse3d import InverseRFT3D

        if isinstance(model, InverseRFT3D):  # a 3-D model: ProbeScorer3D (its own backends), over any draws
            if method is not None or noise_scale is not None or tol != "auto":
                raise ValueError("a 3-D model is scored in its own backend: method, noise_scale and tol do not apply")
            if model._weighted_backends()[1] is not None:
                return MixtureScorer.from_model(model)
            return ProbeScorer3D.from_model(model)
        if grid_size is not None:
            warnings.warn("grid_size belongs to the retired grid belief and is ignored", FutureWarning, stacklevel=2)
        if method == "grid":
            method = "spectral"
        if method is not None and method not in ("auto", "exact", "observations", "pairs", "spectral"):
            raise ValueError(f"method must be None, 'auto', 'observations', 'pairs' or 'spectral', got {method!r}")
        if isinstance(tol, str) and tol != "auto":
            raise ValueError(f"tol must be 'auto', None or a float in (0, 1), got {tol!r}")
        if tol is not None and not isinstance(tol, str):
            if not (0 < tol < 1):
                raise ValueError(f"tol must be in (0, 1), got {tol}")
            if method not in (None, "spectral"):
                raise ValueError(f"tol= sizes a spectral basis: method must be None or 'spectral', got {method!r}")
            tol = float(tol)
        noise_scale = cls._model_noise_scale(model, noise_scale)
        if model._weighted_backends()[1] is not None:  # hyperparameter draws or averaged means: average over them
            return MixtureScorer.from_model(model, method, noise_scale, tol)
        out = cls(cls._derive(model, method, tol), noise_scale)
        out._recipe, out._derived_from = (model, method, tol), cls._state_of(model.backend)
        return out

    @staticmethod
    def _model_noise_scale(model, noise_scale: NoiseScale) -> NoiseScale:
        if noise_scale is None and not torch.all(model.noise_scale == 1):
            warnings.warn("the model was fitted with a noise_scale; candidates are scored with unit noise scale "
                          "unless ProbeScorer gets noise_scale=", stacklevel=3)
        return noise_scale

    @classmethod
    def prior(cls, lengthscale=1.0, outputscale=0.1, noise=0.01, method: str = "exact", dtype=torch.float64,
              noise_scale: NoiseScale = None, grid_size=None) -> ProbeScorer:
        """The prior: nothing measured yet.

        Args:
            lengthscale: of every embedding dimension, a float or a (2, 1, 4) tensor (as the model's).
            outputscale: prior variance of the maps, (N/cm^3)^2, a float or (2,) for (x, z).
            noise: force noise variance, N^2, a float or (2,).
            method: "exact" (the lazy W K W^T; conditioning gives an observations backend) or
                "spectral" (a Fourier basis; faster for many candidates). "grid" is read as "spectral".
        """
        if grid_size is not None:
            warnings.warn("grid_size belongs to the retired grid belief and is ignored", FutureWarning, stacklevel=2)
        if method == "grid":
            method = "spectral"
        if method not in ("exact", "observations", "spectral"):
            raise ValueError(f"method must be 'exact' or 'spectral', got {method!r}")
        ls = torch.as_tensor(lengthscale, dtype=dtype).expand(2, 1, 4).clone()
        os = torch.as_tensor(outputscale, dtype=dtype).expand(2).clone()
        nz = torch.as_tensor(noise, dtype=dtype).expand(2).clone()
        for name, v in (("lengthscale", ls), ("outputscale", os), ("noise", nz)):
            if not (torch.isfinite(v).all() and (v > 0).all()):
                raise ValueError(f"{name} must be positive and finite, got {v.tolist()}")
        hypers = RFTHyperparameters(noise_floor=float(nz.min()) * 1e-3).to(dtype)
        with torch.no_grad():
            hypers.lengthscale, hypers.outputscale, hypers.noise = ls, os, nz
        if method == "spectral":
            empty = Contacts(*(torch.zeros(0, 1, dtype=dtype) for _ in range(4)))
            return cls(make_backend("spectral", hypers, empty, torch.zeros(0, 2, dtype=dtype)), noise_scale)
        return cls(PriorBackend(hypers), noise_scale)

    # ---- candidates --------------------------------------------------------------------------------
    def _cast(self, c) -> Contacts:
        """The candidate on the belief's dtype and device, whitened by its noise scale."""
        c = _as_contacts(c, self.three_d).to(dtype=self.noise.dtype, device=self.noise.device)
        if self.three_d or self.noise_scale is None:
            return c
        s = self.noise_scale(c) if callable(self.noise_scale) else self.noise_scale
        s = torch.as_tensor(s, dtype=c.beta.dtype, device=c.beta.device)
        if s.ndim == 1:
            s = s[:, None].expand(len(c), 2)
        if s.shape != (len(c), 2) or not (torch.isfinite(s).all() and (s > 0).all()):
            raise ValueError(f"noise_scale must give positive finite (T,) or (T, 2) scales for T = {len(c)}, "
                             f"got shape {tuple(s.shape)}")
        return Contacts(c.beta, c.gamma, c.weight_x / s[:, :1], c.weight_z / s[:, 1:])

    @property
    def three_d(self) -> bool:
        """Whether the belief is a 3-D model's (``rft.Contacts3D`` candidates, 3 maps)."""
        return self.backend.contacts_type is not Contacts

    def covariance(self, contacts) -> Tensor:
        """Posterior covariance (2, T, T) of a candidate's (whitened) forces, noise not included, N^2."""
        return self.backend.posterior(self._cast(contacts), covariance=True).covariance

    def information_gain(self, contacts, per_axis: bool = False) -> Tensor:
        """EIG of observing the candidate's forces, nats: summed over the two maps (scalar), or
        ``per_axis`` (2,) = (alpha_x, alpha_z) (each map is seen only through its own force axis)."""
        eig = self._score_batch([self._cast(contacts)], "eig", None)[0]
        return eig if per_axis else eig.sum()

    def _belief_key(self) -> tuple:
        """What the cached region values depend on: the backend itself (a scorer following its model gets
        a new one when the model's is rebuilt, e.g. at a moved surface, with the same data count and
        hyperparameters), its data (its sample count grows with ``add_data``) and the hyperparameters (a
        refit moves them; they are shared with the model)."""
        backend = self.backend
        with torch.no_grad():
            return backend, backend.n_samples, torch.cat([p.detach().reshape(-1) for p in backend.hypers.parameters()])

    def _region(self, region: Region | None) -> tuple[Region, object, Tensor]:
        key = self._belief_key()
        old = self.__dict__.get("_cache_key")
        if (old is None or old[0] is not key[0] or old[1] != key[1]
                or not torch.equal(old[2], key[2])):  # the model moved: forget
            self._regions.clear()
            self.__dict__.pop("_omega", None)
            self._cache_key = key
        if region is None:
            self._square = self._square or Region.square(dtype=self.noise.dtype)
            region = self._square
        rid = id(region)  # the cache holds the region, so its id is not reused while cached
        if rid not in self._regions or self._regions[rid][0] is not region:
            with torch.no_grad():
                r = self.backend.region_rows(region)  # the maps at its points, as the backend's rows
                var = self.backend.region_variance(r)  # (2, N), or a 3-D model's blocks (2, 2N)
            self._regions[rid] = (region, r, var)
        return self._regions[rid]

    def integrated_variance(self, contacts=None, region: Region | None = None, per_axis: bool = False) -> Tensor:
        """Expected integrated map variance over ``region`` (default: the whole square) after
        observing the candidate (now, if None), each map's divided by its prior variance: summed over
        the two maps (scalar: 2 = the prior, 0 = known), or ``per_axis`` (2,) = (alpha_x, alpha_z)."""
        if contacts is None:
            region, _, var = self._region(region)
            iv = (self.backend.fold_maps(var) * region.weight.to(var)).sum(-1) / self._prior_over(region)
        else:
            iv = self._score_batch([self._cast(contacts)], "variance", region)[0]
        return iv if per_axis else iv.sum()

    def score(self, candidates: Sequence, criterion: str = "variance", region: Region | None = None,
              per_axis: bool = False) -> Tensor:
        """Scores (n,) of several candidates: the integrated variance after each ("variance", lower is
        better) or its information gain ("eig", nats, higher is better); ``per_axis``: (n, 2), per map (a 3-D
        model: (n, 3) per map for "variance", (n, 2) per block for "eig")."""
        check_criterion(criterion, region)
        cands = [self._cast(c) for c in candidates]
        if not cands:
            width = len(self.prior_variance) if criterion == "variance" else self.backend.n_blocks
            return torch.zeros((0, width) if per_axis else 0, dtype=self.noise.dtype, device=self.noise.device)
        # Batches of candidates of similar length (shortest first, so that padding to the longest wastes
        # little), each at most SCORE_ROWS rows and SCORE_ROWS^2 / 10 padded block entries: one covariance
        # product and one Cholesky per batch.
        order = sorted(range(len(cands)), key=lambda i: len(cands[i]))
        scores: list = [None] * len(cands)
        chunk: list[int] = []
        rows = 0
        for i in order + [None]:
            n = 0 if i is None else len(cands[i])  # the longest so far: the candidates come sorted
            if chunk and (i is None or rows + n > SCORE_ROWS or (len(chunk) + 1) * n**2 > SCORE_ROWS**2 // 10):
                for j, v in zip(chunk, self._score_batch([cands[j] for j in chunk], criterion, region)):
                    scores[j] = v if per_axis else v.sum()
                chunk, rows = [], 0
            if i is not None:
                chunk.append(i)
                rows += n
        return torch.stack(scores)

    def _score_batch(self, cands: list[Contacts], criterion: str, region: Region | None) -> Tensor:
        """The scores (B, K) per map ("variance"; per block, "eig": the same for a planar model) of candidates
        already cast, at once: every candidate's own posterior covariance (``backend.candidate_rows``), zero-padded
        to the longest (a padded row is a noise-only observation of nothing: it adds 0 to the information gain
        and to the variance reduction)."""
        sizes = [len(c) for c in cands]
        F = self.backend.root_size()
        if F is not None and F < max(sizes):
            return self._score_root_batch(self.backend.posterior_root(Contacts.cat(cands)), sizes, criterion, region)
        if criterion == "eig":
            S, noise, _ = self.backend.candidate_rows(cands)  # (B, 2, n, n)
            return information_nats(S, noise)
        region, rows, var = self._region(region)
        S, noise, cross = self.backend.candidate_rows(cands, rows)
        after = self.backend.fold_maps(variance_after(var, cross, S, noise))  # (B, K, N)
        return (after * region.weight.to(var)).sum(-1) / self._prior_over(region)

    def _score_root_batch(self, Z: Tensor, sizes: list[int], criterion: str, region: Region | None) -> Tensor:
        """The same scores in the root's F dimensions (fewer than a candidate's samples): with Z_i (T_i, F)
        the candidate's rows of the posterior root and L L^T = I + Z_i^T Z_i / noise,
        EIG = sum log diag L, and the region's variance after it is tr(Omega (L L^T)^{-1}), Omega =
        Z_r^T diag(w) Z_r (Woodbury: no T x T matrix, no subtraction)."""
        F = Z.shape[-1]
        Zb = split_blocks(Z, sizes)  # (B, 2, T, F)
        gram = Zb.mT @ Zb  # (B, 2, F, F)
        eye = torch.eye(F, dtype=Z.dtype, device=Z.device)
        L = psd_safe_cholesky(eye + 0.5 * (gram + gram.mT) / self.noise[:, None, None])
        if criterion == "eig":
            return torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
        omega = self._region_omega(region)  # (2, F, F)
        return (omega * torch.cholesky_inverse(L)).sum((-1, -2)) / self._prior_over(self._region(region)[0])

    def _prior_over(self, region: Region) -> Tensor:
        """(2,) the maps' prior variance averaged over ``region`` with its weights, (N/cm^3)^2: ``prior_variance``
        (uniform) but with the generic shape (``kernel="li+generic"``), whose part u g(theta)^2 varies."""
        h = self.backend.hypers
        if h.li is None or not h.li.generic:
            return self.prior_variance
        w = region.weight.to(self.noise)
        pv = h.prior_variance_at(region.beta.to(w), region.gamma.to(w)).detach()  # (N, 2)
        return (pv * w[:, None]).sum(0)

    def _region_omega(self, region: Region | None) -> Tensor:
        """Z_r^T diag(w) Z_r (2, F, F) of the region's points, cached with the region and the root."""
        region, rc, _ = self._region(region)
        cache = self.__dict__.setdefault("_omega", {})  # one Omega per region (``_region`` empties it)
        hit = cache.get(id(region))
        if hit is None or hit[0] is not region:
            Zr = self.backend.posterior_root(rc)
            w = region.weight.to(Zr)
            hit = cache[id(region)] = (region, Zr.mT @ (w[:, None] * Zr))
        return hit[1]

    def condition(self, contacts) -> ProbeScorer:
        """The belief after observing the candidate's forces (whatever their values): a new scorer;
        this one and the model are unchanged."""
        with torch.no_grad():
            return type(self)(self.backend.condition(self._cast(contacts)), self.noise_scale)

    def map_variance(self, beta, gamma) -> Tensor:
        """Current posterior variance of the maps ((alpha_x, alpha_z); a 3-D model's (alpha_x, alpha_y, alpha_z)) at
        angles of broadcast shape S: S + (K,)."""
        S = torch.broadcast_shapes(torch.as_tensor(beta).shape, torch.as_tensor(gamma).shape)
        with torch.no_grad():
            _, var = self.backend.map_moments(beta, gamma)
        return var.reshape(*S, var.shape[-1])


class ProbeScorer3D(ProbeScorer):
    r"""A 3-D model's belief over alpha_x, alpha_y, alpha_z (a ``gp.inverse3d.Backend3D`` at fixed hyperparameters),
    scoring ``rft.Contacts3D`` candidates: a ``ProbeScorer`` on the 3-D backend, whose ``information_gain`` is per
    block (``per_block``) and ``integrated_variance`` per map (``per_map``, 3 maps).

    The force covariance is two independent blocks (docs/inverse3d.md): horizontal, rows (F_x; F_y) seeing alpha_x
    and alpha_y, and vertical, rows F_z seeing alpha_z (the planar model: two one-map blocks). With S_b the
    candidate's block-b rows' posterior covariance (2T x 2T, T x T) and D_b their noise variances,
    EIG = sum_b 1/2 log |I + D_b^{-1/2} S_b D_b^{-1/2}| (nats), and IV = sum_c (the region's weighted variance of map
    c after the candidate) / s_c (s_c its prior variance, Li et al.'s term included): 3 for the prior, 0 for maps
    known exactly (``design.belief``; the backend gives S, the region's rows and their covariances,
    ``Backend3D.candidate_rows``). A 3-D model with a hyperparameter posterior gives a ``MixtureScorer`` of these
    from ``ProbeScorer.from_model``; ``ProbeScorer3D.from_model`` scores at the fitted hyperparameters alone. Scores
    are not differentiable in the candidates (no gradient-based 3-D design yet).

    Attributes:
        outputscale: (3,) the kernel's variances s_c of (alpha_x, alpha_y, alpha_z), (N/cm^3)^2.
        prior_variance: (3,) the maps' prior variances (s_c, plus Li et al.'s v_c with ``kernel="li"``).
        noise: (3,) force-noise variances of (F_x, F_y, F_z), N^2.
    """

    def __init__(self, backend, noise_scale: NoiseScale = None) -> None:
        from ..gp.inverse3d import Backend3D

        if not isinstance(backend, Backend3D):
            raise TypeError(f"backend must be a gp.inverse3d.Backend3D, got {type(backend).__name__}")
        if noise_scale is not None:  # (also the former ProbeScorer3D(backend, model))
            raise TypeError("ProbeScorer3D(backend) takes no model and no noise_scale (a 3-D model is scored with "
                            "unit noise scale; ProbeScorer3D.from_model(model) follows a model)")
        super().__init__(cast(RFTBackend, backend))  # the same questions answered (``Backend3D.candidate_rows``)

    @classmethod
    def from_model(cls, model) -> ProbeScorer3D:  # type: ignore[override]
        """The posterior of a (fitted) ``InverseRFT3D`` at its fitted hyperparameters; the scorer follows the model
        (``add_data``, a refit). Over a hyperparameter posterior's draws: ``ProbeScorer.from_model``."""
        from ..gp.inverse3d import InverseRFT3D

        if not isinstance(model, InverseRFT3D):
            raise TypeError(f"model must be an InverseRFT3D (a planar InverseRFT: design.ProbeScorer), got "
                            f"{type(model).__name__}")
        out = cls(model.backend)
        out._recipe, out._derived_from = (model, None, None), cls._state_of(model.backend)
        return out

    @staticmethod
    def _derive(model, method, tol, own=None):
        return model.backend if own is None else own  # a 3-D model is scored in its own backend

    def covariance(self, contacts) -> list[Tensor]:  # type: ignore[override]
        """Posterior covariances of a candidate's force rows, noise not included, N^2: [(2T, 2T) rows (F_x; F_y),
        (T, T) rows F_z]."""
        S, _, _ = self.backend.candidate_rows([self._cast(contacts)])
        T = len(contacts)
        return [S[0, 0, :2 * T, :2 * T], S[0, 1, :T, :T]]

    def information_gain(self, contacts, per_block: bool = False) -> Tensor:
        """EIG of observing the candidate's three force axes, nats: a scalar, or ``per_block`` (2,) = (horizontal,
        vertical)."""
        return super().information_gain(contacts, per_block)

    def integrated_variance(self, contacts=None, region: Region | None = None, per_map: bool = False) -> Tensor:
        """Expected integrated map variance over ``region`` (default the whole square, 16 x 16) after the candidate
        (now, if None), each map's divided by its prior variance: a scalar (3 = the prior, 0 = known), or
        ``per_map`` (3,) = (alpha_x, alpha_y, alpha_z)."""
        return super().integrated_variance(contacts, region, per_map)


# ---- averaged over a hyperparameter posterior ------------------------------------------------
class MixtureScorer(BeliefScorer):
    """Probe scores averaged over a hyperparameter posterior: one ``ProbeScorer`` per draw theta_s of a model
    fitted with ``hyper_posterior="laplace"`` (or ``"nuts"``), weights w_s, and

        EIG = sum_s w_s EIG(c | theta_s),    IV = sum_s w_s IV(c | theta_s),

    as botorch averages an acquisition function over a fully Bayesian GP's draws. Neither adds the
    information a probe carries about the hyperparameters themselves (BALD's extra term).

    It answers what a ``ProbeScorer`` answers (``score``, ``rank``, ``information_gain``,
    ``integrated_variance``, ``condition``, ``map_variance``, ``covariance``), so ``greedy_design`` and
    ``optimize_probe`` take it as they take a ``ProbeScorer``. A 3-D model's draws are ``ProbeScorer3D``s (their
    per-axis scores: 3 maps for the variance, 2 blocks for the information gain).

    Args:
        scorers: one ``ProbeScorer`` (or ``ProbeScorer3D``) per draw.
        weights: (S,) non-negative, summing to 1 (a planar model's also (S, 2), per map).
    """

    def __init__(self, scorers: Sequence, weights) -> None:
        scorers = list(scorers)
        if not scorers:
            raise ValueError("a MixtureScorer needs at least one scorer")
        w = torch.as_tensor(weights, dtype=scorers[0].noise.dtype, device=scorers[0].noise.device)
        w = w.reshape(-1) if w.ndim < 2 else w
        if (w.shape[0] != len(scorers) or w.ndim > 2 or (w.ndim == 2 and w.shape[1] != 2)
                or not torch.isfinite(w).all() or (w < 0).any() or (w.sum(0) <= 0).any()):
            raise ValueError(f"weights must be {len(scorers)} non-negative finite numbers (or {len(scorers)} x 2, per "
                             f"map) with a positive sum, got shape {tuple(w.shape)}: {w.tolist()}")
        if w.ndim == 2 and scorers[0].three_d:
            raise ValueError("weights per map (S x 2) are for a planar model's two maps; a 3-D model's draws take one "
                             "weight each (S,)")
        self.scorers, self.weights = scorers, w / w.sum(0)
        self._recipe: tuple | None = None  # (model, method, noise_scale, tol) of ``from_model``
        self._draws_of: tuple | None = None  # the model's draws the scorers were built for (``_state``)

    @classmethod
    def from_model(cls, model, method: str | None = None, noise_scale: NoiseScale = None,
                   tol: float | str | None = "auto") -> MixtureScorer:
        """One ``ProbeScorer`` per draw of ``model``'s hyperparameter posterior, each derived from that
        draw's backend as ``ProbeScorer.from_model`` derives from a plug-in model's (``method``, ``tol``).
        The scorer follows the model: when its draws change (a refit, ``add_data``) it is built again."""
        out = cls(*cls._build(model, method, noise_scale, tol))
        out._recipe, out._draws_of = (model, method, noise_scale, tol), cls._state(model)
        return out

    @staticmethod
    def _build(model, method, noise_scale, tol) -> tuple[list, Tensor]:
        """One scorer per backend the model predicts with (a ``ProbeScorer``, or a ``ProbeScorer3D`` for a 3-D
        model) and their weights."""
        from ..gp.inverse3d import InverseRFT3D

        backends, weights = model._weighted_backends()
        if isinstance(model, InverseRFT3D):
            scorers: list = [ProbeScorer3D(b) for b in backends]
        else:
            scorers = [ProbeScorer(ProbeScorer._derive(model, method, tol, own=b), noise_scale) for b in backends]
        return scorers, weights if weights is not None else torch.ones(1, device=scorers[0].noise.device)

    @staticmethod
    def _state(model) -> tuple:
        draws = getattr(model, "_draw_backends", None)
        return (id(draws), None if draws is None else tuple(b.n_samples for b in draws))

    def _current(self) -> list:
        if self._recipe is not None and self._state(self._recipe[0]) != self._draws_of:
            self.scorers, w = self._build(*self._recipe)
            self.weights = w.to(self.scorers[0].noise) / w.sum(0)
            self._draws_of = self._state(self._recipe[0])
        return self.scorers

    def _per_map(self) -> Tensor:
        """(S, 2) the draws' weights per map (one weight for both maps where they are not per map)."""
        return self.weights[:, None].expand(-1, 2) if self.weights.ndim == 1 else self.weights

    def _average(self, values: list[Tensor], per_axis: bool = True) -> Tensor:
        """The weighted average of per-map values (..., K) (with weights per map, (S, 2): each map its own); with
        ``per_axis`` False the average is summed over the last dimension."""
        w = (self.weights if self.weights.ndim == 1 else self._per_map()).to(values[0])
        out = sum(wi * v for wi, v in zip(w, values))
        return out if per_axis else out.sum(-1)

    # ---- what a ProbeScorer answers ---------------------------------------------------------------
    @property
    def method(self) -> str:
        return self._current()[0].method

    @property
    def noise(self) -> Tensor:
        """(K,) the draws' force noise variances, weighted mean per axis, N^2."""
        return self._average([s.noise for s in self._current()])

    @property
    def outputscale(self) -> Tensor:
        """(K,) the draws' RBF variances, weighted mean per map, (N/cm^3)^2."""
        return self._average([s.outputscale for s in self._current()])

    @property
    def prior_variance(self) -> Tensor:
        """(K,) the draws' prior map variances (with Li et al.'s term, if any), weighted mean per map, (N/cm^3)^2."""
        return self._average([s.prior_variance for s in self._current()])

    @property
    def n_draws(self) -> int:
        return len(self._current())

    @property
    def three_d(self) -> bool:
        """Whether the draws are a 3-D model's (``ProbeScorer3D``s: ``rft.Contacts3D`` candidates, 3 maps)."""
        return self._current()[0].three_d

    def covariance(self, contacts):
        """The draws' posterior covariances of the candidate's forces, weighted mean per axis, N^2 (the spread of
        the draws' means is not included: scores depend on the covariances only): (2, T, T), or for a 3-D model
        its blocks [(2T, 2T) rows (F_x; F_y), (T, T) rows F_z]."""
        covs = [s.covariance(contacts) for s in self._current()]
        if isinstance(covs[0], list):  # 3-D: one weight per draw
            w3 = self.weights.to(covs[0][0])
            return [sum(wi * c[b] for wi, c in zip(w3, covs)) for b in range(len(covs[0]))]
        w = self._per_map().to(covs[0])
        return sum(wi[:, None, None] * v for wi, v in zip(w, covs))

    def information_gain(self, contacts, per_axis: bool = False) -> Tensor:
        """Expected information gain averaged over the draws, nats (scalar, or (2,) per map; a 3-D model's per
        block)."""
        return self._average([s.information_gain(contacts, True) for s in self._current()], per_axis)

    def integrated_variance(self, contacts=None, region: Region | None = None, per_axis: bool = False) -> Tensor:
        """Expected integrated map variance after the candidate (now, if None), averaged over the draws
        (each draw's map variance divided by its own prior variance: 2 = the prior (3 in 3-D), 0 = known;
        ``per_axis``: per map)."""
        return self._average([s.integrated_variance(contacts, region, True) for s in self._current()], per_axis)

    def score(self, candidates: Sequence, criterion: str = "variance", region: Region | None = None,
              per_axis: bool = False) -> Tensor:
        """Scores (n,) averaged over the draws (see ``ProbeScorer.score``); ``per_axis``: (n, 2) (a 3-D model's
        variance: (n, 3), per map)."""
        candidates = list(candidates)
        return self._average([s.score(candidates, criterion, region, per_axis=True) for s in self._current()],
                             per_axis)

    def condition(self, contacts) -> MixtureScorer:
        """The belief after the candidate's forces (whatever their values) under every draw, same weights
        (values unseen: nothing to reweight the draws by); this scorer and the model are unchanged."""
        return MixtureScorer([s.condition(contacts) for s in self._current()], self.weights)

    def map_variance(self, beta, gamma) -> Tensor:
        """Current posterior variance of the maps ((alpha_x, alpha_z), or a 3-D model's (alpha_x, alpha_y,
        alpha_z)) at angles of broadcast shape S: the mixture's total variance (the draws' variances and the
        spread of their means, ``gp.hyper.mixture.mixture_moments``), S + (K,)."""
        scorers = self._current()
        S = torch.broadcast_shapes(torch.as_tensor(beta).shape, torch.as_tensor(gamma).shape)
        with torch.no_grad():
            moments = [s.backend.map_moments(beta, gamma) for s in scorers]  # (N, K) each
        means, variances = torch.stack([m for m, _ in moments]), torch.stack([v for _, v in moments])  # (S, N, K)
        _, var = mixture_moments(means, variances, self.weights)  # weights (S,) or (S, 2) per map
        return var.reshape(*S, means.shape[-1])

