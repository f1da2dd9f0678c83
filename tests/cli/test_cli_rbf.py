"""``torchmorph morph --method rbf``: the interior moved by radial basis functions from the
command, compared with scipy's RBFInterpolator and the library's MeshMorph; the RBF options
and the combinations that do not go together."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import structured_cube
from scipy.interpolate import RBFInterpolator

from torchmorph import MeshMorph
from torchmorph.cli import EXIT_OK, EXIT_USAGE, main
from torchmorph.mesh.io import read_mesh, write_mesh

FACES = ("x0", "x1", "y0", "y1", "z0", "z1")


@pytest.fixture
def case(tmp_path):
    """A cube file and a smooth displacement of its boundary nodes (N_b, 3) in d.npy."""
    path = tmp_path / "cube.vtu"
    write_mesh(path, structured_cube(4))
    mesh = read_mesh(path)
    points = mesh.points.numpy()[mesh.boundary_nodes.numpy()]
    x, y, z = points.T
    boundary = 0.05 * np.stack([np.sin(3 * y) * z, np.cos(2 * x) * y, x * y * z], 1)
    np.save(tmp_path / "d.npy", boundary)
    return path, mesh, boundary


def run(tmp_path, path, *options, displacement="d.npy"):
    out = tmp_path / "out.vtu"
    argv = ["morph", str(path), "-d", str(tmp_path / displacement), "-o", str(out)]
    code = main([*argv, "--no-progress", *options])
    field = read_mesh(out, return_data=True)[1]["displacement"].numpy() if code == 0 else None
    return code, field


def test_a_global_kernel_equals_scipy(tmp_path, case, capsys):
    path, mesh, boundary = case
    code, field = run(
        tmp_path, path, "--method", "rbf", "--kernel", "gaussian", "--shape-parameter", "2"
    )
    assert code == EXIT_OK
    out = capsys.readouterr().out
    assert "interpolation   RBF gaussian, shape parameter 2, polynomial degree 1" in out
    assert "method          RBF: every boundary node is a control point" in out
    points = mesh.points.numpy()
    reference = RBFInterpolator(
        points[mesh.boundary_nodes.numpy()], boundary, kernel="gaussian", epsilon=2.0, degree=1
    )(points[mesh.interior_nodes.numpy()])
    np.testing.assert_allclose(field[mesh.interior_nodes.numpy()], reference, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(field[mesh.boundary_nodes.numpy()], boundary)


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
def test_a_wendland_kernel_equals_the_library(tmp_path, case, capsys, mode):
    path, mesh, boundary = case
    code, field = run(
        tmp_path,
        path,
        *("--method", "rbf", "--kernel", "wendland_c2", "--support-radius", "1.5"),
        *("--degree", "0", "--mode", mode),
    )
    assert code == EXIT_OK
    assert "RBF wendland_c2, support radius 1.5, polynomial degree 0" in capsys.readouterr().out
    morph = MeshMorph(mesh, method="rbf", kernel="wendland_c2", support_radius=1.5, degree=0)
    expected = morph(torch.as_tensor(boundary)).numpy()
    np.testing.assert_allclose(field, expected, rtol=0, atol=1e-12)


def test_a_selection_moves_a_translation_rigidly(tmp_path, case, capsys):
    # every boundary node translated: the RBF's linear tail reproduces it on any selection
    path, mesh, _ = case
    np.save(tmp_path / "t.npy", np.array([0.1, -0.05, 0.2]))
    code, field = run(
        tmp_path,
        path,
        *("--method", "rbf", "--select", "0.45", "--moving", *FACES),
        displacement="t.npy",
    )
    assert code == EXIT_OK
    out = capsys.readouterr().out
    assert "method          RBF on the controls of SIDW (random)" in out
    controls = int(out.split("controls        ")[1].split()[0])
    assert controls < mesh.boundary_nodes.numel()
    np.testing.assert_allclose(field, np.broadcast_to([0.1, -0.05, 0.2], field.shape), atol=1e-12)


def test_steps_work_with_rbf(tmp_path, case, capsys):
    path, mesh, boundary = case
    code, field = run(tmp_path, path, "--method", "rbf", "--steps", "2")
    assert code == EXIT_OK
    assert "(in 2 steps)" in capsys.readouterr().out
    np.testing.assert_allclose(field[mesh.boundary_nodes.numpy()], boundary, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (("--kernel", "cubic"), "argument --kernel: an RBF option; needs --method rbf"),
        (("--shape-parameter", "2"), "argument --shape-parameter: an RBF option; needs --method"),
        (("--support-radius", "1"), "argument --support-radius: an RBF option; needs --method"),
        (("--degree", "2"), "argument --degree: an RBF option; needs --method rbf"),
        (("--method", "rbf", "--power", "2"), "argument --power: the IDW exponent"),
        (
            ("--method", "rbf", "--rotations"),
            "argument --rotations: rotation-aware morphing blends IDW weights",
        ),
        (
            ("--method", "rbf", "--support-radius", "1"),
            "argument --support-radius: only the compactly supported kernels",
        ),
        (
            ("--method", "rbf", "--kernel", "wendland_c4"),
            "argument --support-radius: required with --kernel wendland_c4",
        ),
        (
            (
                "--method",
                "rbf",
                "--kernel",
                "wendland_c0",
                "--support-radius",
                "1",
                "--shape-parameter",
                "2",
            ),
            "argument --shape-parameter: --kernel wendland_c0 is scaled by --support-radius",
        ),
        (
            ("--method", "rbf", "--kernel", "inverse_quadratic"),
            "argument --shape-parameter: required with --kernel inverse_quadratic",
        ),
        (("--method", "rbf", "--kernel", "bessel"), "argument --kernel: invalid choice: 'bessel'"),
        (("--method", "rbf", "--degree", "-2"), "argument --degree: must be an integer >= -1"),
        (("--method", "rbf", "--shape-parameter", "0"), "argument --shape-parameter: must be a"),
        (("--method", "spline"), "argument --method: invalid choice: 'spline'"),
        # one vocabulary: --epsilon is fTetWild's envelope in `torchmorph mesh`
        (("--method", "rbf", "--epsilon", "2"), "unrecognized arguments: --epsilon 2"),
    ],
)
def test_bad_combinations_are_usage_errors(tmp_path, case, capsys, options, message):
    path, _, _ = case
    code, _ = run(tmp_path, path, *options)
    assert code == EXIT_USAGE
    assert message in capsys.readouterr().err
