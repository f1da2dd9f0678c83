"""Own surfaces to tetrahedral meshes: checks, closest points, feature sets, fTetWild and snapping."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from torchmorph import meshing
from torchmorph.mesh import read_mesh, signed_volumes
from torchmorph.meshing import (
    Surface,
    box_surface,
    closest_points,
    feature_edges,
    load_surface,
    mesh_surfaces,
    surface_problems,
)
from torchmorph.meshing import surfaces as _surface

trimesh = pytest.importorskip("trimesh")


def icosphere(subdivisions: int = 1, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)


def write_obj(path, vertices, faces, groups=None):
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in vertices]
    label = None
    for index, face in enumerate(faces):
        if groups is not None and groups[index] != label:
            label = groups[index]
            lines.append(f"g {label}")
        lines.append("f " + " ".join(str(v + 1) for v in face))
    path.write_text("\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------- surface checks


def test_closed_sphere_has_no_problems():
    assert surface_problems(*icosphere()) == []


def test_problems_name_holes_inconsistent_orientation_and_zero_area():
    vertices, faces = icosphere()
    (problem,) = surface_problems(vertices, faces[1:])
    removed = {tuple(sorted(int(v) for v in faces[0][pair])) for pair in ([0, 1], [1, 2], [2, 0])}
    assert problem.startswith("3 edge(s) belong to one face only (holes, e.g. the edge between")
    assert any(problem.endswith(f"vertices {edge})") for edge in removed)
    flipped = faces.copy()
    flipped[0] = flipped[0][::-1]
    assert surface_problems(vertices, flipped) == [
        "3 edge(s) are traversed in the same direction by two faces (inconsistent orientation)"
    ]
    doubled = np.concatenate([faces, faces[:1, ::-1]])
    assert "3 edge(s) are shared by more than two faces (non-manifold)" in surface_problems(
        vertices, doubled
    )
    flat = np.concatenate([vertices, vertices[:1]])  # a zero-area face on a duplicated vertex
    assert "1 face(s) have zero area (e.g. face 0)" in surface_problems(
        flat, np.array([[0, len(vertices), 1]])
    )


def test_stl_soup_is_merged_and_an_inward_surface_flipped(tmp_path):
    vertices, faces = icosphere()
    inward = trimesh.Trimesh(vertices, faces[:, ::-1], process=False)
    inward.export(tmp_path / "ball.stl")
    surface = load_surface(tmp_path / "ball.stl")
    assert surface.name == "ball"
    assert len(surface.vertices) == len(vertices) and len(surface.faces) == len(faces)
    reference = trimesh.Trimesh(vertices, faces, process=False).volume
    assert surface.volume == pytest.approx(reference, rel=1e-6)  # STL stores float32


def test_open_surface_is_refused_with_what_is_wrong_and_repaired_on_request(tmp_path):
    vertices, faces = icosphere()
    path = write_obj(tmp_path / "open.obj", vertices, faces[1:])
    with pytest.raises(
        ValueError,
        match=r"path: surface '.*open.obj' is not a closed, "
        r"consistently oriented surface: 3 edge\(s\) belong to one face only .*"
        r"pass repair=True \(torchmorph mesh --repair\)",
    ):
        load_surface(path)
    repaired = load_surface(path, repair=True)
    assert surface_problems(repaired.vertices, repaired.faces) == []
    assert len(repaired.faces) == len(faces)


def test_bad_paths_and_extensions():
    with pytest.raises(ValueError, match=r"path: unsupported surface file extension '.xyz'"):
        load_surface("body.xyz")
    with pytest.raises(FileNotFoundError, match=r"path: surface file 'missing.stl' does not exist"):
        load_surface("missing.stl")


def test_obj_groups_and_ply_labels_become_face_groups(tmp_path):
    vertices, faces = icosphere()
    upper = vertices[faces].mean(1)[:, 2] > 0
    names = np.where(upper, "top", "bottom")
    surface = load_surface(write_obj(tmp_path / "ball.obj", vertices, faces, names))
    assert sorted(surface.groups) == ["bottom", "top"]
    np.testing.assert_array_equal(surface.groups["top"], np.flatnonzero(upper))

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.face_attributes["label"] = upper.astype(np.int64)
    mesh.export(tmp_path / "ball.ply", encoding="ascii", include_attributes=True)
    surface = load_surface(tmp_path / "ball.ply")
    assert sorted(surface.groups) == ["label0", "label1"]
    np.testing.assert_array_equal(surface.groups["label1"], np.flatnonzero(upper))


def test_box_surface_is_closed_outward_with_one_group_per_wall():
    box = box_surface([[0, 0, 0], [2, 3, 4]])
    assert surface_problems(box.vertices, box.faces) == []
    assert box.volume == pytest.approx(24.0)
    for axis, side, wall in [(a, s, f"wall_{'xyz'[a]}{s}") for a in range(3) for s in (0, 1)]:
        corners = box.vertices[box.faces[box.groups[wall]]].reshape(-1, 3)
        np.testing.assert_array_equal(corners[:, axis], [0, 2, 3, 4][0 if side == 0 else axis + 1])
    with pytest.raises(ValueError, match=r"bounds must be \[\[x0, y0, z0\], \[x1, y1, z1\]\]"):
        box_surface([[0, 0, 0], [1, -1, 1]])


def test_closest_points_match_brute_force():
    vertices, faces = icosphere(1)
    rng = np.random.default_rng(0)
    queries = rng.normal(size=(300, 3)) * rng.uniform(0.2, 2.0, size=(300, 1))
    points, face, distance = closest_points(queries, vertices, faces)
    brute = np.stack(
        [
            _surface._closest_on_triangles(
                np.repeat(q[None], len(faces), 0), *(vertices[faces[:, k]] for k in range(3))
            )
            for q in queries
        ]
    )  # (Q, F, 3)
    all_distances = np.linalg.norm(brute - queries[:, None], axis=2)
    np.testing.assert_allclose(distance, all_distances.min(1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        points, brute[np.arange(len(queries)), all_distances.argmin(1)], atol=1e-12
    )
    np.testing.assert_allclose(all_distances[np.arange(len(queries)), face], distance, atol=1e-12)
    # the closest point of a triangle: a vertex, an edge point and an interior point
    a, b, c = np.eye(3)[None, 0], np.eye(3)[None, 1], np.zeros((1, 3))
    np.testing.assert_allclose(_surface._closest_on_triangles(np.array([[2.0, -1, 0]]), a, b, c), a)
    np.testing.assert_allclose(
        _surface._closest_on_triangles(np.array([[1.0, 1, 0]]), a, b, c), [[0.5, 0.5, 0]]
    )
    np.testing.assert_allclose(
        _surface._closest_on_triangles(np.array([[0.2, 0.2, 5]]), a, b, c), [[0.2, 0.2, 0]]
    )


def test_feature_edges_of_a_box_are_its_twelve_edges_and_six_faces():
    box = box_surface([[0, 0, 0], [1, 1, 1]])
    edges, patches = feature_edges(box, 30.0)
    assert len(edges) == 12 and len(patches) == 6
    lengths = np.linalg.norm(box.vertices[edges[:, 0]] - box.vertices[edges[:, 1]], axis=1)
    np.testing.assert_allclose(lengths, 1.0)  # no face diagonal is sharp
    vertices, faces = icosphere(2)
    edges, patches = feature_edges(Surface(vertices, faces), 30.0)
    assert len(edges) == 0 and len(patches) == 1
    with pytest.raises(ValueError, match=r"feature_angle must be in \(0, 180\) degrees"):
        feature_edges(box, 180.0)


# --------------------------------------------------------------------------- fTetWild


@pytest.fixture(scope="module")
def ball_in_box():
    pytest.importorskip("pytetwild")
    vertices, faces = icosphere(1)
    return mesh_surfaces(
        {"ball": Surface(vertices, faces)}, box=1.0, edge_length=1.0, body_edge_length=0.35
    )


def test_sphere_alone_is_meshed_with_its_boundary_on_the_surface():
    pytest.importorskip("pytetwild")
    vertices, faces = icosphere(1)
    mesh = mesh_surfaces(Surface(vertices, faces, "ball"), edge_length=0.4)
    assert sorted(mesh.node_sets) == ["ball"]
    boundary = mesh.boundary_nodes
    torch.testing.assert_close(mesh.node_sets["ball"], boundary)
    distance = closest_points(mesh.points[boundary].numpy(), vertices, faces)[2]
    assert distance.max() < 1e-12
    assert float(mesh.volumes.sum()) == pytest.approx(Surface(vertices, faces).volume, rel=2e-2)
    assert float(mesh.volumes.min()) > 0


def test_body_in_box_names_walls_and_body(ball_in_box):
    mesh = ball_in_box
    assert set(mesh.node_sets) == {"ball", "far_field", *meshing.WALL_NAMES}
    points = mesh.points.numpy()
    low, high = np.full(3, -3.0), np.full(3, 3.0)  # extent 2, padding 1 x 2 on each side
    for axis in range(3):
        for side, value in ((0, low[axis]), (1, high[axis])):
            nodes = mesh.node_sets[f"wall_{'xyz'[axis]}{side}"].numpy()
            np.testing.assert_allclose(points[nodes, axis], value, atol=1e-12)
    ball = mesh.node_sets["ball"].numpy()
    vertices, faces = icosphere(1)
    assert closest_points(points[ball], vertices, faces)[2].max() < 1e-12
    covered = np.union1d(ball, mesh.node_sets["far_field"].numpy())
    np.testing.assert_array_equal(covered, mesh.boundary_nodes.numpy())
    # graded: edges on the ball much shorter than far away
    assert np.ptp(points[ball], axis=0).max() == pytest.approx(2.0, rel=0.1)


def test_feature_angle_puts_nodes_on_the_sharp_edges_and_names_the_patches():
    pytest.importorskip("pytetwild")
    box = box_surface([[0, 0, 0], [1.0, 0.6, 0.4]], name="block")
    mesh = mesh_surfaces([box], edge_length=0.2, feature_angle=30.0)
    names = set(mesh.node_sets)
    assert {"block", "block_edges"} | {f"block_patch{k}" for k in range(6)} <= names
    points = mesh.points.numpy()
    edge_points = points[mesh.node_sets["block_edges"].numpy()]
    at_bound = np.isclose(edge_points, 0.0, atol=1e-12) | np.isclose(
        edge_points, [1.0, 0.6, 0.4], atol=1e-12
    )
    assert (at_bound.sum(1) >= 2).all()  # on an edge: two coordinates at the box's bounds
    patches = [mesh.node_sets[f"block_patch{k}"].numpy() for k in range(6)]
    np.testing.assert_array_equal(np.unique(np.concatenate(patches)), mesh.boundary_nodes.numpy())
    for patch in patches:  # each patch is one face of the box: one coordinate constant
        assert (np.ptp(points[patch], axis=0) < 1e-12).sum() == 1


@pytest.mark.slow
def test_two_files_the_outer_one_is_the_wall(tmp_path):
    pytest.importorskip("pytetwild")
    vertices, faces = icosphere(1, radius=0.3)
    inner = write_obj(tmp_path / "body.obj", vertices, faces)
    box = box_surface([[-1, -1, -1], [1, 1, 1]])
    outer = write_obj(
        tmp_path / "tunnel.obj", box.vertices, box.faces, np.repeat(meshing.WALL_NAMES, 2)
    )
    mesh = mesh_surfaces({"walls": outer, "body": inner}, edge_length=0.4)
    assert {"walls", "body", *meshing.WALL_NAMES} <= set(mesh.node_sets)
    # a hole: no node inside the body
    radius = np.linalg.norm(mesh.points.numpy(), axis=1)
    assert radius.min() >= 0.3 * np.cos(np.radians(37.4)) - 1e-9  # icosphere(1) inradius bound


def test_argument_errors_name_the_argument():
    vertices, faces = icosphere(1)
    ball = Surface(vertices, faces, "ball")
    with pytest.raises(ValueError, match=r"box and bounds: give one of them"):
        mesh_surfaces(ball, box=1.0, bounds=[[-2] * 3, [2] * 3])
    with pytest.raises(ValueError, match=r"body_edge_length and grading need a far field"):
        mesh_surfaces(ball, body_edge_length=0.1)
    with pytest.raises(ValueError, match=r"bounds: the box .* does not contain surface 'ball'"):
        mesh_surfaces(ball, bounds=[[-0.5] * 3, [2] * 3])
    with pytest.raises(ValueError, match=r"box must be one padding >= 0 or six"):
        mesh_surfaces(ball, box=[1, 2])
    with pytest.raises(ValueError, match=r"surfaces: two surfaces are named 'ball'"):
        mesh_surfaces([ball, ball])
    with pytest.raises(ValueError, match=r"surfaces: the name 'far_field' is the box's"):
        mesh_surfaces({"far_field": ball}, box=1.0)


def test_written_mesh_reads_back_with_its_node_sets(ball_in_box, tmp_path):
    from torchmorph.mesh.io import write_mesh

    write_mesh(tmp_path / "ball.vtu", ball_in_box)
    again = read_mesh(tmp_path / "ball.vtu")
    assert set(again.node_sets) == set(ball_in_box.node_sets)
    for name, nodes in ball_in_box.node_sets.items():
        torch.testing.assert_close(again.node_sets[name], nodes)


@pytest.mark.slow
def test_tetrahedralize_reports_start_and_elapsed_time_on_request(capsys):
    pytest.importorskip("pytetwild")
    vertices, faces = icosphere(1)
    points, tets = meshing.tetrahedralize(vertices, faces, edge_length=0.5, progress=True)
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("fTetWild: meshing 80 surface triangles (edge length 0.5, epsilon")
    assert re.fullmatch(
        rf"fTetWild: {len(points)} nodes, {len(tets)} tetrahedra in \d+\.\d s", err[1]
    )
    assert (signed_volumes(torch.from_numpy(points), torch.from_numpy(tets)) > 0).all()
    meshing.tetrahedralize(vertices, faces, edge_length=0.5)
    assert capsys.readouterr().err == ""
    with pytest.raises(ValueError, match=r"epsilon must be a finite number > 0, got -1"):
        meshing.tetrahedralize(vertices, faces, edge_length=0.5, epsilon=-1)
