"""OpenFOAM's file syntax, as the polyMesh files use it: the ``FoamFile`` header, lists
of labels, vectors and faces (ASCII, binary, uniform), the ``boundary`` dictionary, and
the points list written back in the format it was read in.

Private helpers of :mod:`torchmorph.mesh.formats.openfoam`; every error is a
``ValueError`` that names the file.
"""

from __future__ import annotations

import gzip
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "FoamFile",
    "FoamFormat",
    "check_mesh",
    "find_file",
    "format_points",
    "read_boundary",
    "read_faces",
    "read_foam_file",
    "read_labels",
    "read_points",
]

#: White space and comments (``//`` to the end of the line, ``/* ... */``).
_SKIP = re.compile(rb"(?:\s+|//[^\n]*|/\*.*?\*/)*", re.S)
#: One token of a dictionary: a quoted string, a punctuation mark, or a word (which may
#: hold ``/`` but not start a comment).
_TOKEN = re.compile(rb'"(?:[^"\\]|\\.)*"|[{}();\[\]]|(?:[^\s{}();"/\[\]]|/(?![/*]))+')
_COUNT = re.compile(rb"\d+")
#: The end of a list of parenthesised entries: the last entry's ")" and the list's own.
_LIST_END = re.compile(rb"\)\s*\)")
#: Which bytes separate tokens: white space, and white space or parentheses.
_WHITE = np.zeros(256, dtype=bool)
_WHITE[list(b" \t\n\r\f\v")] = True
_WHITE_OR_PARENTHESIS = _WHITE.copy()
_WHITE_OR_PARENTHESIS[list(b"()")] = True
#: ``gzip``'s magic number.
_GZIP_MAGIC = b"\x1f\x8b"


def _skip(data: bytes, position: int) -> int:
    """The position after the white space and comments that start at ``position``."""
    match = _SKIP.match(data, position)
    assert match is not None  # the pattern matches the empty string too
    return match.end()


@dataclass(frozen=True)
class FoamFormat:
    """How a file's lists are stored: ``binary`` or ASCII, the byte sizes of labels and
    scalars and the byte order (``arch`` in the header), and whether it is gzipped."""

    binary: bool = False
    label_bytes: int = 4
    scalar_bytes: int = 8
    byte_order: str = "<"
    compressed: bool = False

    def label_dtype(self) -> np.dtype:
        return np.dtype(f"{self.byte_order}i{self.label_bytes}")

    def scalar_dtype(self) -> np.dtype:
        return np.dtype(f"{self.byte_order}f{self.scalar_bytes}")


@dataclass
class FoamFile:
    """A file's content (decompressed), its header entries and where its body starts."""

    path: Path
    data: bytes
    header: dict[str, str]
    format: FoamFormat
    body_start: int

    def fail(self, message: str) -> ValueError:
        return ValueError(f"case: {self.path}: {message}")


def find_file(directory: Path, name: str) -> Path:
    """``directory/name``, or ``name.gz`` when only that exists (as OpenFOAM looks)."""
    for candidate in (directory / name, directory / f"{name}.gz"):
        if candidate.is_file():
            return candidate
    raise ValueError(f"case: {directory / name} is missing (neither {name!r} nor {name + '.gz'!r})")


def read_foam_file(path: Path) -> FoamFile:
    """Read ``path`` (gzipped or not) and parse its ``FoamFile`` header."""
    raw = path.read_bytes()
    compressed = raw[:2] == _GZIP_MAGIC
    if compressed:
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as error:
            raise ValueError(f"case: {path}: not a readable gzip file ({error})") from None
    position = _skip(raw, 0)
    token = _TOKEN.match(raw, position)
    if token is None or token.group() != b"FoamFile":
        raise ValueError(f"case: {path}: no FoamFile header at the start of the file")
    header: dict[str, str] = {}
    position = _expect(raw, token.end(), b"{", path, "the FoamFile header")
    while True:
        words, position, closing = _entry(raw, position, path)
        if closing:
            break
        if len(words) < 2:
            raise ValueError(f"case: {path}: FoamFile header entry {words!r} has no value")
        header[words[0]] = " ".join(_unquote(word) for word in words[1:])
    form = header.get("format", "ascii")
    if form not in ("ascii", "binary"):
        raise ValueError(f"case: {path}: format must be ascii or binary, got {form!r}")
    return FoamFile(path, raw, header, _parse_format(header, compressed, path), position)


def read_labels(file: FoamFile, position: int, what: str) -> tuple[np.ndarray, int]:
    """A ``labelList`` from ``position``; returns the int64 labels and the position after."""
    count, position, opening = _list_start(file, position, what)
    if opening == b"{":
        value, position = _uniform(file, position, what)
        return np.full(count, _labels(file, value, what, 1)[0], dtype=np.int64), position
    if file.format.binary:
        data, position = _binary(file, position, count, file.format.label_dtype(), what)
        return data.astype(np.int64), position
    end = file.data.find(b")", position)
    if end < 0:
        raise file.fail(f"the {what} list is truncated (no closing parenthesis)")
    labels = _labels(file, file.data[position:end], what, count)
    return labels, end + 1


def read_points(file: FoamFile, position: int) -> tuple[np.ndarray, int, int]:
    """The points (vectorField) from ``position``: (N, 3) float64, the position where the
    list starts (its size) and the position after it."""
    start = _skip(file.data, position)
    count, position, opening = _list_start(file, position, "points")
    if opening == b"{":
        value, position = _uniform(file, position, "points")
        return np.tile(_vectors(file, value, "points", 1), (count, 1)), start, position
    if file.format.binary:
        dtype = file.format.scalar_dtype()
        data, position = _binary(file, position, 3 * count, dtype, "points")
        return data.astype(np.float64).reshape(count, 3), start, position
    body, position = _ascii_entries(file, position, "points")
    return _vectors(file, body, "points", count), start, position


def read_faces(file: FoamFile, position: int) -> tuple[np.ndarray, np.ndarray]:
    """The faces as (offsets (F + 1,), labels (L,)), from a ``faceList`` (ASCII
    ``n(a b c ...)`` entries) or a ``faceCompactList`` (offsets and labels, as binary
    files store them)."""
    kind = file.header.get("class", "faceList")
    if kind == "faceCompactList":
        offsets, position = read_labels(file, position, "faces' offsets")
        labels, position = read_labels(file, position, "faces' labels")
        if offsets.size == 0:
            offsets = np.zeros(1, dtype=np.int64)
        if offsets[0] != 0 or np.any(np.diff(offsets) < 0) or offsets[-1] != labels.size:
            raise file.fail(
                f"the faces' offsets must rise from 0 to the {labels.size} labels, got "
                f"{offsets[0]} .. {offsets[-1]}"
            )
        return offsets, labels
    if kind != "faceList":
        raise file.fail(f"class must be faceList or faceCompactList, got {kind!r}")
    if file.format.binary:
        raise file.fail("a binary faceList is not supported (OpenFOAM writes faceCompactList)")
    count, position, opening = _list_start(file, position, "faces")
    if opening == b"{":
        value, position = _uniform(file, position, "faces")
        offsets, labels = _face_entries(file, value, 1)
        size = labels.size
        return np.arange(count + 1, dtype=np.int64) * size, np.tile(labels, count)
    body, position = _ascii_entries(file, position, "faces")
    return _face_entries(file, body, count)


def read_boundary(file: FoamFile) -> list[dict]:
    """The patches of a ``boundary`` file, each a dict with ``name``, ``text`` (its
    dictionary as written) and ``entries`` (keyword -> value as written)."""
    data, position = file.data, file.body_start
    count, position, opening = _list_start(file, position, "boundary")
    if opening != b"(":
        raise file.fail("expected a list of patch dictionaries")
    patches: list[dict] = []
    while True:
        position = _skip(data, position)
        token = _TOKEN.match(data, position)
        if token is None:
            raise file.fail("the list of patches is truncated (no closing parenthesis)")
        if token.group() == b")":
            position = token.end()
            break
        name = _unquote(token.group().decode("latin-1"))
        if name in "{}();":
            raise file.fail(f"expected a patch name, got {name!r}")
        opening_brace = _expect(data, token.end(), b"{", file.path, f"patch {name!r}")
        entries: dict[str, str] = {}
        position = opening_brace
        while True:
            start = _skip(data, position)
            words, position, closing = _entry(data, start, file.path)
            if closing:
                break
            key, value = words[0], data[start:position].decode("latin-1")
            entries[key] = value[len(key) :].strip().rstrip(";").strip()
        text = data[opening_brace : position - 1].decode("latin-1")
        patches.append({"name": name, "entries": entries, "text": text})
    if count >= 0 and count != len(patches):
        raise file.fail(f"the list says {count} patches, it holds {len(patches)}")
    return patches


def format_points(points: np.ndarray, form: FoamFormat) -> bytes:
    """The points' list (size, parentheses, entries) as OpenFOAM writes it: in ASCII every
    coordinate with 17 significant digits (``%.17g``, exact for float64); in binary the
    raw scalars of ``form``'s size and byte order."""
    count = points.shape[0]
    if form.binary:
        raw = np.ascontiguousarray(points, dtype=form.scalar_dtype()).tobytes()
        return b"%d\n(" % count + raw + b")"
    lines = ("(%.17g %.17g %.17g)\n" * count) % tuple(points.reshape(-1).tolist())
    return b"%d\n(\n" % count + lines.encode("ascii") + b")"


def check_mesh(
    files: dict[str, FoamFile],
    n_points: int,
    offsets: np.ndarray,
    labels: np.ndarray,
    owner: np.ndarray,
    neighbour: np.ndarray,
    patches: list,
) -> None:
    """Check that the mesh files agree: ``owner`` as long as ``faces``, ``neighbour`` no
    longer, the point and cell labels in range, the patches (with ``start_face`` and
    ``n_faces``) following the internal faces and each other up to the last face."""
    n_faces = offsets.size - 1
    if owner.size != n_faces:
        raise files["owner"].fail(f"owner has {owner.size} labels for the {n_faces} faces")
    if neighbour.size > n_faces:
        raise files["neighbour"].fail(
            f"neighbour has {neighbour.size} labels, more than the {n_faces} faces"
        )
    if labels.size and (labels.min() < 0 or labels.max() >= n_points):
        bad = int(np.flatnonzero((labels < 0) | (labels >= n_points))[0])
        face = int(np.searchsorted(offsets, bad, side="right") - 1)
        raise files["faces"].fail(
            f"face {face} refers to point {labels[bad]}, out of range for the {n_points} points"
        )
    for name, cells in (("owner", owner), ("neighbour", neighbour)):
        if cells.size and cells.min() < 0:
            raise files[name].fail(f"{name} holds the negative cell label {cells.min()}")
    expected = neighbour.size
    for patch in patches:
        end = patch.start_face + patch.n_faces
        if end > n_faces:
            raise files["boundary"].fail(
                f"patch {patch.name!r} (faces {patch.start_face} .. {end - 1}) lies beyond "
                f"the {n_faces} faces"
            )
        if patch.start_face != expected:
            raise files["boundary"].fail(
                f"patch {patch.name!r} starts at face {patch.start_face}, expected {expected} "
                "(patches follow the internal faces and each other)"
            )
        expected = end
    if expected != n_faces:
        raise files["boundary"].fail(
            f"the patches end at face {expected}, the faces at {n_faces}: faces "
            f"{expected} .. {n_faces - 1} are in no patch and have no neighbour"
        )


# -- parsing helpers ------------------------------------------------------------------


def _parse_format(header: dict[str, str], compressed: bool, path: Path) -> FoamFormat:
    arch = header.get("arch", "")
    sizes = dict(re.findall(r"(label|scalar)\s*=\s*(\d+)", arch))
    label_bits, scalar_bits = int(sizes.get("label", 32)), int(sizes.get("scalar", 64))
    if label_bits not in (32, 64) or scalar_bits not in (32, 64):
        raise ValueError(
            f"case: {path}: arch {arch!r} gives label={label_bits} scalar={scalar_bits}"
        )
    return FoamFormat(
        binary=header.get("format") == "binary",
        label_bytes=label_bits // 8,
        scalar_bytes=scalar_bits // 8,
        byte_order=">" if arch.startswith("MSB") else "<",
        compressed=compressed,
    )


def _unquote(word: str) -> str:
    return word[1:-1] if len(word) >= 2 and word[0] == word[-1] == '"' else word


def _expect(data: bytes, position: int, mark: bytes, path: Path, where: str) -> int:
    position = _skip(data, position)
    if data[position : position + 1] != mark:
        found = data[position : position + 20].decode("latin-1") or "the end of the file"
        raise ValueError(f"case: {path}: {where}: expected {mark.decode()!r}, found {found!r}")
    return position + 1


def _entry(data: bytes, position: int, path: Path) -> tuple[list[str], int, bool]:
    """One ``keyword value ... ;`` entry or ``keyword { ... }`` sub-dictionary of a
    dictionary: its words and the position after it, or ``closing`` when the
    dictionary's ``}`` comes first. Brackets inside a value are skipped over."""
    words: list[str] = []
    depth = 0
    while True:
        position = _skip(data, position)
        token = _TOKEN.match(data, position)
        if token is None:
            raise ValueError(f"case: {path}: a dictionary is truncated (no closing brace)")
        text, position = token.group(), token.end()
        if not words and text == b"}":
            return words, position, True
        if not words and text == b";":
            continue
        if not words and text in b"{}()[]":
            raise ValueError(f"case: {path}: expected a keyword, found {text.decode()!r}")
        words.append(text.decode("latin-1"))
        if text in (b"{", b"(", b"["):
            depth += 1
        elif text in (b"}", b")", b"]"):
            depth -= 1
            if depth < 0:
                raise ValueError(f"case: {path}: unbalanced {text.decode()!r} in a dictionary")
            if depth == 0 and text == b"}" and words[1] == "{":
                return words, position, False  # a sub-dictionary ends without ";"
        elif text == b";" and depth == 0:
            return words[:-1], position, False


def _list_start(file: FoamFile, position: int, what: str) -> tuple[int, int, bytes]:
    """The optional size of a list and its opening mark (``(`` or ``{``)."""
    data = file.data
    position = _skip(data, position)
    count = -1
    number = _COUNT.match(data, position)
    if number is not None:
        count = int(number.group())
        position = _skip(data, number.end())
    opening = data[position : position + 1]
    if opening not in (b"(", b"{"):
        found = data[position : position + 20].decode("latin-1") or "the end of the file"
        raise file.fail(f"expected the {what} list, found {found!r}")
    if opening == b"{" and count < 0:
        raise file.fail(f"the uniform {what} list {{...}} needs its size before it")
    if file.format.binary and opening == b"(" and count < 0:
        raise file.fail(f"the binary {what} list needs its size before it")
    return count, position + 1, opening


def _uniform(file: FoamFile, position: int, what: str) -> tuple[bytes, int]:
    end = file.data.find(b"}", position)
    if end < 0:
        raise file.fail(f"the uniform {what} list is truncated (no closing brace)")
    return file.data[position:end], end + 1


def _binary(
    file: FoamFile, position: int, count: int, dtype: np.dtype, what: str
) -> tuple[np.ndarray, int]:
    size = count * dtype.itemsize
    end = position + size
    if end >= len(file.data) or file.data[end : end + 1] != b")":
        have = max(len(file.data) - position, 0)
        raise file.fail(
            f"the binary {what} list is truncated or of another precision: {count} "
            f"entries of {dtype.itemsize} bytes need {size} bytes and a ')', {have} bytes follow"
        )
    return np.frombuffer(file.data, dtype=dtype, count=count, offset=position), end + 1


def _ascii_entries(file: FoamFile, position: int, what: str) -> tuple[bytes, int]:
    """The text of a list of parenthesised entries, up to (not including) the list's
    closing parenthesis, and the position after it."""
    data = file.data
    inner = _skip(data, position)
    if data[inner : inner + 1] == b")":
        return b"", inner + 1
    end = _LIST_END.search(data, position)
    if end is None:
        raise file.fail(f"the {what} list is truncated (no closing parenthesis)")
    return data[position : end.start() + 1], end.end()


def _strip_comments(text: bytes) -> bytes:
    return re.sub(rb"//[^\n]*|/\*.*?\*/", b" ", text, flags=re.S) if b"/" in text else text


def _token_starts(text: bytes, separators: np.ndarray) -> np.ndarray:
    """Where the tokens of ``text`` start, tokens being separated by the bytes that
    ``separators`` marks (a table of 256 booleans)."""
    apart = separators[np.frombuffer(text, dtype=np.uint8)]
    return np.flatnonzero(~apart & np.concatenate([[True], apart[:-1]]))


def _numbers(
    file: FoamFile, text: bytes, dtype: type, what: str, expected: int | None = None
) -> np.ndarray:
    """Every white-space-separated token of ``text`` as a number of ``dtype``, parsed in C
    by ``np.fromstring``. A token that is not a number raises; so does a count other than
    ``expected`` (the tokens are counted when no count is expected, to be sure none was
    skipped)."""
    values: np.ndarray | None
    if not text.strip():
        values = np.zeros(0, dtype=dtype)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # older numpy warned, stopped
            try:
                values = np.fromstring(text, dtype=dtype, sep=" ")
            except ValueError:
                values = None
    if values is None or values.size != (
        expected if expected is not None else _token_starts(text, _WHITE).size
    ):
        kind = "label" if dtype is np.int64 else "number"
        tokens = text.split()
        for token in tokens:
            try:
                int(token) if dtype is np.int64 else float(token)
            except ValueError:
                raise file.fail(
                    f"{token.decode('latin-1')!r} in the {what} list is not a {kind}"
                ) from None
        if values is None or values.size != len(tokens):
            raise file.fail(f"the {what} list holds something that is not a {kind}")
    return values


def _labels(file: FoamFile, text: bytes, what: str, count: int) -> np.ndarray:
    labels = _numbers(file, _strip_comments(text), np.int64, what, count if count >= 0 else None)
    if count >= 0 and labels.size != count:
        raise file.fail(f"the {what} list says {count} entries, it holds {labels.size}")
    return labels


def _vectors(file: FoamFile, text: bytes, what: str, count: int) -> np.ndarray:
    text = _strip_comments(text)
    entries = text.count(b"(")
    if entries != text.count(b")"):
        raise file.fail(f"unbalanced parentheses in the {what} list")
    text = text.replace(b"(", b" ").replace(b")", b" ")
    numbers = _numbers(file, text, np.float64, what, 3 * entries)
    if numbers.size != 3 * entries:
        raise file.fail(
            f"{entries} entries of the {what} list hold {numbers.size} numbers, not 3 each"
        )
    if count >= 0 and entries != count:
        raise file.fail(f"the {what} list says {count} entries, it holds {entries}")
    return numbers.reshape(entries, 3)


def _face_entries(file: FoamFile, text: bytes, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Faces written ``n(a b ...)``: offsets (F + 1,) and labels (L,).

    The parentheses are found in the bytes and the tokens counted between them, so
    that every face's size is checked against what it lists without a loop."""
    text = _strip_comments(text)
    data = np.frombuffer(text, dtype=np.uint8)
    opens = np.flatnonzero(data == ord("("))
    closes = np.flatnonzero(data == ord(")"))
    faces = opens.size
    if faces == 0 and closes.size == 0 and not text.strip():
        offsets, labels = np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    else:
        starts = _token_starts(text, _WHITE_OR_PARENTHESIS)
        before_open = np.searchsorted(starts, opens)  # tokens before each "("
        before_close = np.searchsorted(starts, closes)
        previous_close = np.concatenate([[0], before_close[:-1]])
        if (
            closes.size != faces
            or faces == 0
            or np.any(closes < opens)
            or np.any(opens[1:] < closes[:-1])
            or np.any(before_open - previous_close != 1)  # one size before each "("
            or before_close[-1] != starts.size  # nothing after the last ")"
        ):
            raise file.fail("the faces list's entries are not of the form n(a b c ...)")
        listed = before_close - before_open
        text = text.replace(b"(", b" ").replace(b")", b" ")
        tokens = _numbers(file, text, np.int64, "faces", starts.size)
        sizes = tokens[before_open - 1]
        bad = np.flatnonzero(sizes != listed)
        if bad.size:
            face = int(bad[0])
            raise file.fail(f"face {face} says {sizes[face]} vertices, it lists {listed[face]}")
        is_label = np.ones(tokens.size, dtype=bool)
        is_label[before_open - 1] = False
        labels = tokens[is_label]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    if count >= 0 and faces != count:
        raise file.fail(f"the faces list says {count} entries, it holds {faces}")
    return offsets, labels
