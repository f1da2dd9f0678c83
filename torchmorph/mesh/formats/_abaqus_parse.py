"""The line-by-line reader behind :mod:`torchmorph.mesh.formats.abaqus`.

It follows CalculiX's reading of a deck (``readinput.c``, ``nodes.f``, ``elements.f``,
``noelsets.f``): a line whose first non-blank characters are ``**`` is a comment, blank
lines are skipped, a line starting with ``*`` is a keyword line, blanks inside a field
do not count and keywords, parameters and names are case-insensitive. ``*INCLUDE`` lines
are replaced by the included file's lines, so the keyword in force before an include goes
on inside it (a ``*NODE`` line followed by an ``*INCLUDE`` of bare node lines is read as
CalculiX reads it). Every file is kept as its text (decoded as Latin-1, so that every
byte comes back unchanged) with the position of every node line.
"""

from __future__ import annotations

import gzip
import math
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

__all__ = [
    "DeckFile",
    "ElementBlock",
    "ParsedDeck",
    "SetDefinition",
    "element_node_count",
    "parse_deck",
]

#: How deep ``*INCLUDE`` files may nest (CalculiX stops at 9 levels).
MAX_INCLUDE_DEPTH = 9

_INTEGER = re.compile(r"[+-]?\d+")
_LARGEST = 2**63 - 1  # numbers are stored as int64
#: A Fortran real as CalculiX's ``(f20.0)`` reads it: ``1.``, ``.5``, ``1.5E3``, ``1.5D3``
#: and ``1.5+3`` (an exponent without its letter).
_REAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][+-]?\d+|[+-]\d+)?")

#: Node counts of the element types outside the families matched by pattern below.
_FIXED_COUNTS = {
    "B21": 2, "B22": 3, "B31": 2, "B31R": 2, "B32": 3, "B32R": 3, "B33": 2,
    "T2D2": 2, "T2D3": 3, "T3D2": 2, "T3D3": 3, "STRI3": 3, "STRI65": 6,
    "SPRINGA": 2, "SPRING1": 1, "SPRING2": 2, "DASHPOTA": 2, "DASHPOT1": 1, "DASHPOT2": 2,
    "GAPUNI": 2, "DCOUP3D": 1, "MASS": 1, "ROTARYI": 1, "D": 3,
}  # fmt: skip
_COUNT_PATTERNS = (
    re.compile(r"C3D(4|5|6|8|10|15|20)[A-Z]*"),
    re.compile(r"F3D(4|6|8)R?"),
    re.compile(r"(?:CPS|CPE|CAX)(3|4|6|8)[A-Z]*"),
    re.compile(r"(?:S|M3D|R3D)(3|4|6|8|9)(?:[A-Z][A-Z0-9]*)?"),
)


def canonical_type(element_type: str) -> str:
    """The element type with CalculiX's heat-transfer prefix removed (``DC3D8`` is a
    ``C3D8``, ``DS4`` an ``S4``; ``DCOUP3D`` stays)."""
    name = element_type.upper()
    if (name.startswith("DC") and not name.startswith("DCOUP3D")) or name.startswith("DS"):
        return name[1:]
    return name


def is_network_type(element_type: str) -> bool:
    """CalculiX's fluid-network elements (``TYPE=D…``), whose end nodes may be ``0``."""
    name = canonical_type(element_type)
    return name.startswith("D") and not name.startswith(("DCOUP3D", "DASHPOT"))


def element_node_count(element_type: str, user_counts: dict[str, int] | None = None) -> int | None:
    """Nodes per element of ``element_type``, or None where the type is not known here
    (its element lines then continue while they end with a comma)."""
    name = canonical_type(element_type)
    if name in _FIXED_COUNTS:
        return _FIXED_COUNTS[name]
    for pattern in _COUNT_PATTERNS:
        match = pattern.fullmatch(name)
        if match:
            return int(match.group(1))
    if is_network_type(name):
        return 3
    if user_counts and name in user_counts:
        return user_counts[name]
    return None


@dataclass(eq=False)
class DeckFile:
    """One file of a deck as read.

    Attributes
    ----------
    path : Path
        Where it was read from.
    name : PurePosixPath or None
        Its path relative to the main file's directory (the main file: its own name);
        None for an included file outside that directory.
    compressed : bool
        Whether it is gzip-compressed (its name ends with ``.gz``).
    lines : list of str
        Its text split after every ``\\n`` (line ends kept), decoded as Latin-1 so that
        ``"".join(lines).encode("latin-1")`` gives back its bytes.
    reference : str or None
        The ``INPUT=`` text that included it (None for the main file).
    included_by : int or None
        Index of the including file in the deck's ``files``.
    """

    path: Path
    name: PurePosixPath | None
    compressed: bool
    lines: list[str] = field(repr=False)
    reference: str | None = None
    included_by: int | None = None

    @property
    def text(self) -> str:
        """The file's text as read (Latin-1)."""
        return "".join(self.lines)

    def where(self, line: int) -> str:
        """``'<path>, line <n>'`` for the 0-based line index ``line``."""
        return f"{self.path}, line {line + 1}"


@dataclass(eq=False)
class ElementBlock:
    """The elements of one ``*ELEMENT`` keyword.

    Attributes
    ----------
    type : str
        The ``TYPE=`` as written, upper-cased (``"C3D10"``).
    elset : str or None
        Its ``ELSET=`` name.
    ids : ndarray, shape (M,), int64
        Element numbers.
    nodes : ndarray, shape (M, n), int64
        Node numbers of each element in the deck's (Abaqus) order.
    file : int
        Index of the file in the deck's ``files`` and ``line`` the 0-based index of the
        keyword line in it.
    line : int
    element_files, element_lines : ndarray, shape (M,), int64
        Where each element's first line is.
    """

    type: str
    elset: str | None
    ids: np.ndarray
    nodes: np.ndarray
    file: int
    line: int
    element_files: np.ndarray
    element_lines: np.ndarray


@dataclass
class SetDefinition:
    """One ``*NSET``/``*ELSET`` keyword (or a ``NSET=``/``ELSET=`` on ``*NODE``/``*ELEMENT``)."""

    kind: str  # "node" or "element"
    name: str
    file: int
    line: int
    generate: bool = False
    ids: list[int] = field(default_factory=list)
    names: list[tuple[str, int, int]] = field(default_factory=list)  # (name, file, line)
    ranges: list[tuple[int, int, int]] = field(default_factory=list)
    of_elements: str | None = None  # *NSET, ELSET=name: the nodes of those elements
    keyword: bool = False  # an *NSET/*ELSET keyword (not a parameter of *NODE/*ELEMENT)


@dataclass
class _OpenBlock:
    type: str
    elset: str | None
    count: int | None
    network: bool
    file: int
    line: int
    ids: list[int] = field(default_factory=list)
    rows: list[list[int]] = field(default_factory=list)
    files: list[int] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)
    # the element being read across continuation lines
    pending: list[int] | None = None
    truncated: int = 0  # elements given more nodes than the type has


@dataclass
class ParsedDeck:
    """What :func:`parse_deck` read: files, nodes, element blocks and set definitions."""

    files: list[DeckFile]
    node_ids: np.ndarray  # (N,) in file order
    coordinates: np.ndarray  # (N, 3)
    node_files: np.ndarray  # (N,)
    node_lines: np.ndarray  # (N,)
    blocks: list[ElementBlock]
    set_definitions: list[SetDefinition]
    user_counts: dict[str, int]
    warnings: list[str]


def _read_text(path: Path, where: str) -> tuple[list[str], bool]:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise ValueError(f"{where}: cannot read {str(path)!r} ({error.strerror})") from None
    compressed = path.name.lower().endswith(".gz")
    if compressed:
        try:
            data = gzip.decompress(data)
        except (OSError, EOFError, zlib.error) as error:
            raise ValueError(f"{path}: not a readable gzip file ({error})") from None
    text = data.decode("latin-1")
    lines = text.split("\n")
    return [line + "\n" for line in lines[:-1]] + ([lines[-1]] if lines[-1] else []), compressed


def _fields(body: str) -> list[str]:
    """Comma-separated fields without their blanks; a trailing comma adds no field."""
    parts = ["".join(part.split()) for part in body.split(",")]
    if len(parts) > 1 and not parts[-1]:
        parts.pop()
    return parts


def _parameters(parts: list[str], where: str) -> dict[str, str]:
    parameters: dict[str, str] = {}
    for part in parts:
        key, equals, value = part.partition("=")
        key = "".join(key.split()).upper()
        if not key:
            continue
        if key == "INPUT":
            value = value.strip().strip('"').strip()
        else:
            value = "".join(value.split()).strip('"')
        if equals and not value:
            raise ValueError(f"{where}: parameter {key} has no value")
        parameters[key] = value
    return parameters


def _integer(text: str, what: str, where: str) -> int:
    if not _INTEGER.fullmatch(text):
        raise ValueError(f"{where}: {what} {text!r} is not an integer")
    value = int(text)
    if abs(value) > _LARGEST:
        raise ValueError(f"{where}: {what} {text!r} is out of range")
    return value


def _real(text: str, where: str) -> float:
    if not text:
        return 0.0  # an empty field reads as 0, as in CalculiX
    if not _REAL.fullmatch(text):
        raise ValueError(f"{where}: coordinate {text!r} is not a number")
    number = text.replace("d", "e").replace("D", "e")
    if "e" not in number and "E" not in number:
        number = re.sub(r"(?<=[\d.])([+-])", r"e\1", number)
    value = float(number)
    if not math.isfinite(value):
        raise ValueError(f"{where}: coordinate {text!r} is out of range")
    return value


class _Parser:
    def __init__(self, main: Path) -> None:
        self.root = main.parent
        self.files: list[DeckFile] = []
        self.file_index: dict[Path, int] = {}
        self.stack: list[Path] = []
        self.keyword = ""
        self.node_ids: list[int] = []
        self.coordinates: list[tuple[float, float, float]] = []
        self.node_files: list[int] = []
        self.node_lines: list[int] = []
        self.node_set: SetDefinition | None = None
        self.block: _OpenBlock | None = None
        self.blocks: list[ElementBlock] = []
        self.set_definitions: list[SetDefinition] = []
        self.current_set: SetDefinition | None = None
        self.user_counts: dict[str, int] = {}
        self.warnings: list[str] = []

    # -- files ------------------------------------------------------------------------
    def read_file(self, path: Path, reference: str | None, parent: int | None, where: str) -> None:
        resolved = path.resolve()
        if resolved in self.stack:
            raise ValueError(f"{where}: {str(path)!r} includes itself")
        if len(self.stack) > MAX_INCLUDE_DEPTH:
            raise ValueError(f"{where}: includes nest deeper than {MAX_INCLUDE_DEPTH} levels")
        if resolved in self.file_index:
            index = self.file_index[resolved]
        else:
            lines, compressed = _read_text(path, where)
            try:
                name: PurePosixPath | None = PurePosixPath(
                    resolved.relative_to(self.root.resolve())
                )
            except ValueError:
                name = None
            if parent is None:
                name = PurePosixPath(path.name)
            index = len(self.files)
            self.files.append(DeckFile(path, name, compressed, lines, reference, parent))
            self.file_index[resolved] = index
        self.stack.append(resolved)
        for number, line in enumerate(self.files[index].lines):
            self.line(index, number, line)
        self.stack.pop()

    def include(self, reference: str, index: int, number: int) -> None:
        where = self.files[index].where(number)
        including = self.files[index].path.parent
        candidates = [including / reference, self.root / reference]
        for candidate in candidates:
            if candidate.is_file():
                self.read_file(candidate, reference, index, where)
                return
        tried = " or ".join(sorted({repr(str(c)) for c in candidates}))
        raise ValueError(f"{where}: included file {reference!r} not found (looked for {tried})")

    # -- lines ------------------------------------------------------------------------
    def line(self, index: int, number: int, raw: str) -> None:
        body = raw.rstrip("\r\n")
        stripped = body.lstrip()
        if not stripped.strip() or stripped.startswith("**"):
            return
        if stripped.startswith("*"):
            self.keyword_line(index, number, body)
        elif self.keyword == "*NODE":
            self.node_line(index, number, body)
        elif self.keyword == "*ELEMENT":
            self.element_line(index, number, body)
        elif self.keyword in ("*NSET", "*ELSET"):
            self.set_line(index, number, body)

    def keyword_line(self, index: int, number: int, body: str) -> None:
        where = self.files[index].where(number)
        parts = body.split(",")
        keyword = "".join(parts[0].split()).upper()
        if keyword == "*INCLUDE":
            parameters = _parameters(parts[1:], where)
            if "INPUT" not in parameters:
                raise ValueError(f"{where}: *INCLUDE without INPUT=")
            self.include(parameters["INPUT"], index, number)
            return  # the keyword in force goes on, as in CalculiX
        self.close_block()
        self.keyword = keyword
        self.node_set = self.current_set = None
        if keyword not in ("*NODE", "*ELEMENT", "*NSET", "*ELSET", "*USERELEMENT"):
            return
        parameters = _parameters(parts[1:], where)
        if keyword == "*NODE":
            if "NSET" in parameters:
                self.node_set = SetDefinition("node", parameters["NSET"], index, number)
                self.set_definitions.append(self.node_set)
        elif keyword == "*ELEMENT":
            if "TYPE" not in parameters:
                raise ValueError(f"{where}: *ELEMENT without TYPE=")
            element_type = parameters["TYPE"].upper()
            self.block = _OpenBlock(
                element_type,
                parameters.get("ELSET"),
                element_node_count(element_type, self.user_counts),
                is_network_type(element_type),
                index,
                number,
            )
        elif keyword == "*USERELEMENT":
            if "TYPE" in parameters and "NODES" in parameters:
                count = _integer(parameters["NODES"], "NODES=", where)
                self.user_counts[parameters["TYPE"].upper()] = count
        else:
            kind = "node" if keyword == "*NSET" else "element"
            key = "NSET" if kind == "node" else "ELSET"
            if key not in parameters:
                raise ValueError(f"{where}: {keyword} without {key}=")
            self.current_set = SetDefinition(
                kind, parameters[key], index, number, "GENERATE" in parameters, keyword=True
            )
            if kind == "node" and "ELSET" in parameters:
                self.current_set.of_elements = parameters["ELSET"]
            self.set_definitions.append(self.current_set)
        if "INPUT" in parameters:  # data lines in a file of their own
            self.include(parameters["INPUT"], index, number)

    def node_line(self, index: int, number: int, body: str) -> None:
        where = self.files[index].where(number)
        parts = _fields(body)
        node = _integer(parts[0], "node number", where)
        if node <= 0:
            raise ValueError(f"{where}: node number {node} is not positive")
        values = [_real(text, where) for text in parts[1:4]]
        values += [0.0] * (3 - len(values))  # omitted coordinates are 0, as in CalculiX
        self.node_ids.append(node)
        self.coordinates.append((values[0], values[1], values[2]))
        self.node_files.append(index)
        self.node_lines.append(number)
        if self.node_set is not None:
            self.node_set.ids.append(node)

    def element_line(self, index: int, number: int, body: str) -> None:
        block = self.block
        assert block is not None
        where = self.files[index].where(number)
        parts = _fields(body)
        trailing_comma = body.rstrip().endswith(",")
        if block.pending is None:
            element = _integer(parts[0], "element number", where)
            if element <= 0:
                raise ValueError(f"{where}: element number {element} is not positive")
            block.ids.append(element)
            block.files.append(index)
            block.lines.append(number)
            block.pending = []
            parts = parts[1:]
        for text in parts:
            if not text:
                raise ValueError(f"{where}: empty node field in element {block.ids[-1]}")
            block.pending.append(_integer(text, "node number", where))
        if block.count is None:
            if not trailing_comma:  # an unknown type's line continues after a comma
                self.finish_element(where)
        elif len(block.pending) >= block.count:
            if len(block.pending) > block.count:  # CalculiX reads the first ones only
                del block.pending[block.count :]
                block.truncated += 1
            self.finish_element(where)

    def finish_element(self, where: str) -> None:
        block = self.block
        assert block is not None and block.pending is not None
        if block.count is None and block.rows and len(block.pending) != len(block.rows[0]):
            raise ValueError(
                f"{where}: element {block.ids[-1]} of TYPE={block.type} has "
                f"{len(block.pending)} nodes, the block's first element {len(block.rows[0])}"
            )
        block.rows.append(block.pending)
        block.pending = None

    def close_block(self) -> None:
        block = self.block
        if block is None:
            return
        if block.pending is not None:
            where = self.files[block.files[-1]].where(block.lines[-1])
            expected = block.count if block.count is not None else "more"
            raise ValueError(
                f"{where}: element {block.ids[-1]} (TYPE={block.type}) is incomplete: "
                f"{len(block.pending)} nodes of {expected} before the next keyword or the "
                "end of the deck (a continuation line is missing)"
            )
        if block.truncated:
            self.warnings.append(
                f"{self.files[block.file].where(block.line)}: {block.truncated} elements of "
                f"TYPE={block.type} list more than {block.count} nodes; the extra ones are "
                "ignored, as CalculiX ignores them"
            )
        width = len(block.rows[0]) if block.rows else (block.count or 0)
        self.blocks.append(
            ElementBlock(
                block.type,
                block.elset,
                np.asarray(block.ids, dtype=np.int64),
                np.asarray(block.rows, dtype=np.int64).reshape(len(block.rows), width),
                block.file,
                block.line,
                np.asarray(block.files, dtype=np.int64),
                np.asarray(block.lines, dtype=np.int64),
            )
        )
        if block.elset is not None:
            definition = SetDefinition("element", block.elset, block.file, block.line)
            definition.ids = block.ids
            self.set_definitions.append(definition)
        self.block = None

    def set_line(self, index: int, number: int, body: str) -> None:
        definition = self.current_set
        assert definition is not None
        where = self.files[index].where(number)
        parts = [part for part in _fields(body) if part]
        if definition.generate:
            if not 2 <= len(parts) <= 3:
                raise ValueError(
                    f"{where}: GENERATE takes 'first, last[, step]', got {len(parts)} fields"
                )
            first, last, *step = (_integer(text, "GENERATE bound", where) for text in parts)
            increment = step[0] if step else 1
            if first <= 0 or last < first or increment <= 0:
                raise ValueError(
                    f"{where}: GENERATE range {first}, {last}, {increment} is not "
                    "0 < first <= last with a positive step"
                )
            definition.ranges.append((first, last, increment))
            return
        for text in parts:
            if _INTEGER.fullmatch(text):
                definition.ids.append(_integer(text, "set member", where))
            else:
                definition.names.append((text, index, number))

    def finish(self) -> ParsedDeck:
        self.close_block()
        return ParsedDeck(
            self.files,
            np.asarray(self.node_ids, dtype=np.int64),
            np.asarray(self.coordinates, dtype=np.float64).reshape(-1, 3),
            np.asarray(self.node_files, dtype=np.int64),
            np.asarray(self.node_lines, dtype=np.int64),
            self.blocks,
            self.set_definitions,
            self.user_counts,
            self.warnings,
        )


def parse_deck(path: Path) -> ParsedDeck:
    """Read the deck ``path`` and the files it includes; see the module's docstring."""
    parser = _Parser(path)
    parser.read_file(path, None, None, str(path))
    return parser.finish()
