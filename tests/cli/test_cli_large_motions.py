"""``torchmorph morph --rotations`` and ``--steps K``: large motions from the command.

A cube whose whole boundary turns by 120° about the z axis: with ``--rotations`` every
node must follow the rigid rotation; plain IDW does not. ``--steps`` walks the motion in
increments and says at which step a cell first inverts.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import structured_cube

from torchmorph.cli import EXIT_OK, EXIT_USAGE, main
from torchmorph.mesh.io import read_mesh, write_mesh


@pytest.fixture
def cube_file(tmp_path):
    path = tmp_path / "cube.vtu"
    write_mesh(path, structured_cube(4))
    return path


def _morph(tmp_path, cube_file, degrees, *options):
    mesh = read_mesh(cube_file)
    points = mesh.points.numpy()
    centre = points.mean(0)
    boundary = mesh.boundary_nodes.numpy()
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    x, y = points[:, 0] - centre[0], points[:, 1] - centre[1]
    rigid = np.stack([c * x - s * y - x, s * x + c * y - y, 0 * x], 1)
    np.save(tmp_path / "d.npy", rigid[boundary])
    out = tmp_path / "out.vtu"
    code = main(
        ["morph", str(cube_file), "-d", str(tmp_path / "d.npy"), "-o", str(out), "--no-progress"]
        + list(options)
    )
    return code, out, rigid


def test_rotations_turn_every_node_rigidly(tmp_path, cube_file, capsys):
    code, out, rigid = _morph(tmp_path, cube_file, 120.0, "--rotations")
    assert code == EXIT_OK
    displacement = read_mesh(out, return_data=True)[1]["displacement"].numpy()
    np.testing.assert_allclose(displacement, rigid, rtol=0, atol=1e-10)
    assert "(rotation-aware)" in capsys.readouterr().out
    code, out, _ = _morph(tmp_path, cube_file, 120.0)
    plain = read_mesh(out, return_data=True)[1]["displacement"].numpy()
    assert np.abs(plain - rigid).max() > 1e-2


def test_steps_walk_the_motion_and_report_the_first_inverted_step(tmp_path, cube_file, capsys):
    # the file gives the final displacement: the steps walk its chords in equal parts
    code, out, rigid = _morph(tmp_path, cube_file, 120.0, "--rotations", "--steps", "3")
    assert code == EXIT_OK
    mesh, point_data, cell_data = read_mesh(out, return_data=True)
    boundary = mesh.boundary_nodes.numpy()
    moved = point_data["displacement"].numpy()[boundary]
    np.testing.assert_allclose(moved, rigid[boundary], rtol=0, atol=1e-12)
    assert int(cell_data["inverted"].sum()) == 0
    text = capsys.readouterr()
    assert "(rotation-aware, in 3 steps)" in text.out
    assert "first inverted" not in text.err
    # plain IDW in two steps of a half turn folds cells, and says at which step
    code, _, _ = _morph(tmp_path, cube_file, 180.0, "--steps", "2")
    text = capsys.readouterr()
    assert "--steps 2: a cell first inverted at step" in text.err


def test_steps_must_be_a_positive_integer(tmp_path, cube_file, capsys):
    code, _, _ = _morph(tmp_path, cube_file, 10.0, "--steps", "0")
    assert code == EXIT_USAGE
    assert "argument --steps: must be an integer >= 1, got '0'" in capsys.readouterr().err
