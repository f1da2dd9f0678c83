"""``torchmorph morph --adaptive TOL [--max-controls N]``: the error-driven selection."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import structured_cube

from torchmorph.cli import EXIT_ERROR, EXIT_OK, EXIT_USAGE, main
from torchmorph.mesh.io import read_mesh, write_mesh
from torchmorph.mesh.norms import relative_nodal_error
from torchmorph.morph import MeshMorph
from torchmorph.selection import AdaptivePlan, Region, SelectionPlan


@pytest.fixture
def cube_file(tmp_path):
    """A 4x4x4-cell cube (125 nodes, 98 boundary, 384 tets) written to a .vtu file."""
    path = tmp_path / "cube.vtu"
    write_mesh(path, structured_cube(4))
    return path


def _bend(points: np.ndarray) -> np.ndarray:
    out = np.zeros_like(points)
    out[:, 1] = 0.1 * np.sin(3.0 * points[:, 2])
    return out


def _morph(tmp_path, cube_file, *options):
    mesh = read_mesh(cube_file)
    rows = _bend(mesh.points[mesh.node_set("x1")].numpy())
    np.save(tmp_path / "d.npy", rows)
    out = tmp_path / "out.vtu"
    arguments = ["morph", str(cube_file), "-d", str(tmp_path / "d.npy"), "-o", str(out)]
    code = main([*arguments, "--moving", "x1", "--no-progress", *options])
    return code, out, rows


def _full_idw_error(cube_file, out, rows):
    """The written morph's nodal error against full IDW (every boundary node a control)."""
    mesh = read_mesh(cube_file)
    point_data = read_mesh(out, return_data=True)[1]
    full = MeshMorph(mesh)
    reference = full(full.boundary_displacement("x1", lambda x: torch.from_numpy(rows)))
    error = relative_nodal_error(mesh, point_data["displacement"].to(reference.dtype), reference)
    return float(error), int(point_data["control_point"].sum())


def test_adaptive_reaches_the_tolerance(tmp_path, cube_file, capsys):
    code, out, rows = _morph(tmp_path, cube_file, "--adaptive", "0.02")
    assert code == EXIT_OK
    error, controls = _full_idw_error(cube_file, out, rows)
    assert error <= 0.02
    assert 0 < controls < 98
    text = capsys.readouterr().out
    assert "adaptive: nodal error <= 0.02, from a count-stratified start" in text
    assert f"controls        {controls} of 98 boundary nodes" in text
    assert f"nodal error     {error:.4g} against full IDW (tolerance" in text


def test_adaptive_equals_the_plan(tmp_path, cube_file):
    code, out, rows = _morph(tmp_path, cube_file, "--adaptive", "0.02")
    assert code == EXIT_OK
    mesh = read_mesh(cube_file)
    probe = MeshMorph(mesh)
    boundary = probe.boundary_displacement("x1", lambda x: torch.from_numpy(rows))
    morph = MeshMorph(mesh, AdaptivePlan(0.02, boundary))
    displacement = read_mesh(out, return_data=True)[1]["displacement"]
    torch.testing.assert_close(displacement, morph(boundary), rtol=0, atol=1e-14)


def test_max_controls_is_a_budget_and_warns(tmp_path, cube_file, capsys):
    code, out, rows = _morph(tmp_path, cube_file, "--adaptive", "1e-6", "--max-controls", "9")
    assert code == EXIT_OK
    _, controls = _full_idw_error(cube_file, out, rows)
    assert controls == 9
    err = capsys.readouterr().err
    assert "--adaptive 1e-06 not reached" in err and "(budget)" in err


def test_adaptive_starts_from_a_selection(tmp_path, cube_file, capsys):
    code, out, rows = _morph(
        tmp_path, cube_file, "--adaptive", "0.02", "--select", "0.6", "--enrich", "z0"
    )
    assert code == EXIT_OK
    written, point_data, _ = read_mesh(out, return_data=True)
    flags = point_data["control_point"].bool()
    assert flags[written.node_set("z0")].all()
    mesh = read_mesh(cube_file).with_node_sets({"(boundary)": read_mesh(cube_file).boundary_nodes})
    start = SelectionPlan([Region("(boundary)", 0.6)], enrich=["z0"]).select(
        mesh, generator=torch.Generator().manual_seed(0)
    )
    assert flags[start].all()
    assert _full_idw_error(cube_file, out, rows)[0] <= 0.02
    assert "from ESIDW" in capsys.readouterr().out


def test_adaptive_from_the_enrichment_alone(tmp_path, cube_file, capsys):
    code, out, _ = _morph(tmp_path, cube_file, "--adaptive", "0.05", "--enrich", "z0")
    assert code == EXIT_OK
    written, point_data, _ = read_mesh(out, return_data=True)
    assert point_data["control_point"].bool()[written.node_set("z0")].all()
    assert "from the enrichment sets z0" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--adaptive", "0"], "argument --adaptive: must be a finite number > 0"),
        (["--adaptive", "-0.1"], "argument --adaptive: must be a finite number > 0"),
        (["--adaptive", "x"], "argument --adaptive: expected a number"),
        (["--adaptive", "0.1", "--max-controls", "0"], "--max-controls: must be an integer >= 1"),
        (["--adaptive", "0.1", "--max-controls", "2.5"], "--max-controls: expected an integer"),
        (["--max-controls", "5"], "argument --max-controls: needs --adaptive"),
    ],
)
def test_bad_adaptive_options(tmp_path, cube_file, capsys, options, message):
    code, _, _ = _morph(tmp_path, cube_file, *options)
    assert code == EXIT_USAGE
    assert message in capsys.readouterr().err


def test_a_zero_displacement_is_refused_by_name(tmp_path, cube_file, capsys):
    np.save(tmp_path / "zero.npy", np.zeros(3))
    out = tmp_path / "out.vtu"
    code = main(
        ["morph", str(cube_file), "-d", str(tmp_path / "zero.npy"), "-o", str(out)]
        + ["--moving", "x1", "--no-progress", "--adaptive", "0.01"]
    )
    assert code == EXIT_ERROR
    err = capsys.readouterr().err
    assert "--adaptive: displacements: member 0 of the family has a zero reference" in err
    assert "Traceback" not in err


def test_adaptive_with_rbf_reduces_the_rbf(tmp_path, cube_file, capsys):
    from torchmorph.rbf import RBF

    code, out, rows = _morph(
        tmp_path, cube_file, "--adaptive", "0.02", "--method", "rbf", "--kernel", "cubic"
    )
    assert code == EXIT_OK
    text = capsys.readouterr().out
    assert "adaptive: RBF error at the boundary nodes <= 0.02, from no control" in text
    assert "boundary error  " in text and "nodal error" not in text.split("adaptive")[1]
    point_data = read_mesh(out, return_data=True)[1]
    flags = point_data["control_point"].bool()
    assert 4 <= int(flags.sum()) < 98
    # the boundary error, measured here: the cubic RBF of the kept controls at every
    # boundary node against the boundary displacement
    mesh = read_mesh(cube_file)
    boundary = mesh.boundary_nodes
    probe = MeshMorph(mesh)
    values = probe.boundary_displacement("x1", lambda x: torch.from_numpy(rows))
    kept = torch.nonzero(flags[boundary]).flatten()
    points = mesh.points[boundary]
    fitted = RBF(points[kept], points, kernel="cubic")(values[kept])
    error = (fitted - values).norm(dim=1).max() / values.norm(dim=1).max()
    assert float(error) <= 0.02
    line = next(line for line in text.splitlines() if line.startswith("boundary error"))
    assert line.split()[2] == f"{float(error):.4g}:"  # the error the selection measured
