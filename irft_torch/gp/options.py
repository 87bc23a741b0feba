"""The front door's named choices: ``MapPrior`` (what the maps are before the data) and ``Engine`` (how they are
computed), and the translation of the former flat keywords (``li_basis=``, ``method=``, ...) into them.

``InverseRFT(contacts, forces, locations=None, *, prior=None, hyper_posterior=None, surface=None, engine=None,
noise_scale=None, statistics=None)``: the planar model; ``InverseRFT3D`` takes ``prior``, ``hyper_posterior``,
``alpha_y``, ``engine`` and ``features``. A field left None takes the model's default (the planar and 3-D models
differ in the kernel and the prior mean). The flat keywords still work and warn once per call site
(``DeprecationWarning``, naming the new spelling); they will be removed in 0.4.
"""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import torch

__all__ = ["MapPrior", "Engine", "KERNELS", "planar_options", "options_3d", "grouped", "grouped_3d"]

KERNELS = ("li", "rbf", "li+generic")
DEFAULTS = {"InverseRFT": {"kernel": "li", "mean": "zero"}, "InverseRFT3D": {"kernel": "rbf", "mean": "physics"},
            # maps over the ground (InverseRFT(..., locations=xy)): Li et al.'s generic shape as a term too, so its
            # scale can vary over the ground (docs/terrain.md: below every baseline on walks, own and held-out media)
            "InverseRFT spatial": {"kernel": "li+generic", "mean": "zero"}}
REMOVED_IN = "0.4"


@dataclass(frozen=True)
class MapPrior:
    """What the stress maps are before the data. None: the model's default (planar, over the ground / 3-D).

    Args:
        kernel: "li" (planar default; with ``locations``, "li+generic"): the RBF on the angle torus plus Li et al.'s
            9 functions {1, cos 2beta, sin 2beta} x {1, cos gamma, sin gamma} as a term with its own variance per map
            (``gp.kernels.li_basis``):
            what the forces leave unseen follows shapes real media have (docs/calibration.md). "rbf" (3-D
            default): the paper's RBF alone (Table I / II). "li+generic": also Li et al.'s generic map with a scale
            of its own, integrated out; its niche: media known to share the generic shape seen through a narrow
            slice of angles (a leg rotating about its hip: alpha_z coverage 0.98 against 0.84), and maps over the
            ground (the spatial default: its scale varies over the ground; walks over two media, a gradient and
            patches, own and held-out media: below every baseline, docs/terrain.md); it loses the planar wheels'
            vertical force beyond the spread (planar only).
        mean: the prior mean. "zero" (planar default, the paper). "physics" (3-D default: Li et al.'s generic
            shape x learned scales): wins on the rover wheels in 3-D and on walks over media of the generic shape
            (docs/terrain.md); on the DEM plate it is worse in z (docs/experiments.md). "average" (planar: both,
            weighed per map by their evidence, ``gp.mean_average``): for flat beds known to be of the generic
            shape, about 2.3x a plug-in fit. 3-D also takes the names of ``gp.inverse3d`` mean maps.
        hyperpriors: "physical" (default): hyperparameter priors with a physical meaning (``gp.kernels.priors``),
            fitted by MAP (they keep a vertical intrusion's alpha_x from an 845-sigma error, docs/guide.md); None: the
            paper's plain marginal likelihood, as Table I / II (its hyperparameter posterior is improper, so
            ``hyper_posterior`` defaults to "map").
        noise: "per_axis" (default): one noise variance per force axis; "tied": one for both (the paper's, which
            Table I / II reproduce; planar only).
        lengthscale: initial lengthscale of every embedding dimension (default 1.0). Where the data never vary an
            angle (an I-toe samples beta = 0 only) the likelihood cannot move it: it sets how far the map
            extrapolates.
    """

    kernel: str | None = None
    mean: str | None = None
    hyperpriors: str | None = "physical"
    noise: str = "per_axis"
    lengthscale: float = 1.0

    def __post_init__(self) -> None:
        if self.kernel is not None and self.kernel not in KERNELS:
            raise ValueError(f"MapPrior(kernel=...) must be one of {KERNELS}, got {self.kernel!r}")
        if self.hyperpriors not in ("physical", None):
            raise ValueError(f"MapPrior: hyperpriors must be 'physical' or None (the plain marginal likelihood), got "
                             f"{self.hyperpriors!r}")
        if self.noise not in ("per_axis", "tied"):
            raise ValueError(f"MapPrior(noise=...) must be 'per_axis' or 'tied', got {self.noise!r}")


@dataclass(frozen=True)
class Engine:
    """How the posterior is computed; exact in every space up to the spectral basis' stated ``tol``.

    Args:
        method: "auto" (default): the cheapest space for the data, moved as the fit goes (planar:
            ``gp.backends.estimated_costs``); "observations" (or "exact"), "pairs", "spectral"; the 3-D model takes
            ``gp.inverse3d`` methods.
        tol: spectral backend: bound on the kernel's relative truncation error (default 1e-7).
        dtype: float64 (default) or float32.
        max_harmonics: 3-D spectral backend: a cap on the Fourier basis per angle (None: the library's).
    """

    method: str = "auto"
    tol: float = 1e-7
    dtype: torch.dtype = torch.float64
    max_harmonics: int | None = None


# the former flat keywords: where each went
_PRIOR_KEYS = ("li_basis", "generic_shape", "prior_mean", "priors", "tied_noise", "lengthscale")
_ENGINE_KEYS = ("method", "tol", "dtype", "max_harmonics")
_SURFACE_KEYS = ("surface_offset", "surface_groups")
_OWN_FILES = {str(Path(__file__).resolve()), str(Path(__file__).with_name("model.py").resolve()),
              str((Path(__file__).parent / "inverse3d" / "model.py").resolve()),
              str((Path(__file__).parent / "surface" / "profile.py").resolve())}  # passes the user's options on


def _caller_level() -> int:
    """``warnings.warn``'s stacklevel from here to the first frame outside the constructors: the user's call."""
    frame, level = sys._getframe(1), 2
    while frame is not None and str(Path(frame.f_code.co_filename).resolve()) in _OWN_FILES:
        frame, level = frame.f_back, level + 1
    return level - 1


_PRIOR_FIELD = {"li_basis": "kernel", "generic_shape": "kernel", "prior_mean": "mean", "priors": "hyperpriors",
                "tied_noise": "noise", "lengthscale": "lengthscale"}


def _warn_flat(owner: str, flat: dict, prior: MapPrior, engine: Engine, solver: bool = False) -> None:
    """One DeprecationWarning for the flat keywords of one call, with the new spelling of exactly the values given
    (``prior`` / ``engine``: the groups with them put in), at the caller's line."""
    used = list(flat) + (["solver"] if solver else [])
    new = []
    fields = list(dict.fromkeys(_PRIOR_FIELD[k] for k in flat if k in _PRIOR_FIELD))
    if fields:
        new.append(f"prior=MapPrior({', '.join(f'{f}={getattr(prior, f)!r}' for f in fields)})")
    fields = [k for k in _ENGINE_KEYS if k in flat]
    if fields:
        new.append(f"engine=Engine({', '.join(f'{f}={getattr(engine, f)!r}' for f in fields)})")
    if "surface_groups" in flat and flat["surface_groups"] is not None:
        new.append("surface=<the groups>")
    elif "surface_offset" in flat or "surface_groups" in flat:
        new.append("surface=True" if flat.get("surface_offset") else "surface=None (the default)")
    said = f"pass {', '.join(new)}" if new else ""
    if solver:
        said += ("; " if said else "") + ("solver= has no replacement (no case measured where 'gpytorch', CG / "
                                          "Lanczos, wins; the observations backend factors by Cholesky)")
    warnings.warn(f"{owner}({', '.join(k + '=...' for k in used)}): these keywords are deprecated and will be removed "
                  f"in {REMOVED_IN}; {said}", DeprecationWarning, stacklevel=_caller_level())


def _as_engine(engine, owner: str) -> Engine:
    if engine is None:
        return Engine()
    if isinstance(engine, str):
        return Engine(method=engine)
    if not isinstance(engine, Engine):
        raise TypeError(f"{owner}(engine=...) must be an Engine or a method name, got {type(engine).__name__}")
    return engine


def _with_defaults(prior: MapPrior, owner: str) -> MapPrior:
    """The MapPrior with the model's defaults (``DEFAULTS``) where a field is None."""
    d = DEFAULTS[owner]
    return replace(prior, kernel=prior.kernel or d["kernel"], mean=prior.mean or d["mean"])


def _as_prior(prior, owner: str) -> MapPrior:
    if prior is None:
        return MapPrior()
    if not isinstance(prior, MapPrior):
        raise TypeError(f"{owner}(prior=...) must be a MapPrior, got {type(prior).__name__}")
    return prior


def _split_flat(owner: str, flat: dict, allowed: tuple[str, ...], prior, engine, surface) -> None:
    unknown = [k for k in flat if k not in allowed]
    if unknown:
        raise TypeError(f"{owner}() got an unexpected keyword argument {unknown[0]!r}")
    for group, keys, given in (("prior", _PRIOR_KEYS, prior), ("engine", _ENGINE_KEYS, engine),
                               ("surface", _SURFACE_KEYS, surface)):
        both = [k for k in keys if k in flat]
        if both and given is not None:
            raise TypeError(f"{owner}(): pass {group}= or the deprecated {', '.join(k + '=' for k in both)}, not both")


def _with_flat(prior: MapPrior, engine: Engine, flat: dict) -> tuple[MapPrior, Engine]:
    """The groups with the flat keywords' values put in."""
    p: dict = {}
    if "li_basis" in flat or "generic_shape" in flat:
        li, generic = flat.get("li_basis", True), flat.get("generic_shape", False)
        for name, flag in (("li_basis", li), ("generic_shape", generic)):
            if not isinstance(flag, bool):
                raise TypeError(f"{name} must be True or False, got {flag!r}")
        if generic and not li:
            raise ValueError("generic_shape=True needs li_basis=True: the generic shape is a rank-one update of Li et "
                             "al.'s 9-function term (gp.kernels.li_basis)")
        p["kernel"] = "li+generic" if generic else ("li" if li else "rbf")
    if "prior_mean" in flat:
        p["mean"] = flat["prior_mean"]
    if "priors" in flat:
        p["hyperpriors"] = flat["priors"]
    if "tied_noise" in flat:
        p["noise"] = "tied" if flat["tied_noise"] else "per_axis"
    if "lengthscale" in flat:
        p["lengthscale"] = flat["lengthscale"]
    e = {k: flat[k] for k in _ENGINE_KEYS if k in flat}
    return replace(prior, **p), replace(engine, **e)


def planar_options(prior, engine, surface, flat: dict, spatial: bool = False) -> tuple[MapPrior, Engine, object]:
    """``InverseRFT``'s choices resolved: (MapPrior with the planar defaults, or a spatial model's where ``spatial``,
    Engine, surface: None, True or groups (T,)); ``flat``: the deprecated keywords given (warned once, here).
    ``grid_size`` and ``exact_max_segments`` stay in ``flat`` for the caller (retired, ignored with a FutureWarning)."""
    owner = "InverseRFT"
    retired = {k: flat.pop(k) for k in ("grid_size", "exact_max_segments", "_solver") if k in flat}
    solver = "solver" in flat  # no replacement: nothing measured where CG / Lanczos wins here
    if solver:
        retired["_solver"] = flat.pop("solver")
    _split_flat(owner, flat, _PRIOR_KEYS + ("method", "tol", "dtype") + _SURFACE_KEYS, prior, engine, surface)
    p, e = _with_flat(_as_prior(prior, owner), _as_engine(engine, owner), flat)
    if flat or solver:
        _warn_flat(owner, flat, p, e, solver)
    p = _with_defaults(p, "InverseRFT spatial" if spatial else owner)
    if e.max_harmonics is not None:
        raise ValueError("Engine(max_harmonics=...) is the 3-D spectral backend's cap; the planar one sizes its "
                         "basis by tol")
    if "surface_offset" in flat or "surface_groups" in flat:
        groups = flat.get("surface_groups")
        surface = groups if groups is not None else (True if flat.get("surface_offset") else None)
    if surface is False:
        surface = None
    flat.clear()
    flat.update(retired)
    return p, e, surface


_PLANAR_ONLY = {"locations": "a map that changes over the ground", "surface": "a learned surface offset",
                "noise_scale": "a per-sample noise scale", "statistics": "a recording's precomputed statistics"}


def options_3d(prior, engine, flat: dict) -> tuple[MapPrior, Engine]:
    """``InverseRFT3D``'s choices resolved (MapPrior with the 3-D defaults, Engine); ``flat``: the deprecated
    keywords given (warned once, here)."""
    owner = "InverseRFT3D"
    for key, what in _PLANAR_ONLY.items():  # None: not asked (code that builds either model may pass it)
        if key in flat and flat.pop(key) is not None:
            raise TypeError(f"{owner}() takes no {key}=: {what} is planar only (a planar model: "
                            f"InverseRFT(contacts, forces, {key}=...) with rft.Contacts and (T, 2) forces)")
    _split_flat(owner, flat, ("li_basis", "prior_mean", "priors", "lengthscale") + _ENGINE_KEYS, prior, engine, None)
    p, e = _with_flat(_as_prior(prior, owner), _as_engine(engine, owner), flat)
    if flat:
        _warn_flat(owner, flat, p, e)
    p = _with_defaults(p, owner)
    if p.kernel == "li+generic":
        raise ValueError("MapPrior(kernel='li+generic') is planar only; a 3-D model takes 'rbf' or 'li'")
    if p.noise != "per_axis":
        raise ValueError("MapPrior(noise='tied') is planar only: a 3-D model has one noise variance per axis")
    return p, e


def grouped(options: dict) -> dict:
    """Constructor keywords for ``InverseRFT`` from ``options`` that may hold the flat names
    (``InverseRFT._options()``, a model file's, a study's settings), translated without a warning: the library's own
    translation. Keys that are not options of a group (``hyper_posterior``, ``noise_scale``, ``locations``,
    ``statistics``) pass through; ``prior`` / ``engine`` / ``surface`` given are the start."""
    rest = dict(options)
    flat = {k: rest.pop(k) for k in _PRIOR_KEYS + _ENGINE_KEYS + _SURFACE_KEYS if k in rest}
    for k in ("grid_size", "exact_max_segments", "auto"):
        rest.pop(k, None)
    if rest.get("solver", "cholesky") != "cholesky":
        rest["_solver"] = rest.pop("solver")  # the deprecated solver, kept without a warning
    rest.pop("solver", None)
    prior = _with_defaults(_as_prior(rest.pop("prior", None), "InverseRFT"), "InverseRFT")
    p, e = _with_flat(prior, _as_engine(rest.pop("engine", None), "InverseRFT"), flat)
    if flat.get("surface_groups") is not None:
        rest["surface"] = flat["surface_groups"]
    elif flat.get("surface_offset"):
        rest["surface"] = True
    return {**rest, "prior": p, "engine": e}


def grouped_3d(options: dict) -> dict:
    """``grouped`` for ``InverseRFT3D`` (``alpha_y``, ``hyper_posterior``, ``features`` pass through)."""
    rest = dict(options)
    flat = {k: rest.pop(k) for k in _PRIOR_KEYS + _ENGINE_KEYS if k in rest}
    prior = _with_defaults(_as_prior(rest.pop("prior", None), "InverseRFT3D"), "InverseRFT3D")
    p, e = _with_flat(prior, _as_engine(rest.pop("engine", None), "InverseRFT3D"), flat)
    return {**rest, "prior": p, "engine": e}
