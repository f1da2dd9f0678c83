"""Exodus II element types, node orders and side numbering, as tables.

From the Exodus II manual (SEACAS, "Exodus: A Finite Element Data Model", the element
topology figures and the table "Sideset Node Ordering") and checked against SEACAS's
Ioss element topologies (``Ioss_Hex20.C``, ``Ioss_Wedge15.C`` … ``face_node_order``),
node numbers 0-based here:

* **Element types** are read by family and node count (``HEX`` with 20 nodes is a
  HEX20, as older files and SEACAS's own VTK adapter read it); a number in the name
  must equal the block's node count. Accepted families (upper or lower case):
  ``TETRA``/``TET`` (4, 10), ``HEX``/``HEXAHEDRON`` (8, 20, 27), ``WEDGE`` (6, 15, 18),
  ``PYRAMID``/``PYRA`` (5, 13, 14), ``TRI``/``TRIANGLE`` (3, 6), ``QUAD`` (4, 8, 9),
  the structural shells ``SHELL`` (4, 8, 9) and ``TRISHELL`` (3, 6), and the 1-D
  ``BAR``/``BEAM``/``TRUSS`` (2, 3), all without a separator (``HEX20``, ``TRISHELL6``).
  Points (``SPHERE``, ``CIRCLE``) and every other type (``HEX9``, ``TETRA14``,
  ``QUAD5``, ``TRI7``, ``NSIDED``, ``NFACED`` …) are refused by name.
* **Node orders.** Exodus numbers a quadratic cell's corners first, then the mid-edge
  nodes, then the face and body centres, like VTK (meshio), but orders some groups
  differently: HEX20/HEX27 put the four vertical edges (1-5, 2-6, 3-7, 4-8) before the
  top ones, VTK after; WEDGE15/WEDGE18 likewise the vertical edges before the top
  triangle's; HEX27 puts the body centre first (node 21) and its face centres in side
  order (sides 5, 6, 4, 2, 1, 3), VTK the face centres x-, x+, y-, y+, z-, z+ and the
  body centre last. TETRA10, PYRAMID13/14, WEDGE18's face centres, TRI6, QUAD8/9 agree.
  The linear kinds agree too (a WEDGE is taken as meshio's ``wedge`` unchanged, as
  meshio, ParaView and SEACAS's VTK adapter take it; torchmorph records each cell's
  orientation whichever way it turns).
* **Sides** (:data:`SIDES`): side ``i`` of each kind lists its corners so that the
  outward normal follows the right-hand rule (in 2-D, the edges run counter-clockwise
  round a counter-clockwise cell), then its mid-edge nodes, then a face centre, exactly
  as ``ex_get_side_set_node_list`` lists them; the facet's node order is meshio's for
  ``line3``/``triangle6``/``quad8``/``quad9``. A 2-D QUAD or TRI numbers its edges 1..4
  (1..3); a SHELL's sides 1 and 2 are its faces and 3..6 its edges (TRISHELL 3..5).

:class:`SideIndex` finds the cell and side number of a facet given by its nodes (for
writing face sets as side sets, and for checking that a block of facets lies on cells).
"""

from __future__ import annotations

import re
from typing import NamedTuple, NoReturn

import numpy as np

__all__ = [
    "EXODUS_TYPES",
    "FACET_CORNERS",
    "SIDES",
    "TO_VTK",
    "Block",
    "ElementType",
    "Side",
    "SideIndex",
    "element_type",
    "facet_kind",
    "side_table",
]


class ElementType(NamedTuple):
    """An element block's type: meshio's ``kind``, the topological dimension, and the
    side table (a key of :data:`SIDES`; ``None`` for kinds that have no sides here)."""

    kind: str
    dim: int
    sides: str | None


# family -> (dimension, side table, {node count: meshio kind})
_SOLID_TETRA = (3, "tetra", {4: "tetra", 10: "tetra10"})
_SOLID_HEX = (3, "hexahedron", {8: "hexahedron", 20: "hexahedron20", 27: "hexahedron27"})
_SOLID_PYRAMID = (3, "pyramid", {5: "pyramid", 13: "pyramid13", 14: "pyramid14"})
_PLANE_TRI = (2, "triangle", {3: "triangle", 6: "triangle6"})
_LINE = (1, None, {2: "line", 3: "line3"})
_FAMILIES: dict[str, tuple[int, str | None, dict[int, str]]] = {
    "TETRA": _SOLID_TETRA,
    "TET": _SOLID_TETRA,
    "HEX": _SOLID_HEX,
    "HEXAHEDRON": _SOLID_HEX,
    "WEDGE": (3, "wedge", {6: "wedge", 15: "wedge15", 18: "wedge18"}),
    "PYRAMID": _SOLID_PYRAMID,
    "PYRA": _SOLID_PYRAMID,
    "TRI": _PLANE_TRI,
    "TRIANGLE": _PLANE_TRI,
    "QUAD": (2, "quad", {4: "quad", 8: "quad8", 9: "quad9"}),
    "SHELL": (2, "shell", {4: "quad", 8: "quad8", 9: "quad9"}),
    "TRISHELL": (2, "trishell", {3: "triangle", 6: "triangle6"}),
    "BAR": _LINE,
    "BEAM": _LINE,
    "TRUSS": _LINE,
    "SPHERE": (0, None, {1: "vertex"}),
    "CIRCLE": (0, None, {1: "vertex"}),
}

#: What :func:`element_type` accepts, for messages.
ACCEPTED = (
    "TETRA/TET (4, 10 nodes), HEX/HEXAHEDRON (8, 20, 27), WEDGE (6, 15, 18), "
    "PYRAMID/PYRA (5, 13, 14), TRI/TRIANGLE (3, 6), QUAD (4, 8, 9), SHELL (4, 8, 9), "
    "TRISHELL (3, 6), BAR/BEAM/TRUSS (2, 3), optionally with the node count (HEX20)"
)


def element_type(name: str, nodes: int) -> ElementType:
    """The :class:`ElementType` of an ``elem_type`` attribute and a block's node count;
    ``ValueError`` (without a location: the caller names the block) for any other."""
    match = re.fullmatch(r"([A-Z]+?)(\d*)", name.strip().upper())
    family = _FAMILIES.get(match.group(1)) if match else None
    if family is None or not match:
        raise ValueError(f"element type {name!r} is not supported; supported: {ACCEPTED}")
    dim, sides, counts = family
    digits = match.group(2)
    if digits and int(digits) != nodes:
        raise ValueError(
            f"element type {name!r} names {int(digits)} nodes per element, the block has {nodes}"
        )
    kind = counts.get(int(digits) if digits else nodes)
    if kind is None:
        raise ValueError(
            f"element type {name!r} with {nodes} nodes per element is not supported; "
            f"supported: {ACCEPTED}"
        )
    return ElementType(kind, dim, sides)


#: Exodus's node order -> meshio's (VTK's) where they differ: ``vtk = exodus[:, order]``.
TO_VTK: dict[str, tuple[int, ...]] = {
    "hexahedron20": (*range(12), 16, 17, 18, 19, 12, 13, 14, 15),
    "hexahedron27": (*range(12), 16, 17, 18, 19, 12, 13, 14, 15, 23, 24, 25, 26, 21, 22, 20),
    "wedge15": (*range(9), 12, 13, 14, 9, 10, 11),
    "wedge18": (*range(9), 12, 13, 14, 9, 10, 11, 15, 16, 17),
}

#: The element type written for each kind: SEACAS's names, the linear kinds' in the
#: spelling that both SEACAS (as aliases) and meshio's Exodus reader know.
EXODUS_TYPES: dict[str, str] = {
    "tetra": "TETRA",
    "tetra10": "TETRA10",
    "hexahedron": "HEX8",
    "hexahedron20": "HEX20",
    "hexahedron27": "HEX27",
    "wedge": "WEDGE",
    "wedge15": "WEDGE15",
    "wedge18": "WEDGE18",
    "pyramid": "PYRAMID",
    "pyramid13": "PYRAMID13",
    "pyramid14": "PYRAMID14",
    "triangle": "TRI3",
    "triangle6": "TRI6",
    "quad": "QUAD4",
    "quad8": "QUAD8",
    "quad9": "QUAD9",
}


def side_table(kind: str) -> str:
    """The side table (a key of :data:`SIDES`) of a kind written as :data:`EXODUS_TYPES`
    names it (a 2-D QUAD's or TRI's edges)."""
    return re.sub(r"\d+$", "", kind)


class Side(NamedTuple):
    """One side: its corners, mid-edge nodes and face centre (or None), Exodus order."""

    corners: tuple[int, ...]
    mids: tuple[int, ...]
    centre: int | None = None
    face: bool = False  # a shell's face: no facet of a planar mesh


def _sides(*rows: tuple) -> tuple[Side, ...]:
    return tuple(Side(*row) for row in rows)


#: Side ``i`` (1-based) of each side table is ``SIDES[table][i - 1]`` (Exodus II manual,
#: "Sideset Node Ordering", 0-based; face centres from the element figures).
SIDES: dict[str, tuple[Side, ...]] = {
    "tetra": _sides(
        ((0, 1, 3), (4, 8, 7)),
        ((1, 2, 3), (5, 9, 8)),
        ((0, 3, 2), (7, 9, 6)),
        ((0, 2, 1), (6, 5, 4)),
    ),
    "wedge": _sides(
        ((0, 1, 4, 3), (6, 10, 12, 9), 15),
        ((1, 2, 5, 4), (7, 11, 13, 10), 16),
        ((0, 3, 5, 2), (9, 14, 11, 8), 17),
        ((0, 2, 1), (8, 7, 6)),
        ((3, 4, 5), (12, 13, 14)),
    ),
    "hexahedron": _sides(
        ((0, 1, 5, 4), (8, 13, 16, 12), 25),
        ((1, 2, 6, 5), (9, 14, 17, 13), 24),
        ((2, 3, 7, 6), (10, 15, 18, 14), 26),
        ((0, 4, 7, 3), (12, 19, 15, 11), 23),
        ((0, 3, 2, 1), (11, 10, 9, 8), 21),
        ((4, 5, 6, 7), (16, 17, 18, 19), 22),
    ),
    "pyramid": _sides(
        ((0, 1, 4), (5, 10, 9)),
        ((1, 2, 4), (6, 11, 10)),
        ((2, 3, 4), (7, 12, 11)),
        ((3, 0, 4), (8, 9, 12)),
        ((0, 3, 2, 1), (8, 7, 6, 5), 13),
    ),
    "quad": _sides(((0, 1), (4,)), ((1, 2), (5,)), ((2, 3), (6,)), ((3, 0), (7,))),
    "triangle": _sides(((0, 1), (3,)), ((1, 2), (4,)), ((2, 0), (5,))),
    "shell": _sides(
        ((0, 1, 2, 3), (4, 5, 6, 7), 8, True),
        ((0, 3, 2, 1), (7, 6, 5, 4), 8, True),
        ((0, 1), (4,)),
        ((1, 2), (5,)),
        ((2, 3), (6,)),
        ((3, 0), (7,)),
    ),
    "trishell": _sides(
        ((0, 1, 2), (3, 4, 5), None, True),
        ((0, 2, 1), (5, 4, 3), None, True),
        ((0, 1), (3,)),
        ((1, 2), (4,)),
        ((2, 0), (5,)),
    ),
}

#: Kinds with face-centre nodes (their sides list the centre where they have one).
_CENTRED = {"hexahedron27", "wedge18", "pyramid14", "quad9"}


def facet_kind(kind: str, side: Side) -> tuple[str, tuple[int, ...]]:
    """The facet kind of a side of a cell of ``kind`` and its local nodes (Exodus order)."""
    quadratic = kind[-1].isdigit()
    nodes = side.corners + (side.mids if quadratic else ())
    name = {2: "line", 3: "triangle", 4: "quad"}[len(side.corners)]
    if quadratic:
        name = {"line": "line3", "triangle": "triangle6", "quad": "quad8"}[name]
        if side.centre is not None and kind in _CENTRED:
            nodes, name = (*nodes, side.centre), "quad9"
    return name, nodes


class Block(NamedTuple):
    """An element block: ``number`` (its position, 1-based: ``connect<number>``), ``id``,
    ``name``, a ``label`` for messages, its type, the connectivity (M, n) 0-based in
    Exodus's node order, and ``start``, the global (0-based) number of its first element."""

    number: int
    id: int
    name: str
    label: str
    type: ElementType
    nodes: np.ndarray
    start: int


class SideIndex:
    """Every side of the cells of some blocks, to find the cell and side of a facet.

    The sides are keyed by their sorted corners (two int64 keys: the two smallest corners
    and the other two, each pair ``a * num_points + b``), sorted once per corner count; a
    facet is looked up by binary search. ``num_points`` bounds every node number of the
    cells and of the facets looked up (a facet may use a node no cell does).
    """

    def __init__(self, blocks: list[Block], num_points: int) -> None:
        self.blocks = blocks
        self._size = int(num_points)
        used = max((int(b.nodes.max()) for b in blocks if b.nodes.size), default=-1)
        if used >= self._size:
            raise ValueError(f"num_points: {num_points}, but the cells use node {used}")
        self._parts: dict[int, list[tuple[np.ndarray, int, int, int]]] = {}
        for position, block in enumerate(blocks):
            assert block.type.sides is not None
            count = block.nodes.shape[0]
            for number, side in enumerate(SIDES[block.type.sides], 1):
                if not side.face:
                    self._parts.setdefault(len(side.corners), []).append(
                        (block.nodes[:, list(side.corners)], position, count, number)
                    )
        self._sorted: dict[int, tuple[np.ndarray, ...]] = {}

    def _keys(self, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ordered = np.sort(corners, axis=1).astype(np.int64)
        size, width = self._size, ordered.shape[1]
        first = ordered[:, 0] * size + ordered[:, 1]
        if width == 2:
            return first, np.zeros_like(first)
        if width == 3:
            return first, ordered[:, 2]
        return first, ordered[:, 2] * size + ordered[:, 3]

    def _candidates(self, width: int) -> tuple[np.ndarray, ...]:
        """(oriented corners, block positions, rows, sides, first keys, second keys), sorted
        by the keys."""
        if width not in self._sorted:
            parts = self._parts[width]
            oriented = np.concatenate([corners for corners, *_ in parts])
            owner = np.concatenate([np.full(count, p) for _, p, count, _ in parts])
            rows = np.concatenate([np.arange(count) for _, _, count, _ in parts])
            sides = np.concatenate([np.full(count, number) for *_, count, number in parts])
            first, second = self._keys(oriented)
            order = np.lexsort((second, first))
            columns = (oriented, owner, rows, sides, first, second)
            self._sorted[width] = tuple(column[order] for column in columns)
        return self._sorted[width]

    def find(self, kind: str, nodes: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray]:
        """The global element numbers (0-based) and side numbers (1-based) of the facets
        ``nodes`` (K, n) of ``kind``. Where a facet is the side of two cells (an interior
        facet), the cell whose side turns as the facet's corners do. ``ValueError`` naming
        ``label`` and the row for a facet that is no cell's side, or not all of it."""
        width = FACET_CORNERS[kind]
        if not len(nodes):
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        if nodes.min() < 0 or nodes.max() >= self._size:
            raise ValueError(f"{label}: node numbers outside [0, {self._size})")
        if width not in self._parts:
            _no_side(label, kind, nodes, 0)
        corners = nodes[:, :width]
        oriented, owner, rows, sides, first_keys, second_keys = self._candidates(width)
        first, second = self._keys(corners)
        left = np.searchsorted(first_keys, first, side="left")
        right = np.searchsorted(first_keys, first, side="right")
        found = np.full((2, len(nodes)), -1)  # the first two sides with these corners
        for offset in range(int((right - left).max())):
            at = np.minimum(left + offset, len(first_keys) - 1)
            hit = (left + offset < right) & (second_keys[at] == second)
            slot = np.where(found[0] < 0, 0, 1)
            store = hit & (found[1] < 0)
            found[slot[store], np.flatnonzero(store)] = at[store]
        missing = np.flatnonzero(found[0] < 0)
        if missing.size:
            _no_side(label, kind, nodes, int(missing[0]))
        first_side, second_side = found[0], np.where(found[1] < 0, found[0], found[1])
        pick = ~_turns_as(oriented[first_side], corners) & _turns_as(oriented[second_side], corners)
        chosen = np.where(pick, second_side, first_side)
        owner, rows, sides = owner[chosen], rows[chosen], sides[chosen]
        for position, number in {(int(p), int(s)) for p, s in zip(owner, sides, strict=True)}:
            block = self.blocks[position]
            assert block.type.sides is not None
            side_kind, local = facet_kind(block.type.kind, SIDES[block.type.sides][number - 1])
            where = np.flatnonzero((owner == position) & (sides == number))
            row = int(where[0])
            element = f"side {number} of element {block.start + int(rows[row]) + 1} ({block.label})"
            if side_kind != kind:
                raise ValueError(
                    f"{label}: row {row} ({kind} {nodes[row].tolist()}) is {element}, a "
                    f"{side_kind}: give it as a {side_kind}"
                )
            full = np.sort(block.nodes[rows[where]][:, list(local)], axis=1)
            differ = np.flatnonzero((full != np.sort(nodes[where], axis=1)).any(1))
            if differ.size:
                row = int(where[differ[0]])
                raise ValueError(
                    f"{label}: row {row} ({kind} {nodes[row].tolist()}) has the corners of "
                    f"{element} but not its other nodes"
                )
        starts = np.array([block.start for block in self.blocks], dtype=np.int64)
        return starts[owner] + rows, sides.astype(np.int64)


#: Corners of each facet kind.
FACET_CORNERS = {"line": 2, "line3": 2, "triangle": 3, "triangle6": 3}
FACET_CORNERS |= {"quad": 4, "quad8": 4, "quad9": 4}


def _turns_as(sides: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Whether each row of ``sides`` lists the corners of the same row of ``corners`` in
    the same cyclic order (an edge: the same order)."""
    if corners.shape[1] == 2:
        return sides[:, 0] == corners[:, 0]
    rows = np.arange(len(corners))
    width = corners.shape[1]
    after = sides[rows, (sides.argmin(1) + 1) % width]
    return after == corners[rows, (corners.argmin(1) + 1) % width]


def _no_side(label: str, kind: str, nodes: np.ndarray, row: int) -> NoReturn:
    raise ValueError(
        f"{label}: row {row} ({kind} {nodes[row].tolist()}) is no side of a cell of the mesh"
    )
