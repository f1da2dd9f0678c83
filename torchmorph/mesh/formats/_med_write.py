"""Writing MED files, for :func:`torchmorph.mesh.formats.med.write_med` (see its module's
notes for what is written how)."""

from __future__ import annotations

import os

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats._hdf5 import set_text_attribute
from torchmorph.mesh.formats._med_tables import (
    _DIM,
    _GEO_BIT,
    _NO_PROFILE,
    _NODES,
    _STEP,
    _TYPE_OF,
    CELL_SET_PREFIX,
    MED_KINDS,
    VTK_TO_MED,
)
from torchmorph.mesh.formats._sets import checked_fields, checked_points, connectivity, node_rows

__all__ = ["write"]


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


def _numbered(
    memberships: list[frozenset], sign: int, start: int, empty: list[str]
) -> tuple[np.ndarray, dict]:
    """Family numbers for entities by the set of groups each belongs to; the groups of
    ``empty`` get a family of their own that no entity has (MED's empty groups)."""
    numbers: dict[frozenset, int] = {}
    out = np.zeros(len(memberships), dtype=np.int64)
    for k, groups in enumerate(memberships):
        if groups:
            if groups not in numbers:
                numbers[groups] = sign * (start + len(numbers))
            out[k] = numbers[groups]
    for name in empty:
        numbers.setdefault(frozenset([name]), sign * (start + len(numbers)))
    return out, {tuple(sorted(g)): n for g, n in numbers.items()}


def _dataset(parent, name: str, values, count: int):
    dataset = parent.create_dataset(name, data=values)
    dataset.attrs.create("CGT", np.int64(1))
    dataset.attrs.create("NBR", np.int64(count))
    return dataset


def _checked(kind, nodes, dim: int, num_points: int, argument: str, source: str) -> np.ndarray:
    if kind not in _TYPE_OF or _DIM[kind] != dim:
        reason = "MED has no such type" if kind not in _TYPE_OF else f"{dim}-D kinds expected here"
        raise ValueError(
            f"{argument}: a MED file cannot hold {kind!r} cells: {reason} (writing {source!r})"
        )
    return connectivity(nodes, kind, _NODES[_TYPE_OF[kind]], num_points, argument, source)


def _cell_members(data: MeshData, cells: dict, sizes: list[int], source: str):
    """The groups (``cell_set:`` cell data) of each cell, per kind in ``cells``' order."""
    flags = checked_fields(
        {k: v for k, v in data.cell_data.items() if k.startswith(CELL_SET_PREFIX)},
        "data.cell_data",
        sizes,
        source,
    )
    for key, arrays in flags.items():
        if any(a.ndim == 2 and a.shape[1] != 1 for a in arrays):
            raise ValueError(
                f"data.cell_data[{key!r}]: a group of cells is one flag per cell, got arrays "
                f"of {arrays[0].shape[1]} columns (writing {source!r})"
            )
    names = [k[len(CELL_SET_PREFIX) :] for k in flags]
    members: dict[str, list[frozenset]] = {kind: [] for kind in cells}
    for number, (kind, nodes) in enumerate(data.cells):
        rows = [flags[k][number].ravel() for k in flags]
        members[kind] += (
            [
                frozenset(g for g, f in zip(names, row, strict=True) if f)
                for row in zip(*rows, strict=True)
            ]
            if rows
            else [frozenset()] * len(nodes)
        )
    return members


def write(path: str | os.PathLike, data: MeshData) -> None:
    """Write ``data`` as a MED file (:func:`torchmorph.mesh.formats.med.write_med`)."""
    import h5py

    source = str(path)
    points = checked_points(data.points, source)
    num_points, dim = points.shape
    if dim == 2 and data.planar_coordinate is not None:
        points = np.column_stack([points, np.full(num_points, float(data.planar_coordinate))])
    cells: dict[str, list[np.ndarray]] = {}
    sizes = []
    for number, (kind, nodes) in enumerate(data.cells):
        rows = _checked(kind, nodes, dim, num_points, f"data.cells[{number}]", source)
        cells.setdefault(kind, []).append(rows)
        sizes.append(len(rows))
    cell_members = _cell_members(data, cells, sizes, source)
    point_fields = checked_fields(
        data.point_data, "data.point_data", [num_points], source, nodal=True
    )
    cell_fields = checked_fields(
        {k: v for k, v in data.cell_data.items() if not k.startswith(CELL_SET_PREFIX)},
        "data.cell_data",
        sizes,
        source,
    )
    facets: dict[str, dict[tuple, list]] = {}
    for name, blocks in data.face_sets.items():
        _name_row(name, f"data.face_sets[{name!r}]", source)
        for number, (kind, nodes) in enumerate(blocks):
            rows = _checked(
                kind, nodes, dim - 1, num_points, f"data.face_sets[{name!r}][{number}]", source
            )
            table = facets.setdefault(kind, {}) if len(rows) else {}
            for row in rows.tolist():
                table.setdefault(tuple(sorted(row)), [row, set()])[1].add(name)
    node_members: list[set[str]] = [set() for _ in range(num_points)]
    empty_node_sets = []
    for name, nodes in data.node_sets.items():
        rows = node_rows(nodes, f"data.node_sets[{name!r}]", num_points, source)
        if name not in data.face_sets:
            _name_row(name, f"data.node_sets[{name!r}]", source)
            for node in rows.tolist():
                node_members[node].add(name)
            if not rows.size:
                empty_node_sets.append(name)
    node_families, node_table = _numbered(
        [frozenset(m) for m in node_members], 1, 1, empty_node_sets
    )
    element_memberships = {kind: cell_members[kind] for kind in cells}
    element_memberships |= {
        kind: [frozenset(v[1]) for v in table.values()] for kind, table in facets.items()
    }
    all_members = [m for members in element_memberships.values() for m in members]
    empty_face_sets = [name for name, blocks in data.face_sets.items() if not _facets_in(blocks)]
    element_numbers, element_table = _numbered(all_members, -1, 1, empty_face_sets)
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
        families = f.create_group("FAS", track_order=True).create_group("mesh", track_order=True)
        families.create_group("FAMILLE_ZERO").attrs.create("NUM", np.int64(0))
        if node_table:
            _write_families(families.create_group("NOEUD", track_order=True), node_table, source)
        if element_table:
            _write_families(families.create_group("ELEME", track_order=True), element_table, source)
        _write_fields(f, data, point_fields, cell_fields, list(cells), source)


def _facets_in(blocks) -> int:
    return sum(len(np.asarray(nodes)) for _, nodes in blocks)


def _write_fields(
    f,
    data: MeshData,
    point_fields: dict[str, list[np.ndarray]],
    cell_fields: dict[str, list[np.ndarray]],
    kinds: list[str],
    source: str,
) -> None:
    if not point_fields and not cell_fields:
        return
    fields = f.create_group("CHA", track_order=True)
    entries = [(name, "NOE", arrays[0]) for name, arrays in point_fields.items()]
    for name, per_block in cell_fields.items():
        for kind in kinds:
            parts = [v for (k, _), v in zip(data.cells, per_block, strict=True) if k == kind]
            entries.append((name, "MAI." + _TYPE_OF[kind], np.concatenate(parts)))
    supports: dict[str, set[str]] = {}
    for name, support, _ in entries:
        supports.setdefault(name, set()).add(support)
    for name, support, values in entries:
        if "NOE" in supports[name] and len(supports[name]) > 1:
            raise ValueError(
                f"data[{name!r}]: a point field and a cell field of one name (writing {source!r})"
            )
        if not 0 < len(name.encode("utf-8")) <= 64:
            raise ValueError(
                f"data[{name!r}]: MED field names hold 1 to 64 bytes; rename the field "
                f"(writing {source!r})"
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
