"""The numba kernel that scores every candidate of the IDW error oracle in one pass over
the sampled full-IDW weights (:class:`torchmorph.selection.adaptive.IDWErrorOracle`).

For a candidate j (a row of ``Wᵀ``) and the sampled targets i it forms
``t_ij = W_ij / (σ_i + W_ij)`` once and returns ``Σ_i t_ij a_ki`` and ``Σ_i t_ij² b_ki``
for the columns ``a_k``, ``b_k`` of two fields on the
targets: the products ``T a`` and ``T² b`` of the oracle's scores, without
materialising ``T``. Rows run in parallel (numba threads); each row's ratios stay in a
scratch buffer read once per column.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchmorph.idw.backends.numba._jit import _OPTIONS, njit, numba, prange

__all__ = ["available", "score_rows"]


def available(weights_t: Tensor) -> bool:
    """Whether the kernel serves these weights (numba present, CPU, float32/float64)."""
    return (
        numba is not None
        and weights_t.device.type == "cpu"
        and weights_t.dtype in (torch.float32, torch.float64)
    )


@njit(**_OPTIONS)
def _reduce(ratio, columns, count, out):
    """out[k] = Σ_i ratio[i] columns[k, i] over the first ``count`` entries."""
    for k in range(columns.shape[0]):
        column = columns[k]
        total = 0.0
        for i in range(count):
            total += ratio[i] * column[i]
        out[k] = total


@njit(parallel=True, **_OPTIONS)
def _score_rows(weights_t, count, sums, linear, square, first, second):
    rows = weights_t.shape[0]
    tiny = np.finfo(sums.dtype).tiny
    for j in prange(rows):
        row = weights_t[j]
        ratio = np.empty(count, dtype=sums.dtype)
        for i in range(count):
            ratio[i] = row[i] / max(sums[i] + row[i], tiny)
        _reduce(ratio, linear, count, first[j])
        for i in range(count):
            ratio[i] *= ratio[i]
        _reduce(ratio, square, count, second[j])


def score_rows(
    weights_t: Tensor, count: int, sums: Tensor, linear: Tensor, square: Tensor
) -> tuple[Tensor, Tensor]:
    """``(T a, T² b)`` over the first ``count`` columns of ``weights_t`` (N_c, N_s):
    ``t_ij = W_ij / (σ_i + W_ij)``, ``a = linear`` (count, K1), ``b = square`` (count, K2),
    ``σ = sums`` (count,); results (N_c, K1) and (N_c, K2) in the weights' dtype."""
    dtype = weights_t.dtype
    matrix = weights_t.contiguous().numpy()
    columns_a = np.ascontiguousarray(linear.to(dtype).mT.numpy())
    columns_b = np.ascontiguousarray(square.to(dtype).mT.numpy())
    sums_np = np.ascontiguousarray(sums.to(dtype).numpy())
    rows = matrix.shape[0]
    first = np.empty((rows, columns_a.shape[0]), dtype=matrix.dtype)
    second = np.empty((rows, columns_b.shape[0]), dtype=matrix.dtype)
    _score_rows(matrix, count, sums_np, columns_a, columns_b, first, second)
    return torch.from_numpy(first), torch.from_numpy(second)
