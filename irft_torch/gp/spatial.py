"""Maps over the ground through the front door: ``InverseRFT(contacts, forces, locations=xy)``.

With ``locations`` (T, 2) m, each sample's place on the ground (its foothold; a long drag may move it per sample),
the maps become alpha(beta, gamma; s): a medium shared by the whole site times (1 + a spatial kernel)
(``gp.kernels.spatial``), learned with the rest and covered by the hyperparameter posterior. The queries take
places too:

    >>> model = InverseRFT(walk.contacts, forces, locations=walk.locations).fit()
    >>> post = model.stress_map(beta, gamma, locations=grid)      # mean, variance (L, *beta.shape, 2)
    >>> pred = model.predict_forces(contacts, locations=places)    # (T', 2) N, each at its own place

A spatial model's queries without places give the medium shared by the site (the factor's constant part).
Exact (the observations space, T x T per map, by Cholesky): a walk of a few thousand samples.
"""

from __future__ import annotations

import torch

from ..rft.contacts import Contacts, check_locations

__all__ = ["check_spatial_options", "placed_queries", "placed_contacts"]


def check_spatial_options(method: str, prior_mean: str, surface: bool, statistics) -> None:
    """The options a spatial model cannot take yet, refused by name."""
    if method not in ("auto", "observations", "exact"):
        raise ValueError(f"with locations the model is exact in the observations' space: method must be 'auto' or "
                         f"'observations', got {method!r}")
    if prior_mean == "average":
        raise NotImplementedError("MapPrior(mean='average') with locations is not supported: use 'zero' (the default) "
                                  "or 'physics'")
    if surface:
        raise NotImplementedError("a learned surface offset with locations is not supported: fix the surface "
                                  "(contacts.with_surface_offset) and drop surface_offset")
    if statistics is not None:
        raise ValueError("statistics serve the planar spaces: a model with locations cannot take them")


def placed_queries(spatial: bool, c: Contacts, shape: tuple, locations, dtype, device) -> tuple[Contacts, tuple]:
    """Point queries ``c`` (N, 1) at angles of shape ``shape`` placed at each of ``locations`` (L, 2) m: contacts
    (L N, 1) and the result's shape (L, *shape). Without ``locations``: ``c`` and ``shape`` (a spatial model: the
    shared medium). A model without places refuses ``locations`` by name."""
    if locations is None:
        return c, tuple(shape)
    if not spatial:
        raise ValueError("locations: this model was fitted without places (one medium everywhere); fit "
                         "InverseRFT(contacts, forces, locations=...) to ask about places")
    loc = check_locations(locations, name="locations").to(device=device, dtype=dtype)
    if loc.ndim != 2:
        raise ValueError(f"locations must be (L, 2) places (x, y) in m, got shape {tuple(loc.shape)}")
    L, N = loc.shape[0], len(c)
    rep = Contacts(**{k: v.repeat(L, 1) for k, v in c.as_dict().items()}, locations=loc.repeat_interleave(N, 0))
    return rep, (L, *shape)


def placed_contacts(spatial: bool, contacts: Contacts, locations, dtype, device) -> Contacts:
    """``contacts`` (..., T, M) with places ``locations`` (..., T, 2) m (or their own ``contacts.locations``).
    A model without places refuses them by name; a spatial model takes contacts without places as queries of
    the shared medium."""
    if locations is None:
        if contacts.locations is not None and not spatial:
            raise ValueError("contacts.locations: this model was fitted without places (one medium everywhere)")
        return contacts
    if not spatial:
        raise ValueError("locations: this model was fitted without places (one medium everywhere); fit "
                         "InverseRFT(contacts, forces, locations=...) to ask about places")
    loc = torch.as_tensor(locations, dtype=dtype, device=device)
    return contacts.with_locations(loc)
