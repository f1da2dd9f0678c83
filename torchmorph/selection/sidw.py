"""Algorithm 1 of the paper (SIDW): selection of uniformly spread control points.

The implementation behind :func:`torchmorph.selection.select_control_points` (which
is the public name); :mod:`torchmorph.selection` builds the per-region plans on it.
Definitions: ``B(c; r)`` is the open ball ``|x - c| < r`` and ``B(c; r_i, r_e)`` the
shell ``r_i <= |x - c| < r_e``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from torchmorph._checks import as_points, check_choice, check_positive

__all__ = ["DEFAULT_SEED", "STRATEGIES", "select_control_points"]

#: Names accepted by the ``strategy`` argument (the ``SelectControlPoint`` function).
STRATEGIES = ("random", "centroid", "farthest")

#: Seed of the generator used when ``generator=None``: such calls are reproducible.
DEFAULT_SEED = 0

# Ball queries on the KD-tree use a radius enlarged by this relative amount; the
# exact membership tests are then made with the distances computed here, so the
# tree's own rounding never decides whether a point is in a ball.
_QUERY_SLACK = 1e-8

# With "farthest", a restart needs each point's distance to the nearest selected
# point; this many nearest neighbours are looked at, so that near-ties are resolved
# with the same arithmetic as everywhere else.
_FARTHEST_NEIGHBOURS = 8
# ... and the KD-tree over the selected points is rebuilt once more than this many
# points have been selected since its last build (those are compared by brute force).
_TAIL_LIMIT = 64


# --------------------------------------------------------------------------------------
# Algorithm 1
# --------------------------------------------------------------------------------------


def select_control_points(
    points: Tensor | np.ndarray | Sequence,
    radius: float,
    *,
    a: float = 0.8,
    b: float = 1.3,
    start: int | None = None,
    strategy: str = "random",
    generator: torch.Generator | None = None,
) -> Tensor:
    """Select a uniformly spread subset of ``points`` by Algorithm 1 (SIDW), section 2.2 of the paper.

    Around the start point ``c1`` the candidates farther than ``R`` from it are split
    into concentric annuli ``α_1 .. α_n`` of thickness ``a R``; the points of
    ``B(c1; R)`` are dropped. The annuli are then swept outward: a point is chosen in
    the selection area ``β`` (first ``α_1 ∩ B(c1; R, bR)``), the ball ``B(c; R)`` of
    the chosen point ``c`` is removed from every remaining annulus and ``β`` becomes
    ``α_m ∩ B(c; R, bR)``. When ``β`` is empty the sweep moves on to the next annulus,
    with ``β = α_{m+1} ∩ B(c_last; R, bR)``, or, if ``α_m`` still holds points that
    are disconnected from the last choice, restarts inside it with ``β = α_m``.

    Parameters
    ----------
    points : Tensor or ndarray, shape (N, D)
        Candidate points, ``N >= 1``, any dimension ``D >= 1`` (the paper's
        illustration is 2-D, meshes are 3-D). Computations run in float64 on the CPU.
    radius : float
        Selection radius ``R > 0``: the radius of each selected point's area of
        influence.
    a : float, default 0.8
        Annulus thickness factor, ``0 < a < 1``.
    b : float, default 1.3
        Selection-shell factor, ``b > 1``: the next point is sought in
        ``B(c; R, bR)`` around the last one.
    start : int, optional
        Index of the start point ``c1``. ``None`` draws it uniformly from
        ``generator``.
    strategy : {"random", "centroid", "farthest"}, default "random"
        ``SelectControlPoint``: ``"random"`` picks uniformly in ``β`` (the paper's
        choice); ``"centroid"`` the point of ``β`` closest to ``β``'s centroid;
        ``"farthest"`` the point of ``β`` whose distance to the nearest selected point
        is largest. Ties go to the lowest index.
    generator : torch.Generator, optional
        CPU generator for the start point and the ``"random"`` strategy. ``None`` uses
        a fresh generator seeded with :data:`DEFAULT_SEED`, so repeated calls return
        the same selection; pass a generator to draw different ones.

    Returns
    -------
    Tensor, shape (N_sel,), int64
        Indices into ``points`` in the order of selection; the first is ``c1``. On the
        device of ``points`` when it is a tensor, else on the CPU.

    Raises
    ------
    ValueError
        For points that are not a non-empty finite (N, D) array, ``radius`` not finite
        and > 0, ``a`` outside (0, 1), ``b`` not finite and > 1, ``start`` out of
        range, an unknown ``strategy`` or a generator that is not on the CPU.

    Notes
    -----
    Every candidate ends within distance ``R`` of a selected point and the selected
    points are pairwise at least ``R`` apart. The cost is ``O(N log N)`` for the
    KD-tree plus, per selected point, one ball query of radius ``bR``; ``β`` is never
    found by scanning all points (only a restart inside a disconnected annulus scans
    that annulus). Coincident candidates are allowed: at most one of them is
    selected.
    """
    array, device = _points_array(points)
    selection_radius = check_positive(radius, "radius")
    thickness = _check_factor(a, "a", low=0.0, high=1.0)
    shell_factor = _check_factor(b, "b", low=1.0, high=np.inf)
    _check_strategy(strategy)
    generator = _check_generator(generator)
    start_index = _check_start(start, array.shape[0], generator)
    selected = _sidw(
        array, start_index, selection_radius, thickness, shell_factor, strategy, generator
    )
    return torch.as_tensor(np.asarray(selected, dtype=np.int64), device=device)


def _sidw(
    points: np.ndarray,
    start: int,
    radius: float,
    a: float,
    b: float,
    strategy: str,
    generator: torch.Generator,
) -> list[int]:
    """Algorithm 1 on a float64 (N, D) array; returns the selected indices."""
    count = points.shape[0]
    outer = b * radius
    step = a * radius

    # Initialisation: annulus of every point (0 = inside B(c1; R), dropped). Annuli
    # that hold no point are skipped, which the algorithm does anyway (an empty α_m
    # gives an empty β and the sweep moves on with the same last point), so they are
    # numbered densely here: annulus[i] in 0..n_annuli-1, -1 for dropped points.
    distance_to_start = _distances(points, points[start])
    annulus, n_annuli = _dense_annuli(_annulus_index(distance_to_start, radius, step))
    alive = annulus >= 0
    remaining = np.bincount(annulus[alive], minlength=n_annuli)  # |α_m|
    members_of: list[np.ndarray] = []  # by_annulus, annulus_start; built at the first restart

    tree = cKDTree(points, balanced_tree=False)
    query_radius = outer * (1.0 + _QUERY_SLACK)
    # distance to the nearest selected point, exact wherever it is < bR (else inf);
    # kept for the "farthest" strategy only
    nearest_selected = np.full(count, np.inf) if strategy == "farthest" else None
    nearest_distance = _NearestSelected(points)

    def visit(center: int) -> np.ndarray:
        """Remove B(c; R) from the annuli; return the live points of B(c; R, bR), sorted."""
        ball = np.asarray(tree.query_ball_point(points[center], query_radius), dtype=np.int64)
        distance = _distances(points[ball], points[center])
        inside = distance < outer
        ball, distance = ball[inside], distance[inside]
        if nearest_selected is not None:
            nearest_selected[ball] = np.minimum(nearest_selected[ball], distance)
        live = alive[ball]
        near = distance < radius
        removed = ball[live & near]
        if removed.size:
            alive[removed] = False
            np.subtract.at(remaining, annulus[removed], 1)
        return np.sort(ball[live & ~near])

    def restart_members(m: int) -> np.ndarray:
        """The live points of α_m, sorted."""
        if not members_of:
            order = np.argsort(annulus.astype(_small_int_dtype(n_annuli)), kind="stable")
            members_of.extend([order, np.searchsorted(annulus[order], np.arange(n_annuli + 1))])
        order, offsets = members_of
        members = order[offsets[m] : offsets[m + 1]]
        return members[alive[members]]

    def choose(beta: np.ndarray, selected: list[int]) -> int:
        if strategy == "random":
            return int(beta[int(torch.randint(beta.size, (1,), generator=generator))])
        if strategy == "centroid":
            members = points[beta]
            return int(beta[np.argmin(_distances(members, members.mean(axis=0)))])
        assert nearest_selected is not None  # the strategy is "farthest"
        gap = nearest_selected[beta]
        unknown = np.isinf(gap)
        if unknown.any():  # only after a restart: no selected point within bR
            gap = gap.copy()
            gap[unknown] = nearest_distance(points[beta[unknown]], selected)
        return int(beta[np.argmax(gap)])

    selected = [start]
    shell = visit(start)
    m = 0
    while m < n_annuli and remaining[m] == 0:
        m += 1
    if m < n_annuli:
        beta = shell[annulus[shell] == m]
    while m < n_annuli:
        while beta.size:
            center = choose(beta, selected)
            selected.append(center)
            shell = visit(center)
            beta = shell[annulus[shell] == m]
        if remaining[m] == 0:
            # next non-empty annulus, β around the last selected point (unchanged
            # since its visit: nothing has been removed in between)
            m += 1
            while m < n_annuli and remaining[m] == 0:
                m += 1
            if m < n_annuli:
                beta = shell[annulus[shell] == m]
        else:
            # α_m is disconnected from the last choice: restart inside it
            beta = restart_members(m)
    return selected


def _distances(points: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Euclidean distances |points - center| over the last axis."""
    return np.sqrt(_squared_norm(points - center))


def _squared_norm(diff: np.ndarray) -> np.ndarray:
    """``(diff ** 2).sum(axis=-1)``, bit for bit, only faster.

    For fewer than 8 columns NumPy sums them in order, as this loop does; a
    reduction over a short last axis is several times slower than the loop.
    """
    if diff.shape[-1] >= 8:
        return (diff**2).sum(axis=-1)
    squared = diff[..., 0] ** 2
    for column in range(1, diff.shape[-1]):
        squared += diff[..., column] ** 2
    return squared


def _annulus_index(distance: np.ndarray, radius: float, step: float) -> np.ndarray:
    """Annulus number k >= 1 with R + (k-1) aR <= d < R + k aR; 0 for d < R.

    The edges are ``radius + k * step`` evaluated in float64, and the index is made
    consistent with those comparisons (the floor of the quotient alone can be off by
    one through rounding).
    """
    index = np.floor((distance - radius) / step)
    index = np.maximum(index, 0.0)
    for _ in range(2):
        index -= (index > 0) & (distance < radius + index * step)
        index += distance >= radius + (index + 1.0) * step
    index = index.astype(np.int64) + 1
    index[distance < radius] = 0
    return index


def _dense_annuli(raw: np.ndarray) -> tuple[np.ndarray, int]:
    """Renumber the non-empty annuli 0, 1, ... in order; dropped points (raw 0) get -1."""
    inside = raw > 0
    if raw.size and int(raw.max()) <= 4 * raw.size:
        occupied = np.bincount(raw[inside], minlength=int(raw.max()) + 1) > 0
        dense = np.cumsum(occupied) - 1
        return np.where(inside, dense[raw], -1), int(occupied.sum())
    annulus = np.full(raw.size, -1, dtype=np.int64)
    occupied, annulus[inside] = np.unique(raw[inside], return_inverse=True)
    return annulus, int(occupied.size)


def _small_int_dtype(count: int) -> type:
    """Narrowest signed integer type holding -1..count (a faster stable sort)."""
    return np.int16 if count < 2**15 else np.int32 if count < 2**31 else np.int64


class _NearestSelected:
    """Distance from query points to the nearest selected point.

    A KD-tree over the selected points is rebuilt only when more than
    ``_TAIL_LIMIT`` points have been selected since the last build; those are
    compared by brute force. Distances are recomputed here from the
    ``_FARTHEST_NEIGHBOURS`` nearest candidates so that near-ties are settled by the
    same arithmetic as in the rest of the selection.
    """

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        self.built = 0
        self.tree: cKDTree | None = None

    def __call__(self, queries: np.ndarray, selected: list[int]) -> np.ndarray:
        if len(selected) - self.built > _TAIL_LIMIT:
            self.built = len(selected)
            self.tree = cKDTree(self.points[np.asarray(selected)], balanced_tree=False)
        tail = self.points[np.asarray(selected[self.built :], dtype=np.int64)]
        if self.tree is not None:
            neighbours = min(_FARTHEST_NEIGHBOURS, self.built)
            _, index = self.tree.query(queries, k=neighbours)
            candidates = np.concatenate(
                [
                    self.tree.data[index.reshape(queries.shape[0], neighbours)],
                    np.broadcast_to(tail, (queries.shape[0],) + tail.shape),
                ],
                axis=1,
            )
        else:
            candidates = np.broadcast_to(tail, (queries.shape[0],) + tail.shape)
        return np.sqrt(_squared_norm(queries[:, None, :] - candidates).min(axis=1))


# --------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------


def _points_array(points: Any) -> tuple[np.ndarray, torch.device]:
    """Validate ``points`` (N, D) and return it as a float64 array and its device."""
    device = points.device if isinstance(points, Tensor) else torch.device("cpu")
    shape = tuple(points.shape) if hasattr(points, "shape") else np.shape(points)
    if len(shape) != 2 or shape[1] < 1:
        raise ValueError(f"points must have shape (N, D) with D >= 1, got {shape}")
    checked = as_points(points, "points", dim=shape[1])
    return checked.detach().to("cpu", torch.float64).numpy(), device


def _check_factor(value: float, name: str, *, low: float, high: float) -> float:
    number = float(value)
    if not (np.isfinite(number) and low < number < high):
        bounds = f"0 < {name} < 1" if high == 1.0 else f"{name} > 1 (finite)"
        raise ValueError(f"{name} must satisfy {bounds}, got {value!r}")
    return number


def _check_strategy(strategy: str) -> None:
    check_choice(strategy, "strategy", STRATEGIES)


def _check_generator(generator: torch.Generator | None) -> torch.Generator:
    if generator is None:
        return torch.Generator().manual_seed(DEFAULT_SEED)
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator or None, got {type(generator)}")
    if generator.device.type != "cpu":
        raise ValueError(f"generator must be a CPU generator, got one on {generator.device}")
    return generator


def _check_start(start: int | None, count: int, generator: torch.Generator) -> int:
    if start is None:
        return int(torch.randint(count, (1,), generator=generator))
    if isinstance(start, Tensor):
        if start.numel() != 1 or start.is_floating_point() or start.dtype == torch.bool:
            raise TypeError(f"start must be an integer index, got {start!r}")
        start = int(start)
    if isinstance(start, (bool, np.bool_)) or not isinstance(start, (int, np.integer)):
        raise TypeError(f"start must be an integer index or None, got {start!r}")
    if not 0 <= int(start) < count:
        raise ValueError(f"start must lie in [0, {count}) for {count} points, got {start}")
    return int(start)
