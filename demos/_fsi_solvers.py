"""The finite-element solvers and interface maps of demos/fsi.py (not part of the library).

- :class:`PotentialFlow`: incompressible, irrotational flow around the wing in the
  tunnel, P1 on the fluid tetrahedra, assembled by scikit-fem on the *current*
  (morphed) node coordinates at every solve; the wing load is the Bernoulli pressure.
- :class:`Elasticity`: linear elasticity of the wing, P1 vector field on its own
  tetrahedral mesh, clamped at the root, assembled by scikit-fem and factorised once
  (small deformations: the stiffness stays that of the reference wing).
- :class:`SurfaceMap`: the two meshes discretise the same wing surface with different
  triangles; the map takes a structural field to points of the fluid's wing surface by
  linear interpolation on the closest structural surface triangle, and its transpose
  takes fluid forces back to structural nodes, conserving the total force and the
  work of the interface (the usual consistent/conservative pair of partitioned FSI).
- :class:`Aitken`: dynamic under-relaxation of the interface displacement for the
  block Gauss–Seidel coupling (Küttler and Wall, 2008).

scikit-fem (the ``fsi`` extra) is imported here only, so that the demo can refuse
clearly without it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg
from scipy.spatial import cKDTree

try:
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity
    from skfem.models.poisson import laplace
except ImportError as error:  # pragma: no cover - the demo checks this first
    raise ImportError(
        "demos/fsi.py needs scikit-fem: pip install -e '.[fsi]' (or pip install scikit-fem)"
    ) from error

__all__ = [
    "Aitken",
    "Elasticity",
    "FlowSolution",
    "PotentialFlow",
    "SurfaceMap",
    "closest_points_on_triangles",
    "tet_faces",
]

# the four faces of a tetrahedron (a b c d), each ordered so that its right-hand
# normal points away from the opposite vertex when the tetrahedron is positive
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def tet_faces(tets: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The tetrahedron that owns each of ``faces`` (boundary faces, (F, 3)), shape (F,)."""
    if len(faces) == 0:
        return np.zeros(0, dtype=np.int64)
    all_faces = np.sort(tets[:, _TET_FACES].reshape(-1, 3), axis=1)
    wanted = np.sort(faces, axis=1)
    n = int(max(tets.max(), faces.max())) + 1
    key_all = (all_faces[:, 0] * n + all_faces[:, 1]) * n + all_faces[:, 2]
    key_wanted = (wanted[:, 0] * n + wanted[:, 1]) * n + wanted[:, 2]
    order = np.argsort(key_all)
    position = np.searchsorted(key_all[order], key_wanted)
    found = order[np.minimum(position, len(order) - 1)]
    if not np.array_equal(key_all[found], key_wanted):
        raise ValueError("faces: some faces belong to no tetrahedron of tets")
    return found // 4


def _area_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted normals of triangles (right-hand rule), shape (F, 3)."""
    a, b, c = (points[faces[:, k]] for k in range(3))
    return 0.5 * np.cross(b - a, c - a)


def closest_points_on_triangles(
    query: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> np.ndarray:
    """Barycentric coordinates (n, 3) of the point of triangle (a, b, c) closest to ``query``.

    Row by row (all arrays (n, 3)); the regions of Ericson, *Real-Time Collision
    Detection* (2005), section 5.1.5, vectorised: a vertex, an edge or the inside.
    """
    ab, ac = b - a, c - a
    ap, bp, cp = query - a, query - b, query - c
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        total = va + vb + vc
        v, w = vb / total, vc / total
        weights = np.stack([1 - v - w, v, w], axis=1)  # inside
        # later assignments win: the order is the reverse of Ericson's tests
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        weights[on_bc] = np.stack([0 * t, 1 - t, t], axis=1)[on_bc]
        t = d2 / (d2 - d6)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        weights[on_ac] = np.stack([1 - t, 0 * t, t], axis=1)[on_ac]
        weights[(d6 >= 0) & (d5 <= d6)] = (0.0, 0.0, 1.0)
        t = d1 / (d1 - d3)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        weights[on_ab] = np.stack([1 - t, t, 0 * t], axis=1)[on_ab]
        weights[(d3 >= 0) & (d4 <= d3)] = (0.0, 1.0, 0.0)
        weights[(d1 <= 0) & (d2 <= 0)] = (1.0, 0.0, 0.0)
    return weights


class SurfaceMap:
    """Linear interpolation from a triangulated surface's nodes to points near it.

    Each query point is projected onto the closest of the surface triangles (searched
    among the ``candidates`` triangles with the nearest centroids) and takes the
    barycentric blend of that triangle's nodal values. :attr:`matrix` (n_query ×
    n_nodes, rows summing to 1) interpolates a nodal field; its transpose spreads point
    forces onto the nodes with the same total force, so the interface does no spurious
    work (the conservative map of partitioned FSI). :attr:`gaps` are the distances
    from the query points to the surface: how far apart the two discretisations are.
    """

    def __init__(
        self,
        nodes: np.ndarray,
        triangles: np.ndarray,
        query: np.ndarray,
        *,
        num_nodes: int,
        candidates: int = 12,
    ) -> None:
        if len(triangles) == 0 or len(query) == 0:
            raise ValueError("SurfaceMap: triangles and query points must not be empty")
        corners = nodes[triangles]  # (T, 3, 3)
        tree = cKDTree(corners.mean(axis=1))
        k = min(candidates, len(triangles))
        _, nearest = tree.query(query, k=k)
        nearest = nearest.reshape(len(query), k)
        best_distance = np.full(len(query), np.inf)
        best_triangle = np.zeros(len(query), dtype=np.int64)
        best_weights = np.zeros((len(query), 3))
        for j in range(k):
            triangle = nearest[:, j]
            a, b, c = (corners[triangle, m] for m in range(3))
            weights = closest_points_on_triangles(query, a, b, c)
            closest = weights[:, :1] * a + weights[:, 1:2] * b + weights[:, 2:] * c
            distance = np.linalg.norm(closest - query, axis=1)
            better = distance < best_distance
            best_distance[better] = distance[better]
            best_triangle[better] = triangle[better]
            best_weights[better] = weights[better]
        rows = np.repeat(np.arange(len(query)), 3)
        columns = triangles[best_triangle].reshape(-1)
        self.matrix = sparse.csr_matrix(
            (best_weights.reshape(-1), (rows, columns)), shape=(len(query), num_nodes)
        )
        self.gaps = best_distance

    def interpolate(self, field: np.ndarray) -> np.ndarray:
        """Nodal field (n_nodes, D) -> values at the query points (n_query, D)."""
        return self.matrix @ field

    def spread(self, forces: np.ndarray) -> np.ndarray:
        """Point forces (n_query, D) -> nodal forces (n_nodes, D), same total force."""
        return self.matrix.T @ forces


@dataclass
class FlowSolution:
    """One potential-flow solve: the potential, the wing load and what it cost."""

    potential: np.ndarray  # (N,) velocity potential at the nodes
    pressure: np.ndarray  # (F_w,) Bernoulli gauge pressure on each wing face
    forces: np.ndarray  # (F_w, 3) force of the flow on each wing face [N]
    centroids: np.ndarray  # (F_w, 3) the wing faces' centroids (current geometry)
    assembly_seconds: float
    solve_seconds: float


class PotentialFlow:
    """Potential flow past the wing in the tunnel, P1 finite elements (scikit-fem).

    Solves Δφ = 0 in the fluid with the free stream's normal velocity
    ∂φ/∂n = U∞·n on the tunnel walls (so that far from the wing the flow is the
    free stream U∞ = |U∞| (cos α, sin α, 0), at the angle of attack α) and
    ∂φ/∂n = 0 on the wing; φ is fixed at one wall node. The wing load is the
    Bernoulli gauge pressure p = ½ ρ (|U∞|² − |∇φ|²), with the velocity of the fluid
    cell on each wing face. Without a wake or a Kutta condition the flow carries no
    circulation, so there is no lift: the load is the suction and stagnation pressure
    distribution, whose resultant is a moment (Munk's moment, nose up for α > 0) that
    twists the wing — and grows with the twist it causes, the static aeroelastic
    coupling that a one-way analysis misses.

    Parameters
    ----------
    tets : (M, 4) int array
        The fluid tetrahedra (positively oriented in the reference mesh).
    wall_faces, wing_faces : (F, 3) int arrays
        Boundary faces of the tunnel walls and of the wing, ordered with the normal out
        of the fluid.
    num_nodes : int
    velocity : (3,) array
        U∞ [m/s].
    density : float
        ρ [kg/m³].
    """

    def __init__(
        self,
        tets: np.ndarray,
        wall_faces: np.ndarray,
        wing_faces: np.ndarray,
        num_nodes: int,
        *,
        velocity: np.ndarray,
        density: float,
    ) -> None:
        self.tets = np.ascontiguousarray(tets, dtype=np.int64)
        self.wall_faces = wall_faces
        self.wing_faces = wing_faces
        self.wing_cells = tet_faces(self.tets, wing_faces)
        self.num_nodes = num_nodes
        self.velocity = np.asarray(velocity, dtype=np.float64)
        self.density = float(density)
        self.pinned = int(wall_faces[0, 0])

    def _inflow(self, points: np.ndarray) -> np.ndarray:
        """Load vector of the wall condition ∂φ/∂n = U∞·n: (U∞·n) A / 3 per corner."""
        flux = _area_normals(points, self.wall_faces) @ self.velocity
        if abs(flux.sum()) > 1e-9 * max(np.abs(flux).sum(), 1e-300):
            raise ValueError(
                "wall_faces: the free stream's flux through them does not balance "
                f"(net {flux.sum():.3g} m³/s), so no potential flow exists; the walls must "
                "enclose the flow with the wing's faces, where the normal velocity is 0"
            )
        load = np.zeros(self.num_nodes)
        for k in range(3):
            np.add.at(load, self.wall_faces[:, k], flux / 3.0)
        return load

    def solve(self, points: np.ndarray, guess: np.ndarray | None = None) -> FlowSolution:
        """Solve on the mesh with node coordinates ``points`` (N, 3) (reference or morphed)."""
        start = time.perf_counter()
        mesh = skfem.MeshTet(np.ascontiguousarray(points.T), self.tets.T, validate=False)
        basis = skfem.Basis(mesh, skfem.ElementTetP1())
        stiffness = skfem.asm(laplace, basis).tocsr()
        load = self._inflow(points)
        assembled = time.perf_counter()
        free = np.ones(self.num_nodes, dtype=bool)
        free[self.pinned] = False
        reduced = stiffness[free][:, free]
        potential = np.zeros(self.num_nodes)
        start_vector = None if guess is None else guess[free]
        solution, info = sparse_linalg.cg(
            reduced,
            load[free],
            x0=start_vector,
            rtol=1e-10,
            maxiter=20 * self.num_nodes,
            M=sparse.diags(1.0 / reduced.diagonal()),
        )
        if info != 0:
            raise RuntimeError(f"potential flow: CG did not converge (info {info})")
        potential[free] = solution
        solved = time.perf_counter()
        gradient = self._cell_gradients(points, potential, self.wing_cells)
        speed2 = (gradient**2).sum(axis=1)
        pressure = 0.5 * self.density * (self.velocity @ self.velocity - speed2)
        normals = _area_normals(points, self.wing_faces)  # out of the fluid: into the wing
        forces = pressure[:, None] * normals
        return FlowSolution(
            potential=potential,
            pressure=pressure,
            forces=forces,
            centroids=points[self.wing_faces].mean(axis=1),
            assembly_seconds=assembled - start,
            solve_seconds=solved - assembled,
        )

    def _cell_gradients(self, points: np.ndarray, values: np.ndarray, cells: np.ndarray):
        """∇ of the P1 field ``values`` in each of ``cells``, shape (len(cells), 3)."""
        corners = points[self.tets[cells]]  # (n, 4, 3)
        edges = corners[:, 1:] - corners[:, :1]  # rows: the edges from corner 0
        rises = values[self.tets[cells][:, 1:]] - values[self.tets[cells][:, :1]]
        return np.linalg.solve(edges, rises[..., None])[..., 0]


class Elasticity:
    """Linear elasticity of the wing, P1 tetrahedra (scikit-fem), clamped nodes fixed.

    The stiffness is assembled on the reference wing and factorised once (sparse LU):
    each coupling iteration is one pair of triangular solves.

    Parameters
    ----------
    points : (N, 3) array
    tets : (M, 4) int array
    clamped : int array
        Nodes held at zero displacement (the root).
    young, poisson : float
        E [Pa] and ν.
    """

    def __init__(
        self,
        points: np.ndarray,
        tets: np.ndarray,
        clamped: np.ndarray,
        *,
        young: float,
        poisson: float,
    ) -> None:
        start = time.perf_counter()
        mesh = skfem.MeshTet(np.ascontiguousarray(points.T), np.ascontiguousarray(tets.T))
        self.basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP1()))
        stiffness = skfem.asm(linear_elasticity(*lame_parameters(young, poisson)), self.basis)
        self.num_nodes = len(points)
        self.nodal_dofs = self.basis.nodal_dofs  # (3, N): the dof of (component, node)
        fixed = self.nodal_dofs[:, clamped].reshape(-1)
        self.free = np.setdiff1d(np.arange(self.basis.N), fixed)
        self.factor = sparse_linalg.splu(stiffness.tocsc()[self.free][:, self.free].tocsc())
        self.stiffness = stiffness
        self.setup_seconds = time.perf_counter() - start

    def solve(self, forces: np.ndarray) -> np.ndarray:
        """Nodal forces (N, 3) [N] -> nodal displacements (N, 3) [m]."""
        load = np.zeros(self.basis.N)
        load[self.nodal_dofs.T.reshape(-1)] = forces.reshape(-1)
        displacement = np.zeros(self.basis.N)
        displacement[self.free] = self.factor.solve(load[self.free])
        return displacement[self.nodal_dofs].T.copy()


class Aitken:
    """Aitken's dynamic relaxation of a fixed-point iteration x ← x + ω r (Küttler–Wall).

    ω_{k+1} = −ω_k (r_kᵀ (r_{k+1} − r_k)) / |r_{k+1} − r_k|², started at ``initial``
    and kept within [``-maximum``, ``maximum``].
    """

    def __init__(self, initial: float = 0.5, maximum: float = 1.5) -> None:
        if not 0 < initial <= 1:
            raise ValueError(f"initial relaxation must be in (0, 1], got {initial}")
        self.omega = float(initial)
        self.maximum = float(maximum)
        self._previous: np.ndarray | None = None

    def step(self, residual: np.ndarray) -> float:
        """The relaxation factor to apply to ``residual`` (and remember it)."""
        r = residual.reshape(-1)
        if self._previous is not None:
            change = r - self._previous
            denominator = float(change @ change)
            if denominator > 0:
                omega = -self.omega * float(self._previous @ change) / denominator
                self.omega = float(np.clip(omega, -self.maximum, self.maximum))
        self._previous = r.copy()
        return self.omega
