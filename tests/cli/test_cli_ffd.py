"""``torchmorph morph --ffd LATTICE``: the boundary moved by a free-form deformation
lattice, the volume by IDW; against the library's FFD then MeshMorph, and the lattice
archive's errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import structured_cube

from torchmorph import FFD, MeshMorph
from torchmorph.cli import EXIT_OK, EXIT_USAGE, main
from torchmorph.mesh.io import read_mesh, write_mesh


@pytest.fixture
def cube(tmp_path):
    path = tmp_path / "cube.vtu"
    write_mesh(path, structured_cube(4))
    lattice = np.zeros((3, 3, 2, 3))
    lattice[1, 1, 1] = [0.02, -0.03, 0.08]  # lift the middle of the top layer
    np.savez(
        tmp_path / "lattice.npz", origin=[0.2, 0.2, 0.6], lengths=[0.6, 0.6, 0.5],
        displacements=lattice,
    )  # fmt: skip
    return path, read_mesh(path), lattice


def run(tmp_path, path, *options):
    out = tmp_path / "out.vtu"
    code = main(["morph", str(path), "-o", str(out), "--no-progress", *options])
    field = read_mesh(out, return_data=True)[1]["displacement"].numpy() if code == 0 else None
    return code, field


def test_the_lattice_moves_the_boundary_and_idw_the_volume(tmp_path, cube, capsys):
    path, mesh, lattice = cube
    code, field = run(tmp_path, path, "--ffd", str(tmp_path / "lattice.npz"))
    assert code == EXIT_OK
    out = capsys.readouterr().out
    assert "FFD lattice 3 x 3 x 2 (bernstein)" in out
    boundary = mesh.boundary_nodes
    ffd = FFD(
        mesh.points[boundary], origin=[0.2, 0.2, 0.6], lengths=[0.6, 0.6, 0.5], shape=(3, 3, 2)
    )
    moved = ffd(torch.as_tensor(lattice))
    expected = MeshMorph(mesh)(moved).numpy()
    np.testing.assert_allclose(field, expected, rtol=0, atol=1e-14)
    assert np.abs(field[boundary.numpy()]).max() > 0.01  # the top face moved
    outside = ~ffd.inside
    assert np.abs(field[boundary.numpy()][outside.numpy()]).max() == 0.0


def test_moving_sets_limit_the_lattice(tmp_path, cube):
    path, mesh, _ = cube
    code, field = run(tmp_path, path, "--ffd", str(tmp_path / "lattice.npz"), "--moving", "z1")
    assert code == EXIT_OK
    top = mesh.node_set("z1").numpy()
    others = np.setdiff1d(mesh.boundary_nodes.numpy(), top)
    assert np.abs(field[others]).max() == 0.0
    assert np.abs(field[top]).max() > 0.01


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"origin": [0, 0, 0], "lengths": [1, 1, 1]}, "lacks displacements"),
        (
            {"origin": [0, 0, 0], "lengths": [1, 1, 1], "displacements": np.zeros((2, 2, 3))},
            "displacements must have shape (n_1, ..., n_3, 3)",
        ),
        (
            {"origin": [0, 0, 0], "lengths": [1, 1, -1], "displacements": np.zeros((2, 2, 2, 3))},
            "lengths",
        ),
        (
            {"origin": [5, 5, 5], "lengths": [1, 1, 1], "displacements": np.zeros((2, 2, 2, 3))},
            "no boundary node lies in the lattice's box",
        ),
        (
            {
                "origin": [0, 0, 0],
                "lengths": [1, 1, 1],
                "displacements": np.zeros((2, 2, 2, 3)),
                "scale": 2.0,
            },
            "unknown array(s) scale",
        ),
    ],
)
def test_bad_lattices(tmp_path, cube, capsys, arrays, message):
    path, _, _ = cube
    np.savez(tmp_path / "bad.npz", **arrays)
    code, _ = run(tmp_path, path, "--ffd", str(tmp_path / "bad.npz"))
    assert code != EXIT_OK
    assert message in capsys.readouterr().err


def test_one_of_displacement_and_ffd(tmp_path, cube, capsys):
    path, _, _ = cube
    np.save(tmp_path / "d.npy", np.zeros(3))
    for options in ([], ["-d", str(tmp_path / "d.npy"), "--ffd", str(tmp_path / "lattice.npz")]):
        assert run(tmp_path, path, *options)[0] == EXIT_USAGE
        assert "a displacement file (-d) or an FFD lattice (--ffd)" in capsys.readouterr().err
    code, _ = run(tmp_path, path, "--ffd", str(tmp_path / "lattice.npz"), "--batch-index", "0")
    assert code == EXIT_USAGE
