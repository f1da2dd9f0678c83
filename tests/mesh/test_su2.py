"""SU2 mesh files (``.su2``): reading, writing and exact round trips of points, cells and
markers, checked against the files' text, meshio's SU2 reader, gmsh and analytic volumes."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import meshio
import numpy as np
import pytest

from torchmorph.mesh.formats import MeshData
from torchmorph.mesh.formats.su2 import ELEMENT_INDEX, read_su2, write_su2

# A 2-D mesh of a 2 x 1 rectangle: two triangles on the left, a quad on the right, listed
# triangle, quad, triangle (kinds interleave). Comments, blank lines, keywords with and
# without spaces around "=", trailing element and point indices, a domain count.
MESH_2D = """\
% a hand-written 2-D SU2 mesh
NDIME=2

NELEM = 3   % three elements
5 0 1 4 0
9 1 2 5 4 1
5 0 4 3 2
NPOIN= 6 6
0.0 0.0 0
1.0 0.1 1
2.0 0.0 2
0.0 1.0 3
0.3333333333333333 1.0 4
2.0 1.0 5
NMARK= 2
MARKER_TAG= airfoil
MARKER_ELEMS= 2
3 0 1
3 1 2
MARKER_TAG=farfield
MARKER_ELEMS =4
3 2 5
3 5 4
3 4 3
3 3 0
"""

POINTS_2D = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [0.0, 1.0], [1.0 / 3.0, 1.0], [2.0, 1.0]])

# A 3-D mesh of the unit cube (hexahedron) with a pyramid on top, a wedge at x > 1 and a
# tetrahedron on each of the faces y = 0 and x = 0; all positively oriented in SU2's (VTK's)
# convention, total volume 1 + 1/6 + 1/2 + 1/6 + 1/6 = 2.
POINTS_3D = np.array(
    [
        [0.0, 0.0, 0.0],  # 0..7: the unit cube, VTK's hexahedron order
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 0.0, 1.0],
        [1.0, 1.0, 1.0],
        [0.0, 1.0, 1.0],
        [0.5, 0.5, 1.5],  # 8: the pyramid's apex
        [2.0, 0.5, 0.0],  # 9, 10: the wedge's outer edge
        [2.0, 0.5, 1.0],
        [0.5, -1.0, 0.5],  # 11: apex of the tetrahedron on y = 0
        [-1.0, 0.5, 0.5],  # 12: apex of the tetrahedron on x = 0
    ]
)
CELLS_3D = [  # (VTK type, nodes) in the file's order
    (12, [0, 1, 2, 3, 4, 5, 6, 7]),
    (10, [0, 1, 4, 11]),
    (14, [4, 5, 6, 7, 8]),
    (13, [1, 2, 9, 5, 6, 10]),
    (10, [0, 4, 3, 12]),
]
MARKERS_3D = {  # name -> [(VTK type, nodes)]: triangles and quads, interleaved in "sides"
    "bottom": [(9, [0, 3, 2, 1]), (5, [1, 2, 9])],
    "roof": [(5, [4, 5, 8]), (5, [5, 6, 8]), (5, [6, 7, 8]), (5, [7, 4, 8])],
    "sides": [(9, [2, 3, 7, 6]), (5, [0, 11, 1]), (9, [9, 2, 6, 10]), (5, [0, 12, 4])],
}
KIND = {
    3: "line",
    5: "triangle",
    9: "quad",
    10: "tetra",
    12: "hexahedron",
    13: "wedge",
    14: "pyramid",
}


def mesh_3d_text() -> str:
    lines = ["NDIME= 3", f"NELEM= {len(CELLS_3D)}"]
    lines += [" ".join(map(str, [vtk_type, *nodes])) for vtk_type, nodes in CELLS_3D]
    lines += [f"NPOIN= {len(POINTS_3D)}"] + [" ".join(map(repr, p)) for p in POINTS_3D.tolist()]
    lines += [f"NMARK= {len(MARKERS_3D)}"]
    for name, facets in MARKERS_3D.items():
        lines += [f"MARKER_TAG= {name}", f"MARKER_ELEMS= {len(facets)}"]
        lines += [" ".join(map(str, [vtk_type, *nodes])) for vtk_type, nodes in facets]
    return "\n".join(lines) + "\n"


# Outward faces of each kind in SU2's node order (VTK's), as SU2 lists them
# (C{Tetrahedron,Pyramid,Prism,Hexahedron}Connectivity::Faces). SU2's wedge ("prism") has
# its triangle (0, 1, 2) facing away from (3, 4, 5): the mirror image of gmsh's prism.
OUTWARD_FACES = {
    "tetra": [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)],
    "hexahedron": [
        (0, 1, 5, 4),
        (1, 2, 6, 5),
        (2, 3, 7, 6),
        (3, 0, 4, 7),
        (0, 3, 2, 1),
        (4, 5, 6, 7),
    ],
    "wedge": [(3, 4, 1, 0), (5, 2, 1, 4), (2, 5, 3, 0), (0, 1, 2), (5, 4, 3)],
    "pyramid": [(0, 3, 2, 1), (4, 3, 0), (4, 0, 1), (2, 4, 1), (3, 4, 2)],
}


def signed_volumes(points: np.ndarray, kind: str, cells: np.ndarray) -> np.ndarray:
    """Volumes by the divergence theorem over the outward faces (each face fanned from its
    centroid, each triangle closed with the cell's centroid); positive for VTK's order."""
    vertices = points[cells]  # (M, n, 3)
    centre = vertices.mean(axis=1)
    volume = np.zeros(len(cells))
    for face in OUTWARD_FACES[kind]:
        corners = vertices[:, list(face)]
        face_centre = corners.mean(axis=1)
        for a, b in zip(face, face[1:] + face[:1], strict=True):
            edges = np.stack(
                [vertices[:, a] - centre, vertices[:, b] - centre, face_centre - centre], axis=1
            )
            volume += np.linalg.det(edges) / 6.0
    return volume


def meshio_read(path: Path, tmp_path: Path) -> meshio.Mesh:
    """meshio's SU2 reader on a copy of ``path`` in the form it parses: no comments, and
    ``KEYWORD= value`` (it neither strips comments nor spaces before ``=``)."""
    lines = [line.split("%")[0] for line in path.read_text().splitlines()]
    text = "\n".join(re.sub(r"\s*=\s*", "= ", line) for line in lines) + "\n"
    copy = tmp_path / f"meshio_{path.name}"
    copy.write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # meshio warns that it numbers the string tags
        return meshio.su2.read(str(copy))


def write_text(tmp_path: Path, text: str, name: str = "mesh.su2") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def assert_same_mesh(first: MeshData, second: MeshData) -> None:
    """Bit-for-bit equal points, equal cell blocks, element indices and markers."""
    assert first.points.dtype == second.points.dtype == np.float64
    assert first.points.shape == second.points.shape
    assert first.points.tobytes() == second.points.tobytes()
    assert [kind for kind, _ in first.cells] == [kind for kind, _ in second.cells]
    for (_, a), (_, b) in zip(first.cells, second.cells, strict=True):
        assert a.dtype == b.dtype == np.int64 and np.array_equal(a, b)
    assert first.cell_data.keys() == second.cell_data.keys()
    for a, b in zip(first.cell_data[ELEMENT_INDEX], second.cell_data[ELEMENT_INDEX], strict=True):
        assert np.array_equal(a, b)
    assert list(first.face_sets) == list(second.face_sets)
    for name, facets in first.face_sets.items():
        other = second.face_sets[name]
        assert [kind for kind, _ in facets] == [kind for kind, _ in other]
        for (_, a), (_, b) in zip(facets, other, strict=True):
            assert a.dtype == b.dtype == np.int64 and np.array_equal(a, b)
    assert list(first.node_sets) == list(second.node_sets)
    for name, nodes in first.node_sets.items():
        assert np.array_equal(nodes, second.node_sets[name])


def element_lines(path: Path, keyword: str = "NELEM") -> list[list[int]]:
    """The element lines after ``keyword=``, as integers without a trailing index."""
    lines = [line.split("%")[0].strip() for line in path.read_text().splitlines()]
    lines = [line for line in lines if line]
    start = next(
        i for i, line in enumerate(lines) if line.replace(" ", "").startswith(keyword + "=")
    )
    count = int(lines[start].split("=")[1].split()[0])
    rows = [[int(token) for token in line.split()] for line in lines[start + 1 : start + 1 + count]]
    width = {3: 2, 5: 3, 9: 4, 10: 4, 12: 8, 13: 6, 14: 5}
    return [row[: 1 + width[row[0]]] for row in rows]


# --------------------------------------------------------------------------- 2-D


def test_read_2d_mixed(tmp_path):
    path = write_text(tmp_path, MESH_2D)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # indices equal to the line order: no warning
        data = read_su2(path)

    assert data.points.dtype == np.float64 and data.points.shape == (6, 2)
    assert data.points.tobytes() == POINTS_2D.tobytes()  # 1/3 parsed to the same double
    assert [kind for kind, _ in data.cells] == ["triangle", "quad"]
    assert np.array_equal(data.cells[0][1], [[0, 1, 4], [0, 4, 3]])
    assert np.array_equal(data.cells[1][1], [[1, 2, 5, 4]])
    assert all(block.dtype == np.int64 for _, block in data.cells)
    # the file's element order: triangle 0, quad 1, triangle 2
    assert [index.tolist() for index in data.cell_data[ELEMENT_INDEX]] == [[0, 2], [1]]

    assert list(data.face_sets) == ["airfoil", "farfield"]
    assert [kind for kind, _ in data.face_sets["airfoil"]] == ["line"]
    assert np.array_equal(data.face_sets["airfoil"][0][1], [[0, 1], [1, 2]])
    assert np.array_equal(data.face_sets["farfield"][0][1], [[2, 5], [5, 4], [4, 3], [3, 0]])
    assert np.array_equal(data.node_sets["airfoil"], [0, 1, 2])
    assert np.array_equal(data.node_sets["farfield"], [0, 2, 3, 4, 5])
    assert data.groups == {} and data.point_data == {}


def test_read_2d_against_meshio(tmp_path):
    path = write_text(tmp_path, MESH_2D)
    data = read_su2(path)
    reference = meshio_read(path, tmp_path)
    assert np.array_equal(data.points, reference.points)
    blocks = {block.type: block.data for block in reference.cells}
    for kind, connectivity in data.cells:
        assert np.array_equal(connectivity, blocks[kind])
    # meshio merges the markers into one line block tagged 1, 2 in marker order
    lines = blocks["line"]
    tags = next(
        data_
        for block, data_ in zip(reference.cells, reference.cell_data["su2:tag"], strict=True)
        if block.type == "line"
    )
    for tag, name in enumerate(data.face_sets, start=1):
        assert np.array_equal(data.face_sets[name][0][1], lines[tags == tag])


def test_round_trip_2d(tmp_path):
    first = read_su2(write_text(tmp_path, MESH_2D))
    out = tmp_path / "out.su2"
    write_su2(out, first)
    second = read_su2(out)
    assert_same_mesh(first, second)
    # the elements are written back in the file's order, without their indices
    assert element_lines(out) == element_lines(tmp_path / "mesh.su2")
    assert element_lines(out) == [[5, 0, 1, 4], [9, 1, 2, 5, 4], [5, 0, 4, 3]]
    # and the text is what SU2 expects: KEYWORD= value, markers by name
    text = out.read_text()
    for line in ("NDIME= 2", "NELEM= 3", "NPOIN= 6", "NMARK= 2", "MARKER_TAG= airfoil"):
        assert line + "\n" in text
    assert "0.3333333333333333 1.0\n" in text


def test_round_trip_exact_floats(tmp_path):
    generator = np.random.default_rng(7)
    points = generator.standard_normal((200, 3)) * 10.0 ** generator.integers(-300, 300, (200, 3))
    points[:6] = [
        [-0.0, 0.0, 5e-324],
        [1e-308, -2.2250738585072014e-308, 1.7976931348623157e308],
        [0.1, 0.2, 0.30000000000000004],
        [np.pi, np.e, -np.sqrt(2.0)],
        [1e16, 123456789.12345679, -1.0 / 3.0],
        [2.0**-1074, 2.0**52 + 1.0, -(2.0**60)],
    ]
    data = MeshData(points=points, cells=[("tetra", np.array([[0, 1, 2, 3]]))])
    write_su2(tmp_path / "floats.su2", data)
    back = read_su2(tmp_path / "floats.su2")
    assert back.points.tobytes() == points.tobytes()  # every bit, the sign of -0.0 too
    assert np.array_equal(back.cells[0][1], [[0, 1, 2, 3]])
    assert back.face_sets == {} and back.node_sets == {}


def test_crlf_and_comment_positions(tmp_path):
    text = MESH_2D.replace("MARKER_TAG= airfoil", "MARKER_TAG= airfoil   % the wing\n% aside")
    path = tmp_path / "crlf.su2"
    path.write_bytes(text.replace("\n", "\r\n").encode())
    data = read_su2(path)
    reference = read_su2(write_text(tmp_path, MESH_2D))
    assert_same_mesh(data, reference)


def test_permuted_point_indices_follow_the_line_order(tmp_path):
    # SU2 ignores trailing indices (its documentation: implied by the ordering); so does
    # read_su2, and says so
    text = MESH_2D.replace("1.0 0.1 1\n", "1.0 0.1 4\n").replace(
        "0.3333333333333333 1.0 4\n", "0.3333333333333333 1.0 1\n"
    )
    path = write_text(tmp_path, text)
    with pytest.warns(
        UserWarning,
        match=r"line 10: the trailing point index 4 is not the line order \(1\).*2 differ",
    ):
        data = read_su2(path)
    assert data.points.tobytes() == POINTS_2D.tobytes()
    reference = meshio_read(path, tmp_path)
    assert np.array_equal(data.points, reference.points)  # meshio also ignores them


def test_permuted_element_indices_warn(tmp_path):
    text = MESH_2D.replace("5 0 1 4 0\n", "5 0 1 4 7\n")
    with pytest.warns(UserWarning, match=r"line 5: the trailing element index 7"):
        data = read_su2(write_text(tmp_path, text))
    assert np.array_equal(data.cells[0][1], [[0, 1, 4], [0, 4, 3]])


def test_optional_keywords_and_empty_sections(tmp_path):
    text = (
        "NZONE= 1\nIZONE= 1\nNDIME= 2\nAOA_OFFSET= 0.0\nAOS_OFFSET= 0\n"
        "NELEM= 0\nNPOIN= 2\n0 0\n1 1\nNMARK= 1\nMARKER_TAG= empty\nMARKER_ELEMS= 0\n"
        "FFD_NBOX= 0\nFFD_NLEVEL= 0\n"
    )
    data = read_su2(write_text(tmp_path, text))
    assert data.cells == [] and data.points.shape == (2, 2)
    assert data.face_sets == {"empty": []}
    assert data.node_sets["empty"].dtype == np.int64 and data.node_sets["empty"].size == 0
    write_su2(tmp_path / "out.su2", data)
    assert_same_mesh(data, read_su2(tmp_path / "out.su2"))


# --------------------------------------------------------------------------- 3-D


def test_read_3d_mixed(tmp_path):
    path = write_text(tmp_path, mesh_3d_text())
    data = read_su2(path)
    assert data.points.tobytes() == POINTS_3D.tobytes()

    # blocks by kind in order of first appearance, file order within a kind
    assert [kind for kind, _ in data.cells] == ["hexahedron", "tetra", "pyramid", "wedge"]
    expected = {}
    for position, (vtk_type, nodes) in enumerate(CELLS_3D):
        expected.setdefault(KIND[vtk_type], []).append((position, nodes))
    for (kind, connectivity), index in zip(data.cells, data.cell_data[ELEMENT_INDEX], strict=True):
        assert np.array_equal(connectivity, [nodes for _, nodes in expected[kind]])
        assert index.tolist() == [position for position, _ in expected[kind]]

    # markers in the file's order; facets by kind in the order each first appears
    assert list(data.face_sets) == ["bottom", "roof", "sides"]
    for name, facets in MARKERS_3D.items():
        kinds = list(dict.fromkeys(KIND[vtk_type] for vtk_type, _ in facets))
        assert [kind for kind, _ in data.face_sets[name]] == kinds
        for kind, connectivity in data.face_sets[name]:
            assert np.array_equal(
                connectivity, [nodes for vtk_type, nodes in facets if KIND[vtk_type] == kind]
            )
        nodes = sorted({node for _, facet in facets for node in facet})
        assert data.node_sets[name].tolist() == nodes

    # VTK's node order: every cell positively oriented, the volumes add up to 2
    volumes = np.concatenate([signed_volumes(data.points, kind, c) for kind, c in data.cells])
    assert (volumes > 0).all()
    np.testing.assert_allclose(volumes.sum(), 2.0, rtol=1e-14)
    np.testing.assert_allclose(sorted(volumes), sorted([1.0, 1 / 6, 1 / 6, 1 / 6, 0.5]), rtol=1e-14)


def test_read_3d_against_meshio(tmp_path):
    path = write_text(tmp_path, mesh_3d_text())
    data = read_su2(path)
    reference = meshio_read(path, tmp_path)
    assert np.array_equal(data.points, reference.points)
    blocks = {}
    for block, tags in zip(reference.cells, reference.cell_data["su2:tag"], strict=True):
        blocks[block.type] = (block.data, tags)
    for kind, connectivity in data.cells:
        assert np.array_equal(connectivity, blocks[kind][0])
    for tag, facets in enumerate(data.face_sets.values(), start=1):
        for kind, connectivity in facets:
            facet_blocks, tags = blocks[kind]
            assert np.array_equal(connectivity, facet_blocks[tags == tag])


def test_round_trip_3d(tmp_path):
    first = read_su2(write_text(tmp_path, mesh_3d_text()))
    write_su2(tmp_path / "out.su2", first)
    second = read_su2(tmp_path / "out.su2")
    assert_same_mesh(first, second)
    assert element_lines(tmp_path / "out.su2") == [[t, *nodes] for t, nodes in CELLS_3D]
    # a second round trip writes the same text
    write_su2(tmp_path / "again.su2", second)
    assert (tmp_path / "again.su2").read_text() == (tmp_path / "out.su2").read_text()


def test_morphed_points_written_back(tmp_path):
    data = read_su2(write_text(tmp_path, mesh_3d_text()))
    data.points = data.points + 1e-3 * np.sin(data.points[:, [1, 2, 0]])
    write_su2(tmp_path / "morphed.su2", data)
    back = read_su2(tmp_path / "morphed.su2")
    assert back.points.tobytes() == data.points.tobytes()
    assert_same_mesh(back, data)


@pytest.fixture(scope="module")
def gmsh_mesh(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray], np.ndarray]:
    """A gmsh mesh of tetra, pyramids, wedges and hexahedra written by gmsh's own SU2
    writer (domain volume 3), with each marker's node coordinates and the prisms' corner
    coordinates (M, 6, 3) in gmsh's own node order, from gmsh's API."""
    gmsh = pytest.importorskip("gmsh")
    if gmsh.isInitialized():
        pytest.skip("gmsh is in use by another test")
    path = tmp_path_factory.mktemp("gmsh") / "mixed.su2"
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 0)
        gmsh.model.add("su2_mixed")
        occ = gmsh.model.occ
        left, right = occ.addBox(0, 0, 0, 1, 1, 1), occ.addBox(1, 0, 0, 1, 1, 1)
        occ.fragment([(3, left)], [(3, right)])
        occ.synchronize()
        top = gmsh.model.getEntitiesInBoundingBox(-0.1, -0.1, 0.9, 2.1, 1.1, 1.1, 2)
        # layers on the top faces: wedges over triangles, hexahedra over quads
        occ.extrude(top, 0, 0, 0.5, numElements=[2], recombine=True)
        occ.synchronize()
        for _, curve in gmsh.model.getEntities(1):
            gmsh.model.mesh.setTransfiniteCurve(curve, 3)
        # the left box: hexahedra; pyramids where its quads meet the right box's tetrahedra
        left_faces = [tag for _, tag in gmsh.model.getBoundary([(3, left)], oriented=False)]
        for face in left_faces:
            gmsh.model.mesh.setTransfiniteSurface(face)
            gmsh.model.mesh.setRecombine(2, face)
        gmsh.model.mesh.setTransfiniteVolume(left)
        gmsh.model.mesh.setRecombine(3, left)
        volumes = gmsh.model.getEntities(3)
        gmsh.model.addPhysicalGroup(3, [tag for _, tag in volumes], name="fluid")
        boundary = [tag for _, tag in gmsh.model.getBoundary(volumes, oriented=False)]
        groups = {
            "wall": [tag for tag in boundary if tag in left_faces],
            "farfield": [tag for tag in boundary if tag not in left_faces],
        }
        tags = {
            name: gmsh.model.addPhysicalGroup(2, faces, name=name) for name, faces in groups.items()
        }
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
        coordinates = {
            name: gmsh.model.mesh.getNodesForPhysicalGroup(2, tag)[1].reshape(-1, 3)
            for name, tag in tags.items()
        }
        prism = gmsh.model.mesh.getElementType("Prism", 1)
        _, prism_nodes = gmsh.model.mesh.getElementsByType(prism)
        node_tags, node_coordinates, _ = gmsh.model.mesh.getNodes()
        position = np.empty(int(node_tags.max()) + 1, dtype=np.int64)
        position[node_tags] = np.arange(len(node_tags))
        prisms = node_coordinates.reshape(-1, 3)[position[prism_nodes]].reshape(-1, 6, 3)
    finally:
        gmsh.finalize()
    return path, coordinates, prisms


def test_gmsh_mesh(gmsh_mesh, tmp_path):
    path, marker_coordinates, gmsh_prisms = gmsh_mesh
    data = read_su2(path)
    kinds = {kind for kind, _ in data.cells}
    assert kinds == {"tetra", "pyramid", "wedge", "hexahedron"}

    # cells and points as meshio's reader sees them
    reference = meshio_read(path, tmp_path)
    assert np.array_equal(data.points, reference.points)
    blocks = {block.type: block.data for block in reference.cells}
    for kind, connectivity in data.cells:
        assert np.array_equal(connectivity, blocks[kind])
    assert sum(len(c) for _, c in data.cells) == len(element_lines(path))

    # markers: their nodes are the nodes of gmsh's physical groups
    assert list(data.face_sets) == ["wall", "farfield"]
    assert {kind for kind, _ in data.face_sets["farfield"]} == {"triangle", "quad"}
    for name, coordinates in marker_coordinates.items():
        ours = data.points[data.node_sets[name]]
        order = np.lexsort(ours.T[::-1])
        theirs = coordinates[np.lexsort(coordinates.T[::-1])]
        np.testing.assert_allclose(ours[order], theirs, rtol=0, atol=1e-14)

    # VTK's node order for every kind: all cells positive, volumes add up to the domain's
    volumes = np.concatenate([signed_volumes(data.points, kind, c) for kind, c in data.cells])
    assert (volumes > 0).all()
    np.testing.assert_allclose(volumes.sum(), 3.0, rtol=1e-12)

    # SU2's wedge is gmsh's prism mirrored (nodes 1, 2 and 4, 5 swapped): gmsh's SU2
    # writer converts, read_su2 passes SU2's (VTK's) order through
    wedges = next(c for kind, c in data.cells if kind == "wedge")
    ours = data.points[wedges][:, [0, 2, 1, 3, 5, 4]]
    assert ours.shape == gmsh_prisms.shape

    def by_centroid(corners):
        return corners[np.lexsort(corners.mean(axis=1).T[::-1])]

    np.testing.assert_allclose(by_centroid(ours), by_centroid(gmsh_prisms), rtol=0, atol=1e-14)

    # round trip, and the file's interleaved element order kept
    write_su2(tmp_path / "out.su2", data)
    assert_same_mesh(data, read_su2(tmp_path / "out.su2"))
    assert element_lines(tmp_path / "out.su2") == element_lines(path)


# --------------------------------------------------------------------------- reading errors


def edit(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new, 1)


READ_ERRORS = {
    "elements more than counted": (
        lambda t: edit(t, "NELEM = 3", "NELEM = 2"),
        r"line 7: expected a keyword line .* got '5 0 4 3 2'; NELEM= 2 at line 4 announces 2 lines",
    ),
    "elements fewer than counted": (
        lambda t: edit(t, "NELEM = 3", "NELEM = 4"),
        r"line 8: NELEM= 4 at line 4 announces 4 lines, but only 3 follow before 'NPOIN= 6 6'",
    ),
    "points fewer than counted": (
        lambda t: edit(t, "NPOIN= 6 6", "NPOIN= 7"),
        r"line 15: NPOIN= 7 at line 8 announces 7 lines, but only 6 follow",
    ),
    "points more than counted": (
        lambda t: edit(t, "NPOIN= 6 6", "NPOIN= 5"),
        r"line 14: expected a keyword line .*'2.0 1.0 5'; NPOIN= 5 at line 8",
    ),
    "marker elements fewer than counted": (
        lambda t: edit(t, "MARKER_ELEMS =4", "MARKER_ELEMS =5"),
        r"line 21: MARKER_ELEMS= 5 announces 5 lines, but the file ends after 4",
    ),
    "marker elements more than counted": (
        lambda t: edit(t, "MARKER_ELEMS= 2", "MARKER_ELEMS= 1"),
        r"line 19: expected a keyword line .*'3 1 2'; MARKER_ELEMS= 1 at line 17",
    ),
    "markers fewer than counted": (
        lambda t: edit(t, "NMARK= 2", "NMARK= 3"),
        r"line 15: NMARK= 3 but 2 markers \(MARKER_TAG= lines\) follow",
    ),
    "markers more than counted": (
        lambda t: edit(t, "NMARK= 2", "NMARK= 1"),
        r"line 20: NMARK= 1 at line 15, but a marker more follows \('farfield'\)",
    ),
    "unknown VTK type": (
        lambda t: edit(t, "9 1 2 5 4 1", "7 1 2 5 4 1"),
        r"line 6: unknown VTK element type 7 in the 2-D mesh's NELEM= section \(SU2 knows 3 line",
    ),
    "vertex in a marker": (
        lambda t: edit(t, "3 0 1\n", "1 0\n"),
        r"line 18: unknown VTK element type 1 in the marker 'airfoil'",
    ),
    "node out of range": (
        lambda t: edit(t, "5 0 4 3 2", "5 0 4 6 2"),
        r"line 7: node 6 of a triangle is out of range: the mesh has 6 points \(0..5\)",
    ),
    "negative node": (
        lambda t: edit(t, "3 3 0", "3 3 -1"),
        r"line 25: node -1 of a line is out of range",
    ),
    "marker element of the wrong dimension": (
        lambda t: edit(t, "3 1 2\n", "5 1 2 5\n"),
        (
            r"line 19: a triangle \(VTK 5\) is a 2-D element; the marker 'airfoil' \(MARKER_TAG= "
            r"at line 16\) of a 2-D mesh holds 1-D elements: line \(VTK 3\)"
        ),
    ),
    "cell of the wrong dimension": (
        lambda t: edit(t, "5 0 4 3 2", "10 0 4 3 2"),
        r"line 7: a tetra \(VTK 10\) is a 3-D element; the 2-D mesh's NELEM= section holds 2-D",
    ),
    "empty marker name": (
        lambda t: edit(t, "MARKER_TAG= airfoil", "MARKER_TAG=  "),
        r"line 16: MARKER_TAG= '': a marker name must not be empty",
    ),
    "duplicated marker name": (
        lambda t: edit(t, "MARKER_TAG=farfield", "MARKER_TAG= airfoil"),
        r"line 20: marker 'airfoil' given twice \(first at line 16\)",
    ),
    "white space in a marker name": (
        lambda t: edit(t, "MARKER_TAG= airfoil", "MARKER_TAG= main wing"),
        r"line 16: MARKER_TAG= 'main wing': a marker name must not hold white space",
    ),
    "several zones": (
        lambda t: "NZONE= 2\nIZONE= 1\n" + t,
        r"line 1: NZONE= 2: the file holds 2 zones; read_su2 reads single-zone meshes only",
    ),
    "a second zone": (
        lambda t: "IZONE= 1\n" + t + "IZONE= 2\n" + t,
        r"line 27: IZONE= 2: a second zone",
    ),
    "no NDIME": (lambda t: edit(t, "NDIME=2", ""), r"no NDIME= section: not an SU2 mesh"),
    "NDIME not 2 or 3": (
        lambda t: edit(t, "NDIME=2", "NDIME= 4"),
        r"line 2: NDIME= must be 2 or 3",
    ),
    "NDIME twice": (
        lambda t: edit(t, "NMARK= 2", "NDIME= 2\nNMARK= 2"),
        r"line 15: NDIME= given twice \(first at line 2\)",
    ),
    "negative count": (
        lambda t: edit(t, "NELEM = 3", "NELEM = -3"),
        r"line 4: NELEM= expects a non-negative integer, got '-3'",
    ),
    "domain count above the point count": (
        lambda t: edit(t, "NPOIN= 6 6", "NPOIN= 6 7"),
        r"line 8: NPOIN= 6 7: the domain count 7 exceeds the number of points 6",
    ),
    "coordinate not a number": (
        lambda t: edit(t, "2.0 0.0 2", "2.0 zero 2"),
        r"line 11: coordinate 'zero' is not a number",
    ),
    "coordinate not finite": (
        lambda t: edit(t, "2.0 0.0 2", "2.0 nan 2"),
        r"line 11: non-finite coordinate in '2.0 nan 2'",
    ),
    "point with too many values": (
        lambda t: edit(t, "2.0 0.0 2", "2.0 0.0 0.0 2 1"),
        r"line 11: a point of a 2-D mesh has 2 coordinates .* got 5 values",
    ),
    "point index not an integer": (
        lambda t: edit(t, "2.0 0.0 2", "2.0 0.0 0.5"),
        r"line 11: the values after a point's 2 coordinates must be integer indices, got '0.5'",
    ),
    "element with too few nodes": (
        lambda t: edit(t, "9 1 2 5 4 1", "9 1 2 5"),
        r"line 6: a quad line holds its type, 4 node numbers and optionally an element index, got 4",
    ),
    "element with too many values": (
        lambda t: edit(t, "9 1 2 5 4 1", "9 1 2 5 4 1 0"),
        r"line 6: a quad line .* got 7 values",
    ),
    "element value not an integer": (
        lambda t: edit(t, "9 1 2 5 4 1", "9 1 2 5 4.0 1"),
        r"line 6: '4.0' is not an integer",
    ),
    "marker without its count": (
        lambda t: edit(t, "MARKER_ELEMS =4\n", ""),
        r"line 21: MARKER_TAG= farfield must be followed by MARKER_ELEMS=, got '3 2 5'",
    ),
    "marker count without its name": (
        lambda t: edit(t, "MARKER_TAG=farfield\n", ""),
        r"line 20: MARKER_ELEMS= without a MARKER_TAG= line before it",
    ),
    "marker before NMARK": (
        lambda t: edit(t, "NMARK= 2\n", ""),
        r"line 15: MARKER_TAG= before NMARK=",
    ),
    "unknown keyword": (
        lambda t: edit(t, "NMARK= 2", "NPERIODIC= 1\nNMARK= 2"),
        r"line 15: unknown keyword 'NPERIODIC=' .* would be lost on writing",
    ),
    "angle offset": (
        lambda t: "AOA_OFFSET= 2.5\n" + t,
        r"line 1: AOA_OFFSET= 2.5: a non-zero angle offset cannot be kept",
    ),
    "FFD boxes": (
        lambda t: t + "FFD_NBOX= 1\nFFD_NLEVEL= 1\n",
        r"line 26: FFD_NBOX= 1: FFD boxes are not supported",
    ),
}


@pytest.mark.parametrize("case", list(READ_ERRORS))
def test_read_errors(tmp_path, case):
    mutate, message = READ_ERRORS[case]
    path = write_text(tmp_path, mutate(MESH_2D), name="bad mesh.su2")
    # every message names the file
    with pytest.raises(ValueError, match=re.escape(f"path: {str(path)!r}") + ".*" + message):
        read_su2(path)


def test_read_error_3d_line_marker(tmp_path):
    text = edit(mesh_3d_text(), "5 1 2 9", "3 1 2")
    with pytest.raises(ValueError, match=r"a line \(VTK 3\) is a 1-D element; the marker 'bottom'"):
        read_su2(write_text(tmp_path, text))


def test_read_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_su2(tmp_path / "missing.su2")


def test_read_not_utf8(tmp_path):
    path = tmp_path / "binary.su2"
    path.write_bytes(b"NDIME= 2\n\xff\xfe\n")
    with pytest.raises(ValueError, match="binary.su2.*not a text file in UTF-8"):
        read_su2(path)


# --------------------------------------------------------------------------- writing errors


def mesh_2d() -> MeshData:
    return MeshData(
        points=POINTS_2D.copy(),
        cells=[("triangle", np.array([[0, 1, 4], [0, 4, 3]])), ("quad", np.array([[1, 2, 5, 4]]))],
        face_sets={"airfoil": [("line", np.array([[0, 1], [1, 2]]))]},
    )


def test_write_without_element_index(tmp_path):
    data = mesh_2d()
    write_su2(tmp_path / "out.su2", data)
    back = read_su2(tmp_path / "out.su2")
    assert [(kind, c.tolist()) for kind, c in back.cells] == [
        (kind, c.tolist()) for kind, c in data.cells
    ]
    assert [index.tolist() for index in back.cell_data[ELEMENT_INDEX]] == [[0, 1], [2]]
    assert np.array_equal(back.face_sets["airfoil"][0][1], [[0, 1], [1, 2]])


def bad(**changes) -> MeshData:
    data = mesh_2d()
    for name, value in changes.items():
        setattr(data, name, value)
    return data


WRITE_ERRORS = {
    "quadratic cells": (
        bad(cells=[("triangle6", np.zeros((1, 6), dtype=np.int64))]),
        r"data.cells\[0\]: SU2 cannot hold 'triangle6' elements: its kinds are linear only",
    ),
    "cells of the wrong dimension": (
        bad(cells=[("tetra", np.array([[0, 1, 2, 3]]))]),
        r"data.cells\[0\]: 'tetra' is a 3-D kind; the cells of a 2-D SU2 mesh are triangle, quad",
    ),
    "face set of the wrong dimension": (
        bad(face_sets={"wall": [("triangle", np.array([[0, 1, 4]]))]}),
        (
            r"data.face_sets\['wall'\]\[0\]: 'triangle' is a 2-D kind; the boundary facets "
            r"\(markers\) of a 2-D SU2 mesh are line"
        ),
    ),
    "quadratic facets": (
        bad(face_sets={"wall": [("line3", np.array([[0, 1, 2]]))]}),
        r"data.face_sets\['wall'\]\[0\]: SU2 cannot hold 'line3' elements",
    ),
    "non-finite points": (
        bad(points=np.where(np.arange(12).reshape(6, 2) == 7, np.inf, POINTS_2D)),
        r"data.points: row 3 is not finite",
    ),
    "points of 4-D": (bad(points=np.zeros((6, 4))), r"data.points: SU2 meshes are 2-D or 3-D"),
    "node out of range": (
        bad(cells=[("triangle", np.array([[0, 1, 6]]))]),
        r"data.cells\[0\]: node numbers must be in 0..5, got 0..6",
    ),
    "connectivity of the wrong shape": (
        bad(cells=[("quad", np.array([[0, 1, 2]]))]),
        r"data.cells\[0\]: 'quad' connectivity must be integers of shape \(M, 4\), got \(1, 3\)",
    ),
    "empty marker name": (
        bad(face_sets={"": [("line", np.array([[0, 1]]))]}),
        r"data.face_sets\[''\]: a marker name must not be empty",
    ),
    "white space in a marker name": (
        bad(face_sets={"main wing": [("line", np.array([[0, 1]]))]}),
        r"data.face_sets\['main wing'\]: a marker name must not hold white space",
    ),
    "element index not a numbering": (
        bad(cell_data={ELEMENT_INDEX: [np.array([0, 0]), np.array([1])]}),
        r"data.cell_data\['su2:element_index'\]: must number the 3 cells 0..2, each once",
    ),
    "element index of the wrong length": (
        bad(cell_data={ELEMENT_INDEX: [np.array([0, 1, 2])]}),
        r"must be a list of one index array per cell block \(2\), got 1",
    ),
}


@pytest.mark.parametrize("case", list(WRITE_ERRORS))
def test_write_errors(tmp_path, case):
    data, message = WRITE_ERRORS[case]
    target = tmp_path / "target.su2"
    target.write_text("previous content")
    with pytest.raises(ValueError, match=message + ".*" + re.escape(repr(str(target)))):
        write_su2(target, data)
    # nothing written: the previous file is intact, no temporary left behind
    assert target.read_text() == "previous content"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["target.su2"]
