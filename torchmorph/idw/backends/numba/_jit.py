"""The numba kernels of the fused CPU IDW (the paper's eq. 2, two passes: the nearest
distance, then the ratio weights against ``[values, 1]``); their wrappers, argument checks
and thread handling are in :mod:`torchmorph.idw.backends.numba.kernels`."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal, TypedDict

import numpy as np

ROWS = 16
"""Rows (targets; controls in :func:`apply_transposed`) per block of a kernel: the
unit of parallel work, and the number of rows that reuse one chunk from L1."""

CHUNK = 256
"""Points of the other set per chunk: a chunk's coordinates, values and ratios fit
in the L1 cache, and its partial sums go into float64 accumulators."""


if TYPE_CHECKING:  # type-checked against numba's own annotations
    import numba
    from numba import njit, prange
else:
    try:  # numba is optional: without it torchmorph falls back to its torch path
        import numba
        from numba import njit, prange
    except ImportError:  # pragma: no cover - exercised where numba is absent
        numba = None
        prange = range

        def njit(*args, **kwargs):  # the kernels stay plain (never called) Python functions
            return lambda function: function


# --------------------------------------------------------------------------- #
# the kernels (plain numba; compiled lazily, once per dtype, cached on disk)
# --------------------------------------------------------------------------- #
WEIGHT_ROWS = 4
"""Rows per block of :func:`weights`: the block's rows of W (distances, then weights in
place, then scaled) stay in the L2 cache at the paper's sizes."""


class _JitOptions(TypedDict):
    cache: bool
    nogil: bool
    fastmath: set[str]
    error_model: Literal["python", "numpy"]


_FASTMATH = {"nsz", "reassoc", "contract"}  # vectorised sums and mins; no unsafe maths
_OPTIONS: _JitOptions = {
    "cache": True,
    "nogil": True,
    "fastmath": _FASTMATH,
    "error_model": "numpy",
}


@njit(**_OPTIONS)
def _squared_distances(point, points_t, start, stop, out):
    """out[k] = |point - points_t[:, start + k]|² for the chunk (direct differences)."""
    column = points_t[0, start:stop]
    coordinate = point[0]
    for k in range(stop - start):
        diff = coordinate - column[k]
        out[k] = diff * diff
    for axis in range(1, points_t.shape[0]):
        column = points_t[axis, start:stop]
        coordinate = point[axis]
        for k in range(stop - start):
            diff = coordinate - column[k]
            out[k] += diff * diff


@njit(**_OPTIONS)
def _smallest(squared, best):
    """min(best, min_k squared[k]) on the bit patterns (``best`` and the result as integers).

    Squared distances are >= +0, and the IEEE bit patterns of non-negative floats are
    ordered like the values: an integer minimum vectorises, a float one does not here.
    """
    for k in range(squared.shape[0]):
        value = squared[k]
        best = min(best, value)
    return best


@njit(inline="always", **_OPTIONS)
def ratio_power(ratio, half_power, mode):
    """``ratio^(p/2)`` for ``mode`` = :func:`~torchmorph.idw.backends.power_code` of p:
    products and one square root for the integer powers 1 to 8, the general power (a
    logarithm and an exponential, about ten times slower) for ``mode`` 0. The callers
    branch on ``mode`` outside their loops (4 and 2 written out), so a loop calling this
    is compiled once per mode."""
    if mode == 0:
        return ratio**half_power
    if mode == 2:
        return ratio
    square = ratio * ratio
    if mode == 4:
        return square
    if mode == 6:
        return square * ratio
    if mode == 8:
        return square * square
    root = np.sqrt(ratio)  # the odd powers
    if mode == 1:
        return root
    if mode == 3:
        return ratio * root
    if mode == 5:
        return square * root
    return square * ratio * root  # 7


@njit(**_OPTIONS)
def _ratio_powers(nearest, buffer, width, mode, params):
    """buffer[k] <- r_ik from buffer[k] = d²_ik, for one row whose m_i is ``nearest``;
    ``mode`` is :func:`~torchmorph.idw.backends.power_code` (4 and 2 written out, the
    other codes through :func:`ratio_power`)."""
    tiny, radius2, half_power, zero, one = params[0], params[1], params[2], params[3], params[4]
    if nearest <= radius2:  # coincident row: the controls within the radius, equally
        for k in range(width):
            buffer[k] = one if buffer[k] <= radius2 else zero
    elif mode == 4:
        for k in range(width):
            ratio = nearest / max(buffer[k], tiny)
            buffer[k] = ratio * ratio
    elif mode == 2:
        for k in range(width):
            buffer[k] = nearest / max(buffer[k], tiny)
    else:
        for k in range(width):
            buffer[k] = ratio_power(nearest / max(buffer[k], tiny), half_power, mode)


@njit(**_OPTIONS)
def _dot(weights, values, zero):
    """Σ_k weights[k] values[k] in the input dtype (one chunk: SIMD lanes of few terms)."""
    total = zero
    for k in range(weights.shape[0]):
        total += weights[k] * values[k]
    return total


@njit(**_OPTIONS)
def _sum(weights, zero):
    total = zero
    for k in range(weights.shape[0]):
        total += weights[k]
    return total


@njit(parallel=True, **_OPTIONS)
def _nearest_kernel(targets, controls_t, largest, out):
    """Pass 1: out[i] = min_k d²_ik. ``largest``: [the largest integer of the float's width]."""
    n_targets, n_controls = targets.shape[0], controls_t.shape[1]
    blocks = (n_targets + ROWS - 1) // ROWS
    for block in prange(blocks):
        first = block * ROWS
        last = min(first + ROWS, n_targets)
        bits = np.empty(CHUNK, largest.dtype)
        buffer = bits.view(targets.dtype)
        best = np.full(ROWS, largest[0])
        for start in range(0, n_controls, CHUNK):
            stop = min(start + CHUNK, n_controls)
            for row in range(first, last):
                _squared_distances(targets[row], controls_t, start, stop, buffer)
                best[row - first] = _smallest(bits[: stop - start], best[row - first])
        found = best.view(targets.dtype)
        for row in range(first, last):
            out[row] = found[row - first]


@njit(parallel=True, **_OPTIONS)
def _apply_kernel(targets, controls_t, values_t, nearest2, params, mode, out, sums):
    """Ratio weights against [values, 1]: out = W @ values, sums = s (m_i given)."""
    tiny, zero = params[0], params[3]
    n_targets, n_controls = targets.shape[0], controls_t.shape[1]
    columns = values_t.shape[0]
    blocks = (n_targets + ROWS - 1) // ROWS
    for block in prange(blocks):
        first = block * ROWS
        last = min(first + ROWS, n_targets)
        buffer = np.empty(CHUNK, targets.dtype)
        accumulated = np.zeros((ROWS, columns), np.float64)
        total = np.zeros(ROWS, np.float64)
        for start in range(0, n_controls, CHUNK):
            stop = min(start + CHUNK, n_controls)
            width = stop - start
            chunk = buffer[:width]
            for row in range(first, last):
                local = row - first
                _squared_distances(targets[row], controls_t, start, stop, buffer)
                _ratio_powers(max(nearest2[row], tiny), buffer, width, mode, params)
                total[local] += _sum(chunk, zero)
                for column in range(columns):
                    accumulated[local, column] += _dot(chunk, values_t[column, start:stop], zero)
        for row in range(first, last):
            local = row - first
            sums[row] = total[local]
            for column in range(columns):
                out[row, column] = accumulated[local, column] / total[local]


@njit(parallel=True, **_OPTIONS)
def _apply_streaming_kernel(
    targets, controls_t, values_t, params, mode, largest, out, sums, nearest_out
):
    """One pass instead of two: the ratio weights against the smallest distance m seen
    so far; when a chunk holds a nearer control, the row's partial sums are rescaled by
    (m_new / m_old)^(p/2), so that the result is :func:`_apply_kernel`'s with the final
    m (the streaming form of a normalised sum, as in an online softmax). A row meeting
    its first coincident control restarts its sums: coincident rows weigh only the
    controls within the radius. Also writes m (floored at ``tiny``) to ``nearest_out``."""
    tiny, radius2, half_power, zero = params[0], params[1], params[2], params[3]
    n_targets, n_controls = targets.shape[0], controls_t.shape[1]
    columns = values_t.shape[0]
    blocks = (n_targets + ROWS - 1) // ROWS
    for block in prange(blocks):
        first = block * ROWS
        last = min(first + ROWS, n_targets)
        bits = np.empty(CHUNK, largest.dtype)
        buffer = bits.view(targets.dtype)
        scalar = np.empty(1, largest.dtype)
        as_float = scalar.view(targets.dtype)
        accumulated = np.zeros((ROWS, columns), np.float64)
        total = np.zeros(ROWS, np.float64)
        best = np.full(ROWS, np.inf, targets.dtype)
        for start in range(0, n_controls, CHUNK):
            stop = min(start + CHUNK, n_controls)
            width = stop - start
            chunk = buffer[:width]
            for row in range(first, last):
                local = row - first
                _squared_distances(targets[row], controls_t, start, stop, buffer)
                scalar[0] = _smallest(bits[:width], largest[0])
                nearest = max(as_float[0], tiny)
                previous = best[local]
                if nearest < previous:
                    if previous <= radius2:
                        pass  # already coincident: weights are 1 within the radius
                    elif nearest <= radius2 or previous == np.inf:
                        total[local] = 0.0
                        for column in range(columns):
                            accumulated[local, column] = 0.0
                    else:
                        ratio = np.float64(nearest) / np.float64(previous)
                        if mode == 4:
                            scale = ratio * ratio
                        elif mode == 2:
                            scale = ratio
                        else:
                            scale = ratio_power(ratio, np.float64(half_power), mode)
                        total[local] *= scale
                        for column in range(columns):
                            accumulated[local, column] *= scale
                    best[local] = nearest
                _ratio_powers(best[local], buffer, width, mode, params)
                total[local] += _sum(chunk, zero)
                for column in range(columns):
                    accumulated[local, column] += _dot(chunk, values_t[column, start:stop], zero)
        for row in range(first, last):
            local = row - first
            sums[row] = total[local]
            nearest_out[row] = best[local]
            for column in range(columns):
                out[row, column] = accumulated[local, column] / total[local]


@njit(parallel=True, **_OPTIONS)
def _transposed_kernel(controls, targets_t, scaled_t, nearest2, params, mode, out):
    """Wᵀ @ grad, parallel over controls: scaled_t[j, i] = grad[i, j] / s_i."""
    tiny, radius2, half_power, zero, one = params[0], params[1], params[2], params[3], params[4]
    n_controls, n_targets = controls.shape[0], targets_t.shape[1]
    columns = scaled_t.shape[0]
    blocks = (n_controls + ROWS - 1) // ROWS
    for block in prange(blocks):
        first = block * ROWS
        last = min(first + ROWS, n_controls)
        buffer = np.empty(CHUNK, controls.dtype)
        floored = np.empty(CHUNK, controls.dtype)
        accumulated = np.zeros((ROWS, columns), np.float64)
        for start in range(0, n_targets, CHUNK):
            stop = min(start + CHUNK, n_targets)
            width = stop - start
            chunk = buffer[:width]
            nearest = nearest2[start:stop]
            for k in range(width):
                floored[k] = max(nearest[k], tiny)
            for row in range(first, last):
                _squared_distances(controls[row], targets_t, start, stop, buffer)
                # r_ik with the target's m_i varying along the chunk
                if mode == 4:
                    for k in range(width):
                        ratio = floored[k] / max(buffer[k], tiny)
                        within = one if buffer[k] <= radius2 else zero
                        buffer[k] = within if floored[k] <= radius2 else ratio * ratio
                elif mode == 2:
                    for k in range(width):
                        ratio = floored[k] / max(buffer[k], tiny)
                        within = one if buffer[k] <= radius2 else zero
                        buffer[k] = within if floored[k] <= radius2 else ratio
                else:
                    for k in range(width):
                        power = ratio_power(floored[k] / max(buffer[k], tiny), half_power, mode)
                        within = one if buffer[k] <= radius2 else zero
                        buffer[k] = within if floored[k] <= radius2 else power
                for column in range(columns):
                    accumulated[row - first, column] += _dot(
                        chunk, scaled_t[column, start:stop], zero
                    )
        for row in range(first, last):
            for column in range(columns):
                out[row, column] = accumulated[row - first, column]


@njit(parallel=True, **_OPTIONS)
def _weights_kernel(targets, controls_t, params, mode, largest, out):
    """Dense W, one fused pass per block of rows (kept in cache): d² and the nearest
    distance, then r_ik in place and s_i, then r_ik / s_i."""
    tiny, zero = params[0], params[3]
    n_targets, n_controls = targets.shape[0], controls_t.shape[1]
    blocks = (n_targets + WEIGHT_ROWS - 1) // WEIGHT_ROWS
    for block in prange(blocks):
        first = block * WEIGHT_ROWS
        last = min(first + WEIGHT_ROWS, n_targets)
        best = np.full(WEIGHT_ROWS, largest[0])
        total = np.zeros(WEIGHT_ROWS, np.float64)
        for start in range(0, n_controls, CHUNK):  # d² into W's rows, and the nearest
            stop = min(start + CHUNK, n_controls)
            for row in range(first, last):
                chunk = out[row, start:stop]
                _squared_distances(targets[row], controls_t, start, stop, chunk)
                best[row - first] = _smallest(chunk.view(largest.dtype), best[row - first])
        found = best.view(targets.dtype)
        for row in range(first, last):  # r_ik in place and s_i
            values = out[row]
            nearest = max(found[row - first], tiny)
            for start in range(0, n_controls, CHUNK):
                stop = min(start + CHUNK, n_controls)
                chunk = values[start:stop]
                _ratio_powers(nearest, chunk, stop - start, mode, params)
                total[row - first] += _sum(chunk, zero)
        for row in range(first, last):  # normalise
            scale = 1.0 / total[row - first]
            values = out[row]
            for k in range(n_controls):
                values[k] = values[k] * scale
