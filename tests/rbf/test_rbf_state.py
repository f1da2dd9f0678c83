"""The RBF module's saved state and its argument checks: a round trip through
state_dict, a state loaded across modes, mismatched hyper-parameters refused naming the
field, and every bad argument refused with a message that names it."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from torchmorph.rbf import RBF, rbf_interpolate

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64


def cloud(count, dim=3, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).uniform(size=(count, dim)))


def values(count=30, seed=5):
    return torch.from_numpy(np.random.default_rng(seed).normal(size=(count, 3)))


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize(("kernel", "degree"), [("thin_plate_spline", 1), ("quintic", 1)])
def test_state_dict_round_trip(mode, kernel, degree):
    original = RBF(cloud(30), cloud(40, seed=1), kernel=kernel, degree=degree, mode=mode)
    buffer = io.BytesIO()
    torch.save(original.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer)
    # built on other points (other counts): everything is taken from the state
    loaded = RBF(cloud(12, seed=2), cloud(7, seed=3), kernel=kernel, degree=degree, mode=mode)
    loaded.load_state_dict(state)
    assert loaded.solver == original.solver
    assert torch.equal(loaded(values()), original(values()))


def test_a_dense_state_loads_into_a_matrix_free_module_and_back():
    dense = RBF(cloud(30), cloud(40, seed=1), mode="dense")
    free = RBF(cloud(10, seed=2), cloud(5, seed=3), mode="matrix_free")
    free.load_state_dict(dense.state_dict())
    assert free.evaluation is None
    torch.testing.assert_close(free(values()), dense(values()), rtol=0, atol=1e-12)
    again = RBF(cloud(10, seed=2), cloud(5, seed=3), mode="dense")
    again.load_state_dict(free.state_dict())
    assert again.evaluation is not None and again.evaluation.shape == (40, 34)
    torch.testing.assert_close(again(values()), dense(values()), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("field", "options"),
    [
        ("kernel", {"kernel": "cubic"}),
        ("epsilon", {"kernel": "thin_plate_spline", "epsilon": 2.0}),
        ("degree", {"degree": 0}),
    ],
)
def test_a_mismatched_hyperparameter_is_refused(field, options):
    saved = RBF(cloud(30), cloud(4, seed=1)).state_dict()
    other = RBF(cloud(30), cloud(4, seed=1), **options)
    with pytest.raises(ValueError, match=f"^{field}: the state was saved with {field}="):
        other.load_state_dict(saved)


def test_a_mismatched_support_radius_is_refused():
    saved = RBF(cloud(30), cloud(4, seed=1), kernel="wendland_c2", support_radius=0.5)
    other = RBF(cloud(30), cloud(4, seed=1), kernel="wendland_c2", support_radius=0.6)
    with pytest.raises(ValueError, match="^support_radius: the state was saved with"):
        other.load_state_dict(saved.state_dict())


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"kernel": "thin_plate"}, "^kernel must be one of 'thin_plate_spline'"),
        ({"kernel": "gaussian"}, "^epsilon must be given for kernel='gaussian'"),
        ({"kernel": "gaussian", "epsilon": 0.0}, "^epsilon must be a finite number > 0"),
        ({"epsilon": -1.0}, "^epsilon must be a finite number > 0"),
        ({"epsilon": float("nan")}, "^epsilon must be a finite number > 0"),
        ({"kernel": "wendland_c2"}, "^support_radius must be given for kernel='wendland_c2'"),
        (
            {"kernel": "wendland_c4", "support_radius": 0.0},
            "^support_radius must be a finite number > 0",
        ),
        (
            {"kernel": "wendland_c0", "support_radius": 1.0, "epsilon": 2.0},
            "^epsilon must be None for kernel='wendland_c0'",
        ),
        ({"support_radius": 1.0}, "^support_radius is only for the Wendland kernels"),
        ({"degree": -2}, "^degree must be an integer >= -1"),
        ({"degree": 1.5}, "^degree must be an integer >= -1"),
        ({"mode": "sparse"}, "^mode must be one of 'auto', 'dense', 'matrix_free'"),
        ({"block_bytes": 0}, "^block_bytes must be a finite number > 0"),
    ],
)
def test_bad_options_are_named(options, message):
    with pytest.raises(ValueError, match=message):
        RBF(cloud(10), cloud(4, seed=1), **options)


def test_too_few_controls_for_the_polynomial():
    with pytest.raises(
        ValueError, match=r"^controls: degree=1 in 3-D needs at least 4 controls, got 3"
    ):
        RBF(cloud(3), cloud(4, seed=1))
    RBF(cloud(3), cloud(4, seed=1), degree=0)  # a constant needs one


def test_coinciding_controls_are_refused():
    controls = cloud(10)
    controls[7] = controls[2]
    with pytest.raises(ValueError, match="^controls: points 2 and 7 coincide"):
        RBF(controls, cloud(4, seed=1))
    with pytest.raises(ValueError, match="^controls: points 2 and 7 coincide"):
        rbf_interpolate(controls=controls, targets=cloud(4, seed=1), displacements=values(10))


def test_controls_on_a_plane_are_refused_with_an_affine_tail():
    controls = cloud(20)
    controls[:, 2] = 0.5
    with pytest.raises(ValueError, match=r"^controls: the monomials of degree=1 .* rank 3 of 4"):
        RBF(controls, cloud(4, seed=1))


@pytest.mark.parametrize(
    ("controls", "targets", "message"),
    [
        (torch.zeros(0, 3, dtype=F64), cloud(3), "^controls is empty"),
        (cloud(5)[:, :1], cloud(3), r"^controls must have shape \(N, 3\)"),
        (cloud(5), cloud(3, dim=2), r"^targets must have shape \(N, 3\)"),
        (cloud(5).float(), cloud(3), "^targets has dtype torch.float64 but controls has"),
        (torch.full((5, 3), float("nan"), dtype=F64), cloud(3), "^controls holds 15 NaN"),
        (cloud(5), torch.full((2, 3), float("inf"), dtype=F64), "^targets holds 6 NaN"),
        (cloud(5).half(), cloud(3).half(), "^controls has dtype torch.float16"),
    ],
)
def test_bad_points_are_named(controls, targets, message):
    with pytest.raises(ValueError, match=message):
        RBF(controls, targets)


def test_bad_displacements_are_named():
    morph = RBF(cloud(10), cloud(4, seed=1))
    with pytest.raises(ValueError, match=r"^displacements must have shape \(10, 3\)"):
        morph(torch.zeros(9, 3, dtype=F64))
    with pytest.raises(ValueError, match="^displacements has dtype torch.float32"):
        morph(torch.zeros(10, 3))
    bad = torch.zeros(10, 3, dtype=F64)
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="^displacements holds 1 NaN"):
        morph(bad)
    with pytest.raises(ValueError, match=r"^targets must have shape \(4, 3\)"):
        morph(torch.zeros(10, 3, dtype=F64), targets=cloud(5))


def test_repr_names_the_options():
    text = repr(RBF(cloud(10), cloud(4, seed=1), kernel="gaussian", epsilon=3.0, mode="dense"))
    assert "kernel='gaussian'" in text and "epsilon=3" in text and "mode='dense'" in text


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_no_targets_and_the_fewest_controls(mode):
    controls = cloud(4)  # as many as the affine tail's monomials: the affine map itself
    empty = RBF(controls, torch.zeros(0, 3, dtype=F64), mode=mode)
    assert empty(values(4)).shape == (0, 3)
    assert empty(values(4)[None].repeat(2, 1, 1)).shape == (2, 0, 3)
    at_controls = RBF(controls, controls, mode=mode)(values(4))
    torch.testing.assert_close(at_controls, values(4), rtol=0, atol=1e-13)


def test_four_dimensional_points_are_refused():
    with pytest.raises(ValueError, match=r"^controls must have shape \(N, 3\), got \(5, 4\)"):
        RBF(torch.zeros(5, 4, dtype=F64), torch.zeros(2, 4, dtype=F64))
