"""OpenFOAM polyMesh cases: read a case's mesh, see it as cells and patches, and write
morphed points back so that the solver runs on the morphed mesh.

An OpenFOAM mesh (``constant/polyMesh``) is a list of ``points``, a list of ``faces``
(each a polygon of point labels), the ``owner`` cell of every face and the
``neighbour`` cell of every internal face, and the ``boundary`` patches, each a range
of the faces after the internal ones. A face is oriented out of its owner.

* :func:`read_foam_case` reads the five files: ASCII or binary (``format binary;``,
  labels of 32 or 64 bits and scalars of 64 or 32 bits as the header's ``arch`` says),
  gzipped or not (``points.gz`` ..., as ``writeCompression on`` writes them).
* :meth:`FoamCase.to_mesh_data` recognises the cells as tetrahedra, pyramids, wedges
  and hexahedra (meshio's node order) and the patches as face sets.
* :func:`write_foam_points` writes new points in the format they were read in, leaving
  every other file of the case as it was (or copies the case first).
* :func:`pseudo_2d` sees a one-cell-thick case with ``empty`` patches front and back
  (a 2-D study) as a 2-D mesh, and lifts a 2-D displacement back to both layers.

Examples
--------
Morph a 2-D airfoil study and hand it back to the solver::

    case = read_foam_case("airfoil")
    flat = pseudo_2d(case)                 # flat.mesh.points: (n, 2)
    moved = ...                            # the morphed 2-D points, (n, 2) (an IDW morph)
    displacement = flat.lift(moved - flat.mesh.points)
    write_foam_points(case, case.points + displacement, out_case="airfoil-morphed")

Notes
-----
Only the mesh in ``constant/polyMesh`` (or the polyMesh directory given) is read: zones
(``cellZones`` ...), sets and fields are left alone, and copied unchanged. Decomposed
cases (``processor*`` directories) are neither read nor written: decompose the case
again (``decomposePar -force``) after writing new points. A polyhedral mesh
(snappyHexMesh's split hexahedra, polyDualMesh) is read by :func:`read_foam_case` and
its points can be written back, but :meth:`FoamCase.to_mesh_data` refuses it.
"""

from __future__ import annotations

import gzip
import os
import shutil
from collections.abc import Container
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchmorph._atomic import atomic_output
from torchmorph.mesh.formats._data import MeshData
from torchmorph.mesh.formats._foam_2d import (
    face_points,
    front_cells,
    front_lines,
    newell_normals,
    twins,
)
from torchmorph.mesh.formats._foam_cells import cell_blocks, face_blocks
from torchmorph.mesh.formats._foam_io import (
    FoamFile,
    FoamFormat,
    check_mesh,
    find_file,
    format_points,
    read_boundary,
    read_faces,
    read_foam_file,
    read_labels,
    read_points,
)

__all__ = [
    "FoamCase",
    "FoamFormat",
    "FoamPatch",
    "Pseudo2D",
    "pseudo_2d",
    "read_foam_case",
    "write_foam_points",
]

#: The mesh files :func:`read_foam_case` reads (each may be gzipped).
MESH_FILES = ("points", "faces", "owner", "neighbour", "boundary")


@dataclass(frozen=True)
class FoamPatch:
    """One boundary patch as the ``boundary`` file gives it.

    Attributes
    ----------
    name : str
    type : str
        ``patch``, ``wall``, ``empty``, ``symmetryPlane``, ``cyclic``, ``wedge`` ...
    n_faces, start_face : int
        The patch is faces ``start_face .. start_face + n_faces - 1``.
    in_groups : tuple of str
        The groups it belongs to (``inGroups``).
    entries : dict of str to str
        Its other keywords with their values as written (``neighbourPatch``,
        ``transform``, ``physicalType`` ...; a sub-dictionary as its braced text).
    text : str
        Its whole dictionary as written, between the braces.
    """

    name: str
    type: str
    n_faces: int
    start_face: int
    in_groups: tuple[str, ...] = ()
    entries: dict[str, str] = field(default_factory=dict, hash=False)
    text: str = ""


@dataclass(eq=False)
class FoamCase:
    """An OpenFOAM mesh as read by :func:`read_foam_case`.

    Attributes
    ----------
    root : Path
        The directory :func:`write_foam_points` copies for ``out_case``: the case
        directory, or the polyMesh directory itself when it is not inside a case.
    mesh_dir : Path
        The polyMesh directory.
    points : ndarray, shape (N, 3), float64
    face_offsets : ndarray, shape (F + 1,), int64
        Face ``i`` is ``face_labels[face_offsets[i]:face_offsets[i + 1]]``.
    face_labels : ndarray, shape (L,), int64
    owner : ndarray, shape (F,), int64
    neighbour : ndarray, shape (F_internal,), int64
    patches : list of FoamPatch
    points_file : Path
        The file the points came from (``points`` or ``points.gz``).
    points_format : FoamFormat
        How it stores them: ``binary``, ``label_bytes``, ``scalar_bytes``,
        ``byte_order``, ``compressed``.
    """

    root: Path
    mesh_dir: Path
    points: np.ndarray
    face_offsets: np.ndarray
    face_labels: np.ndarray
    owner: np.ndarray
    neighbour: np.ndarray
    patches: list[FoamPatch]
    points_file: Path
    points_format: FoamFormat
    points_before: bytes = field(repr=False, default=b"")
    points_after: bytes = field(repr=False, default=b"")

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.owner.size)

    @property
    def n_internal_faces(self) -> int:
        return int(self.neighbour.size)

    @property
    def n_cells(self) -> int:
        """The number of cells: one more than the largest owner or neighbour label."""
        largest = max(self.owner.max(initial=-1), self.neighbour.max(initial=-1))
        return int(largest) + 1

    def face(self, index: int) -> np.ndarray:
        """The point labels of face ``index``, shape (n,)."""
        return self.face_labels[self.face_offsets[index] : self.face_offsets[index + 1]]

    def patch(self, name: str) -> FoamPatch:
        """The patch called ``name``."""
        for patch in self.patches:
            if patch.name == name:
                return patch
        names = ", ".join(repr(p.name) for p in self.patches)
        raise KeyError(f"name: no patch {name!r}; the patches are {names}")

    def to_mesh_data(self) -> MeshData:
        """The mesh as cells and face sets.

        Returns
        -------
        MeshData
            ``points`` (N, 3); ``cells``: blocks ``"tetra"``, ``"pyramid"``,
            ``"wedge"``, ``"hexahedron"`` (those present, in this order) in meshio's
            node order: a hexahedron's bottom quadrilateral 0-3 turns positively about
            the direction to its top 4-7 (4 above 0); a wedge's triangle 0-1-2 likewise
            about the direction to 3-4-5 (meshio's, which is Gmsh's; VTK's own wedge
            lists 0-2-1, and meshio swaps on writing VTK); a pyramid's base 0-3 about the
            direction to its apex 4; a tetrahedron's 0-1-2 about the direction to 3.
            ``cell_data["foam_cell"]``: the OpenFOAM cell number of every row of each
            block. ``face_sets``: one per patch, named after it, its faces as
            ``"triangle"``/``"quad"`` blocks (out of the domain, as OpenFOAM orients
            them); a patch without faces has an empty list. ``groups``: each group of
            the patches' ``inGroups`` with its member patches.

        Raises
        ------
        ValueError
            If a cell is of another shape (a polyhedron; the cell and its faces are
            named) or a patch face has more than four vertices.

        Notes
        -----
        The node order follows from the faces' orientation, which OpenFOAM keeps out of
        the owner; a valid mesh gives cells of positive volume. Inverted cells (of a bad
        morph) stay inverted: use :mod:`torchmorph.mesh.quality` to find them.
        """
        blocks = cell_blocks(
            self.face_offsets, self.face_labels, self.owner, self.neighbour, self.n_cells
        )
        face_sets = {
            patch.name: face_blocks(
                self.face_offsets, self.face_labels, patch.start_face, patch.n_faces, patch.name
            )
            for patch in self.patches
        }
        return MeshData(
            points=self.points.copy(),
            cells=[(kind, connectivity) for kind, connectivity, _ in blocks],
            face_sets=face_sets,
            groups=_groups(self.patches),
            cell_data={"foam_cell": [ids for _, _, ids in blocks]},
        )


def read_foam_case(case: str | os.PathLike) -> FoamCase:
    """Read an OpenFOAM mesh.

    Parameters
    ----------
    case : str or PathLike
        A case directory (holding ``constant/polyMesh``) or a polyMesh directory.

    Returns
    -------
    FoamCase

    Raises
    ------
    ValueError
        If ``case`` holds no mesh, a mesh file is missing (it is named) or malformed
        (the file and what is wrong are named: a truncated list, a list of another size
        than it says, a label that is not one), the files disagree (``owner`` and
        ``faces`` of different lengths, patches beyond the faces or not following each
        other), or a label is out of range.

    Notes
    -----
    ASCII faces may be a ``faceList`` (``4(0 1 2 3)`` entries) or a ``faceCompactList``;
    binary faces must be a ``faceCompactList`` (what OpenFOAM writes). ``#include`` and
    macro expansions (``$name``) in the files are not supported.
    """
    path = Path(case)
    if (path / "constant" / "polyMesh").is_dir():
        mesh_dir = path / "constant" / "polyMesh"
    elif path.is_dir() and any((path / name).exists() for name in ("faces", "faces.gz")):
        mesh_dir = path
    else:
        raise ValueError(
            f"case: {str(path)!r} is neither a case directory with constant/polyMesh nor a "
            "polyMesh directory"
        )
    files = {name: read_foam_file(find_file(mesh_dir, name)) for name in MESH_FILES}
    points, list_start, list_end = read_points(files["points"], files["points"].body_start)
    offsets, labels = read_faces(files["faces"], files["faces"].body_start)
    owner, _ = read_labels(files["owner"], files["owner"].body_start, "owner")
    neighbour, _ = read_labels(files["neighbour"], files["neighbour"].body_start, "neighbour")
    patches = [_patch(files["boundary"], entry) for entry in read_boundary(files["boundary"])]
    check_mesh(files, points.shape[0], offsets, labels, owner, neighbour, patches)
    root = mesh_dir
    if mesh_dir == path / "constant" / "polyMesh":
        root = path
    elif mesh_dir.name == "polyMesh" and (mesh_dir.parent.parent / "system/controlDict").is_file():
        root = mesh_dir.parent.parent
    points_file = files["points"]
    return FoamCase(
        root=root,
        mesh_dir=mesh_dir,
        points=points,
        face_offsets=offsets,
        face_labels=labels,
        owner=owner,
        neighbour=neighbour,
        patches=patches,
        points_file=points_file.path,
        points_format=points_file.format,
        points_before=points_file.data[:list_start],
        points_after=points_file.data[list_end:],
    )


def write_foam_points(
    case: FoamCase, points: np.ndarray | torch.Tensor, out_case: str | os.PathLike | None = None
) -> Path:
    """Write new points into a case, in the format they were read in.

    Parameters
    ----------
    case : FoamCase
        The case as read; it is not changed.
    points : ndarray or Tensor, shape (N, 3)
        The new coordinates of the case's N points (float64 is written exactly in ASCII
        files; binary files keep their scalar size, so a ``scalar=32`` case rounds to
        float32).
    out_case : str or PathLike, optional
        Where to write: ``case.root`` is first copied there (it must not exist, be empty,
        or be ``case.root`` itself). By default the points are replaced in place.

    Returns
    -------
    Path
        The points file written.

    Raises
    ------
    ValueError
        If ``points`` is not (N, 3) or not finite, or ``out_case`` is a non-empty
        directory other than the case, or lies inside the case.

    Notes
    -----
    Only the points file is rewritten (atomically, with its header and trailing text as
    they were, as ``points.gz`` when it was gzipped); ``faces``, ``owner``,
    ``neighbour``, ``boundary`` and every other file stay byte for byte. The case's
    time directories are not touched: fields in ``0/`` still fit the mesh, which has
    the same cells and faces; but a ``polyMesh`` of a moving-mesh run in a time
    directory takes precedence over ``constant/polyMesh`` from that time on. An ASCII
    list is written with 17 significant digits, as OpenFOAM writes it with
    ``writePrecision 17``.
    """
    if not isinstance(case, FoamCase):
        raise TypeError(f"case: expected a FoamCase, got {type(case).__name__}")
    values = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (case.n_points, 3):
        raise ValueError(
            f"points: expected shape ({case.n_points}, 3) for the case's points, got "
            f"{tuple(values.shape)}"
        )
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if bad.size:
        raise ValueError(
            f"points: {bad.size} of the {case.n_points} rows are not finite (the first is row "
            f"{bad[0]})"
        )
    target = case.points_file
    if out_case is not None:
        target = Path(out_case) / case.points_file.relative_to(case.root)
        _copy_case(case.root, Path(out_case))
    content = case.points_before + format_points(values, case.points_format) + case.points_after
    if case.points_format.compressed:
        content = gzip.compress(content, mtime=0)
    with atomic_output(target) as temporary:
        temporary.write_bytes(content)
    return target


@dataclass(eq=False)
class Pseudo2D:
    """A one-cell-thick case with ``empty`` patches front and back, seen in 2-D.

    Attributes
    ----------
    case : FoamCase
    axis : int
        The coordinate axis normal to the empty patches (0, 1, 2 for x, y, z).
    in_plane : tuple of int
        The two other axes, in cyclic order ((x, y) for z, (y, z) for x, (z, x) for y):
        the 2-D mesh's coordinates.
    planes : tuple of float
        The coordinates along ``axis`` of the front plane (the lower) and the back.
    front : ndarray, shape (n,), int64
        The case's points on the front plane, ascending; row i of ``mesh.points``.
    back : ndarray, shape (n,), int64
        Their twins on the back plane (same in-plane coordinates).
    empty_patches : tuple of str
    mesh : MeshData
        The 2-D mesh: ``points`` (n, 2), the front points' in-plane coordinates;
        ``cells``: the front plane's faces as ``"triangle"``/``"quad"`` blocks,
        counter-clockwise in the ``in_plane`` coordinates, with
        ``cell_data["foam_cell"]`` their owner cells; ``face_sets``: every patch that is
        not empty, its faces' front edges as ``"line"`` facets, counter-clockwise
        around the domain (the domain on their left); ``groups`` as in 3-D, less the
        empty patches; ``planar_coordinate``: the front plane's coordinate along
        ``axis`` (the third coordinate after ``in_plane``).
    """

    case: FoamCase
    axis: int
    in_plane: tuple[int, int]
    planes: tuple[float, float]
    front: np.ndarray
    back: np.ndarray
    empty_patches: tuple[str, ...]
    mesh: MeshData

    def lift(self, displacement: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """A displacement of all the case's points from one of the front points.

        Parameters
        ----------
        displacement : ndarray or Tensor, shape (..., n, 2)
            In-plane displacements of ``front`` (the rows of ``mesh.points``).

        Returns
        -------
        ndarray or Tensor, shape (..., N, 3)
            Of the same kind (a tensor of the same dtype and device; an array of a
            floating dtype): both layers move alike (a front point and its twin),
            nothing moves along ``axis``. Differentiable for a tensor.
        """
        n = self.front.size
        if not isinstance(displacement, torch.Tensor):
            displacement = np.asarray(displacement)
        if displacement.ndim < 2 or tuple(displacement.shape[-2:]) != (n, 2):
            raise ValueError(
                f"displacement: expected shape (..., {n}, 2) for the front points, got "
                f"{tuple(displacement.shape)}"
            )
        shape = (*displacement.shape[:-2], self.case.n_points, 3)
        if isinstance(displacement, torch.Tensor):
            lifted = displacement.new_zeros(shape)
            front = torch.as_tensor(self.front, device=displacement.device)
            back = torch.as_tensor(self.back, device=displacement.device)
            for column, axis in enumerate(self.in_plane):
                lifted[..., front, axis] = displacement[..., column]
                lifted[..., back, axis] = displacement[..., column]
            return lifted
        lifted_array = np.zeros(shape, dtype=np.result_type(displacement.dtype, np.float32))
        for column, axis in enumerate(self.in_plane):
            lifted_array[..., self.front, axis] = displacement[..., column]
            lifted_array[..., self.back, axis] = displacement[..., column]
        return lifted_array


def pseudo_2d(case: FoamCase, *, tolerance: float = 1e-6) -> Pseudo2D | None:
    """See a pseudo-2-D case (one cell thick, ``empty`` patches front and back) in 2-D.

    Parameters
    ----------
    case : FoamCase
    tolerance : float, default 1e-6
        Relative to the diagonal of the points' bounding box: how far a point may lie
        off its plane, and a twin off its front point's in-plane position.

    Returns
    -------
    Pseudo2D or None
        None if the case has no ``empty`` patch (or only ones without faces).

    Raises
    ------
    ValueError
        If the empty faces are not normal to a coordinate axis, do not lie on two
        planes, a point lies off both planes or has no twin, or the case is not one
        cell thick (a cell without a front face).
    """
    empty = [p for p in case.patches if p.type == "empty"]
    if not empty:
        return None
    if not (tolerance > 0 and np.isfinite(tolerance)):
        raise ValueError(f"tolerance: must be > 0, got {tolerance}")
    points = case.points
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    gap = tolerance * diagonal
    faces = np.concatenate([_patch_faces(p) for p in empty])
    if faces.size == 0:
        return None
    offsets, labels = case.face_offsets, case.face_labels
    normals = newell_normals(points, offsets, labels, faces)
    # the empty direction as OpenFOAM finds it: the sum of the faces' |area vectors|
    direction = np.abs(normals).sum(axis=0)
    direction = direction / max(float(np.linalg.norm(direction)), np.finfo(float).tiny)
    axis = int(np.argmax(direction))
    in_plane = ((axis + 1) % 3, (axis + 2) % 3)
    if direction[list(in_plane)].max() > 1e-6:
        raise ValueError(
            "case: the empty patches' faces are not normal to a coordinate axis (their mean "
            f"direction is {tuple(float(f'{c:.6g}') for c in direction)})"
        )
    used = np.unique(face_points(offsets, labels, faces))
    low, high = points[used, axis].min(), points[used, axis].max()
    if high - low <= gap:
        raise ValueError("case: the empty patches lie in one plane, not on two (front and back)")
    on_front = np.abs(points[:, axis] - low) <= gap
    on_back = np.abs(points[:, axis] - high) <= gap
    off = np.flatnonzero(~(on_front | on_back))
    if off.size:
        raise ValueError(
            f"case: point {off[0]} lies off both empty planes ({'xyz'[axis]} = {low:g} and "
            f"{high:g}); {off.size} such points: the case is not one cell thick"
        )
    front, back = np.flatnonzero(on_front), np.flatnonzero(on_back)
    back = back[twins(points, front, back, list(in_plane), gap)]
    local = np.full(case.n_points, -1, dtype=np.int64)
    local[front] = np.arange(front.size)
    front_faces = faces[on_front[labels[offsets[faces]]]]
    if front_faces.size != case.n_cells or np.unique(case.owner[front_faces]).size != case.n_cells:
        raise ValueError(
            f"case: {case.n_cells} cells but {front_faces.size} empty faces on the front "
            "plane: the case is not one cell thick"
        )
    flipped = newell_normals(points, offsets, labels, front_faces)[:, axis] < 0
    cells, owners = front_cells(offsets, labels, case.owner, front_faces, flipped, local)
    lines = {
        patch.name: front_lines(offsets, labels, _patch_faces(patch), on_front, local, patch.name)
        for patch in case.patches
        if patch.type != "empty"
    }
    groups = _groups(case.patches, skip={p.name for p in empty})
    mesh = MeshData(
        points=points[front][:, list(in_plane)].copy(),
        cells=cells,
        face_sets=lines,
        groups={group: members for group, members in groups.items() if members},
        cell_data={"foam_cell": owners},
        planar_coordinate=float(low),
    )
    return Pseudo2D(
        case=case,
        axis=axis,
        in_plane=in_plane,
        planes=(float(low), float(high)),
        front=front,
        back=back,
        empty_patches=tuple(p.name for p in empty),
        mesh=mesh,
    )


# -- helpers --------------------------------------------------------------------------


def _patch(file: FoamFile, entry: dict) -> FoamPatch:
    entries = dict(entry["entries"])
    name = entry["name"]
    values = {}
    for key in ("type", "nFaces", "startFace"):
        if key not in entries:
            raise file.fail(f"patch {name!r} has no {key}")
        values[key] = entries.pop(key)
    for key in ("nFaces", "startFace"):
        if not values[key].isdigit():
            raise file.fail(f"patch {name!r}: {key} {values[key]!r} is not a count")
    groups = entries.pop("inGroups", "")
    groups = groups.removeprefix("List<word>").strip().lstrip("0123456789").strip()
    return FoamPatch(
        name=name,
        type=values["type"],
        n_faces=int(values["nFaces"]),
        start_face=int(values["startFace"]),
        in_groups=tuple(groups.strip("()").replace('"', " ").split()),
        entries=entries,
        text=entry["text"],
    )


def _patch_faces(patch: FoamPatch) -> np.ndarray:
    return np.arange(patch.start_face, patch.start_face + patch.n_faces)


def _groups(patches: list[FoamPatch], skip: Container[str] = frozenset()) -> dict[str, list[str]]:
    groups: dict[str, list[str]] = {}
    for patch in patches:
        for group in patch.in_groups:
            members = groups.setdefault(group, [])
            if patch.name not in skip:
                members.append(patch.name)
    return groups


def _copy_case(root: Path, out: Path) -> None:
    if out.exists():
        if out.is_dir() and os.path.samefile(out, root):
            return
        if not out.is_dir() or any(out.iterdir()):
            raise ValueError(f"out_case: {str(out)!r} exists and is not an empty directory")
    resolved, source = out.resolve(), root.resolve()
    if resolved.is_relative_to(source):
        raise ValueError(f"out_case: {str(out)!r} lies inside the case {str(root)!r}")
    shutil.copytree(root, out, symlinks=True, dirs_exist_ok=True)
