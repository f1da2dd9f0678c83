"""Invariants of the public API, checked on random inputs drawn by hypothesis.

Small sizes and few examples keep this fast; every property is one the paper's
definitions imply (eqs. 2-3 for IDW, Algorithm 1 for the selection).
"""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchmorph import IDW
from torchmorph.selection import select_control_points

F64 = torch.float64
PROPERTY = settings(max_examples=25, deadline=None)


def random_points(count: int, seed: int, dim: int = 3) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(count, dim, generator=generator, dtype=F64)


sizes = st.integers(min_value=1, max_value=24)
seeds = st.integers(min_value=0, max_value=2**31 - 1)
powers = st.sampled_from([1.0, 2.0, 3.0, 4.0, 6.0])


@PROPERTY
@given(num_controls=sizes, num_targets=sizes, seed=seeds, power=powers)
def test_rows_of_w_sum_to_one_and_are_nonnegative(num_controls, num_targets, seed, power):
    controls = random_points(num_controls, seed)
    targets = random_points(num_targets, seed + 1)
    weights = IDW(controls, targets, power=power, mode="dense").weights_matrix()
    assert weights.shape == (num_targets, num_controls)
    assert bool((weights >= 0).all())
    torch.testing.assert_close(
        weights.sum(1), torch.ones(num_targets, dtype=F64), rtol=0, atol=1e-12
    )


@PROPERTY
@given(num_controls=sizes, seed=seeds, power=powers, mode=st.sampled_from(["dense", "matrix_free"]))
def test_exact_reproduction_at_the_controls(num_controls, seed, power, mode):
    controls = random_points(num_controls, seed)
    generator = torch.Generator().manual_seed(seed + 2)
    picked = torch.randint(0, num_controls, (5,), generator=generator)
    displacements = torch.randn(num_controls, 3, generator=generator, dtype=F64)
    out = IDW(controls, controls[picked], power=power, mode=mode)(displacements)
    torch.testing.assert_close(out, displacements[picked], rtol=0, atol=1e-12)


@PROPERTY
@given(num_controls=sizes, num_targets=sizes, seed=seeds, power=powers)
def test_permutation_equivariance(num_controls, num_targets, seed, power):
    controls = random_points(num_controls, seed)
    targets = random_points(num_targets, seed + 1)
    generator = torch.Generator().manual_seed(seed + 3)
    displacements = torch.randn(2, num_controls, 3, generator=generator, dtype=F64)
    by_control = torch.randperm(num_controls, generator=generator)
    by_target = torch.randperm(num_targets, generator=generator)
    reference = IDW(controls, targets, power=power)(displacements)
    permuted = IDW(controls[by_control], targets[by_target], power=power)(
        displacements[:, by_control]
    )
    torch.testing.assert_close(permuted, reference[:, by_target], rtol=1e-12, atol=1e-14)


@PROPERTY
@given(num_controls=sizes, num_targets=sizes, seed=seeds, power=powers)
def test_dense_equals_matrix_free(num_controls, num_targets, seed, power):
    controls = random_points(num_controls, seed)
    targets = random_points(num_targets, seed + 1)
    generator = torch.Generator().manual_seed(seed + 4)
    displacements = torch.randn(3, num_controls, 3, generator=generator, dtype=F64)
    dense = IDW(controls, targets, power=power, mode="dense")(displacements)
    free = IDW(controls, targets, power=power, mode="matrix_free")(displacements)
    torch.testing.assert_close(free, dense, rtol=1e-12, atol=1e-14)


@PROPERTY
@given(
    count=st.integers(min_value=1, max_value=120),
    seed=seeds,
    radius=st.floats(min_value=0.05, max_value=0.6),
    dim=st.sampled_from([2, 3]),
    a=st.floats(min_value=0.2, max_value=0.95),
    b=st.floats(min_value=1.05, max_value=2.5),
    strategy=st.sampled_from(["random", "centroid", "farthest"]),
)
def test_selection_separation_and_coverage(count, seed, radius, dim, a, b, strategy):
    """Algorithm 1: every chosen point removes its ball B(c; R) from the candidates and
    the next one is sought outside it, so the chosen points are pairwise at least R
    apart and every candidate ends within R of one of them."""
    points = random_points(count, seed, dim)
    chosen = select_control_points(
        points, radius, a=a, b=b, strategy=strategy, generator=torch.Generator().manual_seed(seed)
    )
    assert chosen.numel() == chosen.unique().numel() >= 1
    distances = torch.cdist(points, points[chosen])
    assert float(distances.min(1).values.max()) <= radius * (1 + 1e-12)
    if chosen.numel() > 1:
        between = torch.cdist(points[chosen], points[chosen])
        between.fill_diagonal_(float("inf"))
        assert float(between.min()) >= radius * (1 - 1e-12)
