"""Tree-approximated IDW (:mod:`torchmorph.idw.tree`) against exact float64 sums."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmorph.idw import idw_apply, idw_weights
from torchmorph.idw._tree_threshold import RAISE_LEAST
from torchmorph.idw.backends.numba.kernels import available
from torchmorph.idw.tree import SAMPLE_SAFETY, TreeIDW, idw_tree_apply

pytestmark = pytest.mark.skipif(not available(), reason="the tree kernels need numba")


def brute_force(controls, targets, displacements, power):
    """eq. (2) in float64, literally: Σ w d / Σ w with w = |x - x_k|^-p."""
    distances = torch.cdist(targets.double(), controls.double())
    weights = distances ** (-power)
    return (weights @ displacements.double()) / weights.sum(1, keepdim=True)


def sphere(count, generator):
    points = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    return points / points.norm(dim=1, keepdim=True)


def cloud(kind, generator):
    """(controls, targets) of 400 controls and 1,500 targets."""
    if kind == "uniform":
        controls = torch.rand(400, 3, generator=generator, dtype=torch.float64)
        targets = torch.rand(1500, 3, generator=generator, dtype=torch.float64)
        return controls, targets
    controls = sphere(400, generator)
    directions = sphere(1500, generator)
    if kind == "surface":  # targets filling the ball
        radius = torch.rand(1500, 1, generator=generator, dtype=torch.float64) * 0.97
    else:  # graded by 10^4: distances to the surface from 1e-4 to 1
        exponent = torch.rand(1500, 1, generator=generator, dtype=torch.float64) * 4
        radius = 1 - 10 ** (-exponent)
    return controls, directions * radius


def field(controls):
    x, y, z = controls.unbind(1)
    return torch.stack([x * x - 0.3, torch.sin(3 * y), z * x + 0.2], 1)


def relative_error(result, exact):
    return float((result.double() - exact).norm() / exact.norm())


def graded_sphere(monkeypatch):
    """2,000 controls on the sphere and 20,000 targets graded towards it, with 64 sampled
    targets: their blocks are then a small part of all (a first sampled call tunes there)."""
    import torchmorph.idw._tree_sample as sample_module

    monkeypatch.setattr(sample_module, "SAMPLE_TARGETS", 64)
    generator = torch.Generator().manual_seed(5)
    controls = sphere(2000, generator)
    exponent = torch.rand(20000, 1, generator=generator, dtype=torch.float64) * 4
    return controls, sphere(20000, generator) * (1 - 10 ** (-exponent))


def record_traversals(monkeypatch):
    """(a list that each traversal appends its (η, blocks) to, the unpatched apply)."""
    from torchmorph.idw._tree_operator import _TreeOperator

    traversed: list = []
    apply = _TreeOperator.apply

    def recording(self, values, eta, single=False, blocks=None):
        traversed.append((eta, blocks))
        return apply(self, values, eta, single, blocks)

    monkeypatch.setattr(_TreeOperator, "apply", recording)
    return traversed, apply


@pytest.mark.parametrize("tolerance", [1e-2, 1e-4, 1e-6])
@pytest.mark.parametrize("kind", ["uniform", "surface", "graded"])
def test_certified_tolerance_holds_against_exact_float64(kind, tolerance):
    generator = torch.Generator().manual_seed(3)
    controls, targets = cloud(kind, generator)
    displacements = field(controls)
    exact = brute_force(controls, targets, displacements, 4.0)
    module = TreeIDW(controls, targets, tolerance=tolerance)
    result = module(displacements)
    assert relative_error(result, exact) <= tolerance
    assert max(module.last_bound_) <= tolerance  # the certified bound
    assert relative_error(result, exact) <= max(module.last_bound_) + 1e-13


@pytest.mark.parametrize("tolerance", [1e-2, 1e-4, 1e-6])
@pytest.mark.parametrize("kind", ["uniform", "surface", "graded"])
def test_sampled_tolerance_holds_against_exact_float64(kind, tolerance):
    """The sampled check at 1,024 of 1,500 targets; the error over all of them holds too,
    also on a second call (which starts from the first call's threshold)."""
    generator = torch.Generator().manual_seed(9)
    controls, targets = cloud(kind, generator)
    displacements = field(controls)
    exact = brute_force(controls, targets, displacements, 4.0)
    module = TreeIDW(controls, targets, tolerance=tolerance, error_control="sampled")
    for _ in range(2):
        result = module(displacements)
        assert relative_error(result, exact) <= tolerance
        assert max(module.last_sampled_error_) <= tolerance / SAMPLE_SAFETY


@pytest.mark.parametrize("tolerance", [1e-3, 1e-5, 1e-6])
def test_sampled_float32_reference_from_single_reference_up(monkeypatch, tolerance):
    """Float32 inputs: the sampled check takes the float32 fused sums (float64 partial
    sums) from SINGLE_REFERENCE up and float64 sums below; the tolerance holds against
    float64 sums either way."""
    import torchmorph.idw._tree_sample as sample_module

    generator = torch.Generator().manual_seed(9)
    controls, targets = (points.float() for points in cloud("graded", generator))
    displacements = field(controls.double()).float()
    exact = brute_force(controls, targets, displacements, 4.0)
    references = []

    def recording(**arguments):
        references.append(arguments["controls"].dtype)
        return idw_apply(**arguments)

    monkeypatch.setattr(sample_module, "idw_apply", recording)
    module = TreeIDW(controls, targets, tolerance=tolerance, error_control="sampled")
    result = module(displacements)
    single = tolerance >= sample_module.SINGLE_REFERENCE
    assert references == [torch.float32 if single else torch.float64]
    assert result.dtype == torch.float32
    assert relative_error(result, exact) <= max(tolerance, 1e-6)


@pytest.mark.parametrize("error_control", ["certified", "sampled"])
@pytest.mark.parametrize("power", [2.0, 3.0, 4.0, 7.5])
def test_powers(power, error_control):
    generator = torch.Generator().manual_seed(4)
    controls, targets = cloud("graded", generator)
    displacements = field(controls)
    exact = brute_force(controls, targets, displacements, power)
    result = idw_tree_apply(
        controls=controls, targets=targets, displacements=displacements, power=power,
        tolerance=1e-3, error_control=error_control,
    )  # fmt: skip
    assert relative_error(result, exact) <= 1e-3


@pytest.mark.parametrize("power", [1, 2, 3, 4, 5, 6, 7, 8, 2.5])
def test_remainder_bounds_the_expansion_from_above(power):
    """T2(θ) = (1-θ)^-p - 1 - pθ - p(p+1)θ²/2 in closed form for the integer p (and by
    expm1/log1p otherwise) against exact rational arithmetic: never below, and within
    1e-10 relative (the certified bound rests on it)."""
    from fractions import Fraction

    from torchmorph.idw.backends import power_code
    from torchmorph.idw.backends.numba._tree_jit import _remainder_fast

    for theta in [*np.linspace(1e-4, 0.999, 400), 1e-6, 1e-2, 0.5]:
        value = _remainder_fast(float(theta), float(power), power_code(power))
        t = Fraction(float(theta))
        if float(power).is_integer():
            p = int(power)
            exact = 1 / (1 - t) ** p - 1 - p * t - Fraction(p * (p + 1), 2) * t * t
            assert 0 <= (Fraction(value) - exact) / exact <= 1e-10, (theta, value)
        else:  # no closed form: against a float64 evaluation of (1-θ)^-p (float rounding)
            whole = (1 - float(theta)) ** -power - 1 - power * theta
            exact_float = whole - power * (power + 1) / 2 * theta * theta
            assert value == pytest.approx(exact_float, rel=1e-6, abs=1e-15)
    assert _remainder_fast(1.0, float(power), power_code(power)) == np.inf


@pytest.mark.parametrize("power", [3.0, 5.0, 6.0, 8.0])
def test_integer_powers_in_single_precision(power):
    """The integer powers are products and square roots in the kernels. Against its
    block's reference distance a float32 leaf's ratio can leave float32's range at the
    sixth power (here the result was 4e-2 off), so the leaves take them in float64."""
    generator = torch.Generator().manual_seed(4)
    controls, targets = cloud("graded", generator)
    displacements = field(controls)
    exact = brute_force(controls, targets, displacements, power)
    module = TreeIDW(controls.float(), targets.float(), power=power, tolerance=1e-6)
    assert relative_error(module(displacements.float()), exact) <= 1e-6


def test_far_field_is_used_and_error_is_below_bound():
    """At a loose tolerance the far field replaces exact sums (the result differs from
    the exact one) and the measured error stays below the certified bound."""
    generator = torch.Generator().manual_seed(5)
    controls = sphere(3000, generator)
    targets = sphere(2000, generator) * 0.5
    displacements = field(controls)
    exact = brute_force(controls, targets, displacements, 4.0)
    module = TreeIDW(controls, targets, tolerance=1e-1, error_control="sampled")
    result = module(displacements)
    error = relative_error(result, exact)
    assert 1e-12 < error <= 1e-1
    assert error <= max(module.last_bound_)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtypes_and_exact_at_coincident_targets(dtype):
    generator = torch.Generator().manual_seed(6)
    controls, targets = cloud("surface", generator)
    targets = torch.cat([targets, controls[:50]])
    displacements = field(controls)
    result = idw_tree_apply(
        controls=controls.to(dtype), targets=targets.to(dtype),
        displacements=displacements.to(dtype), tolerance=1e-4,
    )  # fmt: skip
    assert result.dtype == dtype
    torch.testing.assert_close(result[-50:], displacements[:50].to(dtype), rtol=0, atol=0)
    exact = idw_apply(controls=controls, targets=targets, displacements=displacements)
    assert relative_error(result, exact) <= 1e-4


def test_duplicated_controls_give_their_mean():
    controls = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]).double()
    displacements = torch.tensor([[1.0, 0, 0], [3.0, 0, 0], [5.0, 0, 0]]).double()
    targets = torch.tensor([[0.0, 0.0, 0.0]]).double()
    result = idw_tree_apply(controls=controls, targets=targets, displacements=displacements)
    torch.testing.assert_close(result, torch.tensor([[2.0, 0.0, 0.0]]).double())


def test_batch_equals_loop():
    generator = torch.Generator().manual_seed(7)
    controls, targets = cloud("graded", generator)
    fields = torch.stack([field(controls), field(controls).flip(1), -2 * field(controls)])
    module = TreeIDW(controls, targets, tolerance=1e-3)
    batched = module(fields)
    for index in range(3):
        exact = brute_force(controls, targets, fields[index], 4.0)
        single = TreeIDW(controls, targets, tolerance=1e-3)(fields[index])
        assert relative_error(batched[index], exact) <= 1e-3
        assert relative_error(single, exact) <= 1e-3
    assert batched.shape == (3, targets.shape[0], 3)


@pytest.mark.parametrize("power", [4.0, 2.0, 3.0])
@pytest.mark.parametrize("single", [False, True])
def test_one_field_paths_equal_the_batch_paths_at_a_fixed_threshold(power, single):
    """One 3-D field takes its own kernels (the leaf's weights and three dot products in one
    pass; the far field's monomials shared by the four forms); as the first of a batch of
    two it takes the general ones. At one threshold the traversal is the same, so the two
    agree to rounding (float32 leaves: to float32's). In float64 the transposed pass (its
    own kernels too) is the exact adjoint and the result stays within the bound; not in
    float32 here, where the operator gets the clouds unnormalised with a coincidence
    radius of 1e-12, so the leaves' weights (1e-12/R)^4 fall below float32's range (the
    module normalises the clouds first)."""
    from torchmorph.idw._tree_operator import _TreeOperator

    generator = torch.Generator().manual_seed(3)
    controls, targets = cloud("graded", generator)
    operator = _TreeOperator(controls.numpy(), targets.numpy(), power, 1e-24, 16)
    values = field(controls).numpy()
    one, _, bound, _ = operator.apply(values, 0.3, single)
    both, _, _, _ = operator.apply(np.concatenate([values, -values[:, ::-1]], 1), 0.3, single)
    scale = np.abs(one).max()
    assert np.abs(one - both[:, :3]).max() <= (1e-6 if single else 1e-13) * scale
    if single:
        return
    sums, coincident = operator.apply(values, 0.3, single)[1], np.zeros(len(targets), np.int64)
    grad = np.random.default_rng(0).standard_normal(one.shape)  # Aᵀ by its own code
    back = operator.apply_transposed(grad, 0.3, sums, coincident, single)
    assert abs((one * grad).sum() - (values * back).sum()) <= 1e-12 * np.abs(one * grad).sum()
    exact = brute_force(controls, targets, field(controls), power).numpy()[operator.target_order]
    spread = float(np.linalg.norm(values.max(0) - values.min(0)))
    assert np.all(np.abs(one - exact).max(1) <= spread * bound + 1e-6 * scale)
    assert 0 < np.abs(one - exact).max()  # the far field was used


def test_a_first_sampled_call_tunes_on_the_sampled_targets_blocks(monkeypatch):
    """The first call in sampled mode tunes η on the blocks holding the sampled targets
    (their rows are those of a whole traversal, to the bit), then traverses every block
    once; the result holds the tolerance against exact float64 sums; the next call keeps
    that η."""
    controls, targets = graded_sphere(monkeypatch)
    module = TreeIDW(controls, targets, tolerance=1e-4, error_control="sampled")
    operator = module._operator
    blocks = module._sample_blocks
    assert blocks is not None and 4 * blocks.size <= operator.block_starts.size - 1
    traversed, apply = record_traversals(monkeypatch)
    result = module(field(controls))
    assert sum(b is None for _, b in traversed) == 1 and len(traversed) >= 2
    assert relative_error(result, brute_force(controls, targets, field(controls), 4.0)) <= 1e-4
    values, eta = field(controls).numpy(), module._applied[0]
    positions = operator.target_rank[module._sample_rows().numpy()]
    whole = apply(operator, values, eta)[0][positions]
    assert np.array_equal(apply(operator, values, eta, blocks=blocks)[0][positions], whole)
    traversed.clear()
    module(field(controls))  # later calls: one whole traversal at the tuned η
    assert [b for _, b in traversed] == [None] and module._applied[0] == eta


@pytest.mark.parametrize(
    ("error_control", "kind"),
    [("sampled", "graded"), ("certified", "graded"), ("certified", "uniform")],
)
def test_repeated_calls_settle_to_one_traversal(error_control, kind):
    """Where the error jumps past the goal between two thresholds, a failed raise is
    remembered: calls settle to one traversal each (they used to raise, fail and
    traverse 3-4 times on every call on these clouds), within the tolerance."""
    generator = torch.Generator().manual_seed(5)
    controls, targets = cloud(kind, generator)
    displacements = field(controls)
    exact = brute_force(controls, targets, displacements, 4.0)
    module = TreeIDW(controls, targets, tolerance=1e-4, error_control=error_control)
    traversals = []
    for _ in range(8):
        result = module(displacements)
        traversals.append(module.last_traversals_)
        assert relative_error(result, exact) <= 1e-4
    assert traversals[-4:] == [1, 1, 1, 1] and max(traversals) > 1, traversals
    assert module._ceiling is not None and module._calibration < module._ceiling


def test_a_ceiling_is_eased_after_quiet_calls(monkeypatch):
    """After CEILING_CALLS calls without a failed trial, the ceiling is raised by
    CEILING_EASE, so that a field that turned easier could take a larger η: on a field
    that did not, one probe fails and the calls settle again."""
    import torchmorph.idw.tree as tree_module

    monkeypatch.setattr(tree_module, "CEILING_CALLS", 3)
    generator = torch.Generator().manual_seed(5)
    controls, targets = cloud("graded", generator)
    module = TreeIDW(controls, targets, tolerance=1e-4, error_control="certified")
    traversals = []
    for _ in range(16):
        module(field(controls))
        traversals.append(module.last_traversals_)
    settled = traversals[traversals.index(1) :]  # one probe every CEILING_CALLS + 1 calls
    assert settled[:8] == [1, 1, 1, 2, 1, 1, 1, 2], traversals


def _step_cloud(monkeypatch):
    """The cloud of :func:`graded_sphere` and an error that jumps past the goal at η = 2
    (1e-4 of the goal below it)."""
    import torchmorph.idw.tree as tree_module

    controls, targets = graded_sphere(monkeypatch)
    traversed, _ = record_traversals(monkeypatch)
    goal = 1e-3 / SAMPLE_SAFETY

    def step(*arguments):  # the error of the last traversal's η
        return [1e-4 * goal if traversed[-1][0] < 2.0 else 10 * goal]

    monkeypatch.setattr(tree_module, "_sampled", step)
    module = TreeIDW(controls, targets, tolerance=1e-3, error_control="sampled")
    return module, controls, traversed


def test_a_first_sampled_call_narrows_a_failed_threshold_on_the_sampled_blocks(monkeypatch):
    """On a step of the error, the first call's cheap trials on the sampled targets'
    blocks close in on it (within RAISE_LEAST² of the lowest η that failed), so that the
    next calls traverse once, probing nothing."""
    module, controls, tried = _step_cloud(monkeypatch)
    module(field(controls))
    assert sum(blocks is None for _, blocks in tried) == 1 and len(tried) > 3
    assert module._applied[0] < 2.0 <= module._ceiling * (module._applied[0] / module._calibration)
    assert module._ceiling < module._calibration * RAISE_LEAST**2
    for _ in range(3):
        tried.clear()
        module(field(controls))
        assert len(tried) == 1 and tried[0][1] is None


def test_a_call_that_never_meets_the_goal_warns_and_keeps_its_last_threshold(monkeypatch):
    """Every trial over the goal: the call warns, returns the last traversal's result and
    keeps that traversal's η (the transposed pass must use the same operator)."""
    import torchmorph.idw.tree as tree_module

    generator = torch.Generator().manual_seed(5)
    controls, targets = cloud("graded", generator)
    module = TreeIDW(controls, targets, tolerance=1e-3, error_control="sampled")
    traversed, apply = record_traversals(monkeypatch)
    monkeypatch.setattr(tree_module, "_sampled", lambda *arguments: [math.inf])
    with pytest.warns(UserWarning, match="could not be brought below"):
        result = module(field(controls))
    tried = [eta for eta, _ in traversed]
    assert module.last_traversals_ == len(tried) > 1 and module._applied[0] == tried[-1]
    expected = apply(module._operator, field(controls).numpy(), tried[-1])[0]
    assert np.allclose(result.numpy(), expected[module._operator.target_rank])


def test_search_goes_halfway_to_a_threshold_that_failed():
    """The search on a step (the error jumps past the goal at η = 10): a raise that
    fails becomes the ceiling, later raises go at most to the geometric mean of the last
    good η and the ceiling, and none is tried once that is within RAISE_LEAST of it."""
    from torchmorph.idw._tree_threshold import RAISE_LEAST, search

    tried: list[float] = []

    def trial(eta):
        tried.append(eta)
        return (1e-6 * eta if eta < 10.0 else 1.0), eta

    def call(start, ceiling):
        tried.clear()
        best, _, start, ceiling = search(
            start, trial, 1e-3, 100.0, certified=False, stop=False, ceiling=ceiling
        )
        assert best is not None and best[0] == start < 10.0
        return start, ceiling

    start, ceiling = call(1.0, None)
    assert tried == [1.0, 100.0] and (start, ceiling) == (1.0, 100.0)
    start, ceiling = call(start, ceiling)
    assert tried == [1.0, 10.0] and (start, ceiling) == (1.0, 10.0)
    for _ in range(4):
        start, ceiling = call(start, ceiling)
        if len(tried) == 1:
            break
    assert len(tried) == 1 and ceiling == 10.0
    assert 10.0 / RAISE_LEAST**2 <= start < 10.0


def test_gradient_is_the_transpose():
    """<A d, g> = <d, Aᵀ g> for the operator a call used, at a tolerance where the far
    field is active, close to the exact Wᵀ g (controls under coincident targets included)."""
    generator = torch.Generator().manual_seed(8)
    controls = sphere(3000, generator)
    targets = torch.cat([sphere(1000, generator) * 0.5, controls[:5]])
    displacements = field(controls).requires_grad_(True)
    module = TreeIDW(controls, targets, tolerance=1e-1, error_control="sampled")
    result = module(displacements)
    assert max(module.last_bound_) > 0  # the far field is in use
    probe = torch.randn(result.shape, generator=generator, dtype=torch.float64)
    (gradient,) = torch.autograd.grad(result, displacements, probe)
    lhs = float((result.detach() * probe).sum())
    rhs = float((displacements.detach() * gradient).sum())
    assert math.isclose(lhs, rhs, rel_tol=1e-10)
    exact = idw_weights(controls=controls, targets=targets).mT @ probe
    assert float((gradient - exact).norm() / exact.norm()) < 1e-1
    torch.testing.assert_close(gradient[:5], exact[:5], rtol=1e-1, atol=1e-2)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"tolerance": 0.0}, "tolerance must lie in"),
        ({"tolerance": 1.0}, "tolerance must lie in"),
        ({"tolerance": -1e-3}, "tolerance must lie in"),
        ({"power": 0.0}, "power must be finite and > 0"),
        ({"leaf_size": 0}, "leaf_size must be a positive integer"),
        ({"error_control": "exact"}, "error_control must be 'certified' or 'sampled'"),
    ],
)
def test_bad_arguments_are_named(arguments, message):
    controls = torch.rand(10, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=message):
        TreeIDW(controls, controls + 0.5, **arguments)


def test_bad_inputs_are_named():
    controls = torch.rand(10, 3, dtype=torch.float64)
    module = TreeIDW(controls, controls + 0.5)
    with pytest.raises(ValueError, match="displacements must have shape"):
        module(torch.zeros(9, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="controls requires grad"):
        TreeIDW(controls.clone().requires_grad_(True), controls)
    with pytest.raises(ValueError, match="displacements"):
        module(torch.full((10, 3), math.nan, dtype=torch.float64))


def test_state_dict_brings_the_clouds_and_rebuilds_the_trees():
    generator = torch.Generator().manual_seed(10)
    controls, targets = cloud("surface", generator)
    other = TreeIDW(controls[:200], targets[:300])
    module = TreeIDW(controls, targets)
    other.load_state_dict(module.state_dict())
    displacements = field(controls)
    exact = brute_force(controls, targets, displacements, 4.0)
    assert relative_error(other(displacements), exact) <= 1e-4
    with pytest.raises(ValueError, match="power"):
        TreeIDW(controls, targets, power=2.0).load_state_dict(module.state_dict())


def exact_transpose(controls, targets, values, power=4.0):
    """Wᵀ values in float64, literally (W's rows are w_k / Σ w)."""
    distances = torch.cdist(targets.double(), controls.double())
    weights = distances ** (-power)
    weights = weights / weights.sum(1, keepdim=True)
    return weights.mT @ values.double()


@pytest.mark.parametrize("error_control", ["certified", "sampled"])
@pytest.mark.parametrize("called_first", [False, True])
@pytest.mark.parametrize("kind", ["surface", "graded"])
def test_transposed_is_the_exact_transpose_within_tolerance(kind, called_first, error_control):
    """Aᵀ g against the exact float64 Wᵀ g, for a smooth and a random g, before any call
    (the threshold of a probe call) and after one; certified: <A d, g> = <d, Aᵀ g>."""
    generator = torch.Generator().manual_seed(11)
    controls, targets = cloud(kind, generator)
    tolerance = 1e-4
    module = TreeIDW(controls, targets, tolerance=tolerance, error_control=error_control)
    displacements = field(controls)
    if called_first:
        module(displacements)
    smooth = field(targets)
    noise = torch.randn(targets.shape, generator=generator, dtype=torch.float64)
    batched = module.transposed(torch.stack([smooth, noise]))
    assert batched.shape == (2, controls.shape[0], 3)
    for index, values in enumerate((smooth, noise)):
        exact = exact_transpose(controls, targets, values)
        assert relative_error(batched[index], exact) <= tolerance
        # one field takes its own kernels, a batch the general ones: equal to rounding
        single = module.transposed(values)
        assert float((single - batched[index]).abs().max()) <= 1e-13 * float(exact.abs().max())
    if error_control == "sampled":  # Aᵀ at a tighter threshold than A's
        return
    result = module(displacements)  # the operator the transpose now uses
    lhs = float((result * noise).sum())
    rhs = float((displacements * module.transposed(noise)).sum())
    assert math.isclose(lhs, rhs, rel_tol=1e-10)


def test_gradient_at_zero_displacements_follows_the_tolerance():
    """A vector-Jacobian product taken at an all-zero field (whose result is zero at any
    threshold) uses the tolerance's threshold, not the loosest one."""
    generator = torch.Generator().manual_seed(12)
    controls, targets = cloud("graded", generator)
    module = TreeIDW(controls, targets, tolerance=1e-5)
    probe = torch.zeros_like(controls, requires_grad=True)
    upstream = torch.randn(targets.shape, generator=generator, dtype=torch.float64)
    (gradient,) = torch.autograd.grad(module(probe), probe, upstream)
    assert relative_error(gradient, exact_transpose(controls, targets, upstream)) <= 1e-5


def test_transposed_bad_values_are_named():
    generator = torch.Generator().manual_seed(13)
    controls, targets = cloud("uniform", generator)
    module = TreeIDW(controls, targets)
    with pytest.raises(ValueError, match=r"^values must have shape \(1500, 3\)"):
        module.transposed(torch.zeros(400, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="^values"):
        module.transposed(torch.full((1500, 3), math.nan, dtype=torch.float64))


@pytest.mark.parametrize("count", [1, 7, 8, 9, 1_000, 4_099])
def test_the_kd_tree_splits_at_the_median_of_the_widest_axis(count):
    from torchmorph.idw._tree_operator import _kd_tree

    rng = np.random.default_rng(count)
    points = rng.normal(size=(count, 3)) * [1.0, 3.0, 0.5]
    points[: count // 3, 0] = 0.25  # ties along an axis
    order, starts, stops, children = _kd_tree(points, 8)
    assert sorted(order.tolist()) == list(range(count))
    assert starts[0] == 0 and stops[0] == count
    for node in range(len(starts)):
        left, right = children[node]
        start, stop = starts[node], stops[node]
        if left < 0:
            assert right < 0 and stop - start <= 8
            continue
        assert left == node + 1  # depth-first preorder
        half = (stop - start) // 2
        assert (starts[left], stops[left]) == (start, start + half)
        assert (starts[right], stops[right]) == (start + half, stop)
        members = points[order[start:stop]]
        axis = int(np.argmax(members.max(0) - members.min(0)))
        lower = points[order[start : start + half], axis]
        upper = points[order[start + half : stop], axis]
        assert lower.max() <= upper.min()
