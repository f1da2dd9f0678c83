"""The stored-matrix product of :mod:`torchmorph._dense` against torch's, in both dtypes."""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from torchmorph import _dense
from torchmorph.idw.backends.numba.kernels import available

pytestmark = pytest.mark.skipif(not available(), reason="the pass needs numba")


def matrix(rows, columns, seed=0, dtype=torch.float64):
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(rows, columns, generator=generator, dtype=torch.float64).to(dtype)


@pytest.mark.parametrize("rows", [0, 1, 5, 64, 67, 1_001])  # whole blocks of four, and not
@pytest.mark.parametrize("columns", [2, 3, 4, 7, 9])
def test_equals_the_float64_product(rows, columns):
    left, right = matrix(rows, 37), matrix(37, columns, seed=1) - 0.5
    product = _dense.dense_product(left, right)
    assert product.shape == (rows, columns) and product.dtype == torch.float64
    torch.testing.assert_close(product, left @ right, rtol=1e-13, atol=1e-13)


def test_float32_sums_in_float64():
    # one rounding of the float64 sum: within an ulp of it, where a float32 BLAS sum of
    # 20,000 terms is not
    left = matrix(64, 20_000, dtype=torch.float32)
    right = matrix(20_000, 3, seed=1, dtype=torch.float32) - 0.5
    exact = left.double() @ right.double()
    product = _dense.dense_product(left, right)
    assert product.dtype == torch.float32
    ulp = torch.finfo(torch.float32).eps * exact.abs()
    assert bool(((product.double() - exact).abs() <= ulp).all())


def test_differentiable_in_the_values():
    left = matrix(9, 6)
    right = (matrix(6, 3, seed=1) - 0.5).requires_grad_()
    assert gradcheck(lambda values: _dense.dense_product(left, values), (right,))


def test_applies_only_where_it_is_faster():
    left = matrix(10, 6)
    assert _dense.applies(left, matrix(6, 3))
    assert not _dense.applies(left, matrix(6, 1))  # a matrix-vector product
    assert not _dense.applies(left, matrix(6, _dense.MAX_COLUMNS + 1))
    assert not _dense.applies(left.T, matrix(10, 3))  # not row-major
    assert not _dense.applies(left.requires_grad_(), matrix(6, 3))
    assert not _dense.applies(matrix(10, 6).to(torch.int64), matrix(6, 3))
