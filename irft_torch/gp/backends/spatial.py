"""The "spatial" backend: exact I-RFT for maps that change over the ground (``gp.kernels.spatial``).

The observations backend's space (T x T per map) with each covariance block multiplied, elementwise, by the
spatial factor 1 + v k_s between the samples' places. Its ExactGP's inputs are the composite rows with each
sample's place (x, y) in m in front. Exact (Cholesky); no closed form for the hyperparameter posterior (the
Laplace proposals are weighed one marginal likelihood each)."""

from __future__ import annotations

import gpytorch
import torch
from torch import Tensor

from ...rft.contacts import Contacts
from ..kernels.angle import RFTCompositeKernel, composite_covariance
from ..kernels.encoding import encode_contacts
from ..kernels.spatial import SpatialCompositeKernel
from .base import FunctionalPosterior
from .observations import ObservationsBackend

__all__ = ["SpatialBackend", "encode_placed"]


def encode_placed(contacts: Contacts, M: int | None = None) -> Tensor:
    """Contacts (T, M') with locations -> rows (2, T, 2 + 3M): each sample's place (x, y) m, then its composite
    row (``gp.kernels.encoding.encode_contacts``)."""
    if contacts.locations is None:
        raise ValueError("these contacts have no locations: a model of maps over the ground needs each sample's "
                         "place (contacts.with_locations(xy), or locations= where the model takes it)")
    rows = encode_contacts(contacts, M)
    return torch.cat([contacts.locations.to(rows).expand(2, *contacts.locations.shape), rows], -1)


class _PlacedMean(gpytorch.means.Mean):
    """The planar prior mean of rows with places in front (it reads the composite rows only)."""

    def __init__(self, mean) -> None:
        super().__init__()
        self.mean = mean

    def forward(self, x: Tensor) -> Tensor:
        return self.mean(x[..., 2:])


class SpatialBackend(ObservationsBackend):
    """Exact I-RFT over angles and places (module docstring).

    Args:
        hypers: ``RFTHyperparameters`` with a ``spatial`` factor (``gp.kernels.spatial.SpatialFactor``).
        contacts: whitened training contacts (T, M) with ``locations`` (T, 2) m.
        forces: whitened training forces (T, 2), N.

    A query's contacts without locations stand for the medium shared by the site (the factor's constant part):
    ``posterior`` then gives that medium's posterior.
    """

    name = "spatial"

    def __init__(self, hypers, contacts: Contacts, forces: Tensor, solver: str = "cholesky") -> None:
        if getattr(hypers, "spatial", None) is None:
            raise ValueError("the spatial backend needs hyperparameters with a spatial factor (RFTHyperparameters("
                             "spatial_lengthscale=...))")
        if solver != "cholesky":
            raise ValueError(f"the spatial backend solves by Cholesky only, got solver={solver!r}")
        super().__init__(hypers, contacts, forces, solver)

    def _encode(self, contacts: Contacts, M: int | None = None) -> Tensor:
        return encode_placed(contacts, M)

    def _gp_parts(self, mean) -> tuple:
        return _PlacedMean(mean), SpatialCompositeKernel(RFTCompositeKernel(self.hypers.kernel, self.hypers.li),
                                                         self.hypers.spatial)

    def with_hypers(self, hypers) -> SpatialBackend:
        """The same data at other hyperparameters (a hyperparameter draw)."""
        return SpatialBackend(hypers, self.train_contacts, self.train_forces, self.solver)

    def closed_form(self):
        """None: the factor breaks the planar closed forms (the hyperparameter posterior uses autograd)."""
        return None

    def _side(self, c: Contacts) -> dict:
        side = super()._side(c)
        side["locations"] = c.locations
        return side

    def _block(self, side1: dict, side2: dict) -> Tensor:
        K = super()._block(side1, side2)
        return K * self.hypers.spatial.factor(side1["locations"], side2["locations"], detach=True)

    def posterior(self, contacts: Contacts, variance: bool = True, covariance: bool = False) -> FunctionalPosterior:
        out = super().posterior(contacts, variance=False, covariance=covariance)
        if variance and not covariance:
            _, _, A = self._query(contacts)
            prior = composite_covariance(self.hypers.kernel, contacts, li=self.hypers.li).diagonal()
            if contacts.locations is not None:
                prior = prior * self.hypers.spatial.diagonal(detach=True)[:, None]
            out.variance = prior - A.pow(2).sum(-2)
        return out
