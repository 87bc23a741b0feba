"""InverseRFT: infer the stress maps alpha_x, alpha_z from composite force observations.

A thin front door in the way botorch's ``SingleTaskGP`` sits on gpytorch parts: it checks and
whitens the data, sets data-scaled initial hyperparameters (``RFTHyperparameters``), picks a
backend (``gp.backends``) and delegates every computation to it.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import torch
from torch import Tensor, nn

from ..rft.contacts import Contacts, check_locations
from .backends import RFTBackend, make_backend
from .backends.base import touching
from .backends.spatial import SpatialBackend
from .fit_control import FitControl, FitDivergedWarning, FitInterruptedWarning
from .hyper.posterior import HyperPosterior, add_data_to_draws
from .hyper.predictions import HyperMixtureMixin
from .inputs import (
    _as_forces,
    _as_noise_scale,
    _check_angles,
    _check_dtype,
    _check_options,
    _check_query,
    _check_statistics,
    _check_units,
    _noise_scale,
    _whiten,
    initial_hyperparameters,
)
from .kernels.priors import (
    CentreSums,
    centres_of_sums,
    prior_centres,
    register_physical_priors,
    register_spatial_priors,
    residual_terms,
    spatial_lengthscale_centre,
)
from .mean_average import MeanAverage, fit_companion, stream_into_average, weigh_means
from .model_file import load_state, model_options, refresh_digest, save_model, without_backend
from .options import Engine, MapPrior, planar_options
from .posterior import Posterior, _force_posterior, _mixture_maps, _predict_chunk
from .spatial import check_spatial_options, placed_contacts, placed_queries
from .surface.offset import SurfaceOffset, init_surface, surface_estimate, surface_loss

__all__ = ["Posterior", "InverseRFT", "FitDivergedWarning", "FitInterruptedWarning"]  # the warnings: fit_control


class InverseRFT(HyperMixtureMixin, nn.Module):
    r"""Inverse RFT (Liu, Xue et al.): GP posteriors of alpha_x(beta, gamma), alpha_z(beta, gamma)
    from forces F_c[t] = sum_m w_c[t, m] alpha_c(theta[t, m]) + noise.

    Every computation goes to one backend (``.backend``), each exact for W K W^T + noise in its space:

    - ``"observations"`` (alias ``"exact"``): a gpytorch ExactGP whose kernel returns the lazy
      W K W^T (T x T); the reference, for few samples with many distinct angle pairs;
    - ``"pairs"``: the U distinct (beta, gamma) pairs of the data (a flat toe, a plate, a toe that
      does not turn): O(U^3) per step, whatever T;
    - ``"spectral"``: a Fourier basis on the angle torus sized so that the kernel's truncation error
      is below ``tol``: one pass over the data, then O(F^3) per step whatever T; streaming.

    ``"auto"`` (default) takes the cheapest (``gp.backends.estimated_costs``), exact ones when close.

    Four named choices, as botorch's ``SingleTaskGP`` takes a likelihood and modules: ``prior`` (what the maps are
    before the data, a ``MapPrior``), ``hyper_posterior`` (how sure), ``surface`` (the free surface) and ``engine``
    (how it is computed, an ``Engine``); each is held as resolved (``model.prior``, ``model.engine``) and the
    machinery one attribute away (``model.hypers``, ``model.backend``, ``model.hyper_posterior``, ``model.surface``).
    The former flat keywords (``li_basis=``, ``generic_shape=``, ``prior_mean=``, ``priors=``, ``tied_noise=``,
    ``lengthscale=``, ``method=``, ``tol=``, ``dtype=``, ``surface_offset=``, ``surface_groups=``) still
    work and raise a ``DeprecationWarning`` naming the new spelling (``gp.options``); removed in 0.4.

    Args:
        contacts: training ``Contacts`` (T, M) (canonical angles, weights in cm^3).
        forces: (T, 2) measured (F_x, F_z) in N, finite; each axis non-zero in some sample (ValueError
            otherwise: an axis that was not measured cannot be passed as zeros).
        locations: (T, 2) m, each sample's place on the ground: maps that vary over it (``gp.kernels.spatial``,
            docs/terrain.md); queries then take ``locations=`` too. None (default): one medium everywhere.
        prior: a ``MapPrior`` (``gp.options``): the kernel ("li", the default: the RBF plus Li et al.'s 9 functions
            as a term with its own variance per map; "rbf": the paper's, Table I / II; "li+generic": also the
            generic map with an uncertain scale), the prior mean ("zero", default; "physics"; "average"), the
            hyperparameter priors ("physical", default; None: the plain marginal likelihood), the noise
            ("per_axis", default; "tied") and the starting lengthscale. Each field's docstring says where it wins.
        hyper_posterior: "laplace" (default): after the fit, a posterior over the hyperparameters
            (``gp.hyper.posterior``, Laplace at the mode, importance-reweighted from a fixed point set: a refit
            predicts the same); predictions are mixtures over its draws (``model.hyper_posterior``). "map": the
            plug-in at the fitted hyperparameters (the paper's; ``TerrainFilter`` and streaming use it), about
            1.5x faster, overconfident on media unlike Li et al.'s generic one (docs/calibration.md). "nuts":
            pyro's NUTS, the reference. With a learned surface or ``MapPrior(hyperpriors=None)`` the default is
            "map" (the offset has its own Laplace std; without priors the posterior is improper).
        surface: learn the free surface's height with the maps (``gp.surface.offset``, docs/surface.md): True for
            one offset in m (positive: the surface is higher than stated), fitted by the marginal likelihood
            through the segment depths, ``model.surface_offset`` gives it with its Laplace std; or (T,) integers
            in [0, G), one offset per group (recording, trial). Needs contacts with ``depth``, ``area_x``,
            ``area_z`` (``rft.contacts``). None (default): the surface is where the contacts say.
        engine: an ``Engine`` (``gp.options``: method, tol, dtype) or just a method name: "auto"
            (default), "observations" (or "exact"), "pairs" or "spectral" (above).
        noise_scale: (T,) or (T, 2) positive relative noise standard deviations per sample (and axis): sample t's
            noise variance is ``noise * noise_scale[t]**2``, applied exactly by whitening each observation in every
            backend; ``train_contacts`` and ``train_forces`` hold the whitened data.
        statistics: spectral sufficient statistics of exactly these contacts and forces
            (``gp.statistics.recording_statistics``, e.g. saved with a dataset and summed over several): the
            spectral backend skips its pass over the data. Checked against the data's sample count and force power
            (ValueError if they differ); ignored by the other backends; not allowed with a ``noise_scale``.
    Example:
        >>> model = InverseRFT(contacts, forces)                       # the default: honest intervals
        >>> paper = InverseRFT(contacts, forces, prior=MapPrior(kernel="rbf"), hyper_posterior="map")
        >>> model.fit(n_iter=300, lr=0.05)
        >>> post = model.stress_map(beta, gamma)        # .mean, .variance: (..., 2) in N/cm^3
        >>> pred = model.predict_forces(new_contacts)   # .mean, .variance: (T', 2) in N
    """

    def __new__(cls, contacts=None, forces=None, *args, **kwargs):
        """``InverseRFT(contacts_3d, forces)`` with a ``rft.Contacts3D`` and (T, 3) forces builds the 3-D model,
        ``gp.inverse3d.InverseRFT3D`` (docs/inverse3d.md)."""
        from ..rft.contacts3d import Contacts3D

        if cls is InverseRFT and isinstance(contacts, Contacts3D):
            from .inverse3d import InverseRFT3D

            return InverseRFT3D(contacts, forces, *args, **kwargs)
        return super().__new__(cls)

    @classmethod
    def load(cls, path, map_location=None):
        """Rebuild a model written by ``save`` (``gp.model_file``); ``InverseRFT.load`` of a 3-D model's file
        gives the 3-D model, as ``InverseRFT(contacts_3d, forces)`` builds one."""
        from .inverse3d.model import FORMAT_3D, InverseRFT3D
        from .model_file import load_model

        return load_model(cls, path, map_location, {FORMAT_3D: InverseRFT3D._from_file} if cls is InverseRFT else None)

    def __init__(self, contacts: Contacts, forces, locations=None, *, prior: MapPrior | None = None,
                 hyper_posterior: str | None = None, surface=None, engine: Engine | str | None = None,
                 noise_scale=None, statistics=None, **deprecated) -> None:
        prior, engine, surface = planar_options(prior, engine, surface, deprecated, spatial=locations is not None or
                                                getattr(contacts, "locations", None) is not None)
        surface_offset, surface_groups = surface is not None, None if surface is None or surface is True else surface
        method, tol, dtype = engine.method, engine.tol, engine.dtype
        solver = deprecated.get("_solver", "cholesky")
        li_basis, generic_shape = prior.kernel in ("li", "li+generic"), prior.kernel == "li+generic"
        prior_mean, priors, tied_noise, lengthscale = prior.mean, prior.hyperpriors, prior.noise == "tied", \
            prior.lengthscale
        grid_size, exact_max_segments = deprecated.get("grid_size"), deprecated.get("exact_max_segments")
        super().__init__()
        self.prior = prior  # the choices as resolved (the planar defaults filled in; the engine's below)
        if not isinstance(contacts, Contacts):
            raise TypeError(f"contacts must be an irft_torch.rft.Contacts, got {type(contacts).__name__}")
        if contacts.beta.ndim != 2:
            raise ValueError(f"contacts must be (T, M) for training, got {tuple(contacts.shape)}")
        method, hyper_posterior = _check_options(prior_mean, priors, method, hyper_posterior, solver, lengthscale,
                                                 surface_offset or surface_groups is not None, tied_noise,
                                                 (li_basis, generic_shape),
                                                 grid_size is not None or exact_max_segments is not None)
        self.engine = replace(engine, method=method)  # with a retired method name resolved
        _check_dtype(dtype)
        T = len(contacts)
        if T < 2:
            raise ValueError(f"need at least 2 force observations, got {T}")
        device = contacts.beta.device
        c = contacts.to(dtype=dtype, device=device)
        if locations is not None:
            c = c.with_locations(check_locations(locations, T).to(device=device, dtype=dtype))
        spatial = c.locations is not None
        if spatial:
            check_spatial_options(method, prior_mean, surface_offset or surface_groups is not None, statistics)
        f = _as_forces(forces, T, dtype, device)
        scale = _as_noise_scale(noise_scale, T, dtype, device)
        _check_units(c, f)  # as measured (whitened by a small noise_scale they would look too large)
        c, f = _whiten(c, f, scale)
        for field, w in (("weight_x", c.weight_x), ("weight_z", c.weight_z)):
            if not (w != 0).any():
                raise ValueError(f"contacts.{field} is zero everywhere: no segment is in contact, nothing to learn")
        for axis, name in enumerate(("F_x", "F_z")):
            if not (f[:, axis] != 0).any():  # each map is learned in its forces' scale (_data_scales): none here
                raise ValueError(f"forces[:, {axis}] ({name}) is zero in every sample: no scale to learn that map in; "
                                 f"if {name} was not measured, zeros would claim the map is zero")
        self.surface = None
        if surface_offset or surface_groups is not None:
            self.surface = SurfaceOffset(c, surface_groups)
        self._method_arg = method
        self.prior_mean_kind, self.solver, self.dtype, self.tol = prior_mean, solver, dtype, float(tol)
        self.priors = priors
        self.hyper_method = hyper_posterior
        self.hyper_posterior: HyperPosterior | None = None  # set by fit (hyper_posterior != "map")
        self._draw_backends: list[RFTBackend] | None = None
        self._companion: list = []  # prior_mean="average": the physics-mean model (a list: not a submodule)
        self.mean_average: MeanAverage | None = None  # MapPrior(mean="average"): the weights (gp.mean_average)
        self.init_lengthscale = float(lengthscale)
        self._parts: list[tuple[Contacts, Tensor, Tensor]] = [(c, f, scale)]
        self._device = device
        self._joined: tuple[Contacts, Tensor, Tensor] | None = None

        self.hypers, map_scale = initial_hyperparameters(c, f, dtype, tied_noise, prior_mean, li_basis, generic_shape,
                                                         lengthscale, spatial)
        if priors == "physical":
            centres = self._register_priors(c, f)
            with torch.no_grad():  # start where the prior is (the data's guess can be a collapsed axis)
                self.hypers.outputscale = centres["outputscale"].to(dtype)
        if self.hypers.li is not None:  # Li et al.'s term at the RBF part's variance, the generic shape's at zeta^2
            self.hypers.start_li(prior_centres(c, f, map_scale)["zeta"])
        if spatial and priors == "physical":
            register_spatial_priors(self.hypers, spatial_lengthscale_centre(c.locations))
        self.auto = method == "auto" and not spatial
        if statistics is not None and self.surface is not None:
            raise ValueError("statistics are of the contacts at the stated surface: they cannot serve a model that "
                             "learns the surface (drop statistics or surface=...)")
        own_mean = "physics" if prior_mean == "physics" else "zero"  # "average": this model is the zero mean's
        self._statistics = _check_statistics(statistics, f, noise_scale, own_mean)
        self.backend: RFTBackend = SpatialBackend(self.hypers, c, f, solver) if spatial else \
            make_backend(method, self.hypers, c, f, solver=solver, tol=tol, statistics=self._statistics)
        self.register_buffer("data_digest", torch.zeros(32, dtype=torch.uint8, device=device), persistent=True)
        self._digest_stale = True  # computed when a state dict is taken or loaded (hashing is O(T M))
        self.loss_history: list[float] = []
        self.fit_control = FitControl()  # the fit's adaptation and guards (gp.fit_control)
        self.eval()

    # ---- views -------------------------------------------------------------------------------
    @property
    def method(self) -> str:
        """The backend in use: "observations", "pairs" or "spectral"."""
        return self.backend.name

    @property
    def spatial(self) -> bool:
        """Whether the maps change over the ground (fitted with ``locations``, ``gp.spatial``)."""
        return self.hypers.spatial is not None

    @property
    def kernel(self):
        """The angle kernel (a gpytorch ScaleKernel(RBFKernel)): lengthscale (2, 1, 4), outputscale (2,)."""
        return self.hypers.kernel

    @property
    def likelihood(self):
        """gpytorch's GaussianLikelihood of the force noise (N^2); ``hypers.noise`` gives it as (2,)."""
        return self.hypers.likelihood

    @property
    def mean_module(self):
        return self.hypers.mean

    @property
    def gp(self):
        """The gpytorch ExactGP (observations backend only)."""
        gp = getattr(self.backend, "gp", None)
        if gp is None:
            raise AttributeError(f"the {self.method!r} backend has no gpytorch ExactGP; use engine='observations'")
        return gp

    @property
    def n_segments(self) -> int:
        return self.train_contacts.n_segments

    def _register_priors(self, c: Contacts, f: Tensor, more: bool = False) -> dict:
        """Register the physical priors centred on the data (c, f) (whitened), or on all the data with ``more``
        from ``add_data`` (sums added: O(new samples)): a grown model has a batch model's objective."""
        physics = self.prior_mean_kind == "physics"
        sums = CentreSums.of(c, f)
        self._centre_sums: CentreSums = self._centre_sums + sums if more else sums
        centres = centres_of_sums(self._centre_sums, None, physics, residual=residual_terms(self.hypers))
        register_physical_priors(self.hypers, centres, physics, self.surface is not None)
        return centres

    def _join(self) -> tuple[Contacts, Tensor, Tensor]:
        if self._joined is None:
            if len(self._parts) > 1:
                cs, fs, ss = zip(*self._parts)
                self._parts = [(Contacts.cat(list(cs)), torch.cat(fs), torch.cat(ss))]
            self._joined = self._parts[0]
        return self._joined

    @property
    def train_contacts(self) -> Contacts:
        """The training contacts (T, M), whitened by ``noise_scale`` (with a learned surface offset: at
        the current offset)."""
        c = self._join()[0]
        return c if self.surface is None else self.surface.shifted(c, detach=True)

    @property
    def train_forces(self) -> Tensor:
        """The training forces (T, 2), whitened by ``noise_scale``."""
        return self._join()[1]

    @property
    def noise_scale(self) -> Tensor:
        """(T, 2) relative noise standard deviations of the training samples (ones by default)."""
        return self._join()[2]

    def _measured(self) -> tuple[Contacts, Tensor]:
        """The training data as measured (the whitening undone)."""
        c, f, s = self._join()
        return c.scale_weights(s[:, :1], s[:, 1:]), f * s

    def _options(self) -> dict:
        """The constructor options that shape this model beyond its data (``gp.model_file.model_options``)."""
        return model_options(self)

    @property
    def averages_means(self) -> bool:
        """Whether predictions average the zero and the physics prior mean (``MapPrior(mean="average")``)."""
        return self.prior_mean_kind == "average"

    @property
    def companion(self):
        """The physics-mean model averaged with this one (``MapPrior(mean="average")``, after ``fit``), or None."""
        return self._companion[0] if self._companion else None

    @property
    def surface_offset(self):
        """The learned surface offset(s) (``gp.surface.offset.SurfaceEstimate``): ``.mean``, ``.std`` (G,) in m
        (``.in_cm()`` for cm), positive when the surface is higher than stated; ``.interval(0.95)``.
        Laplace, from the loss's curvature in the offsets and the hyperparameters (computed on each access)."""
        if self.surface is None:
            raise AttributeError("this model has no learned surface offset (InverseRFT(..., surface=True))")
        return surface_estimate(self)

    def init_surface(self, offsets) -> Tensor:
        """Start the surface offset(s) at the best of ``offsets`` (m, a grid) by the loss at the current
        hyperparameters, one group at a time (the others held): the likelihood in the offset can have
        several local optima (docs/surface.md), and Adam from 0 stops at the nearest. Returns the start (G,) in m;
        ``stress_map`` and ``predict_forces`` are then at it."""
        return init_surface(self, offsets)

    def _rebuild_backend(self) -> None:
        """The surface moved: the backend again, on the contacts at the current offset."""
        self.backend = make_backend(self._method_arg, self.hypers, self.train_contacts, self.train_forces,
                                    solver=self.solver, tol=self.tol)
        self.fit_control.forget_data()

    # ---- state and file ------------------------------------------------------------------------
    def state_dict(self, *args, **kwargs):
        """The hyperparameters and the training data's digest. The backend's own entries (the same
        hyperparameters again, and gpytorch's) are left out: which backend ``auto`` ends on is not part
        of a model's state."""
        refresh_digest(self)
        return without_backend(super().state_dict(*args, **kwargs))

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As ``nn.Module.load_state_dict``; with ``strict`` (default) a state from a model fitted on
        other data is refused (its ``data_digest`` differs). ``strict=False`` loads the
        hyperparameters alone (a warm start on new data)."""
        return load_state(self, state_dict, strict)

    def save(self, path) -> None:
        """Write training data, options, the hyperparameters and a checksum to one file (format 2,
        ``gp.model_file``): ``load`` refuses files that are damaged, foreign or of another version."""
        save_model(self, path)

    def hyperparameters(self) -> dict[str, list]:
        """Current hyperparameters, readable (lengthscales per embedding dim, variances). ``noise`` is
        the force noise variance per axis in N^2 (with ``noise_scale``, that of a sample of scale 1)."""
        return self.hypers.as_dict()

    def truncation_error(self) -> Tensor:
        """(2,) bound on the relative error of the kernel the backend uses (0 for exact arithmetic)."""
        return self.backend.truncation_error()

    def diagnostics(self, warn: bool = True):
        """What the fit can and cannot say, per map (``gp.diagnostics``): the share of the square the
        forces constrain, lengthscales the data cannot inform, a collapsed signal; with ``warn``, a
        ``UserWarning`` in plain words for each unidentified map. ``print(model.diagnostics())``."""
        from .diagnostics import diagnose

        report = diagnose(self)
        if warn:
            for m in report.maps:
                if m.unidentified:
                    warnings.warn(f"{m.name} is not constrained by these forces: its posterior is the prior",
                                  stacklevel=2)
        return report

    # ---- training ----------------------------------------------------------------------------
    def mll(self):
        """gpytorch's ExactMarginalLogLikelihood (observations backend only; ``loss()`` works for all)."""
        if not hasattr(self.backend, "mll"):
            raise RuntimeError(f"the {self.method!r} backend has no gpytorch ExactGP; use model.loss()")
        return self.backend.mll()

    def loss(self) -> Tensor:
        """Negative log marginal likelihood per force sample, summed over the two axes (minus the log
        hyperparameter prior / T where priors are registered)."""
        self.train()
        if self.surface is not None:
            return surface_loss(self)
        return self.backend.loss()

    def fit(self, n_iter: int = 300, lr: float = 0.05, progress: bool = True) -> list[float]:
        """Adam on the exact marginal likelihood. Returns the loss per step (the negative log
        likelihood per force sample, summed over the two axes). Ctrl-C stops early and keeps
        what was learned.

        The model ends at the best iterate the loss saw: where the loss rose above its best (an lr
        too large makes Adam diverge: ``fit(40, lr=5)`` climbs from -0.41 to +7.4), or turned NaN or
        inf (the fit stops there), the hyperparameters of the best step are restored, and a rise of
        more than 0.1 (or 10 %) of the loss is a ``FitDivergedWarning`` suggesting an lr 10x smaller.

        With ``hyper_posterior="laplace"`` Adam stops early once 25 steps gain less than
        ``gp.fit_control.CONVERGED_NATS`` of log posterior: the Laplace step then polishes to the mode (L-BFGS
        and Newton), which Adam only approaches, and predictions are the same as after all ``n_iter`` steps (to
        ~1e-6 of the predictive sd, measured)."""
        if int(n_iter) != n_iter or n_iter < 0 or not math.isfinite(lr) or lr <= 0:
            raise ValueError(f"need an integer n_iter >= 0 and lr > 0, got n_iter={n_iter}, lr={lr}")
        history = self.fit_control.run(self, int(n_iter), float(lr), progress)
        self.loss_history.extend(history)
        self._last_fit = (int(n_iter), float(lr))
        if self.averages_means:
            fit_companion(self, int(n_iter), float(lr), progress)
        self._finish_fit()
        return history

    def _finish_fit(self) -> None:
        """What ends every fit (``fit``, ``gp.fit_together``): the hyperparameter posterior at the fitted
        hyperparameters ("laplace", "nuts"), or the plug-in ("map"); with ``MapPrior(mean="average")``, the
        physics-mean companion (fitted here if ``fit`` did not: ``gp.fit_together``) and the weights."""
        if self.hyper_method != "map":
            self.fit_hyper_posterior()
        else:
            self._set_hyper_posterior(None)
        if self.averages_means:
            if self.companion is None or len(self.companion.train_forces) != len(self.train_forces):
                n_iter, lr = getattr(self, "_last_fit", (300, 0.05))
                fit_companion(self, n_iter, lr, progress=False)
            weigh_means(self)

    def add_data(self, contacts: Contacts, forces, noise_scale=None, locations=None) -> InverseRFT:
        """Streaming: add force samples with the hyperparameters fixed (no refit); the posterior is
        exactly that of a batch fit on all the data at these hyperparameters. ``noise_scale``: as in
        the constructor, for the new samples. The physical priors' centres follow all the data (their sums
        updated), so a later ``fit`` (and a saved and loaded model) has a batch model's objective. ``locations``
        (T, 2) m: the new samples' places (a model fitted with places needs them)."""
        if not isinstance(contacts, Contacts) or contacts.beta.ndim != 2:
            raise ValueError("contacts must be a Contacts of shape (T, M)")
        contacts = placed_contacts(self.spatial, contacts, None if locations is None else
                                   check_locations(locations, len(contacts)), self.dtype, self._device)
        if self.spatial and contacts.locations is None:
            raise ValueError("locations: this model was fitted with places; give the new samples' places (T, 2) m")
        if self.surface is not None:
            raise NotImplementedError("add_data with a learned surface offset: the offset is fitted in batch; build "
                                      "a new InverseRFT on all the data (or fix the offset: "
                                      "contacts.with_surface_offset(model.surface_offset.mean) and no surface=...)")
        device = self._parts[0][1].device
        c = contacts.to(dtype=self.dtype, device=device)
        f = _as_forces(forces, len(c), self.dtype, device)
        scale = _as_noise_scale(noise_scale, len(c), self.dtype, device)
        c, f = _whiten(c, f, scale)

        def add_own() -> None:
            self.backend.add_data(c, f)
            if self._draw_backends is not None:
                add_data_to_draws(self.hyper_posterior, self._draw_backends, c, f)

        if self.averages_means and self.mean_average is not None:
            stream_into_average(self, contacts, forces, noise_scale, add_own)
        else:
            add_own()
            if self.averages_means and self.companion is not None:  # not yet weighed (unfitted): keep in step
                self.companion.add_data(contacts, forces, noise_scale)
        self._statistics = None  # no longer of all the data
        self.fit_control.forget_data()
        self._parts.append((c, f, scale))
        self._joined = None
        self._digest_stale = True
        if self.priors == "physical":  # the centres follow the data (the posterior does not use them)
            self._register_priors(c, f, more=True)
        return self

    # ---- prediction ----------------------------------------------------------------------------
    def stress_map(self, beta, gamma, locations=None) -> Posterior:
        """Posterior of (alpha_x, alpha_z) at angles of any broadcast shape S (rad).

        Angles outside the canonical square are mapped in by the mirror identity. Returns mean and
        variance of shape S + (2,), in N/cm^3 and (N/cm^3)^2 (paper eqs. for mu and sigma^2). A model fitted
        with places (``locations=``, ``gp.spatial``): ``locations`` (L, 2) m gives (L, *S, 2), the maps at
        each place; without, the medium shared by the site.
        """
        beta = torch.as_tensor(beta, dtype=self.dtype, device=self._device)
        gamma = torch.as_tensor(gamma, dtype=self.dtype, device=self._device)
        S = _check_angles(beta, gamma, "stress_map")
        self.eval()
        c, S = placed_queries(self.spatial, Contacts.points(beta, gamma), S, locations, self.dtype, self._device)
        backends, weights = self._weighted_backends()
        posts = [b.posterior(c) for b in backends]
        means = torch.stack([p.mean.T.reshape(*S, 2) for p in posts])
        variances = torch.stack([p.variance.T.reshape(*S, 2) for p in posts])
        return Posterior.mixture(means, variances, weights)

    def sample_maps(self, beta, gamma, n: int = 1, generator: torch.Generator | None = None,
                    locations=None) -> Tensor:
        """Maps drawn from the joint posterior at angles of any broadcast shape S (rad): (n, *S, 2) in
        N/cm^3, axis order (x, z). The points of one draw are jointly distributed (a plausible map, not
        independent noise per point), so a draw can be pushed through ``rft.forces`` or a design score
        to carry the map's uncertainty into anything computed from it. Exact for the observations and
        pairs backends, within the reported truncation for the spectral one (its finite root). The
        dense backends factor the (N x N) covariance of the N points per axis: above 4096 points
        without a root, a ValueError says to sample in pieces or use ``method="spectral"``.
        ``generator``: a ``torch.Generator`` on the model's device, for reproducible draws. ``locations``
        (L, 2) m, a model fitted with places: (n, L, *S, 2), jointly over places too."""
        if int(n) != n or n < 1:
            raise ValueError(f"n must be a positive integer (the number of maps to draw), got {n!r}")
        beta = torch.as_tensor(beta, dtype=self.dtype, device=self._device)
        gamma = torch.as_tensor(gamma, dtype=self.dtype, device=self._device)
        S = _check_angles(beta, gamma, "sample_maps")
        c, S = placed_queries(self.spatial, Contacts.points(beta, gamma), S, locations, self.dtype, self._device)
        N = c.beta.shape[0]
        if N > 4096 and self.backend.posterior_root(c) is None:
            raise ValueError(f"{N} points: the {self.method} backend draws through the dense {N} x {N} covariance; "
                             "sample at most 4096 points at a time, or fit with engine='spectral'")
        self.eval()
        return _mixture_maps(*self._weighted_backends(), int(n), c, generator).permute(2, 1, 0).reshape(int(n), *S, 2)

    def forward(self, beta: Tensor, gamma: Tensor) -> Tensor:
        """Posterior mean map (..., 2): a fitted model is a stress map (``rft.forces(model, c)``)."""
        beta = torch.as_tensor(beta, dtype=self.dtype, device=self._device)
        gamma = torch.as_tensor(gamma, dtype=self.dtype, device=self._device)
        S = _check_angles(beta, gamma, "the model's map")
        c = Contacts.points(beta, gamma)
        backends, weights = self._weighted_backends()
        if weights is None:
            return self.backend.posterior(c, variance=False).mean.T.reshape(*S, 2)
        w = weights if weights.ndim == 2 else weights[:, None].expand(-1, 2)  # (S, 2): per map
        mean = sum(wi[:, None] * b.posterior(c, variance=False).mean for b, wi in zip(backends, w))
        return mean.T.reshape(*S, 2)

    def predict_forces(self, contacts: Contacts, variance: str = "exact", include_noise: bool = False,
                       noise_scale=None, locations=None) -> Posterior:
        """Posterior of the forces (F_x, F_z) for contacts of shape (..., T, M).

        The contacts are used as given: on a model that learned the surface offset
        (``surface=True``), contacts built at the stated surface predict forces there; to
        predict at the learned surface, pass ``contacts.with_surface_offset(model.surface_offset.mean)``.

        Args:
            variance: "exact" (w^T Sigma w, segments correlated) or "independent" (the paper's
                sum_m w_m^2 sigma^2(theta_m)).
            include_noise: add the learned observation noise (predict a measurement).
            noise_scale: with ``include_noise`` (a ValueError without), the new samples' relative noise
                scales, as in the constructor (default 1): per sample, any shape ending in T that
                broadcasts to the contacts' (..., T); or per sample and axis, ending in (T, 2).
            locations: a model fitted with places: (..., T, 2) m, each sample's place (or the contacts' own
                ``locations``); without, the forces of the medium shared by the site.

        Returns:
            Posterior with mean and variance (..., T, 2) in N and N^2. Differentiable in the
            contact angles and weights.
        """
        if not isinstance(contacts, Contacts):
            raise TypeError(f"contacts must be a Contacts, got {type(contacts).__name__}")
        if variance not in ("exact", "independent"):
            raise ValueError(f"variance must be 'exact' or 'independent', got {variance!r}")
        self.eval()
        c = placed_contacts(self.spatial, contacts.to(dtype=self.dtype, device=self._device), locations, self.dtype,
                            self._device)
        _check_query(c, self.train_contacts)
        lead, M = c.shape[:-1], c.n_segments
        flat = Contacts(**{k: v.reshape(-1, M) for k, v in c.as_dict().items()},
                        locations=None if c.locations is None else c.locations.reshape(-1, 2))
        # Rows with no segment in contact have force exactly 0 (mean and variance): skip them.
        rows = touching(flat)
        if noise_scale is not None and not include_noise:
            raise ValueError("noise_scale only applies with include_noise=True (it scales the measurement noise "
                             "added to the prediction)")
        scale = None
        if include_noise:
            scale = torch.ones((), dtype=c.beta.dtype, device=c.beta.device) if noise_scale is None else \
                _noise_scale(noise_scale, lead, c.beta.dtype, c.beta.device)
        backends, weights = self._weighted_backends()
        means, variances = [], []
        for backend in backends:
            mean, var = _force_posterior(backend, flat, rows, variance, chunk=_predict_chunk(backend))
            var = var.T.reshape(*lead, 2)
            if include_noise:
                var = var + backend.hypers.noise * scale.pow(2)
            means.append(mean.T.reshape(*lead, 2))
            variances.append(var)
        return Posterior.mixture(torch.stack(means), torch.stack(variances), weights)

    def cross_validate(self, groups, include_noise: bool = False, refit: bool = False, n_iter: int = 300,
                       lr: float = 0.05):
        """Each group of training samples (a run, a trial, a tilt) predicted from the other groups at the
        fitted hyperparameters, without refitting (``gp.cross_validation``): compare models on the
        training data alone. ``groups``: (T,) one label per training sample; ``include_noise``: add each
        sample's own noise to ``.variance`` (predict a measurement); ``refit``: fit a model like this one on
        the other groups for each group instead (``n_iter``, ``lr``: as this model's fit), unbiased, G fits.
        Returns ``GroupPredictions``: ``.mean``, ``.variance`` (T, 2) in N and N^2, ``.rmse()`` (2,) N,
        ``.log_predictive_density()``."""
        from .cross_validation import cross_validate

        return cross_validate(self, groups, include_noise=include_noise, refit=refit, n_iter=n_iter, lr=lr)

    def extra_repr(self) -> str:
        return f"T={len(self.train_contacts)}, M={self.n_segments}, prior={self.prior}, " \
               f"hyper_posterior={self.hyper_method!r}, backend={self.backend.describe()!r}"
