"""Reading and writing meshes with node sets and fields (vtu, vtk, xdmf, msh)."""

from __future__ import annotations

import meshio
import numpy as np
import pytest
import torch
from _grids import kuhn_grid

from torchmorph.mesh import TetMesh
from torchmorph.mesh.io import from_meshio, read_mesh, to_meshio, write_mesh
from torchmorph.mesh.quality import edge_ratio

F64 = torch.float64


@pytest.fixture
def cube() -> TetMesh:
    points, tets = kuhn_grid(2)
    # irrational-looking coordinates so that a lossy writer would show
    points = points * np.array([1.0, np.pi, np.e]) + 0.1234567890123
    bottom = np.flatnonzero(np.isclose(points[:, 2], points[:, 2].min()))
    corner = [0]
    return TetMesh(points, tets, {"bottom": bottom, "corner": corner, "empty": []}, name="cube")


FORMATS = [".vtu", ".vtk", ".xdmf", ".msh"]


def needs_h5py(extension: str) -> None:
    if extension == ".xdmf":
        pytest.importorskip("h5py")


@pytest.mark.parametrize("extension", FORMATS)
def test_round_trip(tmp_path, cube, extension):
    needs_h5py(extension)
    generator = torch.Generator().manual_seed(0)
    displacement = torch.randn(cube.num_nodes, 3, generator=generator, dtype=F64)
    pressure = torch.randn(cube.num_nodes, generator=generator, dtype=F64)
    quality = edge_ratio(cube.points, cube.tets)
    path = tmp_path / f"mesh{extension}"
    write_mesh(
        path,
        cube,
        point_data={"displacement": displacement, "pressure": pressure},
        cell_data={"quality": quality},
    )
    mesh, point_data, cell_data = read_mesh(path, return_data=True)
    assert mesh.name == "mesh"
    assert torch.equal(mesh.points, cube.points)
    assert torch.equal(mesh.tets, cube.tets)
    assert sorted(mesh.node_sets) == ["bottom", "corner", "empty"]
    for name, nodes in cube.node_sets.items():
        assert torch.equal(mesh.node_set(name), nodes)
    assert sorted(point_data) == ["displacement", "pressure"]
    assert torch.equal(point_data["displacement"], displacement)
    assert torch.equal(point_data["pressure"].reshape(-1), pressure)
    assert sorted(cell_data) == ["quality"]
    assert torch.equal(cell_data["quality"].reshape(-1), quality)


@pytest.mark.parametrize("extension", FORMATS)
def test_read_without_data_returns_the_mesh(tmp_path, cube, extension):
    needs_h5py(extension)
    path = tmp_path / f"mesh{extension}"
    write_mesh(path, cube)
    mesh = read_mesh(path)
    assert isinstance(mesh, TetMesh)
    assert torch.equal(mesh.boundary_faces, cube.boundary_faces)


def test_float32_points_and_tensor_on_meshio_round_trip(cube):
    single = cube.to(dtype=torch.float32)
    m = to_meshio(single, point_data={"flag": torch.ones(cube.num_nodes, dtype=torch.bool)})
    assert m.points.dtype == np.float32
    assert m.point_data["flag"].dtype == np.uint8
    assert m.point_data["set:bottom"].sum() == cube.node_set("bottom").numel()
    back, point_data, _ = from_meshio(m, return_data=True)
    assert torch.equal(back.node_set("corner"), cube.node_set("corner"))
    assert torch.equal(point_data["flag"], torch.ones(cube.num_nodes, dtype=torch.uint8))


def test_other_cell_blocks_are_ignored_and_physical_groups_become_node_sets(tmp_path, cube):
    # a Gmsh 2.2 file with a named physical surface group on the bottom face
    faces = cube.boundary_faces
    on_bottom = torch.isin(faces, cube.node_set("bottom")).all(dim=1)
    triangles = faces[on_bottom].numpy()
    m = meshio.Mesh(
        cube.points.numpy(),
        [("triangle", triangles), ("tetra", cube.tets.numpy())],
        cell_data={
            "gmsh:physical": [np.full(len(triangles), 7), np.full(cube.num_tets, 1)],
            "gmsh:geometrical": [np.full(len(triangles), 1), np.full(cube.num_tets, 1)],
        },
        field_data={"floor": np.array([7, 2]), "fluid": np.array([1, 3])},
    )
    path = tmp_path / "physical.msh"
    meshio.write(path, m, file_format="gmsh22", binary=True)
    mesh = read_mesh(path)
    assert mesh.num_tets == cube.num_tets
    # a physical surface is a face set (a marker); volume groups give no marker
    assert sorted(mesh.markers) == ["floor"] and sorted(mesh.face_sets) == ["floor"]
    assert torch.equal(mesh.node_set("floor"), cube.node_set("bottom"))


def test_gmsh_generated_mesh_with_physical_groups(tmp_path):
    gmsh = pytest.importorskip("gmsh")
    path = tmp_path / "box.msh"
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        surfaces = {
            tag: gmsh.model.occ.getCenterOfMass(dim, tag) for dim, tag in gmsh.model.getEntities(2)
        }
        xmin = [tag for tag, centre in surfaces.items() if abs(centre[0]) < 1e-9]
        ymax = [tag for tag, centre in surfaces.items() if abs(centre[1] - 1) < 1e-9]
        gmsh.model.addPhysicalGroup(2, xmin, name="inlet")
        gmsh.model.addPhysicalGroup(2, ymax, name="top")
        gmsh.model.addPhysicalGroup(3, [1], name="fluid")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.5)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    mesh = read_mesh(path)
    assert sorted(mesh.face_sets) == ["inlet", "top"] and sorted(mesh.markers) == ["inlet", "top"]
    inlet = mesh.points[mesh.node_set("inlet")]
    top = mesh.points[mesh.node_set("top")]
    assert float(inlet[:, 0].abs().max()) < 1e-12
    assert float((top[:, 1] - 1).abs().max()) < 1e-12
    on_x0 = torch.nonzero(mesh.points[:, 0].abs() < 1e-12).flatten()
    assert torch.equal(mesh.node_set("inlet"), on_x0)
    torch.testing.assert_close(mesh.volumes.sum(), torch.tensor(1.0, dtype=F64))


# ----------------------------------------------------------------------------- errors


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_mesh(tmp_path / "absent.vtu")


@pytest.mark.parametrize("name", ["mesh.stl", "mesh", "mesh.txt"])
def test_unknown_extension(tmp_path, cube, name):
    with pytest.raises(ValueError, match="unsupported mesh file extension"):
        read_mesh(tmp_path / name)
    with pytest.raises(ValueError, match="unsupported mesh file extension"):
        write_mesh(tmp_path / name, cube)


def test_a_surface_in_3d_or_lines_alone_are_no_mesh(tmp_path):
    path = tmp_path / "surface.vtu"
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    triangles = np.array([[0, 1, 2], [0, 1, 3]])
    meshio.write(path, meshio.Mesh(points, [("triangle", triangles)]))
    with pytest.raises(ValueError, match=r"surface.vtu.*a surface mesh in 3-D is not a volume"):
        read_mesh(path)
    meshio.write(path, meshio.Mesh(points, [("line", np.array([[0, 1]]))]))
    with pytest.raises(ValueError, match=r"no cells of dimension 2 or 3"):
        read_mesh(path)


def test_a_planar_triangle_mesh_is_read_in_2d(tmp_path):
    path = tmp_path / "plane.vtu"
    points = np.array([[0.0, 0, 5], [1, 0, 5], [0, 1, 5], [1, 1, 5]])
    meshio.write(path, meshio.Mesh(points, [("triangle", np.array([[0, 1, 2], [1, 3, 2]]))]))
    mesh = read_mesh(path)
    assert mesh.dim == 2 and mesh.cell_counts == {"triangle": 2}
    torch.testing.assert_close(mesh.points, torch.from_numpy(points[:, :2]))


def test_unreadable_file(tmp_path):
    path = tmp_path / "broken.msh"
    path.write_text("not a mesh\n")
    with pytest.raises(ValueError, match="could not read"):
        read_mesh(path)


def test_write_rejects_bad_fields(tmp_path, cube):
    path = tmp_path / "mesh.vtu"
    with pytest.raises(ValueError, match=r"point_data\['d'\] must have shape \(27,\) or \(27, k\)"):
        write_mesh(path, cube, point_data={"d": torch.zeros(5, 3)})
    with pytest.raises(ValueError, match=r"cell_data\['q'\] must have shape \(48,\)"):
        write_mesh(path, cube, cell_data={"q": torch.zeros(47)})
    with pytest.raises(ValueError, match=r"point_data\['set:x'\]: names starting with 'set:'"):
        write_mesh(path, cube, point_data={"set:x": torch.zeros(27)})


# --------------------------------------------------------------------------- awkward names

AWKWARD_SET_NAMES = [
    "inlet wall",
    'q"uote',
    "less<than",
    "amp&ersand",
    "tab\tname",
    "new\nline",
    "apos'trophe",
    "greater>than",
    "per%cent",
    "per%41cent",
    "ümlaut-ε",
    "semi;colon",
    "col:on",
    " leading",
    "trailing ",
    "no\u00a0break",
    "set:nested",
    "back\\slash",
]


@pytest.mark.parametrize("extension", FORMATS)
def test_awkward_node_set_names_round_trip(tmp_path, cube, extension):
    needs_h5py(extension)
    sets = {name: [index] for index, name in enumerate(AWKWARD_SET_NAMES)}
    mesh = TetMesh(cube.points, cube.tets, sets)
    path = tmp_path / f"awkward{extension}"
    write_mesh(path, mesh)
    back = read_mesh(path)
    assert sorted(back.node_sets) == sorted(AWKWARD_SET_NAMES)
    for name, nodes in sets.items():
        assert back.node_sets[name].tolist() == nodes


def test_node_set_names_are_percent_encoded_only_where_needed(cube):
    from torchmorph.mesh.io import decode_set_name, encode_set_name

    assert encode_set_name("wing") == "wing"
    assert encode_set_name("ε-wall_2") == "ε-wall_2"
    assert encode_set_name('a b"<&%') == "a%20b%22%3C%26%25"
    assert encode_set_name("tab\tline\n") == "tab%09line%0A"
    for name in AWKWARD_SET_NAMES:
        assert decode_set_name(encode_set_name(name)) == name
    converted = to_meshio(TetMesh(cube.points, cube.tets, {"inlet wall": [0]}))
    assert "set:inlet%20wall" in converted.point_data


# Field names each format refuses (before writing anything) and the ones it keeps.
FIELD_NAMES = {
    ".vtu": (['q"x', "l<x", "g>x", "a&x", "p'x", "t\tx", "n\nx"], ["a b", "ü", "c:d"]),
    ".vtk": (["a b", "t\tx", "n\nx", " lead"], ['q"x', "l<x", "a&x", "ü"]),
    ".xdmf": (["t\tx", "n\nx"], ["a b", 'q"x', "l<x", "a&x", "ü"]),
    ".msh": (['q"x', "t\tx", "n\nx"], ["a b", "l<x", "a&x", "ü"]),
}


@pytest.mark.parametrize("extension", FORMATS)
def test_field_names_validated_per_format(tmp_path, cube, extension):
    needs_h5py(extension)
    refused, kept = FIELD_NAMES[extension]
    path = tmp_path / f"fields{extension}"
    values = np.arange(cube.num_nodes, dtype=np.float64)
    for name in refused:
        with pytest.raises(ValueError, match=r"point_data\[.*cannot hold the character"):
            write_mesh(path, cube, point_data={name: values})
        with pytest.raises(ValueError, match=r"cell_data\[.*cannot hold the character"):
            write_mesh(path, cube, cell_data={name: np.ones(cube.num_tets)})
        assert list(tmp_path.iterdir()) == []  # nothing written, no temporary left
    write_mesh(path, cube, point_data=dict.fromkeys(kept, values))
    _, point_data, _ = read_mesh(path, return_data=True)
    assert sorted(point_data) == sorted(kept)
    for name in kept:
        np.testing.assert_array_equal(point_data[name].numpy().ravel(), values)


@pytest.mark.parametrize("extension", FORMATS)
def test_failing_overwrite_leaves_the_old_file_intact(tmp_path, cube, extension, monkeypatch):
    needs_h5py(extension)
    path = tmp_path / f"mesh{extension}"
    write_mesh(path, cube)
    before = {item.name: item.read_bytes() for item in tmp_path.iterdir()}

    def broken_write(filename, mesh, *args, **kwargs):
        with open(filename, "wb") as handle:  # half a file, then a failure
            handle.write(b"truncated")
        raise OSError("disk full")

    monkeypatch.setattr(meshio, "write", broken_write)
    with pytest.raises(OSError, match="disk full"):
        write_mesh(path, TetMesh(cube.points * 2.0, cube.tets))
    after = {item.name: item.read_bytes() for item in tmp_path.iterdir()}
    assert after == before  # old file(s) unchanged, no temporary left behind
    assert torch.equal(read_mesh(path).points, cube.points)


def test_xdmf_overwrite_replaces_both_files(tmp_path, cube):
    pytest.importorskip("h5py")
    path = tmp_path / "mesh.xdmf"
    write_mesh(path, cube)
    write_mesh(path, TetMesh(cube.points * 2.0, cube.tets))
    assert sorted(item.name for item in tmp_path.iterdir()) == ["mesh.h5", "mesh.xdmf"]
    assert torch.allclose(read_mesh(path).points, cube.points * 2.0)


def test_written_files_are_readable_by_others(tmp_path, cube):
    import os
    import stat

    umask = os.umask(0o022)
    try:
        write_mesh(tmp_path / "mesh.vtu", cube)
    finally:
        os.umask(umask)
    mode = stat.S_IMODE((tmp_path / "mesh.vtu").stat().st_mode)
    assert mode == 0o644


def test_write_into_a_missing_directory(tmp_path, cube):
    with pytest.raises(FileNotFoundError, match="path: directory .*does not exist"):
        write_mesh(tmp_path / "missing" / "mesh.vtu", cube)
