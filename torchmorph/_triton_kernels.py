"""Fused IDW kernels in Triton (CUDA; and the CPU through ``TRITON_INTERPRET=1``).

Each kernel computes the paper's eq. (2) weights in registers and never writes a
pairwise tile to memory. The caller (:mod:`torchmorph.idw`) hands over geometry
already translated and scaled so that the point cloud's bounding-box diagonal is 1,
coordinates stored axis by axis (shape ``(D, N)``, contiguous), so every squared
distance lies in [0, 1] and a block of one coordinate is one contiguous load.

For target ``i`` and control ``k``, with ``d²_ik`` from direct coordinate
differences floored at the dtype's smallest normal ``tiny`` and ``m_i = min_k d²_ik``:

- an ordinary row (``m_i > radius2``) has ``r_ik = (m_i / d²_ik)^(p/2)`` (every term
  in [0, 1]) and ``w_ik = r_ik / s_i`` with ``s_i = Σ_k r_ik``;
- a coincident row (``m_i <= radius2``) has ``r_ik = [d²_ik <= radius2]`` and
  ``s_i`` their count: the target takes the mean of the controls it sits on.

Kernels
-------
``_apply_kernel``
    ``W @ V`` for V of shape (N_c, K): one pass over the controls keeping a running
    minimum ``m`` and rescaling the accumulators whenever it drops (as online
    softmax does), so no separate nearest-distance pass is needed; coincident rows
    are redone with indicator weights in the same program, after the main loop.
    Also returns ``m_i`` and ``s_i`` for the backward pass.
``_apply_transposed_kernel``
    ``Wᵀ @ G`` (the gradient to the displacements): parallel over controls, looping
    over targets with the saved ``m_i`` and ``s_i``.
``_row_stats_kernel`` + ``_weights_kernel``
    dense W: the row statistics ``m_i, s_i`` first, then W written tile by tile.
``_dense_apply_kernel``
    ``W @ v`` for a stored W and at most three columns, reading W once.

Each has a plain torch twin in :mod:`torchmorph.idw` that the tests compare it with.
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl
from torch import Tensor

__all__ = [
    "apply",
    "apply_transposed",
    "dense_apply",
    "nearest_squared",
    "position_gradients",
    "power_kind",
    "tile_shapes",
    "weights",
]


def power_kind(power: float) -> int:
    """A compile-time code for ``(m/d²)^(p/2)``: 4 → square, 2 → the ratio, 1 → its
    square root, 0 → any other p through exp2/log2."""
    return {4.0: 4, 2.0: 2, 1.0: 1}.get(float(power), 0)


@triton.jit
def _divide(numerator, denominator, FAST: tl.constexpr):
    """``numerator / denominator`` for positive normal operands.

    FAST == 1: float32 approximate division (2 ulp). FAST == 2: float64 reciprocal
    estimate refined by two Newton steps (full precision, a fraction of the cost of
    IEEE division). Otherwise IEEE division (the interpreter's only option).
    """
    if FAST == 1:
        result = tl.fdiv(numerator, denominator, ieee_rounding=False)
    elif FAST == 2:
        guess = tl.inline_asm_elementwise(
            "rcp.approx.ftz.f64 $0, $1;",
            "=d,d",
            [denominator],
            dtype=tl.float64,
            is_pure=True,
            pack=1,
        )
        guess = guess + guess * (1.0 - denominator * guess)
        guess = guess + guess * (1.0 - denominator * guess)
        # a masked column (denominator +inf) has guess 0 and a NaN correction: weight 0
        result = tl.where(denominator == float("inf"), 0.0, numerator * guess)
    else:
        result = numerator / denominator
    return result


@triton.jit
def _ratio_power(nearest2, dist2, half_power, KIND: tl.constexpr, FAST: tl.constexpr):
    """``(nearest2 / dist2)^(p/2)`` for ``0 < nearest2 <= dist2`` (0 where dist2 is inf)."""
    ratio = _divide(nearest2, dist2, FAST)
    if KIND == 4:
        result = ratio * ratio
    elif KIND == 2:
        result = ratio
    elif KIND == 1:
        result = tl.sqrt(ratio)
    else:
        result = tl.exp2(half_power * tl.log2(ratio))
    return result


@triton.jit
def _squared_distances(
    rows_t,
    n_rows,
    rows,
    row_ok,
    cols_t,
    n_cols,
    cols,
    col_ok,
    tiny,
    D: tl.constexpr,
    BLOCK_R: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    """(BLOCK_R, BLOCK_C) squared distances between a block of rows and one of columns
    (coordinates stored axis by axis), floored at ``tiny``; ``+inf`` in masked columns."""
    dist2 = tl.zeros((BLOCK_R, BLOCK_C), dtype=cols_t.dtype.element_ty)
    for axis in tl.static_range(D):
        r = tl.load(rows_t + axis * n_rows + rows, mask=row_ok, other=0.0)
        c = tl.load(cols_t + axis * n_cols + cols, mask=col_ok, other=0.0)
        diff = r[:, None] - c[None, :]
        dist2 += diff * diff
    return tl.where(col_ok[None, :], tl.maximum(dist2, tiny), float("inf"))


@triton.jit
def _weight_tile(
    dist2,
    nearest2,
    coincident,
    any_coincident,
    radius2,
    half_power,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    ROWWISE: tl.constexpr,
):
    """r for a tile: ratio powers, or indicators on coincident rows (ROWWISE) or
    columns (the transposed pass, where each column is a target)."""
    if ROWWISE:
        weight = _ratio_power(nearest2[:, None], dist2, half_power, KIND, FAST)
        if any_coincident:
            indicator = tl.where(dist2 <= radius2, 1.0, 0.0).to(weight.dtype)
            weight = tl.where(coincident[:, None], indicator, weight)
    else:
        weight = _ratio_power(nearest2[None, :], dist2, half_power, KIND, FAST)
        if any_coincident:
            indicator = tl.where(dist2 <= radius2, 1.0, 0.0).to(weight.dtype)
            weight = tl.where(coincident[None, :], indicator, weight)
    return weight


@triton.jit
def _nearest_kernel(
    targets_t,
    controls_t,
    nearest_out,
    n_t,
    n_c,
    tiny,
    D: tl.constexpr,
    BLOCK_T: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    # pass 1: m_i = min_k d²_ik, kept per tile position and reduced once at the end
    rows = tl.program_id(0) * BLOCK_T + tl.arange(0, BLOCK_T)
    row_ok = rows < n_t
    cols0 = tl.arange(0, BLOCK_C)
    best = tl.full((BLOCK_T, BLOCK_C), float("inf"), dtype=controls_t.dtype.element_ty)
    for start in range(0, n_c, BLOCK_C):
        cols = start + cols0
        col_ok = cols < n_c
        best = tl.minimum(
            best,
            _squared_distances(
                targets_t,
                n_t,
                rows,
                row_ok,
                controls_t,
                n_c,
                cols,
                col_ok,
                tiny,
                D,
                BLOCK_T,
                BLOCK_C,
            ),
        )
    tl.store(nearest_out + rows, tl.min(best, axis=1), mask=row_ok)


@triton.jit
def _apply_kernel(
    targets_t,
    controls_t,
    values,
    nearest2_in,
    out,
    sums_out,
    n_t,
    n_c,
    stride_v,
    stride_o,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    K: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    BLOCK_T: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    # pass 2, K <= 3 columns: ratio weights against [v, 1], accumulated per tile
    # position (no reduction inside the loop), divided at the end
    rows = tl.program_id(0) * BLOCK_T + tl.arange(0, BLOCK_T)
    row_ok = rows < n_t
    cols0 = tl.arange(0, BLOCK_C)
    dtype = controls_t.dtype.element_ty
    nearest2 = tl.load(nearest2_in + rows, mask=row_ok, other=1.0)
    coincident = (nearest2 <= radius2) & row_ok
    any_coincident = tl.max(coincident.to(tl.int32), axis=0) > 0
    sums = tl.zeros((BLOCK_T, BLOCK_C), dtype=dtype)
    acc0 = tl.zeros((BLOCK_T, BLOCK_C), dtype=dtype)
    acc1 = tl.zeros((BLOCK_T, BLOCK_C), dtype=dtype)
    acc2 = tl.zeros((BLOCK_T, BLOCK_C), dtype=dtype)
    for start in range(0, n_c, BLOCK_C):
        cols = start + cols0
        col_ok = cols < n_c
        dist2 = _squared_distances(
            targets_t, n_t, rows, row_ok, controls_t, n_c, cols, col_ok, tiny, D, BLOCK_T, BLOCK_C
        )
        weight = _weight_tile(
            dist2, nearest2, coincident, any_coincident, radius2, half_power, KIND, FAST, True
        )
        sums += weight
        if K > 0:
            acc0 += (
                weight
                * tl.load(values + cols.to(tl.int64) * stride_v, mask=col_ok, other=0.0)[None, :]
            )
        if K > 1:
            acc1 += (
                weight
                * tl.load(values + cols.to(tl.int64) * stride_v + 1, mask=col_ok, other=0.0)[
                    None, :
                ]
            )
        if K > 2:
            acc2 += (
                weight
                * tl.load(values + cols.to(tl.int64) * stride_v + 2, mask=col_ok, other=0.0)[
                    None, :
                ]
            )
    total = tl.sum(sums, axis=1)
    tl.store(sums_out + rows, total, mask=row_ok)
    if K > 0:
        tl.store(out + rows.to(tl.int64) * stride_o, tl.sum(acc0, axis=1) / total, mask=row_ok)
    if K > 1:
        tl.store(out + rows.to(tl.int64) * stride_o + 1, tl.sum(acc1, axis=1) / total, mask=row_ok)
    if K > 2:
        tl.store(out + rows.to(tl.int64) * stride_o + 2, tl.sum(acc2, axis=1) / total, mask=row_ok)


@triton.jit
def _apply_dot_kernel(
    targets_t,
    controls_t,
    values,
    nearest2_in,
    out,
    sums_out,
    n_t,
    n_c,
    stride_v,
    stride_o,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    K: tl.constexpr,
    KP: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    PRECISION: tl.constexpr,
    BLOCK_T: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    # pass 2, any K: the tile of ratio weights times [v, 1] (column K of ones gives
    # the row sums) on the matrix units, divided at the end
    rows = tl.program_id(0) * BLOCK_T + tl.arange(0, BLOCK_T)
    row_ok = rows < n_t
    cols0 = tl.arange(0, BLOCK_C)
    k_idx = tl.arange(0, KP)
    dtype = controls_t.dtype.element_ty
    nearest2 = tl.load(nearest2_in + rows, mask=row_ok, other=1.0)
    coincident = (nearest2 <= radius2) & row_ok
    any_coincident = tl.max(coincident.to(tl.int32), axis=0) > 0
    acc = tl.zeros((BLOCK_T, KP), dtype=dtype)
    for start in range(0, n_c, BLOCK_C):
        cols = start + cols0
        col_ok = cols < n_c
        dist2 = _squared_distances(
            targets_t, n_t, rows, row_ok, controls_t, n_c, cols, col_ok, tiny, D, BLOCK_T, BLOCK_C
        )
        weight = _weight_tile(
            dist2, nearest2, coincident, any_coincident, radius2, half_power, KIND, FAST, True
        )
        v = tl.load(
            values + cols.to(tl.int64)[:, None] * stride_v + k_idx[None, :],
            mask=col_ok[:, None] & (k_idx[None, :] < K),
            other=0.0,
        )
        v = tl.where((k_idx[None, :] == K) & col_ok[:, None], 1.0, v).to(dtype)
        if PRECISION == 1:
            acc += tl.dot(weight, v, input_precision="tf32x3")
        elif PRECISION == 2:
            acc += tl.dot(weight, v, input_precision="ieee")
        else:
            acc += tl.dot(weight, v)
    total = tl.sum(tl.where(k_idx[None, :] == K, acc, 0.0), axis=1)
    tl.store(sums_out + rows, total, mask=row_ok)
    tl.store(
        out + rows.to(tl.int64)[:, None] * stride_o + k_idx[None, :],
        acc / total[:, None],
        mask=row_ok[:, None] & (k_idx[None, :] < K),
    )


@triton.jit
def _transposed_kernel(
    controls_t,
    targets_t,
    nearest2_in,
    grad,
    out,
    n_c,
    n_t,
    stride_g,
    stride_o,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    K: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    BLOCK_C: tl.constexpr,
    BLOCK_T: tl.constexpr,
):
    # Wᵀ G for K <= 3 (G already divided by the row sums s_i): parallel over controls
    rows = tl.program_id(0) * BLOCK_C + tl.arange(0, BLOCK_C)
    row_ok = rows < n_c
    cols0 = tl.arange(0, BLOCK_T)
    dtype = controls_t.dtype.element_ty
    acc0 = tl.zeros((BLOCK_C, BLOCK_T), dtype=dtype)
    acc1 = tl.zeros((BLOCK_C, BLOCK_T), dtype=dtype)
    acc2 = tl.zeros((BLOCK_C, BLOCK_T), dtype=dtype)
    for start in range(0, n_t, BLOCK_T):
        cols = start + cols0
        col_ok = cols < n_t
        dist2 = _squared_distances(
            controls_t, n_c, rows, row_ok, targets_t, n_t, cols, col_ok, tiny, D, BLOCK_C, BLOCK_T
        )
        nearest2 = tl.load(nearest2_in + cols, mask=col_ok, other=1.0)
        coincident = (nearest2 <= radius2) & col_ok
        any_coincident = tl.max(coincident.to(tl.int32), axis=0) > 0
        weight = _weight_tile(
            dist2, nearest2, coincident, any_coincident, radius2, half_power, KIND, FAST, False
        )
        acc0 += (
            weight * tl.load(grad + cols.to(tl.int64) * stride_g, mask=col_ok, other=0.0)[None, :]
        )
        if K > 1:
            acc1 += (
                weight
                * tl.load(grad + cols.to(tl.int64) * stride_g + 1, mask=col_ok, other=0.0)[None, :]
            )
        if K > 2:
            acc2 += (
                weight
                * tl.load(grad + cols.to(tl.int64) * stride_g + 2, mask=col_ok, other=0.0)[None, :]
            )
    tl.store(out + rows.to(tl.int64) * stride_o, tl.sum(acc0, axis=1), mask=row_ok)
    if K > 1:
        tl.store(out + rows.to(tl.int64) * stride_o + 1, tl.sum(acc1, axis=1), mask=row_ok)
    if K > 2:
        tl.store(out + rows.to(tl.int64) * stride_o + 2, tl.sum(acc2, axis=1), mask=row_ok)


@triton.jit
def _transposed_dot_kernel(
    controls_t,
    targets_t,
    nearest2_in,
    grad,
    out,
    n_c,
    n_t,
    stride_g,
    stride_o,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    K: tl.constexpr,
    KP: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    PRECISION: tl.constexpr,
    BLOCK_C: tl.constexpr,
    BLOCK_T: tl.constexpr,
):
    # Wᵀ G for any K on the matrix units (G already divided by the row sums s_i)
    rows = tl.program_id(0) * BLOCK_C + tl.arange(0, BLOCK_C)
    row_ok = rows < n_c
    cols0 = tl.arange(0, BLOCK_T)
    k_idx = tl.arange(0, KP)
    dtype = controls_t.dtype.element_ty
    acc = tl.zeros((BLOCK_C, KP), dtype=dtype)
    for start in range(0, n_t, BLOCK_T):
        cols = start + cols0
        col_ok = cols < n_t
        dist2 = _squared_distances(
            controls_t, n_c, rows, row_ok, targets_t, n_t, cols, col_ok, tiny, D, BLOCK_C, BLOCK_T
        )
        nearest2 = tl.load(nearest2_in + cols, mask=col_ok, other=1.0)
        coincident = (nearest2 <= radius2) & col_ok
        any_coincident = tl.max(coincident.to(tl.int32), axis=0) > 0
        weight = _weight_tile(
            dist2, nearest2, coincident, any_coincident, radius2, half_power, KIND, FAST, False
        )
        g = tl.load(
            grad + cols.to(tl.int64)[:, None] * stride_g + k_idx[None, :],
            mask=col_ok[:, None] & (k_idx[None, :] < K),
            other=0.0,
        )
        if PRECISION == 1:
            acc += tl.dot(weight, g, input_precision="tf32x3")
        elif PRECISION == 2:
            acc += tl.dot(weight, g, input_precision="ieee")
        else:
            acc += tl.dot(weight, g)
    tl.store(
        out + rows.to(tl.int64)[:, None] * stride_o + k_idx[None, :],
        acc,
        mask=row_ok[:, None] & (k_idx[None, :] < K),
    )


@triton.jit
def _position_grad_kernel(
    rows_t,
    cols_t,
    rows_values,
    cols_values,
    rows_extra,
    cols_extra,
    nearest2_in,
    out_grad_t,
    n_rows,
    n_cols,
    stride_rv,
    stride_cv,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    K: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    TARGET_ROWS: tl.constexpr,
    BLOCK_R: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    # Gradient to point positions, one side per launch. With G the incoming gradient,
    # G~ = G / s and a = G~ . out per target, dL/dd²_ik = -(p/2) r_ik / d²_ik (G~_i . v_k - a_i)
    # on ordinary rows (0 on coincident ones), and dd²_ik/dt_i = 2 (t_i - c_k) = -dd²_ik/dc_k.
    # TARGET_ROWS: rows are targets (values = G~, extra = a) and columns controls (values v);
    # otherwise rows are controls (values v) and columns targets (values = G~, extra = a).
    rows = tl.program_id(0) * BLOCK_R + tl.arange(0, BLOCK_R)
    row_ok = rows < n_rows
    cols0 = tl.arange(0, BLOCK_C)
    dtype = cols_t.dtype.element_ty
    acc0 = tl.zeros((BLOCK_R, BLOCK_C), dtype=dtype)
    acc1 = tl.zeros((BLOCK_R, BLOCK_C), dtype=dtype)
    acc2 = tl.zeros((BLOCK_R, BLOCK_C), dtype=dtype)
    if TARGET_ROWS:
        nearest2_rows = tl.load(nearest2_in + rows, mask=row_ok, other=1.0)
        extra_rows = tl.load(rows_extra + rows, mask=row_ok, other=0.0)
    for start in range(0, n_cols, BLOCK_C):
        cols = start + cols0
        col_ok = cols < n_cols
        dist2 = _squared_distances(
            rows_t, n_rows, rows, row_ok, cols_t, n_cols, cols, col_ok, tiny, D, BLOCK_R, BLOCK_C
        )
        products = tl.zeros((BLOCK_R, BLOCK_C), dtype=dtype)
        for j in tl.static_range(K):
            left = tl.load(rows_values + rows.to(tl.int64) * stride_rv + j, mask=row_ok, other=0.0)
            right = tl.load(cols_values + cols.to(tl.int64) * stride_cv + j, mask=col_ok, other=0.0)
            products += left[:, None] * right[None, :]
        if TARGET_ROWS:
            ratio = _ratio_power(nearest2_rows[:, None], dist2, half_power, KIND, FAST)
            coefficient = _divide(ratio, dist2, FAST) * (products - extra_rows[:, None])
            ordinary = (nearest2_rows > radius2)[:, None] & col_ok[None, :]
        else:
            nearest2_cols = tl.load(nearest2_in + cols, mask=col_ok, other=1.0)
            extra_cols = tl.load(cols_extra + cols, mask=col_ok, other=0.0)
            ratio = _ratio_power(nearest2_cols[None, :], dist2, half_power, KIND, FAST)
            coefficient = _divide(ratio, dist2, FAST) * (products - extra_cols[None, :])
            ordinary = (nearest2_cols > radius2)[None, :] & col_ok[None, :]
        coefficient = tl.where(ordinary, coefficient, 0.0)
        r = tl.load(rows_t + rows, mask=row_ok, other=0.0)
        c = tl.load(cols_t + cols, mask=col_ok, other=0.0)
        acc0 += coefficient * (r[:, None] - c[None, :])
        if D > 1:
            r = tl.load(rows_t + n_rows + rows, mask=row_ok, other=0.0)
            c = tl.load(cols_t + n_cols + cols, mask=col_ok, other=0.0)
            acc1 += coefficient * (r[:, None] - c[None, :])
        if D > 2:
            r = tl.load(rows_t + 2 * n_rows + rows, mask=row_ok, other=0.0)
            c = tl.load(cols_t + 2 * n_cols + cols, mask=col_ok, other=0.0)
            acc2 += coefficient * (r[:, None] - c[None, :])
    # d/dt: -p Σ_k coef (t - c); d/dc: +p Σ_i coef (t - c) = -p Σ_i coef (c - t)
    factor = -2.0 * half_power
    tl.store(out_grad_t + rows, factor * tl.sum(acc0, axis=1), mask=row_ok)
    if D > 1:
        tl.store(out_grad_t + n_rows + rows, factor * tl.sum(acc1, axis=1), mask=row_ok)
    if D > 2:
        tl.store(out_grad_t + 2 * n_rows + rows, factor * tl.sum(acc2, axis=1), mask=row_ok)


@triton.jit
def _weights_kernel(
    targets_t,
    controls_t,
    nearest2_in,
    sums_in,
    out,
    n_t,
    n_c,
    stride_o,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    BLOCK_T: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    # one (BLOCK_T, BLOCK_C) tile of W from the row statistics m_i, s_i
    rows = tl.program_id(0) * BLOCK_T + tl.arange(0, BLOCK_T)
    cols = tl.program_id(1) * BLOCK_C + tl.arange(0, BLOCK_C)
    row_ok = rows < n_t
    col_ok = cols < n_c
    dist2 = _squared_distances(
        targets_t, n_t, rows, row_ok, controls_t, n_c, cols, col_ok, tiny, D, BLOCK_T, BLOCK_C
    )
    nearest2 = tl.load(nearest2_in + rows, mask=row_ok, other=1.0)
    sums = tl.load(sums_in + rows, mask=row_ok, other=1.0)
    coincident = (nearest2 <= radius2) & row_ok
    any_coincident = tl.max(coincident.to(tl.int32), axis=0) > 0
    weight = _weight_tile(
        dist2, nearest2, coincident, any_coincident, radius2, half_power, KIND, FAST, True
    )
    # 64-bit offsets: W may hold more than 2**31 entries
    tl.store(
        out + rows.to(tl.int64)[:, None] * stride_o + cols[None, :],
        weight / sums[:, None],
        mask=row_ok[:, None] & col_ok[None, :],
    )


@triton.jit
def _dense_apply_kernel(
    weights,
    values,
    out,
    n_t,
    n_c,
    stride_w,
    stride_v,
    stride_o,
    K: tl.constexpr,
    BLOCK_T: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    # out = W @ v for K <= 3 columns, W read once, tile by tile along its rows
    rows = tl.program_id(0) * BLOCK_T + tl.arange(0, BLOCK_T)
    row_ok = rows < n_t
    cols0 = tl.arange(0, BLOCK_C)
    dtype = weights.dtype.element_ty
    acc0 = tl.zeros((BLOCK_T, BLOCK_C), dtype=dtype)
    acc1 = tl.zeros((BLOCK_T, BLOCK_C), dtype=dtype)
    acc2 = tl.zeros((BLOCK_T, BLOCK_C), dtype=dtype)
    for start in range(0, n_c, BLOCK_C):
        cols = start + cols0
        col_ok = cols < n_c
        w = tl.load(
            weights + rows.to(tl.int64)[:, None] * stride_w + cols[None, :],
            mask=row_ok[:, None] & col_ok[None, :],
            other=0.0,
        )
        acc0 += w * tl.load(values + cols.to(tl.int64) * stride_v, mask=col_ok, other=0.0)[None, :]
        if K > 1:
            acc1 += (
                w
                * tl.load(values + cols.to(tl.int64) * stride_v + 1, mask=col_ok, other=0.0)[
                    None, :
                ]
            )
        if K > 2:
            acc2 += (
                w
                * tl.load(values + cols.to(tl.int64) * stride_v + 2, mask=col_ok, other=0.0)[
                    None, :
                ]
            )
    tl.store(out + rows.to(tl.int64) * stride_o, tl.sum(acc0, axis=1), mask=row_ok)
    if K > 1:
        tl.store(out + rows.to(tl.int64) * stride_o + 1, tl.sum(acc1, axis=1), mask=row_ok)
    if K > 2:
        tl.store(out + rows.to(tl.int64) * stride_o + 2, tl.sum(acc2, axis=1), mask=row_ok)


# --------------------------------------------------------------------------- #
# launchers
# --------------------------------------------------------------------------- #
#: (BLOCK_rows, BLOCK_cols, num_warps) per kernel and dtype, from sweeps of
#: ``benchmarks/gpu_tiles.py`` on an H100; ``None`` is any dtype.
_TILES: dict[tuple[str, torch.dtype | None], tuple[int, int, int]] = {
    ("nearest", torch.float32): (16, 128, 4),
    ("nearest", torch.float64): (32, 64, 4),
    ("apply", torch.float32): (32, 64, 4),
    ("apply", torch.float64): (16, 128, 4),
    ("apply_dot", None): (32, 32, 4),
    ("transposed", None): (16, 128, 4),
    ("transposed_dot", torch.float32): (128, 32, 8),
    ("transposed_dot", torch.float64): (64, 32, 4),
    ("weights", None): (32, 256, 4),
    ("dense_apply", torch.float32): (8, 512, 8),
    ("dense_apply", torch.float64): (4, 512, 4),
    ("position_grad", None): (32, 64, 4),
}

#: Fused gradients to point positions: up to this many columns and three dimensions.
POSITION_GRAD_COLUMNS = 24

#: float32 ``tl.dot`` precision: 1 = tf32x3 (float32 accuracy from three tf32 products
#: on the matrix units), 2 = IEEE float32 on the ordinary cores.
DOT_PRECISION_FLOAT32 = 1

#: Tile shapes forced by the sweep script, by kernel name.
_OVERRIDE: dict[str, tuple[int, int, int]] = {}

#: Up to this many columns are accumulated one by one; more go through ``tl.dot``.
SMALL_COLUMNS = 3


def tile_shapes(kernel: str, dtype: torch.dtype) -> tuple[int, int, int]:
    """(BLOCK_rows, BLOCK_cols, num_warps) for ``kernel`` at ``dtype``."""
    if kernel in _OVERRIDE:
        return _OVERRIDE[kernel]
    return _TILES.get((kernel, dtype), _TILES.get((kernel, None), (64, 64, 4)))


def _interpreted() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def _constants(dtype: torch.dtype, power: float, radius2: float):
    """(radius2, tiny, p/2, KIND, FAST) for a launch."""
    tiny = torch.finfo(dtype).tiny
    fast = 0 if _interpreted() else (1 if dtype == torch.float32 else 2)
    return max(float(radius2), tiny), tiny, float(power) / 2, power_kind(power), fast


def _dot_layout(dtype: torch.dtype, columns: int) -> tuple[int, int]:
    """(KP, PRECISION) of a ``tl.dot`` accumulation of ``columns`` columns: KP a power of
    two >= 16 with room for the ones column; float32 through tf32x3 (float32 accuracy
    on the matrix units), float64 as is."""
    precision = DOT_PRECISION_FLOAT32 if dtype == torch.float32 else 0
    return max(16, triton.next_power_of_2(columns + 1)), precision


def nearest_squared(targets_t: Tensor, controls_t: Tensor) -> Tensor:
    """``max(min_k d²_ik, tiny)`` for each target, shape (N_t,)."""
    dim, n_t = targets_t.shape
    out = targets_t.new_empty(n_t)
    if n_t == 0:
        return out
    block_t, block_c, warps = tile_shapes("nearest", targets_t.dtype)
    _nearest_kernel[(triton.cdiv(n_t, block_t),)](
        targets_t,
        controls_t,
        out,
        n_t,
        controls_t.shape[1],
        torch.finfo(targets_t.dtype).tiny,
        D=dim,
        BLOCK_T=block_t,
        BLOCK_C=block_c,
        num_warps=warps,
    )
    return out


def apply(
    targets_t: Tensor,
    controls_t: Tensor,
    values: Tensor,
    power: float,
    radius2: float,
    nearest2: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """``W @ values`` with W never stored.

    Parameters
    ----------
    targets_t : Tensor, shape (D, N_t), contiguous, normalised coordinates
    controls_t : Tensor, shape (D, N_c), contiguous, normalised coordinates
    values : Tensor, shape (N_c, K), rows contiguous (K may be 0: row sums only)
    power, radius2 : the exponent p and the squared coincidence radius
    nearest2 : Tensor, shape (N_t,), optional
        :func:`nearest_squared` of the same geometry, when the caller has it.

    Returns
    -------
    (out (N_t, K), nearest2 (N_t,), sums (N_t,)): the result and the row statistics
    ``m_i`` and ``s_i`` for :func:`apply_transposed`.
    """
    dim, n_t = targets_t.shape
    n_c, columns = values.shape
    if nearest2 is None:
        nearest2 = nearest_squared(targets_t, controls_t)
    out = values.new_empty(n_t, columns)
    sums = values.new_empty(n_t)
    if n_t == 0:
        return out, nearest2, sums
    radius2, tiny, half_power, kind, fast = _constants(values.dtype, power, radius2)
    if columns <= SMALL_COLUMNS:
        block_t, block_c, warps = tile_shapes("apply", values.dtype)
        _apply_kernel[(triton.cdiv(n_t, block_t),)](
            targets_t,
            controls_t,
            values,
            nearest2,
            out,
            sums,
            n_t,
            n_c,
            values.stride(0) if n_c else 0,
            out.stride(0) if columns else 0,
            radius2,
            tiny,
            half_power,
            D=dim,
            K=columns,
            KIND=kind,
            FAST=fast,
            BLOCK_T=block_t,
            BLOCK_C=block_c,
            num_warps=warps,
        )
    else:
        padded, precision = _dot_layout(values.dtype, columns)
        block_t, block_c, warps = tile_shapes("apply_dot", values.dtype)
        _apply_dot_kernel[(triton.cdiv(n_t, block_t),)](
            targets_t,
            controls_t,
            values,
            nearest2,
            out,
            sums,
            n_t,
            n_c,
            values.stride(0),
            out.stride(0),
            radius2,
            tiny,
            half_power,
            D=dim,
            K=columns,
            KP=padded,
            KIND=kind,
            FAST=fast,
            PRECISION=precision,
            BLOCK_T=block_t,
            BLOCK_C=block_c,
            num_warps=warps,
        )
    return out, nearest2, sums


def apply_transposed(
    targets_t: Tensor,
    controls_t: Tensor,
    grad: Tensor,
    nearest2: Tensor,
    sums: Tensor,
    power: float,
    radius2: float,
) -> Tensor:
    """``Wᵀ @ grad`` for grad of shape (N_t, K), from the row statistics of :func:`apply`."""
    dim, n_c = controls_t.shape
    n_t, columns = grad.shape
    scaled = (grad / sums[:, None]).contiguous()
    out = grad.new_zeros(n_c, columns)
    if n_t == 0 or columns == 0:
        return out
    radius2, tiny, half_power, kind, fast = _constants(grad.dtype, power, radius2)
    if columns <= SMALL_COLUMNS:
        block_c, block_t, warps = tile_shapes("transposed", grad.dtype)
        _transposed_kernel[(triton.cdiv(n_c, block_c),)](
            controls_t,
            targets_t,
            nearest2,
            scaled,
            out,
            n_c,
            n_t,
            scaled.stride(0),
            out.stride(0),
            radius2,
            tiny,
            half_power,
            D=dim,
            K=columns,
            KIND=kind,
            FAST=fast,
            BLOCK_C=block_c,
            BLOCK_T=block_t,
            num_warps=warps,
        )
    else:
        padded, precision = _dot_layout(grad.dtype, columns)
        block_c, block_t, warps = tile_shapes("transposed_dot", grad.dtype)
        _transposed_dot_kernel[(triton.cdiv(n_c, block_c),)](
            controls_t,
            targets_t,
            nearest2,
            scaled,
            out,
            n_c,
            n_t,
            scaled.stride(0),
            out.stride(0),
            radius2,
            tiny,
            half_power,
            D=dim,
            K=columns,
            KP=padded,
            KIND=kind,
            FAST=fast,
            PRECISION=precision,
            BLOCK_C=block_c,
            BLOCK_T=block_t,
            num_warps=warps,
        )
    return out


def weights(
    targets_t: Tensor, controls_t: Tensor, power: float, radius2: float, out: Tensor | None = None
) -> Tensor:
    """Dense W (N_t, N_c), rows summing to 1, written once (into ``out`` if given)."""
    dim, n_t = targets_t.shape
    n_c = controls_t.shape[1]
    dtype = controls_t.dtype
    if out is None:
        out = controls_t.new_empty(n_t, n_c)
    if n_t == 0:
        return out
    _, nearest2, sums = apply(targets_t, controls_t, controls_t.new_empty(n_c, 0), power, radius2)
    radius2, tiny, half_power, kind, fast = _constants(dtype, power, radius2)
    block_t, block_c, warps = tile_shapes("weights", dtype)
    grid = (triton.cdiv(n_t, block_t), triton.cdiv(n_c, block_c))
    _weights_kernel[grid](
        targets_t,
        controls_t,
        nearest2,
        sums,
        out,
        n_t,
        n_c,
        out.stride(0),
        radius2,
        tiny,
        half_power,
        D=dim,
        KIND=kind,
        FAST=fast,
        BLOCK_T=block_t,
        BLOCK_C=block_c,
        num_warps=warps,
    )
    return out


def dense_apply(weights_matrix: Tensor, values: Tensor) -> Tensor:
    """``W @ values`` for a stored row-major W and at most three columns, reading W once."""
    n_t, n_c = weights_matrix.shape
    columns = values.shape[1]
    if not 1 <= columns <= SMALL_COLUMNS:
        raise ValueError(f"values: dense_apply takes 1 to {SMALL_COLUMNS} columns, got {columns}")
    out = values.new_empty(n_t, columns)
    if n_t == 0:
        return out
    block_t, block_c, warps = tile_shapes("dense_apply", values.dtype)
    _dense_apply_kernel[(triton.cdiv(n_t, block_t),)](
        weights_matrix,
        values,
        out,
        n_t,
        n_c,
        weights_matrix.stride(0),
        values.stride(0),
        out.stride(0),
        K=columns,
        BLOCK_T=block_t,
        BLOCK_C=block_c,
        num_warps=warps,
    )
    return out


def position_gradients(
    targets_t: Tensor,
    controls_t: Tensor,
    values: Tensor,
    grad: Tensor,
    out: Tensor,
    nearest2: Tensor,
    sums: Tensor,
    power: float,
    radius2: float,
    need_targets: bool = True,
    need_controls: bool = True,
) -> tuple[Tensor | None, Tensor | None]:
    """Gradients of ``L`` to the target and control coordinates, in the (D, N) layout,
    given ``grad = dL/d out`` for ``out = W @ values`` (from :func:`apply`).

    Coincident rows contribute nothing (their weights are locally constant). At most
    :data:`POSITION_GRAD_COLUMNS` columns and D <= 3.
    """
    dim, n_t = targets_t.shape
    n_c, columns = values.shape
    if dim > 3 or columns > POSITION_GRAD_COLUMNS:
        raise ValueError(
            f"position_gradients takes D <= 3 and at most {POSITION_GRAD_COLUMNS} "
            f"columns, got D = {dim}, {columns} columns"
        )
    scaled = (grad / sums[:, None]).contiguous()
    extra = (scaled * out).sum(1).contiguous()
    values = values.contiguous()
    radius2, tiny, half_power, kind, fast = _constants(values.dtype, power, radius2)
    block_r, block_c, warps = tile_shapes("position_grad", values.dtype)
    grad_targets = grad_controls = None
    if need_targets:
        grad_targets = torch.zeros_like(targets_t)
        if n_t:
            _position_grad_kernel[(triton.cdiv(n_t, block_r),)](
                targets_t,
                controls_t,
                scaled,
                values,
                extra,
                extra,
                nearest2,
                grad_targets,
                n_t,
                n_c,
                scaled.stride(0),
                values.stride(0),
                radius2,
                tiny,
                half_power,
                D=dim,
                K=columns,
                KIND=kind,
                FAST=fast,
                TARGET_ROWS=True,
                BLOCK_R=block_r,
                BLOCK_C=block_c,
                num_warps=warps,
            )
    if need_controls:
        grad_controls = torch.zeros_like(controls_t)
        if n_t:
            _position_grad_kernel[(triton.cdiv(n_c, block_r),)](
                controls_t,
                targets_t,
                values,
                scaled,
                extra,
                extra,
                nearest2,
                grad_controls,
                n_c,
                n_t,
                values.stride(0),
                scaled.stride(0),
                radius2,
                tiny,
                half_power,
                D=dim,
                K=columns,
                KIND=kind,
                FAST=fast,
                TARGET_ROWS=False,
                BLOCK_R=block_r,
                BLOCK_C=block_c,
                num_warps=warps,
            )
    return grad_targets, grad_controls
