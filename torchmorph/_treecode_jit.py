"""The numba kernels of the treecode (:mod:`torchmorph._treecode`), float64: the kd-trees,
the dual traversal's lists, the interpolation between points and their nodes' proxies
and between the proxies of nested nodes (and their transposes), and the kernel sums
(thin-plate or inverse power) of a group of rows over its far nodes' proxies and its
near sources (and their transpose), in parallel.

A group's sums take the points it interacts with (proxies, then near sources) gathered
into contiguous arrays, then chunks of :data:`CHUNK` of them against each of its rows
(targets, or a target node's proxies) with :mod:`torchmorph._kernel_rows`' passes
(squared distances, the kernel of them, dot products), so
that a chunk stays in the L1 cache while the group's rows go over it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from torchmorph._kernel_rows import FLAGS, inverse_power_row, squared_row, tps_row

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
    "PROXIES_FROM_PROXIES",
    "PROXIES_FROM_SOURCES",
    "STACK",
    "TARGETS_FROM_PROXIES",
    "TARGETS_FROM_SOURCES",
    "dual_lists",
    "group_sums",
    "group_sums_transposed",
    "interpolate",
    "midpoint_tree",
    "shift_down",
    "shift_up",
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


#: The kinds of interaction of :func:`dual_lists`: a target node's proxies from a source
#: node's proxies or sources, a target node's targets from a source node's proxies or
#: sources.
PROXIES_FROM_PROXIES, PROXIES_FROM_SOURCES, TARGETS_FROM_PROXIES, TARGETS_FROM_SOURCES = range(4)


@njit(cache=True)
def dual_lists(target_centres, target_radii, target_children, target_expanded, source_centres,
               source_radii, source_children, source_expanded, theta):  # fmt: skip
    """The dual traversal of the target and source trees (Wilson, Vaughn and Krasny, *A
    GPU-accelerated fast multipole method based on barycentric Lagrange interpolation
    and dual tree traversal*, Comput. Phys. Commun. 265, 2021, Algorithm 2): a pair of
    nodes whose balls are well separated, r_T + r_C < θ R, interacts through the
    proxies of each side that has an expansion (more points than proxies); a pair too
    close opens its larger node (a leaf pair interacts directly). Returns (kinds,
    target nodes, source nodes) of the interactions."""
    capacity = 1024
    kinds = np.empty(capacity, np.int8)
    targets = np.empty(capacity, np.int64)
    sources = np.empty(capacity, np.int64)
    count = 0
    stack = np.empty((4 * STACK, 2), np.int64)
    stack[0, 0], stack[0, 1] = 0, 0
    depth = 1
    while depth > 0:
        depth -= 1
        node, other = stack[depth, 0], stack[depth, 1]
        dx = target_centres[node, 0] - source_centres[other, 0]
        dy = target_centres[node, 1] - source_centres[other, 1]
        dz = target_centres[node, 2] - source_centres[other, 2]
        distance = math.sqrt(dx * dx + dy * dy + dz * dz)
        target_leaf = target_children[node, 0] < 0
        source_leaf = source_children[other, 0] < 0
        kind = -1
        if target_radii[node] + source_radii[other] < theta * distance:
            if target_expanded[node]:
                kind = PROXIES_FROM_PROXIES if source_expanded[other] else PROXIES_FROM_SOURCES
            else:
                kind = TARGETS_FROM_PROXIES if source_expanded[other] else TARGETS_FROM_SOURCES
        elif target_leaf and source_leaf:
            kind = TARGETS_FROM_SOURCES
        elif source_leaf or (not target_leaf and target_radii[node] >= source_radii[other]):
            stack[depth, 0], stack[depth, 1] = target_children[node, 1], other
            stack[depth + 1, 0], stack[depth + 1, 1] = target_children[node, 0], other
            depth += 2
        else:
            stack[depth, 0], stack[depth, 1] = node, source_children[other, 1]
            stack[depth + 1, 0], stack[depth + 1, 1] = node, source_children[other, 0]
            depth += 2
        if kind >= 0:
            if count == capacity:
                capacity *= 2
                kinds = _grown(kinds, capacity)
                targets = _grown(targets, capacity)
                sources = _grown(sources, capacity)
            kinds[count], targets[count], sources[count] = kind, node, other
            count += 1
    return kinds[:count].copy(), targets[:count].copy(), sources[:count].copy()


@njit(cache=True)
def _grown(array, capacity):
    out = np.empty(capacity, array.dtype)
    out[: array.shape[0]] = array
    return out


@njit(fastmath=FLAGS, error_model="numpy", cache=True)
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


@njit(fastmath=FLAGS, error_model="numpy", cache=True)
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


@njit(fastmath=FLAGS, error_model="numpy", cache=True)
def _kernel_row(rows, i, px, py, pz, begin, end, scale2, power, floor, chunk, exponent,
                mantissa_bits):  # fmt: skip
    """``chunk[j] = K(|x_i − p_(begin + j)|)`` for the gathered points ``begin:end``: the
    thin-plate ``φ(ε r)`` for ``power`` 0 (``scale2`` = ε²), else ``r^-power``
    (:mod:`torchmorph._kernel_rows`' passes: squared distances, then the kernel)."""
    squared_row(
        rows[i, 0], rows[i, 1], rows[i, 2], px[begin:end], py[begin:end], pz[begin:end], scale2,
        chunk,
    )  # fmt: skip
    if power == 0.0:
        tps_row(chunk, exponent[: end - begin], mantissa_bits[: end - begin])
    else:
        inverse_power_row(chunk, power, floor)


@njit(parallel=True, fastmath=FLAGS, error_model="numpy", cache=True)
def group_sums(rows, group_starts, group_stops, far_offsets, far, near_offsets, near,
               proxy_offsets, proxies, charges_t, starts, stops, sources, values_t, scale2,
               power, floor, out):  # fmt: skip
    """``out[i] = Σ K(|x_i − p|) q_p`` (K of :func:`_kernel_row`) over the far proxies
    (charges ``charges_t``) and near sources (``values_t``) of the group of row i (the
    rows of group g are ``group_starts[g]:group_stops[g]``, each row in one group),
    sources in tree order. IDW's weight r^-4 against one column (its weight sums) or three
    (a 3-D field) takes one fused pass (distances, weights and sums together)."""
    columns = values_t.shape[0]
    for block in prange(group_starts.shape[0]):
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
        first, last = group_starts[block], group_stops[block]
        sums = np.zeros((last - first, columns))
        row = np.empty(CHUNK)
        exponent = np.empty(CHUNK)
        mantissa_bits = np.empty(CHUNK, dtype=np.int64)
        for begin in range(0, total, CHUNK):
            end = min(begin + CHUNK, total)
            chunk = row[: end - begin]
            for i in range(first, last):
                if power == 4.0 and columns == 3:  # IDW's common case: one fused pass
                    x, y, z = rows[i, 0], rows[i, 1], rows[i, 2]
                    first_weights = weights_t[0, begin:end]
                    second_weights = weights_t[1, begin:end]
                    third_weights = weights_t[2, begin:end]
                    cx, cy, cz = px[begin:end], py[begin:end], pz[begin:end]
                    a = b = c = 0.0
                    for j in range(end - begin):
                        dx = x - cx[j]
                        dy = y - cy[j]
                        dz = z - cz[j]
                        s = max((dx * dx + dy * dy + dz * dz) * scale2, floor)
                        value = 1.0 / (s * s)
                        a += value * first_weights[j]
                        b += value * second_weights[j]
                        c += value * third_weights[j]
                    sums[i - first, 0] += a
                    sums[i - first, 1] += b
                    sums[i - first, 2] += c
                    continue
                if power == 4.0 and columns == 1:  # IDW's weight sums
                    x, y, z = rows[i, 0], rows[i, 1], rows[i, 2]
                    only_weights = weights_t[0, begin:end]
                    cx, cy, cz = px[begin:end], py[begin:end], pz[begin:end]
                    a = 0.0
                    for j in range(end - begin):
                        dx = x - cx[j]
                        dy = y - cy[j]
                        dz = z - cz[j]
                        s = max((dx * dx + dy * dy + dz * dz) * scale2, floor)
                        a += only_weights[j] / (s * s)
                    sums[i - first, 0] += a
                    continue
                _kernel_row(rows, i, px, py, pz, begin, end, scale2, power, floor, chunk,
                            exponent, mantissa_bits)  # fmt: skip
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


@njit(parallel=True, fastmath=FLAGS, error_model="numpy", cache=True)
def group_sums_transposed(rows, group_starts, group_stops, far_offsets, far, near_offsets,
                          near, proxy_offsets, proxies, starts, stops, sources, grads_t, scale2,
                          power, floor, parts, potentials_t, out_t):  # fmt: skip
    """The transpose of :func:`group_sums`: ``potentials_t[k, :, p] += Σ_i K(|x_i − p|)
    grads_t[:, i]`` for far proxy p and ``out_t[k, :, j] += ...`` for near source j, over
    the rows i of the groups of part k (``parts`` contiguous ranges of groups, one
    private accumulator each; the caller sums them)."""
    columns = grads_t.shape[0]
    blocks = group_starts.shape[0]
    for group in prange(parts):
        for block in range(group * blocks // parts, (group + 1) * blocks // parts):
            px, py, pz = _gather(block, far_offsets, far, near_offsets, near, proxy_offsets,
                                 proxies, starts, stops, sources)  # fmt: skip
            total = px.shape[0]
            gathered = np.zeros((columns, total))
            first, last = group_starts[block], group_stops[block]
            row = np.empty(CHUNK)
            exponent = np.empty(CHUNK)
            mantissa_bits = np.empty(CHUNK, dtype=np.int64)
            for begin in range(0, total, CHUNK):
                end = min(begin + CHUNK, total)
                chunk = row[: end - begin]
                for i in range(first, last):
                    _kernel_row(rows, i, px, py, pz, begin, end, scale2, power, floor,
                                chunk, exponent, mantissa_bits)  # fmt: skip
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


@njit(fastmath=FLAGS, error_model="numpy", cache=True)
def _shift_matrices(parent, child, axis_nodes, degrees):
    """Per axis, the parent's Lagrange basis at the child's Chebyshev points: (3, n + 1,
    n + 1), entry [axis, child point, parent point]."""
    width = axis_nodes.shape[2]
    out = np.zeros((3, width, width))
    basis = np.empty(width)
    for axis in range(3):
        for point in range(degrees[child, axis] + 1):
            _basis(axis_nodes[child, axis, point], axis_nodes[parent, axis], degrees[parent, axis],
                   basis)  # fmt: skip
            for k in range(degrees[parent, axis] + 1):
                out[axis, point, k] = basis[k]
    return out


@njit(fastmath=FLAGS, error_model="numpy", cache=True)
def _contract(matrices, source, source_shape, target_shape, out, transpose):
    """``out += (M0 ⊗ M1 ⊗ M2) source`` on grids of ``source_shape`` → ``target_shape``
    (``transpose``: ``(M0 ⊗ M1 ⊗ M2)ᵀ``, the shapes swapped), axis by axis."""
    a0, a1, a2 = source_shape[0], source_shape[1], source_shape[2]
    b0, b1, b2 = target_shape[0], target_shape[1], target_shape[2]
    first = np.zeros((a0, a1, b2))
    for i in range(a0):
        for j in range(a1):
            for m in range(b2):
                total = 0.0
                for k in range(a2):
                    weight = matrices[2, k, m] if transpose else matrices[2, m, k]
                    total += weight * source[(i * a1 + j) * a2 + k]
                first[i, j, m] = total
    second = np.zeros((a0, b1, b2))
    for i in range(a0):
        for n in range(b1):
            for j in range(a1):
                weight = matrices[1, j, n] if transpose else matrices[1, n, j]
                for m in range(b2):
                    second[i, n, m] += weight * first[i, j, m]
    for p in range(b0):
        for i in range(a0):
            weight = matrices[0, i, p] if transpose else matrices[0, p, i]
            for n in range(b1):
                for m in range(b2):
                    out[(p * b1 + n) * b2 + m] += weight * second[i, n, m]


@njit(parallel=True, fastmath=FLAGS, error_model="numpy", cache=True)
def shift_down(levels, level_offsets, parents, axis_nodes, degrees, proxy_offsets, potentials_t):
    """Each expanded node's proxy potentials plus those of ``parents[node]`` (its nearest
    expanded ancestor) interpolated at its proxies, from the top level down (``levels``:
    the nodes that take them, by depth, CSR ``level_offsets``)."""
    columns = potentials_t.shape[0]
    for level in range(level_offsets.shape[0] - 1):
        begin, end = level_offsets[level], level_offsets[level + 1]
        for index in prange(end - begin):
            node = levels[begin + index]
            parent = parents[node]
            matrices = _shift_matrices(parent, node, axis_nodes, degrees)
            parent_shape = degrees[parent] + 1
            node_shape = degrees[node] + 1
            for column in range(columns):
                source = potentials_t[column, proxy_offsets[parent] : proxy_offsets[parent + 1]]
                target = potentials_t[column, proxy_offsets[node] : proxy_offsets[node + 1]]
                _contract(matrices, source, parent_shape, node_shape, target, False)


@njit(parallel=True, fastmath=FLAGS, error_model="numpy", cache=True)
def shift_up(levels, level_offsets, child_offsets, child_nodes, axis_nodes, degrees,
             proxy_offsets, potentials_t):  # fmt: skip
    """The transpose of :func:`shift_down`: from the deepest level up, each node gathers
    the potentials of the nodes it shifts to (``levels``: those nodes' sources of shift,
    by depth, CSR ``level_offsets``; ``child_nodes``, CSR ``child_offsets`` by position
    in ``levels``)."""
    columns = potentials_t.shape[0]
    for level in range(level_offsets.shape[0] - 2, -1, -1):
        begin, end = level_offsets[level], level_offsets[level + 1]
        for index in prange(end - begin):
            position = begin + index
            parent = levels[position]
            parent_shape = degrees[parent] + 1
            for child in range(child_offsets[position], child_offsets[position + 1]):
                node = child_nodes[child]
                matrices = _shift_matrices(parent, node, axis_nodes, degrees)
                node_shape = degrees[node] + 1
                for column in range(columns):
                    source = potentials_t[column, proxy_offsets[node] : proxy_offsets[node + 1]]
                    target = potentials_t[column, proxy_offsets[parent] : proxy_offsets[parent + 1]]
                    _contract(matrices, source, node_shape, parent_shape, target, True)


@njit(parallel=True, fastmath=FLAGS, error_model="numpy", cache=True)
def interpolate(rows, owners, own_offsets, own_starts, own_stops, axis_nodes, degrees,
                proxy_offsets, proxies_t, points, transpose):  # fmt: skip
    """``points[i] += Σ_l L_l(x_i) proxies[l]`` over the proxies of the node that owns
    point i (its lowest expanded ancestor; ``owners`` with CSR ``own_offsets`` into the
    point ranges ``own_starts:own_stops`` each owns), ``points`` (N, S) and
    ``proxies_t`` (S, P); ``transpose``: ``proxies[l] += Σ_i L_l(x_i) points[i]``."""
    columns = proxies_t.shape[0]
    for index in prange(owners.shape[0]):
        node = owners[index]
        d0, d1, d2 = degrees[node, 0], degrees[node, 1], degrees[node, 2]
        first = np.empty(d0 + 1)
        second = np.empty(d1 + 1)
        third = np.empty(d2 + 1)
        offset = proxy_offsets[node]
        for span in range(own_offsets[index], own_offsets[index + 1]):
            for i in range(own_starts[span], own_stops[span]):
                _basis(rows[i, 0], axis_nodes[node, 0], d0, first)
                _basis(rows[i, 1], axis_nodes[node, 1], d1, second)
                _basis(rows[i, 2], axis_nodes[node, 2], d2, third)
                for column in range(columns):
                    value = points[i, column]
                    total = 0.0
                    k = offset
                    for a in range(d0 + 1):
                        for b in range(d1 + 1):
                            inner = first[a] * second[b]
                            for c in range(d2 + 1):
                                if transpose:
                                    proxies_t[column, k] += inner * third[c] * value
                                else:
                                    total += inner * third[c] * proxies_t[column, k]
                                k += 1
                    if not transpose:
                        points[i, column] += total
