"""MED's tables for :mod:`torchmorph.mesh.formats.med`: its geometric types, their node
orders and the constants of the file layout."""

from __future__ import annotations

import numpy as np

from torchmorph.mesh.cells import CELL_KINDS

__all__ = ["CELL_SET_PREFIX", "MED_KINDS", "MED_TO_VTK", "VTK_TO_MED"]

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
