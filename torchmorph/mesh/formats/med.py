"""MED meshes (``.med``, Salome, Code_Aster): one unstructured mesh with its groups as
markers, read, written and written back moved.

A MED file (HDF5) holds a mesh's nodes (``NOE``: coordinates ``COO``, family numbers
``FAM``) and its elements by geometric type (``MAI/TE4``, ``MAI/TR3`` …: connectivity
``NOD``, family numbers ``FAM``), volume cells and boundary faces alike; families
(``FAS``: positive numbers for nodes, negative for elements) name the groups their
entities belong to. meshio reads the cells and the family numbers but not what they
mean, keeps boundary faces as unnamed blocks and orders the nodes as the file does.
:func:`read_med` reads:

* **Cells**: the element types of the mesh's top dimension, one block per type in the
  file's order, the others (faces, edges, points) are no domain cells. MED orders a
  tetrahedron's, pyramid's and hexahedron's corners the other way round from VTK (a
  MED cell of positive volume, by MEDCoupling's measure, is VTK's mirror image, as
  Gmsh's MED exchange permutes them too); a prism's too, and a HEXA27's face centres
  differ: each type is permuted to meshio's (VTK's) order (:data:`MED_TO_VTK`; the 2-D
  kinds and edges are in the same order). The permutations were derived from
  MEDCoupling's own cell models (its edges and faces of each type) and checked against
  its signed volumes. Polygons and polyhedra (``POG``/``POE``) and ``TR7`` are refused by name.
* **Groups of nodes** become node sets; **groups of boundary faces** (faces of a 3-D
  mesh, edges of a 2-D one) become face sets; groups of lower elements (edges of a 3-D
  mesh, ``PO1`` points) node sets of their nodes; **groups of cells** (a volume's
  regions) cell data ``cell_set:<group>`` (1 for a member cell, 0 otherwise), which
  :func:`write_med` writes back as groups. Boundary faces of no group are kept as the
  face set ``unmarked`` (edges and points of no group as the node sets
  ``unmarked_lines``, ``unmarked_points``), as the other formats keep them.
* **Fields** (``CHA``) on nodes, or on the domain's cells, of one step and no profile:
  point and cell data.

One mesh of one computation step; structured grids are refused. :func:`write_med`
writes MED 4.1 (``PENTA18`` needs 4) as MEDCoupling writes it, a mesh named ``mesh``
(MEDCoupling 9.14 reads its mesh, groups and fields back): one block per kind
(blocks of one kind are merged, as MED holds one per type), the face sets' facets as
boundary elements (a facet in several face sets once, its family naming them all), node
sets, face sets and ``cell_set:`` cell data as groups (names of at most 80 bytes),
point and cell data as fields. ``groups`` of markers are not written (MED has no group
of groups), nor ``pyramid14`` cells (MED has no such type). :func:`move_med` copies the
file and replaces only the coordinates (``COO``), everything else kept.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.cells import CELL_KINDS, FACET_KINDS
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats._hdf5 import set_text_attribute

__all__ = ["CELL_SET_PREFIX", "MED_KINDS", "MED_TO_VTK", "move_med", "read_med", "write_med"]

#: MED geometric types of the kinds torchmorph holds: type name -> (meshio kind, MED code).
MED_KINDS: dict[str, tuple[str, int]] = {
    "PO1": ("vertex", 1), "SE2": ("line", 102), "SE3": ("line3", 103),
    "TR3": ("triangle", 203), "QU4": ("quad", 204), "TR6": ("triangle6", 206),
    "QU8": ("quad8", 208), "QU9": ("quad9", 209), "TE4": ("tetra", 304),
    "PY5": ("pyramid", 305), "PE6": ("wedge", 306), "HE8": ("hexahedron", 308),
    "T10": ("tetra10", 310), "P13": ("pyramid13", 313), "P15": ("wedge15", 315),
    "P18": ("wedge18", 318), "H20": ("hexahedron20", 320), "H27": ("hexahedron27", 327),
}  # fmt: skip

#: meshio's (VTK's) node order -> MED's, where they differ: a VTK block ``v`` is
#: ``v[:, order]`` in MED's order (and a MED block ``m`` is ``m[:, argsort(order)]``).
VTK_TO_MED: dict[str, tuple[int, ...]] = {
    "tetra": (0, 2, 1, 3),
    "pyramid": (0, 3, 2, 1, 4),
    "wedge": (0, 2, 1, 3, 5, 4),
    "hexahedron": (0, 3, 2, 1, 4, 7, 6, 5),
    "tetra10": (0, 2, 1, 3, 6, 5, 4, 7, 9, 8),
    "pyramid13": (0, 3, 2, 1, 4, 8, 7, 6, 5, 9, 12, 11, 10),
    "wedge15": (0, 2, 1, 3, 5, 4, 8, 7, 6, 11, 10, 9, 12, 14, 13),
    "wedge18": (0, 2, 1, 3, 5, 4, 8, 7, 6, 11, 10, 9, 12, 14, 13, 17, 16, 15),
    "hexahedron20": (0, 3, 2, 1, 4, 7, 6, 5, 11, 10, 9, 8, 15, 14, 13, 12, 16, 19, 18, 17),
    "hexahedron27": (0, 3, 2, 1, 4, 7, 6, 5, 11, 10, 9, 8, 15, 14, 13, 12, 16, 19, 18, 17)
    + (24, 20, 23, 21, 22, 25, 26),
}
#: MED's node order -> meshio's (VTK's).
MED_TO_VTK: dict[str, tuple[int, ...]] = {
    kind: tuple(int(i) for i in np.argsort(order)) for kind, order in VTK_TO_MED.items()
}
#: Prefix of the cell data that carry groups of domain cells.
CELL_SET_PREFIX = "cell_set:"

_TYPE_OF = {kind: name for name, (kind, _) in MED_KINDS.items()}
_DIM = {"vertex": 0, "line": 1, "line3": 1} | {name: kind.dim for name, kind in CELL_KINDS.items()}
_NODES = {name: code % 100 for name, (_, code) in MED_KINDS.items()}
_NO_PROFILE = "MED_NO_PROFILE_INTERNAL"
_UNMARKED = {1: "unmarked", 2: "unmarked_lines"}
#: The bit of each type in MED 4.1's index of a field's types (MEDCoupling writes these).
_GEO_BIT = {"PO1": 0, "SE2": 1, "SE3": 2, "TR3": 4, "QU4": 5, "TR6": 6, "QU8": 8, "QU9": 9}
_GEO_BIT |= {"TE4": 10, "PY5": 11, "PE6": 12, "HE8": 13, "T10": 14, "P13": 16, "P15": 17}
_GEO_BIT |= {"P18": 18, "H20": 19, "H27": 20}
_STEP = "-0000000000000000001-0000000000000000001"


# --------------------------------------------------------------------------- reading


def _group_names(family) -> list[str]:
    groups = family.get("GRO")
    if groups is None or "NOM" not in groups:
        return []
    names = np.asarray(groups["NOM"][()]).reshape(-1, 80).astype(np.uint8)
    decoded = (row.tobytes().decode("utf-8", errors="replace") for row in names)
    return [name.rstrip("\0 ") for name in decoded if name.rstrip("\0 ")]


def _families(fas, part: str) -> dict[int, list[str]]:
    out: dict[int, list[str]] = {}
    if fas is None or part not in fas:
        return out
    for family in fas[part].values():
        if "NUM" in family.attrs:
            out[int(family.attrs["NUM"])] = _group_names(family)
    return out


def _the_step(f, source: str):
    if "ENS_MAA" not in f:
        raise ValueError(f"path: {source!r} is no MED file (no ENS_MAA)")
    meshes = list(f["ENS_MAA"])
    if len(meshes) != 1:
        raise ValueError(
            f"path: {source!r} holds {len(meshes)} meshes ({', '.join(meshes) or 'none'}); "
            "torchmorph reads MED files of one mesh"
        )
    name = meshes[0]
    mesh = f["ENS_MAA"][name]
    if int(mesh.attrs.get("TYP", 0)) != 0:
        raise ValueError(
            f"path: {source!r}: mesh {name!r} is structured; torchmorph reads unstructured ones"
        )
    if "NOE" in mesh:  # MED 2: no computation steps
        step = mesh
    else:
        steps = [k for k in mesh if hasattr(mesh[k], "keys")]
        if len(steps) != 1:
            raise ValueError(
                f"path: {source!r}: mesh {name!r} has {len(steps)} computation steps; torchmorph "
                "reads meshes of one"
            )
        step = mesh[steps[0]]
    fas = (
        mesh["FAS"]
        if "FAS" in mesh
        else f["FAS"][name]
        if "FAS" in f and name in f["FAS"]
        else None
    )
    return name, mesh, step, fas


def _counted(dataset, columns: int) -> np.ndarray:
    count = int(dataset.attrs["NBR"])
    return np.asarray(dataset[()]).reshape((count, columns), order="F")


def read_med(path: str | os.PathLike) -> MeshData:
    """Read a MED file of one unstructured mesh with its groups as markers.

    Parameters
    ----------
    path : str or PathLike
        The ``.med`` (or ``.rmed``/``.mmed``) file.

    Returns
    -------
    MeshData
        ``points`` (N, D); ``cells``: the top dimension's types (VTK node order);
        ``node_sets``, ``face_sets`` and ``cell_data['cell_set:<group>']`` from the
        groups; point and cell data from the fields (see the module's notes).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        Naming the file and what is wrong: not HDF5 or no MED file, several meshes or
        computation steps, a structured mesh, element types torchmorph cannot handle
        (polygons, polyhedra, ``TR7``), node numbers out of range, a surface mesh.
    """
    import h5py

    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: mesh file {source!r} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as error:
        raise ValueError(f"path: {source!r} is no MED file (not HDF5: {error})") from error
    with f:
        mesh_name, mesh, step, fas = _the_step(f, source)
        space = int(mesh.attrs.get("ESP", mesh.attrs.get("DIM", 3)))
        points = _counted(step["NOE"]["COO"], space).astype(np.float64)
        num_points = points.shape[0]
        node_families = (
            np.asarray(step["NOE"]["FAM"][()]) if "FAM" in step["NOE"] else np.zeros(num_points)
        )
        blocks = []
        for type_name, group in step["MAI"].items() if "MAI" in step else []:
            if type_name not in MED_KINDS:
                what = {"POG": "polygons", "POE": "polyhedra"}.get(type_name, "elements")
                raise ValueError(
                    f"path: {source!r}: {what} of MED type {type_name} cannot be handled "
                    f"(supported: {', '.join(MED_KINDS)})"
                )
            kind = MED_KINDS[type_name][0]
            nodes = _counted(group["NOD"], _NODES[type_name]).astype(np.int64) - 1
            if nodes.size and (nodes.min() < 0 or nodes.max() >= num_points):
                raise ValueError(
                    f"path: {source!r}: {type_name} node numbers outside 1..{num_points}"
                )
            if kind in MED_TO_VTK:
                nodes = nodes[:, list(MED_TO_VTK[kind])]
            families = np.asarray(group["FAM"][()]) if "FAM" in group else np.zeros(len(nodes))
            blocks.append((type_name, kind, nodes, families.astype(np.int64)))
        point_fields, cell_fields = _fields(f, mesh_name, num_points)
        node_groups, element_groups = _families(fas, "NOEUD"), _families(fas, "ELEME")
    top = max((_DIM[kind] for _, kind, _, _ in blocks), default=-1)
    if top < 2:
        raise ValueError(f"path: {source!r}: the mesh holds no cells of dimension 2 or 3")
    planar = None
    if top == 2 and space == 3:
        z = points[:, 2]
        if z.size and np.ptp(z) > 1e-12 * max(1.0, float(np.abs(points).max())):
            raise ValueError(
                f"path: {source!r}: planar cells with points off one plane z = const: a "
                "surface mesh in 3-D is not a volume or planar mesh"
            )
        planar, points = (float(z[0]) if z.size else 0.0), points[:, :2]
    elif top == 3 and space != 3:
        raise ValueError(f"path: {source!r}: volume cells in a space of dimension {space}")
    node_sets: dict[str, list[np.ndarray]] = {}
    for number in np.unique(node_families):
        for group in node_groups.get(int(number), []) if number else []:
            node_sets.setdefault(group, []).append(np.flatnonzero(node_families == number))
    face_sets: dict[str, list[tuple[str, np.ndarray]]] = {}
    domain = [b for b in blocks if _DIM[b[1]] == top]
    cell_data: dict[str, list[np.ndarray]] = {}
    for type_name, kind, nodes, families in blocks:
        groups_of = {n: g for n, g in element_groups.items() if n and g}
        named = np.isin(families, list(groups_of))
        if _DIM[kind] < top and not named.all():  # kept, as every format keeps them
            families = np.where(named, families, 0)
            groups_of[0] = [_UNMARKED.get(top - _DIM[kind], "unmarked_points")]
        for number in np.unique(families):
            rows = np.flatnonzero(families == number)
            for group in groups_of.get(int(number), []):
                if _DIM[kind] == top:
                    key = CELL_SET_PREFIX + group
                    flags = cell_data.setdefault(
                        key, [np.zeros(len(b[2]), np.uint8) for b in domain]
                    )
                    flags[[b[0] for b in domain].index(type_name)][rows] = 1
                elif _DIM[kind] == top - 1 and kind in FACET_KINDS:
                    face_sets.setdefault(group, []).append((kind, nodes[rows]))
                else:
                    node_sets.setdefault(group, []).append(nodes[rows].ravel())
    for key, values in cell_fields.items():
        if all(t in values for t, _, _, _ in domain):
            cell_data[key] = [values[t] for t, _, _, _ in domain]
    return MeshData(
        points=np.ascontiguousarray(points),
        cells=[(kind, nodes) for _, kind, nodes, _ in domain],
        node_sets={k: np.unique(np.concatenate(v)) for k, v in node_sets.items()},
        face_sets=face_sets,
        point_data=point_fields,
        cell_data=cell_data,
        planar_coordinate=planar,
    )


def _fields(f, mesh_name: str, num_points: int):
    """Fields of one step and no profile on the nodes, or per type on the cells."""
    point_data: dict[str, np.ndarray] = {}
    cell_data: dict[str, dict[str, np.ndarray]] = {}
    for name, field in f["CHA"].items() if "CHA" in f else []:
        if _text(field.attrs.get("MAI", b"")) != mesh_name or len(field) != 1:
            continue
        components = int(field.attrs.get("NCO", 1))
        step = next(iter(field.values()))
        for support, values in step.items():
            profile = values.get(_NO_PROFILE)
            if profile is None or "CO" not in profile or int(profile.attrs.get("NGA", 1)) != 1:
                continue
            array = np.asarray(profile["CO"][()]).reshape((-1, components), order="F")
            array = array[:, 0] if components == 1 else array
            if support == "NOE" and len(array) == num_points:
                point_data[name] = array
            elif support.startswith("MAI."):
                cell_data.setdefault(name, {})[support[4:]] = array
    return point_data, cell_data


def _text(value) -> str:
    return value.decode("utf-8", errors="replace") if isinstance(value, bytes) else str(value)


# --------------------------------------------------------------------------- writing


def _name_row(name: str, argument: str, source: str) -> np.ndarray:
    encoded = name.encode("utf-8") if isinstance(name, str) else b""
    if not encoded or len(encoded) > 80:
        raise ValueError(
            f"{argument}: MED group names are non-empty strings of at most 80 bytes, got "
            f"{name!r} (writing {source!r})"
        )
    return np.frombuffer(encoded.ljust(80, b" "), dtype=np.int8)


def _write_families(parent, families: dict[tuple[str, ...], int], source: str) -> None:
    for groups, number in families.items():
        family = parent.create_group(f"FAM_{number}", track_order=True)
        family.attrs.create("NUM", np.int64(number))
        if groups:
            gro = family.create_group("GRO")
            gro.attrs.create("NBR", np.int64(len(groups)))
            rows = np.stack([_name_row(g, "group", source) for g in groups])
            names = gro.create_dataset("NOM", shape=(len(groups),), dtype=np.dtype(("i1", (80,))))
            names[...] = rows


def _numbered(memberships: list[frozenset], sign: int, start: int) -> tuple[np.ndarray, dict]:
    """Family numbers for entities by the set of groups each belongs to."""
    numbers: dict[frozenset, int] = {}
    out = np.zeros(len(memberships), dtype=np.int64)
    for k, groups in enumerate(memberships):
        if groups:
            if groups not in numbers:
                numbers[groups] = sign * (start + len(numbers))
            out[k] = numbers[groups]
    return out, {tuple(sorted(g)): n for g, n in numbers.items()}


def _dataset(parent, name: str, values, count: int):
    dataset = parent.create_dataset(name, data=values)
    dataset.attrs.create("CGT", np.int64(1))
    dataset.attrs.create("NBR", np.int64(count))
    return dataset


def write_med(path: str | os.PathLike, data: MeshData) -> None:
    """Write ``data`` as a MED file (see the module's notes for what is written how).

    Parameters
    ----------
    path : str or PathLike
        The file to write (replaced atomically: a failing write leaves it as it was).
    data : MeshData
        Points (N, 2) or (N, 3), cells, face sets (facets of the dimension below), node
        sets, ``cell_set:<group>`` cell data, point and cell data.

    Raises
    ------
    ValueError
        Naming the entry: points not (N, 2) or (N, 3) or not finite, a kind MED cannot
        hold (``pyramid14``) or of the wrong dimension, connectivity of the wrong shape
        or out of range, a group name longer than 80 bytes.
    """
    import h5py

    source = str(path)
    points = np.asarray(data.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3) or not np.isfinite(points).all():
        raise ValueError(
            f"data.points: must be finite, of shape (N, 2) or (N, 3), got {points.shape} "
            f"(writing {source!r})"
        )
    num_points, dim = points.shape
    if dim == 2 and data.planar_coordinate is not None:
        points = np.column_stack([points, np.full(num_points, float(data.planar_coordinate))])
    cells: dict[str, list[np.ndarray]] = {}
    for number, (kind, nodes) in enumerate(data.cells):
        cells.setdefault(kind, []).append(
            _checked(kind, nodes, dim, num_points, f"data.cells[{number}]", source)
        )
    cell_groups = {
        k[len(CELL_SET_PREFIX) :]: v
        for k, v in data.cell_data.items()
        if k.startswith(CELL_SET_PREFIX)
    }
    cell_members: dict[str, list[frozenset]] = {kind: [] for kind in cells}
    for number, (kind, nodes) in enumerate(data.cells):
        flags = [np.asarray(v[number]).ravel() for v in cell_groups.values()]
        cell_members[kind] += (
            [
                frozenset(g for g, f in zip(cell_groups, row, strict=True) if f)
                for row in zip(*flags, strict=True)
            ]
            if flags
            else [frozenset()] * len(nodes)
        )
    facets: dict[str, dict[tuple, list]] = {}
    for name, blocks in data.face_sets.items():
        for number, (kind, nodes) in enumerate(blocks):
            rows = _checked(
                kind, nodes, dim - 1, num_points, f"data.face_sets[{name!r}][{number}]", source
            )
            table = facets.setdefault(kind, {})
            for row in rows.tolist():
                table.setdefault(tuple(sorted(row)), [row, set()])[1].add(name)
    node_members: list[set[str]] = [set() for _ in range(num_points)]
    for name, nodes in data.node_sets.items():
        if name not in data.face_sets:
            for node in np.unique(np.asarray(nodes, dtype=np.int64)).tolist():
                node_members[node].add(name)
    node_families, node_table = _numbered([frozenset(m) for m in node_members], 1, 1)
    element_memberships = {kind: cell_members[kind] for kind in cells}
    element_memberships |= {
        kind: [frozenset(v[1]) for v in table.values()] for kind, table in facets.items()
    }
    all_members = [m for members in element_memberships.values() for m in members]
    element_numbers, element_table = _numbered(all_members, -1, 1)
    with atomic_output(path) as temporary, h5py.File(temporary, "w", track_order=True) as f:
        info = f.create_group("INFOS_GENERALES")
        for key, value in (("MAJ", 4), ("MIN", 1), ("REL", 0)):
            info.attrs.create(key, np.int64(value))
        mesh = f.create_group("ENS_MAA", track_order=True).create_group("mesh", track_order=True)
        space = points.shape[1]
        for key, value in (("DIM", max(_DIM[k] for k in cells) if cells else dim), ("ESP", space)):
            mesh.attrs.create(key, np.int64(value))
        for key, value in (("NXI", -1), ("NXT", -1), ("REP", 0), ("SRT", 0), ("TYP", 0)):
            mesh.attrs.create(key, np.int64(value))
        set_text_attribute(mesh, "DES", "written by torchmorph")
        set_text_attribute(mesh, "NOM", "".join(f"{a:<16}" for a in "XYZ"[:space]))
        set_text_attribute(mesh, "UNI", " " * 16 * space)
        set_text_attribute(mesh, "UNT", "")
        step = mesh.create_group(_STEP, track_order=True)
        for key, value in (("CGT", 1), ("NDT", -1), ("NOR", -1), ("NXI", -1), ("NXT", -1)):
            step.attrs.create(key, np.int64(value))
        for key, value in (("PVI", -1), ("PVT", -1)):
            step.attrs.create(key, np.int64(value))
        step.attrs.create("PDT", np.float64(0.0))
        noe = step.create_group("NOE", track_order=True)
        for key in ("CGS", "CGT"):
            noe.attrs.create(key, np.int64(1))
        set_text_attribute(noe, "PFL", _NO_PROFILE)
        _dataset(noe, "COO", points.ravel(order="F"), num_points)
        _dataset(noe, "FAM", node_families, num_points)
        mai = step.create_group("MAI", track_order=True)
        mai.attrs.create("CGT", np.int64(1))
        offset = 0
        written: list[tuple[str, np.ndarray]] = []
        for kind in [*cells, *facets]:
            if kind in cells:
                rows = np.concatenate(cells[kind])
            else:
                rows = np.array([v[0] for v in facets[kind].values()], dtype=np.int64)
            med = rows[:, list(VTK_TO_MED[kind])] if kind in VTK_TO_MED else rows
            group = mai.create_group(_TYPE_OF[kind], track_order=True)
            for key in ("CGS", "CGT"):
                group.attrs.create(key, np.int64(1))
            group.attrs.create("GEO", np.int64(MED_KINDS[_TYPE_OF[kind]][1]))
            set_text_attribute(group, "PFL", _NO_PROFILE)
            _dataset(group, "NOD", (med + 1).ravel(order="F"), len(rows))
            _dataset(group, "FAM", element_numbers[offset : offset + len(rows)], len(rows))
            offset += len(rows)
            written.append((kind, rows))
        families = f.create_group("FAS", track_order=True).create_group("mesh", track_order=True)
        families.create_group("FAMILLE_ZERO").attrs.create("NUM", np.int64(0))
        if node_table:
            _write_families(families.create_group("NOEUD", track_order=True), node_table, source)
        if element_table:
            _write_families(families.create_group("ELEME", track_order=True), element_table, source)
        _write_fields(f, data, list(cells), num_points)


def _checked(kind, nodes, dim: int, num_points: int, argument: str, source: str) -> np.ndarray:
    if kind not in _TYPE_OF or _DIM[kind] != dim:
        reason = "MED has no such type" if kind not in _TYPE_OF else f"{dim}-D kinds expected here"
        raise ValueError(
            f"{argument}: a MED file cannot hold {kind!r} cells: {reason} (writing {source!r})"
        )
    array = np.asarray(nodes)
    expected = _NODES[_TYPE_OF[kind]]
    if array.ndim != 2 or array.shape[1] != expected:
        raise ValueError(
            f"{argument}: {kind!r} connectivity must have shape (M, {expected}), got {array.shape} "
            f"(writing {source!r})"
        )
    if array.size and (array.min() < 0 or array.max() >= num_points):
        raise ValueError(
            f"{argument}: node numbers must be in 0..{num_points - 1} (writing {source!r})"
        )
    return array.astype(np.int64)


def _write_fields(f, data: MeshData, kinds: list[str], num_points: int) -> None:
    cell_fields = {k: v for k, v in data.cell_data.items() if not k.startswith(CELL_SET_PREFIX)}
    if not data.point_data and not cell_fields:
        return
    fields = f.create_group("CHA", track_order=True)
    entries = [(name, "NOE", np.asarray(values)) for name, values in data.point_data.items()]
    for name, per_block in cell_fields.items():
        if len(per_block) == len(data.cells):
            for kind in kinds:
                parts = [
                    np.asarray(v)
                    for (k, _), v in zip(data.cells, per_block, strict=True)
                    if k == kind
                ]
                entries.append((name, "MAI." + _TYPE_OF[kind], np.concatenate(parts)))
    supports: dict[str, set[str]] = {}
    for name, support, _ in entries:
        supports.setdefault(name, set()).add(support)
    for name, support, values in entries:
        if "NOE" in supports[name] and len(supports[name]) > 1:
            raise ValueError(f"data[{name!r}]: a point field and a cell field of one name")
        if not 0 < len(name.encode("utf-8")) <= 64:
            raise ValueError(
                f"data[{name!r}]: MED field names hold 1 to 64 bytes; rename the field"
            )
        columns = values.reshape(values.shape[0], -1).astype(np.float64)
        if name not in fields:
            field = fields.create_group(name, track_order=True)
            set_text_attribute(field, "MAI", "mesh")
            field.attrs.create("TYP", np.int64(6))  # MED_FLOAT64
            field.attrs.create("NCO", np.int64(columns.shape[1]))
            set_text_attribute(
                field, "NOM", "".join(f"{f'C{k}':<16}" for k in range(columns.shape[1]))
            )
            set_text_attribute(field, "UNI", " " * 16 * columns.shape[1])
            set_text_attribute(field, "UNT", "")
            step = field.create_group("0000000000000000000100000000000000000001", track_order=True)
            for key, value in (("NDT", 1), ("NOR", 1), ("RDT", -1), ("ROR", -1)):
                step.attrs.create(key, np.int64(value))
            step.attrs.create("PDT", np.float64(0.0))
            # MED 4.1's index of a field's supports: entity kinds (cells 1, nodes 8) and
            # geometric types (bits of MED's type list), on the field and on its step
            on_nodes = supports[name] == {"NOE"}
            mask = 1 if on_nodes else sum(1 << _GEO_BIT[t[4:]] for t in supports[name])
            for node in (field, step):
                _bitfield(node, "LEN", 8 if on_nodes else 1)
                _bitfield(node, "LGN" if on_nodes else "LGC", mask)
            field.attrs.create("LAA", np.int64(1))
            field.attrs.create("LNA" if on_nodes else "LCA", np.int64(1))
        step = next(iter(fields[name].values()))
        group = step.create_group(support, track_order=True)
        set_text_attribute(group, "GAU", "")
        set_text_attribute(group, "PFL", _NO_PROFILE)
        profile = group.create_group(_NO_PROFILE)
        profile.attrs.create("NBR", np.int64(columns.shape[0]))
        profile.attrs.create("NGA", np.int64(1))
        set_text_attribute(profile, "GAU", "")
        profile.create_dataset("CO", data=columns.ravel(order="F"))


def _bitfield(node, key: str, value: int) -> None:
    """A 32-bit bitfield attribute (HDF5's B32), as the MED library writes its masks."""
    import h5py

    bits = h5py.h5t.STD_B32LE
    attribute = h5py.h5a.create(node.id, key.encode(), bits, h5py.h5s.create(h5py.h5s.SCALAR))
    attribute.write(np.array(value, dtype="<u4"), mtype=bits)


# --------------------------------------------------------------------------- moving


def move_med(source: str | os.PathLike, points, output: str | os.PathLike) -> None:
    """Write ``source`` again at ``output`` with new coordinates: the file is copied and the
    mesh's ``COO`` dataset replaced (its type kept), everything else as it was.
    ``points`` (N, D) in the rows of :func:`read_med`'s points (D = 2 for a planar mesh
    stored with three coordinates: the third is kept)."""
    import h5py

    source, output = Path(source), Path(output)
    data = read_med(source)
    points = np.asarray(points, dtype=np.float64)
    if points.shape != data.points.shape:
        raise ValueError(f"points must have shape {data.points.shape}, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points holds NaN or infinite values")
    with atomic_output(output) as temporary:
        shutil.copyfile(source, temporary)
        with h5py.File(temporary, "r+") as f:
            _, mesh, step, _ = _the_step(f, str(source))
            dataset = step["NOE"]["COO"]
            stored = _counted(dataset, int(mesh.attrs.get("ESP", points.shape[1])))
            stored = stored.astype(np.float64)
            stored[:, : points.shape[1]] = points
            dataset[...] = stored.ravel(order="F").astype(dataset.dtype)
