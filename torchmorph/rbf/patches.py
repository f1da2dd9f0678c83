"""The geometry of the partition-of-unity RBF (:mod:`torchmorph.rbf.partition`): a
balanced kd-split of the controls, the coarse subset (one control per cell of a split
into as many cells), the overlapping patches (balls around the cells of a finer split)
with the controls and targets each holds, the patches' local frames, and the blend
weights of the targets.

All of it is computed once, at the fit, in float64 NumPy on the CPU (scipy's
``cKDTree`` for the ball queries).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "FLAT_TOLERANCE",
    "Patches",
    "blend_weights",
    "build_patches",
    "coarse_subset",
    "kd_split",
    "local_frame",
    "midpoint_split",
    "wendland_weight",
]

#: An axis of a patch's principal frame along which its controls spread less than this
#: fraction of their largest spread is flat: the polynomial tail drops it (controls on a
#: plane or a line, where the linear monomials are dependent).
FLAT_TOLERANCE = 1e-8


def kd_split(points: np.ndarray, cells: int) -> list[np.ndarray]:
    """Indices of ``points`` (N, D) in ``cells`` cells of a balanced kd-split: a cell
    meant to hold k leaves is cut across the longest side of its bounding box at the
    quantile ``floor(k / 2) / k`` of its points, so the leaves' sizes differ by at most
    one (for ``cells`` <= N)."""
    stack = [(np.arange(points.shape[0]), max(1, min(cells, points.shape[0])))]
    leaves = []
    while stack:
        index, count = stack.pop()
        if count <= 1:
            leaves.append(index)
            continue
        part = points[index]
        axis = int(np.argmax(part.max(axis=0) - part.min(axis=0)))
        left = count // 2
        cut = index.shape[0] * left // count
        order = np.argpartition(part[:, axis], cut)
        stack.append((index[order[cut:]], count - left))
        stack.append((index[order[:cut]], left))
    return leaves


def coarse_subset(points: np.ndarray, size: int) -> np.ndarray:
    """``size`` indices spread over ``points``: in each cell of :func:`kd_split` into
    ``size`` cells, the point nearest the cell's mean (sorted; all of them when ``size``
    >= N)."""
    if size >= points.shape[0]:
        return np.arange(points.shape[0])
    chosen = []
    for cell in kd_split(points, size):
        part = points[cell]
        distance = ((part - part.mean(axis=0)) ** 2).sum(axis=1)
        chosen.append(cell[int(np.argmin(distance))])
    return np.sort(np.asarray(chosen, dtype=np.int64))


def wendland_weight(scaled: np.ndarray) -> np.ndarray:
    """Wendland's C² function ``(1 − t)₊⁴ (4t + 1)`` of the scaled distance t: 1 at the
    patch's centre, 0 from its radius on (the blend weight)."""
    rest = np.clip(1.0 - scaled, 0.0, None)
    return rest**4 * (4.0 * scaled + 1.0)


def local_frame(points: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The principal axes of ``points`` about ``centre`` as the columns of a rotation
    (D, D), and the points' largest |coordinate| along each (their half spread)."""
    offsets = points - centre
    _, _, rows = np.linalg.svd(offsets, full_matrices=False)
    frame = rows.T
    if frame.shape[1] < points.shape[1]:  # fewer points than dimensions: complete it
        frame = np.linalg.qr(np.hstack([frame, np.eye(points.shape[1])]))[0]
    spread = np.abs(offsets @ frame).max(axis=0)
    return frame, spread


@dataclass
class Patches:
    """The overlapping patches, P of them, and what each holds.

    ``centres`` (P, D) and ``radii`` (P,): the balls; ``members``: the controls
    strictly inside each ball (CSR: ``member_offsets`` (P + 1,)); ``frames`` (P, D, D)
    the principal axes (columns) of each patch's members about its centre;
    ``spreads`` (P, D) their half spreads along them (1 along a flat axis); ``flat``
    (P, D) which axes are flat (:data:`FLAT_TOLERANCE`); ``owner`` (N,) the patch whose
    cell holds each control (every patch holds its own cell's controls)."""

    centres: np.ndarray
    radii: np.ndarray
    members: np.ndarray
    member_offsets: np.ndarray
    frames: np.ndarray
    spreads: np.ndarray
    flat: np.ndarray
    owner: np.ndarray


def _inside(
    tree: cKDTree, points: np.ndarray, centres: np.ndarray, radii: np.ndarray
) -> list[np.ndarray]:
    """Per ball, the sorted indices of ``points`` whose scaled distance |x − c| / R is < 1
    (computed as :func:`blend_weights` computes it, so that membership and a non-zero
    weight agree to the last bit)."""
    found = tree.query_ball_point(centres, radii * (1.0 + 1e-9), return_sorted=False)
    inside = []
    for centre, radius, candidates in zip(centres, radii, found, strict=True):
        index = np.asarray(candidates, dtype=np.int64)
        scaled = np.sqrt(((points[index] - centre) ** 2).sum(axis=1)) / radius
        inside.append(np.sort(index[scaled < 1.0]))
    return inside


def midpoint_split(points: np.ndarray, capacity: int) -> list[np.ndarray]:
    """Indices of ``points`` (N, D) in the leaves of a kd-split that halves the longest
    side of each cell's bounding box (the box of its points) until a cell holds at most
    ``capacity``: cells stay compact (a cell never spans an empty gap of the cloud, as a
    split by counts can), at the price of leaves of unequal counts."""
    stack = [np.arange(points.shape[0])]
    leaves = []
    while stack:
        index = stack.pop()
        part = points[index]
        low, high = part.min(axis=0), part.max(axis=0)
        if index.shape[0] <= capacity or not (high > low).any():
            leaves.append(index)
            continue
        axis = int(np.argmax(high - low))
        below = part[:, axis] <= (low[axis] + high[axis]) / 2
        stack.extend([index[~below], index[below]])
    return leaves


def build_patches(
    controls: np.ndarray, patch_size: int, overlap: float, least: int, extra: int = 0
) -> Patches:
    """Cover the controls (N, D) by patches: the cells of :func:`midpoint_split` with
    ``patch_size`` controls at most, each enlarged to the ball about its bounding box's
    centre whose radius is ``overlap`` times the distance to its farthest control, or
    larger when that holds fewer than ``least`` controls, or fewer than ``extra`` more
    than its own cell's (then the ``least`` or cell-plus-``extra`` nearest the centre).
    Every control lies at a scaled distance <= 1 / overlap from its own cell's centre.

    ``extra``: the local fits' polynomial terms. A local fit's coefficients satisfy one
    moment condition per term, so they have ``held − extra`` free values; the global
    fit's preconditioner (:mod:`~torchmorph.rbf.refine`) takes a coefficient for each of
    the cell's own controls from them, which needs ``held >= own + extra``."""
    cells = midpoint_split(controls, patch_size)
    count, dim = len(cells), controls.shape[1]
    owner = np.empty(controls.shape[0], dtype=np.int64)
    centres = np.empty((count, dim))
    radii = np.empty(count)
    for index, cell in enumerate(cells):
        part = controls[cell]
        owner[cell] = index
        centres[index] = (part.min(axis=0) + part.max(axis=0)) / 2
        farthest = np.sqrt(((part - centres[index]) ** 2).sum(axis=1)).max()
        radii[index] = overlap * max(farthest, np.finfo(np.float64).tiny)
    tree = cKDTree(controls)
    needed = np.minimum(
        np.maximum(least, np.array([cell.shape[0] for cell in cells]) + extra), controls.shape[0]
    )
    nearest, _ = tree.query(centres, k=int(needed.max()))
    nearest = nearest.reshape(count, -1)[np.arange(count), needed - 1]
    nearest = nearest * (1.0 + 1e-6)  # the needed-th nearest inside
    radii = np.maximum(radii, nearest)
    members = _inside(tree, controls, centres, radii)
    frames = np.empty((count, dim, dim))
    spreads = np.empty((count, dim))
    flat = np.zeros((count, dim), dtype=bool)
    for index, held in enumerate(members):
        frames[index], spread = local_frame(controls[held], centres[index])
        flat[index] = spread <= FLAT_TOLERANCE * spread.max()
        spreads[index] = np.where(flat[index], 1.0, spread)
    offsets = np.zeros(count + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([held.shape[0] for held in members])
    return Patches(centres, radii, np.concatenate(members), offsets, frames, spreads, flat, owner)


def blend_weights(
    targets: np.ndarray, centres: np.ndarray, radii: np.ndarray, floor: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The targets each patch blends into and their weights: (indices, offsets (P + 1,),
    weights), CSR by patch.

    The weight of patch j at x is ``w_j(x) / max(Σ_i w_i(x), floor)``,
    ``w_j = wendland_weight(|x − c_j| / R_j)``: the weights sum to 1 wherever the
    patches' raw weights sum to at least ``floor`` (at every control, :func:`build_patches`
    makes it so with ``floor = wendland_weight(1 / overlap)``), and fade to 0 with the
    raw sum elsewhere (targets far from every control get no patch's value)."""
    if targets.shape[0] == 0 or centres.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, np.zeros(centres.shape[0] + 1, dtype=np.int64), np.zeros(0)
    inside = _inside(cKDTree(targets), targets, centres, radii)
    indices = np.concatenate(inside)
    offsets = np.zeros(centres.shape[0] + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([held.shape[0] for held in inside])
    raw = np.concatenate(
        [
            wendland_weight(np.sqrt(((targets[held] - centre) ** 2).sum(axis=1)) / radius)
            for held, centre, radius in zip(inside, centres, radii, strict=True)
        ]
    )
    total = np.bincount(indices, weights=raw, minlength=targets.shape[0])
    return indices, offsets, raw / np.maximum(total[indices], floor)
