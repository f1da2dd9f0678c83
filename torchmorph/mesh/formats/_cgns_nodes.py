"""CGNS/HDF5 nodes and element tables, for :mod:`torchmorph.mesh.formats.cgns`.

A CGNS/HDF5 file (the CGNS HDF5 file mapping, as the Mid-Level Library's ADFH layer
writes it) is a tree of HDF5 groups, one per node, each with the attributes ``name``,
``label`` (the SIDS type, ``Zone_t`` …), ``type`` (``MT``, ``C1``, ``I4``, ``I8``,
``R4``, ``R8``) and ``flags``, and its data, if any, in a dataset named ``" data"``.
Array dimensions are stored reversed (Fortran order): an ``IndexArray_t`` of SIDS
dimensions (1, n) is an HDF5 dataset of shape (n, 1). Character data (``C1``) are int8
arrays. Children are kept in creation order (tracked and indexed), as the library
creates them.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from torchmorph.mesh.formats._hdf5 import set_text_attribute

__all__ = [
    "CGNS_KINDS",
    "CGNS_TO_VTK",
    "ELEMENT_TYPE_NAMES",
    "array",
    "children",
    "data",
    "label",
    "new_node",
    "set_text_attribute",
    "text",
]

#: CGNS ElementType_t codes of the kinds torchmorph holds: code -> (meshio kind, nodes).
CGNS_KINDS: dict[int, tuple[str, int]] = {
    2: ("vertex", 1),
    3: ("line", 2),
    4: ("line3", 3),
    5: ("triangle", 3),
    6: ("triangle6", 6),
    7: ("quad", 4),
    8: ("quad8", 8),
    9: ("quad9", 9),
    10: ("tetra", 4),
    11: ("tetra10", 10),
    12: ("pyramid", 5),
    13: ("pyramid14", 14),
    14: ("wedge", 6),
    15: ("wedge15", 15),
    16: ("wedge18", 18),
    17: ("hexahedron", 8),
    18: ("hexahedron20", 20),
    19: ("hexahedron27", 27),
    21: ("pyramid13", 13),
}

#: Every ElementType_t name, by code (CGNS 4: cgnslib.h), for messages.
ELEMENT_TYPE_NAMES: dict[int, str] = {
    0: "ElementTypeNull", 1: "ElementTypeUserDefined", 2: "NODE", 3: "BAR_2", 4: "BAR_3",
    5: "TRI_3", 6: "TRI_6", 7: "QUAD_4", 8: "QUAD_8", 9: "QUAD_9", 10: "TETRA_4",
    11: "TETRA_10", 12: "PYRA_5", 13: "PYRA_14", 14: "PENTA_6", 15: "PENTA_15",
    16: "PENTA_18", 17: "HEXA_8", 18: "HEXA_20", 19: "HEXA_27", 20: "MIXED", 21: "PYRA_13",
    22: "NGON_n", 23: "NFACE_n", 24: "BAR_4", 25: "TRI_9", 26: "TRI_10", 27: "QUAD_12",
    28: "QUAD_16", 29: "TETRA_16", 30: "TETRA_20", 31: "PYRA_21", 32: "PYRA_29",
    33: "PYRA_30", 34: "PENTA_24", 35: "PENTA_38", 36: "PENTA_40", 37: "HEXA_32",
    38: "HEXA_56", 39: "HEXA_64", 40: "BAR_5", 41: "TRI_12", 42: "TRI_15", 43: "QUAD_P4_16",
    44: "QUAD_25", 45: "TETRA_22", 46: "TETRA_34", 47: "TETRA_35", 48: "PYRA_P4_29",
    49: "PYRA_50", 50: "PYRA_55", 51: "PENTA_33", 52: "PENTA_66", 53: "PENTA_75",
    54: "HEXA_44", 55: "HEXA_98", 56: "HEXA_125",
}  # fmt: skip

#: CGNS node order -> meshio's (VTK's), where they differ: a CGNS block ``c`` is
#: ``c[:, order]`` in VTK's order. CGNS puts a prism's or hexahedron's vertical edges
#: before its top edges (SIDS, "Unstructured Grid Element Numbering Conventions"), VTK
#: after them; HEXA_27 orders its face centres z-min, y-min, x-max, y-max, x-min, z-max,
#: VTK x-min, x-max, y-min, y-max, z-min, z-max. Every other kind is in the same order
#: (TETRA_10, PYRA_13/14, PENTA_6, HEXA_8, the 2-D kinds). VTK's own CGNS reader applies
#: the same permutations.
CGNS_TO_VTK: dict[str, tuple[int, ...]] = {
    "wedge15": (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 13, 14, 9, 10, 11),
    "wedge18": (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 13, 14, 9, 10, 11, 15, 16, 17),
    "hexahedron20": (*range(12), 16, 17, 18, 19, 12, 13, 14, 15),
    "hexahedron27": (*range(12), 16, 17, 18, 19, 12, 13, 14, 15, 24, 22, 21, 23, 20, 25, 26),
}

_FORTRAN_TO_HDF5 = {"I4": np.int32, "I8": np.int64, "R4": np.float32, "R8": np.float64}


def _string(value) -> str:
    """An attribute's text: a fixed-length string or (older files) an int8 array."""
    if isinstance(value, np.ndarray) and value.dtype.kind in "iu":
        value = value.astype(np.uint8).tobytes()
    if isinstance(value, np.ndarray):
        value = value.tobytes() if value.dtype.kind == "S" else str(value)
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    return str(value).split("\0", 1)[0]


def label(group) -> str:
    """The SIDS label of a node (``""`` where it has none)."""
    return _string(group.attrs["label"]) if "label" in group.attrs else ""


def data(group) -> np.ndarray | None:
    """A node's data, as stored (dimensions reversed), or None."""
    dataset = group.get(" data")
    if dataset is None or not hasattr(dataset, "shape"):
        return None
    return np.asarray(dataset[()])


def array(group) -> np.ndarray:
    """A node's data, as stored, or an empty array where it has none."""
    values = data(group)
    return np.zeros(0, dtype=np.int64) if values is None else values


def text(group) -> str:
    """A ``C1`` node's data as text (trailing NULs and blanks removed)."""
    values = data(group)
    if values is None:
        return ""
    return values.astype(np.uint8).tobytes().decode("utf-8", errors="replace").rstrip("\0 ")


def children(group, wanted: str | None = None) -> Iterator[tuple[str, Any]]:
    """The child nodes of a group (name, group), in the file's order; only those labelled
    ``wanted`` if given. Datasets (``" data"``) and links that lead nowhere are skipped."""
    for name in group:
        if name.startswith(" "):
            continue
        try:
            child = group[name]
        except KeyError:  # a link to a missing file or node
            continue
        if hasattr(child, "attrs") and not hasattr(child, "shape"):
            if wanted is None or label(child) == wanted:
                yield name, child


def new_node(parent, name: str, node_label: str, kind: str = "MT", value=None):
    """Create a node under ``parent`` as the ADFH layer does: attributes ``name``,
    ``label`` (33-byte strings), ``type`` (3 bytes) and ``flags`` ([1]), data in ``" data"``
    (``value`` as stored, its dimensions already reversed; text for ``C1``)."""
    group = parent.create_group(name, track_order=True)
    set_text_attribute(group, "name", name, 33)
    set_text_attribute(group, "label", node_label, 33)
    set_text_attribute(group, "type", kind, 3)
    group.attrs.create("flags", np.array([1], dtype=np.int32))
    if kind == "C1":
        array = np.frombuffer(str(value).encode("utf-8"), dtype=np.int8)
        group.create_dataset(" data", data=array)
    elif kind != "MT":
        group.create_dataset(" data", data=np.asarray(value, dtype=_FORTRAN_TO_HDF5[kind]))
    return group
