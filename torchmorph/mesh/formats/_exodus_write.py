"""Writing Exodus II files: :class:`MeshData` checked and laid out as element blocks, node
sets, side sets and variables (:func:`layout`), then written to a netCDF file (:func:`write`)
as the Exodus library lays it out (``ex_put_init_ext``, ``ex_put_block``, ``ex_put_set`` …)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from torchmorph.mesh.cells import CELL_KINDS
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats._exodus_tables import (
    EXODUS_TYPES,
    FACET_CORNERS,
    TO_VTK,
    Block,
    ElementType,
    SideIndex,
    side_table,
)

__all__ = ["Layout", "layout", "write"]

#: The Exodus library version whose file layout is followed.
_VERSION = np.float32(9.06)
_LEN_NAME, _LEN_STRING, _LEN_LINE = 256, 33, 81


class Layout(NamedTuple):
    """What :func:`write` writes: points (N, 2 or 3), the mesh's dimension, the element
    blocks (Exodus order), side sets (name, elements 1-based, sides), node sets (name,
    nodes 1-based), nodal variables (name, [values]) and element variables (name, one
    array per block)."""

    points: np.ndarray
    dim: int
    blocks: list[Block]
    side_sets: list[tuple[str, np.ndarray, np.ndarray]]
    node_sets: list[tuple[str, np.ndarray]]
    nodal: list[tuple[str, list[np.ndarray]]]
    element_vars: list[tuple[str, list[np.ndarray]]]


def layout(data: MeshData) -> Layout:
    """Check ``data`` and lay it out for :func:`write` (``ValueError`` naming the entry)."""
    points = np.asarray(data.points)
    if points.dtype.kind not in "fiu" or points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"data.points must be real, of shape (N, 2) or (N, 3), got {points.shape}")
    points = points.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(points).all(1))
    if bad.size:
        raise ValueError(f"data.points: row {bad[0]} is not finite ({points[bad[0]].tolist()})")
    num_nodes, dim = points.shape
    if num_nodes >= 2**31:
        raise ValueError(f"data.points: {num_nodes} nodes, more than 32-bit node numbers hold")
    if dim == 2 and data.planar_coordinate is not None:
        points = np.column_stack([points, np.full(num_nodes, float(data.planar_coordinate))])
    blocks: list[Block] = []
    start = 0
    for position, (kind, nodes) in enumerate(data.cells):
        label = f"data.cells[{position}] ({kind})"
        if kind not in EXODUS_TYPES:
            raise ValueError(
                f"{label}: {kind!r} cells are not written to Exodus files; the kinds are "
                + ", ".join(EXODUS_TYPES)
            )
        sides = side_table(kind)
        if (sides in ("quad", "triangle")) != (dim == 2):
            raise ValueError(f"{label}: not a cell of a {dim}-D mesh")
        nodes = _connectivity(label, nodes, num_nodes, CELL_KINDS[kind].num_nodes)
        if not len(nodes):
            continue
        order = TO_VTK.get(kind)
        exodus = nodes[:, list(np.argsort(order))] if order else nodes
        number = len(blocks) + 1
        element = ElementType(kind, 3 if dim == 3 else 2, sides)
        blocks.append(Block(number, number, "", label, element, exodus, start))
        start += len(nodes)
    if not blocks:
        raise ValueError("data.cells holds no cells")
    index = SideIndex(blocks, num_nodes)
    facets = {"line", "line3"} if dim == 2 else set(FACET_CORNERS) - {"line", "line3"}
    side_sets = []
    for name, members in data.face_sets.items():
        label = f"data.face_sets[{name!r}]"
        elements, sides_of = [], []
        for position, (kind, nodes) in enumerate(members):
            where = f"{label}[{position}]"
            if kind not in facets:
                raise ValueError(f"{where}: {kind!r} is not a facet of a {dim}-D mesh")
            width = {"line": 2, "line3": 3, "triangle": 3, "triangle6": 6, "quad": 4}
            nodes = _connectivity(where, nodes, num_nodes, {**width, "quad8": 8, "quad9": 9}[kind])
            found, side = index.find(kind, nodes, where)
            elements.append(found)
            sides_of.append(side)
        side_sets.append((_name(name, label), _joined(elements) + 1, _joined(sides_of)))
    node_sets = []
    for name, rows in data.node_sets.items():
        label = f"data.node_sets[{name!r}]"
        rows = np.asarray(rows)
        if rows.size and rows.dtype.kind not in "iu":
            raise ValueError(f"{label}: node rows must be integers, got {rows.dtype} values")
        rows = np.unique(rows.astype(np.int64).reshape(-1))
        if rows.size and (rows[0] < 0 or rows[-1] >= num_nodes):
            raise ValueError(f"{label}: rows outside [0, {num_nodes})")
        node_sets.append((_name(name, label), rows + 1))
    nodal = _variables(data.point_data, "data.point_data", [num_nodes], nodal=True)
    sizes = [len(nodes) for _, nodes in data.cells]
    per_block = _variables(data.cell_data, "data.cell_data", sizes)
    kept = [k for k, size in enumerate(sizes) if size]
    element_vars = [(name, [arrays[k] for k in kept]) for name, arrays in per_block]
    return Layout(points, dim, blocks, side_sets, node_sets, nodal, element_vars)


def _connectivity(label: str, nodes: Any, num_nodes: int, width: int) -> np.ndarray:
    array = np.asarray(nodes)
    if array.size == 0:
        return np.zeros((0, width), dtype=np.int64)
    if array.dtype.kind not in "iu" or array.shape != (len(array), width):
        raise ValueError(
            f"{label}: node numbers must be integers of shape (M, {width}), got "
            f"{array.dtype} {array.shape}"
        )
    array = array.astype(np.int64)
    if array.min() < 0 or array.max() >= num_nodes:
        raise ValueError(f"{label}: node numbers outside [0, {num_nodes})")
    return array


def _joined(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def _name(name: Any, label: str) -> str:
    if not isinstance(name, str) or not name or "\0" in name:
        raise ValueError(f"{label}: names must be non-empty strings without NUL, got {name!r}")
    if len(name.encode()) >= _LEN_NAME:
        raise ValueError(f"{label}: names hold at most {_LEN_NAME - 1} bytes (UTF-8)")
    return name


def _variables(
    fields: dict, label: str, sizes: list[int], *, nodal: bool = False
) -> list[tuple[str, list[np.ndarray]]]:
    """Fields split into Exodus variables: (name, one array per block; one array for
    ``nodal`` fields)."""
    result = []
    for key, value in fields.items():
        where = f"{label}[{key!r}]"
        arrays = [np.asarray(value)] if nodal else [np.asarray(a) for a in value]
        if len(arrays) != len(sizes):
            raise ValueError(f"{where}: {len(arrays)} arrays for {len(sizes)} cell blocks")
        width = {a.shape[1] if a.ndim == 2 else 0 for a in arrays}
        for array, size in zip(arrays, sizes, strict=True):
            if array.dtype.kind not in "fiub" or array.ndim not in (1, 2) or len(array) != size:
                raise ValueError(f"{where}: must be numbers of shape ({size},) or ({size}, k)")
        if len(width) != 1:
            raise ValueError(f"{where}: the blocks' arrays differ in width")
        k = width.pop()
        suffixes = (
            [""]
            if k <= 1
            else [f"_{c}" for c in "xyz"[:k]]
            if k <= 3
            else [f"_{c}" for c in range(1, k + 1)]
        )
        for column, suffix in enumerate(suffixes):
            name = _name(f"{key}{suffix}", where)
            parts = [
                (a.reshape(len(a)) if k <= 1 else a[:, column]).astype(np.float64) for a in arrays
            ]
            result.append((name, parts))
    names = [name for name, _ in result]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"{label}: the variable name(s) {', '.join(repeated)} come twice")
    return result


def _chars(names: list[str], length: int) -> np.ndarray:
    array = np.zeros((len(names), length), dtype="S1")
    for row, name in enumerate(names):
        encoded = name.encode()
        array[row, : len(encoded)] = np.frombuffer(encoded, dtype="S1")
    return array


def write(nc: Any, plan: Layout) -> None:
    """Define and write every dimension, variable and attribute of ``plan`` in the open,
    empty netCDF dataset ``nc``."""
    points, blocks, side_sets, node_sets = plan.points, plan.blocks, plan.side_sets, plan.node_sets
    nodal, element_vars = plan.nodal, plan.element_vars
    names = [n for n, *_ in side_sets] + [n for n, _ in node_sets]
    names += [n for n, _ in nodal] + [n for n, _ in element_vars]
    nc.setncattr("api_version", _VERSION)
    nc.setncattr("version", _VERSION)
    nc.setncattr("floating_point_word_size", np.int32(8))
    nc.setncattr("file_size", np.int32(1))
    nc.setncattr("maximum_name_length", np.int32(max([32] + [len(n.encode()) for n in names])))
    nc.setncattr("int64_status", np.int32(0))
    nc.setncattr("title", "torchmorph mesh")
    num_dim = points.shape[1]
    for name, size in (
        ("len_string", _LEN_STRING),
        ("len_line", _LEN_LINE),
        ("four", 4),
        ("len_name", _LEN_NAME),
        ("time_step", None),
        ("num_dim", num_dim),
        ("num_nodes", len(points)),
        ("num_elem", sum(len(b.nodes) for b in blocks)),
        ("num_el_blk", len(blocks)),
    ):
        nc.createDimension(name, size)
    steps = 1 if nodal or element_vars else 0
    values: list[tuple[Any, Any]] = []  # written once everything is defined

    def variable(key: str, kind: str, dims: tuple, data: Any, **attributes: Any) -> None:
        created = nc.createVariable(key, kind, dims)
        for key, value in attributes.items():
            created.setncattr(key, value)
        values.append((created, data))

    variable("time_whole", "f8", ("time_step",), np.zeros(steps))
    _objects(variable, "eb", "num_el_blk", [""] * len(blocks))
    variable("coor_names", "S1", ("num_dim", "len_name"), _chars(list("XYZ"[:num_dim]), _LEN_NAME))
    for axis, letter in enumerate("xyz"[:num_dim]):
        variable(f"coord{letter}", "f8", ("num_nodes",), points[:, axis])
    for block in blocks:
        count, width = block.nodes.shape
        k = block.number
        nc.createDimension(f"num_el_in_blk{k}", count)
        nc.createDimension(f"num_nod_per_el{k}", width)
        dims = (f"num_el_in_blk{k}", f"num_nod_per_el{k}")
        kind = EXODUS_TYPES[block.type.kind]
        variable(f"connect{k}", "i4", dims, block.nodes + 1, elem_type=kind)
    for prefix, count_dim, items, members in (
        ("ns", "num_node_sets", node_sets, (("node_ns", "num_nod_ns"),)),
        ("ss", "num_side_sets", side_sets, (("elem_ss", "num_side_ss"), ("side_ss", ""))),
    ):
        if not items:
            continue
        nc.createDimension(count_dim, len(items))
        status = _objects(variable, prefix, count_dim, [item[0] for item in items])
        for k, item in enumerate(items, 1):
            if not len(item[1]):
                status[k - 1] = 0  # a null set: no entries, no variables
                continue
            entries = (f"{members[0][1]}{k}",)
            nc.createDimension(entries[0], len(item[1]))
            for (stem, _), array in zip(members, item[1:], strict=True):
                variable(f"{stem}{k}", "i4", entries, array)
    if nodal:
        nc.createDimension("num_nod_var", len(nodal))
        chars = _chars([name for name, _ in nodal], _LEN_NAME)
        variable("name_nod_var", "S1", ("num_nod_var", "len_name"), chars)
        for k, (_, (array,)) in enumerate(nodal, 1):
            variable(f"vals_nod_var{k}", "f8", ("time_step", "num_nodes"), array[None])
    if element_vars:
        nc.createDimension("num_elem_var", len(element_vars))
        chars = _chars([name for name, _ in element_vars], _LEN_NAME)
        variable("name_elem_var", "S1", ("num_elem_var", "len_name"), chars)
        table = np.ones((len(blocks), len(element_vars)), dtype=np.int32)
        variable("elem_var_tab", "i4", ("num_el_blk", "num_elem_var"), table)
        for v, (_, arrays) in enumerate(element_vars, 1):
            for block, array in zip(blocks, arrays, strict=True):
                dims = ("time_step", f"num_el_in_blk{block.number}")
                variable(f"vals_elem_var{v}eb{block.number}", "f8", dims, array[None])
    for created, data in values:
        created[:] = data


def _objects(variable: Any, prefix: str, count_dim: str, names: list[str]) -> np.ndarray:
    """Status (1: entries), ids 1, 2, … and names of blocks or sets; the status array is
    returned for null sets to be marked before it is written."""
    status = np.ones(len(names), dtype=np.int32)
    variable(f"{prefix}_status", "i4", (count_dim,), status)
    ids = np.arange(1, len(names) + 1, dtype=np.int32)
    variable(f"{prefix}_prop1", "i4", (count_dim,), ids, name="ID")
    variable(f"{prefix}_names", "S1", (count_dim, "len_name"), _chars(names, _LEN_NAME))
    return status
