"""The fused Triton kernels compiled on a CUDA device, through the public API, against
the torch implementation and a float64 reference (skipped without a CUDA device)."""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from torchmorph import IDW, idw_apply, idw_weights
from torchmorph.idw import fused_available

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]

F64 = torch.float64


def sphere_cloud(n_controls, n_targets, dtype, seed=0):
    """Controls on the unit sphere, targets inside it (graded towards the surface)."""
    generator = torch.Generator().manual_seed(seed)
    controls = torch.randn(n_controls, 3, generator=generator, dtype=F64)
    controls /= controls.norm(dim=1, keepdim=True)
    targets = torch.randn(n_targets, 3, generator=generator, dtype=F64)
    targets *= (
        torch.rand(n_targets, 1, generator=generator, dtype=F64) ** 0.25
        * 0.999
        / targets.norm(dim=1, keepdim=True)
    )
    return controls.to(dtype).cuda(), targets.to(dtype).cuda(), generator


def test_fused_kernels_are_available():
    assert fused_available("cuda")


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("batch", [None, 4, 16])
@pytest.mark.parametrize("power", [4.0, 2.5])
def test_fused_matrix_free_matches_float64(dtype, batch, power):
    controls, targets, generator = sphere_cloud(3000, 5000, dtype)
    shape = (3000, 3) if batch is None else (batch, 3000, 3)
    displacements = torch.randn(*shape, generator=generator, dtype=F64)
    reference = idw_apply(
        controls=controls.double().cpu(),
        targets=targets.double().cpu(),
        displacements=displacements,
        power=power,
        implementation="torch",
    )
    got = idw_apply(
        controls=controls,
        targets=targets,
        displacements=displacements.to(dtype).cuda(),
        power=power,
        implementation="fused",
    )
    error = (got.double().cpu() - reference).norm() / reference.norm()
    assert error < (1e-5 if dtype == torch.float32 else 1e-12), float(error)


def test_fused_batch_keeps_float32_accuracy_over_many_controls():
    # the batched pass runs on the matrix units: summed there over all 442 tiles of
    # controls, their truncating accumulation drifted to 6.7e-5 at these counts
    controls, targets, generator = sphere_cloud(14126, 2000, torch.float32, seed=1)
    displacements = torch.randn(16, 14126, 3, generator=generator, dtype=F64).cuda()
    reference = idw_apply(
        controls=controls.double(),
        targets=targets.double(),
        displacements=displacements,
        implementation="torch",
    )
    got = idw_apply(
        controls=controls,
        targets=targets,
        displacements=displacements.float(),
        implementation="fused",
    )
    error = (got.double() - reference).norm() / reference.norm()
    assert error < 1e-5, float(error)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_fused_wide_batch_and_its_gradient_run_in_groups_of_columns(dtype):
    # 100 displacements: 300 value columns, three launches of the batched pass each way
    controls, targets, generator = sphere_cloud(1500, 2500, dtype, seed=2)
    displacements = torch.randn(100, 1500, 3, generator=generator, dtype=F64)
    weights = idw_weights(
        controls=controls.double().cpu(), targets=targets.double().cpu(), implementation="torch"
    )
    leaf = displacements.to(dtype).cuda().requires_grad_()
    got = idw_apply(controls=controls, targets=targets, displacements=leaf, implementation="fused")
    expected = weights @ displacements
    tolerance = 1e-5 if dtype == torch.float32 else 1e-12
    assert (got.double().cpu() - expected).norm() / expected.norm() < tolerance
    upstream = torch.randn(100, 2500, 3, generator=generator, dtype=F64)
    got.backward(upstream.to(dtype).cuda())
    expected_grad = weights.T @ upstream
    error = (leaf.grad.double().cpu() - expected_grad).norm() / expected_grad.norm()
    assert error < tolerance, float(error)


def test_fused_exact_at_controls_and_mean_on_duplicates():
    controls, targets, generator = sphere_cloud(500, 800, F64)
    controls[7] = controls[6]
    targets[0], targets[1] = controls[3], controls[6]
    displacements = torch.randn(500, 3, generator=generator, dtype=F64).cuda()
    got = idw_apply(
        controls=controls, targets=targets, displacements=displacements, implementation="fused"
    )
    assert torch.equal(got[0], displacements[3])
    torch.testing.assert_close(got[1], (displacements[6] + displacements[7]) / 2)
    torch.testing.assert_close(
        got,
        idw_apply(
            controls=controls, targets=targets, displacements=displacements, implementation="torch"
        ),
    )


def test_fused_gradient_to_displacements_gradcheck():
    controls, targets, generator = sphere_cloud(40, 60, F64)
    displacements = torch.randn(2, 40, 3, generator=generator, dtype=F64).cuda()
    displacements.requires_grad_(True)
    assert gradcheck(
        lambda d: idw_apply(
            controls=controls, targets=targets, displacements=d, implementation="fused"
        ),
        (displacements,),
    )
    module = IDW(controls, targets, mode="matrix_free", implementation="fused")
    assert gradcheck(module, (displacements,))


def test_fused_gradient_to_positions_gradcheck():
    controls, targets, generator = sphere_cloud(30, 50, F64)
    targets[0] = controls[2]  # a coincident row: no gradient through it
    displacements = torch.randn(2, 30, 3, generator=generator, dtype=F64).cuda()
    targets.requires_grad_(True)
    controls.requires_grad_(True)
    displacements.requires_grad_(True)
    assert gradcheck(
        lambda t, c, d: idw_apply(
            controls=c, targets=t, displacements=d, power=3.0, implementation="fused"
        ),
        (targets, controls, displacements),
    )
    fused = torch.autograd.grad(
        idw_apply(controls=controls, targets=targets, displacements=displacements[0])
        .square()
        .sum(),
        (targets, controls),
    )
    plain = torch.autograd.grad(
        idw_apply(
            controls=controls,
            targets=targets,
            displacements=displacements[0],
            implementation="torch",
        )
        .square()
        .sum(),
        (targets, controls),
    )
    for got, expected in zip(fused, plain, strict=True):
        torch.testing.assert_close(got, expected)


def test_gradient_to_positions_with_many_columns_falls_back_to_torch():
    controls, targets, generator = sphere_cloud(30, 50, F64)
    displacements = torch.randn(9, 30, 3, generator=generator, dtype=F64).cuda()
    targets.requires_grad_(True)
    assert gradcheck(
        lambda t: idw_apply(controls=controls, targets=t, displacements=displacements), (targets,)
    )
    with pytest.raises(
        ValueError,
        match="implementation='fused' cannot run here: gradients to "
        "point positions are fused on CUDA for D <= 3",
    ):
        idw_apply(
            controls=controls, targets=targets, displacements=displacements, implementation="fused"
        )


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_fused_dense_assembly_and_apply(dtype):
    controls, targets, generator = sphere_cloud(2000, 3000, dtype)
    fused = idw_weights(controls=controls, targets=targets, implementation="fused")
    plain = idw_weights(controls=controls, targets=targets, implementation="torch")
    tolerance = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else {}
    torch.testing.assert_close(fused, plain, **tolerance)
    module = IDW(controls, targets, mode="dense")
    displacements = torch.randn(2000, 3, generator=generator, dtype=dtype).cuda()
    displacements.requires_grad_(True)
    moved = module(displacements)
    torch.testing.assert_close(moved, plain @ displacements, **tolerance)
    weights = torch.randn_like(moved)
    (gradient,) = torch.autograd.grad((moved * weights).sum(), displacements)
    torch.testing.assert_close(gradient, plain.T @ weights, **tolerance)


def test_module_to_cuda_uses_fused_kernels_and_matches_cpu():
    controls, targets, generator = sphere_cloud(400, 700, F64)
    displacements = torch.randn(3, 400, 3, generator=generator, dtype=F64)
    for mode in ("dense", "matrix_free"):
        on_cpu = IDW(controls.cpu(), targets.cpu(), mode=mode, implementation="torch")
        on_gpu = IDW(controls.cpu(), targets.cpu(), mode=mode).to("cuda")
        torch.testing.assert_close(on_gpu(displacements.cuda()).cpu(), on_cpu(displacements))


def test_traced_calls_use_torch_and_forcing_fused_there_fails():
    controls, targets, generator = sphere_cloud(50, 80, F64)
    module = IDW(controls, targets, mode="dense")
    mus = torch.linspace(0, 1, 5, dtype=F64).cuda()
    direction = torch.randn(50, 3, generator=generator, dtype=F64).cuda()
    batched = torch.func.vmap(lambda mu: module(mu * direction))(mus)
    torch.testing.assert_close(batched, module(mus[:, None, None] * direction))
    with pytest.raises(ValueError, match="the call is traced"):
        torch.func.vmap(
            lambda d: idw_apply(
                controls=controls, targets=targets, displacements=d, implementation="fused"
            )
        )(mus[:, None, None] * direction)
