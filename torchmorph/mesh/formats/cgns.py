"""CGNS meshes (``.cgns``, CGNS/HDF5): one unstructured zone, its element sections and its
boundary conditions as markers, read, written and written back moved.

meshio reads only a tetrahedral ``Base/Zone1/GridElements`` section of a CGNS file; the
boundary conditions (``ZoneBC``/``BC_t``) and the boundary element sections that a
mesher (Pointwise, ANSA, ICEM, SU2, Fluent …) writes are lost. :func:`read_cgns` reads
them as torchmorph's markers:

* **Points**: ``GridCoordinates``' ``CoordinateX``/``Y``/``Z`` (R4 or R8). A base of cell
  dimension 2 with three coordinates is a planar mesh when z is constant (kept in
  ``planar_coordinate``), refused otherwise (a surface mesh).
* **Cells**: every ``Elements_t`` section whose elements are of the base's cell
  dimension (volume elements in 3-D, faces in 2-D), in file order; a ``MIXED`` section
  (with or without CGNS 4's ``ElementStartOffset``) is split into one block per kind
  in the order each kind first appears. Node orders become meshio's (VTK's): PENTA_15/18
  and HEXA_20/27 are permuted (:data:`~torchmorph.mesh.formats._cgns_nodes.CGNS_TO_VTK`),
  the other kinds are in the same order. ``NGON_n``/``NFACE_n`` (polyhedra) and the
  cubic and quartic kinds are refused by name.
* **Boundary conditions**: a ``BC_t`` whose ``GridLocation`` is ``Vertex`` (the default)
  is a node set of its ``PointRange``/``PointList`` (vertex ids). One whose location is
  ``FaceCenter``/``EdgeCenter`` (or the deprecated ``CellCenter`` of a BC, or that uses
  the ``ElementRange``/``ElementList`` of CGNS 2, as the Mid-Level Library reads them)
  refers to element ids of the boundary sections (faces in 3-D, edges in 2-D): it is a
  face set named after the BC. A ``GridLocation`` inside a ``BCDataSet_t`` (before
  CGNS 1.2) counts where the BC has none. Element ids that no section holds, or that are
  domain cells, are an error naming the BC.
* **Boundary sections**: elements of a lower dimension are no domain cells. Those that
  no BC refers to are a face set named after their section (SU2's own CGNS reader names
  its markers so), or after the section with ``_unreferenced`` where a BC took that
  name. Lower-dimensional elements below the facets (edges in 3-D, ``NODE``) referred to
  by a BC make a node set of their nodes.
* **Families**: a BC's ``FamilyName`` (and ``AdditionalFamilyName``) becomes a group of
  markers named after the family (where no marker has that name already), so that a
  file whose BCs have generic names can be addressed by family.
* **Fields**: ``FlowSolution_t`` arrays at ``Vertex`` become point data; those at
  ``CellCenter`` cell data (in the order of the domain's element ids, whatever the
  order of the blocks). Components ``<name>X``, ``<name>Y`` (and ``<name>Z``) of one
  size are joined into one vector field ``<name>``. An array not of the zone's number
  of vertices (cells) is an error naming it.
* **Names**: a BC that refers to facets and to lower elements (edges of a 3-D mesh) is
  a face set and, where the lower elements' nodes are other than the facets', the node
  set ``<BC>_nodes`` (with a warning: a mesh keeps only the face set of a name).

One zone only: a file of several zones (in one base or several) is refused, naming
them (merge the zones first); structured zones and the ADF format are refused too.
``DataConversion`` and ``Rind`` of the coordinates are not applied.

:func:`write_cgns` writes one base ``Base`` with one zone ``Zone1`` (the names meshio's
reader expects): the coordinates (R8), one section per domain block (the first named
``GridElements``), then one section per face set and kind, numbered after the domain's
cells, a ``ZoneBC`` (where there are markers) with a ``BC_t`` per face set (``PointRange`` over its sections' element ids,
``GridLocation`` ``FaceCenter``, or ``EdgeCenter`` in 2-D, as ``cg_boco_write`` of CGNS
3.4 writes an element range), a ``BC_t`` per node set (``GridLocation`` ``Vertex``,
``PointList``), groups as families (``Family_t``, ``FamilyName`` on their BCs), point
data in a ``FlowSolution`` at ``Vertex`` and cell data in ``FlowSolutionCells`` at
``CellCenter`` (a vector field as one array per component, ``nameX``/``Y``/``Z``;
integers as ``I4`` where they fit, ``I8`` otherwise, the rest ``R8``). The
file is stamped CGNS 3.4 and holds no ``MIXED`` sections, so the 3.x and 4.x libraries
read it alike. :func:`move_cgns` copies a file and replaces only ``GridCoordinates``'
arrays (same type and shape), every other node kept.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.formats._cgns_nodes import CGNS_KINDS, CGNS_TO_VTK, new_node
from torchmorph.mesh.formats._cgns_read import (
    _DIM,
    AXES,
    _boundary_conditions,
    _coordinates,
    _markers,
    _open,
    _sections,
    _solutions,
    _the_zone,
    malformed,
)
from torchmorph.mesh.formats._data import MeshData, in_plane
from torchmorph.mesh.formats._hdf5 import set_text_attribute
from torchmorph.mesh.formats._sets import checked_fields, checked_points, connectivity, node_rows

__all__ = ["move_cgns", "read_cgns", "write_cgns"]

_CODE_OF = {kind: code for code, (kind, _) in CGNS_KINDS.items()}
_VTK_TO_CGNS = {
    kind: tuple(int(i) for i in np.argsort(order)) for kind, order in CGNS_TO_VTK.items()
}


def read_cgns(path: str | os.PathLike) -> MeshData:
    """Read a CGNS/HDF5 file of one unstructured zone with its markers.

    Parameters
    ----------
    path : str or PathLike
        The ``.cgns`` file.

    Returns
    -------
    MeshData
        ``points`` (N, D); ``cells``: the domain's sections (VTK node order); ``face_sets``:
        the element-based BCs and the boundary sections no BC refers to; ``node_sets``:
        the vertex BCs; ``groups``: the BCs' families; ``point_data``/``cell_data`` from
        the flow solutions (see the module's notes).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        Naming the file and what is wrong: an ADF or non-HDF5 file, no zone or several,
        a structured zone, polyhedral (``NGON_n``/``NFACE_n``) or unsupported element
        types, node numbers out of range, a BC pointing at element ids that no section
        holds, or at domain cells, a surface mesh (2-D cells off one plane), a node
        missing or of the wrong size (naming it).
    """
    path = Path(path)
    source = str(path)
    with _open(path) as f, malformed(source):
        zone, cell_dim, phys_dim, num_points = _the_zone(f, source)
        points = _coordinates(zone, phys_dim, num_points, source)
        blocks = _sections(zone, num_points, source)
        conditions = _boundary_conditions(zone, source)
        num_cells = sum(b.ids.size for b in blocks if _DIM[b.kind] == cell_dim)
        point_data, flat_cell_data = _solutions(zone, num_points, num_cells, source)
    with malformed(source):
        higher = sorted({b.kind for b in blocks if _DIM[b.kind] > cell_dim})
        if higher:
            raise ValueError(
                f"path: {source!r}: elements of kind {', '.join(higher)} in a base of cell "
                f"dimension {cell_dim}"
            )
        domain = [b for b in blocks if _DIM[b.kind] == cell_dim]
        if not domain:
            raise ValueError(
                f"path: {source!r}: the zone holds no elements of dimension {cell_dim}"
            )
        planar = None
        if cell_dim == 2 and phys_dim == 3:
            points, planar = in_plane(points, f"path: {source!r}")
        node_sets, face_sets, groups = _markers(blocks, conditions, cell_dim, num_points, source)
        cell_data: dict[str, list[np.ndarray]] = {}
        # cell-centred values are in the order of the domain's element ids
        ordered = np.sort(np.concatenate([b.ids for b in domain]))
        for key, values in flat_cell_data.items():
            cell_data[key] = [values[np.searchsorted(ordered, b.ids)] for b in domain]
        return MeshData(
            points=np.ascontiguousarray(points),
            cells=[(b.kind, b.nodes) for b in domain],
            node_sets=node_sets,
            face_sets=face_sets,
            groups=groups,
            point_data=point_data,
            cell_data=cell_data,
            planar_coordinate=planar,
        )


# --------------------------------------------------------------------------- writing


def _check_name(name: object, argument: str, source: str) -> str:
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name:
        raise ValueError(
            f"{argument}: CGNS names must be non-empty strings without '/', got {name!r} "
            f"(writing {source!r})"
        )
    if len(name.encode("utf-8")) > 32:
        raise ValueError(
            f"{argument}: CGNS names hold at most 32 characters, {name!r} has {len(name)} "
            f"(writing {source!r}); rename the marker"
        )
    return name


def _unique(preferred: str, taken: set[str], fallback: str) -> str:
    name = preferred if len(preferred.encode("utf-8")) <= 32 else fallback
    stem, k = name, 2
    while name in taken:
        name, k = f"{stem[:28]}_{k}", k + 1
    taken.add(name)
    return name


def _index_kind(largest: int) -> str:
    return "I4" if largest < 2**31 else "I8"


def _section(zone, name: str, kind: str, nodes: np.ndarray, first: int) -> int:
    """Write one element section of ``kind``; returns the id after its last element."""
    nodes = np.asarray(nodes, dtype=np.int64)
    if kind in _VTK_TO_CGNS:
        nodes = nodes[:, list(_VTK_TO_CGNS[kind])]
    last = first + nodes.shape[0] - 1
    section = new_node(zone, name, "Elements_t", "I4", [_CODE_OF[kind], 0])
    new_node(section, "ElementRange", "IndexRange_t", _index_kind(last), [first, last])
    values = nodes.ravel() + 1
    kind_of_values = _index_kind(int(values.max()) if values.size else 0)
    new_node(section, "ElementConnectivity", "DataArray_t", kind_of_values, values)
    return last + 1


def _checked_blocks(blocks, dim: int, num_points: int, argument: str, source: str):
    checked = []
    for number, (kind, nodes) in enumerate(blocks):
        label_here = f"{argument}[{number}]"
        if kind not in _CODE_OF or _DIM[kind] != dim:
            raise ValueError(
                f"{label_here}: {kind!r} cannot stand here: {dim}-D kinds expected (writing "
                f"{source!r})"
            )
        expected = CGNS_KINDS[_CODE_OF[kind]][1]
        checked.append((kind, connectivity(nodes, kind, expected, num_points, label_here, source)))
    return checked


def _members(groups: dict[str, list[str]], name: str, seen: frozenset = frozenset()) -> list[str]:
    """The markers of a group, groups inside it expanded."""
    out: list[str] = []
    for member in groups.get(name, []):
        if member in groups and member not in seen:
            out += _members(groups, member, seen | {name})
        elif member not in groups:
            out.append(member)
    return out


def _fields(solution, fields: dict[str, np.ndarray], argument: str, source: str) -> None:
    """Write checked fields (:func:`checked_fields`): one array per column, a vector's
    ``<name>X``/``Y``/``Z`` (``<name>_<k>`` beyond three columns)."""
    for name, values in fields.items():
        columns = values.reshape(values.shape[0], -1)
        where = f"{argument}[{name!r}]"
        if columns.dtype.kind == "u" and columns.size and int(columns.max()) >= 2**63:
            raise ValueError(
                f"{where}: unsigned integers above 2**63 - 1 do not fit CGNS's I8 (writing "
                f"{source!r})"
            )
        if columns.dtype.kind == "b" or (
            columns.dtype.kind in "iu" and columns.dtype.itemsize < 4 + (columns.dtype.kind == "i")
        ):
            kind = "I4"  # bool, int8 to int32, uint8, uint16
        else:
            kind = "I8" if columns.dtype.kind in "iu" else "R8"
        for k in range(columns.shape[1]):
            suffix = (
                "" if columns.shape[1] == 1 else ("XYZ"[k] if columns.shape[1] <= 3 else f"_{k}")
            )
            field_name = _check_name(name + suffix, where, source)
            new_node(solution, field_name, "DataArray_t", kind, columns[:, k])


def write_cgns(path: str | os.PathLike, data: MeshData) -> None:
    """Write ``data`` as a CGNS/HDF5 file (see the module's notes for the layout).

    Parameters
    ----------
    path : str or PathLike
        The file to write (replaced atomically: a failing write leaves it as it was).
    data : MeshData
        Points (N, 2) or (N, 3), cells of one dimension (the mesh's), face sets of the
        dimension below, node sets, groups (written as families of the BCs), point and
        cell data.

    Raises
    ------
    ValueError
        Naming the entry: points not (N, 2) or (N, 3) or not finite, a cell kind CGNS
        cannot hold here, connectivity of the wrong shape or out of range, node set rows
        that are no integers in [0, N), point data not of N rows, cell data not an array
        of each block's length per block, unsigned integers above 2**63 - 1, a marker or
        field name CGNS cannot hold (more than 32 characters, ``/``), a group named
        ``Zone1`` (the zone's name).
    """
    import h5py

    source = str(path)
    points = checked_points(data.points, source)
    num_points, dim = points.shape
    cells = _checked_blocks(data.cells, dim, num_points, "data.cells", source)
    face_sets = {
        _check_name(name, "data.face_sets", source): _checked_blocks(
            blocks, dim - 1, num_points, f"data.face_sets[{name!r}]", source
        )
        for name, blocks in data.face_sets.items()
    }
    rows_of = {
        name: node_rows(nodes, f"data.node_sets[{name!r}]", num_points, source)
        for name, nodes in data.node_sets.items()
    }
    node_sets = {
        _check_name(name, "data.node_sets", source): rows
        for name, rows in rows_of.items()
        if name not in face_sets
    }
    sizes = [len(nodes) for _, nodes in cells]
    point_data = checked_fields(
        data.point_data, "data.point_data", [num_points], source, nodal=True
    )
    cell_data = checked_fields(data.cell_data, "data.cell_data", sizes, source)
    families: dict[str, list[str]] = {}
    for group in data.groups:
        if group == "Zone1":
            raise ValueError(
                f"data.groups: a group named 'Zone1' cannot be written: the zone has that name "
                f"and the groups become families beside it; rename the group (writing {source!r})"
            )
        for member in _members(data.groups, group):
            if member in face_sets or member in node_sets:
                families.setdefault(member, []).append(_check_name(group, "data.groups", source))
    phys = 3 if dim == 3 or data.planar_coordinate is not None else 2
    if phys == 3 and dim == 2 and data.planar_coordinate is not None:
        points = np.column_stack([points, np.full(num_points, float(data.planar_coordinate))])
    num_cells = sum(len(nodes) for _, nodes in cells)
    with atomic_output(path) as temporary, h5py.File(temporary, "w", track_order=True) as f:
        set_text_attribute(f, "name", "HDF5 MotherNode", 33)
        set_text_attribute(f, "label", "Root Node of HDF5 File", 33)
        set_text_attribute(f, "type", "MT", 3)
        f.create_dataset(" format", data=np.frombuffer(b"IEEE_LITTLE_32\0", dtype=np.int8))
        version = f"HDF5 Version {h5py.version.hdf5_version}".encode().ljust(33, b"\0")
        f.create_dataset(" hdf5version", data=np.frombuffer(version[:33], dtype=np.int8))
        new_node(f, "CGNSLibraryVersion", "CGNSLibraryVersion_t", "R4", [3.4])
        base = new_node(f, "Base", "CGNSBase_t", "I4", [dim, phys])
        for name in [*face_sets, *node_sets]:  # each marker its family, as meshers write
            families[name] = (
                [name] + families.get(name, []) if name != "Zone1" else families.get(name, [])
            )
        for family in dict.fromkeys(g for names in families.values() for g in names):
            new_node(
                new_node(base, family, "Family_t"), "FamilyBC", "FamilyBC_t", "C1", "UserDefined"
            )
        zone_sizes = np.array([[num_points], [num_cells], [0]])
        zone_kind = _index_kind(max(num_points, num_cells))
        zone = new_node(base, "Zone1", "Zone_t", zone_kind, zone_sizes)
        new_node(zone, "ZoneType", "ZoneType_t", "C1", "Unstructured")
        grid = new_node(zone, "GridCoordinates", "GridCoordinates_t")
        for axis, column in zip(AXES, points.T, strict=False):
            new_node(grid, axis, "DataArray_t", "R8", np.ascontiguousarray(column))
        taken = {"ZoneType", "GridCoordinates", "ZoneBC", "FlowSolution", "FlowSolutionCells"}
        next_id = 1
        for number, (kind, nodes) in enumerate(cells):
            name = _unique(
                "GridElements" if number == 0 else f"GridElements_{number + 1}", taken, ""
            )
            next_id = _section(zone, name, kind, nodes, next_id)
        ranges = {}
        for number, (name, blocks) in enumerate(face_sets.items()):
            first = next_id
            for kind, nodes in blocks:
                preferred = name if len(blocks) == 1 else f"{name}_{_CODE_OF[kind]}"
                next_id = _section(
                    zone, _unique(preferred, taken, f"FaceSet{number + 1}"), kind, nodes, next_id
                )
            ranges[name] = (first, next_id - 1)
        zone_bc = new_node(zone, "ZoneBC", "ZoneBC_t") if face_sets or node_sets else None
        location = "FaceCenter" if dim == 3 else "EdgeCenter"
        for name in [*face_sets, *node_sets]:
            names = families.get(name, [])
            bc = new_node(
                zone_bc, name, "BC_t", "C1", "FamilySpecified" if names else "UserDefined"
            )
            if name in face_sets:
                first, last = ranges[name]
                new_node(bc, "GridLocation", "GridLocation_t", "C1", location)
                if last >= first:
                    new_node(bc, "PointRange", "IndexRange_t", _index_kind(last), [[first], [last]])
                else:  # an empty face set
                    new_node(bc, "PointList", "IndexArray_t", "I4", np.zeros((0, 1)))
            else:
                new_node(bc, "GridLocation", "GridLocation_t", "C1", "Vertex")
                ids = node_sets[name][:, None] + 1
                new_node(bc, "PointList", "IndexArray_t", _index_kind(num_points), ids)
            for k, family in enumerate(names):
                if k == 0:
                    new_node(bc, "FamilyName", "FamilyName_t", "C1", family)
                else:
                    new_node(bc, f"AddFamilyName{k}", "AdditionalFamilyName_t", "C1", family)
        if point_data:
            solution = new_node(zone, "FlowSolution", "FlowSolution_t")
            new_node(solution, "GridLocation", "GridLocation_t", "C1", "Vertex")
            flat = {k: v[0] for k, v in point_data.items()}
            _fields(solution, flat, "data.point_data", source)
        if cell_data and cells:
            solution = new_node(zone, "FlowSolutionCells", "FlowSolution_t")
            new_node(solution, "GridLocation", "GridLocation_t", "C1", "CellCenter")
            flat = {k: np.concatenate(v) for k, v in cell_data.items()}
            _fields(solution, flat, "data.cell_data", source)


# --------------------------------------------------------------------------- moving


def move_cgns(source: str | os.PathLike, points, output: str | os.PathLike) -> None:
    """Write ``source`` again at ``output`` with new coordinates: the file is copied and
    ``GridCoordinates``' arrays are replaced (their type and shape kept), every other node
    as it was. ``points`` (N, D) in the rows of :func:`read_cgns`'s points (D = 2 for a
    planar mesh: a stored third coordinate is kept)."""
    import h5py

    source, output = Path(source), Path(output)
    with _open(source) as f, malformed(str(source)):
        zone, cell_dim, phys_dim, num_points = _the_zone(f, str(source))
        _coordinates(zone, phys_dim, num_points, str(source))  # there, of the zone's size
        grid_path = zone["GridCoordinates"].name
    points = np.asarray(points, dtype=np.float64)
    columns = cell_dim if cell_dim == 2 and phys_dim == 3 else phys_dim
    if points.shape != (num_points, columns):
        raise ValueError(f"points must have shape ({num_points}, {columns}), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points holds NaN or infinite values")
    with atomic_output(output) as temporary:
        shutil.copyfile(source, temporary)
        with h5py.File(temporary, "r+") as f:
            grid = f[grid_path]
            for axis, column in zip(AXES, points.T, strict=False):
                dataset = grid[axis][" data"]
                dataset[...] = column.reshape(dataset.shape).astype(dataset.dtype)
