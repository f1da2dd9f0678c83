"""Large motions (torchmorph.large_motions): rotation-aware morphs and morphs in steps.

References: the rigid motion a rotation-aware morph must reproduce, plain IDW (no
rotation, one step), the boundary neighbourhoods from the facets by plain Python sets,
loops for batches, gradcheck in float64, and the paper's hull (case C) turned by 60°,
where plain IDW folds cells and the rotation-aware morph in steps keeps them all.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmorph import MeshMorph, box_mesh
from torchmorph.large_motions import SteppedMorph, boundary_neighbours, morph_in_steps
from torchmorph.mesh import Mesh

F64 = torch.float64


def _turn(points, degrees, axis=2):
    angle = math.radians(degrees)
    c, s = math.cos(angle), math.sin(angle)
    i, j = [k for k in range(points.shape[1]) if k != axis][:2] if points.shape[1] == 3 else (0, 1)
    centre = points.mean(0)
    moved = points.clone()
    moved[:, i] = centre[i] + c * (points[:, i] - centre[i]) - s * (points[:, j] - centre[j])
    moved[:, j] = centre[j] + s * (points[:, i] - centre[i]) + c * (points[:, j] - centre[j])
    return moved - points


def _square(n=6):
    ticks = np.linspace(0.0, 1.0, n + 1)
    points = np.stack(np.meshgrid(ticks, ticks, indexing="ij"), -1).reshape(-1, 2)
    index = np.arange(len(points)).reshape(n + 1, n + 1)
    corners = (index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:])
    return Mesh(points, [("quad", np.stack(corners, -1).reshape(-1, 4))])


def test_boundary_neighbours_are_the_nodes_sharing_a_facet():
    mesh = box_mesh(2)
    morph = MeshMorph(mesh)
    table = boundary_neighbours(morph)
    boundary = morph.boundary_nodes.tolist()
    expected = {node: {node} for node in boundary}
    for face in mesh.boundary_faces.tolist():
        for node in face:
            expected[node].update(face)
    for row, node in enumerate(boundary):
        got = {boundary[k] for k in table[row].tolist() if k >= 0}
        assert got == expected[node]
    assert boundary_neighbours(morph) is table  # kept


@pytest.mark.parametrize("degrees", [30.0, 120.0])
def test_rotation_aware_morph_moves_a_rigidly_turned_box_rigidly(degrees):
    mesh = box_mesh(4)
    morph = MeshMorph(mesh)
    expected = _turn(mesh.points, degrees)
    boundary = expected[morph.boundary_nodes]
    moved = morph(boundary, rotations="fit")
    torch.testing.assert_close(moved, expected, rtol=0, atol=1e-10)
    assert (morph(boundary) - expected).abs().max() > 1e-2  # plain IDW does not


def test_rotation_aware_morph_in_2d_and_with_given_rotations():
    mesh = _square()
    morph = MeshMorph(mesh)
    expected = _turn(mesh.points, 75.0)
    boundary = expected[morph.boundary_nodes]
    torch.testing.assert_close(morph(boundary, rotations="fit"), expected, rtol=0, atol=1e-10)
    given = torch.full((morph.num_boundary, 1), math.radians(75.0), dtype=F64)
    torch.testing.assert_close(morph(boundary, rotations=given), expected, rtol=0, atol=1e-10)
    zero = torch.zeros_like(given)
    torch.testing.assert_close(morph(boundary, rotations=zero), morph(boundary), rtol=0, atol=1e-15)


def test_rotation_aware_morph_batches_and_gradients():
    mesh = box_mesh(2)
    morph = MeshMorph(mesh)
    generator = torch.Generator().manual_seed(0)
    batch = 0.05 * torch.randn(3, morph.num_boundary, 3, generator=generator, dtype=F64)
    together = morph(batch, rotations="fit")
    for k in range(3):
        torch.testing.assert_close(
            together[k], morph(batch[k], rotations="fit"), rtol=0, atol=1e-14
        )
    single = batch[0].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d: morph(d, rotations="fit"), (single,))


def test_rotation_aware_morph_refuses_bad_rotations():
    morph = MeshMorph(box_mesh(2))
    boundary = torch.zeros(morph.num_boundary, 3, dtype=F64)
    with pytest.raises(ValueError, match="rotations must be None, 'fit'"):
        morph(boundary, rotations="estimate")
    with pytest.raises(ValueError, match="rotations must have shape"):
        morph(boundary, rotations=torch.zeros(morph.num_boundary, 1, dtype=F64))
    bad = torch.zeros(morph.num_boundary, 3, dtype=F64)
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="rotations must be finite"):
        morph(boundary, rotations=bad)
    with pytest.raises(ValueError, match="dtype and device"):
        morph(boundary, rotations=bad.float())
    with pytest.raises(ValueError, match="reach must be a positive length"):
        morph(boundary, rotations="fit", reach=-1.0)
    with pytest.raises(ValueError, match="reach: only a rotation-aware morph"):
        morph(boundary, reach=1.0)


def test_one_step_is_the_plain_morph_and_steps_end_on_the_boundary():
    mesh = box_mesh(3)
    morph = MeshMorph(mesh)
    generator = torch.Generator().manual_seed(1)
    final = 0.03 * torch.randn(morph.num_boundary, 3, generator=generator, dtype=F64)
    one = morph_in_steps(morph, final, 1)
    torch.testing.assert_close(one.displacement, morph(final), rtol=0, atol=1e-14)
    assert one.fractions == [1.0] and one.first_inverted is None
    rotating = morph_in_steps(morph, final, 1, rotations="fit")
    torch.testing.assert_close(
        rotating.displacement, morph(final, rotations="fit"), rtol=0, atol=1e-14
    )
    stepped = morph_in_steps(morph, final, 4)
    torch.testing.assert_close(stepped.displacement[morph.boundary_nodes], final, rtol=0, atol=0)
    assert stepped.fractions == [0.25, 0.5, 0.75, 1.0]
    assert (stepped.displacement - morph(final)).abs().max() > 1e-6  # W follows the mesh
    by_function = morph_in_steps(morph, lambda t: t * final, 4)
    torch.testing.assert_close(by_function.displacement, stepped.displacement, rtol=0, atol=0)
    batch = morph_in_steps(morph, torch.stack([final, -final]), 4)
    torch.testing.assert_close(batch.displacement[0], stepped.displacement, rtol=0, atol=1e-14)
    assert isinstance(batch, SteppedMorph) and len(batch.fractions) == 2


def test_morph_in_steps_refuses_bad_arguments():
    morph = MeshMorph(box_mesh(2))
    final = torch.zeros(morph.num_boundary, 3, dtype=F64)
    for steps in (0, 2.5, True):
        with pytest.raises(ValueError, match="steps must be a positive integer"):
            morph_in_steps(morph, final, steps)
    with pytest.raises(ValueError, match="refine must be a non-negative integer"):
        morph_in_steps(morph, final, 2, refine=-1)
    with pytest.raises(ValueError, match="rotations must be None or 'fit'"):
        morph_in_steps(morph, final, 2, rotations="given")
    with pytest.raises(TypeError, match="path must be"):
        morph_in_steps(morph, final.numpy(), 2)
    with pytest.raises(ValueError, match="boundary_displacement"):
        morph_in_steps(morph, final[:-1], 2)


@pytest.mark.slow
def test_hull_turned_by_60_degrees_folds_cells_only_without_rotations():
    pytest.importorskip("gmsh")
    from torchmorph.paper import load_mesh
    from torchmorph.paper.cases import hull_rotation

    morph = MeshMorph(load_mesh("hull", size="small"))

    def path(t):
        return morph.boundary_displacement(
            ("hull",), lambda p: hull_rotation(p, torch.tensor(-60.0 * t, dtype=p.dtype))
        )

    assert morph.count_inverted(morph(path(1.0))) > 0
    coarse = morph_in_steps(morph, lambda t: path(1.5 * t), 2)  # 90° in two steps
    assert coarse.first_inverted is not None
    first = coarse.fractions[next(k for k, n in enumerate(coarse.inverted) if n)]
    assert coarse.first_inverted == first
    refined = morph_in_steps(morph, lambda t: path(1.5 * t), 2, refine=2)
    assert len(refined.fractions) > 2 and refined.fractions[-1] == 1.0
    rotating = morph_in_steps(morph, path, 10, rotations="fit")
    assert rotating.first_inverted is None and max(rotating.inverted) == 0
    assert morph.count_inverted(rotating.displacement) == 0
    hull = morph.node_sets["hull"]
    torch.testing.assert_close(
        rotating.displacement[hull], hull_rotation(morph.points[hull], -60.0), rtol=0, atol=1e-12
    )
