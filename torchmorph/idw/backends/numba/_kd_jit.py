"""The kd-tree of the tree-approximated IDW (:mod:`torchmorph.idw.tree`), built in place by
numba: median splits on the widest axis, nodes in depth-first preorder, each node a range
of a permutation of the points."""

from __future__ import annotations

import numpy as np

from torchmorph.idw.backends.numba._jit import njit  # numba's, or a stand-in without it

STACK = 256
"""Depth of a traversal's stack of nodes (a kd-tree of median splits is ~log2(N) deep,
and a visit pushes at most two nodes)."""


@njit(cache=True)
def kd_tree(points, leaf_size, order, starts, stops, children):
    """A kd-tree of median splits on the widest axis, built in place: ``order`` (the
    identity on entry) permuted so that each node is the range ``order[start:stop]``,
    nodes in depth-first preorder (``starts``, ``stops``, ``children`` (nodes, 2), -1 for
    a leaf; arrays of at least :func:`max_nodes` rows). The median is found by
    quickselect on the node's range. Returns the number of nodes."""
    dim = points.shape[1]
    pending = np.empty((STACK, 4), np.int64)  # (start, stop, parent, side)
    pending[0, 0], pending[0, 1], pending[0, 2], pending[0, 3] = 0, points.shape[0], -1, 0
    depth = 1
    count = 0
    while depth > 0:
        depth -= 1
        start, stop, parent, side = (
            pending[depth, 0],
            pending[depth, 1],
            pending[depth, 2],
            pending[depth, 3],
        )
        node = count
        count += 1
        starts[node], stops[node] = start, stop
        children[node, 0], children[node, 1] = -1, -1
        if parent >= 0:
            children[parent, side] = node
        if stop - start <= leaf_size:
            continue
        axis = 0
        widest = -1.0
        for a in range(dim):
            low, high = np.inf, -np.inf
            for k in range(start, stop):
                value = points[order[k], a]
                low = min(low, value)
                high = max(high, value)
            if high - low > widest:
                widest, axis = high - low, a
        half = (stop - start) // 2
        _select(points, order, start, stop - 1, start + half, axis)
        pending[depth, 0], pending[depth, 1] = start + half, stop
        pending[depth, 2], pending[depth, 3] = node, 1
        pending[depth + 1, 0], pending[depth + 1, 1] = start, start + half
        pending[depth + 1, 2], pending[depth + 1, 3] = node, 0
        depth += 2
    return count


@njit(cache=True)
def _select(points, order, low, high, kth, axis):
    """Quickselect: permute ``order[low:high + 1]`` so that ``order[kth]`` holds the
    point of rank ``kth - low`` along ``axis``, none after it smaller, none before it
    larger (Hoare's partition, the median of three as pivot)."""
    while low < high:
        middle = (low + high) // 2
        a = points[order[low], axis]
        b = points[order[middle], axis]
        c = points[order[high], axis]
        pivot = max(min(a, b), min(max(a, b), c))
        i, j = low, high
        while i <= j:
            while points[order[i], axis] < pivot:
                i += 1
            while points[order[j], axis] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if kth <= j:
            high = j
        elif kth >= i:
            low = i
        else:
            return


def max_nodes(count: int, leaf_size: int) -> int:
    """An upper bound on the nodes of :func:`kd_tree` over ``count`` points: its leaves
    hold more than ``leaf_size / 2`` points each (median splits of larger nodes)."""
    return 4 * (count // max(1, leaf_size) + 1) + 1
