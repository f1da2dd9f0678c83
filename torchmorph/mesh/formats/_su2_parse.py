"""The line parser and tables of SU2 mesh files, read and written by
:mod:`torchmorph.mesh.formats.su2`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

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
