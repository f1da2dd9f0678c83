"""A treecode for the thin-plate spline's kernel sums ``u_i = Σ_j φ(ε|x_i − y_j|) w_j``
over many targets and sources: the barycentric Lagrange treecode (Wang, Krasny and
Tlupova, *A kernel-independent treecode based on barycentric Lagrange interpolation*,
Commun. Comput. Phys. 28, 2020), on the CPU (numba, in parallel over target blocks).

The sources are split by a kd-tree (the widest side of each node's box halved, leaves
of :data:`LEAF_SIZE`) and the targets the same way into blocks (leaves of
:data:`TARGET_BLOCK`). A source
node C of half-diagonal r_C seen from a block (centre c, half-diagonal r) at a distance
R under the opening angle θ, r_C < θ (R − r), acts on the block's targets through
proxies: the tensor grid of Chebyshev points of the second kind on its bounding box,
with the proxy charges

    q_k = Σ_{j ∈ C} L_k(y_j) w_j

(L_k the tensor-product Lagrange basis), so that Σ_{j ∈ C} φ(|x − y_j|) w_j ≈
Σ_k φ(|x − t_k|) q_k: the interpolation of φ(|x − ·|) in the source variable, whose
error falls with the degree n as ρ^-n, ρ ≈ 2/θ for a kernel analytic away from x. An
axis along which the box is thin takes a lower degree (the smallest that keeps the
error of that axis's factor, (θ h_a / r_C)^(n_a+1), below θ^(n+1)); a flat axis one
point. A node with no more sources than proxies, and a leaf seen too closely, is summed
directly. The charges are made for every call (they carry the values); the lists and
the proxies once per pair of point sets.

The approximation is linear in w: :meth:`TreeCode.apply_transposed` is its exact
transpose (the same lists, the charges' basis applied backwards), so gradients through
:func:`tree_sum` are those of the approximate operator, to rounding.

The error is relative to the size of the terms, not of the sum: thin-plate sums of
coefficients with vanishing moments (an interpolant's) cancel, and their relative error
is larger than the terms'. On the wing in a box of walls of ``benchmarks/rbf_scale.py``
(3·10^4 controls, the global fit's coefficients, targets in the volume) degree 8 at
θ = 0.35 gave 5e-5 of the sum, degree 10 2e-7.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchmorph._threads import numba_threads
from torchmorph.rbf import _treecode_jit

__all__ = ["DEFAULT_THETA", "LEAF_SIZE", "TARGET_BLOCK", "TreeCode", "axis_degrees", "tree_sum"]

DEFAULT_THETA = 0.35
"""The opening angle θ: a node acts through its proxies when its half-diagonal is below
θ times its distance from the block (less the block's half-diagonal)."""

LEAF_SIZE = 32
"""Most sources in a leaf of the source tree."""

TARGET_BLOCK = 64
"""Most targets in a block (a leaf of the target tree): a block shares one traversal
and one list of far proxies and near sources."""


def axis_degrees(low: np.ndarray, high: np.ndarray, degree: int, theta: float) -> np.ndarray:
    """Per node and axis, the interpolation degree on the box [low, high] (K, 3): ``degree``
    on the longest axes, 0 on a flat one, and in between the smallest n_a with
    (θ h_a / r)^(n_a + 1) <= θ^(degree + 1), h_a the half-width and r the half-diagonal."""
    half = (high - low) / 2
    radius = np.linalg.norm(half, axis=1, keepdims=True)
    safe = np.where(radius > 0, radius, 1.0)
    ratio = theta * half / safe
    with np.errstate(divide="ignore", invalid="ignore"):
        needed = np.ceil((degree + 1) * math.log(theta) / np.log(ratio)) - 1
    needed = np.where(ratio >= theta * (1 - 1e-12), degree, needed)
    needed = np.where(half <= 1e-12 * safe, 0, needed)
    return np.clip(needed, 0, degree).astype(np.int64)


def _boxes(points: np.ndarray, starts, stops, children) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box of each node (points in tree order; nodes in preorder, so the
    children follow their parent: a reverse pass combines them)."""
    nodes = starts.shape[0]
    low = np.empty((nodes, 3))
    high = np.empty((nodes, 3))
    leaves = np.flatnonzero(children[:, 0] < 0)
    if points.shape[0]:
        ordered = leaves[np.argsort(starts[leaves])]
        low[ordered] = np.minimum.reduceat(points, starts[ordered], axis=0)
        high[ordered] = np.maximum.reduceat(points, starts[ordered], axis=0)
    for node in range(nodes - 1, -1, -1):
        left, right = children[node]
        if left >= 0:
            low[node] = np.minimum(low[left], low[right])
            high[node] = np.maximum(high[left], high[right])
    return low, high


def _midpoint_tree(points: np.ndarray, leaf_size: int):
    """(order, starts, stops, children) of :func:`~torchmorph.rbf._treecode_jit.midpoint_tree`."""
    count = points.shape[0]
    size = max(2 * count - 1, 1)
    order = np.arange(count, dtype=np.int64)
    starts = np.empty(size, np.int64)
    stops = np.empty(size, np.int64)
    children = np.empty((size, 2), np.int64)
    nodes = _treecode_jit.midpoint_tree(
        np.ascontiguousarray(points, dtype=np.float64), leaf_size, order, starts, stops, children
    )
    return order, starts[:nodes].copy(), stops[:nodes].copy(), children[:nodes].copy()


def _padded(points: np.ndarray) -> np.ndarray:
    """Points as (N, 3) float64 (a zero third coordinate in 2-D)."""
    out = np.zeros((points.shape[0], 3))
    out[:, : points.shape[1]] = points
    return out


class TreeCode:
    """The lists, proxies and orderings of one pair of point sets (float64 NumPy, (N, D),
    D = 2 or 3) for :meth:`apply` (targets × sources) and :meth:`apply_transposed`.

    Parameters
    ----------
    sources, targets : numpy.ndarray, shape (N_s, D) and (N_t, D)
    scale : float
        The kernel's distance scale ε: φ(ε r) with φ(r) = r² log r.
    degree : int
        The interpolation degree per axis (the longest axes of a node's box).
    theta : float
        The opening angle (:data:`DEFAULT_THETA`).

    Attributes
    ----------
    pairs : int
        Kernel evaluations per value column of one :meth:`apply` (against N_t N_s for
        the exact sum).
    """

    def __init__(
        self,
        sources: np.ndarray,
        targets: np.ndarray,
        scale: float,
        degree: int,
        theta: float = DEFAULT_THETA,
    ) -> None:
        self.scale2, self.degree, self.theta = float(scale) ** 2, int(degree), float(theta)
        self.num_sources, self.num_targets = sources.shape[0], targets.shape[0]
        order, starts, stops, children = _midpoint_tree(sources, LEAF_SIZE)
        self.source_order, self.starts, self.stops = order, starts, stops
        self.sources = _padded(sources[order])
        low, high = _boxes(self.sources, starts, stops, children)
        centres, radii = (low + high) / 2, np.linalg.norm(high - low, axis=1) / 2
        self.degrees = axis_degrees(low, high, self.degree, self.theta)
        counts = np.prod(self.degrees + 1, axis=1)
        expanded = (stops - starts) > counts
        self.expanded_nodes = np.flatnonzero(expanded)
        self.proxy_offsets = np.zeros(starts.shape[0] + 1, np.int64)
        self.proxy_offsets[1:] = np.cumsum(np.where(expanded, counts, 0))
        self.axis_nodes = np.zeros((starts.shape[0], 3, self.degree + 1))
        for node in self.expanded_nodes:
            for axis in range(3):
                used = self.degrees[node, axis]
                half = (high[node, axis] - low[node, axis]) / 2
                points = (
                    centres[node, axis] + half * np.cos(np.pi * np.arange(used + 1) / used)
                    if used
                    else centres[node, axis : axis + 1]
                )
                self.axis_nodes[node, axis, : used + 1] = points
        self.proxies = np.empty((int(self.proxy_offsets[-1]), 3))
        for node in self.expanded_nodes:
            grids = [self.axis_nodes[node, a, : self.degrees[node, a] + 1] for a in range(3)]
            mesh = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 3)
            self.proxies[self.proxy_offsets[node] : self.proxy_offsets[node + 1]] = mesh
        depth = np.zeros(starts.shape[0], np.int64)
        for parent in range(starts.shape[0]):  # preorder: a parent before its children
            if children[parent, 0] >= 0:
                depth[children[parent]] = depth[parent] + 1
        by_depth = self.expanded_nodes[np.argsort(depth[self.expanded_nodes], kind="stable")]
        self.levels = by_depth
        self.level_offsets = np.searchsorted(
            depth[by_depth], np.arange(int(depth.max(initial=0)) + 2)
        ).astype(np.int64)
        target_order, target_starts, _, target_children = _midpoint_tree(targets, TARGET_BLOCK)
        self.target_order = target_order
        self.targets = _padded(targets[target_order])
        leaves = np.sort(target_starts[target_children[:, 0] < 0])
        self.block_starts = np.append(leaves[: len(leaves) if targets.shape[0] else 0],
                                      targets.shape[0]).astype(np.int64)  # fmt: skip
        block_low, block_high = self._block_boxes()
        block_centres = (block_low + block_high) / 2
        block_radii = np.linalg.norm(block_high - block_low, axis=1) / 2
        self.far_offsets, self.far, self.near_offsets, self.near = _treecode_jit.interaction_lists(
            block_centres, block_radii, centres, radii, children, expanded, self.theta
        )
        sizes = np.diff(self.block_starts)
        far_counts = np.diff(self.proxy_offsets)[self.far]
        near_counts = (stops - starts)[self.near]
        self.pairs = int(
            (np.repeat(sizes, np.diff(self.far_offsets)) * far_counts).sum()
            + (np.repeat(sizes, np.diff(self.near_offsets)) * near_counts).sum()
        )

    def _block_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        if self.num_targets == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        first = self.block_starts[:-1]
        return (
            np.minimum.reduceat(self.targets, first, axis=0),
            np.maximum.reduceat(self.targets, first, axis=0),
        )

    def apply(self, values: np.ndarray, threads: int | None = None) -> np.ndarray:
        """``Σ_j φ(ε|x_i − y_j|) values_j`` at every target, approximated: (N_t, S) for
        ``values`` (N_s, S), both in the callers' order."""
        values_t = np.ascontiguousarray(values[self.source_order].T)
        columns = values_t.shape[0]
        out = np.empty((self.num_targets, columns))
        with numba_threads(threads):
            charges_t = np.zeros((columns, self.proxies.shape[0]))
            _treecode_jit.charges(
                self.sources, values_t, self.starts, self.stops, self.expanded_nodes,
                self.axis_nodes, self.degrees, self.proxy_offsets, charges_t,
            )  # fmt: skip
            _treecode_jit.block_sums(
                self.targets, self.block_starts, self.far_offsets, self.far,
                self.near_offsets, self.near, self.proxy_offsets, self.proxies, charges_t,
                self.starts, self.stops, self.sources, values_t, self.scale2, out,
            )  # fmt: skip
        result = np.empty_like(out)
        result[self.target_order] = out
        return result

    def apply_transposed(self, grads: np.ndarray, threads: int | None = None) -> np.ndarray:
        """The exact transpose of :meth:`apply`: (N_s, S) for ``grads`` (N_t, S)."""
        grads_t = np.ascontiguousarray(grads[self.target_order].T)
        columns = grads_t.shape[0]
        with numba_threads(threads):
            import numba

            groups = max(1, min(numba.get_num_threads(), self.block_starts.shape[0] - 1))
            potentials = np.zeros((groups, columns, self.proxies.shape[0]))
            near = np.zeros((groups, columns, self.num_sources))
            _treecode_jit.block_sums_transposed(
                self.targets, self.block_starts, self.far_offsets, self.far,
                self.near_offsets, self.near, self.proxy_offsets, self.proxies, self.starts,
                self.stops, self.sources, grads_t, self.scale2, groups, potentials, near,
            )  # fmt: skip
            out_t = near.sum(axis=0)
            _treecode_jit.charges_transposed(
                self.sources, potentials.sum(axis=0), self.starts, self.stops, self.levels,
                self.level_offsets, self.axis_nodes, self.degrees, self.proxy_offsets, out_t,
            )  # fmt: skip
        result = np.empty((self.num_sources, columns))
        result[self.source_order] = out_t.T
        return result


class _TreeSum(torch.autograd.Function):
    """``TreeCode.apply`` on a float64 CPU tensor; backward: the transpose."""

    @staticmethod
    def forward(ctx, values: Tensor, tree: TreeCode, threads: int | None):  # type: ignore[override]
        ctx.tree, ctx.threads = tree, threads
        return torch.from_numpy(tree.apply(values.detach().numpy(), threads))

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        transposed = ctx.tree.apply_transposed(grad.detach().contiguous().numpy(), ctx.threads)
        return torch.from_numpy(transposed), None, None


def tree_sum(tree: TreeCode, values: Tensor, threads: int | None = None) -> Tensor:
    """:meth:`TreeCode.apply` of ``values`` (N_s, S), a float64 CPU tensor, differentiable
    in the values (the backward pass is the approximation's exact transpose)."""
    return _TreeSum.apply(values, tree, threads)
