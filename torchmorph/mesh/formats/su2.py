"""SU2's native mesh format (``.su2``), read and written with its markers kept by name.

meshio reads ``.su2`` files but numbers the markers and loses their names
(``MARKER_TAG= airfoil``); a morphed mesh handed back to SU2 needs them, since SU2's
configuration file assigns the boundary conditions by marker name. :func:`read_su2`
returns a :class:`~torchmorph.mesh.formats.MeshData` whose ``face_sets`` are the markers,
and :func:`write_su2` writes them back exactly.

The format (SU2's documentation, "Mesh File")::

    NDIME= 2                      % the dimension, 2 or 3
    NELEM= 2                      % the domain's elements: VTK type, its nodes
    5 0 1 2                       %   (an optional trailing element index)
    9 1 3 4 2
    NPOIN= 5                      % the points: x y [z] (an optional trailing index)
    0.0 0.0
    ...
    NMARK= 1                      % the markers: name, count, boundary elements
    MARKER_TAG= airfoil
    MARKER_ELEMS= 2
    3 0 1
    3 1 3

Element kinds are VTK's type ids with VTK's node order, which is also meshio's, so the
connectivity is passed through unchanged: 3 line, 5 triangle, 9 quad, 10 tetra,
12 hexahedron, 13 wedge (SU2's "prism"), 14 pyramid. SU2 has no quadratic kinds. In this
order (SU2's own face tables, ``CPrismConnectivity`` and its siblings, list the faces
outward) a pyramid's base (0, 1, 2, 3) turns counter-clockwise seen from its apex 4, and
a wedge's triangle (0, 1, 2) turns clockwise seen from its triangle (3, 4, 5): the
mirror image of gmsh's prism (gmsh's own SU2 writer swaps nodes 1, 2 and 4, 5; meshio's
gmsh reader does not, so a "wedge" read from a ``.msh`` file by meshio is the mirror of
SU2's order and must be permuted before it is written here).

How a file maps to :class:`MeshData`, and what is decided where the format leaves room:

* **Row and element numbers are the line order.** SU2 numbers points and elements by
  the order of their lines and ignores a trailing index on a point or element line
  (its documentation: "implied by the ordering ... can be ignored"). This reader does
  the same, so that it sees the mesh SU2 simulates; where the trailing indices are not
  0, 1, 2 … in line order it says so in a :class:`UserWarning` and still follows the
  line order. (A trailing value on a marker's element line is accepted and ignored.)
* **Cells are grouped by kind**, blocks in the order in which each kind first appears,
  elements of one kind in file order. Each cell's position among the ``NELEM=`` lines
  is kept in ``cell_data[ELEMENT_INDEX]`` (one array per block), and :func:`write_su2`
  writes the elements back in that order, so a file whose kinds interleave keeps its
  element numbering.
* **Markers become face sets** in the file's order, named by their tags; a marker's
  facets are grouped by kind in the order each kind first appears (the order of a
  marker's facets of one kind is kept; the interleaving of its triangles and quads is
  not). ``node_sets`` holds each marker's nodes (sorted, unique), derived from its facets.
* ``NPOIN= n n_domain`` (a domain count, from partitioned legacy files): the count is
  checked (``0 <= n_domain <= n``) and not kept, as SU2 itself ignores it.
* ``%`` starts a comment anywhere on a line; blank lines are skipped; keywords are
  read with or without spaces around ``=`` (SU2 itself wants ``KEYWORD=``, which is
  what :func:`write_su2` writes; it writes no comments).
* One zone: ``NZONE= 1`` and ``IZONE= 1`` are accepted, a file with several zones is
  refused. ``AOA_OFFSET=``/``AOS_OFFSET=`` of zero and ``FFD_NBOX= 0``/``FFD_NLEVEL= 0``
  are accepted (they say nothing); non-zero offsets and FFD boxes are refused, since
  :class:`MeshData` cannot carry them and writing the mesh back would drop them. Every
  other keyword is refused by name.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.formats._data import MeshData

__all__ = ["ELEMENT_INDEX", "SU2_KINDS", "read_su2", "write_su2"]

#: SU2's element kinds: VTK type id -> (meshio's kind name, nodes per element, dimension).
SU2_KINDS: dict[int, tuple[str, int, int]] = {
    3: ("line", 2, 1),
    5: ("triangle", 3, 2),
    9: ("quad", 4, 2),
    10: ("tetra", 4, 3),
    12: ("hexahedron", 8, 3),
    13: ("wedge", 6, 3),
    14: ("pyramid", 5, 3),
}

#: Key of ``MeshData.cell_data`` holding each cell's position among the ``NELEM=`` lines
#: (SU2's global element number), one int64 array per cell block.
ELEMENT_INDEX = "su2:element_index"

_VTK_TYPE_OF = {kind: vtk_type for vtk_type, (kind, _, _) in SU2_KINDS.items()}
_NODES_OF = {kind: nodes for kind, nodes, _ in SU2_KINDS.values()}
_DIMENSION_OF = {kind: dimension for kind, _, dimension in SU2_KINDS.values()}
_KNOWN_TYPES = ", ".join(f"{vtk_type} {kind}" for vtk_type, (kind, _, _) in SU2_KINDS.items())
# Lookup tables over VTK type ids 0..14 (0: not an SU2 kind).
_TABLE_SIZE = max(SU2_KINDS) + 1
_NODES_TABLE = np.zeros(_TABLE_SIZE, dtype=np.int64)
_DIMENSION_TABLE = np.zeros(_TABLE_SIZE, dtype=np.int64)
for _vtk_type, (_, _nodes, _dimension) in SU2_KINDS.items():
    _NODES_TABLE[_vtk_type] = _nodes
    _DIMENSION_TABLE[_vtk_type] = _dimension
del _vtk_type, _nodes, _dimension

_KEYWORDS = "NDIME=, NELEM=, NPOIN=, NMARK=, MARKER_TAG=, MARKER_ELEMS="


# ------------------------------------------------------------------------------- reading


@dataclass
class _Lines:
    """The file's non-blank lines without comments: their 1-based numbers and contents."""

    numbers: Sequence[int]
    contents: list[str]


@dataclass
class _Block:
    """The data lines that follow a counted keyword (``NELEM=``, ``NPOIN=``, ``MARKER_ELEMS=``)."""

    keyword: str
    line: int
    count: int
    numbers: Sequence[int] = ()
    texts: list[str] = field(default_factory=list)


@dataclass
class _Marker:
    name: str
    line: int
    block: _Block


@dataclass
class _Sections:
    dimension: int | None = None
    dimension_line: int = 0
    elements: _Block | None = None
    points: _Block | None = None
    domain_points: int | None = None
    marker_count: int | None = None
    marker_count_line: int = 0
    markers: list[_Marker] = field(default_factory=list)


def read_su2(path: str | os.PathLike) -> MeshData:
    """Read an SU2 mesh (``.su2``, one zone, 2-D or 3-D) with its markers by name.

    Parameters
    ----------
    path : str or PathLike
        The ``.su2`` file.

    Returns
    -------
    MeshData
        ``points`` : ndarray, shape (N, D), float64, D = ``NDIME`` (2 or 3), rows in the
        order of the point lines.
        ``cells`` : list of (kind, ndarray (M_k, n_k) int64), the ``NELEM=`` elements
        grouped by kind (``"triangle"``, ``"quad"`` in 2-D; ``"tetra"``, ``"hexahedron"``,
        ``"wedge"``, ``"pyramid"`` in 3-D), blocks in the order each kind first appears,
        node order VTK's (SU2's and meshio's).
        ``cell_data[ELEMENT_INDEX]`` : list of ndarray (M_k,) int64, each cell's position
        among the ``NELEM=`` lines.
        ``face_sets`` : dict of marker name to list of (kind, ndarray (K_k, n_k) int64),
        markers in the file's order, facets (``"line"`` in 2-D, ``"triangle"``/``"quad"``
        in 3-D) grouped by kind in the order each kind first appears.
        ``node_sets`` : dict of marker name to ndarray (K,) int64, each marker's nodes,
        sorted and unique. ``groups`` and ``point_data`` are empty.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        For a malformed file, naming the file and the line: a missing or duplicated
        section, a count (``NELEM=``, ``NPOIN=``, ``NMARK=``, ``MARKER_ELEMS=``) that does
        not match the lines that follow, a line with the wrong number of values or a value
        that is not a number, an unknown VTK type, an element of the wrong dimension (a
        tetrahedron in a 2-D mesh, a line in a 3-D marker), a node number out of range, a
        non-finite coordinate, an empty, duplicated or white-space-holding marker name,
        several zones, an unknown keyword, or content :class:`MeshData` cannot carry
        (non-zero ``AOA_OFFSET=``/``AOS_OFFSET=``, FFD boxes).

    Warns
    -----
    UserWarning
        Where trailing point or element indices disagree with the line order (which is
        followed, as SU2 follows it).

    Notes
    -----
    See the module's documentation for what is decided where the format leaves room.
    Does not check the cells' orientation or validity (call the mesh's quality checks).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: mesh file {str(path)!r} does not exist")
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"path: {source!r}: not a text file in UTF-8 ({error})") from error
    sections = _scan(source, text)
    dimension = sections.dimension
    assert dimension is not None and sections.points is not None and sections.elements is not None

    points, point_warning = _parse_points(source, sections.points, dimension)
    num_points = points.shape[0]
    if sections.domain_points is not None and sections.domain_points > num_points:
        raise _error(
            source,
            sections.points.line,
            f"NPOIN= {num_points} {sections.domain_points}: the domain count "
            f"{sections.domain_points} exceeds the number of points {num_points}",
        )

    groups, element_warning = _parse_elements(
        source, sections.elements, dimension, num_points, f"{dimension}-D mesh's NELEM= section"
    )
    for warning in (point_warning, element_warning):
        if warning is not None:
            warnings.warn(warning, UserWarning, stacklevel=2)
    cells = [(kind, connectivity) for kind, _, connectivity in groups]
    element_index = [rows for _, rows, _ in groups]

    face_sets: dict[str, list[tuple[str, np.ndarray]]] = {}
    node_sets: dict[str, np.ndarray] = {}
    for marker in sections.markers:
        facets, _ = _parse_elements(
            source,
            marker.block,
            dimension - 1,
            num_points,
            f"marker {marker.name!r} (MARKER_TAG= at line {marker.line}) of a {dimension}-D mesh",
        )
        face_sets[marker.name] = [(kind, connectivity) for kind, _, connectivity in facets]
        nodes = [connectivity.ravel() for _, _, connectivity in facets]
        node_sets[marker.name] = np.unique(np.concatenate(nodes)) if nodes else _no_nodes()
    return MeshData(
        points=points,
        cells=cells,
        node_sets=node_sets,
        face_sets=face_sets,
        cell_data={ELEMENT_INDEX: element_index},
    )


def _no_nodes() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


def _error(source: str, line: int | None, message: str) -> ValueError:
    where = f"path: {source!r}" if line is None else f"path: {source!r}, line {line}"
    return ValueError(f"{where}: {message}")


def _scan(source: str, text: str) -> _Sections:
    """Split the file into its sections, checking keywords, counts and their order."""
    lines = text.splitlines()
    if "%" in text:
        contents = [line.partition("%")[0].strip() for line in lines]
    else:
        contents = [line.strip() for line in lines]
    if "" in contents:
        kept = [row for row, content in enumerate(contents) if content]
        entries = _Lines([row + 1 for row in kept], [contents[row] for row in kept])
    else:
        entries = _Lines(range(1, len(contents) + 1), contents)

    sections = _Sections()
    previous: _Block | None = None  # the last counted section, for a hint on a stray line
    position = 0
    while position < len(entries.contents):
        number, content = entries.numbers[position], entries.contents[position]
        position += 1
        key, equals, value = content.partition("=")
        key, value = key.strip(), value.strip()
        if not equals:
            hint = ""
            if previous is not None:
                hint = (
                    f"; {previous.keyword}= {previous.count} at line {previous.line} announces "
                    f"{previous.count} lines, are there more?"
                )
            raise _error(
                source, number, f"expected a keyword line ({_KEYWORDS} ...), got {content!r}{hint}"
            )
        if key == "NDIME":
            if sections.dimension is not None:
                raise _error(
                    source, number, f"NDIME= given twice (first at line {sections.dimension_line})"
                )
            if value not in ("2", "3"):
                raise _error(source, number, f"NDIME= must be 2 or 3, got {value!r}")
            sections.dimension, sections.dimension_line = int(value), number
        elif key in ("NELEM", "NPOIN"):
            existing = sections.elements if key == "NELEM" else sections.points
            if existing is not None:
                raise _error(source, number, f"{key}= given twice (first at line {existing.line})")
            counts = value.split()
            if key == "NPOIN" and len(counts) == 2:
                sections.domain_points = _count(source, number, key, counts[1])
            elif len(counts) != 1:
                expected = "a count and optionally a domain count" if key == "NPOIN" else "a count"
                raise _error(source, number, f"{key}= expects {expected}, got {value!r}")
            block = _Block(key, number, _count(source, number, key, counts[0]))
            position = _take(source, entries, position, block)
            if key == "NELEM":
                sections.elements = block
            else:
                sections.points = block
            previous = block
        elif key == "NMARK":
            if sections.marker_count is not None:
                raise _error(
                    source,
                    number,
                    f"NMARK= given twice (first at line {sections.marker_count_line})",
                )
            sections.marker_count = _count(source, number, key, value)
            sections.marker_count_line = number
        elif key == "MARKER_TAG":
            marker, position = _take_marker(source, entries, position, number, value, sections)
            sections.markers.append(marker)
            previous = marker.block
        elif key == "MARKER_ELEMS":
            raise _error(source, number, "MARKER_ELEMS= without a MARKER_TAG= line before it")
        elif key == "NZONE":
            zones = _count(source, number, key, value)
            if zones != 1:
                raise _error(
                    source,
                    number,
                    f"NZONE= {zones}: the file holds {zones} zones; read_su2 reads single-zone "
                    f"meshes only (write each zone to a file of its own)",
                )
        elif key == "IZONE":
            if value != "1":
                raise _error(
                    source,
                    number,
                    f"IZONE= {value}: a second zone; read_su2 reads single-zone meshes only "
                    f"(write each zone to a file of its own)",
                )
        elif key in ("AOA_OFFSET", "AOS_OFFSET"):
            if _number(source, number, key, value) != 0.0:
                raise _error(
                    source,
                    number,
                    f"{key}= {value}: a non-zero angle offset cannot be kept (writing the mesh "
                    f"back would drop it); move it into the SU2 configuration (AOA=/AOS=)",
                )
        elif key in ("FFD_NBOX", "FFD_NLEVEL"):
            if _count(source, number, key, value) != 0:
                raise _error(
                    source,
                    number,
                    f"{key}= {value}: FFD boxes are not supported (writing the mesh back would "
                    f"drop them); remove the FFD section (from FFD_NBOX= on) to read the mesh",
                )
        else:
            raise _error(
                source,
                number,
                f"unknown keyword {key + '='!r} (known: {_KEYWORDS}, NZONE=, IZONE=); its "
                f"content would be lost on writing",
            )

    for keyword, present in (
        ("NDIME", sections.dimension is not None),
        ("NPOIN", sections.points is not None),
        ("NELEM", sections.elements is not None),
    ):
        if not present:
            raise _error(source, None, f"no {keyword}= section: not an SU2 mesh")
    if sections.marker_count is not None and len(sections.markers) != sections.marker_count:
        raise _error(
            source,
            sections.marker_count_line,
            f"NMARK= {sections.marker_count} but {len(sections.markers)} markers "
            f"(MARKER_TAG= lines) follow",
        )
    return sections


def _take(source: str, entries: _Lines, position: int, block: _Block) -> int:
    """Move the ``block.count`` data lines from ``position`` on into ``block``; the new position."""
    end = position + block.count
    texts = entries.contents[position:end]
    if "=" in "\n".join(texts):  # a keyword line among them: the count is too large
        offset = next(offset for offset, content in enumerate(texts) if "=" in content)
        raise _error(
            source,
            entries.numbers[position + offset],
            f"{block.keyword}= {block.count} at line {block.line} announces {block.count} "
            f"lines, but only {offset} follow before {texts[offset]!r}",
        )
    if end > len(entries.contents):
        raise _error(
            source,
            block.line,
            f"{block.keyword}= {block.count} announces {block.count} lines, but the file ends "
            f"after {len(entries.contents) - position}",
        )
    block.numbers = entries.numbers[position:end]
    block.texts = texts
    return end


def _take_marker(
    source: str,
    entries: _Lines,
    position: int,
    number: int,
    name: str,
    sections: _Sections,
) -> tuple[_Marker, int]:
    """Read one marker from its ``MARKER_TAG=`` line (``number``) on; the marker, new position."""
    if sections.marker_count is None:
        raise _error(source, number, "MARKER_TAG= before NMARK=")
    if len(sections.markers) == sections.marker_count:
        raise _error(
            source,
            number,
            f"NMARK= {sections.marker_count} at line {sections.marker_count_line}, but a marker "
            f"more follows ({name!r})",
        )
    problem = _marker_name_problem(name)
    if problem:
        raise _error(source, number, f"MARKER_TAG= {name!r}: {problem}")
    for marker in sections.markers:
        if marker.name == name:
            raise _error(
                source, number, f"marker {name!r} given twice (first at line {marker.line})"
            )
    if position == len(entries.contents):
        raise _error(
            source,
            number,
            f"MARKER_TAG= {name} must be followed by MARKER_ELEMS=, got the end of the file",
        )
    following, content = entries.numbers[position], entries.contents[position]
    key, equals, value = content.partition("=")
    if not equals or key.strip() != "MARKER_ELEMS":
        raise _error(
            source,
            following,
            f"MARKER_TAG= {name} must be followed by MARKER_ELEMS=, got {content!r}",
        )
    block = _Block("MARKER_ELEMS", following, _count(source, following, "MARKER_ELEMS", value))
    position = _take(source, entries, position + 1, block)
    return _Marker(name, number, block), position


def _marker_name_problem(name: str) -> str | None:
    """Why SU2 cannot hold ``name`` as a marker tag, or None."""
    if not name:
        return "a marker name must not be empty"
    if any(character.isspace() for character in name):
        return "a marker name must not hold white space (SU2 drops it from the name)"
    if "%" in name:
        return "a marker name must not hold '%' (it starts a comment)"
    return None


def _count(source: str, number: int, key: str, value: str) -> int:
    try:
        count = int(value)
    except ValueError:
        count = -1
    if count < 0:
        raise _error(source, number, f"{key}= expects a non-negative integer, got {value!r}")
    return count


def _number(source: str, number: int, key: str, value: str) -> float:
    try:
        return float(value)
    except ValueError:
        raise _error(source, number, f"{key}= expects a number, got {value!r}") from None


def _tokens(texts: list[str]) -> tuple[list[str], np.ndarray]:
    """The white-space separated tokens of ``texts`` in order, and their count per line (M,)."""
    joined = "\n".join(texts)
    tokens = joined.split()
    if not joined.isascii():
        return tokens, np.fromiter(map(len, map(str.split, texts)), np.int64, len(texts))
    # ASCII: within a line str.split separates at space, tab and \x1f (the other ASCII white
    # space characters end a line); a token starts where a separator or "\n" precedes it
    characters = np.frombuffer(joined.encode("ascii"), dtype=np.uint8)
    newline = characters == 10
    separator = newline | (characters == 32) | (characters == 9) | (characters == 31)
    starts = ~separator
    starts[1:] &= separator[:-1]
    line_of_start = np.searchsorted(np.flatnonzero(newline), np.flatnonzero(starts))
    widths = np.bincount(line_of_start, minlength=len(texts)).astype(np.int64)
    return tokens, widths


def _parse_points(source: str, block: _Block, dimension: int) -> tuple[np.ndarray, str | None]:
    """The point lines as an (N, D) float64 array, checked, and a warning on their indices."""
    tokens, widths = _tokens(block.texts)
    bad = np.flatnonzero((widths < dimension) | (widths > dimension + 2))
    if bad.size:
        row = int(bad[0])
        raise _error(
            source,
            block.numbers[row],
            f"a point of a {dimension}-D mesh has {dimension} coordinates (and optionally its "
            f"index), got {widths[row]} values: {block.texts[row]!r}",
        )
    starts = np.cumsum(widths) - widths
    if (widths == dimension).all():
        coordinates = tokens
    else:
        picked = (starts[:, None] + np.arange(dimension)).ravel()
        coordinates = [tokens[index] for index in picked.tolist()]
    try:
        points = np.fromiter(
            map(float, coordinates), dtype=np.float64, count=block.count * dimension
        )
    except ValueError:
        for number, content in zip(block.numbers, block.texts, strict=True):
            for token in content.split()[:dimension]:
                try:
                    float(token)
                except ValueError:
                    raise _error(source, number, f"coordinate {token!r} is not a number") from None
        raise
    points = points.reshape(block.count, dimension)
    not_finite = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if not_finite.size:
        row = int(not_finite[0])
        raise _error(source, block.numbers[row], f"non-finite coordinate in {block.texts[row]!r}")

    # Trailing indices: integers, ignored (SU2 numbers points by line order).
    extra_rows = np.flatnonzero(widths > dimension)
    if extra_rows.size == 0:
        return points, None
    second_rows = np.flatnonzero(widths == dimension + 2)
    positions = np.concatenate([starts[extra_rows], starts[second_rows] + 1]) + dimension
    extras = [tokens[position] for position in positions.tolist()]
    try:
        values = np.fromiter(map(int, extras), dtype=np.int64, count=len(extras))
    except (ValueError, OverflowError):
        for row in extra_rows.tolist():
            trailing = block.texts[row].split()[dimension:]
            try:
                [int(value) for value in trailing]
            except ValueError:
                raise _error(
                    source,
                    block.numbers[row],
                    f"the values after a point's {dimension} coordinates must be integer "
                    f"indices, got {' '.join(trailing)!r}",
                ) from None
        raise
    indices = np.zeros(block.count, dtype=np.int64)
    indices[extra_rows] = values[: extra_rows.size]
    warning = _index_warning(source, block, indices, widths > dimension, "point")
    return points, warning


def _parse_integers(source: str, block: _Block, tokens: list[str]) -> np.ndarray:
    try:
        return np.fromiter(map(int, tokens), dtype=np.int64, count=len(tokens))
    except (ValueError, OverflowError):
        limit = np.iinfo(np.int64).max
        for number, content in zip(block.numbers, block.texts, strict=True):
            tokens = content.split()
            for token in tokens:
                try:
                    value = int(token)
                except ValueError:
                    raise _error(
                        source, number, f"{token!r} is not an integer (in {' '.join(tokens)!r})"
                    ) from None
                if abs(value) > limit:
                    raise _error(source, number, f"{token} is out of range") from None
        raise


def _parse_elements(
    source: str, block: _Block, dimension: int, num_points: int, section: str
) -> tuple[list[tuple[str, np.ndarray, np.ndarray]], str | None]:
    """Parse element lines ``VTK_TYPE n1 ... nk [index]`` of one dimension.

    Returns
    -------
    groups : list of (kind, rows (M_k,) int64, connectivity (M_k, n_k) int64)
        By kind in the order each kind first appears; ``rows`` are the elements' positions
        in ``block``.
    warning : str or None
        Where the trailing element indices are not the line order.
    """
    tokens, widths = _tokens(block.texts)
    values = _parse_integers(source, block, tokens)
    starts = np.cumsum(widths) - widths
    types = values[starts]

    known = (types >= 0) & (types < _TABLE_SIZE)
    known[known] = _NODES_TABLE[types[known]] > 0
    if not known.all():
        row = int(np.flatnonzero(~known)[0])
        raise _error(
            source,
            block.numbers[row],
            f"unknown VTK element type {types[row]} in the {section} (SU2 knows {_KNOWN_TYPES})",
        )
    wrong = np.flatnonzero(_DIMENSION_TABLE[types] != dimension)
    if wrong.size:
        row = int(wrong[0])
        kind, _, kind_dimension = SU2_KINDS[int(types[row])]
        allowed = " or ".join(
            f"{name} (VTK {vtk_type})"
            for vtk_type, (name, _, other) in SU2_KINDS.items()
            if other == dimension
        )
        raise _error(
            source,
            block.numbers[row],
            f"a {kind} (VTK {types[row]}) is a {kind_dimension}-D element; the {section} "
            f"holds {dimension}-D elements: {allowed}",
        )
    nodes = _NODES_TABLE[types]
    extra = widths - 1 - nodes
    bad = np.flatnonzero((extra < 0) | (extra > 1))
    if bad.size:
        row = int(bad[0])
        kind = SU2_KINDS[int(types[row])][0]
        raise _error(
            source,
            block.numbers[row],
            f"a {kind} line holds its type, {nodes[row]} node numbers and optionally an "
            f"element index, got {widths[row]} values: {block.texts[row]!r}",
        )

    has_index = extra == 1
    indices = np.zeros(block.count, dtype=np.int64)
    indices[has_index] = values[(starts + 1 + nodes)[has_index]]
    warning = _index_warning(source, block, indices, has_index, "element")

    unique_types, first = np.unique(types, return_index=True)
    groups = []
    for vtk_type in unique_types[np.argsort(first)].tolist():
        kind, count, _ = SU2_KINDS[vtk_type]
        rows = np.flatnonzero(types == vtk_type)
        connectivity = values[starts[rows, None] + 1 + np.arange(count)]
        outside = np.flatnonzero(((connectivity < 0) | (connectivity >= num_points)).any(axis=1))
        if outside.size:
            row = int(rows[outside[0]])
            node = connectivity[outside[0]]
            node = node[(node < 0) | (node >= num_points)][0]
            raise _error(
                source,
                block.numbers[row],
                f"node {node} of a {kind} is out of range: the mesh has {num_points} points "
                f"(0..{num_points - 1})",
            )
        groups.append((kind, rows.astype(np.int64), connectivity))
    return groups, warning


def _index_warning(
    source: str, block: _Block, indices: np.ndarray, given: np.ndarray, what: str
) -> str | None:
    """A warning where given trailing indices are not the line order 0, 1, 2 …; or None."""
    disagree = np.flatnonzero(given & (indices != np.arange(indices.shape[0])))
    if disagree.size == 0:
        return None
    row = int(disagree[0])
    return (
        f"path: {source!r}, line {block.numbers[row]}: the trailing {what} index "
        f"{indices[row]} is not the line order ({row}); like SU2, read_su2 numbers {what}s "
        f"by line order and ignores these indices ({disagree.size} differ)"
    )


# ------------------------------------------------------------------------------- writing


def write_su2(path: str | os.PathLike, data: MeshData) -> None:
    """Write a mesh as an SU2 mesh file (``.su2``) with its face sets as markers.

    Writes ``NDIME=``, the cells (``NELEM=``), the points at full float64 precision
    (``NPOIN=``, shortest round-tripping decimals) and the face sets as markers
    (``NMARK=``, ``MARKER_TAG=``, ``MARKER_ELEMS=``) in the order of ``data.face_sets``,
    so that :func:`read_su2` of the file gives back every array and marker exactly.

    Parameters
    ----------
    path : str or PathLike
        The file to write (replaced atomically: a failing write leaves it as it was).
    data : MeshData
        ``points`` : array, shape (N, D), D = 2 or 3, finite.
        ``cells`` : triangles and quads (2-D) or tetra, hexahedron, wedge and pyramid
        blocks (3-D), VTK node order; written block by block, or in the order given by
        ``cell_data[ELEMENT_INDEX]`` where present (as :func:`read_su2` returns it).
        ``face_sets`` : lines (2-D) or triangles and quads (3-D) per marker name.

    Raises
    ------
    ValueError
        Naming the file and the offending entry: points not of shape (N, 2) or (N, 3) or
        not finite; a cell kind SU2 cannot hold (quadratic and other higher-order kinds,
        polyhedra) or of the wrong dimension; connectivity of the wrong shape or with node
        numbers out of range; a face set whose facets are not of the dimension below the
        mesh's; a marker name that is empty or holds white space or ``%``; a
        ``cell_data[ELEMENT_INDEX]`` that does not number the cells 0..M-1.

    Notes
    -----
    SU2 files hold no node sets, groups or data: ``node_sets`` (derived from the face sets
    on reading), ``groups``, ``point_data`` and ``cell_data`` other than
    ``ELEMENT_INDEX`` are not written, nor is ``planar_coordinate`` (SU2's 2-D meshes have
    two coordinates: a planar mesh is written from its (N, 2) points). Cell blocks of one kind come back from
    :func:`read_su2` merged into one block. Trailing point or element indices are not
    written (SU2 numbers by line order). The file holds no comments.
    """
    source = str(path)
    points = _checked_points(source, data.points)
    dimension, num_points = points.shape[1], points.shape[0]
    cells = [
        _checked_block(source, f"data.cells[{number}]", kind, connectivity, dimension, num_points)
        for number, (kind, connectivity) in enumerate(data.cells)
    ]
    order = _element_order(source, data.cell_data.get(ELEMENT_INDEX), cells)
    markers: list[tuple[str, list[tuple[str, np.ndarray]]]] = []
    for name, facets in data.face_sets.items():
        if not isinstance(name, str):
            raise ValueError(
                f"data.face_sets: marker names must be strings, got {name!r} (writing {source!r})"
            )
        label = f"data.face_sets[{name!r}]"
        problem = _marker_name_problem(name)
        if problem:
            raise ValueError(f"{label}: {problem} (writing {source!r})")
        markers.append(
            (
                name,
                [
                    _checked_block(
                        source, f"{label}[{number}]", kind, connectivity, dimension, num_points, 1
                    )
                    for number, (kind, connectivity) in enumerate(facets)
                ],
            )
        )

    with atomic_output(path) as temporary, open(temporary, "w", encoding="utf-8") as stream:
        stream.write(f"NDIME= {dimension}\n")
        stream.write(f"NELEM= {sum(len(connectivity) for _, connectivity in cells)}\n")
        lines = list(chain.from_iterable(_element_lines(kind, block) for kind, block in cells))
        if order is not None:
            lines = [lines[row] for row in order.tolist()]
        _write_lines(stream, lines)
        stream.write(f"NPOIN= {num_points}\n")
        _write_lines(stream, [" ".join(map(repr, row)) for row in points.tolist()])
        stream.write(f"NMARK= {len(markers)}\n")
        for name, facets in markers:
            stream.write(f"MARKER_TAG= {name}\n")
            stream.write(f"MARKER_ELEMS= {sum(len(block) for _, block in facets)}\n")
            for kind, block in facets:
                _write_lines(stream, _element_lines(kind, block))


def _element_lines(kind: str, connectivity: np.ndarray) -> list[str]:
    prefix = f"{_VTK_TYPE_OF[kind]} "
    return [prefix + " ".join(map(str, row)) for row in connectivity.tolist()]


def _write_lines(stream, lines: Sequence[str]) -> None:
    if lines:
        stream.write("\n".join(lines))
        stream.write("\n")


def _checked_points(source: str, points: object) -> np.ndarray:
    array = np.asarray(points)
    if array.dtype.kind not in "fiu":
        raise ValueError(
            f"data.points: must hold real numbers, got dtype {array.dtype} (writing {source!r})"
        )
    if array.ndim != 2 or array.shape[1] not in (2, 3):
        raise ValueError(
            f"data.points: SU2 meshes are 2-D or 3-D, points must have shape (N, 2) or "
            f"(N, 3), got {array.shape} (writing {source!r})"
        )
    array = array.astype(np.float64, copy=False)
    not_finite = np.flatnonzero(~np.isfinite(array).all(axis=1))
    if not_finite.size:
        row = int(not_finite[0])
        raise ValueError(
            f"data.points: row {row} is not finite ({array[row].tolist()}); "
            f"{not_finite.size} such rows (writing {source!r})"
        )
    return array


def _checked_block(
    source: str,
    label: str,
    kind: str,
    connectivity: object,
    dimension: int,
    num_points: int,
    codimension: int = 0,
) -> tuple[str, np.ndarray]:
    """Check a block of a ``dimension``-D mesh's cells (codimension 0) or boundary facets (1).

    Returns the kind and the connectivity as int64.
    """
    if kind not in _VTK_TYPE_OF:
        raise ValueError(
            f"{label}: SU2 cannot hold {kind!r} elements: its kinds are linear only "
            f"({', '.join(_VTK_TYPE_OF)}), no quadratic or other higher-order kinds "
            f"(writing {source!r})"
        )
    if _DIMENSION_OF[kind] != dimension - codimension:
        allowed = ", ".join(
            name for name, other in _DIMENSION_OF.items() if other == dimension - codimension
        )
        what = "boundary facets (markers)" if codimension else "cells"
        raise ValueError(
            f"{label}: {kind!r} is a {_DIMENSION_OF[kind]}-D kind; the {what} of a "
            f"{dimension}-D SU2 mesh are {allowed} (writing {source!r})"
        )
    array = np.asarray(connectivity)
    nodes = _NODES_OF[kind]
    if array.ndim != 2 or array.shape[1] != nodes or (array.size and array.dtype.kind not in "iu"):
        raise ValueError(
            f"{label}: {kind!r} connectivity must be integers of shape (M, {nodes}), got "
            f"{array.shape} of dtype {array.dtype} (writing {source!r})"
        )
    array = array.astype(np.int64, copy=False)
    if array.size and (array.min() < 0 or array.max() >= num_points):
        raise ValueError(
            f"{label}: node numbers must be in 0..{num_points - 1}, got "
            f"{array.min()}..{array.max()} (writing {source!r})"
        )
    return kind, array


def _element_order(
    source: str, element_index: object, cells: list[tuple[str, np.ndarray]]
) -> np.ndarray | None:
    """The block-order rows by file position, from ``cell_data[ELEMENT_INDEX]``; or None."""
    if element_index is None:
        return None
    label = f"data.cell_data[{ELEMENT_INDEX!r}]"
    if not isinstance(element_index, Sequence) or len(element_index) != len(cells):
        count = len(element_index) if isinstance(element_index, Sequence) else "no list"
        raise ValueError(
            f"{label}: must be a list of one index array per cell block ({len(cells)}), got "
            f"{count} (writing {source!r})"
        )
    arrays = []
    for number, (indices, (_, connectivity)) in enumerate(zip(element_index, cells, strict=True)):
        array = np.asarray(indices)
        if array.shape != (len(connectivity),) or (array.size and array.dtype.kind not in "iu"):
            raise ValueError(
                f"{label}[{number}]: must be integers of shape ({len(connectivity)},), got "
                f"{array.shape} of dtype {array.dtype} (writing {source!r})"
            )
        arrays.append(array.astype(np.int64, copy=False))
    positions = np.concatenate(arrays) if arrays else np.zeros(0, dtype=np.int64)
    if not np.array_equal(np.sort(positions), np.arange(positions.shape[0])):
        raise ValueError(
            f"{label}: must number the {positions.shape[0]} cells 0..{positions.shape[0] - 1}, "
            f"each once (writing {source!r})"
        )
    order = np.empty_like(positions)
    order[positions] = np.arange(positions.shape[0])
    return order
