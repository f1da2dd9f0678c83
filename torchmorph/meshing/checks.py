"""Guards shared by the meshers: argument checks, bodies that overlap or touch, far
coordinates, and progress lines on stderr.

Bodies meshed together must be disjoint: two bodies that overlap would be meshed twice
where they overlap (or not at all, by fTetWild's winding number), and two that touch
leave a gap of zero thickness that no tetrahedron can fill. A body inside another is
legitimate in one case only, without a far-field box: the body whose bounding box holds
all the others is then the outer wall and the others are holes in it (bodies in a
tunnel). :func:`surface_contacts` finds, for closed triangle surfaces, which of these
relations two bodies have; :mod:`torchmorph.meshing.cad` does the same with
OpenCASCADE's booleans.
"""

from __future__ import annotations

import math
import sys
import time
from numbers import Integral, Real
from typing import Any, overload

import numpy as np

__all__ = [
    "Progress",
    "check_body_contacts",
    "check_max_elements",
    "check_size",
    "check_threads",
    "far_offset",
    "inside_surface",
    "surface_contacts",
]

#: Two bodies closer than this fraction of the domain's diagonal touch.
TOUCH_TOLERANCE = 1e-6


def check_threads(threads: Any) -> int:
    """``threads`` as an int >= 1 (None: 1, the reproducible default); else ``ValueError``."""
    if threads is None:
        return 1
    if isinstance(threads, bool) or not isinstance(threads, Integral) or threads < 1:
        raise ValueError(
            f"threads must be an integer >= 1 (or None for the default, 1), got {threads!r}; "
            "for every core pass os.cpu_count()"
        )
    return int(threads)


def check_max_elements(max_elements: Any) -> int | None:
    """``max_elements`` as an int >= 1 or None (no limit); else ``ValueError``."""
    if max_elements is None:
        return None
    if (
        isinstance(max_elements, bool)
        or not isinstance(max_elements, Real)
        or not math.isfinite(max_elements)
        or not float(max_elements) >= 1
        or max_elements != math.floor(max_elements)
    ):
        raise ValueError(
            f"max_elements must be an integer >= 1 or None (no limit), got {max_elements!r}"
        )
    whole = math.floor(max_elements)  # integral (checked above): its value, exactly
    return int(whole)


@overload
def check_size(
    label: str, value: None, *, extent: float | None = None, what: str = "the domain's"
) -> None: ...
@overload
def check_size(
    label: str, value: float, *, extent: float | None = None, what: str = "the domain's"
) -> float: ...
def check_size(
    label: str, value: Any, *, extent: float | None = None, what: str = "the domain's"
) -> float | None:
    """A size argument as float: finite, > 0 and at most ``extent`` (None passes through).

    An edge length above the domain's largest extent asks for less than one element
    across it: the mesher cannot honour it (fTetWild then runs for minutes) and it is
    almost always a unit mistake, so it is refused.
    """
    if value is None:
        return None
    if (
        isinstance(value, bool)
        or not isinstance(value, Real)
        or not (math.isfinite(value) and float(value) > 0)
    ):
        raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
    if extent is not None and float(value) > extent:
        raise ValueError(
            f"{label} must be at most {what} largest extent {extent:.4g} (less than one "
            f"element across it), got {value!r}; are the sizes in the geometry's units?"
        )
    return float(value)


def far_offset(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The bounding box's centre when it lies farther from the origin than its diagonal, else 0.

    Meshers lose precision (fTetWild stalls) on coordinates large next to the body: a
    body at 1e7 is meshed about the origin and moved back.
    """
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    centre = 0.5 * (low + high)
    if np.linalg.norm(centre) > np.linalg.norm(high - low):
        return centre
    return np.zeros(3)


class Progress:
    """Lines on stderr with the time since the start, when ``enabled``."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = bool(enabled)
        self.start = time.perf_counter()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def __call__(self, message: str) -> None:
        if self.enabled:
            print(f"[{self.elapsed:6.1f} s] {message}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- contacts


def _edges(faces: np.ndarray) -> np.ndarray:
    return np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)


def _pairs_cross(starts, ends, corners, margin: float) -> bool:
    """Whether segment k crosses triangle ``corners[k]`` for some k (see :func:`_segments_cross`)."""
    direction = ends - starts
    a, e1, e2 = corners[:, 0], corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    h = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, h)
    scale = (
        np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(direction, axis=1)
    )
    proper = np.abs(det) > 1e-12 * scale  # not parallel
    with np.errstate(divide="ignore", invalid="ignore"):
        s = starts - a
        u = np.einsum("ij,ij->i", s, h) / det
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", direction, q) / det
        t = np.einsum("ij,ij->i", e2, q) / det
        inside = (u > margin) & (v > margin) & (u + v < 1 - margin)
        return bool((proper & inside & (t > 1e-9) & (t < 1 - 1e-9)).any())


def _segments_cross(starts, ends, vertices, faces, *, edges_too: bool) -> bool:
    """Whether a segment passes through a triangle (Möller–Trumbore): through its inside,
    or with ``edges_too`` through its edges as well.

    A segment that ends on a triangle, or lies in its plane, does not cross it: that is
    a touch (see :func:`surface_contacts`).
    """
    from scipy.spatial import cKDTree

    margin = -1e-9 if edges_too else 1e-9
    corners = vertices[faces]
    # only segments and triangles where the two bounding boxes overlap can meet
    low, high = np.minimum(starts, ends), np.maximum(starts, ends)
    near = ((low <= corners.max(axis=(0, 1))) & (high >= corners.min(axis=(0, 1)))).all(axis=1)
    starts, ends, low, high = starts[near], ends[near], low[near], high[near]
    if not len(starts):
        return False
    reach = (corners.max(axis=1) >= low.min(axis=0)) & (corners.min(axis=1) <= high.max(axis=0))
    corners = corners[reach.all(axis=1)]
    if not len(corners):
        return False
    centroids = corners.mean(axis=1)
    radius = float(np.linalg.norm(corners - centroids[:, None], axis=2).max())
    middle, half = 0.5 * (starts + ends), 0.5 * np.linalg.norm(ends - starts, axis=1)
    tree = cKDTree(centroids)
    for begin in range(0, len(starts), 5_000):
        chunk = slice(begin, begin + 5_000)
        lists = tree.query_ball_point(middle[chunk], half[chunk] + radius * (1 + 1e-9))
        counts = np.fromiter((len(item) for item in lists), dtype=np.int64, count=len(lists))
        segments = begin + np.repeat(np.arange(len(lists)), counts)
        faces_hit = np.fromiter(
            (f for item in lists for f in item), dtype=np.int64, count=counts.sum()
        )
        for first in range(0, len(segments), 500_000):  # pairs in bounded memory
            segment, face = segments[first : first + 500_000], faces_hit[first : first + 500_000]
            if _pairs_cross(starts[segment], ends[segment], corners[face], margin):
                return True
    return False


def inside_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which points lie inside a closed triangle surface (ray parity, all triangles per point).

    Meant for a few points: the cost is points x triangles. The ray's direction is
    generic, so it misses the surface's edges and vertices but for a measure-zero set.
    """
    direction = np.array([0.5773502691896258, 0.5773502691896257, 0.5773502691896259])
    direction += np.array([1.3e-3, -2.9e-3, 0.7e-3])
    corners = vertices[faces]
    a, e1, e2 = corners[:, 0], corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    h = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, h)
    result = np.zeros(len(points), dtype=bool)
    for index, point in enumerate(np.asarray(points, dtype=np.float64)):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = point - a
            u = np.einsum("ij,ij->i", s, h) / det
            q = np.cross(s, e1)
            v = (q @ direction) / det
            t = np.einsum("ij,ij->i", e2, q) / det
            hits = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        result[index] = bool(hits.sum() % 2)
    return result


def _touches(points: np.ndarray, surface, tolerance: float) -> bool:
    """Whether a point lies within ``tolerance`` of the surface; the exact distance only for
    points within reach of a triangle's centroid (far points cost nothing)."""
    from scipy.spatial import cKDTree

    from torchmorph.meshing.surfaces import closest_points

    corners = surface.vertices[surface.faces]
    centroids = corners.mean(axis=1)
    radius = float(np.linalg.norm(corners - centroids[:, None], axis=2).max())
    reach = cKDTree(centroids).query(points, distance_upper_bound=radius + tolerance)[0]
    near = points[np.isfinite(reach)]
    if not len(near):
        return False
    return bool(closest_points(near, surface.vertices, surface.faces)[2].min() <= tolerance)


def surface_contacts(first, second, tolerance: float) -> str | None:
    """How two closed triangle surfaces (:class:`~torchmorph.meshing.Surface`) meet.

    Returns ``"cross"`` (their surfaces cross: the bodies overlap), ``"touch"`` (a
    vertex of one lies within ``tolerance`` of the other), ``"first inside"`` or
    ``"second inside"`` (one body inside the other), or None (apart). Crossings through
    the inside of triangles are looked for first, then touching vertices, then crossings
    through triangle edges (two mirror-image spheres cross only there). A touch along
    edges only, with no vertex on the other surface, is taken for a crossing.
    """
    (low_a, high_a), (low_b, high_b) = first.bounds, second.bounds
    if (low_a > high_b + tolerance).any() or (low_b > high_a + tolerance).any():
        return None

    def cross(edges_too: bool) -> bool:
        for one, other in ((first, second), (second, first)):
            edges = _edges(one.faces)
            start, end = one.vertices[edges[:, 0]], one.vertices[edges[:, 1]]
            if _segments_cross(start, end, other.vertices, other.faces, edges_too=edges_too):
                return True
        return False

    if cross(edges_too=False):
        return "cross"
    for one, other in ((first, second), (second, first)):
        if _touches(one.vertices[np.unique(one.faces)], other, tolerance):
            return "touch"
    if cross(edges_too=True):
        return "cross"
    if inside_surface(first.vertices[first.faces[:1, 0]], second.vertices, second.faces)[0]:
        return "first inside"
    if inside_surface(second.vertices[second.faces[:1, 0]], first.vertices, first.faces)[0]:
        return "second inside"
    return None


def check_body_contacts(bodies, container, tolerance: float) -> None:
    """Refuse bodies (:class:`~torchmorph.meshing.Surface`) that overlap, touch or nest.

    ``container`` is the outer wall when the bodies are holes in it (see the module doc),
    else None; a body inside it is then expected, not refused.
    """
    for i, first in enumerate(bodies):
        for second in bodies[i + 1 :]:
            contact = surface_contacts(first, second, tolerance)
            pair = f"{first.name!r} and {second.name!r}"
            if contact == "cross":
                raise ValueError(
                    f"surfaces: {pair} overlap (their surfaces cross): bodies must be "
                    "disjoint; merge them into one closed surface, or move them apart"
                )
            if contact == "touch":
                raise ValueError(
                    f"surfaces: {pair} touch (a vertex of one is closer than {tolerance:.2g} "
                    "to the other): bodies must be apart, a gap of zero thickness cannot be "
                    "meshed; merge them into one closed surface, or move them apart"
                )
            if contact is None:
                continue
            inner, outer = (first, second) if contact == "first inside" else (second, first)
            if outer is not container:
                raise ValueError(
                    f"surfaces: {inner.name!r} lies inside {outer.name!r}: a body inside "
                    "another is a hole only without box/bounds, the outer surface's bounding "
                    "box holding all the others (bodies in a tunnel)"
                )
