"""Exodus II files (``.e``, ``.exo``: Cubit/Trelis, SEACAS, MOOSE, Sierra) read and written
with their element blocks, node sets and side sets, through the netCDF4 package.

An Exodus II file is a netCDF file (the SEACAS manual, "Exodus: A Finite Element Data
Model", appendix "Implementation of EXODUS II with netCDF"). :func:`read_exodus` returns
a :class:`~torchmorph.mesh.formats.MeshData`:

* ``points``: ``coordx``/``coordy``/``coordz`` (or the older ``coord``), rows in the
  file's node order (internal node numbers 1..N are rows 0..N-1; a ``node_num_map``'s
  user ids are not rows, and the maps stay in the file for :func:`move_exodus`). A 2-D
  file (``num_dim`` 2) gives points (N, 2); a 3-D file of 2-D elements in one plane
  z = const is a planar mesh (points (N, 2), ``planar_coordinate`` z).
* ``cells``: every element block of the top dimension (``connect<k>`` and its
  ``elem_type``), in file order, as meshio's kinds with meshio's (VTK's) node order; the
  element types accepted and the node orders that differ are listed in
  :mod:`torchmorph.mesh.formats._exodus_tables`. Blocks without elements are skipped.
* ``face_sets``: every side set (``elem_ss<k>``, ``side_ss<k>``; named by ``ss_names``,
  ``sideset_<id>`` where unnamed, ``id`` from ``ss_prop1``) as facet blocks
  (``triangle``/``quad``/``triangle6``/``quad8``/``quad9`` in 3-D, ``line``/``line3`` in
  2-D) grouped by kind in the order each kind first appears, facets of one kind in the
  side set's order, each facet's nodes as the Exodus manual lists the side (outward for
  a cell of Exodus's orientation). An element block one dimension below the top (a
  SHELL or TRI block of a 3-D mesh, a BAR block of a 2-D one) whose every element is a
  side of a cell becomes the face set named after the block (``block_<id>`` where
  unnamed); a block that is not, or of a lower dimension still, is a ``ValueError``
  naming it: nothing is dropped.
* ``node_sets``: every node set (``node_ns<k>``, ``ns_names``, ``ns_prop1``;
  ``nodeset_<id>`` where unnamed), sorted unique rows. A node set named like a side set
  is that side set's nodes in files that write both (MOOSE, Cubit): where its nodes are
  not the side set's, it is renamed ``nodeset_<id>`` with a warning, so that both survive
  in a :class:`~torchmorph.mesh.Mesh`.
* ``point_data`` and ``cell_data``: the nodal and element variables at the last time
  step, as float64; components named ``<base>_x``, ``_y`` [, ``_z``] or ``<base>_1`` …
  ``_k`` one after another form one field ``<base>`` (N, k). Element variables are read
  for the domain's blocks (NaN in a block that does not have the variable). Global,
  node set and side set variables, attributes, distribution factors, QA and info records
  are not read, and are kept by :func:`move_exodus`.

:func:`write_exodus` writes such a file (netCDF 64-bit offset, float64, 32-bit
integers; the dimensions, variables and attributes of the Exodus library's own files).
Face sets become side sets: each facet is the side of the cell it belongs to (a facet
between two cells, as in an internal side set, that of the cell for which its corners
turn outward), and must be all of that side, of its kind (a hexahedron20's side is a
``quad8``); read back, it lists its nodes as the manual does,
which starts a hexahedron's side 4 and a wedge's side 3 at another corner than
:data:`torchmorph.mesh.cells.CELL_KINDS` (the same facet, turning the same way). Node
sets become node sets, point and cell data nodal and element variables at one time step
0.0 (vectors as ``_x``/``_y``/``_z`` components, wider fields as ``_1`` … ``_k``); groups
are not written (Exodus has none). :func:`move_exodus` writes a file again with only its
coordinates changed.
"""

from __future__ import annotations

import os
import re
import shutil
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.formats._data import MeshData, in_plane
from torchmorph.mesh.formats._exodus_tables import (
    SIDES,
    TO_VTK,
    Block,
    SideIndex,
    element_type,
    facet_kind,
)
from torchmorph.mesh.formats._exodus_write import layout, write
from torchmorph.mesh.formats._netcdf3 import shortfall

__all__ = ["INSTALL_HINT", "move_exodus", "read_exodus", "write_exodus"]

#: How to install what Exodus files need.
INSTALL_HINT = "pip install 'torchmorph[exodus]' (or: pip install netCDF4)"


def _netcdf4() -> Any:
    try:
        import netCDF4
    except ImportError as error:
        raise ImportError(
            f"Exodus II files (.e, .exo) are read and written with the netCDF4 package: "
            f"{INSTALL_HINT}"
        ) from error
    return netCDF4


def read_exodus(path: str | os.PathLike) -> MeshData:
    """Read an Exodus II file with its element blocks, node sets and side sets.

    Parameters
    ----------
    path : str or PathLike
        The ``.e``/``.exo`` file.

    Returns
    -------
    MeshData
        See the module's documentation for what is read and how.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ImportError
        Without the netCDF4 package (the message says how to install it).
    ValueError
        Naming the file and what is wrong: not a netCDF file or a truncated one, no
        coordinates or cells, an element type that is not supported (named, with the
        supported ones), a block that is no volume or planar domain nor its facets, node
        numbers out of range or not integers, a side set's element out of range or side
        number not of its element's kind, two node or side sets of one name, a set or
        variable missing or of the wrong length, a non-planar 2-D mesh in 3-D coordinates.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: Exodus file {str(path)!r} does not exist")
    netcdf4 = _netcdf4()
    source = str(path)
    try:
        dataset = netcdf4.Dataset(source, "r")
    except OSError as error:
        raise ValueError(
            f"path: {source!r} is not a netCDF file, as Exodus II files are ({error})"
        ) from error
    with dataset:
        short = shortfall(path)
        if short:
            raise ValueError(f"path: {source!r} is truncated: {short}")
        dataset.set_auto_mask(False)
        try:
            return _read(dataset)
        except ValueError as error:
            raise ValueError(f"path: {source!r}: {error}") from error
        except (RuntimeError, OSError) as error:  # the netCDF library's errors
            raise ValueError(
                f"path: {source!r}: the netCDF library cannot read it ({error}): a damaged "
                "or truncated file"
            ) from error


def _read(nc: Any) -> MeshData:
    num_dim, num_nodes = _size(nc, "num_dim"), _size(nc, "num_nodes")
    if num_dim not in (2, 3):
        raise ValueError(f"num_dim is {num_dim}: torchmorph reads 2-D and 3-D meshes")
    if num_nodes == 0:
        raise ValueError("the file holds no nodes")
    points = _coordinates(nc, num_dim, num_nodes)
    blocks = _blocks(nc, num_nodes)
    top = max((block.type.dim for block in blocks), default=-1)
    if top < 2:
        raise ValueError("the file holds no element block of dimension 2 or 3")
    if top > num_dim:
        raise ValueError(f"3-D elements in a file of num_dim {num_dim}")
    for block in blocks:
        if block.type.dim < top - 1 or block.type.dim == 0:
            raise ValueError(
                f"{block.label}: {block.type.dim}-D elements in a {top}-D mesh cannot be "
                "represented (a torchmorph mesh holds cells of one dimension and, as face "
                "sets, their facets); remove the block"
            )
        if block.type.dim == top and num_dim == 2 and block.type.sides in ("shell", "trishell"):
            raise ValueError(f"{block.label}: structural shells in a 2-D file (num_dim 2)")
    planar = None
    if top == 2 and num_dim == 3:
        points, planar = in_plane(points, "2-D elements")
    domain = [block for block in blocks if block.type.dim == top]
    cells = [(block.type.kind, _to_vtk(block.type.kind, block.nodes)) for block in domain]
    index = SideIndex(domain, len(points))
    face_sets = _side_sets(nc, blocks, {block.number for block in domain})
    for block in blocks:
        if block.type.dim == top - 1:
            name = block.name or f"block_{block.id}"
            if name in face_sets:
                raise ValueError(f"{block.label} and a side set are both named {name!r}")
            try:
                index.find(block.type.kind, block.nodes, block.label)
            except ValueError as error:
                raise ValueError(
                    f"{error}; a block of {top - 1}-D elements in a {top}-D mesh is read "
                    "only as facets of its cells (a face set)"
                ) from None
            face_sets[name] = [(block.type.kind, block.nodes.copy())]
    node_sets = _node_sets(nc, num_nodes, face_sets)
    point_data, cell_data = _results(nc, num_nodes, domain)
    return MeshData(
        points=points,
        cells=cells,
        node_sets=node_sets,
        face_sets=face_sets,
        point_data=point_data,
        cell_data=cell_data,
        planar_coordinate=planar,
    )


# --------------------------------------------------------------------------- reading


def _size(nc: Any, name: str) -> int:
    return len(nc.dimensions[name]) if name in nc.dimensions else 0


def _whole(values: Any, name: str) -> np.ndarray:
    """The values of the variable ``name`` as int64, where they are whole numbers."""
    array = np.asarray(values)
    if array.dtype.kind not in "iu":
        if array.dtype.kind != "f":
            raise ValueError(f"{name} holds {array.dtype} values, not integers")
        bad = np.flatnonzero(~np.isfinite(array) | (array != np.round(array)))
        if bad.size:
            value = array.reshape(-1)[bad[0]]
            raise ValueError(f"{name} holds {value}, not an integer")
    return array.astype(np.int64)


def _integers(nc: Any, name: str) -> np.ndarray:
    return _whole(nc.variables[name][:], name).reshape(-1)


def _ids(nc: Any, name: str, count: int) -> list[int]:
    if name not in nc.variables:
        return list(range(1, count + 1))
    ids = _integers(nc, name)
    if ids.size != count:
        raise ValueError(f"{name} holds {ids.size} ids for {count} entries")
    return ids.tolist()


def _names(nc: Any, name: str, count: int) -> list[str]:
    """The names of a ``(count, len_name)`` character variable ("" where blank)."""
    if name not in nc.variables or count == 0:
        return [""] * count
    variable = nc.variables[name]
    if len(variable.shape) != 2 or variable.shape[0] != count:
        raise ValueError(f"{name} has shape {variable.shape}, not ({count}, len_name)")
    variable.set_auto_chartostring(False)
    raw = np.asarray(variable[:])
    names = []
    for row in raw:
        text = b"".join(c if isinstance(c, bytes) else str(c).encode() for c in row.tolist())
        text = text.split(b"\0", 1)[0]
        try:
            names.append(text.decode("utf-8").strip())
        except UnicodeDecodeError:
            names.append(text.decode("latin-1").strip())
    return names


def _coordinates(nc: Any, num_dim: int, num_nodes: int) -> np.ndarray:
    names = ("coordx", "coordy", "coordz")[:num_dim]
    variables = nc.variables
    if all(name in variables for name in names):
        columns = [np.asarray(variables[name][:], dtype=np.float64).reshape(-1) for name in names]
        if any(column.size != num_nodes for column in columns):
            raise ValueError(f"coordx/coordy/coordz do not hold {num_nodes} values each")
        points = np.stack(columns, 1)
    elif "coord" in variables:
        values = np.asarray(variables["coord"][:], dtype=np.float64)
        if values.shape != (num_dim, num_nodes):
            raise ValueError(f"coord has shape {values.shape}, not ({num_dim}, {num_nodes})")
        points = np.ascontiguousarray(values.T)
    else:
        raise ValueError("no coordinates (coordx, coordy[, coordz] or coord)")
    bad = np.flatnonzero(~np.isfinite(points).all(1))
    if bad.size:
        raise ValueError(f"node {bad[0] + 1} has non-finite coordinates {points[bad[0]].tolist()}")
    return points


def _blocks(nc: Any, num_nodes: int) -> list[Block]:
    count = _size(nc, "num_el_blk")
    ids, names = _ids(nc, "eb_prop1", count), _names(nc, "eb_names", count)
    blocks, start = [], 0
    for number in range(1, count + 1):
        size = _size(nc, f"num_el_in_blk{number}")
        label = f"element block {ids[number - 1]}" + (
            f" ({names[number - 1]!r})" if names[number - 1] else ""
        )
        variable = nc.variables.get(f"connect{number}")
        if size == 0:
            if variable is not None and variable.size:
                raise ValueError(f"{label}: connect{number} but no num_el_in_blk{number}")
            continue
        if variable is None or "elem_type" not in variable.ncattrs():
            raise ValueError(f"{label}: {size} elements but no connect{number} with an elem_type")
        name = variable.getncattr("elem_type")
        name = name.decode() if isinstance(name, bytes) else str(name)
        nodes = _whole(variable[:], f"connect{number}")
        if nodes.ndim != 2 or nodes.shape[0] != size:
            raise ValueError(f"{label}: connect{number} has shape {nodes.shape}, not ({size}, n)")
        try:
            kind = element_type(name, nodes.shape[1])
        except ValueError as error:
            raise ValueError(f"{label}: {error}") from None
        label = label[:-1] + f", {name})" if names[number - 1] else f"{label} ({name})"
        bad = np.flatnonzero(((nodes < 1) | (nodes > num_nodes)).any(1))
        if bad.size:
            raise ValueError(
                f"{label}: element {start + bad[0] + 1} refers to nodes "
                f"{nodes[bad[0]].tolist()}, outside 1..{num_nodes}"
            )
        blocks.append(
            Block(number, ids[number - 1], names[number - 1], label, kind, nodes - 1, start)
        )
        start += size
    if start != _size(nc, "num_elem"):
        raise ValueError(
            f"the element blocks hold {start} elements, num_elem is {_size(nc, 'num_elem')}"
        )
    return blocks


def _to_vtk(kind: str, nodes: np.ndarray) -> np.ndarray:
    order = TO_VTK.get(kind)
    return np.ascontiguousarray(nodes[:, list(order)] if order else nodes)


def _set_label(what: str, ident: int, name: str) -> str:
    return f"{what} {ident}" + (f" ({name!r})" if name else "")


def _side_sets(
    nc: Any, blocks: list[Block], domain: set[int]
) -> dict[str, list[tuple[str, np.ndarray]]]:
    count = _size(nc, "num_side_sets")
    ids, names = _ids(nc, "ss_prop1", count), _names(nc, "ss_names", count)
    num_elem = _size(nc, "num_elem")
    starts = np.array([block.start for block in blocks], dtype=np.int64)
    result: dict[str, list[tuple[str, np.ndarray]]] = {}
    for number in range(1, count + 1):
        ident, name = ids[number - 1], names[number - 1]
        label = _set_label("side set", ident, name)
        key = name or f"sideset_{ident}"
        if key in result:
            raise ValueError(f"{label}: a second side set named {key!r}")
        size = _size(nc, f"num_side_ss{number}")
        members = (f"elem_ss{number}", f"side_ss{number}")
        missing = [member for member in members if member not in nc.variables]
        if size == 0 and len(missing) == 2:
            result[key] = []
            continue
        if missing:
            raise ValueError(f"{label}: {size} sides but no {' or '.join(missing)}")
        elements = _integers(nc, members[0]) - 1
        sides = _integers(nc, members[1])
        if elements.shape != (size,) or sides.shape != (size,):
            raise ValueError(
                f"{label}: {members[0]} and {members[1]} hold {elements.size} and "
                f"{sides.size} values, num_side_ss{number} is {size}"
            )
        bad = np.flatnonzero((elements < 0) | (elements >= num_elem))
        if bad.size:
            raise ValueError(
                f"{label}: entry {bad[0]} names element {elements[bad[0]] + 1}, outside the "
                f"file's elements 1..{num_elem}"
            )
        which = np.searchsorted(starts, elements, side="right") - 1
        result[key] = _facets(label, blocks, domain, which, elements, sides)
    return result


def _facets(
    label: str,
    blocks: list[Block],
    domain: set[int],
    which: np.ndarray,
    elements: np.ndarray,
    sides: np.ndarray,
) -> list[tuple[str, np.ndarray]]:
    """The facets of side-set entries (block positions, global elements, sides), grouped
    by kind in the order each kind first appears, entries of one kind in order."""
    found: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    first: dict[str, int] = {}
    for position in np.unique(which).tolist():
        block = blocks[position]
        in_block = np.flatnonzero(which == position)
        if block.number not in domain or block.type.sides is None:
            element = f"element {elements[in_block[0]] + 1} ({block.label})"
            raise ValueError(f"{label}: {element} is not a cell of the mesh's domain")
        table = SIDES[block.type.sides]
        valid = [k for k, s in enumerate(table, 1) if not s.face]
        bad = in_block[~np.isin(sides[in_block], valid)]
        if bad.size:
            raise ValueError(
                f"{label}: entry {bad[0]}: side {sides[bad[0]]} of element "
                f"{elements[bad[0]] + 1} ({block.label}) is not one of its sides "
                f"{valid[0]}..{valid[-1]}"
                + (" (1 and 2 are the shell's faces)" if valid[0] > 1 else "")
            )
        for side in np.unique(sides[in_block]).tolist():
            entries = in_block[sides[in_block] == side]
            kind, local = facet_kind(block.type.kind, table[side - 1])
            rows = elements[entries] - block.start
            found.setdefault(kind, []).append((entries, block.nodes[rows][:, list(local)]))
            first[kind] = min(first.get(kind, len(elements)), int(entries[0]))
    result = []
    for kind in sorted(found, key=first.__getitem__):
        entries = np.concatenate([e for e, _ in found[kind]])
        nodes = np.concatenate([n for _, n in found[kind]])
        result.append((kind, np.ascontiguousarray(nodes[np.argsort(entries, kind="stable")])))
    return result


def _node_sets(
    nc: Any, num_nodes: int, face_sets: dict[str, list[tuple[str, np.ndarray]]]
) -> dict[str, np.ndarray]:
    count = _size(nc, "num_node_sets")
    ids, names = _ids(nc, "ns_prop1", count), _names(nc, "ns_names", count)
    result: dict[str, np.ndarray] = {}
    for number in range(1, count + 1):
        ident, name = ids[number - 1], names[number - 1]
        label = _set_label("node set", ident, name)
        key = name or f"nodeset_{ident}"
        if key in result:
            raise ValueError(f"{label}: a second node set named {key!r}")
        nodes = np.zeros(0, dtype=np.int64)
        size, member = _size(nc, f"num_nod_ns{number}"), f"node_ns{number}"
        if size and member not in nc.variables:
            raise ValueError(f"{label}: {size} nodes but no {member}")
        if member in nc.variables:
            nodes = _integers(nc, member) - 1
            if nodes.size != size:
                raise ValueError(f"{label}: {member} holds {nodes.size} values, not {size}")
        bad = np.flatnonzero((nodes < 0) | (nodes >= num_nodes))
        if bad.size:
            raise ValueError(
                f"{label}: node {nodes[bad[0]] + 1} is outside the file's nodes 1..{num_nodes}"
            )
        nodes = np.unique(nodes)
        if key in face_sets:
            blocks = face_sets[key]
            of_faces = np.unique(np.concatenate([n.ravel() for _, n in blocks] or [nodes[:0]]))
            if not np.array_equal(of_faces, nodes):
                renamed = f"nodeset_{ident}"
                if renamed in face_sets or renamed in result or renamed in names:
                    raise ValueError(f"{label}: named like a side set, with other nodes")
                warnings.warn(
                    f"{label} is named like a side set but holds other nodes; it is read as "
                    f"{renamed!r}",
                    UserWarning,
                    stacklevel=4,
                )
                key = renamed
        result[key] = nodes
    return result


def _results(
    nc: Any, num_nodes: int, domain: list[Block]
) -> tuple[dict[str, np.ndarray], dict[str, list[np.ndarray]]]:
    """Nodal and element variables at the last time step (see the module notes)."""
    steps = _size(nc, "time_step")
    if steps == 0:
        return {}, {}
    variables = nc.variables
    names = _names(nc, "name_nod_var", _size(nc, "num_nod_var"))
    nodal: list[tuple[str, np.ndarray]] = []
    for number, name in enumerate(names, 1):
        key = name or f"nodal_variable_{number}"
        if f"vals_nod_var{number}" in variables:
            values = variables[f"vals_nod_var{number}"][steps - 1]
        elif "vals_nod_var" in variables:  # the older layout: (time, variable, node)
            values = variables["vals_nod_var"][steps - 1, number - 1]
        else:
            raise ValueError(f"nodal variable {key!r}: no vals_nod_var{number}")
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if values.size != num_nodes:
            raise ValueError(
                f"nodal variable {key!r}: {values.size} values for the {num_nodes} nodes"
            )
        nodal.append((key, values))
    point_data = {
        base: np.stack([nodal[k][1] for k in group], 1) if len(group) > 1 else nodal[group[0]][1]
        for base, group in _fields([name for name, _ in nodal])
    }
    names = _names(nc, "name_elem_var", _size(nc, "num_elem_var"))
    per_block: list[tuple[str, list[np.ndarray]]] = []
    for number, name in enumerate(names, 1):
        arrays, present = [], False
        for block in domain:
            variable = variables.get(f"vals_elem_var{number}eb{block.number}")
            values = np.full(len(block.nodes), np.nan)
            if variable is not None:
                values, present = np.asarray(variable[steps - 1], dtype=np.float64), True
                if values.size != len(block.nodes):
                    raise ValueError(
                        f"element variable {name or number!r}: vals_elem_var{number}eb"
                        f"{block.number} holds {values.size} values for the "
                        f"{len(block.nodes)} elements of {block.label}"
                    )
            arrays.append(values.reshape(-1))
        if present:
            per_block.append((name or f"element_variable_{number}", arrays))
    cell_data = {
        base: [
            np.stack([per_block[k][1][b] for k in group], 1)
            if len(group) > 1
            else per_block[group[0]][1][b]
            for b in range(len(domain))
        ]
        for base, group in _fields([name for name, _ in per_block])
    }
    return point_data, cell_data


_COMPONENT = re.compile(r"(.+)_([xX]|1)")


def _fields(names: list[str]) -> list[tuple[str, list[int]]]:
    """Fields of variables: runs of components ``<base>_x, _y[, _z]`` or ``<base>_1 … _k``
    (k >= 2, one after another, ``<base>`` no other variable's name) are one field."""
    taken = set(names)
    fields: list[tuple[str, list[int]]] = []
    position = 0
    while position < len(names):
        match = _COMPONENT.fullmatch(names[position])
        run = [position]
        if match and match.group(1) not in taken:
            base, letter = match.group(1), match.group(2)
            suffixes = ("y", "z") if letter in "xX" else (str(k) for k in range(2, len(names) + 2))
            for suffix in suffixes:
                following = run[-1] + 1
                if (
                    following < len(names)
                    and names[following].lower() == f"{base}_{suffix}".lower()
                ):
                    run.append(following)
                else:
                    break
        if len(run) > 1 and match:
            fields.append((match.group(1), run))
            taken.add(match.group(1))
        else:
            fields.append((names[position], run[:1]))
        position = run[-1] + 1 if len(run) > 1 else position + 1
    return fields


# --------------------------------------------------------------------------- writing


def write_exodus(path: str | os.PathLike, data: MeshData) -> None:
    """Write a mesh as an Exodus II file, its face sets as side sets.

    Parameters
    ----------
    path : str or PathLike
        The file to write (replaced atomically: a failing write leaves it as it was).
    data : MeshData
        ``points`` (N, 2) or (N, 3), finite (a 2-D mesh with a ``planar_coordinate`` is
        written in 3-D at that z); ``cells`` of the kinds in
        :data:`~torchmorph.mesh.formats._exodus_tables.EXODUS_TYPES` (one element block
        each, in order, ids 1, 2, …; blocks without cells are left out); ``face_sets``
        (side sets, ids 1, 2, … in order), ``node_sets`` (node sets, ids 1, 2, …),
        ``point_data`` and ``cell_data`` (nodal and element variables, one time step).

    Raises
    ------
    ImportError
        Without the netCDF4 package.
    ValueError
        Naming the file and the entry: points of the wrong shape or not finite, a cell
        kind Exodus cannot hold or of the wrong dimension, node numbers out of range, a
        facet that is no side of a cell (or of another kind than that side: a hexahedron20's
        side is a quad8), node set rows out of range, names longer than 255 bytes, data of
        the wrong length. ``groups`` are not written (Exodus has none).
    """
    netcdf4 = _netcdf4()
    target = str(path)
    try:
        plan = layout(data)
    except ValueError as error:
        raise ValueError(f"{error} (writing {target!r})") from error
    with atomic_output(path) as temporary:
        with netcdf4.Dataset(str(temporary), "w", format="NETCDF3_64BIT_OFFSET") as dataset:
            write(dataset, plan)


# --------------------------------------------------------------------------- moving


def move_exodus(source: str | os.PathLike, points: Any, output: str | os.PathLike) -> None:
    """Write the Exodus file ``source`` again at ``output`` with new coordinates, every
    other variable, dimension and attribute as it was (results, QA and info records, maps,
    attributes, distribution factors …): the file is copied and its coordinate variables
    overwritten, atomically.

    Parameters
    ----------
    source : str or PathLike
    points : array, shape (N, D)
        New coordinates of :func:`read_exodus`'s points (D = 2 for a planar mesh in a 3-D
        file: its z is kept). Stored in the file's own precision (float32 files round).
    output : str or PathLike

    Raises
    ------
    ValueError
        If ``points`` do not have read_exodus's shape or are not finite, or ``source``
        cannot be read (see :func:`read_exodus`).
    """
    netcdf4 = _netcdf4()
    reference = read_exodus(source)
    moved = np.asarray(points, dtype=np.float64)
    if moved.shape != reference.points.shape:
        raise ValueError(f"points must have shape {reference.points.shape}, got {moved.shape}")
    if not np.isfinite(moved).all():
        raise ValueError("points holds NaN or infinite values")
    with atomic_output(output) as temporary:
        shutil.copyfile(source, temporary)
        with netcdf4.Dataset(str(temporary), "a") as nc:
            nc.set_auto_mask(False)
            if "coordx" in nc.variables:
                for axis, letter in enumerate("xyz"[: moved.shape[1]]):
                    nc.variables[f"coord{letter}"][:] = moved[:, axis]
            else:
                nc.variables["coord"][: moved.shape[1], :] = moved.T
