"""Count-stratified control points: the candidates in an order whose every prefix is
spread evenly, by count, along a Hilbert curve through them.

Why count and not distance
--------------------------
Far from the candidates, IDW from a subset S of them reproduces IDW from all of them
when S holds the same share of the candidates in every region: each region's weight in
``Σ_{j∈S} w_j d_j / Σ_{j∈S} w_j`` is then that share of its weight in full IDW, and the
share cancels. SIDW (Ballarin et al. 2017, Algorithm 1) spaces its points by distance,
so on a graded boundary it keeps a smaller share where the boundary is finely meshed:
that region weighs less in the selective field than in full IDW, and the field errs far
from it. Measured at size paper (relative nodal error at μ*, ``benchmarks/adaptive.py``):
case C (the hull in its box) keeps 1,092 controls by ESIDW for 1.26 %; every seventh
node along the curve (538) gives 1.2 %; case A, 365 by ESIDW for 1.77 %, every tenth
(182) 0.7 %.

The order
---------
:func:`hilbert_order` sorts the points along a Hilbert curve of their bounding box (a
curve that keeps neighbours along it near in space). :func:`nested_order` then visits
the curve's positions in van der Corput order (the binary digits of 0, 1, 2, ...
reversed: 0, 1/2, 1/4, 3/4, 1/8, ...), so that the first n points of it lie about
``N / n`` apart along the curve for every n: one order serves every count, and the
error of each prefix adds only the new points to the sums of the shorter one
(:meth:`~torchmorph.selection.oracle.IDWErrorOracle.prefix_errors`).
:func:`stratified_count` finds, by those errors, the shortest prefix that meets a
tolerance; :func:`~torchmorph.selection.adaptive.select_adaptive` (``start="stratified"``,
the default) starts from a share of it and adds the controls the error asks for.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import as_points, dim_of
from torchmorph.idw.backends.numba._jit import _OPTIONS, njit

__all__ = ["hilbert_order", "nested_order", "stratified_count"]


def hilbert_order(points: Tensor) -> Tensor:
    """Indices that sort ``points`` (N, D) along a Hilbert curve of their bounding box
    (``2^b`` cells a side, ``b = min(16, 63 // D)``; ties keep the input order).

    Skilling's construction ("Programming the Hilbert curve", AIP Conf. Proc. 707,
    2004): each point's cell coordinates are turned into the curve's "transposed"
    index by Gray-code steps, whose bits interleaved give the position along the curve.
    """
    points = as_points(points, "points", dim=dim_of(points))
    array = points.detach().to("cpu", torch.float64).numpy()
    count, dim = array.shape
    if dim == 1:
        return torch.from_numpy(np.argsort(array[:, 0], kind="stable"))
    bits = min(16, 63 // dim)
    low = array.min(axis=0)
    span = float((array.max(axis=0) - low).max())
    cells = np.rint((array - low) / (span if span > 0 else 1.0) * (2**bits - 1))
    keys = np.empty(count, dtype=np.int64)
    _hilbert_keys(cells.astype(np.int64), bits, keys)
    return torch.from_numpy(np.argsort(keys, kind="stable"))


@njit(**_OPTIONS)
def _hilbert_keys(cells, bits, out):
    """out[k] = the position along the curve of the cell ``cells[k]`` (D coordinates in
    [0, 2^bits)), by Skilling's transposed index."""
    count, dim = cells.shape
    x = np.empty(dim, dtype=np.int64)
    top = np.int64(1) << (bits - 1)
    for point in range(count):
        for axis in range(dim):
            x[axis] = cells[point, axis]
        q = top
        while q > 1:  # undo the curve's rotations and reflections, level by level
            p = q - 1
            for axis in range(dim):
                if x[axis] & q:
                    x[0] ^= p
                else:
                    swap = (x[0] ^ x[axis]) & p
                    x[0] ^= swap
                    x[axis] ^= swap
            q >>= 1
        for axis in range(1, dim):  # Gray encode
            x[axis] ^= x[axis - 1]
        flip = np.int64(0)
        q = top
        while q > 1:
            if x[dim - 1] & q:
                flip ^= q - 1
            q >>= 1
        key = np.int64(0)
        for bit in range(bits - 1, -1, -1):  # interleave, most significant bit first
            for axis in range(dim):
                key = (key << 1) | (((x[axis] ^ flip) >> bit) & 1)
        out[point] = key


def nested_order(points: Tensor) -> Tensor:
    """Indices of ``points`` (N, D) whose every prefix of length n holds about one
    point in each ``N / n`` consecutive ones along :func:`hilbert_order` (positions
    along the curve in van der Corput order). A permutation of ``range(N)``."""
    along = hilbert_order(points).numpy()
    count = along.shape[0]
    if count <= 1:
        return torch.from_numpy(along.copy())
    bits = int(count - 1).bit_length()
    index = np.arange(1 << bits, dtype=np.int64)
    reversed_bits = np.zeros_like(index)
    for bit in range(bits):
        reversed_bits |= ((index >> bit) & 1) << (bits - 1 - bit)
    position = (reversed_bits * count) >> bits  # 2^bits fractions onto N positions
    _, first = np.unique(position, return_index=True)
    return torch.from_numpy(along[position[np.sort(first)]])


def stratified_count(
    prefix_errors: Callable[[list[int]], list[float]],
    tolerance: float,
    limit: int,
    first: int = 8,
) -> int | None:
    """The shortest prefix length n <= ``limit`` whose error meets ``tolerance``, to
    about a sixteenth of it, or None when ``limit`` does not.

    ``prefix_errors(counts)`` returns the errors of the prefixes of those increasing
    lengths. The lengths double from ``first`` until one meets the tolerance; then the
    lengths between the last two are tried in sixteenths of the longer one, in order,
    up to the first that meets it (an oracle that extends the sums of the longest
    shorter prefix reads each point once).
    """

    def meets(count: int) -> bool:
        return prefix_errors([count])[0] <= tolerance

    low, high = 0, max(1, min(first, limit))
    while not meets(high):
        if high >= limit:
            return None
        low, high = high, min(2 * high, limit)
    step = max(1, high // 16)
    return next((n for n in range(low + step, high, step) if meets(n)), high)
