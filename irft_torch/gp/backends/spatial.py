"""The "spatial" backend: exact I-RFT for maps that change over the ground (``gp.kernels.spatial``).

The observations backend's space (T x T per map) with each covariance block multiplied, elementwise, by the
spatial factor 1 + v k_s between the samples' places. Its ExactGP's inputs are the composite rows with each
sample's place (x, y) in m in front. Exact (Cholesky); no closed form for the hyperparameter posterior (the
Laplace proposals are weighed one marginal likelihood each)."""

from __future__ import annotations

from collections.abc import Iterator

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

    def placed_covariances(self, queries: Contacts, stroke: Contacts, offsets: Tensor, footholds: Tensor,
                           chunk: int | None = None) -> Iterator[tuple[Tensor, Tensor]]:
        """Posterior covariances of one stroke placed at each of P footholds, without its forces, ``chunk``
        footholds at a time (default all): per chunk (S_qc (P', 2, Q, T), the queries' (Q weighted sums, with
        places) against the placed stroke's T samples, and S_cc (P', 2, T, T)), N^2 (or (N/cm^3) N against point
        queries), each map's. ``stroke`` (T, M) its contacts, ``offsets`` (T, 2) m each sample's place from the
        foothold, ``footholds`` (P, 2) m. The same numbers as ``cross_covariance`` of ``stroke`` placed at each
        foothold, batched: the angles' part of every block is formed once for all footholds (a foothold moves the
        places only), the places' factor per foothold, and the stroke's own factor once (the Matern kernel sees
        differences of places only)."""
        side_t, L, _ = self._factor()
        side_q, _, A_q = self._query(queries)  # A_q (2, n, Q) = L^-1 K_tq, the places' factor included
        angles = super()._side(stroke)
        K_qc = super()._block(side_q, angles)  # (2, Q, T): the angles' part (the base block reads no places)
        K_tc = super()._block(side_t, angles)  # (2, n, T)
        K_cc = super()._block(angles, angles) * self.hypers.spatial.factor(offsets, offsets, True)
        footholds = footholds.to(offsets)
        n, Q, T = L.shape[-1], K_qc.shape[1], offsets.shape[0]
        for feet in footholds.split(max(1, int(chunk or len(footholds)))):
            P = feet.shape[0]
            at = (feet[:, None, :] + offsets[None]).reshape(P * T, 2)

            def placed(K: Tensor, s: Tensor | None) -> Tensor:  # K (2, N, T) times the factor to each placed sample
                if s is None:  # queries of the shared medium: factor 1
                    return K[:, :, None, :].expand(-1, -1, P, -1).reshape(2, K.shape[1], P * T)
                factor = torch.as_tensor(self.hypers.spatial.factor(s, at, True))  # (2, N, P T): both have places
                return (K[:, :, None, :] * factor.reshape(2, s.shape[0], P, T)).reshape(2, K.shape[1], P * T)

            A_c = torch.linalg.solve_triangular(L, placed(K_tc, side_t["locations"]), upper=False)  # (2, n, P T)
            S_qc = (placed(K_qc, queries.locations) - A_q.mT @ A_c).reshape(2, Q, P, T).permute(2, 0, 1, 3)
            A_c = A_c.reshape(2, n, P, T)
            yield S_qc, K_cc - torch.einsum("bnpt,bnps->pbts", A_c, A_c)

    def posterior(self, contacts: Contacts, variance: bool = True, covariance: bool = False) -> FunctionalPosterior:
        out = super().posterior(contacts, variance=False, covariance=covariance)
        if variance and not covariance:
            _, _, A = self._query(contacts)
            prior = composite_covariance(self.hypers.kernel, contacts, li=self.hypers.li).diagonal()
            if contacts.locations is not None:
                prior = prior * self.hypers.spatial.diagonal(detach=True)[:, None]
            out.variance = prior - A.pow(2).sum(-2)
        return out
