"""The numba kernels of the RBF treecode (:mod:`torchmorph.rbf.treecode`), float64: the
interaction lists of the target blocks, the proxy charges of the source clusters (and
their transpose), and the thin-plate sums of a block over its far clusters' proxies and
its near sources (and their transpose), in parallel over blocks.

A block's sums take the points it interacts with (proxies, then near sources) gathered
into contiguous rows, then chunks of :data:`CHUNK` of them against each of its targets
with :mod:`torchmorph.rbf._numba`'s passes (squared distances, ``s log(s) / 2`` with the
vectorised logarithm, dot products), so that a chunk stays in the L1 cache while the
block's targets go over it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from torchmorph.rbf import _numba

if TYPE_CHECKING:
    from numba import njit, prange
else:
    try:
        from numba import njit, prange
    except ImportError:  # pragma: no cover - exercised where numba is absent
        prange = range

        def njit(*args, **kwargs):
            return lambda function: function


__all__ = [
    "CHUNK",
    "STACK",
    "block_sums",
    "block_sums_transposed",
    "charges",
    "charges_transposed",
    "interaction_lists",
    "midpoint_tree",
]

CHUNK = 512
"""Gathered points per pass of a block's targets (three scratch rows of 4 KiB: L1)."""

STACK = 256
"""Depth of a traversal's stack of source nodes (a median kd-tree is ~log2(N) deep)."""


@njit(cache=True)
def midpoint_tree(points, leaf_size, order, starts, stops, children):
    """A kd-tree that halves the widest side of each node's bounding box (the box of its
    points) until a node holds at most ``leaf_size`` points or all of them coincide,
    built in place as :func:`torchmorph.idw.backends.numba._kd_jit.kd_tree` builds its
    median tree (``order`` permuted, nodes in depth-first preorder, arrays of at least
    2 N - 1 rows). Its nodes stay compact where the points lie on surfaces apart (a
    median split puts a wall and a wing into one node). Returns the number of nodes."""
    pending = np.empty((STACK, 4), np.int64)  # (start, stop, parent, side)
    pending[0, 0], pending[0, 1], pending[0, 2], pending[0, 3] = 0, points.shape[0], -1, 0
    depth = 1
    count = 0
    while depth > 0:
        depth -= 1
        start, stop, parent, side = (
            pending[depth, 0], pending[depth, 1], pending[depth, 2], pending[depth, 3],
        )  # fmt: skip
        node = count
        count += 1
        starts[node], stops[node] = start, stop
        children[node, 0], children[node, 1] = -1, -1
        if parent >= 0:
            children[parent, side] = node
        if stop - start <= leaf_size:
            continue
        axis = 0
        widest = 0.0
        middle = 0.0
        for a in range(points.shape[1]):
            low, high = np.inf, -np.inf
            for k in range(start, stop):
                value = points[order[k], a]
                low = min(low, value)
                high = max(high, value)
            if high - low > widest:
                widest, axis, middle = high - low, a, low + (high - low) / 2
        if widest == 0.0 or depth + 2 > STACK:  # coincident points, or too deep: a leaf
            continue
        i, j = start, stop - 1
        while i <= j:  # points <= middle first
            if points[order[i], axis] <= middle:
                i += 1
            else:
                order[i], order[j] = order[j], order[i]
                j -= 1
        if i == start or i == stop:  # the middle rounded onto an end: a leaf
            continue
        pending[depth, 0], pending[depth, 1] = i, stop
        pending[depth, 2], pending[depth, 3] = node, 1
        pending[depth + 1, 0], pending[depth + 1, 1] = start, i
        pending[depth + 1, 2], pending[depth + 1, 3] = node, 0
        depth += 2
    return count


@njit(cache=True)
def _visit(centre, radius, node_centres, node_radii, children, expanded, theta, far, near, fill):
    """Traverse the source tree for one block (``centre``, ``radius``): a node whose
    ball is seen under ``theta`` (its radius < theta × (distance − block radius)) is far
    when it has an expansion, near (summed directly, its whole range) otherwise; a
    node seen too closely is opened, a leaf among them near. Writes the nodes into
    ``far``/``near`` when ``fill``; returns the counts (far, near)."""
    stack = np.empty(STACK, np.int64)
    stack[0] = 0
    depth = 1
    count_far = 0
    count_near = 0
    while depth > 0:
        depth -= 1
        node = stack[depth]
        dx = node_centres[node, 0] - centre[0]
        dy = node_centres[node, 1] - centre[1]
        dz = node_centres[node, 2] - centre[2]
        distance = math.sqrt(dx * dx + dy * dy + dz * dz)
        seen = node_radii[node] < theta * (distance - radius)
        if seen and expanded[node]:
            if fill:
                far[count_far] = node
            count_far += 1
        elif seen or children[node, 0] < 0:
            if fill:
                near[count_near] = node
            count_near += 1
        else:
            stack[depth] = children[node, 1]
            stack[depth + 1] = children[node, 0]
            depth += 2
    return count_far, count_near


@njit(parallel=True, cache=True)
def interaction_lists(block_centres, block_radii, node_centres, node_radii, children, expanded,
                      theta):  # fmt: skip
    """CSR lists per block: (far offsets, far nodes, near offsets, near nodes)."""
    blocks = block_centres.shape[0]
    far_counts = np.zeros(blocks + 1, np.int64)
    near_counts = np.zeros(blocks + 1, np.int64)
    empty = np.empty(0, np.int64)
    for block in prange(blocks):
        count_far, count_near = _visit(
            block_centres[block], block_radii[block], node_centres, node_radii, children,
            expanded, theta, empty, empty, False,
        )  # fmt: skip
        far_counts[block + 1] = count_far
        near_counts[block + 1] = count_near
    far_offsets = np.cumsum(far_counts)
    near_offsets = np.cumsum(near_counts)
    far = np.empty(far_offsets[-1], np.int64)
    near = np.empty(near_offsets[-1], np.int64)
    for block in prange(blocks):
        _visit(
            block_centres[block], block_radii[block], node_centres, node_radii, children,
            expanded, theta, far[far_offsets[block] : far_offsets[block + 1]],
            near[near_offsets[block] : near_offsets[block + 1]], True,
        )  # fmt: skip
    return far_offsets, far, near_offsets, near


@njit(fastmath=_numba._FLAGS, error_model="numpy", cache=True)
def _basis(value, nodes, degree, out):
    """The barycentric Lagrange basis on Chebyshev points of the second kind
    (``nodes[:degree + 1]``) at ``value``: ``out[k] = L_k(value)`` (Berrut and Trefethen,
    *Barycentric Lagrange interpolation*, SIAM Review 46, 2004, eq. 4.2 with weights
    (-1)^k, halved at both ends); exactly 1 and 0 at a node."""
    if degree == 0:
        out[0] = 1.0
        return
    total = 0.0
    for k in range(degree + 1):
        difference = value - nodes[k]
        if difference == 0.0:
            for m in range(degree + 1):
                out[m] = 0.0
            out[k] = 1.0
            return
        weight = -1.0 if k % 2 else 1.0
        if k == 0 or k == degree:
            weight *= 0.5
        out[k] = weight / difference
        total += out[k]
    for k in range(degree + 1):
        out[k] /= total


@njit(parallel=True, fastmath=_numba._FLAGS, error_model="numpy", cache=True)
def charges(sources, values_t, starts, stops, expanded_nodes, axis_nodes, degrees,
            proxy_offsets, out):  # fmt: skip
    """The proxy charges of each expanded node, ``out[:, proxies of node] = Σ_j L(y_j)
    values_t[:, j]`` over its sources (tree order), L the tensor-product basis."""
    columns = values_t.shape[0]
    for index in prange(expanded_nodes.shape[0]):
        node = expanded_nodes[index]
        d0, d1, d2 = degrees[node, 0], degrees[node, 1], degrees[node, 2]
        first = np.empty(d0 + 1)
        second = np.empty(d1 + 1)
        third = np.empty(d2 + 1)
        offset = proxy_offsets[node]
        count = (d0 + 1) * (d1 + 1) * (d2 + 1)
        local = np.zeros((columns, count))
        for j in range(starts[node], stops[node]):
            _basis(sources[j, 0], axis_nodes[node, 0], d0, first)
            _basis(sources[j, 1], axis_nodes[node, 1], d1, second)
            _basis(sources[j, 2], axis_nodes[node, 2], d2, third)
            for column in range(columns):
                value = values_t[column, j]
                k = 0
                for a in range(d0 + 1):
                    outer = first[a] * value
                    for b in range(d1 + 1):
                        inner = outer * second[b]
                        for c in range(d2 + 1):
                            local[column, k] += inner * third[c]
                            k += 1
        for column in range(columns):
            for k in range(count):
                out[column, offset + k] = local[column, k]


@njit(parallel=True, fastmath=_numba._FLAGS, error_model="numpy", cache=True)
def charges_transposed(sources, potentials_t, starts, stops, levels, level_offsets, axis_nodes,
                       degrees, proxy_offsets, out_t):  # fmt: skip
    """The transpose of :func:`charges`: ``out_t[:, j] += Σ_k L_k(y_j) potentials_t[:,
    proxy k of node]`` over the expanded nodes holding source j, one depth at a time
    (``levels`` the expanded nodes by depth, CSR ``level_offsets``: the nodes of one
    depth hold disjoint sources, so their loop is parallel without races)."""
    columns = potentials_t.shape[0]
    for level in range(level_offsets.shape[0] - 1):
        begin, end = level_offsets[level], level_offsets[level + 1]
        for index in prange(end - begin):
            node = levels[begin + index]
            d0, d1, d2 = degrees[node, 0], degrees[node, 1], degrees[node, 2]
            first = np.empty(d0 + 1)
            second = np.empty(d1 + 1)
            third = np.empty(d2 + 1)
            offset = proxy_offsets[node]
            for j in range(starts[node], stops[node]):
                _basis(sources[j, 0], axis_nodes[node, 0], d0, first)
                _basis(sources[j, 1], axis_nodes[node, 1], d1, second)
                _basis(sources[j, 2], axis_nodes[node, 2], d2, third)
                for column in range(columns):
                    total = 0.0
                    k = offset
                    for a in range(d0 + 1):
                        for b in range(d1 + 1):
                            inner = first[a] * second[b]
                            for c in range(d2 + 1):
                                total += inner * third[c] * potentials_t[column, k]
                                k += 1
                    out_t[column, j] += total


@njit(fastmath=_numba._FLAGS, error_model="numpy", cache=True)
def _gather(block, far_offsets, far, near_offsets, near, proxy_offsets, proxies, starts, stops,
            sources):  # fmt: skip
    """The points one block interacts with, contiguous per axis: its far nodes' proxies,
    then its near nodes' sources."""
    total = 0
    for index in range(far_offsets[block], far_offsets[block + 1]):
        node = far[index]
        total += proxy_offsets[node + 1] - proxy_offsets[node]
    for index in range(near_offsets[block], near_offsets[block + 1]):
        node = near[index]
        total += stops[node] - starts[node]
    px = np.empty(total)
    py = np.empty(total)
    pz = np.empty(total)
    k = 0
    for index in range(far_offsets[block], far_offsets[block + 1]):
        node = far[index]
        for p in range(proxy_offsets[node], proxy_offsets[node + 1]):
            px[k], py[k], pz[k] = proxies[p, 0], proxies[p, 1], proxies[p, 2]
            k += 1
    for index in range(near_offsets[block], near_offsets[block + 1]):
        node = near[index]
        for j in range(starts[node], stops[node]):
            px[k], py[k], pz[k] = sources[j, 0], sources[j, 1], sources[j, 2]
            k += 1
    return px, py, pz


@njit(parallel=True, fastmath=_numba._FLAGS, error_model="numpy", cache=True)
def block_sums(targets, block_starts, far_offsets, far, near_offsets, near, proxy_offsets,
               proxies, charges_t, starts, stops, sources, values_t, scale2, out):  # fmt: skip
    """``out[i] = Σ φ(|x_i − p|) q_p`` over block i's far proxies (charges ``charges_t``)
    and near sources (``values_t``), targets and sources in tree order."""
    columns = values_t.shape[0]
    for block in prange(block_starts.shape[0] - 1):
        px, py, pz = _gather(block, far_offsets, far, near_offsets, near, proxy_offsets,
                             proxies, starts, stops, sources)  # fmt: skip
        total = px.shape[0]
        weights_t = np.empty((columns, total))
        k = 0
        for index in range(far_offsets[block], far_offsets[block + 1]):
            node = far[index]
            for p in range(proxy_offsets[node], proxy_offsets[node + 1]):
                for column in range(columns):
                    weights_t[column, k] = charges_t[column, p]
                k += 1
        for index in range(near_offsets[block], near_offsets[block + 1]):
            node = near[index]
            for j in range(starts[node], stops[node]):
                for column in range(columns):
                    weights_t[column, k] = values_t[column, j]
                k += 1
        first, last = block_starts[block], block_starts[block + 1]
        sums = np.zeros((last - first, columns))
        row = np.empty(CHUNK)
        exponent = np.empty(CHUNK)
        mantissa_bits = np.empty(CHUNK, dtype=np.int64)
        for begin in range(0, total, CHUNK):
            end = min(begin + CHUNK, total)
            chunk = row[: end - begin]
            for i in range(first, last):
                _numba._squared_row(
                    targets[i, 0], targets[i, 1], targets[i, 2], px[begin:end], py[begin:end],
                    pz[begin:end], scale2, chunk,
                )  # fmt: skip
                _numba._tps_row(chunk, exponent[: end - begin], mantissa_bits[: end - begin])
                if columns == 3:  # a 3-D field: one pass, three sums
                    first_weights = weights_t[0, begin:end]
                    second_weights = weights_t[1, begin:end]
                    third_weights = weights_t[2, begin:end]
                    a = b = c = 0.0
                    for j in range(end - begin):
                        value = chunk[j]
                        a += value * first_weights[j]
                        b += value * second_weights[j]
                        c += value * third_weights[j]
                    sums[i - first, 0] += a
                    sums[i - first, 1] += b
                    sums[i - first, 2] += c
                    continue
                for column in range(columns):
                    weights = weights_t[column, begin:end]
                    accumulated = 0.0
                    for j in range(end - begin):
                        accumulated += chunk[j] * weights[j]
                    sums[i - first, column] += accumulated
        for i in range(first, last):
            for column in range(columns):
                out[i, column] = sums[i - first, column]


@njit(parallel=True, fastmath=_numba._FLAGS, error_model="numpy", cache=True)
def block_sums_transposed(targets, block_starts, far_offsets, far, near_offsets, near,
                          proxy_offsets, proxies, starts, stops, sources, grads_t, scale2,
                          groups, potentials_t, out_t):  # fmt: skip
    """The transpose of :func:`block_sums`: ``potentials_t[g, :, p] += Σ_i φ(|x_i − p|)
    grads_t[:, i]`` for far proxy p and ``out_t[g, :, j] += ...`` for near source j, over
    the targets i of the blocks of group g (``groups`` contiguous ranges of blocks, one
    private accumulator each; the caller sums them)."""
    columns = grads_t.shape[0]
    blocks = block_starts.shape[0] - 1
    for group in prange(groups):
        for block in range(group * blocks // groups, (group + 1) * blocks // groups):
            px, py, pz = _gather(block, far_offsets, far, near_offsets, near, proxy_offsets,
                                 proxies, starts, stops, sources)  # fmt: skip
            total = px.shape[0]
            gathered = np.zeros((columns, total))
            first, last = block_starts[block], block_starts[block + 1]
            row = np.empty(CHUNK)
            exponent = np.empty(CHUNK)
            mantissa_bits = np.empty(CHUNK, dtype=np.int64)
            for begin in range(0, total, CHUNK):
                end = min(begin + CHUNK, total)
                chunk = row[: end - begin]
                for i in range(first, last):
                    _numba._squared_row(
                        targets[i, 0], targets[i, 1], targets[i, 2], px[begin:end],
                        py[begin:end], pz[begin:end], scale2, chunk,
                    )  # fmt: skip
                    _numba._tps_row(chunk, exponent[: end - begin], mantissa_bits[: end - begin])
                    for column in range(columns):
                        grad = grads_t[column, i]
                        target_row = gathered[column, begin:end]
                        for j in range(end - begin):
                            target_row[j] += chunk[j] * grad
            k = 0
            for index in range(far_offsets[block], far_offsets[block + 1]):
                node = far[index]
                for p in range(proxy_offsets[node], proxy_offsets[node + 1]):
                    for column in range(columns):
                        potentials_t[group, column, p] += gathered[column, k]
                    k += 1
            for index in range(near_offsets[block], near_offsets[block + 1]):
                node = near[index]
                for j in range(starts[node], stops[node]):
                    for column in range(columns):
                        out_t[group, column, j] += gathered[column, k]
                    k += 1
