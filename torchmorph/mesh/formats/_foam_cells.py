"""OpenFOAM's cells (lists of faces) recognised as tetrahedra, pyramids, wedges and
hexahedra, in meshio's node order.

Private helper of :mod:`torchmorph.mesh.formats.openfoam`. Every cell is built from one
base face turned inward (OpenFOAM orients a face out of its owner, into its neighbour)
and the vertices joined to the base by the other faces' edges, so a cell's node order
follows from the mesh's topology alone and is positively oriented wherever the mesh is
valid (OpenFOAM's face orientation agrees with its geometry).
"""

from __future__ import annotations

import numpy as np

__all__ = ["CELL_KINDS", "cell_blocks", "face_blocks"]

#: The cell kinds recognised, as meshio names them, in the order of the blocks.
CELL_KINDS = ("tetra", "pyramid", "wedge", "hexahedron")


def cell_blocks(
    offsets: np.ndarray, labels: np.ndarray, owner: np.ndarray, neighbour: np.ndarray, n_cells: int
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The cells as blocks ``(kind, connectivity (M, n), cell ids (M,))`` in the order
    of :data:`CELL_KINDS`, kinds that occur only.

    Raises
    ------
    ValueError
        If a cell is not a tetrahedron, pyramid, wedge or hexahedron (its number of
        faces and their sizes are named), or its faces do not close up as that shape.
    """
    sizes = np.diff(offsets)
    n_internal = neighbour.size
    # cell -> (face, outward) incidences, grouped by cell
    cells = np.concatenate([owner, neighbour])
    faces = np.concatenate([np.arange(owner.size), np.arange(n_internal)])
    outward = np.concatenate([np.ones(owner.size, bool), np.zeros(n_internal, bool)])
    order = np.argsort(cells, kind="stable")
    cells, faces, outward = cells[order], faces[order], outward[order]
    n_faces = np.bincount(cells, minlength=n_cells)
    first = np.concatenate([[0], np.cumsum(n_faces)[:-1]])
    face_size = sizes[faces]
    triangles = np.bincount(cells, weights=face_size == 3, minlength=n_cells).astype(np.int64)
    quads = np.bincount(cells, weights=face_size == 4, minlength=n_cells).astype(np.int64)
    shapes = {
        "tetra": (n_faces == 4) & (triangles == 4),
        "pyramid": (n_faces == 5) & (triangles == 4) & (quads == 1),
        "wedge": (n_faces == 5) & (triangles == 2) & (quads == 3),
        "hexahedron": (n_faces == 6) & (quads == 6),
    }
    known = np.zeros(n_cells, dtype=bool)
    for mask in shapes.values():
        known |= mask
    if not known.all():
        _unknown_cell(np.flatnonzero(~known), n_faces, triangles, quads)
    # every face (all are triangles or quadrilaterals now) padded to four vertices, a
    # triangle repeating its first; turned inward where it leaves its owner
    width = sizes[:, None]
    padded = labels[offsets[:-1, None] + np.minimum(np.arange(4), width - 1)]
    turned = np.where(width == 3, padded[:, [0, 2, 1, 0]], padded[:, [0, 3, 2, 1]])
    blocks = []
    for kind, mask in shapes.items():
        ids = np.flatnonzero(mask)
        if ids.size == 0:
            continue
        count = n_faces[ids[0]]
        slots = first[ids, None] + np.arange(count)
        cell_faces = np.where(
            outward[slots, None], turned[faces[slots]], padded[faces[slots]]
        )  # (M, count, 4)
        connectivity = _build(kind, cell_faces, face_size[slots], ids)
        blocks.append((kind, connectivity, ids))
    return blocks


def face_blocks(
    offsets: np.ndarray, labels: np.ndarray, start: int, count: int, patch: str
) -> list[tuple[str, np.ndarray]]:
    """A patch's faces as ``triangle`` and ``quad`` blocks (those that occur), in the
    file's vertex order (out of the domain)."""
    sizes = np.diff(offsets[start : start + count + 1])
    large = np.flatnonzero(sizes > 4)
    if large.size:
        face = start + int(large[0])
        raise ValueError(
            f"case: patch {patch!r} face {face} has {sizes[large[0]]} vertices; only "
            f"triangles and quadrilaterals are supported ({large.size} such faces)"
        )
    blocks = []
    for kind, size in (("triangle", 3), ("quad", 4)):
        rows = start + np.flatnonzero(sizes == size)
        if rows.size:
            blocks.append((kind, labels[offsets[rows, None] + np.arange(size)]))
    return blocks


def _unknown_cell(
    bad: np.ndarray, n_faces: np.ndarray, triangles: np.ndarray, quads: np.ndarray
) -> None:
    cell = int(bad[0])
    others = n_faces[cell] - triangles[cell] - quads[cell]
    raise ValueError(
        f"case: cell {cell} has {n_faces[cell]} faces ({triangles[cell]} triangles, "
        f"{quads[cell]} quadrilaterals, {others} larger polygons) and is not a tetrahedron, "
        f"pyramid, wedge or hexahedron; {bad.size} such cells (a polyhedral mesh, as "
        "snappyHexMesh or polyDualMesh write, cannot be converted to cells of these kinds)"
    )


def _build(kind: str, cell_faces: np.ndarray, sizes: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Connectivity (M, n) of cells of one kind from their inward faces (M, k, 4).

    The base is a triangle (tetrahedron, wedge) or quadrilateral (pyramid, hexahedron)
    face; a tetrahedron or pyramid adds the one vertex off the base. A wedge or
    hexahedron adds, for every base vertex, the vertex its edge off the base leads to:
    each such edge is written once leaving the base in one of the inward faces."""
    rows = np.arange(ids.size)
    corners = 4 if kind in ("pyramid", "hexahedron") else 3
    base = cell_faces[rows, np.argmax(sizes == corners, axis=1)][:, :corners]
    in_base = (cell_faces[..., None] == base[:, None, None, :]).any(-1)  # (M, k, 4)
    if kind in ("tetra", "pyramid"):
        off_base = cell_faces.reshape(ids.size, -1)
        outside = ~in_base.reshape(ids.size, -1)
        apex = off_base[rows, np.argmax(outside, axis=1)]
        closed = outside.any(1) & ~(outside & (off_base != apex[:, None])).any(1)
        if not closed.all():
            _not_closed(kind, ids[~closed])
        connectivity = np.concatenate([base, apex[:, None]], axis=1)
    else:
        leaving = in_base & ~np.roll(in_base, -1, axis=2)  # edge (v, next) leaves the base
        closed = leaving.sum(axis=(1, 2)) == corners
        if not closed.all():
            _not_closed(kind, ids[~closed])
        foot = cell_faces[leaving].reshape(ids.size, corners)
        head = np.roll(cell_faces, -1, axis=2)[leaving].reshape(ids.size, corners)
        position = np.argmax(foot[:, :, None] == base[:, None, :], axis=2)
        closed = (np.sort(position, axis=1) == np.arange(corners)).all(1)
        if not closed.all():
            _not_closed(kind, ids[~closed])
        top = np.empty_like(base)
        top[rows[:, None], position] = head
        connectivity = np.concatenate([base, top], axis=1)
    distinct = np.sort(connectivity, axis=1)
    repeated = (distinct[:, 1:] == distinct[:, :-1]).any(1)
    if repeated.any():
        _not_closed(kind, ids[repeated])
    return connectivity


def _not_closed(kind: str, bad: np.ndarray) -> None:
    raise ValueError(
        f"case: cell {int(bad[0])} has the faces of a {kind} but they do not close up as "
        f"one ({bad.size} such cells)"
    )
