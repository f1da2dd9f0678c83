"""The terms of the tree-approximated IDW's traversal (:mod:`._tree_jit`), numba: a leaf
of controls summed exactly against a block of targets (the weights, their sums and the
products with the values; transposed, the scatter back to the controls), and an accepted
node's second-order expansion evaluated at the block's targets (transposed, gathered
into the node's coefficients). One 3-D field has kernels of its own (one pass for the
weights and the three columns); the forward and transposed passes take the same sums,
so that their acceptance decisions agree to the bit."""

from __future__ import annotations

import numpy as np

from torchmorph.idw.backends.numba._jit import _OPTIONS, njit, ratio_power  # numba's, or stand-ins


@njit(**_OPTIONS)
def _squared(point, points_t, start, stop, out):
    """out[k] = |point - points_t[:, start + k]|² (direct coordinate differences)."""
    width = stop - start
    column = points_t[0, start:stop]
    for k in range(width):
        diff = point[0] - column[k]
        out[k] = diff * diff
    for axis in range(1, points_t.shape[0]):
        column = points_t[axis, start:stop]
        for k in range(width):
            diff = point[axis] - column[k]
            out[k] += diff * diff


@njit(**_OPTIONS)
def _weights(chunk, width, ref2, half_power, mode):
    """chunk[k] <- (ref² / d²_k)^(p/2) in place (0 where d² is infinite)."""
    if mode == 4:
        for k in range(width):
            ratio = ref2 / chunk[k]
            chunk[k] = ratio * ratio
    elif mode == 2:
        for k in range(width):
            chunk[k] = ref2 / chunk[k]
    else:
        for k in range(width):
            chunk[k] = ratio_power(np.float64(ref2 / chunk[k]), half_power, mode)


@njit(**_OPTIONS)
def _quadratic(offset, matrix, rows, out):
    """out[t] = offset[:, t]ᵀ matrix offset[:, t] for a symmetric matrix (rows vectorised)."""
    dim = offset.shape[0]
    for t in range(rows):
        out[t] = 0.0
    for a in range(dim):
        for b in range(a, dim):
            entry = matrix[a, b] if a == b else 2.0 * matrix[a, b]
            for t in range(rows):
                out[t] += entry * offset[a, t] * offset[b, t]


@njit(**_OPTIONS)
def _leaf_by_controls(
    local, controls_t, values_t, start, stop, rows, ref2, half_power, mode, weight, sums,
    numerator, transpose, scaled, out,
):  # fmt: skip
    """A leaf's exact sums for a block none of whose targets lies within the coincidence
    radius of it, added to the block's ``sums`` (rows,) and ``numerator`` (columns, rows),
    or when transposed ``out[k] += Σ_t w_tk scaled[:, t]``: target by target, one fused
    pass over the leaf's contiguous controls for the weights and their sum (squared
    distances, the ratio form), then one dot product per value column (``weight`` is
    scratch of the leaf's width). The forward and transposed passes share it, so that
    their running sums, hence their acceptance decisions, are the same to the bit: with
    one 3-D field the sums come from :func:`_leaf_field3` in both (one call site), and the
    transposed pass then scatters by :func:`_leaf_field3_transposed`, the weights again.

    The arithmetic is in the dtype of ``local``, ``controls_t``, ``values_t``, ``ref2``
    and ``weight`` (float32 for float32 inputs: twice the vector lanes), each leaf's sums
    then added to the float64 block sums."""
    dim, columns = controls_t.shape[0], values_t.shape[0]
    width = stop - start
    zero = ref2 - ref2  # 0 in the leaf's dtype
    if dim == 3 and columns == 3:  # one 3-D field: its own kernels, no scratch
        # transposed: values_t is zero, the products unused, the sums the same bits
        _leaf_field3(local, controls_t, values_t, start, stop, rows, ref2, half_power, mode,
                     sums, numerator)  # fmt: skip
        if transpose:
            _leaf_field3_transposed(local, controls_t, start, stop, rows, ref2, half_power,
                                    mode, scaled, out)  # fmt: skip
        return
    for t in range(rows):
        total = zero
        if dim == 3:
            x0, x1, x2 = local[0, t], local[1, t], local[2, t]
            c0 = controls_t[0, start:stop]
            c1 = controls_t[1, start:stop]
            c2 = controls_t[2, start:stop]
            if mode == 4:
                for k in range(width):
                    d0, d1, d2 = x0 - c0[k], x1 - c1[k], x2 - c2[k]
                    ratio = ref2 / (d0 * d0 + d1 * d1 + d2 * d2)
                    w = ratio * ratio
                    weight[k] = w
                    total += w
            else:
                for k in range(width):
                    d0, d1, d2 = x0 - c0[k], x1 - c1[k], x2 - c2[k]
                    w = _power_of_ratio(ref2 / (d0 * d0 + d1 * d1 + d2 * d2), half_power, mode)
                    weight[k] = w
                    total += w
        else:
            for k in range(width):
                weight[k] = 0.0
            for a in range(dim):
                coordinate = local[a, t]
                column = controls_t[a, start:stop]
                for k in range(width):
                    diff = coordinate - column[k]
                    weight[k] += diff * diff
            for k in range(width):
                w = _power_of_ratio(ref2 / weight[k], half_power, mode)
                weight[k] = w
                total += w
        sums[t] += total
        if transpose:
            for column in range(scaled.shape[0]):
                g = scaled[column, t]
                if g != 0.0:
                    for k in range(width):
                        out[start + k, column] += weight[k] * g
        else:
            for column in range(columns):
                row = values_t[column, start:stop]
                dot = zero
                for k in range(width):
                    dot += weight[k] * row[k]
                numerator[column, t] += dot


@njit(**_OPTIONS)
def _leaf_field3(
    local, controls_t, values_t, start, stop, rows, ref2, half_power, mode, sums, numerator
):
    """:func:`_leaf_by_controls` forward for one 3-D field: the weights, their sum and the
    three dot products in one pass over the leaf's controls (1.07× the whole traversal's
    speed at 10^6 × 10^5 against a pass for the weights and one per column)."""
    zero = ref2 - ref2
    c0, c1, c2 = controls_t[0, start:stop], controls_t[1, start:stop], controls_t[2, start:stop]
    v0, v1, v2 = values_t[0, start:stop], values_t[1, start:stop], values_t[2, start:stop]
    for t in range(rows):
        x0, x1, x2 = local[0, t], local[1, t], local[2, t]
        total, n0, n1, n2 = zero, zero, zero, zero
        if mode == 4:  # the branch outside the loop, which then vectorises
            for k in range(stop - start):
                d0, d1, d2 = x0 - c0[k], x1 - c1[k], x2 - c2[k]
                ratio = ref2 / (d0 * d0 + d1 * d1 + d2 * d2)
                w = ratio * ratio
                total += w
                n0 += w * v0[k]
                n1 += w * v1[k]
                n2 += w * v2[k]
        else:
            for k in range(stop - start):
                d0, d1, d2 = x0 - c0[k], x1 - c1[k], x2 - c2[k]
                w = _power_of_ratio(ref2 / (d0 * d0 + d1 * d1 + d2 * d2), half_power, mode)
                total += w
                n0 += w * v0[k]
                n1 += w * v1[k]
                n2 += w * v2[k]
        sums[t] += total
        numerator[0, t] += n0
        numerator[1, t] += n1
        numerator[2, t] += n2


@njit(inline="always", **_OPTIONS)
def _leaf_field3_transposed(
    local, controls_t, start, stop, rows, ref2, half_power, mode, scaled, out
):
    """The transposed scatter of one 3-D field's leaf: ``out[k] += Σ_t w_tk scaled[:, t]``
    control by control, the block's targets in the vector lanes (one read-modify-write of
    ``out`` per control and column, where the general loop writes it per target; 2.8 s of
    a 5.9 s transposed pass at 10^6 × 10^5 before)."""
    s0, s1, s2 = scaled[0], scaled[1], scaled[2]  # float64: the sums over t in float64
    x0, x1, x2 = local[0], local[1], local[2]
    for k in range(stop - start):
        y0, y1, y2 = controls_t[0, start + k], controls_t[1, start + k], controls_t[2, start + k]
        a0, a1, a2 = 0.0, 0.0, 0.0
        if mode == 4:
            for t in range(rows):
                d0, d1, d2 = x0[t] - y0, x1[t] - y1, x2[t] - y2
                ratio = ref2 / (d0 * d0 + d1 * d1 + d2 * d2)
                w = ratio * ratio
                a0 += w * s0[t]
                a1 += w * s1[t]
                a2 += w * s2[t]
        else:
            for t in range(rows):
                d0, d1, d2 = x0[t] - y0, x1[t] - y1, x2[t] - y2
                w = _power_of_ratio(ref2 / (d0 * d0 + d1 * d1 + d2 * d2), half_power, mode)
                a0 += w * s0[t]
                a1 += w * s1[t]
                a2 += w * s2[t]
        out[start + k, 0] += a0
        out[start + k, 1] += a1
        out[start + k, 2] += a2


@njit(**_OPTIONS)
def _power_of_ratio(ratio, half_power, mode):
    """ratio^(p/2) for ratio = ref²/d², in float64
    (:func:`~torchmorph.idw.backends.numba._jit.ratio_power`): against a block's
    reference distance a float32 leaf's ratio can lie far from 1, and its sixth power
    outside float32's range."""
    return ratio_power(np.float64(ratio), half_power, mode)


@njit(inline="always", **_OPTIONS)
def _factors_and_monomials(offset, weight, inverse2, rows, power, monomials, factors):
    """Per target of a block, for an accepted node's expansion in 3-D (both directions):
    ``factors`` = the weight times ``p/R²``, ``(p(p+2)/2)/R⁴`` and ``(p/2)/R²``, and the six
    monomials ``r_a r_b`` of the offset from the node's centroid."""
    coefficient = 0.5 * power * (power + 2.0)
    half_power = 0.5 * power
    for t in range(rows):
        i2 = inverse2[t]
        factors[0, t] = weight[t] * power * i2
        factors[1, t] = weight[t] * coefficient * i2 * i2
        factors[2, t] = weight[t] * half_power * i2
        o0, o1, o2 = offset[0, t], offset[1, t], offset[2, t]
        monomials[0, t], monomials[1, t], monomials[2, t] = o0 * o0, o1 * o1, o2 * o2
        monomials[3, t], monomials[4, t], monomials[5, t] = o0 * o1, o0 * o2, o1 * o2


@njit(inline="always", **_OPTIONS)
def _far_field3(
    offset, weight, inverse2, rows, power, count, geometry, zeroth, first, second, monomials,
    factors, far_sums, numerator,
):  # fmt: skip
    """An accepted node's expansion P at a block's targets in 3-D: ``far_sums[t] += Σ_k P_k``
    and ``numerator[column, t] += Σ_k P_k d_k``, from the node's moments (``geometry`` its
    Σ s sᵀ; ``zeroth``, ``first``, ``second`` per column), with ``P`` written as
    ``w [m + p (M1·r)/R² + (p(p+2)/2)(rᵀ M2 r)/R⁴ - (p/2) tr(M2)/R²]``: the six monomials
    of ``r`` and the three factors of ``w`` once per target for all the forms (1.14× the
    whole traversal's speed at 10^6 × 10^5 against a quadratic form by form)."""
    _factors_and_monomials(offset, weight, inverse2, rows, power, monomials, factors)
    linear_factor, quadratic_factor, trace_factor = factors[0], factors[1], factors[2]
    q0, q1, q2 = geometry[0, 0], geometry[1, 1], geometry[2, 2]
    q3, q4, q5 = 2.0 * geometry[0, 1], 2.0 * geometry[0, 2], 2.0 * geometry[1, 2]
    trace = q0 + q1 + q2
    for t in range(rows):  # the weights themselves
        quadratic = (
            q0 * monomials[0, t] + q1 * monomials[1, t] + q2 * monomials[2, t]
            + q3 * monomials[3, t] + q4 * monomials[4, t] + q5 * monomials[5, t]
        )  # fmt: skip
        far_sums[t] += weight[t] * count + quadratic_factor[t] * quadratic - trace_factor[t] * trace
    for column in range(zeroth.shape[0]):
        q0, q1, q2 = second[column, 0, 0], second[column, 1, 1], second[column, 2, 2]
        q3, q4, q5 = (
            2.0 * second[column, 0, 1],
            2.0 * second[column, 0, 2],
            2.0 * second[column, 1, 2],
        )
        trace = q0 + q1 + q2
        base = zeroth[column]
        f0, f1, f2 = first[column, 0], first[column, 1], first[column, 2]
        for t in range(rows):
            quadratic = (
                q0 * monomials[0, t] + q1 * monomials[1, t] + q2 * monomials[2, t]
                + q3 * monomials[3, t] + q4 * monomials[4, t] + q5 * monomials[5, t]
            )  # fmt: skip
            linear = f0 * offset[0, t] + f1 * offset[1, t] + f2 * offset[2, t]
            numerator[column, t] += (
                weight[t] * base
                + linear_factor[t] * linear
                + quadratic_factor[t] * quadratic
                - trace_factor[t] * trace
            )


@njit(inline="always", **_OPTIONS)
def _far_field3_transposed(
    offset, weight, inverse2, rows, power, scaled, monomials, factors, zeroth, first, second
):
    """The transpose of :func:`_far_field3`: an accepted node's coefficients ``C0 += Σ_t g_t
    w_t``, ``C1 += Σ_t g_t w_t p r_t / R_t²`` and ``C2 += Σ_t g_t w_t ((p(p+2)/2) r_t r_tᵀ /
    R_t⁴ - (p/2) I / R_t²)`` per column of ``scaled`` (``g``, zero at coincident targets),
    which :func:`._tree_moments.push_down` spreads to the node's controls as ``C0 + C1·s +
    sᵀ C2 s``: eleven sums over the block's targets per column, in the vector lanes (the
    general code accumulates them target by target; 3.6 s of a 9.2 s transposed pass at
    10^6 × 10^5 before)."""
    _factors_and_monomials(offset, weight, inverse2, rows, power, monomials, factors)
    linear_factor, quadratic_factor, trace_factor = factors[0], factors[1], factors[2]
    for column in range(scaled.shape[0]):
        g = scaled[column]
        c0 = c1 = c2 = c3 = 0.0
        q0 = q1 = q2 = q3 = q4 = q5 = 0.0
        trace = 0.0
        for t in range(rows):
            c0 += g[t] * weight[t]
            gl = g[t] * linear_factor[t]
            c1 += gl * offset[0, t]
            c2 += gl * offset[1, t]
            c3 += gl * offset[2, t]
            gq = g[t] * quadratic_factor[t]
            q0 += gq * monomials[0, t]
            q1 += gq * monomials[1, t]
            q2 += gq * monomials[2, t]
            q3 += gq * monomials[3, t]
            q4 += gq * monomials[4, t]
            q5 += gq * monomials[5, t]
            trace += g[t] * trace_factor[t]
        zeroth[column] += c0
        first[column, 0] += c1
        first[column, 1] += c2
        first[column, 2] += c3
        second[column, 0, 0] += q0 - trace
        second[column, 1, 1] += q1 - trace
        second[column, 2, 2] += q2 - trace
        second[column, 0, 1] += q3
        second[column, 1, 0] += q3
        second[column, 0, 2] += q4
        second[column, 2, 0] += q4
        second[column, 1, 2] += q5
        second[column, 2, 1] += q5
