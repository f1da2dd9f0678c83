"""IDW weights, the IDW module and the matrix-free path (SPEC.md §1)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from torchmorph import IDW, idw_apply, idw_weights
from torchmorph.idw import fused_available
from torchmorph.idw.module import auto_mode

F64 = torch.float64


def brute_force_weights(targets: np.ndarray, controls: np.ndarray, power: float = 4.0):
    """Eq. (2) literally, in float64 NumPy: |x - c|^-p normalised, exact at controls."""
    weights = np.zeros((len(targets), len(controls)))
    for i, x in enumerate(targets):
        dist = np.sqrt(((x - controls) ** 2).sum(1))
        if (dist == 0).any():
            weights[i, np.argmin(dist)] = 1.0
            continue
        inverse = dist ** (-power)
        weights[i] = inverse / inverse.sum()
    return weights


def cloud(n_targets=40, n_controls=25, seed=0, dtype=F64):
    generator = torch.Generator().manual_seed(seed)
    controls = torch.rand(n_controls, 3, generator=generator, dtype=dtype)
    targets = torch.rand(n_targets, 3, generator=generator, dtype=dtype)
    return targets, controls, generator


def graded_cloud(dtype=F64):
    """Controls and targets on spheres whose radii span 1e-6 .. 1e2."""
    generator = torch.Generator().manual_seed(7)

    def sphere_points(radii, per_shell):
        directions = torch.randn(len(radii) * per_shell, 3, generator=generator, dtype=F64)
        directions /= directions.norm(dim=1, keepdim=True)
        return (
            directions
            * torch.repeat_interleave(torch.as_tensor(radii, dtype=F64), per_shell)[:, None]
        )

    controls = sphere_points(np.logspace(-6, 2, 9), 12)
    targets = sphere_points(np.logspace(-6, 2, 17) * 1.7, 8)
    return targets.to(dtype), controls.to(dtype)


# --------------------------------------------------------------------------- #
# weights
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("power", [1.0, 2.0, 3.5, 4.0, 6.0])
def test_weights_match_brute_force(power):
    targets, controls, _ = cloud()
    weights = idw_weights(controls=controls, targets=targets, power=power)
    reference = brute_force_weights(targets.numpy(), controls.numpy(), power)
    torch.testing.assert_close(weights, torch.from_numpy(reference), rtol=1e-12, atol=1e-14)


def test_targets_on_and_next_to_controls_get_that_row():
    targets, controls, _ = cloud()
    targets[0] = controls[3]
    targets[1] = controls[7] + 1e-12
    targets[2] = controls[9] - torch.tensor([0.0, 1e-12, 0.0], dtype=F64)
    weights = idw_weights(controls=controls, targets=targets)
    for row, control in ((0, 3), (1, 7), (2, 9)):
        expected = torch.zeros(controls.shape[0], dtype=F64)
        expected[control] = 1.0
        assert torch.equal(weights[row], expected)
    reference = brute_force_weights(targets.numpy(), controls.numpy())
    torch.testing.assert_close(weights, torch.from_numpy(reference), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_rows_sum_to_one_and_lie_in_unit_interval(dtype):
    targets, controls = graded_cloud(dtype)
    weights = idw_weights(controls=controls, targets=targets)
    assert torch.isfinite(weights).all()
    assert (weights >= 0).all() and (weights <= 1).all()
    tolerance = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(
        weights.sum(1), torch.ones(len(targets), dtype=dtype), rtol=0, atol=tolerance
    )


def test_float32_weights_do_not_overflow_far_or_near():
    # |x - c|^-4 alone overflows float32 below 1e-10 and underflows above 1e10
    controls = torch.tensor([[0.0, 0, 0], [1e-11, 0, 0], [3e10, 0, 0]], dtype=torch.float32)
    targets = torch.tensor([[5e-12, 1e-12, 0.0], [1e10, 0, 0]], dtype=torch.float32)
    weights = idw_weights(controls=controls, targets=targets, coincidence_tolerance=0.0)
    assert torch.isfinite(weights).all()
    reference = brute_force_weights(targets.double().numpy(), controls.double().numpy())
    torch.testing.assert_close(weights.double(), torch.from_numpy(reference), rtol=1e-5, atol=1e-6)


def test_uniform_displacement_is_reproduced_exactly():
    targets, controls = graded_cloud()
    shift = torch.tensor([0.25, -1.5, 3.0], dtype=F64)
    displacements = shift.expand(controls.shape[0], 3).contiguous()
    for mode in ("dense", "matrix_free"):
        moved = IDW(controls, targets, mode=mode)(displacements)
        torch.testing.assert_close(moved, shift.expand_as(moved), rtol=1e-14, atol=1e-14)


def test_weights_of_a_2d_cloud():
    generator = torch.Generator().manual_seed(3)
    controls = torch.rand(10, 2, generator=generator, dtype=F64)
    targets = torch.rand(6, 2, generator=generator, dtype=F64)
    reference = brute_force_weights(targets.numpy(), controls.numpy())
    torch.testing.assert_close(
        idw_weights(controls=controls, targets=targets), torch.from_numpy(reference)
    )


# --------------------------------------------------------------------------- #
# module: dense and matrix-free
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_batched_equals_loop_of_single_calls(mode):
    targets, controls, generator = cloud(n_targets=60, n_controls=33)
    batch = torch.randn(5, 33, 3, generator=generator, dtype=F64)
    morph = IDW(controls, targets, mode=mode, block_bytes=8192)
    batched = morph(batch)
    assert batched.shape == (5, 60, 3)
    looped = torch.stack([morph(single) for single in batch])
    torch.testing.assert_close(batched, looped, rtol=1e-13, atol=1e-14)


def test_dense_module_applies_the_weight_matrix():
    targets, controls, generator = cloud()
    displacements = torch.randn(controls.shape[0], 3, generator=generator, dtype=F64)
    morph = IDW(controls, targets, mode="dense")
    weights = torch.from_numpy(brute_force_weights(targets.numpy(), controls.numpy()))
    torch.testing.assert_close(morph.weights_matrix(), weights)
    torch.testing.assert_close(morph(displacements), weights @ displacements)


def test_matrix_free_equals_dense_in_float64():
    targets, controls = graded_cloud()
    generator = torch.Generator().manual_seed(11)
    displacements = torch.randn(4, controls.shape[0], 3, generator=generator, dtype=F64)
    dense = IDW(controls, targets, mode="dense")(displacements)
    for block_bytes in (512, 4096, 10**6):  # tiles of a few rows/columns up to one tile
        free = idw_apply(
            controls=controls, targets=targets, displacements=displacements, block_bytes=block_bytes
        )
        torch.testing.assert_close(free, dense, rtol=0, atol=1e-12)


def test_float32_matches_float64_on_graded_cloud():
    targets, controls = graded_cloud()
    generator = torch.Generator().manual_seed(5)
    displacements = torch.randn(controls.shape[0], 3, generator=generator, dtype=F64)
    exact = IDW(controls, targets, mode="dense")(displacements)
    scale = exact.abs().amax(1, keepdim=True).clamp_min(displacements.abs().max() * 1e-3)
    for mode in ("dense", "matrix_free"):
        single = IDW(controls.float(), targets.float(), mode=mode)(displacements.float())
        relative = ((single.double() - exact).abs() / scale).max()
        assert relative < 1e-5, (mode, float(relative))


def test_auto_mode_picks_by_device_dtype_and_budget():
    targets, controls, _ = cloud()
    # the torch implementation (or a GPU) in float64: W stored when it fits
    assert IDW(controls, targets, implementation="torch").mode == "dense"
    small_budget = IDW(controls, targets, dense_bytes=100, implementation="torch")
    assert small_budget.mode == "matrix_free" and small_budget.weights is None
    # float32: never a float32 W, whose BLAS sums are less accurate than the kernels'
    assert IDW(controls.float(), targets.float(), implementation="torch").mode == "matrix_free"
    # the fused CPU kernels: one pass costs about a dense product, so no W
    expected = "matrix_free" if fused_available("cpu") else "dense"
    assert IDW(controls, targets).mode == expected
    assert auto_mode(40, 25, dtype=F64, device=torch.device("cpu"), dense_bytes=10**9) == expected
    with pytest.raises(ValueError, match="mode must be"):
        IDW(controls, targets, mode="sparse")


def test_empty_target_set_gives_empty_result():
    _, controls, generator = cloud()
    morph = IDW(controls, torch.zeros(0, 3, dtype=F64))
    assert morph(torch.randn(controls.shape[0], 3, generator=generator, dtype=F64)).shape == (0, 3)


# --------------------------------------------------------------------------- #
# autograd
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_gradcheck_displacements(mode):
    targets, controls, generator = cloud(n_targets=7, n_controls=9)
    displacements = torch.randn(2, 9, 3, generator=generator, dtype=F64, requires_grad=True)
    morph = IDW(controls, targets, mode=mode, block_bytes=400)
    assert gradcheck(morph, (displacements,))


def test_gradcheck_positions_functional():
    targets, controls, generator = cloud(n_targets=6, n_controls=8)
    targets.requires_grad_(True)
    controls.requires_grad_(True)
    displacements = torch.randn(8, 3, generator=generator, dtype=F64, requires_grad=True)
    assert gradcheck(
        lambda t, c, d: idw_weights(controls=c, targets=t) @ d, (targets, controls, displacements)
    )
    assert gradcheck(
        lambda t, c, d: idw_apply(controls=c, targets=t, displacements=d, block_bytes=300),
        (targets, controls, displacements),
    )


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_module_built_from_positions_that_require_grad_rebuilds_w(mode):
    targets, controls, generator = cloud(n_targets=6, n_controls=8)
    targets.requires_grad_(True)
    controls.requires_grad_(True)
    displacements = torch.randn(8, 3, generator=generator, dtype=F64)
    morph = IDW(controls, targets, mode=mode)
    morph(displacements).square().sum().backward()
    assert controls.grad is not None and controls.grad.abs().sum() > 0
    assert targets.grad is not None and targets.grad.abs().sum() > 0
    # and the gradient is the true one
    assert gradcheck(
        lambda t, c: IDW(c, t, mode=mode)(displacements),
        (targets.detach().requires_grad_(), controls.detach().requires_grad_()),
    )


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_forward_with_moved_geometry_against_finite_differences(mode):
    targets, controls, generator = cloud(n_targets=5, n_controls=7)
    displacements = torch.randn(7, 3, generator=generator, dtype=F64)
    morph = IDW(controls, targets, mode=mode)
    moved = controls.clone().requires_grad_(True)
    objective = morph(displacements, controls=moved).sum()
    (gradient,) = torch.autograd.grad(objective, moved)
    step = 1e-6
    for index in [(0, 0), (3, 1), (6, 2)]:
        plus, minus = controls.clone(), controls.clone()
        plus[index] += step
        minus[index] -= step
        numeric = (
            morph(displacements, controls=plus).sum() - morph(displacements, controls=minus).sum()
        ) / (2 * step)
        assert math.isclose(float(gradient[index]), float(numeric), rel_tol=1e-6, abs_tol=1e-9)


# --------------------------------------------------------------------------- #
# buffers, devices, state
# --------------------------------------------------------------------------- #
def test_state_dict_round_trip():
    targets, controls, generator = cloud()
    morph = IDW(controls, targets, mode="dense")
    state = morph.state_dict()
    assert set(state) == {"controls", "targets", "weights", "_extra_state"}
    assert state["_extra_state"] == {"power": 4.0, "coincidence_tolerance": 1e-10, "mode": "dense"}
    shifted = IDW(controls + 1.0, targets, mode="dense")
    shifted.load_state_dict(state)
    displacements = torch.randn(controls.shape[0], 3, generator=generator, dtype=F64)
    torch.testing.assert_close(shifted(displacements), morph(displacements), rtol=0, atol=0)


def test_state_with_another_power_or_tolerance_fails_to_load():
    targets, controls, _ = cloud()
    state = IDW(controls, targets, power=2.0).state_dict()
    with pytest.raises(
        ValueError, match="power: the state was saved with power=2.0 but this IDW has power=4.0"
    ):
        IDW(controls, targets).load_state_dict(state)
    state = IDW(controls, targets, coincidence_tolerance=1e-6).state_dict()
    with pytest.raises(ValueError, match="coincidence_tolerance: the state was saved with"):
        IDW(controls, targets).load_state_dict(state)


@pytest.mark.parametrize(("saved", "loaded"), [("dense", "matrix_free"), ("matrix_free", "dense")])
def test_state_loads_across_modes(saved, loaded):
    targets, controls, generator = cloud()
    other_targets, other_controls, _ = cloud(seed=3)
    source = IDW(controls, targets, mode=saved)
    receiver = IDW(other_controls, other_targets, mode=loaded)
    receiver.load_state_dict(source.state_dict())
    assert receiver.mode == loaded
    displacements = torch.randn(controls.shape[0], 3, generator=generator, dtype=F64)
    torch.testing.assert_close(receiver(displacements), source(displacements))


def test_module_copies_its_inputs():
    targets, controls, generator = cloud()
    displacements = torch.randn(controls.shape[0], 3, generator=generator, dtype=F64)
    for mode in ("dense", "matrix_free"):
        moved_controls, moved_targets = controls.clone(), targets.clone()
        morph = IDW(moved_controls, moved_targets, mode=mode)
        before = morph(displacements)
        moved_controls.mul_(2.0)  # the caller edits its tensors in place
        moved_targets.add_(1.0)
        torch.testing.assert_close(morph(displacements), before, rtol=0, atol=0)


def test_to_dtype_moves_buffers():
    targets, controls, generator = cloud()
    morph = IDW(controls, targets, mode="dense").to(torch.float32)
    assert morph.weights.dtype == morph.controls.dtype == torch.float32
    displacements = torch.randn(controls.shape[0], 3, generator=generator)
    torch.testing.assert_close(
        morph(displacements).double(),
        IDW(controls, targets)(displacements.double()),
        rtol=1e-5,
        atol=1e-6,
    )


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_cuda_matches_cpu(mode):
    targets, controls, generator = cloud(n_targets=500, n_controls=300)
    displacements = torch.randn(3, 300, 3, generator=generator, dtype=F64)
    expected = IDW(controls, targets, mode=mode)(displacements)
    on_gpu = IDW(controls, targets, mode=mode).to("cuda")
    torch.testing.assert_close(on_gpu(displacements.cuda()).cpu(), expected)


# --------------------------------------------------------------------------- #
# errors
# --------------------------------------------------------------------------- #
def test_errors_name_the_argument():
    targets, controls, _ = cloud()
    # points of any dimension D, the same for controls and targets
    with pytest.raises(ValueError, match=r"targets must have shape \(N, 2\), got \(40, 3\)"):
        IDW(controls[:, :2], targets)
    with pytest.raises(ValueError, match=r"controls must have shape \(N, 3\), got \(25,\)"):
        IDW(controls[:, 0], targets)
    with pytest.raises(ValueError, match="controls is empty"):
        IDW(controls[:0], targets)
    with pytest.raises(ValueError, match="targets must have shape"):
        idw_weights(controls=controls, targets=targets[:, :2])
    bad = controls.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match="controls holds 1 NaN or infinite"):
        IDW(bad, targets)
    bad = targets.clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match="targets holds 1 NaN or infinite"):
        idw_weights(controls=controls, targets=bad)
    for power in (0.0, -2.0, float("nan")):
        with pytest.raises(ValueError, match="power must be a finite number > 0"):
            IDW(controls, targets, power=power)
    with pytest.raises(ValueError, match="targets has dtype torch.float32 but controls"):
        IDW(controls, targets.float())


def test_forward_errors_name_the_argument():
    targets, controls, _ = cloud()
    morph = IDW(controls, targets)
    with pytest.raises(
        ValueError, match=r"displacements must have shape \(25, 3\) or \(B, 25, 3\)"
    ):
        morph(torch.zeros(24, 3, dtype=F64))
    with pytest.raises(ValueError, match="displacements has dtype torch.float32"):
        morph(torch.zeros(25, 3))
    bad = torch.zeros(25, 3, dtype=F64)
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="displacements holds 1 NaN"):
        morph(bad)
    with pytest.raises(ValueError, match="controls must have shape"):
        morph(torch.zeros(25, 3, dtype=F64), controls=controls[:3])
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="displacements is on device"):
            morph(torch.zeros(25, 3, dtype=F64, device="cuda"))
    with pytest.raises(ValueError, match="displacements must have shape"):
        idw_apply(
            controls=controls, targets=targets, displacements=torch.zeros(2, 2, 25, 3, dtype=F64)
        )


# --------------------------------------------------------------------------- #
# numerics: scale, duplicates, coincident gradients; memory; implementations
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize(
    ("dtype", "scale"),
    [(torch.float32, 1e-19), (torch.float32, 1e30), (F64, 1e-170), (F64, 1e155), (F64, 1e300)],
)
def test_weights_do_not_depend_on_the_units(dtype, scale):
    targets, controls, _ = cloud()
    expected = idw_weights(controls=controls, targets=targets)
    got = idw_weights(controls=(controls * scale).to(dtype), targets=(targets * scale).to(dtype))
    assert torch.isfinite(got).all()
    tolerance = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else {}
    torch.testing.assert_close(got.double(), expected, **tolerance)


def test_duplicate_controls_give_the_mean_whatever_their_order():
    targets, controls, generator = cloud()
    controls[11] = controls[4]
    targets[0] = controls[4]
    displacements = torch.randn(25, 3, generator=generator, dtype=F64)
    with pytest.warns(
        UserWarning,
        match="controls: 2 control points lie within the coincidence radius of another one",
    ):
        morph = IDW(controls, targets, mode="dense")
    moved = morph(displacements)
    torch.testing.assert_close(moved[0], (displacements[4] + displacements[11]) / 2)
    order = torch.randperm(25, generator=generator)
    with pytest.warns(UserWarning, match="controls: 2 control points"):
        permuted = IDW(controls[order], targets, mode="matrix_free")
    torch.testing.assert_close(permuted(displacements[order]), moved)


@pytest.mark.parametrize("power", [0.5, 1.0, 1.5])
def test_position_gradients_are_finite_on_coincident_rows(power):
    targets, controls, _ = cloud()
    controls[0] = torch.tensor([50.0, 50.0, 50.0], dtype=F64)  # a far control
    targets[2] = controls[5]  # a target exactly on a control
    targets.requires_grad_(True)
    controls.requires_grad_(True)
    displacements = torch.randn(25, 3, dtype=F64)
    for function in (
        lambda: idw_weights(controls=controls, targets=targets, power=power) @ displacements,
        lambda: idw_apply(
            controls=controls, targets=targets, displacements=displacements, power=power
        ),
    ):
        gradients = torch.autograd.grad(function().square().sum(), (targets, controls))
        assert all(torch.isfinite(g).all() for g in gradients)


def test_dense_that_cannot_fit_fails_before_allocating(monkeypatch):
    from torchmorph.idw import module as idw_module

    targets, controls, _ = cloud()
    monkeypatch.setattr(idw_module, "free_memory", lambda device: 1000)
    with pytest.raises(
        ValueError,
        match=r"mode='dense': W \(40 x 25, 0.0 GiB\) does not fit in "
        r"the 0.0 GiB free on cpu; use mode='matrix_free'",
    ):
        IDW(controls, targets, mode="dense")
    torch_only = {"implementation": "torch"}  # where auto stores W that fits
    assert IDW(controls, targets, **torch_only).mode == "matrix_free"  # half of what is free
    monkeypatch.setattr(idw_module, "free_memory", lambda device: 2 * 40 * 25 * 8)
    assert IDW(controls, targets, **torch_only).mode == "dense"


def test_implementation_is_checked_and_forced_fused_explains_why_not():
    targets, controls, _ = cloud()
    displacements = torch.zeros(25, 3, dtype=F64)
    with pytest.raises(
        ValueError, match="implementation must be one of 'auto', 'fused', 'torch'; got 'cuda'"
    ):
        IDW(controls, targets, implementation="cuda")
    if not fused_available("cpu"):
        with pytest.raises(
            ValueError,
            match="implementation='fused' cannot run here: no fused kernels on device cpu",
        ):
            idw_apply(
                controls=controls,
                targets=targets,
                displacements=displacements,
                implementation="fused",
            )
    torch.testing.assert_close(
        idw_apply(
            controls=controls,
            targets=targets,
            displacements=displacements + 1.0,
            implementation="torch",
        ),
        torch.ones(40, 3, dtype=F64),
    )


@pytest.mark.skipif(not fused_available("cpu"), reason="needs numba (the CPU fused kernels)")
@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_cpu_fused_matches_torch(mode):
    targets, controls, generator = cloud(n_targets=300, n_controls=200)
    controls[7] = controls[6]
    targets[0] = controls[6]
    displacements = torch.randn(4, 200, 3, generator=generator, dtype=F64)
    with pytest.warns(UserWarning, match="controls: 2 control points"):
        fused = IDW(controls, targets, mode=mode, implementation="fused")
    with pytest.warns(UserWarning, match="controls: 2 control points"):
        plain = IDW(controls, targets, mode=mode, implementation="torch")
    torch.testing.assert_close(fused(displacements), plain(displacements))
    assert gradcheck(fused, (displacements[:1].detach().requires_grad_(True),))


def test_points_are_keywords_and_the_old_positional_order_is_deprecated():
    targets, controls, generator = cloud()
    displacements = torch.randn(25, 3, generator=generator, dtype=F64)
    expected = idw_apply(controls=controls, targets=targets, displacements=displacements)
    with pytest.warns(
        DeprecationWarning,
        match=r"idw_apply\(targets, controls, \.\.\.\) with "
        "positional points is deprecated",
    ):
        old = idw_apply(targets, controls, displacements)
    torch.testing.assert_close(old, expected, rtol=0, atol=0)
    with pytest.warns(DeprecationWarning, match=r"idw_weights\(targets, controls"):
        weights = idw_weights(targets, controls)
    torch.testing.assert_close(weights @ displacements, expected)
    with pytest.raises(
        TypeError,
        match=r"idw_weights\(\) takes its points as keywords: "
        r"idw_weights\(controls=\.\.\., targets=\.\.\.\)",
    ):
        idw_weights(targets, controls=controls)
    with pytest.raises(TypeError, match=r"idw_apply\(\) needs displacements="):
        idw_apply(controls=controls, targets=targets)


def test_no_targets_with_gradients_gives_an_empty_result():
    _, controls, generator = cloud()
    controls.requires_grad_(True)
    targets = torch.zeros(0, 3, dtype=F64, requires_grad=True)
    displacements = torch.randn(25, 3, generator=generator, dtype=F64, requires_grad=True)
    for mode in ("dense", "matrix_free"):
        module = IDW(controls, targets, mode=mode)
        moved = module(displacements, targets=targets)
        assert moved.shape == (0, 3)
        moved.sum().backward()
    assert torch.equal(displacements.grad, torch.zeros_like(displacements))


# --------------------------------------------------------------------------- #
# numeric guards: extreme inputs give the right answer or a clear error
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("power", ["4", True, None, 1 + 2j])
def test_power_must_be_a_real_number(power):
    targets, controls, _ = cloud()
    with pytest.raises(ValueError, match="power must be a finite number > 0, got"):
        IDW(controls, targets, power=power)
    with pytest.raises(ValueError, match="power must be a finite number > 0, got"):
        idw_weights(controls=controls, targets=targets, power=power)


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize("implementation", ["torch", "fused"])
@pytest.mark.parametrize(("dtype", "largest"), [(F64, 1.7e308), (torch.float32, 3.3e38)])
def test_displacements_near_the_largest_number_stay_finite(mode, implementation, dtype, largest):
    targets, controls, generator = cloud()
    targets, controls = targets.to(dtype), controls.to(dtype)
    unit = torch.rand(25, 3, generator=generator, dtype=F64).to(dtype)
    idw = IDW(controls, targets, mode=mode, implementation=implementation)
    huge = idw(unit * largest)
    assert bool(torch.isfinite(huge).all())
    # the morph is linear: the same field scaled (exact, as the weights are in [0, 1])
    expected = idw(unit.double().to(dtype)).double() * largest
    rtol = 1e-14 if dtype == F64 else 2e-6
    torch.testing.assert_close(huge.double(), expected, rtol=rtol, atol=0)


def test_float32_clouds_too_far_apart_to_resolve_are_refused():
    targets, controls, generator = cloud()
    displacements = torch.rand(25, 3, generator=generator, dtype=F64)
    far = controls.float().clone()
    far[0] = 1e25  # one control far away: the others' squared distances underflow
    with warnings.catch_warnings():  # refused before its collapsed controls are reported
        warnings.simplefilter("error")
        with pytest.raises(
            ValueError, match=r"targets span .* torch.float32 cannot resolve .* use float64"
        ):
            IDW(far, targets.float(), coincidence_tolerance=0)
    # float64 resolves them: the far control has (almost) no weight
    far = controls.clone()
    far[0] = 1e25
    near = IDW(controls[1:], targets)(displacements[1:])
    torch.testing.assert_close(
        IDW(far, targets, coincidence_tolerance=0)(displacements),
        near,
        rtol=1e-12,
        atol=1e-14,
    )


def test_matrix_free_first_call_streams_and_later_calls_reuse_the_nearest_distances():
    pytest.importorskip("numba")
    generator = torch.Generator().manual_seed(11)
    controls = torch.rand(700, 3, generator=generator, dtype=torch.float64)
    targets = torch.rand(900, 3, generator=generator, dtype=torch.float64)
    d = torch.randn(700, 3, generator=generator, dtype=torch.float64)
    free = IDW(controls, targets, mode="matrix_free", implementation="fused")
    dense = IDW(controls, targets, mode="dense", implementation="torch")
    first = free(d)
    assert free._fused_cache is not None and free._fused_cache[-1] is not None
    torch.testing.assert_close(first, dense(d), rtol=0, atol=1e-12)
    torch.testing.assert_close(free(2 * d), 2 * first, rtol=0, atol=1e-12)
    # with a graph to the displacements the first call is differentiable as before
    other = IDW(controls, targets, mode="matrix_free", implementation="fused")
    d.requires_grad_(True)
    other(d).sum().backward()
    torch.testing.assert_close(d.grad, dense.weights.sum(0)[:, None].expand(700, 3))
