"""MeshMorph with near-wall stiffening (``stiffening_length``/``stiffening_power``, and the
command's ``--stiffening``): the two-term weights against their literal formula, the
state, POD, the rotation-aware morph and the argument errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import structured_cube

from torchmorph import MeshMorph, PODReducer, SelectionPlan
from torchmorph.cli import EXIT_OK, EXIT_USAGE, main
from torchmorph.mesh.io import read_mesh, write_mesh


def literal(controls, targets, values, power, steep, length):
    r = np.sqrt(((targets[:, None, :] - controls[None, :, :]) ** 2).sum(-1))
    w = r**-power + length ** (steep - power) * r**-steep
    return (w / w.sum(1, keepdims=True)) @ values


@pytest.fixture
def cube():
    mesh = structured_cube(4)
    points = mesh.points[mesh.boundary_nodes]
    d = 0.05 * torch.stack(
        [torch.sin(3 * points[:, 1]), points[:, 0] * points[:, 2], points[:, 1] ** 2], 1
    )
    return mesh, d


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_equals_the_two_term_formula_on_a_selection(cube, mode):
    mesh, d = cube
    plan = SelectionPlan(dict.fromkeys(("x0", "x1", "y0", "y1", "z0", "z1"), 0.45))
    morph = MeshMorph(mesh, plan, stiffening_length=0.15, mode=mode)
    assert morph.idw.stiffening_power == 6.0  # p + 2
    out = morph(d).numpy()
    points = mesh.points.numpy()
    rows = morph.selected.numpy()
    expected = literal(
        points[morph.control_nodes.numpy()],
        points[morph.interior_nodes.numpy()],
        d.numpy()[rows],
        4.0,
        6.0,
        0.15,
    )
    np.testing.assert_allclose(out[morph.interior_nodes.numpy()], expected, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(out[morph.boundary_nodes.numpy()], d.numpy())
    W = morph.weights_matrix()
    np.testing.assert_allclose(W.sum(1).numpy(), 1.0, rtol=0, atol=1e-14)


def test_state_carries_the_stiffening(cube):
    mesh, d = cube
    stiff = MeshMorph(mesh, stiffening_length=0.2, stiffening_power=7.0)
    twin = MeshMorph(mesh, stiffening_length=0.2, stiffening_power=7.0, mode="dense")
    twin.load_state_dict(stiff.state_dict())
    assert torch.allclose(twin(d), stiff(d), atol=1e-15, rtol=0)
    for other in (MeshMorph(mesh), MeshMorph(mesh, stiffening_length=0.3, stiffening_power=7.0)):
        with pytest.raises(ValueError, match="stiffening: the state was saved with"):
            other.load_state_dict(stiff.state_dict())
    with pytest.raises(ValueError, match="stiffening: the state was saved with .*None"):
        stiff.load_state_dict(MeshMorph(mesh).state_dict())


def test_pod_and_rotations_take_a_stiffened_morph(cube):
    mesh, d = cube
    morph = MeshMorph(mesh, stiffening_length=0.2)
    family = torch.stack([d, d.flip(0), 0.5 * d + 0.01])
    reducer = PODReducer(num_modes=3).fit(morph, family)
    assert torch.allclose(reducer(family), morph(family), atol=1e-13, rtol=0)
    turned = morph(d, rotations="fit")
    assert torch.equal(turned[morph.boundary_nodes], d)


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"stiffening_power": 6.0}, "stiffening_power: near-wall stiffening needs"),
        ({"stiffening_length": -1.0}, "stiffening_length must be a finite number > 0"),
        ({"stiffening_length": 0.1, "stiffening_power": 3.0}, "larger than power"),
        ({"stiffening_length": 0.1, "mode": "tree"}, "mode: near-wall stiffening"),
        ({"stiffening_length": 0.1, "method": "rbf"}, "stiffening_length: an option of"),
    ],
)
def test_bad_arguments(cube, keywords, message):
    mesh, _ = cube
    with pytest.raises(ValueError, match=message):
        MeshMorph(mesh, **keywords)


def test_the_command_stiffens(tmp_path, cube, capsys):
    mesh, d = cube
    path = tmp_path / "cube.vtu"
    write_mesh(path, mesh)
    np.save(tmp_path / "d.npy", d.numpy())
    out = tmp_path / "out.vtu"
    argv = ["morph", str(path), "-d", str(tmp_path / "d.npy"), "-o", str(out), "--no-progress"]
    assert main([*argv, "--stiffening", "0.2", "--stiffening-power", "7"]) == EXIT_OK
    assert "stiffened near the walls (q=7, length 0.2)" in capsys.readouterr().out
    field = read_mesh(out, return_data=True)[1]["displacement"].numpy()
    reference = read_mesh(path)
    expected = MeshMorph(reference, stiffening_length=0.2, stiffening_power=7.0)(d).numpy()
    np.testing.assert_allclose(field, expected, rtol=0, atol=1e-12)
    for options, message in (
        (["--stiffening-power", "7"], "--stiffening-power: needs --stiffening"),
        (["--stiffening", "0.2", "--stiffening-power", "3"], "must be larger than --power"),
        (["--stiffening", "0.2", "--method", "rbf"], "--stiffening: near-wall stiffening"),
    ):
        assert main([*argv, *options]) == EXIT_USAGE
        assert message in capsys.readouterr().err
