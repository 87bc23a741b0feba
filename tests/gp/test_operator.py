"""RFTKernelLinearOperator through linear_operator's own test battery, against its dense twin."""

import unittest

import torch
from linear_operator.test.linear_operator_test_case import LinearOperatorTestCase, RectangularLinearOperatorTestCase

from irft_torch.gp import RFTKernelLinearOperator, RowSeparableRFTOperator


def make(batch=(), T1=6, T2=6, M=3, U=20, seed=0, square=True):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(*batch, U, 4, generator=g, dtype=torch.float64) * 3.0
    s = torch.rand(*batch, 1, 1, generator=g, dtype=torch.float64) + 2.0
    # distinct table rows per observation keep W K W^T well conditioned (each row its own segments)
    li = torch.randperm(U, generator=g)[: T1 * M].reshape(T1, M).expand(*batch, T1, M).contiguous()
    lw = torch.rand(*batch, T1, M, generator=g, dtype=torch.float64) + 1.0
    lw[..., 0, -1] = 0.0  # a padding segment
    if square:
        return RFTKernelLinearOperator(x, x, s, li, lw, li, lw)
    ri = torch.randint(0, U, (*batch, T2, M), generator=g)
    rw = torch.randn(*batch, T2, M, generator=g, dtype=torch.float64)
    return RFTKernelLinearOperator(x, x.clone(), s, li, lw, ri, rw)


def with_grads(op):
    for a in op._args:
        if a.dtype.is_floating_point:
            a.requires_grad_(True)
    return op


def dense(op):
    """Explicit W K W^T from the operator's raw arguments (no operator code involved)."""
    x1, x2, s, li, lw, ri, rw = op._args
    d2 = ((x1[..., :, None, :] - x2[..., None, :, :]) ** 2).sum(-1)
    K = s * torch.exp(-0.5 * d2)
    U1, U2 = x1.shape[-2], x2.shape[-2]
    L = torch.zeros(*li.shape[:-1], U1, dtype=lw.dtype).scatter_add(-1, li, lw)
    R = torch.zeros(*ri.shape[:-1], U2, dtype=rw.dtype).scatter_add(-1, ri, rw)
    return L @ K @ R.mT


class TestRFTKernelLinearOperator(LinearOperatorTestCase, unittest.TestCase):
    seed = 0
    should_test_sample = False

    def create_linear_op(self):
        return with_grads(make())

    def evaluate_linear_op(self, linear_op):
        return dense(linear_op)


class TestRFTKernelLinearOperatorBatch(TestRFTKernelLinearOperator):
    def create_linear_op(self):
        return with_grads(make(batch=(2,), seed=1))


class TestRFTKernelLinearOperatorRectangular(RectangularLinearOperatorTestCase, unittest.TestCase):
    seed = 0

    def create_linear_op(self):
        return with_grads(make(T1=5, T2=7, square=False, seed=2))

    def evaluate_linear_op(self, linear_op):
        return dense(linear_op)


def test_memory_budget_chunks_and_both_algebras_give_the_same_matrix(monkeypatch):
    from irft_torch.gp import memory_budget
    from irft_torch.gp.kernels import operators

    monkeypatch.setattr(operators, "DENSE_WEIGHTS_MAX_RATIO", 0)  # force the gather path

    op = make(batch=(2,), T1=6, M=3, U=30, seed=3)
    full = op.to_dense()
    rhs = torch.randn(2, 6, 3, dtype=torch.float64)
    with memory_budget(64):  # forces one row per block
        torch.testing.assert_close(op.to_dense(), full)
        torch.testing.assert_close(op._matmul(rhs), full @ rhs)
    torch.testing.assert_close(full, dense(op))
    monkeypatch.setattr(operators, "DENSE_WEIGHTS_MAX_RATIO", 1000)  # the dense-weights path
    torch.testing.assert_close(op.to_dense(), full)
    # gradients through the checkpointed blocks equal those of one block
    x1 = op.x1.clone().requires_grad_(True)
    args = (x1, x1, op.outputscale, op.left_index, op.left_weight, op.left_index, op.left_weight)
    monkeypatch.setattr(operators, "DENSE_WEIGHTS_MAX_RATIO", 0)
    g_full = torch.autograd.grad(operators.RFTKernelLinearOperator(*args).to_dense().pow(2).sum(), x1)[0]
    with memory_budget(64):
        g_chunk = torch.autograd.grad(operators.RFTKernelLinearOperator(*args).to_dense().pow(2).sum(), x1)[0]
    torch.testing.assert_close(g_full, g_chunk)


class TestRFTKernelLinearOperatorGatherPath(TestRFTKernelLinearOperatorBatch):
    """The same battery on the gather algebra (large tables), forced."""

    def setUp(self):
        from irft_torch.gp.kernels import operators

        self._old = operators.DENSE_WEIGHTS_MAX_RATIO
        operators.DENSE_WEIGHTS_MAX_RATIO = 0
        super().setUp() if hasattr(super(), "setUp") else None

    def tearDown(self):
        from irft_torch.gp.kernels import operators

        operators.DENSE_WEIGHTS_MAX_RATIO = self._old


def test_unique_pairs_agrees_with_torch_unique():
    from irft_torch.gp.kernels.operators import unique_pairs

    g = torch.Generator().manual_seed(4)
    for dtype in (torch.float64, torch.float32):
        pairs = (torch.randint(0, 9, (500, 2), generator=g) / 7.0).to(dtype)
        u, inv = unique_pairs(pairs)
        assert torch.equal(u[inv], pairs)  # every row is its table entry, bit for bit
        want = torch.unique(pairs, dim=0)
        assert u.shape == want.shape and torch.equal(torch.unique(u, dim=0), want)
    u, inv = unique_pairs(torch.zeros(0, 2, dtype=torch.float64))
    assert u.shape == (0, 2) and inv.shape == (0,)


def make_separable(batch=(), T1=6, T2=5, nb=3, seed=0, square=True):
    """A RowSeparableRFTOperator with random tables: n_b distinct betas, one gamma per row."""
    g = torch.Generator().manual_seed(seed)
    zb = torch.randn(*batch, nb, 2, generator=g, dtype=torch.float64)
    zg1 = torch.randn(*batch, T1, 2, generator=g, dtype=torch.float64) * 2.0
    s = torch.rand(*batch, 1, 1, generator=g, dtype=torch.float64) + 2.0
    L1 = torch.rand(*batch, T1, nb, generator=g, dtype=torch.float64) + 0.5
    if square:
        return RowSeparableRFTOperator(zb, zb, zg1, zg1, s, L1, L1)
    zg2 = torch.randn(*batch, T2, 2, generator=g, dtype=torch.float64)
    L2 = torch.randn(*batch, T2, nb + 1, generator=g, dtype=torch.float64)
    zb2 = torch.randn(*batch, nb + 1, 2, generator=g, dtype=torch.float64)
    return RowSeparableRFTOperator(zb, zb2, zg1, zg2, s, L1, L2)


def dense_separable(op):
    """s exp(-|zg_t - zg_t'|^2 / 2) (L1 exp(-|zb - zb'|^2 / 2) L2^T), written with explicit differences."""
    zb1, zb2, zg1, zg2, s, L1, L2 = op._args
    kb = torch.exp(-0.5 * ((zb1[..., :, None, :] - zb2[..., None, :, :]) ** 2).sum(-1))
    kg = torch.exp(-0.5 * ((zg1[..., :, None, :] - zg2[..., None, :, :]) ** 2).sum(-1))
    return s * kg * (L1 @ kb @ L2.mT)


class TestRowSeparableRFTOperator(LinearOperatorTestCase, unittest.TestCase):
    seed = 0
    should_test_sample = False

    def create_linear_op(self):
        return with_grads(make_separable(T1=6, nb=6))  # n_b = T: full rank, so the battery's solves are defined

    def evaluate_linear_op(self, linear_op):
        return dense_separable(linear_op)


class TestRowSeparableRFTOperatorBatch(TestRowSeparableRFTOperator):
    def create_linear_op(self):
        return with_grads(make_separable(batch=(2,), T1=5, nb=5, seed=1))


class TestRowSeparableRFTOperatorRectangular(RectangularLinearOperatorTestCase, unittest.TestCase):
    seed = 0

    def create_linear_op(self):
        return with_grads(make_separable(seed=2, square=False))

    def evaluate_linear_op(self, linear_op):
        return dense_separable(linear_op)


def _dense_segments(b1, g1, w1, b2, g2, w2, ls, os):
    """sum_{m, m'} w1_tm w2_t'm' k(theta1_tm, theta2_t'm'), every segment pair written out (einsum)."""
    from irft_torch.gp.kernels.embedding import embed_angles

    def emb(b, g):
        x = embed_angles(b, g) / ls[..., None, :, :]  # (2, T, M, 4)
        return x

    x1, x2 = emb(b1, g1), emb(b2, g2)
    d2 = ((x1[..., :, :, None, None, :] - x2[..., None, None, :, :, :]) ** 2).sum(-1)  # (2, T1, M1, T2, M2)
    K = os[:, None, None, None, None] * torch.exp(-0.5 * d2)
    return torch.einsum("bim,bimjn,bjn->bij", w1, K, w2)


def test_row_separable_structure_matches_every_segment_pair_written_out():
    """The translating-toe form against W K W^T summed over every pair of segments: different zero patterns
    for x and z, a row with no contact, an axis with no contact on a row, inactive segments whose gamma
    differs (ignored), a row whose x and z segments move differently; then the operator's entries, slices,
    products, diagonal, transpose and gradients; and the cross-covariance, falling back to the general
    operator when one side is not separable."""
    import math

    from irft_torch.gp.kernels.operators import RowSeparableRFTOperator

    g = torch.Generator().manual_seed(0)
    dt = torch.float64
    T, M = 7, 4
    beta = (torch.rand(T, M, generator=g, dtype=dt) - 0.5) * math.pi
    gamma = ((torch.rand(T, 1, generator=g, dtype=dt) - 0.5) * math.pi).expand(T, M).clone()
    wx, wz = torch.rand(T, M, generator=g, dtype=dt), torch.rand(T, M, generator=g, dtype=dt)
    wx[torch.rand(T, M, generator=g) < 0.4] = 0
    wz[torch.rand(T, M, generator=g) < 0.4] = 0
    wx[2], wz[2], wx[3] = 0, 0, 0  # a row with no contact; an axis with none on row 3
    gamma[(wx == 0) & (wz == 0)] = 1.234  # inactive segments: any gamma
    wx[4], wz[4] = 0, 0
    wx[4, 0], wz[4, 1], gamma[4, 0], gamma[4, 1] = 1.0, 1.0, 0.3, -0.7  # x and z rows each translate
    ls = torch.rand(2, 1, 4, generator=g, dtype=dt) + 0.5
    os = torch.rand(2, generator=g, dtype=dt) + 0.5
    w = torch.stack([wx, wz])
    B = torch.Size([2])
    ex = lambda v: v[None].expand(2, *v.shape)  # noqa: E731
    st = RFTKernelLinearOperator.segment_structure(beta[None], gamma[None], w, beta[None], gamma[None], w, B,
                                                   same_inputs=True)
    op = RFTKernelLinearOperator.from_structure(st, ls, os, B)
    assert isinstance(op, RowSeparableRFTOperator)
    D = _dense_segments(ex(beta), ex(gamma), w, ex(beta), ex(gamma), w, ls, os)
    torch.testing.assert_close(op.to_dense(), D, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(op._diagonal(), torch.diagonal(D, dim1=-2, dim2=-1), rtol=1e-12, atol=1e-13)
    i, j, bi = torch.tensor([0, 1, 4, 6]), torch.tensor([4, 2, 4, 0]), torch.tensor([1, 0, 1, 0])
    torch.testing.assert_close(op[bi, i, j], D[bi, i, j], rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(op[..., 1:5, 2:].to_dense(), D[..., 1:5, 2:], rtol=1e-12, atol=1e-13)
    rhs = torch.randn(2, T, 3, generator=g, dtype=dt)
    torch.testing.assert_close(op.matmul(rhs), D @ rhs, rtol=1e-12, atol=1e-12)
    # gradients in the hyperparameters
    ls_, os_ = ls.clone().requires_grad_(), os.clone().requires_grad_()
    got = torch.autograd.grad(RFTKernelLinearOperator.from_structure(st, ls_, os_, B).to_dense().pow(2).sum(),
                              (ls_, os_))
    ls2, os2 = ls.clone().requires_grad_(), os.clone().requires_grad_()
    want = torch.autograd.grad(_dense_segments(ex(beta), ex(gamma), w, ex(beta), ex(gamma), w, ls2, os2).pow(2).sum(),
                               (ls2, os2))
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    # cross-covariances: a general right side falls back; a translating one keeps the product form
    b2 = (torch.rand(5, 3, generator=g, dtype=dt) - 0.5) * math.pi
    w2 = torch.rand(2, 5, 3, generator=g, dtype=dt)
    for g2, separable in (((torch.rand(5, 3, generator=g, dtype=dt) - 0.5) * math.pi, False),
                          (((torch.rand(5, 1, generator=g, dtype=dt) - 0.5) * math.pi).expand(5, 3).clone(), True)):
        st2 = RFTKernelLinearOperator.segment_structure(beta[None], gamma[None], w, b2[None], g2[None], w2, B)
        op2 = RFTKernelLinearOperator.from_structure(st2, ls, os, B)
        assert isinstance(op2, RowSeparableRFTOperator) == separable
        D2 = _dense_segments(ex(beta), ex(gamma), w, ex(b2), ex(g2), w2, ls, os)
        torch.testing.assert_close(op2.to_dense(), D2, rtol=1e-12, atol=1e-13)
        torch.testing.assert_close(op2.mT.to_dense(), D2.mT, rtol=1e-12, atol=1e-13)
