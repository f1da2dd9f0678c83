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
  ``unmarked_lines``, ``unmarked_points``), as the other formats keep them. A group of
  nodes named like a group of faces is the face set's marker where it holds the faces'
  nodes, and the node set ``<group>_nodes`` (with a warning) where it holds others (as
  a mesh keeps only the face set of a name). A group of no entity (MED's empty
  group) is an empty node set if it is a group of nodes, an empty face set otherwise.
* **Fields** (``CHA``) on nodes, or on the domain's cells, of one step and no profile:
  point and cell data (a field of the wrong number of values is an error naming it).

One mesh of one computation step; structured grids are refused. :func:`write_med`
writes MED 4.1 (``PENTA18`` needs 4) as MEDCoupling writes it, a mesh named ``mesh``
(MEDCoupling 9.14 reads its mesh, groups and fields back): one block per kind
(blocks of one kind are merged, as MED holds one per type), the face sets' facets as
boundary elements (a facet in several face sets once, its family naming them all), node
sets, face sets and ``cell_set:`` cell data as groups (names of at most 80 bytes; empty
node sets and face sets as groups of no entity; a ``cell_set:`` of no cell is not written),
point and cell data as fields (an array per block, of the block's length). ``groups`` of markers are not written (MED has no group
of groups), nor ``pyramid14`` cells (MED has no such type). :func:`move_med` copies the
file and replaces only the coordinates (``COO``), everything else kept.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.cells import FACET_KINDS
from torchmorph.mesh.formats._data import MeshData, in_plane
from torchmorph.mesh.formats._med_tables import (
    _DIM,
    _NO_PROFILE,
    _NODES,
    _UNMARKED,
    CELL_SET_PREFIX,
    MED_KINDS,
    MED_TO_VTK,
)
from torchmorph.mesh.formats._med_write import write
from torchmorph.mesh.formats._sets import separate_node_sets

__all__ = ["CELL_SET_PREFIX", "MED_KINDS", "MED_TO_VTK", "move_med", "read_med", "write_med"]


# --------------------------------------------------------------------------- reading


def _where(node) -> str:
    return str(node.name).lstrip("/")


def _group_names(family, source: str) -> list[str]:
    groups = family.get("GRO")
    if groups is None or "NOM" not in groups:
        return []
    raw = np.asarray(groups["NOM"][()])
    if raw.size % 80:
        raise ValueError(
            f"path: {source!r}: {_where(groups)}/NOM holds {raw.size} bytes, not names of 80"
        )
    names = raw.reshape(-1, 80).astype(np.uint8)
    decoded = (row.tobytes().decode("utf-8", errors="replace") for row in names)
    return [name.rstrip("\0 ") for name in decoded if name.rstrip("\0 ")]


def _families(fas, part: str, source: str) -> dict[int, list[str]]:
    out: dict[int, list[str]] = {}
    if fas is None or part not in fas:
        return out
    for family in fas[part].values():
        if "NUM" in family.attrs:
            out[int(family.attrs["NUM"])] = _group_names(family, source)
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
    if "NOE" not in step or "COO" not in step["NOE"]:
        raise ValueError(f"path: {source!r}: {_where(step)} has no nodes (NOE/COO)")
    fas = (
        mesh["FAS"]
        if "FAS" in mesh
        else f["FAS"][name]
        if "FAS" in f and name in f["FAS"]
        else None
    )
    return name, mesh, step, fas


def _counted(group, name: str, columns: int, source: str) -> np.ndarray:
    """The rows of ``group[name]``, ``NBR`` rows of ``columns`` values stored by column."""
    if name not in group:
        raise ValueError(f"path: {source!r}: {_where(group)} has no {name}")
    dataset = group[name]
    if "NBR" not in dataset.attrs:
        raise ValueError(f"path: {source!r}: {_where(dataset)} has no NBR (its number of rows)")
    count = int(dataset.attrs["NBR"])
    values = np.asarray(dataset[()]).ravel()
    if count < 0 or values.size != count * columns:
        raise ValueError(
            f"path: {source!r}: {_where(dataset)} holds {values.size} values, not NBR = {count} "
            f"rows of {columns}"
        )
    return values.reshape((count, columns), order="F")


def _family_numbers(group, count: int, source: str) -> np.ndarray:
    if "FAM" not in group:
        return np.zeros(count, dtype=np.int64)
    numbers = np.asarray(group["FAM"][()]).ravel()
    if numbers.size != count or numbers.dtype.kind not in "iu":
        raise ValueError(
            f"path: {source!r}: {_where(group['FAM'])} holds {numbers.size} {numbers.dtype} "
            f"values, not a family number for each of the {count} entities"
        )
    return numbers.astype(np.int64)


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
        (polygons, polyhedra, ``TR7``), node numbers out of range, a surface mesh, a
        dataset missing or of the wrong size (naming it).
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
        try:
            return _read(f, source)
        except ValueError as error:
            if str(error).startswith("path: "):
                raise
            raise ValueError(f"path: {source!r}: malformed MED file ({error})") from error
        except (KeyError, IndexError, TypeError, AttributeError, OSError) as error:
            raise ValueError(
                f"path: {source!r}: malformed MED file ({type(error).__name__}: {error})"
            ) from error


def _read(f, source: str) -> MeshData:
    mesh_name, mesh, step, fas = _the_step(f, source)
    space = int(mesh.attrs.get("ESP", mesh.attrs.get("DIM", 3)))
    if space not in (1, 2, 3):
        raise ValueError(f"path: {source!r}: {_where(mesh)} has space dimension ESP = {space}")
    points = _counted(step["NOE"], "COO", space, source).astype(np.float64)
    num_points = points.shape[0]
    node_families = _family_numbers(step["NOE"], num_points, source)
    blocks = []
    for type_name, group in step["MAI"].items() if "MAI" in step else []:
        if type_name not in MED_KINDS:
            what = {"POG": "polygons", "POE": "polyhedra"}.get(type_name, "elements")
            raise ValueError(
                f"path: {source!r}: {what} of MED type {type_name} cannot be handled "
                f"(supported: {', '.join(MED_KINDS)})"
            )
        kind = MED_KINDS[type_name][0]
        nodes = _counted(group, "NOD", _NODES[type_name], source).astype(np.int64) - 1
        if nodes.size and (nodes.min() < 0 or nodes.max() >= num_points):
            raise ValueError(f"path: {source!r}: {type_name} node numbers outside 1..{num_points}")
        if kind in MED_TO_VTK:
            nodes = nodes[:, list(MED_TO_VTK[kind])]
        blocks.append((type_name, kind, nodes, _family_numbers(group, len(nodes), source)))
    counts = {type_name: len(nodes) for type_name, _, nodes, _ in blocks}
    point_fields, cell_fields = _fields(f, mesh_name, num_points, counts, source)
    node_groups = _families(fas, "NOEUD", source)
    element_groups = _families(fas, "ELEME", source)
    top = max((_DIM[kind] for _, kind, _, _ in blocks), default=-1)
    if top < 2:
        raise ValueError(f"path: {source!r}: the mesh holds no cells of dimension 2 or 3")
    planar = None
    if top == 2 and space == 3:
        points, planar = in_plane(points, f"path: {source!r}")
    elif space < top:
        raise ValueError(
            f"path: {source!r}: cells of dimension {top} in a space of dimension {space}"
        )
    node_sets: dict[str, list[np.ndarray]] = {}
    for number in np.unique(node_families):
        for group in node_groups.get(int(number), []) if number else []:
            node_sets.setdefault(group, []).append(np.flatnonzero(node_families == number))
    face_sets: dict[str, list[tuple[str, np.ndarray]]] = {}
    domain = [b for b in blocks if _DIM[b[1]] == top]
    cell_data: dict[str, list[np.ndarray]] = {}
    used = {0} | set(node_families.tolist())
    for type_name, kind, nodes, families in blocks:
        used |= set(families.tolist())
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
    # groups of no entity: MED's empty groups (of nodes: node sets; else face sets)
    taken = set(node_sets) | set(face_sets) | {k[len(CELL_SET_PREFIX) :] for k in cell_data}
    for table, target in ((node_groups, node_sets), (element_groups, face_sets)):
        for number, groups in table.items():
            for group in groups if number not in used else []:
                if group not in taken:
                    target.setdefault(group, [])  # type: ignore[arg-type]
    for key, values in cell_fields.items():
        if all(t in values for t, _, _, _ in domain):
            cell_data[key] = [values[t] for t, _, _, _ in domain]
    nodes_of = {
        k: np.unique(np.concatenate(v)) if v else np.zeros(0, dtype=np.int64)
        for k, v in node_sets.items()
    }
    return MeshData(
        points=np.ascontiguousarray(points),
        cells=[(kind, nodes) for _, kind, nodes, _ in domain],
        node_sets=separate_node_sets(nodes_of, face_sets, "the group of nodes", source),
        face_sets=face_sets,
        point_data=point_fields,
        cell_data=cell_data,
        planar_coordinate=planar,
    )


def _fields(f, mesh_name: str, num_points: int, counts: dict[str, int], source: str):
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
            raw = np.asarray(profile["CO"][()]).ravel()
            if support == "NOE":
                on, expected = "the nodes", num_points
            elif support.startswith("MAI."):
                on, expected = f"the {support[4:]} elements", counts.get(support[4:], 0)
            else:
                continue
            if components < 1 or raw.size != expected * components:
                raise ValueError(
                    f"path: {source!r}: field {name!r} holds {raw.size} values on {on} "
                    f"({_where(profile)}/CO), not {expected} rows of NCO = {components} "
                    "components"
                )
            array = raw.reshape((-1, components), order="F")
            array = array[:, 0] if components == 1 else array
            if support == "NOE":
                point_data[name] = array
            else:
                cell_data.setdefault(name, {})[support[4:]] = array
    return point_data, cell_data


def _text(value) -> str:
    return value.decode("utf-8", errors="replace") if isinstance(value, bytes) else str(value)


# --------------------------------------------------------------------------- writing


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
        or out of range, node set rows that are no integers in [0, N), point data not
        of N rows, cell data not an array of each block's length per block, a group
        name longer than 80 bytes.
    """
    write(path, data)


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
            space = int(mesh.attrs.get("ESP", mesh.attrs.get("DIM", 3)))
            stored = _counted(step["NOE"], "COO", space, str(source)).astype(np.float64)
            stored[:, : points.shape[1]] = points
            dataset[...] = stored.ravel(order="F").astype(dataset.dtype)
