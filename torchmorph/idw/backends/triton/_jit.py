"""The Triton kernels of the fused IDW (the paper's eq. 2, weights in registers); their
launchers, tile table and semantics are in :mod:`torchmorph.idw.backends.triton.kernels`.

Each kernel's first comment says which pass it is; helpers are ``@triton.jit``
functions inlined into the kernels.
"""

from __future__ import annotations

import triton
import triton.language as tl


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
    elif KIND == 3:
        result = ratio * tl.sqrt(ratio)
    elif KIND == 5:
        result = ratio * ratio * tl.sqrt(ratio)
    elif KIND == 6:
        result = ratio * ratio * ratio
    elif KIND == 7:
        result = ratio * ratio * ratio * tl.sqrt(ratio)
    elif KIND == 8:
        square = ratio * ratio
        result = square * square
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
def _split_tf32(x):
    """(hi, lo) with ``hi`` the float32 ``x`` truncated to tf32 (its top 19 bits, which a
    tf32 product reads exactly) and ``lo = x - hi`` (exact)."""
    hi = (x.to(tl.int32, bitcast=True) & -8192).to(tl.float32, bitcast=True)
    return hi, x - hi


@triton.jit
def _dot_accumulate(weight, v_hi, v_lo, cols, col_ok, acc, KP: tl.constexpr, SPLIT: tl.constexpr):
    """``acc + weight @ v`` on the matrix units, for the rows ``cols`` of a host-padded
    (N, KP) operand ``v`` (see ``_dot_operands`` of :mod:`.kernels`).

    SPLIT (float32): ``v = v_hi + v_lo`` split on the host and ``weight`` split here, the
    three products ``w_lo v_hi + w_hi v_lo + w_hi v_hi`` in tf32 (float32 accuracy) summed
    into a fresh tile that is added to ``acc`` by an ordinary float32 addition: the
    matrix units' own accumulation truncates, and run over the whole loop it drifts
    (6.7e-5 of |v| at case-B counts, against 2.8e-6 this way). Otherwise ``v_hi`` is v and
    the product is exact to the dtype (float64).
    """
    offsets = cols.to(tl.int64)[:, None] * KP + tl.arange(0, KP)[None, :]
    hi = tl.load(v_hi + offsets, mask=col_ok[:, None], other=0.0)
    if SPLIT:
        lo = tl.load(v_lo + offsets, mask=col_ok[:, None], other=0.0)
        w_hi, w_lo = _split_tf32(weight)
        tile = tl.dot(w_lo, hi, tl.zeros_like(acc), input_precision="tf32")
        tile = tl.dot(w_hi, lo, tile, input_precision="tf32")
        tile = tl.dot(w_hi, hi, tile, input_precision="tf32")
        result = acc + tile
    else:
        result = acc + tl.dot(weight, hi)
    return result


@triton.jit
def _apply_dot_kernel(
    targets_t,
    controls_t,
    v_hi,
    v_lo,
    nearest2_in,
    out,
    sums_out,
    n_t,
    n_c,
    stride_o,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    K: tl.constexpr,
    KP: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    SPLIT: tl.constexpr,
    BLOCK_T: tl.constexpr,
    BLOCK_C: tl.constexpr,
):
    # pass 2, any K: the tile of ratio weights times [v, 1, 0...] (padded to KP columns
    # on the host; column K of ones gives the row sums) on the matrix units, divided at
    # the end
    rows = tl.program_id(0) * BLOCK_T + tl.arange(0, BLOCK_T)
    row_ok = rows < n_t
    cols0 = tl.arange(0, BLOCK_C)
    k_idx = tl.arange(0, KP)
    nearest2 = tl.load(nearest2_in + rows, mask=row_ok, other=1.0)
    coincident = (nearest2 <= radius2) & row_ok
    any_coincident = tl.max(coincident.to(tl.int32), axis=0) > 0
    acc = tl.zeros((BLOCK_T, KP), dtype=controls_t.dtype.element_ty)
    for start in range(0, n_c, BLOCK_C):
        cols = start + cols0
        col_ok = cols < n_c
        dist2 = _squared_distances(
            targets_t, n_t, rows, row_ok, controls_t, n_c, cols, col_ok, tiny, D, BLOCK_T, BLOCK_C
        )
        weight = _weight_tile(
            dist2, nearest2, coincident, any_coincident, radius2, half_power, KIND, FAST, True
        )
        acc = _dot_accumulate(weight, v_hi, v_lo, cols, col_ok, acc, KP, SPLIT)
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
    g_hi,
    g_lo,
    out,
    n_c,
    n_t,
    stride_o,
    radius2,
    tiny,
    half_power,
    D: tl.constexpr,
    K: tl.constexpr,
    KP: tl.constexpr,
    KIND: tl.constexpr,
    FAST: tl.constexpr,
    SPLIT: tl.constexpr,
    BLOCK_C: tl.constexpr,
    BLOCK_T: tl.constexpr,
):
    # Wᵀ G for any K on the matrix units (G already divided by the row sums s_i and
    # padded to KP columns on the host)
    rows = tl.program_id(0) * BLOCK_C + tl.arange(0, BLOCK_C)
    row_ok = rows < n_c
    cols0 = tl.arange(0, BLOCK_T)
    k_idx = tl.arange(0, KP)
    acc = tl.zeros((BLOCK_C, KP), dtype=controls_t.dtype.element_ty)
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
        acc = _dot_accumulate(weight, g_hi, g_lo, cols, col_ok, acc, KP, SPLIT)
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
