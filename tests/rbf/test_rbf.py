"""The RBF module against scipy's RBFInterpolator (every kernel, degrees 1, 0 and -1,
float64), and the invariants of an interpolant: exact at the controls, affine motions
reproduced, batches equal to loops, dense equal to matrix-free, gradients checked."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scipy.interpolate import RBFInterpolator
from torch.autograd import gradcheck

from torchmorph.rbf import MIN_DEGREE, RBF, rbf_interpolate

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
SCIPY_KERNELS = [
    ("thin_plate_spline", None),
    ("linear", None),
    ("cubic", None),
    ("quintic", None),
    ("multiquadric", 4.0),
    ("inverse_multiquadric", 4.0),
    ("inverse_quadratic", 4.0),
    ("gaussian", 4.0),
]
WENDLAND = ["wendland_c0", "wendland_c2", "wendland_c4"]


def cloud(count, dim=3, seed=0):
    return np.random.default_rng(seed).uniform(size=(count, dim))


def scipy_reference(controls, values, targets, kernel, epsilon, degree):
    with warnings.catch_warnings():  # scipy warns for degrees below a kernel's order
        warnings.simplefilter("ignore")
        interpolant = RBFInterpolator(
            controls, values, kernel=kernel, epsilon=epsilon, degree=degree
        )
    at_controls = float(np.abs(interpolant(controls) - values).max())
    return interpolant(targets), at_controls


@pytest.mark.parametrize(("kernel", "epsilon"), SCIPY_KERNELS)
@pytest.mark.parametrize("degree", [2, 1, 0, -1])
@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_equals_scipy(kernel, epsilon, degree, mode):
    if degree < MIN_DEGREE.get(kernel, -1):
        pytest.skip("scipy warns: below the kernel's order the system may be singular")
    controls, targets = cloud(60), cloud(200, seed=1)
    values = np.random.default_rng(2).normal(size=(60, 3))
    reference, scipy_error = scipy_reference(controls, values, targets, kernel, epsilon, degree)
    morph = RBF(
        torch.from_numpy(controls),
        torch.from_numpy(targets),
        kernel=kernel,
        epsilon=epsilon,
        degree=degree,
        mode=mode,
    )
    result = morph(torch.from_numpy(values)).numpy()
    assert np.abs(result - reference).max() <= 10 * scipy_error
    at_controls = RBF(
        torch.from_numpy(controls),
        torch.from_numpy(controls),
        kernel=kernel,
        epsilon=epsilon,
        degree=degree,
        mode=mode,
    )(torch.from_numpy(values)).numpy()
    assert np.abs(at_controls - values).max() <= 10 * scipy_error


@pytest.mark.parametrize("kernel", WENDLAND)
def test_wendland_is_exact_at_the_controls_and_local(kernel):
    controls, _targets = cloud(80), cloud(50, seed=1)
    values = torch.from_numpy(np.random.default_rng(2).normal(size=(80, 3)))
    radius = 0.5
    at_controls = RBF(
        torch.from_numpy(controls),
        torch.from_numpy(controls),
        kernel=kernel,
        support_radius=radius,
        degree=-1,
    )(values)
    torch.testing.assert_close(at_controls, values, rtol=0, atol=1e-11)
    # without a polynomial, a target farther than the radius from every control stays put
    far = torch.tensor([[3.0, 3.0, 3.0]], dtype=F64)
    morph = RBF(torch.from_numpy(controls), far, kernel=kernel, support_radius=radius, degree=-1)
    assert torch.equal(morph(values), torch.zeros(1, 3, dtype=F64))


@pytest.mark.parametrize("kernel", WENDLAND)
def test_wendland_functions(kernel):
    # the textbook forms of Wendland's phi_{3,k} at r = distance / support_radius
    radius = 0.8
    distance = np.linspace(0.0, 1.0, 11)
    r = distance / radius
    rest = np.clip(1 - r, 0, None)
    expected = {
        "wendland_c0": rest**2,
        "wendland_c2": rest**4 * (4 * r + 1),
        "wendland_c4": rest**6 * (35 * r**2 + 18 * r + 3) / 3,
    }[kernel]
    points = torch.from_numpy(np.stack([distance, 0 * distance, 0 * distance], 1))
    origin = torch.zeros(1, 3, dtype=F64)
    from torchmorph.rbf.kernels import kernel_matrix

    values = kernel_matrix(points, origin, kernel, 1 / radius)[:, 0].numpy()
    np.testing.assert_allclose(values, expected, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize(("kernel", "epsilon"), [*SCIPY_KERNELS[:4], ("gaussian", 3.0)])
@pytest.mark.parametrize("dim", [2, 3])
def test_affine_motions_are_reproduced(kernel, epsilon, dim):
    controls, targets = cloud(70, dim), cloud(150, dim, seed=1) * 1.5 - 0.25
    rng = np.random.default_rng(3)
    matrix, shift = rng.normal(size=(dim, dim)), rng.normal(size=dim)
    values = controls @ matrix.T + shift
    morph = RBF(
        torch.from_numpy(controls), torch.from_numpy(targets), kernel=kernel, epsilon=epsilon
    )
    result = morph(torch.from_numpy(values)).numpy()
    np.testing.assert_allclose(result, targets @ matrix.T + shift, rtol=0, atol=1e-10)


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_batches_equal_loops_and_modes_agree(mode):
    controls, targets = torch.from_numpy(cloud(50)), torch.from_numpy(cloud(120, seed=1))
    batch = torch.from_numpy(np.random.default_rng(4).normal(size=(4, 50, 3)))
    morph = RBF(controls, targets, mode=mode, block_bytes=4096)
    looped = torch.stack([morph(values) for values in batch])
    torch.testing.assert_close(morph(batch), looped, rtol=0, atol=1e-13)
    other = RBF(controls, targets, mode="matrix_free" if mode == "dense" else "dense")
    torch.testing.assert_close(other(batch), morph(batch), rtol=0, atol=1e-12)


def test_the_one_shot_function_equals_the_module():
    controls, targets = torch.from_numpy(cloud(40)), torch.from_numpy(cloud(30, seed=1))
    values = torch.from_numpy(np.random.default_rng(5).normal(size=(2, 40, 3)))
    for kernel, epsilon in SCIPY_KERNELS:
        module = RBF(controls, targets, kernel=kernel, epsilon=epsilon)
        direct = rbf_interpolate(
            controls=controls, targets=targets, displacements=values, kernel=kernel, epsilon=epsilon
        )
        torch.testing.assert_close(direct, module(values), rtol=0, atol=1e-10)


def test_float32_follows_float64():
    controls, targets = cloud(50), cloud(80, seed=1)
    values = np.random.default_rng(6).normal(size=(50, 3)) * 0.1
    single = RBF(
        torch.tensor(controls, dtype=torch.float32), torch.tensor(targets, dtype=torch.float32)
    )
    double = RBF(torch.from_numpy(controls), torch.from_numpy(targets))
    result = single(torch.tensor(values, dtype=torch.float32))
    assert result.dtype == torch.float32
    torch.testing.assert_close(result.double(), double(torch.from_numpy(values)), rtol=0, atol=1e-5)


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize(("kernel", "epsilon"), [("thin_plate_spline", None), ("gaussian", 2.0)])
def test_gradcheck_displacements(mode, kernel, epsilon):
    controls, targets = torch.from_numpy(cloud(12)), torch.from_numpy(cloud(9, seed=1))
    morph = RBF(controls, targets, kernel=kernel, epsilon=epsilon, mode=mode)
    values = torch.from_numpy(np.random.default_rng(7).normal(size=(2, 12, 3)))
    assert gradcheck(morph, (values.requires_grad_(),))


@pytest.mark.parametrize(
    ("kernel", "epsilon", "support"),
    [
        ("thin_plate_spline", None, None),
        ("cubic", None, None),
        ("multiquadric", 1.5, None),
        ("wendland_c2", None, 0.9),
    ],
)
def test_gradcheck_positions(kernel, epsilon, support):
    controls, targets = torch.from_numpy(cloud(10)), torch.from_numpy(cloud(7, seed=1))
    values = torch.from_numpy(np.random.default_rng(8).normal(size=(10, 3)))
    morph = RBF(
        controls,
        targets,
        kernel=kernel,
        epsilon=epsilon,
        support_radius=support,
        degree=-1 if support else 1,
    )

    def moved(c, t):
        return morph(values, controls=c, targets=t)

    assert gradcheck(moved, (controls.clone().requires_grad_(), targets.clone().requires_grad_()))
    # a target on a control: the gradient stays finite
    on_control = controls[:3].clone().requires_grad_()
    morph3 = RBF(
        controls,
        controls[:3],
        kernel=kernel,
        epsilon=epsilon,
        support_radius=support,
        degree=-1 if support else 1,
    )
    morph3(values, targets=on_control).sum().backward()
    assert torch.isfinite(on_control.grad).all()


def test_module_built_from_points_that_require_grad():
    controls = torch.from_numpy(cloud(10)).requires_grad_()
    targets = torch.from_numpy(cloud(6, seed=1))
    values = torch.from_numpy(np.random.default_rng(9).normal(size=(10, 3)))
    RBF(controls, targets)(values).square().sum().backward()
    assert controls.grad is not None and controls.grad.abs().sum() > 0


@pytest.mark.parametrize("kernel", [name for name, _ in SCIPY_KERNELS] + WENDLAND)
def test_in_place_blocks_equal_the_masked_kernels(kernel):
    from torchmorph.rbf.kernels import KERNELS, kernel_matrix

    points, centres = torch.from_numpy(cloud(70)), torch.from_numpy(cloud(40, seed=1))
    points[5] = centres[3]  # one zero distance
    fast = kernel_matrix(points, centres, kernel, 1.7)
    distance = torch.cdist(points, centres) * 1.7
    function, at_zero = KERNELS[kernel]
    expected = torch.where(distance > 0, function(distance.square()), at_zero)
    torch.testing.assert_close(fast, expected, rtol=1e-13, atol=1e-14)
    slow = kernel_matrix(points.clone().requires_grad_(), centres, kernel, 1.7)
    torch.testing.assert_close(slow.detach(), fast, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize(
    ("kernel", "epsilon", "degree"),
    [("thin_plate_spline", None, 1), ("cubic", None, 2), ("gaussian", 12.0, -1)],
)
def test_equals_scipy_where_lapack_factorises(kernel, epsilon, degree):
    # from LAPACK_CHOLESKY_ORDER controls on, one triangle of the system is assembled and
    # factorised (with and without the polynomial's projection)
    controls, targets = cloud(1_050), cloud(300, seed=1)
    values = np.random.default_rng(2).normal(size=(1_050, 3))
    reference, scipy_error = scipy_reference(controls, values, targets, kernel, epsilon, degree)
    morph = RBF(
        torch.from_numpy(controls),
        torch.from_numpy(np.concatenate([targets, controls])),
        kernel=kernel,
        epsilon=epsilon,
        degree=degree,
    )
    assert morph.solver == "cholesky"
    result = morph(torch.from_numpy(values)).numpy()
    scale = np.abs(reference).max()
    assert np.abs(result[:300] - reference).max() <= max(10 * scipy_error, 1e-9 * scale)
    assert np.abs(result[300:] - values).max() <= max(10 * scipy_error, 1e-9)


@pytest.mark.parametrize(
    ("degree", "kernel", "size"),
    [
        (0, "cubic", 50),
        (1, "cubic", 50),
        (2, "cubic", 50),
        # from LAPACK_CHOLESKY_ORDER on: one triangle by the BLAS (the fused thin-plate
        # spline writes only that one, the torch blocks of the cubic the whole matrix)
        (1, "thin_plate_spline", 1_004),
        (1, "cubic", 1_004),
    ],
)
def test_the_projected_blocks_equal_lapack_ormqr(degree, kernel, size):
    from torchmorph.rbf.kernels import (
        kernel_matrix,
        monomial_powers,
        polynomial_matrix,
        polynomial_scaling,
    )
    from torchmorph.rbf.system import LAPACK_CHOLESKY_ORDER, cholesky, projected_blocks

    controls = torch.from_numpy(cloud(size))
    shift, scale = polynomial_scaling(controls)
    poly = polynomial_matrix(controls, monomial_powers(3, degree), shift, scale)
    qr, tau = torch.geqrf(poly)
    matrix = kernel_matrix(controls, controls, kernel, 1.0)
    left = torch.ormqr(qr, tau, matrix, left=True, transpose=True)
    expected = torch.ormqr(qr, tau, left, left=False, transpose=False)
    trailing, coupling = projected_blocks(controls, kernel, 1.0, qr, tau)
    count = poly.shape[1]
    assert trailing.is_contiguous()
    tolerance = 1e-12 * float(matrix.abs().max())
    if size - count >= LAPACK_CHOLESKY_ORDER:  # the triangle LAPACK reads
        upper = torch.ones_like(trailing, dtype=torch.bool).triu()
        torch.testing.assert_close(
            trailing[upper], expected[count:, count:][upper], rtol=0, atol=tolerance
        )
        factor, info = cholesky(trailing.clone())
        assert info == 0
        torch.testing.assert_close(
            factor @ factor.T, expected[count:, count:], rtol=0, atol=1e3 * tolerance
        )
    else:
        torch.testing.assert_close(trailing, expected[count:, count:], rtol=0, atol=tolerance)
    torch.testing.assert_close(coupling, expected[:count, count:], rtol=0, atol=tolerance)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_cuda_matches_cpu(mode):
    controls, targets = torch.from_numpy(cloud(80)), torch.from_numpy(cloud(300, seed=1))
    values = torch.from_numpy(np.random.default_rng(3).normal(size=(2, 80, 3)))
    morph = RBF(controls, targets, mode=mode)
    expected = morph(values)
    on_gpu = morph.to("cuda")
    torch.testing.assert_close(on_gpu(values.cuda()).cpu(), expected, rtol=0, atol=1e-11)
    built = RBF(controls.cuda(), targets.cuda(), mode=mode)
    torch.testing.assert_close(built(values.cuda()).cpu(), expected, rtol=0, atol=1e-11)
    moved = controls.cuda().requires_grad_()
    built(values.cuda(), controls=moved).sum().backward()
    assert moved.grad is not None and torch.isfinite(moved.grad).all()


def test_the_cpu_cholesky_equals_torch():
    from torchmorph.rbf.system import cholesky

    generator = torch.Generator().manual_seed(1)
    square = torch.randn(40, 40, dtype=F64, generator=generator)
    matrix = square @ square.T + 40 * torch.eye(40, dtype=F64)
    factor, info = cholesky(matrix[3:, 3:])  # a strided block, as the fit's
    assert info == 0
    torch.testing.assert_close(factor, torch.linalg.cholesky(matrix[3:, 3:]), rtol=0, atol=1e-13)
    indefinite = matrix.clone()
    indefinite[5, 5] = -1.0
    assert cholesky(indefinite)[1] > 0
