"""Rotation-aware IDW (torchmorph.idw.rotations) against independent references.

The exponential map against torch's matrix exponential of the skew matrix; the fitted
rotations against the rotation that made a rigid motion; the blend against the rigid
motion it must reproduce exactly, against plain IDW when nothing turns, exact at the
controls, batched as looped, and gradcheck in float64.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchmorph.idw import IDW, idw_apply
from torchmorph.idw.rotations import (
    blend_rigid_motions,
    default_reach,
    fit_rotations,
    rotation_matrices,
    rotation_size,
)

F64 = torch.float64


def _skew(v):
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def _random_rotation_vectors(n, generator, scale=1.0):
    return scale * torch.randn(n, 3, generator=generator, dtype=F64)


@pytest.mark.parametrize("scale", [1e-9, 1e-4, 0.5, 2.5])
def test_rotation_matrices_equal_the_matrix_exponential(scale):
    generator = torch.Generator().manual_seed(1)
    vectors = _random_rotation_vectors(50, generator, scale)
    expected = torch.linalg.matrix_exp(_skew(vectors))
    torch.testing.assert_close(rotation_matrices(vectors), expected, rtol=0, atol=1e-14)
    angles = scale * torch.randn(50, 1, generator=generator, dtype=F64)
    c, s = torch.cos(angles[:, 0]), torch.sin(angles[:, 0])
    planar = rotation_matrices(angles)
    torch.testing.assert_close(planar[:, 0, 0], c)
    torch.testing.assert_close(planar[:, 1, 0], s)


def test_rotation_matrices_are_differentiable_at_the_identity():
    zero = torch.zeros(2, 3, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(rotation_matrices, (zero,))
    generator = torch.Generator().manual_seed(2)
    vectors = _random_rotation_vectors(3, generator).requires_grad_(True)
    assert torch.autograd.gradcheck(rotation_matrices, (vectors,))
    with pytest.raises(ValueError, match="1 .* or 3"):
        rotation_matrices(torch.zeros(4, 2, dtype=F64))


def _rigid(points, vector, centre, shift):
    turn = torch.linalg.matrix_exp(_skew(vector)) if points.shape[1] == 3 else None
    if turn is None:
        c, s = math.cos(float(vector)), math.sin(float(vector))
        turn = torch.tensor([[c, -s], [s, c]], dtype=F64)
    return (points - centre) @ turn.T + centre + shift


@pytest.mark.parametrize("flat", [False, True])
def test_fitted_rotations_recover_a_rigid_motion(flat):
    generator = torch.Generator().manual_seed(3)
    points = torch.randn(40, 3, generator=generator, dtype=F64)
    if flat:  # a neighbourhood on a surface: the points in one plane
        points[:, 2] = 0.3
    vector = torch.tensor([0.4, -1.1, 0.7], dtype=F64)
    moved = _rigid(points, vector, torch.tensor([1.0, 2.0, 3.0], dtype=F64), 0.5)
    neighbours = torch.stack(
        [torch.randperm(40, generator=generator)[:6] for _ in range(40)]
    )  # six points each
    fitted = fit_rotations(points, moved, neighbours)
    torch.testing.assert_close(fitted, vector.expand(40, 3), rtol=0, atol=1e-10)


def test_fitted_rotations_in_2d_with_padding_and_batches():
    generator = torch.Generator().manual_seed(4)
    points = torch.randn(30, 2, generator=generator, dtype=F64)
    angles = torch.tensor([0.3, -1.2, 2.0], dtype=F64)
    moved = torch.stack([_rigid(points, a, torch.zeros(2, dtype=F64), 0.1) for a in angles])
    neighbours = torch.arange(30).reshape(10, 3).repeat_interleave(3, 0)
    neighbours = torch.cat([neighbours, torch.full((30, 2), -1)], 1)  # padding
    fitted = fit_rotations(points, moved, neighbours)
    assert fitted.shape == (3, 30, 1)
    torch.testing.assert_close(fitted[..., 0], angles[:, None].expand(3, 30), rtol=0, atol=1e-12)
    # a point whose neighbourhood did not move turns by nothing
    still = fit_rotations(points, points.clone(), neighbours[:, :3])
    assert still.abs().max() < 1e-14


def test_fit_rotations_refuses_bad_input():
    points = torch.zeros(5, 3, dtype=F64)
    with pytest.raises(ValueError, match="neighbours must have shape"):
        fit_rotations(points, points, torch.zeros(4, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="neighbours: entries"):
        fit_rotations(points, points, torch.full((5, 2), 7))
    with pytest.raises(TypeError, match="integer"):
        fit_rotations(points, points, torch.zeros(5, 2))
    with pytest.raises(ValueError, match="moved must have shape"):
        fit_rotations(points, torch.zeros(5, 2, dtype=F64), torch.zeros(5, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="dimension 4"):
        rotation_size(4)


def _cloud(dim, generator):
    controls = torch.rand(60, dim, generator=generator, dtype=F64)
    targets = torch.rand(90, dim, generator=generator, dtype=F64)
    return controls, targets


@pytest.mark.parametrize("dim", [2, 3])
def test_blend_reproduces_a_rigid_motion_where_plain_idw_does_not(dim):
    generator = torch.Generator().manual_seed(5)
    controls, targets = _cloud(dim, generator)
    centre = torch.full((dim,), 0.4, dtype=F64)
    if dim == 3:
        vector = torch.tensor([0.2, 0.9, -0.5], dtype=F64)
        rotations = vector.expand(60, 3)
    else:
        vector = torch.tensor(1.2, dtype=F64)
        rotations = vector.reshape(1, 1).expand(60, 1)
    displacements = _rigid(controls, vector, centre, 0.3) - controls
    expected = _rigid(targets, vector, centre, 0.3) - targets
    idw = IDW(controls, targets)
    blended = blend_rigid_motions(
        idw,
        controls=controls,
        targets=targets,
        displacements=displacements,
        rotations=rotations,
        reach=10.0,
    )
    torch.testing.assert_close(blended, expected, rtol=0, atol=1e-12)
    assert (idw(displacements) - expected).abs().max() > 1e-2  # plain IDW shears it


@pytest.mark.parametrize("dim", [2, 3])
def test_blend_is_exact_at_controls_and_plain_idw_without_rotation(dim):
    generator = torch.Generator().manual_seed(6)
    controls, targets = _cloud(dim, generator)
    displacements = 0.1 * torch.randn(60, dim, generator=generator, dtype=F64)
    rotations = torch.randn(60, rotation_size(dim), generator=generator, dtype=F64)
    at_controls = blend_rigid_motions(
        IDW(controls, controls.clone()),
        controls=controls,
        targets=controls,
        displacements=displacements,
        rotations=rotations,
        reach=10.0,
    )
    torch.testing.assert_close(at_controls, displacements, rtol=0, atol=1e-13)
    idw = IDW(controls, targets)
    still = blend_rigid_motions(
        idw,
        controls=controls,
        targets=targets,
        displacements=displacements,
        rotations=torch.zeros_like(rotations),
        reach=10.0,
    )
    torch.testing.assert_close(still, idw(displacements), rtol=0, atol=1e-14)


def test_blend_batches_equal_loops_and_gradcheck():
    generator = torch.Generator().manual_seed(7)
    controls = torch.rand(12, 3, generator=generator, dtype=F64)
    targets = torch.rand(15, 3, generator=generator, dtype=F64)
    d = 0.1 * torch.randn(4, 12, 3, generator=generator, dtype=F64)
    omega = 0.3 * torch.randn(4, 12, 3, generator=generator, dtype=F64)

    def apply(values):
        return idw_apply(controls=controls, targets=targets, displacements=values)

    batch = blend_rigid_motions(
        apply, controls=controls, targets=targets, displacements=d, rotations=omega, reach=0.3
    )
    for k in range(4):
        single = blend_rigid_motions(
            apply,
            controls=controls,
            targets=targets,
            displacements=d[k],
            rotations=omega[k],
            reach=0.3,
        )
        torch.testing.assert_close(batch[k], single, rtol=0, atol=1e-14)
    d1, omega1 = d[0].clone().requires_grad_(True), omega[0].clone().requires_grad_(True)

    def function(displacements, rotations):
        return blend_rigid_motions(
            apply,
            controls=controls,
            targets=targets,
            displacements=displacements,
            rotations=rotations,
            reach=0.3,
        )

    assert torch.autograd.gradcheck(function, (d1, omega1))
    with pytest.raises(ValueError, match="rotations must have shape"):
        function(d[0], omega[0, :, :1])


@pytest.mark.parametrize("dim", [2, 3])
def test_fitted_rotations_gradcheck(dim):
    generator = torch.Generator().manual_seed(8)
    points = torch.randn(8, dim, generator=generator, dtype=F64)
    moved = (points + 0.2 * torch.randn(8, dim, generator=generator, dtype=F64)).requires_grad_(
        True
    )
    neighbours = torch.stack([torch.randperm(8, generator=generator)[:5] for _ in range(8)])
    assert torch.autograd.gradcheck(lambda m: fit_rotations(points, m, neighbours), (moved,))


def test_the_turn_falls_off_beyond_the_reach():
    # one control turning in place by θ among still ones: a target at distance r > ℓ
    # from it turns about it by (ℓ / r) times the blended angle
    controls = torch.tensor([[0.0, 0.0], [10.0, 0.0], [-10.0, 0.0]], dtype=F64)
    targets = torch.tensor([[0.0, 4.0]], dtype=F64)
    rotations = torch.tensor([[1.0], [0.0], [0.0]], dtype=F64)
    displacements = torch.zeros(3, 2, dtype=F64)
    idw = IDW(controls, targets, mode="dense")
    weight = float(idw.weights[0, 0])
    for reach, expected_angle in ((8.0, weight), (2.0, weight * 2.0 / 4.0)):
        moved = blend_rigid_motions(
            idw,
            controls=controls,
            targets=targets,
            displacements=displacements,
            rotations=rotations,
            reach=reach,
        )
        c, s = math.cos(expected_angle), math.sin(expected_angle)
        expected = torch.tensor([[-4.0 * s, 4.0 * c - 4.0]], dtype=F64)
        torch.testing.assert_close(moved, expected, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="reach must be a positive length"):
        blend_rigid_motions(
            idw,
            controls=controls,
            targets=targets,
            displacements=displacements,
            rotations=rotations,
            reach=0.0,
        )


def test_default_reach_is_the_size_of_the_turning_part():
    points = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [9.0, 9.0, 9.0]])
    rotations = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.8], [0.0, 0.6, 0.0], [0.1, 0, 0]])
    assert default_reach(points, rotations) == pytest.approx(0.5 * math.sqrt(5.0))
    assert default_reach(points, torch.zeros(4, 3)) == 1.0
