"""The FFD module against PyGeM's formula in NumPy loops, and the invariants of a lattice
map: translations and affine fields reproduced, points outside fixed, batches equal to
loops, gradients checked against differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _ffd_reference import pygem_ffd, rotation_2d, rotation_matrix
from torch.autograd import gradcheck, gradgradcheck

from torchmorph.ffd import FFD, ffd_apply, ffd_bases, functional, lattice_sum
from torchmorph.ffd.lattice import tensor_product

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
ORIGIN = np.array([0.1, -0.2, 0.3])
LENGTHS = np.array([1.2, 0.7, 0.9])


def cloud(count=300, dim=3, seed=0, low=-0.4, high=1.4):
    """Points around the box ORIGIN + [0, LENGTHS]: about a third of them outside."""
    rng = np.random.default_rng(seed)
    local = rng.uniform(low, high, size=(count, dim))
    return ORIGIN[:dim] + local * LENGTHS[:dim]


def random_mu(shape, seed=1, scale=0.1):
    return np.random.default_rng(seed).normal(size=(*shape, len(shape))) * scale


# --------------------------------------------------------------------------- #
# against PyGeM's formula
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("shape", [(2, 2, 2), (4, 3, 5), (6, 6, 6)])
@pytest.mark.parametrize("angles", [None, (10.0, -20.0, 35.0)])
def test_bernstein_equals_pygem_formula(shape, angles):
    points = cloud()
    mu = random_mu(shape)
    rotation = None if angles is None else rotation_matrix(angles)
    reference = pygem_ffd(points, ORIGIN, LENGTHS, mu, rotation)
    # PyGeM's normalised weights along the box axes -> physical displacements
    frame = np.eye(3) if rotation is None else rotation
    displacements = (mu * LENGTHS) @ frame.T
    morph = FFD(
        torch.from_numpy(points),
        origin=ORIGIN,
        lengths=LENGTHS,
        shape=shape,
        rotation=None if rotation is None else torch.from_numpy(rotation),
    )
    assert 0 < morph.num_inside < len(points)
    moved = points + morph(torch.from_numpy(displacements)).numpy()
    np.testing.assert_allclose(moved, reference, rtol=0, atol=1e-13)


@pytest.mark.parametrize(("shape", "degree"), [((5, 4, 6), 3), ((4, 4, 4), 2), ((6, 3, 5), 1)])
def test_bspline_equals_loop_formula_with_scipy_bases(shape, degree):
    points = cloud(count=150)
    mu = random_mu(shape)
    reference = pygem_ffd(points, ORIGIN, LENGTHS, mu, basis="bspline", degree=degree)
    morph = FFD(
        torch.from_numpy(points),
        origin=ORIGIN,
        lengths=LENGTHS,
        shape=shape,
        basis="bspline",
        degree=degree,
    )
    moved = points + morph(torch.from_numpy(mu * LENGTHS)).numpy()
    np.testing.assert_allclose(moved, reference, rtol=0, atol=1e-13)


@pytest.mark.parametrize("basis", ["bernstein", "bspline"])
def test_two_dimensional_equals_loop_formula(basis):
    points = cloud(dim=2)
    shape = (5, 4)
    mu = random_mu(shape)
    rotation = rotation_2d(25.0)
    reference = pygem_ffd(points, ORIGIN[:2], LENGTHS[:2], mu, rotation, basis=basis)
    morph = FFD(
        torch.from_numpy(points),
        origin=ORIGIN[:2],
        lengths=LENGTHS[:2],
        shape=shape,
        basis=basis,
        rotation=rotation,
    )
    moved = points + morph(torch.from_numpy((mu * LENGTHS[:2]) @ rotation.T)).numpy()
    np.testing.assert_allclose(moved, reference, rtol=0, atol=1e-13)


def test_functional_equals_module():
    points = torch.from_numpy(cloud())
    displacements = torch.from_numpy(random_mu((4, 5, 3)))
    box = dict(origin=ORIGIN, lengths=LENGTHS, basis="bspline", degree=2)
    expected = FFD(points, shape=(4, 5, 3), **box)(displacements)
    torch.testing.assert_close(
        ffd_apply(points=points, displacements=displacements, **box), expected, rtol=0, atol=0
    )


# --------------------------------------------------------------------------- #
# invariants
# --------------------------------------------------------------------------- #
def affine_field(dim, seed=5):
    generator = torch.Generator().manual_seed(seed)
    matrix = torch.randn(dim, dim, generator=generator, dtype=F64)
    shift = torch.randn(dim, generator=generator, dtype=F64)
    return matrix, shift


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize(
    ("basis", "degree", "shape"), [("bernstein", None, 5), ("bspline", 3, 7), ("bspline", 2, 4)]
)
def test_uniform_lattice_displacement_translates_inside_points(dim, basis, degree, shape):
    points = torch.from_numpy(cloud(dim=dim))
    morph = FFD(
        points,
        origin=ORIGIN[:dim],
        lengths=LENGTHS[:dim],
        shape=(shape,) * dim,
        basis=basis,
        degree=degree,
    )
    _, shift = affine_field(dim)
    moved = morph(shift.expand(*morph.shape, dim))
    inside = morph.inside_mask
    torch.testing.assert_close(
        moved[inside], shift.expand(morph.num_inside, dim), rtol=0, atol=1e-15
    )
    assert torch.equal(moved[~inside], torch.zeros_like(moved[~inside]))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize(
    ("basis", "degree", "shape"),
    [("bernstein", None, (3, 5, 4)), ("bspline", 3, (6, 4, 7)), ("bspline", 1, (2, 3, 5))],
)
@pytest.mark.parametrize("angles", [None, (30.0, 0.0, -50.0)])
def test_affine_lattice_field_is_reproduced(dim, basis, degree, shape, angles):
    points = torch.from_numpy(cloud(dim=dim))
    rotation = None
    if angles is not None:  # in 2-D, the rotation about z
        rotation = rotation_2d(angles[2]) if dim == 2 else rotation_matrix(angles)
        rotation = torch.from_numpy(rotation)
    morph = FFD(
        points,
        origin=ORIGIN[:dim],
        lengths=LENGTHS[:dim],
        shape=shape[:dim],
        basis=basis,
        degree=degree,
        rotation=rotation,
    )
    matrix, shift = affine_field(dim)
    moved = morph(morph.control_points @ matrix.T + shift)
    inside = morph.inside_mask
    torch.testing.assert_close(moved[inside], points[inside] @ matrix.T + shift, rtol=0, atol=1e-14)


def test_control_points_span_the_box():
    rotation = torch.from_numpy(rotation_matrix((10.0, 20.0, 30.0)))
    morph = FFD(
        torch.from_numpy(cloud()),
        origin=ORIGIN,
        lengths=LENGTHS,
        shape=(3, 4, 2),
        rotation=rotation,
    )
    lattice = morph.control_points
    assert lattice.shape == (3, 4, 2, 3)
    origin = torch.from_numpy(ORIGIN)
    torch.testing.assert_close(lattice[0, 0, 0], origin)
    torch.testing.assert_close(lattice[-1, 0, 0], origin + LENGTHS[0] * rotation[:, 0])
    torch.testing.assert_close(lattice[1, 0, 0], origin + LENGTHS[0] / 2 * rotation[:, 0])
    torch.testing.assert_close(
        lattice[0, -1, -1], origin + LENGTHS[1] * rotation[:, 1] + LENGTHS[2] * rotation[:, 2]
    )


def test_points_outside_do_not_move_and_the_boundary_is_inside():
    # the unit box: faces, edges and corners exactly; points just outside each face
    origin, lengths = np.zeros(3), np.ones(3)
    on_faces = np.array(
        [[0.0, 0.3, 0.7], [1.0, 0.3, 0.7], [0.2, 1.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]
    )
    outside = np.array([[-1e-9, 0.5, 0.5], [0.5, 1 + 1e-9, 0.5], [0.5, 0.5, 2.0], [-3.0, 7.0, 0.1]])
    points = torch.from_numpy(np.concatenate([on_faces, outside]))
    morph = FFD(points, origin=origin, lengths=lengths, shape=(3, 3, 3))
    assert morph.inside.tolist() == [0, 1, 2, 3, 4]
    displacements = torch.from_numpy(random_mu((3, 3, 3), scale=1.0))
    moved = morph(displacements)
    assert torch.equal(moved[5:], torch.zeros(4, 3, dtype=F64))
    # a corner moves with its control point
    torch.testing.assert_close(moved[3], displacements[2, 2, 2], rtol=0, atol=0)
    torch.testing.assert_close(moved[4], displacements[0, 0, 0], rtol=0, atol=0)
    np.testing.assert_allclose(
        points.numpy() + moved.numpy(),
        pygem_ffd(points.numpy(), origin, lengths, displacements.numpy()),
        rtol=0,
        atol=1e-15,
    )


def test_a_face_point_rounded_past_the_face_is_inside():
    # (0.8 - 0.1) / 0.7 rounds to 1 + 1 ulp in float64: still on the face x = 0.8
    origin, lengths = np.array([0.1, 0.0]), np.array([0.7, 1.0])
    assert (0.8 - 0.1) / 0.7 > 1.0
    points = torch.tensor([[0.8, 0.5], [0.8 + 1e-12, 0.5]], dtype=F64)
    morph = FFD(points, origin=origin, lengths=lengths, shape=(2, 2))
    assert morph.inside.tolist() == [0]
    displacements = torch.zeros(2, 2, 2, dtype=F64)
    displacements[1, :, 0] = 0.25  # the face x = 0.8 moves by 0.25 along x
    torch.testing.assert_close(morph(displacements)[0], torch.tensor([0.25, 0.0], dtype=F64))


def test_no_point_inside():
    points = torch.from_numpy(cloud(count=10, low=2.0, high=3.0))
    morph = FFD(points, origin=ORIGIN, lengths=LENGTHS, shape=(2, 3, 2))
    assert morph.num_inside == 0
    displacements = torch.ones(4, 2, 3, 2, 3, dtype=F64, requires_grad=True)
    moved = morph(displacements)
    assert torch.equal(moved, torch.zeros(4, 10, 3, dtype=F64))
    moved.sum().backward()
    assert torch.equal(displacements.grad, torch.zeros_like(displacements))


@pytest.mark.parametrize("basis", ["bernstein", "bspline"])
def test_batched_equals_loop_of_single_calls(basis):
    points = torch.from_numpy(cloud())
    morph = FFD(
        points, origin=ORIGIN, lengths=LENGTHS, shape=(4, 5, 6), basis=basis, block_bytes=4096
    )
    generator = torch.Generator().manual_seed(2)
    batch = torch.randn(2, 3, 4, 5, 6, 3, generator=generator, dtype=F64)
    moved = morph(batch)
    assert moved.shape == (2, 3, 300, 3)
    looped = torch.stack([torch.stack([morph(single) for single in row]) for row in batch])
    torch.testing.assert_close(moved, looped, rtol=0, atol=1e-15)


def test_blocks_do_not_change_the_result():
    points = torch.from_numpy(cloud())
    displacements = torch.from_numpy(random_mu((5, 5, 5)))
    whole = FFD(points, origin=ORIGIN, lengths=LENGTHS, shape=(5, 5, 5))(displacements)
    for block_bytes in (1, 1000, 10**5):
        morph = FFD(
            points, origin=ORIGIN, lengths=LENGTHS, shape=(5, 5, 5), block_bytes=block_bytes
        )
        torch.testing.assert_close(morph(displacements), whole, rtol=0, atol=1e-15)


def test_lattice_sum_is_the_tensor_product_weights_times_displacements():
    inside, bases = ffd_bases(
        torch.from_numpy(cloud()), origin=ORIGIN, lengths=LENGTHS, shape=(3, 4, 5)
    )
    weights = tensor_product(bases)
    assert weights.shape == (inside.numel(), 60)
    torch.testing.assert_close(
        weights.sum(1), torch.ones(inside.numel(), dtype=F64), rtol=0, atol=1e-15
    )
    displacements = torch.from_numpy(random_mu((3, 4, 5)))
    torch.testing.assert_close(
        lattice_sum(bases, displacements),
        weights @ displacements.reshape(60, 3),
        rtol=0,
        atol=1e-15,
    )


def test_float32_matches_float64():
    points = cloud()
    displacements = random_mu((5, 4, 6))
    exact = FFD(torch.from_numpy(points), origin=ORIGIN, lengths=LENGTHS, shape=(5, 4, 6))
    single = FFD(torch.from_numpy(points).float(), origin=ORIGIN, lengths=LENGTHS, shape=(5, 4, 6))
    assert single.lengths.dtype == torch.float32
    assert torch.equal(single.inside, exact.inside)
    torch.testing.assert_close(
        single(torch.from_numpy(displacements).float()).double(),
        exact(torch.from_numpy(displacements)),
        rtol=0,
        atol=1e-6,
    )


# --------------------------------------------------------------------------- #
# gradients
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize(
    ("basis", "dim"), [("bernstein", 3), ("bspline", 3), ("bernstein", 2), ("bspline", 2)]
)
@pytest.mark.parametrize("factored", [True, False])
def test_gradcheck_in_the_displacements(basis, dim, factored):
    points = torch.from_numpy(cloud(count=25, dim=dim, low=-0.1, high=1.1))
    shape = (4, 5, 4)[:dim]
    morph = FFD(points, origin=ORIGIN[:dim], lengths=LENGTHS[:dim], shape=shape, basis=basis)
    rows = 4  # points per block: several blocks
    lattice = math.prod(shape)
    per_row = max(lattice, lattice // shape[-1] * 2 * dim) if factored else lattice
    block_bytes = rows * 8 * per_row
    assert morph.num_inside > 2 * rows

    def morph_with(displacements):
        return lattice_sum(morph.bases, displacements, block_bytes=block_bytes, factored=factored)

    displacements = torch.from_numpy(random_mu(shape)).expand(2, *shape, dim).clone()
    assert gradcheck(morph_with, (displacements.requires_grad_(True),))
    single = displacements[0].detach().clone().requires_grad_(True)
    assert gradgradcheck(morph_with, (single,), fast_mode=True)
    # the module's own choice
    assert gradcheck(morph, (single,))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("batch", [(), (3,), (16,), (2, 5)])
def test_factored_and_dense_sums_agree(dim, batch):
    points = torch.from_numpy(cloud(dim=dim, low=-0.1, high=1.1))
    shape = (6, 4, 5)[:dim]
    inside, bases = ffd_bases(points, origin=ORIGIN[:dim], lengths=LENGTHS[:dim], shape=shape)
    generator = torch.Generator().manual_seed(8)
    displacements = torch.randn(*batch, *shape, dim, generator=generator, dtype=F64)
    displacements.requires_grad_(True)
    upstream = torch.randn(*batch, inside.numel(), dim, generator=generator, dtype=F64)
    results = []
    for factored in (True, False):
        for block_bytes in (3000, None):
            moved = lattice_sum(bases, displacements, block_bytes=block_bytes, factored=factored)
            (gradient,) = torch.autograd.grad((moved * upstream).sum(), displacements)
            results.append((moved, gradient))
    expected = tensor_product(bases) @ displacements.detach().reshape(-1, math.prod(shape), dim)
    for moved, gradient in results:
        torch.testing.assert_close(moved, expected.reshape(moved.shape), rtol=0, atol=1e-14)
        torch.testing.assert_close(gradient, results[0][1], rtol=0, atol=1e-14)


def test_backward_keeps_the_bases_only_and_matches_the_weights():
    points = torch.from_numpy(cloud())
    morph = FFD(points, origin=ORIGIN, lengths=LENGTHS, shape=(4, 4, 4), block_bytes=2048)
    displacements = torch.from_numpy(random_mu((4, 4, 4))).requires_grad_(True)
    generator = torch.Generator().manual_seed(4)
    upstream = torch.randn(300, 3, generator=generator, dtype=F64)
    (gradient,) = torch.autograd.grad((morph(displacements) * upstream).sum(), displacements)
    weights = tensor_product(morph.bases)  # (N_in, 64)
    expected = (weights.T @ upstream[morph.inside]).reshape(4, 4, 4, 3)
    torch.testing.assert_close(gradient, expected, rtol=0, atol=1e-14)


@pytest.mark.parametrize("basis", ["bernstein", "bspline"])
def test_gradcheck_in_moved_points(basis):
    # points well inside: the clamp at the faces is not differentiable
    points = torch.from_numpy(cloud(count=12, low=0.05, high=0.95))
    morph = FFD(points, origin=ORIGIN, lengths=LENGTHS, shape=(4, 4, 5), basis=basis)
    displacements = torch.from_numpy(random_mu((4, 4, 5))).requires_grad_(True)
    moved_points = points.clone().requires_grad_(True)
    assert gradcheck(lambda d, x: morph(d, points=x), (displacements, moved_points))
    (gradient,) = torch.autograd.grad(morph(displacements, points=moved_points).sum(), moved_points)
    assert torch.isfinite(gradient).all() and (gradient != 0).all()
    # the stored points give the stored result
    torch.testing.assert_close(
        morph(displacements, points=points), morph(displacements), rtol=0, atol=1e-15
    )


def test_moved_points_leave_the_box():
    points = torch.from_numpy(cloud(count=50))
    morph = FFD(points, origin=ORIGIN, lengths=LENGTHS, shape=(3, 3, 3))
    displacements = torch.from_numpy(random_mu((3, 3, 3)))
    moved_points = points + torch.from_numpy(LENGTHS) * 2.0
    assert torch.equal(morph(displacements, points=moved_points), torch.zeros(50, 3, dtype=F64))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("basis", ["bernstein", "bspline"])
def test_cuda_matches_cpu(basis):
    points = torch.from_numpy(cloud(count=2000))
    displacements = torch.from_numpy(random_mu((6, 5, 7))).expand(3, 6, 5, 7, 3).contiguous()
    morph = FFD(points, origin=ORIGIN, lengths=LENGTHS, shape=(6, 5, 7), basis=basis)
    expected = morph(displacements)
    on_gpu = morph.to("cuda")
    torch.testing.assert_close(on_gpu(displacements.cuda()).cpu(), expected, rtol=0, atol=1e-14)
    built = FFD(points.cuda(), origin=ORIGIN, lengths=LENGTHS, shape=(6, 5, 7), basis=basis)
    torch.testing.assert_close(built(displacements.cuda()).cpu(), expected, rtol=0, atol=1e-14)
    for name in ("inside", "basis_x", "basis_y", "basis_z"):
        assert getattr(built, name).is_cuda


@pytest.mark.parametrize("basis", ["bernstein", "bspline"])
def test_bases_evaluated_in_blocks_equal_one_block(basis, monkeypatch):
    points = torch.from_numpy(cloud())
    box = dict(origin=ORIGIN, lengths=LENGTHS, shape=(5, 4, 6), basis=basis)
    inside, whole = ffd_bases(points, **box)
    monkeypatch.setattr(functional, "BASIS_BLOCK_ROWS", 7)
    blocked_inside, blocked = ffd_bases(points, **box)
    assert torch.equal(blocked_inside, inside)
    for matrix, reference in zip(blocked, whole, strict=True):
        assert torch.equal(matrix, reference)
    # with grad: the blocks are concatenated, and the gradient is the one-block one
    moved = points.clone().requires_grad_(True)
    (gradient,) = torch.autograd.grad(
        sum(m.square().sum() for m in ffd_bases(moved, **box)[1]), moved
    )
    monkeypatch.setattr(functional, "BASIS_BLOCK_ROWS", 2**15)
    (expected,) = torch.autograd.grad(
        sum(m.square().sum() for m in ffd_bases(moved, **box)[1]), moved
    )
    assert (gradient != 0).any()
    torch.testing.assert_close(gradient, expected, rtol=0, atol=1e-15)


def test_functional_is_differentiable_in_the_box():
    points = torch.from_numpy(cloud(count=10, low=0.1, high=0.9))
    displacements = torch.from_numpy(random_mu((3, 4, 3)))
    origin = torch.from_numpy(ORIGIN).requires_grad_(True)
    lengths = torch.from_numpy(LENGTHS).requires_grad_(True)
    rotation = torch.from_numpy(rotation_matrix((5.0, 10.0, -15.0)))

    def morph(origin, lengths):
        return ffd_apply(
            points=points,
            displacements=displacements,
            origin=origin,
            lengths=lengths,
            rotation=rotation,
        )

    assert gradcheck(morph, (origin, lengths))


@pytest.mark.parametrize("basis", ["bernstein", "bspline"])
def test_composes_with_torch_func(basis):
    points = torch.from_numpy(cloud(count=40))
    morph = FFD(
        points, origin=ORIGIN, lengths=LENGTHS, shape=(4, 4, 5), basis=basis, block_bytes=4000
    )
    family = (
        torch.from_numpy(random_mu((4, 4, 5)))
        * torch.linspace(0.5, 2.0, 6, dtype=F64)[:, None, None, None, None]
    )
    torch.testing.assert_close(torch.func.vmap(morph)(family), morph(family), rtol=0, atol=1e-15)
    backward = torch.func.jacrev(morph)(family[0])
    forward = torch.func.jacfwd(morph)(family[0])
    assert backward.shape == (40, 3, 4, 4, 5, 3)
    torch.testing.assert_close(forward, backward, rtol=0, atol=1e-15)
    # the Jacobian is the weight of each control point, the same on every component
    weights = torch.zeros(40, 80, dtype=F64)
    weights[morph.inside] = tensor_product(morph.bases)
    for component in range(3):
        torch.testing.assert_close(
            backward[:, component, ..., component].reshape(40, 80), weights, rtol=0, atol=1e-15
        )
    gradient = torch.func.grad(lambda d: morph(d).square().sum())(family[1])
    torch.testing.assert_close(
        gradient,
        torch.func.vmap(torch.func.grad(lambda d: morph(d).square().sum()))(family)[1],
        rtol=0,
        atol=1e-15,
    )
