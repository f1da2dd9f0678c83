"""The thin-plate treecode (:mod:`torchmorph._treecode`): its sums against exact float64
sums, an error that falls with the degree, the exact transpose and gradcheck, its trees
and degrees, 2-D points, empty sets and thread counts; and the partition of unity's global
fit through it (:class:`torchmorph.rbf.PartitionRBF` with ``summation``)."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest
import torch

from torchmorph._treecode import TreeCode, _midpoint_tree, axis_degrees, tree_sum
from torchmorph.rbf import PartitionRBF, _numba, refine

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64


def sphere_and_walls(count: int, seed: int = 0) -> np.ndarray:
    """A unit sphere of ``count`` points inside the faces of the cube [-2, 2]³ (a quarter
    as many, uniform)."""
    rng = np.random.default_rng(seed)
    body = rng.normal(size=(count, 3))
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    walls = rng.uniform(-2, 2, size=(count // 4, 3))
    axis = rng.integers(0, 3, size=count // 4)
    walls[np.arange(count // 4), axis] = rng.choice([-2.0, 2.0], size=count // 4)
    return np.concatenate([body, walls])


def volume(count: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-2, 2, size=(4 * count, 3))
    return points[np.linalg.norm(points, axis=1) > 1.05][:count]


def away(count: int, seed: int = 1) -> np.ndarray:
    """A small cloud of targets 5 away from the sphere: every node is far from it."""
    return 0.2 * volume(count, seed) + np.array([5.0, 0.0, 0.0])


def exact(targets: np.ndarray, sources: np.ndarray, values: np.ndarray, scale=1.0):
    """Σ_j φ(scale |x − y_j|) values_j in float64, from the definition r² log r."""
    r = scale * np.linalg.norm(targets[:, None, :] - sources[None, :, :], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(r > 0, r * r * np.log(r), 0.0)
    return phi @ values


@pytest.mark.slow
def test_the_sums_against_exact_ones_and_the_error_falls_with_the_degree():
    sources, targets = sphere_and_walls(4000), volume(6000)
    values = np.random.default_rng(2).normal(size=(sources.shape[0], 3))
    reference = exact(targets, sources, values, scale=0.7)
    errors = []
    for degree in (2, 3, 4):
        tree = TreeCode(sources, targets, 0.7, degree)
        assert tree.far.shape[0] > 100  # far source nodes act through their proxies
        assert tree.target_chains.owners.shape[0] > 10  # and target nodes through theirs
        result = tree.apply(values)
        errors.append(np.linalg.norm(result - reference) / np.linalg.norm(reference))
    assert errors[-1] < 2e-5  # measured 6.5e-3, 2.1e-4, 6.2e-6
    assert all(later < earlier / 10 for earlier, later in itertools.pairwise(errors))
    assert TreeCode(sources, targets, 0.7, 4).pairs < 0.7 * 6000 * 5000


def test_a_call_leaves_nothing_to_the_next():
    """Target nodes below one that takes pairs carry its proxy sums without taking any
    themselves; their rows start from zero on every call (they were left uninitialised
    once, and a call read the previous call's sums there)."""
    sources, targets = sphere_and_walls(800), volume(30000)
    tree = TreeCode(sources, targets, 1.0, 3)
    starts = tree.group_starts
    proxy_groups = starts[starts >= tree.num_targets] - tree.num_targets
    taking = np.searchsorted(tree.target.proxy_offsets, proxy_groups, side="right") - 1
    chains = tree.target_chains
    carrying = np.flatnonzero(~np.isin(chains.owners, taking))
    assert carrying.shape[0] > 0
    spans = np.concatenate(
        [np.arange(chains.own_offsets[k], chains.own_offsets[k + 1]) for k in carrying]
    )
    rows = np.concatenate([np.arange(chains.own_starts[k], chains.own_stops[k]) for k in spans])
    checked = tree.target.order[rows]  # the carried targets, in the callers' order
    rng = np.random.default_rng(10)
    first, second = rng.normal(size=(2, sources.shape[0], 3))
    reference = exact(targets[checked], sources, second)
    tree.apply(1e6 * first)
    result = tree.apply(second)[checked]
    assert np.linalg.norm(result - reference) / np.linalg.norm(reference) < 2e-3  # 1.6e-4


def test_exact_where_every_node_is_near():
    sources, targets = sphere_and_walls(200), volume(100)
    values = np.random.default_rng(3).normal(size=(sources.shape[0], 2))
    tree = TreeCode(sources, targets, 1.0, 16)  # more proxies than any node's points
    assert not tree.source.expanded.any() and not tree.target.expanded.any()
    assert tree.pairs == targets.shape[0] * sources.shape[0]
    np.testing.assert_allclose(tree.apply(values), exact(targets, sources, values), atol=1e-12)


def test_the_transpose_is_exact_and_gradcheck_passes():
    sources, targets = sphere_and_walls(800), volume(3000)
    tree = TreeCode(sources, targets, 1.0, 3)
    assert (
        tree.far.shape[0] > 0 and tree.target_chains.owners.shape[0] > 0
    )  # both sides' proxies act
    assert tree.target_chains.down_levels.shape[0] > 0
    rng = np.random.default_rng(4)
    values, grads = rng.normal(size=(800 + 200, 2)), rng.normal(size=(3000, 2))
    forward = float((grads * tree.apply(values)).sum())
    backward = float((tree.apply_transposed(grads) * values).sum())
    assert abs(forward - backward) <= 1e-12 * abs(forward)
    small = TreeCode(sources[:300], away(40), 1.0, 2)
    assert small.far.shape[0] > 0
    weights = torch.from_numpy(rng.normal(size=(300, 3))).requires_grad_()
    assert torch.autograd.gradcheck(lambda w: tree_sum(small, w), (weights,), fast_mode=True)


def test_tree_sum_keeps_the_values_dtype():
    sources, targets = sphere_and_walls(800), volume(3000)
    tree = TreeCode(sources, targets, 1.0, 3)
    values = torch.from_numpy(np.random.default_rng(11).normal(size=(1000, 3)))
    single = tree_sum(tree, values.float().requires_grad_())
    assert single.dtype == torch.float32
    torch.testing.assert_close(single.double(), tree_sum(tree, values), rtol=1e-5, atol=1e-4)
    single.sum().backward()


def test_threads_give_the_same_sums():
    sources, targets = sphere_and_walls(3000), volume(2000)
    values = np.random.default_rng(5).normal(size=(sources.shape[0], 3))
    grads = np.random.default_rng(6).normal(size=(targets.shape[0], 3))
    tree = TreeCode(sources, targets, 1.0, 6)
    assert np.array_equal(tree.apply(values, 1), tree.apply(values, 2))
    np.testing.assert_allclose(
        tree.apply_transposed(grads, 1), tree.apply_transposed(grads, 2), rtol=1e-12, atol=1e-9
    )


def test_two_dimensional_points_and_empty_targets():
    rng = np.random.default_rng(7)
    angle = rng.uniform(0, 2 * np.pi, 3000)
    sources = np.stack([np.cos(angle), 0.3 * np.sin(angle)], 1)
    targets = rng.uniform(-3, 3, size=(800, 2))
    values = rng.normal(size=(3000, 2))
    tree = TreeCode(sources, targets, 1.0, 8)
    assert (tree.source.degrees[:, 2] == 0).all() and (tree.target.degrees[:, 2] == 0).all()
    reference = exact(targets, sources, values)
    result = tree.apply(values)
    assert np.linalg.norm(result - reference) / np.linalg.norm(reference) < 1e-7
    nothing = TreeCode(sources, np.zeros((0, 2)), 1.0, 8)
    assert nothing.apply(values).shape == (0, 2) and nothing.pairs == 0
    assert np.array_equal(nothing.apply_transposed(np.zeros((0, 2))), np.zeros((3000, 2)))


def test_a_target_on_a_source_takes_phi_of_zero():
    sources = sphere_and_walls(600)
    values = np.random.default_rng(8).normal(size=(sources.shape[0], 1))
    tree = TreeCode(sources, sources[:50], 1.0, 12)
    np.testing.assert_allclose(
        tree.apply(values), exact(sources[:50], sources, values), rtol=1e-9, atol=1e-9
    )


def test_the_midpoint_tree_and_the_axis_degrees():
    points = sphere_and_walls(2000)
    order, starts, stops, children = _midpoint_tree(points, 32)
    assert sorted(order.tolist()) == list(range(points.shape[0]))
    leaves = children[:, 0] < 0
    assert (stops - starts)[leaves].max() <= 32
    assert sorted(starts[leaves].tolist()) == sorted(np.append(0, stops[leaves])[:-1].tolist())
    for node in np.flatnonzero(~leaves)[:50]:  # the children split the widest side's middle
        part = points[order[starts[node] : stops[node]]]
        axis = int(np.argmax(np.ptp(part, axis=0)))
        middle = part[:, axis].min() + np.ptp(part[:, axis]) / 2
        left, right = children[node]
        assert (points[order[starts[left] : stops[left]], axis] <= middle).all()
        assert (points[order[starts[right] : stops[right]], axis] > middle).all()
    same = np.zeros((100, 3))
    _, starts, stops, children = _midpoint_tree(same, 8)  # coincident points: one leaf
    assert starts.tolist() == [0] and stops.tolist() == [100]
    low = np.zeros((4, 3))
    high = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 0.1, 0.05], [1.0, 0.3, 1e-14]])
    degrees = axis_degrees(low, high, 8, 0.7)
    assert degrees[0].tolist() == [8, 0, 0]  # a segment: its axis the full degree
    assert degrees[1].tolist() == [8, 8, 0]  # a square: both sides
    assert degrees[3, 2] == 0  # a flat axis: one point

    def rho(half, radius):  # the Bernstein parameter of an axis of half-width ``half``
        ratio = radius / 0.7 / half
        return ratio + np.sqrt(ratio**2 + 1)

    for node in (2, 3):  # the smallest degree whose error matches the longest axis's
        half = (high[node] - low[node]) / 2
        radius = np.linalg.norm(half)
        goal = rho(half.max(), radius) ** 9
        for axis in (1, 2)[: 2 if node == 2 else 1]:
            used = degrees[node, axis]
            assert 0 < used < 8
            assert rho(half[axis], radius) ** (used + 1) >= goal * (1 - 1e-12)
            assert rho(half[axis], radius) ** used < goal


# ------------------------------------------------------------ the partition of unity
def body(count: int) -> torch.Tensor:
    return torch.from_numpy(sphere_and_walls(count, seed=11))


def smooth(points: torch.Tensor) -> torch.Tensor:
    x, y, z = points.T
    return 0.05 * torch.stack([torch.sin(3 * x) + z * y, torch.cos(2 * y) * x, z**2 - 0.3 * x], 1)


SMALL = {"patch_size": 40, "coarse_size": 100}


@pytest.mark.slow
def test_the_global_fit_through_the_treecode(monkeypatch):
    """At these sizes the degree a tolerance gives leaves no node far enough: lower
    degrees (through ``treecode_degree``) make the far field act, and the morph's error
    against the exact sums' global fit is what the sampled check says, falling with the
    degree."""
    controls = body(1200)
    targets = torch.cat([torch.from_numpy(volume(3000, seed=12)), controls[::9]])
    values = smooth(controls)
    values[1200:] = 0  # the walls stay
    reference = PartitionRBF(controls, targets, tolerance=1e-10, summation="exact", **SMALL)
    expected = reference(values)
    errors = []
    for degree in (3, 5):
        monkeypatch.setattr(refine, "treecode_degree", lambda tolerance, degree=degree: degree)
        monkeypatch.setattr(refine, "control_degree", lambda tolerance, degree=degree: degree)
        module = PartitionRBF(controls, targets, tolerance=1e-6, summation="treecode", **SMALL)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the sampled error above 1e-6
            moved = module(values)
        sums = module._sums
        assert sums is not None and sums.control_tree is not None
        assert sums.target_tree is not None and sums.coarse_tree is not None
        assert sums.target_tree.far.shape[0] > 0 and sums.control_tree.far.shape[0] > 0
        error = float((moved - expected).norm() / expected.norm())
        assert 0.3 * error < module.last_treecode_error_ < 3 * error  # 0.91, 0.44
        on = len(controls[::9])  # the targets on controls take their displacements exactly
        assert torch.equal(moved[-on:], values[::9])
        errors.append(error)
    assert errors[1] < errors[0] / 30 and errors[1] < 1e-4  # measured 0.16, 6.9e-5
    batch = torch.stack([values, 2 * values])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        torch.testing.assert_close(module(batch)[1], 2 * moved, rtol=0, atol=1e-10)


def test_the_backward_pass_through_the_treecode_is_the_transpose(monkeypatch):
    """The morph is linear in the displacements, so its backward pass must satisfy
    ⟨g, M v⟩ = ⟨Mᵀ g, v⟩ with the targets' treecode in the chain (its sums at the
    controls made exact, so that the solve is the symmetric system's; to the solve's
    tolerance: finite differences would see the iterations' stopping, not the
    derivative)."""
    monkeypatch.setattr(refine, "treecode_degree", lambda tolerance: 4)
    monkeypatch.setattr(refine, "control_degree", lambda tolerance: 4)
    controls = body(400)
    module = PartitionRBF(
        controls, torch.from_numpy(away(30, seed=13)), tolerance=1e-8, max_iterations=300,
        summation="treecode", patch_size=20, coarse_size=40,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the sampled error above 1e-8
        module(smooth(controls))
        sums = module._sums
        assert sums is not None and sums.target_tree is not None
        assert sums.target_tree.far.shape[0] > 0
        sums.control_tree = sums.coarse_tree = None
        rng = np.random.default_rng(17)
        values = torch.from_numpy(rng.normal(size=(controls.shape[0], 3))).requires_grad_()
        grads = torch.from_numpy(rng.normal(size=(30, 3)))
        moved = module(values)
        (transposed,) = torch.autograd.grad(moved, values, grads)
    forward = float((grads * moved.detach()).sum())
    backward = float((transposed * values.detach()).sum())
    assert abs(forward - backward) < 1e-5 * abs(forward)  # measured 1.3e-6
    assert module.last_iterations_ < 300


def test_auto_takes_the_treecode_from_the_pair_count(monkeypatch):
    controls, targets = body(400), torch.from_numpy(volume(600, seed=14))
    values = smooth(controls)
    module = PartitionRBF(controls, targets, tolerance=1e-6, **SMALL)
    module(values)
    assert module._sums.control_tree is None and module._sums.target_tree is None  # type: ignore[union-attr]
    monkeypatch.setattr(refine, "TREECODE_PAIRS", 500 * 500 + 1)  # 500 controls, 600 targets
    module = PartitionRBF(controls, targets, tolerance=1e-6, **SMALL)
    module(values)
    assert module._sums.control_tree is None and module._sums.target_tree is not None  # type: ignore[union-attr]
    cubic = PartitionRBF(controls, targets, kernel="cubic", tolerance=1e-6, **SMALL)
    cubic(values)
    assert cubic._sums.target_tree is None  # type: ignore[union-attr]
    exact_module = PartitionRBF(controls, targets, tolerance=1e-6, summation="exact", **SMALL)
    exact_module(values)
    assert exact_module._sums.target_tree is None  # type: ignore[union-attr]


@pytest.mark.filterwarnings("ignore:PartitionRBF. the global fit stopped:RuntimeWarning")
def test_a_coarse_treecode_warns_with_its_sampled_error(monkeypatch):
    controls, targets = body(1200), torch.from_numpy(volume(400, seed=15))
    monkeypatch.setattr(refine, "treecode_degree", lambda tolerance: 1)
    monkeypatch.setattr(refine, "control_degree", lambda tolerance: 1)
    module = PartitionRBF(controls, targets, tolerance=1e-8, summation="treecode", **SMALL)
    with pytest.warns(RuntimeWarning, match=r"^PartitionRBF: the treecode's sums were .* off the "
                      r"exact ones at the sampled targets, > tolerance=1e-08"):  # fmt: skip
        module(smooth(controls))
    assert module.last_treecode_error_ > 1e-8


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"summation": "tree", "tolerance": 1e-4}, r"^summation must be one of 'auto', "),
        ({"summation": "treecode"}, r"^summation='treecode' needs a tolerance"),
        ({"summation": "treecode", "tolerance": 1e-4, "kernel": "cubic"},
         r"^summation='treecode' serves kernel='thin_plate_spline', got 'cubic'"),
    ],
)  # fmt: skip
def test_bad_summations(options, message):
    with pytest.raises(ValueError, match=message):
        PartitionRBF(body(100), body(100)[:5], **options, **SMALL)


def test_the_treecode_needs_numba(monkeypatch):
    monkeypatch.setattr(_numba, "available", lambda: False)
    with pytest.raises(ValueError, match="^summation='treecode' needs numba"):
        PartitionRBF(body(100), body(100)[:5], tolerance=1e-4, summation="treecode", **SMALL)


def test_summation_is_part_of_the_state_and_older_states_load():
    controls, targets = body(300), torch.from_numpy(volume(20, seed=16))
    module = PartitionRBF(controls, targets, tolerance=1e-6, summation="exact", **SMALL)
    state = module.state_dict()
    with pytest.raises(ValueError, match="^summation: the state was saved with summation='exact'"):
        PartitionRBF(controls, targets, tolerance=1e-6, **SMALL).load_state_dict(state)
    older = dict(PartitionRBF(controls, targets, **SMALL).state_dict())
    older["_extra_state"] = {
        key: value
        for key, value in older["_extra_state"].items()
        if key not in ("tolerance", "max_iterations", "summation")
    }
    loaded = PartitionRBF(body(200), targets, **SMALL)
    loaded.load_state_dict(older)
    values = smooth(controls)
    torch.testing.assert_close(loaded(values), PartitionRBF(controls, targets, **SMALL)(values))


def test_the_exact_sums_of_the_fused_pass_are_the_reference():
    """The tests' own reference (:func:`exact`) against the library's fused pass."""
    sources, targets = sphere_and_walls(300), volume(50)
    values = np.random.default_rng(9).normal(size=(sources.shape[0], 2))
    fused = _numba.tps_apply(
        torch.from_numpy(targets), torch.from_numpy(sources), 1.3, torch.from_numpy(values)
    )
    np.testing.assert_allclose(fused.numpy(), exact(targets, sources, values, 1.3), rtol=1e-12,
                               atol=1e-12)  # fmt: skip
