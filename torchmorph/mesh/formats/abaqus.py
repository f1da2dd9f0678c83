"""CalculiX / Abaqus input decks (``.inp``, ``.inp.gz``): read the mesh, write the whole
deck back with only the coordinates of the nodes changed.

:func:`read_deck` reads a deck and the files it ``*INCLUDE``\\ s into an
:class:`AbaqusDeck`, which keeps the text of every file and the line of every node;
:meth:`AbaqusDeck.to_mesh_data` gives the mesh as a :class:`MeshData` (nodes in number
order, the solid or plane elements as cell blocks in meshio's node order, every node set);
:func:`write_deck` writes the deck with new node coordinates, every other byte as read,
so that the solver (``ccx``) runs the morphed deck with the same materials, steps, loads
and boundary conditions.

The reading follows CalculiX's (``readinput.c``, ``nodes.f``, ``elements.f``,
``noelsets.f``); see :mod:`torchmorph.mesh.formats._abaqus_parse` for the details.
"""

from __future__ import annotations

import gzip
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.formats._abaqus_parse import (
    DeckFile,
    ElementBlock,
    canonical_type,
    parse_deck,
)
from torchmorph.mesh.formats._abaqus_tables import find, resolve
from torchmorph.mesh.formats._data import MeshData

__all__ = [
    "CALCULIX_FIELD_WIDTH",
    "AbaqusDeck",
    "DeckFile",
    "ElementBlock",
    "element_kind",
    "format_coordinate",
    "read_deck",
    "write_deck",
]

#: Characters of a coordinate field that CalculiX reads: ``nodes.f`` reads
#: ``textpart(2)(1:20)`` with the format ``(f20.0)``, so a longer number is cut.
CALCULIX_FIELD_WIDTH = 20

#: Element families that are cells of the domain, and the meshio kind for each node count.
#: CalculiX's node orders (its manual's figures, Abaqus's) are meshio's for all of them, so
#: no permutation is applied: C3D10 corners then edges 1-2, 2-3, 3-1, 1-4, 2-4, 3-4; C3D20
#: corners, bottom edges, top edges, vertical edges; C3D15 corners, edges of the bottom
#: triangle, of the top one, then the three vertical edges. A wedge's first triangle
#: (1, 2, 3) turns counter-clockwise seen from the second one (4, 5, 6), as in Gmsh, in
#: meshio's own Abaqus and Gmsh readers and in :mod:`torchmorph.mesh.cells`; VTK's wedge
#: is the mirror image of that (its first triangle's normal points away from the
#: second), so a signed volume written for VTK's wedge comes out negative for these.
#: Every cell of CalculiX's 355 test decks has positive corner volumes in this order.
_KIND_PATTERNS: tuple[tuple[re.Pattern[str], dict[int, str]], ...] = (
    (
        re.compile(r"C3D(4|5|6|8|10|15|20)[A-Z]*"),
        {
            4: "tetra",
            5: "pyramid",
            6: "wedge",
            8: "hexahedron",
            10: "tetra10",
            15: "wedge15",
            20: "hexahedron20",
        },
    ),
    (re.compile(r"F3D(4|6|8)R?"), {4: "tetra", 6: "wedge", 8: "hexahedron"}),
    (
        re.compile(r"(?:CPS|CPE|CAX)(3|4|6|8)[A-Z]*"),
        {3: "triangle", 4: "quad", 6: "triangle6", 8: "quad8"},
    ),
)
_PLANE_KINDS = frozenset({"triangle", "quad", "triangle6", "quad8"})


def element_kind(element_type: str) -> str | None:
    """The meshio kind of a CalculiX/Abaqus element type that is a cell of a domain.

    Parameters
    ----------
    element_type : str
        The ``TYPE=`` of an ``*ELEMENT`` keyword, any case.

    Returns
    -------
    str or None
        ``"tetra"`` (C3D4, F3D4), ``"tetra10"`` (C3D10, C3D10T, C3D10M …),
        ``"hexahedron"`` (C3D8, C3D8R, C3D8I, C3D8T, F3D8 …), ``"hexahedron20"`` (C3D20,
        C3D20R …), ``"wedge"`` (C3D6, F3D6), ``"wedge15"`` (C3D15), ``"pyramid"`` (C3D5),
        ``"triangle"``/``"quad"``/``"triangle6"``/``"quad8"`` (CPS/CPE/CAX with 3, 4, 6, 8
        nodes, with or without R); heat-transfer types (``DC3D8`` …) as their solid twin.
        None for anything else: springs, masses, dashpots, gaps, beams, trusses, shells,
        membranes, network and coupling elements, user elements.
    """
    name = canonical_type(element_type)
    for pattern, kinds in _KIND_PATTERNS:
        match = pattern.fullmatch(name)
        if match:
            return kinds[int(match.group(1))]
    return None


def format_coordinate(value: float) -> str:
    """A coordinate as :func:`write_deck` writes it: the shortest text that reads back as
    the same float64 (``repr``), or, where that is longer than CalculiX's 20-character
    field (``-1.2345678901234567e-05``), the most significant digits that fit
    (``-1.2345678901235e-05``): 14 or 15 digits, a relative change below 5e-14, where
    the exponent has two digits, 13 digits (below 5e-13) where it has three."""
    text = repr(float(value))
    digits = 16
    while len(text) > CALCULIX_FIELD_WIDTH:
        text = f"{float(value):.{digits}e}"
        digits -= 1
    return text


def _type_counts(blocks: list[ElementBlock]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for block in blocks:
        counts[block.type] = counts.get(block.type, 0) + len(block.ids)
    return counts


@dataclass(eq=False, repr=False)
class AbaqusDeck:
    """A deck as read by :func:`read_deck`: its files' text and its mesh.

    Attributes
    ----------
    path : Path
        The main file.
    files : list of DeckFile
        The main file first, then every included file in the order first included, each
        with its text (lines as read) and its path relative to the main file's directory.
    node_ids : ndarray, shape (N,), int64
        Node numbers, ascending: row ``i`` of ``points`` is node ``node_ids[i]``.
    points : ndarray, shape (N, 3), float64
        Node coordinates as read (omitted trailing coordinates are 0).
    node_files, node_lines : ndarray, shape (N,), int64
        Where each node's line is: index in ``files`` and 0-based line index.
    element_blocks : list of ElementBlock
        Every ``*ELEMENT`` keyword's elements, of any type, in the deck's order.
    node_sets : dict of str to ndarray (K,) int64
        Every node set (``*NSET`` and ``NSET=`` on ``*NODE``) as node numbers, ascending.
    element_sets : dict of str to ndarray (K,) int64
        Every element set (``*ELSET`` and ``ELSET=`` on ``*ELEMENT``) as element numbers.
    warnings : list of str
        What was read but left aside as CalculiX leaves it (set members that are no node
        or element, extra nodes on an element line), each naming its file and line.
    """

    path: Path
    files: list[DeckFile]
    node_ids: np.ndarray
    points: np.ndarray
    node_files: np.ndarray
    node_lines: np.ndarray
    element_blocks: list[ElementBlock]
    node_sets: dict[str, np.ndarray]
    element_sets: dict[str, np.ndarray]
    warnings: list[str]

    def __repr__(self) -> str:
        types = ", ".join(f"{t} ({n})" for t, n in _type_counts(self.element_blocks).items())
        return (
            f"AbaqusDeck({str(self.path)!r}, {len(self.node_ids)} nodes, elements: "
            f"{types or 'none'}, {len(self.files)} file(s))"
        )

    @property
    def unsupported_elements(self) -> dict[str, int]:
        """Element types that are no cell of the domain (:func:`element_kind` is None),
        with how many elements of each the deck holds."""
        blocks = [b for b in self.element_blocks if element_kind(b.type) is None]
        return _type_counts(blocks)

    @property
    def dimension(self) -> int:
        """2 where the deck's cells are all plane/axisymmetric (CPS, CPE, CAX) and every
        node has z = 0, otherwise 3: the columns of :meth:`to_mesh_data`'s points."""
        kinds = {element_kind(block.type) for block in self.element_blocks} - {None}
        if kinds and kinds <= _PLANE_KINDS and not self.points[:, 2].any():
            return 2
        return 3

    def node_rows(self, node_ids: Any) -> np.ndarray:
        """Rows of ``points`` for node numbers ``node_ids`` (any shape; ValueError for a
        number no node has)."""
        wanted = np.asarray(node_ids, dtype=np.int64)
        rows, found = find(self.node_ids, wanted)
        if not found.all():
            raise ValueError(f"node_ids: {wanted[~found].ravel()[0]} is no node of the deck")
        return rows.astype(np.int64)

    def to_mesh_data(self, *, ignore_unsupported: bool = False) -> MeshData:
        """The deck's mesh: nodes, solid (or plane) cells and node sets.

        Parameters
        ----------
        ignore_unsupported : bool, optional
            Accept a deck that also holds elements that are no cell of the domain
            (springs, masses, gaps, beams, shells, coupling or user elements, listed in
            :attr:`unsupported_elements`): they are left out of ``cells``. Their nodes are
            still nodes: rows of ``points`` that a morph moves like any other and that
            :func:`write_deck` writes. Nothing checks those elements' shape after a morph
            and a boundary computed from ``cells`` does not see them, so a beam or shell
            lying off the solid moves by whatever the morph gives its nodes. Default
            False: such a deck raises.

        Returns
        -------
        MeshData
            ``points`` (N, 3) in node-number order (:attr:`node_ids`), or (N, 2) for a
            plane deck (:attr:`dimension`); ``cells`` one block per ``*ELEMENT`` keyword
            of a cell type, in the deck's order, as rows of ``points`` in meshio's node
            order; ``cell_data["element_id"]`` the element numbers of each block;
            ``node_sets`` every node set as rows. Element sets stay in
            :attr:`element_sets`.

        Raises
        ------
        ValueError
            If the deck defines no node (a ``*RESTART, READ`` deck takes its mesh from
            the restart file), holds element types that are no cell without
            ``ignore_unsupported``, or mixes 3-D solid and 2-D plane elements.
        """
        if not len(self.node_ids):
            raise ValueError(f"{self.path}: the deck defines no nodes")
        unsupported = self.unsupported_elements
        if unsupported and not ignore_unsupported:
            listed = ", ".join(f"{name} ({count})" for name, count in unsupported.items())
            raise ValueError(
                f"{self.path}: elements of types {listed} are not solid or plane cells; "
                "pass ignore_unsupported=True to take the mesh without them (their nodes "
                "stay nodes and move with the morph)"
            )
        blocks = [b for b in self.element_blocks if element_kind(b.type) is not None]
        solid = sorted({b.type for b in blocks if element_kind(b.type) not in _PLANE_KINDS})
        plane = sorted({b.type for b in blocks if element_kind(b.type) in _PLANE_KINDS})
        if solid and plane:
            raise ValueError(
                f"{self.path}: the deck mixes 3-D solid elements ({', '.join(solid)}) with "
                f"2-D plane elements ({', '.join(plane)}); a mesh has cells of one dimension"
            )
        cells = [(str(element_kind(b.type)), self.node_rows(b.nodes)) for b in blocks if len(b.ids)]
        element_ids = [b.ids.copy() for b in blocks if len(b.ids)]
        return MeshData(
            points=self.points[:, : self.dimension].copy(),
            cells=cells,
            node_sets={name: self.node_rows(ids) for name, ids in self.node_sets.items()},
            cell_data={"element_id": element_ids} if cells else {},
        )


def read_deck(path: str | os.PathLike) -> AbaqusDeck:
    """Read a CalculiX/Abaqus input deck and every file it includes.

    Parameters
    ----------
    path : str or PathLike
        The deck (``.inp``, or gzip-compressed ``.inp.gz``).

    Returns
    -------
    AbaqusDeck

    Raises
    ------
    FileNotFoundError
        If ``path`` is no file.
    ValueError
        For malformed input, naming the file and the line: a node or element line whose
        number or coordinates do not read, an element whose continuation line is missing,
        an element that refers to an undefined node, a node or element defined twice, a
        ``GENERATE`` range that is not ``0 < first <= last`` with a positive step, a set
        name used before it is defined, a keyword without its required parameter
        (``*ELEMENT`` without ``TYPE=``), an ``*INCLUDE`` whose file is missing.

    Notes
    -----
    Everything but the mesh (materials, sections, steps, loads, boundary conditions,
    ``*HEADING`` text, comments) is kept as text only. ``*INCLUDE, INPUT=`` names a file
    relative to the including file's directory or, as CalculiX (which runs in the main
    deck's directory) reads it, relative to the main deck's directory; ``INPUT=`` on
    ``*NODE``, ``*ELEMENT``, ``*NSET`` or ``*ELSET`` (data lines in a file of their own)
    is read the same way. Node-generating keywords (``*NGEN``, ``*NFILL``, ``*NCOPY``,
    ``*ELGEN``), which CalculiX does not read either, are not expanded.
    """
    source = Path(path)
    if not source.is_file():
        raise FileNotFoundError(f"path: {str(source)!r} is not a file")
    parsed = parse_deck(source)
    tables = resolve(parsed)
    return AbaqusDeck(
        path=source,
        files=parsed.files,
        node_ids=tables.node_ids,
        points=tables.points,
        node_files=tables.node_files,
        node_lines=tables.node_lines,
        element_blocks=parsed.blocks,
        node_sets=tables.node_sets,
        element_sets=tables.element_sets,
        warnings=tables.warnings,
    )


def _checked_points(deck: AbaqusDeck, points: Any) -> np.ndarray:
    if hasattr(points, "detach"):  # a torch tensor
        points = points.detach().cpu().numpy()
    array = np.asarray(points, dtype=np.float64)
    count = len(deck.node_ids)
    columns = (3, 2) if deck.dimension == 2 else (3,)
    if array.ndim != 2 or array.shape[0] != count or array.shape[1] not in columns:
        wanted = " or ".join(f"({count}, {c})" for c in columns)
        raise ValueError(
            f"points: expected shape {wanted} (one row per node of the deck), "
            f"got {tuple(array.shape)}"
        )
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise ValueError(f"points: row {row} (node {deck.node_ids[row]}) is not finite")
    if array.shape[1] == 2:
        full = deck.points.copy()
        full[:, :2] = array
        return full
    return array


def _replace_token(field: str, text: str) -> str:
    """``field`` with its content (between leading and trailing blanks) replaced."""
    content = field.strip()
    if not content:  # an empty field (read as 0): its blanks stay before the number
        return field + text
    start = field.index(content)
    return field[:start] + text + field[start + len(content) :]


def _rewrite_node_line(line: str, old: np.ndarray, new: np.ndarray) -> str:
    """A node line with its changed coordinates replaced, everything else as it was."""
    body = line.rstrip("\r\n")
    fields = body.split(",")
    changed = [bool(new[j] != old[j]) for j in range(3)]
    needed = max((j + 1 for j in range(3) if changed[j]), default=0)
    present = len(fields) - 1
    fields += [" "] * (needed - present)  # omitted trailing coordinates (0) get fields
    for j in range(needed):
        if changed[j] or j >= present:
            fields[j + 1] = _replace_token(fields[j + 1], format_coordinate(new[j]))
    return ",".join(fields) + line[len(body) :]


def _destinations(deck: AbaqusDeck, target: Path, changed: set[int]) -> list[Path | None]:
    """Where each file goes (None: left where it is), or ValueError where it cannot go."""
    in_place = target.resolve() == deck.path.resolve()
    same_directory = target.parent.resolve() == deck.path.parent.resolve()
    destinations: list[Path | None] = [target]
    for index, file in enumerate(deck.files[1:], start=1):
        parent = file.included_by if file.included_by is not None else 0
        including = f"(included as {file.reference!r} by {str(deck.files[parent].path)!r})"
        if file.name is None:
            if index in changed:
                raise ValueError(
                    f"path: the included file {str(file.path)!r} {including} holds moved "
                    "nodes but lies outside the deck's directory; write_deck writes "
                    "included files beside the deck under the same relative names"
                )
            moved_including = destinations[parent] is not None
            absolute = Path(str(file.reference)).is_absolute()
            if moved_including and not same_directory and not absolute:
                raise ValueError(
                    f"path: the included file {str(file.path)!r} {including} lies outside "
                    "the deck's directory and its relative reference would not reach it "
                    "from the new directory; write into the deck's own directory"
                )
            destinations.append(None)
            continue
        destination = target.parent / Path(*file.name.parts)
        if destination.resolve() == file.path.resolve():
            if index not in changed:
                destinations.append(None)  # already there, byte for byte
                continue
            if not in_place:
                raise ValueError(
                    f"path: writing {str(target)!r} would overwrite the included file "
                    f"{str(file.path)!r} {including}, which the original deck also reads; "
                    "write the morphed deck into another directory (or over the deck itself)"
                )
        destinations.append(destination)
    return destinations


def _write_file(destination: Path, lines: list[str], compressed: bool) -> None:
    data = "".join(lines).encode("latin-1")
    if compressed:
        data = gzip.compress(data, mtime=0)
    destination.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(destination) as temporary:
        temporary.write_bytes(data)


def write_deck(deck: AbaqusDeck, points: Any, path: str | os.PathLike) -> None:
    """Write ``deck`` with new node coordinates, every other byte as read.

    Parameters
    ----------
    deck : AbaqusDeck
        A deck from :func:`read_deck`.
    points : array_like or Tensor, shape (N, 3)
        New coordinates, one row per node in the order of ``deck.node_ids`` (as
        :meth:`AbaqusDeck.to_mesh_data` gives them); (N, 2) for a plane deck (z kept).
    path : str or PathLike
        The deck to write (gzip-compressed if it ends with ``.gz``). Included files are
        written beside it under the same relative names (their directories created).

    Raises
    ------
    ValueError
        If ``points`` has the wrong shape or a value that is not finite; if an included
        file cannot be placed (it lies outside the deck's directory and holds moved nodes
        or is reached by a relative path from a new directory; or writing it beside
        ``path`` would overwrite the original deck's own included file).

    Notes
    -----
    Only the lines of nodes whose coordinates changed are rewritten: the node number and
    the layout (spacing, other fields, line end) stay, each changed coordinate is
    replaced by :func:`format_coordinate`'s text (full float64 precision where it fits
    in CalculiX's 20-character field, 13 to 15 significant digits where it does not);
    coordinates omitted on the line get fields up to the last one that changed. Every file is
    written atomically (included files first, the main deck last), but not all of them as
    one: a failure part-way can leave new included files beside an old main deck. Does
    not check the morphed elements' shape: see :mod:`torchmorph.mesh.quality`.
    """
    new_points = _checked_points(deck, points)
    target = Path(path)
    if not target.parent.is_dir():
        raise FileNotFoundError(f"path: directory {str(target.parent)!r} does not exist")
    lines: dict[int, list[str]] = {}  # the edited files' lines, by index in deck.files
    moved = np.flatnonzero((new_points != deck.points).any(axis=1))
    for row in moved:
        file, line = int(deck.node_files[row]), int(deck.node_lines[row])
        text = lines.setdefault(file, list(deck.files[file].lines))
        text[line] = _rewrite_node_line(text[line], deck.points[row], new_points[row])
    destinations = _destinations(deck, target, set(lines))
    for index in [*range(1, len(deck.files)), 0]:
        destination = destinations[index]
        if destination is None:
            continue
        compressed = target.name.lower().endswith(".gz") if index == 0 else None
        file = deck.files[index]
        _write_file(
            destination,
            lines.get(index, file.lines),
            file.compressed if compressed is None else compressed,
        )
