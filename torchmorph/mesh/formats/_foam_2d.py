"""The geometry behind :func:`torchmorph.mesh.formats.openfoam.pseudo_2d`: face normals,
front and back twins, the front plane's cells and the patches' front edges.

Private helpers; faces are given as OpenFOAM's compact lists (``offsets`` (F + 1,),
``labels`` (L,)) and a selection of face numbers.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["face_points", "front_cells", "front_lines", "newell_normals", "twins"]


def _ranges(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(start, end)`` of every pair."""
    lengths = ends - starts
    shift = np.repeat(starts - np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
    return np.arange(lengths.sum()) + shift


def _edges(offsets: np.ndarray, labels: np.ndarray, faces: np.ndarray):
    """Every edge of ``faces`` in their cyclic order: (from, to, face row), each (E,)."""
    starts, ends = offsets[faces], offsets[faces + 1]
    slots = _ranges(starts, ends)
    following = slots + 1
    following[np.cumsum(ends - starts) - 1] = starts  # a face's last vertex wraps to its first
    rows = np.repeat(np.arange(faces.size), ends - starts)
    return labels[slots], labels[following], rows


def face_points(offsets: np.ndarray, labels: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The point labels of ``faces``, concatenated (with repeats)."""
    return labels[_ranges(offsets[faces], offsets[faces + 1])]


def newell_normals(
    points: np.ndarray, offsets: np.ndarray, labels: np.ndarray, faces: np.ndarray
) -> np.ndarray:
    """Area vectors of ``faces`` by Newell's method, shape (K, 3): the normal by the
    right-hand rule about the face's vertex order, as long as the face's area."""
    here, there, rows = _edges(offsets, labels, faces)
    terms = np.cross(points[here], points[there])
    return np.stack([np.bincount(rows, terms[:, k], faces.size) for k in range(3)], 1) / 2


def twins(
    points: np.ndarray, front: np.ndarray, back: np.ndarray, in_plane: list[int], gap: float
) -> np.ndarray:
    """For every front point, the row of ``back`` at its in-plane position (within
    ``gap``); a ``ValueError`` where there is none or two front points share one."""
    if front.size != back.size:
        raise ValueError(
            f"case: {front.size} points on the front plane but {back.size} on the back: "
            "some point has no twin"
        )
    distance, twin = cKDTree(points[back][:, in_plane]).query(points[front][:, in_plane])
    lonely = np.flatnonzero(distance > gap)
    if lonely.size:
        raise ValueError(
            f"case: point {front[lonely[0]]} on the front plane has no twin on the back "
            f"(the nearest is {distance[lonely[0]]:.3g} away in-plane); {lonely.size} such points"
        )
    if np.unique(twin).size != twin.size:
        raise ValueError("case: two front points share a twin on the back plane")
    return twin


def front_cells(
    offsets: np.ndarray,
    labels: np.ndarray,
    owner: np.ndarray,
    faces: np.ndarray,
    flipped: np.ndarray,
    local: np.ndarray,
) -> tuple[list[tuple[str, np.ndarray]], list[np.ndarray]]:
    """The front plane's ``faces`` as ``triangle``/``quad`` blocks in 2-D point numbers
    (``local``), those marked ``flipped`` turned; and each block's owner cells."""
    sizes = offsets[faces + 1] - offsets[faces]
    large = np.flatnonzero(sizes > 4)
    if large.size:
        raise ValueError(
            f"case: front face {faces[large[0]]} has {sizes[large[0]]} vertices; only "
            "triangles and quadrilaterals are supported"
        )
    cells, owners = [], []
    for kind, size in (("triangle", 3), ("quad", 4)):
        chosen = sizes == size
        if not chosen.any():
            continue
        rows = faces[chosen]
        vertices = labels[offsets[rows, None] + np.arange(size)]
        turn = flipped[chosen]
        vertices[turn] = vertices[turn][:, ::-1]
        cells.append((kind, local[vertices]))
        owners.append(owner[rows])
    return cells, owners


def front_lines(
    offsets: np.ndarray,
    labels: np.ndarray,
    faces: np.ndarray,
    on_front: np.ndarray,
    local: np.ndarray,
    patch: str,
) -> list[tuple[str, np.ndarray]]:
    """The one edge of each of a patch's ``faces`` that lies in the front plane, as a
    ``line`` block in 2-D point numbers, in the face's vertex order."""
    if faces.size == 0:
        return []
    here, there, rows = _edges(offsets, labels, faces)
    in_front = on_front[here] & on_front[there]
    counts = np.bincount(rows[in_front], minlength=faces.size)
    if np.any(counts != 1):
        bad = int(np.flatnonzero(counts != 1)[0])
        raise ValueError(
            f"case: patch {patch!r} face {faces[bad]} has {counts[bad]} edges in the front "
            "plane, not one (a side face of a one-cell-thick case has one)"
        )
    return [("line", np.stack([local[here[in_front]], local[there[in_front]]], axis=1))]
