"""Reading CGNS/HDF5 zones, sections and boundary conditions, for
:mod:`torchmorph.mesh.formats.cgns` (see its notes)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchmorph.mesh.cells import CELL_KINDS, FACET_KINDS
from torchmorph.mesh.formats._cgns_nodes import (
    CGNS_KINDS,
    CGNS_TO_VTK,
    ELEMENT_TYPE_NAMES,
    array,
    children,
    data,
    label,
    text,
)
from torchmorph.mesh.formats._sets import separate_node_sets

_DIM = {"vertex": 0, "line": 1, "line3": 1} | {name: kind.dim for name, kind in CELL_KINDS.items()}
_NODES_OF = {code: nodes for code, (_, nodes) in CGNS_KINDS.items()}
_ELEMENT_LOCATIONS = (
    "FaceCenter",
    "EdgeCenter",
    "CellCenter",
    "IFaceCenter",
    "JFaceCenter",
    "KFaceCenter",
)
AXES = ("CoordinateX", "CoordinateY", "CoordinateZ")


@dataclass
class _Block:
    section: str
    kind: str
    ids: np.ndarray  # element ids, as in the file
    nodes: np.ndarray  # (M, n) 0-based rows, VTK order


@dataclass
class _BC:
    name: str
    location: str
    ids: np.ndarray
    families: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- reading


@contextmanager
def malformed(source: str) -> Iterator[None]:
    """Errors of reading a malformed file (a missing node or attribute, data of the wrong
    shape) as a ``ValueError`` naming the file; those naming it already as they are."""
    try:
        yield
    except ValueError as error:
        if str(error).startswith("path: "):
            raise
        raise ValueError(f"path: {source!r}: malformed CGNS file ({error})") from error
    except (KeyError, IndexError, TypeError, AttributeError, OSError) as error:
        raise ValueError(
            f"path: {source!r}: malformed CGNS file ({type(error).__name__}: {error})"
        ) from error


def _open(path: Path):
    import h5py

    if not path.is_file():
        raise FileNotFoundError(f"path: mesh file {str(path)!r} does not exist")
    try:
        return h5py.File(path, "r")
    except OSError as error:
        with open(path, "rb") as handle:
            head = handle.read(64)
        if b"ADF Database" in head:
            raise ValueError(
                f"path: {str(path)!r} is a CGNS file in the ADF format; torchmorph reads "
                "CGNS/HDF5: convert it with the CGNS tools (adf2hdf, or cgnsconvert -h)"
            ) from error
        raise ValueError(f"path: {str(path)!r} is not a CGNS/HDF5 file ({error})") from error


def _the_zone(f, source: str):
    """The one zone of the file and its base's cell and physical dimensions."""
    zones = [
        (base_name, base, zone_name, zone)
        for base_name, base in children(f, "CGNSBase_t")
        for zone_name, zone in children(base, "Zone_t")
    ]
    if not zones:
        raise ValueError(f"path: {source!r} holds no zone (CGNSBase_t/Zone_t); not a CGNS mesh")
    if len(zones) > 1:
        names = ", ".join(f"{b}/{z}" for b, _, z, _ in zones[:4]) + (
            ", …" if len(zones) > 4 else ""
        )
        raise ValueError(
            f"path: {source!r} holds {len(zones)} zones ({names}); torchmorph reads CGNS files "
            "of one unstructured zone: merge the zones into one first"
        )
    base_name, base, zone_name, zone = zones[0]
    zone_types = [text(node) for _, node in children(zone, "ZoneType_t")]
    if zone_types and zone_types[0] != "Unstructured":
        raise ValueError(
            f"path: {source!r}: zone {base_name}/{zone_name} is {zone_types[0]}; torchmorph "
            "reads unstructured zones only"
        )
    dims = data(base)
    sizes = data(zone)
    if dims is None or dims.size < 2 or sizes is None or sizes.size != 3:
        raise ValueError(
            f"path: {source!r}: base {base_name!r} or zone {zone_name!r} lacks its dimensions "
            "(a structured zone, or a malformed file)"
        )
    cell_dim, phys_dim = int(dims.ravel()[0]), int(dims.ravel()[1])
    if cell_dim not in (2, 3) or phys_dim not in (2, 3) or phys_dim < cell_dim:
        raise ValueError(
            f"path: {source!r}: base {base_name!r} has cell dimension {cell_dim} and physical "
            f"dimension {phys_dim}; torchmorph reads volume (3, 3) and planar (2, 2 or 3) meshes"
        )
    return zone, cell_dim, phys_dim, int(sizes.ravel()[0])


def _coordinates(zone, phys_dim: int, num_points: int, source: str) -> np.ndarray:
    grid = zone.get("GridCoordinates")
    if grid is None:
        raise ValueError(f"path: {source!r}: the zone has no GridCoordinates")
    columns = []
    for axis in AXES[:phys_dim]:
        node = grid.get(axis)
        values = None if node is None else data(node)
        if values is None:
            raise ValueError(
                f"path: {source!r}: GridCoordinates has no {axis} (torchmorph reads Cartesian "
                "coordinates)"
            )
        if values.size != num_points:
            raise ValueError(
                f"path: {source!r}: {axis} holds {values.size} values for the zone's "
                f"{num_points} vertices"
            )
        columns.append(values.ravel().astype(np.float64))
    points = np.column_stack(columns)
    if not np.isfinite(points).all():
        raise ValueError(f"path: {source!r}: the coordinates hold NaN or infinite values")
    return points


def _mixed(section, name: str, connectivity: np.ndarray, count: int, source: str):
    """Type codes and first-node positions of a MIXED section's elements."""
    offsets_node = section.get("ElementStartOffset")
    if offsets_node is not None:
        offsets = array(offsets_node).ravel().astype(np.int64)
        if offsets.size != count + 1 or offsets[-1] != connectivity.size:
            raise ValueError(
                f"path: {source!r}: section {name!r}: ElementStartOffset does not match its "
                f"{count} elements"
            )
        if offsets[0] != 0 or (np.diff(offsets) <= 0).any():
            raise ValueError(
                f"path: {source!r}: section {name!r}: ElementStartOffset must start at 0 and "
                "increase from element to element"
            )
        types = connectivity[offsets[:-1]]
        lengths = np.diff(offsets) - 1
        bad = [int(t) for t in np.unique(types) if int(t) not in _NODES_OF]
        if not bad:
            expected = np.array([_NODES_OF[int(t)] for t in types.tolist()], dtype=np.int64)
            if not np.array_equal(lengths, expected):
                raise ValueError(
                    f"path: {source!r}: section {name!r}: element lengths do not match their types"
                )
        starts = offsets[:-1] + 1
    else:  # CGNS 3: type code, then the nodes, element after element
        values = connectivity.tolist()
        type_list, start_list, position = [], [], 0
        for _ in range(count):
            if position >= len(values):
                break
            code = values[position]
            type_list.append(code)
            start_list.append(position + 1)
            if code not in _NODES_OF:
                break
            position += _NODES_OF[code] + 1
        types, starts = np.array(type_list, dtype=np.int64), np.array(start_list, dtype=np.int64)
        bad = [int(t) for t in np.unique(types) if int(t) not in _NODES_OF]
        if not bad and (types.size != count or position != len(values)):
            raise ValueError(
                f"path: {source!r}: section {name!r}: MIXED connectivity does not hold "
                f"{count} elements"
            )
    if bad:
        raise ValueError(_unsupported(source, name, bad[0], "inside MIXED"))
    return types, starts


def _unsupported(source: str, name: str, code: int, where: str = "") -> str:
    type_name = ELEMENT_TYPE_NAMES.get(code, f"code {code}")
    if code in (22, 23):
        reason = "polyhedral sections not supported (torchmorph reads elements of fixed kinds)"
    else:
        reason = "not supported; supported: " + ", ".join(
            ELEMENT_TYPE_NAMES[c] for c in sorted(CGNS_KINDS)
        )
    where = f" {where}" if where else ""
    return f"path: {source!r}: section {name!r}: element type {type_name}{where}: {reason}"


def _sections(zone, num_points: int, source: str) -> list[_Block]:
    blocks: list[_Block] = []
    for name, section in children(zone, "Elements_t"):
        header, ranges = data(section), section.get("ElementRange")
        connectivity_node = section.get("ElementConnectivity")
        if header is None or ranges is None or connectivity_node is None:
            raise ValueError(
                f"path: {source!r}: section {name!r} lacks its type, ElementRange or "
                "ElementConnectivity"
            )
        bounds = array(ranges).ravel()
        if header.size < 1 or header.dtype.kind not in "iu":
            raise ValueError(
                f"path: {source!r}: section {name!r}: its data (element type, boundary count) "
                f"is {header.size} {header.dtype} values, not integers"
            )
        if bounds.size != 2 or bounds.dtype.kind not in "iu":
            raise ValueError(
                f"path: {source!r}: section {name!r}: ElementRange holds {bounds.size} "
                f"{bounds.dtype} values, not two integers (the first and last element id)"
            )
        code = int(header.ravel()[0])
        first, last = int(bounds[0]), int(bounds[1])
        count = last - first + 1
        if count < 0:
            raise ValueError(
                f"path: {source!r}: section {name!r}: ElementRange {first}..{last} runs backwards"
            )
        connectivity = array(connectivity_node).ravel().astype(np.int64)
        if code == 20:
            types, starts = _mixed(section, name, connectivity, count, source)
        elif code in CGNS_KINDS:
            nodes = _NODES_OF[code]
            if connectivity.size != count * nodes:
                raise ValueError(
                    f"path: {source!r}: section {name!r}: {connectivity.size} connectivity "
                    f"values for {count} {ELEMENT_TYPE_NAMES[code]} elements"
                )
            types = np.full(count, code, dtype=np.int64)
            starts = np.arange(count, dtype=np.int64) * nodes
        else:
            raise ValueError(_unsupported(source, name, code))
        ids = np.arange(first, last + 1, dtype=np.int64)
        for code_here in dict.fromkeys(types.tolist()):
            kind, nodes = CGNS_KINDS[code_here]
            rows = np.flatnonzero(types == code_here)
            connectivity_rows = connectivity[starts[rows, None] + np.arange(nodes)] - 1
            if connectivity_rows.size and (
                connectivity_rows.min() < 0 or connectivity_rows.max() >= num_points
            ):
                raise ValueError(
                    f"path: {source!r}: section {name!r}: node numbers outside 1..{num_points}"
                )
            if kind in CGNS_TO_VTK:
                connectivity_rows = connectivity_rows[:, list(CGNS_TO_VTK[kind])]
            blocks.append(_Block(name, kind, ids[rows], connectivity_rows))
    return blocks


def _boundary_conditions(zone, source: str) -> list[_BC]:
    conditions = []
    for _, zone_bc in children(zone, "ZoneBC_t"):
        for name, bc in children(zone_bc, "BC_t"):
            location, ids, by_element, families = None, None, False, []
            for child_name, child in children(bc):
                child_label = label(child)
                if child_label == "GridLocation_t":
                    location = text(child)
                elif child_name in ("PointRange", "ElementRange"):
                    values = array(child).ravel()
                    if values.size != 2 or values.dtype.kind not in "iu":
                        raise ValueError(
                            f"path: {source!r}: BC {name!r}: {child_name} of {values.size} "
                            f"{values.dtype} values, not two integer ids (a structured zone's "
                            "range?)"
                        )
                    ids = np.arange(int(values[0]), int(values[1]) + 1, dtype=np.int64)
                    by_element = child_name == "ElementRange"
                elif child_name in ("PointList", "ElementList"):
                    ids = array(child).ravel()
                    if ids.size and ids.dtype.kind not in "iu":
                        raise ValueError(
                            f"path: {source!r}: BC {name!r}: {child_name} holds {ids.dtype} "
                            "values, not integer ids"
                        )
                    ids = ids.astype(np.int64)
                    by_element = child_name == "ElementList"
                elif child_label in ("FamilyName_t", "AdditionalFamilyName_t"):
                    families.append(text(child))
            if location is None:  # before CGNS 1.2, GridLocation sat in BCDataSet_t
                for _, dataset in children(bc, "BCDataSet_t"):
                    for _, node in children(dataset, "GridLocation_t"):
                        location = text(node)
            if by_element:
                location = "FaceCenter"
            if ids is None:
                raise ValueError(f"path: {source!r}: BC {name!r} has no PointRange or PointList")
            location = location or "Vertex"
            if location != "Vertex" and location not in _ELEMENT_LOCATIONS:
                raise ValueError(
                    f"path: {source!r}: BC {name!r}: GridLocation {location!r} is not supported "
                    "(Vertex, FaceCenter, EdgeCenter or CellCenter)"
                )
            conditions.append(_BC(name, location, ids, [f for f in families if f]))
    return conditions


def _solutions(
    zone, num_points: int, num_cells: int, source: str
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The flow solutions' arrays at vertices and at cell centres (flat, in the order of
    the domain's element ids), a vector's components ``<name>X``/``Y``/``Z`` joined."""
    point_data: dict[str, np.ndarray] = {}
    cell_data: dict[str, np.ndarray] = {}
    for solution_name, solution in children(zone, "FlowSolution_t"):
        locations = [text(node) for _, node in children(solution, "GridLocation_t")]
        location = locations[0] if locations else "Vertex"
        target = point_data if location == "Vertex" else cell_data
        if location not in ("Vertex", "CellCenter"):
            continue
        expected = num_points if location == "Vertex" else num_cells
        for name, node in children(solution, "DataArray_t"):
            values = data(node)
            if values is None:
                continue
            if values.size != expected:
                what = "vertices" if location == "Vertex" else "cells"
                raise ValueError(
                    f"path: {source!r}: FlowSolution {solution_name!r}: {name} holds "
                    f"{values.size} values for the zone's {expected} {what} ({location})"
                )
            key = name if name not in target else f"{solution_name}/{name}"
            target[key] = np.ascontiguousarray(values.ravel())
    return _vectors(point_data), _vectors(cell_data)


def _vectors(fields: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fields with the components ``<name>X``, ``<name>Y`` (and ``<name>Z``) of one size
    joined into one (n, 2) or (n, 3) field ``<name>``, where no field has that name."""
    joined: dict[str, str] = {}
    for key in fields:
        stem = key[:-1]
        if key.endswith("X") and stem and stem not in fields:
            parts = [stem + axis for axis in "XYZ" if stem + axis in fields]
            if parts[:2] == [stem + "X", stem + "Y"] and len({fields[p].size for p in parts}) == 1:
                joined.update(dict.fromkeys(parts, stem))
    out: dict[str, np.ndarray] = {}
    for key, values in fields.items():
        vector = joined.get(key)
        if vector is None:
            out[key] = values
        elif vector not in out:
            out[vector] = np.column_stack(
                [fields[vector + a] for a in "XYZ" if vector + a in fields]
            )
    return out


def _markers(blocks: list[_Block], conditions: list[_BC], top: int, num_points: int, source):
    """Node sets, face sets and groups from the BCs and the unreferenced boundary sections."""
    all_ids = np.concatenate([b.ids for b in blocks])
    owner = np.concatenate([np.full(b.ids.size, k) for k, b in enumerate(blocks)])
    row = np.concatenate([np.arange(b.ids.size) for b in blocks])
    order = np.argsort(all_ids, kind="stable")
    sorted_ids = all_ids[order]
    if sorted_ids.size and (np.diff(sorted_ids) == 0).any():
        raise ValueError(f"path: {source!r}: element ids overlap between sections")
    referenced = np.zeros(all_ids.size, dtype=bool)
    node_sets: dict[str, np.ndarray] = {}
    face_sets: dict[str, list[tuple[str, np.ndarray]]] = {}
    families: dict[str, list[str]] = {}

    def add(name: str, hits: np.ndarray) -> None:
        facets: list[tuple[str, np.ndarray]] = []
        nodes: list[np.ndarray] = []
        for k in dict.fromkeys(owner[hits].tolist()):
            block = blocks[k]
            rows = row[hits[owner[hits] == k]]
            if _DIM[block.kind] == top - 1 and block.kind in FACET_KINDS:
                facets.append((block.kind, block.nodes[rows]))
            else:
                nodes.append(block.nodes[rows].ravel())
        if facets:
            face_sets[name] = facets
        if nodes:
            node_sets[name] = np.unique(np.concatenate(nodes))
            if facets:  # the rule of a node set named like a face set (see _sets)
                taken = {bc.name for bc in conditions} | set(node_sets) | set(face_sets)
                node_sets.update(
                    separate_node_sets(
                        {name: node_sets.pop(name)},
                        {name: facets},
                        "BC",
                        source,
                        taken=taken - {name},
                        stacklevel=5,
                    )
                )

    for bc in conditions:
        for family in bc.families:
            families.setdefault(family, []).append(bc.name)
        if bc.location == "Vertex":
            if bc.ids.size and (bc.ids.min() < 1 or bc.ids.max() > num_points):
                raise ValueError(
                    f"path: {source!r}: BC {bc.name!r} points at vertex ids outside 1..{num_points}"
                )
            node_sets[bc.name] = np.unique(bc.ids - 1)
            continue
        position = np.minimum(np.searchsorted(sorted_ids, bc.ids), sorted_ids.size - 1)
        found = sorted_ids[position] == bc.ids
        if not found.all():
            missing = bc.ids[~found]
            ranges = ", ".join(f"{b.section} {b.ids.min()}..{b.ids.max()}" for b in blocks)
            raise ValueError(
                f"path: {source!r}: BC {bc.name!r} points at element ids outside the element "
                f"sections' ranges ({missing[:5].tolist()}; the sections hold {ranges})"
            )
        hits = order[position]
        in_domain = [
            blocks[k].section for k in np.unique(owner[hits]) if _DIM[blocks[k].kind] == top
        ]
        if in_domain:
            raise ValueError(
                f"path: {source!r}: BC {bc.name!r} ({bc.location}) points at domain cells of "
                f"section {in_domain[0]!r}, not at boundary elements"
            )
        referenced[hits] = True
        add(bc.name, hits)
        if not hits.size:
            face_sets[bc.name] = []
    starts = np.concatenate([[0], np.cumsum([b.ids.size for b in blocks])])
    leftovers: dict[str, list[int]] = {}
    for k, block in enumerate(blocks):
        if _DIM[block.kind] < top:
            unused = np.flatnonzero(~referenced[starts[k] : starts[k + 1]]) + starts[k]
            if unused.size:
                leftovers.setdefault(block.section, []).extend(unused.tolist())
    for section, entries in leftovers.items():
        name = section if section not in node_sets and section not in face_sets else ""
        add(name or f"{section}_unreferenced", np.array(entries, dtype=np.int64))
    markers = set(node_sets) | set(face_sets)
    groups = {
        family: list(dict.fromkeys(members))
        for family, members in families.items()
        if family not in markers
    }
    return node_sets, face_sets, groups
