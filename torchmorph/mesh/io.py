"""Reading and writing tetrahedral meshes through meshio.

Formats, chosen by the file extension:

==========  =====================================================================
extension   notes
==========  =====================================================================
``.vtu``    VTK XML unstructured grid (ParaView).
``.vtk``    legacy VTK.
``.xdmf``   XDMF with its heavy data in an HDF5 file beside it (``.h5``); needs
``.xmf``    the ``h5py`` package.
``.msh``    Gmsh. Written as MSH 4.1 binary; MSH 2.2 and 4.1, ASCII or binary,
            are read.
==========  =====================================================================

Node sets are stored as point-data flag arrays named ``set:<name>`` (1 for a
member, 0 otherwise), so they survive a round trip in every format and show up
in ParaView and Gmsh (as views). Characters that some format cannot hold in a
name (``%``, ``"``, ``'``, ``<``, ``>``, ``&``, white space and control
characters) are percent-encoded in the stored name (``"inlet wall"`` is stored
as ``set:inlet%20wall``) and decoded on reading, so every node-set name round-trips
in every format. Names of point and cell data fields are not renamed: a name the
target format cannot hold is rejected before anything is written.

Writes are atomic (:func:`torchmorph._atomic.atomic_output`): the file is written
beside the target and renamed over it only when complete, so a failing overwrite
leaves the previous file intact. XDMF writes its ``.h5`` file first, then the
``.xdmf`` file that refers to it. Reading also turns Gmsh physical groups of
points, curves and surfaces into node sets named after the group, and meshio
``point_sets`` (Abaqus, MED, …) into node sets.

Only linear tetrahedra (meshio's ``"tetra"`` cells) are read; other cell blocks
(triangles, lines, …) are used for physical groups only, then ignored.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import urllib.parse
from collections.abc import Mapping
from pathlib import Path
from typing import Literal, overload

import numpy as np
import torch
from torch import Tensor

from torchmorph._atomic import atomic_output
from torchmorph.mesh.model import TetMesh

__all__ = [
    "MESH_FORMATS",
    "decode_set_name",
    "encode_set_name",
    "from_meshio",
    "read_mesh",
    "to_meshio",
    "write_mesh",
]

#: File extensions understood by :func:`read_mesh` and :func:`write_mesh`, and
#: the meshio format used for each.
MESH_FORMATS: dict[str, str] = {
    ".vtu": "vtu",
    ".vtk": "vtk",
    ".xdmf": "xdmf",
    ".xmf": "xdmf",
    ".msh": "gmsh",
}

#: Prefix of the point-data arrays that carry node sets.
NODE_SET_PREFIX = "set:"

# Point and cell data that meshio adds for bookkeeping, not user fields.
_BOOKKEEPING_PREFIXES = ("gmsh:",)

PathLike = str | os.PathLike


# --------------------------------------------------------------------------- meshio


def to_meshio(
    mesh: TetMesh,
    *,
    point_data: Mapping[str, Tensor | np.ndarray] | None = None,
    cell_data: Mapping[str, Tensor | np.ndarray] | None = None,
):
    """Convert a mesh (and fields on it) to a :class:`meshio.Mesh`.

    Parameters
    ----------
    mesh : TetMesh
        The mesh. Its node sets become point data ``set:<name>`` (uint8 flags).
    point_data : mapping of str to array, shape (N,) or (N, k), optional
        Nodal fields, e.g. ``{"displacement": d}``.
    cell_data : mapping of str to array, shape (M,) or (M, k), optional
        Per-tetrahedron fields, e.g. ``{"quality": q}``.

    Returns
    -------
    meshio.Mesh
        One ``"tetra"`` cell block.

    Raises
    ------
    ValueError
        If a field does not have N (or M) rows, or a point-data name starts
        with the reserved ``set:`` prefix.
    """
    import meshio

    if not isinstance(mesh, TetMesh):
        raise TypeError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
    points = _to_numpy(mesh.points)
    tets = _to_numpy(mesh.tets)
    fields: dict[str, np.ndarray] = {}
    for key, value in (point_data or {}).items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"point_data: names must be non-empty strings, got {key!r}")
        if key.startswith(NODE_SET_PREFIX):
            raise ValueError(
                f"point_data[{key!r}]: names starting with {NODE_SET_PREFIX!r} are reserved "
                "for node sets; pass node sets through the mesh"
            )
        fields[key] = _field(value, f"point_data[{key!r}]", mesh.num_nodes, "nodes")
    for name, nodes in mesh.node_sets.items():
        flags = np.zeros(mesh.num_nodes, dtype=np.uint8)
        flags[_to_numpy(nodes)] = 1
        fields[NODE_SET_PREFIX + encode_set_name(name)] = flags
    cells: dict[str, list[np.ndarray]] = {}
    for key, value in (cell_data or {}).items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"cell_data: names must be non-empty strings, got {key!r}")
        cells[key] = [_field(value, f"cell_data[{key!r}]", mesh.num_tets, "tetrahedra")]
    return meshio.Mesh(points, [("tetra", tets)], point_data=fields, cell_data=cells)


@overload
def from_meshio(m, *, name: str | None = None, return_data: Literal[False] = False) -> TetMesh: ...


@overload
def from_meshio(
    m, *, name: str | None = None, return_data: Literal[True]
) -> tuple[TetMesh, dict[str, Tensor], dict[str, Tensor]]: ...


def from_meshio(m, *, name: str | None = None, return_data: bool = False):
    """Build a :class:`TetMesh` from a :class:`meshio.Mesh`.

    Parameters
    ----------
    m : meshio.Mesh
        Must hold at least one ``"tetra"`` cell block; all such blocks are
        concatenated in order. Points must be 3-D.
    name : str, optional, keyword-only
        The mesh's name.
    return_data : bool, keyword-only
        Also return the point and cell data.

    Returns
    -------
    TetMesh
        With node sets from ``set:<name>`` point data, ``m.point_sets`` and
        Gmsh physical groups of dimension 0 to 2 (in that order of precedence
        when names clash).
    point_data : dict of str to Tensor, shape (N, ...)
        Only with ``return_data``: the point data, less node-set flags and
        ``gmsh:`` bookkeeping arrays.
    cell_data : dict of str to Tensor, shape (M, ...)
        Only with ``return_data``: data of the tetra blocks, concatenated,
        aligned with the tetrahedra, less ``gmsh:`` bookkeeping arrays.

    Raises
    ------
    ValueError
        If there are no tetrahedra, the points are not 3-D, or the mesh is
        invalid for :class:`TetMesh`.
    """
    points = np.asarray(m.points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"mesh points must be 3-D, shape (N, 3), got {points.shape}")
    blocks = [i for i, block in enumerate(m.cells) if block.type == "tetra"]
    if not blocks:
        present = ", ".join(sorted({block.type for block in m.cells})) or "none"
        raise ValueError(
            f"the mesh holds no linear tetrahedra ('tetra' cells); cell types present: {present}"
        )
    tets = np.concatenate([np.asarray(m.cells[i].data, dtype=np.int64) for i in blocks])
    num_nodes = points.shape[0]

    node_sets: dict[str, np.ndarray] = {}
    point_data: dict[str, Tensor] = {}
    for key, value in m.point_data.items():
        value = np.asarray(value)
        if key.startswith(NODE_SET_PREFIX):
            node_sets[decode_set_name(key[len(NODE_SET_PREFIX) :])] = np.flatnonzero(
                value.reshape(num_nodes, -1)[:, 0]
            )
        elif not key.startswith(_BOOKKEEPING_PREFIXES):
            point_data[key] = _to_tensor(value)
    for key, value in getattr(m, "point_sets", {}).items():
        node_sets.setdefault(key, np.asarray(value, dtype=np.int64))
    for key, value in _physical_group_nodes(m).items():
        node_sets.setdefault(key, value)

    mesh = TetMesh(points, tets, node_sets, name=name)
    if not return_data:
        return mesh
    cell_data: dict[str, Tensor] = {}
    for key, per_block in m.cell_data.items():
        if key.startswith(_BOOKKEEPING_PREFIXES):
            continue
        parts = [np.asarray(per_block[i]) for i in blocks]
        cell_data[key] = _to_tensor(np.concatenate(parts))
    return mesh, point_data, cell_data


def _physical_group_nodes(m) -> dict[str, np.ndarray]:
    """Nodes of the Gmsh physical groups of dimension 0, 1 and 2, by group name."""
    names: dict[tuple[int, int], str] = {}
    for name, value in (m.field_data or {}).items():
        value = np.asarray(value).ravel()
        if value.size == 2:
            names[(int(value[1]), int(value[0]))] = name  # field_data: [tag, dim]
    group_names = set(names.values())
    collected: dict[str, list[np.ndarray]] = {}
    # MSH 4.1 (meshio >= 5): cell_sets name -> one index array per cell block.
    for name, per_block in (m.cell_sets or {}).items():
        if name not in group_names:
            continue
        for block, indices in zip(m.cells, per_block, strict=False):
            if indices is None or len(indices) == 0 or block.dim >= 3:
                continue
            collected.setdefault(name, []).append(np.asarray(block.data)[indices].ravel())
    # MSH 2.2: a physical tag per cell in cell_data["gmsh:physical"].
    if not collected and "gmsh:physical" in m.cell_data:
        for block, tags in zip(m.cells, m.cell_data["gmsh:physical"], strict=True):
            if block.dim >= 3:
                continue
            tags = np.asarray(tags)
            for tag in np.unique(tags):
                if tag <= 0:
                    continue
                name = names.get((block.dim, int(tag)), f"physical_{int(tag)}")
                cells = np.asarray(block.data)[tags == tag]
                collected.setdefault(name, []).append(cells.ravel())
    return {name: np.unique(np.concatenate(parts)) for name, parts in collected.items()}


# --------------------------------------------------------------------------- files


def _format_of(path: Path, argument: str) -> str:
    extension = path.suffix.lower()
    if extension not in MESH_FORMATS:
        known = ", ".join(sorted(MESH_FORMATS))
        raise ValueError(
            f"{argument}: unsupported mesh file extension {extension or '(none)'!r} "
            f"in {str(path)!r}; supported: {known}"
        )
    return MESH_FORMATS[extension]


def _require_h5py(path: Path) -> None:
    try:
        import h5py  # noqa: F401
    except ImportError:
        raise ValueError(
            f"path: XDMF files ({str(path)!r}) need the h5py package: pip install h5py"
        ) from None


@overload
def read_mesh(path: PathLike, *, return_data: Literal[False] = False) -> TetMesh: ...


@overload
def read_mesh(
    path: PathLike, *, return_data: Literal[True]
) -> tuple[TetMesh, dict[str, Tensor], dict[str, Tensor]]: ...


def read_mesh(path: PathLike, *, return_data: bool = False):
    """Read a tetrahedral mesh, with its node sets, from a file.

    Parameters
    ----------
    path : str or path-like
        A ``.vtu``, ``.vtk``, ``.xdmf``/``.xmf`` or ``.msh`` file.
    return_data : bool, keyword-only
        Also return the point data and the cell data of the tetrahedra, as
        tensors (``point_data["displacement"]`` of shape (N, 3), …).

    Returns
    -------
    TetMesh or (TetMesh, dict, dict)
        The mesh, named after the file's stem; see :func:`from_meshio` for the
        node sets and data.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        For an unsupported extension, a file meshio cannot parse, a file
        without tetrahedra, or an invalid mesh.
    """
    import meshio

    path = Path(path)
    file_format = _format_of(path, "path")
    if not path.is_file():
        raise FileNotFoundError(f"path: mesh file {str(path)!r} does not exist")
    if file_format == "xdmf":
        _require_h5py(path)
    # The format's own reader: meshio.read ends the process (sys.exit) on a parse error.
    reader = getattr(meshio, file_format).read
    try:
        m = reader(str(path))
    except Exception as error:  # parsers raise many kinds; report them uniformly
        raise ValueError(
            f"path: could not read {str(path)!r} as {file_format}: {type(error).__name__}: {error}"
        ) from error
    try:
        return from_meshio(m, name=path.stem, return_data=return_data)
    except ValueError as error:
        raise ValueError(f"path: {str(path)!r}: {error}") from error


def write_mesh(
    path: PathLike,
    mesh: TetMesh,
    *,
    point_data: Mapping[str, Tensor | np.ndarray] | None = None,
    cell_data: Mapping[str, Tensor | np.ndarray] | None = None,
) -> None:
    """Write a mesh, its node sets and optional fields to a file.

    Parameters
    ----------
    path : str or path-like
        Target file; the extension picks the format (``.vtu``, ``.vtk``,
        ``.xdmf``/``.xmf``, ``.msh``). ``.msh`` is written as Gmsh MSH 4.1
        binary; ``.xdmf`` writes an ``.h5`` file beside it.
    mesh : TetMesh
        The mesh; node sets are written as point data ``set:<name>``.
    point_data : mapping of str to array, shape (N,) or (N, k), optional
        Nodal fields, e.g. ``{"displacement": d}`` (shown as vectors in
        ParaView).
    cell_data : mapping of str to array, shape (M,) or (M, k), optional
        Per-tetrahedron fields, e.g. ``{"quality": edge_ratio(...)}``.

    Raises
    ------
    ValueError
        For an unsupported extension, fields of the wrong length, reserved
        names, a field name the format cannot hold (control characters anywhere;
        ``" ' < > &`` in ``.vtu``; white space in ``.vtk``; ``"`` in ``.msh``),
        or a missing h5py for XDMF. Nothing is written then.
    FileNotFoundError
        If the target's directory does not exist.

    Notes
    -----
    The write is atomic: an existing file is replaced only once the new one is
    complete; if writing fails, the old file is left as it was. Node-set names
    are percent-encoded where needed (see the module's notes) and come back
    unchanged from :func:`read_mesh`.

    Gmsh stores node data as float64: integer fields come back as floats from
    ``.msh`` files. Gmsh node data must have 1, 3 or 9 components to be shown
    as scalars, vectors or tensors in Gmsh itself.
    """
    import meshio

    path = Path(path)
    file_format = _format_of(path, "path")
    if file_format == "xdmf":
        _require_h5py(path)
    converted = to_meshio(mesh, point_data=point_data, cell_data=cell_data)
    for kind, names in (("point_data", converted.point_data), ("cell_data", converted.cell_data)):
        for key in names:
            if not key.startswith(NODE_SET_PREFIX):
                _check_field_name(key, file_format, f"{kind}[{key!r}]")
    options = {"binary": True} if file_format == "gmsh" else {}
    if file_format == "xdmf":
        _write_xdmf(path, converted)
        return
    with atomic_output(path) as temporary:
        meshio.write(temporary, converted, file_format=file_format, **options)


def _write_xdmf(path: Path, converted) -> None:
    """XDMF and its ``.h5`` file, each atomically, the ``.h5`` first.

    meshio names the heavy-data file after the ``.xdmf`` file and refers to it by
    name, so both are written under their final names in a temporary directory
    beside the target, then moved into place.
    """
    import meshio

    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"path: directory {str(directory)!r} does not exist")
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=directory))
    try:
        staged = staging / path.name
        meshio.write(staged, converted, file_format="xdmf")
        heavy = staged.with_suffix(".h5")
        with atomic_output(path.with_suffix(".h5")) as temporary:
            os.replace(heavy, temporary)
        with atomic_output(path) as temporary:
            os.replace(staged, temporary)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


# --------------------------------------------------------------------------- names

# Characters percent-encoded in stored node-set names: the escape character itself,
# what XML attributes (VTU, XDMF) and Gmsh's quoted strings cannot hold, and white
# space (legacy VTK splits names on it).
_ENCODED_CHARACTERS = frozenset("%\"'<>&")

# Characters each format cannot hold in a field name (beyond control characters,
# which no format holds).
_FORBIDDEN_IN_FIELD_NAMES: dict[str, str] = {
    "vtu": "\"'<>&",
    "vtk": "",  # and white space
    "xdmf": "",
    "gmsh": '"',
}


def _needs_encoding(character: str) -> bool:
    return character in _ENCODED_CHARACTERS or character.isspace() or not character.isprintable()


def encode_set_name(name: str) -> str:
    """The stored form of a node-set name: unsafe characters percent-encoded.

    ``%``, ``"``, ``'``, ``<``, ``>``, ``&``, white space and non-printable
    characters become ``%XX`` (their UTF-8 bytes); everything else is kept, so
    ordinary names (``"wing"``, ``"z1"``, ``"ε-wall"``) are stored unchanged.
    :func:`decode_set_name` inverts it.
    """
    return "".join(
        urllib.parse.quote(character, safe="") if _needs_encoding(character) else character
        for character in name
    )


def decode_set_name(stored: str) -> str:
    """Inverse of :func:`encode_set_name` (``%XX`` sequences decoded as UTF-8)."""
    return urllib.parse.unquote(stored, errors="strict") if "%" in stored else stored


def _check_field_name(name: str, file_format: str, argument: str) -> None:
    """Raise ``ValueError`` if a point/cell data name cannot be stored in ``file_format``.

    Control characters are refused everywhere; VTU refuses ``" ' < > &``
    (XML attributes), legacy VTK refuses white space, Gmsh refuses ``"``.
    """
    bad = sorted(
        {
            c
            for c in name
            if not c.isprintable()
            or c in _FORBIDDEN_IN_FIELD_NAMES[file_format]
            or (file_format == "vtk" and c.isspace())
        }
    )
    if bad:
        shown = ", ".join(repr(c) for c in bad)
        raise ValueError(
            f"{argument}: a {file_format} file cannot hold the character(s) {shown} in a field "
            "name; rename the field"
        )


# --------------------------------------------------------------------------- helpers


def _to_numpy(value: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(value, Tensor):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def _to_tensor(array: np.ndarray) -> Tensor:
    """A tensor from a file's array (legacy VTK data are big-endian)."""
    array = np.asarray(array)
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    return torch.from_numpy(np.ascontiguousarray(array))


def _field(value: Tensor | np.ndarray, name: str, rows: int, what: str) -> np.ndarray:
    array = _to_numpy(value)
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    if array.dtype.kind not in "fiu":
        raise ValueError(f"{name} must hold numbers, got dtype {array.dtype}")
    if array.ndim not in (1, 2) or array.shape[0] != rows:
        raise ValueError(
            f"{name} must have shape ({rows},) or ({rows}, k) for {rows} {what}, got {array.shape}"
        )
    return np.ascontiguousarray(array)
