"""The InverseRFT model file (format 2): training data as measured, options, the hyperparameters'
state and a sha256 checksum over all of it. ``load_model`` refuses what does not match with a
``ModelFileError`` that says what to do, and translates 0.1.0's files."""

from __future__ import annotations

import hashlib
import warnings
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from .._files import atomic_write
from ..rft.contacts import Contacts
from .options import grouped

__all__ = ["FILE_FORMAT", "FILE_VERSION", "ModelFileError", "save_model", "load_model", "digest", "model_options",
           "data_digest_of", "refresh_digest", "without_backend", "load_state"]

FILE_FORMAT = "irft_torch.InverseRFT"
FILE_VERSION = 2


class ModelFileError(ValueError):
    """A model file that cannot be loaded as it is (damaged, foreign, or for other data)."""



def digest(obj) -> str:
    """sha256 over every tensor and value in a (nested) dict, in a fixed order: a saved payload's
    checksum, or a fingerprint of training data."""
    h = hashlib.sha256()

    def feed(key, v):
        h.update(str(key).encode())
        if isinstance(v, Tensor):
            a = np.ascontiguousarray(v.detach().cpu().numpy())
            h.update(str(a.dtype).encode() + str(a.shape).encode())
            h.update(a.tobytes())
        elif isinstance(v, dict):
            for k in sorted(v):
                feed(f"{key}.{k}", v[k])
        else:
            h.update(repr(v).encode())

    feed("payload", obj)
    return h.hexdigest()


def save_model(model, path) -> None:
    """Write an ``InverseRFT``'s training data (as measured: the whitening undone), options,
    hyperparameters and a checksum to one file (torch.save), atomically: to a temporary file beside
    it, fsynced, then renamed over ``path`` (``_files.atomic_write``), so a full disk, Ctrl-C or a
    crash leaves the previous file loadable. A folder, a missing folder or a failed write is an
    ``OSError`` naming the path."""
    contacts, forces = model._measured()
    payload = {
        "contacts": {k: v.detach().cpu() for k, v in contacts.as_dict().items()},
        "forces": forces.detach().cpu(),
        "noise_scale": model.noise_scale.cpu(),
        "options": {**model_options(model), "method": "observations" if model.spatial else model.method,
                    "dtype": str(model.dtype).replace("torch.", ""),
                    "auto": bool(model.auto)},
        "hypers": {k: v.detach().cpu() for k, v in model.hypers.state_dict().items()},
        "loss_history": list(model.loss_history),
        # the training data's fingerprint as the model holds it: the loaded copy's data equal these to the last
        # bit only without a noise_scale (whitening by it and undoing it rounds), so the copy takes this one
        "data_digest": model.state_dict()["data_digest"].cpu(),
    }
    if contacts.locations is not None:  # a model of maps over the ground: each sample's place, m
        payload["locations"] = contacts.locations.detach().cpu()
    if model.hyper_posterior is not None:  # the hyperparameter draws and weights predictions average over
        payload["hyper_posterior"] = model.hyper_posterior.state()
    if getattr(model, "mean_average", None) is not None:  # prior_mean="average": the physics-mean companion
        comp = model.companion
        payload["companion"] = {"hypers": {k: v.detach().cpu() for k, v in comp.hypers.state_dict().items()},
                                "method": comp.method, "auto": bool(comp.auto)}
        if comp.hyper_posterior is not None:
            payload["companion"]["hyper_posterior"] = comp.hyper_posterior.state()
        payload["mean_average"] = model.mean_average.state()
    if model.surface is not None:  # a learned surface offset (gp.surface.offset): its groups and value
        payload["options"]["surface_offset"] = True
        payload["options"]["surface_groups"] = model.surface.groups.cpu() if model.surface.grouped else None
        payload["surface_offset"] = model.surface.offset.detach().cpu()
    blob = {"format": FILE_FORMAT, "version": FILE_VERSION, "checksum": digest(payload), "payload": payload}
    atomic_write(path, lambda fh: torch.save(blob, fh), "model")


def load_model(cls, path, map_location=None, others: dict | None = None):
    """Rebuild an ``InverseRFT`` (``cls``) written by ``save_model`` (format 2, or 0.1.0's format,
    whose hyperparameters are translated). ``others``: format -> builder(file dict, path) for the files of other
    models the caller reads too (the front door: the 3-D model's). Raises ``ModelFileError`` naming what is wrong
    otherwise."""
    try:
        d = torch.load(path, map_location=map_location, weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for damaged files
        raise ModelFileError(f"{path}: not a readable irft_torch model file ({type(e).__name__}: {e}). "
                             f"It may be truncated or damaged: save the model again (InverseRFT.save) or "
                             f"refit it from its dataset (irft fit DATASET)") from None
    if not isinstance(d, dict):
        raise ModelFileError(f"{path}: not an irft_torch model file (holds a {type(d).__name__})")
    if "state_dict" in d and "options" in d and "format" not in d:
        return _load_v1(cls, d, path)
    if others and d.get("format") in others:
        return others[d["format"]](d, path)
    if d.get("format") != FILE_FORMAT:
        raise ModelFileError(f"{path}: not an irft_torch model file (format {d.get('format')!r})")
    if d.get("version") != FILE_VERSION:
        raise ModelFileError(f"{path}: model file version {d.get('version')!r}; this irft_torch reads version "
                             f"{FILE_VERSION}: refit the model from its dataset with this version")
    payload = d.get("payload")
    if not isinstance(payload, dict) or digest(payload) != d.get("checksum"):
        raise ModelFileError(f"{path}: checksum mismatch: the file is damaged; save the model again or refit it")
    opts = dict(payload["options"])
    opts["dtype"] = getattr(torch, opts["dtype"])
    opts.setdefault("priors", None)  # files written before the priors were fitted without them
    opts.setdefault("hyper_posterior", "map")  # files written before these options: the plug-in RBF of then
    opts.setdefault("li_basis", False)
    auto = bool(opts.pop("auto", False))  # method="auto": the backend it was on, and free to move again in fit
    model = cls(Contacts(**payload["contacts"]), payload["forces"], noise_scale=payload["noise_scale"],
                locations=payload.get("locations"), **grouped(opts))
    model.auto = auto
    if auto:  # built on the backend it was saved on, and free to move again: the choice was "auto"
        model.engine = replace(model.engine, method="auto")
    model.hypers.load_state_dict(payload["hypers"])
    if "surface_offset" in payload:
        with torch.no_grad():
            model.surface.offset.copy_(payload["surface_offset"].to(model.surface.offset))
        model._rebuild_backend()
    if "hyper_posterior" in payload:
        from .hyper.posterior import HyperPosterior

        model._set_hyper_posterior(HyperPosterior.from_state(payload["hyper_posterior"]))
    if "companion" in payload:  # prior_mean="average"
        from .hyper.posterior import HyperPosterior
        from .mean_average import MeanAverage

        saved = payload["companion"]
        from .mean_average import new_companion

        comp = new_companion(model, method=saved["method"])
        comp.auto = bool(saved["auto"])
        comp.hypers.load_state_dict(saved["hypers"])
        comp._set_hyper_posterior(HyperPosterior.from_state(saved["hyper_posterior"]) if "hyper_posterior" in saved
                                  else None)
        model._companion[:] = [comp]
        model.mean_average = MeanAverage.from_state(payload["mean_average"])
    model.loss_history = list(payload.get("loss_history", []))
    if "data_digest" in payload:  # the saved model's fingerprint (files before it: recomputed from the data)
        model.data_digest.copy_(payload["data_digest"].to(model.data_digest))
        model._digest_stale = False
    return model

def _load_v1(cls, d: dict, path):
    """0.1.0's files: options + a state dict of the old modules; the hyperparameters are read
    through the old constraints (softplus, lengthscale >= 0.05) and set on a new model."""
    try:
        opts = dict(d["options"])
        for k in ("grid_size",):
            opts.pop(k, None)
        if opts.get("method") in ("grid",):
            opts["method"] = "spectral"
        opts["dtype"] = getattr(torch, opts["dtype"])
        opts.setdefault("priors", None)  # 0.1 fitted without hyperparameter priors
        opts.update(hyper_posterior="map", li_basis=False)  # nor a hyperparameter posterior or Li et al.'s term
        model = cls(Contacts(**d["contacts"]), d["forces"], noise_scale=d.get("noise_scale"), **grouped(opts))
        sd = d["state_dict"]
        sp = torch.nn.functional.softplus

        def pick(suffix):
            hits = [v for k, v in sd.items() if k.endswith(suffix)]
            if not hits:
                raise KeyError(suffix)
            return hits[0].to(model.dtype)

        with torch.no_grad():
            model.hypers.lengthscale = (sp(pick("raw_lengthscale")) + 0.05).reshape(2, 1, 4)
            model.hypers.outputscale = sp(pick("raw_outputscale")).reshape(2)
            model.hypers.noise = sp(pick("raw_noise")).reshape(-1).expand(2)
            if model.hypers.mean is not None:
                model.hypers.mean.scales = sp(pick("raw_scales")).reshape(2)
    except Exception as e:  # noqa: BLE001
        raise ModelFileError(f"{path}: an irft_torch 0.1 model file that could not be translated ({e}); refit it "
                             f"from its dataset with `irft fit`") from None
    warnings.warn(f"{path}: read an irft_torch 0.1 model file; save it again to write format {FILE_VERSION}",
                  stacklevel=3)
    model.loss_history = list(d.get("loss_history", []))
    return model


def model_options(model) -> dict:
    """The constructor options that shape an ``InverseRFT``, beyond its data, backend and surface: what a model like
    it on other data needs (``save``, ``cross_validate(refit=True)``, the mean average's companion)."""
    li = model.hypers.li
    return {"prior_mean": model.prior_mean_kind, "tied_noise": model.hypers.tied,
            "lengthscale": model.init_lengthscale, "tol": model.tol, "solver": model.solver, "dtype": model.dtype,
            "priors": model.priors, "hyper_posterior": model.hyper_method, "li_basis": li is not None,
            "generic_shape": li is not None and li.generic}


def data_digest_of(model) -> Tensor:
    """(32,) uint8: the sha256 of an ``InverseRFT``'s training data as measured (``digest``): the weights (what the
    maps see), the signed depths and areas only where the surface is learned, the places, the noise scales."""
    c, f = model._measured()
    data = c.as_dict() if model.surface is not None else {k: c.as_dict()[k] for k in list(c.as_dict())[:4]}
    if c.locations is not None:
        data = {**data, "locations": c.locations}
    d = digest({"contacts": data, "forces": f, "noise_scale": model.noise_scale})
    return torch.tensor(list(bytes.fromhex(d)), dtype=torch.uint8, device=model._device)


def refresh_digest(model) -> None:
    """The model's ``data_digest`` buffer recomputed where its data changed since (hashing is O(T M))."""
    if model._digest_stale:
        model.data_digest.copy_(data_digest_of(model))
        model._digest_stale = False


def without_backend(state: dict) -> dict:
    """An ``InverseRFT``'s ``nn.Module`` state dict less the backend's entries (the same hyperparameters again, and
    gpytorch's): which backend ``auto`` ends on is not part of a model's state."""
    for k in [k for k in state if k.split(".", 1)[0] == "backend" or ".backend." in k]:
        del state[k]
    return state


def load_state(model, state_dict, strict: bool = True):
    """``InverseRFT.load_state_dict``: the hyperparameters (and a learned surface's offsets) from a state dict; with
    ``strict`` a state from a model fitted on other data is refused (its ``data_digest`` differs), ``strict=False``
    loads the hyperparameters alone (a warm start on new data)."""
    refresh_digest(model)
    theirs = state_dict.get("data_digest")
    if theirs is not None and not torch.equal(theirs.to(model.data_digest.device), model.data_digest):
        if strict:
            raise ModelFileError("this state was fitted on other training data (data_digest differs); pass "
                                 "strict=False to load only its hyperparameters")
        state_dict = {k: v for k, v in state_dict.items() if k != "data_digest"}
    state_dict = {k: v for k, v in state_dict.items() if not k.startswith("backend.")}
    result = model.hypers.load_state_dict({k[len("hypers."):]: v for k, v in state_dict.items()
                                           if k.startswith("hypers.")}, strict=strict)
    if "data_digest" in state_dict:
        model.data_digest.copy_(state_dict["data_digest"].to(model.data_digest))
    if model.surface is not None and "surface.offset" in state_dict:
        with torch.no_grad():
            model.surface.offset.copy_(state_dict["surface.offset"].to(model.surface.offset))
        model._rebuild_backend()
    unexpected = [k for k in state_dict if not (k.startswith("hypers.") or k == "data_digest"
                                                or (model.surface is not None and k == "surface.offset"))]
    if strict and unexpected:
        raise RuntimeError(f"unexpected key(s) in state_dict: {unexpected}")
    return result
