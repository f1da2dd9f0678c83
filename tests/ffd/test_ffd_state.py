"""The FFD module's state (buffers, extra state, the load rule, devices and dtypes) and
its argument checks: every message names the argument."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from torchmorph.ffd import FFD

F64 = torch.float64


def points(count=80, dim=3, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(count, dim, generator=generator, dtype=F64) * 1.4 - 0.2


def build(dim=3, count=80, seed=0, **options):
    box = dict(origin=[0.0] * dim, lengths=[1.0] * dim, shape=(4, 5, 6)[:dim])
    box.update(options)
    return FFD(points(count, dim, seed), **box)


def lattice(morph, seed=3, batch=()):
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(*batch, *morph.shape, morph.dim, generator=generator, dtype=F64)


# --------------------------------------------------------------------------- #
# state
# --------------------------------------------------------------------------- #
def test_state_dict_holds_buffers_and_hyperparameters():
    state = build(basis="bspline", degree=2).state_dict()
    assert set(state) == {
        "points",
        "origin",
        "lengths",
        "rotation",
        "inside",
        "basis_x",
        "basis_y",
        "basis_z",
        "_extra_state",
    }
    assert state["_extra_state"] == {"basis": "bspline", "degree": 2, "shape": (4, 5, 6)}
    assert state["inside"].dtype == torch.int64
    assert state["basis_y"].shape == (state["inside"].numel(), 5)
    assert set(build(dim=2).state_dict()) >= {"basis_x", "basis_y"}
    assert "basis_z" not in build(dim=2).state_dict()


@pytest.mark.parametrize("basis", ["bernstein", "bspline"])
def test_state_round_trip_into_a_module_built_on_other_points(basis):
    source = build(basis=basis)
    receiver = build(
        count=33, seed=5, origin=[0.5, 0.1, -1.0], lengths=[2.0, 3.0, 4.0], basis=basis
    )
    buffer = io.BytesIO()
    torch.save(source.state_dict(), buffer)
    buffer.seek(0)
    receiver.load_state_dict(torch.load(buffer, weights_only=True))
    assert receiver.num_points == 80 and receiver.num_inside == source.num_inside
    displacements = lattice(source, batch=(2,))
    assert torch.equal(receiver(displacements), source(displacements))
    torch.testing.assert_close(receiver.control_points, source.control_points, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("saved", "loaded", "message"),
    [
        (
            dict(basis="bspline"),
            dict(),
            "basis: the state was saved with basis='bspline' but this FFD has basis='bernstein'",
        ),
        (
            dict(basis="bspline", degree=2),
            dict(basis="bspline"),
            "degree: the state was saved with degree=2 but this FFD has degree=3",
        ),
        (
            dict(shape=(4, 5, 7)),
            dict(),
            r"shape: the state was saved with shape=\(4, 5, 7\) but this FFD has shape=\(4, 5, 6\)",
        ),
    ],
)
def test_state_with_other_hyperparameters_fails_to_load(saved, loaded, message):
    state = build(**saved).state_dict()
    receiver = build(**loaded)
    before = receiver.basis_x.clone()
    with pytest.raises(ValueError, match=message):
        receiver.load_state_dict(state)
    assert torch.equal(receiver.basis_x, before)  # refused before anything was loaded


def test_state_of_another_dimension_fails_to_load():
    with pytest.raises(ValueError, match=r"shape: the state was saved with shape=\(4, 5\)"):
        build().load_state_dict(build(dim=2).state_dict())


def test_saved_shape_as_a_list_loads():
    state = build().state_dict()
    state["_extra_state"] = {**state["_extra_state"], "shape": [4, 5, 6]}
    build().load_state_dict(state)


def test_inconsistent_bases_are_reported():
    state = build().state_dict()
    state["basis_y"] = state["basis_y"][:-1]
    with pytest.raises(RuntimeError, match="basis_y: shape .* does not match"):
        build().load_state_dict(state)


def test_to_dtype_and_module_copies_its_points():
    source = points()
    morph = FFD(source, origin=[0.0, 0, 0], lengths=[1.0, 1, 1], shape=(3, 3, 3))
    displacements = lattice(morph)
    before = morph(displacements)
    source.add_(10.0)  # the caller's points change: the module's do not
    assert torch.equal(morph(displacements), before)
    single = morph.to(torch.float32)
    assert single.basis_x.dtype == torch.float32 and single.inside.dtype == torch.int64
    torch.testing.assert_close(single(displacements.float()).double(), before, rtol=0, atol=1e-5)


def test_numpy_points_and_tensor_box():
    array = points().numpy()
    morph = FFD(array, origin=torch.zeros(3, dtype=F64), lengths=np.ones(3), shape=[3, 3, 3])
    assert morph.points.dtype == F64
    assert torch.equal(morph.points, torch.from_numpy(array))


def test_repr():
    assert repr(build(basis="bspline")).startswith(
        "FFD(num_points=80, num_inside="
    ) and "lattice=4 x 5 x 6, basis='bspline', degree=3" in repr(build(basis="bspline"))


# --------------------------------------------------------------------------- #
# errors
# --------------------------------------------------------------------------- #
BOX = dict(origin=[0.0, 0.0, 0.0], lengths=[1.0, 1.0, 1.0], shape=(4, 4, 4))


@pytest.mark.parametrize(
    ("changes", "error", "message"),
    [
        (
            dict(points=torch.zeros(5, 4, dtype=F64)),
            ValueError,
            r"points must have shape \(N, 2\) or \(N, 3\), got \(5, 4\)",
        ),
        (
            dict(points=torch.zeros(5, dtype=F64)),
            ValueError,
            r"points must have shape \(N, 2\) or \(N, 3\), got \(5,\)",
        ),
        (dict(points=torch.zeros(0, 3, dtype=F64)), ValueError, "points is empty"),
        (
            dict(points=torch.tensor([[0.0, float("nan"), 0.0]])),
            ValueError,
            "points holds 1 NaN or infinite",
        ),
        (
            dict(points=torch.zeros(5, 3, dtype=torch.float16)),
            ValueError,
            "points has dtype torch.float16",
        ),
        (
            dict(points=torch.zeros(5, 3, dtype=torch.int64)),
            ValueError,
            "points must be a floating-point tensor",
        ),
        (
            dict(origin=[0.0, 0.0]),
            ValueError,
            r"origin must have shape \(3,\) for points in 3-D, got \(2,\)",
        ),
        (dict(origin=[0.0, float("inf"), 0.0]), ValueError, "origin holds 1 NaN or infinite"),
        (
            dict(origin=torch.zeros(3)),
            ValueError,
            "origin has dtype torch.float32 but points has torch.float64",
        ),
        (dict(origin=["a", "b", "c"]), ValueError, "origin must hold numbers"),
        (
            dict(lengths=[1.0, 0.0, 1.0]),
            ValueError,
            r"lengths must be > 0 along every axis, got \[1.0, 0.0, 1.0\]",
        ),
        (dict(lengths=[1.0, -2.0, 1.0]), ValueError, "lengths must be > 0 along every axis"),
        (dict(lengths=[1.0, float("nan"), 1.0]), ValueError, "lengths holds 1 NaN or infinite"),
        (
            dict(shape=(4, 4)),
            ValueError,
            r"shape must hold 3 lattice sizes \(n_x, n_y, n_z\) for points in 3-D, got \(4, 4\)",
        ),
        (dict(shape=4), ValueError, "shape must hold 3 lattice sizes"),
        (
            dict(shape=(4, 1, 4)),
            ValueError,
            "shape\\[1\\] must be >= 2 for a Bernstein basis, got 1",
        ),
        (
            dict(shape=(4, 4, 3), basis="bspline"),
            ValueError,
            "shape\\[2\\] must be >= 4 for a B-spline basis of degree 3, got 3",
        ),
        (dict(shape=(4, 2.5, 4)), ValueError, "shape\\[1\\] must be an integer, got 2.5"),
        (
            dict(basis="nurbs"),
            ValueError,
            "basis must be one of 'bernstein', 'bspline'; got 'nurbs'",
        ),
        (dict(degree=3), ValueError, "degree: the Bernstein basis has degree shape\\[k\\] - 1"),
        (dict(basis="bspline", degree=0), ValueError, "degree must be an integer >= 1, got 0"),
        (
            dict(rotation=torch.eye(2, dtype=F64)),
            ValueError,
            r"rotation must have shape \(3, 3\) for points in 3-D, got \(2, 2\)",
        ),
        (dict(rotation=2 * torch.eye(3, dtype=F64)), ValueError, "rotation must be orthogonal"),
        (dict(block_bytes=0), ValueError, "block_bytes must be a finite number > 0"),
    ],
)
def test_constructor_errors_name_the_argument(changes, error, message):
    arguments = dict(points=points(), **BOX)
    arguments.update(changes)
    with pytest.raises(error, match=message):
        FFD(arguments.pop("points"), **arguments)


def test_forward_errors_name_the_argument():
    morph = FFD(points(), **BOX)
    good = lattice(morph)
    with pytest.raises(
        ValueError,
        match=r"displacements must have shape \(\.\.\., 4, 4, 4, 3\) for a 4 x 4 x 4 lattice in 3-D, got \(4, 4, 3, 3\)",
    ):
        morph(good[:, :, :3])
    with pytest.raises(ValueError, match=r"displacements must have shape .* got \(4, 4, 4, 2\)"):
        morph(good[..., :2])
    with pytest.raises(
        ValueError,
        match="displacements has dtype torch.float32 but the module's points has torch.float64",
    ):
        morph(good.float())
    bad = good.clone()
    bad[1, 2, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="displacements holds 1 NaN or infinite"):
        morph(bad)
    with pytest.raises(TypeError, match="displacements must be a torch.Tensor, got ndarray"):
        morph(good.numpy())
    with pytest.raises(ValueError, match=r"points must have shape \(80, 3\), got \(79, 3\)"):
        morph(good, points=points()[1:])
    with pytest.raises(
        ValueError, match="points has dtype torch.float32 but the module's points has torch.float64"
    ):
        morph(good, points=points().float())
    moved = points()
    moved[0, 0] = float("inf")
    with pytest.raises(ValueError, match="points holds 1 NaN or infinite"):
        morph(good, points=moved)


def test_functional_errors_name_the_argument():
    from torchmorph.ffd import ffd_apply

    with pytest.raises(
        ValueError,
        match=r"displacements must have shape \(\.\.\., n_x, n_y, n_z, 3\) for points in 3-D, got \(4, 4, 2\)",
    ):
        ffd_apply(
            points=points(),
            displacements=torch.zeros(4, 4, 2, dtype=F64),
            origin=[0.0] * 3,
            lengths=[1.0] * 3,
        )
    with pytest.raises(
        ValueError,
        match="displacements' lattice shape\\[0\\] must be >= 4 for a B-spline basis of degree 3, got 3",
    ):
        ffd_apply(
            points=points(),
            displacements=torch.zeros(3, 4, 4, 3, dtype=F64),
            origin=[0.0] * 3,
            lengths=[1.0] * 3,
            basis="bspline",
        )
