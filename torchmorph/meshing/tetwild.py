"""Tetrahedral meshes from your own closed triangle surfaces (STL, OBJ, PLY, OFF).

The path from a surface file to a :class:`~torchmorph.mesh.TetMesh` that
:class:`~torchmorph.morph.MeshMorph` can morph:

1. :func:`load_surface` reads a triangulated surface (trimesh; OBJ is read
   here so that its ``g``/``o`` groups keep their faces), merges coincident
   vertices and checks that the surface is closed (every edge shared by exactly
   two faces) and consistently oriented; ``repair=True`` lets trimesh remove
   degenerate faces, fix the winding and fill holes first. A surface whose
   normals point inwards is flipped.
2. :func:`mesh_surfaces` optionally places the bodies in a box (the far field
   of a fluid case; :func:`box_surface`), tetrahedralises the domain with
   fTetWild (:func:`tetrahedralize`, through pytetwild), snaps the boundary
   nodes back onto the input surfaces (fTetWild's surface is only within its
   envelope ``epsilon`` of the input) and names the boundary node sets: one per
   input surface, one per face group of a file (OBJ groups, PLY face labels),
   the box walls ``wall_x0`` … ``wall_z1``, and, with ``feature_angle``, the
   sharp edges (``<surface>_edges``) and the smooth patches between them
   (``<surface>_patch<k>``): the kind of sets the paper's ESIDW enriches
   (Ballarin et al. 2017, Algorithm 2 step (ii); the hull's edge in Section 2.3.3).
   Before fTetWild runs, the bodies are checked not to overlap, touch or nest
   (:mod:`torchmorph.meshing.checks`) and the number of tetrahedra is estimated
   and refused above ``max_elements`` (:mod:`torchmorph.meshing.estimate`).

This module is not part of the morphing core (which never imports it). It needs
the ``tetwild`` extra: ``pip install 'torchmorph[tetwild]'`` (pytetwild, which
imports pyvista, and trimesh).

CAD files (STEP ``.step``/``.stp``, IGES ``.iges``/``.igs``, BREP ``.brep``)
take the gmsh path instead (:func:`mesh_cad`, which :func:`mesh_surfaces`
dispatches to by extension; the ``mesh`` extra, ``pip install
'torchmorph[mesh]'``): gmsh's OpenCASCADE kernel imports the solids, cuts them
out of the same far-field box, and meshes the exact CAD geometry (boundary
nodes lie on it, no snapping); the node sets are named the same way, with one
set per CAD face (``<surface>_face<k>``) and the nodes on the curves between
faces (``<surface>_edges``).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

from torchmorph.mesh.quality import quality_report
from torchmorph.meshing import snapping
from torchmorph.meshing.cad import ALGORITHM_3D, _mesh_cad, is_cad_input
from torchmorph.meshing.checks import (
    TOUCH_TOLERANCE,
    Progress,
    check_body_contacts,
    check_max_elements,
    check_size,
    check_threads,
    far_offset,
)
from torchmorph.meshing.estimate import (
    _INVERSE_REGULAR,
    MAX_ELEMENTS,
    TETS_PER_REGULAR,
    TetEstimate,
    check_budget,
    estimate_tets,
)
from torchmorph.meshing.surfaces import (
    _EXTRA,
    Surface,
    _closest_on_segments,
    box_bounds,
    box_surface,
    closest_points,
    feature_edges,
    load_surface,
)

if TYPE_CHECKING:
    from torchmorph.mesh import TetMesh

__all__ = ["mesh_surfaces", "tetrahedralize"]

# --------------------------------------------------------------------------- fTetWild


class _TetWildOptions(TypedDict, total=False):
    """The keyword arguments given to ``pytetwild.tetrahedralize``."""

    edge_length_abs: float
    epsilon: float
    stop_energy: float
    num_opt_iter: int
    num_threads: int
    quiet: bool
    bg_vertices: np.ndarray
    bg_tets: np.ndarray
    bg_values: np.ndarray


@contextlib.contextmanager
def _scratch_directory() -> Iterator[None]:
    """fTetWild writes a scratch file into the working directory: run in a temporary one."""
    previous = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="torchmorph-tetwild-") as directory:
        os.chdir(directory)
        try:
            yield
        finally:
            os.chdir(previous)


def tetrahedralize(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    edge_length: float,
    epsilon: float = 1e-3,
    stop_energy: float = 10.0,
    iterations: int = 80,
    sizing: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    threads: int | None = None,
    max_elements: int | None = MAX_ELEMENTS,
    progress: bool = False,
    verbose: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedralise the inside of a closed triangle surface with fTetWild.

    Parameters
    ----------
    vertices : array, shape (V, 3)
    faces : int array, shape (F, 3)
        The domain's boundary: fTetWild keeps the tetrahedra of winding number
        1, so an outer wall has outward normals and a body inside it inward ones.
    edge_length : float
        Target edge length (absolute), at most the surface's largest extent
        (fTetWild cannot honour more and then runs for minutes); ``sizing``
        overrides it where smaller.
    epsilon : float, default 1e-3
        Envelope: the mesh's surface lies within ``epsilon`` times the
        bounding-box diagonal of the input. Smaller follows the input more
        closely (and is slower).
    stop_energy : float, default 10
        fTetWild stops optimising once the worst element's AMIPS energy is
        below this (3 is a perfect tetrahedron); smaller gives better elements
        and takes longer.
    iterations : int, default 80
        At most this many optimisation passes.
    sizing : (points (P, 3), tets (T, 4), values (P,)), optional
        Background mesh with the target edge length at its nodes.
    threads : int, optional
        fTetWild's threads, >= 1 (default 1; with more its output varies run to run).
    max_elements : int or None, default :data:`MAX_ELEMENTS`
        Refuse when the estimated number of tetrahedra is larger (the volume over
        a regular tetrahedron's of ``edge_length``; with ``sizing``, integrated
        over the background mesh); None: no limit.
    progress : bool, default False
        Print a line on stderr before and after (with the elapsed time):
        fTetWild holds the interpreter while it runs, so no bar can move.
    verbose : bool, default False
        fTetWild's own log.

    Returns
    -------
    points : array, shape (N, 3)
    tets : int array, shape (M, 4), positively oriented

    Raises
    ------
    ValueError
        For a bad argument (named in the message) or an estimate above ``max_elements``.

    Notes
    -----
    A surface far from the origin (farther than its bounding box's diagonal; fTetWild
    stalls on a body at 1e7) is meshed about its centre and moved back.
    """
    try:
        import pytetwild  # imports pyvista
    except ImportError as error:
        raise ImportError(
            f"tetrahedralising needs pytetwild (which imports pyvista): {_EXTRA}"
        ) from error
    vertices = np.asarray(vertices, dtype=np.float64)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    edge_length = check_size("edge_length", edge_length, extent=float((high - low).max()))
    epsilon, stop_energy = check_size("epsilon", epsilon), check_size("stop_energy", stop_energy)
    if not (isinstance(iterations, (int, np.integer)) and iterations >= 0):
        raise ValueError(f"iterations must be an integer >= 0, got {iterations!r}")
    threads, max_elements = check_threads(threads), check_max_elements(max_elements)
    estimate = _estimate(vertices, faces, edge_length, sizing)
    check_budget(estimate, max_elements)
    offset = far_offset(low, high)
    vertices = vertices - offset
    options: _TetWildOptions = {
        "edge_length_abs": float(edge_length),
        "epsilon": float(epsilon),
        "stop_energy": float(stop_energy),
        "num_opt_iter": int(iterations),
        "num_threads": int(threads),
        "quiet": not verbose,
    }
    if sizing is not None:
        options["bg_vertices"] = np.ascontiguousarray(
            np.asarray(sizing[0]) - offset, dtype=np.float64
        )
        options["bg_tets"] = np.ascontiguousarray(sizing[1], dtype=np.int32)
        options["bg_values"] = np.ascontiguousarray(sizing[2], dtype=np.float64)
    if progress:
        print(
            f"fTetWild: meshing {len(faces)} surface triangles (edge length {edge_length:.3g}"
            f"{', graded' if sizing is not None else ''}, epsilon {epsilon:g}, stop energy "
            f"{stop_energy:g}; about {estimate.total:,.0f} tetrahedra estimated); this can "
            "take a minute ...",
            file=sys.stderr,
            flush=True,
        )
    start = time.perf_counter()
    with _scratch_directory():
        points, tets = pytetwild.tetrahedralize(
            np.ascontiguousarray(vertices, dtype=np.float64),
            np.ascontiguousarray(faces, dtype=np.int32),
            **options,
        )
    points = np.asarray(points, dtype=np.float64) + offset
    tets = np.asarray(tets, dtype=np.int64)
    if progress:
        print(
            f"fTetWild: {len(points)} nodes, {len(tets)} tetrahedra in "
            f"{time.perf_counter() - start:.1f} s",
            file=sys.stderr,
            flush=True,
        )
    if len(tets) == 0:
        raise RuntimeError(
            "fTetWild returned an empty mesh (is the surface closed and does it enclose a volume?)"
        )
    return points, snapping.orient(points, tets)


def _estimate(vertices, faces, edge_length, sizing) -> TetEstimate:
    """The tetrahedra :func:`tetrahedralize` would make: the enclosed volume at
    ``edge_length``, or with ``sizing`` the integral over its background mesh."""
    a, b, c = (vertices[np.asarray(faces)[:, k]] for k in range(3))
    volume = abs(float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0))
    uniform = TETS_PER_REGULAR["ftetwild"] * _INVERSE_REGULAR * volume / edge_length**3
    if sizing is None:
        return TetEstimate(uniform, uniform, volume, {"edge_length": edge_length})
    points, tets, values = (np.asarray(item, dtype=np.float64) for item in sizing)
    tets = tets.astype(np.int64)
    h = np.minimum(values, edge_length)
    corners = points[tets]
    volumes = (
        np.abs(
            np.einsum(
                "ij,ij->i",
                corners[:, 1] - corners[:, 0],
                np.cross(corners[:, 2] - corners[:, 0], corners[:, 3] - corners[:, 0]),
            )
        )
        / 6.0
    )
    density = (_INVERSE_REGULAR / h[tets] ** 3).mean(axis=1)
    total = TETS_PER_REGULAR["ftetwild"] * float(
        volumes @ density
    )  # holes included: an upper bound
    return TetEstimate(total, total, volume, {"sizing": float(h.min())})


def _sizing_field(
    bounds: np.ndarray,
    bodies: Sequence[Surface],
    far: float,
    near: float,
    grading: float,
    cells: int = 24,
):
    """A Kuhn-split grid over ``bounds``: ``min(far, near + (far - near) d / grading)``."""
    axes = [np.linspace(bounds[0, k], bounds[1, k], cells + 1) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    n = cells + 1
    index = np.arange(n**3).reshape(n, n, n)
    corner = [
        index[i : n - 1 + i, j : n - 1 + j, k : n - 1 + k].ravel()
        for k in (0, 1)
        for j in (0, 1)
        for i in (0, 1)
    ]
    paths = [(1, 3), (1, 5), (2, 3), (2, 6), (4, 5), (4, 6)]
    tets = np.concatenate([np.c_[corner[0], corner[a], corner[b], corner[7]] for a, b in paths])
    vertices, faces = _merge([(body, False) for body in bodies])
    distance = closest_points(grid, vertices, faces)[2]
    values = np.minimum(far, near + (far - near) * distance / grading)
    return grid, snapping.orient(grid, tets).astype(np.int32), values


def _merge(surfaces: Sequence[tuple[Surface, bool]]) -> tuple[np.ndarray, np.ndarray]:
    """One vertex/face array of several surfaces, each flipped when its flag is set."""
    vertices, faces, offset = [], [], 0
    for surface, flip in surfaces:
        vertices.append(surface.vertices)
        faces.append((surface.faces[:, ::-1] if flip else surface.faces) + offset)
        offset += len(surface.vertices)
    return np.concatenate(vertices), np.concatenate(faces)


# --------------------------------------------------------------------------- the mesh


def _as_surfaces(surfaces: Any, repair: bool) -> list[Surface]:
    if isinstance(surfaces, (str, os.PathLike, Surface)):
        surfaces = [surfaces]
    if isinstance(surfaces, Mapping):
        items = [(name, item) for name, item in surfaces.items()]
    else:
        items = [(None, item) for item in surfaces]
    if not items:
        raise ValueError("surfaces: give at least one surface")
    result = []
    for name, item in items:
        if isinstance(item, Surface):
            result.append(
                item if name is None else Surface(item.vertices, item.faces, name, item.groups)
            )
        else:
            result.append(load_surface(item, name=name, repair=repair))
    names = [surface.name for surface in result]
    for duplicate in {n for n in names if names.count(n) > 1}:
        raise ValueError(
            f"surfaces: two surfaces are named {duplicate!r}; name them "
            "(a mapping name -> file, or NAME=FILE on the command line)"
        )
    return result


def _contains(outer: Surface, inner: Surface) -> bool:
    return bool(
        (outer.bounds[0] < inner.bounds[0]).all() and (inner.bounds[1] < outer.bounds[1]).all()
    )


def mesh_surfaces(
    surfaces: Any,
    *,
    box: float | Sequence[float] | None = None,
    bounds: Any = None,
    edge_length: float | None = None,
    body_edge_length: float | None = None,
    grading: float | None = None,
    epsilon: float = 1e-3,
    stop_energy: float = 10.0,
    iterations: int = 80,
    feature_angle: float | None = None,
    snap: bool = True,
    repair: bool = False,
    threads: int | None = None,
    max_elements: int | None = MAX_ELEMENTS,
    progress: bool = False,
    name: str | None = None,
) -> TetMesh:
    """A tetrahedral mesh of the volume bounded by closed surfaces, with named node sets.

    Parameters
    ----------
    surfaces : path, Surface, sequence of them, or mapping name -> path or Surface
        Without ``box``/``bounds``: one surface is meshed inside; with several,
        one whose bounding box contains all the others is the outer wall and
        the others are holes in it (bodies in a tunnel), otherwise each is
        meshed as a solid. With ``box``/``bounds`` every surface is a body
        in the box, strictly inside it (a body touching a wall, e.g. a half
        model on a symmetry plane, is refused). Bodies must not overlap or
        touch, and a body may lie inside another only as a hole in the outer
        wall above. CAD files (:data:`CAD_FORMATS`: STEP, IGES, BREP) go to
        :func:`mesh_cad` (gmsh on the exact CAD geometry; ``edge_length``,
        ``body_edge_length`` and ``grading`` are its sizes, the fTetWild and
        snapping options do not apply); CAD and triangle files cannot be mixed.
    box : float or 6 floats, optional
        Place the bodies in an axis-aligned box padded by this multiple of
        their largest extent on every side, or per side ``(x0, x1, y0, y1,
        z0, z1)`` (a tunnel: e.g. ``(2, 6, 2, 2, 2, 2)``).
    bounds : array, shape (2, 3), optional
        The box's corners instead of ``box``.
    edge_length : float, optional
        Target edge length (default: the domain's bounding-box diagonal / 20);
        at most the domain's largest extent.
    body_edge_length, grading : float, optional
        Edge length on the bodies (at most their largest extent), growing
        linearly with the distance from them to ``edge_length`` over
        ``grading`` (default: the bodies' largest extent); needs a box (a
        background sizing field).
    epsilon, stop_energy, iterations, threads
        fTetWild's envelope, optimisation target and passes, threads (an
        int >= 1, default 1; :func:`tetrahedralize`). For CAD files
        ``threads`` are gmsh's.
    max_elements : int or None, default :data:`MAX_ELEMENTS`
        Refuse, before meshing, when the estimated number of tetrahedra
        (:func:`~torchmorph.meshing.estimate.estimate_tets`) is larger; the
        message names the size to raise. None: no limit.
    feature_angle : float, optional
        Degrees: add the sets ``<surface>_edges`` (boundary nodes placed on
        the sharp edges of the surface, dihedral angle above this) and
        ``<surface>_patch<k>`` (the smooth patches between them, largest
        first; nodes on a sharp edge are in both patches).
    snap : bool, default True
        Move boundary nodes onto the input surfaces (onto a sharp edge those
        within ``3 epsilon`` times the diagonal and half their shortest edge of
        it); a move is shortened where it would invert a tetrahedron.
    repair : bool, default False
        Passed to :func:`load_surface` for files.
    progress : bool, default False
        Print the estimate, the meshing steps with elapsed times and the
        quality on stderr.
    name : str, optional
        The mesh's name (default: the first surface's).

    Returns
    -------
    TetMesh
        Node sets: one per surface (by name), one per face group (by its name;
        ``<surface>_<group>`` where names would clash), with a box its whole
        surface ``far_field`` and its walls ``wall_x0`` … ``wall_z1``, and the
        feature sets. Empty sets are left out. A boundary node
        belongs to every set whose faces it lies on (within 1e-9 of the
        domain's size of the nearest).

    Raises
    ------
    ValueError
        For a bad surface or argument (named in the message); bodies that
        overlap, touch or nest (see above); an estimate above ``max_elements``;
        when the mesh has inverted tetrahedra after snapping (not expected).
    ImportError
        Without the ``tetwild`` extra.

    Notes
    -----
    Surfaces far from the origin (farther than their bounding box's diagonal)
    are meshed about their centre and moved back: fTetWild stalls on a body at
    1e7. Touching is found where a vertex of one body lies on the other; bodies
    touching only along edges are not detected.
    """
    from torchmorph.mesh import TetMesh

    if is_cad_input(surfaces):
        if feature_angle is not None or repair:
            raise ValueError(
                "feature_angle and repair are for triangle surfaces: a CAD file's faces and "
                "curves are node sets already"
            )
        return _mesh_cad(
            surfaces,
            box=box,
            bounds=bounds,
            sizes=(edge_length, body_edge_length, grading),
            labels=("edge_length", "body_edge_length", "grading"),
            algorithm=ALGORITHM_3D,
            optimize="",
            seed=0,
            threads=threads,
            max_elements=max_elements,
            progress=progress,
            name=name,
        )
    report = Progress(progress)
    sizes = ("edge_length", "body_edge_length", "grading")
    for label, value in zip(sizes, (edge_length, body_edge_length, grading), strict=True):
        check_size(label, value)
    threads, max_elements = check_threads(threads), check_max_elements(max_elements)
    bodies = _as_surfaces(surfaces, repair)
    if box is not None and bounds is not None:
        raise ValueError("box and bounds: give one of them, not both")
    if (body_edge_length is not None or grading is not None) and box is None and bounds is None:
        raise ValueError("body_edge_length and grading need a far field: give box or bounds")
    low = np.min([b.bounds[0] for b in bodies], axis=0)
    high = np.max([b.bounds[1] for b in bodies], axis=0)
    offset = far_offset(low, high)
    if offset.any():  # mesh about the origin, move back at the end
        bodies = [Surface(b.vertices - offset, b.faces, b.name, b.groups) for b in bodies]
        low, high = low - offset, high - offset
        report(f"surfaces: meshed about their centre {offset.tolist()} and moved back")
    walls = None
    if box is not None:
        walls = box_surface(box_bounds(bodies, box))
    elif bounds is not None:
        walls = box_surface(np.asarray(bounds, dtype=np.float64) - offset)
    if walls is not None:
        if any(body.name == walls.name for body in bodies):
            raise ValueError(
                f"surfaces: the name {walls.name!r} is the box's; name the surface otherwise"
            )
        for body in bodies:
            if not _contains(walls, body):
                raise ValueError(
                    f"bounds: the box {(walls.bounds + offset).tolist()} does not contain "
                    f"surface {body.name!r} (bounds {(body.bounds + offset).tolist()}); "
                    "bodies must lie strictly inside the box, not touching its walls"
                )
        boundary = [(walls, False)] + [(body, True) for body in bodies]
        container = None
    else:
        outer = [s for s in bodies if all(_contains(s, o) for o in bodies if o is not s)]
        container = outer[0] if len(bodies) > 1 and outer else None
        boundary = [(s, container is not None and s is not container) for s in bodies]
    if feature_angle is not None and not 0 < feature_angle < 180:
        raise ValueError(f"feature_angle must be in (0, 180) degrees, got {feature_angle!r}")
    if len(bodies) > 1:
        report("surfaces: checking that the bodies do not overlap or touch")
        check_body_contacts(bodies, container, TOUCH_TOLERANCE * np.linalg.norm(high - low))
    all_surfaces = [surface for surface, _ in boundary]
    vertices, faces = _merge(boundary)
    extent = np.ptp(vertices, axis=0)
    diagonal = float(np.linalg.norm(extent))
    edge_length = check_size("edge_length", edge_length, extent=float(extent.max()))
    edge_length = edge_length or diagonal / 20.0
    body_extent = float((high - low).max())
    check_size("body_edge_length", body_edge_length, extent=body_extent, what="the bodies'")
    volume = Surface(vertices, faces).volume
    sizing = None
    if body_edge_length is not None:
        assert walls is not None  # body_edge_length needs box or bounds (checked above)
        grading = grading if grading is not None else body_extent
        body_vertices, body_faces = _merge([(body, False) for body in bodies])
        a, b, c = (body_vertices[body_faces[:, k]] for k in range(3))
        estimate = estimate_tets(
            volume=volume,
            size=edge_length,
            body_size=body_edge_length,
            grading=grading,
            bounds=walls.bounds,
            body_vertices=body_vertices,
            body_faces=body_faces,
            body_area=0.5 * float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()),
            mesher="ftetwild",
        )
    else:
        estimate = estimate_tets(volume=volume, size=edge_length, mesher="ftetwild")
    limit = "no limit" if max_elements is None else f"max_elements {max_elements:,}"
    report(f"estimate: about {estimate.total:,.0f} tetrahedra ({limit})")
    check_budget(estimate, max_elements)
    if body_edge_length is not None:
        assert walls is not None and grading is not None  # as for the estimate above
        sizing = _sizing_field(walls.bounds, bodies, edge_length, body_edge_length, grading)

    points, tets = tetrahedralize(
        vertices,
        faces,
        edge_length=edge_length,
        epsilon=epsilon,
        stop_energy=stop_energy,
        iterations=iterations,
        sizing=sizing,
        threads=threads,
        max_elements=None,  # estimated above
        progress=progress,
    )
    boundary_nodes = snapping.boundary_nodes(tets)
    tolerance = 1e-9 * diagonal
    unsnapped = 0
    features = {}
    if feature_angle is not None:
        for surface in bodies:
            features[surface.name] = feature_edges(surface, feature_angle)
    if snap:
        shortest = snapping.edge_lengths_at_nodes(points, tets)
        target = closest_points(points[boundary_nodes], vertices, faces)[0]
        for surface in bodies:
            edges = features.get(surface.name, (np.zeros((0, 2), np.int64), []))[0]
            if len(edges):
                on_edge, distance = _closest_on_segments(
                    points[boundary_nodes],
                    surface.vertices[edges[:, 0]],
                    surface.vertices[edges[:, 1]],
                )
                # fTetWild keeps a crease within its envelope: nodes that close to a sharp
                # edge (and closer than half their shortest edge) belong on it
                reach = np.minimum(0.5 * shortest[boundary_nodes], 3.0 * epsilon * diagonal)
                near = distance < reach
                target[near] = on_edge[near]
        points, unsnapped = snapping.snap(points, tets, boundary_nodes, target)

    node_sets: dict[str, np.ndarray] = {}
    query = points[boundary_nodes]
    nearest = closest_points(query, vertices, faces)[2] + tolerance

    def on(surface_vertices, surface_faces) -> np.ndarray:
        distance = closest_points(query, surface_vertices, surface_faces)[2]
        return boundary_nodes[distance <= nearest]

    group_owner: dict[str, str] = {}
    for surface in all_surfaces:
        node_sets[surface.name] = on(surface.vertices, surface.faces)
        for group in surface.groups:
            group_owner.setdefault(group, surface.name)
    for surface in all_surfaces:
        for group, ids in surface.groups.items():
            clash = group in node_sets or group_owner[group] != surface.name
            key = f"{surface.name}_{group}" if clash else group
            node_sets[key] = on(surface.vertices, surface.faces[ids])
    for surface_name, (edges, patches) in features.items():
        surface = next(s for s in bodies if s.name == surface_name)
        if len(edges):
            _, distance = _closest_on_segments(
                query, surface.vertices[edges[:, 0]], surface.vertices[edges[:, 1]]
            )
            node_sets[f"{surface_name}_edges"] = boundary_nodes[distance <= tolerance]
        for k, patch in enumerate(patches):
            node_sets[f"{surface_name}_patch{k}"] = on(surface.vertices, surface.faces[patch])
    node_sets = {key: ids for key, ids in node_sets.items() if ids.size}

    inverted = int((snapping.signed_volumes(points, tets) <= 0).sum())
    if inverted:
        raise ValueError(
            f"the mesh has {inverted} inverted tetrahedra after snapping; try "
            "snap=False or a smaller epsilon"
        )
    mesh = TetMesh(points + offset, tets, node_sets, name=name or bodies[0].name)
    if progress:
        quality = quality_report(mesh)
        snapped = (
            f"; {unsnapped} boundary node(s) kept off the surface to keep tetrahedra valid"
            if unsnapped
            else ""
        )
        report(f"mesh: {mesh.num_nodes} nodes, {mesh.num_tets} tetrahedra, {quality}{snapped}")
    return mesh
