"""Mesh files, solver decks and cases: :func:`read_mesh`, :func:`write_mesh`,
:func:`write_morphed`, one table of formats (:data:`FORMATS`, :func:`register_format`).

==================================  ============================================================
format (extensions)                 markers kept
==================================  ============================================================
VTU ``.vtu``, VTK ``.vtk``,         node sets (``set:<name>`` point data), face sets (facet
XDMF ``.xdmf``/``.xmf`` (+ ``.h5``)  blocks flagged ``face_set:<name>``), meshio point sets
Gmsh ``.msh`` (read 2.2/4.1,        physical groups (faces: face sets; points, curves: node
written 4.1 binary)                 sets), node sets as ``set:`` node data
SU2 ``.su2``                        markers (``MARKER_TAG``) as face sets, exactly
medit ``.mesh``/``.meshb``          references of boundary facets (``ref<k>``; no names)
Nastran ``.bdf``/``.nas``/``.fem``  property ids of boundary elements (``pid<k>``; no names)
Exodus II ``.e``/``.exo``            node sets, side sets (face sets) and facet blocks, by
                                    name; written back whole, coordinates changed only
CGNS ``.cgns`` (CGNS/HDF5, one      BCs: element-based ones (``FaceCenter``/``EdgeCenter``)
unstructured zone)                  and unreferenced boundary sections as face sets, vertex
                                    ones as node sets, families as groups; written back
                                    whole, coordinates changed only
MED ``.med``/``.rmed``/``.mmed``    groups: of nodes as node sets, of boundary faces as
                                    face sets, of cells as ``cell_set:`` cell data; written
                                    back whole, coordinates changed only
CalculiX/Abaqus ``.inp``            ``*NSET``s; written back whole, coordinates changed only
OpenFOAM case (a directory)         patches (face sets) and ``inGroups`` (groups); points
                                    written back, every other file byte-identical;
                                    pseudo-2-D cases (one cell thick, ``empty`` patches)
                                    read in their plane
==================================  ============================================================

:func:`read_mesh` returns a :class:`~torchmorph.mesh.TetMesh` for one block of linear
tetrahedra and a :class:`~torchmorph.mesh.Mesh` otherwise: every cell block kept, in
order (a kind torchmorph cannot handle is an error naming it, never a silent drop).
:func:`write_mesh` writes a mesh with its markers and fields to the mesh formats;
:func:`write_morphed` writes a file, deck or case again with new coordinates and
everything else kept (what a solver needs back after a morph). Writes are atomic
(:func:`torchmorph.mesh.atomic_output`): a failing write leaves the target as it was.
Marker names that a format cannot hold in a field name (``%``, quotes, ``<``, ``>``,
``&``, white space, control characters) are percent-encoded there and decoded on
reading, so every name round-trips.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats.meshio_formats import (
    FACE_SET_PREFIX,
    MESHIO_FORMATS,
    NODE_SET_PREFIX,
    data_to_meshio,
    decode_set_name,
    encode_set_name,
    meshio_to_data,
    move_meshio,
    read_meshio,
    write_meshio,
)
from torchmorph.mesh.model import Mesh
from torchmorph.mesh.tetmesh import TetMesh

__all__ = [
    "FORMATS",
    "MESH_FORMATS",
    "MeshFormat",
    "decode_set_name",
    "encode_set_name",
    "format_of",
    "from_meshio",
    "mesh_data",
    "mesh_from_data",
    "read_mesh",
    "register_format",
    "to_meshio",
    "write_mesh",
    "write_morphed",
]

PathLike = str | os.PathLike


@dataclass(frozen=True)
class MeshFormat:
    """One format of the table: how to read it, write it, and write it moved.

    ``read(path) -> MeshData``; ``write(path, data)`` or None where torchmorph writes no
    new files of the format; ``move(source, points, output)`` writes ``source`` again
    at ``output`` with new coordinates (``points`` in the rows of ``read``'s points) and
    everything else kept. ``directory``: the format is a case directory.
    """

    name: str
    extensions: tuple[str, ...]
    read: Callable[[Path], MeshData]
    write: Callable[[Path, MeshData], None] | None
    move: Callable[[Path, Any, Path], None]
    directory: bool = False


#: Every format, by name (see the module table).
FORMATS: dict[str, MeshFormat] = {}


def register_format(mesh_format: MeshFormat) -> None:
    """Add a format to :data:`FORMATS` (its extensions must be new)."""
    taken = {ext for f in FORMATS.values() if f.name != mesh_format.name for ext in f.extensions}
    clash = taken & set(mesh_format.extensions)
    if clash:
        raise ValueError(f"mesh_format: extension(s) {', '.join(sorted(clash))} are taken")
    FORMATS[mesh_format.name] = mesh_format


def _meshio(name: str, extensions: tuple[str, ...]) -> MeshFormat:
    def read(path: Path) -> MeshData:
        if name == "xdmf":
            _require_h5py(path)
        return read_meshio(path, name)

    def write(path: Path, data: MeshData) -> None:
        if name == "xdmf":
            _require_h5py(path)
        write_meshio(path, data, name)

    return MeshFormat(name, extensions, read, write, move_meshio)


for _name in dict.fromkeys(MESHIO_FORMATS.values()):
    register_format(_meshio(_name, tuple(ext for ext, n in MESHIO_FORMATS.items() if n == _name)))


def _su2() -> MeshFormat:
    def read(path: Path) -> MeshData:
        from torchmorph.mesh.formats.su2 import read_su2

        return read_su2(path)

    def write(path: Path, data: MeshData) -> None:
        from torchmorph.mesh.formats.su2 import write_su2

        write_su2(path, data)

    def move(source: Path, points: Any, output: Path) -> None:
        data = read(source)
        data.points = _checked_points(points, data.points.shape, "points")
        write(output, data)

    return MeshFormat("su2", (".su2",), read, write, move)


def _exodus() -> MeshFormat:
    def read(path: Path) -> MeshData:
        from torchmorph.mesh.formats.exodus import read_exodus

        return read_exodus(path)

    def write(path: Path, data: MeshData) -> None:
        from torchmorph.mesh.formats.exodus import write_exodus

        write_exodus(path, data)

    def move(source: Path, points: Any, output: Path) -> None:
        from torchmorph.mesh.formats.exodus import move_exodus

        move_exodus(source, points, output)

    return MeshFormat("exodus", (".e", ".exo"), read, write, move)


def _cgns() -> MeshFormat:
    def read(path: Path) -> MeshData:
        _require_h5py(path)
        from torchmorph.mesh.formats.cgns import read_cgns

        return read_cgns(path)

    def write(path: Path, data: MeshData) -> None:
        _require_h5py(path)
        from torchmorph.mesh.formats.cgns import write_cgns

        write_cgns(path, data)

    def move(source: Path, points: Any, output: Path) -> None:
        _require_h5py(source)
        from torchmorph.mesh.formats.cgns import move_cgns

        move_cgns(source, points, output)

    return MeshFormat("cgns", (".cgns",), read, write, move)


def _med() -> MeshFormat:
    def read(path: Path) -> MeshData:
        _require_h5py(path)
        from torchmorph.mesh.formats.med import read_med

        return read_med(path)

    def write(path: Path, data: MeshData) -> None:
        _require_h5py(path)
        from torchmorph.mesh.formats.med import write_med

        write_med(path, data)

    def move(source: Path, points: Any, output: Path) -> None:
        _require_h5py(source)
        from torchmorph.mesh.formats.med import move_med

        move_med(source, points, output)

    return MeshFormat("med", (".med", ".rmed", ".mmed"), read, write, move)


def _abaqus() -> MeshFormat:
    def read(path: Path) -> MeshData:
        from torchmorph.mesh.formats.abaqus import read_deck

        return read_deck(path).to_mesh_data()

    def write(path: Path, data: MeshData) -> None:
        write_meshio(path, data, "abaqus")

    def move(source: Path, points: Any, output: Path) -> None:
        from torchmorph.mesh.formats.abaqus import read_deck, write_deck

        deck = read_deck(source)
        write_deck(deck, points, output)

    return MeshFormat("abaqus", (".inp",), read, write, move)


def _openfoam() -> MeshFormat:
    def read(path: Path, *, planar: bool = True) -> MeshData:
        from torchmorph.mesh.formats.openfoam import pseudo_2d, read_foam_case

        case = read_foam_case(path)
        flat = pseudo_2d(case) if planar else None
        return case.to_mesh_data() if flat is None else flat.mesh

    def move(source: Path, points: Any, output: Path) -> None:
        from torchmorph.mesh.formats.openfoam import pseudo_2d, read_foam_case, write_foam_points

        case = read_foam_case(source)
        points = np.asarray(points.detach().cpu() if isinstance(points, Tensor) else points)
        if points.ndim == 2 and points.shape[1] == 2:  # in-plane points of a pseudo-2-D case
            flat = pseudo_2d(case)
            if flat is None:
                raise ValueError(
                    f"points: 2-D points for {str(source)!r}, which is no pseudo-2-D case"
                )
            reference = flat.mesh.points
            points = _checked_points(points, reference.shape, "points")
            points = case.points + flat.lift(points - reference)
        write_foam_points(case, _checked_points(points, case.points.shape, "points"), output)

    return MeshFormat("openfoam", (), read, None, move, directory=True)


for _factory in (_su2, _exodus, _cgns, _med, _abaqus, _openfoam):
    register_format(_factory())

#: File extensions :func:`read_mesh` understands, and their format (an OpenFOAM case is a
#: directory).
MESH_FORMATS: dict[str, str] = {ext: f.name for f in FORMATS.values() for ext in f.extensions}


def format_of(path: PathLike, argument: str = "path") -> MeshFormat:
    """The format of ``path``: an OpenFOAM case for a directory (holding
    ``constant/polyMesh``, or the polyMesh directory itself), else by extension."""
    path = Path(path)
    if path.is_dir():
        return FORMATS["openfoam"]
    extension = path.suffix.lower()
    if extension == ".gz" and Path(path.stem).suffix.lower() == ".inp":
        extension = ".inp"
    for mesh_format in FORMATS.values():
        if extension in mesh_format.extensions:
            return mesh_format
    known = ", ".join(sorted(MESH_FORMATS))
    raise ValueError(
        f"{argument}: unsupported mesh file extension {extension or '(none)'!r} in "
        f"{str(path)!r}; supported: {known}, or an OpenFOAM case directory"
    )


def _require_h5py(path: Path) -> None:
    try:
        import h5py  # noqa: F401
    except ImportError:
        raise ValueError(f"path: {str(path)!r} needs the h5py package: pip install h5py") from None


def _checked_points(points: Any, shape: tuple[int, ...], argument: str) -> np.ndarray:
    array = np.asarray(points.detach().cpu() if isinstance(points, Tensor) else points)
    array = array.astype(np.float64)
    if array.shape != tuple(shape):
        raise ValueError(f"{argument} must have shape {tuple(shape)}, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{argument} holds NaN or infinite values")
    return array


# --------------------------------------------------------------------------- conversion


def mesh_from_data(data: MeshData, *, name: str | None = None) -> Mesh:
    """The :class:`Mesh` of ``data`` (a :class:`TetMesh` for one block of linear
    tetrahedra). A node set named like a face set that holds the face set's nodes (a
    reader's nodes of its face markers) is the face set's: the face set carries the
    marker; one that holds other nodes is kept as ``<name>_nodes``, with a warning."""
    from torchmorph.mesh.formats._sets import separate_node_sets

    node_sets = {
        k: v
        for k, v in separate_node_sets(
            {k: np.asarray(v) for k, v in data.node_sets.items()},
            data.face_sets,
            "node set",
            name or "mesh data",
            stacklevel=3,
        ).items()
        if k not in data.face_sets
    }
    if len(data.cells) == 1 and data.cells[0][0] == "tetra" and data.points.shape[1] == 3:
        return TetMesh(
            data.points,
            data.cells[0][1],
            node_sets,
            face_sets=data.face_sets,
            groups=data.groups,
            name=name,
        )
    return Mesh(data.points, data.cells, node_sets, data.face_sets, groups=data.groups, name=name)


def mesh_data(
    mesh: Mesh,
    *,
    point_data: Mapping[str, Tensor | np.ndarray] | None = None,
    cell_data: Mapping[str, Tensor | np.ndarray] | None = None,
) -> MeshData:
    """:class:`MeshData` of a mesh and fields on it (point data (N, ...), cell data
    (M, ...) over the cells numbered across blocks, split per block here)."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a torchmorph Mesh, got {type(mesh).__name__}")
    fields: dict[str, np.ndarray] = {}
    for key, value in (point_data or {}).items():
        _check_key(key, "point_data")
        if key.startswith(NODE_SET_PREFIX):
            raise ValueError(
                f"point_data[{key!r}]: names starting with {NODE_SET_PREFIX!r} are reserved "
                "for node sets; pass node sets through the mesh"
            )
        fields[key] = _field(value, f"point_data[{key!r}]", mesh.num_nodes, "nodes")
    counts = [int(block.nodes.shape[0]) for block in mesh.cells]
    per_block: dict[str, list[np.ndarray]] = {}
    for key, value in (cell_data or {}).items():
        _check_key(key, "cell_data")
        if key.startswith(FACE_SET_PREFIX):
            raise ValueError(
                f"cell_data[{key!r}]: names starting with {FACE_SET_PREFIX!r} are reserved"
            )
        array = _field(value, f"cell_data[{key!r}]", mesh.num_cells, "cells")
        per_block[key] = np.split(array, np.cumsum(counts)[:-1])
    return MeshData(
        points=_to_numpy(mesh.points),
        cells=[(b.kind, _to_numpy(b.nodes)) for b in mesh.cells],
        node_sets={k: _to_numpy(v) for k, v in mesh.node_sets.items()},
        face_sets={
            k: [(b.kind, _to_numpy(b.nodes)) for b in blocks]
            for k, blocks in mesh.face_sets.items()
        },
        groups={k: list(v) for k, v in mesh.groups.items()},
        point_data=fields,
        cell_data=per_block,
    )


def to_meshio(
    mesh: Mesh,
    *,
    point_data: Mapping[str, Tensor | np.ndarray] | None = None,
    cell_data: Mapping[str, Tensor | np.ndarray] | None = None,
):
    """A :class:`meshio.Mesh` of a mesh and fields on it: every cell block, node sets as
    point data ``set:<name>``, face sets as facet blocks flagged ``face_set:<name>``."""
    return data_to_meshio(mesh_data(mesh, point_data=point_data, cell_data=cell_data), "vtu")


def from_meshio(m, *, name: str | None = None, return_data: bool = False):
    """The :class:`Mesh` of a :class:`meshio.Mesh` (markers as :func:`read_mesh` reads
    them); with ``return_data`` also its point data and cell data (over the domain's
    cells, blocks concatenated) as tensors."""
    data = meshio_to_data(m)
    mesh = mesh_from_data(data, name=name)
    return (mesh, *_data_tensors(data)) if return_data else mesh


def _data_tensors(data: MeshData) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    point_data = {k: _to_tensor(v) for k, v in data.point_data.items()}
    cell_data = {k: _to_tensor(np.concatenate(v)) for k, v in data.cell_data.items() if v}
    return point_data, cell_data


# --------------------------------------------------------------------------- files


def read_mesh(path: PathLike, *, return_data: bool = False, planar: bool = True):
    """Read a mesh, deck or case with its markers.

    Parameters
    ----------
    path : str or path-like
        A mesh file of the module's table, or an OpenFOAM case directory.
    return_data : bool, keyword-only
        Also return the point data and the cell data (over the cells, blocks
        concatenated), as tensors.
    planar : bool, keyword-only
        An OpenFOAM pseudo-2-D case (one cell thick, ``empty`` patches front and back)
        is read as the 2-D mesh of its front plane (default), or with ``False`` as the
        3-D slab.

    Returns
    -------
    Mesh or (Mesh, dict, dict)
        A :class:`TetMesh` for one block of linear tetrahedra, a :class:`Mesh` otherwise;
        named after the file's stem.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        For an unsupported extension, a file that cannot be parsed, cells of a kind that
        cannot be handled (named), an invalid mesh; the message names the file.
    """
    path = Path(path)
    mesh_format = format_of(path)
    if not path.exists():
        raise FileNotFoundError(f"path: mesh file {str(path)!r} does not exist")
    if mesh_format.directory:
        data = mesh_format.read(path, planar=planar)  # type: ignore[call-arg]
    else:
        data = mesh_format.read(path)
    name = (
        path.name if path.is_dir() else Path(path.stem).stem if path.suffix == ".gz" else path.stem
    )
    try:
        mesh = mesh_from_data(data, name=name)
    except ValueError as error:
        raise ValueError(f"path: {str(path)!r}: {error}") from error
    return (mesh, *_data_tensors(data)) if return_data else mesh


def write_mesh(
    path: PathLike,
    mesh: Mesh,
    *,
    point_data: Mapping[str, Tensor | np.ndarray] | None = None,
    cell_data: Mapping[str, Tensor | np.ndarray] | None = None,
) -> None:
    """Write a mesh, its markers and optional fields to a mesh file.

    Parameters
    ----------
    path : str or path-like
        Target file; the extension picks the format (the module's table; OpenFOAM cases
        and decks that must keep their other content are written by
        :func:`write_morphed`).
    mesh : Mesh
    point_data : mapping of str to array, shape (N,) or (N, k), optional
        Nodal fields, e.g. ``{"displacement": d}``.
    cell_data : mapping of str to array, shape (M,) or (M, k), optional
        Per-cell fields over the cells numbered across blocks.

    Raises
    ------
    ValueError
        For an unsupported extension, a format torchmorph does not write, fields of the
        wrong length, reserved names, or a field name the format cannot hold; nothing is
        written then.
    FileNotFoundError
        If the target's directory does not exist.
    """
    path = Path(path)
    mesh_format = format_of(path)
    if mesh_format.write is None:
        raise ValueError(
            f"path: torchmorph writes no new {mesh_format.name} files; write a morphed one "
            "with write_morphed(source, points, output)"
        )
    data = mesh_data(mesh, point_data=point_data, cell_data=cell_data)
    for kind, names in (("point_data", data.point_data), ("cell_data", data.cell_data)):
        for key in names:
            _check_field_name(key, mesh_format.name, f"{kind}[{key!r}]")
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"path: directory {str(directory)!r} does not exist")
    mesh_format.write(path, data)


def write_morphed(source: PathLike, points: Tensor | np.ndarray, output: PathLike) -> Path:
    """Write ``source`` (a mesh file, a CalculiX/Abaqus deck or an OpenFOAM case) again at
    ``output`` with new coordinates, everything else as it was: a deck's materials,
    steps and loads, a case's faces, owner, neighbour and boundary (byte-identical), a
    file's blocks, markers and fields.

    Parameters
    ----------
    source : str or path-like
    points : Tensor or array, shape (N, D)
        The new coordinates of :func:`read_mesh`'s points (for a pseudo-2-D OpenFOAM
        case read in its plane, the in-plane points: both layers move alike).
    output : str or path-like
        A file of the same format, or the new case directory (it must not exist or be
        empty; ``source`` itself rewrites it in place).

    Returns
    -------
    Path
        ``output``.
    """
    source, output = Path(source), Path(output)
    mesh_format = format_of(source, "source")
    if not source.exists():
        raise FileNotFoundError(f"source: {str(source)!r} does not exist")
    if not mesh_format.directory and format_of(output, "output") is not mesh_format:
        raise ValueError(
            f"output: {str(output)!r} is not a {mesh_format.name} file like the source; "
            "convert formats with write_mesh"
        )
    if isinstance(points, Tensor):
        points = points.detach().cpu().numpy()
    mesh_format.move(source, np.asarray(points, dtype=np.float64), output)
    return output


# --------------------------------------------------------------------------- names

# Characters each format cannot hold in a field name (beyond control characters, which
# no format holds).
_FORBIDDEN_IN_FIELD_NAMES: dict[str, str] = {"vtu": "\"'<>&", "vtk": "", "gmsh": '"'}


def _check_field_name(name: str, file_format: str, argument: str) -> None:
    """Raise ``ValueError`` if a point/cell data name cannot be stored in ``file_format``:
    control characters everywhere; ``" ' < > &`` in VTU (XML attributes), white space
    in legacy VTK, ``"`` in Gmsh."""
    forbidden = _FORBIDDEN_IN_FIELD_NAMES.get(file_format, "")
    bad = sorted(
        {
            c
            for c in name
            if not c.isprintable() or c in forbidden or (file_format == "vtk" and c.isspace())
        }
    )
    if bad:
        shown = ", ".join(repr(c) for c in bad)
        raise ValueError(
            f"{argument}: a {file_format} file cannot hold the character(s) {shown} in a field "
            "name; rename the field"
        )


# --------------------------------------------------------------------------- helpers


def _check_key(key: Any, argument: str) -> None:
    if not isinstance(key, str) or not key:
        raise ValueError(f"{argument}: names must be non-empty strings, got {key!r}")


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
