"""POD-reduced morphing, Algorithm 3 (the paper's section 3)."""

from __future__ import annotations

import io
import math

import pytest
import torch
from torch.autograd import gradcheck

from torchmorph.idw import IDW
from torchmorph.mesh import TetMesh
from torchmorph.morph import MeshMorph
from torchmorph.pod import PODReducer, paper_matrices, pod_basis, projection_matrix
from torchmorph.selection import SelectionPlan

F64 = torch.float64
ONLINE = ("projection", "paper")


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


def box_surface(count: int, low, high, generator: torch.Generator) -> torch.Tensor:
    """``count`` random points on the surface of the box [low, high]."""
    low, high = torch.tensor(low, dtype=F64), torch.tensor(high, dtype=F64)
    points = low + (high - low) * torch.rand(count, 3, generator=generator, dtype=F64)
    axis = torch.randint(0, 3, (count,), generator=generator)
    side = torch.randint(0, 2, (count,), generator=generator).bool()
    rows = torch.arange(count)
    points[rows, axis] = torch.where(side, high[axis], low[axis])
    return points


def box_inside(count: int, low, high, generator: torch.Generator) -> torch.Tensor:
    low, high = torch.tensor(low, dtype=F64), torch.tensor(high, dtype=F64)
    return low + (high - low) * torch.rand(count, 3, generator=generator, dtype=F64)


@pytest.fixture
def cloud() -> IDW:
    """60 controls on the unit cube's surface, 90 targets inside."""
    generator = torch.Generator().manual_seed(0)
    controls = box_surface(60, (0, 0, 0), (1, 1, 1), generator)
    targets = box_inside(90, (0.05,) * 3, (0.95,) * 3, generator)
    return IDW(controls, targets)


@pytest.fixture
def rank_two(cloud):
    """d = μ1 f1 + μ2 f2 on the controls: exactly rank 2."""
    generator = torch.Generator().manual_seed(1)
    fields = torch.randn(2, cloud.num_controls, 3, generator=generator, dtype=F64)

    def family(mu: torch.Tensor) -> torch.Tensor:
        return torch.einsum("...k,kij->...ij", mu, fields)

    return family


def random_parameters(count: int, dim: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(count, dim, generator=generator, dtype=F64) * 2 - 1


# --------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("online", ONLINE)
def test_rank_two_family_is_reproduced_to_round_off(cloud, rank_two, online):
    reducer = PODReducer(online=online).fit(
        cloud, family=rank_two, parameters=random_parameters(12, 2, seed=2)
    )
    assert reducer.num_modes_ == 2
    assert reducer.modes_.shape == (2, cloud.num_targets, 3)
    assert reducer.singular_values_.shape == (12,)
    # the method of snapshots resolves σ_i down to about sqrt(eps) · σ_1 (pod_basis notes)
    assert float(reducer.singular_values_[2]) < 1e-7 * float(reducer.singular_values_[0])
    fresh = random_parameters(7, 2, seed=3)
    reduced = reducer.morph_parameters(fresh)
    full = cloud(rank_two(fresh))
    for r, f in zip(reduced, full, strict=True):
        assert relative(r, f) < 1e-10
    assert float(reducer.relative_error(rank_two(fresh)).max()) < 1e-10


def test_modes_are_orthonormal_and_energy_is_cumulative(cloud, rank_two):
    reducer = PODReducer().fit(cloud, family=rank_two, parameters=random_parameters(9, 2, 4))
    flat = reducer.modes_.reshape(reducer.num_modes_, -1)
    torch.testing.assert_close(flat @ flat.T, torch.eye(2, dtype=F64), rtol=0, atol=1e-13)
    energy = reducer.energy_captured_
    assert energy.shape == reducer.singular_values_.shape
    assert bool((energy[1:] >= energy[:-1]).all())
    assert float(energy[-1]) == pytest.approx(1.0, abs=1e-14)
    assert set(reducer.offline_time_) == {"snapshots", "svd", "online_matrices", "total"}


def test_energy_criterion_picks_the_smallest_sufficient_count():
    # four orthogonal fields of energies 1, 1e-2, 1e-4, 1e-8 (times the same coefficients)
    generator = torch.Generator().manual_seed(5)
    basis, _ = torch.linalg.qr(torch.randn(60, 4, generator=generator, dtype=F64))
    scales = torch.tensor([1.0, 1e-1, 1e-2, 1e-4], dtype=F64)
    coefficients = torch.linalg.qr(torch.randn(8, 4, generator=generator, dtype=F64))[0]
    snapshots = (coefficients * scales) @ basis.T  # singular values = scales
    snapshots = snapshots.reshape(8, 20, 3)
    energy = scales.square() / scales.square().sum()
    for tolerance, expected in ((0.5, 1), (1e-3, 2), (1e-5, 3), (1e-9, 4)):
        modes, singular_values, _ = pod_basis(snapshots, energy_tolerance=tolerance)
        assert modes.shape[0] == expected, tolerance
        assert float(energy[expected:].sum()) <= tolerance
        if expected > 1:
            assert float(energy[expected - 1 :].sum()) > tolerance
    torch.testing.assert_close(singular_values[:4], scales, rtol=1e-12, atol=0)


def test_wing_bending_needs_one_mode():
    """δy = μ z² on the controls of a thin wing-like box of span 2π."""
    generator = torch.Generator().manual_seed(6)
    low, high = (0.0, -0.06, 0.0), (1.01, 0.06, 2 * math.pi)
    controls = box_surface(200, low, high, generator)
    targets = box_inside(150, (0.02, -0.05, 0.05), (0.99, 0.05, 2 * math.pi - 0.05), generator)
    idw = IDW(controls, targets)
    z = controls[:, 2]

    def bending(mu: torch.Tensor) -> torch.Tensor:
        d = torch.zeros(*mu.shape, controls.shape[0], 3, dtype=F64)
        d[..., 1] = mu[..., None] * z.square()
        return d

    training = torch.rand(20, generator=generator, dtype=F64) * 1.3
    # W is wide here (more controls than targets): W⁺ amplifies round-off in "paper"
    # (5e-12 on one thread, 9e-11 on two with OpenBLAS on an AMD EPYC)
    for online, tolerance in (("projection", 1e-13), ("paper", 1e-9)):
        reducer = PODReducer(online=online).fit(idw, family=bending, parameters=training)
        assert reducer.num_modes_ == 1
        mu = torch.tensor([0.01, 0.7, 1.3], dtype=F64)
        assert float(reducer.relative_error(bending(mu)).max()) < tolerance


def rotation_setup():
    """A hull-like box rotating about z inside a fixed outer box (case C in small)."""
    generator = torch.Generator().manual_seed(7)
    hull = box_surface(80, (-1.25, -0.2, -0.3), (1.25, 0.2, 0.3), generator)
    walls = box_surface(80, (-5, -3, -1), (5, 3, 1), generator)
    controls = torch.cat([hull, walls])
    targets = box_inside(200, (-4.9, -2.9, -0.9), (4.9, 2.9, 0.9), generator)
    outside = (
        (targets[:, 0].abs() > 1.3) | (targets[:, 1].abs() > 0.25) | (targets[:, 2].abs() > 0.35)
    )
    idw = IDW(controls, targets[outside])

    def rotation(mu: torch.Tensor) -> torch.Tensor:
        cos, sin = torch.cos(mu)[..., None], torch.sin(mu)[..., None]
        x, y = hull[:, 0], hull[:, 1]
        moved = torch.stack(
            [(cos - 1) * x - sin * y, sin * x + (cos - 1) * y, torch.zeros_like(cos * x)], -1
        )
        fixed = torch.zeros(*mu.shape, walls.shape[0], 3, dtype=F64)
        return torch.cat([moved, fixed], -2)

    return idw, rotation


def test_rotation_needs_two_modes():
    idw, rotation = rotation_setup()
    generator = torch.Generator().manual_seed(8)
    angles = -math.radians(36) * torch.rand(50, generator=generator, dtype=F64)
    fresh = -math.radians(36) * torch.rand(20, generator=generator, dtype=F64)
    automatic = PODReducer().fit(idw, family=rotation, parameters=angles)
    assert automatic.num_modes_ == 2
    for online in ONLINE:
        two = PODReducer(num_modes=2, online=online).fit(idw, family=rotation, parameters=angles)
        assert float(two.relative_error(rotation(fresh)).max()) < 1e-8
        one = PODReducer(num_modes=1, online=online).fit(idw, family=rotation, parameters=angles)
        assert float(one.relative_error(rotation(fresh)).max()) > 1e-3


def test_projection_is_never_less_accurate_than_paper(cloud):
    generator = torch.Generator().manual_seed(9)
    fields = torch.randn(5, cloud.num_controls, 3, generator=generator, dtype=F64)

    def family(mu):
        return torch.einsum("...k,kij->...ij", mu, fields)

    training, fresh = random_parameters(30, 5, seed=10), random_parameters(40, 5, seed=11)
    for modes in (1, 2, 3, 4):
        errors = {}
        for online in ONLINE:
            reducer = PODReducer(num_modes=modes, online=online)
            reducer.fit(cloud, family=family, parameters=training)
            errors[online] = reducer.relative_error(family(fresh))
        assert bool((errors["projection"] <= errors["paper"] + 1e-12).all()), modes
        assert float(errors["projection"].mean()) < float(errors["paper"].mean())


@pytest.mark.parametrize("count", [2, 5])  # mat-vec and GEMM paths of projection_matrix
def test_functional_matrices_match_dense_kronecker_formulas(cloud, count):
    """P = Zᵀ(W⊗I), A = Zᵀ(W⁺⊗I)ᵀ(W⁺⊗I)Z, B = Zᵀ(W⁺⊗I)ᵀ with the flattened layout."""
    generator = torch.Generator().manual_seed(12)
    modes = torch.linalg.qr(
        torch.randn(3 * cloud.num_targets, count, generator=generator, dtype=F64)
    )[0]
    modes = modes.T.reshape(count, cloud.num_targets, 3)
    weights = cloud.weights_matrix().contiguous()
    z = modes.reshape(count, -1).T  # (3 N_int, N), component-interleaved rows
    big = torch.kron(weights, torch.eye(3, dtype=F64))
    big_pinv = torch.linalg.pinv(big)
    projection = projection_matrix(modes, weights)
    torch.testing.assert_close(projection.reshape(count, -1), z.T @ big, rtol=1e-12, atol=1e-13)
    system, rhs = paper_matrices(modes, weights)
    torch.testing.assert_close(rhs.reshape(count, -1), z.T @ big_pinv.T, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(system, z.T @ big_pinv.T @ big_pinv @ z, rtol=1e-9, atol=1e-10)


# --------------------------------------------------------------------------- online phase


@pytest.mark.parametrize("online", ONLINE)
def test_batched_equals_looped(cloud, rank_two, online):
    reducer = PODReducer(num_modes=2, online=online)
    reducer.fit(cloud, family=rank_two, parameters=random_parameters(6, 2, 13))
    mu = random_parameters(5, 2, 14)
    batch = reducer(rank_two(mu))
    looped = torch.stack([reducer(rank_two(m)) for m in mu])
    torch.testing.assert_close(batch, looped, rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(reducer.morph_parameters(mu), batch, rtol=0, atol=0)
    torch.testing.assert_close(reducer.morph_parameters(mu[2]), batch[2], rtol=1e-13, atol=1e-15)
    beta = reducer.coefficients(rank_two(mu))
    assert beta.shape == (5, 2)
    torch.testing.assert_close(reducer.coefficients(rank_two(mu[0])), beta[0])


@pytest.mark.parametrize("online", ONLINE)
def test_out_argument_writes_the_same_values(cloud, rank_two, cube, online):
    reducer = PODReducer(online=online).fit(
        cloud, family=rank_two, parameters=random_parameters(6, 2, 40)
    )
    d = rank_two(random_parameters(3, 2, 41))
    out = torch.empty(3, cloud.num_targets, 3, dtype=F64)
    result = reducer(d, out=out)
    assert result.data_ptr() == out.data_ptr()
    torch.testing.assert_close(out, reducer(d), rtol=0, atol=0)
    single = torch.empty(cloud.num_targets, 3, dtype=F64)
    torch.testing.assert_close(reducer(d[1], out=single), reducer(d[1]), rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"out must have shape \(3, 90, 3\)"):
        reducer(d, out=single)
    with pytest.raises(ValueError, match="out has dtype torch.float32"):
        reducer(d, out=out.float())
    with pytest.raises(ValueError, match="out must be contiguous"):
        reducer(d, out=torch.empty(3, 3, cloud.num_targets, dtype=F64).transpose(1, 2))
    with pytest.raises(ValueError, match="out= does not support autograd"):
        reducer(d.clone().requires_grad_(), out=out)
    morph = MeshMorph(cube)
    family = bumps(morph)
    mesh_reducer = PODReducer(online=online).fit(
        morph, family=family, parameters=random_parameters(5, 2, 42)
    )
    boundary = family(random_parameters(2, 2, 43))
    full = torch.full((2, cube.num_nodes, 3), float("nan"), dtype=F64)
    torch.testing.assert_close(
        mesh_reducer(boundary, out=full), mesh_reducer(boundary), rtol=0, atol=0
    )


def test_family_called_per_value_when_not_batched(cloud, rank_two):
    calls = []

    def one_at_a_time(mu):  # only understands a single parameter vector (2,)
        calls.append(tuple(mu.shape))
        if mu.ndim != 1:
            raise RuntimeError("one value at a time")
        return rank_two(mu)

    training = random_parameters(5, 2, 15)
    # a family failing on the batch fails the fit: no silent retry value by value
    with pytest.raises(RuntimeError, match="one value at a time"):
        PODReducer().fit(cloud, family=one_at_a_time, parameters=training)
    assert calls == [(5, 2)]
    calls.clear()
    reducer = PODReducer().fit(cloud, family=one_at_a_time, parameters=training, batched=False)
    assert calls == [(2,)] * 5
    mu = random_parameters(3, 2, 16)
    torch.testing.assert_close(
        reducer.morph_parameters(mu), cloud(rank_two(mu)), rtol=1e-10, atol=1e-14
    )
    with pytest.raises(RuntimeError, match="one value at a time"):
        PODReducer().fit(cloud, family=one_at_a_time, parameters=training, batched=True)
    with pytest.raises(ValueError, match="batched must be True or False, got None"):
        PODReducer().fit(cloud, family=rank_two, parameters=training, batched=None)
    with pytest.raises(ValueError, match="pass batched=False"):
        PODReducer().fit(cloud, family=lambda mu: rank_two(mu)[0], parameters=training)


def test_fit_from_displacements_equals_fit_from_family(cloud, rank_two):
    training = random_parameters(8, 2, 17)
    a = PODReducer().fit(cloud, rank_two(training))
    b = PODReducer().fit(cloud, family=rank_two, parameters=training)
    d = rank_two(random_parameters(3, 2, 18))
    torch.testing.assert_close(a(d), b(d), rtol=1e-12, atol=1e-14)
    with pytest.raises(RuntimeError, match="no displacement family"):
        a.morph_parameters(torch.zeros(2, dtype=F64))
    torch.testing.assert_close(
        a.morph_parameters(torch.zeros(1, 2, dtype=F64), family=rank_two),
        torch.zeros(1, cloud.num_targets, 3, dtype=F64),
    )


@pytest.mark.parametrize("online", ONLINE)
def test_gradcheck_online_phase(online):
    generator = torch.Generator().manual_seed(19)
    small = IDW(
        box_surface(12, (0, 0, 0), (1, 1, 1), generator),
        box_inside(15, (0.1,) * 3, (0.9,) * 3, generator),
    )
    fields = torch.randn(2, 12, 3, generator=generator, dtype=F64)

    def rank_two(mu):
        return torch.einsum("...k,kij->...ij", mu, fields)

    reducer = PODReducer(num_modes=2, online=online)
    reducer.fit(small, family=rank_two, parameters=random_parameters(6, 2, 19))
    d = rank_two(random_parameters(2, 2, 20)).requires_grad_()
    assert gradcheck(reducer, (d,))
    mu = random_parameters(3, 2, 21).requires_grad_()
    assert gradcheck(reducer.morph_parameters, (mu,))
    (grad,) = torch.autograd.grad(reducer.morph_parameters(mu).square().sum(), mu)
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().max()) > 0


def test_float32(cloud, rank_two):
    idw32 = IDW(cloud.controls.float(), cloud.targets.float())
    training = random_parameters(10, 2, 22)
    reducer = PODReducer().fit(idw32, family=rank_two, parameters=training)  # cast to float32
    assert reducer.num_modes_ == 2 and reducer.modes_.dtype == torch.float32
    fresh = rank_two(random_parameters(4, 2, 23)).float()
    assert float(reducer.relative_error(fresh).max()) < 1e-5
    with pytest.raises(ValueError, match="dtype"):
        reducer(fresh.double())


# --------------------------------------------------------------------------- state


@pytest.mark.parametrize("online", ONLINE)
def test_state_dict_round_trip_into_a_fresh_reducer(cloud, rank_two, online):
    reducer = PODReducer(online=online, energy_tolerance=1e-7)
    reducer.fit(cloud, family=rank_two, parameters=random_parameters(6, 2, 24))
    buffer = io.BytesIO()
    torch.save(reducer.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer)
    # the hyper-parameters must match (one load rule for every module), the fit is taken
    with pytest.raises(
        ValueError,
        match="energy_tolerance: the state was saved with energy_tolerance=1e-07 but this PODReducer has energy_tolerance=1e-05",
    ):
        PODReducer(online=online).load_state_dict(state)
    fresh = PODReducer(online=online, energy_tolerance=1e-7)
    fresh.load_state_dict(state)
    assert fresh.is_fitted and fresh.online == online and fresh.energy_tolerance == 1e-7
    assert fresh.num_modes_ == reducer.num_modes_ and fresh.modes_.dtype == F64
    assert fresh.offline_time_ == reducer.offline_time_
    torch.testing.assert_close(fresh.singular_values_, reducer.singular_values_, rtol=0, atol=0)
    d = rank_two(random_parameters(3, 2, 25))
    torch.testing.assert_close(fresh(d), reducer(d), rtol=0, atol=0)
    # the morph and the family are not part of the state
    with pytest.raises(RuntimeError, match="no full morph"):
        fresh.relative_error(d)
    torch.testing.assert_close(
        fresh.relative_error(d, morph=cloud), reducer.relative_error(d), rtol=0, atol=0
    )
    # refitting changes shapes; loading back restores them
    reducer.fit(cloud, family=rank_two, parameters=random_parameters(6, 2, 26), batched=True)
    other = PODReducer(online=online, energy_tolerance=1e-7).fit(
        cloud, family=rank_two, parameters=random_parameters(4, 2, 27)
    )
    other.load_state_dict(fresh.state_dict())
    half = other
    torch.testing.assert_close(half(d), fresh(d), rtol=0, atol=0)


def test_to_moves_buffers(cloud, rank_two):
    reducer = PODReducer().fit(cloud, family=rank_two, parameters=random_parameters(6, 2, 28))
    d = rank_two(random_parameters(2, 2, 29))
    expected = reducer(d)
    reducer.to(torch.float32)
    assert reducer.modes_.dtype == torch.float32 and reducer.projection_.dtype == torch.float32
    assert reducer.reduced_rows_.dtype == torch.int64
    torch.testing.assert_close(reducer(d.float()), expected.float(), rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- MeshMorph


def bumps(mesh_morph: MeshMorph):
    """Top face bent by two smooth bumps: μ1 sin(πx) sin(πy) + μ2 sin(2πx) sin(πy)."""

    def family(mu: torch.Tensor) -> torch.Tensor:
        def top(points):
            x, y = points[:, 0], points[:, 1]
            shapes = torch.stack(
                [
                    torch.sin(torch.pi * x) * torch.sin(torch.pi * y),
                    torch.sin(2 * torch.pi * x) * torch.sin(torch.pi * y),
                ]
            )
            bump = 0.1 * torch.einsum("...k,kn->...n", mu, shapes)
            return torch.stack([0.3 * bump, torch.zeros_like(bump), bump], -1)

        return mesh_morph.boundary_displacement("z1", top)

    return family


@pytest.mark.parametrize("online", ONLINE)
@pytest.mark.parametrize("selective", [False, True])
def test_mesh_morph_boundary_exact_interior_round_off(cube, online, selective):
    plan = (
        SelectionPlan(dict.fromkeys(("x0", "x1", "y0", "y1", "z0", "z1"), 0.6), enrich=["z1"])
        if selective
        else None
    )
    morph = MeshMorph(cube, plan, generator=torch.Generator().manual_seed(30))
    family = bumps(morph)
    reducer = PODReducer(online=online).fit(
        morph, family=family, parameters=random_parameters(8, 2, 31)
    )
    assert torch.equal(reducer.copied_output_rows_, cube.boundary_nodes)
    assert torch.equal(reducer.reduced_rows_, cube.interior_nodes) and reducer.num_modes_ == 2
    assert reducer.modes_.shape == (2, cube.interior_nodes.numel(), 3)
    mu = random_parameters(4, 2, 32)
    boundary = family(mu)
    reduced, full = reducer(boundary), morph(boundary)
    assert reduced.shape == (4, cube.num_nodes, 3)
    assert torch.equal(reduced[:, cube.boundary_nodes], boundary)
    interior = cube.interior_nodes
    for r, f in zip(reduced[:, interior], full[:, interior], strict=True):
        assert relative(r, f) < 1e-10
    assert float(reducer.relative_error(boundary).max()) < 1e-10
    assert float(reducer.relative_error(boundary, norm="mass").max()) < 1e-10
    torch.testing.assert_close(reducer.morph_parameters(mu[1]), reduced[1], rtol=1e-13, atol=0)


def test_mesh_morph_gradcheck_and_state(cube):
    morph = MeshMorph(cube)
    family = bumps(morph)
    reducer = PODReducer().fit(morph, family=family, parameters=random_parameters(5, 2, 33))
    boundary = family(random_parameters(2, 2, 34)).requires_grad_()
    assert gradcheck(reducer, (boundary,), fast_mode=True)
    fresh = PODReducer()
    fresh.load_state_dict(reducer.state_dict())
    torch.testing.assert_close(fresh(boundary), reducer(boundary), rtol=0, atol=0)
    torch.testing.assert_close(fresh(boundary)[:, cube.boundary_nodes], boundary, rtol=0, atol=0)


def boundary_first(mesh: TetMesh) -> TetMesh:
    """The same mesh with its boundary nodes numbered first (as gmsh does)."""
    order = torch.cat([mesh.boundary_nodes, mesh.interior_nodes])
    new_id = torch.empty_like(order)
    new_id[order] = torch.arange(order.numel())
    sets = {name: new_id[nodes].sort().values for name, nodes in mesh.node_sets.items()}
    return TetMesh(mesh.points[order], new_id[mesh.tets], sets)


@pytest.mark.parametrize("online", ONLINE)
def test_mesh_numbered_boundary_first_uses_slices_and_matches(cube, online):
    mesh = boundary_first(cube)
    morph = MeshMorph(mesh)
    family = bumps(morph)
    reducer = PODReducer(online=online).fit(
        morph, family=family, parameters=random_parameters(6, 2, 44)
    )
    assert reducer._runs is not None
    boundary = family(random_parameters(3, 2, 45))
    by_slices = reducer(boundary)
    assert torch.equal(by_slices[:, mesh.boundary_nodes], boundary)
    assert relative(by_slices, morph(boundary)) < 1e-10
    with torch.enable_grad():
        differentiable = reducer(boundary.clone().requires_grad_())  # the indexed path
    assert differentiable.requires_grad
    torch.testing.assert_close(differentiable.detach(), by_slices, rtol=1e-14, atol=1e-16)
    out = torch.full_like(by_slices, float("nan"))
    torch.testing.assert_close(reducer(boundary, out=out), by_slices, rtol=0, atol=0)
    fresh = PODReducer(online=online)
    fresh.load_state_dict(reducer.state_dict())
    assert fresh._runs == reducer._runs
    torch.testing.assert_close(fresh(boundary), by_slices, rtol=0, atol=0)


def test_matrix_free_idw_gives_the_same_projection(cloud, rank_two):
    matrix_free = IDW(cloud.controls, cloud.targets, mode="matrix_free")
    training = random_parameters(6, 2, 35)
    dense = PODReducer().fit(cloud, family=rank_two, parameters=training)
    free = PODReducer().fit(matrix_free, family=rank_two, parameters=training)
    torch.testing.assert_close(free.projection_, dense.projection_, rtol=1e-10, atol=1e-14)


# --------------------------------------------------------------------------- errors


def test_unfitted_reducer_raises(cloud):
    reducer = PODReducer()
    d = torch.zeros(cloud.num_controls, 3, dtype=F64)
    for call in (
        lambda: reducer(d),
        lambda: reducer.coefficients(d),
        lambda: reducer.relative_error(d),
        lambda: reducer.morph_parameters(0.1),
        lambda: reducer.num_inputs,
    ):
        with pytest.raises(RuntimeError, match="not fitted"):
            call()


@pytest.mark.parametrize("value", [0.0, 1.0, -1e-3, 2.0, float("nan"), "small"])
def test_energy_tolerance_outside_unit_interval(value):
    with pytest.raises(ValueError, match="energy_tolerance"):
        PODReducer(energy_tolerance=value)


@pytest.mark.parametrize("value", [0, -1, 2.5, True])
def test_bad_num_modes(value):
    with pytest.raises(ValueError, match="num_modes must be a positive integer"):
        PODReducer(num_modes=value)


def test_unknown_online_variant():
    with pytest.raises(ValueError, match="online must be one of 'projection', 'paper'"):
        PODReducer(online="galerkin")


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_training_data_with_nan_or_inf(cloud, rank_two, bad):
    training = rank_two(random_parameters(4, 2, 36))
    training[1, 3, 0] = bad
    with pytest.raises(ValueError, match="displacements holds 1 NaN or infinite"):
        PODReducer().fit(cloud, training)
    with pytest.raises(ValueError, match=r"family\(parameters\) holds 1 NaN or infinite"):
        PODReducer().fit(cloud, family=lambda mu: training, parameters=torch.zeros(4))
    with pytest.raises(ValueError, match="parameters holds 1 NaN or infinite"):
        PODReducer().fit(cloud, family=rank_two, parameters=torch.tensor([[0.0, bad]]))


def test_more_modes_than_snapshots_or_rank(cloud, rank_two):
    with pytest.raises(ValueError, match=r"num_modes=5 exceeds the number of snapshots \(4\)"):
        PODReducer(num_modes=5).fit(cloud, family=rank_two, parameters=random_parameters(4, 2, 37))
    with pytest.raises(ValueError, match="num_modes=3 exceeds the numerical rank 2"):
        PODReducer(num_modes=3).fit(cloud, family=rank_two, parameters=random_parameters(6, 2, 38))
    with pytest.raises(ValueError, match="all zero"):
        PODReducer().fit(cloud, torch.zeros(3, cloud.num_controls, 3, dtype=F64))


def test_wrong_shapes_and_arguments(cloud, rank_two):
    n = cloud.num_controls
    with pytest.raises(ValueError, match=r"displacements must have shape \(n_train, N_in, D\)"):
        PODReducer().fit(cloud, torch.zeros(n, 3, dtype=F64))
    # the morph checks its own input rows
    with pytest.raises(ValueError, match=rf"displacements must have shape \({n}, 3\) or"):
        PODReducer().fit(cloud, torch.zeros(2, n + 1, 3, dtype=F64))
    with pytest.raises(ValueError, match="no training data"):
        PODReducer().fit(cloud)
    with pytest.raises(ValueError, match="not both"):
        PODReducer().fit(
            cloud,
            rank_two(torch.ones(2, 2, dtype=F64)),
            family=rank_two,
            parameters=torch.ones(2, 2, dtype=F64),
        )
    with pytest.raises(ValueError, match="parameters given without family"):
        PODReducer().fit(cloud, parameters=torch.ones(3))
    with pytest.raises(ValueError, match="parameters must be given with family"):
        PODReducer().fit(cloud, family=rank_two)
    with pytest.raises(ValueError, match=r"parameters must have shape \(n_train,\)"):
        PODReducer().fit(cloud, family=rank_two, parameters=torch.ones(2, 2, 2))
    with pytest.raises(ValueError, match="family must be callable"):
        PODReducer().fit(cloud, family="bend", parameters=torch.ones(2))
    with pytest.raises(ValueError, match=r"family\(mu\) must return a tensor of shape"):
        PODReducer().fit(
            cloud, family=lambda mu: torch.zeros(3), parameters=torch.ones(2), batched=False
        )
    with pytest.raises(ValueError, match="when batched=True"):
        PODReducer().fit(
            cloud, family=lambda mu: torch.zeros(n, 3), parameters=torch.ones(2), batched=True
        )
    with pytest.raises(TypeError, match="morph must be a callable linear map, got str"):
        PODReducer().fit("idw", rank_two(torch.ones(2, 2, dtype=F64)))

    reducer = PODReducer().fit(cloud, family=rank_two, parameters=random_parameters(4, 2, 39))
    with pytest.raises(
        ValueError,
        match=rf"displacement must have shape \({n}, 3\) or "
        rf"\(B, {n}, 3\) for the {n} input rows of the fitted morph",
    ):
        reducer(torch.zeros(n - 1, 3, dtype=F64))
    with pytest.raises(ValueError, match="displacement must have shape"):
        reducer(torch.zeros(1, 1, n, 3, dtype=F64))
    with pytest.raises(TypeError, match="displacement must be a torch.Tensor"):
        reducer([[0.0, 0.0, 0.0]] * n)
    with pytest.raises(ValueError, match=r"mu must have shape \(2,\) or \(B, 2\)"):
        reducer.morph_parameters(torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="norm must be one of 'nodal', 'mass'"):
        reducer.relative_error(rank_two(torch.ones(2, dtype=F64)), norm="energy")
    with pytest.raises(ValueError, match=r"norm='mass' needs mesh= \(the mass matrix lives"):
        reducer.relative_error(rank_two(torch.ones(2, dtype=F64)), norm="mass")


# ------------------------------------------------------------------ POD basis: method and scale


def graded_snapshots(count: int, length: int, decay: float, seed: int = 11) -> torch.Tensor:
    """``count`` snapshots of ``length`` points with singular values decay**i."""
    generator = torch.Generator().manual_seed(seed)
    left, _ = torch.linalg.qr(torch.randn(3 * length, count, generator=generator, dtype=F64))
    right, _ = torch.linalg.qr(torch.randn(count, count, generator=generator, dtype=F64))
    values = decay ** torch.arange(count, dtype=F64)
    return ((right * values) @ left.T).reshape(count, length, 3), values


def span_distance(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spectral distance between the projectors onto the spans of two mode sets."""
    qa, qb = a.flatten(1).T, b.flatten(1).T
    return float(torch.linalg.matrix_norm(qa @ qa.T - qb @ qb.T, ord=2))


@pytest.mark.parametrize("decay", [0.5, 0.2])
def test_correlation_route_matches_the_thin_svd(decay):
    snapshots, values = graded_snapshots(12, 150, decay)
    for tolerance in (1e-2, 1e-5):
        svd = pod_basis(snapshots, energy_tolerance=tolerance, method="svd")
        fast = pod_basis(snapshots, energy_tolerance=tolerance, method="correlation")
        assert fast[0].shape == svd[0].shape
        assert span_distance(fast[0], svd[0]) < 1e-10
        gram = fast[0].flatten(1) @ fast[0].flatten(1).T
        torch.testing.assert_close(gram, torch.eye(gram.shape[0], dtype=F64), atol=1e-14, rtol=0)
        kept = fast[0].shape[0]
        # σ_i from the correlation matrix: accurate to about eps · σ_1² / σ_i
        torch.testing.assert_close(fast[1][:kept], values[:kept], rtol=1e-11, atol=0)
        torch.testing.assert_close(fast[1], values, rtol=0, atol=1e-7 * float(values[0]))
        torch.testing.assert_close(fast[2], svd[2], rtol=1e-12, atol=1e-14)


def test_correlation_route_falls_back_to_the_svd_when_it_would_lose_the_modes(monkeypatch):
    # the kept modes' singular values span 1 ... 1e-6: the correlation matrix cannot
    # resolve them (eps * 1 / 1e-12 >> 1e-10)
    snapshots, values = graded_snapshots(8, 200, 0.1)
    calls = []
    original = torch.linalg.svd

    def counting_svd(matrix, *args, **kwargs):
        calls.append(tuple(matrix.shape))
        return original(matrix, *args, **kwargs)

    monkeypatch.setattr(torch.linalg, "svd", counting_svd)
    modes, singular_values, _ = pod_basis(snapshots, num_modes=7, method="correlation")
    assert (8, 600) in calls  # the thin SVD of the whole matrix ran
    reference = pod_basis(snapshots, num_modes=7, method="svd")[0]
    assert span_distance(modes, reference) < 1e-12
    torch.testing.assert_close(singular_values, values, rtol=1e-9, atol=0)


@pytest.mark.parametrize("scale", [1e-300, 1e-170, 1e155, 1e300])
@pytest.mark.parametrize("method", ["svd", "correlation"])
def test_extreme_scales_keep_the_modes_and_energies(scale, method):
    snapshots, values = graded_snapshots(6, 100, 0.1)
    modes, singular_values, energy = pod_basis(
        snapshots * scale, energy_tolerance=1e-5, method=method
    )
    reference = pod_basis(snapshots, energy_tolerance=1e-5, method="svd")
    assert modes.shape == reference[0].shape == (3, 100, 3)
    assert span_distance(modes, reference[0]) < 1e-9
    torch.testing.assert_close(singular_values[:3], values[:3] * scale, rtol=1e-10, atol=0)
    assert torch.isfinite(energy).all()
    torch.testing.assert_close(energy, reference[2], rtol=1e-10, atol=1e-12)


def test_pod_basis_rejects_half_precision_and_unknown_method():
    snapshots, _ = graded_snapshots(4, 10, 0.5)
    for dtype in (torch.float16, torch.bfloat16):
        with pytest.raises(ValueError, match=r"snapshots has dtype torch\.(b)?float16: half"):
            pod_basis(snapshots.to(dtype))
    with pytest.raises(ValueError, match="method must be one of 'auto', 'svd', 'correlation'"):
        pod_basis(snapshots, method="qr")


# ------------------------------------------------------------------ any linear map


class DenseMap(torch.nn.Module):
    """A user's linear map: output = A @ input per component, plus two copied rows."""

    def __init__(self, matrix: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("matrix", matrix)

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        interior = torch.einsum("ij,bjc->bic", self.matrix, d)
        return torch.cat([d[:, :2], interior], 1)  # rows 0, 1 copy inputs 0, 1

    def copied_rows(self):
        return torch.tensor([0, 1]), torch.tensor([0, 1])


def test_any_linear_map_without_type_dispatch(rank_two, cloud):
    generator = torch.Generator().manual_seed(50)
    matrix = torch.rand(40, cloud.num_controls, generator=generator, dtype=F64)
    user = DenseMap(matrix)
    training = random_parameters(6, 2, 51)
    reducer = PODReducer().fit(user, family=rank_two, parameters=training)
    assert reducer.num_inputs == cloud.num_controls and reducer.num_outputs == 42
    assert reducer.reduced_rows_.tolist() == list(range(2, 42))
    d = rank_two(random_parameters(3, 2, 52))
    reduced, full = reducer(d), user(d)
    assert torch.equal(reduced[:, :2], d[:, :2])  # copied rows exact
    assert relative(reduced, full) < 1e-12
    # P = Zᵀ A by autograd equals the closed form
    expected = torch.einsum("lic,ij->ljc", reducer.modes_, matrix)
    torch.testing.assert_close(reducer.projection_, expected, rtol=1e-12, atol=1e-14)
    # a plain function (no module, no optional methods) works too
    plain = PODReducer().fit(
        lambda x: torch.einsum("ij,bjc->bic", matrix, x), family=rank_two, parameters=training
    )
    assert plain.copied_output_rows_.numel() == 0 and plain.num_outputs == 40
    assert relative(plain(d), full[:, 2:]) < 1e-12
    with pytest.raises(ValueError, match=r"online='paper' needs the morph's matrix W"):
        PODReducer(online="paper").fit(user, family=rank_two, parameters=training)


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_mesh_morph_adjoint_is_the_transpose(cube, mode):
    morph = MeshMorph(
        cube,
        SelectionPlan(dict.fromkeys(FACES_OF_CUBE, 0.6)),
        mode=mode,
        generator=torch.Generator().manual_seed(53),
    )
    generator = torch.Generator().manual_seed(54)
    d = torch.randn(2, morph.num_boundary, 3, generator=generator, dtype=F64)
    g = torch.randn(2, morph.num_nodes, 3, generator=generator, dtype=F64)
    left = (morph(d) * g).sum((1, 2))
    right = (d * morph.adjoint(g)).sum((1, 2))
    torch.testing.assert_close(left, right, rtol=1e-12, atol=1e-12)
    # a batch and a single field sum in other orders (BLAS kernels): equal to round-off
    torch.testing.assert_close(morph.adjoint(g[0]), morph.adjoint(g)[0], rtol=1e-13, atol=1e-15)


FACES_OF_CUBE = ("x0", "x1", "y0", "y1", "z0", "z1")


def saved_state(module: torch.nn.Module) -> dict:
    buffer = io.BytesIO()
    torch.save(module.state_dict(), buffer)
    buffer.seek(0)
    return torch.load(buffer)


@pytest.mark.parametrize("online", ONLINE)
def test_mesh_reducer_round_trips_into_a_reducer_of_another_size(cube, online):
    from conftest import structured_cube

    morph = MeshMorph(cube)
    reducer = PODReducer(online=online).fit(
        morph, family=bumps(morph), parameters=random_parameters(6, 2, 55)
    )
    small = MeshMorph(structured_cube(2))
    other = PODReducer(online=online).fit(
        small, family=bumps(small), parameters=random_parameters(4, 2, 56)
    )
    other.load_state_dict(saved_state(reducer))
    assert other.online == online and other.num_modes is None
    for name in (*PODReducer._FLOAT_BUFFERS, *PODReducer._INDEX_BUFFERS):
        assert torch.equal(getattr(other, name), getattr(reducer, name)), name
    boundary = bumps(morph)(random_parameters(3, 2, 57))
    assert torch.equal(other(boundary), reducer(boundary))


@pytest.mark.parametrize(
    ("key", "change", "message"),
    [
        (
            "modes_",
            lambda v: v[:, 1:],
            r"'modes_'\]: has shape \(2, 26, 3\), expected \(2, 27, 3\)",
        ),
        ("projection_", lambda v: v[:1], r"'projection_'\]: has shape"),
        ("reduced_rows_", lambda v: v + 1000, r"'reduced_rows_'\]: holds rows outside \[0, 125\)"),
        ("reduced_rows_", lambda v: v[:-1], r"reduced_rows_ and copied_output_rows_ must split"),
        ("copied_input_rows_", lambda v: v[1:], r"must have the length of copied_output_rows_"),
        ("singular_values_", lambda v: v[:1], r"'singular_values_'\]: must be 1-D with at least 2"),
        (
            "_extra_state",
            lambda v: {**v, "num_modes_": 3},
            r"'modes_'\]: has shape \(2, 27, 3\), expected \(3, 27, 3\)",
        ),
        ("_extra_state", lambda v: {**v, "num_outputs_": 0}, r"num_outputs_ must be a positive"),
        (
            "_extra_state",
            lambda v: {**v, "online": "fast"},
            r"online must be one of 'projection', 'paper'",
        ),
        ("_extra_state", lambda v: {**v, "version": 1}, r"version 1 is not 2"),
    ],
)
def test_a_tampered_reducer_state_fails_to_load(cube, key, change, message):
    morph = MeshMorph(cube)
    reducer = PODReducer().fit(morph, family=bumps(morph), parameters=random_parameters(6, 2, 58))
    state = saved_state(reducer)
    state[key] = change(state[key])
    fresh = PODReducer()
    with pytest.raises(ValueError, match=message):
        fresh.load_state_dict(state)
    assert not fresh.is_fitted and fresh.modes_.numel() == 0


# ------------------------------------------------------------------ fields of 2-D meshes


def square_cloud(seed: int = 60) -> tuple[torch.Tensor, torch.Tensor]:
    """40 controls on the unit square's sides, 70 targets inside (2-D points)."""
    generator = torch.Generator().manual_seed(seed)
    along = torch.rand(40, generator=generator, dtype=F64)
    side = torch.arange(40) % 4
    x = torch.where(
        side == 0, along, torch.where(side == 1, 1.0, torch.where(side == 2, along, 0.0))
    )
    y = torch.where(side == 0, 0.0, torch.where(side == 2, 1.0, along))
    targets = 0.05 + 0.9 * torch.rand(70, 2, generator=generator, dtype=F64)
    return torch.stack([x, y], 1), targets


class PlanarMorph(torch.nn.Module):
    """A 2-D mesh morph by the protocol: the 40 boundary rows copy the inputs, the 70
    interior rows are W d of the 14 controls every third boundary row (W of IDW)."""

    def __init__(self) -> None:
        from torchmorph.idw import idw_weights

        super().__init__()
        boundary, interior = square_cloud()
        self.register_buffer("selected", torch.arange(0, 40, 3))
        self.register_buffer(
            "weights", idw_weights(controls=boundary[self.selected], targets=interior)
        )

    @property
    def weight_columns(self) -> torch.Tensor:
        return self.selected

    def weights_matrix(self) -> torch.Tensor:
        return self.weights

    def copied_rows(self):
        return torch.arange(40), torch.arange(40)

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        interior = torch.einsum("ij,bjc->bic", self.weights, d[:, self.selected])
        return torch.cat([d, interior], 1)


def planar_family(mu: torch.Tensor) -> torch.Tensor:
    """Boundary displacements of 2-D points, linear in two parameters (rank 2)."""
    boundary, _ = square_cloud()
    bend = torch.stack([torch.zeros(40, dtype=F64), boundary[:, 0].square()], 1)
    stretch = torch.stack([boundary[:, 0] - 0.5, torch.zeros(40, dtype=F64)], 1)
    return mu[..., 0, None, None] * bend + mu[..., 1, None, None] * stretch


@pytest.mark.parametrize("online", ONLINE)
def test_planar_morph_reduced_exactly_with_two_components(online):
    morph = PlanarMorph()
    reducer = PODReducer(online=online).fit(
        morph, family=planar_family, parameters=random_parameters(6, 2, 61)
    )
    assert reducer.dim == 2 and reducer.num_modes_ == 2
    assert reducer.modes_.shape == (2, 70, 2) and reducer.num_outputs == 110
    mu = random_parameters(4, 2, 62)
    d = planar_family(mu)
    reduced, full = reducer(d), morph(d)
    assert reduced.shape == (4, 110, 2)
    assert torch.equal(reduced[:, :40], d)  # the boundary rows are copied, exactly
    assert relative(reduced, full) < 1e-12
    torch.testing.assert_close(reducer(d[1]), reduced[1], rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(reducer.morph_parameters(mu), reduced, rtol=0, atol=0)
    out = torch.empty(4, 110, 2, dtype=F64)
    assert reducer(d, out=out) is out and torch.equal(out, reduced)
    with pytest.raises(ValueError, match=r"displacement must have shape \(40, 2\) or \(B, 40, 2\)"):
        reducer(torch.zeros(40, 3, dtype=F64))
    # the state alone runs the reduced morph, in a reducer fitted to 3-D points before
    fresh = PODReducer(online=online)
    fresh.load_state_dict(saved_state(reducer))
    assert fresh.dim == 2 and torch.equal(fresh(d), reduced)


def test_planar_functional_matrices_match_dense_kronecker_formulas():
    morph = PlanarMorph()
    weights = morph.weights
    generator = torch.Generator().manual_seed(63)
    modes = torch.linalg.qr(torch.randn(2 * 70, 3, generator=generator, dtype=F64))[0]
    modes = modes.T.reshape(3, 70, 2)
    z = modes.reshape(3, -1).T  # (2 N_int, N), component-interleaved rows
    big = torch.kron(weights, torch.eye(2, dtype=F64))
    projection = projection_matrix(modes, weights)
    assert projection.shape == (3, 14, 2)
    torch.testing.assert_close(projection.reshape(3, -1), z.T @ big, rtol=1e-12, atol=1e-13)
    system, rhs = paper_matrices(modes, weights)
    big_pinv = torch.linalg.pinv(big)
    torch.testing.assert_close(rhs.reshape(3, -1), z.T @ big_pinv.T, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(system, z.T @ big_pinv.T @ big_pinv @ z, rtol=1e-9, atol=1e-10)
    snapshots = morph(planar_family(random_parameters(5, 2, 64)))[:, 40:]
    basis, values, _ = pod_basis(snapshots, method="svd")
    torch.testing.assert_close(
        values, torch.linalg.svdvals(snapshots.reshape(5, -1)), rtol=1e-12, atol=1e-13
    )
    assert basis.shape[1:] == (70, 2)


def test_pod_reducer_fitted_to_a_planar_idw():
    boundary, interior = square_cloud()
    try:
        idw = IDW(boundary, interior, mode="dense")
    except ValueError as error:  # the IDW module before it took 2-D points
        pytest.skip(f"torchmorph.idw.IDW refuses 2-D points: {error}")
    reducer = PODReducer().fit(idw, family=planar_family, parameters=random_parameters(6, 2, 65))
    d = planar_family(random_parameters(3, 2, 66))
    assert reducer.dim == 2 and relative(reducer(d), idw(d)) < 1e-12
