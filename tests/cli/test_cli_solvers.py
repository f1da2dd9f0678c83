"""``torchmorph morph`` on solvers' own inputs, judged by the solvers: an OpenFOAM case
(3-D hexahedra, hybrid cells, and pseudo-2-D in its plane) passed by ``checkMesh`` and solved by ``potentialFoam``,
a CalculiX deck of quadratic elements solved by ``ccx``; the morph checked against an
independent float64 IDW from the true boundary, and only the coordinates changed."""

from __future__ import annotations

import filecmp
import gzip
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "mesh"))

from _foam_cases import (
    channel,
    flat_channel,
    foam,
    fv_dicts,
    gmsh_case,
    mesh_statistics,
    needs_openfoam,
    potential_fields,
)
from _kinds import box, idw_reference

from torchmorph.cli import EXIT_OK, main
from torchmorph.mesh import read_mesh
from torchmorph.mesh.formats.abaqus import read_deck
from torchmorph.mesh.formats.openfoam import pseudo_2d, read_foam_case

TEST_DECKS = Path("/usr/share/doc/calculix-ccx-test/examples/test")

pytestmark = pytest.mark.slow


def _bump(points: np.ndarray, length: float, height: float) -> np.ndarray:
    """An inward bump of a wall: ``height sin(π x / length)²`` along the wall normal."""
    return height * np.sin(np.pi * points[:, 0] / length) ** 2


def _interior_against_idw(source_points, moved_points, boundary, displacement):
    """The morphed interior equals float64 IDW from the boundary's displacement."""
    interior = np.setdiff1d(np.arange(len(source_points)), boundary)
    expected = idw_reference(source_points[interior], source_points[boundary], displacement)
    got = moved_points[interior] - source_points[interior]
    scale = np.abs(displacement).max()
    np.testing.assert_allclose(got, expected, atol=1e-9 * scale)


def test_an_openfoam_case_morphed_passes_checkmesh_and_potentialfoam(tmp_path):
    needs_openfoam("potentialFoam")
    case = tmp_path / "channel"
    channel(case, cells=(10, 6, 4))
    mesh = read_mesh(case)
    assert mesh.cell_counts == {"hexahedron": 240} and "walls" in mesh.face_sets
    # the y = 0 wall bulges inwards; every other patch is fixed
    moving = mesh.node_set("walls").numpy()
    moving = moving[mesh.points.numpy()[moving, 1] < 0.5]
    rows = np.zeros((moving.size, 3))
    rows[:, 1] = _bump(mesh.points.numpy()[moving], 2.0, 0.12)
    np.save(tmp_path / "d.npy", rows)
    np.save(tmp_path / "ids.npy", moving)
    # the moving nodes are the y = 0 half of 'walls': name them with a node file of ours
    out = tmp_path / "morphed"
    boundary = mesh.boundary_nodes.numpy()
    full = np.zeros((boundary.size, 3))
    full[np.searchsorted(boundary, moving)] = rows
    np.save(tmp_path / "boundary.npy", full)
    code = main(
        ["morph", str(case), "-d", str(tmp_path / "boundary.npy"), "-o", str(out), "--no-progress"]
    )
    assert code == EXIT_OK
    for name in ("faces", "owner", "neighbour", "boundary"):  # byte-identical
        assert filecmp.cmp(
            case / "constant/polyMesh" / name, out / "constant/polyMesh" / name, shallow=False
        )
    moved = read_foam_case(out).points
    _interior_against_idw(mesh.points.numpy(), moved, boundary, full)
    fv_dicts(out)
    log = foam("checkMesh", out)
    assert "Mesh OK." in log and mesh_statistics(log)["cells"] == 240
    potential_fields(
        out,
        {
            "inlet": "inlet",
            "outlet": "outlet",
            "walls": "wall",
            "bottom": "symmetryPlane",
            "top": "symmetry",
        },
    )
    assert "End" in foam("potentialFoam -writep", out)


@pytest.mark.parametrize(
    ("layers", "kinds"),
    [
        (("hexahedron", "pyramid"), {"hexahedra": 16, "pyramids": 96}),
        (("wedge", "tetra"), {"prisms": 32, "tetrahedra": 96}),
    ],
)
def test_a_hybrid_case_morphed_passes_checkmesh_and_potentialfoam(tmp_path, layers, kinds):
    """Hexahedra beside pyramids, prisms beside tetrahedra (gmshToFoam's case of our cells):
    the bottom wall bulges; OpenFOAM counts the cells by kind, finds the mesh OK and
    solves on it."""
    needs_openfoam("gmshToFoam", "potentialFoam")
    points, cells = box(layers, 4)
    case = tmp_path / "hybrid"
    case.mkdir()
    gmsh_case(case, np.asarray(points, dtype=float), [(k, np.asarray(c)) for k, c in cells])
    mesh = read_mesh(case)
    source, boundary = mesh.points.numpy(), mesh.boundary_nodes.numpy()
    low, high = source.min(0), source.max(0)
    on = source[boundary]
    inside = (np.abs(on[:, 2] - low[2]) < 1e-12) & np.all(
        (on[:, :2] > low[:2]) & (on[:, :2] < high[:2]), axis=1
    )
    full = np.zeros((boundary.size, 3))
    unit = (on[inside, :2] - low[:2]) / (high[:2] - low[:2])
    full[inside, 2] = 0.25 * (high[2] - low[2]) * np.prod(np.sin(np.pi * unit), axis=1)
    assert inside.sum() == 9
    np.save(tmp_path / "d.npy", full)
    out = tmp_path / "morphed"
    code = main(["morph", str(case), "-d", str(tmp_path / "d.npy"), "-o", str(out), "--strict"])
    assert code == EXIT_OK
    _interior_against_idw(source, read_foam_case(out).points, boundary, full)
    fv_dicts(out)
    log = foam("checkMesh", out)
    statistics = mesh_statistics(log)
    assert "Mesh OK." in log and {k: statistics[k] for k in kinds} == kinds
    potential_fields(out, {"inlet": "inlet", "outlet": "outlet", "walls": "wall"})
    assert "End" in foam("potentialFoam -writep", out)


def test_a_pseudo_2d_case_is_morphed_in_its_plane(tmp_path, capsys):
    needs_openfoam("potentialFoam")
    case = tmp_path / "flat"
    flat_channel(case, cells=(24, 8))
    planar = read_mesh(case)  # the front plane, in 2-D
    assert planar.dim == 2 and planar.cell_counts == {"quad": 192}
    assert "frontAndBack" not in planar.markers and "lower" in planar.face_sets
    lower = planar.node_set("lower").numpy()
    rows = np.zeros((lower.size, 2))
    rows[:, 1] = _bump(planar.points.numpy()[lower], 4.0, 0.2)
    np.save(tmp_path / "d.npy", rows)
    out = tmp_path / "morphed"
    code = main(
        [
            "morph",
            str(case),
            "--moving",
            "lower",
            "-d",
            str(tmp_path / "d.npy"),
            "-o",
            str(out),
            "--no-progress",
        ]
    )
    assert code == EXIT_OK
    assert "2-D, 225 nodes" in capsys.readouterr().out
    reference, moved = read_foam_case(case).points, read_foam_case(out).points
    assert np.array_equal(moved[:, 2], reference[:, 2])  # no point leaves its plane
    twins = pseudo_2d(read_foam_case(case))  # each front point and its twin at the back
    shift = moved - reference
    # the layers move alike (to the rounding of points that blockMesh wrote a bit apart)
    np.testing.assert_allclose(shift[twins.front], shift[twins.back], rtol=0, atol=1e-15)
    boundary = planar.boundary_nodes.numpy()
    full = np.zeros((boundary.size, 2))
    full[np.searchsorted(boundary, lower)] = rows
    again = read_mesh(out)
    _interior_against_idw(planar.points.numpy(), again.points.numpy(), boundary, full)
    fv_dicts(out)
    log = foam("checkMesh", out)
    assert "Mesh OK." in log
    potential_fields(
        out,
        {
            "inlet": "inlet",
            "outlet": "outlet",
            "lower": "wall",
            "upper": "wall",
            "frontAndBack": "empty",
        },
    )
    assert "End" in foam("potentialFoam -writep", out)


@pytest.mark.parametrize("deck", ["beam20p", "beam10p", "c3d15"])
def test_a_calculix_deck_morphed_keeps_all_but_coordinates_and_ccx_solves_it(tmp_path, deck):
    if shutil.which("ccx") is None or not TEST_DECKS.is_dir():
        pytest.skip("CalculiX (ccx) or its test decks are not installed")
    source = next(TEST_DECKS.glob(f"{deck}.inp*"))
    original = tmp_path / f"{deck}.inp"
    data = gzip.open(source).read() if source.suffix == ".gz" else source.read_bytes()
    original.write_bytes(data)
    mesh = read_mesh(original)
    # a gentle taper along the beam (z): the section shrinks by up to 10 %
    points = mesh.points.numpy()
    length = points[:, 2].max()
    field = np.zeros_like(points)
    field[:, :2] = -0.1 * (points[:, 2:3] / length) * (points[:, :2] - 0.5)
    np.save(tmp_path / "d.npy", field)
    out = tmp_path / f"{deck}_morphed.inp"
    code = main(
        ["morph", str(original), "-d", str(tmp_path / "d.npy"), "-o", str(out), "--no-progress"]
    )
    assert code == EXIT_OK
    before, after = original.read_text().splitlines(), out.read_text().splitlines()
    assert len(before) == len(after)
    node_lines = set(read_deck(original).node_lines.tolist())  # 0-based, one file here
    changed = [i for i, (a, b) in enumerate(zip(before, after, strict=True)) if a != b]
    assert changed and set(changed) <= node_lines  # only node lines changed, coordinates
    assert all(after[i].split(",")[0] == before[i].split(",")[0] for i in changed)  # node ids
    moved = read_mesh(out).points.numpy()
    boundary = mesh.boundary_nodes.numpy()
    np.testing.assert_allclose(moved[boundary] - points[boundary], field[boundary], atol=1e-12)
    _interior_against_idw(points, moved, boundary, field[boundary])
    run = subprocess.run(
        ["ccx", out.stem], cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False
    )
    log = run.stdout + run.stderr
    assert run.returncode == 0 and "nonpositive jacobian" not in log.lower() and "*ERROR" not in log
    assert (tmp_path / f"{out.stem}.dat").is_file()
