"""The element kinds torchmorph meshes hold, in one table: :data:`CELL_KINDS`.

Kinds are named as meshio names them and their nodes ordered as meshio (and VTK) order
them: corners first, then the mid-edge nodes in the order of :attr:`CellKind.edges`,
then face-centre nodes and a body-centre node where the kind has them.

For every kind the table gives the facets (outward for a cell of positive
orientation), the edges between corners, a fixed decomposition of the corner skeleton
into simplices (the signed volume of a cell is the sum of theirs) and one *corner frame*
per corner: the corner and its edge neighbours in right-handed order, whose
determinant is the Jacobian of the element at that corner (Knupp's scaled Jacobian
divides it by the edge lengths). A cell is *positively oriented* when its corner
Jacobians are positive; a cell given in the mirrored order (all of them negative) is a
valid cell of orientation −1: torchmorph keeps the file's node order and records the
orientation, so a mesh written back is the mesh read.

Quadratic kinds share the geometry measures of their linear kind (the corners): their
mid-side, face and body nodes are nodes like any other for a morph, and lie on the
boundary when their facet does, but they do not enter volumes or Jacobians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["CELL_KINDS", "FACET_KINDS", "TET_EDGES", "TET_OUTWARD_FACES", "CellKind", "cell_kind"]

#: The six edges of a tetrahedron as pairs of local vertex numbers.
TET_EDGES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))

#: The four faces, face k opposite vertex k, oriented outward when the tetrahedron's
#: signed volume is positive.
TET_OUTWARD_FACES: tuple[tuple[int, int, int], ...] = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))


@dataclass(frozen=True)
class CellKind:
    """One element kind.

    Attributes
    ----------
    name : str
        meshio's name (``"tetra"``, ``"hexahedron20"`` …).
    dim : int
        Topological dimension: 3 for volume cells, 2 for planar cells.
    num_nodes : int
        Nodes per cell.
    corners : int
        Corner nodes (the first ``corners`` of a cell).
    linear : str
        The linear kind of the same shape (itself for a linear kind).
    facets : tuple of (str, tuple of int)
        The facets (faces of a volume cell, edges of a planar one) with their kind and
        local nodes, outward for a positively oriented cell.
    edges : tuple of (int, int)
        Corner pairs joined by an edge.
    simplices : tuple of tuple of int
        Tetrahedra (triangles in 2-D) of corners that decompose the cell, each
        positively oriented in a positively oriented cell.
    corner_frames : tuple of tuple of int
        ``(corner, neighbour, neighbour[, neighbour])``: the edge vectors from the
        corner to its neighbours span a positive frame in a positively oriented cell.
    jacobian_scale : float
        Factor that makes the scaled Jacobian of the ideal element 1.
    mirror : tuple of int
        A node permutation that reverses the orientation.
    """

    name: str
    dim: int
    num_nodes: int
    corners: int
    linear: str
    facets: tuple[tuple[str, tuple[int, ...]], ...]
    edges: tuple[tuple[int, int], ...]
    simplices: tuple[tuple[int, ...], ...]
    corner_frames: tuple[tuple[int, ...], ...]
    jacobian_scale: float
    mirror: tuple[int, ...]
    is_simplex: bool = field(default=False)

    @property
    def is_linear(self) -> bool:
        return self.linear == self.name


#: Facet kinds: their corner count, the facet kind's mirror permutation (reversed
#: orientation, mid nodes following their edges) and the linear facet kind.
FACET_KINDS: dict[str, tuple[int, tuple[int, ...], str]] = {
    "line": (2, (1, 0), "line"),
    "line3": (2, (1, 0, 2), "line"),
    "triangle": (3, (0, 2, 1), "triangle"),
    "triangle6": (3, (0, 2, 1, 5, 4, 3), "triangle"),
    "quad": (4, (0, 3, 2, 1), "quad"),
    "quad8": (4, (0, 3, 2, 1, 7, 6, 5, 4), "quad"),
    "quad9": (4, (0, 3, 2, 1, 7, 6, 5, 4, 8), "quad"),
}

_SQRT2, _TWO_BY_SQRT3 = math.sqrt(2.0), 2.0 / math.sqrt(3.0)


def _linear(
    name: str,
    dim: int,
    facets: tuple[tuple[int, ...], ...],
    edges: tuple[tuple[int, int], ...],
    simplices: tuple[tuple[int, ...], ...],
    frames: tuple[tuple[int, ...], ...],
    scale: float,
    mirror: tuple[int, ...],
) -> CellKind:
    names = {2: "line", 3: "triangle", 4: "quad"}
    return CellKind(
        name=name,
        dim=dim,
        num_nodes=len(mirror),
        corners=len(mirror),
        linear=name,
        facets=tuple((names[len(f)], f) for f in facets),
        edges=edges,
        simplices=simplices,
        corner_frames=frames,
        jacobian_scale=scale,
        mirror=mirror,
        is_simplex=len(simplices) == 1,
    )


def _quadratic(
    base: CellKind,
    name: str,
    mids: tuple[tuple[int, int], ...],
    face_centres: tuple[tuple[int, ...], ...] = (),
    body_centre: bool = False,
) -> CellKind:
    """``base`` with a node on each edge of ``mids`` (in node order), then a node at the
    centre of each face (corner tuples, in node order) and optionally one at the body
    centre."""
    mid_of = {frozenset(pair): base.corners + k for k, pair in enumerate(mids)}
    centre_of = {
        frozenset(face): base.corners + len(mids) + k for k, face in enumerate(face_centres)
    }
    quadratic_names = {"line": "line3", "triangle": "triangle6", "quad": "quad8"}
    facets = []
    for kind, corners in base.facets:
        ring = [
            mid_of[frozenset(pair)] for pair in zip(corners, corners[1:] + corners[:1], strict=True)
        ]
        if kind == "line":
            ring = ring[:1]
        centre = centre_of.get(frozenset(corners))
        nodes = (*corners, *ring, *(() if centre is None else (centre,)))
        facets.append(("quad9" if centre is not None else quadratic_names[kind], nodes))
    count = base.corners + len(mids) + len(face_centres) + int(body_centre)
    mirror = list(range(count))
    mirror[: base.corners] = base.mirror
    for pair, node in mid_of.items():
        a, b = tuple(pair)
        mirror[node] = mid_of[frozenset((base.mirror[a], base.mirror[b]))]
    for face, node in centre_of.items():
        mirror[node] = centre_of[frozenset(base.mirror[c] for c in face)]
    return CellKind(
        name=name,
        dim=base.dim,
        num_nodes=count,
        corners=base.corners,
        linear=base.name,
        facets=tuple(facets),
        edges=base.edges,
        simplices=base.simplices,
        corner_frames=base.corner_frames,
        jacobian_scale=base.jacobian_scale,
        mirror=tuple(mirror),
    )


_TRIANGLE = _linear(
    "triangle",
    2,
    ((0, 1), (1, 2), (2, 0)),
    ((0, 1), (1, 2), (2, 0)),
    ((0, 1, 2),),
    ((0, 1, 2), (1, 2, 0), (2, 0, 1)),
    _TWO_BY_SQRT3,
    (0, 2, 1),
)
_QUAD = _linear(
    "quad",
    2,
    ((0, 1), (1, 2), (2, 3), (3, 0)),
    ((0, 1), (1, 2), (2, 3), (3, 0)),
    ((0, 1, 2), (0, 2, 3)),
    ((0, 1, 3), (1, 2, 0), (2, 3, 1), (3, 0, 2)),
    1.0,
    (0, 3, 2, 1),
)
_TETRA = _linear(
    "tetra",
    3,
    TET_OUTWARD_FACES,
    TET_EDGES,
    ((0, 1, 2, 3),),
    ((0, 1, 2, 3), (1, 2, 0, 3), (2, 0, 1, 3), (3, 0, 2, 1)),
    _SQRT2,
    (0, 1, 3, 2),
)
# the pyramid's base corner frames are the four tetrahedra on both diagonals of the base
_PYRAMID = _linear(
    "pyramid",
    3,
    ((0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)),
    ((0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4)),
    ((0, 1, 2, 4), (0, 2, 3, 4)),
    ((0, 1, 3, 4), (1, 2, 0, 4), (2, 3, 1, 4), (3, 0, 2, 4)),
    _SQRT2,
    (0, 3, 2, 1, 4),
)
_WEDGE = _linear(
    "wedge",
    3,
    ((0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)),
    ((0, 1), (1, 2), (2, 0), (3, 4), (4, 5), (5, 3), (0, 3), (1, 4), (2, 5)),
    ((0, 1, 2, 3), (1, 2, 3, 4), (2, 3, 4, 5)),
    ((0, 1, 2, 3), (1, 2, 0, 4), (2, 0, 1, 5), (3, 5, 4, 0), (4, 3, 5, 1), (5, 4, 3, 2)),
    _TWO_BY_SQRT3,
    (0, 2, 1, 3, 5, 4),
)
_HEXAHEDRON = _linear(
    "hexahedron",
    3,
    ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)),
    (
        (0, 1),
        (1, 2),
        (2, 3),
        (3, 0),
        (4, 5),
        (5, 6),
        (6, 7),
        (7, 4),
        (0, 4),
        (1, 5),
        (2, 6),
        (3, 7),
    ),
    ((0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)),
    (
        (0, 1, 3, 4),
        (1, 2, 0, 5),
        (2, 3, 1, 6),
        (3, 0, 2, 7),
        (4, 7, 5, 0),
        (5, 4, 6, 1),
        (6, 5, 7, 2),
        (7, 6, 4, 3),
    ),
    1.0,
    (0, 3, 2, 1, 4, 7, 6, 5),
)

_KINDS = [
    _TRIANGLE,
    _QUAD,
    _TETRA,
    _PYRAMID,
    _WEDGE,
    _HEXAHEDRON,
    _quadratic(_TRIANGLE, "triangle6", ((0, 1), (1, 2), (2, 0))),
    _quadratic(_QUAD, "quad8", ((0, 1), (1, 2), (2, 3), (3, 0))),
    _quadratic(_QUAD, "quad9", ((0, 1), (1, 2), (2, 3), (3, 0)), body_centre=True),
    _quadratic(_TETRA, "tetra10", ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))),
    _quadratic(
        _PYRAMID, "pyramid13", ((0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4))
    ),
    _quadratic(
        _PYRAMID,
        "pyramid14",
        ((0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4)),
        face_centres=((0, 1, 2, 3),),
    ),
    _quadratic(_WEDGE, "wedge15", _WEDGE.edges),
    _quadratic(
        _WEDGE, "wedge18", _WEDGE.edges, face_centres=((0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5))
    ),
    _quadratic(_HEXAHEDRON, "hexahedron20", _HEXAHEDRON.edges),
    _quadratic(
        _HEXAHEDRON,
        "hexahedron27",
        _HEXAHEDRON.edges,
        face_centres=(
            (0, 3, 7, 4),
            (1, 2, 6, 5),
            (0, 1, 5, 4),
            (3, 2, 6, 7),
            (0, 1, 2, 3),
            (4, 5, 6, 7),
        ),
        body_centre=True,
    ),
]

#: Every kind a mesh may hold, by meshio's name.
CELL_KINDS: dict[str, CellKind] = {kind.name: kind for kind in _KINDS}


def cell_kind(name: str, *, argument: str = "cells") -> CellKind:
    """The :class:`CellKind` named ``name``; ``ValueError`` naming ``argument`` and the
    supported kinds otherwise."""
    try:
        return CELL_KINDS[name]
    except (KeyError, TypeError):
        known = ", ".join(CELL_KINDS)
        raise ValueError(
            f"{argument}: cell kind {name!r} is not supported; the supported kinds are {known}"
        ) from None
