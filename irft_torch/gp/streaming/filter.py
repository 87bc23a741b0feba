r"""Many streaming I-RFT posteriors that share one fitted model's hyperparameters: a terrain estimate per
parallel environment (legged-robot RL on granular terrain), updated together, with no loop over
environments.

Each environment b has its own samples i = 1..n (the last ``window`` of them, if one is set). Its
posterior is exactly that of ``InverseRFT`` on those samples at the shared hyperparameters (the
observations backend's W K W^T + sigma^2 I, the model's prior mean), kept per map axis a in observation
space through the *inverse* Cholesky factor of the samples' covariance:

    S = W K W^T + sigma_a^2 I = L L^T,   U = L^{-1} (n x n, lower),   z = U (y - m)   (n,)

so that for any functionals q (map points, forces of other contacts) with prior cross-covariance
K_q (n x Q): A = U K_q, mean = m_q + A^T z, variance = k_qq - sum_i A_iq^2.

- **Append** a sample (one row of L): l = U k, d^2 = k_new + sigma^2 - |l|^2 (>= sigma^2), and the new
  row of U is (e_n - l^T U) / d: O(n^2) per environment, plus the kernel row k (n M^2 kernel values).
- **Forget the oldest** (a sliding window): removing the first row and column of S leaves
  S' = L22 L22^T + c c^T (c = L[1:, 0]), a rank-one *update* of L22 (stable, unlike a downdate).
  With p = L22^{-1} c = -U[1:, 0] / U[0, 0], L' = L22 Lt with Lt the Cholesky factor of I + p p^T, which
  has a closed form (Gill, Golub, Murray & Saunders 1974): t_i = 1 + sum_{j<=i} p_j^2,
  d_i = sqrt(t_i / t_{i-1}), Lt = diag(d) + strictly_lower(p beta^T), beta_j = p_j / sqrt(t_j t_{j-1}).
  Its inverse applied to any x is again a prefix sum,
      (Lt^{-1} x)_i = (x_i - p_i sum_{j<i} p_j x_j / t_{i-1}) / d_i,
  so U' = Lt^{-1} U[1:, 1:], z' = Lt^{-1} (z[1:] + p z_0), A' = Lt^{-1} (A[1:] + p A_0): O(n^2) per
  environment, vectorised over all of them, no factorisation.

The last map query's points are *tracked*: their A is extended by one row per sample (Q M kernel values)
and carried through the window's update, and their posterior is refreshed inside each update, so that
a policy asking the same points every step reads it instead of evaluating n M Q kernel values.

Exactness: the same numbers as each environment's own ``InverseRFT(..., engine="observations")`` at
these hyperparameters fed the same samples with ``add_data`` (``tests/gp/test_terrain_filter.py``
checks 1e-8 against it, the pairs backend and the dense formula); a model fitted with another backend
is the same GP, so a spectral model's own posterior differs from the filter's as it differs from the
exact posterior, within its truncation (the test: 1e-6 at the default tol 1e-7).
The hyperparameters are the model's fitted ones (the plug-in; with ``hyper_posterior`` draws, the mode),
copied when the filter is built.

A model with ``kernel="li"`` (``gp.kernels.li_basis``) adds Li et al.'s rank-9 term f(theta)^T P_a f(theta') to
the kernel (P_a = diag(v_a), plus u_a c_a c_a^T with ``generic_shape``): each sample keeps its 9 weighted
features per axis (``weighted_li_features``, cm^3), and every covariance above gains (W f)^T P_a (W' f): 81
multiply-adds per pair at most beside the RBF's M^2 kernel values.

A spatial model (``InverseRFT(..., locations=xy)``, ``gp.kernels.spatial``) gives a spatial filter: each sample
then carries its place s (m), every covariance above is multiplied by the factor 1 + v_a k_s(|s - s'| / l_a)
between the two places (Matern 5/2, the model's v and l), and queries name the places they ask about
(``locations=``; none: the medium shared by the site, factor 1). A sample's own variance takes 1 + v_a. So an
environment whose robot walks on weighs its samples by how near they were, beside how recent (the window).

Gradients: the filter's state carries none (``update`` runs without autograd: a policy does not
differentiate through the terrain's past). ``stress_map`` and ``predict_forces`` are differentiable in
their inputs (the query angles, the contacts' angles and weights); the hyperparameters are constants.

Cost per environment and step (float64, ``window`` n): n M^2 kernel values for the new sample's row,
O(n^2) for the factor, O(n Q) for a tracked query. ``experiments/benchmarks/bench_inference.py`` case 9 measures it.
"""

from __future__ import annotations

import copy

import torch
from linear_operator import to_dense
from torch import Tensor, nn

from ...rft.contacts import Contacts
from ..kernels.embedding import embed_angles
from ..kernels.li_basis import weighted_li_features
from ..model import InverseRFT
from ..posterior import Posterior
from .window import env_index, forget_oldest, pad_slots

__all__ = ["TerrainFilter"]


class TerrainFilter(nn.Module):
    r"""B streaming posteriors of the stress maps, one per environment, sharing a fitted model's
    hyperparameters and prior mean, on the model's device and dtype.

    Args:
        model: a (fitted) ``InverseRFT``; its kernel, noise and prior mean are copied (the plug-in
            hyperparameters; its training data are *not* part of the environments' posteriors).
        n_envs: B, the number of environments.
        window: keep only each environment's last ``window`` samples (a terrain that changes along the
            way); None (default): every sample since its last ``reset`` (the capacity then doubles as
            needed, and the cost of a step grows with the samples held).
        capacity: initial room for samples per environment without a window (default 32).
        block_bytes: CPU only: environments are updated in blocks whose working set is about this size,
            so that a step reads and writes each environment's state once from memory (default 32 MiB: the
            estimate leaves out the step's temporaries, and each block costs a few hundred small operations;
            on this project's 2-core EPYC (32 MiB L3), B = 4096, M = 10, window 16: 8 / 16 / 32 / 64 MiB gave
            19.7k / 27.1k / 28.9k env-steps/s in float64 and 32.1k / 38.9k / 43.6k / 48.1k in float32).
        hypers: the hyperparameters to use instead of the model's own (an ``RFTHyperparameters``: one draw of
            its hyperparameter posterior, as ``TerrainFilterMixture`` builds one filter per draw).

    Example:
        >>> filt = irft.TerrainFilter(model, n_envs=4096, window=16)
        >>> filt.update(contacts, forces)                 # contacts (B, M), forces (B, 2) N; mask= (B,)
        >>> post = filt.stress_map(beta, gamma)           # .mean, .variance (B, Q, 2) in N/cm^3
        >>> filt.reset(done)                              # those environments back to the prior
    """

    # buffers (register_buffer): the hyperparameters and each environment's state (see __init__)
    lengthscale: Tensor
    outputscale: Tensor
    noise: Tensor
    mean_scales: Tensor | None
    li_variance: Tensor | None
    li_covariance: Tensor | None
    count: Tensor
    start: Tensor
    U: Tensor
    z: Tensor
    emb: Tensor
    cp: Tensor
    wt: Tensor
    lf: Tensor
    loc: Tensor
    At: Tensor
    post_mean: Tensor
    post_var: Tensor

    def __init__(self, model: InverseRFT, n_envs: int, window: int | None = None, capacity: int = 32,
                 block_bytes: int = 32 << 20, hypers=None) -> None:
        super().__init__()
        if not isinstance(model, InverseRFT):
            raise TypeError(f"model must be an irft_torch.InverseRFT (fitted), got {type(model).__name__}")
        for name, v, low in (("n_envs", n_envs, 1), ("capacity", capacity, 1), ("block_bytes", block_bytes, 1)):
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if window is not None and (isinstance(window, bool) or not isinstance(window, int) or window < 1):
            raise ValueError(f"window must be None or a positive integer number of samples, got {window!r}")
        hypers = model.hypers if hypers is None else hypers  # another draw's (``TerrainFilterMixture``)
        self.dtype = model.dtype
        self.device = torch.device(model._device)
        self.n_envs = B = n_envs
        self.window = window
        self.block_bytes = block_bytes
        N = window or capacity
        dt, dev = self.dtype, self.device
        with torch.no_grad():
            self.register_buffer("lengthscale",
                                 hypers.lengthscale.detach().clone().to(dtype=dt, device=dev))  # (2, 1, 4)
            self.register_buffer("outputscale",
                                 hypers.outputscale.detach().clone().to(dtype=dt, device=dev))  # (2,)
            self.register_buffer("noise", hypers.noise.detach().clone().to(dtype=dt, device=dev))  # (2,)
            scales = hypers.mean_scales
            self.register_buffer("mean_scales",
                                 None if scales is None else scales.detach().clone().to(dtype=dt, device=dev))
            li = hypers.li_variance  # (2,) (N/cm^3)^2: Li et al.'s term, or None
            self.register_buffer("li_variance", None if li is None else li.detach().clone().to(dtype=dt, device=dev))
            P = hypers.li.covariance if hypers.li is not None and hypers.li.generic else None  # (2, 9, 9) or None
            self.register_buffer("li_covariance", None if P is None else P.detach().clone().to(dtype=dt, device=dev))
        sp = getattr(hypers, "spatial", None)  # the spatial factor (gp.kernels.spatial), or None
        self.spatial = sp is not None
        # its gpytorch kernel v k_s (ScaleKernel(MaternKernel(nu=2.5)), batch (2,)), copied like the prior mean's shape
        self._spatial = (None if sp is None
                         else copy.deepcopy(sp.kernel).to(dtype=dt, device=dev).requires_grad_(False))
        self._shape = (None if hypers.mean is None
                       else copy.deepcopy(hypers.mean).to(dtype=dt, device=dev).requires_grad_(False))
        # The state of environment b, map axis a (the module docstring): n = capacity sample positions
        self.register_buffer("count", torch.zeros(B, dtype=torch.long, device=dev))  # samples held
        self.register_buffer("start", torch.zeros(B, dtype=torch.long, device=dev))  # ring slot of oldest sample
        # U^T, Cholesky order
        self.register_buffer("U", torch.eye(N, dtype=dt, device=dev).expand(B, 2, N, N).clone())
        self.register_buffer("z", torch.zeros(B, 2, N, dtype=dt, device=dev))  # U (y - m), Cholesky order
        # [phi; 1] of the samples' segments, by slot
        self.register_buffer("emb", torch.zeros(B, 5, 0, dtype=dt, device=dev))
        self.register_buffer("cp", torch.zeros(B, 2, 0, dtype=dt, device=dev))  # -|phi / l_a|^2 / 2 of the same
        self.register_buffer("wt", torch.zeros(B, 2, N, 0, dtype=dt, device=dev))  # their weights (x, z), by slot
        # Li et al.'s term: each sample's weighted features per axis (B, 2, N, 9) by slot (9 -> 0 without it)
        self.register_buffer("lf", torch.zeros(B, 2, N, 0 if li is None else 9, dtype=dt, device=dev))
        # a spatial model's samples' places (B, N, 2) in m by slot ((B, N, 0) without one)
        self.register_buffer("loc", torch.zeros(B, N, 2 if self.spatial else 0, dtype=dt, device=dev))
        # the tracked map points: A^T (B, 2, Q, n) and the posterior there (B, 2, Q), kept current
        self.register_buffer("At", torch.zeros(B, 2, 0, N, dtype=dt, device=dev))
        self.register_buffer("post_mean", torch.zeros(B, 2, 0, dtype=dt, device=dev))
        self.register_buffer("post_var", torch.zeros(B, 2, 0, dtype=dt, device=dev))
        # key (angles), emb (5, Q), cp (2, 1, Q), w (2, Q), li (2, Q, 9) or None, places (B, L, 2) or None (the
        # shared medium; L = 1), prior mean / var (2, L Q)
        self._query: dict | None = None
        self._exported = False  # a query's autograd graph holds the state: copy it before writing in place

    # ---- sizes -------------------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        """Sample positions per environment (the window, or the current capacity without one)."""
        return self.U.shape[-1]

    @property
    def n_segments(self) -> int:
        return self.wt.shape[-1]

    def extra_repr(self) -> str:
        return (f"n_envs={self.n_envs}, window={self.window}, capacity={self.capacity}, M={self.n_segments}, "
                f"spatial={self.spatial}, dtype={self.dtype}, device={self.device}")

    # ---- the kernel pieces ------------------------------------------------------------------------
    def _sides(self, beta: Tensor, gamma: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Angles (..., M) -> the left side (..., 2, M, 5) = [phi / l_a^2, log s_a - |phi / l_a|^2 / 2] and
        the right side [phi; 1] (..., 5, M), c (..., 2, 1, M) = -|phi / l_a|^2 / 2, so that
        left . right + c = log s_a - |(phi - phi') / l_a|^2 / 2: the exponent of ``embedding.rbf``."""
        phi = embed_angles(beta, gamma)  # (..., M, 4)
        ls = self.lengthscale.view(2, 1, 4)
        scaled = phi.unsqueeze(-3) / ls  # (..., 2, M, 4)
        half = -0.5 * scaled.pow(2).sum(-1)  # (..., 2, M)
        left = torch.cat([scaled / ls, (self.outputscale.log()[:, None] + half)[..., None]], -1)
        right = torch.cat([phi, torch.ones_like(phi[..., :1])], -1).mT
        return left, right, half.unsqueeze(-2)

    def _prior_mean(self, c: Contacts) -> Tensor | None:
        """The prior mean (..., 2) of the weighted sums of contacts (..., M), or None (zero mean)."""
        if self._shape is None:
            return None
        lead, M = c.shape[:-1], c.n_segments
        flat = Contacts(c.beta.reshape(-1, M), c.gamma.reshape(-1, M), c.weight_x.reshape(-1, M),
                        c.weight_z.reshape(-1, M))
        return (self.mean_scales[:, None] * self._shape.shape_forces(flat)).T.reshape(*lead, 2)

    @staticmethod
    def _kernel(left: Tensor, w_left: Tensor, right: Tensor, c_right: Tensor, w_right: Tensor) -> Tensor:
        """Prior covariances of weighted sums, per item and axis: sum_{m, m'} w_left[p, m] k(p_m, r_m')
        w_right[r, m'] from left (X, 2, P * Ml, 5), w_left (X, 2, P, Ml), right (X, 5, R * Mr),
        c_right (X, 2, 1, R * Mr), w_right (X, 2, R, Mr) (X may be 1 on the right: shared) -> (X, 2, P, R)."""
        X, _, PM, _ = left.shape
        P, Ml = w_left.shape[-2:]
        R, Mr = w_right.shape[-2:]
        if right.shape[0] == X:
            E = torch.bmm(left.reshape(X, 2 * PM, 5), right).view(X, 2, PM, R * Mr)
        else:
            E = (left.reshape(X * 2 * PM, 5) @ right[0]).view(X, 2, PM, R * Mr)
        grad = torch.is_grad_enabled() and any(t.requires_grad for t in (left, w_left, right, c_right, w_right))
        E = (E + c_right).exp() if grad else E.add_(c_right).exp_()
        r = (w_left[..., None, :] @ E.view(X, 2, P, Ml, R * Mr)).view(X, 2, P, R, Mr)
        return (r * w_right.unsqueeze(2)).sum(-1)

    def _li_features(self, beta: Tensor, gamma: Tensor, w: Tensor) -> Tensor | None:
        """The term's features of weighted sums: angles (..., P, M), weights (..., 2, P, M) -> (..., 2, P, 9)
        (cm^3), or None without the term."""
        if self.li_variance is None:
            return None
        return weighted_li_features(beta.unsqueeze(-3), gamma.unsqueeze(-3), w)  # the angles shared by both axes

    def _li_cross(self, f_left: Tensor, f_right: Tensor) -> Tensor:
        """f_left P_a f_right^T: (X, 2, P, 9), (X, 2, R, 9) (X may be 1 on the right) -> (X, 2, P, R)."""
        return self._li_weigh(f_left) @ f_right.mT

    def _li_weigh(self, f: Tensor) -> Tensor:
        """f P_a per map (..., 2, P, 9): diag(v_a) without the generic shape (9 products a row), P_a with it."""
        return f * self.li_variance[:, None, None] if self.li_covariance is None else f @ self.li_covariance

    @property
    def spatial_variance(self) -> Tensor:
        """(2,) v per map: the spatial variation's variance relative to the shared medium (a spatial filter)."""
        return self._spatial.outputscale

    def _factor(self, s1: Tensor, s2: Tensor) -> Tensor:
        """The spatial factor 1 + v_a k_5/2(|s1 - s2| / l_a) per map between places s1 (..., P, 2) and s2
        (..., R, 2) in m: (..., 2, P, R), from the model's own gpytorch kernel."""
        x1 = s1.unsqueeze(-3).expand(*s1.shape[:-2], 2, *s1.shape[-2:])
        x2 = s2.unsqueeze(-3).expand(*s2.shape[:-2], 2, *s2.shape[-2:])
        return 1 + to_dense(self._spatial(x1, x2))

    def _places(self, locations, want: tuple[int, ...], name: str) -> Tensor | None:
        """``locations`` checked against a spatial model: (*want, 2) places in m, finite; None where the filter is
        not spatial, or (queries) the shared medium."""
        if locations is None:
            return None
        if not self.spatial:
            raise ValueError(f"{name} given, but the model has no spatial factor (a model fitted with "
                             "InverseRFT(..., locations=xy) gives a spatial filter)")
        s = torch.as_tensor(locations, dtype=self.dtype, device=self.device)
        if tuple(s.shape) != (*want, 2):
            raise ValueError(f"{name} must have shape {(*want, 2)} (x, y in m), got {tuple(s.shape)}")
        if not torch.isfinite(s).all():
            raise ValueError(f"{name} contains NaN or inf")
        return s

    def _blocks(self, per_env: int) -> list[tuple[int, int]]:
        """Ranges of environments whose working set (``per_env`` elements each) fits ``block_bytes``; one
        range on a GPU. Blocks of many environments, each computed at once (never one environment at a time)."""
        B = self.n_envs
        if self.device.type != "cpu":
            return [(0, B)]
        size = max(1, self.block_bytes // max(1, per_env * self.U.element_size()))
        return [(i, min(B, i + size)) for i in range(0, B, size)]

    # ---- input checks -----------------------------------------------------------------------------
    def _contacts(self, contacts, name: str, shapes: str, ndims: tuple[int, ...]) -> Contacts:
        if not isinstance(contacts, Contacts):
            raise TypeError(f"{name} must be an irft_torch.rft.Contacts, got {type(contacts).__name__}")
        shape = tuple(contacts.shape)
        if contacts.beta.ndim not in ndims or shape[0] != self.n_envs:
            raise ValueError(f"{name} must have shape {shapes} with B = n_envs = {self.n_envs}, got {shape}")
        return contacts.to(dtype=self.dtype, device=self.device)

    # ---- updates ----------------------------------------------------------------------------------
    @torch.no_grad()
    def update(self, contacts: Contacts, forces, mask=None, locations=None) -> TerrainFilter:
        """Add one sample per environment (contacts (B, M), forces (B, 2) = (F_x, F_z) in N), or t per
        environment in time order (contacts (B, t, M), forces (B, t, 2)). ``mask`` (B,) or (B, t) bool:
        False leaves that sample out (the environment is unchanged by it, and it does not count toward the
        window). ``locations`` (B, 2) or (B, t, 2): each sample's place in m (its foothold), required by a spatial
        filter and refused by any other. Returns self."""
        c = self._contacts(contacts, "contacts", "(B, M) or (B, t, M)", (2, 3))
        block = c.beta.ndim == 3
        want = (self.n_envs, *(c.shape[1:2] if block else ()), 2)
        f = torch.as_tensor(forces, dtype=self.dtype, device=self.device)
        if tuple(f.shape) != want:
            raise ValueError(f"forces must have shape {want} (F_x, F_z in N) for contacts of shape "
                             f"{tuple(c.shape)}, got {tuple(f.shape)}")
        if not torch.isfinite(f).all():
            raise ValueError("forces contains NaN or inf: leave those samples out with mask=")
        if mask is not None:
            mask = torch.as_tensor(mask, device=self.device)
            if mask.dtype != torch.bool or tuple(mask.shape) != want[:-1]:
                raise ValueError(f"mask must be a bool tensor of shape {want[:-1]} (True: add the sample), got "
                                 f"{mask.dtype} of shape {tuple(mask.shape)}")
        s = self._places(locations, want[:-1], "locations")
        if self.spatial and s is None:
            raise ValueError(f"locations is required: the model is spatial, so each sample needs its place, shape "
                             f"{(*want[:-1], 2)} (x, y in m)")
        if not block:
            self._append(c, f, mask, s)
            return self
        for i in range(c.shape[1]):  # a block's samples in time order, each step vectorised over environments
            self._append(c[i], f[:, i], None if mask is None else mask[:, i],
                         None if s is None else s[:, i])  # c[i]: sample i of each
        return self

    def _state_names(self) -> tuple[str, ...]:
        return ("U", "z", "emb", "cp", "wt", "lf", "loc", "At", "post_mean", "post_var")

    def _own_state(self) -> None:
        """Copy the state before writing it in place if a query's autograd graph may hold it."""
        if self._exported:
            for name in self._state_names():
                setattr(self, name, getattr(self, name).clone())
            self._exported = False

    def _resize(self, N2: int, M2: int) -> None:
        """Room for N2 samples of M2 segments (no window: the capacity doubles; wider samples): identity
        rows and columns in U, zeros elsewhere."""
        B, N, M = self.n_envs, self.capacity, self.n_segments
        if N2 > N:
            U = torch.eye(N2, dtype=self.dtype, device=self.device).expand(B, 2, N2, N2).clone()
            U[..., :N, :N] = self.U
            self.U = U
            self.z = torch.nn.functional.pad(self.z, (0, N2 - N))
            self.At = torch.nn.functional.pad(self.At, (0, N2 - N))
        self.emb = pad_slots(self.emb, N, M, N2, M2)
        self.cp = pad_slots(self.cp, N, M, N2, M2)
        self.wt = torch.nn.functional.pad(self.wt, (0, M2 - M, 0, N2 - N))
        self.lf = torch.nn.functional.pad(self.lf, (0, 0, 0, N2 - N))
        self.loc = torch.nn.functional.pad(self.loc, (0, 0, 0, N2 - N))

    def _append(self, c: Contacts, f: Tensor, mask: Tensor | None, s: Tensor | None = None) -> None:
        """One sample per environment (c (B, M), f (B, 2)); ``mask`` (B,) or None; places s (B, 2) m or None."""
        self._own_state()
        B = self.n_envs
        add = torch.ones(B, dtype=torch.bool, device=self.device) if mask is None else mask
        full = add & (self.count >= self.capacity)
        any_full = bool(full.any())
        grow = any_full and self.window is None
        if grow or c.n_segments > self.n_segments:
            self._resize(2 * self.capacity if grow else self.capacity, max(c.n_segments, self.n_segments))
        if grow:
            full, any_full = torch.zeros_like(full), False
        N, M = self.capacity, self.n_segments
        c = c.pad_segments(M)
        left, right, c_right = self._sides(c.beta, c.gamma)  # (B, 2, M, 5), (B, 5, M), (B, 2, 1, M)
        w = torch.stack([c.weight_x, c.weight_z], 1)  # (B, 2, M)
        fl = self._li_features(c.beta[:, None], c.gamma[:, None], w[:, :, None])  # (B, 2, 1, 9) or None
        m = self._prior_mean(c)
        y = f if m is None else f - m
        # where each sample goes, after the oldest is forgotten in the full environments
        start = torch.where(full, (self.start + 1) % N, self.start) if any_full else self.start
        held = self.count - full.long()
        pos = held.clamp_max(N - 1)
        slot = (start + pos) % N
        per_env = 2 * (2 * N * N + 2 * M * N * M + 2 * N * max(1, self.At.shape[-2])) + 8 * N * M
        for i, j in self._blocks(per_env):
            sl = slice(i, j)
            self._step(sl, left[sl], right[sl], c_right[sl], w[sl], None if fl is None else fl[sl], y[sl],
                       None if mask is None else add[sl], full[sl] if any_full else None, start[sl], held[sl],
                       pos[sl], slot[sl], None if s is None else s[sl])
        self.start = start
        self.count = held + add.long()

    def _step(self, sl: slice, left, right, c_right, w, fl, y, add, full, start, held, pos, slot, s=None) -> None:
        """The update of the environments ``sl`` (one block: everything below stays in cache)."""
        b = left.shape[0]
        N, M = self.capacity, self.n_segments
        U, z, At = self.U[sl], self.z[sl], self.At[sl]
        if full is not None and bool(full.any()):
            forget_oldest(U, z, At, full)
        w4 = w.view(b, 2, 1, M)
        k_new = self._kernel(left, w4, right, c_right, w4).view(b, 2)
        k = self._kernel(left, w4, self.emb[sl], self.cp[sl].unsqueeze(-2), self.wt[sl]).view(b, 2, N)
        if fl is not None:  # Li et al.'s term (by slot, like k)
            k_new = k_new + self._li_cross(fl, fl).view(b, 2)
            k = k + self._li_cross(fl, self.lf[sl]).view(b, 2, N)
        if s is not None:  # a spatial model: the factor between the new place and each slot's (by slot, like k)
            k = k * self._factor(s[:, None], self.loc[sl]).view(b, 2, N)
            k_new = k_new * (1 + self.spatial_variance)
        order = (start[:, None] + torch.arange(N, device=self.device)) % N  # Cholesky position -> ring slot
        k = k.gather(-1, order[:, None, :].expand(b, 2, N))
        k.mul_((torch.arange(N, device=self.device) < held[:, None])[:, None, :])  # only the samples held
        X = 2 * b
        Uv = U.view(X, N, N)
        l = torch.bmm(k.view(X, 1, N), Uv).view(b, 2, N)  # U k (U is held transposed)
        d = (k_new + self.noise - l.pow(2).sum(-1)).clamp_min(self.noise).sqrt()  # (b, 2), >= sigma
        row = torch.bmm(Uv, l.view(X, N, 1)).view(b, 2, N).neg_()  # -(l^T U): the new row of U
        row.scatter_(-1, pos.view(b, 1, 1).expand(b, 2, 1), 1.0).div_(d[..., None])
        z_new = (y - (l * z).sum(-1)) / d
        keep = None if add is None else ~add

        def put(t: Tensor, dim: int, idx: Tensor, value: Tensor) -> None:
            """t[idx] = value along dim, in the environments that add a sample."""
            if keep is not None:
                value = torch.where(keep.view(b, *[1] * (t.ndim - 1)), t.gather(dim, idx), value)
            t.scatter_(dim, idx, value)

        put(U, -1, pos.view(b, 1, 1, 1).expand(b, 2, N, 1), row[..., None])
        put(z, -1, pos.view(b, 1, 1).expand(b, 2, 1), z_new[..., None])
        cols = slot[:, None] * M + torch.arange(M, device=self.device)
        put(self.emb[sl], -1, cols[:, None, :].expand(b, 5, M), right)
        put(self.cp[sl], -1, cols[:, None, :].expand(b, 2, M), c_right[:, :, 0])
        put(self.wt[sl], -2, slot.view(b, 1, 1, 1).expand(b, 2, 1, M), w4)
        if fl is not None:
            put(self.lf[sl], -2, slot.view(b, 1, 1, 1).expand(b, 2, 1, 9), fl)
        if s is not None:
            put(self.loc[sl], -2, slot.view(b, 1, 1).expand(b, 1, 2), s[:, None])
        q = self._query
        if q is not None:  # the tracked points: a new row of A, and the posterior there
            Q = q["w"].shape[-1]
            kq = self._kernel(left, w4, q["emb"][None], q["cp"][None], q["w"][None, :, :, None]).view(b, 2, Q)
            if fl is not None:
                kq = kq + self._li_cross(fl, q["li"][None]).view(b, 2, Q)
            if q["loc"] is not None:  # each place asked about: the angle part times the factor to the new place
                L = q["loc"].shape[1]
                kq = (kq[:, :, None, :] * self._factor(s[:, None], q["loc"][sl]).view(b, 2, L, 1)).reshape(b, 2, L * Q)
                Q = L * Q
            a_new = torch.baddbmm(kq.view(X, Q, 1), At.view(X, Q, N), l.view(X, N, 1), alpha=-1).view(b, 2, Q)
            put(At, -1, pos.view(b, 1, 1, 1).expand(b, 2, Q, 1), a_new.div_(d[..., None])[..., None])
            self._posterior_into(At, z, self.post_mean[sl], self.post_var[sl])

    def _posterior_into(self, At: Tensor, z: Tensor, mean: Tensor, var: Tensor) -> None:
        """The tracked points' posterior from A^T (b, 2, Q, n) and z (b, 2, n), written into mean and var."""
        q = self._query
        torch.matmul(At, z[..., None], out=mean[..., None])
        mean.add_(q["prior_mean"])
        torch.sub(q["prior_var"], torch.linalg.vector_norm(At, dim=-1).pow_(2), out=var)

    @torch.no_grad()
    def reset(self, env_ids=None) -> TerrainFilter:
        """Return environments to the prior (forget all their samples): ``env_ids`` integer indices, a bool
        mask (B,) or None (all). Returns self."""
        ids = env_index(env_ids, self.n_envs, self.device)
        if ids.numel() == 0:
            return self
        self._own_state()
        self.U[ids] = torch.eye(self.capacity, dtype=self.dtype, device=self.device)
        for t in (self.z, self.emb, self.cp, self.wt, self.lf, self.loc, self.At):
            t[ids] = 0.0
        if self._query is not None:  # the prior, exactly
            self.post_mean[ids] = self._query["prior_mean"]
            self.post_var[ids] = self._query["prior_var"]
        self.count[ids] = 0
        self.start[ids] = 0
        return self

    # ---- queries ----------------------------------------------------------------------------------
    def _cross_t(self, left: Tensor, w: Tensor, fl: Tensor | None, places: Tensor | None = None) -> Tensor:
        """K^T (B, 2, P, n): the prior covariance of P functionals per environment (left sides
        (B, 2, P * Ml, 5), weights (B, 2, P, Ml), the term's features (B, 2, P, 9) or None; expanded views are
        fine; a spatial filter's places (B, L, 2) m, L dividing P, each the place of P / L consecutive functionals,
        or None: the shared medium) with the samples held, in Cholesky order (zero past them)."""
        B, N, M = self.n_envs, self.capacity, self.n_segments
        P = w.shape[-2]
        if torch.is_grad_enabled() and (left.requires_grad or w.requires_grad):
            self._exported = True  # the graph holds the state: the next update copies it first
        if M == 0:
            return left.new_zeros(B, 2, P, N)
        per_env = 2 * P * w.shape[-1] * N * M
        parts = [self._kernel(left[i:j], w[i:j], self.emb[i:j], self.cp[i:j].unsqueeze(-2), self.wt[i:j])
                 for i, j in self._blocks(per_env)]
        K = torch.cat(parts) if len(parts) > 1 else parts[0]
        if fl is not None:
            K = K + self._li_cross(fl, self.lf)  # zero features in the empty slots
        if places is not None:  # one factor per place, shared by its functionals
            L = places.shape[1]
            K = (K.view(B, 2, L, P // L, N) * self._factor(places, self.loc).unsqueeze(-2)).view(B, 2, P, N)
        order = (self.start[:, None] + torch.arange(N, device=self.device)) % N
        return K.gather(-1, order[:, None, None, :].expand(B, 2, P, N))

    def stress_map(self, beta, gamma, locations=None) -> Posterior:
        """Each environment's posterior of (alpha_x, alpha_z) at angles (rad) of any broadcast shape S, the
        same points for every environment (per-environment points: ``predict_forces`` of one-segment
        contacts of unit weight, ``Contacts.points``). Returns mean and variance (B, *S, 2) in N/cm^3 and
        (N/cm^3)^2. A spatial filter takes ``locations``: (B, 2), each environment's place in m (result
        (B, *S, 2)), or (B, L, 2), L places each (result (B, L, *S, 2)); None: the medium shared by the site. (The
        same L places for every environment: expand them to (B, L, 2); an (L, 2) tensor is read as one place per
        environment.)

        The last points asked are *tracked*: every later ``update`` extends their posterior, so asking
        them again costs nothing more. Differentiable in beta and gamma (then computed afresh)."""
        beta = torch.as_tensor(beta, dtype=self.dtype, device=self.device)
        gamma = torch.as_tensor(gamma, dtype=self.dtype, device=self.device)
        S = torch.broadcast_shapes(beta.shape, gamma.shape)
        B = self.n_envs
        shape = tuple(torch.as_tensor(locations).shape) if locations is not None else ()
        if locations is not None and self.spatial and len(shape) not in (2, 3):
            raise ValueError(f"locations must have shape (B, 2) or (B, L, 2) (x, y in m) with B = n_envs = {B}, got "
                             f"{shape}")
        one_place = len(shape) == 2
        where = self._places(locations, (B,) if one_place else (B, shape[1] if len(shape) == 3 else 1), "locations")
        if where is not None and one_place:
            where = where[:, None]  # (B, L, 2)
        L = 1 if where is None else where.shape[1]
        lead = (B, *S) if where is None or one_place else (B, L, *S)
        grad = torch.is_grad_enabled() and (beta.requires_grad or gamma.requires_grad)
        key = torch.stack(torch.broadcast_tensors(beta, gamma)).reshape(2, -1).detach()
        q = self._query
        same = (q is not None and q["key"].shape == key.shape and torch.equal(q["key"], key)
                and (q["loc"] is None) == (where is None) and (where is None or (q["loc"].shape == where.shape
                                                                                and torch.equal(q["loc"], where))))
        if not grad and same:
            mean, var = self.post_mean, self.post_var
        else:
            pts = Contacts.points(beta, gamma)  # (Q, 1): canonical angles, weights (mirror sign, 1)
            w = torch.stack([pts.weight_x[:, 0], pts.weight_z[:, 0]])  # (2, Q)
            Q = w.shape[-1]
            prior = self._prior_mean(pts)
            prior = w.new_zeros(2, Q) if prior is None else prior.T
            prior_var = self.outputscale[:, None] * w.pow(2)  # k(theta, theta) w^2 = s
            fq = self._li_features(pts.beta, pts.gamma, w[..., None])  # (2, Q, 9) or None
            if fq is not None:
                prior_var = prior_var + (self._li_weigh(fq) * fq).sum(-1)
            if where is not None:  # at a place: the shared medium and the variation there
                prior_var = prior_var * (1 + self.spatial_variance[:, None])
            prior, prior_var = prior.repeat(1, L), prior_var.repeat(1, L)  # (2, L Q), place-major
            left, right, c_right = self._sides(pts.beta[:, 0], pts.gamma[:, 0])  # (2, Q, 5), (5, Q), (2, 1, Q)
            P = L * Q
            left_q = left.unsqueeze(0).unsqueeze(2).expand(B, 2, L, Q, 5).reshape(B, 2, P, 5)
            fq_b = None if fq is None else fq.unsqueeze(1).expand(2, L, Q, 9).reshape(2, P, 9).expand(B, 2, P, 9)
            K_t = self._cross_t(left_q, w.repeat(1, L)[None, :, :, None].expand(B, 2, P, 1), fq_b, where)
            At = K_t @ self.U
            if grad:
                mean = prior[..., None] + At @ self.z[..., None]
                return Posterior((mean[..., 0]).mT.reshape(*lead, 2),
                                 (prior_var - At.pow(2).sum(-1)).mT.reshape(*lead, 2))
            self._query = {"key": key.clone(), "emb": right, "cp": c_right, "w": w, "li": fq,
                           "loc": None if where is None else where.clone(), "prior_mean": prior,
                           "prior_var": prior_var}
            self.At = At
            self.post_mean, self.post_var = At.new_empty(B, 2, P), At.new_empty(B, 2, P)
            self._posterior_into(At, self.z, self.post_mean, self.post_var)
            mean, var = self.post_mean, self.post_var
        return Posterior(mean.mT.reshape(*lead, 2).clone(), var.mT.reshape(*lead, 2).clone())

    def predict_forces(self, contacts: Contacts, include_noise: bool = False, locations=None) -> Posterior:
        """Each environment's posterior of the forces (F_x, F_z) on its own contacts (B, T, M): mean and
        variance (B, T, 2) in N and N^2 (the exact variance w^T Sigma w, segments correlated);
        ``include_noise`` adds the noise variance (predict a measurement). A spatial filter takes each sample's
        place, ``locations`` (B, T, 2) in m (None: the shared medium's forces). Differentiable in the contacts'
        angles and weights."""
        c = self._contacts(contacts, "contacts", "(B, T, M)", (3,))
        B, T, M = c.shape
        places = self._places(locations, (B, T), "locations")
        left, right, c_right = self._sides(c.beta, c.gamma)  # (B, T, 2, M, 5), (B, T, 5, M), (B, T, 2, 1, M)
        w = torch.stack([c.weight_x, c.weight_z], 1)  # (B, 2, T, M)
        fl = self._li_features(c.beta, c.gamma, w)  # (B, 2, T, 9) or None
        At = self._cross_t(left.transpose(1, 2).reshape(B, 2, T * M, 5), w, fl, places) @ self.U  # (B, 2, T, n)
        mean = (At @ self.z[..., None])[..., 0]
        prior = self._prior_mean(c)
        if prior is not None:
            mean = mean + prior.mT
        w_own = w.transpose(1, 2).reshape(B * T, 2, 1, M)
        own = self._kernel(left.reshape(B * T, 2, M, 5), w_own, right.reshape(B * T, 5, M),
                           c_right.reshape(B * T, 2, 1, M), w_own).view(B, T, 2)
        if fl is not None:
            own = own + (self._li_weigh(fl) * fl).sum(-1).mT
        if places is not None:
            own = own * (1 + self.spatial_variance)
        var = own - At.pow(2).sum(-1).mT
        if include_noise:
            var = var + self.noise
        return Posterior(mean.mT, var)
