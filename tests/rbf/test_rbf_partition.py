"""The partition-of-unity RBF (:class:`torchmorph.rbf.PartitionRBF`): exact at the
controls, weights that sum to 1, affine motions reproduced, the global dense fit as its
limit and its reference, batches, gradients, float32, saved state and argument checks."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch

from torchmorph.rbf import RBF, PartitionRBF, _numba, build_rbf
from torchmorph.rbf import partition as partition_defaults
from torchmorph.rbf import solvers as solvers_module
from torchmorph.rbf._parallel import tps_apply_parallel
from torchmorph.rbf.patches import build_patches, kd_split, midpoint_split, wendland_weight

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
SMALL = {"patch_size": 40, "coarse_size": 60}
DEFAULT_ITERATIONS = partition_defaults.DEFAULT_MAX_ITERATIONS


def sphere(count: int) -> torch.Tensor:
    """A Fibonacci lattice on the unit sphere."""
    index = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * index / count)
    azimuth = math.pi * (1 + 5**0.5) * index
    return torch.from_numpy(
        np.stack(
            [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
        )
    )


def box_walls(per_side: int = 8, half: float = 2.5) -> torch.Tensor:
    """A grid on each face of the cube [-half, half]³ (the points of one face coplanar)."""
    ticks = (np.arange(per_side) + 0.5) / per_side * 2 * half - half
    first, second = (grid.ravel() for grid in np.meshgrid(ticks, ticks, indexing="ij"))
    faces = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        for side in (-half, half):
            face = np.zeros((first.shape[0], 3))
            face[:, others[0]], face[:, others[1]], face[:, axis] = first, second, side
            faces.append(face)
    return torch.from_numpy(np.concatenate(faces))


def shell(count: int, seed: int = 0, inner: float = 1.05, outer: float = 2.4) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(inner**3, outer**3, size=(count, 1)) ** (1 / 3)
    return torch.from_numpy(direction * radius)


def body_and_walls() -> torch.Tensor:
    return torch.cat([sphere(300), box_walls()])


def smooth_field(points: torch.Tensor) -> torch.Tensor:
    x, y, z = points.T
    return 0.05 * torch.stack([torch.sin(3 * x) + z * y, torch.cos(2 * y) * x, z**2 - 0.3 * x], 1)


def test_exact_at_the_controls():
    controls = body_and_walls()
    values = torch.from_numpy(np.random.default_rng(1).normal(size=(controls.shape[0], 3)))
    module = PartitionRBF(controls, controls, **SMALL)
    assert module.num_patches > 5
    torch.testing.assert_close(module(values), values, rtol=0, atol=1e-10)


def test_the_blend_weights_sum_to_one_at_the_controls_and_fade_far_away():
    controls = body_and_walls()
    far = torch.tensor([[40.0, 0.0, 0.0]], dtype=F64)
    module = PartitionRBF(controls, torch.cat([controls, far]), **SMALL)
    sums = torch.zeros(controls.shape[0] + 1, dtype=F64)
    sums.index_add_(0, module.blend_targets, module.blend_weights)
    torch.testing.assert_close(sums[:-1], torch.ones(controls.shape[0], dtype=F64))
    assert sums[-1] == 0  # far from every patch: no patch's value
    assert (module.blend_weights > 0).all()


def test_a_target_far_from_every_control_gets_the_coarse_fit():
    controls = body_and_walls()
    far = torch.tensor([[40.0, 3.0, -2.0], [-30.0, 10.0, 5.0]], dtype=F64)
    module = PartitionRBF(controls, far, **SMALL)
    assert module.blend_targets.numel() == 0
    values = smooth_field(controls)
    coarse = module.coarse_indices
    reference = RBF(controls[coarse], far)(values[coarse])
    torch.testing.assert_close(module(values), reference, rtol=1e-10, atol=1e-12)


def test_affine_motions_are_reproduced_with_flat_patches_on_the_walls():
    controls = body_and_walls()
    targets = shell(500, outer=3.5)
    module = PartitionRBF(controls, targets, **SMALL)
    assert module.patch_flat.any(), "the walls' patches should be flat"
    matrix = torch.tensor([[0.1, -0.3, 0.2], [0.05, 0.2, -0.1], [0.3, 0.0, 0.15]], dtype=F64)
    shift = torch.tensor([0.4, -1.0, 2.0], dtype=F64)
    moved = module(controls @ matrix.T + shift)
    torch.testing.assert_close(moved, targets @ matrix.T + shift, rtol=0, atol=1e-10)


def test_all_controls_coarse_is_the_global_fit():
    controls, targets = sphere(200), shell(300)
    values = smooth_field(controls)
    module = PartitionRBF(controls, targets, patch_size=40, coarse_size=200)
    assert module.num_patches == 0
    reference = RBF(controls, targets)(values)
    torch.testing.assert_close(module(values), reference, rtol=0, atol=1e-11)


def test_close_to_the_global_fit_on_a_sphere():
    """Surface controls, volume targets (radius 1.05 to 2.4), a smooth field: the relative
    2-norm error 2.6e-4 measured (1,500 controls, 400 coarse, cells of 60; 1.7e-3 with
    150 coarse: the coarse fit sets the error)."""
    controls, targets = sphere(1500), shell(3000)
    values = smooth_field(controls)
    module = PartitionRBF(controls, targets, patch_size=60, coarse_size=400)
    reference = RBF(controls, targets)(values)
    error = float((module(values) - reference).norm() / reference.norm())
    assert error < 4e-4


def test_other_kernels_and_float32_run_the_torch_blocks():
    controls = body_and_walls()
    values = smooth_field(controls)
    cubic = PartitionRBF(controls, controls, kernel="cubic", **SMALL)
    torch.testing.assert_close(cubic(values), values, rtol=0, atol=1e-10)
    wendland = PartitionRBF(
        controls, controls, kernel="wendland_c2", support_radius=1.0, degree=-1, **SMALL
    )
    torch.testing.assert_close(wendland(values), values, rtol=0, atol=1e-10)
    single = PartitionRBF(controls.float(), controls.float(), **SMALL)
    moved = single(values.float())
    assert moved.dtype == torch.float32
    torch.testing.assert_close(moved, values.float(), rtol=0, atol=1e-6)


def test_a_batch_equals_the_loop():
    controls, targets = body_and_walls(), shell(200)
    module = PartitionRBF(controls, targets, **SMALL)
    rng = np.random.default_rng(2)
    batch = torch.from_numpy(rng.normal(size=(3, controls.shape[0], 3)))
    together = module(batch)
    assert together.shape == (3, 200, 3)
    for index in range(3):
        torch.testing.assert_close(together[index], module(batch[index]), rtol=1e-12, atol=1e-11)


def test_gradcheck_in_the_displacements():
    controls = torch.cat([sphere(40), box_walls(3)])
    module = PartitionRBF(controls, shell(15, outer=2.0), patch_size=12, coarse_size=20)
    assert module.num_patches > 2
    values = smooth_field(controls).requires_grad_()
    assert torch.autograd.gradcheck(module, (values,), eps=1e-6, atol=1e-7, fast_mode=True)


def test_the_parallel_fused_pass_equals_the_one_thread_pass():
    if not _numba.available():
        pytest.skip("numba is not installed")
    points, centres = shell(700), sphere(90)
    weights = torch.from_numpy(np.random.default_rng(3).normal(size=(90, 4)))
    torch.testing.assert_close(
        tps_apply_parallel(points, centres, 1.3, weights, 2),
        _numba.tps_apply(points, centres, 1.3, weights),
        rtol=1e-13,
        atol=1e-13,
    )


def test_the_splits():
    points = sphere(1000).numpy()
    cells = kd_split(points, 7)
    assert len(cells) == 7
    assert sorted(np.concatenate(cells).tolist()) == list(range(1000))
    assert max(map(len, cells)) - min(map(len, cells)) <= 1
    leaves = midpoint_split(points, 50)
    assert sorted(np.concatenate(leaves).tolist()) == list(range(1000))
    assert max(map(len, leaves)) <= 50
    assert wendland_weight(np.array([0.0, 1.0, 2.0])).tolist() == [1.0, 0.0, 0.0]


def test_every_patch_holds_its_cell_and_the_local_polynomial_terms_more():
    """Small cells, thin overlap: without the ``extra`` rule a patch held its 5 own
    controls and 2 more, so its local fit (4 polynomial terms) left 3 free coefficients for
    5 own controls, and the global fit's preconditioner was singular."""
    points = torch.cat([sphere(40), box_walls(3)]).numpy()
    for extra in (0, 4):
        patches = build_patches(points, 12, 1.5, 6, extra)
        for index in range(patches.centres.shape[0]):
            held = patches.members[
                patches.member_offsets[index] : patches.member_offsets[index + 1]
            ]
            own = int((patches.owner == index).sum())
            assert np.isin(np.flatnonzero(patches.owner == index), held).all()
            assert held.shape[0] >= min(own + extra, points.shape[0])
    short = build_patches(points, 12, 1.5, 6, 0)
    counts = np.diff(short.member_offsets) - np.bincount(short.owner)
    assert counts.min() < 4  # the case the rule is for


def saved(module) -> dict:
    buffer = io.BytesIO()
    torch.save(module.state_dict(), buffer)
    buffer.seek(0)
    return torch.load(buffer)


def test_state_dict_round_trip():
    controls, targets = body_and_walls(), shell(100)
    original = PartitionRBF(controls, targets, **SMALL)
    loaded = PartitionRBF(sphere(150), shell(7, seed=4), **SMALL)  # other points
    loaded.load_state_dict(saved(original))
    values = smooth_field(controls)
    assert loaded.num_patches == original.num_patches
    assert torch.equal(loaded(values), original(values))


@pytest.mark.parametrize(
    ("field", "options"),
    [
        ("patch_size", {"patch_size": 41}),
        ("overlap", {"overlap": 1.6}),
        ("kernel", {"kernel": "cubic"}),
    ],
)
def test_a_mismatched_hyperparameter_is_refused(field, options):
    state = PartitionRBF(body_and_walls(), shell(10), **SMALL).state_dict()
    other = PartitionRBF(body_and_walls(), shell(10), **{**SMALL, **options})
    with pytest.raises(ValueError, match=f"^{field}: the state was saved with {field}="):
        other.load_state_dict(state)


@pytest.mark.parametrize(
    ("options", "error", "message"),
    [
        ({"patch_size": 3}, ValueError, r"^patch_size must be an integer >= 8, got 3"),
        ({"patch_size": 40.0}, ValueError, "^patch_size must be an integer"),
        ({"overlap": 1.0}, ValueError, r"^overlap must be > 1 \(patches must overlap\)"),
        ({"overlap": -2.0}, ValueError, "^overlap must be"),
        ({"coarse_size": 0}, ValueError, "^coarse_size must be an integer >= 4"),
        ({"kernel": "tps"}, ValueError, "^kernel must be one of"),
        ({"kernel": "gaussian"}, ValueError, "^epsilon must be given"),
        ({"tolerance": 0.0}, ValueError, "^tolerance must be"),
        ({"tolerance": float("nan")}, ValueError, "^tolerance must be"),
        ({"max_iterations": 0}, ValueError, r"^max_iterations must be an integer >= 1, got 0"),
    ],
)
def test_bad_arguments(options, error, message):
    with pytest.raises(error, match=message):
        PartitionRBF(sphere(50), shell(5), **options)


def test_bad_displacements():
    module = PartitionRBF(sphere(50), shell(5), patch_size=10, coarse_size=20)
    with pytest.raises(ValueError, match="^displacements must have shape"):
        module(torch.zeros(49, 3, dtype=F64))
    with pytest.raises(ValueError, match="^controls: points 0 and 50 coincide"):
        PartitionRBF(torch.cat([sphere(50), sphere(50)[:1]]), shell(5))


def test_build_rbf_picks_by_the_control_count(monkeypatch):
    controls, targets = sphere(60), shell(5)
    assert type(build_rbf(controls, targets)) is RBF
    assert type(build_rbf(controls, targets, solver="partition", patch_size=20)) is PartitionRBF
    monkeypatch.setattr(solvers_module, "PARTITION_CONTROLS", 50)
    assert type(build_rbf(controls, targets, coarse_size=20)) is PartitionRBF
    assert type(build_rbf(controls, targets, solver="dense", mode="dense")) is RBF
    with pytest.raises(ValueError, match="^solver must be one of"):
        build_rbf(controls, targets, solver="bogus")


@pytest.mark.slow
def test_close_to_the_global_fit_with_walls():
    """A sphere of 3,000 controls moving inside a box of 2,400 fixed wall controls,
    targets in the box: the relative 2-norm error against the global fit 6.5e-4 measured
    with 2,000 coarse controls (1.4e-3 with 1,000), exact at the controls."""
    controls = torch.cat([sphere(3000), box_walls(20)])
    rng = np.random.default_rng(5)
    targets = torch.from_numpy(rng.uniform(-2.5, 2.5, size=(6000, 3)))
    targets = torch.cat([targets[targets.norm(dim=1) > 1.05], controls[::50]])
    values = smooth_field(controls)
    values[3000:] = 0
    reference = RBF(controls, targets)(values)
    module = PartitionRBF(controls, targets, coarse_size=2000)
    moved = module(values)
    error = float((moved - reference).norm() / reference.norm())
    assert error < 1e-3
    torch.testing.assert_close(moved[-108:], values[::50], rtol=0, atol=1e-10)


@pytest.mark.parametrize("tolerance", [1e-4, 1e-9])
def test_a_tolerance_gives_the_global_fit(tolerance):
    """The body inside walls with few coarse controls (the partition alone is 1e-2 from the
    global fit here): the preconditioned iterations reach the global dense fit to about
    the tolerance in a few iterations, and the morph stays exact at the controls."""
    controls = body_and_walls()
    targets = torch.cat([shell(400, outer=2.4), controls[::7]])
    values = smooth_field(controls)
    values[300:] = 0
    reference = RBF(controls, targets)(values)
    alone = PartitionRBF(controls, targets, **SMALL)(values)
    assert float((alone - reference).norm() / reference.norm()) > 1e-3
    module = PartitionRBF(controls, targets, tolerance=tolerance, **SMALL)
    moved = module(values)
    error = float((moved - reference).norm() / reference.norm())
    assert error < 10 * tolerance
    assert 1 <= module.last_iterations_ <= 20
    assert module.last_residual_.shape == (3,)
    assert (module.last_residual_ <= tolerance).all()
    torch.testing.assert_close(moved[-len(controls[::7]) :], values[::7], rtol=0, atol=1e-10)


def test_a_tolerance_with_other_kernels_batches_and_affine_motions():
    controls, targets = body_and_walls(), shell(150, outer=3.0)
    for options in ({"kernel": "cubic"}, {"kernel": "gaussian", "epsilon": 4.0, "degree": -1}):
        reference = RBF(controls, targets, **options)
        module = PartitionRBF(controls, targets, tolerance=1e-10, **options, **SMALL)
        values = smooth_field(controls)
        torch.testing.assert_close(module(values), reference(values), rtol=0, atol=1e-9)
    module = PartitionRBF(controls, targets, tolerance=1e-8, **SMALL)
    batch = torch.from_numpy(np.random.default_rng(3).normal(size=(2, controls.shape[0], 3)))
    together = module(batch)
    for index in range(2):
        torch.testing.assert_close(together[index], module(batch[index]), rtol=0, atol=1e-7)
    matrix = torch.tensor([[0.1, -0.3, 0.2], [0.05, 0.2, -0.1], [0.3, 0.0, 0.15]], dtype=F64)
    moved = module(controls @ matrix.T)
    torch.testing.assert_close(moved, targets @ matrix.T, rtol=0, atol=1e-10)
    assert module.last_iterations_ == 0  # the coarse fit reproduces it: no iteration


def test_a_tolerance_gradcheck_and_the_stopped_solve_warns():
    controls = torch.cat([sphere(40), box_walls(3)])
    module = PartitionRBF(
        controls, shell(15, outer=2.0), patch_size=12, coarse_size=20, tolerance=1e-13
    )
    values = smooth_field(controls).requires_grad_()
    assert torch.autograd.gradcheck(module, (values,), eps=1e-6, atol=1e-7, fast_mode=True)
    short = PartitionRBF(
        controls, shell(15, outer=2.0), patch_size=12, coarse_size=20, tolerance=1e-14,
        max_iterations=1,
    )  # fmt: skip
    with pytest.warns(RuntimeWarning, match=r"^PartitionRBF: the global fit stopped at "
                      r"max_iterations=1 with a relative residual of .* > tolerance=1e-14"):  # fmt: skip
        short(smooth_field(controls))
    assert short.last_iterations_ == 1


def test_the_backward_pass_of_the_global_fit_is_the_transpose():
    """⟨g, M v⟩ = ⟨Mᵀ g, v⟩ for the linear morph M, to the solve's tolerance. The backward
    solve's right-hand side has moment rows (Pᵀλ = s, s ≠ 0) that the forward one does
    not; a preconditioner blind to them stalled it (3× off)."""
    controls = body_and_walls()
    module = PartitionRBF(controls, shell(40, outer=2.0), tolerance=1e-9, **SMALL)
    rng = np.random.default_rng(18)
    values = torch.from_numpy(rng.normal(size=(controls.shape[0], 3))).requires_grad_()
    grads = torch.from_numpy(rng.normal(size=(40, 3)))
    moved = module(values)
    (transposed,) = torch.autograd.grad(moved, values, grads)
    forward = float((grads * moved.detach()).sum())
    backward = float((transposed * values.detach()).sum())
    assert abs(forward - backward) < 1e-7 * abs(forward)
    assert module.last_iterations_ < DEFAULT_ITERATIONS


def test_a_tolerance_is_part_of_the_state():
    controls, targets = body_and_walls(), shell(30)
    state = PartitionRBF(controls, targets, tolerance=1e-6, **SMALL).state_dict()
    with pytest.raises(ValueError, match="^tolerance: the state was saved with tolerance="):
        PartitionRBF(controls, targets, **SMALL).load_state_dict(state)
    loaded = PartitionRBF(sphere(60), shell(4), tolerance=1e-6, **SMALL)
    loaded.load_state_dict(state)
    assert torch.equal(loaded.patch_owner, PartitionRBF(controls, targets, **SMALL).patch_owner)
    values = smooth_field(controls)
    original = PartitionRBF(controls, targets, tolerance=1e-6, **SMALL)
    torch.testing.assert_close(loaded(values), original(values), rtol=0, atol=0)
