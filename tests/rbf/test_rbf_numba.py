"""The fused numba kernels of the thin-plate spline against their torch twin (the
in-place blocks) and against NumPy's log."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmorph.rbf import RBF, _numba, kernels
from torchmorph.rbf.functional import evaluate

pytestmark = [
    pytest.mark.usefixtures("one_thread"),
    pytest.mark.skipif(not _numba.available(), reason="needs numba"),
]


def points(count, dim=3, seed=0, spread=1.0):
    return torch.from_numpy(np.random.default_rng(seed).normal(size=(count, dim)) * spread)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("spread", [1e-4, 1.0, 1e3])
def test_rows_equal_the_torch_blocks(dim, spread, monkeypatch):
    targets, controls = points(90, dim, spread=spread), points(70, dim, seed=1, spread=spread)
    targets[4] = controls[9]  # a zero distance
    fused = kernels.kernel_matrix(targets, controls, "thin_plate_spline", 1.3)
    monkeypatch.setattr(kernels, "fused", lambda kernel, points: False)
    plain = kernels.kernel_matrix(targets, controls, "thin_plate_spline", 1.3)
    assert fused[4, 9] == 0.0
    torch.testing.assert_close(fused, plain, rtol=2e-15, atol=1e-300)


def test_the_logarithm_over_the_range():
    # s log(s) / 2 against NumPy's log for s from 1e-300 to 1e300
    s = torch.from_numpy(np.logspace(-300, 300, 20001))
    row = torch.stack([s.sqrt(), torch.zeros_like(s), torch.zeros_like(s)], 1)
    origin = torch.zeros(1, 3, dtype=torch.float64)
    values = kernels.kernel_matrix(row, origin, "thin_plate_spline", 1.0)[:, 0].numpy()
    squared = (row[:, 0] ** 2).numpy()
    expected = 0.5 * squared * np.log(squared)
    np.testing.assert_allclose(values, expected, rtol=1e-15, atol=0)


@pytest.mark.parametrize("count", [40, 512, 1_100])  # one chunk, exactly one, three
@pytest.mark.parametrize("columns", [1, 2, 3, 6])  # 3: the one-pass branch
def test_apply_equals_rows_times_weights(count, columns):
    targets, controls = points(50), points(count, seed=1)
    weights = points(count, dim=columns, seed=2)
    poly = torch.zeros(0, columns, dtype=torch.float64)
    options = {"kernel": "thin_plate_spline", "scale": 0.7, "powers": [], "shift": None}
    fused = evaluate(targets, controls, weights, poly, poly_scale=None, **options)
    matrix = kernels.kernel_matrix(targets, controls, "thin_plate_spline", 0.7)
    # summation order differs: the bound is a few roundings of the sum of |terms|
    bound = 1e-15 * count * (matrix.abs() @ weights.abs())
    assert fused.shape == (50, columns)
    assert bool(((fused - matrix @ weights).abs() <= bound).all())


def test_a_strided_evaluation_matrix_is_written_in_place():
    controls, targets = points(30), points(45, seed=1)
    dense = RBF(controls, targets, mode="dense")
    assert dense.evaluation is not None and dense.evaluation.shape == (45, 34)
    expected = kernels.kernel_matrix(targets, controls, "thin_plate_spline", 1.0)
    torch.testing.assert_close(dense.evaluation[:, :30], expected, rtol=0, atol=0)


def test_the_fused_pass_is_differentiable_in_the_weights():
    from torch.autograd import gradcheck

    targets, controls = points(12), points(9, seed=1)
    weights = points(9, seed=2).requires_grad_()
    poly = torch.zeros(0, 3, dtype=torch.float64)

    def fused(weights):
        return evaluate(
            targets,
            controls,
            weights,
            poly,
            kernel="thin_plate_spline",
            scale=0.8,
            powers=[],
            shift=None,
            poly_scale=None,
        )

    assert gradcheck(fused, (weights,))
    morph = RBF(controls, targets, mode="matrix_free")
    values = points(9, seed=3).requires_grad_()
    assert gradcheck(morph, (values,))


def test_the_upper_triangle_alone():
    cloud = points(70)
    full = kernels.kernel_matrix(cloud, cloud, "thin_plate_spline", 1.3)
    out = torch.full((70, 70), float("nan"), dtype=torch.float64)
    _numba.tps_upper(cloud, 1.3, out)
    upper = torch.ones(70, 70, dtype=torch.bool).triu()
    torch.testing.assert_close(out[upper], full[upper], rtol=0, atol=0)
    assert bool(out[~upper].isnan().all())  # below the diagonal: not written


def test_a_dense_morph_is_differentiable_through_the_fused_product():
    from torch.autograd import gradcheck

    controls, targets = points(15), points(11, seed=1)
    morph = RBF(controls, targets, mode="dense")
    displacements = points(15, seed=2).requires_grad_()
    assert gradcheck(morph, (displacements,))
    batch = points(15, seed=3).reshape(1, 15, 3).repeat(2, 1, 1)  # six columns
    torch.testing.assert_close(morph(batch)[1], morph(batch[1]), rtol=0, atol=1e-13)
