"""The physics-driven shape optimisation demo and its finite-element solve.

demos/_elasticity.py: the torch stiffness matrix equals scikit-fem's assembly (the
independent reference), the sparse solve and the whole compliance pass gradcheck in
float64, and a missing solver names the ``fsi`` extra. demos/physics_optimisation.py:
the thickness family keeps the enclosed volume exactly, and the demo (small mesh)
checks dJ/dμ against central differences, improves the objective on the full IDW morph
and leaves no inverted tetrahedron.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("scipy.sparse.linalg")
skfem = pytest.importorskip("skfem")

from torchmorph.mesh import box_mesh  # noqa: E402
from torchmorph.mesh.quality import signed_volumes  # noqa: E402

DEMOS = Path(__file__).resolve().parents[1] / "demos"

pytestmark = pytest.mark.usefixtures("one_thread")


def load_demo(name: str):
    if str(DEMOS) not in sys.path:
        sys.path.insert(0, str(DEMOS))  # the demos import their private helpers by name
    spec = importlib.util.spec_from_file_location(f"demo_{name}", DEMOS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def elasticity():
    return load_demo("_elasticity")


def skewed_box(cells: int = 2, seed: int = 0):
    """A box mesh with its interior nodes moved at random (no two tets alike)."""
    mesh = box_mesh(cells)
    generator = torch.Generator().manual_seed(seed)
    shift = (
        0.1
        / cells
        * (torch.rand(mesh.points.shape, generator=generator, dtype=torch.float64) - 0.5)
    )
    moved = torch.zeros_like(mesh.points)
    moved[mesh.interior_nodes] = shift[mesh.interior_nodes]
    return mesh, mesh.points + moved


@pytest.mark.parametrize("order", [1, 2])
def test_stiffness_equals_scikit_fem(elasticity, order):
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    mesh, points = skewed_box()
    lame = elasticity.lame_parameters(70e9, 0.33)
    assert lame == pytest.approx(lame_parameters(70e9, 0.33), rel=1e-15)
    space = elasticity.LagrangeSpace.of(mesh, order)
    clamped = space.nodes_within(mesh.node_set("z0"))
    pattern = elasticity.StiffnessPattern.of(space.cells, space.num_nodes, clamped)
    matrices = elasticity.element_stiffness(points, mesh.tets, lame, order=order)
    values = pattern.assemble(matrices)
    element = skfem.ElementTetP1() if order == 1 else skfem.ElementTetP2()
    basis = skfem.Basis(
        skfem.MeshTet(points.numpy().T.copy(), mesh.tets.numpy().T.copy()),
        skfem.ElementVector(element),
    )
    reference = skfem.asm(linear_elasticity(*lame), basis).toarray()
    free = space.skfem_numbering(basis)[pattern.free_dofs.numpy()]
    reference = reference[np.ix_(free, free)]
    ours = pattern.to_scipy(values).toarray()
    assert abs(ours - reference).max() <= 1e-13 * abs(reference).max()
    # the clamped face: 9 nodes (P1), and for P2 also its 16 edges
    assert space.num_nodes - pattern.size // 3 == (9 if order == 1 else 25)


def test_p2_traction_nodes_carry_the_force_of_a_face(elasticity):
    mesh, _ = skewed_box()
    space = elasticity.LagrangeSpace.of(mesh, 2)
    faces = mesh.boundary_faces[:5]
    nodes = space.traction_nodes(faces)
    edges = space.edges[nodes - space.num_vertices]  # (F, 3, 2): the edges' ends
    for face, ends in zip(faces.tolist(), edges.tolist(), strict=True):
        assert sorted(map(tuple, ends)) == sorted(
            tuple(sorted(pair))
            for pair in ((face[0], face[1]), (face[1], face[2]), (face[0], face[2]))
        )


def test_sparse_solve_passes_gradcheck(elasticity):
    mesh, points = skewed_box(1)
    pattern = elasticity.StiffnessPattern.of(mesh.tets, mesh.num_nodes, mesh.node_set("z0"))
    values = pattern.assemble(elasticity.element_stiffness(points, mesh.tets, (1.0, 0.5)))
    rhs = torch.linspace(-1.0, 1.0, pattern.size, dtype=torch.float64)
    values.requires_grad_(True)
    rhs.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda v, f: elasticity.SparseSolve.apply(v, f, pattern), (values, rhs)
    )


@pytest.mark.parametrize("order", [1, 2])
def test_compliance_gradient_to_the_points_passes_gradcheck(elasticity, order):
    mesh, points = skewed_box(1)
    space = elasticity.LagrangeSpace.of(mesh, order)
    clamped = space.nodes_within(mesh.node_set("z0"))
    pattern = elasticity.StiffnessPattern.of(space.cells, space.num_nodes, clamped)
    load = torch.zeros(space.num_nodes, 3, dtype=torch.float64)
    load[space.nodes_within(mesh.node_set("z1")), 0] = 1.0
    load = load.reshape(-1)[pattern.free_dofs]

    def compliance(points):
        matrix = elasticity.element_stiffness(points, mesh.tets, (1.0, 0.5), order=order)
        solution = elasticity.SparseSolve.apply(pattern.assemble(matrix), load, pattern)
        return load @ solution

    assert torch.autograd.gradcheck(compliance, (points.clone().requires_grad_(True),))


def test_p1_gradients_reproduce_a_linear_field(elasticity):
    mesh, points = skewed_box()
    volumes, gradients = elasticity.p1_gradients(points, mesh.tets)
    slope = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)
    values = points @ slope
    recovered = torch.einsum("ma,mak->mk", values[mesh.tets], gradients)
    torch.testing.assert_close(recovered, slope.expand_as(recovered), rtol=0, atol=1e-12)
    torch.testing.assert_close(volumes, signed_volumes(points, mesh.tets), rtol=1e-12, atol=0)


def test_p2_gradients_reproduce_a_quadratic_field(elasticity):
    mesh, points = skewed_box()
    space = elasticity.LagrangeSpace.of(mesh, 2)
    midpoints = points[space.edges].mean(1)
    nodes = torch.cat([points, midpoints])

    def field(x):  # a quadratic, interpolated exactly by P2
        return x[..., 0] ** 2 - 2.0 * x[..., 1] * x[..., 2] + x[..., 2]

    def gradient(x):
        return torch.stack([2.0 * x[..., 0], -2.0 * x[..., 2], 1.0 - 2.0 * x[..., 1]], -1)

    _, gradients, weights = elasticity.shape_gradients(points, mesh.tets, order=2)
    values = field(nodes)[space.cells]  # (M, 10)
    recovered = torch.einsum("ma,mqak->mqk", values, gradients)
    a, b = elasticity.QUADRATURE_A, elasticity.QUADRATURE_B
    barycentric = torch.full((4, 4), b, dtype=torch.float64).fill_diagonal_(a)
    quadrature_points = torch.einsum("qi,mik->mqk", barycentric, points[mesh.tets])
    torch.testing.assert_close(recovered, gradient(quadrature_points), rtol=0, atol=1e-12)
    assert weights.sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="order must be 1 or 2, got 3"):
        elasticity.shape_gradients(points, mesh.tets, order=3)


def test_lame_parameters_name_the_bad_argument(elasticity):
    with pytest.raises(ValueError, match="poisson must lie in"):
        elasticity.lame_parameters(1.0, 0.5)
    with pytest.raises(ValueError, match="young must be positive"):
        elasticity.lame_parameters(0.0, 0.3)


def test_missing_solver_names_the_fsi_extra(elasticity, monkeypatch):
    monkeypatch.setitem(sys.modules, "skfem", None)  # import skfem now raises ImportError
    with pytest.raises(ImportError, match=r"skfem is not importable .*torchmorph\[fsi\]"):
        elasticity.require_solver()


@pytest.fixture(scope="module")
def demo():
    return load_demo("physics_optimisation")


def wing_like_box():
    """A box 1 x 0.2 x 2 (x chord, y thickness around 0, z span from the root z = 0)."""
    mesh = box_mesh(3)
    points = mesh.points * torch.tensor([1.0, 0.2, 2.0], dtype=torch.float64)
    points[:, 1] -= 0.1
    return mesh, points


def test_thickness_family_keeps_the_enclosed_volume(demo):
    from torchmorph import TetMesh

    mesh, points = wing_like_box()
    mesh = TetMesh(points, mesh.tets)
    boundary = mesh.boundary_nodes
    weights = demo.enclosed_volume_weights(mesh, boundary)
    family = demo.SpanwiseThickness(points[boundary], weights, num_bumps=3, span=2.0)
    mu = torch.tensor([[0.5, -0.3, 0.8], [-0.2, 0.4, -0.5]], dtype=torch.float64)
    displacements = family(mu)
    assert displacements.shape == (2, len(boundary), 3)
    assert (displacements[..., [0, 2]] == 0).all()
    for displacement in displacements:  # the interior stays: the sum of volumes is the
        field = torch.zeros_like(points)  # volume enclosed by the boundary all the same
        field[boundary] = displacement
        volume = signed_volumes(points + field, mesh.tets).sum()
        torch.testing.assert_close(volume, mesh.volumes.sum(), rtol=1e-13, atol=0)
    # t(0) = 1: the root section is only scaled by c(μ)
    root = points[boundary, 2] == 0
    torch.testing.assert_close(
        displacements[0, root, 1], (family.scale(mu[0]) - 1.0) * points[boundary][root, 1]
    )


def test_thickness_family_refuses_bad_arguments(demo):
    points = torch.zeros(5, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="num_bumps must be >= 1"):
        demo.SpanwiseThickness(points, torch.ones(5, dtype=torch.float64), num_bumps=0)
    with pytest.raises(ValueError, match=r"volume_weights must have shape \(5,\)"):
        demo.SpanwiseThickness(points, torch.ones(4, dtype=torch.float64), num_bumps=2)
    family = demo.SpanwiseThickness(points, torch.ones(5, dtype=torch.float64), num_bumps=2)
    with pytest.raises(ValueError, match=r"mu must have shape \(2,\) or \(B, 2\)"):
        family(torch.zeros(3, dtype=torch.float64))


@pytest.mark.slow
def test_physics_optimisation_improves_a_valid_wing(demo, tmp_path):
    pytest.importorskip("gmsh")
    pytest.importorskip("matplotlib")
    result = demo.main(
        [
            "--size",
            "small",
            "--out",
            str(tmp_path),
            "--quiet",
            "--repeats",
            "2",
        ]
    )
    # dJ/dμ by autograd through solver, morph and family against central differences
    assert result["fd_error_start"] <= 1e-5
    assert result["fd_error_end"] <= 1e-5  # d(C/C0)/dμ at the optimum
    assert result["fd_error_idw"] <= 1e-5
    # POD-ESIDW is exact on this family; full IDW moves the interior differently
    assert result["num_modes"] == 4
    assert result["pod_error"] < 1e-12
    assert result["gradient_vs_esidw"] < 1e-10
    assert result["gradient_vs_idw"] < 1e-2
    # a stiffer wing, verified on the full IDW morph, every tet valid, volume kept
    assert result["objective_final"] < 0.8 * result["objective_initial"]
    assert result["full_objective_final"] < 0.8 * result["full_objective_initial"]
    assert result["full_compliance_final"] < result["full_compliance_initial"]
    assert result["inverted"] == 0 and result["full_inverted"] == 0
    assert result["full_min_volume_ratio"] > 0
    assert abs(result["volume_change"]) < 1e-12
    assert result["stiffness_vs_skfem"] < 1e-13
    for costs in result["timings_s"].values():
        assert costs["morph"] > 0 and costs["objective"] > costs["morph"]
    assert result["figure"].is_file() and result["figure"].stat().st_size > 10_000
