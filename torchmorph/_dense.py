"""A stored dense matrix times a few columns on the CPU, read at the memory's speed.

A morph with a stored matrix (IDW's W, the paper's Algorithm 2; RBF's evaluation matrix
``[Φ_tc P_t]``) spends each later morph in one product ``M @ d`` with a handful of
columns (D = 2 or 3 per displacement field). The BLAS reads M as a general matrix
product and reaches a fraction of the memory bandwidth there: measured on one thread
(AMD EPYC, float64), torch's ``mm`` took 0.35 s for 50,000 × 5,004 and three columns,
where one pass that reads M once, four rows at a time with the three columns' entries
loaded once for the four, took 0.105 s; at case C's W (3,322 × 3,864) 6.3 ms against
18 ms, at case B's (19,852 × 13,616) 111 ms against 375 ms. Sums are kept in float64,
also for a float32 matrix (one rounding of the result instead of a float32 BLAS sum).

:func:`dense_product` is that pass (numba, ``prange`` over blocks of rows on numba's
current thread count) for float32 and float64 matrices, three columns per pass;
:func:`applies` says when it is the faster choice.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

try:  # numba is optional: without it torch's product runs
    from numba import njit, prange
except ImportError:  # pragma: no cover - exercised where numba is missing
    njit = None  # type: ignore[assignment]
    prange = range  # type: ignore[misc,assignment]

__all__ = ["MAX_COLUMNS", "applies", "dense_product"]

#: The most value columns the pass takes (three per pass over the matrix: up to three
#: passes, still faster than the BLAS product, measured 0.34 s against 0.36 s for six
#: columns at 50,000 × 5,004 with two passes).
MAX_COLUMNS = 9

_BLOCK_ROWS = 64  # rows per parallel block (a multiple of the four of the inner loop)


def _three_columns(matrix, columns_t, out):
    """out[:, :3] = matrix @ columns_t[:3].T, float64 sums."""
    rows, width = matrix.shape
    first, second, third = columns_t[0], columns_t[1], columns_t[2]
    for block in prange((rows + _BLOCK_ROWS - 1) // _BLOCK_ROWS):
        end = min(rows, (block + 1) * _BLOCK_ROWS)
        for i in range(block * _BLOCK_ROWS, end, 4):
            if i + 4 <= end:
                r0, r1, r2, r3 = matrix[i], matrix[i + 1], matrix[i + 2], matrix[i + 3]
                a0 = a1 = a2 = a3 = 0.0
                b0 = b1 = b2 = b3 = 0.0
                c0 = c1 = c2 = c3 = 0.0
                for j in range(width):
                    x, y, z = first[j], second[j], third[j]
                    v = np.float64(r0[j])
                    a0 += v * x
                    b0 += v * y
                    c0 += v * z
                    v = np.float64(r1[j])
                    a1 += v * x
                    b1 += v * y
                    c1 += v * z
                    v = np.float64(r2[j])
                    a2 += v * x
                    b2 += v * y
                    c2 += v * z
                    v = np.float64(r3[j])
                    a3 += v * x
                    b3 += v * y
                    c3 += v * z
                out[i, 0], out[i, 1], out[i, 2] = a0, b0, c0
                out[i + 1, 0], out[i + 1, 1], out[i + 1, 2] = a1, b1, c1
                out[i + 2, 0], out[i + 2, 1], out[i + 2, 2] = a2, b2, c2
                out[i + 3, 0], out[i + 3, 1], out[i + 3, 2] = a3, b3, c3
            else:
                for k in range(i, end):
                    row = matrix[k]
                    a = b = c = 0.0
                    for j in range(width):
                        v = np.float64(row[j])
                        a += v * first[j]
                        b += v * second[j]
                        c += v * third[j]
                    out[k, 0], out[k, 1], out[k, 2] = a, b, c


if njit is not None:
    _three_columns = njit(
        parallel=True,
        fastmath={"reassoc", "contract", "nsz", "arcp"},
        error_model="numpy",
        cache=True,
        nogil=True,
    )(_three_columns)


def applies(matrix: Tensor, values: Tensor) -> bool:
    """Whether :func:`dense_product` takes ``matrix @ values``: a contiguous float32 or
    float64 CPU matrix without gradient, 2 to :data:`MAX_COLUMNS` value columns (one
    column is the BLAS's matrix-vector product, as fast), numba installed."""
    return (
        njit is not None
        and 2 <= values.shape[-1] <= MAX_COLUMNS
        and values.ndim == 2
        and matrix.device.type == "cpu"
        and matrix.dtype in (torch.float32, torch.float64)
        and matrix.is_contiguous()
        and not matrix.requires_grad
    )


def dense_product(matrix: Tensor, values: Tensor) -> Tensor:
    """``matrix @ values``, (N, M) @ (M, S) -> (N, S) in the matrix's dtype, by passes
    that read the matrix once per three columns (see :func:`applies` for when it
    is the faster choice); differentiable in ``values`` (the matrix is a constant)."""
    return _DenseProduct.apply(matrix, values)


class _DenseProduct(torch.autograd.Function):
    @staticmethod
    def forward(ctx, matrix, values):  # type: ignore[override]
        ctx.save_for_backward(matrix)
        ctx.values_dtype = values.dtype
        columns = values.shape[1]
        padded = -(-columns // 3) * 3
        columns_t = np.zeros((padded, values.shape[0]))
        columns_t[:columns] = values.detach().double().numpy().T
        out = np.empty((padded // 3, matrix.shape[0], 3))
        array = matrix.detach().numpy()
        if matrix.shape[0]:
            for group in range(padded // 3):
                _three_columns(array, columns_t[3 * group : 3 * group + 3], out[group])
        joined = out.transpose(1, 0, 2).reshape(matrix.shape[0], padded)
        return torch.from_numpy(np.ascontiguousarray(joined[:, :columns])).to(matrix.dtype)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        (matrix,) = ctx.saved_tensors
        return None, (matrix.mT @ grad.to(matrix.dtype)).to(ctx.values_dtype)
