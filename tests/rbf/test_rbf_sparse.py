"""The sparse RBF (:class:`torchmorph.rbf.SparseRBF`): the dense global fit of the same
Wendland kernel as its reference, exact at the controls, affine motions reproduced, the
neighbour search against brute force, compact support, batches, gradients, float32,
saved state and argument checks."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from torchmorph.rbf import RBF, PartitionRBF, SparseRBF, build_rbf
from torchmorph.rbf import solvers as solvers_module
from torchmorph.rbf.kernels import WENDLAND
from torchmorph.rbf.sparse import _Pairs, mean_neighbours

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64


def cloud(count: int, dim: int = 3, seed: int = 0, spread: float = 1.0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(count, dim, generator=generator, dtype=F64) * spread


def field(points: torch.Tensor) -> torch.Tensor:
    """A smooth displacement field with a different pattern per axis."""
    x = points
    columns = [torch.sin(2 * x[:, 0]) * x[:, -1], torch.cos(x[:, 1]) + x[:, 0] ** 2]
    if points.shape[1] == 3:
        columns.append(x[:, 2] * x[:, 1])
    return torch.stack(columns, dim=1)


def saved(module: torch.nn.Module) -> dict:
    buffer = io.BytesIO()
    torch.save(module.state_dict(), buffer)
    buffer.seek(0)
    return torch.load(buffer)


@pytest.mark.parametrize("kernel", WENDLAND)
@pytest.mark.parametrize("degree", [-1, 0, 1])
@pytest.mark.parametrize("dim", [2, 3])
def test_equals_the_dense_global_fit(kernel, degree, dim):
    controls, targets = cloud(300, dim), cloud(400, dim, seed=1, spread=1.4) - 0.2
    values = field(controls)
    sparse = SparseRBF(controls, targets, kernel=kernel, support_radius=0.45, degree=degree)
    dense = RBF(controls, targets, kernel=kernel, support_radius=0.45, degree=degree)
    expected = dense(values)
    error = (sparse(values) - expected).norm() / expected.norm()
    assert error < 1e-12
    assert sparse.kernel_columns.shape[0] < 0.5 * 300**2  # the matrix is sparse


def test_the_pairs_are_those_of_brute_force():
    points = cloud(500, seed=3).numpy()
    queries = np.concatenate([cloud(300, seed=4, spread=1.6).numpy() - 0.3, points[:20]])
    radius = 0.17
    indptr, columns, values = _Pairs(points, radius).rows(queries, 2)
    distance = np.linalg.norm(queries[:, None] - points[None], axis=2)
    for row in range(queries.shape[0]):
        found = columns[indptr[row] : indptr[row + 1]]
        assert sorted(found.tolist()) == np.flatnonzero(distance[row] < radius).tolist()
        scaled = distance[row, found] / radius
        expected = (1 - scaled) ** 4 * (4 * scaled + 1)
        np.testing.assert_allclose(
            values[indptr[row] : indptr[row + 1]], expected, rtol=0, atol=1e-15
        )


def test_exact_at_the_controls_and_affine_motions_reproduced():
    controls = cloud(400)
    targets = torch.cat([controls[::7], cloud(200, seed=5)])
    values = field(controls)
    module = SparseRBF(controls, targets, support_radius=0.3)
    torch.testing.assert_close(module(values)[:58], values[::7], rtol=0, atol=1e-12)
    matrix = torch.tensor([[0.1, -0.3, 0.2], [0.05, 0.0, -0.1], [0.3, 0.2, 0.1]], dtype=F64)
    shift = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    torch.testing.assert_close(
        module(controls @ matrix.T + shift), targets @ matrix.T + shift, rtol=0, atol=1e-12
    )


def test_a_target_beyond_the_support_moves_by_the_tail_only():
    controls = cloud(200)
    far = torch.tensor([[5.0, 5.0, 5.0], [-4.0, 0.5, 0.5]], dtype=F64)
    plain = SparseRBF(controls, far, support_radius=0.3, degree=-1)
    assert plain.eval_columns.shape[0] == 0
    assert torch.equal(plain(field(controls)), torch.zeros(2, 3, dtype=F64))
    shift = torch.tensor([0.1, 0.2, -0.3], dtype=F64)
    tail = SparseRBF(controls, far, support_radius=0.3, degree=0)
    torch.testing.assert_close(tail(shift.expand(200, 3)), shift.expand(2, 3), rtol=0, atol=1e-13)


def test_a_batch_equals_the_loop_and_float32_runs():
    controls, targets = cloud(200), cloud(100, seed=2)
    module = SparseRBF(controls, targets, support_radius=0.4)
    batch = torch.stack([field(controls), field(controls).flip(1), -field(controls)])
    looped = torch.stack([module(one) for one in batch])
    torch.testing.assert_close(module(batch), looped, rtol=0, atol=1e-14)
    empty = SparseRBF(controls, targets[:0], support_radius=0.4)
    assert empty(batch).shape == (3, 0, 3)
    single = SparseRBF(controls.float(), targets.float(), support_radius=0.4)
    out = single(field(controls).float())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), looped[0], rtol=0, atol=1e-5)
    cast = SparseRBF(controls, targets, support_radius=0.4).float()
    assert cast.controls.dtype == torch.float32 and cast.kernel_values.dtype == F64
    torch.testing.assert_close(cast(field(controls).float()), out, rtol=0, atol=1e-6)


@pytest.mark.parametrize("degree", [-1, 1])
def test_gradcheck_in_the_displacements(degree):
    controls, targets = cloud(40), cloud(30, seed=6)
    module = SparseRBF(controls, targets, support_radius=0.5, degree=degree)
    values = field(controls).requires_grad_()
    assert torch.autograd.gradcheck(module, (values,))
    batch = torch.randn(2, 40, 3, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(module, (batch,))


def test_state_dict_round_trip_and_a_refactorisation():
    controls, targets = cloud(150), cloud(80, seed=7)
    original = SparseRBF(controls, targets, support_radius=0.35)
    loaded = SparseRBF(cloud(40, seed=8), cloud(5, seed=9), support_radius=0.35)  # other points
    loaded.load_state_dict(saved(original))
    values = field(controls)
    torch.testing.assert_close(loaded(values), original(values), rtol=0, atol=1e-14)


@pytest.mark.parametrize(
    ("field_name", "options"),
    [
        ("support_radius", {"support_radius": 0.4}),
        ("kernel", {"kernel": "wendland_c4"}),
        ("degree", {"degree": 0}),
    ],
)
def test_a_mismatched_hyperparameter_is_refused(field_name, options):
    state = SparseRBF(cloud(50), cloud(5), support_radius=0.35).state_dict()
    other = SparseRBF(cloud(50), cloud(5), **{"support_radius": 0.35, **options})
    with pytest.raises(ValueError, match=f"^{field_name}: the state was saved with"):
        other.load_state_dict(state)


def test_a_corrupted_state_is_refused():
    state = SparseRBF(cloud(50), cloud(5), support_radius=0.35).state_dict()
    state["kernel_columns"] = state["kernel_columns"] + 50
    with pytest.raises(RuntimeError, match="kernel_columns: indices beyond the stored controls"):
        SparseRBF(cloud(50), cloud(5), support_radius=0.35).load_state_dict(state)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"kernel": "thin_plate_spline"}, "^kernel must be one of 'wendland_c0'"),
        ({"support_radius": None}, "^support_radius must be given"),
        ({"support_radius": 0.0}, "^support_radius must be a finite number > 0"),
        ({"support_radius": float("nan")}, "^support_radius must be a finite number > 0"),
        ({"support_radius": 1e-21}, r"^support_radius: 1e-21 is too small"),
        ({"degree": 2.0}, "^degree must be an integer >= -1"),
    ],
)
def test_bad_arguments_are_named(options, message):
    with pytest.raises(ValueError, match=message):
        SparseRBF(cloud(50), cloud(5), **{"support_radius": 0.3, **options})


def test_bad_points_and_displacements_are_named():
    controls = cloud(50)
    with pytest.raises(ValueError, match="^controls: points 0 and 50 coincide"):
        SparseRBF(torch.cat([controls, controls[:1]]), cloud(5), support_radius=0.3)
    with pytest.raises(ValueError, match="^controls requires grad"):
        SparseRBF(controls.clone().requires_grad_(), cloud(5), support_radius=0.3)
    bad = cloud(5)
    bad[2, 1] = float("inf")
    with pytest.raises(ValueError, match="^targets"):
        SparseRBF(controls, bad, support_radius=0.3)
    plane = controls.clone()
    plane[:, 2] = 0.0
    with pytest.raises(ValueError, match="^controls: the monomials of degree=1"):
        SparseRBF(plane, cloud(5), support_radius=0.3)
    module = SparseRBF(controls, cloud(5), support_radius=0.3)
    with pytest.raises(ValueError, match="^displacements must have shape"):
        module(torch.zeros(49, 3, dtype=F64))


def test_build_rbf_picks_the_sparse_fit_for_a_wendland_kernel(monkeypatch):
    controls, targets = cloud(60), cloud(5)
    options = {"kernel": "wendland_c2", "support_radius": 0.5}
    assert type(build_rbf(controls, targets, **options)) is RBF
    assert type(build_rbf(controls, targets, solver="sparse", **options)) is SparseRBF
    monkeypatch.setattr(solvers_module, "PARTITION_CONTROLS", 50)
    assert type(build_rbf(controls, targets, **options)) is SparseRBF
    assert mean_neighbours(controls, 0.5) == pytest.approx(
        float((torch.cdist(controls, controls) < 0.5).sum()) / 60
    )
    # a support holding more controls than SPARSE_NEIGHBOURS on average: the partition
    monkeypatch.setattr(solvers_module, "SPARSE_NEIGHBOURS", 10)
    assert mean_neighbours(controls, 0.5) > 10
    chosen = build_rbf(controls, targets, patch_size=20, coarse_size=30, **options)
    assert type(chosen) is PartitionRBF
    with pytest.raises(ValueError, match="^kernel must be one of 'wendland_c0'"):
        build_rbf(controls, targets, solver="sparse", kernel="thin_plate_spline")
