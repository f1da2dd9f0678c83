"""From boundary patches to exact boundary nodes and named node sets.

Both meshers end the same way: they report, for each boundary *patch* (a box
wall, the wing's upper or lower side, an end face, a side of the hull), the
nodes lying on it (its edges included). The functions here project those nodes
onto the exact analytic surface of :mod:`data_gen.geometry` and derive the
node sets of each case from the patches. Nodes on two patches are on the
curve where they meet (an end profile, the leading or trailing edge, a keel,
the stem): they are projected onto that curve.
"""

from __future__ import annotations

import numpy as np

from data_gen.geometry import (
    BOX_WALLS,
    CHORD,
    HULL_DRAFT,
    HULL_LENGTH,
    SPAN,
    project_to_profile,
    wigley_half_breadth,
)

__all__ = ["HULL_PATCHES", "WALL_PATCHES", "WING_PATCHES", "finish_hull", "finish_wing"]

WALL_PATCHES = tuple(name for name, _, _ in BOX_WALLS)
#: Patches of the wing's surface: its two sides and its two end faces.
WING_PATCHES = ("upper", "lower", "root", "tip")
#: Patches of the hull's surface: the sides z > 0 and z < 0.
HULL_PATCHES = ("starboard", "port")


def _union(*arrays: np.ndarray | None) -> np.ndarray:
    present = [a for a in arrays if a is not None]
    if not present:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(present)).astype(np.int64)


def _node_tets(tets: np.ndarray, num_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR map node -> tetrahedra containing it: (offsets (N+1,), tet ids)."""
    nodes = tets.ravel()
    order = np.argsort(nodes, kind="stable")
    offsets = np.zeros(num_nodes + 1, dtype=np.int64)
    np.add.at(offsets, nodes + 1, 1)
    return np.cumsum(offsets), order // 4


def _select_line_nodes(
    candidates: np.ndarray, gaps: np.ndarray, node_tets, shortest: np.ndarray
) -> np.ndarray:
    """Greedy choice, nearest first, of candidates to put onto one straight edge line.

    Used for surfaces that only approximate a sharp edge (fTetWild), where the
    nodes between the two sides form a zigzag band rather than a line. A
    candidate is refused when a tetrahedron containing it already holds two
    chosen nodes (three nodes of one tetrahedron on a line would make it flat),
    or when the move (``gaps``) exceeds half its shortest edge (``shortest``),
    which would fold its elements over; this happens where the body is thinner
    than fTetWild's envelope and its surface cuts the edge off. If every
    candidate is that far, the nearest one is still chosen, so that the line
    has a node.
    """
    offsets, tet_ids = node_tets
    on_line: dict[int, int] = {}
    chosen = []
    near = gaps <= 0.5 * shortest[candidates]
    if not near.any() and len(candidates):
        near = gaps == gaps.min()  # keep the line's node set non-empty: its nearest node
    candidates, gaps = candidates[near], gaps[near]
    for node in candidates[np.argsort(gaps, kind="stable")]:
        tets = tet_ids[offsets[node] : offsets[node + 1]]
        if any(on_line.get(int(t), 0) >= 2 for t in tets):
            continue
        for t in tets:
            on_line[int(t)] = on_line.get(int(t), 0) + 1
        chosen.append(node)
    return np.sort(np.asarray(chosen, dtype=np.int64))


def _shortest_edges(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Length of the shortest mesh edge at each node, shape (N,) (inf for unused nodes)."""
    pairs = tets[:, [0, 0, 0, 1, 1, 2]], tets[:, [1, 2, 3, 2, 3, 3]]
    a, b = pairs[0].ravel(), pairs[1].ravel()
    length = np.linalg.norm(points[a] - points[b], axis=1)
    shortest = np.full(len(points), np.inf)
    np.minimum.at(shortest, a, length)
    np.minimum.at(shortest, b, length)
    return shortest


def _snap_walls(points: np.ndarray, patches: dict[str, np.ndarray], bounds) -> None:
    for name, axis, side in BOX_WALLS:
        if name in patches:
            points[patches[name], axis] = bounds[side][axis]


def finish_wing(
    points: np.ndarray,
    patches: dict[str, np.ndarray],
    *,
    tunnel_bounds=None,
    tets: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Project the boundary nodes of case A or B and name its node sets.

    Parameters
    ----------
    points : array, shape (N, 3)
        Node coordinates (not modified).
    patches : dict of str to int array
        Nodes of each patch: "upper", "lower", "tip", and "root" (case A) or
        the six walls "wall_x0" … "wall_z1" (case B, the root lies on wall_z0).
    tunnel_bounds : ((x0, y0, z0), (x1, y1, z1)), optional
        The tunnel box of case B; None for the wing alone.
    tets : int array, shape (M, 4), optional
        Give the tetrahedra when the mesh's surface only approximates the
        sharp edges (fTetWild): the nodes shared by the upper and lower sides
        then form a band, and only some of them (:func:`_select_line_nodes`)
        are moved onto the leading and trailing edge lines; the others go onto
        their side of the profile.

    Returns
    -------
    points : array, shape (N, 3)
        Coordinates with every boundary node on the exact surface.
    node_sets : dict of str to int64 array
    """
    points = np.array(points, dtype=np.float64, copy=True)
    upper, lower, tip = patches["upper"], patches["lower"], patches["tip"]
    root = patches["wall_z0"] if tunnel_bounds is not None else patches["root"]
    # planes first (they fix z), then the profile (it fixes x and y): independent coordinates
    if tunnel_bounds is not None:
        _snap_walls(points, patches, tunnel_bounds)
    else:
        points[root, 2] = 0.0
    points[tip, 2] = SPAN
    on_upper = np.zeros(len(points), dtype=bool)
    on_lower = np.zeros(len(points), dtype=bool)
    on_upper[upper] = True
    on_lower[lower] = True
    edge = np.flatnonzero(on_upper & on_lower)
    if tets is not None:
        node_tets = _node_tets(tets, len(points))
        shortest = _shortest_edges(points, tets)
        front = edge[points[edge, 0] < CHORD / 2]
        back = edge[points[edge, 0] >= CHORD / 2]
        front_gap = np.hypot(points[front, 0], points[front, 1])
        back_gap = np.hypot(points[back, 0] - CHORD, points[back, 1])
        kept = np.concatenate(
            [
                _select_line_nodes(front, front_gap, node_tets, shortest),
                _select_line_nodes(back, back_gap, node_tets, shortest),
            ]
        )
        refused = np.setdiff1d(edge, kept)
        above = points[refused, 1] >= 0
        on_lower[refused[above]] = False
        on_upper[refused[~above]] = False
        edge = kept
        upper, lower = np.flatnonzero(on_upper), np.flatnonzero(on_lower)
    for nodes, side in (
        (np.flatnonzero(on_upper & ~on_lower), 1.0),
        (np.flatnonzero(on_lower & ~on_upper), -1.0),
    ):
        px, py = project_to_profile(points[nodes, 0], points[nodes, 1], np.full(len(nodes), side))
        points[nodes, 0], points[nodes, 1] = px, py
    leading = edge[points[edge, 0] < CHORD / 2]
    trailing = edge[points[edge, 0] >= CHORD / 2]
    points[leading, 0] = 0.0
    points[trailing, 0] = CHORD
    points[edge, 1] = 0.0

    wing_sides = _union(upper, lower)
    sets = {
        "upper": _union(upper),
        "lower": _union(lower),
        "tip": _union(tip),
        "tip_profile": np.intersect1d(tip, wing_sides),
        "root_profile": np.intersect1d(root, wing_sides),
        "leading_edge": _union(leading),
        "trailing_edge": _union(trailing),
    }
    if tunnel_bounds is None:
        sets["root"] = _union(root)
        sets["wing"] = _union(upper, lower, tip, root)
    else:
        sets["wing"] = _union(upper, lower, tip)
        for name in WALL_PATCHES:
            sets[name] = _union(patches[name])
    return points, sets


_HALF_LENGTH = HULL_LENGTH / 2.0
# (name, axis, value) of the four sharp edges of the double body, all in the plane z = 0
_HULL_EDGES = (
    ("stem", 0, _HALF_LENGTH),
    ("stern", 0, -_HALF_LENGTH),
    ("keel", 1, -HULL_DRAFT),
    ("keel_top", 1, HULL_DRAFT),
)


def finish_hull(
    points: np.ndarray,
    patches: dict[str, np.ndarray],
    *,
    box_bounds,
    tets: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Project the boundary nodes of case C and name its node sets.

    Parameters
    ----------
    points : array, shape (N, 3)
        Node coordinates (not modified).
    patches : dict of str to int array
        Nodes of "starboard" (z >= 0), "port" (z <= 0) and the six walls.
    box_bounds : ((x0, y0, z0), (x1, y1, z1))
        The box around the hull.
    tets : int array, shape (M, 4), optional
        Give the tetrahedra when the mesh's surface only approximates the
        sharp edges (fTetWild): only some of the nodes shared by the two sides
        are then moved onto the edge lines (as in :func:`finish_wing`), and
        the edge node nearest to each of the hull's four corners is moved onto
        the corner. gmsh meshes have nodes on the edges and corners already.

    Returns
    -------
    points : array, shape (N, 3)
    node_sets : dict of str to int64 array
        The walls, "hull", "starboard", "port", the edges "stem" (x = L/2),
        "stern" (x = -L/2), "keel" (y = -T), "keel_top" (y = +T, the keel's
        mirror image: the top edge of the double body) and their union
        "hull_edges".
    """
    points = np.array(points, dtype=np.float64, copy=True)
    _snap_walls(points, patches, box_bounds)
    starboard, port = patches["starboard"], patches["port"]
    on_starboard = np.zeros(len(points), dtype=bool)
    on_port = np.zeros(len(points), dtype=bool)
    on_starboard[starboard] = True
    on_port[port] = True
    edge = np.flatnonzero(on_starboard & on_port)
    if tets is not None:
        node_tets = _node_tets(tets, len(points))
        shortest = _shortest_edges(points, tets)
        gaps = np.stack(
            [
                np.hypot(points[edge, axis] - value, points[edge, 2])
                for _, axis, value in _HULL_EDGES
            ],
            axis=1,
        )
        nearest = np.argmin(gaps, axis=1)
        kept = np.unique(
            np.concatenate(
                [
                    _select_line_nodes(
                        edge[nearest == k], gaps[nearest == k, k], node_tets, shortest
                    )
                    for k in range(len(_HULL_EDGES))
                ]
            )
        )
        refused = np.setdiff1d(edge, kept)
        positive = points[refused, 2] >= 0
        on_port[refused[positive]] = False
        on_starboard[refused[~positive]] = False
        edge = kept
        starboard, port = np.flatnonzero(on_starboard), np.flatnonzero(on_port)

    # sides: keep (x, y) inside the hull's rectangle, put z on the surface
    for nodes, side in (
        (np.flatnonzero(on_starboard & ~on_port), 1.0),
        (np.flatnonzero(on_port & ~on_starboard), -1.0),
    ):
        x = np.clip(points[nodes, 0], -_HALF_LENGTH, _HALF_LENGTH)
        y = np.clip(points[nodes, 1], -HULL_DRAFT, HULL_DRAFT)
        points[nodes, 0], points[nodes, 1] = x, y
        points[nodes, 2] = side * wigley_half_breadth(x, y)

    # edges: z = 0 and onto the nearest of the four edge lines
    points[edge, 2] = 0.0
    points[edge, 0] = np.clip(points[edge, 0], -_HALF_LENGTH, _HALF_LENGTH)
    points[edge, 1] = np.clip(points[edge, 1], -HULL_DRAFT, HULL_DRAFT)
    gaps = np.stack([np.abs(points[edge, axis] - value) for _, axis, value in _HULL_EDGES], axis=1)
    nearest = np.argmin(gaps, axis=1)
    for k, (_, axis, value) in enumerate(_HULL_EDGES):
        points[edge[nearest == k], axis] = value
    if tets is not None and len(edge):
        # a corner takes the nearest edge node, if that is near: moving a node by more than
        # a fraction of its shortest edge would fold its elements over
        for x_corner in (-_HALF_LENGTH, _HALF_LENGTH):
            for y_corner in (-HULL_DRAFT, HULL_DRAFT):
                gap = np.hypot(points[edge, 0] - x_corner, points[edge, 1] - y_corner)
                nearest_node = np.argmin(gap)
                node = edge[nearest_node]
                if gap[nearest_node] <= 0.3 * shortest[node]:
                    points[node, 0], points[node, 1] = x_corner, y_corner

    tolerance = 1e-9 * HULL_LENGTH
    sets = {name: _union(patches[name]) for name in WALL_PATCHES}
    sets["hull"] = _union(starboard, port)
    sets["starboard"] = _union(starboard)
    sets["port"] = _union(port)
    edge_sets = []
    for name, axis, value in _HULL_EDGES:
        sets[name] = _union(edge[np.abs(points[edge, axis] - value) <= tolerance])
        edge_sets.append(sets[name])
    sets["hull_edges"] = _union(*edge_sets)
    return points, sets
