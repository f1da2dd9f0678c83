"""The per-node moments of the tree-approximated IDW (:mod:`torchmorph.idw.tree`), numba:
each node's centroid, radius, second moment and effective count (once per control
tree), its displacements' moments up to second order (once per call), and the spreading
of the transposed far field's per-node coefficients back to the controls."""

from __future__ import annotations

import math

from torchmorph.idw.backends.numba._jit import _OPTIONS, njit, prange  # numba's, or stand-ins


@njit(**_OPTIONS)
def node_geometry(points, starts, stops, centroids, radii, second, effective):
    """Per node: the centroid, the radius ρ about it, Σ s sᵀ and the effective count
    Σ|s|³/ρ³ <= n over its controls (every term of the remainder is of degree >= 3 in
    |s|, so Σ_k T2(|s_k|/R) <= (Σ|s_k|³/ρ³) T2(ρ/R))."""
    dim = points.shape[1]
    for node in prange(starts.shape[0]):
        start, stop = starts[node], stops[node]
        for axis in range(dim):
            centroids[node, axis] = points[start:stop, axis].mean()
        largest = 0.0
        for k in range(start, stop):
            squared = 0.0
            for a in range(dim):
                sa = points[k, a] - centroids[node, a]
                squared += sa * sa
                for b in range(dim):
                    second[node, a, b] += sa * (points[k, b] - centroids[node, b])
            largest = max(largest, squared)
            effective[node] += squared * math.sqrt(squared)
        radii[node] = math.sqrt(largest)
        if largest > 0:
            effective[node] /= largest * radii[node]
        else:
            effective[node] = stop - start


@njit(**_OPTIONS)
def node_moments(points, values, starts, stops, centroids, zeroth, first, second):
    """Per node and value column: Σ d, Σ d s and Σ d s sᵀ over its controls."""
    dim, columns = points.shape[1], values.shape[1]
    for node in prange(starts.shape[0]):
        for k in range(starts[node], stops[node]):
            for column in range(columns):
                value = values[k, column]
                zeroth[node, column] += value
                for a in range(dim):
                    sa = points[k, a] - centroids[node, a]
                    first[node, column, a] += value * sa
                    for b in range(dim):
                        sb = points[k, b] - centroids[node, b]
                        second[node, column, a, b] += value * sa * sb


@njit(**_OPTIONS)
def push_down(points, starts, stops, centroids, zeroth, first, second, out):
    """out[k] += C0 + C1·s_k + s_kᵀ C2 s_k for every control k of every node (the
    transposed far field: coefficients gathered per node, spread to its controls)."""
    dim, columns = points.shape[1], out.shape[1]
    for node in range(starts.shape[0]):
        for k in range(starts[node], stops[node]):
            for column in range(columns):
                total = zeroth[node, column]
                for a in range(dim):
                    sa = points[k, a] - centroids[node, a]
                    total += first[node, column, a] * sa
                    for b in range(dim):
                        total += (
                            second[node, column, a, b] * sa * (points[k, b] - centroids[node, b])
                        )
                out[k, column] += total
