"""OpenFOAM polyMesh cases: reading (ASCII, binary, gzipped), cells and patches, points
written back, pseudo-2-D cases. References: blockMesh's and checkMesh's counts,
gmshToFoam's conversion of known cells, analytic volumes, byte comparisons, and
polyMesh files written by hand (those tests need no OpenFOAM). Every test that runs
OpenFOAM's tools is marked slow (they spawn processes), and skipped without them."""

from __future__ import annotations

import dataclasses
import gzip
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from _foam_cases import (
    axisymmetric_wedge,
    box_case,
    channel,
    control_dict,
    flat_channel,
    foam,
    fv_dicts,
    gmsh_case,
    mesh_statistics,
    mixed_cells,
    needs_openfoam,
    potential_fields,
    triangle_slab,
    write_polymesh,
)

from torchmorph.mesh.formats.openfoam import (
    FoamCase,
    pseudo_2d,
    read_foam_case,
    write_foam_points,
)

MESH_FILES = ("points", "faces", "owner", "neighbour", "boundary")

#: Each kind split into positively oriented tetrahedra (meshio's node order).
TETS = {
    "tetra": [(0, 1, 2, 3)],
    "pyramid": [(0, 1, 2, 4), (0, 2, 3, 4)],
    "wedge": [(0, 1, 2, 5), (0, 1, 5, 4), (0, 4, 5, 3)],
    "hexahedron": [
        (0, 1, 2, 6),
        (0, 2, 3, 6),
        (0, 3, 7, 6),
        (0, 7, 4, 6),
        (0, 4, 5, 6),
        (0, 5, 1, 6),
    ],
}


def signed_volumes(points: np.ndarray, kind: str, cells: np.ndarray) -> np.ndarray:
    total = np.zeros(len(cells))
    for tet in TETS[kind]:
        a, b, c, d = (points[cells[:, k]] for k in tet)
        total += np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6
    return total


def polygon_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Newell normals of faces (M, k) (right-hand rule about their order)."""
    here, there = points[faces], points[np.roll(faces, -1, axis=1)]
    return np.cross(here, there).sum(axis=1) / 2


def signed_areas(points_2d: np.ndarray, cells: np.ndarray) -> np.ndarray:
    here, there = points_2d[cells], points_2d[np.roll(cells, -1, axis=1)]
    return (here[..., 0] * there[..., 1] - here[..., 1] * there[..., 0]).sum(axis=1) / 2


def checkmesh_volume(log: str) -> float:
    return float(re.search(r"Total volume = ([-+0-9.eE]+)\.", log).group(1))


def same_files(first: Path, second: Path, names=MESH_FILES) -> list[str]:
    """The names whose files differ in bytes between two polyMesh directories."""
    return [n for n in names if (first / n).read_bytes() != (second / n).read_bytes()]


# -- cases --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def channel_case(tmp_path_factory) -> tuple[Path, str]:
    needs_openfoam()
    case = tmp_path_factory.mktemp("channel") / "case"
    log = channel(case)
    fv_dicts(case)
    return case, log


@pytest.fixture
def box_dir(tmp_path) -> Path:
    """A hand-written case: a 3 x 2 x 2 box of hexahedra [0, 3] x [0, 2] x [0, 1]."""
    case = tmp_path / "box"
    write_polymesh(case / "constant" / "polyMesh", box_case())
    control_dict(case)
    return case


def flat_box(tmp_path: Path, counts=(4, 3, 1)) -> FoamCase:
    """A hand-written pseudo-2-D box [0, 3] x [0, 2] x [0, 1] with frontAndBack empty."""
    mesh_dir = tmp_path / "flat" / "constant" / "polyMesh"
    write_polymesh(mesh_dir, box_case(counts, empty_z=True))
    return read_foam_case(mesh_dir)


# -- reading blockMesh cases --------------------------------------------------------


@pytest.mark.slow
def test_channel_counts_and_patches_match_blockmesh(channel_case):
    case_dir, log = channel_case
    case = read_foam_case(case_dir)
    stats = mesh_statistics(log)
    assert (case.n_points, case.n_faces, case.n_internal_faces, case.n_cells) == (
        stats["points"],
        stats["faces"],
        stats["internal faces"],
        stats["cells"],
    )
    assert (case.n_points, case.n_cells) == (9 * 6 * 4, 8 * 5 * 3)
    reported = re.findall(r"patch \d+ \(start: (\d+) size: (\d+)\) name: (\w+)", log)
    assert [(p.name, p.start_face, p.n_faces) for p in case.patches] == [
        (name, int(start), int(size)) for start, size, name in reported
    ]
    assert [(p.name, p.type, p.n_faces) for p in case.patches] == [
        ("inlet", "patch", 15),
        ("outlet", "patch", 15),
        ("walls", "wall", 48),
        ("bottom", "symmetryPlane", 40),
        ("top", "symmetry", 40),
    ]
    assert case.patch("walls").in_groups == ("wall", "solid")
    assert "nFaces" in case.patch("walls").text
    assert case.root == case_dir and case.points_file == case_dir / "constant/polyMesh/points"


@pytest.mark.slow
def test_channel_cells_are_positive_hexahedra_filling_the_box(channel_case):
    mesh = read_foam_case(channel_case[0]).to_mesh_data()
    assert [kind for kind, _ in mesh.cells] == ["hexahedron"]
    hexes = mesh.cells[0][1]
    assert hexes.shape == (120, 8) and hexes.dtype == np.int64
    volumes = signed_volumes(mesh.points, "hexahedron", hexes)
    np.testing.assert_allclose(volumes, 2 * 1 * 0.5 / 120, rtol=1e-12)
    # node 4 above node 0 (the bottom quad 0-3 turns positively about the way up)
    bottom_normals = polygon_normals(mesh.points, hexes[:, :4])
    rise = mesh.points[hexes[:, 4]] - mesh.points[hexes[:, 0]]
    assert np.all(np.einsum("ij,ij->i", bottom_normals, rise) > 0)
    np.testing.assert_array_equal(mesh.cell_data["foam_cell"][0], np.arange(120))


@pytest.mark.slow
def test_channel_face_sets_lie_on_their_planes_facing_out(channel_case):
    mesh = read_foam_case(channel_case[0]).to_mesh_data()
    planes = {
        "inlet": (0, 0.0, -1),
        "outlet": (0, 2.0, 1),
        "bottom": (2, 0.0, -1),
        "top": (2, 0.5, 1),
    }
    for name, (axis, value, outward) in planes.items():
        [(kind, quads)] = mesh.face_sets[name]
        assert kind == "quad"
        np.testing.assert_allclose(mesh.points[quads, axis], value, atol=1e-12)
        assert np.all(polygon_normals(mesh.points, quads)[:, axis] * outward > 0)
    [(_, walls)] = mesh.face_sets["walls"]
    assert len(walls) == 48
    assert np.all(np.isclose(mesh.points[walls, 1], 0) | np.isclose(mesh.points[walls, 1], 1))
    assert mesh.groups == {
        "wall": ["walls"],
        "solid": ["walls"],
        "symmetryPlane": ["bottom"],
        "symmetry": ["top"],
    }


@pytest.mark.slow
def test_axisymmetric_wedge_case_has_prisms_on_the_axis(tmp_path):
    needs_openfoam()
    case_dir = tmp_path / "wedge"
    axisymmetric_wedge(case_dir, length=2.0, radius=0.5, angle=5.0, cells=(6, 4))
    fv_dicts(case_dir)
    log = foam("checkMesh", case_dir)
    stats = mesh_statistics(log)
    case = read_foam_case(case_dir)
    mesh = case.to_mesh_data()
    counts = {kind: len(cells) for kind, cells in mesh.cells}
    assert (
        counts
        == {"wedge": stats["prisms"], "hexahedron": stats["hexahedra"]}
        == {
            "wedge": 6,
            "hexahedron": 18,
        }
    )
    total = 0.0
    for kind, cells in mesh.cells:
        volumes = signed_volumes(mesh.points, kind, cells)
        assert np.all(volumes > 0)
        total += volumes.sum()
    # the straight-sided wedge: L * R^2 sin(angle) / 2, as checkMesh finds too
    np.testing.assert_allclose(total, 2.0 * 0.25 * np.sin(np.radians(5.0)) / 2, rtol=1e-12)
    np.testing.assert_allclose(total, checkmesh_volume(log), rtol=1e-12)
    # the wedge cells are the ones touching the axis (two nodes on it each... six)
    on_axis = np.isclose(np.hypot(mesh.points[:, 1], mesh.points[:, 2]), 0)
    [wedges] = [cells for kind, cells in mesh.cells if kind == "wedge"]
    assert np.all(on_axis[wedges].sum(axis=1) == 2)
    assert [p.type for p in case.patches] == ["patch", "patch", "wall", "wedge", "wedge", "empty"]
    assert mesh.face_sets["axis"] == []
    assert [kind for kind, _ in mesh.face_sets["inlet"]] == ["triangle", "quad"]


@pytest.mark.slow
def test_mixed_cells_from_gmshtofoam_match_checkmesh_and_the_cells_given(tmp_path):
    needs_openfoam("gmshToFoam")
    case_dir = tmp_path / "mixed"
    points, cells = mixed_cells()
    gmsh_case(case_dir, points, cells)
    fv_dicts(case_dir)
    log = foam("checkMesh", case_dir)
    stats = mesh_statistics(log)
    case = read_foam_case(case_dir)
    mesh = case.to_mesh_data()
    counts = {kind: len(block) for kind, block in mesh.cells}
    assert (
        counts
        == {
            "tetra": stats["tetrahedra"],
            "pyramid": stats["pyramids"],
            "wedge": stats["prisms"],
            "hexahedron": stats["hexahedra"],
        }
        == {"tetra": 2, "pyramid": 5, "wedge": 2, "hexahedron": 1}
    )
    total = 0.0
    for kind, block in mesh.cells:
        given = {frozenset(map(tuple, points[cell].round(9))) for cell in dict(cells)[kind]}
        found = {frozenset(map(tuple, mesh.points[cell].round(9))) for cell in block}
        assert found == given
        volumes = signed_volumes(mesh.points, kind, block)
        assert np.all(volumes > 0)
        total += volumes.sum()
    np.testing.assert_allclose(total, 3.0, rtol=1e-12)
    np.testing.assert_allclose(total, checkmesh_volume(log), rtol=1e-12)
    assert case.patch("walls").entries == {"physicalType": "patch"}
    assert [(kind, len(block)) for kind, block in mesh.face_sets["outlet"]] == [("triangle", 2)]
    assert [(kind, len(block)) for kind, block in mesh.face_sets["inlet"]] == [("quad", 1)]


# -- file formats -------------------------------------------------------------------


@pytest.mark.slow
def test_binary_and_gzipped_cases_read_as_the_ascii_one(channel_case, tmp_path):
    ascii_dir = channel_case[0]
    reference = read_foam_case(ascii_dir)
    converted = {}
    for name, write_format, compression in (("binary", "binary", "off"), ("gzip", "ascii", "on")):
        case_dir = tmp_path / name
        shutil.copytree(ascii_dir, case_dir)
        control_dict(case_dir, write_format=write_format, compression=compression)
        foam("foamFormatConvert -constant", case_dir)
        converted[name] = read_foam_case(case_dir)
    mesh_dir = tmp_path / "binary" / "constant" / "polyMesh"
    assert b"format      binary;" in (mesh_dir / "faces").read_bytes()
    assert b"faceCompactList" in (mesh_dir / "faces").read_bytes()
    assert converted["binary"].points_format.binary
    assert not converted["binary"].points_format.compressed
    assert converted["gzip"].points_format.compressed
    assert converted["gzip"].points_file.name == "points.gz"
    assert not (tmp_path / "gzip" / "constant" / "polyMesh" / "points").exists()
    for case in converted.values():
        for field in ("points", "face_offsets", "face_labels", "owner", "neighbour"):
            np.testing.assert_array_equal(getattr(case, field), getattr(reference, field))
        # (foamFormatConvert rewrites inGroups as `2 ( wall solid )`: the text differs)
        assert [dataclasses.replace(p, text="") for p in case.patches] == [
            dataclasses.replace(p, text="") for p in reference.patches
        ]


@pytest.mark.parametrize(
    "options",
    [
        {"binary": True},
        {"binary": True, "label_bits": 64},
        {"binary": True, "scalar_bits": 32},
        {"binary": True, "byte_order": ">"},
        {"binary": True, "compress": True},
        {"compact_ascii": True},
        {"compress": True},
    ],
    ids=["binary", "label64", "scalar32", "big-endian", "binary-gzip", "ascii-compact", "gzip"],
)
def test_hand_written_formats_read_alike(tmp_path, options):
    arrays = box_case()
    write_polymesh(tmp_path / "ascii", arrays)
    write_polymesh(tmp_path / "other", arrays, **options)
    reference, case = read_foam_case(tmp_path / "ascii"), read_foam_case(tmp_path / "other")
    for field in ("points", "face_offsets", "face_labels", "owner", "neighbour"):
        np.testing.assert_array_equal(getattr(case, field), getattr(reference, field))
    form = case.points_format
    assert form.binary == options.get("binary", False)
    assert form.compressed == options.get("compress", False)
    assert (form.label_bytes, form.scalar_bytes) == (
        options.get("label_bits", 32) // 8,
        options.get("scalar_bits", 64) // 8,
    )
    assert form.byte_order == options.get("byte_order", "<")
    # the boundary stays ASCII; inGroups written `List<word> 1(group_patch)`
    assert case.patch("xmin").in_groups == ("group_patch",)
    assert case.patch("xmin").entries == {}
    assert case.patches == reference.patches


def test_ascii_syntax_variants_read_alike(tmp_path):
    """Comments in the header and the lists, sizes on the list's line, lists without a
    size, uniform lists N{v}, and a face list on one line."""
    arrays = box_case((1, 1, 1), (1.0, 1.0, 1.0))
    write_polymesh(tmp_path / "plain", arrays)
    reference = read_foam_case(tmp_path / "plain")
    variant = tmp_path / "variant"
    shutil.copytree(tmp_path / "plain", variant)
    points = (variant / "points").read_text()
    points = points.replace("FoamFile\n{", "FoamFile // the header\n{ /* a\nblock comment */")
    points = points.replace("8\n(\n", "// eight points\n8 (  // on one line\n", 1)
    (variant / "points").write_text(points)
    (variant / "owner").write_text(
        (variant / "owner").read_text().split("6\n(")[0] + "6{0}\n// uniform\n"
    )
    faces = (variant / "faces").read_text()
    head, body = faces.split("6\n(\n")
    (variant / "faces").write_text(head + "(" + body.replace("\n", " "))  # no size, one line
    case = read_foam_case(variant)
    for field in ("points", "face_offsets", "face_labels", "owner", "neighbour"):
        np.testing.assert_array_equal(getattr(case, field), getattr(reference, field))
    assert case.n_cells == 1 and case.owner.tolist() == [0] * 6 and case.neighbour.size == 0
    [(kind, hexes)] = case.to_mesh_data().cells
    assert kind == "hexahedron" and signed_volumes(case.points, kind, hexes) == pytest.approx([1.0])


# -- writing points -----------------------------------------------------------------


@pytest.mark.slow
def test_unchanged_round_trip_leaves_every_file_byte_identical(channel_case, tmp_path):
    case = read_foam_case(channel_case[0])
    out = tmp_path / "copy"
    written = write_foam_points(case, case.points, out_case=out)
    assert written == out / "constant" / "polyMesh" / "points"
    originals = sorted(p.relative_to(case.root) for p in case.root.rglob("*") if p.is_file())
    copies = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert copies == originals
    # blockMesh wrote the points with writePrecision 17: even they come back byte for byte
    assert all((out / p).read_bytes() == (case.root / p).read_bytes() for p in originals)
    np.testing.assert_array_equal(read_foam_case(out).points, case.points)


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"binary": True},
        {"binary": True, "scalar_bits": 32, "label_bits": 64},
        {"compress": True},
    ],
    ids=["ascii", "binary", "binary-32-64", "gzip"],
)
def test_written_points_keep_the_format_and_read_back(box_dir, options, tmp_path):
    mesh_dir = box_dir / "constant" / "polyMesh"
    shutil.rmtree(mesh_dir)
    write_polymesh(mesh_dir, box_case(), **options)
    case = read_foam_case(box_dir)
    rng = np.random.default_rng(0)
    moved = case.points + 0.01 * rng.standard_normal(case.points.shape) / 3
    before = {p: p.read_bytes() for p in mesh_dir.iterdir()}
    written = write_foam_points(case, torch.from_numpy(moved))  # in place, from a tensor
    assert written == case.points_file
    for path, content in before.items():
        if path != case.points_file:
            assert path.read_bytes() == content, path.name
    again = read_foam_case(box_dir)
    expected = moved.astype(np.float32) if options.get("scalar_bits") == 32 else moved
    np.testing.assert_array_equal(again.points, expected)
    assert again.points_format == case.points_format
    compressed = options.get("compress", False)
    raw = written.read_bytes()
    assert (raw[:2] == b"\x1f\x8b") == compressed

    def text(content: bytes) -> bytes:
        return gzip.decompress(content) if compressed else content

    original = text(before[case.points_file])
    header = original.index(b"// * *")
    assert text(raw)[:header] == original[:header]  # the header as it was
    # unchanged points come back byte for byte (17 significant digits in ASCII)
    write_foam_points(again, case.points)
    assert text(case.points_file.read_bytes()) == original


def test_write_points_checks_its_arguments(box_dir, tmp_path):
    case = read_foam_case(box_dir)
    with pytest.raises(ValueError, match=r"points: expected shape \(36, 3\).*got \(36, 2\)"):
        write_foam_points(case, case.points[:, :2])
    bad = case.points.copy()
    bad[5, 1] = np.nan
    with pytest.raises(
        ValueError, match=r"points: 1 of the 36 rows are not finite \(the first is row 5\)"
    ):
        write_foam_points(case, bad)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "something").write_text("x")
    with pytest.raises(ValueError, match="out_case: .* exists and is not an empty directory"):
        write_foam_points(case, case.points, out_case=tmp_path / "full")
    with pytest.raises(ValueError, match="out_case: .* lies inside the case"):
        write_foam_points(case, case.points, out_case=box_dir / "copy")
    with pytest.raises(TypeError, match="case: expected a FoamCase"):
        write_foam_points(str(box_dir), case.points)
    with pytest.raises(KeyError, match="name: no patch 'inlet'; the patches are 'zmin', 'ymin'"):
        case.patch("inlet")
    # the polyMesh directory of a case reads as the case
    assert read_foam_case(box_dir / "constant" / "polyMesh").root == box_dir
    # the same case as out_case writes in place; an empty directory is filled
    write_foam_points(case, case.points, out_case=box_dir)
    (tmp_path / "empty").mkdir()
    write_foam_points(case, case.points + 1.0, out_case=tmp_path / "empty")
    np.testing.assert_array_equal(read_foam_case(tmp_path / "empty").points, case.points + 1.0)
    assert (tmp_path / "empty" / "system" / "controlDict").is_file()


def channel_displacement(points: np.ndarray) -> np.ndarray:
    """A smooth in-plane displacement that fixes the walls, inlet and outlet."""
    x, y = points[:, 0], points[:, 1]
    displacement = np.zeros_like(points)
    displacement[:, 1] = 0.05 * np.sin(np.pi * x / 2) * np.sin(np.pi * y)
    return displacement


@pytest.mark.slow
def test_moved_channel_passes_checkmesh_and_runs_potentialfoam(channel_case, tmp_path):
    case = read_foam_case(channel_case[0])
    moved = case.points + channel_displacement(case.points)
    out = tmp_path / "moved"
    write_foam_points(case, moved, out_case=out)
    assert same_files(case.mesh_dir, out / "constant" / "polyMesh") == ["points"]
    np.testing.assert_array_equal(read_foam_case(out).points, moved)
    assert "Mesh OK." in foam("checkMesh", out)
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
    log = foam("potentialFoam -writep", out)
    assert "Solving for Phi" in log and log.rstrip().endswith("End")
    assert "nonuniform" in (out / "0" / "U").read_text()


@pytest.mark.slow
def test_moved_binary_and_gzipped_cases_pass_checkmesh(channel_case, tmp_path):
    for name, write_format, compression in (("binary", "binary", "off"), ("gzip", "ascii", "on")):
        source = tmp_path / name
        shutil.copytree(channel_case[0], source)
        control_dict(source, write_format=write_format, compression=compression)
        foam("foamFormatConvert -constant", source)
        case = read_foam_case(source)
        out = tmp_path / f"{name}-moved"
        write_foam_points(case, case.points + channel_displacement(case.points), out_case=out)
        log = foam("checkMesh", out)
        assert "Mesh OK." in log
        # the boundary stays where it was (walls, inlet and outlet fixed, in-plane motion)
        np.testing.assert_allclose(checkmesh_volume(log), 1.0, rtol=1e-12)


# -- pseudo-2-D cases ---------------------------------------------------------------


@pytest.mark.slow
def test_pseudo_2d_channel(tmp_path):
    needs_openfoam()
    case_dir = tmp_path / "flat"
    flat_channel(case_dir, cells=(20, 8), thickness=0.1)
    case = read_foam_case(case_dir)
    flat = pseudo_2d(case)
    assert flat.axis == 2 and flat.in_plane == (0, 1)
    assert flat.planes == pytest.approx((0.0, 0.1), abs=1e-15)
    assert flat.mesh.planar_coordinate == flat.planes[0]
    assert flat.empty_patches == ("frontAndBack",)
    assert flat.front.size == flat.back.size == 21 * 9 == case.n_points // 2
    # blockMesh's twins can differ in the last bit
    np.testing.assert_allclose(case.points[flat.front, :2], case.points[flat.back, :2], atol=1e-15)
    assert np.all(case.points[flat.front, 2] == flat.planes[0])
    np.testing.assert_allclose(case.points[flat.back, 2], 0.1, rtol=1e-15)
    mesh = flat.mesh
    np.testing.assert_array_equal(mesh.points, case.points[flat.front, :2])
    [(kind, quads)] = mesh.cells
    assert kind == "quad" and quads.shape == (160, 4)
    areas = signed_areas(mesh.points, quads)
    np.testing.assert_allclose(areas, 4.0 / 160, rtol=1e-12)  # counter-clockwise
    assert sorted(mesh.cell_data["foam_cell"][0]) == list(range(160))
    lines = {name: blocks[0][1] for name, blocks in mesh.face_sets.items()}
    assert {name: len(block) for name, block in lines.items()} == {
        "inlet": 8,
        "outlet": 8,
        "lower": 20,
        "upper": 20,
    }
    outward = {"inlet": (-1, 0), "outlet": (1, 0), "lower": (0, -1), "upper": (0, 1)}
    for name, block in lines.items():
        tangent = mesh.points[block[:, 1]] - mesh.points[block[:, 0]]
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)  # the tangent turned right
        assert np.all(normal @ np.array(outward[name]) > 0), name
    assert mesh.groups == {"walls": ["lower", "upper"], "wall": ["lower", "upper"]}


@pytest.mark.slow
def test_pseudo_2d_triangles_and_quads_from_a_collapsed_block(tmp_path):
    needs_openfoam()
    case_dir = tmp_path / "slab"
    triangle_slab(case_dir, cells=4)
    fv_dicts(case_dir)
    stats = mesh_statistics(foam("checkMesh", case_dir))
    case = read_foam_case(case_dir)
    cells = {kind: len(block) for kind, block in case.to_mesh_data().cells}
    assert (
        cells
        == {"wedge": stats["prisms"], "hexahedron": stats["hexahedra"]}
        == {
            "wedge": 4,
            "hexahedron": 12,
        }
    )
    flat = pseudo_2d(case)
    kinds = dict(flat.mesh.cells)
    assert {kind: len(block) for kind, block in kinds.items()} == {"triangle": 4, "quad": 12}
    total = sum(signed_areas(flat.mesh.points, block).sum() for block in kinds.values())
    assert all(np.all(signed_areas(flat.mesh.points, block) > 0) for block in kinds.values())
    np.testing.assert_allclose(total, 0.5, rtol=1e-12)
    sets = flat.mesh.face_sets
    assert {name: sum(len(b) for _, b in blocks) for name, blocks in sets.items()} == {
        "bottom": 4,
        "right": 4,
        "left": 4,
    }
    # blockMesh's defaultFaces (no faces here) is empty too
    assert flat.empty_patches == ("frontAndBack", "defaultFaces")


@pytest.mark.slow
def test_lifted_displacement_written_back_passes_checkmesh(tmp_path):
    needs_openfoam()
    case_dir = tmp_path / "flat"
    flat_channel(case_dir, cells=(20, 8))
    fv_dicts(case_dir)
    case = read_foam_case(case_dir)
    flat = pseudo_2d(case)
    x, y = flat.mesh.points[:, 0], flat.mesh.points[:, 1]
    displacement = np.stack(
        [
            0.1 * np.sin(np.pi * y) * np.sin(np.pi * x / 4),
            0.04 * np.sin(np.pi * y) * np.sin(np.pi * x / 2),
        ],
        axis=1,
    )
    lifted = flat.lift(displacement)
    out = tmp_path / "moved"
    write_foam_points(case, case.points + lifted, out_case=out)
    moved = read_foam_case(out)
    again = pseudo_2d(moved)
    np.testing.assert_array_equal(again.front, flat.front)
    np.testing.assert_allclose(
        again.mesh.points, flat.mesh.points + displacement, rtol=0, atol=1e-15
    )
    np.testing.assert_array_equal(moved.points[:, 2], case.points[:, 2])
    log = foam("checkMesh", out)
    assert "Mesh OK." in log and "Mesh has 2 geometric (non-empty/wedge) directions" in log


def test_lift_moves_both_layers_alike_for_arrays_and_tensors(tmp_path):
    case = flat_box(tmp_path)
    flat = pseudo_2d(case)
    n = flat.front.size
    assert n == 5 * 4 and case.n_points == 2 * n
    rng = np.random.default_rng(1)
    displacement = rng.standard_normal((n, 2))
    lifted = flat.lift(displacement)
    assert lifted.shape == (case.n_points, 3) and lifted.dtype == np.float64
    np.testing.assert_array_equal(lifted[flat.front, :2], displacement)
    np.testing.assert_array_equal(lifted[flat.back, :2], displacement)
    assert np.all(lifted[:, 2] == 0)
    batch = torch.tensor(rng.standard_normal((3, n, 2)), requires_grad=True)
    lifted_batch = flat.lift(batch)
    assert isinstance(lifted_batch, torch.Tensor) and lifted_batch.shape == (3, case.n_points, 3)
    for k in range(3):
        np.testing.assert_array_equal(
            lifted_batch[k].detach().numpy(), flat.lift(batch[k].detach().numpy())
        )
    lifted_batch.sum().backward()
    np.testing.assert_array_equal(batch.grad.numpy(), np.full((3, n, 2), 2.0))
    with pytest.raises(ValueError, match=r"displacement: expected shape \(\.\.\., 20, 2\)"):
        flat.lift(np.zeros((n, 3)))


def test_pseudo_2d_along_x(tmp_path):
    """The flat box with its coordinates turned (x, y, z) -> (z, x, y): empty along x."""
    flat_z = pseudo_2d(flat_box(tmp_path))
    case = flat_z.case
    turned = dataclasses.replace(case, points=case.points[:, [2, 0, 1]])
    flat_x = pseudo_2d(turned)
    assert flat_x.axis == 0 and flat_x.in_plane == (1, 2) and flat_x.planes == (0.0, 1.0)
    np.testing.assert_array_equal(flat_x.front, flat_z.front)
    np.testing.assert_array_equal(flat_x.back, flat_z.back)
    np.testing.assert_array_equal(flat_x.mesh.points, flat_z.mesh.points)
    for (kind_x, cells_x), (kind_z, cells_z) in zip(
        flat_x.mesh.cells, flat_z.mesh.cells, strict=True
    ):
        assert kind_x == kind_z == "quad"
        np.testing.assert_array_equal(cells_x, cells_z)
        np.testing.assert_allclose(signed_areas(flat_x.mesh.points, cells_x), 0.5)
    lifted = flat_x.lift(np.ones((flat_x.front.size, 2)))
    assert np.all(lifted[:, 0] == 0) and np.all(lifted[:, 1:] == 1)


def test_pseudo_2d_is_none_without_empty_patches(box_dir):
    assert pseudo_2d(read_foam_case(box_dir)) is None


def test_pseudo_2d_refuses_what_is_not_one_cell_thick(tmp_path):
    case = flat_box(tmp_path)
    flat = pseudo_2d(case)
    turn = np.radians(30)
    rotation = np.array(
        [[1, 0, 0], [0, np.cos(turn), -np.sin(turn)], [0, np.sin(turn), np.cos(turn)]]
    )
    turned = dataclasses.replace(case, points=case.points @ rotation.T)
    with pytest.raises(
        ValueError, match="case: the empty patches' faces are not normal to a coordinate axis"
    ):
        pseudo_2d(turned)
    astray = case.points.copy()
    astray[flat.back[3], 0] += 0.05
    with pytest.raises(
        ValueError, match=rf"case: point {flat.front[3]} on the front plane has no twin"
    ):
        pseudo_2d(dataclasses.replace(case, points=astray))
    with pytest.raises(ValueError, match="tolerance: must be > 0"):
        pseudo_2d(case, tolerance=0.0)
    thick = flat_box(tmp_path / "thick", counts=(2, 2, 2))
    with pytest.raises(
        ValueError, match=r"case: point \d+ lies off both empty planes \(z = 0 and 1\)"
    ):
        pseudo_2d(thick)


# -- bad input ----------------------------------------------------------------------


def test_missing_files_and_directories_are_named(box_dir, tmp_path):
    (box_dir / "constant" / "polyMesh" / "owner").unlink()
    with pytest.raises(ValueError, match=r"case: .*polyMesh/owner is missing"):
        read_foam_case(box_dir)
    with pytest.raises(ValueError, match="case: .* is neither a case directory"):
        read_foam_case(tmp_path / "nothing")


def edit(path: Path, old: str, new: str, count: int = 1) -> None:
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, count))


def test_truncated_lists_are_named(box_dir):
    mesh_dir = box_dir / "constant" / "polyMesh"
    points = (mesh_dir / "points").read_text()
    middle = points.index("\n(", points.index("\n36\n(") + 5) + 4
    (mesh_dir / "points").write_text(points[:middle])
    with pytest.raises(ValueError, match=r"case: .*polyMesh/points: the points list is truncated"):
        read_foam_case(box_dir)


def test_truncated_binary_list_is_named(tmp_path):
    mesh_dir = tmp_path / "polyMesh"
    write_polymesh(mesh_dir, box_case(), binary=True)
    raw = (mesh_dir / "owner").read_bytes()
    (mesh_dir / "owner").write_bytes(raw[: raw.rindex(b")") - 8])
    with pytest.raises(
        ValueError, match=r"case: .*polyMesh/owner: the binary owner list is truncated"
    ):
        read_foam_case(mesh_dir)
    write_polymesh(mesh_dir, box_case(), binary=True, scalar_bits=32)
    edit_bytes = (mesh_dir / "points").read_bytes().replace(b"scalar=32", b"scalar=64")
    (mesh_dir / "points").write_bytes(edit_bytes)
    with pytest.raises(
        ValueError, match="points: the binary points list is truncated or of another precision"
    ):
        read_foam_case(mesh_dir)


def test_counts_that_disagree_are_named(box_dir):
    mesh_dir = box_dir / "constant" / "polyMesh"
    n = read_foam_case(box_dir).n_faces
    edit(mesh_dir / "owner", f"\n{n}\n(", f"\n{n - 1}\n(")
    with pytest.raises(
        ValueError, match=f"owner: the owner list says {n - 1} entries, it holds {n}"
    ):
        read_foam_case(box_dir)
    edit(mesh_dir / "owner", f"\n{n - 1}\n(\n0\n", f"\n{n - 1}\n(\n")
    with pytest.raises(ValueError, match=f"owner has {n - 1} labels for the {n} faces"):
        read_foam_case(box_dir)


def test_patches_beyond_the_faces_are_named(box_dir):
    mesh_dir = box_dir / "constant" / "polyMesh"
    n = read_foam_case(box_dir).n_faces
    text = (mesh_dir / "boundary").read_text()
    head, last, tail = re.split(r"nFaces +(\d+);(?!.*nFaces)", text, flags=re.S)
    (mesh_dir / "boundary").write_text(f"{head}nFaces {int(last) + 1};{tail}")
    with pytest.raises(
        ValueError, match=rf"boundary: patch '\w+' \(faces \d+ \.\. {n}\) lies beyond the {n} faces"
    ):
        read_foam_case(box_dir)


def test_labels_out_of_range_are_named(box_dir):
    mesh_dir = box_dir / "constant" / "polyMesh"
    text = (mesh_dir / "faces").read_text()
    first = re.search(r"\n4\((\d+) ", text).group(1)
    edit(mesh_dir / "faces", f"\n4({first} ", "\n4(999 ")
    with pytest.raises(
        ValueError, match="faces: face 0 refers to point 999, out of range for the 36 points"
    ):
        read_foam_case(box_dir)
    edit(mesh_dir / "faces", "\n4(999 ", "\n4(x7 ")
    with pytest.raises(ValueError, match="polyMesh/faces: 'x7' in the faces list is not a label"):
        read_foam_case(box_dir)


def test_a_polyhedron_is_refused_by_name(tmp_path):
    """Two hexahedra merged into one cell of 10 faces (the face between them removed)."""
    arrays = box_case((2, 1, 1), (2.0, 1.0, 1.0))
    assert len(arrays["neighbour"]) == 1
    arrays["faces"] = arrays["faces"][1:]
    arrays["owner"] = np.zeros(len(arrays["faces"]), dtype=np.int64)
    arrays["neighbour"] = np.zeros(0, dtype=np.int64)
    arrays["patches"] = [(name, kind, n, start - 1) for name, kind, n, start in arrays["patches"]]
    write_polymesh(tmp_path / "polyMesh", arrays)
    case = read_foam_case(tmp_path / "polyMesh")
    assert case.n_cells == 1 and case.n_faces == 10
    with pytest.raises(
        ValueError,
        match=r"case: cell 0 has 10 faces \(0 triangles, 10 quadrilaterals.*not a tetrahedron",
    ):
        case.to_mesh_data()
