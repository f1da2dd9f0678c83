"""CAD files (STEP, BREP, IGES) meshed with gmsh: validity, exact boundaries, node sets, determinism, errors."""

from __future__ import annotations

import sys

import numpy as np
import pytest

gmsh = pytest.importorskip("gmsh")

from conftest import write_cad  # noqa: E402

from torchmorph import meshing  # noqa: E402
from torchmorph.mesh.quality import count_inverted  # noqa: E402

RADIUS = 0.7
CENTRE = (0.1, -0.2, 0.3)


@pytest.fixture(scope="module")
def cad(tmp_path_factory):
    """ball.step (an OCC sphere) and part.step (a box with a cylindrical hole: 7 faces)."""
    directory = tmp_path_factory.mktemp("cad")
    ball, part = directory / "ball.step", directory / "part.step"
    write_cad(ball, lambda occ: occ.addSphere(*CENTRE, RADIUS))
    write_cad(part)
    return ball, part


def _volumes(mesh) -> np.ndarray:
    p, t = mesh.points.numpy(), mesh.tets.numpy()
    a, b, c, d = (p[t[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


def test_sphere_alone_is_valid_with_nodes_on_the_sphere(cad):
    ball, _ = cad
    mesh = meshing.mesh_surfaces(ball, edge_length=0.25)
    assert count_inverted(mesh) == 0 and _volumes(mesh).min() > 0
    assert list(mesh.node_sets) == ["ball"]  # one CAD face: no face or edge sets
    boundary = mesh.points[mesh.node_sets["ball"]].numpy()
    radius = np.linalg.norm(boundary - CENTRE, axis=1)
    np.testing.assert_allclose(radius, RADIUS, rtol=1e-9)
    assert np.array_equal(mesh.node_sets["ball"].numpy(), mesh.boundary_nodes.numpy())
    # the volume of the ball, to the discretisation error of a size-0.25 mesh
    assert abs(_volumes(mesh).sum() / (4 / 3 * np.pi * RADIUS**3) - 1) < 0.05


@pytest.mark.parametrize("exact", [True, False])
def test_sphere_in_a_box_walls_and_far_field(cad, exact):
    ball, _ = cad
    low, high = np.array(CENTRE) - RADIUS, np.array(CENTRE) + RADIUS
    extent = 2 * RADIUS
    corners = [low - extent, high + extent * np.array([2, 1, 1])]
    if exact:
        mesh = meshing.mesh_cad({"body": ball}, bounds=corners, mesh_size=0.5)
    else:  # the box around OpenCASCADE's bounding box: padded by the CAD tolerance
        mesh = meshing.mesh_cad({"body": ball}, box=(1, 2, 1, 1, 1, 1), mesh_size=0.5)
    assert count_inverted(mesh) == 0
    sets = {k: set(v.tolist()) for k, v in mesh.node_sets.items()}
    assert list(sets) == ["body", "far_field", *meshing.WALL_NAMES]
    points = mesh.points.numpy()
    for k, wall in enumerate(meshing.WALL_NAMES):
        axis, side = divmod(k, 2)
        on_wall = points[list(sets[wall]), axis]
        assert np.ptp(on_wall) == 0  # a plane
        np.testing.assert_allclose(on_wall, corners[side][axis], atol=1e-14 if exact else 1e-6)
    assert sets["far_field"] == set().union(*(sets[w] for w in meshing.WALL_NAMES))
    assert not sets["body"] & sets["far_field"]
    assert sets["body"] | sets["far_field"] == set(mesh.boundary_nodes.tolist())
    radius = np.linalg.norm(points[list(sets["body"])] - CENTRE, axis=1)
    np.testing.assert_allclose(radius, RADIUS, rtol=1e-9)


def test_faces_and_edges_of_a_holed_box_in_a_box(cad):
    _, part = cad
    mesh = meshing.mesh_surfaces(part, box=1, edge_length=0.8, body_edge_length=0.3)
    assert count_inverted(mesh) == 0
    sets = {k: set(v.tolist()) for k, v in mesh.node_sets.items()}
    faces = [f"part_face{k}" for k in range(7)]
    assert list(sets) == ["part", "far_field", *meshing.WALL_NAMES, *faces, "part_edges"]
    assert set().union(*(sets[f] for f in faces)) == sets["part"]
    # faces meet only on the CAD curves: shared nodes are edge nodes
    for i, a in enumerate(faces):
        for b in faces[i + 1 :]:
            assert sets[a] & sets[b] <= sets["part_edges"]
    points = mesh.points.numpy()
    # the hole's wall: nodes at radius 0.4 from the z axis (the cylinder's face)
    hole = next(f for f in faces if len(sets[f]) and _on_cylinder(points[list(sets[f])]))
    # its edge nodes are the two circles z = +-0.5; the seam is not an edge
    rim = points[list(sets[hole] & sets["part_edges"])]
    np.testing.assert_allclose(np.abs(rim[:, 2]), 0.5, atol=1e-12)
    # the box's 12 edges and the 2 circles: every edge node is on one of them
    edge = points[list(sets["part_edges"])]
    on_box_edge = (
        np.isclose(np.abs(edge[:, :2]), 1).sum(1) + np.isclose(np.abs(edge[:, 2]), 0.5)
    ) >= 2
    assert (on_box_edge | _on_cylinder(edge, each=True)).all()


def _on_cylinder(points, each=False):
    close = np.isclose(np.linalg.norm(points[:, :2], axis=1), 0.4, rtol=1e-9)
    return close if each else close.all()


def test_a_body_inside_another_is_a_hole_in_it(cad, tmp_path):
    _, part = cad
    shell = write_cad(tmp_path / "shell.step", lambda occ: occ.addSphere(0, 0, 0, 2.0))
    mesh = meshing.mesh_surfaces({"shell": shell, "part": part}, edge_length=0.5)
    assert count_inverted(mesh) == 0
    sets = {k: set(v.tolist()) for k, v in mesh.node_sets.items()}
    faces = [f"part_face{k}" for k in range(7)]
    assert list(sets) == ["shell", "part", *faces, "part_edges"]
    assert not sets["shell"] & sets["part"]
    assert sets["shell"] | sets["part"] == set(mesh.boundary_nodes.tolist())
    radius = np.linalg.norm(mesh.points[mesh.node_sets["shell"]].numpy(), axis=1)
    np.testing.assert_allclose(radius, 2.0, rtol=1e-9)
    # the ball of radius 2 less the holed box: the polygonal sphere loses a little volume
    exact = 4 / 3 * np.pi * 2.0**3 - (4 - 0.16 * np.pi)
    assert -0.03 < _volumes(mesh).sum() / exact - 1 < 0


def test_two_builds_are_identical(cad):
    _, part = cad
    first, second = (meshing.mesh_cad(part, box=1, mesh_size=0.8) for _ in range(2))
    assert np.array_equal(first.points.numpy(), second.points.numpy())
    assert np.array_equal(first.tets.numpy(), second.tets.numpy())
    assert first.node_sets.keys() == second.node_sets.keys()
    for key in first.node_sets:
        assert np.array_equal(first.node_sets[key].numpy(), second.node_sets[key].numpy())


def test_a_brep_file_meshes_like_the_step_file(cad, tmp_path):
    _, part = cad
    brep = write_cad(tmp_path / "part.brep")
    from_step, from_brep = (meshing.mesh_surfaces(f, box=1, edge_length=0.8) for f in (part, brep))
    assert from_brep.node_sets.keys() == from_step.node_sets.keys()
    # the box [-3, 3]^2 x [-2.5, 2.5] less the holed box (4 - 0.4^2 pi), the hole polygonal
    exact = 180 - (4 - 0.16 * np.pi)
    for mesh in (from_step, from_brep):
        assert count_inverted(mesh) == 0
        assert abs(_volumes(mesh).sum() / exact - 1) < 1e-3


def test_bad_input_is_refused(cad, tmp_path):
    ball, _ = cad
    with pytest.raises(ValueError, match=r"files: unsupported CAD file extension '.stpx'"):
        meshing.mesh_cad(tmp_path / "body.stpx")
    with pytest.raises(FileNotFoundError, match=r"files: CAD file .*missing.step' does not exist"):
        meshing.mesh_surfaces(tmp_path / "missing.step")
    with pytest.raises(ValueError, match=r"path: unsupported surface file extension '.xyz'"):
        meshing.mesh_surfaces(tmp_path / "body.xyz")
    with pytest.raises(ValueError, match=r"CAD files .* and triangle surfaces .* cannot be"):
        meshing.mesh_surfaces([ball, tmp_path / "body.stl"])
    with pytest.raises(ValueError, match=r"feature_angle and repair are for triangle surfaces"):
        meshing.mesh_surfaces(ball, feature_angle=30)
    with pytest.raises(ValueError, match=r"bounds: the box .* does not contain body 'ball'"):
        meshing.mesh_cad(ball, bounds=[[0, 0, 0], [1, 1, 1]])
    with pytest.raises(ValueError, match=r"body_mesh_size and grading need a far field"):
        meshing.mesh_cad(ball, body_mesh_size=0.1)
    with pytest.raises(ValueError, match=r"mesh_size must be a finite number > 0, got -1"):
        meshing.mesh_cad(ball, mesh_size=-1)
    faces_only = tmp_path / "faces.iges"  # gmsh writes IGES faces, not solids
    write_cad(faces_only, lambda occ: occ.addBox(0, 0, 0, 1, 1, 1))
    with pytest.raises(
        ValueError, match=r"faces.iges' holds no solid, only entities of dimension \[2\]"
    ):
        meshing.mesh_cad(faces_only)
    broken = tmp_path / "broken.step"
    broken.write_text("not a STEP file\n")
    with pytest.raises(ValueError, match=r"files: .*broken.step"):
        meshing.mesh_cad(broken)


def test_without_gmsh_the_error_names_the_mesh_extra(cad, monkeypatch):
    ball, _ = cad
    monkeypatch.setitem(sys.modules, "gmsh", None)  # import gmsh -> ImportError
    with pytest.raises(
        ImportError, match=r"CAD files needs gmsh: pip install 'torchmorph\[mesh\]'"
    ):
        meshing.mesh_surfaces(ball)
