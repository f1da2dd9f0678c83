"""Closed triangle surfaces for :mod:`torchmorph.meshing`: reading, checks, closest points, features.

Public names are re-exported by :mod:`torchmorph.meshing`; see there.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

__all__ = [
    "BOX_WALLS",
    "CAD_FORMATS",
    "PLY_LABELS",
    "SURFACE_FORMATS",
    "WALL_NAMES",
    "Surface",
    "box_bounds",
    "box_surface",
    "closest_points",
    "feature_edges",
    "load_surface",
    "surface_problems",
]

#: File extensions :func:`load_surface` reads.
SURFACE_FORMATS = (".stl", ".obj", ".ply", ".off")
#: CAD file extensions (meshed with gmsh by :func:`torchmorph.meshing.mesh_cad`).
CAD_FORMATS = (".step", ".stp", ".iges", ".igs", ".brep")
#: Node-set names of the box walls (the face of the box at the low / high end of x, y, z).
#: Node-set name, axis and side (0 = lower bound, 1 = upper bound) of the six walls of a box.
BOX_WALLS = (
    ("wall_x0", 0, 0),
    ("wall_x1", 0, 1),
    ("wall_y0", 1, 0),
    ("wall_y1", 1, 1),
    ("wall_z0", 2, 0),
    ("wall_z1", 2, 1),
)
WALL_NAMES = tuple(name for name, _, _ in BOX_WALLS)
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
        if (
            faces.ndim != 2
            or faces.shape[1] != 3
            or len(faces) == 0
            or faces.dtype.kind not in "iu"
        ):
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
        problems.append(
            f"{int((counts == 1).sum())} edge(s) belong to one face only (holes, "
            f"e.g. the edge between vertices {tuple(int(v) for v in undirected[counts == 1][0])})"
        )
    if (counts > 2).any():
        problems.append(
            f"{int((counts > 2).sum())} edge(s) are shared by more than two faces (non-manifold)"
        )
    _, directed_counts = np.unique(directed, axis=0, return_counts=True)
    if (directed_counts > 1).any():
        problems.append(
            f"{int((directed_counts > 1).sum())} edge(s) are traversed in the same "
            "direction by two faces (inconsistent orientation)"
        )
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    scale = float(np.ptp(vertices, axis=0).max()) or 1.0
    degenerate = area2 <= 1e-14 * scale**2
    if degenerate.any():
        problems.append(
            f"{int(degenerate.sum())} face(s) have zero area (e.g. face "
            f"{int(np.flatnonzero(degenerate)[0])})"
        )
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
    return (
        np.asarray(vertices, dtype=np.float64),
        np.asarray(faces, dtype=np.int64),
        {name: np.asarray(ids) for name, ids in groups.items()},
    )


def _read_with_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    try:
        import trimesh
    except ImportError as error:
        raise ImportError(f"reading {path.suffix} surfaces needs trimesh: {_EXTRA}") from error
    loaded = trimesh.load(str(path), process=False, force="mesh")
    if not isinstance(loaded, trimesh.Trimesh):  # what force="mesh" asks for
        raise ValueError(f"trimesh read no triangle mesh but a {type(loaded).__name__}")
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


def load_surface(
    path: str | os.PathLike, *, name: str | None = None, repair: bool = False
) -> Surface:
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
        raise ValueError(
            f"path: unsupported surface file extension {suffix or '(none)'!r} in "
            f"{str(path)!r}; supported: {', '.join(SURFACE_FORMATS)} (and CAD files, "
            f"{', '.join(CAD_FORMATS)}, in mesh_surfaces)"
        )
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
        raise ValueError(
            f"path: could not read surface file {str(path)!r}: {type(error).__name__}: {error}"
        ) from error
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
        hint = (
            "trimesh's repairs could not fix it; fix the file in a mesh editor"
            if repair
            else "pass repair=True (torchmorph mesh --repair) to let trimesh try to fix it, "
            "or fix the file in a mesh editor"
        )
        raise ValueError(
            f"path: surface {str(path)!r} is not a closed, consistently oriented "
            f"surface: {'; '.join(problems)}; {hint}"
        )
    groups = {group: np.flatnonzero(labels == index) for index, group in enumerate(group_names)}
    surface = Surface(
        vertices, faces, name or path.stem, {k: v for k, v in groups.items() if v.size}
    )
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
        raise ValueError(
            f"bounds must be [[x0, y0, z0], [x1, y1, z1]] with x0 < x1, y0 < y1, "
            f"z0 < z1, got {bounds.tolist()}"
        )
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
    d1, d2, d3, d4, d5, d6 = (
        dot(ab, ap),
        dot(ac, ap),
        dot(ab, bp),
        dot(ac, bp),
        dot(ab, cp),
        dot(ac, cp),
    )
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        total = va + vb + vc
        v = np.where(total != 0, vb / total, 0.0)
        w = np.where(total != 0, vc / total, 0.0)
        result = a + ab * v[:, None] + ac * w[:, None]
        done = np.zeros(len(p), dtype=bool)
        regions = [
            (d1 <= 0) & (d2 <= 0),
            (d3 >= 0) & (d4 <= d3),
            (vc <= 0) & (d1 >= 0) & (d3 <= 0),
            (d6 >= 0) & (d5 <= d6),
            (vb <= 0) & (d2 >= 0) & (d6 <= 0),
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
        ]
        points = [
            a,
            b,
            a + ab * np.nan_to_num(d1 / (d1 - d3))[:, None],
            c,
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
        q, f = query_ids[start : start + chunk], face_ids[start : start + chunk]
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
        q = queries[begin : begin + step]
        t = np.clip(np.einsum("qsj,sj->qs", q[:, None] - starts[None], direction) / length2, 0, 1)
        point = starts[None] + t[..., None] * direction[None]
        distance = np.linalg.norm(point - q[:, None], axis=2)
        nearest = distance.argmin(1)
        rows = np.arange(len(q))
        best[begin : begin + step] = distance[rows, nearest]
        best_point[begin : begin + step] = point[rows, nearest]
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
    graph = coo_matrix(
        (np.ones(int(smooth.sum())), (first[smooth], second[smooth])),
        shape=(len(faces), len(faces)),
    )
    count, label = connected_components(graph, directed=False)
    patches = sorted((np.flatnonzero(label == k) for k in range(count)), key=len, reverse=True)
    return pairs[:-1][same][sharp], patches


class _Bounded(Protocol):
    """Anything with the bounds of a :class:`Surface`: ``bounds[0]`` low, ``bounds[1]`` high."""

    @property
    def bounds(self) -> np.ndarray: ...


def box_bounds(bodies: Sequence[_Bounded], box: float | Sequence[float]) -> np.ndarray:
    padding = np.asarray(box, dtype=np.float64).reshape(-1)
    if padding.size == 1:
        padding = np.repeat(padding, 6)
    if padding.size != 6 or not (np.isfinite(padding).all() and (padding >= 0).all()):
        raise ValueError(
            f"box must be one padding >= 0 or six (x0, x1, y0, y1, z0, z1), as "
            f"multiples of the bodies' largest extent, got {np.asarray(box).tolist()}"
        )
    low = np.min([body.bounds[0] for body in bodies], axis=0)
    high = np.max([body.bounds[1] for body in bodies], axis=0)
    extent = float((high - low).max())
    return np.stack([low - padding[0::2] * extent, high + padding[1::2] * extent])
