"""SU2's native mesh format (``.su2``), read and written with its markers kept by name.

meshio reads ``.su2`` files but numbers the markers and loses their names
(``MARKER_TAG= airfoil``); a morphed mesh handed back to SU2 needs them, since SU2's
configuration file assigns the boundary conditions by marker name. :func:`read_su2`
returns a :class:`~torchmorph.mesh.formats.MeshData` whose ``face_sets`` are the markers,
and :func:`write_su2` writes them back exactly.

The format (SU2's documentation, "Mesh File")::

    NDIME= 2                      % the dimension, 2 or 3
    NELEM= 2                      % the domain's elements: VTK type, its nodes
    5 0 1 2                       %   (an optional trailing element index)
    9 1 3 4 2
    NPOIN= 5                      % the points: x y [z] (an optional trailing index)
    0.0 0.0
    ...
    NMARK= 1                      % the markers: name, count, boundary elements
    MARKER_TAG= airfoil
    MARKER_ELEMS= 2
    3 0 1
    3 1 3

Element kinds are VTK's type ids with VTK's node order, which is also meshio's, so the
connectivity is passed through unchanged: 3 line, 5 triangle, 9 quad, 10 tetra,
12 hexahedron, 13 wedge (SU2's "prism"), 14 pyramid. SU2 has no quadratic kinds. In this
order (SU2's own face tables, ``CPrismConnectivity`` and its siblings, list the faces
outward) a pyramid's base (0, 1, 2, 3) turns counter-clockwise seen from its apex 4, and
a wedge's triangle (0, 1, 2) turns clockwise seen from its triangle (3, 4, 5): the
mirror image of gmsh's prism (gmsh's own SU2 writer swaps nodes 1, 2 and 4, 5; meshio's
gmsh reader does not, so a "wedge" read from a ``.msh`` file by meshio is the mirror of
SU2's order and must be permuted before it is written here).

How a file maps to :class:`MeshData`, and what is decided where the format leaves room:

* **Row and element numbers are the line order.** SU2 numbers points and elements by
  the order of their lines and ignores a trailing index on a point or element line
  (its documentation: "implied by the ordering ... can be ignored"). This reader does
  the same, so that it sees the mesh SU2 simulates; where the trailing indices are not
  0, 1, 2 … in line order it says so in a :class:`UserWarning` and still follows the
  line order. (A trailing value on a marker's element line is accepted and ignored.)
* **Cells are grouped by kind**, blocks in the order in which each kind first appears,
  elements of one kind in file order. Each cell's position among the ``NELEM=`` lines
  is kept in ``cell_data[ELEMENT_INDEX]`` (one array per block), and :func:`write_su2`
  writes the elements back in that order, so a file whose kinds interleave keeps its
  element numbering.
* **Markers become face sets** in the file's order, named by their tags; a marker's
  facets are grouped by kind in the order each kind first appears (the order of a
  marker's facets of one kind is kept; the interleaving of its triangles and quads is
  not). ``node_sets`` holds each marker's nodes (sorted, unique), derived from its facets.
* ``NPOIN= n n_domain`` (a domain count, from partitioned legacy files): the count is
  checked (``0 <= n_domain <= n``) and not kept, as SU2 itself ignores it.
* ``%`` starts a comment anywhere on a line; blank lines are skipped; keywords are
  read with or without spaces around ``=`` (SU2 itself wants ``KEYWORD=``, which is
  what :func:`write_su2` writes; it writes no comments).
* One zone: ``NZONE= 1`` and ``IZONE= 1`` are accepted, a file with several zones is
  refused. ``AOA_OFFSET=``/``AOS_OFFSET=`` of zero and ``FFD_NBOX= 0``/``FFD_NLEVEL= 0``
  are accepted (they say nothing); non-zero offsets and FFD boxes are refused, since
  :class:`MeshData` cannot carry them and writing the mesh back would drop them. Every
  other keyword is refused by name.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from itertools import chain
from pathlib import Path

import numpy as np

from torchmorph._atomic import atomic_output
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats._su2_parse import (
    _DIMENSION_OF,
    _NODES_OF,
    _VTK_TYPE_OF,
    ELEMENT_INDEX,
    SU2_KINDS,
    _error,
    _marker_name_problem,
    _no_nodes,
    _parse_elements,
    _parse_points,
    _scan,
)

__all__ = ["ELEMENT_INDEX", "SU2_KINDS", "read_su2", "write_su2"]


def read_su2(path: str | os.PathLike) -> MeshData:
    """Read an SU2 mesh (``.su2``, one zone, 2-D or 3-D) with its markers by name.

    Parameters
    ----------
    path : str or PathLike
        The ``.su2`` file.

    Returns
    -------
    MeshData
        ``points`` : ndarray, shape (N, D), float64, D = ``NDIME`` (2 or 3), rows in the
        order of the point lines.
        ``cells`` : list of (kind, ndarray (M_k, n_k) int64), the ``NELEM=`` elements
        grouped by kind (``"triangle"``, ``"quad"`` in 2-D; ``"tetra"``, ``"hexahedron"``,
        ``"wedge"``, ``"pyramid"`` in 3-D), blocks in the order each kind first appears,
        node order VTK's (SU2's and meshio's).
        ``cell_data[ELEMENT_INDEX]`` : list of ndarray (M_k,) int64, each cell's position
        among the ``NELEM=`` lines.
        ``face_sets`` : dict of marker name to list of (kind, ndarray (K_k, n_k) int64),
        markers in the file's order, facets (``"line"`` in 2-D, ``"triangle"``/``"quad"``
        in 3-D) grouped by kind in the order each kind first appears.
        ``node_sets`` : dict of marker name to ndarray (K,) int64, each marker's nodes,
        sorted and unique. ``groups`` and ``point_data`` are empty.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        For a malformed file, naming the file and the line: a missing or duplicated
        section, a count (``NELEM=``, ``NPOIN=``, ``NMARK=``, ``MARKER_ELEMS=``) that does
        not match the lines that follow, a line with the wrong number of values or a value
        that is not a number, an unknown VTK type, an element of the wrong dimension (a
        tetrahedron in a 2-D mesh, a line in a 3-D marker), a node number out of range, a
        non-finite coordinate, an empty, duplicated or white-space-holding marker name,
        several zones, an unknown keyword, or content :class:`MeshData` cannot carry
        (non-zero ``AOA_OFFSET=``/``AOS_OFFSET=``, FFD boxes).

    Warns
    -----
    UserWarning
        Where trailing point or element indices disagree with the line order (which is
        followed, as SU2 follows it).

    Notes
    -----
    See the module's documentation for what is decided where the format leaves room.
    Does not check the cells' orientation or validity (call the mesh's quality checks).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: mesh file {str(path)!r} does not exist")
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"path: {source!r}: not a text file in UTF-8 ({error})") from error
    sections = _scan(source, text)
    dimension = sections.dimension
    assert dimension is not None and sections.points is not None and sections.elements is not None

    points, point_warning = _parse_points(source, sections.points, dimension)
    num_points = points.shape[0]
    if sections.domain_points is not None and sections.domain_points > num_points:
        raise _error(
            source,
            sections.points.line,
            f"NPOIN= {num_points} {sections.domain_points}: the domain count "
            f"{sections.domain_points} exceeds the number of points {num_points}",
        )

    groups, element_warning = _parse_elements(
        source, sections.elements, dimension, num_points, f"{dimension}-D mesh's NELEM= section"
    )
    for warning in (point_warning, element_warning):
        if warning is not None:
            warnings.warn(warning, UserWarning, stacklevel=2)
    cells = [(kind, connectivity) for kind, _, connectivity in groups]
    element_index = [rows for _, rows, _ in groups]

    face_sets: dict[str, list[tuple[str, np.ndarray]]] = {}
    node_sets: dict[str, np.ndarray] = {}
    for marker in sections.markers:
        facets, _ = _parse_elements(
            source,
            marker.block,
            dimension - 1,
            num_points,
            f"marker {marker.name!r} (MARKER_TAG= at line {marker.line}) of a {dimension}-D mesh",
        )
        face_sets[marker.name] = [(kind, connectivity) for kind, _, connectivity in facets]
        nodes = [connectivity.ravel() for _, _, connectivity in facets]
        node_sets[marker.name] = np.unique(np.concatenate(nodes)) if nodes else _no_nodes()
    return MeshData(
        points=points,
        cells=cells,
        node_sets=node_sets,
        face_sets=face_sets,
        cell_data={ELEMENT_INDEX: element_index},
    )


def write_su2(path: str | os.PathLike, data: MeshData) -> None:
    """Write a mesh as an SU2 mesh file (``.su2``) with its face sets as markers.

    Writes ``NDIME=``, the cells (``NELEM=``), the points at full float64 precision
    (``NPOIN=``, shortest round-tripping decimals) and the face sets as markers
    (``NMARK=``, ``MARKER_TAG=``, ``MARKER_ELEMS=``) in the order of ``data.face_sets``,
    so that :func:`read_su2` of the file gives back every array and marker exactly.

    Parameters
    ----------
    path : str or PathLike
        The file to write (replaced atomically: a failing write leaves it as it was).
    data : MeshData
        ``points`` : array, shape (N, D), D = 2 or 3, finite.
        ``cells`` : triangles and quads (2-D) or tetra, hexahedron, wedge and pyramid
        blocks (3-D), VTK node order; written block by block, or in the order given by
        ``cell_data[ELEMENT_INDEX]`` where present (as :func:`read_su2` returns it).
        ``face_sets`` : lines (2-D) or triangles and quads (3-D) per marker name.

    Raises
    ------
    ValueError
        Naming the file and the offending entry: points not of shape (N, 2) or (N, 3) or
        not finite; a cell kind SU2 cannot hold (quadratic and other higher-order kinds,
        polyhedra) or of the wrong dimension; connectivity of the wrong shape or with node
        numbers out of range; a face set whose facets are not of the dimension below the
        mesh's; a marker name that is empty or holds white space or ``%``; a
        ``cell_data[ELEMENT_INDEX]`` that does not number the cells 0..M-1.

    Notes
    -----
    SU2 files hold no node sets, groups or data: ``node_sets`` (derived from the face sets
    on reading), ``groups``, ``point_data`` and ``cell_data`` other than
    ``ELEMENT_INDEX`` are not written, nor is ``planar_coordinate`` (SU2's 2-D meshes have
    two coordinates: a planar mesh is written from its (N, 2) points). Cell blocks of one kind come back from
    :func:`read_su2` merged into one block. Trailing point or element indices are not
    written (SU2 numbers by line order). The file holds no comments.
    """
    source = str(path)
    points = _checked_points(source, data.points)
    dimension, num_points = points.shape[1], points.shape[0]
    cells = [
        _checked_block(source, f"data.cells[{number}]", kind, connectivity, dimension, num_points)
        for number, (kind, connectivity) in enumerate(data.cells)
    ]
    order = _element_order(source, data.cell_data.get(ELEMENT_INDEX), cells)
    markers: list[tuple[str, list[tuple[str, np.ndarray]]]] = []
    for name, facets in data.face_sets.items():
        if not isinstance(name, str):
            raise ValueError(
                f"data.face_sets: marker names must be strings, got {name!r} (writing {source!r})"
            )
        label = f"data.face_sets[{name!r}]"
        problem = _marker_name_problem(name)
        if problem:
            raise ValueError(f"{label}: {problem} (writing {source!r})")
        markers.append(
            (
                name,
                [
                    _checked_block(
                        source, f"{label}[{number}]", kind, connectivity, dimension, num_points, 1
                    )
                    for number, (kind, connectivity) in enumerate(facets)
                ],
            )
        )

    with atomic_output(path) as temporary, open(temporary, "w", encoding="utf-8") as stream:
        stream.write(f"NDIME= {dimension}\n")
        stream.write(f"NELEM= {sum(len(connectivity) for _, connectivity in cells)}\n")
        lines = list(chain.from_iterable(_element_lines(kind, block) for kind, block in cells))
        if order is not None:
            lines = [lines[row] for row in order.tolist()]
        _write_lines(stream, lines)
        stream.write(f"NPOIN= {num_points}\n")
        _write_lines(stream, [" ".join(map(repr, row)) for row in points.tolist()])
        stream.write(f"NMARK= {len(markers)}\n")
        for name, facets in markers:
            stream.write(f"MARKER_TAG= {name}\n")
            stream.write(f"MARKER_ELEMS= {sum(len(block) for _, block in facets)}\n")
            for kind, block in facets:
                _write_lines(stream, _element_lines(kind, block))


def _element_lines(kind: str, connectivity: np.ndarray) -> list[str]:
    prefix = f"{_VTK_TYPE_OF[kind]} "
    return [prefix + " ".join(map(str, row)) for row in connectivity.tolist()]


def _write_lines(stream, lines: Sequence[str]) -> None:
    if lines:
        stream.write("\n".join(lines))
        stream.write("\n")


def _checked_points(source: str, points: object) -> np.ndarray:
    array = np.asarray(points)
    if array.dtype.kind not in "fiu":
        raise ValueError(
            f"data.points: must hold real numbers, got dtype {array.dtype} (writing {source!r})"
        )
    if array.ndim != 2 or array.shape[1] not in (2, 3):
        raise ValueError(
            f"data.points: SU2 meshes are 2-D or 3-D, points must have shape (N, 2) or "
            f"(N, 3), got {array.shape} (writing {source!r})"
        )
    array = array.astype(np.float64, copy=False)
    not_finite = np.flatnonzero(~np.isfinite(array).all(axis=1))
    if not_finite.size:
        row = int(not_finite[0])
        raise ValueError(
            f"data.points: row {row} is not finite ({array[row].tolist()}); "
            f"{not_finite.size} such rows (writing {source!r})"
        )
    return array


def _checked_block(
    source: str,
    label: str,
    kind: str,
    connectivity: object,
    dimension: int,
    num_points: int,
    codimension: int = 0,
) -> tuple[str, np.ndarray]:
    """Check a block of a ``dimension``-D mesh's cells (codimension 0) or boundary facets (1).

    Returns the kind and the connectivity as int64.
    """
    if kind not in _VTK_TYPE_OF:
        raise ValueError(
            f"{label}: SU2 cannot hold {kind!r} elements: its kinds are linear only "
            f"({', '.join(_VTK_TYPE_OF)}), no quadratic or other higher-order kinds "
            f"(writing {source!r})"
        )
    if _DIMENSION_OF[kind] != dimension - codimension:
        allowed = ", ".join(
            name for name, other in _DIMENSION_OF.items() if other == dimension - codimension
        )
        what = "boundary facets (markers)" if codimension else "cells"
        raise ValueError(
            f"{label}: {kind!r} is a {_DIMENSION_OF[kind]}-D kind; the {what} of a "
            f"{dimension}-D SU2 mesh are {allowed} (writing {source!r})"
        )
    array = np.asarray(connectivity)
    nodes = _NODES_OF[kind]
    if array.ndim != 2 or array.shape[1] != nodes or (array.size and array.dtype.kind not in "iu"):
        raise ValueError(
            f"{label}: {kind!r} connectivity must be integers of shape (M, {nodes}), got "
            f"{array.shape} of dtype {array.dtype} (writing {source!r})"
        )
    array = array.astype(np.int64, copy=False)
    if array.size and (array.min() < 0 or array.max() >= num_points):
        raise ValueError(
            f"{label}: node numbers must be in 0..{num_points - 1}, got "
            f"{array.min()}..{array.max()} (writing {source!r})"
        )
    return kind, array


def _element_order(
    source: str, element_index: object, cells: list[tuple[str, np.ndarray]]
) -> np.ndarray | None:
    """The block-order rows by file position, from ``cell_data[ELEMENT_INDEX]``; or None."""
    if element_index is None:
        return None
    label = f"data.cell_data[{ELEMENT_INDEX!r}]"
    if not isinstance(element_index, Sequence) or len(element_index) != len(cells):
        count = len(element_index) if isinstance(element_index, Sequence) else "no list"
        raise ValueError(
            f"{label}: must be a list of one index array per cell block ({len(cells)}), got "
            f"{count} (writing {source!r})"
        )
    arrays = []
    for number, (indices, (_, connectivity)) in enumerate(zip(element_index, cells, strict=True)):
        array = np.asarray(indices)
        if array.shape != (len(connectivity),) or (array.size and array.dtype.kind not in "iu"):
            raise ValueError(
                f"{label}[{number}]: must be integers of shape ({len(connectivity)},), got "
                f"{array.shape} of dtype {array.dtype} (writing {source!r})"
            )
        arrays.append(array.astype(np.int64, copy=False))
    positions = np.concatenate(arrays) if arrays else np.zeros(0, dtype=np.int64)
    if not np.array_equal(np.sort(positions), np.arange(positions.shape[0])):
        raise ValueError(
            f"{label}: must number the {positions.shape[0]} cells 0..{positions.shape[0] - 1}, "
            f"each once (writing {source!r})"
        )
    order = np.empty_like(positions)
    order[positions] = np.arange(positions.shape[0])
    return order
