"""The operator of the tree-approximated IDW (:mod:`torchmorph.idw.tree`): the kd-trees
of one pair of normalised clouds, their node geometry, and the forward and transposed
applications by the numba traversal (:mod:`torchmorph.idw.backends.numba._tree_jit`),
with the autograd function that ties them together. The error bound, the acceptance
rule and the tolerance's control are described in :mod:`torchmorph.idw.tree`."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchmorph._threads import numba_threads
from torchmorph.idw.backends._protocol import power_code
from torchmorph.idw.backends.numba import _kd_jit, _tree_jit, _tree_moments

__all__ = ["TARGET_BLOCK"]

TARGET_BLOCK = 64
"""Targets per block (a leaf of the target tree): a block shares one traversal. With
float32 leaf sums, 64 took 0.90× the time of 32 at 10^5 × 10^4 and at 10^6 × 10^5
(1e-4, one thread; ``benchmarks/tree.py``'s clouds); with float64 leaf sums 128 had
been 1.12× faster than 32 at 10^6 but slower at 10^5 and below."""

REFERENCE_REACH = 0.01
"""How far (times the controls' bounding-box diagonal) a block's reference distance is
searched for (see ``_TreeOperator._references``)."""


def _kd_tree(points: np.ndarray, leaf_size: int):
    """(order, starts, stops, children) of a kd-tree of median splits on the widest axis,
    nodes in depth-first preorder, each node the range ``order[start:stop]``
    (:func:`torchmorph.idw.backends.numba._kd_jit.kd_tree`: 1.9 s for the two trees of
    3·10^6 targets and 3·10^5 controls, where a loop over the nodes in Python with
    NumPy's ``argpartition`` took 8.4 s)."""
    count = points.shape[0]
    size = _kd_jit.max_nodes(count, leaf_size)
    order = np.arange(count, dtype=np.int64)
    starts = np.empty(size, np.int64)
    stops = np.empty(size, np.int64)
    children = np.empty((size, 2), np.int64)
    nodes = _kd_jit.kd_tree(
        np.ascontiguousarray(points, dtype=np.float64), leaf_size, order, starts, stops, children
    )
    return order, starts[:nodes].copy(), stops[:nodes].copy(), children[:nodes].copy()


class _TreeOperator:
    """The trees and geometry of one pair of normalised clouds (float64 numpy)."""

    def __init__(self, controls: np.ndarray, targets: np.ndarray, power, radius2, leaf_size):
        from scipy.spatial import cKDTree

        self.power, self.radius2 = float(power), float(radius2)
        self.mode = power_code(power)
        order, self.starts, self.stops, self.children = _kd_tree(controls, leaf_size)
        self.control_order = order
        self.controls = np.ascontiguousarray(controls[order])
        self.controls_t = np.ascontiguousarray(self.controls.T)
        self.max_leaf = int((self.stops - self.starts)[self.children[:, 0] < 0].max())
        nodes, dim = self.starts.shape[0], controls.shape[1]
        self.centroids = np.zeros((nodes, dim))
        self.radii = np.zeros(nodes)
        self.second = np.zeros((nodes, dim, dim))
        self.effective = np.zeros(nodes)
        _tree_moments.node_geometry(
            self.controls, self.starts, self.stops, self.centroids, self.radii, self.second,
            self.effective,
        )  # fmt: skip
        target_order, starts, _, children = _kd_tree(targets, TARGET_BLOCK)
        self.target_order = target_order
        self.target_rank = np.argsort(target_order)
        self.targets = np.ascontiguousarray(targets[target_order])
        leaves = np.sort(starts[children[:, 0] < 0]) if targets.shape[0] else starts[:0]
        self.block_starts = np.append(leaves, targets.shape[0]).astype(np.int64)
        self.all_blocks = np.arange(self.block_starts.shape[0] - 1)  # what a traversal visits
        self.references = self._references(cKDTree(self.controls))
        self._leaves: dict[type, tuple[np.ndarray, np.ndarray]] = {}

    def _leaf_arrays(self, dtype: type) -> tuple[np.ndarray, np.ndarray]:
        """(controls transposed, squared block references) in the dtype of the leaves'
        exact sums: float32 for float32 inputs (twice the vector lanes), else float64."""
        if dtype not in self._leaves:
            self._leaves[dtype] = (
                self.controls_t.astype(dtype, copy=False),
                (self.references**2).astype(dtype),
            )
        return self._leaves[dtype]

    def _references(self, searcher) -> np.ndarray:
        """Per block: a distance below its targets' nearest control, so that their weights
        (reference / d)^p stay <= 1 (the traversal's scale; any lower bound serves).

        The nearest control is searched within :data:`REFERENCE_REACH` of the controls'
        bounding-box diagonal only, and a block beyond takes that reach: a nearest
        neighbour search from deep inside a closed surface of controls visits nearly all
        of them (1.55 s for 31,250 block centres among 10^5 controls on a sphere, 26.6 s
        at 3·10^5: quadratic growth), the bounded search 0.03 s and 0.3 s."""
        blocks = self.block_starts.shape[0] - 1
        if blocks <= 0:
            return np.zeros(0)
        counts = np.diff(self.block_starts)
        centres = np.add.reduceat(self.targets, self.block_starts[:-1], axis=0)
        centres /= counts[:, None]
        spread = np.linalg.norm(self.targets - np.repeat(centres, counts, axis=0), axis=1)
        radius = np.maximum.reduceat(spread, self.block_starts[:-1])
        extent = self.controls.max(axis=0) - self.controls.min(axis=0)
        reach = REFERENCE_REACH * float(np.linalg.norm(extent))
        if reach > 0:
            nearest, _ = searcher.query(centres, k=1, distance_upper_bound=reach)
            nearest = np.minimum(nearest, reach)  # beyond the reach: the reach, a lower bound
        else:  # every control at one point: the exact search is cheap
            nearest, _ = searcher.query(centres, k=1)
        return np.maximum(nearest - radius, math.sqrt(self.radius2))

    def _run(self, values, scaled, eta, transpose, single, coincident=None, blocks=None):
        n_targets, n_controls = self.targets.shape[0], self.controls.shape[0]
        columns, dim = values.shape[1], self.controls.shape[1]
        nodes = self.starts.shape[0]
        with numba_threads():
            groups = _tree_jit.numba_threads()
            if transpose:
                node_zeroth = np.zeros((groups, nodes, columns))
                node_first = np.zeros((groups, nodes, columns, dim))
                node_second = np.zeros((groups, nodes, columns, dim, dim))
                out = np.zeros((groups, n_controls, columns))
            else:
                node_zeroth = np.zeros((groups, 0, columns))
                node_first = np.zeros((groups, 0, columns, dim))
                node_second = np.zeros((groups, 0, columns, dim, dim))
                out = np.zeros((groups, 0, columns))
            zeroth = np.zeros((nodes, columns))
            first = np.zeros((nodes, columns, dim))
            second = np.zeros((nodes, columns, dim, dim))
            if not transpose:
                _tree_moments.node_moments(
                    self.controls, values, self.starts, self.stops, self.centroids,
                    zeroth, first, second,
                )  # fmt: skip
            sums = np.zeros(n_targets)
            numerator = np.zeros((n_targets, columns))
            bounds = np.zeros(n_targets)
            if coincident is None:
                coincident = np.zeros(n_targets, np.int64)
            coincident_sum = np.zeros((n_targets, columns))
            dtype = np.float32 if single else np.float64
            controls_leaf, references = self._leaf_arrays(dtype)
            values_t = np.ascontiguousarray(values.T)
            _tree_jit.traverse(
                self.targets, self.block_starts, self.references, self.controls_t,
                values_t,
                scaled, self.children, self.starts, self.stops, self.centroids, self.radii,
                self.second, self.effective, zeroth, first, second, self.power, self.mode,
                float(eta),
                self.radius2, transpose, groups, sums, numerator, bounds, coincident,
                coincident_sum, node_zeroth, node_first, node_second, out, self.max_leaf,
                references, controls_leaf, values_t.astype(dtype, copy=False),
                self.all_blocks if blocks is None else blocks,
            )  # fmt: skip
            if transpose:
                total = out.sum(axis=0)
                _tree_moments.push_down(
                    self.controls, self.starts, self.stops, self.centroids,
                    node_zeroth.sum(axis=0), node_first.sum(axis=0), node_second.sum(axis=0),
                    total,
                )  # fmt: skip
                return total
        return sums, numerator, bounds, coincident, coincident_sum

    def apply(self, values: np.ndarray, eta: float, single: bool = False, blocks=None):
        """(u' in the targets' tree order, S', the per-target bound E / (S' - E) on
        ``|u' - u| / Δ``, the coincident counts); ``values`` (N_c, K) in control order;
        ``single``: the leaves' exact sums in float32; ``blocks``: the indices of the
        target blocks to traverse (default all; the others' rows are left at zero, their
        results the same to the bit as in a whole traversal)."""
        values = np.ascontiguousarray(values[self.control_order])
        empty = np.zeros((self.targets.shape[0], values.shape[1]))
        sums, numerator, bounds, coincident, coincident_sum = self._run(
            values, empty, eta, False, single, blocks=blocks
        )
        result = numerator / np.where(sums > 0, sums, 1.0)[:, None]
        hit = coincident > 0
        result[hit] = coincident_sum[hit] / coincident[hit, None]
        margin = sums - bounds
        relative = np.where(margin > 0, bounds / np.where(margin > 0, margin, 1.0), np.inf)
        relative[hit] = 0.0
        return result, sums, relative, coincident

    def apply_transposed(
        self, grad: np.ndarray, eta: float, sums, coincident, single: bool = False
    ) -> np.ndarray:
        """Aᵀ grad for ``grad`` (N_t, K) in the targets' tree order; (N_c, K), control order
        (``single`` as the forward call's)."""
        hit = coincident > 0
        scale = np.where(hit, 1.0 / np.maximum(coincident, 1), 1.0 / np.where(sums > 0, sums, 1))
        scaled = np.ascontiguousarray(grad * scale[:, None])
        values = np.zeros((self.controls.shape[0], grad.shape[1]))
        total = self._run(values, scaled, eta, True, single, coincident.copy())
        out = np.empty_like(total)
        out[self.control_order] = total
        return out


class _TreeApply(torch.autograd.Function):
    """u = A d for the operator fixed by the forward pass; backward: Aᵀ grad."""

    @staticmethod
    def forward(ctx, values: Tensor, operator: _TreeOperator, eta: float, state: dict):
        single = values.dtype == torch.float32
        result, sums, relative, coincident = operator.apply(
            values.detach().double().numpy(), eta, single
        )
        state["sums"], state["coincident"], state["relative"] = sums, coincident, relative
        ctx.operator, ctx.eta, ctx.state, ctx.single = operator, eta, state, single
        out = torch.from_numpy(result)
        return out.to(values.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):
        state = ctx.state
        total = ctx.operator.apply_transposed(
            grad.detach().double().numpy(), ctx.eta, state["sums"], state["coincident"], ctx.single
        )
        return torch.from_numpy(total).to(grad.dtype), None, None, None
