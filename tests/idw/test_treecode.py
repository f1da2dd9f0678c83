"""IDW by the interpolating treecode (:mod:`torchmorph.idw.treecode`): errors against
float64 sums written out here, exactness at controls, the exact transpose and gradcheck,
batches, powers, 2-D, the degree raised by the sampled check, the state and the
refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmorph.idw import IDW
from torchmorph.idw import treecode as treecode_module
from torchmorph.idw.treecode import DEGREE_ERRORS, TreecodeIDW, start_degree

pytestmark = pytest.mark.usefixtures("one_thread")


def reference(controls, targets, displacements, power=4.0):
    """Eq. (2) in float64 by brute force (targets on a control take its displacement)."""
    c, t, d = (x.double() for x in (controls, targets, displacements))
    distances = torch.cdist(t, c)
    weights = distances ** (-power)
    result = weights @ d / weights.sum(1, keepdim=True)
    hit = distances.min(1).values == 0
    result[hit] = d[distances[hit].argmin(1)]
    return result


def sphere(count: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    points = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    return points / points.norm(dim=1, keepdim=True)


def graded(count: int, seed: int = 1) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    directions = sphere(count, seed)
    depth = 10 ** (-4 * torch.rand(count, 1, generator=generator, dtype=torch.float64))
    return directions * (1 - depth)


def smooth(points: torch.Tensor) -> torch.Tensor:
    x, y, z = points.unbind(1)
    return torch.stack([0.1 * x * y, 0.05 * torch.sin(3 * z), 0.02 + 0.1 * x * z], 1)


CLOUDS = {
    "graded": lambda: (sphere(600), graded(3000)),
    "uniform": lambda: (torch.rand(600, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1,
                        torch.rand(3000, 3, generator=torch.Generator().manual_seed(3)) * 2 - 1),
}  # fmt: skip


@pytest.mark.parametrize("cloud", sorted(CLOUDS))
@pytest.mark.parametrize("tolerance", [1e-2, 1e-3, 1e-4, 1e-6])
def test_the_error_is_within_the_tolerance(cloud, tolerance):
    controls, targets = (x.double() for x in CLOUDS[cloud]())
    displacements = smooth(controls)
    module = TreecodeIDW(controls, targets, tolerance=tolerance)
    result = module(displacements)
    exact = reference(controls, targets, displacements)
    error = float((result - exact).norm() / exact.norm())
    assert error <= tolerance
    assert error > 0  # an approximation: far pairs went through the proxies
    assert module.last_sampled_error_[0] == pytest.approx(error, rel=0.6)


def test_a_degree_that_falls_short_is_raised(monkeypatch):
    """A start too low (a table that claims degree 2 suffices) is caught by the sampled
    check: the degree rises until the sampled error is within the goal."""
    monkeypatch.setattr(treecode_module, "DEGREE_ERRORS", {2: 1e-12})
    controls, targets = sphere(600), graded(3000)
    module = TreecodeIDW(controls, targets, tolerance=1e-5)
    assert module.degree == 2
    result = module(smooth(controls))
    assert module.degree > 4
    exact = reference(controls, targets, smooth(controls))
    assert float((result - exact).norm() / exact.norm()) <= 1e-5


def test_a_tolerance_out_of_reach_warns(monkeypatch):
    monkeypatch.setattr(treecode_module, "DEGREE_ERRORS", {2: 1e-12})
    monkeypatch.setattr(treecode_module, "MAX_DEGREE", 2)
    controls, targets = sphere(600), graded(3000)
    module = TreecodeIDW(controls, targets, tolerance=1e-6)
    with pytest.warns(UserWarning, match="could not be brought below"):
        module(smooth(controls))
    assert module.last_sampled_error_[0] > 1e-6 / 1.5


def test_the_start_degree_follows_the_measured_errors():
    assert start_degree(1e-2) == 2 and start_degree(1e-3) == 3 and start_degree(1e-4) == 4
    assert start_degree(1e-6) == 7
    assert start_degree(1e-8) == 7 + math.ceil(
        math.log(1e-8 / 1.5 / DEGREE_ERRORS[7]) / math.log(1 / 7)
    )


def test_targets_on_controls_take_their_displacement():
    controls = sphere(500)
    twin = controls[7:8].clone()
    controls = torch.cat([controls, twin])  # two controls at one point: the mean
    targets = torch.cat([graded(1000), controls[:20], twin])
    displacements = smooth(controls) + torch.randn(
        501, 3, generator=torch.Generator().manual_seed(4)
    )
    result = TreecodeIDW(controls, targets, tolerance=1e-3)(displacements)
    torch.testing.assert_close(result[1000:1007], displacements[:7], rtol=0, atol=1e-15)
    mean = (displacements[7] + displacements[500]) / 2
    torch.testing.assert_close(result[1007], mean, rtol=0, atol=1e-15)
    torch.testing.assert_close(result[-1], mean, rtol=0, atol=1e-15)
    assert torch.isfinite(result).all()


def test_the_transpose_is_exact_and_gradients_check():
    controls = sphere(300)
    targets = torch.cat([graded(900), controls[:3]])  # coincident rows in the transpose too
    module = TreecodeIDW(controls, targets, tolerance=1e-3)
    generator = torch.Generator().manual_seed(5)
    d = torch.randn(2, 300, 3, generator=generator, dtype=torch.float64)
    g = torch.randn(2, 903, 3, generator=generator, dtype=torch.float64)
    forward = module(d)
    back = module.transposed(g)
    assert float((forward * g).sum()) == pytest.approx(float((d * back).sum()), rel=1e-12)
    small = TreecodeIDW(controls[:40], targets[:200], tolerance=1e-2)
    field = torch.randn(40, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(small, (field,))
    d.requires_grad_(True)
    (module(d) * g).sum().backward()
    torch.testing.assert_close(d.grad, back, rtol=1e-12, atol=1e-14)


def test_a_batch_is_its_fields_one_by_one():
    """Two fields (six columns, the general pass) against each alone (three columns, the
    fused pass at p = 4): the same sums to rounding."""
    controls, targets = sphere(400), graded(2000)
    module = TreecodeIDW(controls, targets, tolerance=1e-4)
    fields = torch.stack([smooth(controls), smooth(controls.flip(1))])
    batch = module(fields)
    for k in range(2):
        torch.testing.assert_close(batch[k], module(fields[k]), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("power", [2.0, 3.0, 6.0, 2.5])
def test_other_powers(power):
    controls, targets = sphere(500), graded(2000)
    displacements = smooth(controls)
    module = TreecodeIDW(controls, targets, power=power, tolerance=1e-4)
    exact = reference(controls, targets, displacements, power)
    assert float((module(displacements) - exact).norm() / exact.norm()) <= 1e-4


def test_two_dimensions_and_float32():
    angle = torch.linspace(0, 2 * math.pi, 401, dtype=torch.float64)[:-1]
    controls = torch.stack([angle.cos(), angle.sin()], 1)
    generator = torch.Generator().manual_seed(6)
    radius = 1 - 10 ** (-3 * torch.rand(3000, 1, generator=generator, dtype=torch.float64))
    phase = 2 * math.pi * torch.rand(3000, generator=generator, dtype=torch.float64)
    targets = radius * torch.stack([phase.cos(), phase.sin()], 1)
    displacements = torch.stack([0.1 * controls[:, 0] * controls[:, 1], 0.05 * controls[:, 0]], 1)
    exact = reference(controls, targets, displacements)
    for dtype in (torch.float64, torch.float32):
        module = TreecodeIDW(controls.to(dtype), targets.to(dtype), tolerance=1e-4)
        result = module(displacements.to(dtype))
        assert result.dtype == dtype and result.shape == (3000, 2)
        assert float((result.double() - exact).norm() / exact.norm()) <= 1e-4


def test_state_round_trip_and_mismatch():
    controls, targets = sphere(300), graded(1000)
    module = TreecodeIDW(controls, targets, tolerance=1e-3)
    other = TreecodeIDW(sphere(200, seed=9), graded(500, seed=9), tolerance=1e-3)
    other.load_state_dict(module.state_dict())
    torch.testing.assert_close(other(smooth(controls)), module(smooth(controls)), rtol=0, atol=0)
    wrong = TreecodeIDW(controls, targets, power=2.0, tolerance=1e-3)
    with pytest.raises(ValueError, match="power"):
        wrong.load_state_dict(module.state_dict())


def test_refusals_and_empty_targets():
    controls = sphere(50)
    with pytest.raises(ValueError, match="power"):
        TreecodeIDW(controls, graded(10), power=0.0)
    with pytest.raises(ValueError, match="tolerance"):
        TreecodeIDW(controls, graded(10), tolerance=1.5)
    with pytest.raises(ValueError, match="controls"):
        TreecodeIDW(controls.requires_grad_(True), graded(10))
    module = TreecodeIDW(sphere(50), graded(0))
    assert module(smooth(sphere(50))).shape == (0, 3)
    with pytest.raises(ValueError, match="displacements"):
        module(torch.zeros(49, 3, dtype=torch.float64))


def test_the_sampled_tree_mode_is_the_treecode():
    controls, targets = sphere(300), graded(1500)
    module = IDW(controls, targets, mode="tree", tolerance=1e-3, error_control="sampled")
    operator = module._tree.operator(module.controls, module.targets)
    assert isinstance(operator, TreecodeIDW)
    exact = reference(controls, targets, smooth(controls))
    assert float((module(smooth(controls)) - exact).norm() / exact.norm()) <= 1e-3
    assert np.isfinite(module.transposed(exact).numpy()).all()


@pytest.mark.parametrize("power", [4.0, 3.0])
def test_the_inverse_power_sums_and_their_fused_passes(power):
    """The treecode's sums of r^-p against float64 sums written out here, the error
    falling with the degree; at p = 4 the fused passes (one column, three columns) equal
    the general pass (two, six columns) to rounding."""
    from torchmorph._treecode import TreeCode

    sources, targets = sphere(4000).numpy(), graded(2000).numpy()
    values = np.random.default_rng(7).standard_normal((4000, 3))
    distances2 = ((targets[:, None, :] - sources[None]) ** 2).sum(-1)
    exact = distances2 ** (-power / 2) @ values
    errors = []
    for degree in (2, 3, 4):
        tree = TreeCode(sources, targets, 1.0, degree, power=power, floor=1e-30)
        approximate = tree.apply(values)
        errors.append(np.linalg.norm(approximate - exact) / np.linalg.norm(exact))
        doubled = tree.apply(np.concatenate([values, values], 1))
        np.testing.assert_allclose(approximate, doubled[:, :3], rtol=1e-12)
        ones = np.ones((4000, 1))
        np.testing.assert_allclose(
            tree.apply(ones), tree.apply(np.concatenate([ones, ones], 1))[:, :1], rtol=1e-12
        )
    assert errors[0] > 3 * errors[1] > 9 * errors[2] and 0 < errors[2] < 1e-4
