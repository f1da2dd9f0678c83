"""The two error norms of torchmorph.mesh.quality: P1 mass matrix and nodal ℓ2."""

from __future__ import annotations

import pytest
import torch
from conftest import structured_cube

from torchmorph.mesh.norms import ERROR_NORMS, relative_l2_error, relative_nodal_error

F64 = torch.float64


def fields(mesh, seed=0):
    generator = torch.Generator().manual_seed(seed)
    d = torch.randn(mesh.num_nodes, 3, generator=generator, dtype=F64)
    d_ref = torch.randn(mesh.num_nodes, 3, generator=generator, dtype=F64)
    return d, d_ref


def test_default_norm_is_the_mass_matrix_norm():
    mesh = structured_cube(3)
    d, d_ref = fields(mesh)
    assert ERROR_NORMS == ("mass", "nodal")
    torch.testing.assert_close(
        relative_l2_error(mesh, d, d_ref),
        relative_l2_error(mesh, d, d_ref, norm="mass"),
        rtol=0,
        atol=0,
    )


def test_nodal_norm_against_a_literal_loop():
    mesh = structured_cube(3)
    d, d_ref = fields(mesh, 1)
    numerator = sum(float(((d[i] - d_ref[i]) ** 2).sum()) for i in range(mesh.num_nodes))
    denominator = sum(float((d_ref[i] ** 2).sum()) for i in range(mesh.num_nodes))
    expected = (numerator / denominator) ** 0.5
    assert float(relative_nodal_error(mesh, d, d_ref)) == pytest.approx(expected, rel=1e-13)
    assert float(relative_l2_error(mesh, d, d_ref, norm="nodal")) == pytest.approx(
        expected, rel=1e-13
    )


def test_the_norms_differ_on_a_graded_mesh():
    # an error only at the nodes of the small elements: the mass norm sees it less
    mesh = structured_cube(4)
    points = mesh.points.clone()
    points = points**2  # elements shrink towards the corner x = y = z = 0
    from torchmorph.mesh import TetMesh

    graded = TetMesh(points, mesh.tets)
    d_ref = torch.ones(graded.num_nodes, 3, dtype=F64)
    d = d_ref.clone()
    near_origin = points.norm(dim=1) < 0.3
    d[near_origin] += 1.0
    nodal = float(relative_nodal_error(graded, d, d_ref))
    mass = float(relative_l2_error(graded, d, d_ref))
    assert nodal == pytest.approx((int(near_origin.sum()) / graded.num_nodes) ** 0.5, rel=1e-12)
    assert mass < 0.5 * nodal


def test_old_spelling_warns_and_means_mass():
    mesh = structured_cube(2)
    d, d_ref = fields(mesh, 2)
    with pytest.warns(DeprecationWarning, match="norm='l2'\\) is deprecated"):
        old = relative_l2_error(mesh, d, d_ref, norm="l2")
    torch.testing.assert_close(old, relative_l2_error(mesh, d, d_ref, norm="mass"), rtol=0, atol=0)
