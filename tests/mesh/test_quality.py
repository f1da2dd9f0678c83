"""Quality and error measures (SPEC.md §5): volumes, Q, inversions, mass matrix, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _grids import kuhn_grid
from torch.autograd import gradcheck

from torchmorph.mesh import TetMesh
from torchmorph.mesh.norms import mass_matrix, relative_l2_error
from torchmorph.mesh.quality import (
    count_inverted,
    edge_ratio,
    inverted,
    quality_summary,
    signed_volumes,
    validity_barrier,
)

F64 = torch.float64

REFERENCE_POINTS = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


@pytest.fixture
def reference_tet() -> TetMesh:
    return TetMesh(torch.tensor(REFERENCE_POINTS, dtype=F64), torch.tensor([[0, 1, 2, 3]]))


@pytest.fixture
def unit_cube() -> TetMesh:
    return TetMesh(*kuhn_grid(1))


@pytest.fixture
def cube_grid() -> TetMesh:
    return TetMesh(*kuhn_grid(3))


def reflect_vertex_3() -> torch.Tensor:
    """Displacement of the reference tet that reflects (0, 0, 1) through the face z = 0."""
    displacement = torch.zeros(4, 3, dtype=F64)
    displacement[3, 2] = -2.0
    return displacement


# ----------------------------------------------------------------------------- geometry


def test_reference_tet_volume_and_edge_ratio(reference_tet):
    points, tets = reference_tet.points, reference_tet.tets
    torch.testing.assert_close(signed_volumes(points, tets), torch.tensor([1 / 6], dtype=F64))
    torch.testing.assert_close(edge_ratio(points, tets), torch.tensor([math.sqrt(2)], dtype=F64))


def test_signed_volume_changes_sign_with_orientation(reference_tet):
    swapped = torch.tensor([[0, 2, 1, 3]])
    torch.testing.assert_close(
        signed_volumes(reference_tet.points, swapped), torch.tensor([-1 / 6], dtype=F64)
    )


def test_regular_tetrahedron_has_unit_edge_ratio():
    points = torch.tensor([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=F64)
    torch.testing.assert_close(
        edge_ratio(points, torch.tensor([[0, 1, 2, 3]])), torch.ones(1, dtype=F64)
    )


def test_unit_cube_volumes_and_edge_ratios(unit_cube):
    assert unit_cube.num_tets == 6
    volumes = signed_volumes(unit_cube.points, unit_cube.tets)
    torch.testing.assert_close(volumes, torch.full((6,), 1 / 6, dtype=F64))
    torch.testing.assert_close(volumes.sum(), torch.tensor(1.0, dtype=F64))
    # each Kuhn tetrahedron has edges 1, 1, 1, sqrt 2, sqrt 2, sqrt 3
    ratios = edge_ratio(unit_cube.points, unit_cube.tets)
    torch.testing.assert_close(ratios, torch.full((6,), math.sqrt(3), dtype=F64))


def test_batched_geometry_equals_loop(cube_grid):
    generator = torch.Generator().manual_seed(0)
    batch = cube_grid.points + 0.05 * torch.randn(
        3, cube_grid.num_nodes, 3, generator=generator, dtype=F64
    )
    volumes = signed_volumes(batch, cube_grid.tets)
    ratios = edge_ratio(batch, cube_grid.tets)
    for b in range(3):
        torch.testing.assert_close(volumes[b], signed_volumes(batch[b], cube_grid.tets))
        torch.testing.assert_close(ratios[b], edge_ratio(batch[b], cube_grid.tets))


def test_geometry_gradcheck(reference_tet):
    # a generic tetrahedron: no ties between its edge lengths
    generator = torch.Generator().manual_seed(4)
    points = reference_tet.points + 0.1 * torch.rand(4, 3, generator=generator, dtype=F64)
    points.requires_grad_(True)
    assert gradcheck(lambda p: signed_volumes(p, reference_tet.tets), (points,))
    assert gradcheck(lambda p: edge_ratio(p, reference_tet.tets), (points,))


@pytest.mark.parametrize(
    ("points", "tets", "message"),
    [
        (torch.zeros(4, 2, dtype=F64), torch.tensor([[0, 1, 2, 3]]), r"points must have shape"),
        (torch.zeros(4, 3, dtype=torch.int64), torch.tensor([[0, 1, 2, 3]]), r"floating-point"),
        (torch.zeros(4, 3, dtype=F64), torch.tensor([[0, 1, 2]]), r"tets must have shape \(M, 4\)"),
        (torch.zeros(4, 3, dtype=F64), torch.tensor([[0.0, 1, 2, 3]]), r"tets must hold integer"),
        (torch.zeros(4, 3, dtype=F64), torch.tensor([[0, 1, 2, 4]]), r"outside \[0, 4\)"),
    ],
)
def test_geometry_errors(points, tets, message):
    with pytest.raises(ValueError, match=message):
        signed_volumes(points, tets)
    with pytest.raises(ValueError, match=message):
        edge_ratio(points, tets)


# ----------------------------------------------------------------------------- inversions


def test_count_inverted_reflected_vertex(reference_tet):
    assert count_inverted(reference_tet, torch.zeros(4, 3, dtype=F64)) == 0
    assert count_inverted(reference_tet, reflect_vertex_3()) == 1
    assert count_inverted(reference_tet.deformed(reflect_vertex_3())) == 1


def test_count_inverted_counts_flat_tets(reference_tet):
    flat = torch.zeros(4, 3, dtype=F64)
    flat[3, 2] = -1.0
    assert count_inverted(reference_tet, flat) == 1


def test_count_inverted_in_a_grid(unit_cube):
    # push corner (0, 0, 0) through the body diagonal beyond the opposite corner:
    # every tet of the cube contains node 0 and the diagonal node 7
    displacement = torch.zeros(unit_cube.num_nodes, 3, dtype=F64)
    displacement[0] = 2.0
    assert count_inverted(unit_cube, displacement) == 6
    displacement[0] = 0.1
    assert count_inverted(unit_cube, displacement) == 0


def test_inverted_mask_batched(reference_tet):
    batch = torch.stack([torch.zeros(4, 3, dtype=F64), reflect_vertex_3()])
    assert inverted(reference_tet, batch).tolist() == [[False], [True]]


def test_count_inverted_rejects_bad_displacement(reference_tet):
    with pytest.raises(ValueError, match=r"displacement must have shape \(4, 3\)"):
        count_inverted(reference_tet, torch.zeros(5, 3, dtype=F64))
    with pytest.raises(TypeError, match="mesh must be a torchmorph Mesh"):
        count_inverted("mesh", torch.zeros(4, 3, dtype=F64))


def test_quality_summary(unit_cube, reference_tet):
    summary = quality_summary(unit_cube)
    assert summary["num_tets"] == 6
    assert summary["max_edge_ratio"] == pytest.approx(math.sqrt(3))
    assert summary["mean_edge_ratio"] == pytest.approx(math.sqrt(3))
    assert summary["min_volume"] == pytest.approx(1 / 6)
    assert summary["min_volume_ratio"] == pytest.approx(1.0)
    assert summary["num_inverted"] == 0
    moved = quality_summary(reference_tet, reflect_vertex_3())
    assert moved["num_inverted"] == 1
    assert moved["min_volume"] == pytest.approx(-1 / 6)
    assert moved["min_volume_ratio"] == pytest.approx(-1.0)


# ----------------------------------------------------------------------------- mass matrix


def test_mass_matrix_reference_tet(reference_tet):
    matrix = mass_matrix(reference_tet)
    assert matrix.dtype == F64 and matrix.is_sparse and matrix.is_coalesced()
    expected = (1 / 6) / 20 * (torch.ones(4, 4, dtype=F64) + torch.eye(4, dtype=F64))
    torch.testing.assert_close(matrix.to_dense(), expected, rtol=0, atol=1e-16)


def test_mass_matrix_is_cached(reference_tet):
    assert mass_matrix(reference_tet) is mass_matrix(reference_tet)


def test_mass_matrix_matches_dense_assembly(cube_grid):
    dense = torch.zeros(cube_grid.num_nodes, cube_grid.num_nodes, dtype=F64)
    local = torch.ones(4, 4, dtype=F64) + torch.eye(4, dtype=F64)
    for tet, volume in zip(cube_grid.tets.tolist(), cube_grid.volumes.tolist(), strict=True):
        dense[np.ix_(tet, tet)] += volume / 20 * local
    matrix = mass_matrix(cube_grid).to_dense()
    torch.testing.assert_close(matrix, dense, rtol=0, atol=1e-16)
    torch.testing.assert_close(matrix, matrix.T)
    torch.testing.assert_close(matrix.sum(), torch.tensor(1.0, dtype=F64))


def test_mass_matrix_integrates_linear_fields_exactly(cube_grid):
    matrix = mass_matrix(cube_grid)
    x = cube_grid.points[:, :1]
    # ∫_cube x² = 1/3, exact for the P1 interpolant of a linear field
    torch.testing.assert_close(
        (x * torch.sparse.mm(matrix, x)).sum(), torch.tensor(1 / 3, dtype=F64)
    )
    # ∫_cube (x + 2y - z + 1)² = (1/3 + 4/3 + 1/3 + 1) + 2 (1/2 - 1/4 + 1/2 - 1/2 + 1 - 1/2)
    u = cube_grid.points @ torch.tensor([1.0, 2.0, -1.0], dtype=F64) + 1.0
    integral = (u * torch.sparse.mm(matrix, u[:, None])[:, 0]).sum()
    torch.testing.assert_close(integral, torch.tensor(9 / 2, dtype=F64))


# ----------------------------------------------------------------------------- relative error


@pytest.mark.parametrize("norm", ["mass", "nodal"])
def test_relative_error_of_half_a_constant_field(cube_grid, norm):
    constant = torch.tensor([0.3, -1.2, 2.0], dtype=F64).expand(cube_grid.num_nodes, 3)
    error = relative_l2_error(cube_grid, constant, 2 * constant, norm=norm)
    assert error.shape == ()
    torch.testing.assert_close(error, torch.tensor(0.5, dtype=F64))


def test_relative_error_l2_of_linear_fields(cube_grid):
    # d = (x, 0, 0), d_ref = (x, y, 0): ||d - d_ref||² = ∫ y² = 1/3, ||d_ref||² = 2/3
    points = cube_grid.points
    d_ref = torch.stack([points[:, 0], points[:, 1], torch.zeros_like(points[:, 0])], 1)
    d = d_ref.clone()
    d[:, 1] = 0.0
    torch.testing.assert_close(
        relative_l2_error(cube_grid, d, d_ref), torch.tensor(0.5**0.5, dtype=F64)
    )


@pytest.mark.parametrize("norm", ["mass", "nodal"])
def test_relative_error_batched_equals_loop(cube_grid, norm):
    generator = torch.Generator().manual_seed(1)
    d = torch.randn(4, cube_grid.num_nodes, 3, generator=generator, dtype=F64)
    d_ref = torch.randn(4, cube_grid.num_nodes, 3, generator=generator, dtype=F64)
    batched = relative_l2_error(cube_grid, d, d_ref, norm=norm)
    assert batched.shape == (4,)
    for b in range(4):
        torch.testing.assert_close(
            batched[b], relative_l2_error(cube_grid, d[b], d_ref[b], norm=norm)
        )


def test_relative_error_is_differentiable(reference_tet):
    generator = torch.Generator().manual_seed(2)
    d = torch.randn(4, 3, generator=generator, dtype=F64, requires_grad=True)
    d_ref = torch.randn(4, 3, generator=generator, dtype=F64)
    assert gradcheck(lambda x: relative_l2_error(reference_tet, x, d_ref), (d,))
    assert gradcheck(lambda x: relative_l2_error(reference_tet, x, d_ref, norm="nodal"), (d,))


def test_relative_error_errors(reference_tet):
    d = torch.ones(4, 3, dtype=F64)
    with pytest.raises(ValueError, match="d_ref has zero mass norm"):
        relative_l2_error(reference_tet, d, torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"d_ref has zero nodal norm \(batch entries 1\)"):
        relative_l2_error(reference_tet, d.expand(2, 4, 3), torch.stack([d, 0 * d]), norm="nodal")
    with_nan = d.clone()
    with_nan[2, 1] = float("nan")
    with pytest.raises(ValueError, match="d holds 1 NaN"):
        relative_l2_error(reference_tet, with_nan, d)
    with pytest.raises(ValueError, match="norm must be one of 'mass', 'nodal'; got 'h1'"):
        relative_l2_error(reference_tet, d, d, norm="h1")
    with pytest.raises(ValueError, match="d and d_ref must have the same shape"):
        relative_l2_error(reference_tet, d, torch.ones(2, 4, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"d must have shape \(4, 3\) or \(B, 4, 3\)"):
        relative_l2_error(reference_tet, torch.ones(5, 3, dtype=F64), torch.ones(5, 3, dtype=F64))


# ----------------------------------------------------------------------------- barrier


def test_barrier_is_zero_for_the_identity(cube_grid):
    displacement = torch.zeros(cube_grid.num_nodes, 3, dtype=F64, requires_grad=True)
    value = validity_barrier(cube_grid, displacement)
    assert float(value.detach()) == 0.0
    value.backward()
    assert float(displacement.grad.abs().max()) == 0.0


def test_barrier_values(reference_tet):
    # move vertex 3 down so the volume ratio r = 1 + dz
    def barrier_at(ratio, threshold=0.1):
        displacement = torch.zeros(4, 3, dtype=F64)
        displacement[3, 2] = ratio - 1.0
        return float(validity_barrier(reference_tet, displacement, threshold=threshold))

    assert barrier_at(0.5) == 0.0
    assert barrier_at(0.1) == pytest.approx(0.0, abs=1e-20)
    assert barrier_at(0.05) == pytest.approx(0.25)
    assert barrier_at(0.0) == pytest.approx(1.0)
    assert barrier_at(-1.0) == pytest.approx(121.0)  # finite for inverted tets
    assert barrier_at(0.5, threshold=1.0) == pytest.approx(0.25)


def test_barrier_gradcheck_through_the_active_region(cube_grid):
    generator = torch.Generator().manual_seed(3)
    displacement = 0.2 * torch.randn(cube_grid.num_nodes, 3, generator=generator, dtype=F64)
    ratio = signed_volumes(cube_grid.points + displacement, cube_grid.tets) / cube_grid.volumes
    assert bool((ratio < 0.3).any())  # the penalty is active somewhere
    displacement.requires_grad_(True)
    for reduction in ("sum", "mean", "none"):
        assert gradcheck(
            lambda d, r=reduction: validity_barrier(cube_grid, d, threshold=0.3, reduction=r),
            (displacement,),
        )


def test_barrier_reductions_and_batches(reference_tet):
    displacement = torch.stack([torch.zeros(4, 3, dtype=F64), reflect_vertex_3()])
    per_tet = validity_barrier(reference_tet, displacement, reduction="none")
    assert per_tet.shape == (2, 1)
    torch.testing.assert_close(validity_barrier(reference_tet, displacement), per_tet.sum(-1))
    torch.testing.assert_close(
        validity_barrier(reference_tet, displacement, reduction="mean"), per_tet.mean(-1)
    )


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"threshold": 0.0}, r"threshold must lie in \(0, 1\]"),
        ({"threshold": 1.5}, r"threshold must lie in \(0, 1\]"),
        ({"threshold": float("nan")}, r"threshold must lie in \(0, 1\]"),
        ({"reduction": "max"}, "reduction must be one of 'sum', 'mean', 'none'"),
    ],
)
def test_barrier_errors(reference_tet, options, message):
    with pytest.raises(ValueError, match=message):
        validity_barrier(reference_tet, torch.zeros(4, 3, dtype=F64), **options)


def test_barrier_rejects_wrong_shape(reference_tet):
    with pytest.raises(ValueError, match=r"displacement must have shape"):
        validity_barrier(reference_tet, torch.zeros(3, 3, dtype=F64))
