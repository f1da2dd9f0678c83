"""Small meshes of every element kind, built by hand on a grid of unit cells: each kind
alone, hybrid stacks, 2-D ones, and the quadratic version of any of them. Independent of
the library: plain NumPy, node orders written out here from meshio's (VTK's) conventions.
"""

from __future__ import annotations

import itertools

import numpy as np


def grid(counts: tuple[int, ...], size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Points of a regular grid over [0, size]^D and their index array."""
    ticks = [np.linspace(0.0, size, n + 1) for n in counts]
    mesh = np.meshgrid(*ticks, indexing="ij")
    points = np.stack([m.ravel() for m in mesh], 1)
    index = np.arange(points.shape[0]).reshape(tuple(n + 1 for n in counts))
    return points, index


def _cube_corners(index: np.ndarray, i: int, j: int, k: int) -> list[int]:
    """The eight corners of cell (i, j, k) in VTK hexahedron order."""
    return [
        index[i, j, k],
        index[i + 1, j, k],
        index[i + 1, j + 1, k],
        index[i, j + 1, k],
        index[i, j, k + 1],
        index[i + 1, j, k + 1],
        index[i + 1, j + 1, k + 1],
        index[i, j + 1, k + 1],
    ]


def _wedges(c: list[int]) -> list[list[int]]:
    """A cube cut along the diagonal 0-2 of its bottom face into two wedges (triangles
    0-1-2 and 0-2-3 extruded along z), counter-clockwise seen from above."""
    return [[c[0], c[1], c[2], c[4], c[5], c[6]], [c[0], c[2], c[3], c[4], c[6], c[7]]]


def _pyramids(c: list[int], centre: int) -> list[list[int]]:
    """A cube cut into six pyramids with apex at its centre, each base a cube face
    ordered so that its normal points to the apex."""
    faces = [(0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)]
    return [[c[a], c[b], c[cc], c[d], centre] for a, b, cc, d in faces]


def _tets(c: list[int]) -> list[list[int]]:
    """A cube cut into six tetrahedra around its diagonal 0-6 (Kuhn)."""
    paths = ((1, 2), (2, 3), (3, 7), (7, 4), (4, 5), (5, 1))
    return [[c[0], c[a], c[b], c[6]] for a, b in paths]


def box(kinds_by_layer: tuple[str, ...], cells: int = 2):
    """A box of ``cells x cells`` columns and one layer of unit cells per entry of
    ``kinds_by_layer`` (``"hexahedron"``, ``"wedge"``, ``"pyramid"``, ``"tetra"``).

    Layers that conform: a wedge layer (a prism layer extruded along z) under a tetra
    layer (their triangles share the diagonal 0-2 of each cube face), hexahedra under
    pyramids (the pyramids' bases are the cube faces), a layer over one of its own kind.
    A wedge or tetra layer next to a hexahedron or pyramid layer does not conform (a
    quad against two triangles): ``Mesh`` rejects it.

    Returns points (N, 3), cells [(kind, array)], the number of boundary nodes.
    """
    layers = len(kinds_by_layer)
    points, index = grid((cells, cells, layers), size=1.0)
    points = points * np.array([cells, cells, layers], dtype=np.float64)  # unit cells
    extra = []
    blocks: dict[str, list[list[int]]] = {}
    for k, kind in enumerate(kinds_by_layer):
        for i, j in itertools.product(range(cells), range(cells)):
            c = _cube_corners(index, i, j, k)
            if kind == "hexahedron":
                blocks.setdefault(kind, []).append(c)
            elif kind == "wedge":
                blocks.setdefault(kind, []).extend(_wedges(c))
            elif kind == "pyramid":
                centre = len(points) + len(extra)
                extra.append(points[c].mean(0))
                blocks.setdefault(kind, []).extend(_pyramids(c, centre))
            elif kind == "tetra":
                blocks.setdefault(kind, []).extend(_tets(c))
            else:
                raise ValueError(kind)
    if extra:
        points = np.concatenate([points, np.array(extra)])
    return points, [(kind, np.array(rows, dtype=np.int64)) for kind, rows in blocks.items()]


def columns(cells: int = 2):
    """A box of 2 cells x ``cells`` x ``cells``: hexahedra for x < 1, wedges (each cube cut
    along a vertical diagonal plane) for x > 1 — the two kinds share whole quads."""
    points, index = grid((2, cells, cells))
    points = points * np.array([2, cells, cells], dtype=np.float64)
    hexes, wedges = [], []
    for j, k in itertools.product(range(cells), range(cells)):
        hexes.append(_cube_corners(index, 0, j, k))
        wedges.extend(_wedges(_cube_corners(index, 1, j, k)))
    return points, [
        ("hexahedron", np.array(hexes, dtype=np.int64)),
        ("wedge", np.array(wedges, dtype=np.int64)),
    ]


def rectangle(kind: str, cells: int = 3):
    """The unit square in ``cells x cells`` quads, or triangles (each quad cut along
    its diagonal), counter-clockwise."""
    points, index = grid((cells, cells))
    points = points * cells  # unit cells
    rows = []
    for i, j in itertools.product(range(cells), range(cells)):
        a, b, c, d = index[i, j], index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]
        rows += [[a, b, c, d]] if kind == "quad" else [[a, b, c], [a, c, d]]
    return points, [(kind, np.array(rows, dtype=np.int64))]


# local edges (by corner) of the linear kinds, in the order of the quadratic kinds'
# mid-edge nodes, and the faces with a centre node (for quad9, hexahedron27, wedge18,
# pyramid14)
EDGES = {
    "triangle": [(0, 1), (1, 2), (2, 0)],
    "quad": [(0, 1), (1, 2), (2, 3), (3, 0)],
    "tetra": [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)],
    "pyramid": [(0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4)],
    "wedge": [(0, 1), (1, 2), (2, 0), (3, 4), (4, 5), (5, 3), (0, 3), (1, 4), (2, 5)],
    "hexahedron": [
        (0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6),
        (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7),
    ],
}  # fmt: skip
CENTRES = {
    "quad9": ([], True),
    "pyramid14": ([(0, 1, 2, 3)], False),
    "wedge18": ([(0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)], False),
    "hexahedron27": (
        [(0, 3, 7, 4), (1, 2, 6, 5), (0, 1, 5, 4), (3, 2, 6, 7), (0, 1, 2, 3), (4, 5, 6, 7)],
        True,
    ),
}
QUADRATIC = {
    "triangle": "triangle6",
    "quad": "quad8",
    "tetra": "tetra10",
    "pyramid": "pyramid13",
    "wedge": "wedge15",
    "hexahedron": "hexahedron20",
}


def quadratic(points: np.ndarray, cells, full: bool = False):
    """The quadratic version of a linear mesh: a node at the middle of every edge (shared
    between cells), and with ``full`` at the centre of every quad face and of quad/hex
    cells (quad9, hexahedron27, wedge18, pyramid14)."""
    points = list(points)
    mids: dict[tuple[int, ...], int] = {}

    def node_at(key: tuple[int, ...]) -> int:
        if key not in mids:
            mids[key] = len(points)
            points.append(np.mean([points[k] for k in key], axis=0))
        return mids[key]

    result = []
    for kind, rows in cells:
        name = QUADRATIC[kind]
        faces, body = ([], False)
        if full:
            name = {"quad": "quad9", "hexahedron": "hexahedron27", "wedge": "wedge18"}.get(
                kind, {"pyramid": "pyramid14"}.get(kind, name)
            )
            faces, body = CENTRES.get(name, ([], False))
        out = []
        for row in rows:
            nodes = list(row)
            nodes += [node_at(tuple(sorted((row[a], row[b])))) for a, b in EDGES[kind]]
            nodes += [node_at(tuple(sorted(row[list(face)]))) for face in faces]
            if body:
                nodes.append(node_at(tuple(sorted(row))))
            out.append(nodes)
        result.append((name, np.array(out, dtype=np.int64)))
    return np.array(points), result


def on_box_surface(points: np.ndarray) -> np.ndarray:
    """Rows of the points on the surface of their bounding box."""
    low, high = points.min(0), points.max(0)
    return np.flatnonzero((np.isclose(points, low) | np.isclose(points, high)).any(1))


def idw_reference(points: np.ndarray, controls: np.ndarray, values: np.ndarray, power=4.0):
    """Float64 IDW (the paper's eq. 2) from ``controls`` to every point, brute force."""
    distance2 = ((points[:, None, :] - controls[None, :, :]) ** 2).sum(-1)
    result = np.empty((points.shape[0], values.shape[1]))
    for i, row in enumerate(distance2):
        hit = row == 0
        if hit.any():
            result[i] = values[hit].mean(0)
        else:
            weights = row ** (-power / 2)
            result[i] = weights @ values / weights.sum()
    return result
