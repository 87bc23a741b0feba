"""InverseRFT3D: learn alpha_x(beta, gamma), alpha_y and alpha_z(beta, gamma) from 3-D forces.

``irft.InverseRFT(contacts_3d, forces)`` with a ``Contacts3D`` and (T, 3) forces builds this model. It is
the planar front door's 3-D counterpart: it checks the data, sets data-scaled initial hyperparameters and
physical priors, picks a backend (``gp.inverse3d.select``) and delegates every computation to it.
"""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from ..._files import atomic_write
from ...rft.contacts3d import Contacts3D
from ..fit_control import FitControl, lbfgs_polish
from ..hyper.posterior import HYPER_POSTERIORS, HyperPosterior, add_data_to_draws
from ..hyper.predictions import HyperMixtureMixin
from ..inputs import _as_forces, _check_angles, _check_dtype
from ..kernels.hyperparameters import ALPHA_Y, AXES_3D, LENGTHSCALE_FLOOR_3D, MAPS_3D, RFT3DHyperparameters
from ..kernels.priors import data_scales_3d, prior_centres_3d, register_physical_priors  # K maps, one module
from ..options import Engine, MapPrior, grouped_3d, options_3d
from ..posterior import Posterior
from .backends import Backend3D
from .mean import MEAN_MAPS, fit_mean_scales, shape_forces_3d
from .rows import point_contacts
from .select import METHODS_3D, make_backend_3d

__all__ = ["InverseRFT3D", "Posterior3D", "point_contacts", "FORMAT_3D"]

FORMAT_3D = "irft_torch.InverseRFT3D/1"


Posterior3D = Posterior  # one posterior type for every model (``gp.posterior.Posterior``, K = 3 axes here)


class InverseRFT3D(HyperMixtureMixin):
    """3-D I-RFT: GP posteriors of alpha_x(beta, gamma), alpha_z(beta, gamma) and alpha_y (a third map over
    (beta, gamma), or a constant) from forces F[t] = sum_k W[t, k] alpha(theta[t, k]) + noise (docs/inverse3d.md).

    Args:
        contacts: training ``Contacts3D`` (T, K) (``rft.contacts_3d``).
        forces: (T, 3) measured (F_x, F_y, F_z) in N.
        prior: a ``MapPrior`` (``gp.options``), with the 3-D defaults where a field is None. ``kernel``: "rbf"
            (default) or "li" (Li et al.'s 9 functions as a term of each map over (beta, gamma),
            ``gp.kernels.li_basis``; variances ``model.hypers.li_variance`` (3,)). "rbf", unlike the planar model's
            default: with "li" and ``hyper_posterior="laplace"`` the measured wheels' held-out forces lose to the
            authors' 3-D RFT on the smooth wheel's longitudinal and lateral axes and the Laplace weights are
            unreliable there (docs/inverse3d.md, "Which defaults in 3-D"). ``mean``: "physics" (default),
            "physics_alpha_y" or "zero". "physics": alpha_x and alpha_z's prior means are Li et al.'s generic
            maps, one least-squares scale each fitted to these forces and then fixed (``gp.inverse3d.mean``;
            ``model.mean_scales``), alpha_y's is zero: where the forces do not constrain a map, predictions fall
            back on the scaled generic medium instead of zero; "physics_alpha_y": alpha_y too (its shape the
            generic alpha_x(0, 0)); "zero": every map zero-mean. Why "physics": the rover wheels' held-out forces
            (docs/inverse3d.md). ``hyperpriors``: "physical" (default, ``gp.kernels.priors``) or None;
            ``lengthscale``: the initial lengthscale. Every lengthscale stays above ``LENGTHSCALE_FLOOR_3D`` = 0.21
            (``gp.kernels.hyperparameters``: the finest features measured media show; the default spectral basis is
            exact to ``tol`` above it).
        hyper_posterior: "map" (default: predict at the fitted hyperparameters), "laplace" or "nuts": ``fit``
            then also fits the posterior over the hyperparameters (``fit_hyper_posterior``, the planar
            ``gp.hyper.posterior`` machinery) and every prediction is a mixture over its draws.
        alpha_y: "map" (default: a GP over (beta, gamma) like the other two) or "constant" (one value with a
            zero-mean normal prior: a rank-one kernel term).
        engine: an ``Engine`` (``gp.options``) or a method name: "auto" (default), "observations", "pairs" or
            "spectral" (``gp.inverse3d.backends``, ``spectral``); its ``tol`` bounds the spectral truncation and
            ``max_harmonics`` caps the spectral basis per angle (default 30; below the lengthscales ``tol`` needs,
            the kernel is the RBF truncated there: ``truncation_error`` says by how much, a ``UserWarning`` after
            ``fit``).
        features: spectral backend: the training rows' features from a ``SpectralFeatureBank`` over a larger
            data set (``bank.rows(index)``, these contacts being its samples ``index``): folds of a cross-validation
            then share one pass over the elements.

    Example:
        >>> model = InverseRFT(contacts_3d, forces)       # (T, 3) forces: a 3-D model
        >>> model.fit(n_iter=200)
        >>> model.predict_forces(new).covariance         # (T', 3, 3)
        >>> model.stress_map(beta, gamma).mean           # (..., 3): alpha_x, alpha_y, alpha_z
    """

    def __init__(self, contacts: Contacts3D, forces, *, prior: MapPrior | None = None,
                 hyper_posterior: str | None = None, alpha_y: str = "map", engine: Engine | str | None = None,
                 features=None, **deprecated) -> None:
        prior, engine = options_3d(prior, engine, deprecated)
        method, tol, dtype, max_harmonics = engine.method, engine.tol, engine.dtype, engine.max_harmonics
        priors, lengthscale, prior_mean = prior.hyperpriors, prior.lengthscale, prior.mean
        li_basis = prior.kernel == "li"
        super().__init__()
        self.prior, self.engine = prior, engine  # the choices as resolved (the 3-D defaults filled in)
        if not isinstance(contacts, Contacts3D):
            raise TypeError(f"contacts must be an irft_torch.rft.Contacts3D, got {type(contacts).__name__}")
        if alpha_y not in ALPHA_Y:
            raise ValueError(f"alpha_y must be one of {ALPHA_Y}, got {alpha_y!r}")
        if method not in METHODS_3D:
            raise ValueError(f"method must be one of {METHODS_3D}, got {method!r}")
        hyper_posterior = "map" if hyper_posterior is None else hyper_posterior
        if hyper_posterior not in HYPER_POSTERIORS:
            raise ValueError(f"hyper_posterior must be one of {HYPER_POSTERIORS}, got {hyper_posterior!r}")
        if priors not in ("physical", None):
            raise ValueError(f"priors must be 'physical' or None, got {priors!r}")
        if prior_mean not in ("zero", *MEAN_MAPS):
            raise ValueError(f"MapPrior(mean=...) (formerly prior_mean) must be one of {('zero', *MEAN_MAPS)} for a "
                             f"3-D model, got {prior_mean!r}")
        if not isinstance(li_basis, bool):
            raise TypeError(f"li_basis must be True or False, got {li_basis!r}")
        _check_dtype(dtype)
        if not (math.isfinite(lengthscale) and lengthscale > LENGTHSCALE_FLOOR_3D):
            raise ValueError(f"lengthscale must be a finite value > {LENGTHSCALE_FLOOR_3D} (the 3-D lengthscale floor, "
                             f"gp.kernels.hyperparameters), got {lengthscale}")
        T = len(contacts)
        if T < 2:
            raise ValueError(f"need at least 2 force observations, got {T}")
        device = contacts.beta.device
        c = contacts.to(dtype=dtype, device=device)
        f = _as_forces(forces, T, dtype, device, AXES_3D)
        if not (c.weight_z != 0).any() and not (c.weight_x != 0).any():
            raise ValueError("contacts carry no weight: no element is in contact, nothing to learn")
        if float(f.abs().max()) > 1e4:
            warnings.warn(f"forces reach {float(f.abs().max()):.3g}: above 1e4 N; are they in mN? (forces are in N)",
                          stacklevel=2)
        self.alpha_y, self.method_arg, self.priors, self.dtype = alpha_y, method, priors, dtype
        self.prior_mean = prior_mean
        # (3,) scales of the generic maps in the prior mean (None: a zero mean); the training rows' shape forces
        G = shape_forces_3d(c) if prior_mean in MEAN_MAPS else None
        self.mean_scales: Tensor | None = None if G is None else fit_mean_scales(c, f, G, MEAN_MAPS[prior_mean])
        self.hyper_method = hyper_posterior
        self.hyper_posterior: HyperPosterior | None = None  # set by fit (hyper_posterior != "map")
        self._draw_backends: list[Backend3D] | None = None
        self.tol, self.init_lengthscale = float(tol), float(lengthscale)
        self.train_contacts, self.train_forces = c, f
        self._device = device
        power = f.pow(2).mean(0)
        noise_floor = max(float(power[power > 0].min()) if (power > 0).any() else 1.0, 1e-300) * \
            (1e-8 if dtype == torch.float64 else 1e-5)
        self._noise_floor = noise_floor
        force_scale, map_scale = data_scales_3d(c, f)
        self.hypers = RFT3DHyperparameters(alpha_y, noise_floor, force_scale.clamp_min(1e-6).cpu(),
                                           map_scale.cpu(), li_basis=li_basis).to(device=device, dtype=dtype)
        centres = prior_centres_3d(c, f, map_scale, noise_floor)
        with torch.no_grad():
            self.hypers.outputscale = centres["outputscale"].to(dtype)
            self.hypers.lengthscale = torch.full((3, 1, 4), float(lengthscale), dtype=dtype)
            self.hypers.noise = centres["noise"].to(dtype)
            if li_basis:  # its prior's centre (``gp.kernels.priors``)
                self.hypers.li.variance = self.hypers.outputscale
        if priors == "physical":
            register_physical_priors(self.hypers, centres)
        from ..kernels.fourier import MAX_HARMONICS

        self.max_harmonics = MAX_HARMONICS if max_harmonics is None else int(max_harmonics)
        residual = f if G is None else f - G @ self.mean_scales
        self.backend: Backend3D = make_backend_3d(method, self.hypers, c, residual, tol=tol,
                                                  features=features, max_harmonics=self.max_harmonics)
        self.loss_history: list[float] = []
        self.fit_control = FitControl()  # the planar model's Adam loop and guards (gp.fit_control)
        self.eval()

    auto = False  # the backend chosen at construction stays (the fit loop does not move a 3-D model between spaces)
    surface = None  # no learned surface offset

    # ---- the prior mean -----------------------------------------------------------------------------------------
    def mean_forces(self, contacts: Contacts3D) -> Tensor:
        """(T, 3) the prior mean's forces of ``contacts`` in N (zeros for a zero mean; map values for
        ``point_contacts``)."""
        c = contacts.to(dtype=self.dtype, device=self._device)
        if self.mean_scales is None:
            return c.beta.new_zeros(len(c), 3)
        return shape_forces_3d(c) @ self.mean_scales.to(c.beta)

    def _residual(self, contacts: Contacts3D, forces: Tensor) -> Tensor:
        """What the GPs see: the forces less the prior mean's."""
        return forces if self.mean_scales is None else forces - self.mean_forces(contacts)

    # ---- views -------------------------------------------------------------------------------------------------
    @property
    def method(self) -> str:
        return self.backend.name

    def hyperparameters(self) -> dict:
        return self.hypers.as_dict()

    def truncation_error(self) -> Tensor:
        return self.backend.truncation_error()

    def loss(self) -> Tensor:
        """Negative log marginal likelihood per sample summed over the two blocks (minus log prior / T)."""
        return self.backend.loss()

    def fit(self, n_iter: int = 300, lr: float = 0.05, progress: bool = True) -> list[float]:
        """The exact marginal likelihood's mode (MAP with the priors): at most ``n_iter`` Adam steps, stopped where 25
        steps gain less than ``CONVERGED_NATS`` of log posterior; from there L-BFGS to the mode (``lbfgs_polish``;
        with "laplace", its own polish). A fit that uses its ``n_iter`` steps before that ends
        at Adam's iterate. Ctrl-C keeps what was learned. The planar fit's loop (``gp.fit_control.FitControl``, held
        as ``fit_control``), so as the planar fit: the model ends at the best iterate the
        loss saw (the loss rose above it, or turned NaN or inf: the fit stops there), and a rise of more than 0.1
        (or 10 %) is a ``FitDivergedWarning`` suggesting a smaller lr (and no polish follows). Returns Adam's
        losses per step (per sample), then the loss L-BFGS ended at where it ran."""
        if int(n_iter) != n_iter or n_iter < 0 or not math.isfinite(lr) or lr <= 0:
            raise ValueError(f"need an integer n_iter >= 0 and lr > 0, got n_iter={n_iter}, lr={lr}")
        control = self.fit_control
        history = control.run(self, int(n_iter), float(lr), progress, stop_at_convergence=True)
        if control.converged_stop and not control.diverged and self.hyper_method != "laplace":  # (Laplace polishes)
            params = [p for p in self.hypers.parameters() if p.requires_grad]
            try:
                value, evals = lbfgs_polish(params, self.backend.loss, self.backend.n_samples, self.backend.refresh)
                if not math.isfinite(value):  # Adam's last step left no finite loss: its best iterate
                    with torch.no_grad():
                        self.hypers.load_state_dict(control.best_state[1])
                    self.backend.refresh()
                elif evals:
                    history.append(value)
            except KeyboardInterrupt:
                warnings.warn("fit interrupted in its L-BFGS polish; the model keeps the last values it accepted",
                              stacklevel=2)
        if self.hyper_method != "map":
            self.fit_hyper_posterior()
            self.backend.refresh()  # the polished mode may need a larger basis
        else:
            self._set_hyper_posterior(None)
        err = float(self.backend.truncation_error().max())
        if err > self.tol:
            warnings.warn(f"the lengthscales need more than max_harmonics={self.max_harmonics} harmonics for tol="
                          f"{self.tol:.0e}: the kernel used is the RBF truncated there (relative error <= {err:.1e})",
                          stacklevel=2)
        self.loss_history.extend(history)
        return history

    # ---- streaming -------------------------------------------------------------------------------------------------
    def add_data(self, contacts: Contacts3D, forces) -> InverseRFT3D:
        """Streaming: append force samples with the hyperparameters fixed (no refit). The posterior is exactly
        that of a batch fit on all the data at these hyperparameters (each backend appends to its own exact
        factors: ``Backend3D.add_data``); hyperparameter draws are reweighted by the new samples' likelihood
        (``gp.hyper.posterior.add_data_to_draws``). The physical priors' centres follow all the data, so a later
        ``fit`` (and a saved and loaded model) has the objective of a model built on all of it."""
        if not isinstance(contacts, Contacts3D):
            raise TypeError(f"contacts must be a Contacts3D, got {type(contacts).__name__}")
        c = contacts.to(dtype=self.dtype, device=self._device)
        f = _as_forces(forces, len(c), self.dtype, self._device, AXES_3D)
        r = self._residual(c, f)
        if self._draw_backends is not None and self.hyper_posterior is not None:  # before the shared data move
            add_data_to_draws(self.hyper_posterior, self._draw_backends, c, r)
        self.backend.add_data(c, r)
        self.train_contacts = self.backend.train_contacts
        self.train_forces = torch.cat([self.train_forces, f])  # as measured (the backend holds the residuals)
        if self.priors == "physical":
            _, map_scale = data_scales_3d(self.train_contacts, self.train_forces)
            register_physical_priors(self.hypers, prior_centres_3d(self.train_contacts, self.train_forces, map_scale,
                                                                   self._noise_floor))
        return self

    # ---- prediction ----------------------------------------------------------------------------------------------
    def predict_forces(self, contacts: Contacts3D, include_noise: bool = False) -> Posterior:
        """Posterior of (F_x, F_y, F_z) for contacts (T, K): mean, variance (T, 3) in N, N^2 and each sample's
        3 x 3 ``covariance`` (F_x and F_y correlate through alpha_x and alpha_y; F_z is independent of both). With
        a hyperparameter posterior, the mixture over its draws (``Posterior.of_covariances``)."""
        if not isinstance(contacts, Contacts3D):
            raise TypeError(f"contacts must be a Contacts3D, got {type(contacts).__name__}")
        c = contacts.to(dtype=self.dtype, device=self._device)
        backends, weights = self._weighted_backends()
        means, covs = [], []
        prior = self.mean_forces(c)
        with torch.no_grad():
            for backend in backends:
                mean, cov = backend.posterior(c)
                mean = mean + prior
                cov = 0.5 * (cov + cov.mT)
                if include_noise:
                    cov = cov + torch.diag_embed(backend.hypers.noise.detach()).expand_as(cov)
                means.append(mean)
                covs.append(cov)
        return Posterior.of_covariances(torch.stack(means), torch.stack(covs), weights)

    def _angles(self, beta, gamma) -> tuple[Tensor, Tensor, torch.Size]:
        """Query angles (rad) broadcast together, checked as the planar model checks them (shapes that do not
        broadcast, NaN or inf: a ValueError naming the argument; a turn or more: a warning, degrees?)."""
        beta = torch.as_tensor(beta, dtype=self.dtype, device=self._device)
        gamma = torch.as_tensor(gamma, dtype=self.dtype, device=self._device)
        S = torch.Size(_check_angles(beta, gamma, "the model's map"))
        for name, v in (("beta", beta), ("gamma", gamma)):
            if not torch.isfinite(v).all():
                raise ValueError(f"{name} contains NaN or inf")
        beta, gamma = torch.broadcast_tensors(beta, gamma)
        return beta, gamma, S

    def stress_map(self, beta, gamma) -> Posterior:
        """Posterior of (alpha_x, alpha_y, alpha_z) at angles of any broadcast shape S (rad): mean, variance
        S + (3,) in N/cm^3 (angles outside the canonical square mapped in by the mirror identity)."""
        beta, gamma, S = self._angles(beta, gamma)
        return self.predict_forces(point_contacts(beta, gamma)).reshape(*S)

    def forward(self, beta, gamma) -> Tensor:
        """Posterior mean map (..., 3) = (alpha_x, alpha_y, alpha_z): ``rft.forces_3d(model, contacts)`` works."""
        return self.stress_map(beta, gamma).mean

    def sample_maps(self, beta, gamma, n: int = 1, generator: torch.Generator | None = None) -> Tensor:
        """Maps drawn from the joint posterior at angles of any broadcast shape S: (n, *S, 3) in N/cm^3 (the
        points of one draw jointly distributed; alpha_x and alpha_y correlated as the data make them). With a
        hyperparameter posterior each map first picks a draw by its weight."""
        if int(n) != n or n < 1:
            raise ValueError(f"n must be a positive integer, got {n!r}")
        beta, gamma, S = self._angles(beta, gamma)
        c = point_contacts(beta, gamma)
        N = len(c)
        if N > 3000:
            raise ValueError(f"{N} points: sample at most 3000 at a time (the joint covariance is dense)")
        from ..posterior import _psd_root

        backends, weights = self._weighted_backends()
        if weights is None:
            counts = [int(n)]
        else:
            pick = torch.multinomial(weights, int(n), replacement=True, generator=generator)
            counts = torch.bincount(pick, minlength=len(backends)).tolist()
        out = []
        prior = self.mean_forces(c)
        with torch.no_grad():
            for backend, k in zip(backends, counts):
                if k == 0:
                    continue
                mean, _, joints = backend.posterior(c, joint=True)
                draw = mean.new_zeros(k, N, 3)
                h = joints[0]
                eps = torch.randn(h.shape[0], k, generator=generator, dtype=h.dtype, device=h.device)
                dh = (_psd_root(h) @ eps).T.reshape(k, 2, N)
                draw[..., 0], draw[..., 1] = dh[:, 0], dh[:, 1]
                eps = torch.randn(N, k, generator=generator, dtype=h.dtype, device=h.device)
                draw[..., 2] = (_psd_root(joints[1]) @ eps).T
                out.append(draw + mean + prior)
        draws = torch.cat(out)
        if len(out) > 1:  # interleave the draws' maps
            draws = draws[torch.randperm(int(n), generator=generator, device=draws.device)]
        return draws.reshape(int(n), *S, 3)

    def cross_validate(self, groups, refit: bool = False, n_iter: int = 300, lr: float = 0.05,
                       include_noise: bool = False) -> Posterior:
        """Each group of training samples predicted from the other groups: at this model's fitted
        hyperparameters (default; with a hyperparameter posterior, the mixture over its draws) or by a model like
        this one fitted on the others (``refit``). ``groups``: (T,) one label per training sample, any sortable
        values (run numbers, names), checked as the planar model checks them. Returns the held-out ``Posterior``
        (T, 3) in the training order."""
        from ..cross_validation import _group_index

        T = len(self.train_contacts)
        index, labels = _group_index(groups, T, self._device)
        backends, weights = self._weighted_backends()
        S = 1 if refit else len(backends)
        mean = self.train_forces.new_zeros(S, T, 3)
        cov = self.train_forces.new_zeros(S, T, 3, 3)
        for label in range(len(labels)):
            test = index == label
            ctr, ftr = self.train_contacts[~test], self.train_forces[~test]
            if refit:
                m = InverseRFT3D(ctr, ftr, **grouped_3d(self._options()))
                m.fit(n_iter=n_iter, lr=lr, progress=False)
                p = m.predict_forces(self.train_contacts[test], include_noise=include_noise)
                mean[0, test], cov[0, test] = p.mean, p.covariance
                continue
            for s, backend in enumerate(backends):
                held = make_backend_3d(self.method, backend.hypers, ctr, self._residual(ctr, ftr), tol=self.tol,
                                       max_harmonics=self.max_harmonics)
                with torch.no_grad():
                    ms, cs = held.posterior(self.train_contacts[test])
                    ms = ms + self.mean_forces(self.train_contacts[test])
                if include_noise:
                    cs = cs + torch.diag_embed(backend.hypers.noise.detach())
                mean[s, test], cov[s, test] = ms, 0.5 * (cs + cs.mT)
        return Posterior.of_covariances(mean, cov, None if refit else weights)

    def _at_mode(self) -> None:
        """Where the hyperparameter posterior leaves the hyperparameters: the basis they need, which the draws'
        backends start from (as a loaded model's do: save and load give the same mixture)."""
        self.backend.refresh()

    def diagnostics(self, n: int = 21) -> dict:
        """Per map, the share of the canonical square where the posterior std is below half the prior's (what
        the forces constrain); a ``UserWarning`` for a map the forces do not constrain anywhere. Under "kernel":
        the backend, the kernel's relative error bound per map (3,) (nonzero only where the spectral basis
        approximates it: ``truncation_error``), the ``tol`` asked for and whether the bound is within it; with a
        hyperparameter posterior, "draws_truncated": how many of its draws' kernels are truncated beyond ``tol``."""
        b = torch.linspace(-math.pi / 2, math.pi / 2, n, dtype=self.dtype, device=self.hypers.outputscale.device)
        beta, gamma = torch.meshgrid(b, b, indexing="ij")
        post = self.stress_map(beta, gamma)
        prior = self.hypers.prior_variance.detach().sqrt()  # with Li et al.'s term: s + v
        share = (post.stddev < 0.5 * prior).reshape(-1, 3).to(self.dtype).mean(0)
        out: dict[str, dict] = {name: {"constrained_share": float(s), "prior_std": float(p)}
               for name, s, p in zip(MAPS_3D, share, prior)}
        for name, s in zip(MAPS_3D, share):
            if float(s) == 0:
                warnings.warn(f"{name} is not constrained by these forces: its posterior is the prior", stacklevel=2)
        err = self.truncation_error()
        out["kernel"] = {"backend": self.backend.describe(), "truncation_error": err.tolist(), "tol": self.tol,
                         "within_tol": bool((err <= self.tol).all())}
        if self._draw_backends is not None:  # the hyperparameter draws whose kernel the basis truncates beyond tol
            cut = sum(float(b.truncation_error().max()) > self.tol for b in self._draw_backends)
            out["kernel"]["draws_truncated"] = f"{cut} of {len(self._draw_backends)}"
        return out

    # ---- persistence -----------------------------------------------------------------------------------------------
    def _options(self) -> dict:
        return {"alpha_y": self.alpha_y, "method": self.method_arg, "priors": self.priors, "dtype": self.dtype,
                "lengthscale": self.init_lengthscale, "tol": self.tol, "max_harmonics": self.max_harmonics,
                "hyper_posterior": self.hyper_method, "prior_mean": self.prior_mean,
                "li_basis": self.hypers.li is not None}

    def save(self, path) -> None:
        """Training data (after ``add_data``: all of it), options, hyperparameters and any hyperparameter
        posterior's draws and weights in one file (``load`` rebuilds the model, predictions the same), written
        atomically as the planar model's (``_files.atomic_write``: a full disk, Ctrl-C or a crash leaves the
        previous file loadable; a folder or a missing folder is an ``OSError`` naming the path)."""
        payload = {"format": FORMAT_3D, "contacts": {k: v.cpu() for k, v in self.train_contacts.as_dict().items()},
                   "forces": self.train_forces.cpu(), "options": self._options(),
                   "hypers": {k: v.cpu() for k, v in self.hypers.state_dict().items()}}
        if self.hyper_posterior is not None:
            payload["hyper_posterior"] = self.hyper_posterior.state()
        if self.mean_scales is not None:
            payload["mean_scales"] = self.mean_scales.cpu()
        atomic_write(path, lambda fh: torch.save(payload, fh), "model")

    @classmethod
    def load(cls, path, map_location=None) -> InverseRFT3D:
        """Rebuild a model written by ``save`` (``InverseRFT.load`` reads these files too). Tensors and plain
        values only (``weights_only``); ``ModelFileError`` for a damaged or foreign file."""
        from ..model_file import ModelFileError

        try:
            d = torch.load(path, map_location=map_location, weights_only=True)
        except FileNotFoundError:
            raise
        except Exception as e:  # noqa: BLE001 - torch raises many kinds for damaged files
            raise ModelFileError(f"{path}: not a readable irft_torch model file ({type(e).__name__}: {e})") from None
        if not isinstance(d, dict) or d.get("format") != FORMAT_3D:
            raise ModelFileError(f"{path} is not a 3-D I-RFT model file ({FORMAT_3D})")
        return cls._from_file(d, path)

    @classmethod
    def _from_file(cls, d: dict, path=None) -> InverseRFT3D:
        """The model of a loaded 3-D file's dict (``load``; ``InverseRFT.load`` of a 3-D file)."""
        opts = {"prior_mean": "zero", **d["options"]}  # files from before prior_mean: a zero mean
        if opts.get("lengthscale", 1.0) <= LENGTHSCALE_FLOOR_3D:  # a file from before the 3-D floor was raised: the
            opts["lengthscale"] = 1.0  # initial value only (its state, the constraint's floor included, follows)
        model = cls(Contacts3D(**d["contacts"]), d["forces"], **grouped_3d(opts))
        if "mean_scales" in d:  # the scales it was built with (after add_data, not those of all its data)
            model.mean_scales = d["mean_scales"].to(device=model._device, dtype=model.dtype)
            model.backend = make_backend_3d(model.method_arg, model.hypers, model.train_contacts,
                                            model._residual(model.train_contacts, model.train_forces),
                                            tol=model.tol, max_harmonics=model.max_harmonics)
        model.hypers.load_state_dict(d["hypers"], strict=False)
        model.backend.refresh()
        if "hyper_posterior" in d:
            model._set_hyper_posterior(HyperPosterior.from_state(d["hyper_posterior"]))
        return model

    def extra_repr(self) -> str:
        return f"T={len(self.train_contacts)}, K={self.train_contacts.n_elements}, alpha_y={self.alpha_y!r}, " \
               f"prior={self.prior}, hyper_posterior={self.hyper_method!r}, " \
               f"backend={self.backend.describe()!r}"
