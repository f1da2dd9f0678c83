"""The ``torchmorph`` console command, run in-process through ``main``."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import types

import numpy as np
import pytest
import torch
from conftest import structured_cube, write_cad

import torchmorph
from torchmorph.cli import EXIT_ERROR, EXIT_INVERTED, EXIT_OK, EXIT_USAGE, build_parser, main
from torchmorph.mesh import TetMesh
from torchmorph.mesh.io import read_mesh, write_mesh
from torchmorph.morph import MeshMorph
from torchmorph.selection import Region, SelectionPlan

FACES = ("x0", "x1", "y0", "y1", "z0", "z1")


@pytest.fixture
def cube_file(tmp_path):
    """A 4x4x4-cell cube (125 nodes, 98 boundary, 384 tets) written to a .vtu file."""
    path = tmp_path / "cube.vtu"
    write_mesh(path, structured_cube(4))
    return path


def _moving_rows(seed: int = 0, rows: int = 25) -> np.ndarray:
    generator = np.random.default_rng(seed)
    return 0.05 * generator.standard_normal((rows, 3))


def _morph(tmp_path, cube_file, displacement, *options, name="d.npy"):
    """Run ``morph`` on the cube with a saved displacement; return (code, out path)."""
    source = tmp_path / name
    if name.endswith(".npy"):
        np.save(source, displacement)
    else:
        np.savetxt(source, displacement, delimiter="," if name.endswith(".csv") else " ")
    out = tmp_path / "out.vtu"
    code = main(
        ["morph", str(cube_file), "-d", str(source), "-o", str(out), "--no-progress", *options]
    )
    return code, out


def _result(out):
    mesh, point_data, cell_data = read_mesh(out, return_data=True)
    return mesh, point_data, cell_data


# --------------------------------------------------------------------------- help


@pytest.mark.parametrize("command", [[], ["info"], ["morph"], ["reproduce"], ["mesh"]])
def test_help_exits_zero(command, capsys):
    assert main([*command, "--help"]) == EXIT_OK
    assert "usage: torchmorph" in capsys.readouterr().out


def test_version(capsys):
    assert main(["--version"]) == EXIT_OK
    assert capsys.readouterr().out.strip() == f"torchmorph {torchmorph.__version__}"


def test_no_command_is_a_usage_error(capsys):
    assert main([]) == EXIT_USAGE
    assert "required" in capsys.readouterr().err


@pytest.mark.slow  # a fresh interpreter imports torch
def test_console_script_help():
    executable = shutil.which("torchmorph")
    if executable is None:
        pytest.skip("the torchmorph console script is not on PATH")
    done = subprocess.run(
        [executable, "--help"], check=False, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0
    assert "morph" in done.stdout and "reproduce" in done.stdout


# --------------------------------------------------------------------------- info


def test_info_counts(cube_file, capsys):
    assert main(["info", str(cube_file), "--no-progress"]) == EXIT_OK
    out = capsys.readouterr().out
    assert "125 (98 boundary, 27 interior)" in out
    lines = {line.split()[0]: line for line in out.splitlines() if line.strip()}
    assert lines["cells"].split()[1] == "384" and lines["tetra"].split()[1] == "384"
    assert lines["dimension"].split()[1] == "3-D"
    for name in FACES:
        assert f"{name}  25 nodes (node set)" in out
    assert "0 boundary node(s) in no marker" in out
    assert "[0, 0, 0] .. [1, 1, 1]" in out
    assert "max 1.732" in out  # Kuhn tets of a cube: edge ratio sqrt(3)
    assert "min volume      0.00260417" in out  # (1/4)^3 / 6


# --------------------------------------------------------------------------- morph


def test_morph_moving_rows_exact_and_interior_matches_meshmorph(tmp_path, cube_file, capsys):
    rows = _moving_rows()
    code, out = _morph(tmp_path, cube_file, rows, "--moving", "x1")
    assert code == EXIT_OK
    printed = capsys.readouterr().out
    assert "controls        98 of 98 boundary nodes" in printed
    assert "inverted cells  0 of 384" in printed

    mesh, point_data, cell_data = _result(out)
    displacement = point_data["displacement"]
    moving = mesh.node_set("x1")
    assert torch.equal(displacement[moving], torch.from_numpy(rows))  # exact, in node-id order

    reference = read_mesh(cube_file)
    morph = MeshMorph(reference)
    boundary = torch.zeros(morph.num_boundary, 3, dtype=torch.float64)
    boundary[torch.searchsorted(morph.boundary_nodes, moving)] = torch.from_numpy(rows)
    expected = morph(boundary)
    torch.testing.assert_close(displacement, expected, rtol=0, atol=1e-14)
    fixed = reference.boundary_nodes[~torch.isin(reference.boundary_nodes, moving)]
    assert torch.count_nonzero(displacement[fixed]) == 0

    # the reference geometry is written, with flags and quality
    torch.testing.assert_close(mesh.points, reference.points, rtol=0, atol=0)
    assert torch.equal(
        point_data["control_point"].bool().nonzero().flatten(), reference.boundary_nodes
    )
    assert cell_data["quality"].shape == (384,)
    torch.testing.assert_close(
        cell_data["quality_reference"], torch.full((384,), 3.0**0.5, dtype=torch.float64)
    )
    assert int(cell_data["inverted"].sum()) == 0


def test_morph_layouts_agree(tmp_path, cube_file):
    reference = read_mesh(cube_file)
    moving = reference.node_set("x1")
    rows = _moving_rows(1)
    results = []
    nodal = np.zeros((reference.num_nodes, 3))
    nodal[moving.numpy()] = rows
    boundary = nodal[reference.boundary_nodes.numpy()]
    for array in (rows, boundary, nodal):
        code, out = _morph(tmp_path, cube_file, array, "--moving", "x1")
        assert code == EXIT_OK
        results.append(_result(out)[1]["displacement"])
    # without --moving the file gives every boundary node
    code, out = _morph(tmp_path, cube_file, boundary)
    assert code == EXIT_OK
    results.append(_result(out)[1]["displacement"])
    for other in results[1:]:
        torch.testing.assert_close(other, results[0], rtol=0, atol=0)


def test_morph_translation_and_text_files(tmp_path, cube_file):
    shift = np.array([0.03, -0.01, 0.02])
    code, out = _morph(tmp_path, cube_file, shift, "--moving", "x1")
    assert code == EXIT_OK
    translated = _result(out)[1]["displacement"]
    moving = read_mesh(cube_file).node_set("x1")
    assert torch.equal(translated[moving], torch.from_numpy(shift).expand(25, 3))
    for name in ("d.csv", "d.txt"):
        code, out = _morph(
            tmp_path, cube_file, np.tile(shift, (25, 1)), "--moving", "x1", name=name
        )
        assert code == EXIT_OK
        torch.testing.assert_close(_result(out)[1]["displacement"], translated, rtol=0, atol=1e-15)


def test_morph_rows_outside_moving_sets_are_fixed_with_warning(tmp_path, cube_file, capsys):
    reference = read_mesh(cube_file)
    nodal = np.full((reference.num_nodes, 3), 0.01)
    code, out = _morph(tmp_path, cube_file, nodal, "--moving", "x1")
    assert code == EXIT_OK
    assert "WARNING" in capsys.readouterr().err
    displacement = _result(out)[1]["displacement"]
    moving = reference.node_set("x1")
    fixed = reference.boundary_nodes[~torch.isin(reference.boundary_nodes, moving)]
    assert torch.count_nonzero(displacement[fixed]) == 0
    assert torch.all(displacement[moving] == 0.01)


def test_morph_batch_index(tmp_path, cube_file, capsys):
    batch = np.stack([_moving_rows(seed) for seed in range(3)])
    code, out = _morph(tmp_path, cube_file, batch, "--moving", "x1", "--batch-index", "-2")
    assert code == EXIT_OK
    chosen = _result(out)[1]["displacement"]
    code, out = _morph(tmp_path, cube_file, batch[1], "--moving", "x1")
    torch.testing.assert_close(chosen, _result(out)[1]["displacement"], rtol=0, atol=0)
    capsys.readouterr()
    code, _ = _morph(tmp_path, cube_file, batch, "--moving", "x1")
    assert code == EXIT_ERROR
    assert "--batch-index" in capsys.readouterr().err
    code, _ = _morph(tmp_path, cube_file, batch, "--moving", "x1", "--batch-index", "3")
    assert code == EXIT_ERROR
    assert "out of range" in capsys.readouterr().err


def _controls(out) -> int:
    return int(_result(out)[1]["control_point"].sum())


def test_select_reduces_controls(tmp_path, cube_file, capsys):
    rows = _moving_rows()
    code, out = _morph(tmp_path, cube_file, rows, "--moving", "x1", "--select", "0.5,0.8,1.3")
    assert code == EXIT_OK
    selected = _controls(out)
    assert 0 < selected < 98
    assert f"controls        {selected} of 98 boundary nodes" in capsys.readouterr().out
    # the moving face still moves exactly
    displacement = _result(out)[1]["displacement"]
    moving = read_mesh(cube_file).node_set("x1")
    assert torch.equal(displacement[moving], torch.from_numpy(rows))


def test_region_matches_meshmorph_with_plan(tmp_path, cube_file, capsys):
    rows = _moving_rows(2)
    regions = ["--region", "x0+x1=0.6,0.8,1.3", "--region", "y0+y1+z0+z1=0.6,0.8,1.3"]
    code, out = _morph(tmp_path, cube_file, rows, "--moving", "x1", *regions, "--seed", "5")
    assert code == EXIT_OK
    assert "SIDW" in capsys.readouterr().out
    displacement = _result(out)[1]["displacement"]

    reference = read_mesh(cube_file)
    plan = SelectionPlan([Region(("x0", "x1"), 0.6), Region(("y0", "y1", "z0", "z1"), 0.6)])
    morph = MeshMorph(reference, plan, generator=torch.Generator().manual_seed(5))
    assert _controls(out) == morph.num_controls < 98
    boundary = morph.boundary_displacement("x1", lambda x: torch.from_numpy(rows))
    torch.testing.assert_close(displacement, morph(boundary), rtol=0, atol=1e-14)


def test_enrich_adds_its_nodes(tmp_path, cube_file, capsys):
    code, out = _morph(
        tmp_path, cube_file, _moving_rows(), "--moving", "x1", "--select", "0.6", "--enrich", "z0"
    )
    assert code == EXIT_OK
    assert "ESIDW" in capsys.readouterr().out
    mesh, point_data, _ = _result(out)
    flags = point_data["control_point"].bool()
    assert flags[mesh.node_set("z0")].all()
    assert int(flags.sum()) < 98


def test_inverting_morph_warns_and_strict_exits_3(tmp_path, cube_file, capsys):
    push = np.array([-1.5, 0.0, 0.0])  # x1 face pushed through the fixed x0 face
    code, out = _morph(tmp_path, cube_file, push, "--moving", "x1")
    assert code == EXIT_OK
    err = capsys.readouterr().err
    assert "WARNING" in err and "inverts" in err
    assert int(_result(out)[2]["inverted"].sum()) > 0
    code, out = _morph(tmp_path, cube_file, push, "--moving", "x1", "--strict")
    assert code == EXIT_INVERTED
    assert out.exists()


def test_write_deformed(tmp_path, cube_file):
    rows = _moving_rows()
    code, out = _morph(tmp_path, cube_file, rows, "--moving", "x1", "--write-deformed")
    assert code == EXIT_OK
    mesh, point_data, _ = _result(out)
    reference = read_mesh(cube_file)
    torch.testing.assert_close(mesh.points, reference.points + point_data["displacement"])


# --------------------------------------------------------------------------- errors


def _error(capsys) -> str:
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return captured.err


def test_missing_mesh(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nope.vtu")]) == EXIT_ERROR
    assert "does not exist" in _error(capsys)
    np.save(tmp_path / "d.npy", np.zeros((3,)))
    code = main(
        [
            "morph",
            str(tmp_path / "nope.vtu"),
            "--moving",
            "x1",
            "-d",
            str(tmp_path / "d.npy"),
            "-o",
            str(tmp_path / "o.vtu"),
        ]
    )
    assert code == EXIT_ERROR
    assert "nope.vtu" in _error(capsys)


def test_unreadable_mesh(tmp_path, capsys):
    bad = tmp_path / "bad.vtu"
    bad.write_text("this is not a VTU file")
    assert main(["info", str(bad)]) == EXIT_ERROR
    assert "could not read" in _error(capsys)
    stl = tmp_path / "mesh.stl"
    stl.write_text("solid empty\nendsolid empty\n")
    assert main(["info", str(stl)]) == EXIT_ERROR
    assert "unsupported mesh file extension" in _error(capsys)


def test_unknown_set_lists_known(tmp_path, cube_file, capsys):
    code, _ = _morph(tmp_path, cube_file, np.zeros(3), "--moving", "wing")
    assert code == EXIT_ERROR
    assert "unknown marker 'wing' in --moving; known: x0, x1, y0, y1, z0, z1" in _error(capsys)
    code, _ = _morph(
        tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--select", "0.5", "--enrich", "edges"
    )
    assert code == EXIT_ERROR
    assert "unknown marker 'edges' in --enrich" in _error(capsys)
    code, _ = _morph(tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--region", "top=0.5")
    assert code == EXIT_ERROR
    assert "unknown marker 'top' in --region" in _error(capsys)


def test_wrong_displacement_shape_lists_accepted(tmp_path, cube_file, capsys):
    code, _ = _morph(tmp_path, cube_file, np.zeros((7, 3)), "--moving", "x1")
    assert code == EXIT_ERROR
    err = _error(capsys)
    assert "shape (7, 3)" in err
    for accepted in ("(25, 3)", "(98, 3)", "(125, 3)", "(3,)"):
        assert accepted in err
    code, _ = _morph(tmp_path, cube_file, np.zeros((25, 2)), "--moving", "x1")
    assert code == EXIT_ERROR
    assert "accepted shapes" in _error(capsys)
    # moving rows without --moving: the hint names --moving
    code, _ = _morph(tmp_path, cube_file, np.zeros((25, 3)))
    assert code == EXIT_ERROR
    assert "--moving" in _error(capsys)


def test_bad_displacement_files(tmp_path, cube_file, capsys):
    out = str(tmp_path / "o.vtu")
    base = ["morph", str(cube_file), "--moving", "x1", "-o", out]
    assert main([*base, "-d", str(tmp_path / "missing.npy")]) == EXIT_ERROR
    assert "does not exist" in _error(capsys)
    (tmp_path / "d.json").write_text("[]")
    assert main([*base, "-d", str(tmp_path / "d.json")]) == EXIT_ERROR
    assert "supported: .npy" in _error(capsys)
    np.save(tmp_path / "nan.npy", np.full((25, 3), np.nan))
    assert main([*base, "-d", str(tmp_path / "nan.npy")]) == EXIT_ERROR
    assert "NaN" in _error(capsys)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("-1", "radius must be"),
        ("0", "radius must be"),
        ("0.3,1.5", "a must satisfy 0 < a < 1"),
        ("0.3,0.8,0.9", "b must satisfy b > 1"),
        ("abc", "expected numbers"),
        ("0.3,0.8,1.3,2", "expected R"),
    ],
)
def test_bad_selection_parameters(tmp_path, cube_file, capsys, value, message):
    code, _ = _morph(tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--select", value)
    assert code == EXIT_USAGE
    assert message in _error(capsys)
    code, _ = _morph(tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--region", f"x1={value}")
    assert code == EXIT_USAGE
    assert message in _error(capsys)


def test_uncovered_boundary_nodes_are_named(tmp_path, cube_file, capsys):
    code, _ = _morph(tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--region", "x1=0.5")
    assert code == EXIT_ERROR
    err = _error(capsys)
    assert "73 of the 98 boundary nodes are in no --region" in err
    assert "25 in x0" in err and "--uncovered ignore" in err
    code, out = _morph(
        tmp_path,
        cube_file,
        np.zeros(3),
        "--moving",
        "x1",
        "--region",
        "x1=0.5",
        "--uncovered",
        "ignore",
    )
    assert code == EXIT_OK
    assert _controls(out) < 25


def test_conflicting_regions_name_the_option(tmp_path, cube_file, capsys):
    code, _ = _morph(
        tmp_path,
        cube_file,
        np.zeros(3),
        "--moving",
        "x1",
        "--region",
        "x0+x1=0.4",
        "--region",
        "y0+y1+z0+z1=0.6",
    )
    assert code == EXIT_ERROR
    assert "--overlap first" in _error(capsys)
    code, _ = _morph(
        tmp_path,
        cube_file,
        np.zeros(3),
        "--moving",
        "x1",
        "--overlap",
        "first",
        "--region",
        "x0+x1=0.4",
        "--region",
        "y0+y1+z0+z1=0.6",
    )
    assert code == EXIT_OK


def test_selection_errors_are_typed_and_carry_their_data():
    """The command builds its messages from the library's exception types, not their text."""
    from torchmorph.selection import RegionOverlapError, UncoveredNodesError

    cube = structured_cube(4)
    with pytest.raises(UncoveredNodesError) as caught:
        SelectionPlan({"x1": 0.5}).select(cube)
    assert caught.value.total == 98
    np.testing.assert_array_equal(
        caught.value.nodes, np.setdiff1d(cube.boundary_nodes.numpy(), cube.node_set("x1").numpy())
    )
    with pytest.raises(RegionOverlapError) as caught:
        SelectionPlan([Region(("x0", "x1"), 0.4), Region(("y0", "y1", "z0", "z1"), 0.6)]).select(
            cube
        )
    assert caught.value.first.names == ("x0", "x1") and caught.value.count > 0


def test_usage_errors(tmp_path, cube_file, capsys):
    code, _ = _morph(tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--enrich", "z0")
    assert code == EXIT_USAGE
    assert "--enrich: needs --select, --region or --adaptive" in _error(capsys)
    code, _ = _morph(
        tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--select", "0.5", "--region", "x1=0.5"
    )
    assert code == EXIT_USAGE
    assert "not allowed with" in _error(capsys)
    np.save(tmp_path / "d.npy", np.zeros(3))
    code = main(
        [
            "morph",
            str(cube_file),
            "--moving",
            "x1",
            "-d",
            str(tmp_path / "d.npy"),
            "-o",
            str(tmp_path / "out.stl"),
        ]
    )
    assert code == EXIT_USAGE
    assert "unsupported mesh file extension '.stl'" in _error(capsys)
    code, _ = _morph(tmp_path, cube_file, np.zeros(3), "--moving", "x1", "--power", "-1")
    assert code == EXIT_USAGE


def test_moving_set_with_interior_nodes(tmp_path, capsys):
    cube = structured_cube(4)
    sets = {**cube.node_sets, "inner": cube.interior_nodes[:3]}
    path = tmp_path / "cube.vtu"
    write_mesh(path, TetMesh(cube.points, cube.tets, sets))
    code, _ = _morph(tmp_path, path, np.zeros(3), "--moving", "inner")
    assert code == EXIT_ERROR
    assert "interior node" in _error(capsys)


# --------------------------------------------------------------------------- reproduce


@pytest.fixture
def fake_paper(monkeypatch):
    """Replace torchmorph.paper by a module that records its calls (case names resolved by
    the real one)."""
    from torchmorph.paper import case_key

    calls = []
    module = types.ModuleType("torchmorph.paper")
    module.case_key = case_key

    def reproduce(case, **options):
        calls.append((case, options))
        if case == "hull":
            raise ImportError("No module named 'gmsh'")

    module.reproduce = reproduce
    monkeypatch.setitem(sys.modules, "torchmorph.paper", module)
    monkeypatch.setattr(torchmorph, "paper", module, raising=False)
    return calls


def test_reproduce_passes_options(tmp_path, fake_paper):
    out = tmp_path / "results"
    code = main(
        [
            "reproduce",
            "B",
            "--size",
            "small",
            "--out",
            str(out),
            "--mesher",
            "pytetwild",
            "--seed",
            "3",
        ]
    )
    assert code == EXIT_OK
    assert fake_paper == [
        (
            "fluid-wing",
            {"size": "small", "out": str(out), "mesher": "pytetwild", "seed": 3, "verbose": True},
        )
    ]
    assert main(["reproduce", "wing"]) == EXIT_OK
    assert fake_paper[-1] == (
        "wing",
        {"size": "paper", "out": None, "mesher": "gmsh", "seed": 0, "verbose": True},
    )


def test_reproduce_missing_dependency_names_extra(fake_paper, capsys):
    assert main(["reproduce", "hull"]) == EXIT_ERROR
    err = _error(capsys)
    assert "gmsh" in err and "pip install 'torchmorph[mesh]'" in err


def test_reproduce_without_the_reproduction_installed(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "torchmorph.paper", None)  # import fails
    monkeypatch.delattr(torchmorph, "paper", raising=False)
    assert main(["reproduce", "wing", "--size", "small"]) == EXIT_ERROR
    assert "torchmorph.paper is not part of this installation" in _error(capsys)


def test_reproduce_bad_arguments(capsys):
    assert main(["reproduce", "airfoil"]) == EXIT_USAGE
    assert "unknown case 'airfoil'" in _error(capsys)
    assert main(["reproduce", "wing", "--size", "huge"]) == EXIT_USAGE


@pytest.mark.slow
def test_reproduce_wing_small(tmp_path, capsys):
    pytest.importorskip("torchmorph.paper")
    pytest.importorskip("gmsh")
    assert main(["reproduce", "wing", "--size", "small", "--out", str(tmp_path)]) == EXIT_OK
    assert capsys.readouterr().out
    assert any(tmp_path.iterdir())


# --------------------------------------------------------------------------- environment


def test_tests_run_with_a_temporary_home_and_a_repository_cache(temporary_home):
    import os
    from pathlib import Path

    home = Path(os.environ["HOME"])
    assert home == temporary_home / "home" and home.is_dir()
    assert Path(os.environ["MPLCONFIGDIR"]).is_relative_to(temporary_home)
    assert Path("~").expanduser() == home
    repository_cache = Path(__file__).resolve().parents[2] / ".cache" / "tests"
    assert Path(os.environ["TORCHMORPH_CACHE"]).is_relative_to(repository_cache)
    assert Path(os.environ["NUMBA_CACHE_DIR"]).is_relative_to(repository_cache)


# --------------------------------------------------------------------------- mesh


def _sphere_obj(path, drop_first_face: bool = False):
    trimesh = pytest.importorskip("trimesh")
    sphere = trimesh.creation.icosphere(subdivisions=1)
    faces = sphere.faces[1:] if drop_first_face else sphere.faces
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in sphere.vertices]
    lines += ["f " + " ".join(str(v + 1) for v in face) for face in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_mesh_writes_a_mesh_with_named_sets_and_reports_quality(tmp_path, capsys):
    pytest.importorskip("pytetwild")
    source = _sphere_obj(tmp_path / "ball.obj")
    out = tmp_path / "ball.vtu"
    code = main(
        [
            "mesh",
            f"body={source}",
            "--box",
            "1",
            "--edge-length",
            "1",
            "-o",
            str(out),
            "--no-progress",
        ]
    )
    assert code == EXIT_OK
    printed = capsys.readouterr().out
    assert "surface         body:" in printed and "80 triangles" in printed
    assert re.search(r"quality Q\s+max \d+(\.\d+)?, mean \d", printed)
    assert "inverted tets   0" in printed
    mesh = read_mesh(out)
    assert {"body", "far_field", "wall_x0", "wall_z1"} <= set(mesh.node_sets)
    for name, nodes in mesh.node_sets.items():
        assert f"  {name}" in printed and f"{nodes.numel()} nodes" in printed


def test_mesh_errors(tmp_path, capsys):
    pytest.importorskip("trimesh")
    holed = _sphere_obj(tmp_path / "holed.obj", drop_first_face=True)
    out = str(tmp_path / "x.vtu")
    assert main(["mesh", str(holed), "-o", out]) == EXIT_ERROR
    err = _error(capsys)
    assert "is not a closed, consistently oriented surface: 3 edge(s) belong to one face" in err
    assert "--repair" in err
    assert main(["mesh", str(tmp_path / "none.stl"), "-o", out]) == EXIT_ERROR
    assert "surface file" in _error(capsys)
    assert main(["mesh", str(holed), "-o", str(tmp_path / "x.stl")]) == EXIT_USAGE
    assert "unsupported mesh file extension '.stl'" in _error(capsys)
    assert main(["mesh", str(holed), "--feature-angle", "200", "-o", out]) == EXIT_USAGE
    assert "--feature-angle: must be in (0, 180)" in _error(capsys)
    assert main(["mesh", str(holed), "--body-edge-length", "0.1", "-o", out]) == EXIT_USAGE
    assert "needs --box or --bounds" in _error(capsys)
    assert main(["mesh", str(holed), "--box", "1,2", "-o", out]) == EXIT_USAGE
    assert "expected 1 or 6 number(s)" in _error(capsys)


def test_mesh_without_pytetwild_names_the_tetwild_extra(tmp_path, monkeypatch, capsys):
    source = _sphere_obj(tmp_path / "ball.obj")
    monkeypatch.setitem(sys.modules, "pytetwild", None)  # import pytetwild -> ImportError
    assert main(["mesh", str(source), "-o", str(tmp_path / "ball.vtu")]) == EXIT_ERROR
    err = _error(capsys)
    assert (
        "tetrahedralising needs pytetwild (which imports pyvista): pip install "
        "'torchmorph[tetwild]'"
    ) in err
    assert "torchmorph[mesh]" not in err
    assert not (tmp_path / "ball.vtu").exists()


WALLS = ("wall_x0", "wall_x1", "wall_y0", "wall_y1", "wall_z0", "wall_z1")


def _step(path):
    pytest.importorskip("gmsh")
    return write_cad(path)


def test_mesh_of_a_step_file_in_a_box(tmp_path, capsys):
    source = _step(tmp_path / "body.step")
    out = tmp_path / "out.vtu"
    args = ["mesh", str(source), "--box", "1,2,1,1,1,1", "--edge-length", "0.8", "-o", str(out)]
    assert main([*args, "--no-progress"]) == EXIT_OK
    printed = capsys.readouterr().out
    assert "CAD file        body:" in printed and "inverted tets   0" in printed
    assert re.search(r"quality Q\s+max \d+(\.\d+)?, mean \d", printed)
    mesh = read_mesh(out)
    faces = [f"body_face{k}" for k in range(7)]
    assert list(mesh.node_sets) == ["body", "far_field", *WALLS, *faces, "body_edges"]
    for name, nodes in mesh.node_sets.items():
        assert f"  {name}" in printed and f"{nodes.numel()} nodes" in printed
    x = mesh.points[mesh.node_set("wall_x1"), 0]
    torch.testing.assert_close(x, torch.full_like(x, 1 + 2 * 2.0), rtol=0, atol=1e-6)
    mixed = ["mesh", str(source), str(tmp_path / "ball.stl"), "-o", str(out)]
    assert main(mixed) == EXIT_ERROR
    assert "cannot be meshed together" in _error(capsys)
    assert main(["mesh", str(tmp_path / "none.step"), "-o", str(out)]) == EXIT_ERROR
    err = _error(capsys)
    assert "CAD file" in err and "none.step' does not exist" in err
    assert main([*args, "--feature-angle", "30"]) == EXIT_ERROR
    assert "feature_angle and repair are for triangle surfaces" in _error(capsys)


# --------------------------------------------------------------------------- --help examples


def help_examples(command: str) -> list[str]:
    """The command lines under 'examples:' in ``torchmorph COMMAND --help``."""
    text = build_parser()._subparsers._group_actions[0].choices[command].format_help()
    block = text.split("examples:\n", 1)[1]
    lines, current = [], ""
    for line in block.splitlines():
        if not line.startswith("  "):
            break
        current += line.strip().removesuffix("\\").strip() + " "
        if not line.rstrip().endswith("\\"):
            lines.append(current.strip())
            current = ""
    return lines


def test_help_examples_are_found():
    assert len(help_examples("morph")) == 2 and len(help_examples("mesh")) == 4
    assert all(line.startswith("torchmorph ") for line in help_examples("mesh"))


@pytest.mark.slow
def test_every_help_example_runs_as_printed(tmp_path, monkeypatch, capsys):
    """On the project's own small wing (gmsh) and small surfaces (fTetWild)."""
    import shlex

    data_gen = pytest.importorskip("data_gen")
    pytest.importorskip("gmsh")
    pytest.importorskip("pytetwild")
    trimesh = pytest.importorskip("trimesh")
    write_mesh(tmp_path / "wing.vtu", data_gen.build("wing", "small", "gmsh", cache_dir=tmp_path))
    np.save(tmp_path / "tip.npy", np.array([0.0, 0.05, 0.0]))
    np.save(tmp_path / "d.npy", np.array([0.0, 0.01, 0.0]))
    trimesh.creation.icosphere(subdivisions=2, radius=0.5).export(tmp_path / "body.stl")
    car = trimesh.convex.convex_hull(
        np.array(
            [[x, y, z] for x in (0, 1) for y in (-0.22, 0.22) for z in (0, 0.2)]
            + [[x, y, 0.36] for x in (0.32, 0.68) for y in (-0.17, 0.17)]
        )
    )
    car.export(tmp_path / "car.obj")
    _step(tmp_path / "part.step")
    monkeypatch.chdir(tmp_path)
    for command in ("morph", "mesh"):
        for line in help_examples(command):
            assert main(shlex.split(line)[1:]) == EXIT_OK, (line, capsys.readouterr().err)
    out = capsys.readouterr().out
    assert "car_edges" in out and "wall_z0" in out and "part_face6" in out
