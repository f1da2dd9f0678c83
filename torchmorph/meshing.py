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

This module is not part of the morphing core (which never imports it). It needs
the ``tetwild`` extra: ``pip install 'torchmorph[tetwild]'`` (pytetwild, which
imports pyvista, and trimesh). For surfaces that come from CAD, gmsh on the CAD
model gives exact boundaries; this path is for triangle surfaces.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from torchmorph.mesh import TetMesh

__all__ = [
    "SURFACE_FORMATS",
    "WALL_NAMES",
    "Surface",
    "box_surface",
    "closest_points",
    "feature_edges",
    "load_surface",
    "mesh_surfaces",
    "quality_report",
    "surface_problems",
    "tetrahedralize",
]

#: File extensions :func:`load_surface` reads.
SURFACE_FORMATS = (".stl", ".obj", ".ply", ".off")
#: Node-set names of the box walls (the face of the box at the low / high end of x, y, z).
WALL_NAMES = ("wall_x0", "wall_x1", "wall_y0", "wall_y1", "wall_z0", "wall_z1")
#: PLY face properties read as face labels (the first one present is used).
PLY_LABELS = ("label", "labels", "group", "region", "patch", "tag", "marker")

_EXTRA = "pip install 'torchmorph[tetwild]'"


# --------------------------------------------------------------------------- surfaces


@dataclass(frozen=True, eq=False)
class Surface:
    """A closed triangle surface with named face groups.

    Parameters
    ----------
    vertices : array, shape (V, 3)
        Vertex coordinates (stored as float64).
    faces : int array, shape (F, 3)
        Vertex indices of the triangles; outward normals for a body
        (counter-clockwise seen from outside).
    name : str
        The surface's name: the node set of its boundary nodes.
    groups : mapping of str to int array
        Named face groups (face indices), e.g. the OBJ file's groups.

    Raises
    ------
    ValueError
        For arrays of the wrong shape, non-finite vertices, face indices out
        of range, an empty name, or group face indices out of range.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = "surface"
    groups: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        vertices = np.asarray(self.vertices, dtype=np.float64)
        faces = np.asarray(self.faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
            raise ValueError(f"vertices must have shape (V, 3) with V > 0, got {vertices.shape}")
        if not np.isfinite(vertices).all():
            raise ValueError("vertices hold NaN or infinite values")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or faces.dtype.kind not in "iu":
            raise ValueError(
                f"faces must be integers of shape (F, 3) with F > 0, got {faces.dtype} {faces.shape}"
            )
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"faces index vertices outside [0, {len(vertices)})")
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        groups = {}
        for group, ids in self.groups.items():
            ids = np.unique(np.asarray(ids, dtype=np.int64).reshape(-1))
            if ids.size and (ids[0] < 0 or ids[-1] >= len(faces)):
                raise ValueError(f"group {group!r} holds face indices outside [0, {len(faces)})")
            groups[str(group)] = ids
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces.astype(np.int64))
        object.__setattr__(self, "groups", groups)

    @property
    def bounds(self) -> np.ndarray:
        """``[[x0, y0, z0], [x1, y1, z1]]`` of the vertices used by the faces."""
        used = self.vertices[np.unique(self.faces)]
        return np.stack([used.min(0), used.max(0)])

    @property
    def volume(self) -> float:
        """Enclosed signed volume (> 0 for outward normals)."""
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)

    def flipped(self) -> Surface:
        """The same surface with every face's orientation reversed."""
        return Surface(self.vertices, self.faces[:, ::-1], self.name, self.groups)


def surface_problems(vertices: np.ndarray, faces: np.ndarray) -> list[str]:
    """What keeps a triangle surface from bounding a volume; empty when it is closed.

    Checks that every edge is shared by exactly two faces (watertight,
    manifold), that the two faces of each edge traverse it in opposite
    directions (consistent orientation) and that no face has zero area.
    Vertices are compared by index: merge coincident vertices first.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    problems = []
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    if (counts == 1).any():
        problems.append(f"{int((counts == 1).sum())} edge(s) belong to one face only (holes, "
                        f"e.g. the edge between vertices {tuple(int(v) for v in undirected[counts == 1][0])})")
    if (counts > 2).any():
        problems.append(f"{int((counts > 2).sum())} edge(s) are shared by more than two faces "
                        "(non-manifold)")
    _, directed_counts = np.unique(directed, axis=0, return_counts=True)
    if (directed_counts > 1).any():
        problems.append(f"{int((directed_counts > 1).sum())} edge(s) are traversed in the same "
                        "direction by two faces (inconsistent orientation)")
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    scale = float(np.ptp(vertices, axis=0).max()) or 1.0
    degenerate = area2 <= 1e-14 * scale**2
    if degenerate.any():
        problems.append(f"{int(degenerate.sum())} face(s) have zero area (e.g. face "
                        f"{int(np.flatnonzero(degenerate)[0])})")
    return problems


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Vertices, triangles (polygons fanned) and ``g``/``o`` groups of a Wavefront OBJ file."""
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    groups: dict[str, list[int]] = {}
    current: str | None = None
    with path.open("r", encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                if parts[0] == "v":
                    vertices.append([float(x) for x in parts[1:4]])
                elif parts[0] in ("g", "o"):
                    current = " ".join(parts[1:]) or None
                elif parts[0] == "f":
                    ids = []
                    for item in parts[1:]:
                        index = int(item.split("/")[0])
                        ids.append(index - 1 if index > 0 else len(vertices) + index)
                    if len(ids) < 3:
                        raise ValueError("a face needs three vertices")
                    for k in range(1, len(ids) - 1):
                        if current is not None:
                            groups.setdefault(current, []).append(len(faces))
                        faces.append([ids[0], ids[k], ids[k + 1]])
            except (ValueError, IndexError) as error:
                raise ValueError(f"line {number}: {line.strip()!r}: {error}") from None
    if not faces:
        raise ValueError("no faces")
    return (np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
            {name: np.asarray(ids) for name, ids in groups.items()})


def _read_with_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    try:
        import trimesh
    except ImportError as error:
        raise ImportError(f"reading {path.suffix} surfaces needs trimesh: {_EXTRA}") from error
    loaded = trimesh.load(str(path), process=False, force="mesh")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    groups: dict[str, np.ndarray] = {}
    raw = loaded.metadata.get("_ply_raw", {}).get("face", {}).get("data", {})
    for prop in PLY_LABELS:
        if prop in raw:
            labels = np.asarray(raw[prop]).reshape(len(faces), -1)[:, 0]
            for value in np.unique(labels):
                groups[f"{prop}{value}"] = np.flatnonzero(labels == value)
            break
    return vertices, faces, groups


def _merge_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge exactly coincident vertices (an STL file repeats them per face); drop unused ones."""
    used = np.unique(faces)
    unique, inverse = np.unique(vertices[used], axis=0, return_inverse=True)
    remap = np.zeros(len(vertices), dtype=np.int64)
    remap[used] = inverse.reshape(-1)
    return unique, remap[faces]


def _repair(vertices, faces, labels):
    """trimesh's repairs: degenerate faces removed, winding fixed, holes filled."""
    try:
        import trimesh
    except ImportError as error:
        raise ImportError(f"repair=True needs trimesh: {_EXTRA}") from error
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    keep = mesh.nondegenerate_faces()
    mesh.update_faces(keep)
    labels = labels[keep]
    mesh.remove_unreferenced_vertices()
    trimesh.repair.fix_winding(mesh)
    count = len(mesh.faces)
    trimesh.repair.fill_holes(mesh)  # appends the new faces
    labels = np.concatenate([labels, np.full(len(mesh.faces) - count, -1)])
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, np.int64), labels


def load_surface(path: str | os.PathLike, *, name: str | None = None,
                 repair: bool = False) -> Surface:
    """Read a closed triangle surface and check that it bounds a volume.

    Parameters
    ----------
    path : str or path
        ``.stl``, ``.obj``, ``.ply`` or ``.off`` file. OBJ groups (``g`` or
        ``o``) and PLY integer face properties named ``label`` (or ``group``,
        ``region``, ``patch``, ``tag``, ``marker``; groups ``label0``,
        ``label1`` …) become face groups.
    name : str, optional
        The surface's name (default: the file name without extension).
    repair : bool, default False
        Let trimesh remove zero-area faces, make the winding consistent and
        fill holes before the checks (faces it adds belong to no group).

    Returns
    -------
    Surface
        Coincident vertices merged, normals outward (a surface whose enclosed
        volume is negative is flipped as a whole).

    Raises
    ------
    FileNotFoundError
        If ``path`` is not a file.
    ValueError
        For an unsupported extension, an unreadable file, or a surface that is
        not closed and consistently oriented (the message says what is wrong:
        holes, non-manifold or inconsistently oriented edges, zero-area faces).
    ImportError
        If trimesh is needed (STL, PLY, OFF, ``repair``) and not installed.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SURFACE_FORMATS:
        raise ValueError(f"path: unsupported surface file extension {suffix or '(none)'!r} in "
                         f"{str(path)!r}; supported: {', '.join(SURFACE_FORMATS)}")
    if not path.is_file():
        raise FileNotFoundError(f"path: surface file {str(path)!r} does not exist")
    try:
        if suffix == ".obj":
            vertices, faces, groups = _read_obj(path)
        else:
            vertices, faces, groups = _read_with_trimesh(path)
    except ImportError:
        raise
    except Exception as error:  # parsers raise anything on a corrupt file
        raise ValueError(f"path: could not read surface file {str(path)!r}: "
                         f"{type(error).__name__}: {error}") from error
    if len(faces) == 0:
        raise ValueError(f"path: surface file {str(path)!r} holds no triangles")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"path: surface file {str(path)!r} has faces that index missing vertices")
    vertices, faces = _merge_vertices(vertices, faces)
    labels = np.full(len(faces), -1, dtype=np.int64)
    group_names = list(groups)
    for index, group in enumerate(group_names):
        labels[groups[group]] = index
    if repair:
        vertices, faces, labels = _repair(vertices, faces, labels)
    problems = surface_problems(vertices, faces)
    if problems:
        hint = ("trimesh's repairs could not fix it; fix the file in a mesh editor" if repair
                else "pass repair=True (torchmorph mesh --repair) to let trimesh try to fix it, "
                     "or fix the file in a mesh editor")
        raise ValueError(f"path: surface {str(path)!r} is not a closed, consistently oriented "
                         f"surface: {'; '.join(problems)}; {hint}")
    groups = {group: np.flatnonzero(labels == index) for index, group in enumerate(group_names)}
    surface = Surface(vertices, faces, name or path.stem, {k: v for k, v in groups.items() if v.size})
    return surface if surface.volume > 0 else surface.flipped()


def box_surface(bounds: Any, name: str = "far_field") -> Surface:
    """The 12 triangles of an axis-aligned box, outward, with one group per wall.

    Parameters
    ----------
    bounds : array, shape (2, 3)
        ``[[x0, y0, z0], [x1, y1, z1]]`` with ``x0 < x1`` etc.
    name : str
        The surface's name.

    Returns
    -------
    Surface
        Groups ``wall_x0`` (the face x = x0), ``wall_x1``, … ``wall_z1``.
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    if bounds.shape != (2, 3) or not np.isfinite(bounds).all() or not (bounds[0] < bounds[1]).all():
        raise ValueError(f"bounds must be [[x0, y0, z0], [x1, y1, z1]] with x0 < x1, y0 < y1, "
                         f"z0 < z1, got {bounds.tolist()}")
    (x0, y0, z0), (x1, y1, z1) = bounds
    vertices = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)])
    # each wall as a quad (outward, counter-clockwise seen from outside): z0, z1, y0, y1, x0, x1
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    walls = ("wall_z0", "wall_z1", "wall_y0", "wall_y1", "wall_x0", "wall_x1")
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    position = {wall: k for k, wall in enumerate(walls)}
    groups = {wall: np.array([2 * position[wall], 2 * position[wall] + 1]) for wall in WALL_NAMES}
    return Surface(vertices, faces, name, groups)


# --------------------------------------------------------------------------- geometry


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point to each ``p[k]`` on triangle ``(a[k], b[k], c[k])`` (Ericson's regions)."""
    def dot(u, v):
        return np.einsum("ij,ij->i", u, v)

    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        total = va + vb + vc
        v = np.where(total != 0, vb / total, 0.0)
        w = np.where(total != 0, vc / total, 0.0)
        result = a + ab * v[:, None] + ac * w[:, None]
        done = np.zeros(len(p), dtype=bool)
        regions = [
            (d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3),
            (vc <= 0) & (d1 >= 0) & (d3 <= 0), (d6 >= 0) & (d5 <= d6),
            (vb <= 0) & (d2 >= 0) & (d6 <= 0), (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
        ]
        points = [
            a, b,
            a + ab * np.nan_to_num(d1 / (d1 - d3))[:, None], c,
            a + ac * np.nan_to_num(d2 / (d2 - d6))[:, None],
            b + (c - b) * np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None],
        ]
    for region, point in zip(regions, points, strict=True):
        take = region & ~done
        result[take] = point[take]
        done |= region
    return result


def closest_points(
    queries: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *, chunk: int = 200_000
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest point of a triangle surface to each query point (exact).

    Candidate triangles are those whose centroid is within ``d0 + r`` of the
    query (``d0`` the distance to the nearest centroid, ``r`` the largest
    centroid-to-vertex distance): the closest triangle is always among them.

    Parameters
    ----------
    queries : array, shape (Q, 3)
    vertices : array, shape (V, 3)
    faces : int array, shape (F, 3)

    Returns
    -------
    points : array, shape (Q, 3)
        The closest surface points.
    face : int array, shape (Q,)
        The triangle each lies on.
    distance : array, shape (Q,)
    """
    from scipy.spatial import cKDTree

    queries = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    centroids = corners.mean(axis=1)
    radius = float(np.linalg.norm(corners - centroids[:, None], axis=2).max())
    tree = cKDTree(centroids)
    nearest, _ = tree.query(queries)
    lists = tree.query_ball_point(queries, nearest * (1 + 1e-9) + radius + 1e-300)
    lengths = np.fromiter((len(item) for item in lists), dtype=np.int64, count=len(queries))
    query_ids = np.repeat(np.arange(len(queries)), lengths)
    face_ids = np.fromiter((f for item in lists for f in item), dtype=np.int64, count=lengths.sum())
    best = np.full(len(queries), np.inf)
    best_face = np.zeros(len(queries), dtype=np.int64)
    best_point = np.zeros_like(queries)
    for start in range(0, len(query_ids), chunk):
        q, f = query_ids[start:start + chunk], face_ids[start:start + chunk]
        point = _closest_on_triangles(queries[q], *(corners[f, k] for k in range(3)))
        distance = np.linalg.norm(point - queries[q], axis=1)
        order = np.lexsort((distance, q))  # per query, nearest first
        first = order[np.r_[True, q[order][1:] != q[order][:-1]]]
        better = distance[first] < best[q[first]]
        take = first[better]
        best[q[take]] = distance[take]
        best_face[q[take]] = f[take]
        best_point[q[take]] = point[take]
    return best_point, best_face, best


def _closest_on_segments(queries: np.ndarray, starts: np.ndarray, ends: np.ndarray):
    """Closest point on the nearest of the segments, and its distance (brute force in chunks)."""
    best = np.full(len(queries), np.inf)
    best_point = np.zeros_like(queries)
    direction = ends - starts
    length2 = np.maximum(np.einsum("ij,ij->i", direction, direction), 1e-300)
    step = max(1, 2_000_000 // max(len(starts), 1))
    for begin in range(0, len(queries), step):
        q = queries[begin:begin + step]
        t = np.clip(np.einsum("qsj,sj->qs", q[:, None] - starts[None], direction) / length2, 0, 1)
        point = starts[None] + t[..., None] * direction[None]
        distance = np.linalg.norm(point - q[:, None], axis=2)
        nearest = distance.argmin(1)
        rows = np.arange(len(q))
        best[begin:begin + step] = distance[rows, nearest]
        best_point[begin:begin + step] = point[rows, nearest]
    return best_point, best


def feature_edges(surface: Surface, angle: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """Sharp edges of a surface and the smooth patches between them.

    Parameters
    ----------
    surface : Surface
    angle : float
        Feature angle in degrees, in (0, 180): an edge is sharp where the
        normals of its two faces differ by more than ``angle``.

    Returns
    -------
    edges : int array, shape (E, 2)
        Vertex pairs of the sharp edges.
    patches : list of int arrays
        Face indices of each patch (faces connected across smooth edges),
        largest first.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not 0 < angle < 180:
        raise ValueError(f"feature_angle must be in (0, 180) degrees, got {angle!r}")
    faces = surface.faces
    a, b, c = (surface.vertices[faces[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(faces)), 3)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    pairs, owner = pairs[order], owner[order]
    same = (pairs[1:] == pairs[:-1]).all(axis=1)  # closed surface: each edge twice, adjacent
    first, second = owner[:-1][same], owner[1:][same]
    cosine = np.einsum("ij,ij->i", normal[first], normal[second])
    sharp = cosine < np.cos(np.radians(angle))
    smooth = ~sharp
    graph = coo_matrix((np.ones(int(smooth.sum())), (first[smooth], second[smooth])),
                       shape=(len(faces), len(faces)))
    count, label = connected_components(graph, directed=False)
    patches = sorted((np.flatnonzero(label == k) for k in range(count)), key=len, reverse=True)
    return pairs[:-1][same][sharp], patches


# --------------------------------------------------------------------------- fTetWild


def _orient(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tets with the last two vertices swapped where the signed volume is negative."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    flip = _signed_volumes(points, tets) < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    return tets


def _signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


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
    threads: int = 1,
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
        Target edge length (absolute); ``sizing`` overrides it where smaller.
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
    threads : int, default 1
        fTetWild's threads (0: all cores; its output then varies run to run).
    progress : bool, default False
        Print a line on stderr before and after (with the elapsed time):
        fTetWild holds the interpreter while it runs, so no bar can move.
    verbose : bool, default False
        fTetWild's own log.

    Returns
    -------
    points : array, shape (N, 3)
    tets : int array, shape (M, 4), positively oriented
    """
    try:
        import pytetwild  # imports pyvista
    except ImportError as error:
        raise ImportError(f"tetrahedralising needs pytetwild (which imports pyvista): {_EXTRA}"
                          ) from error
    for label, value in (("edge_length", edge_length), ("epsilon", epsilon),
                         ("stop_energy", stop_energy)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
    if not (isinstance(iterations, (int, np.integer)) and iterations >= 0):
        raise ValueError(f"iterations must be an integer >= 0, got {iterations!r}")
    options = {
        "edge_length_abs": float(edge_length),
        "epsilon": float(epsilon),
        "stop_energy": float(stop_energy),
        "num_opt_iter": int(iterations),
        "num_threads": int(threads),
        "quiet": not verbose,
    }
    if sizing is not None:
        options.update(bg_vertices=np.ascontiguousarray(sizing[0], dtype=np.float64),
                       bg_tets=np.ascontiguousarray(sizing[1], dtype=np.int32),
                       bg_values=np.ascontiguousarray(sizing[2], dtype=np.float64))
    if progress:
        print(f"fTetWild: meshing {len(faces)} surface triangles (edge length {edge_length:.3g}"
              f"{', graded' if sizing is not None else ''}, epsilon {epsilon:g}, stop energy "
              f"{stop_energy:g}); this can take a minute ...", file=sys.stderr, flush=True)
    start = time.perf_counter()
    with _scratch_directory():
        points, tets = pytetwild.tetrahedralize(
            np.ascontiguousarray(vertices, dtype=np.float64),
            np.ascontiguousarray(faces, dtype=np.int32),
            **options,
        )
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if progress:
        print(f"fTetWild: {len(points)} nodes, {len(tets)} tetrahedra in "
              f"{time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    if len(tets) == 0:
        raise RuntimeError("fTetWild returned an empty mesh (is the surface closed and does it "
                           "enclose a volume?)")
    return points, _orient(points, tets)


def _sizing_field(bounds: np.ndarray, bodies: Sequence[Surface], far: float, near: float,
                  grading: float, cells: int = 24):
    """A Kuhn-split grid over ``bounds``: ``min(far, near + (far - near) d / grading)``."""
    axes = [np.linspace(bounds[0, k], bounds[1, k], cells + 1) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    n = cells + 1
    index = np.arange(n**3).reshape(n, n, n)
    corner = [index[i:n - 1 + i, j:n - 1 + j, k:n - 1 + k].ravel()
              for k in (0, 1) for j in (0, 1) for i in (0, 1)]
    paths = [(1, 3), (1, 5), (2, 3), (2, 6), (4, 5), (4, 6)]
    tets = np.concatenate([np.c_[corner[0], corner[a], corner[b], corner[7]] for a, b in paths])
    vertices, faces = _merge([(body, False) for body in bodies])
    distance = closest_points(grid, vertices, faces)[2]
    values = np.minimum(far, near + (far - near) * distance / grading)
    return grid, _orient(grid, tets).astype(np.int32), values


def _merge(surfaces: Sequence[tuple[Surface, bool]]) -> tuple[np.ndarray, np.ndarray]:
    """One vertex/face array of several surfaces, each flipped when its flag is set."""
    vertices, faces, offset = [], [], 0
    for surface, flip in surfaces:
        vertices.append(surface.vertices)
        faces.append((surface.faces[:, ::-1] if flip else surface.faces) + offset)
        offset += len(surface.vertices)
    return np.concatenate(vertices), np.concatenate(faces)


# --------------------------------------------------------------------------- the mesh


def _box_bounds(bodies: Sequence[Surface], box: float | Sequence[float]) -> np.ndarray:
    padding = np.asarray(box, dtype=np.float64).reshape(-1)
    if padding.size == 1:
        padding = np.repeat(padding, 6)
    if padding.size != 6 or not (np.isfinite(padding).all() and (padding >= 0).all()):
        raise ValueError(f"box must be one padding >= 0 or six (x0, x1, y0, y1, z0, z1), as "
                         f"multiples of the bodies' largest extent, got {np.asarray(box).tolist()}")
    low = np.min([body.bounds[0] for body in bodies], axis=0)
    high = np.max([body.bounds[1] for body in bodies], axis=0)
    extent = float((high - low).max())
    return np.stack([low - padding[0::2] * extent, high + padding[1::2] * extent])


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
            result.append(item if name is None else Surface(item.vertices, item.faces, name,
                                                            item.groups))
        else:
            result.append(load_surface(item, name=name, repair=repair))
    names = [surface.name for surface in result]
    for duplicate in {n for n in names if names.count(n) > 1}:
        raise ValueError(f"surfaces: two surfaces are named {duplicate!r}; name them "
                         "(a mapping name -> file, or NAME=FILE on the command line)")
    return result


def _contains(outer: Surface, inner: Surface) -> bool:
    return bool((outer.bounds[0] < inner.bounds[0]).all() and (inner.bounds[1] < outer.bounds[1]).all())


def _snap(points, tets, nodes, targets, *, sweeps: int = 30):
    """Move ``nodes`` to ``targets``, backing moves off where a tetrahedron would invert.

    Returns the moved points and the number of nodes not moved all the way.
    """
    original = points[nodes].copy()
    fraction = np.ones(len(nodes))
    position = np.full(len(points), -1)
    position[nodes] = np.arange(len(nodes))
    longest = np.sqrt(np.max([np.sum((points[tets[:, i]] - points[tets[:, j]]) ** 2, axis=1)
                              for i in range(4) for j in range(i + 1, 4)], axis=0))
    minimum = 1e-8 * longest**3
    for _ in range(sweeps):
        points[nodes] = original + fraction[:, None] * (targets - original)
        bad = _signed_volumes(points, tets) <= minimum
        if not bad.any():
            break
        culprits = np.unique(position[tets[bad]])
        culprits = culprits[culprits >= 0]
        if culprits.size == 0:
            break
        fraction[culprits] = np.where(fraction[culprits] > 1e-3, fraction[culprits] / 2, 0.0)
    return points, int((fraction < 1).sum())


def _edge_lengths_at_nodes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    pairs = tets[:, [0, 1, 0, 2, 0, 3, 1, 2, 1, 3, 2, 3]].reshape(-1, 2)
    lengths = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    shortest = np.full(len(points), np.inf)
    np.minimum.at(shortest, pairs[:, 0], lengths)
    np.minimum.at(shortest, pairs[:, 1], lengths)
    return shortest


def _boundary_nodes(tets: np.ndarray) -> np.ndarray:
    faces = np.sort(tets[:, [1, 2, 3, 0, 3, 2, 0, 1, 3, 0, 2, 1]].reshape(-1, 3), axis=1)
    unique, counts = np.unique(faces, axis=0, return_counts=True)
    return np.unique(unique[counts == 1])


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
    threads: int = 1,
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
        in the box.
    box : float or 6 floats, optional
        Place the bodies in an axis-aligned box padded by this multiple of
        their largest extent on every side, or per side ``(x0, x1, y0, y1,
        z0, z1)`` (a tunnel: e.g. ``(2, 6, 2, 2, 2, 2)``).
    bounds : array, shape (2, 3), optional
        The box's corners instead of ``box``.
    edge_length : float, optional
        Target edge length (default: the domain's bounding-box diagonal / 20).
    body_edge_length, grading : float, optional
        Edge length on the bodies, growing linearly with the distance from
        them to ``edge_length`` over ``grading`` (default: the bodies' largest
        extent); needs a box (a background sizing field).
    epsilon, stop_energy, iterations, threads
        fTetWild's envelope, optimisation target and passes, threads
        (:func:`tetrahedralize`).
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
        Print the meshing steps with elapsed times and the quality on stderr.
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
        For a bad surface or argument (named in the message); when the mesh
        has inverted tetrahedra after snapping (not expected).
    ImportError
        Without the ``tetwild`` extra.
    """
    from torchmorph.mesh import TetMesh

    start = time.perf_counter()
    bodies = _as_surfaces(surfaces, repair)
    if box is not None and bounds is not None:
        raise ValueError("box and bounds: give one of them, not both")
    if (body_edge_length is not None or grading is not None) and box is None and bounds is None:
        raise ValueError("body_edge_length and grading need a far field: give box or bounds")
    walls = None
    if box is not None:
        walls = box_surface(_box_bounds(bodies, box))
    elif bounds is not None:
        walls = box_surface(bounds)
    if walls is not None:
        if any(body.name == walls.name for body in bodies):
            raise ValueError(f"surfaces: the name {walls.name!r} is the box's; name the "
                             "surface otherwise")
        for body in bodies:
            if not _contains(walls, body):
                raise ValueError(f"bounds: the box {walls.bounds.tolist()} does not contain "
                                 f"surface {body.name!r} (bounds {body.bounds.tolist()})")
        boundary = [(walls, False)] + [(body, True) for body in bodies]
    else:
        outer = [s for s in bodies if all(_contains(s, o) for o in bodies if o is not s)]
        if len(bodies) > 1 and outer:
            boundary = [(s, s is not outer[0]) for s in bodies]
        else:
            boundary = [(s, False) for s in bodies]
    all_surfaces = [surface for surface, _ in boundary]
    vertices, faces = _merge(boundary)
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    if edge_length is None:
        edge_length = diagonal / 20.0
    sizing = None
    if body_edge_length is not None:
        for label, value in (("body_edge_length", body_edge_length), ("grading", grading)):
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        body_bounds = np.stack([np.min([b.bounds[0] for b in bodies], 0),
                                np.max([b.bounds[1] for b in bodies], 0)])
        grading = grading if grading is not None else float(np.ptp(body_bounds, axis=0).max())
        sizing = _sizing_field(walls.bounds, bodies, edge_length, body_edge_length, grading)
    if feature_angle is not None and not 0 < feature_angle < 180:
        raise ValueError(f"feature_angle must be in (0, 180) degrees, got {feature_angle!r}")

    points, tets = tetrahedralize(vertices, faces, edge_length=edge_length, epsilon=epsilon,
                                  stop_energy=stop_energy, iterations=iterations, sizing=sizing,
                                  threads=threads, progress=progress)
    boundary_nodes = _boundary_nodes(tets)
    tolerance = 1e-9 * diagonal
    unsnapped = 0
    features = {}
    if feature_angle is not None:
        for surface in bodies:
            features[surface.name] = feature_edges(surface, feature_angle)
    if snap:
        shortest = _edge_lengths_at_nodes(points, tets)
        target = closest_points(points[boundary_nodes], vertices, faces)[0]
        for surface in bodies:
            edges = features.get(surface.name, (np.zeros((0, 2), np.int64), []))[0]
            if len(edges):
                on_edge, distance = _closest_on_segments(
                    points[boundary_nodes], surface.vertices[edges[:, 0]],
                    surface.vertices[edges[:, 1]])
                # fTetWild keeps a crease within its envelope: nodes that close to a sharp
                # edge (and closer than half their shortest edge) belong on it
                reach = np.minimum(0.5 * shortest[boundary_nodes], 3.0 * epsilon * diagonal)
                near = distance < reach
                target[near] = on_edge[near]
        points, unsnapped = _snap(points, tets, boundary_nodes, target)

    node_sets: dict[str, np.ndarray] = {}
    query = points[boundary_nodes]
    nearest = closest_points(query, vertices, faces)[2] + tolerance

    def on(surface_vertices, surface_faces) -> np.ndarray:
        distance = closest_points(query, surface_vertices, surface_faces)[2]
        return boundary_nodes[distance <= nearest]

    group_owner: dict[str, str] = {}
    for surface in all_surfaces:
        node_sets[surface.name] = on(surface.vertices, surface.faces)
        for group, ids in surface.groups.items():
            group_owner.setdefault(group, surface.name)
    for surface in all_surfaces:
        for group, ids in surface.groups.items():
            clash = group in node_sets or group_owner[group] != surface.name
            key = f"{surface.name}_{group}" if clash else group
            node_sets[key] = on(surface.vertices, surface.faces[ids])
    for surface_name, (edges, patches) in features.items():
        surface = next(s for s in bodies if s.name == surface_name)
        if len(edges):
            _, distance = _closest_on_segments(query, surface.vertices[edges[:, 0]],
                                               surface.vertices[edges[:, 1]])
            node_sets[f"{surface_name}_edges"] = boundary_nodes[distance <= tolerance]
        for k, patch in enumerate(patches):
            node_sets[f"{surface_name}_patch{k}"] = on(surface.vertices, surface.faces[patch])
    node_sets = {key: ids for key, ids in node_sets.items() if ids.size}

    inverted = int((_signed_volumes(points, tets) <= 0).sum())
    if inverted:
        raise ValueError(f"the mesh has {inverted} inverted tetrahedra after snapping; try "
                         "snap=False or a smaller epsilon")
    mesh = TetMesh(points, tets, node_sets, name=name or bodies[0].name)
    if progress:
        report = quality_report(mesh)
        snapped = (f"; {unsnapped} boundary node(s) kept off the surface to keep tetrahedra "
                   "valid" if unsnapped else "")
        print(f"mesh: {mesh.num_nodes} nodes, {mesh.num_tets} tetrahedra, {report}{snapped} "
              f"({time.perf_counter() - start:.1f} s in all)", file=sys.stderr, flush=True)
    return mesh


def quality_report(mesh: TetMesh) -> str:
    """One line: the quality Q (max/mean edge ratio), the smallest volume, inverted tets."""
    from torchmorph.quality import quality_summary

    summary = quality_summary(mesh)
    return (f"quality Q max {summary['max_edge_ratio']:.4g}, mean {summary['mean_edge_ratio']:.4g}"
            f" (edge ratio, 1 is best); min volume {summary['min_volume']:.4g}; inverted "
            f"{summary['num_inverted']}")
