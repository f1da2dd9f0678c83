"""The numba traversal of the tree-approximated IDW (:mod:`torchmorph.idw.tree`; the
trees are built by :mod:`._kd_jit`, the nodes' moments by :mod:`._tree_moments`, a leaf's
and an accepted node's terms by :mod:`._tree_terms`): one traversal per block of targets
that sums near leaves exactly and accepted far nodes by a second-order (quadrupole)
expansion of ``|x - y|^-p`` about the node's centroid, with a rigorous bound on each
accepted node's error. The same traversal, run with
``transpose=True``, applies the transpose of the operator it built (the backward pass to
the displacements).

Notation (all arithmetic in float64): a node holds ``n`` controls ``y_k`` about their
centroid ``c`` within the radius ``rho``; for a target ``x`` put ``r = x - c``,
``R = |r|``, ``s_k = y_k - c``, ``theta = rho / R``. For ``theta < 1`` the Gegenbauer
expansion ``|x - y|^-p = R^-p Σ_m C_m^(p/2)(cos γ) (|s|/R)^m`` holds, its degree-m
term is a homogeneous polynomial of degree m in ``s``, and ``|C_m^(p/2)(t)| <= C_m^(p/2)(1)``
with ``Σ_m C_m^(p/2)(1) θ^m = (1 - θ)^-p``. Keeping the terms of degree <= 2,

    P(s) = R^-p [1 + p (r̂·s)/R - (p/2)|s|²/R² + (p(p+2)/2)(r̂·s)²/R²],

every control's weight is approximated with the error bound
``δ = R^-p T2(θ)``, ``T2(θ) = (1 - θ)^-p - 1 - pθ - p(p+1)θ²/2``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import numba
    from numba import njit, prange
else:
    try:
        import numba
        from numba import njit, prange
    except ImportError:  # pragma: no cover - exercised where numba is absent
        numba = None
        prange = range

        def njit(*args, **kwargs):
            return lambda function: function


from torchmorph.idw.backends.numba._jit import _OPTIONS, ratio_power  # cached, vectorised sums
from torchmorph.idw.backends.numba._kd_jit import STACK
from torchmorph.idw.backends.numba._tree_terms import (
    _far_field3,
    _far_field3_transposed,
    _leaf_by_controls,
    _quadratic,
    _squared,
    _weights,
)


def numba_threads() -> int:
    """The threads numba's parallel loops run on now (1 without numba)."""
    return 1 if numba is None else int(numba.get_num_threads())


@njit(**_OPTIONS)
def remainder(theta, power):
    """T2(θ) = (1-θ)^-p - 1 - pθ - p(p+1)θ²/2 >= 0, the bound on Σ_{m>=3} C_m^(p/2)(1) θ^m
    (``expm1``/``log1p`` keep it accurate for small θ); infinite for θ >= 1."""
    if theta >= 1.0:
        return np.inf
    whole = math.expm1(-power * math.log1p(-theta))
    value = whole - power * theta - 0.5 * power * (power + 1.0) * theta * theta
    return max(value, 0.0) * (1.0 + 1e-12) + 1e-300


@njit(**_OPTIONS)
def _remainder_fast(theta, power, mode):
    """T2(θ) as :func:`remainder`, in closed form for the integer p from 1 to 8 (no log/exp)."""
    if mode == 4:
        if theta >= 1.0:
            return np.inf
        gap = 1.0 - theta
        gap2 = gap * gap
        value = theta**3 * (20.0 - theta * (45.0 - theta * (36.0 - 10.0 * theta))) / (gap2 * gap2)
        return value * (1.0 + 1e-12) + 1e-300
    if mode == 2:
        if theta >= 1.0:
            return np.inf
        gap = 1.0 - theta
        return theta**3 * (4.0 - 3.0 * theta) / (gap * gap) * (1.0 + 1e-12) + 1e-300
    if mode == 0:
        return remainder(theta, power)
    if theta >= 1.0:
        return np.inf
    # the other integer p: T2 = θ³ q(θ) / (1-θ)^p with q's integer coefficients (1 - (1-θ)^p
    # (1 + pθ + p(p+1)θ²/2) = θ³ q(θ)); Horner's rounding stays below 3e-13 relative
    if mode == 1:
        q = 1.0
    elif mode == 3:
        q = 10.0 - theta * (15.0 - 6.0 * theta)
    elif mode == 5:
        q = 35.0 - theta * (105.0 - theta * (126.0 - theta * (70.0 - 15.0 * theta)))
    elif mode == 6:
        q = 120.0 - 21.0 * theta
        q = 56.0 - theta * (210.0 - theta * (336.0 - theta * (280.0 - theta * q)))
    elif mode == 7:
        q = 540.0 - theta * (189.0 - 28.0 * theta)
        q = 84.0 - theta * (378.0 - theta * (756.0 - theta * (840.0 - theta * q)))
    else:  # 8
        q = 1800.0 - theta * (945.0 - theta * (280.0 - 36.0 * theta))
        q = 120.0 - theta * (630.0 - theta * (1512.0 - theta * (2100.0 - theta * q)))
    gap = 1.0 - theta
    denominator = 1.0
    for _ in range(mode):
        denominator *= gap
    return theta**3 * q / denominator * (1.0 + 1e-11) + 1e-300


@njit(**_OPTIONS)
def _power(ratio, power, mode):
    """ratio^p, by products (and a square root for odd p) for the integer p up to 8."""
    return ratio_power(ratio * ratio, 0.5 * power, mode)


@njit(**_OPTIONS)
def _visit_block(
    first_target, last_target, targets, reference, controls_t, values_t, scaled, children,
    starts, stops, centroids, radii, second_geometry, effective, zeroth, first, second, power, mode,
    eta, n_controls, radius2, transpose, sums, numerator, bounds, coincident, coincident_sum,
    node_zeroth, node_first, node_second, out, max_leaf, ref2_leaf, controls_leaf, values_leaf,
):  # fmt: skip
    """One block of targets against the tree (see :func:`traverse`)."""
    dim, columns = controls_t.shape[0], values_t.shape[0]
    rows = last_target - first_target
    half_power = 0.5 * power
    ref2 = reference * reference
    lower = np.zeros(rows)  # with block_sums: lower bounds of the weights met so far (<= S)
    distance = np.empty(rows)
    unit = np.empty(dim)
    buffer = np.empty(max_leaf)
    offset = np.empty((dim, rows))
    inverse2 = np.empty(rows)
    weight = np.empty(rows)
    node_bound = np.empty(rows)
    quad = np.empty(rows)
    linear = np.empty(rows)
    local = np.empty((dim, rows))  # the block's targets, transposed
    monomials = np.empty((6, rows))  # scratch of :func:`_far_field3`
    factors = np.empty((3, rows))
    for t in range(rows):
        for a in range(dim):
            local[a, t] = targets[first_target + t, a]
    local_leaf = local.astype(controls_leaf.dtype)  # the leaves' arithmetic
    buffer_leaf = np.empty(max_leaf, controls_leaf.dtype)
    block_centre = np.zeros(dim)
    for a in range(dim):
        for t in range(rows):
            block_centre[a] += local[a, t]
        block_centre[a] /= rows
    block_sums = np.zeros(rows)  # leaf sums of :func:`_leaf_by_controls`
    block_numerator = np.zeros((columns, rows))  # leaves and accepted nodes
    far_sums = np.zeros(rows)  # S of the accepted nodes (not a lower bound)
    block_scaled = np.zeros((scaled.shape[1], rows if transpose else 0))
    if transpose:  # coincident targets take no weighted sums
        for t in range(rows):
            if coincident[first_target + t] == 0:
                for column in range(scaled.shape[1]):
                    block_scaled[column, t] = scaled[first_target + t, column]
    stack = np.empty(STACK, np.int64)
    stack[0] = 0
    depth = 1
    while depth > 0:
        depth -= 1
        node = stack[depth]
        rho = radii[node]
        nearest = np.inf
        smallest_lower = np.inf
        farthest = 0.0
        for t in range(rows):  # r = x - c and R, the block's targets in the vector lanes
            distance[t] = 0.0
        for a in range(dim):
            centre = centroids[node, a]
            for t in range(rows):
                diff = local[a, t] - centre
                offset[a, t] = diff
                distance[t] += diff * diff
        for t in range(rows):
            distance[t] = math.sqrt(distance[t])
        for t in range(rows):
            nearest = min(nearest, distance[t])
            farthest = max(farthest, distance[t])
            smallest_lower = min(smallest_lower, lower[t] + block_sums[t])
        accepted = False
        worst = 0.0
        count = stops[node] - starts[node]
        if rho < nearest:
            worst = _power(reference / nearest, power, mode) * _remainder_fast(
                rho / nearest, power, mode
            )
            share = max(
                smallest_lower / n_controls, _power(reference / (farthest + rho), power, mode)
            )
            accepted = effective[node] * worst <= 0.5 * eta * count * share
            if accepted:
                for t in range(rows):
                    node_bound[t] = worst
            else:  # each target against its own bound and its own sums
                accepted = True
                for t in range(rows):
                    node_bound[t] = _power(reference / distance[t], power, mode) * _remainder_fast(
                        rho / distance[t], power, mode
                    )
                    own = max(
                        (lower[t] + block_sums[t]) / n_controls,
                        _power(reference / (distance[t] + rho), power, mode),
                    )
                    if effective[node] * node_bound[t] > 0.5 * eta * count * own:
                        accepted = False
                        break
        if accepted:
            coefficient = 0.5 * power * (power + 2.0)
            for t in range(rows):  # 1/R², the centroid's weight (ref/R)^p
                inverse2[t] = 1.0 / (distance[t] * distance[t])
            for t in range(rows):
                lower[t] += count * _power(reference / (distance[t] + rho), power, mode)
            if mode == 4:
                for t in range(rows):
                    ratio = ref2 * inverse2[t]
                    weight[t] = ratio * ratio
            elif mode == 2:
                for t in range(rows):
                    weight[t] = ref2 * inverse2[t]
            else:
                for t in range(rows):
                    weight[t] = ratio_power(ref2 * inverse2[t], half_power, mode)
            if not transpose:
                for t in range(rows):
                    bounds[first_target + t] += effective[node] * node_bound[t]
            if not transpose and dim == 3:  # P summed over the node, the monomials shared
                _far_field3(
                    offset, weight, inverse2, rows, power, count, second_geometry[node],
                    zeroth[node], first[node], second[node], monomials, factors, far_sums,
                    block_numerator,
                )  # fmt: skip
            elif not transpose:  # P summed over the node: n, Σd, Σd s, Σ s sᵀ, Σ d s sᵀ
                trace = 0.0
                for a in range(dim):
                    trace += second_geometry[node, a, a]
                _quadratic(offset, second_geometry[node], rows, quad)
                for t in range(rows):
                    far_sums[t] += weight[t] * (
                        count
                        + (coefficient * quad[t] * inverse2[t] - half_power * trace) * inverse2[t]
                    )
                for column in range(columns):
                    trace = 0.0
                    for a in range(dim):
                        trace += second[node, column, a, a]
                    _quadratic(offset, second[node, column], rows, quad)
                    base = zeroth[node, column]
                    for t in range(rows):
                        linear[t] = 0.0
                    for a in range(dim):
                        moment = first[node, column, a]
                        for t in range(rows):
                            linear[t] += moment * offset[a, t]
                    for t in range(rows):
                        block_numerator[column, t] += weight[t] * (
                            base
                            + power * linear[t] * inverse2[t]
                            + (coefficient * quad[t] * inverse2[t] - half_power * trace)
                            * inverse2[t]
                        )
            elif dim == 3:  # the transposed expansion's coefficients, summed over the block
                _far_field3_transposed(
                    offset, weight, inverse2, rows, power, block_scaled, monomials, factors,
                    node_zeroth[node], node_first[node], node_second[node],
                )  # fmt: skip
            else:
                for t in range(rows):
                    target = first_target + t
                    if coincident[target] != 0:
                        continue
                    inverse = math.sqrt(inverse2[t])
                    for a in range(dim):
                        unit[a] = offset[a, t] * inverse
                    for column in range(columns):
                        g = scaled[target, column] * weight[t]
                        if g == 0.0:
                            continue
                        node_zeroth[node, column] += g
                        for a in range(dim):
                            node_first[node, column, a] += g * power * unit[a] * inverse
                            for b in range(dim):
                                term = coefficient * unit[a] * unit[b]
                                if a == b:
                                    term -= half_power
                                node_second[node, column, a, b] += g * term * inverse * inverse
        elif children[node, 0] < 0:  # a leaf, summed exactly
            start, stop = starts[node], stops[node]
            width = stop - start
            reachable = nearest - rho <= 2.0 * math.sqrt(radius2)  # a coincidence possible
            if not reachable:  # controls outer, the block's targets in SIMD
                _leaf_by_controls(
                    local_leaf, controls_leaf, values_leaf, start, stop, rows, ref2_leaf,
                    half_power, mode, buffer_leaf, block_sums, block_numerator, transpose,
                    block_scaled, out,
                )  # fmt: skip
                continue
            for t in range(rows):
                target = first_target + t
                chunk = buffer[:width]
                _squared(targets[target], controls_t, start, stop, chunk)
                closest = np.inf
                if reachable:
                    for k in range(width):
                        closest = min(closest, chunk[k])
                if closest <= radius2:  # coincident controls: counted, never weighted
                    for k in range(width):
                        if chunk[k] <= radius2:
                            if transpose:
                                if coincident[target] > 0:
                                    for column in range(columns):
                                        out[start + k, column] += scaled[target, column]
                            else:
                                coincident[target] += 1
                                for column in range(columns):
                                    coincident_sum[target, column] += values_t[column, start + k]
                            chunk[k] = np.inf
                _weights(chunk, width, ref2, half_power, mode)
                total = 0.0
                for k in range(width):
                    total += chunk[k]
                lower[t] += total
                if transpose:
                    if coincident[target] == 0:
                        for column in range(columns):
                            g = scaled[target, column]
                            for k in range(width):
                                out[start + k, column] += chunk[k] * g
                else:
                    sums[target] += total
                    for column in range(columns):
                        dot = 0.0
                        row = values_t[column, start:stop]
                        for k in range(width):
                            dot += chunk[k] * row[k]
                        numerator[target, column] += dot
        else:  # open the node: the nearer child is visited first
            near, far = children[node, 0], children[node, 1]
            near_distance = 0.0
            far_distance = 0.0
            for a in range(dim):
                near_distance += (block_centre[a] - centroids[near, a]) ** 2
                far_distance += (block_centre[a] - centroids[far, a]) ** 2
            if near_distance > far_distance:
                near, far = far, near
            stack[depth] = far
            stack[depth + 1] = near
            depth += 2
    if not transpose:
        for t in range(rows):
            sums[first_target + t] += block_sums[t] + far_sums[t]
            for column in range(columns):
                numerator[first_target + t, column] += block_numerator[column, t]


@njit(parallel=True, **_OPTIONS)
def traverse(
    targets, block_starts, references, controls_t, values_t, scaled, children, starts, stops,
    centroids, radii, second_geometry, effective, zeroth, first, second, power, mode, eta,
    radius2, transpose, groups, sums, numerator, bounds, coincident, coincident_sum, node_zeroth,
    node_first, node_second, out, max_leaf, ref2_leaf, controls_leaf, values_leaf, visit,
):  # fmt: skip
    """The blocks of targets listed in ``visit`` against the tree, in parallel over ``groups``
    groups of them (each with its own transposed accumulators ``node_*[group]``,
    ``out[group]``); each block's results depend on that block alone.

    A node of ``n`` controls (effective count ``m``, see :func:`node_geometry`) is accepted
    for a block when its bound ``δ_t`` at each target of the block satisfies
    ``m δ_t <= (η/2) n max(L_t / N_c, (ref / (R_t + ρ))^p)``, with ``L_t`` the weights
    summed so far for that target (a lower bound of its S, near nodes first); the block is
    tested at once first (``δ`` at its nearest target, the smallest ``L_t``, its farthest
    target), then target by target. Summed over accepted nodes the first term stays below
    ``(η/2) S``, the second below ``(η/2)`` times the far nodes' share of S, so
    ``E = Σ m δ <= η S`` for every target. Leaves not accepted are summed exactly;
    a target within ``radius2`` of a control is coincident (counted, its values summed).
    Forward (``transpose=False``): ``sums``, ``numerator``, ``bounds`` (E) and the
    coincident counts and sums. Transposed: ``out[group] += Aᵀ scaled`` by leaves and by
    per-node coefficients (spread by :func:`push_down`), ``scaled`` holding grad / S'."""
    for group in prange(groups):
        for index in range(group, visit.shape[0], groups):
            block = visit[index]
            _visit_block(
                block_starts[block], block_starts[block + 1], targets, references[block],
                controls_t, values_t, scaled, children, starts, stops, centroids, radii,
                second_geometry, effective, zeroth, first, second, power, mode, eta,
                stops[0] - starts[0], radius2, transpose, sums, numerator, bounds, coincident, coincident_sum,
                node_zeroth[group], node_first[group], node_second[group], out[group],
                max_leaf, ref2_leaf[block], controls_leaf, values_leaf,
            )  # fmt: skip
