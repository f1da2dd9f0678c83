"""Meshing with fTetWild (pytetwild) from a triangulated surface.

The domain's boundary is given as a closed triangle surface (NumPy): the wing
as a ruled surface of profile stations with strip-triangulated end caps; the
tunnel and the hull's box as the box's 12 triangles plus the body's surface
with inward normals (fTetWild keeps the tetrahedra of winding number 1: inside
the box, outside the body). For case B the wing's surface starts below the
wall z = 0, so that the root profile is where the two surfaces intersect.

fTetWild's surface only approximates the input (within the envelope
``epsilon``), so its boundary faces are classified afterwards (box walls by
plane and normal, the wing's end faces by normal, its sides and the hull's by
side) and the nodes are projected onto the exact surfaces by
:mod:`data_gen._surfaces`. Mesh sizes come from a background tetrahedral
sizing field graded away from the body.

Limitations (not in the gmsh meshes): where the body is thinner than the
envelope (within a few centimetres of the hull's stem, stern and keels, and
of the wing's trailing edge) fTetWild's surface cuts the sharp end off; the
projection then only reaches the edge line where that moves a node by less
than half its shortest edge, so the edge node sets can be sparse there
(the hull's "stem" may hold a single node), and a few fluid nodes may lie
inside the exact body's thin end. After the projection, inverted elements are
repaired by moving interior nodes (:func:`data_gen._arrays.untangle`); a mesh
that still fails its checks is made again (up to three times in all).

fTetWild runs through :func:`torchmorph.meshing.tetrahedralize`, the same call
as a user's own surfaces (``torchmorph mesh``). Its output is not reproducible
bit for bit from run to run.
"""

from __future__ import annotations

import sys

import numpy as np

from data_gen._arrays import boundary_faces, orient
from data_gen.geometry import (
    BOX_WALLS,
    CHORD,
    HULL_BOX_BOUNDS,
    HULL_DRAFT,
    HULL_LENGTH,
    SPAN,
    TUNNEL_BOUNDS,
    naca_profile,
    wigley_half_breadth,
)
from torchmorph.meshing import box_surface, tetrahedralize

__all__ = ["mesh_fluid_wing", "mesh_hull", "mesh_wing"]

# the wing's surface for case B starts this far below the wall z = 0 [m]
_ROOT_OVERLAP = 0.25


def _tetrahedralize(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    edge_length: float,
    epsilon: float,
    stop_energy: float,
    iterations: int,
    sizing: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    verbose: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`torchmorph.meshing.tetrahedralize`, one thread; the start and the end (with the
    elapsed time) are printed when ``verbose`` or when stderr is a terminal."""
    return tetrahedralize(
        vertices,
        faces,
        edge_length=edge_length,
        epsilon=epsilon,
        stop_energy=stop_energy,
        iterations=iterations,
        sizing=sizing,
        threads=1,
        progress=verbose or sys.stderr.isatty(),
        verbose=verbose,
    )


# --------------------------------------------------------------------------- input surfaces


def _wing_surface(profile_points: int, span_points: int, z0: float, z1: float):
    """Closed triangulated wing, outward normals. Returns (vertices, faces)."""
    x, y = naca_profile(profile_points)
    n = profile_points
    # ring: leading edge, upper side to the trailing edge, lower side back
    ring = np.concatenate([np.c_[x, y], np.c_[x[-2:0:-1], -y[-2:0:-1]]])
    k = len(ring)
    zs = np.linspace(z0, z1, span_points)
    vertices = np.concatenate([np.c_[ring, np.full(k, z)] for z in zs])
    faces = []
    i = np.arange(k)
    for j in range(span_points - 1):
        a, b = j * k + i, j * k + (i + 1) % k
        faces += [np.c_[a, a + k, b + k], np.c_[a, b + k, b]]
    # end caps: strips between the upper and the lower station at the same x
    upper = np.arange(n)
    lower = np.r_[0, np.arange(k - 1, n - 1, -1), n - 1]
    cap = [[upper[0], upper[1], lower[1]]]
    for s in range(1, n - 2):
        cap += [[upper[s], upper[s + 1], lower[s]], [lower[s], upper[s + 1], lower[s + 1]]]
    cap.append([upper[n - 2], upper[n - 1], lower[n - 2]])
    caps = np.array(cap)
    all_faces = np.concatenate(faces + [caps, caps[:, ::-1] + (span_points - 1) * k])
    return vertices, _outward(vertices, all_faces)


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip all faces if the enclosed signed volume is negative."""
    a, b, c = (vertices[faces[:, m]] for m in range(3))
    volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    return faces if volume > 0 else faces[:, ::-1].copy()


def _box_surface(bounds):
    surface = box_surface(bounds)
    return surface.vertices, surface.faces


def _hull_surface(points_per_side: int):
    """Closed triangulated Wigley double body, outward normals."""
    n = points_per_side
    half_length = HULL_LENGTH / 2.0
    gx, gy = np.meshgrid(
        np.linspace(-half_length, half_length, n),
        np.linspace(-HULL_DRAFT, HULL_DRAFT, n),
        indexing="ij",
    )
    gz = wigley_half_breadth(gx, gy)
    index = np.arange(n * n).reshape(n, n)
    starboard = np.c_[gx.ravel(), gy.ravel(), gz.ravel()]
    interior = np.zeros((n, n), dtype=bool)
    interior[1:-1, 1:-1] = True
    port_index = index.copy()
    port_index[interior] = n * n + np.arange(interior.sum())
    port = starboard[interior.ravel()] * np.array([1.0, 1.0, -1.0])
    vertices = np.concatenate([starboard, port])
    # split each grid cell along the diagonal a-c, unless both its ends are on the
    # rim z = 0 (two corner cells): the triangle would then be flat and shared by both sides
    rim = ~interior
    flat = (rim[:-1, :-1] & rim[1:, 1:]).ravel()
    faces = []
    for grid, flip in ((index, False), (port_index, True)):
        a, b = grid[:-1, :-1].ravel(), grid[1:, :-1].ravel()
        c, d = grid[1:, 1:].ravel(), grid[:-1, 1:].ravel()
        tris = np.concatenate(
            [
                np.c_[a, b, c][~flat],
                np.c_[a, c, d][~flat],
                np.c_[a, b, d][flat],
                np.c_[b, c, d][flat],
            ]
        )
        faces.append(tris[:, ::-1] if flip else tris)
    return vertices, _outward(vertices, np.concatenate(faces))


def _merge(*surfaces):
    vertices, faces, offset = [], [], 0
    for v, f, inward in surfaces:
        vertices.append(v)
        faces.append((f[:, ::-1] if inward else f) + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


# --------------------------------------------------------------------------- sizing field


def _axis_stations(lo: float, hi: float, body_lo: float, body_hi: float, step: float, wall: float):
    """Coordinates on [lo, hi]: the body's span, geometric steps away from it and
    stations within ``wall`` of both ends."""
    stations = [lo, hi, body_lo, body_hi, np.linspace(body_lo, body_hi, 5)]
    offset = step
    while offset < (hi - lo):
        stations.append([body_lo - offset, body_hi + offset])
        offset *= 1.6
    stations.append([lo + wall / 2, lo + wall, hi - wall / 2, hi - wall])
    values = np.concatenate([np.atleast_1d(np.asarray(s, dtype=np.float64)) for s in stations])
    return np.unique(np.clip(values, lo, hi))


def _sizing_field(bounds, body_bounds, distance, params: dict):
    """Background tetrahedral mesh of the box with the target edge length.

    A tensor grid refined geometrically towards the body, each cell split into
    six tetrahedra; the value is the smallest of ``h_far``,
    ``h_body + (h_far - h_body) d_body / grading_body`` (``d_body =
    distance(points)``) and, if ``params`` has ``h_wall``,
    ``h_wall + (h_far - h_wall) d_wall / grading_wall`` with ``d_wall`` the
    distance to the nearest box wall.
    """
    h_body, h_far = params["h_body"], params["h_far"]
    h_wall = params.get("h_wall", h_far)
    grading_wall = params.get("grading_wall", 1.0)
    axes = [
        _axis_stations(
            bounds[0][a],
            bounds[1][a],
            body_bounds[0][a],
            body_bounds[1][a],
            0.5 * h_body,
            grading_wall,
        )
        for a in range(3)
    ]
    nx, ny, nz = (len(a) for a in axes)
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    points = np.c_[gx.ravel(), gy.ravel(), gz.ravel()]
    index = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    corners = [
        index[i : nx - 1 + i, j : ny - 1 + j, k : nz - 1 + k].ravel()
        for k in (0, 1)
        for j in (0, 1)
        for i in (0, 1)
    ]  # corner (i, j, k) of every cell, numbered i + 2j + 4k
    # six tetrahedra along the cell's main diagonal 0-7 (Kuhn subdivision)
    paths = [(1, 3), (1, 5), (2, 3), (2, 6), (4, 5), (4, 6)]
    tets = np.concatenate([np.c_[corners[0], corners[a], corners[b], corners[7]] for a, b in paths])
    tets = orient(points, tets)
    values = np.minimum(
        h_far, h_body + (h_far - h_body) * distance(points) / params["grading_body"]
    )
    wall_distance = np.minimum(points - np.asarray(bounds[0]), np.asarray(bounds[1]) - points)
    wall_size = h_wall + (h_far - h_wall) * wall_distance.min(axis=1) / grading_wall
    values = np.minimum(values, wall_size)
    return points, tets.astype(np.int32), values.astype(np.float64)


# --------------------------------------------------------------------------- classification


def _faces_geometry(points: np.ndarray, tets: np.ndarray):
    faces = boundary_faces(tets)
    a, b, c = (points[faces[:, m]] for m in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return faces, (a + b + c) / 3.0, normal


def _wall_labels(centre, normal, bounds, tolerance) -> np.ndarray:
    labels = np.full(len(centre), "", dtype=object)
    for name, axis, side in BOX_WALLS:
        on_plane = np.abs(centre[:, axis] - bounds[side][axis]) <= tolerance
        labels[on_plane & (np.abs(normal[:, axis]) > 0.7)] = name
    return labels


def _wing_labels(centre, outward, labels, *, with_root: bool) -> None:
    """Label the unlabelled faces of the wing: end faces by normal, sides by centre."""
    free = labels == ""
    end = free & (np.abs(outward[:, 2]) > 0.7)
    if with_root:
        labels[end & (centre[:, 2] < SPAN / 2)] = "root"
        labels[end & (centre[:, 2] >= SPAN / 2)] = "tip"
    else:
        labels[end] = "tip"
    side = free & ~end
    up = np.where(np.abs(centre[:, 1]) > 1e-12, centre[:, 1] > 0, outward[:, 1] > 0)
    labels[side & up] = "upper"
    labels[side & ~up] = "lower"


def _patches(faces: np.ndarray, labels: np.ndarray, names) -> dict[str, np.ndarray]:
    return {name: np.unique(faces[labels == name]) for name in names}


def _wall_tolerance(bounds, epsilon: float) -> float:
    diagonal = float(np.linalg.norm(np.subtract(bounds[1], bounds[0])))
    return 4.0 * epsilon * diagonal


# --------------------------------------------------------------------------- cases


def mesh_wing(params: dict, *, seed: int, verbose: bool):
    """Case A with fTetWild. Returns (points, tets, patches)."""
    del seed  # fTetWild takes no seed
    vertices, faces = _wing_surface(params["profile_points"], params["span_points"], 0.0, SPAN)
    points, tets = _tetrahedralize(
        vertices,
        faces,
        edge_length=params["h_body"],
        epsilon=params["epsilon"],
        stop_energy=params["stop_energy"],
        iterations=params["iterations"],
        sizing=None,
        verbose=verbose,
    )
    faces, centre, outward = _faces_geometry(points, tets)
    labels = np.full(len(faces), "", dtype=object)
    _wing_labels(centre, outward, labels, with_root=True)
    return points, tets, _patches(faces, labels, ("upper", "lower", "root", "tip"))


def _wing_distance(points: np.ndarray) -> np.ndarray:
    dx = np.maximum(0.0, np.maximum(-points[:, 0], points[:, 0] - CHORD))
    dz = np.maximum(0.0, points[:, 2] - SPAN)
    return np.sqrt(dx**2 + points[:, 1] ** 2 + dz**2)


def _mesh_body_in_box(bounds, body, body_bounds, distance, params: dict, verbose: bool):
    """Tetrahedralize the fluid between a box and a closed body, then label the walls.

    Returns points, tets, the boundary faces, their centres and their normals
    (pointing out of the fluid), and a label per face: a wall name, or "" for
    the faces of the body, which the caller names.
    """
    box = _box_surface(bounds)
    vertices, faces = _merge((*box, False), (*body, True))
    sizing = _sizing_field(bounds, body_bounds, distance, params)
    points, tets = _tetrahedralize(
        vertices,
        faces,
        edge_length=params["h_far"],
        epsilon=params["epsilon"],
        stop_energy=params["stop_energy"],
        iterations=params["iterations"],
        sizing=sizing,
        verbose=verbose,
    )
    faces, centre, outward = _faces_geometry(points, tets)
    labels = _wall_labels(centre, outward, bounds, _wall_tolerance(bounds, params["epsilon"]))
    return points, tets, faces, centre, outward, labels


def mesh_fluid_wing(params: dict, *, seed: int, verbose: bool):
    """Case B with fTetWild. Returns (points, tets, patches)."""
    del seed
    wing = _wing_surface(params["profile_points"], params["span_points"], -_ROOT_OVERLAP, SPAN)
    body_bounds = ((0.0, -0.1, 0.0), (CHORD, 0.1, SPAN))
    points, tets, faces, centre, outward, labels = _mesh_body_in_box(
        TUNNEL_BOUNDS, wing, body_bounds, _wing_distance, params, verbose
    )
    _wing_labels(centre, -outward, labels, with_root=False)
    names = ("upper", "lower", "tip") + tuple(name for name, _, _ in BOX_WALLS)
    return points, tets, _patches(faces, labels, names)


def _hull_distance(points: np.ndarray) -> np.ndarray:
    dx = np.maximum(0.0, np.abs(points[:, 0]) - HULL_LENGTH / 2.0)
    dy = np.maximum(0.0, np.abs(points[:, 1]) - HULL_DRAFT)
    return np.sqrt(dx**2 + dy**2 + points[:, 2] ** 2)


def mesh_hull(params: dict, *, seed: int, verbose: bool):
    """Case C with fTetWild. Returns (points, tets, patches)."""
    del seed
    body = _hull_surface(params["hull_points"])
    half = HULL_LENGTH / 2.0
    body_bounds = ((-half, -HULL_DRAFT, -0.2 * HULL_DRAFT), (half, HULL_DRAFT, 0.2 * HULL_DRAFT))
    points, tets, faces, centre, outward, labels = _mesh_body_in_box(
        HULL_BOX_BOUNDS, body, body_bounds, _hull_distance, params, verbose
    )
    free = labels == ""
    starboard = np.where(np.abs(centre[:, 2]) > 1e-12, centre[:, 2] > 0, outward[:, 2] < 0)
    labels[free & starboard] = "starboard"
    labels[free & ~starboard] = "port"
    names = ("starboard", "port") + tuple(name for name, _, _ in BOX_WALLS)
    return points, tets, _patches(faces, labels, names)
