"""The formats read and written through meshio, with their markers kept: VTU/VTK/XDMF,
Gmsh MSH, medit, Nastran (Exodus II, CGNS and MED files have readers and writers of their
own: :mod:`torchmorph.mesh.formats.exodus`, :mod:`~torchmorph.mesh.formats.cgns`,
:mod:`~torchmorph.mesh.formats.med`; new Abaqus decks are written through meshio too).

Reading (:func:`read_meshio`) keeps every cell block of the top dimension, in order
(a kind torchmorph cannot handle is a ``ValueError`` naming it, never a silent drop),
and turns the file's markers into node and face sets:

- node sets from our ``set:<name>`` point data, meshio's ``point_sets`` and Gmsh
  physical groups of points and curves (in 3-D);
- face sets from the facet blocks (triangles and quads of a 3-D mesh, lines of a 2-D
  one) named by our ``face_set:<name>`` cell data, Gmsh physical groups, medit
  references (``ref<k>``) or Nastran property ids (``pid<k>``);
- lower-dimensional cells that the file puts in no marker are kept all the same: facets
  as the face set ``unmarked``, edges of a 3-D mesh and vertices as the node sets
  ``unmarked_lines`` and ``unmarked_points``. Nothing a file holds is dropped.

Writing (:func:`write_meshio`) stores node sets as ``set:<name>`` point data and face
sets as facet blocks after the domain's, flagged by ``face_set:<name>`` cell data (and,
in MSH files, as physical groups; in medit files as references and in Nastran files as
property ids, which keep numbers, not names: ``ref<k>``/``pid<k>`` keep their k). An
Abaqus deck gets every marker as an ``*NSET`` (face sets by their nodes) and no boundary
elements. :func:`move_meshio` writes a file again with new coordinates and
everything else as meshio read it, for a morph that must keep the file whole.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.cells import CELL_KINDS, FACET_KINDS
from torchmorph.mesh.formats._data import MeshData, in_plane

__all__ = [
    "FACE_SET_PREFIX",
    "MESHIO_FORMATS",
    "NODE_SET_PREFIX",
    "decode_set_name",
    "encode_set_name",
    "meshio_to_data",
    "move_meshio",
    "read_meshio",
    "write_meshio",
]

#: File extensions read and written through meshio, and meshio's format names.
MESHIO_FORMATS: dict[str, str] = {
    ".vtu": "vtu",
    ".vtk": "vtk",
    ".xdmf": "xdmf",
    ".xmf": "xdmf",
    ".msh": "gmsh",
    ".mesh": "medit",
    ".meshb": "medit",
    ".bdf": "nastran",
    ".fem": "nastran",
    ".nas": "nastran",
}

#: Prefixes of the point and cell data that carry node and face sets.
NODE_SET_PREFIX = "set:"
FACE_SET_PREFIX = "face_set:"
_BOOKKEEPING_PREFIXES = ("gmsh:", "medit:", FACE_SET_PREFIX)

_TOPOLOGY = {"vertex": 0, "line": 1, "line3": 1}
_TOPOLOGY |= {name: kind.dim for name, kind in CELL_KINDS.items()}

#: Gmsh's node order -> meshio's (VTK's) for the kinds meshio 5.3 reads from MSH files in
#: Gmsh's order (it reorders wedge15 and pyramid13, not these): a gmsh block ``g`` is
#: ``g[:, order]`` in VTK's order.
_GMSH_TO_VTK = {
    "wedge18": (0, 1, 2, 3, 4, 5, 6, 9, 7, 12, 14, 13, 8, 10, 11, 15, 17, 16),
    "pyramid14": (0, 1, 2, 3, 4, 5, 8, 10, 6, 7, 9, 11, 12, 13),
}


#: The kinds a format's meshio writer holds, where it does not hold them all.
_WRITABLE = {
    "medit": {"line", "triangle", "quad", "tetra", "wedge", "pyramid", "hexahedron"},
}
_LINEAR = {"line", "triangle", "quad", "tetra", "wedge", "pyramid", "hexahedron"}


def _writable(file_format: str, kinds: set[str]) -> set[str]:
    """The kinds of ``kinds`` that meshio's writer of ``file_format`` holds."""
    if file_format in _WRITABLE:
        return _WRITABLE[file_format]
    try:
        if file_format in ("vtu", "vtk"):
            from meshio._vtk_common import meshio_to_vtk_type as table
        elif file_format == "xdmf":
            from meshio.xdmf.common import meshio_to_xdmf_type as table
        elif file_format == "gmsh":
            from meshio.gmsh.common import _meshio_to_gmsh_type as table
        else:
            return kinds
    except ImportError:  # another meshio: let its writer decide
        return kinds
    return set(table)


def _complete_meshio_kinds() -> None:
    """meshio 5.3's table of topological dimensions lacks two kinds its own readers
    produce (its MSH 4.1 reader fails on them with ``KeyError``): add them."""
    import meshio

    table = meshio._mesh.topological_dimension
    for name in ("wedge15", "pyramid13"):
        table.setdefault(name, 3)


def encode_set_name(name: str) -> str:
    """The stored form of a marker name: ``%``, ``"``, ``'``, ``<``, ``>``, ``&``, white
    space and non-printable characters become ``%XX`` (their UTF-8 bytes); everything
    else is kept, so ordinary names are stored unchanged. :func:`decode_set_name`
    inverts it."""
    import urllib.parse

    def needs(character: str) -> bool:
        return character in "%\"'<>&" or character.isspace() or not character.isprintable()

    return "".join(
        urllib.parse.quote(character, safe="") if needs(character) else character
        for character in name
    )


def decode_set_name(stored: str) -> str:
    """Inverse of :func:`encode_set_name` (``%XX`` sequences decoded as UTF-8)."""
    import urllib.parse

    return urllib.parse.unquote(stored, errors="strict") if "%" in stored else stored


def _format_of(path: Path, file_format: str | None) -> str:
    if file_format is not None:
        return file_format
    return MESHIO_FORMATS[path.suffix.lower()]


def read_meshio(path: str | os.PathLike, file_format: str | None = None) -> MeshData:
    """Read a mesh file through meshio into :class:`MeshData` (see the module notes).

    Raises ``ValueError`` naming the file for what meshio cannot parse (meshio's own
    exits and errors are caught: no reader ends the process) and for cells of a kind
    torchmorph cannot handle.
    """
    import meshio

    path = Path(path)
    file_format = _format_of(path, file_format)
    reader = getattr(meshio, file_format.replace("-", "_")).read
    _complete_meshio_kinds()
    try:
        m = reader(str(path))
    except (Exception, SystemExit) as error:  # parsers raise many kinds, some exit
        raise ValueError(
            f"path: could not read {str(path)!r} as {file_format}: {type(error).__name__}: {error}"
        ) from error
    if file_format == "gmsh":
        for block in m.cells:
            if block.type in _GMSH_TO_VTK:
                block.data = np.asarray(block.data)[:, list(_GMSH_TO_VTK[block.type])]
    try:
        return meshio_to_data(m)
    except ValueError as error:
        raise ValueError(f"path: {str(path)!r}: {error}") from error


def _physical_names(m) -> dict[tuple[int, int], str]:
    """(dim, tag) -> name of the Gmsh physical groups (``field_data``: name -> [tag, dim])."""
    names = {}
    for name, value in (m.field_data or {}).items():
        value = np.asarray(value).ravel()
        if value.size == 2:
            names[(int(value[1]), int(value[0]))] = name
    return names


def _block_members(m, index: int, top: int) -> dict[str, np.ndarray]:
    """Names of the markers that cells of block ``index`` belong to -> the rows."""
    block = m.cells[index]
    count = len(block.data)
    members: dict[str, np.ndarray] = {}
    for key, per_block in m.cell_data.items():
        values = np.asarray(per_block[index])
        if key.startswith(FACE_SET_PREFIX):
            rows = np.flatnonzero(values.reshape(count, -1)[:, 0])
            if rows.size:
                members[decode_set_name(key[len(FACE_SET_PREFIX) :])] = rows
    names = _physical_names(m)
    group_names = set(names.values())
    for name, per_block in (m.cell_sets or {}).items():
        if name in group_names and index < len(per_block) and per_block[index] is not None:
            rows = np.asarray(per_block[index], dtype=np.int64)
            if rows.size:
                members.setdefault(name, rows)
    if not (m.cell_sets or {}) and "gmsh:physical" in m.cell_data:
        tags = np.asarray(m.cell_data["gmsh:physical"][index])
        for tag in np.unique(tags):
            if tag > 0:
                name = names.get((_TOPOLOGY[block.type], int(tag)), f"physical_{int(tag)}")
                members.setdefault(name, np.flatnonzero(tags == tag))
    if "medit:ref" in m.cell_data and _TOPOLOGY[block.type] == top - 1:
        refs = np.asarray(m.cell_data["medit:ref"][index])
        for ref in np.unique(refs):
            members.setdefault(f"ref{int(ref)}", np.flatnonzero(refs == ref))
    if "nastran:ref" in m.cell_data:  # property ids of boundary elements
        refs = np.asarray(m.cell_data["nastran:ref"][index])
        for ref in np.unique(refs):
            members.setdefault(f"pid{int(ref)}", np.flatnonzero(refs == ref))
    covered = np.zeros(count, dtype=bool)
    for rows in members.values():
        covered[rows] = True
    if not covered.all():  # lower-dimensional cells of no marker: kept under one name
        members[_UNMARKED.get(top - _TOPOLOGY[block.type], "unmarked_points")] = np.flatnonzero(
            ~covered
        )
    return members


#: Markers of the lower-dimensional cells that a file puts in no marker, by how many
#: dimensions below the domain they are: facets form a face set, the rest node sets.
_UNMARKED = {1: "unmarked", 2: "unmarked_lines"}


def meshio_to_data(m) -> MeshData:
    """:class:`MeshData` from a :class:`meshio.Mesh` (see the module notes)."""
    points = np.asarray(m.points)
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"points must have shape (N, 2) or (N, 3), got {points.shape}")
    unknown = sorted({b.type for b in m.cells if b.type not in _TOPOLOGY})
    dims = [_TOPOLOGY.get(b.type, -1) for b in m.cells]
    top = max(dims, default=-1)
    if unknown and (top < 2 or any(_unknown_is_domain(kind, top) for kind in unknown)):
        known = ", ".join(CELL_KINDS)
        raise ValueError(
            f"cells of kind {', '.join(unknown)} cannot be handled (supported: {known})"
        )
    if top < 2:
        raise ValueError("the file holds no cells of dimension 2 or 3 (a volume or planar mesh)")
    domain = [i for i, d in enumerate(dims) if d == top]
    cells = [(m.cells[i].type, np.asarray(m.cells[i].data, dtype=np.int64)) for i in domain]
    planar = None
    if top == 2 and points.shape[1] == 3:
        points, planar = in_plane(points, "points")
    node_sets: dict[str, np.ndarray] = {}
    point_data: dict[str, np.ndarray] = {}
    for key, value in m.point_data.items():
        value = np.asarray(value)
        if key.startswith(NODE_SET_PREFIX):
            flags = value.reshape(len(points), -1)[:, 0]
            node_sets[decode_set_name(key[len(NODE_SET_PREFIX) :])] = np.flatnonzero(flags)
        elif not key.startswith(_BOOKKEEPING_PREFIXES):
            point_data[key] = _native(value)
    for key, value in (getattr(m, "point_sets", None) or {}).items():
        node_sets.setdefault(key, np.unique(np.asarray(value, dtype=np.int64)))
    face_sets: dict[str, list[tuple[str, np.ndarray]]] = {}
    for index, block in enumerate(m.cells):
        dim = _TOPOLOGY.get(block.type, -1)
        if dim == top or dim < 0:
            continue
        data = np.asarray(block.data, dtype=np.int64)
        for name, rows in _block_members(m, index, top).items():
            if dim == top - 1 and block.type in FACET_KINDS:
                face_sets.setdefault(name, []).append((block.type, data[rows]))
            else:  # physical points or curves of a 3-D mesh: their nodes
                nodes = np.unique(data[rows].ravel())
                if name in node_sets:
                    nodes = np.union1d(node_sets[name], nodes)
                node_sets[name] = nodes
    for name in list(node_sets):
        if name in face_sets:  # the same marker as faces: the face set carries it
            node_sets.pop(name)
    cell_data = {
        key: [_native(np.asarray(per_block[i])) for i in domain]
        for key, per_block in m.cell_data.items()
        if not key.startswith(_BOOKKEEPING_PREFIXES)
    }
    return MeshData(
        points=points,
        cells=cells,
        node_sets={k: np.unique(v.astype(np.int64)) for k, v in node_sets.items()},
        face_sets=face_sets,
        point_data=point_data,
        cell_data=cell_data,
        planar_coordinate=planar,
    )


def _unknown_is_domain(kind: str, top: int) -> bool:
    """Whether a kind meshio names but torchmorph does not know sits at the top
    dimension (higher-order Lagrange cells, polyhedra): such cells would be lost."""
    import meshio

    dim = meshio._mesh.topological_dimension.get(kind)
    return dim is None or dim >= top


def _native(array: np.ndarray) -> np.ndarray:
    """An array in native byte order (legacy VTK data are big-endian)."""
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    return np.ascontiguousarray(array)


def data_to_meshio(data: MeshData, file_format: str):
    """A :class:`meshio.Mesh` of ``data`` for ``file_format`` (see the module notes)."""
    import meshio

    points = np.asarray(data.points)
    if points.shape[1] == 2:  # files hold three coordinates; a planar mesh's third is constant
        plane = 0.0 if data.planar_coordinate is None else data.planar_coordinate
        points = np.column_stack([points, np.full(len(points), plane)])
    cells = [(kind, np.asarray(nodes)) for kind, nodes in data.cells]
    domain_count = len(cells)
    owners: list[str | None] = [None] * domain_count
    for name, blocks in data.face_sets.items():
        for kind, nodes in blocks:
            cells.append((kind, np.asarray(nodes)))
            owners.append(name)
    point_data = {key: np.asarray(value) for key, value in data.point_data.items()}
    for name, nodes in data.node_sets.items():
        flags = np.zeros(len(points), dtype=np.uint8)
        flags[np.asarray(nodes, dtype=np.int64)] = 1
        point_data[NODE_SET_PREFIX + encode_set_name(name)] = flags
    cell_data: dict[str, list[np.ndarray]] = {}
    for key, per_block in data.cell_data.items():
        arrays = [np.asarray(a) for a in per_block]
        shape_tail = arrays[0].shape[1:] if arrays else ()
        cell_data[key] = arrays + [
            np.zeros((len(nodes), *shape_tail), dtype=arrays[0].dtype if arrays else float)
            for _, nodes in cells[domain_count:]
        ]
    names = list(data.face_sets)
    if names and file_format not in ("gmsh", "medit"):  # those hold them as tags
        for name in names:
            cell_data[FACE_SET_PREFIX + encode_set_name(name)] = [
                np.full(len(nodes), int(owner == name), dtype=np.uint8)
                for (_, nodes), owner in zip(cells, owners, strict=True)
            ]
    field_data: dict[str, Any] = {}
    if file_format == "gmsh":
        top = (
            3 if points.shape[1] == 3 and any(CELL_KINDS[k].dim == 3 for k, _ in data.cells) else 2
        )
        tags = {name: k + 1 for k, name in enumerate(names)}
        physical = [
            np.full(len(nodes), tags[owner] if owner else len(names) + 1, dtype=np.int32)
            for (_, nodes), owner in zip(cells, owners, strict=True)
        ]
        cell_data["gmsh:physical"] = physical
        cell_data["gmsh:geometrical"] = [p.copy() for p in physical]
        field_data = {name: np.array([tag, top - 1]) for name, tag in tags.items()}
        field_data["domain"] = np.array([len(names) + 1, top])
    if file_format == "medit":
        cell_data = {
            "medit:ref": [
                np.full(len(nodes), names.index(owner) + 1 if owner else 0, dtype=np.int32)
                for (_, nodes), owner in zip(cells, owners, strict=True)
            ]
        }
        point_data = {}
    point_sets: dict[str, np.ndarray] = {}
    if file_format == "nastran":  # property ids: ``pid<k>`` keeps k, other names the next
        cell_data["nastran:ref"] = _property_ids(data, cells, owners)
    if file_format == "abaqus":  # *NSETs: face sets by their nodes, no boundary elements
        point_sets = {
            name: np.unique(np.concatenate([np.asarray(n).ravel() for _, n in blocks]))
            for name, blocks in data.face_sets.items()
        }
        point_sets |= {name: np.asarray(nodes) for name, nodes in data.node_sets.items()}
        cells, point_data = cells[:domain_count], {}
        cell_data = {key: value[:domain_count] for key, value in cell_data.items()}
        cell_data = {k: v for k, v in cell_data.items() if not k.startswith(FACE_SET_PREFIX)}
    return meshio.Mesh(
        points,
        cells,
        point_data=point_data,
        cell_data=cell_data,
        field_data=field_data,
        point_sets=point_sets,
    )


def _property_ids(data: MeshData, cells: list, owners: list[str | None]) -> list[np.ndarray]:
    """Nastran property ids per block: the domain's own (cell data ``nastran:ref``) or 1;
    a face set named ``pid<k>`` gets k, any other name the next free id (Nastran holds
    numbers, not names)."""
    own = data.cell_data.get("nastran:ref")
    kept = {n: int(n[3:]) for n in data.face_sets if re.fullmatch(r"pid[1-9]\d*", n)}
    taken = set(kept.values()) | {1}
    if own is not None:
        taken |= {int(v) for block in own for v in np.unique(np.asarray(block))}
    ids: dict[str, int] = {}
    for name in data.face_sets:
        if name in kept:
            ids[name] = kept[name]
        else:
            ids[name] = max(taken) + 1
            taken.add(ids[name])
    result = []
    for index, ((_, nodes), owner) in enumerate(zip(cells, owners, strict=True)):
        if owner is not None:
            result.append(np.full(len(nodes), ids[owner], dtype=np.int64))
        elif own is not None:
            result.append(np.asarray(own[index], dtype=np.int64))
        else:
            result.append(np.ones(len(nodes), dtype=np.int64))
    return result


def write_meshio(path: str | os.PathLike, data: MeshData, file_format: str | None = None) -> None:
    """Write ``data`` to ``path`` through meshio, atomically (see the module notes)."""
    import meshio

    path = Path(path)
    file_format = _format_of(path, file_format)
    kinds = {kind for kind, _ in data.cells} | {
        kind for blocks in data.face_sets.values() for kind, _ in blocks
    }
    unwritable = sorted(kinds - _writable(file_format, kinds))
    if unwritable:
        raise ValueError(
            f"path: a {file_format} file cannot hold cells of kind {', '.join(unwritable)}; "
            "write .vtu or .msh"
        )
    if file_format == "xdmf" and len(kinds) > 1 and any(k not in _LINEAR for k in kinds):
        raise ValueError(
            "path: meshio reads no XDMF file back whose topology mixes kinds with quadratic "
            f"ones ({', '.join(sorted(kinds))}); write .vtu or .msh"
        )
    blocks = len(data.cells) + sum(len(b) for b in data.face_sets.values())
    if file_format == "gmsh" and data.cell_data and blocks > 1:
        raise ValueError(
            "path: meshio reads no MSH file back whose cell data spans several cell blocks "
            f"({', '.join(sorted(kinds))}); write .vtu, or leave out cell_data"
        )
    converted = data_to_meshio(data, file_format)
    if file_format == "xdmf":
        _write_xdmf(path, converted)
        return
    options: dict[str, Any] = {}
    if file_format == "gmsh":  # MSH 2.2: any mix of kinds without gmsh's entity table
        for block in converted.cells:
            if block.type in _GMSH_TO_VTK:
                block.data = block.data[:, list(np.argsort(_GMSH_TO_VTK[block.type]))]
        file_format, options = "gmsh22", {"binary": True}
    with atomic_output(path) as temporary:
        meshio.write(temporary, converted, file_format=file_format, **options)


def move_meshio(source: str | os.PathLike, points: np.ndarray, output: str | os.PathLike) -> None:
    """Write ``source`` again at ``output`` (same format) with new coordinates, every
    block, marker and field as meshio read them; ``points`` (N, D) in the rows of
    :func:`read_meshio`'s points (D = 2 for a planar mesh: the third coordinate kept)."""
    import meshio

    source, output = Path(source), Path(output)
    file_format = _format_of(source, None)
    _complete_meshio_kinds()
    try:
        m = getattr(meshio, file_format).read(str(source))
    except (Exception, SystemExit) as error:
        raise ValueError(f"source: could not read {str(source)!r}: {error}") from error
    points = np.asarray(points, dtype=np.float64)
    stored = np.asarray(m.points, dtype=np.float64)
    if points.shape[0] != stored.shape[0] or points.shape[1] > stored.shape[1]:
        raise ValueError(
            f"points must have shape ({stored.shape[0]}, {stored.shape[1]}) (or the in-plane "
            f"coordinates of a planar mesh), got {points.shape}"
        )
    if not np.isfinite(points).all():
        raise ValueError("points holds NaN or infinite values")
    moved = stored.copy()
    moved[:, : points.shape[1]] = points
    m.points = moved
    options: dict[str, Any] = {}
    if file_format == "gmsh":  # the source's MSH version, binary or ASCII
        with open(source, "rb") as handle:
            header = handle.read(64).split(b"$MeshFormat", 1)[-1].split()
        version, binary = (header + [b"4.1", b"0"])[:2], (header + [b"", b"0"])[1:2]
        file_format = "gmsh22" if version[0].startswith(b"2") else "gmsh"
        options = {"binary": binary[0] == b"1"}
    if output.suffix.lower() in (".xdmf", ".xmf"):
        raise ValueError("output: XDMF files are written with write_mesh (they need an .h5 file)")
    with atomic_output(output) as temporary:
        meshio.write(temporary, m, file_format=file_format, **options)


def _write_xdmf(path: Path, converted) -> None:
    """XDMF and its ``.h5`` file, each atomically, the ``.h5`` first (meshio names the
    heavy-data file after the ``.xdmf`` file, so both are written under their final
    names in a temporary directory beside the target, then moved into place)."""
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
