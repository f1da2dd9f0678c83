"""MeshMorph(method="rbf"): the interior moved by radial basis functions from the selected
controls, checked against scipy's RBFInterpolator and a plain NumPy solve of the system."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.interpolate import RBFInterpolator
from torch.autograd import gradcheck

from torchmorph import MeshMorph, box_mesh
from torchmorph.large_motions import morph_in_steps
from torchmorph.mesh import Mesh
from torchmorph.selection import AdaptivePlan, SelectionPlan

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
FACES = ("x0", "x1", "y0", "y1", "z0", "z1")
MODES = ("dense", "matrix_free")


def smooth_field(points: torch.Tensor) -> torch.Tensor:
    """A smooth, non-polynomial displacement of every point (n, 3)."""
    x, y, z = points.unbind(-1)
    return 0.05 * torch.stack([torch.sin(3 * y) * z, torch.cos(2 * x) * y, x * y * z], -1)


def selected_morph(mesh, **options) -> MeshMorph:
    """An RBF morph on an SIDW selection (fewer controls than boundary nodes)."""
    plan = SelectionPlan(dict.fromkeys(FACES, 0.45))
    morph = MeshMorph(mesh, plan, generator=torch.Generator().manual_seed(0), **options)
    assert 0 < morph.num_controls < morph.num_boundary
    return morph


def numpy_rbf(controls, values, targets, phi):
    """The interpolant with a linear tail solved from its block system in NumPy:
    [[Φ, P], [Pᵀ, 0]] [λ; β] = [d; 0], then s(x) = Φ(x) λ + p(x) β."""
    distances = np.linalg.norm(controls[:, None] - controls[None], axis=-1)
    poly = np.hstack([np.ones((len(controls), 1)), controls])
    count = poly.shape[1]
    system = np.block([[phi(distances), poly], [poly.T, np.zeros((count, count))]])
    rhs = np.vstack([values, np.zeros((count, values.shape[1]))])
    solution = np.linalg.solve(system, rhs)
    at_targets = np.linalg.norm(targets[:, None] - controls[None], axis=-1)
    target_poly = np.hstack([np.ones((len(targets), 1)), targets])
    return phi(at_targets) @ solution[: len(controls)] + target_poly @ solution[len(controls) :]


@pytest.fixture(scope="module")
def mesh():
    return box_mesh(4)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize(
    ("kernel", "epsilon"),
    [("thin_plate_spline", None), ("cubic", None), ("gaussian", 2.0), ("multiquadric", 1.5)],
)
def test_interior_equals_scipy_on_the_selected_controls(mesh, mode, kernel, epsilon):
    morph = selected_morph(mesh, method="rbf", kernel=kernel, epsilon=epsilon, mode=mode)
    boundary = smooth_field(morph.boundary_points)
    field = morph(boundary)
    assert torch.equal(field[morph.boundary_nodes], boundary)
    reference = RBFInterpolator(
        morph.points[morph.control_nodes].numpy(),
        boundary[morph.selected].numpy(),
        kernel=kernel,
        epsilon=1.0 if epsilon is None else epsilon,
        degree=1,
    )(morph.points[morph.interior_nodes].numpy())
    np.testing.assert_allclose(field[morph.interior_nodes].numpy(), reference, rtol=0, atol=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_wendland_interior_equals_a_numpy_solve(mesh, mode):
    radius = 1.2
    morph = selected_morph(
        mesh, method="rbf", kernel="wendland_c2", support_radius=radius, mode=mode
    )
    boundary = smooth_field(morph.boundary_points)

    def wendland_c2(r):
        r = r / radius
        return np.clip(1 - r, 0, None) ** 4 * (4 * r + 1)

    reference = numpy_rbf(
        morph.points[morph.control_nodes].numpy(),
        boundary[morph.selected].numpy(),
        morph.points[morph.interior_nodes].numpy(),
        wendland_c2,
    )
    field = morph(boundary)
    np.testing.assert_allclose(field[morph.interior_nodes].numpy(), reference, rtol=0, atol=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_exact_at_the_controls(mesh, mode):
    # interior nodes moved onto control points: the interpolant there is the control's value
    morph = selected_morph(mesh, method="rbf", mode=mode)
    boundary = smooth_field(morph.boundary_points)
    count = min(morph.num_interior, morph.num_controls)
    points = morph.points.clone()
    points[morph.interior_nodes[:count]] = morph.points[morph.control_nodes[:count]]
    field = morph(boundary, points=points)
    torch.testing.assert_close(
        field[morph.interior_nodes[:count]],
        boundary[morph.selected[:count]],
        rtol=0,
        atol=1e-12,
    )


@pytest.mark.parametrize("mode", MODES)
def test_affine_motions_are_reproduced_on_any_selection(mesh, mode):
    morph = selected_morph(mesh, method="rbf", mode=mode)
    matrix = torch.tensor([[0.1, -0.2, 0.05], [0.3, 0.0, -0.1], [0.02, 0.1, 0.2]], dtype=F64)
    shift = torch.tensor([0.5, -0.25, 1.0], dtype=F64)
    field = morph(morph.boundary_points @ matrix.T + shift)
    torch.testing.assert_close(field, morph.points @ matrix.T + shift, rtol=0, atol=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_batch_equals_the_loop(mesh, mode):
    morph = selected_morph(mesh, method="rbf", mode=mode)
    amplitudes = torch.tensor([0.5, -1.0, 2.0], dtype=F64)
    batch = amplitudes[:, None, None] * smooth_field(morph.boundary_points)
    batch[1] += torch.linspace(0, 1, morph.num_boundary, dtype=F64)[:, None]
    together = morph(batch)
    assert together.shape == (3, morph.num_nodes, 3)
    for member, field in zip(batch, together, strict=True):
        torch.testing.assert_close(field, morph(member), rtol=0, atol=1e-14)


@pytest.mark.parametrize("mode", MODES)
def test_gradcheck_in_the_displacement_and_the_points(mode):
    morph = MeshMorph(box_mesh((3, 2, 2)), method="rbf", mode=mode)
    boundary = smooth_field(morph.boundary_points).requires_grad_()
    points = morph.points.clone().requires_grad_()
    assert gradcheck(lambda d: morph(d), (boundary,))
    assert gradcheck(lambda p: morph(boundary.detach(), points=p), (points,))


def test_weights_matrix_and_adjoint_are_those_of_the_morph(mesh):
    morph = selected_morph(mesh, method="rbf")
    boundary = smooth_field(morph.boundary_points)
    field = morph(boundary)
    weights = morph.weights_matrix()
    assert weights.shape == (morph.num_interior, morph.num_controls)
    torch.testing.assert_close(
        weights @ boundary[morph.weight_columns], field[morph.interior_nodes], rtol=0, atol=1e-13
    )
    # affine reproduction: the rows of W sum to one
    torch.testing.assert_close(weights.sum(1), torch.ones(morph.num_interior, dtype=F64))
    fields = torch.randn(
        2, morph.num_nodes, 3, generator=torch.Generator().manual_seed(1), dtype=F64
    )
    lhs = (morph(torch.stack([boundary, 2 * boundary])) * fields).sum()
    rhs = (torch.stack([boundary, 2 * boundary]) * morph.adjoint(fields)).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=0)


def test_an_adaptive_plan_selects_for_either_method(mesh):
    displacement = MeshMorph(mesh).boundary_displacement("z1", smooth_field)
    plan = AdaptivePlan(0.05, displacement, method="idw")  # IDW's error for either
    idw = MeshMorph(mesh, plan)
    rbf = MeshMorph(mesh, plan, method="rbf")
    assert torch.equal(idw.control_nodes, rbf.control_nodes)
    assert rbf.num_controls < rbf.num_boundary
    reference = RBFInterpolator(
        rbf.points[rbf.control_nodes].numpy(), displacement[rbf.selected].numpy(), degree=1
    )(rbf.points[rbf.interior_nodes].numpy())
    np.testing.assert_allclose(
        rbf(displacement)[rbf.interior_nodes].numpy(), reference, rtol=0, atol=1e-12
    )
    # without a method of its own the plan follows the morph: the RBF's error
    following = AdaptivePlan(0.05, displacement)
    MeshMorph(mesh, following, method="rbf")
    assert following.method_ == "rbf" and following.result_.error <= 0.05


def test_a_planar_mesh():
    axis = np.linspace(0.0, 1.0, 5)
    x, y = np.meshgrid(axis, axis, indexing="ij")
    points = np.stack([x.ravel(), y.ravel()], 1)
    index = np.arange(25).reshape(5, 5)
    quads = np.stack([index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]], -1)
    mesh = Mesh(points, [("quad", quads.reshape(-1, 4))])
    morph = MeshMorph(mesh, method="rbf", kernel="quintic", degree=2)
    boundary = 0.1 * torch.sin(3 * morph.boundary_points.flip(1))
    reference = RBFInterpolator(
        morph.boundary_points.numpy(), boundary.numpy(), kernel="quintic", degree=2
    )(morph.points[morph.interior_nodes].numpy())
    np.testing.assert_allclose(
        morph(boundary)[morph.interior_nodes].numpy(), reference, rtol=0, atol=1e-12
    )


def test_steps_rebuild_the_rbf_from_each_mesh(mesh):
    morph = MeshMorph(mesh, method="rbf")
    boundary = morph.boundary_displacement("z1", smooth_field)
    one = morph_in_steps(morph, boundary, 1)
    torch.testing.assert_close(one.displacement, morph(boundary), rtol=0, atol=1e-13)
    two = morph_in_steps(morph, boundary, 2)
    assert torch.equal(two.displacement[morph.boundary_nodes], boundary)
    assert two.first_inverted is None
    half = morph(0.5 * boundary)
    moved = morph.points + half
    second = morph(0.5 * boundary, points=moved)  # the second half from the moved mesh
    torch.testing.assert_close(two.displacement, half + second, rtol=0, atol=1e-13)


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"method": "spline"}, "method must be one of 'idw', 'rbf'; got 'spline'"),
        ({"method": "rbf", "power": 2.0}, r"power: an option of method='idw', not of method='rbf'"),
        ({"method": "rbf", "implementation": "torch"}, "implementation: an option of method='idw'"),
        ({"method": "rbf", "coincidence_tolerance": 1e-9}, "coincidence_tolerance: an option of"),
        ({"kernel": "cubic"}, r"kernel: an option of method='rbf', not of method='idw'"),
        ({"epsilon": 1.0}, "epsilon: an option of method='rbf'"),
        ({"degree": 0}, "degree: an option of method='rbf'"),
        ({"support_radius": 0.5}, "support_radius: an option of method='rbf'"),
        ({"method": "rbf", "mode": "tree"}, "mode: 'tree' is IDW's; method='rbf' takes"),
        ({"method": "rbf", "mode": "sparse"}, "mode must be one of 'auto', 'dense', 'matrix_f"),
        ({"method": "rbf", "kernel": "gaussian"}, "epsilon"),
        ({"method": "rbf", "kernel": "thin_plate_spline", "support_radius": 1.0}, "support_radius"),
    ],
)
def test_options_of_the_other_method_are_errors(options, message):
    with pytest.raises(ValueError, match=message):
        MeshMorph(box_mesh(2), **options)


def test_rotations_are_idw_only(mesh):
    morph = MeshMorph(mesh, method="rbf")
    boundary = morph.boundary_displacement("z1", smooth_field)
    message = r"rotations: the rotation-aware morph blends IDW weights \(method='idw'\)"
    with pytest.raises(ValueError, match=message):
        morph(boundary, rotations="fit")
    with pytest.raises(ValueError, match=message):
        morph_in_steps(morph, boundary, 2, rotations="fit")
    with pytest.raises(ValueError, match="reach: only a rotation-aware morph"):
        morph(boundary, reach=1.0)


def test_torch_func_of_the_displacement_is_refused_and_of_the_points_works():
    morph = MeshMorph(box_mesh(2), method="rbf")
    boundary = smooth_field(morph.boundary_points)
    scale = torch.tensor(1.0, dtype=F64)
    message = "boundary_displacement: torch.func transforms .* are not supported"
    with pytest.raises(ValueError, match=message):
        torch.func.jacrev(lambda a: morph(a * boundary))(scale)
    with pytest.raises(ValueError, match=message):
        torch.func.vmap(lambda a: morph(a * boundary))(scale.repeat(2))
    with pytest.raises(ValueError, match="points: vmap over the points"):
        torch.func.vmap(lambda a: morph(boundary, points=morph.points * a))(scale.repeat(2))
    # reverse mode in the points re-solves the system in torch: as torch.autograd does
    grow = lambda a: morph(boundary, points=morph.points * a)  # noqa: E731
    expected = torch.autograd.functional.jacobian(grow, scale)
    torch.testing.assert_close(torch.func.jacrev(grow)(scale), expected, rtol=1e-12, atol=1e-14)


# ----------------------------------------------------------------------------- state


def test_state_round_trip_into_another_selection(mesh):
    morph = selected_morph(mesh, method="rbf", kernel="wendland_c2", support_radius=1.5)
    copy = MeshMorph(mesh, method="rbf", kernel="wendland_c2", support_radius=1.5)
    assert copy.num_controls != morph.num_controls
    copy.load_state_dict(morph.state_dict())
    assert copy.method == "rbf" and torch.equal(copy.control_nodes, morph.control_nodes)
    boundary = smooth_field(morph.boundary_points)
    torch.testing.assert_close(copy(boundary), morph(boundary), rtol=0, atol=0)
    extra = morph.state_dict()["_extra_state"]
    assert extra["method"] == "rbf" and extra["version"] == 3
    assert morph.state_dict()["rbf._extra_state"]["kernel"] == "wendland_c2"


def test_a_dense_state_loads_into_a_matrix_free_morph(mesh):
    dense = MeshMorph(mesh, method="rbf", mode="dense")
    matrix_free = MeshMorph(mesh, method="rbf", mode="matrix_free")
    matrix_free.load_state_dict(dense.state_dict())
    boundary = smooth_field(dense.boundary_points)
    torch.testing.assert_close(matrix_free(boundary), dense(boundary), rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    ("saved", "loading", "message"),
    [
        ({}, {"method": "rbf"}, "method: the state was saved with method='idw'"),
        ({"method": "rbf"}, {}, "method: the state was saved with method='rbf'"),
        ({"method": "rbf"}, {"method": "rbf", "kernel": "cubic"}, "kernel: the state was saved"),
        ({"method": "rbf"}, {"method": "rbf", "degree": 2}, "degree: the state was saved"),
        (
            {"method": "rbf", "kernel": "gaussian", "epsilon": 2.0},
            {"method": "rbf", "kernel": "gaussian", "epsilon": 3.0},
            "epsilon: the state was saved with epsilon=2.0",
        ),
    ],
)
def test_a_state_of_another_method_or_hyperparameters_is_refused_untouched(saved, loading, message):
    mesh = box_mesh(2)
    source = MeshMorph(mesh, SelectionPlan(dict.fromkeys(FACES, 0.6)), **saved)
    target = MeshMorph(mesh, **loading)
    before = {
        key: value.clone() for key, value in target.state_dict().items() if key[-6:] != "_state"
    }
    with pytest.raises(ValueError, match=message):
        target.load_state_dict(source.state_dict())
    for key, value in target.state_dict().items():
        if key in before:
            assert torch.equal(value, before[key]), key


def test_a_state_without_a_known_method_is_refused():
    morph = MeshMorph(box_mesh(2), method="rbf")
    state = morph.state_dict()
    state["_extra_state"] = {**state["_extra_state"], "method": "kriging"}
    with pytest.raises(ValueError, match="method 'kriging' is not 'idw' or 'rbf'"):
        morph.load_state_dict(state)


def test_a_state_of_version_2_loads_as_idw():
    mesh = box_mesh(2)
    morph = MeshMorph(mesh, SelectionPlan(dict.fromkeys(FACES, 0.6)))
    state = morph.state_dict()
    extra = {k: v for k, v in state["_extra_state"].items() if k != "method"}
    state["_extra_state"] = {**extra, "version": 2}  # as saved before the method existed
    copy = MeshMorph(mesh)
    copy.load_state_dict(state)
    boundary = smooth_field(morph.boundary_points)
    assert copy.method == "idw"
    torch.testing.assert_close(copy(boundary), morph(boundary), rtol=0, atol=0)
    with pytest.raises(ValueError, match="method: the state was saved with method='idw'"):
        MeshMorph(mesh, method="rbf").load_state_dict(state)


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_to_float32_keeps_the_factorisation_in_float64(mode):
    mesh = box_mesh(4)
    morph = MeshMorph(mesh, method="rbf", mode=mode)
    generator = torch.Generator().manual_seed(2)
    d = 0.05 * torch.randn(morph.num_boundary, 3, generator=generator, dtype=torch.float64)
    reference = morph(d)
    single = morph.to(torch.float32)
    assert single.rbf.factor.dtype == torch.float64
    assert single.rbf.shift.dtype == torch.float64
    assert single.rbf.controls.dtype == torch.float32
    out = single(d.float())
    assert out.dtype == torch.float32
    assert float((out.double() - reference).abs().max()) <= 1e-5 * float(d.abs().max())


@pytest.mark.parametrize(
    ("solver", "options", "name", "bound"),
    [
        ("partition", {}, "partition-of-unity", 2e-2),
        ("sparse", {"kernel": "wendland_c2", "support_radius": 0.6}, "sparse", 1e-12),
    ],
)
def test_the_partition_and_sparse_solvers(monkeypatch, solver, options, name, bound):
    """Against the dense fit with the same kernel (the partition approximates it, the
    sparse fit is it), exact at the boundary, POD, the adjoint, the state, the refusals."""
    from torchmorph import PODReducer
    from torchmorph.rbf import PartitionRBF, SparseRBF, partition

    monkeypatch.setattr(partition, "DEFAULT_COARSE_SIZE", 60)
    monkeypatch.setattr(partition, "DEFAULT_PATCH_SIZE", 24)
    mesh = box_mesh(6)
    morph = MeshMorph(mesh, method="rbf", solver=solver, **options)
    if solver == "partition":
        assert isinstance(morph.rbf, PartitionRBF) and morph.rbf.num_patches > 1
    else:
        assert isinstance(morph.rbf, SparseRBF)
    points = mesh.points[morph.boundary_nodes]
    d = 0.05 * torch.stack(
        [torch.sin(3 * points[:, 1]), points[:, 0] * points[:, 2], 0 * points[:, 0]], 1
    )
    dense = MeshMorph(mesh, method="rbf", **options)(d)
    out = morph(d)
    assert torch.equal(out[morph.boundary_nodes], d)
    assert float((out - dense).norm() / dense.norm()) < bound
    family = torch.stack([d, d.flip(0), 0.5 * d + 0.01])
    reducer = PODReducer(num_modes=3).fit(morph, family)
    assert torch.allclose(reducer(family), morph(family), atol=1e-12, rtol=0)
    g = torch.randn(1, mesh.num_nodes, 3, dtype=d.dtype, generator=torch.Generator().manual_seed(1))
    left = float((morph(d[None]) * g).sum())
    right = float((d[None] * morph.adjoint(g)).sum())
    assert left == pytest.approx(right, rel=1e-12)
    twin = MeshMorph(mesh, method="rbf", solver=solver, **options)
    twin.load_state_dict(morph.state_dict())
    assert torch.equal(twin(d), out)
    with pytest.raises(ValueError, match=f"solver: the state was saved with the {solver}"):
        MeshMorph(mesh, method="rbf", **options).load_state_dict(morph.state_dict())
    with pytest.raises(ValueError, match=f"points: the {name} RBF"):
        morph(d, points=mesh.points)
    with pytest.raises(ValueError, match=f"mode: solver='{solver}'"):
        MeshMorph(mesh, method="rbf", solver=solver, mode="dense", **options)
    with pytest.raises(ValueError, match="solver: an option of method='rbf'"):
        MeshMorph(mesh, solver=solver)


def test_the_partition_fits_the_global_interpolant_to_a_tolerance(monkeypatch):
    """fit_tolerance: the partition's global fit, against the dense fit (the partition
    alone is 1e-2 from it here), through POD, the adjoint and the state."""
    from torchmorph import PODReducer
    from torchmorph.rbf import partition

    monkeypatch.setattr(partition, "DEFAULT_COARSE_SIZE", 60)
    monkeypatch.setattr(partition, "DEFAULT_PATCH_SIZE", 24)
    mesh = box_mesh(6)
    morph = MeshMorph(mesh, method="rbf", solver="partition", fit_tolerance=1e-10)
    assert morph.rbf.tolerance == 1e-10 and morph.rbf.num_patches > 1
    points = mesh.points[morph.boundary_nodes]
    d = 0.05 * torch.stack(
        [torch.sin(3 * points[:, 1]), points[:, 0] * points[:, 2], 0 * points[:, 0]], 1
    )
    dense = MeshMorph(mesh, method="rbf")(d)
    alone = MeshMorph(mesh, method="rbf", solver="partition")(d)
    out = morph(d)
    assert float((alone - dense).norm() / dense.norm()) > 1e-4
    assert float((out - dense).norm() / dense.norm()) < 1e-8
    assert torch.equal(out[morph.boundary_nodes], d)
    family = torch.stack([d, d.flip(0), 0.5 * d + 0.01])
    reducer = PODReducer(num_modes=3).fit(morph, family)
    torch.testing.assert_close(reducer(family), morph(family), rtol=0, atol=1e-9)
    g = torch.randn(1, mesh.num_nodes, 3, dtype=d.dtype, generator=torch.Generator().manual_seed(2))
    left = float((morph(d[None]) * g).sum())
    assert left == pytest.approx(float((d[None] * morph.adjoint(g)).sum()), rel=1e-8)
    twin = MeshMorph(mesh, method="rbf", solver="partition", fit_tolerance=1e-10)
    twin.load_state_dict(morph.state_dict())
    assert torch.equal(twin(d), out)
    with pytest.raises(ValueError, match="^tolerance: the state was saved with tolerance=1e-10"):
        MeshMorph(mesh, method="rbf", solver="partition").load_state_dict(morph.state_dict())


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"method": "rbf", "fit_tolerance": 1e-4}, (r"^fit_tolerance: the partition of unity's"
         r" global fit \(solver='partition' or 'auto'\); solver='dense' is the global fit")),
        ({"method": "rbf", "solver": "partition", "fit_tolerance": 0.0},
         "^fit_tolerance must be"),
        ({"fit_tolerance": 1e-4}, "^fit_tolerance: an option of method='rbf'"),
    ],
)  # fmt: skip
def test_fit_tolerance_refusals(options, message):
    with pytest.raises(ValueError, match=message):
        MeshMorph(box_mesh(3), **options)


def test_the_sparse_solver_needs_a_wendland_kernel():
    with pytest.raises(ValueError, match="^kernel must be one of 'wendland_c0'"):
        MeshMorph(box_mesh(3), method="rbf", solver="sparse")


def test_a_state_saved_before_the_sparse_fit_still_loads():
    mesh = box_mesh(4)
    morph = MeshMorph(mesh, method="rbf")
    state = morph.state_dict()
    extra = dict(state["_extra_state"])
    del extra["solver"]
    state["_extra_state"] = {**extra, "partition": False}
    twin = MeshMorph(mesh, method="rbf")
    twin.load_state_dict(state)
    state["_extra_state"] = {**extra, "partition": True}
    with pytest.raises(ValueError, match="solver: the state was saved with the partition"):
        twin.load_state_dict(state)
