"""The fused Triton kernels against a float64 brute force, run on the CPU by Triton's
interpreter (``TRITON_INTERPRET=1``, set by conftest.py when there is no CUDA device);
on a CUDA machine tests/test_gpu_fused.py runs them compiled.

Needs the ``triton`` extra (``pip install -e '.[triton]'``); skipped without it.
"""

from __future__ import annotations

import os

import pytest
import torch

pytest.importorskip("triton")

# masked tile columns take log2(0) = -inf on the way to a weight of exactly 0
pytestmark = pytest.mark.filterwarnings("ignore:divide by zero encountered in log2")

F64 = torch.float64


@pytest.fixture(scope="module")
def kernels():
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present: tests/test_gpu_fused.py runs the compiled kernels")
    if os.environ.get("TRITON_INTERPRET") != "1":
        pytest.skip("TRITON_INTERPRET is not 1 (set by conftest.py before triton is imported)")
    from torchmorph.idw.backends.triton import kernels as _triton_kernels

    return _triton_kernels


def brute_force(targets, controls, power, radius2):
    """W of eq. (2) in float64 with the coincidence rule (mean over controls within the
    radius), written independently of the kernels."""
    t, c = targets.double(), controls.double()
    dist2 = ((t[:, None, :] - c[None, :, :]) ** 2).sum(-1)
    weights = torch.zeros_like(dist2)
    for row in range(dist2.shape[0]):
        close = dist2[row] <= radius2
        if close.any():
            weights[row, close] = 1.0 / int(close.sum())
        else:
            inverse = dist2[row] ** (-power / 2)
            weights[row] = inverse / inverse.sum()
    return weights


def cloud(n_targets, n_controls, dim, dtype, seed):
    generator = torch.Generator().manual_seed(seed)
    controls = torch.rand(n_controls, dim, generator=generator, dtype=F64) * 2 - 1
    targets = torch.rand(n_targets, dim, generator=generator, dtype=F64) * 2 - 1
    targets[3] = controls[5]  # a target on a control
    controls[9] = controls[8]  # duplicated controls ...
    targets[4] = controls[8]  # ... and a target on them: the mean
    return targets.to(dtype), controls.to(dtype), generator


TOLERANCES = {torch.float32: dict(rtol=2e-5, atol=2e-6), F64: dict(rtol=1e-11, atol=1e-13)}


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize(
    ("power", "dim", "columns"),
    [(4.0, 3, 3), (2.0, 3, 1), (1.0, 2, 2), (0.5, 3, 3), (7.5, 3, 5), (4.0, 3, 20)]
    + [(3.0, 3, 3), (5.0, 2, 1), (6.0, 3, 2), (7.0, 3, 3), (8.0, 3, 1)],  # every power code
)
def test_apply_and_transposed_match_brute_force(kernels, dtype, power, dim, columns):
    # sizes that are not multiples of the tiles: masked rows and columns
    targets, controls, generator = cloud(70, 45, dim, dtype, seed=int(power * 10) + columns)
    values = torch.randn(45, columns, generator=generator, dtype=F64).to(dtype)
    radius2 = 1e-20
    weights = brute_force(targets, controls, power, radius2)
    nearest2 = kernels.nearest_squared(targets.T.contiguous(), controls.T.contiguous())
    out, sums = kernels.apply(
        targets.T.contiguous(), controls.T.contiguous(), values, power, radius2, nearest2
    )
    torch.testing.assert_close(out.double(), weights @ values.double(), **TOLERANCES[dtype])
    assert torch.equal(out[3], values[5])  # exact interpolation
    torch.testing.assert_close(
        out[4].double(), (values[8].double() + values[9].double()) / 2, **TOLERANCES[dtype]
    )
    grad = torch.randn(70, columns, generator=generator, dtype=F64).to(dtype)
    transposed = kernels.apply_transposed(
        targets.T.contiguous(), controls.T.contiguous(), grad, power, radius2, nearest2, sums
    )
    torch.testing.assert_close(transposed.double(), weights.T @ grad.double(), **TOLERANCES[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_dense_weights_and_dense_apply(kernels, dtype):
    targets, controls, generator = cloud(50, 37, 3, dtype, seed=1)
    expected = brute_force(targets, controls, 4.0, 1e-20)
    weights = kernels.weights(targets.T.contiguous(), controls.T.contiguous(), 4.0, 1e-20)
    torch.testing.assert_close(weights.double(), expected, **TOLERANCES[dtype])
    torch.testing.assert_close(
        weights.sum(1).double(), torch.ones(50, dtype=F64), **TOLERANCES[dtype]
    )
    for columns in (1, 2, 3):
        values = torch.randn(37, columns, generator=generator, dtype=F64).to(dtype)
        torch.testing.assert_close(
            kernels.dense_apply(weights, values).double(),
            weights.double() @ values.double(),
            **TOLERANCES[dtype],
        )
    with pytest.raises(ValueError, match="values: dense_apply takes 1 to 3 columns, got 4"):
        kernels.dense_apply(weights, torch.zeros(37, 4, dtype=dtype))


def test_coincidence_radius_selects_near_controls(kernels):
    targets, controls, generator = cloud(20, 30, 3, F64, seed=2)
    targets[0] = controls[1] + 1e-7  # within a radius of 1e-6, not exactly on it
    values = torch.randn(30, 3, generator=generator, dtype=F64)
    out, sums = kernels.apply(targets.T.contiguous(), controls.T.contiguous(), values, 0.5, 1e-12)
    assert torch.equal(out[0], values[1])
    assert sums[0] == 1.0
    expected = brute_force(targets, controls, 0.5, 1e-12) @ values
    torch.testing.assert_close(out, expected, rtol=1e-11, atol=1e-13)


def test_nearest_squared(kernels):
    targets, controls, _ = cloud(33, 21, 3, F64, seed=4)
    expected = ((targets[:, None] - controls[None]) ** 2).sum(-1).amin(1)
    got = kernels.nearest_squared(targets.T.contiguous(), controls.T.contiguous())
    torch.testing.assert_close(got, expected.clamp_min(torch.finfo(F64).tiny), rtol=0, atol=0)


def test_one_power_code_for_every_backend():
    from torchmorph.idw.backends import power_code

    powers = (4, 2.0, 1, 3.0, 5, 6, 7, 8.0, 0.5, 7.5, 9, 12)
    assert [power_code(p) for p in powers] == [4, 2, 1, 3, 5, 6, 7, 8, 0, 0, 0, 0]


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize(("power", "columns"), [(4.0, 3), (1.5, 1), (3.0, 7)])
def test_position_gradients_match_autograd(kernels, dtype, power, columns):
    targets, controls, generator = cloud(40, 30, 3, F64, seed=5)
    values = torch.randn(30, columns, generator=generator, dtype=F64)
    grad = torch.randn(40, columns, generator=generator, dtype=F64)
    radius2 = 1e-20
    # reference: autograd through a float64 brute force of the same function
    t, c = targets.clone().requires_grad_(True), controls.clone().requires_grad_(True)
    dist2 = ((t[:, None, :] - c[None, :, :]) ** 2).sum(-1)
    coincident = dist2.detach().amin(1, keepdim=True) <= radius2
    safe = torch.where(coincident, torch.ones_like(dist2), dist2)
    inverse = safe ** (-power / 2)
    weights = torch.where(
        coincident,
        brute_force(targets, controls, power, radius2),
        inverse / inverse.sum(1, keepdim=True),
    )
    expected = torch.autograd.grad(((weights @ values) * grad).sum(), (t, c))
    targets_t, controls_t = targets.T.contiguous().to(dtype), controls.T.contiguous().to(dtype)
    nearest2 = kernels.nearest_squared(targets_t, controls_t)
    out, sums = kernels.apply(targets_t, controls_t, values.to(dtype), power, radius2, nearest2)
    got = kernels.position_gradients(
        targets_t, controls_t, values.to(dtype), grad.to(dtype), out, nearest2, sums, power, radius2
    )
    tolerance = dict(rtol=1e-4, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-9)
    for value, reference in zip(got, expected, strict=True):
        torch.testing.assert_close(value.T.double(), reference, **tolerance)


@pytest.mark.parametrize("ones_column", [True, False])
def test_dot_operands_split_float32_exactly_into_a_tf32_part_and_a_rest(kernels, ones_column):
    generator = torch.Generator().manual_seed(3)
    values = torch.randn(9, 5, generator=generator) * torch.logspace(-30, 30, 5)
    hi, lo, padded, split = kernels._dot_operands(values, ones_column)
    assert split and padded == 16 and hi.shape == lo.shape == (9, 16)
    assert hi.is_contiguous() and lo.is_contiguous()
    assert not (hi.view(torch.int32) & 0x1FFF).any()  # hi has tf32's 10 mantissa bits
    assert torch.equal(hi[:, :5] + lo[:, :5], values)  # and the rest is exact
    assert (lo.abs() <= hi.abs() * 2**-10).all()
    assert torch.equal(hi[:, 5], torch.full((9,), float(ones_column)))
    assert not hi[:, 6:].any() and not lo[:, 5:].any()
    full, same, padded, split = kernels._dot_operands(values.double(), ones_column)
    assert not split and same is full and torch.equal(full[:, :5], values.double())


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_wide_batches_run_in_groups_of_columns(kernels, dtype, monkeypatch):
    # 40 columns in launches of at most 16 padded columns: 15 + 15 + 10 forward (each
    # with the column of ones), 16 + 16 + 8 transposed
    monkeypatch.setattr(kernels, "DOT_COLUMNS", 16)
    targets, controls, generator = cloud(70, 45, 3, dtype, seed=11)
    values = torch.randn(45, 40, generator=generator, dtype=F64).to(dtype)
    weights = brute_force(targets, controls, 4.0, 1e-20)
    nearest2 = kernels.nearest_squared(targets.T.contiguous(), controls.T.contiguous())
    out, sums = kernels.apply(
        targets.T.contiguous(), controls.T.contiguous(), values, 4.0, 1e-20, nearest2
    )
    torch.testing.assert_close(out.double(), weights @ values.double(), **TOLERANCES[dtype])
    assert torch.equal(out[3], values[5])
    grad = torch.randn(70, 40, generator=generator, dtype=F64).to(dtype)
    transposed = kernels.apply_transposed(
        targets.T.contiguous(), controls.T.contiguous(), grad, 4.0, 1e-20, nearest2, sums
    )
    torch.testing.assert_close(transposed.double(), weights.T @ grad.double(), **TOLERANCES[dtype])
