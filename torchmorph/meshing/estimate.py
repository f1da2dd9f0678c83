"""How many tetrahedra a mesh will have, estimated before meshing, and the budget check.

A mesher asked for edge length ``h`` fills a volume with tetrahedra of about the
regular tetrahedron's volume ``h³ / (6√2)``, so a domain Ω meshed with a size field
``h(x)`` has about

    N ≈ c ∫_Ω 6√2 / h(x)³ dV

tetrahedra, with ``c`` the mesher's measured ratio (:data:`TETS_PER_REGULAR`: real meshes
are not made of regular tetrahedra). Graded sizes grow linearly with the distance ``d``
from the bodies, ``h(d) = min(H, h_b + (H - h_b) d / G)`` (``H`` the edge length, ``h_b``
the body edge length, ``G`` the grading distance). The integral is taken on a grid of
cells over the box (distance from a triangulation of the bodies, cells inside a body
left out) and, in the layer ``d < d0`` thinner than a cell, analytically as ``A ∫_0^d0
6√2 / h(d)³ dd`` with ``A`` the bodies' surface area (a thin layer's volume is ``A d``).

:func:`check_budget` refuses an estimate above ``max_elements`` (default
:data:`MAX_ELEMENTS`) with a message that gives the estimate, the budget and which size
to raise, so that a size typed a thousand times too small fails in a second instead of
meshing for an hour. The estimate is a guide, not a promise. Measured (real / estimated
tetrahedra): gmsh 0.87-1.22 (HXT) and 0.87-1.67 (Delaunay) on spheres, boxes, a holed
part and a wing in a box, uniform and graded; fTetWild 0.7-1.4 with uniform sizes and
0.2-0.7 graded (its background grid of 24 cells per side is coarser than a steep
grading, so it meshes coarser than asked). It does not count elements a mesher adds
to resolve surface details smaller than the sizes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MAX_ELEMENTS", "TETS_PER_REGULAR", "TetEstimate", "check_budget", "estimate_tets"]

#: Default largest estimated number of tetrahedra meshed without being asked
#: (``max_elements=``; ``torchmorph mesh --max-elements``): about a few GB and minutes.
MAX_ELEMENTS = 3_000_000
#: Tetrahedra per regular tetrahedron of the size field's volume, as measured on spheres,
#: boxes and a wing in a box: gmsh's Delaunay (``algorithm=1``) and HXT (10), fTetWild
#: (which refines curved surfaces beyond the size: 1.5-1.8 on a sphere, 0.9 on a cube).
TETS_PER_REGULAR = {"gmsh": 0.62, "gmsh-hxt": 0.5, "ftetwild": 1.3}
_INVERSE_REGULAR = 6.0 * math.sqrt(2.0)  # 1 / volume of the regular tetrahedron of edge 1


@dataclass(frozen=True)
class TetEstimate:
    """An estimated tetrahedron count and its parts.

    Attributes
    ----------
    total : float
        The estimate.
    uniform : float
        What the whole domain would need at the edge length alone.
    volume : float
        The domain's volume.
    sizes : dict
        The sizes used, by argument name.
    """

    total: float
    uniform: float
    volume: float
    sizes: dict


def size_at(
    distance: np.ndarray, size: float, body_size: float | None, grading: float | None
) -> np.ndarray:
    """The graded edge length at ``distance`` from the bodies: ``min(H, h_b + (H - h_b) d / G)``."""
    distance = np.asarray(distance, dtype=np.float64)
    if body_size is None or body_size >= size:
        return np.full(distance.shape, float(size))
    if grading is None:
        raise ValueError("grading is needed with a body_size below size")
    return np.minimum(size, body_size + (size - body_size) * distance / grading)


def _layer_integral(depth: float, size: float, body_size: float, grading: float) -> float:
    """``∫_0^depth 6√2 / h(d)³ dd`` for the grading of :func:`size_at`, in closed form."""
    if body_size >= size:
        return _INVERSE_REGULAR * depth / size**3
    slope = (size - body_size) / grading
    graded = min(depth, grading)
    reached = body_size + slope * graded
    total = _INVERSE_REGULAR / (2.0 * slope) * (1.0 / body_size**2 - 1.0 / reached**2)
    return total + _INVERSE_REGULAR * max(depth - grading, 0.0) / size**3


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> np.ndarray:
    """Points on the triangles no farther than ``spacing`` apart (each triangle's barycentric
    grid of ``m`` divisions, ``m`` from its longest edge; at most 64 divisions)."""
    corners = vertices[faces]
    longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
    divisions = np.clip(np.ceil(longest / spacing), 1, 64).astype(np.int64)
    samples = [vertices[np.unique(faces)]]
    for m in np.unique(divisions):
        i, j = np.meshgrid(np.arange(m + 1), np.arange(m + 1), indexing="ij")
        keep = i + j <= m
        weights = np.stack([i[keep], j[keep]], -1) / m  # (P, 2) barycentric (b, c)
        group = corners[divisions == m]
        samples.append(
            (
                group[:, None, 0] * (1 - weights.sum(1))[None, :, None]
                + group[:, None, 1] * weights[None, :, 0, None]
                + group[:, None, 2] * weights[None, :, 1, None]
            ).reshape(-1, 3)
        )
    return np.concatenate(samples)


def _inside_grid(axes, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which grid points ``axes[0] x axes[1] x axes[2]`` lie inside the closed surface.

    A ray along +x from each point crosses the surface an odd number of times from
    inside. Crossings are found per grid line (y_j, z_k) from the triangles' projections
    on the y-z plane; grid lines exactly through an edge are not expected (the cells'
    centres are used) and would flip one line.
    """
    xs, ys, zs = axes
    corners = vertices[faces]  # (F, 3, 3)
    low, high = corners[:, :, 1:].min(1), corners[:, :, 1:].max(1)
    j0 = np.searchsorted(ys, low[:, 0], side="left")
    j1 = np.searchsorted(ys, high[:, 0], side="right")
    k0 = np.searchsorted(zs, low[:, 1], side="left")
    k1 = np.searchsorted(zs, high[:, 1], side="right")
    nj, nk = np.maximum(j1 - j0, 0), np.maximum(k1 - k0, 0)
    counts = nj * nk
    face = np.repeat(np.arange(len(faces)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    j = j0[face] + local // np.maximum(nk[face], 1)
    k = k0[face] + local % np.maximum(nk[face], 1)
    a, b, c = (corners[face, m] for m in range(3))
    y, z = ys[j], zs[k]
    # barycentric coordinates of (y, z) in the projected triangle
    det = (b[:, 1] - a[:, 1]) * (c[:, 2] - a[:, 2]) - (c[:, 1] - a[:, 1]) * (b[:, 2] - a[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        u = ((y - a[:, 1]) * (c[:, 2] - a[:, 2]) - (c[:, 1] - a[:, 1]) * (z - a[:, 2])) / det
        v = ((b[:, 1] - a[:, 1]) * (z - a[:, 2]) - (y - a[:, 1]) * (b[:, 2] - a[:, 2])) / det
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)
    x = (a[:, 0] + u * (b[:, 0] - a[:, 0]) + v * (c[:, 0] - a[:, 0]))[hit]
    line = (j * len(zs) + k)[hit]
    # crossings beyond grid point i of the line: those in bins i+1 ... (bin = points before x)
    bins = np.searchsorted(xs, x, side="left")
    histogram = np.zeros((len(ys) * len(zs), len(xs) + 1), dtype=np.int64)
    np.add.at(histogram, (line, bins), 1)
    beyond = np.cumsum(histogram[:, ::-1], axis=1)[:, ::-1][:, 1:]  # (lines, nx)
    return (beyond % 2 == 1).reshape(len(ys), len(zs), len(xs)).transpose(2, 0, 1)


def estimate_tets(
    *,
    volume: float,
    size: float,
    body_size: float | None = None,
    grading: float | None = None,
    bounds: np.ndarray | None = None,
    body_vertices: np.ndarray | None = None,
    body_faces: np.ndarray | None = None,
    body_area: float = 0.0,
    mesher: str = "gmsh",
    labels: tuple[str, str, str] = ("edge_length", "body_edge_length", "grading"),
    cells: int = 24,
) -> TetEstimate:
    """Estimate the number of tetrahedra of a mesh before meshing (see the module doc).

    Parameters
    ----------
    volume : float
        The domain's volume.
    size : float
        The edge length away from the bodies (everywhere when not graded).
    body_size, grading : float, optional
        The edge length on the bodies and the distance over which it grows to ``size``;
        with them, ``bounds``, the bodies' closed triangulation and their area are needed.
    bounds : array, shape (2, 3), optional
        The box the domain fills (the bodies are holes in it).
    body_vertices : array, shape (V, 3), optional
    body_faces : int array, shape (F, 3), optional
        The bodies' surfaces (a coarse triangulation is enough: the distance to it).
    body_area : float
        The bodies' surface area (exact, e.g. from the CAD faces).
    mesher : str
        A key of :data:`TETS_PER_REGULAR`.
    labels : three str
        The names of ``size``, ``body_size`` and ``grading`` in the caller's signature
        (for :func:`check_budget`'s message).
    cells : int
        Grid cells per side of ``bounds``.

    Returns
    -------
    TetEstimate

    Raises
    ------
    ValueError
        If ``body_size`` is below ``size`` and ``grading``, ``bounds``, ``body_vertices``
        or ``body_faces`` is missing.
    """
    factor = TETS_PER_REGULAR[mesher]
    uniform = factor * _INVERSE_REGULAR * volume / size**3
    sizes = {labels[0]: size}
    if body_size is None or body_size >= size:
        return TetEstimate(uniform, uniform, volume, sizes)
    if grading is None or bounds is None or body_vertices is None or body_faces is None:
        raise ValueError(
            "grading, bounds, body_vertices and body_faces are needed with a body_size below size"
        )
    sizes.update({labels[1]: body_size, labels[2]: grading})
    bounds = np.asarray(bounds, dtype=np.float64)
    step = (bounds[1] - bounds[0]) / cells
    # cell centres, nudged off the bodies' symmetry planes (see _inside_grid)
    axes = [
        bounds[0, k] + step[k] * (np.arange(cells) + 0.5 + 1e-4 * math.sqrt(2 + k))
        for k in range(3)
    ]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    from scipy.spatial import cKDTree

    # distances to points a quarter of a cell apart: at the cells used (d >= depth, below)
    # within (s / √2)² / 2d < 2 % of a cell of the distance to the surface
    samples = _surface_samples(body_vertices, body_faces, float(step.min()) / 4)
    outside = ~_inside_grid(axes, body_vertices, body_faces).reshape(-1)
    # beyond the grading distance the size is the edge length: no need to know how far
    distance = np.full(len(centres), np.inf)
    distance[outside] = cKDTree(samples).query(centres[outside], distance_upper_bound=grading)[0]
    depth = 0.5 * float(np.linalg.norm(step))  # a cell centre farther than this: off the layer
    far = outside & (distance >= depth)
    cell = float(np.prod(step))
    h = size_at(distance[far], size, body_size, grading)
    total = cell * float(np.sum(_INVERSE_REGULAR / h**3))
    total += body_area * _layer_integral(depth, size, body_size, grading)
    return TetEstimate(factor * total, uniform, volume, sizes)


def check_budget(estimate: TetEstimate, max_elements: int | None) -> None:
    """Raise ``ValueError`` when ``estimate.total`` is above ``max_elements`` (None: no limit).

    The message starts with the size to raise (the body size when the grading near the
    bodies costs more than the rest) and says about how far to raise it.
    """
    if max_elements is None or estimate.total <= max_elements:
        return
    labels = list(estimate.sizes)
    graded = estimate.total - estimate.uniform  # what the finer sizes near the bodies add
    if len(labels) == 3 and graded > estimate.uniform:
        label = labels[1]  # the layer near the bodies costs ~ area / h_b²
        room = max(max_elements - estimate.uniform, 0.1 * max_elements)
        suggestion = estimate.sizes[label] * math.sqrt(graded / room)
        also = f" (or shorten {labels[2]})"
    else:
        label = labels[0]  # the volume costs ~ volume / h³
        room = max(max_elements - graded, 0.1 * max_elements)
        suggestion = estimate.sizes[label] * (estimate.uniform / room) ** (1 / 3)
        also = ""
    sizes = ", ".join(f"{name} {value:.3g}" for name, value in estimate.sizes.items())
    raise ValueError(
        f"{label}: the mesh would have about {estimate.total:.2g} tetrahedra (estimated from "
        f"the domain's volume {estimate.volume:.3g} and {sizes}), more than max_elements = "
        f"{max_elements:,}; raise {label} to about {suggestion:.2g}{also}, or raise "
        "max_elements (None: no limit) to mesh it anyway"
    )
