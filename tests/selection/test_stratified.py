"""Tests of the count-stratified order (torchmorph.selection.stratified) and of the
adaptive selection's stratified start and exact sequential picks."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from test_adaptive import bent_box, nodal_error

from torchmorph.idw import idw_weights
from torchmorph.selection import AdaptivePlan, IDWErrorOracle, select_adaptive
from torchmorph.selection.stratified import (
    _hilbert_keys,
    hilbert_order,
    nested_order,
    stratified_count,
)


@pytest.mark.parametrize(("dim", "bits"), [(2, 3), (3, 2), (3, 3)])
def test_consecutive_cells_along_the_curve_are_neighbours(dim, bits):
    """The defining property of a Hilbert curve: it visits every cell of the 2^b grid
    once, each step to a face neighbour."""
    cells = np.array(list(itertools.product(range(2**bits), repeat=dim)), dtype=np.int64)
    keys = np.empty(len(cells), dtype=np.int64)
    _hilbert_keys(cells, bits, keys)
    assert sorted(keys.tolist()) == list(range(len(cells)))
    path = cells[np.argsort(keys)]
    assert (np.abs(np.diff(path, axis=0)).sum(1) == 1).all()


def test_the_order_is_a_permutation_invariant_to_translation_and_scale():
    points = torch.rand(500, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    order = hilbert_order(points)
    assert sorted(order.tolist()) == list(range(500))
    assert torch.equal(hilbert_order(points * 8.0 - 3.0), order)
    nested = nested_order(points)
    assert sorted(nested.tolist()) == list(range(500))
    assert hilbert_order(points[:1]).tolist() == [0]
    assert hilbert_order(points[:, :1]).tolist() == torch.argsort(points[:, 0]).tolist()


@pytest.mark.parametrize("count", [10, 37, 64, 100, 333])
def test_every_prefix_is_spread_evenly_along_the_curve(count):
    """A prefix of n of N points leaves no gap longer than 2 N / n along the curve."""
    points = torch.rand(1000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    rank = torch.empty(1000, dtype=torch.int64)
    rank[hilbert_order(points)] = torch.arange(1000)
    prefix = torch.sort(rank[nested_order(points)[:count]]).values
    gaps = torch.diff(torch.cat([prefix, prefix[:1] + 1000]))
    assert int(gaps.max()) <= 2 * 1000 / count


def test_stratified_count_finds_the_shortest_prefix_to_a_sixteenth():
    asked: list[int] = []

    def errors(counts):
        asked.extend(counts)
        return [1.0 / n for n in counts]

    found = stratified_count(errors, 1 / 300, limit=5000)
    assert 300 <= found <= 300 + 512 // 16
    # doubling, then sixteenths of 512 upwards from 256, each count asked once
    assert asked[:7] == [8, 16, 32, 64, 128, 256, 512]
    assert asked[7:] == list(range(288, found + 1, 32))
    assert stratified_count(errors, 1 / 300, limit=200) is None
    assert stratified_count(errors, 1.0, limit=200) == 1  # one point meets it
    assert stratified_count(errors, 1 / 150, limit=150) == 150


@pytest.mark.parametrize("power", [4.0, 2.0, 3.0])
def test_the_oracle_weights_are_full_idw_up_to_a_factor_per_target(power):
    mesh, displacement = bent_box(4)
    boundary = mesh.points[mesh.boundary_nodes]
    interior = mesh.points[mesh.interior_nodes]
    targets = torch.cat([interior, boundary[3:4]])  # the last one on a candidate
    oracle = IDWErrorOracle(boundary, targets, displacement, num_samples=len(targets), power=power)
    weights = oracle.weights_t.mT
    expected = idw_weights(controls=boundary, targets=oracle.targets, power=power)
    rows = weights / weights.sum(1, keepdim=True)
    assert torch.allclose(rows, expected, rtol=1e-12, atol=1e-15)
    assert float(weights.max()) <= 1.0  # scaled by each target's nearest distance


def test_prefix_errors_equal_the_errors_of_each_prefix():
    mesh, displacement = bent_box(5)
    boundary = mesh.points[mesh.boundary_nodes]
    oracle = IDWErrorOracle(boundary, mesh.points[mesh.interior_nodes], displacement)
    base = torch.tensor([0, 5])
    order = nested_order(boundary)
    order = order[~torch.isin(order, base)]
    first = oracle.prefix_errors(base, order, [3, 10, 40])
    again = oracle.prefix_errors(base, order, [7, 12])  # from the sums of 3 and 10
    for count, error in zip([3, 10, 40, 7, 12], torch.cat([first, again]).tolist(), strict=True):
        fresh = oracle.errors(torch.cat([base, order[:count]]))
        assert error == pytest.approx(float(fresh.max()), rel=1e-12)


@pytest.mark.parametrize("on_a_candidate", [False, True])
def test_each_pick_is_the_best_candidate_of_the_pool(on_a_candidate):
    mesh, displacement = bent_box(5)
    boundary = mesh.points[mesh.boundary_nodes]
    family = torch.stack([displacement, 0.5 * displacement.roll(7, 0)])
    targets = mesh.points[mesh.interior_nodes]
    selected = nested_order(boundary)[:12]
    moving = torch.nonzero(displacement[:, 1] > 0.05).flatten()
    candidate = int(moving[~torch.isin(moving, selected)][0])
    if on_a_candidate:  # a target there: IDW from the others until it is picked
        targets = torch.cat([targets, boundary[candidate : candidate + 1]])
    oracle = IDWErrorOracle(boundary, targets, family, num_samples=len(targets))
    _, scores = oracle.scores(selected)
    pool = torch.argsort(scores, descending=True)[:32]
    if on_a_candidate:
        pool = torch.cat([torch.tensor([candidate]), pool[pool != candidate][:31]])
    picked = oracle.pick(selected, pool, 1e-9, 3)
    pool = pool[:16]  # with F = 2 members, the first half of the pool is read
    assert len(picked) == 3
    chosen = selected
    for candidate in picked.tolist():  # brute force: every pool member tried
        trials = {
            j: float(oracle.errors(torch.cat([chosen, torch.tensor([j])])).square().sum())
            for j in pool.tolist()
            if j not in chosen.tolist()
        }
        assert trials[candidate] == pytest.approx(min(trials.values()), rel=1e-12)
        chosen = torch.cat([chosen, torch.tensor([candidate])])
    assert float(oracle.errors(chosen).square().sum()) < float(
        oracle.errors(selected).square().sum()
    )


@pytest.mark.parametrize("start", ["stratified", "empty"])
def test_both_starts_reach_the_tolerance(start):
    mesh, displacement = bent_box(6)
    boundary = mesh.boundary_nodes
    result = select_adaptive(
        mesh.points[boundary],
        mesh.points[mesh.interior_nodes],
        displacement,
        tolerance=0.01,
        start=start,
    )
    error = nodal_error(mesh, displacement, boundary[result.indices].numpy())
    assert result.converged and error <= 0.01
    assert error == pytest.approx(result.error, rel=1e-9)
    first = result.history[0][0]
    assert first == (8 if start == "stratified" else 0)


def test_a_bad_start_is_refused():
    mesh, displacement = bent_box(4)
    with pytest.raises(ValueError, match="start must be one of"):
        AdaptivePlan(0.01, displacement, start="random")
    with pytest.raises(TypeError, match="start must be 'stratified', a SelectionPlan or None"):
        AdaptivePlan(0.01, displacement, start=3)
    with pytest.raises(ValueError, match="start must be one of"):
        select_adaptive(
            mesh.points[mesh.boundary_nodes],
            mesh.points[mesh.interior_nodes],
            displacement,
            tolerance=0.01,
            start="random",
        )
