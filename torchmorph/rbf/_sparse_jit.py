"""The numba kernels of the sparse RBF (:mod:`torchmorph.rbf.sparse`): the pairs of points
closer than the support radius, found on a uniform grid of cells one radius wide and
written as a CSR matrix of Wendland values, and the CSR product with a block of columns,
both in parallel over rows (float64).

The grid: a point's cell is ``floor((x − low) / radius)`` per axis and its key the cell's
row-major index; the indexed points are sorted by key, so a cell's points are one range
found by a binary search over the distinct keys. A query visits its own cell and its
3^D − 1 neighbours, which hold every point within one radius.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal, TypedDict

import numpy as np

if TYPE_CHECKING:
    from numba import njit, prange
else:
    try:
        from numba import njit, prange
    except ImportError:  # pragma: no cover - exercised where numba is absent
        prange = range

        def njit(*args, **kwargs):
            return lambda function: function


__all__ = ["WENDLAND_CODES", "count_pairs", "csr_product", "fill_pairs", "grid_keys"]

#: The kernels' codes in :func:`fill_pairs`.
WENDLAND_CODES = {"wendland_c0": 0, "wendland_c2": 2, "wendland_c4": 4}


class _JitOptions(TypedDict):
    cache: bool
    nogil: bool
    error_model: Literal["python", "numpy"]


_OPTIONS: _JitOptions = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_OPTIONS)
def _key(point, low, inverse, dims):
    """The row-major key of the cell holding ``point`` (-1 outside the grid)."""
    key = 0
    for axis in range(point.shape[0]):
        cell = math.floor((point[axis] - low[axis]) * inverse)
        if cell < 0 or cell >= dims[axis]:
            return -1
        key = key * dims[axis] + cell
    return key


@njit(**_OPTIONS)
def grid_keys(points, low, inverse, dims, out):
    """out[i] = the key of point i's cell (every indexed point is inside the grid)."""
    for index in range(points.shape[0]):
        out[index] = _key(points[index], low, inverse, dims)


@njit(**_OPTIONS)
def _wendland(scaled, code):
    """Wendland's function of ``r / support_radius`` (< 1)."""
    rest = 1.0 - scaled
    if code == 0:
        return rest * rest
    square = rest * rest
    if code == 2:
        return square * square * (4.0 * scaled + 1.0)
    return square * square * square * (35.0 * scaled * scaled + 18.0 * scaled + 3.0) / 3.0


@njit(**_OPTIONS)
def _visit(query, points, keys, starts, low, inverse, dims, offsets, radius2, code, inv_radius,
           order, columns, values, position):  # fmt: skip
    """Count (``columns`` empty) or write the pairs of one query; returns the count or
    the next position."""
    dim = query.shape[0]
    found = 0
    home = np.empty(dim, np.int64)
    for axis in range(dim):
        home[axis] = np.int64(math.floor((query[axis] - low[axis]) * inverse))
    for shift in range(offsets.shape[0]):
        key = 0
        for axis in range(dim):
            cell = home[axis] + offsets[shift, axis]
            if cell < 0 or cell >= dims[axis]:
                key = -1
                break
            key = key * dims[axis] + cell
        if key < 0:
            continue
        slot = np.searchsorted(keys, key)
        if slot >= keys.shape[0] or keys[slot] != key:
            continue
        for other in range(starts[slot], starts[slot + 1]):
            squared = 0.0
            for axis in range(dim):
                diff = query[axis] - points[other, axis]
                squared += diff * diff
            if squared < radius2:
                if columns.shape[0]:
                    columns[position] = order[other]
                    values[position] = _wendland(math.sqrt(squared) * inv_radius, code)
                    position += 1
                else:
                    found += 1
    return position if columns.shape[0] else found


@njit(parallel=True, **_OPTIONS)
def count_pairs(queries, points, keys, starts, low, inverse, dims, offsets, radius2, counts):
    """counts[q] = the number of indexed points within the radius of query q."""
    empty_int = np.zeros(0, np.int64)
    empty = np.zeros(0)
    for query in prange(queries.shape[0]):
        counts[query] = _visit(
            queries[query], points, keys, starts, low, inverse, dims, offsets, radius2, 0,
            0.0, empty_int, empty_int, empty, 0,
        )  # fmt: skip


@njit(parallel=True, **_OPTIONS)
def fill_pairs(queries, points, keys, starts, low, inverse, dims, offsets, radius2, code,
               inv_radius, order, indptr, columns, values):  # fmt: skip
    """The CSR rows (``indptr`` from :func:`count_pairs`): the indexed points' original
    indices (``order``) and the kernel's values."""
    for query in prange(queries.shape[0]):
        _visit(
            queries[query], points, keys, starts, low, inverse, dims, offsets, radius2, code,
            inv_radius, order, columns, values, indptr[query],
        )  # fmt: skip


@njit(parallel=True, **_OPTIONS)
def csr_product(indptr, columns, values, block, out):
    """out = M @ block for M in CSR (rows, n) and ``block`` (n, k), row by row."""
    width = block.shape[1]
    for row in prange(indptr.shape[0] - 1):
        for column in range(width):
            out[row, column] = 0.0
        for entry in range(indptr[row], indptr[row + 1]):
            weight = values[entry]
            source = columns[entry]
            for column in range(width):
                out[row, column] += weight * block[source, column]
