r"""The "pairs" backend: exact inference in the space of the recording's distinct angle pairs.

When only U distinct (beta, gamma) pairs occur (a flat toe, a plate at fixed tilt and direction,
a toe that does not turn on a straight stroke), W = W_U P with W_U (T x U) the weights summed per
pair, so W K W^T = W_U K_UU W_U^T: the weight-space algebra (``weight_space``) with u = the map at
the U pairs and Sigma = K_UU, exact, O(U^3) per step whatever T.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts import Contacts
from ..kernels.angle import angle_covariance, composite_covariance
from ..kernels.li_basis import li_features
from ..kernels.operators import unique_pairs
from .weight_space import FeatureStatistics, WeightSpaceBackend, chunk_rows

__all__ = ["PairsBackend", "distinct_pairs", "KERNEL_COST"]

KERNEL_COST = 20.0  # one kernel value against one multiply-add (``PairsBackend.draw_cost``)


def distinct_pairs(c: Contacts) -> tuple[Tensor, Tensor]:
    """Distinct angle pairs (U, 2) of the segments in contact (either axis) and each segment's row
    in them (T, M) (0 for segments not in contact, whose weights are 0)."""
    active = (c.weight_x != 0) | (c.weight_z != 0)
    pairs = torch.stack([c.beta[active], c.gamma[active]], -1)
    if pairs.shape[0] == 0:
        return c.beta.new_zeros(1, 2), torch.zeros(c.shape, dtype=torch.long, device=c.beta.device)
    table, inverse = unique_pairs(pairs.detach())
    return table, torch.zeros(c.shape, dtype=torch.long, device=c.beta.device).masked_scatter(active, inverse)


class PairsBackend(WeightSpaceBackend):
    """Exact I-RFT in the U-dimensional space of distinct angle pairs.

    Args:
        hypers: shared hyperparameters.
        contacts: whitened training contacts (T, M).
        forces: whitened training forces (T, 2), N.
    """

    name = "pairs"
    #: evaluate the likelihood through the segments where cheaper (``closed_form``): set on the spectral backend's
    #: exact twin (``SpectralBackend.exact_twin``), whose hyperparameter draws are many and short; a fit's own pairs
    #: backend keeps the weight space (its terms, ``_closed_form_terms``, are where a new kernel term plugs in)
    segments = False

    def __init__(self, hypers, contacts: Contacts, forces: Tensor) -> None:
        super().__init__(hypers, contacts, forces)
        self.table, _ = distinct_pairs(contacts)
        self._kept = (contacts, forces)  # the data the statistics are of, for the factor from rows (``_rows``)
        self._set_stats(self._statistics(contacts, forces, self.table))

    @property
    def n_pairs(self) -> int:
        return self.table.shape[0]

    def describe(self) -> str:
        return f"pairs: T={self.n_samples}, U={self.n_pairs} distinct angle pairs"

    # ---- statistics -------------------------------------------------------------------------
    def _index(self, c: Contacts, table: Tensor) -> Tensor:
        """Each segment's row (T, M) in ``table``, which must hold every pair of c in contact."""
        own, idx = distinct_pairs(c)
        both, inverse = unique_pairs(torch.cat([table, own]))
        if both.shape[0] != table.shape[0]:
            raise ValueError("contacts hold angle pairs that are not in the table")
        lookup = inverse[table.shape[0]:]  # own row -> table row (bit-equal pairs)
        remap = torch.empty(table.shape[0], dtype=torch.long, device=idx.device)
        remap[inverse[:table.shape[0]]] = torch.arange(table.shape[0], device=idx.device)
        return remap[lookup][idx]

    def _phi(self, c: Contacts, idx: Tensor, U: int) -> Tensor:
        """Phi (2, t, U): each sample's weights summed per pair (idx (t, M): each segment's pair)."""
        w = torch.stack([c.weight_x, c.weight_z])  # (2, t, M)
        return w.new_zeros(2, idx.shape[0], U).scatter_add(-1, idx.expand(2, *idx.shape), w)

    def _rows(self):
        """Phi (2, T, U), the forces (2, T) and the mean's shape forces (or None) while the backend holds the data its
        statistics are of: with fewer samples than pairs the data factor comes from them (their Gram, T^2 U) instead of
        P's eigendecomposition (U^3; 0.66 s at U = 1,514 here, where the rows take 0.01 s)."""
        kept = self.__dict__.get("_kept")
        if kept is None or len(kept[0]) != self.n_samples:
            return None
        c, f = kept
        with torch.no_grad():
            g = self.hypers.mean.shape_forces(c) if self.hypers.mean is not None else None
            return self._phi(c, self._index(c, self.table), self.n_pairs), f.T, g

    def _statistics(self, c: Contacts, f: Tensor, table: Tensor) -> FeatureStatistics:
        U = table.shape[0]
        stats = FeatureStatistics.zeros(U, dtype=f.dtype, device=f.device, meta={"space": "pairs", "U": U})
        idx = self._index(c, table)
        same = self._same_gram(c)
        shape = self.hypers.mean.shape_forces(c) if self.hypers.mean is not None else None
        chunk = chunk_rows(U, c.n_segments)
        for i in range(0, len(c), chunk):
            Phi = self._phi(c[i:i + chunk], idx[i:i + chunk], U)
            stats.accumulate(Phi, f[i:i + chunk].T, None if shape is None else shape[:, i:i + chunk], same)
        return stats

    # ---- the weight-space pieces ------------------------------------------------------------
    def _K(self) -> Tensor:
        t = self.table
        K = angle_covariance(self.hypers.kernel, t[:, 0], t[:, 1], t[:, 0], t[:, 1])
        if self.hypers.li is not None:
            f = li_features(t[:, 0], t[:, 1])
            K = K + self.hypers.li.weigh(f) @ f.mT
        return K

    def _apply_sigma(self, X: Tensor) -> Tensor:
        return X @ self._K()

    def _closed_form_terms(self, f) -> list:
        from .covariance_terms import PairsRBF, li_terms

        t = self.table.to(f.R)
        return [PairsRBF(t)] + li_terms(self.hypers, li_features(t[:, 0], t[:, 1]))

    def _segment_form(self) -> bool:
        """Whether the likelihood is evaluated in the observations' space through the segments (``closed_form``):
        where ``segments`` is set and that is the cheaper form."""
        kept = self.__dict__.get("_kept")
        T, U = self.n_samples, self.n_pairs
        return (self.segments and kept is not None and len(kept[0]) == T
                and T ** 3 / 3 + 4 * T * kept[0].n_segments * U < 2 * min(T, U) * U * U)

    def draw_cost(self) -> float:
        """About the multiply-adds of one hyperparameter draw's likelihood (both maps), in the units of
        ``spectral.basis_cost``: a kernel value costs about ``KERNEL_COST`` (an exponential and three passes over
        memory, measured here), then the products of the closed form's space."""
        T, U = self.n_samples, self.n_pairs
        if self._segment_form():
            return 2 * (KERNEL_COST * U * U + 6 * T * self._kept[0].n_segments * U + T ** 3 / 3)
        r = min(T, U)
        return 2 * (KERNEL_COST * U * U + 2 * r * U * U + r ** 3 / 3)

    def closed_form(self):
        """``closed_form.ClosedForm`` in the observations' space (A = W_U K_UU W_U^T through each sample's segments,
        ``SegmentPairsRBF``) with ``segments`` set where that is the cheaper exact form, T^3 / 3 + 4 T M U against the
        weight space's 2 r U^2 (many distinct pairs, few samples: a turning toe's short-lengthscale draws, 6x faster at
        T = 150, U = 1,514); else the weight space's (``WeightSpaceBackend.closed_form``). The same likelihood."""
        from .closed_form import ClosedForm, closed_form_enabled
        from .covariance_terms import SegmentPairsRBF, li_terms

        if not (closed_form_enabled() and self._segment_form()):
            return super().closed_form()
        kept, T, U = self._kept, self.n_samples, self.n_pairs
        hit = self.__dict__.get("_segments_closed_form")
        if hit is not None and hit[0] is self.stats:
            return hit[1]
        c, f = kept
        with torch.no_grad():
            idx = self._index(c, self.table)
            w = torch.stack([c.weight_x, c.weight_z]).to(f)
            g = self.hypers.mean.shape_forces(c) if self.hypers.mean is not None else None
            t = self.table.to(f)
            terms = [SegmentPairsRBF(t, idx, w)]
            if self.hypers.li is not None:  # Li et al.'s 9 features summed with each sample's weights: (2, T, 9)
                terms += li_terms(self.hypers, self._phi(c, idx, U).to(f) @ li_features(t[:, 0], t[:, 1]))
        cf = ClosedForm(None, f.T, g, f.new_zeros(2, 3), T, terms, symmetrize=False)
        self._segments_closed_form = (self.stats, cf)
        return cf

    def _cross(self, c: Contacts) -> Tensor:
        """W_q K(theta_q, pairs): (2, N, U), differentiable in the contacts (not the hyperparameters)."""
        pairs = Contacts.points(self.table[:, 0], self.table[:, 1])  # the map at each pair: weight 1
        return composite_covariance(self.hypers.kernel, c, pairs, li=self.hypers.li).to_dense()

    def _prior_cov(self, c: Contacts, full: bool) -> Tensor:
        op = composite_covariance(self.hypers.kernel, c, li=self.hypers.li)
        return op.to_dense() if full else op.diagonal()

    def _prior_cross(self, c1: Contacts, c2: Contacts) -> Tensor:
        return composite_covariance(self.hypers.kernel, c1, c2, li=self.hypers.li).to_dense()

    # ---- more data ---------------------------------------------------------------------------
    def _grown(self, c: Contacts) -> tuple[Tensor, Tensor]:
        """The table with c's new pairs appended, and where the old rows went (U_old,)."""
        new, _ = distinct_pairs(c)
        table, inverse = unique_pairs(torch.cat([self.table, new]))
        return table, inverse[:self.table.shape[0]]

    def _reindexed(self, table: Tensor, where: Tensor) -> FeatureStatistics:
        s = self.stats
        U = table.shape[0]
        out = FeatureStatistics.zeros(U, dtype=s.P.dtype, device=s.P.device, meta={"space": "pairs", "U": U})
        out.P[:, where[:, None], where[None, :]] = s.P
        out.b[:, where] = s.b
        out.bg[:, where] = s.bg
        out.yy, out.yg, out.gg, out.n = s.yy.clone(), s.yg.clone(), s.gg.clone(), s.n
        return out

    def _with_data(self, c: Contacts, f: Tensor) -> PairsBackend:
        new = PairsBackend.__new__(PairsBackend)
        WeightSpaceBackend.__init__(new, self.hypers, c, f)
        new.table, where = self._grown(c)
        new._set_stats(self._reindexed(new.table, where) + self._statistics(c, f, new.table))
        return new

    def with_hypers(self, hypers) -> PairsBackend:
        """The same pairs, statistics and data factor (none depends on the hyperparameters) at ``hypers``."""
        new = PairsBackend.__new__(PairsBackend)
        WeightSpaceBackend.__init__(new, hypers, self.table, None)  # type: ignore[arg-type]  # no data: the statistics hold it
        new.table = self.table
        new._set_stats(self.stats)
        new._data_factor = self._factor()
        return new

    def add_data(self, contacts: Contacts, forces: Tensor) -> None:
        table, where = self._grown(contacts)
        stats = self._reindexed(table, where) + self._statistics(contacts, forces, table)
        self.table = table
        self._set_stats(stats)

