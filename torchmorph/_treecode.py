"""A treecode for kernel sums ``u_i = Σ_j K(|x_i − y_j|) w_j`` over many targets and
sources, K the thin-plate spline's ``φ(ε r)`` (the RBF's global fit,
:mod:`torchmorph.rbf.refine`) or IDW's weight ``r^-p`` (:mod:`torchmorph.idw.treecode`):
barycentric Lagrange interpolation on both sides with a
dual tree traversal (Wang, Krasny and Tlupova, *A kernel-independent treecode based on
barycentric Lagrange interpolation*, Commun. Comput. Phys. 28, 2020; Wilson, Vaughn and
Krasny, Comput. Phys. Commun. 265, 2021), on the CPU (numba, in parallel).

Sources and targets are split by kd-trees (the widest side of each node's box halved;
leaves of :data:`LEAF_SIZE` sources, blocks of :data:`TARGET_BLOCK` targets). A node
with more points than proxies has an expansion: the tensor grid of Chebyshev points of
the second kind on its bounding box. For a source node C the proxy charges

    q_k = Σ_{j ∈ C} L_k(y_j) w_j

(L_k the tensor-product Lagrange basis) give Σ_{j ∈ C} K(|x − y_j|) w_j ≈
Σ_k K(|x − t_k|) q_k, the interpolation of K(|x − ·|) in the source variable; for a
target node T the sums at its proxies, interpolated, give them at its targets. A pair
of nodes whose balls are well separated under the opening angle θ, r_T + r_C < θ R,
interacts through the proxies of each side that has them; a pair too close opens its
larger node, and two leaves interact directly. A target node's proxy sums are passed
down to the expanded nodes below it (interpolated at their proxies) and end at the
targets. The kernel is analytic away from its centre, so the error of degree n falls as
ρ^-n (ρ the Bernstein ellipse's parameter, about 2/θ); an axis along which a box is thin
takes the lower degree that matches it (:func:`axis_degrees`), a flat one one point.
The charges are made for every call (they carry the values); trees, lists and proxies
once per pair of point sets.

The approximation is linear in w: :meth:`TreeCode.apply_transposed` is its exact
transpose (the same lists, each interpolation applied backwards), so gradients through
:func:`tree_sum` are those of the approximate operator, to rounding.

The error is relative to the size of the terms, not of the sum: thin-plate sums of an
interpolant's coefficients (vanishing moments) cancel, and their relative error is
larger than the terms'. Measured on the sums of the global fit's coefficients (see
:data:`DEFAULT_THETA`): 7.1e-5 of the sum at degree 6, 8.0e-7 at degree 8.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchmorph import _treecode_jit
from torchmorph._threads import numba_threads

__all__ = ["DEFAULT_THETA", "LEAF_SIZE", "TARGET_BLOCK", "TreeCode", "axis_degrees", "tree_sum"]

DEFAULT_THETA = 0.7
"""The opening angle θ: two nodes act through their proxies when the sum of their
half-diagonals is below θ times the distance between their centres. On the wing in a box
of ``benchmarks/rbf_scale.py`` (10^5 controls, 10^6 targets, the global fit's
coefficients, one call on two threads): θ = 0.6 took 5.5 s at degree 6 (5.2e-5 of the
sum) and 10.3 s at degree 8 (2.7e-7); θ = 0.7 3.4 s (7.1e-5) and 7.2 s (8.0e-7)."""

LEAF_SIZE = 32
"""Most sources in a leaf of the source tree."""

TARGET_BLOCK = 64
"""Most targets in a block (a leaf of the target tree): a block's targets share one list
of far proxies and near sources."""


def axis_degrees(low: np.ndarray, high: np.ndarray, degree: int, theta: float) -> np.ndarray:
    """Per node and axis, the interpolation degree on the box [low, high] (K, 3): ``degree``
    on the longest axis, 0 on a flat one, and on a shorter axis the smallest n_a whose
    error matches the longest axis's. The kernel seen from a box interacting under θ is
    analytic in a Bernstein ellipse of parameter ρ(x) = x + √(x² + 1), x = (r / θ) / h,
    about an axis of half-width h (r the box's half-diagonal, r / θ the least distance
    of the other side): the error of degree n falls as ρ^-n (Trefethen, *Approximation
    Theory and Approximation Practice*, Thm. 8.2), so n_a + 1 >= (n + 1) log ρ_max /
    log ρ_a. (A rule on θ h_a / r instead, (θ h_a / r)^(n_a + 1) <= θ^(n + 1), gave thin
    axes too few points: 2e-2 of the sum where the full degrees gave 2e-8.)"""
    half = (high - low) / 2
    radius = np.linalg.norm(half, axis=1, keepdims=True)
    longest = half.max(axis=1, keepdims=True)
    safe = np.where(half > 0, half, 1.0)
    reach = radius / theta

    def rho(width):
        ratio = reach / np.where(width > 0, width, 1.0)
        return ratio + np.sqrt(ratio * ratio + 1)

    with np.errstate(divide="ignore", invalid="ignore"):
        needed = np.ceil((degree + 1) * np.log(rho(longest)) / np.log(rho(safe)) - 1e-9) - 1
    needed = np.where(half >= longest * (1 - 1e-12), degree, needed)
    needed = np.where(half <= 1e-12 * np.where(radius > 0, radius, 1.0), 0, needed)
    return np.clip(needed, 0, degree).astype(np.int64)


def _boxes(points: np.ndarray, starts, stops, children) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box of each node (points in tree order; nodes in preorder, so the
    children follow their parent: a reverse pass combines them)."""
    nodes = starts.shape[0]
    low = np.zeros((nodes, 3))  # an empty set's one node: a point at the origin
    high = np.zeros((nodes, 3))
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
    """(order, starts, stops, children) of :func:`~torchmorph._treecode_jit.midpoint_tree`."""
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


class _Chains(NamedTuple):
    """:meth:`_Tree.chains`: the shifts between expanded nodes (down: ``down_levels`` by
    depth, each from ``shift_parents``; up: ``up_levels`` by depth, each gathering
    ``child_nodes[child_offsets[k]:child_offsets[k + 1]]``) and the owners of the
    points."""

    shift_parents: np.ndarray
    down_levels: np.ndarray
    down_offsets: np.ndarray
    up_levels: np.ndarray
    up_offsets: np.ndarray
    child_offsets: np.ndarray
    child_nodes: np.ndarray
    owners: np.ndarray
    own_offsets: np.ndarray
    own_starts: np.ndarray
    own_stops: np.ndarray


class _Tree:
    """One side's kd-tree (:func:`_midpoint_tree`, points in tree order, padded to 3-D):
    node boxes, balls, depths, per-axis degrees, which nodes have an expansion (more
    points than proxies) and their Chebyshev grids (``axis_nodes`` (K, 3, n + 1),
    proxies in ``proxies[proxy_offsets[k]:proxy_offsets[k + 1]]``, the last axis
    fastest)."""

    def __init__(self, points: np.ndarray, leaf_size: int, degree: int, theta: float) -> None:
        order, starts, stops, children = _midpoint_tree(points, leaf_size)
        self.order, self.starts, self.stops, self.children = order, starts, stops, children
        self.points = _padded(points[order])
        nodes = starts.shape[0]
        low, high = _boxes(self.points, starts, stops, children)
        self.centres, self.radii = (low + high) / 2, np.linalg.norm(high - low, axis=1) / 2
        self.degrees = axis_degrees(low, high, degree, theta)
        counts = np.prod(self.degrees + 1, axis=1)
        self.expanded = (stops - starts) > counts
        self.expanded_nodes = np.flatnonzero(self.expanded)
        self.proxy_offsets = np.zeros(nodes + 1, np.int64)
        self.proxy_offsets[1:] = np.cumsum(np.where(self.expanded, counts, 0))
        self.axis_nodes = np.zeros((nodes, 3, degree + 1))
        self.proxies = np.empty((int(self.proxy_offsets[-1]), 3))
        for node in self.expanded_nodes:
            for axis in range(3):
                used = self.degrees[node, axis]
                half = (high[node, axis] - low[node, axis]) / 2
                self.axis_nodes[node, axis, : used + 1] = (
                    self.centres[node, axis] + half * np.cos(np.pi * np.arange(used + 1) / used)
                    if used
                    else self.centres[node, axis]
                )
            grids = [self.axis_nodes[node, a, : self.degrees[node, a] + 1] for a in range(3)]
            mesh = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 3)
            self.proxies[self.proxy_offsets[node] : self.proxy_offsets[node + 1]] = mesh
        self.parents = np.full(nodes, -1, np.int64)
        self.depth = np.zeros(nodes, np.int64)
        for parent in range(nodes):  # preorder: a parent before its children
            if children[parent, 0] >= 0:
                self.parents[children[parent]] = parent
                self.depth[children[parent]] = self.depth[parent] + 1
        leaves = np.flatnonzero(children[:, 0] < 0)
        self.leaves = leaves[np.argsort(starts[leaves])] if points.shape[0] else leaves[:0]

    def chains(self, taking: np.ndarray) -> _Chains:
        """How proxy values pass between the expanded nodes: a node takes those of its
        nearest expanded ancestor (``shift_parents``, -1 for none) when some node on that
        chain is in ``taking``; each leaf's points belong to their lowest expanded node
        (``owners``, CSR ``own_offsets`` into the point ranges ``own_starts:own_stops``)
        when it carries anything."""
        nodes = self.starts.shape[0]
        carries = np.zeros(nodes, bool)
        carries[taking] = True
        nearest = np.full(nodes, -1, np.int64)  # the lowest expanded node at or above
        shift_parents = np.full(nodes, -1, np.int64)
        for node in range(nodes):  # preorder
            parent = self.parents[node]
            above = nearest[parent] if parent >= 0 else -1
            if self.expanded[node]:
                if above >= 0 and carries[above]:
                    shift_parents[node] = above
                    carries[node] = True
                nearest[node] = node
            else:
                nearest[node] = above
        shifted = np.flatnonzero(shift_parents >= 0)
        down_levels, down_offsets = self.by_depth(shifted)
        up_levels, up_offsets = self.by_depth(np.unique(shift_parents[shifted]))
        position = np.full(nodes, -1, np.int64)
        position[up_levels] = np.arange(up_levels.shape[0])
        child_offsets, child_nodes = _csr(
            position[shift_parents[shifted]], shifted, up_levels.shape[0]
        )
        leaves = self.leaves
        owners = nearest[leaves]
        used = (owners >= 0) & carries[np.maximum(owners, 0)]
        owner_nodes, firsts = np.unique(owners[used], return_inverse=True)
        own_offsets, spans = _csr(firsts, np.flatnonzero(used), owner_nodes.shape[0])
        return _Chains(
            shift_parents, down_levels, down_offsets, up_levels, up_offsets, child_offsets,
            child_nodes, owner_nodes, own_offsets, self.starts[leaves[spans]],
            self.stops[leaves[spans]],
        )  # fmt: skip

    def by_depth(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``nodes`` sorted by depth, with the CSR offsets of each depth."""
        ordered = nodes[np.argsort(self.depth[nodes], kind="stable")]
        offsets = np.searchsorted(self.depth[ordered], np.arange(int(self.depth.max()) + 2))
        return ordered, offsets.astype(np.int64)

    def leaves_under(self, nodes: np.ndarray, leaf_starts: np.ndarray):
        """Per node, the range of positions in ``leaf_starts`` (the sorted starts of the
        leaves) of the leaves under it."""
        return (
            np.searchsorted(leaf_starts, self.starts[nodes]),
            np.searchsorted(leaf_starts, self.stops[nodes]),
        )


def _csr(groups: np.ndarray, items: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (count + 1,), items ordered by group), stable within a group."""
    order = np.argsort(groups, kind="stable")
    offsets = np.zeros(count + 1, np.int64)
    offsets[1:] = np.cumsum(np.bincount(groups, minlength=count))
    return offsets, items[order]


def _expand(nodes, items, first, last) -> tuple[np.ndarray, np.ndarray]:
    """Each (node, item) pair repeated for the positions ``first[k]:last[k]``: (positions,
    items)."""
    counts = last - first
    positions = np.repeat(first - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
    return positions, np.repeat(items, counts)


class TreeCode:
    """The trees, lists and proxies of one pair of point sets (float64 NumPy, (N, D),
    D = 2 or 3) for :meth:`apply` (targets × sources) and :meth:`apply_transposed`.

    Both sides have trees and expansions; :func:`~torchmorph._treecode_jit.dual_lists`
    pairs their nodes. A pair whose target node has an expansion adds to its proxy
    potentials (from the source node's proxies or sources); those are shifted down to the
    expanded nodes below it (interpolated at their proxies) and finally interpolated at
    the targets of each target's lowest expanded node. Every other pair adds to the
    targets directly. Target proxies and targets are one set of rows, each row in one
    group (a leaf block's targets, or a node's proxies) with its lists of source nodes:
    far (through their proxies) and near (their sources).

    Parameters
    ----------
    sources, targets : numpy.ndarray, shape (N_s, D) and (N_t, D)
    scale : float
        The kernel's distance scale ε: φ(ε r) with φ(r) = r² log r (thin-plate; with a
        ``power`` the weights are (ε r)^-p).
    degree : int
        The interpolation degree per axis (the longest axes of a node's box).
    theta : float
        The opening angle (:data:`DEFAULT_THETA`).
    power : float, optional
        ``K(r) = r^-power`` (> 0) instead of the thin-plate spline.
    floor : float
        With a ``power``: squared (scaled) distances below it are raised to it, so that a
        target on a source has a finite (meaningless) sum; its caller replaces it.

    Attributes
    ----------
    pairs : int
        Kernel evaluations per value column of one :meth:`apply` (against N_t N_s for
        the exact sum), the proxies' included.
    """

    def __init__(
        self,
        sources: np.ndarray,
        targets: np.ndarray,
        scale: float,
        degree: int,
        theta: float = DEFAULT_THETA,
        *,
        power: float | None = None,
        floor: float = 0.0,
    ) -> None:
        self.scale2, self.degree, self.theta = float(scale) ** 2, int(degree), float(theta)
        self.power, self.floor = (0.0 if power is None else float(power)), float(floor)
        self.num_sources, self.num_targets = sources.shape[0], targets.shape[0]
        source = self.source = _Tree(sources, LEAF_SIZE, self.degree, self.theta)
        target = self.target = _Tree(targets, TARGET_BLOCK, self.degree, self.theta)
        self.source_chains = source.chains(source.expanded_nodes)  # the charges pass up
        kinds, nodes, others = _treecode_jit.dual_lists(
            target.centres, target.radii, target.children, target.expanded, source.centres,
            source.radii, source.children, source.expanded, self.theta,
        )  # fmt: skip
        self.rows = np.concatenate([target.points, target.proxies])
        self._groups(kinds, nodes, others)
        self.target_chains = target.chains(nodes[kinds <= _treecode_jit.PROXIES_FROM_SOURCES])
        sizes = self.group_stops - self.group_starts
        far = np.diff(source.proxy_offsets)[self.far]
        near = (source.stops - source.starts)[self.near]
        self.pairs = int(
            (np.repeat(sizes, np.diff(self.far_offsets)) * far).sum()
            + (np.repeat(sizes, np.diff(self.near_offsets)) * near).sum()
        )

    def _groups(self, kinds, nodes, others) -> None:
        """The groups of rows and their far and near lists: first the leaf blocks (each
        with the pairs of every node above it whose targets take them), then the target
        nodes whose proxies take pairs."""
        target, jit = self.target, _treecode_jit
        leaves = target.leaves
        leaf_starts = target.starts[leaves]
        blocks = leaves.shape[0]
        direct = kinds >= jit.TARGETS_FROM_PROXIES
        first, last = target.leaves_under(nodes[direct], leaf_starts)
        positions, items = _expand(nodes[direct], others[direct], first, last)
        far_kind = np.repeat(kinds[direct] == jit.TARGETS_FROM_PROXIES, last - first)
        taking = np.unique(nodes[~direct])
        slot = np.full(target.starts.shape[0], -1, np.int64)
        slot[taking] = blocks + np.arange(taking.shape[0])
        groups_far = np.concatenate(
            [positions[far_kind], slot[nodes[kinds == jit.PROXIES_FROM_PROXIES]]]
        )
        items_far = np.concatenate([items[far_kind], others[kinds == jit.PROXIES_FROM_PROXIES]])
        groups_near = np.concatenate(
            [positions[~far_kind], slot[nodes[kinds == jit.PROXIES_FROM_SOURCES]]]
        )
        items_near = np.concatenate([items[~far_kind], others[kinds == jit.PROXIES_FROM_SOURCES]])
        count = blocks + taking.shape[0]
        base = self.num_targets
        starts = np.concatenate([leaf_starts, base + target.proxy_offsets[taking]])
        stops = np.concatenate([target.stops[leaves], base + target.proxy_offsets[taking + 1]])
        # the groups in a fixed shuffled order: numba's parallel loops hand each thread a
        # contiguous range of iterations (its chunk size setting had no effect on the OpenMP
        # layer, measured), so that ranges of cheap leaf blocks and of costly proxy groups
        # left one thread idle (1.98 s where the two kinds apart took 1.47 s on 2 threads)
        order = np.random.default_rng(0).permutation(count)
        rank = np.empty(count, np.int64)
        rank[order] = np.arange(count)
        self.far_offsets, self.far = _csr(rank[groups_far], items_far, count)
        self.near_offsets, self.near = _csr(rank[groups_near], items_near, count)
        self.group_starts = starts[order].astype(np.int64)
        self.group_stops = stops[order].astype(np.int64)

    def apply(self, values: np.ndarray, threads: int | None = None) -> np.ndarray:
        """``Σ_j K(|x_i − y_j|) values_j`` at every target, approximated: (N_t, S) for
        ``values`` (N_s, S), both in the callers' order."""
        source, target = self.source, self.target
        values_t = np.ascontiguousarray(values[source.order].T)
        columns = values_t.shape[0]
        # the proxy rows of nodes that take no pair (they only carry) must start at 0
        out = np.zeros((self.rows.shape[0], columns))
        with numba_threads(threads):
            charges_t = np.zeros((columns, source.proxies.shape[0]))
            _interpolate(source, self.source_chains, charges_t, values_t.T, transpose=True)
            _shift(source, self.source_chains, charges_t, up=True)
            _treecode_jit.group_sums(
                self.rows, self.group_starts, self.group_stops, self.far_offsets, self.far,
                self.near_offsets, self.near, source.proxy_offsets, source.proxies, charges_t,
                source.starts, source.stops, source.points, values_t, self.scale2, self.power,
                self.floor, out,
            )  # fmt: skip
            potentials_t = np.ascontiguousarray(out[self.num_targets :].T)
            _shift(target, self.target_chains, potentials_t, up=False)
            result = out[: self.num_targets]
            _interpolate(target, self.target_chains, potentials_t, result, transpose=False)
        unsorted = np.empty_like(result)
        unsorted[target.order] = result
        return unsorted

    def apply_transposed(self, grads: np.ndarray, threads: int | None = None) -> np.ndarray:
        """The exact transpose of :meth:`apply`: (N_s, S) for ``grads`` (N_t, S)."""
        source, target = self.source, self.target
        columns = grads.shape[1]
        grads_t = np.zeros((columns, self.rows.shape[0]))
        grads_t[:, : self.num_targets] = grads[target.order].T
        with numba_threads(threads):
            import numba

            potentials_t = np.zeros((columns, target.proxies.shape[0]))
            _interpolate(target, self.target_chains, potentials_t, grads_t.T, transpose=True)
            _shift(target, self.target_chains, potentials_t, up=True)
            grads_t[:, self.num_targets :] = potentials_t
            parts = max(1, min(numba.get_num_threads(), self.group_starts.shape[0]))
            charges = np.zeros((parts, columns, source.proxies.shape[0]))
            near = np.zeros((parts, columns, self.num_sources))
            _treecode_jit.group_sums_transposed(
                self.rows, self.group_starts, self.group_stops, self.far_offsets, self.far,
                self.near_offsets, self.near, source.proxy_offsets, source.proxies,
                source.starts, source.stops, source.points, grads_t, self.scale2, self.power,
                self.floor, parts, charges, near,
            )  # fmt: skip
            charges_t = np.ascontiguousarray(charges.sum(axis=0))
            _shift(source, self.source_chains, charges_t, up=False)
            out = np.ascontiguousarray(near.sum(axis=0).T)
            _interpolate(source, self.source_chains, charges_t, out, transpose=False)
        result = np.empty((self.num_sources, columns))
        result[source.order] = out
        return result


def _shift(tree: _Tree, chains: _Chains, values_t: np.ndarray, up: bool) -> None:
    """Proxy values along the chains, in place: up (each node gathers those of the nodes
    below it, interpolated at its proxies' basis) or down (the transpose)."""
    if up:
        _treecode_jit.shift_up(
            chains.up_levels, chains.up_offsets, chains.child_offsets, chains.child_nodes,
            tree.axis_nodes, tree.degrees, tree.proxy_offsets, values_t,
        )  # fmt: skip
    else:
        _treecode_jit.shift_down(
            chains.down_levels, chains.down_offsets, chains.shift_parents, tree.axis_nodes,
            tree.degrees, tree.proxy_offsets, values_t,
        )  # fmt: skip


def _interpolate(tree: _Tree, chains: _Chains, proxies_t, points, transpose: bool) -> None:
    """Points and their owners' proxies: ``points`` (N, S) += the owners' proxy values
    ``proxies_t`` (S, P) interpolated at the points, or (``transpose``) ``proxies_t`` +=
    the points' values spread on their owners' proxies (the proxy charges)."""
    _treecode_jit.interpolate(
        tree.points, chains.owners, chains.own_offsets, chains.own_starts, chains.own_stops,
        tree.axis_nodes, tree.degrees, tree.proxy_offsets, proxies_t, points, transpose,
    )  # fmt: skip


class _TreeSum(torch.autograd.Function):
    """``TreeCode.apply`` on a tensor (computed in float64 on the CPU, returned in its
    dtype and on its device); backward: the transpose."""

    @staticmethod
    def forward(ctx, values: Tensor, tree: TreeCode, threads: int | None):  # type: ignore[override]
        ctx.tree, ctx.threads = tree, threads
        result = tree.apply(values.detach().cpu().double().numpy(), threads)
        return torch.from_numpy(result).to(device=values.device, dtype=values.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        array = grad.detach().cpu().double().contiguous().numpy()
        transposed = torch.from_numpy(ctx.tree.apply_transposed(array, ctx.threads))
        return transposed.to(device=grad.device, dtype=grad.dtype), None, None


def tree_sum(tree: TreeCode, values: Tensor, threads: int | None = None) -> Tensor:
    """:meth:`TreeCode.apply` of ``values`` (N_s, S), differentiable in the values (the
    backward pass is the approximation's exact transpose). The treecode runs on the CPU
    in float64 whatever the tensor's device and dtype (numba's threads, ``threads`` of
    them); the result comes back in both."""
    return _TreeSum.apply(values, tree, threads)
