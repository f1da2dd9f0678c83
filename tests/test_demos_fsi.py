"""The FSI demo: its solvers and maps against closed forms, and the coupled run.

demos/_fsi_solvers.py is checked where the answer is exact: uniform potential flow
(P1 reproduces a linear potential, so the Bernoulli pressure vanishes), uniaxial tension
of a bar with ν = 0 (a linear displacement, reproduced by P1), closest points on
triangles against the minimum over a triangle's plane, edges and vertices, linear
fields carried exactly by the surface map and forces conserved by its transpose, and
Aitken's relaxation solving a scalar-multiple fixed point in one relaxed step. The
coupled demo must converge at size small with each morph, agree across them, keep every
fluid cell valid, and spend under 5 % of an iteration in the POD morph.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("skfem")

DEMOS = Path(__file__).resolve().parents[1] / "demos"
sys.path.insert(0, str(DEMOS))

import _fsi_solvers as fsi  # noqa: E402

from torchmorph.mesh import box_mesh  # noqa: E402


def _faces_in(mesh, names):
    faces = mesh.boundary_faces.numpy()
    chosen = np.zeros(len(faces), dtype=bool)
    for name in names:
        member = np.zeros(mesh.num_nodes, dtype=bool)
        member[mesh.node_set(name).numpy()] = True
        chosen |= member[faces].all(axis=1)
    return faces[chosen]


def test_uniform_potential_flow_is_exact_and_leaves_no_load():
    mesh = box_mesh((4, 3, 3), (2.0, 1.0, 1.0))
    velocity = np.array([2.0, 0.0, 0.5])
    flow = fsi.PotentialFlow(
        mesh.tets.numpy(),
        _faces_in(mesh, ("x0", "x1", "z0", "z1")),
        _faces_in(mesh, ("y0", "y1")),  # no-flux faces: U∞·n = 0 there anyway
        mesh.num_nodes,
        velocity=velocity,
        density=1.2,
    )
    points = mesh.points.numpy()
    solution = flow.solve(points)
    expected = points @ velocity
    expected += solution.potential[flow.pinned] - expected[flow.pinned]
    np.testing.assert_allclose(solution.potential, expected, atol=1e-8)
    assert np.abs(solution.pressure).max() < 1e-7
    np.testing.assert_allclose(solution.forces.sum(axis=0), 0.0, atol=1e-8)


def test_potential_flow_refuses_walls_whose_flux_does_not_balance():
    # flow towards a no-flux face x1 with no outflow: no potential exists
    mesh = box_mesh((4, 2, 2), (2.0, 1.0, 1.0))
    flow = fsi.PotentialFlow(
        mesh.tets.numpy(),
        _faces_in(mesh, ("x0", "y0", "y1", "z0", "z1")),
        _faces_in(mesh, ("x1",)),
        mesh.num_nodes,
        velocity=np.array([1.0, 0.0, 0.0]),
        density=2.0,
    )
    with pytest.raises(ValueError, match="wall_faces: the free stream's flux"):
        flow.solve(mesh.points.numpy())


def test_bar_in_tension_with_zero_poisson_ratio_is_exact():
    length, young, traction = 4.0, 2.0e5, 3.0e3
    mesh = box_mesh((8, 2, 2), (length, 1.0, 1.0))
    points = mesh.points.numpy()
    structure = fsi.Elasticity(
        points, mesh.tets.numpy(), mesh.node_set("x0").numpy(), young=young, poisson=0.0
    )
    forces = np.zeros_like(points)
    for face in _faces_in(mesh, ("x1",)):
        a, b, c = points[face]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a))
        forces[face, 0] += traction * area / 3.0
    displacement = structure.solve(forces)
    np.testing.assert_allclose(displacement[:, 0], traction * points[:, 0] / young, atol=1e-12)
    np.testing.assert_allclose(displacement[:, 1:], 0.0, atol=1e-12)


def _closest_by_candidates(query, a, b, c):
    """The closest point as the nearest of the projection onto the plane (when inside),
    the three clamped edge projections and the three vertices."""
    best, best_distance = None, np.inf
    normal = np.cross(b - a, c - a)
    projected = query - np.dot(query - a, normal) / np.dot(normal, normal) * normal
    matrix = np.stack([b - a, c - a], axis=1)
    (v, w), *_ = np.linalg.lstsq(matrix, projected - a, rcond=None)
    candidates = [a, b, c]
    if v >= 0 and w >= 0 and v + w <= 1:
        candidates.append(projected)
    for p, q in ((a, b), (b, c), (a, c)):
        t = np.clip(np.dot(query - p, q - p) / np.dot(q - p, q - p), 0.0, 1.0)
        candidates.append(p + t * (q - p))
    for point in candidates:
        distance = np.linalg.norm(point - query)
        if distance < best_distance:
            best, best_distance = point, distance
    return best


def test_closest_points_on_triangles_match_the_candidate_minimum():
    rng = np.random.default_rng(3)
    a, b, c = (rng.normal(size=(400, 3)) for _ in range(3))
    query = 2.0 * rng.normal(size=(400, 3))
    weights = fsi.closest_points_on_triangles(query, a, b, c)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-12)
    assert weights.min() >= -1e-12
    closest = weights[:, :1] * a + weights[:, 1:2] * b + weights[:, 2:] * c
    expected = np.array(
        [_closest_by_candidates(*rows) for rows in zip(query, a, b, c, strict=True)]
    )
    np.testing.assert_allclose(closest, expected, atol=1e-9)


def test_surface_map_carries_linear_fields_and_conserves_forces():
    mesh = box_mesh(3, (1.0, 2.0, 0.5))
    points = mesh.points.numpy()
    faces = mesh.boundary_faces.numpy()
    rng = np.random.default_rng(0)
    chosen = rng.integers(0, len(faces), size=300)
    bary = rng.dirichlet(np.ones(3), size=300)
    on_surface = np.einsum("qk,qkd->qd", bary, points[faces[chosen]])
    surface_map = fsi.SurfaceMap(points, faces, on_surface, num_nodes=mesh.num_nodes)
    assert surface_map.gaps.max() < 1e-12
    linear = np.array([[1.0, -2.0, 0.5], [0.3, 0.0, 2.0], [-1.0, 1.0, 1.0]])
    field = points @ linear + np.array([0.1, 0.2, -0.3])
    expected = on_surface @ linear + np.array([0.1, 0.2, -0.3])
    np.testing.assert_allclose(surface_map.interpolate(field), expected, atol=1e-12)
    forces = rng.normal(size=(300, 3))
    np.testing.assert_allclose(surface_map.spread(forces).sum(axis=0), forces.sum(axis=0))
    with pytest.raises(ValueError, match="must not be empty"):
        fsi.SurfaceMap(points, faces[:0], on_surface, num_nodes=mesh.num_nodes)


@pytest.mark.parametrize("contraction", [0.2, -0.5, -0.9])
def test_aitken_solves_a_scalar_multiple_fixed_point_in_one_relaxed_step(contraction):
    # x = c x + b: the secant step of Aitken's factor is ω = 1 / (1 - c), exact at once
    offset = np.array([1.0, -2.0, 0.5])
    fixed_point = offset / (1 - contraction)
    aitken = fsi.Aitken(0.5)
    x = np.zeros(3)
    for _ in range(2):
        residual = contraction * x + offset - x
        x = x + aitken.step(residual) * residual
    np.testing.assert_allclose(aitken.omega, 1 / (1 - contraction), rtol=1e-12)
    np.testing.assert_allclose(x, fixed_point, rtol=1e-12)
    with pytest.raises(ValueError, match="initial relaxation"):
        fsi.Aitken(0.0)


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_fsi_demo_converges_with_every_morph(tmp_path):
    pytest.importorskip("gmsh")
    pytest.importorskip("matplotlib")
    spec = importlib.util.spec_from_file_location("demo_fsi", DEMOS / "fsi.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    result = module.main(["--size", "small", "--out", str(tmp_path), "--quiet"])
    assert result["converged"]
    for record in result["records"].values():
        assert record.residual[-1] < 1e-6
        assert record.iterations <= 15
    one_way_twist, coupled_twist = result["one_way"][1], result["coupled"][1]
    assert 0 < one_way_twist < coupled_twist  # the moment grows with the twist it causes
    assert coupled_twist > 1.1 * one_way_twist
    assert max(result["agreement"].values()) < 1e-4  # the morph moves only the interior
    assert result["inverted"] == 0 and result["min_volume_ratio"] > 0.5
    assert result["morph_share"]["pod-esidw"] < 0.05
    assert result["max_gap"] < 0.02  # the two meshes' wing surfaces
    assert (tmp_path / "fsi.png").stat().st_size > 10_000
    with pytest.raises(SystemExit, match="--morphs"):
        module.main(["--size", "small", "--morphs", "rbf", "--quiet"])
    with pytest.raises(SystemExit, match="--young"):
        module.main(["--size", "small", "--young", "-1", "--quiet"])
