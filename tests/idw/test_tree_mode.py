"""``IDW(mode="tree")``: the tree of :mod:`torchmorph.idw.tree` as a mode of the module,
against the exact modes."""

from __future__ import annotations

import pytest
import torch

from torchmorph import MeshMorph, box_mesh
from torchmorph.idw import IDW
from torchmorph.idw._tree_mode import TreeOperator
from torchmorph.idw.backends.numba.kernels import available
from torchmorph.idw.functional import DEFAULT_COINCIDENCE_TOLERANCE
from torchmorph.idw.tree import DEFAULT_TOLERANCE, TreeIDW

pytestmark = pytest.mark.skipif(not available(), reason="the tree kernels need numba")


def sphere(count, generator):
    points = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    return points / points.norm(dim=1, keepdim=True)


def surface_cloud(seed=3, controls=300, targets=900):
    """Controls on the unit sphere, targets filling the ball."""
    generator = torch.Generator().manual_seed(seed)
    surface = sphere(controls, generator)
    radius = torch.rand(targets, 1, generator=generator, dtype=torch.float64) * 0.97
    return surface, sphere(targets, generator) * radius


def field(controls):
    x, y, z = controls.unbind(-1)
    return torch.stack([x * x - 0.3, torch.sin(3 * y), z * x + 0.2], -1)


def relative_error(result, exact):
    return float((result.double() - exact).norm() / exact.norm())


@pytest.mark.parametrize("tolerance", [1e-2, 1e-4])
def test_tree_mode_is_within_tolerance_of_matrix_free(tolerance):
    controls, targets = surface_cloud()
    displacements = field(controls)
    exact = IDW(controls, targets, mode="matrix_free")(displacements)
    tree = IDW(controls, targets, mode="tree", tolerance=tolerance)
    assert tree.mode == "tree" and tree.tolerance == tolerance
    assert relative_error(tree(displacements), exact) <= tolerance


def test_tree_mode_default_tolerance_on_a_volume_cloud():
    generator = torch.Generator().manual_seed(5)
    controls = torch.rand(300, 3, generator=generator, dtype=torch.float64)
    targets = torch.rand(800, 3, generator=generator, dtype=torch.float64)
    displacements = field(controls)
    exact = IDW(controls, targets, mode="matrix_free")(displacements)
    tree = IDW(controls, targets, mode="tree")
    assert tree.tolerance == DEFAULT_TOLERANCE
    assert relative_error(tree(displacements), exact) <= DEFAULT_TOLERANCE


def test_tree_mode_equals_tree_idw_and_batches_like_single_calls():
    controls, targets = surface_cloud()
    generator = torch.Generator().manual_seed(1)
    batch = torch.randn(3, controls.shape[0], 3, generator=generator, dtype=torch.float64)
    module = IDW(controls, targets, mode="tree")
    batched = module(batch)
    assert batched.shape == (3, targets.shape[0], 3)
    exact = IDW(controls, targets, mode="matrix_free")(batch)
    for field_index in range(3):
        single = module(batch[field_index])
        assert relative_error(single, exact[field_index]) <= DEFAULT_TOLERANCE
        assert relative_error(batched[field_index], exact[field_index]) <= DEFAULT_TOLERANCE
    reference = TreeIDW(controls, targets)(batch[0])
    assert relative_error(module(batch[0]), reference.double()) <= 2 * DEFAULT_TOLERANCE


def test_tree_mode_float32_in_float32_out():
    controls, targets = surface_cloud()
    module = IDW(controls.float(), targets.float(), mode="tree")
    result = module(field(controls).float())
    assert result.dtype == torch.float32
    exact = IDW(controls, targets, mode="matrix_free")(field(controls))
    assert relative_error(result, exact) <= DEFAULT_TOLERANCE + 1e-6


def test_tree_mode_is_not_picked_by_auto():
    controls, targets = surface_cloud(controls=50, targets=60)
    assert IDW(controls, targets).mode in ("dense", "matrix_free")
    assert IDW(controls, targets).tolerance is None


def test_tree_mode_gradcheck_to_the_displacements():
    """The forward's operator at a fixed η is linear in d and its backward applies that
    operator's transpose: gradcheck at a tolerance tight enough that the finite
    differences see the same acceptance of nodes."""
    controls, targets = surface_cloud(seed=7, controls=40, targets=30)
    module = IDW(controls, targets, mode="tree", tolerance=1e-10)
    displacements = field(controls).requires_grad_()
    assert torch.autograd.gradcheck(module, (displacements,), atol=1e-7, rtol=1e-6)


def test_tree_mode_vector_jacobian_product_is_the_transpose_within_tolerance():
    controls, targets = surface_cloud()
    generator = torch.Generator().manual_seed(2)
    displacements = field(controls).requires_grad_()
    upstream = torch.randn(targets.shape[0], 3, generator=generator, dtype=torch.float64)
    tree = IDW(controls, targets, mode="tree", tolerance=1e-6)
    (gradient,) = torch.autograd.grad(tree(displacements), displacements, upstream)
    weights = IDW(controls, targets, mode="dense").weights_matrix()
    assert torch.isfinite(gradient).all() and gradient.abs().sum() > 0
    assert relative_error(gradient, weights.mT @ upstream) <= 1e-4


def test_tolerance_with_another_mode_is_refused():
    controls, targets = surface_cloud(controls=20, targets=10)
    for mode in ("dense", "matrix_free"):
        match = f"^tolerance: only mode='tree' or 'auto' takes.*mode='{mode}'"
        with pytest.raises(ValueError, match=match):
            IDW(controls, targets, mode=mode, tolerance=1e-3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="^error_control: only mode='tree' takes.*mode='auto'"):
        IDW(controls, targets, error_control="sampled")
    with pytest.raises(ValueError, match="^tolerance must lie in"):
        IDW(controls, targets, tolerance=1.5)


def test_auto_mode_takes_the_tree_where_it_pays():
    """The rule at its measured thresholds (no points needed): p = 4, 3-D, the fused CPU
    kernels, points that do not require grad, from 10^9 pairs at 1e-5 and up, from 10^10
    at 1e-7 and up, never below."""
    from torchmorph.idw.module import auto_mode

    cpu, f32 = torch.device("cpu"), torch.float32

    def mode(targets, controls, tolerance, **options):
        options = {"dtype": f32, "device": cpu, "tolerance": tolerance, **options}
        return auto_mode(targets, controls, **options)

    assert mode(10**5, 10**4, 1e-4) == mode(10**5, 10**4, 1e-5) == "tree"
    assert mode(10**5, 10**4 - 1, 1e-4) == "matrix_free"  # below 10^9 pairs
    assert mode(10**5, 10**4, None) == "matrix_free"  # no tolerance: exact
    assert mode(10**5, 10**4, 1e-6) == "matrix_free"
    assert mode(10**6, 10**4, 1e-6) == mode(10**6, 10**4, 1e-7) == "tree"
    assert mode(10**7, 10**6, 1e-8) == "matrix_free"  # never below 1e-7
    for options in ({"power": 3.0}, {"dim": 2}, {"requires_grad": True}):
        assert mode(10**6, 10**5, 1e-4, **options) == "matrix_free", options
    assert mode(10**6, 10**5, 1e-4, implementation="torch") == "matrix_free"
    on_gpu = {"device": torch.device("cuda"), "dense_bytes": 10**9}  # no CUDA tree
    assert mode(10**6, 10**5, 1e-4, **on_gpu) == "matrix_free"


def test_auto_mode_with_a_tolerance_builds_the_sampled_tree(monkeypatch):
    """Above the (here lowered) threshold ``IDW(c, t, tolerance=...)`` is the sampled tree,
    within the tolerance, whose state loads into an explicit tree module; below it, the
    exact morph, with no tolerance kept."""
    import torchmorph.idw._tree_mode as tree_mode

    controls, targets = surface_cloud()
    displacements = field(controls)
    exact = IDW(controls, targets, mode="matrix_free")(displacements)
    below = IDW(controls, targets, tolerance=1e-3)
    assert below.mode == "matrix_free" and below.tolerance is None
    assert below.error_control is None
    torch.testing.assert_close(below(displacements), exact, rtol=0, atol=0)
    monkeypatch.setattr(tree_mode, "AUTO_TREE_PAIRS", ((1e-5, 300 * 900),))
    auto = IDW(controls, targets, tolerance=1e-3)
    assert (auto.mode, auto.tolerance, auto.error_control) == ("tree", 1e-3, "sampled")
    result = auto(displacements)
    assert 0 < relative_error(result, exact) <= 1e-3
    tree = IDW(controls, targets, mode="tree", tolerance=1e-3, error_control="sampled")
    tree.load_state_dict(auto.state_dict())
    torch.testing.assert_close(tree(displacements), result, rtol=0, atol=0)
    assert IDW(controls.float(), targets.float(), tolerance=1e-3).mode == "tree"
    steep = IDW(controls, targets, tolerance=1e-3, power=3.0)
    assert steep.mode == "matrix_free"
    moving = IDW(controls.clone().requires_grad_(True), targets, tolerance=1e-3)
    assert moving.mode == "matrix_free"


@pytest.mark.parametrize("tolerance", [0.0, 1.0, -1e-3])
def test_tree_mode_bad_tolerance_is_refused(tolerance):
    controls, targets = surface_cloud(controls=20, targets=10)
    with pytest.raises(ValueError, match="^tolerance must lie in"):
        IDW(controls, targets, mode="tree", tolerance=tolerance)


def test_tree_mode_refuses_moved_points_and_geometry_that_requires_grad():
    controls, targets = surface_cloud(controls=20, targets=10)
    module = IDW(controls, targets, mode="tree")
    displacements = field(controls)
    with pytest.raises(ValueError, match="^controls: mode='tree' applies"):
        module(displacements, controls=controls + 0.01)
    with pytest.raises(ValueError, match="^targets: mode='tree' applies"):
        module(displacements, targets=targets)
    with pytest.raises(ValueError, match="^controls requires grad: mode='tree'"):
        IDW(controls.clone().requires_grad_(), targets, mode="tree")
    with pytest.raises(ValueError, match="^targets requires grad: mode='tree'"):
        IDW(controls, targets.clone().requires_grad_(), mode="tree")


def test_tree_mode_has_no_weights_matrix():
    controls, targets = surface_cloud(controls=20, targets=10)
    module = IDW(controls, targets, mode="tree")
    assert module.weights is None
    with pytest.raises(RuntimeError, match="^weights_matrix: mode='tree' stores no W"):
        module.weights_matrix()


def test_tree_mode_off_the_cpu_names_the_device():
    """The check of every tree-mode build and call (meta tensors stand for a GPU: the
    module's own finiteness checks cannot run on them, so the helper is called)."""
    controls, targets = surface_cloud(controls=20, targets=10)
    tree = TreeOperator(4.0, DEFAULT_COINCIDENCE_TOLERANCE, None)
    with pytest.raises(ValueError, match="^controls: mode='tree' runs on the CPU only.*meta"):
        tree.operator(controls.to("meta"), targets.to("meta"))
    with pytest.raises(ValueError, match="^targets: mode='tree' runs on the CPU only.*meta"):
        tree.operator(controls, targets.to("meta"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_tree_module_moved_to_cuda_refuses_to_run_naming_the_device():
    controls, targets = surface_cloud(controls=20, targets=10)
    module = IDW(controls, targets, mode="tree").to("cuda")
    with pytest.raises(ValueError, match="^controls: mode='tree' runs on the CPU only.*cuda"):
        module(field(controls).cuda())


def test_tree_state_round_trip_and_tolerance_check():
    controls, targets = surface_cloud()
    displacements = field(controls)
    saved = IDW(controls, targets, mode="tree", tolerance=1e-3)
    state = saved.state_dict()
    assert state["_extra_state"]["mode"] == "tree"
    assert state["_extra_state"]["tolerance"] == 1e-3
    other_controls, other_targets = surface_cloud(seed=11)
    loaded = IDW(other_controls, other_targets, mode="tree", tolerance=1e-3)
    loaded.load_state_dict(state)  # the trees are rebuilt from the loaded geometry
    exact = IDW(controls, targets, mode="matrix_free")(displacements)
    assert relative_error(loaded(displacements), exact) <= 1e-3
    mismatch = IDW(other_controls, other_targets, mode="tree", tolerance=1e-4)
    with pytest.raises(ValueError, match="^tolerance: the state was saved with tolerance=0.001"):
        mismatch.load_state_dict(state)


@pytest.mark.parametrize("exact_mode", ["dense", "matrix_free"])
def test_tree_and_exact_states_load_into_each_other(exact_mode):
    controls, targets = surface_cloud()
    displacements = field(controls)
    exact = IDW(controls, targets, mode="matrix_free")(displacements)
    other_controls, other_targets = surface_cloud(seed=11)
    tree = IDW(other_controls, other_targets, mode="tree")
    tree.load_state_dict(IDW(controls, targets, mode=exact_mode).state_dict())
    assert relative_error(tree(displacements), exact) <= DEFAULT_TOLERANCE
    assert "tolerance" not in IDW(controls, targets, mode=exact_mode).get_extra_state()
    back = IDW(other_controls, other_targets, mode=exact_mode)
    back.load_state_dict(IDW(controls, targets, mode="tree").state_dict())
    torch.testing.assert_close(back(displacements), exact, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="^power: the state was saved with power=4.0"):
        IDW(controls, targets, mode="tree", power=2.0).load_state_dict(
            IDW(controls, targets, mode=exact_mode).state_dict()
        )


def test_mesh_morph_in_tree_mode_matches_the_exact_morph():
    mesh = box_mesh(6)
    exact = MeshMorph(mesh, mode="matrix_free")
    tree = MeshMorph(mesh, mode="tree")
    assert tree.idw.mode == "tree" and tree.idw.tolerance == DEFAULT_TOLERANCE
    boundary = mesh.points[exact.boundary_nodes]
    x, y, z = boundary.unbind(1)
    displacement = 0.05 * torch.stack([torch.sin(3 * y), x * z, torch.cos(2 * x) - y], 1)
    interior = exact.interior_nodes
    expected = exact(displacement)[interior]
    assert relative_error(tree(displacement)[interior], expected) <= DEFAULT_TOLERANCE


def test_mesh_morph_auto_with_a_tolerance(monkeypatch):
    """MeshMorph passes ``tolerance`` to auto (the tree above the lowered threshold);
    near-wall stiffening has no tree, so with auto it stays exact, and with an exact mode
    the tolerance is refused."""
    import torchmorph.idw._tree_mode as tree_mode

    monkeypatch.setattr(tree_mode, "AUTO_TREE_PAIRS", ((1e-5, 1000),))
    mesh = box_mesh(6)
    morph = MeshMorph(mesh, tolerance=1e-3)
    assert (morph.idw.mode, morph.idw.error_control) == ("tree", "sampled")
    stiff = MeshMorph(mesh, tolerance=1e-3, stiffening_length=0.1)
    exact = MeshMorph(mesh, stiffening_length=0.1)
    boundary = mesh.points[exact.boundary_nodes]
    displacement = 0.05 * torch.sin(3 * boundary)
    torch.testing.assert_close(stiff(displacement), exact(displacement), rtol=0, atol=0)
    with pytest.raises(ValueError, match="^tolerance: the tree's, and near-wall stiffening"):
        MeshMorph(mesh, mode="matrix_free", tolerance=1e-3, stiffening_length=0.1)
    with pytest.raises(ValueError, match="^error_control: the tree's"):
        MeshMorph(mesh, error_control="sampled", stiffening_length=0.1)


def test_mesh_morph_adjoint_in_tree_mode_is_the_exact_adjoint_within_tolerance():
    """MeshMorph.adjoint in tree mode against the exact (dense) adjoint, before and after
    a morph; the boundary rows pass through exactly."""
    mesh = box_mesh(6)
    exact = MeshMorph(mesh, mode="dense")
    tree = MeshMorph(mesh, mode="tree")
    generator = torch.Generator().manual_seed(4)
    fields = torch.randn(2, mesh.points.shape[0], 3, generator=generator, dtype=torch.float64)
    expected = exact.adjoint(fields)
    assert relative_error(tree.adjoint(fields), expected) <= DEFAULT_TOLERANCE
    boundary = mesh.points[exact.boundary_nodes]
    tree(0.05 * boundary.flip(1))
    assert relative_error(tree.adjoint(fields), expected) <= DEFAULT_TOLERANCE
    assert relative_error(tree.adjoint(fields[0]), expected[0]) <= DEFAULT_TOLERANCE


def test_pod_offline_phase_on_a_tree_mode_morph():
    """PODReducer.fit on MeshMorph(mode='tree'): snapshots and the projection (by the
    tree's adjoint) agree with the exact morph's within the tolerance; online='paper',
    which needs W, is refused naming the argument."""
    from torchmorph.pod import PODReducer

    mesh = box_mesh(8)
    exact = MeshMorph(mesh, mode="dense")
    tree = MeshMorph(mesh, mode="tree")
    boundary = mesh.points[exact.boundary_nodes]
    x, y, z = boundary.unbind(1)
    training = 0.05 * torch.stack(
        [torch.stack([torch.sin(k * y), x * z * k, torch.cos(k * x) - y], 1) for k in (1, 2, 3)]
    )
    expected = PODReducer(num_modes=3).fit(exact, training)
    reduced = PODReducer(num_modes=3).fit(tree, training)
    probe = 0.5 * training[0] + 0.2 * training[2]
    assert relative_error(reduced(probe), expected(probe)) <= DEFAULT_TOLERANCE
    with pytest.raises(ValueError, match=r"^online='paper' needs the morph's matrix W"):
        PODReducer(num_modes=3, online="paper").fit(tree, training)


def test_error_control_is_passed_saved_and_checked():
    mesh = box_mesh(6)
    generator = torch.Generator().manual_seed(0)
    boundary = 0.05 * torch.randn(len(mesh.boundary_nodes), 3, generator=generator)
    boundary = boundary.to(mesh.points.dtype)
    sampled = MeshMorph(mesh, mode="tree", tolerance=1e-3, error_control="sampled")
    assert sampled.idw.error_control == "sampled"
    assert sampled.idw._tree.operator(sampled.idw.controls, sampled.idw.targets).error_control == (
        "sampled"
    )
    exact = MeshMorph(mesh)(boundary)
    error = float((sampled(boundary) - exact).norm() / exact.norm())
    assert error <= 1e-3
    certified = MeshMorph(mesh, mode="tree", tolerance=1e-3)
    assert certified.idw.error_control == "certified"
    with pytest.raises(ValueError, match="error_control: the state was saved with"):
        certified.load_state_dict(sampled.state_dict())
    twin = MeshMorph(mesh, mode="tree", tolerance=1e-3, error_control="sampled")
    twin.load_state_dict(sampled.state_dict())
    with pytest.raises(ValueError, match="error_control: only mode='tree' takes error_control"):
        MeshMorph(mesh, error_control="sampled")
    with pytest.raises(ValueError, match="error_control must be 'certified' or 'sampled'"):
        MeshMorph(mesh, mode="tree", error_control="bound")
