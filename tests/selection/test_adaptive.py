"""Tests of the error-driven selection (torchmorph.selection.adaptive and .greedy)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmorph.mesh import TetMesh
from torchmorph.mesh.tetmesh import box_mesh
from torchmorph.morph import MeshMorph
from torchmorph.selection import (
    AdaptivePlan,
    IDWErrorOracle,
    Region,
    SelectionPlan,
    select_adaptive,
)


def reference_idw(controls, targets, values, power=4.0):
    """Eq. (2) literally, in NumPy: w_k = |x - c_k|^-p / sum_j |x - c_j|^-p."""
    controls, targets, values = (
        np.asarray(a, dtype=np.float64) for a in (controls, targets, values)
    )
    distances = np.sqrt(((targets[:, None, :] - controls[None, :, :]) ** 2).sum(-1))
    weights = distances**-power
    weights /= weights.sum(1, keepdims=True)
    return weights @ values


def bent_box(cells=6):
    """A box whose top face bends (δy = 0.2 x² on y = 1), the rest fixed."""
    mesh = box_mesh(cells)
    boundary = mesh.boundary_nodes
    points = mesh.points[boundary]
    displacement = torch.zeros_like(points)
    top = points[:, 1] > 1 - 1e-12
    displacement[top, 1] = 0.2 * points[top, 0] ** 2
    return mesh, displacement


def nodal_error(mesh, boundary_displacement, selected_nodes, weights=None):
    """Relative weighted nodal error of IDW from ``selected_nodes`` against IDW from every
    boundary node, over the whole mesh, from the NumPy reference."""
    boundary = mesh.boundary_nodes.numpy()
    interior = mesh.interior_nodes.numpy()
    points = mesh.points.numpy()
    d = boundary_displacement.numpy()
    full = reference_idw(points[boundary], points[interior], d)
    rows = np.searchsorted(boundary, np.asarray(selected_nodes))
    partial = reference_idw(points[boundary[rows]], points[interior], d[rows])
    w = np.ones(mesh.num_nodes) if weights is None else np.asarray(weights, dtype=np.float64)
    error = (w[interior, None] * (partial - full) ** 2).sum()
    norm = (w[interior, None] * full**2).sum() + (w[boundary, None] * d**2).sum()
    return np.sqrt(error / norm)


@pytest.mark.parametrize("tolerance", [0.05, 0.01])
def test_tolerance_reached_against_the_literal_formula(tolerance):
    mesh, displacement = bent_box()
    plan = AdaptivePlan(tolerance, displacement)
    morph = MeshMorph(mesh, plan)
    assert plan.result_.converged and plan.result_.reason == "tolerance"
    error = nodal_error(mesh, displacement, morph.control_nodes.numpy())
    assert error <= tolerance
    assert error == pytest.approx(plan.result_.error, rel=1e-9)  # every target sampled
    assert morph.num_controls < morph.num_boundary


def test_at_least_one_control_when_no_control_is_within_tolerance():
    mesh, displacement = bent_box(4)
    plan = AdaptivePlan(0.99, displacement)  # the zero field is within 99 %
    morph = MeshMorph(mesh, plan)
    assert morph.num_controls >= 1 and plan.result_.converged


def test_budget_respected():
    mesh, displacement = bent_box()
    plan = AdaptivePlan(1e-9, displacement, max_controls=7)
    morph = MeshMorph(mesh, plan)
    assert morph.num_controls == 7
    assert plan.result_.reason == "budget" and not plan.result_.converged
    # the recorded error is the morph's
    assert nodal_error(mesh, displacement, morph.control_nodes.numpy()) == pytest.approx(
        plan.result_.error, rel=1e-9
    )


def test_start_set_is_kept():
    mesh, displacement = bent_box()
    start = SelectionPlan([Region("y1", 0.5)], uncovered="ignore")
    chosen = start.select(mesh)
    morph = MeshMorph(mesh, AdaptivePlan(0.02, displacement, start=start))
    assert set(chosen.tolist()) <= set(morph.control_nodes.tolist())


def test_weights_respected():
    mesh, displacement = bent_box()
    x = mesh.points[:, 0]
    weights = (x > 0.5).to(mesh.dtype)  # only the right half counts
    tolerance = 0.01
    plan = AdaptivePlan(tolerance, displacement, weights=weights)
    morph = MeshMorph(mesh, plan)
    weighted = nodal_error(mesh, displacement, morph.control_nodes.numpy(), weights.numpy())
    assert weighted <= tolerance
    assert weighted == pytest.approx(plan.result_.error, rel=1e-9)
    # the unweighted error of that selection is not what was driven
    plain = nodal_error(mesh, displacement, morph.control_nodes.numpy())
    assert plain != pytest.approx(weighted, rel=1e-3)


def test_worst_over_the_family():
    mesh, bend = bent_box()
    twist = torch.zeros_like(bend)
    points = mesh.points[mesh.boundary_nodes]
    top = points[:, 1] > 1 - 1e-12
    twist[top, 2] = 0.1 * torch.sin(3 * points[top, 0])
    family = torch.stack([bend, twist])
    plan = AdaptivePlan(0.01, family)
    morph = MeshMorph(mesh, plan)
    nodes = morph.control_nodes.numpy()
    errors = [nodal_error(mesh, member, nodes) for member in family]
    assert max(errors) <= 0.01
    assert max(errors) == pytest.approx(plan.result_.error, rel=1e-9)


def test_scores_are_the_error_decrease_of_each_candidate_alone():
    mesh, displacement = bent_box(4)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    oracle = IDWErrorOracle(boundary, interior, displacement)
    selected = torch.arange(0, boundary.shape[0], 3)
    errors, scores = oracle.scores(selected)
    assert (scores[selected] == -float("inf")).all()
    assert (scores > 0).any()
    for candidate in (1, 5, 29, 61):
        after = oracle.errors(torch.cat([selected, torch.tensor([candidate])]))
        decrease = float(errors.square().sum() - after.square().sum())
        assert float(scores[candidate]) == pytest.approx(decrease, rel=1e-9, abs=1e-15)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_scores_equal_the_torch_products(monkeypatch, dtype):
    from torchmorph.selection import _score_jit

    mesh, displacement = bent_box(4)
    boundary = mesh.points[mesh.boundary_nodes].to(dtype)
    interior = mesh.points[mesh.interior_nodes].to(dtype)
    family = torch.stack([displacement, displacement.flip(0)]).to(dtype)
    oracle = IDWErrorOracle(boundary, interior, family)
    selected = torch.arange(0, boundary.shape[0], 5)
    assert _score_jit.available(oracle.weights_t)
    errors, fused = oracle.scores(selected)
    monkeypatch.setattr(_score_jit, "available", lambda weights_t: False)
    errors_torch, plain = oracle.scores(selected)
    assert torch.equal(errors, errors_torch)
    finite = torch.isfinite(plain)
    assert torch.equal(finite, torch.isfinite(fused))
    scale = float(plain[finite].abs().max())
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    assert float((fused[finite] - plain[finite]).abs().max()) <= tolerance * scale


def test_errors_after_a_scoring_equal_a_fresh_oracle():
    """The oracle reuses the last scoring's sums for the selections that extend it."""
    mesh, displacement = bent_box(4)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    oracle = IDWErrorOracle(boundary, interior, displacement)
    base = torch.arange(0, boundary.shape[0], 4)
    oracle.scores(base)
    extended = torch.cat([base, torch.tensor([1, 2, 7])])
    other = torch.arange(1, boundary.shape[0], 3)  # does not start with the base
    for selected in (base, extended, other, base[:5]):
        fresh = IDWErrorOracle(boundary, interior, displacement).errors(selected)
        assert float(oracle.errors(selected)) == pytest.approx(float(fresh), rel=1e-12)


def test_from_nothing_the_scores_are_shares_of_the_error():
    mesh, displacement = bent_box(4)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    oracle = IDWErrorOracle(boundary, interior, displacement)
    errors, scores = oracle.scores(torch.zeros(0, dtype=torch.int64))
    # with no control the error is the whole reference field; the shares add up to it
    assert float(scores.sum()) == pytest.approx(float(errors.square().sum()), rel=1e-9)


def test_sampled_targets_estimate_the_error():
    mesh, displacement = bent_box(8)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    full = IDWErrorOracle(boundary, interior, displacement)
    sampled = IDWErrorOracle(boundary, interior, displacement, num_samples=interior.shape[0] // 3)
    selected = torch.arange(0, boundary.shape[0], 7)
    assert len(sampled.sample) == interior.shape[0] // 3
    assert float(sampled.errors(selected)) == pytest.approx(float(full.errors(selected)), rel=0.3)


def test_functional_form_returns_candidate_indices():
    mesh, displacement = bent_box()
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    result = select_adaptive(boundary, interior, displacement, tolerance=0.02)
    assert result.indices.dtype == torch.int64
    assert len(set(result.indices.tolist())) == len(result.indices)
    assert result.history[-1] == (len(result.indices), result.error)


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"tolerance": 0.0}, "tolerance must be a finite number > 0"),
        ({"tolerance": -1.0}, "tolerance must be a finite number > 0"),
        ({"tolerance": float("nan")}, "tolerance must be a finite number > 0"),
        ({"tolerance": 0.1, "max_controls": 0}, "max_controls must be an integer >= 1"),
        ({"tolerance": 0.1, "max_controls": 2.5}, "max_controls must be an integer >= 1"),
    ],
)
def test_bad_tolerance_and_budget(keywords, message):
    mesh, displacement = bent_box(2)
    with pytest.raises(ValueError, match=message):
        AdaptivePlan(displacements=displacement, **keywords)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    with pytest.raises(ValueError, match=message):
        select_adaptive(boundary, interior, displacement, **keywords)


def test_bad_shapes_and_values():
    mesh, displacement = bent_box(2)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    n = boundary.shape[0]
    with pytest.raises(ValueError, match=rf"displacements must have shape \({n}, 3\)"):
        select_adaptive(boundary, interior, displacement[:-1], tolerance=0.1)
    broken = displacement.clone()
    broken[0, 0] = float("nan")
    with pytest.raises(ValueError, match="displacements holds 1 NaN"):
        select_adaptive(boundary, interior, broken, tolerance=0.1)
    bad = interior.clone()
    bad[0, 1] = float("inf")
    with pytest.raises(ValueError, match="targets holds"):
        select_adaptive(boundary, bad, displacement, tolerance=0.1)
    with pytest.raises(ValueError, match=r"targets must have shape \(N, 3\)"):
        select_adaptive(boundary, interior[:, :2], displacement, tolerance=0.1)
    with pytest.raises(ValueError, match=r"weights must have shape"):
        select_adaptive(boundary, interior, displacement, tolerance=0.1, weights=torch.ones(3))
    weights = torch.ones(interior.shape[0])
    weights[0] = -1
    with pytest.raises(ValueError, match="weights holds negative"):
        select_adaptive(boundary, interior, displacement, tolerance=0.1, weights=weights)
    zeros = torch.zeros(interior.shape[0])
    with pytest.raises(ValueError, match="weights are all zero"):
        select_adaptive(boundary, interior, displacement, tolerance=0.1, weights=zeros)
    with pytest.raises(ValueError, match="member 0 of the family has a zero reference"):
        select_adaptive(boundary, interior, torch.zeros_like(displacement), tolerance=0.1)
    with pytest.raises(ValueError, match="initial holds indices outside"):
        select_adaptive(boundary, interior, displacement, tolerance=0.1, initial=torch.tensor([n]))
    with pytest.raises(ValueError, match=r"max_controls \(1\) is smaller than the 2 initial"):
        select_adaptive(
            boundary,
            interior,
            displacement,
            tolerance=0.1,
            max_controls=1,
            initial=torch.tensor([0, 1]),
        )
    with pytest.raises(ValueError, match=r"weights must have shape \(\d+,\) \(one per node\)"):
        MeshMorph(mesh, AdaptivePlan(0.1, displacement, weights=torch.ones(3)))
    with pytest.raises(TypeError, match="displacements must be a Tensor"):
        AdaptivePlan(0.1, [1.0, 2.0])


def test_callable_family_of_the_boundary_points():
    mesh, displacement = bent_box()

    def bend(points):
        out = torch.zeros_like(points)
        top = points[:, 1] > 1 - 1e-12
        out[top, 1] = 0.2 * points[top, 0] ** 2
        return out

    by_tensor = MeshMorph(mesh, AdaptivePlan(0.02, displacement))
    by_callable = MeshMorph(mesh, AdaptivePlan(0.02, bend))
    assert torch.equal(by_tensor.control_nodes, by_callable.control_nodes)


def test_a_morph_of_adaptive_controls_is_differentiable_and_batched():
    mesh, displacement = bent_box(4)
    morph = MeshMorph(mesh, AdaptivePlan(0.05, displacement))
    batch = torch.stack([displacement, 2 * displacement]).requires_grad_()
    out = morph(batch)
    torch.testing.assert_close(out[1], 2 * morph(displacement))
    (grad,) = torch.autograd.grad(out.square().sum(), batch)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_two_dimensional_mesh():
    square = box_mesh(6)
    del square  # the 3-D helper; a planar mesh below
    xs = torch.linspace(0, 1, 7, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    assert isinstance(TetMesh, type)  # imported for the module's mesh kinds
    from torchmorph.mesh import Mesh

    cells = []
    for i in range(6):
        for j in range(6):
            a, b, c, d = i * 7 + j, (i + 1) * 7 + j, (i + 1) * 7 + j + 1, i * 7 + j + 1
            cells += [[a, b, c], [a, c, d]]
    mesh = Mesh(grid, {"triangle": torch.tensor(cells)})
    boundary = mesh.points[mesh.boundary_nodes]
    displacement = torch.zeros_like(boundary)
    displacement[:, 1] = 0.1 * torch.sin(3 * boundary[:, 0]) * (boundary[:, 1] > 0.99)
    plan = AdaptivePlan(0.02, displacement)
    morph = MeshMorph(mesh, plan)
    assert plan.result_.converged
    assert nodal_error(mesh, displacement, morph.control_nodes.numpy()) <= 0.02


def test_members_equal_up_to_a_factor_count_once():
    mesh, displacement = bent_box(4)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    family = torch.stack([displacement, -3.0 * displacement, 0.5 * displacement])
    oracle = IDWErrorOracle(boundary, interior, family)
    single = IDWErrorOracle(boundary, interior, displacement)
    selected = torch.arange(0, boundary.shape[0], 4)
    assert oracle.errors(selected).shape == (1,)
    torch.testing.assert_close(oracle.errors(selected), single.errors(selected))
    twisted = displacement.clone()
    twisted[:, 2] = displacement[:, 1]
    assert IDWErrorOracle(boundary, interior, torch.stack([displacement, twisted])).errors(
        selected
    ).shape == (2,)


class _CoverOracle:
    """A toy interpolant for the loop alone: the error is the share of ``needed``
    candidates not selected, each needed candidate scores 1, the others 0."""

    def __init__(self, count, needed):
        self.points = torch.rand(count, 2, generator=torch.Generator().manual_seed(3))
        self.needed = set(needed)
        self.calls = 0

    def errors(self, selected):
        missing = self.needed - set(selected.tolist())
        return torch.tensor([len(missing) / len(self.needed)], dtype=torch.float64)

    def scores(self, selected):
        self.calls += 1
        values = torch.zeros(len(self.points))
        values[sorted(self.needed - set(selected.tolist()))] = 1.0
        return self.errors(selected), values


def test_the_loop_takes_any_oracle():
    from torchmorph.selection import ErrorOracle, greedy_selection

    oracle = _CoverOracle(200, range(0, 200, 5))
    assert isinstance(oracle, ErrorOracle)
    result = greedy_selection(oracle, tolerance=0.05, spacing=0.0)
    # 40 needed, 5 % may stay missing: 38 of them, nothing else, found by bisection
    assert set(result.indices.tolist()) <= oracle.needed
    assert len(result.indices) == 38 and result.converged
    capped = greedy_selection(_CoverOracle(200, range(0, 200, 5)), tolerance=0.05, max_controls=10)
    assert len(capped.indices) == 10 and capped.reason == "budget"
    with pytest.raises(ValueError, match="min_batch must be an integer >= 1"):
        greedy_selection(oracle, tolerance=0.1, min_batch=0)
    with pytest.raises(ValueError, match="spacing must be a finite number >= 0"):
        greedy_selection(oracle, tolerance=0.1, spacing=-1.0)
    with pytest.raises(ValueError, match="initial holds repeated indices"):
        greedy_selection(oracle, tolerance=0.1, initial=torch.tensor([1, 1]))


def test_a_sampled_selection_is_checked_on_every_target():
    mesh, displacement = bent_box(8)
    tolerance = 0.01
    plan = AdaptivePlan(tolerance, displacement, num_samples=40)
    morph = MeshMorph(mesh, plan)
    assert plan.sampled_targets_ == morph.num_interior  # the final error is every node's
    error = nodal_error(mesh, displacement, morph.control_nodes.numpy())
    assert error == pytest.approx(plan.result_.error, rel=1e-9)
    assert error <= tolerance and plan.result_.converged
    # every run counted, from the stratified start's first prefix of 8 nodes
    assert plan.result_.rounds > 1 and plan.result_.history[0][0] == 8


# ---------------------------------------------------------------- driven by the RBF error


def rbf_boundary_error(mesh, displacement, nodes, kernel="thin_plate_spline", **options):
    """max |s − d| / max |d| over the boundary nodes of the RBF fitted at ``nodes``, in
    NumPy (φ(r) = r² log r or r³ with the linear polynomial: the saddle system solved)."""
    boundary = mesh.boundary_nodes.numpy()
    points = mesh.points.numpy()[boundary]
    rows = np.searchsorted(boundary, np.asarray(nodes))
    d = displacement.numpy()

    def phi(a, b):
        r = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1))
        if kernel == "cubic":
            return r**3
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(r > 0, r**2 * np.log(r), 0.0)

    centres = points[rows]
    poly = np.hstack([np.ones((len(rows), 1)), centres])
    system = np.block([[phi(centres, centres), poly], [poly.T, np.zeros((4, 4))]])
    coefficients = np.linalg.solve(system, np.vstack([d[rows], np.zeros((4, 3))]))
    fitted = np.hstack([phi(points, centres), np.ones((len(points), 1)), points]) @ coefficients
    return np.linalg.norm(fitted - d, axis=1).max() / np.linalg.norm(d, axis=1).max()


@pytest.mark.parametrize("kernel", ["thin_plate_spline", "cubic"])
def test_an_rbf_morph_selects_by_the_rbf_error(kernel):
    from torchmorph.rbf import RBFErrorOracle
    from torchmorph.selection.greedy import greedy_selection

    mesh, displacement = bent_box()
    plan = AdaptivePlan(0.01, displacement)
    morph = MeshMorph(mesh, plan, method="rbf", kernel=kernel)
    assert plan.method_ == "rbf" and plan.sampled_targets_ == 0
    nodes = morph.control_nodes
    assert rbf_boundary_error(mesh, displacement, nodes, kernel) <= 0.01
    assert plan.result_.error == pytest.approx(
        rbf_boundary_error(mesh, displacement, nodes, kernel), rel=1e-8
    )
    assert len(nodes) < len(mesh.boundary_nodes)
    # the same as the selection loop with the RBF oracle, from the polynomial's anchors
    oracle = RBFErrorOracle(mesh.points[mesh.boundary_nodes], displacement, kernel=kernel)
    direct = greedy_selection(oracle, tolerance=0.01, initial=oracle.anchors)
    expected = torch.sort(mesh.boundary_nodes[direct.indices]).values
    assert torch.equal(nodes, expected)


def test_the_plan_method_overrides_the_morph():
    mesh, displacement = bent_box()
    idw_driven = AdaptivePlan(0.02, displacement, method="idw")
    MeshMorph(mesh, idw_driven, method="rbf")
    assert idw_driven.method_ == "idw"
    alone = AdaptivePlan(0.02, displacement).select(mesh)
    assert torch.equal(torch.sort(idw_driven.select(mesh)).values, alone)
    # the plan's own RBF options win over the morph's; alone, RBF's defaults
    own = AdaptivePlan(0.01, displacement, method="rbf", kernel="cubic")
    morph = MeshMorph(mesh, own, method="rbf", kernel="thin_plate_spline")
    assert rbf_boundary_error(mesh, displacement, morph.control_nodes, "cubic") <= 0.01
    default = AdaptivePlan(0.01, displacement, method="rbf").select(mesh)
    assert rbf_boundary_error(mesh, displacement, default) <= 0.01


def test_an_rbf_selection_keeps_its_start_and_the_anchors():
    mesh, displacement = bent_box()
    start = SelectionPlan([Region("(boundary)", 0.9)])
    boxed = mesh.with_node_sets({"(boundary)": mesh.boundary_nodes})
    plan = AdaptivePlan(0.01, displacement, start=start, method="rbf")
    nodes = plan.select(boxed, generator=torch.Generator().manual_seed(0))
    first = start.select(boxed, generator=torch.Generator().manual_seed(0))
    assert bool(torch.isin(first, nodes).all())
    assert rbf_boundary_error(mesh, displacement, nodes) <= 0.01


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"method": "spline"}, "method"),
        ({"method": "idw", "kernel": "cubic"}, "kernel: an option of method='rbf'"),
        ({"method": "rbf", "weights": torch.ones(343)}, "weights: the RBF error"),
        ({"method": "rbf", "num_samples": 10}, "num_samples: the RBF error"),
        ({"method": "rbf", "score_samples": 10}, "score_samples: the RBF error"),
        ({"method": "rbf", "max_controls": 2}, "max_controls (2) is smaller than the 4"),
        ({"method": "rbf", "kernel": "cubic", "degree": 0}, "degree must be at least 1"),
    ],
)
def test_bad_rbf_plans(keywords, message):
    mesh, displacement = bent_box()
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        AdaptivePlan(0.01, displacement, **keywords).select(mesh)
