"""``torchmorph morph --mode tree [--tree-tolerance TOL]`` and ``--method rbf --rbf-solver
partition | sparse``: the command's tree-approximated IDW, partition-of-unity RBF and
sparse Wendland RBF against the library, and the combinations that do not go together."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import structured_cube

from torchmorph import MeshMorph
from torchmorph.cli import EXIT_OK, EXIT_USAGE, main
from torchmorph.mesh.io import read_mesh, write_mesh


@pytest.fixture
def case(tmp_path):
    path = tmp_path / "cube.vtu"
    write_mesh(path, structured_cube(5))
    mesh = read_mesh(path)
    points = mesh.points.numpy()[mesh.boundary_nodes.numpy()]
    x, y, z = points.T
    boundary = 0.05 * np.stack([np.sin(3 * y) * z, np.cos(2 * x) * y, x * y * z], 1)
    np.save(tmp_path / "d.npy", boundary)
    return path, mesh, torch.as_tensor(boundary)


def run(tmp_path, path, *options):
    out = tmp_path / "out.vtu"
    argv = ["morph", str(path), "-d", str(tmp_path / "d.npy"), "-o", str(out), "--no-progress"]
    code = main([*argv, *options])
    field = read_mesh(out, return_data=True)[1]["displacement"].numpy() if code == 0 else None
    return code, field


def test_tree_mode_keeps_its_tolerance(tmp_path, case, capsys):
    path, mesh, boundary = case
    code, field = run(tmp_path, path, "--mode", "tree", "--tree-tolerance", "1e-3")
    assert code == EXIT_OK
    assert "tree: far controls by clusters, tolerance 0.001" in capsys.readouterr().out
    exact = MeshMorph(mesh)(boundary).numpy()
    assert np.linalg.norm(field - exact) <= 1e-3 * np.linalg.norm(exact)
    np.testing.assert_array_equal(field[mesh.boundary_nodes.numpy()], boundary.numpy())


def test_auto_mode_takes_the_tree_by_its_tolerance(tmp_path, case, capsys, monkeypatch):
    """``--tree-tolerance`` with the default ``--mode auto``: the tree where it pays
    (here from 1,000 pairs, the threshold lowered), the exact morph below that."""
    import torchmorph.idw._tree_mode as tree_mode

    path, mesh, boundary = case
    exact = MeshMorph(mesh)(boundary).numpy()
    code, field = run(tmp_path, path, "--tree-tolerance", "1e-3")
    assert code == EXIT_OK and "tree:" not in capsys.readouterr().out
    np.testing.assert_allclose(field, exact, rtol=0, atol=1e-12)
    monkeypatch.setattr(tree_mode, "AUTO_TREE_PAIRS", ((1e-5, 1000),))
    code, field = run(tmp_path, path, "--tree-tolerance", "1e-3")
    assert code == EXIT_OK
    assert "tree: far controls by clusters, tolerance 0.001" in capsys.readouterr().out
    assert np.linalg.norm(field - exact) <= 1e-3 * np.linalg.norm(exact)


def test_partition_solver_equals_the_library(tmp_path, case, capsys):
    path, mesh, boundary = case
    code, field = run(tmp_path, path, "--method", "rbf", "--rbf-solver", "partition")
    assert code == EXIT_OK
    assert "partition of unity" in capsys.readouterr().out
    expected = MeshMorph(mesh, method="rbf", solver="partition")(boundary).numpy()
    np.testing.assert_allclose(field, expected, rtol=0, atol=1e-14)


def test_the_partition_fit_to_a_tolerance_equals_the_library(tmp_path, case, capsys):
    path, mesh, boundary = case
    options = ["--method", "rbf", "--rbf-solver", "partition", "--fit-tolerance", "1e-8"]
    code, field = run(tmp_path, path, *options)
    assert code == EXIT_OK
    assert "the global fit to 1e-08 by iterations" in capsys.readouterr().out
    expected = MeshMorph(mesh, method="rbf", solver="partition", fit_tolerance=1e-8)
    np.testing.assert_allclose(field, expected(boundary).numpy(), rtol=0, atol=1e-14)
    dense = MeshMorph(mesh, method="rbf")(boundary).numpy()
    np.testing.assert_allclose(field, dense, rtol=0, atol=1e-6 * np.abs(dense).max())


def test_sparse_solver_equals_the_library(tmp_path, case, capsys):
    path, mesh, boundary = case
    options = ["--method", "rbf", "--kernel", "wendland_c2", "--support-radius", "0.6"]
    code, field = run(tmp_path, path, *options, "--rbf-solver", "sparse")
    assert code == EXIT_OK
    assert "sparse: kernel and evaluation matrices" in capsys.readouterr().out
    expected = MeshMorph(
        mesh, method="rbf", solver="sparse", kernel="wendland_c2", support_radius=0.6
    )(boundary).numpy()
    np.testing.assert_allclose(field, expected, rtol=0, atol=1e-14)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--mode", "dense", "--tree-tolerance", "1e-3"], "--tree-tolerance: needs --mode tree"),
        (["--method", "rbf", "--tree-tolerance", "1e-3"], "--tree-tolerance: the IDW tree's"),
        (["--rbf-solver", "partition"], "--rbf-solver: an RBF option"),
        (["--fit-tolerance", "1e-4"], "--fit-tolerance: an RBF option"),
        (["--method", "rbf", "--fit-tolerance", "1e-4"], "--fit-tolerance: the partition of"),
        (["--method", "rbf", "--mode", "tree"], "--mode: tree is IDW's"),
        (
            ["--method", "rbf", "--rbf-solver", "partition", "--mode", "dense"],
            "--mode: --rbf-solver partition may fit the partition of unity",
        ),
        (
            ["--method", "rbf", "--rbf-solver", "sparse"],
            "--rbf-solver: sparse needs a compactly supported --kernel",
        ),
        (["--mode", "tree", "--stiffening", "0.1"], "--stiffening: near-wall stiffening has no"),
    ],
)
def test_bad_combinations(tmp_path, case, capsys, options, message):
    path, _, _ = case
    code, _ = run(tmp_path, path, *options)
    assert code == EXIT_USAGE
    assert message in capsys.readouterr().err
