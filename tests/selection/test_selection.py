"""Tests of torchmorph.selection: Algorithm 1 (the paper's section 2.2) and selection plans (2.2.1)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist

from torchmorph.mesh import TetMesh
from torchmorph.selection import Region, SelectionPlan, select_control_points

STRATEGIES = ("random", "centroid", "farthest")


# --------------------------------------------------------------------------------------
# plain reference: SPEC.md §2 transcribed line by line, O(N^2)
# --------------------------------------------------------------------------------------


def reference_sidw(points, radius, a, b, start, strategy, generator):
    """Algorithm 1 with explicit annulus index arrays and full rescans.

    Annuli are ``R + (n-1) aR <= |x - c1| < R + n aR``, balls ``|x - c| < R`` and
    shells ``R <= |x - c| < bR``; index arrays are kept sorted so that ties and random
    draws (one ``torch.randint`` per choice) line up with the library's.
    """
    points = np.asarray(points, dtype=np.float64)
    step = a * radius
    everything = np.arange(len(points))

    def distance(indices, center):
        return np.sqrt(((points[indices] - points[center]) ** 2).sum(axis=-1))

    def shell(indices, center, inner, outer):
        d = distance(indices, center)
        return indices[(d >= inner) & (d < outer)]

    def select_control_point(beta, selected):
        if strategy == "random":
            return int(beta[int(torch.randint(len(beta), (1,), generator=generator))])
        if strategy == "centroid":
            centroid = points[beta].mean(axis=0)
            return int(beta[np.argmin(np.sqrt(((points[beta] - centroid) ** 2).sum(axis=-1)))])
        chosen = points[np.asarray(selected)]
        gaps = np.sqrt(((points[beta][:, None, :] - chosen[None, :, :]) ** 2).sum(axis=-1))
        return int(beta[np.argmax(gaps.min(axis=1))])

    # initialisation
    r_omega = distance(everything, start).max()
    alpha = []
    n = 0
    while radius + n * step <= r_omega:
        n += 1
        alpha.append(shell(everything, start, radius + (n - 1) * step, radius + n * step))
    selected = [start]
    # selection
    m = 1
    beta = shell(alpha[0], start, radius, b * radius) if n >= 1 else everything[:0]
    while m <= n:
        while len(beta):
            c = select_control_point(beta, selected)
            selected.append(c)
            for level in range(m, n + 1):
                alpha[level - 1] = alpha[level - 1][distance(alpha[level - 1], c) >= radius]
            beta = shell(alpha[m - 1], c, radius, b * radius)
        if len(alpha[m - 1]) == 0:
            m += 1
            if m <= n:
                beta = shell(alpha[m - 1], selected[-1], radius, b * radius)
        else:
            beta = alpha[m - 1]
    return selected


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def grid_2d(spacing: float) -> np.ndarray:
    """Points of the grid of the given spacing strictly inside (0, 10)^2."""
    ticks = np.arange(spacing, 10.0 - spacing / 2, spacing)
    return np.stack(np.meshgrid(ticks, ticks, indexing="ij"), axis=-1).reshape(-1, 2)


def assert_sidw_properties(points, selected, radius):
    """Every point strictly within R of a selected one; selected pairwise >= R apart."""
    points = np.asarray(points, dtype=np.float64)
    selected = selected.numpy()
    assert selected.dtype == np.int64
    assert len(np.unique(selected)) == len(selected)
    gap, _ = cKDTree(points[selected]).query(points)
    assert gap.max() < radius
    if len(selected) > 1:
        assert pdist(points[selected]).min() >= radius


def cube_mesh(cells: int = 4) -> TetMesh:
    """Structured mesh of [0, 1]^3, 6 tetrahedra per cube, with face node sets.

    Node sets: ``x0, x1, y0, y1, z0, z1`` (faces, sharing their edges), ``edge``
    (the 4 edges at x = 0) and ``core`` (an interior node).
    """
    ticks = np.linspace(0.0, 1.0, cells + 1)
    points = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3)
    index = np.arange(points.shape[0]).reshape((cells + 1,) * 3)
    tets = []
    for i, j, k in itertools.product(range(cells), repeat=3):
        corner = {
            bits: index[i + bits[0], j + bits[1], k + bits[2]]
            for bits in itertools.product((0, 1), repeat=3)
        }
        for order in itertools.permutations(range(3)):
            path, bits = [corner[(0, 0, 0)]], [0, 0, 0]
            for axis in order:
                bits[axis] = 1
                path.append(corner[tuple(bits)])
            tets.append(path)
    sets = {}
    for axis, name in enumerate("xyz"):
        sets[f"{name}0"] = np.flatnonzero(points[:, axis] == 0.0)
        sets[f"{name}1"] = np.flatnonzero(points[:, axis] == 1.0)
    on_x0 = points[:, 0] == 0.0
    on_rim = (points[:, 1] % 1.0 == 0.0) | (points[:, 2] % 1.0 == 0.0)
    sets["edge"] = np.flatnonzero(on_x0 & on_rim)
    sets["core"] = [index[cells // 2, cells // 2, cells // 2]]
    return TetMesh(points, np.asarray(tets), sets)


FACES = ("x0", "x1", "y0", "y1", "z0", "z1")


@pytest.fixture(scope="module")
def cube8():
    return cube_mesh(8)


# --------------------------------------------------------------------------------------
# Algorithm 1: equality with the plain reference
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("seed", range(8))
def test_equals_reference_on_random_clouds(strategy, seed):
    rng = np.random.default_rng(seed)
    dim = 1 + seed % 3
    points = rng.random((int(rng.integers(1, 300)), dim)) * rng.uniform(0.5, 5.0)
    radius, a, b = rng.uniform(0.05, 1.0), rng.uniform(0.2, 0.95), rng.uniform(1.05, 2.5)
    start = int(rng.integers(len(points)))
    expected = reference_sidw(
        points, radius, a, b, start, strategy, torch.Generator().manual_seed(seed)
    )
    got = select_control_points(
        points,
        radius,
        a=a,
        b=b,
        start=start,
        strategy=strategy,
        generator=torch.Generator().manual_seed(seed),
    )
    assert got.tolist() == expected


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("seed", range(4))
def test_equals_reference_on_grids_with_ties(strategy, seed):
    # grid points (many equal distances) and duplicated points
    rng = np.random.default_rng(100 + seed)
    points = np.round(rng.random((250, 2 + seed % 2)) * 8) / 4
    radius = [0.3, 0.5, 0.75, 1.0][seed]
    expected = reference_sidw(
        points, radius, 0.8, 1.3, seed, strategy, torch.Generator().manual_seed(seed)
    )
    got = select_control_points(
        points, radius, start=seed, strategy=strategy, generator=torch.Generator().manual_seed(seed)
    )
    assert got.tolist() == expected


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_equals_reference_on_paper_grid(strategy):
    points = grid_2d(0.2)
    expected = reference_sidw(points, 2.1, 0.8, 1.4, 1234, strategy, torch.Generator())
    got = select_control_points(
        points, 2.1, a=0.8, b=1.4, start=1234, strategy=strategy, generator=torch.Generator()
    )
    assert got.tolist() == expected


def test_equals_reference_on_disconnected_annuli():
    # two clusters far apart along x plus a ring: annuli are cut into separate arcs,
    # so the sweep has to restart inside an annulus (β = α_m)
    rng = np.random.default_rng(7)
    angle = rng.uniform(0.0, 2 * np.pi, 200)
    ring = np.stack([np.cos(angle), np.sin(angle)], axis=1) * 3.0
    clusters = np.concatenate(
        [rng.normal(size=(50, 2)) * 0.2 + [6.0, 0.0], rng.normal(size=(50, 2)) * 0.2 + [-6.0, 0.0]]
    )
    points = np.concatenate([[[0.0, 0.0]], ring, clusters])
    for strategy in STRATEGIES:
        expected = reference_sidw(points, 0.4, 0.8, 1.3, 0, strategy, torch.Generator())
        got = select_control_points(
            points, 0.4, start=0, strategy=strategy, generator=torch.Generator()
        )
        assert got.tolist() == expected


# --------------------------------------------------------------------------------------
# Algorithm 1: properties
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("dim", [2, 3])
def test_covers_and_separates_random_clouds(strategy, dim):
    rng = np.random.default_rng(dim)
    points = rng.random((3000, dim))
    radius = 0.08 if dim == 2 else 0.15
    selected = select_control_points(
        points, radius, strategy=strategy, generator=torch.Generator().manual_seed(3)
    )
    assert 10 < len(selected) < 600
    assert_sidw_properties(points, selected, radius)


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_paper_illustration(strategy):
    # Figs. 1-2 of the paper: candidates on the grid of spacing 0.2 inside (0, 10)^2
    # (49 x 49 = 2401 points), R = 2.1, a = 0.8, b = 1.4. Over seeds 0..49 we get
    # 18-22 points (median 20) with "random", 18-22 with "centroid", 16-20 with
    # "farthest"; the default generator gives 20 for each strategy.
    points = grid_2d(0.2)
    for seed in range(5):
        selected = select_control_points(
            points,
            2.1,
            a=0.8,
            b=1.4,
            strategy=strategy,
            generator=torch.Generator().manual_seed(seed),
        )
        assert 15 <= len(selected) <= 25
        assert_sidw_properties(points, selected, 2.1)
        # uniformly spread: every cell of a 3 x 3 partition of the square holds one
        cells = np.floor(points[selected.numpy()] / (10.0 / 3)).astype(int)
        assert len({tuple(cell) for cell in cells}) == 9


def test_radius_below_spacing_selects_everything():
    points = grid_2d(0.5)
    selected = select_control_points(points, 0.4, strategy="random")
    assert sorted(selected.tolist()) == list(range(len(points)))


def test_radius_above_extent_selects_only_the_start():
    points = np.random.default_rng(0).random((100, 3))
    assert select_control_points(points, 10.0, start=17).tolist() == [17]


def test_coincident_points():
    points = np.zeros((20, 3))
    assert len(select_control_points(points, 1.0)) == 1


def test_start_is_first_and_output_format():
    points = torch.rand(500, 3, generator=torch.Generator().manual_seed(0))
    selected = select_control_points(points, 0.2, start=42)
    assert selected[0] == 42
    assert selected.dtype == torch.int64
    assert selected.ndim == 1
    assert_sidw_properties(points.numpy(), selected, 0.2)


def test_accepts_numpy_float32_and_torch():
    points = np.random.default_rng(0).random((400, 2))
    from_numpy = select_control_points(points, 0.1, start=0, strategy="centroid")
    from_torch = select_control_points(torch.from_numpy(points), 0.1, start=0, strategy="centroid")
    assert from_numpy.tolist() == from_torch.tolist()
    assert_sidw_properties(points, select_control_points(points.astype(np.float32), 0.1), 0.1)


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_deterministic_given_generator(strategy):
    points = np.random.default_rng(1).random((2000, 2))

    def run(seed):
        generator = None if seed is None else torch.Generator().manual_seed(seed)
        return select_control_points(points, 0.05, strategy=strategy, generator=generator).tolist()

    assert run(5) == run(5)
    assert run(None) == run(None)  # None: a fresh generator with a fixed seed
    assert run(5) != run(6)  # different start points (and, for "random", choices)


def test_random_strategy_depends_on_generator_beyond_start():
    points = np.random.default_rng(2).random((2000, 2))
    first = select_control_points(points, 0.05, start=0, generator=torch.Generator().manual_seed(1))
    second = select_control_points(
        points, 0.05, start=0, generator=torch.Generator().manual_seed(2)
    )
    assert first.tolist() != second.tolist()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"radius": 0.0}, "radius"),
        ({"radius": -1.0}, "radius"),
        ({"radius": float("inf")}, "radius"),
        ({"radius": float("nan")}, "radius"),
        ({"a": 0.0}, "a must satisfy 0 < a < 1"),
        ({"a": 1.0}, "a must satisfy"),
        ({"b": 1.0}, "b must satisfy b > 1"),
        ({"b": float("inf")}, "b must satisfy"),
        ({"start": 100}, r"start must lie in \[0, 100\)"),
        ({"start": -1}, "start must lie"),
        ({"strategy": "nearest"}, "strategy must be one of 'random', 'centroid', 'farthest'"),
    ],
)
def test_bad_arguments(kwargs, message):
    points = np.random.default_rng(0).random((100, 3))
    arguments = {"radius": 0.1, **kwargs}
    radius = arguments.pop("radius")
    with pytest.raises(ValueError, match=message):
        select_control_points(points, radius, **arguments)


def test_wrong_kinds_of_arguments():
    points = np.random.default_rng(0).random((100, 3))
    with pytest.raises(TypeError, match="start must be an integer"):
        select_control_points(points, 0.1, start=1.5)
    with pytest.raises(TypeError, match="start must be an integer"):
        select_control_points(points, 0.1, start=True)
    with pytest.raises(TypeError, match="generator must be a torch.Generator"):
        select_control_points(points, 0.1, generator=3)


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((0, 3)), "points is empty"),
        (np.zeros(5), r"points must have shape \(N, D\)"),
        (np.zeros((4, 0)), r"points must have shape \(N, D\)"),
        (np.array([[0.0, np.nan]]), "points holds 1 NaN or infinite"),
        (np.array([["a", "b"]]), "points must hold numbers"),
    ],
)
def test_bad_points(points, message):
    with pytest.raises(ValueError, match=message):
        select_control_points(points, 0.1)


# --------------------------------------------------------------------------------------
# regions and plans
# --------------------------------------------------------------------------------------


def test_plan_on_cube_covers_each_region(cube8):
    plan = SelectionPlan(
        [Region(("x0", "x1"), 0.3), Region(("y0", "y1", "z0", "z1"), 0.5)], overlap="first"
    )
    selected = plan.select(cube8, generator=torch.Generator().manual_seed(0))
    points = cube8.points.numpy()
    assert torch.equal(selected, torch.unique(selected))
    assert set(selected.tolist()) <= set(cube8.boundary_nodes.tolist())
    for region, nodes in zip(plan.regions, plan.region_nodes(cube8), strict=True):
        mine = np.intersect1d(selected.numpy(), nodes.numpy())
        assert_sidw_properties(
            points[nodes.numpy()],
            torch.from_numpy(np.searchsorted(nodes.numpy(), mine)),
            region.radius,
        )


def test_plan_dict_shorthand_and_enrichment(cube8):
    plan = SelectionPlan(
        {
            "x0": 0.4,
            ("x1", "y0"): (0.4, 0.8),
            "y1": (0.4, 0.8, 1.3),
            "z0": {"radius": 0.4},
            "z1": 0.4,
        },
        enrich=["edge", "x1"],
    )
    assert plan.regions[1] == Region(("x1", "y0"), 0.4, 0.8, 1.3)
    selected = set(plan.select(cube8).tolist())
    assert set(cube8.node_set("edge").tolist()) <= selected
    assert set(cube8.node_set("x1").tolist()) <= selected
    # enrichment adds nodes: the plan without it selects fewer
    plain = SelectionPlan(dict.fromkeys(FACES, 0.4))
    assert len(plain.select(cube8)) < len(selected)


def test_plan_selects_like_select_control_points(cube8):
    nodes = cube8.boundary_nodes
    generator = torch.Generator().manual_seed(4)
    expected = nodes[
        select_control_points(cube8.points[nodes], 0.3, strategy="centroid", generator=generator)
    ]
    plan = SelectionPlan([Region(FACES, 0.3)], strategy="centroid")
    got = plan.select(cube8, generator=torch.Generator().manual_seed(4))
    assert got.tolist() == sorted(expected.tolist())


def test_plan_is_deterministic(cube8):
    plan = SelectionPlan(dict.fromkeys(FACES, 0.3))
    assert torch.equal(plan.select(cube8), plan.select(cube8))
    first = plan.select(cube8, generator=torch.Generator().manual_seed(1))
    again = plan.select(cube8, generator=torch.Generator().manual_seed(1))
    other = plan.select(cube8, generator=torch.Generator().manual_seed(2))
    assert torch.equal(first, again)
    assert not torch.equal(first, other)


def test_conflicting_overlap_names_both_regions(cube8):
    plan = SelectionPlan({"x0": 0.2, "y0": 0.5, "x1": 0.5, "y1": 0.5, "z0": 0.5, "z1": 0.5})
    with pytest.raises(ValueError, match="regions 'x0' .* and 'y0' .* share 9 node"):
        plan.select(cube8)


def test_overlap_first_and_share(cube8):
    regions = [Region("x0", 0.2), Region(FACES, 0.5)]
    first = SelectionPlan(regions, overlap="first").region_nodes(cube8)
    assert set(first[0].tolist()) == set(cube8.node_set("x0").tolist())
    assert not set(first[0].tolist()) & set(first[1].tolist())
    shared = SelectionPlan(regions, overlap="share").region_nodes(cube8)
    assert torch.equal(shared[1], cube8.boundary_nodes)
    selected = SelectionPlan(regions, overlap="share").select(cube8).numpy()
    points = cube8.points.numpy()
    gap_x0, _ = cKDTree(points[selected]).query(points[cube8.node_set("x0").numpy()])
    gap_all, _ = cKDTree(points[selected]).query(points[cube8.boundary_nodes.numpy()])
    assert gap_x0.max() < 0.2
    assert gap_all.max() < 0.5


def test_equal_parameters_may_overlap(cube8):
    # faces share their edges; with equal parameters a shared node goes to the first
    nodes = SelectionPlan(dict.fromkeys(FACES, 0.3)).region_nodes(cube8)
    union = np.concatenate([ids.numpy() for ids in nodes])
    assert len(union) == len(np.unique(union)) == cube8.boundary_nodes.numel()


def test_uncovered_nodes(cube8):
    with pytest.raises(ValueError, match="are in no region and no enrichment set"):
        SelectionPlan({"x0": 0.3}).select(cube8)
    selected = SelectionPlan({"x0": 0.3}, enrich=["y0"], uncovered="ignore").select(cube8)
    allowed = set(cube8.node_set("x0").tolist()) | set(cube8.node_set("y0").tolist())
    assert set(selected.tolist()) <= allowed
    # enrichment counts as covered
    SelectionPlan(dict.fromkeys(FACES[1:], 0.3), enrich=["x0"]).select(cube8)


def test_candidates_override(cube8):
    candidates = cube8.nodes_of(["x0", "core"])
    plan = SelectionPlan({"x0": 0.3}, enrich=["core"])
    selected = plan.select(cube8, candidates=candidates)
    assert set(selected.tolist()) <= set(candidates.tolist())
    assert cube8.node_set("core").item() in selected.tolist()


def test_plan_errors(cube8):
    with pytest.raises(ValueError, match="unknown marker 'wing'; known: "):
        SelectionPlan({"wing": 0.3}).select(cube8)
    with pytest.raises(ValueError, match="unknown marker 'tip'"):
        SelectionPlan(dict.fromkeys(FACES, 0.3), enrich=["tip"]).select(cube8)
    with pytest.raises(ValueError, match="region node set 'core' holds 1 node.* not boundary"):
        SelectionPlan({"core": 0.3}, uncovered="ignore").select(cube8)
    with pytest.raises(ValueError, match="enrichment node set 'core' holds 1 node"):
        SelectionPlan(dict.fromkeys(FACES, 0.3), enrich=["core"]).select(cube8)
    with pytest.raises(ValueError, match="candidates holds indices outside"):
        SelectionPlan({"x0": 0.3}).select(cube8, candidates=[10**6])
    with pytest.raises(TypeError, match="generator must be a torch.Generator"):
        SelectionPlan(dict.fromkeys(FACES, 0.3)).select(cube8, generator=1)


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Region("x0", 0.0), "radius must be a finite number > 0"),
        (lambda: Region("x0", 0.3, a=1.2), "a must satisfy 0 < a < 1"),
        (lambda: Region("x0", 0.3, b=0.9), "b must satisfy b > 1"),
        (lambda: Region((), 0.3), "nodes must name at least one node set"),
        (lambda: SelectionPlan({"x0": (0.3, 0.8, 1.3, 2)}), r"regions\['x0'\] must be radius"),
        (lambda: SelectionPlan({"x0": -1.0}), "radius must be a finite number > 0"),
        (lambda: SelectionPlan({"x0": 0.3}, strategy="best"), "strategy must be one of"),
        (lambda: SelectionPlan({"x0": 0.3}, overlap="merge"), "overlap must be one of"),
        (lambda: SelectionPlan({"x0": 0.3}, uncovered="warn"), "uncovered must be one of"),
        (lambda: SelectionPlan({"x0": 0.3}, enrich=[1]), "enrich must be a sequence"),
    ],
)
def test_region_and_plan_validation(build, message):
    with pytest.raises(ValueError, match=message):
        build()


def test_region_and_plan_types():
    with pytest.raises(TypeError, match="nodes must be a node-set name"):
        Region(3, 0.3)
    with pytest.raises(TypeError, match=r"regions\[0\] must be a Region"):
        SelectionPlan(["x0"])
    with pytest.raises(TypeError, match="regions must be a sequence of Region or a mapping"):
        SelectionPlan(0.3)
