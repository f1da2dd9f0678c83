"""What every mesh reader returns: :class:`MeshData`, a mesh as its file gives it, in plain
NumPy arrays with meshio's cell-kind names and node orders (VTK's)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MeshData", "in_plane"]


@dataclass
class MeshData:
    """A mesh as a file gives it.

    Attributes
    ----------
    points : ndarray, shape (N, D), float64
        Node coordinates, rows in the order of the mesh's node numbering (a format with
        sparse or 1-based node ids maps them to rows 0..N-1 and keeps the map in its
        own source object, for writing back).
    cells : list of (kind, ndarray (M_k, n_k) int64)
        The domain's cells (those of the top dimension), block by block in the file's
        order, kinds named as meshio names them (``"tetra"``, ``"hexahedron20"``,
        ``"wedge"``, ``"triangle"``, ``"quad9"`` …) with meshio's (VTK's) node order.
    node_sets : dict of str to ndarray (K,) int64
        Named node sets (sorted unique rows).
    face_sets : dict of str to list of (kind, ndarray)
        Named sets of boundary facets (``"triangle"``/``"quad"``/``"triangle6"`` … of a
        3-D mesh, ``"line"``/``"line3"`` of a 2-D one), where the format's markers are
        faces (SU2 markers, OpenFOAM patches, Exodus side sets, Gmsh physical surfaces).
        Their node sets are derived from them; they are kept to be written back exactly.
    groups : dict of str to list of str
        Named groups of markers (OpenFOAM's ``inGroups``): a group is a marker too.
    point_data : dict of str to ndarray (N, ...)
    cell_data : dict of str to list of ndarray
        One array per block of ``cells``.
    planar_coordinate : float, optional
        For a planar mesh (2-D cells) that the file stores with three coordinates: the
        constant third one, dropped from ``points`` and restored on writing.
    """

    points: np.ndarray
    cells: list[tuple[str, np.ndarray]]
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    face_sets: dict[str, list[tuple[str, np.ndarray]]] = field(default_factory=dict)
    groups: dict[str, list[str]] = field(default_factory=dict)
    point_data: dict[str, np.ndarray] = field(default_factory=dict)
    cell_data: dict[str, list[np.ndarray]] = field(default_factory=dict)
    planar_coordinate: float | None = None


def in_plane(points: np.ndarray, where: str) -> tuple[np.ndarray, float]:
    """The in-plane coordinates (N, 2) of planar cells stored with three coordinates, and
    the constant third one; ``ValueError`` (``where``: the file) if the points leave the
    plane z = const (a surface mesh in 3-D is not a volume or planar mesh)."""
    z = points[:, 2]
    if z.size and np.ptp(z) > 1e-12 * max(1.0, float(np.abs(points).max())):
        raise ValueError(
            f"{where}: planar cells with points off one plane z = const: a surface mesh in "
            "3-D is not a volume or planar mesh"
        )
    return np.ascontiguousarray(points[:, :2]), (float(z[0]) if z.size else 0.0)
