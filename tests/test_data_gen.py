"""data_gen: the paper's three test meshes, both meshers, the cache and the CLI."""

from __future__ import annotations

import math
import re
import time

import numpy as np
import pytest

import data_gen
from data_gen import cases
from data_gen._arrays import boundary_faces, signed_volumes, untangle
from data_gen.geometry import (
    CHORD,
    HULL_BEAM,
    HULL_BOX_BOUNDS,
    HULL_DRAFT,
    HULL_LENGTH,
    SPAN,
    TUNNEL_BOUNDS,
    naca_half_thickness,
    naca_profile,
    project_to_profile,
    wigley_half_breadth,
)

TOL = 1e-9  # boundary nodes are projected onto the exact surfaces
WING_SETS = {
    "upper",
    "lower",
    "tip",
    "tip_profile",
    "root_profile",
    "leading_edge",
    "trailing_edge",
    "wing",
}
WALLS = {
    "wall_x0": (0, 0),
    "wall_x1": (0, 1),
    "wall_y0": (1, 0),
    "wall_y1": (1, 1),
    "wall_z0": (2, 0),
    "wall_z1": (2, 1),
}
EXPECTED_SETS = {
    "wing": WING_SETS | {"root"},
    "fluid_wing": WING_SETS | set(WALLS),
    "hull": {"hull", "starboard", "port", "stem", "stern", "keel", "keel_top", "hull_edges"}
    | set(WALLS),
}
# node counts of the "small" presets (generous: pytetwild varies from run to run)
SMALL_NODES = {"wing": (700, 4000), "fluid_wing": (1200, 6000), "hull": (700, 4000)}


def _naca_area() -> float:
    x = np.linspace(0.0, CHORD, 400001)
    y = naca_half_thickness(x)
    return float(np.sum((y[1:] + y[:-1]) * np.diff(x)))  # 2 ∫ y_t dx, trapezoidal


WING_VOLUME = _naca_area() * SPAN
HULL_VOLUME = HULL_BEAM * (2.0 * HULL_LENGTH / 3.0) * (4.0 * HULL_DRAFT / 3.0)


def _box_volume(bounds) -> float:
    return float(np.prod(np.subtract(bounds[1], bounds[0])))


EXPECTED_VOLUME = {
    "wing": WING_VOLUME,
    "fluid_wing": _box_volume(TUNNEL_BOUNDS) - WING_VOLUME,
    "hull": _box_volume(HULL_BOX_BOUNDS) - HULL_VOLUME,
}


# --------------------------------------------------------------------------- checks


def check_mesh(
    mesh: data_gen.MeshArrays, case: str, *, exact_edges: bool = True, envelope: float = 0.0
) -> None:
    """Every property a generated mesh must have.

    ``exact_edges=False`` and ``envelope`` > 0 for fTetWild meshes: their surface
    approximates the input within ``envelope``, so the body's sharp ends thinner
    than that (the trailing edge, the hull's stem, stern and keels) may be cut
    off, leaving a few fluid nodes inside the exact body there.
    """
    points, tets, sets = mesh.points, mesh.tets, mesh.node_sets
    volumes = signed_volumes(points, tets)
    assert volumes.min() > 0.0
    # no dangling nodes, volume of the domain as the analytic one (chords cut the curved surfaces)
    assert np.array_equal(np.unique(tets), np.arange(len(points)))
    assert volumes.sum() == pytest.approx(EXPECTED_VOLUME[case], rel=4e-2)
    # every boundary node tagged, every tagged node on the boundary
    boundary = np.unique(boundary_faces(tets))
    assert np.array_equal(boundary, np.unique(np.concatenate(list(sets.values()))))
    assert set(sets) == EXPECTED_SETS[case]
    for name, nodes in sets.items():
        assert len(nodes) > 0, name
        assert nodes.dtype == np.int64 and np.all(np.diff(nodes) > 0), name
    for name, (axis, side) in WALLS.items():
        if name in sets:
            bounds = TUNNEL_BOUNDS if case == "fluid_wing" else HULL_BOX_BOUNDS
            assert np.abs(points[sets[name], axis] - bounds[side][axis]).max() <= TOL, name
    if case == "hull":
        check_hull(points, sets, exact_edges=exact_edges, envelope=envelope)
    else:
        check_wing(points, sets, case, exact_edges=exact_edges, envelope=envelope)


def check_wing(
    points: np.ndarray, sets: dict, case: str, *, exact_edges: bool, envelope: float
) -> None:
    x, y, z = points.T
    for name, sign in (("upper", 1.0), ("lower", -1.0)):
        nodes = sets[name]
        assert np.abs(y[nodes] - sign * naca_half_thickness(x[nodes])).max() <= TOL, name
        assert x[nodes].min() >= -TOL and x[nodes].max() <= CHORD + TOL
        assert z[nodes].min() >= -TOL and z[nodes].max() <= SPAN + TOL
    root = sets["root"] if case == "wing" else sets["wall_z0"]
    assert np.abs(z[root]).max() <= TOL
    assert np.abs(z[sets["tip"]] - SPAN).max() <= TOL
    for name, height in (("root_profile", 0.0), ("tip_profile", SPAN)):
        nodes = sets[name]
        assert np.abs(z[nodes] - height).max() <= TOL, name
        assert np.abs(np.abs(y[nodes]) - naca_half_thickness(x[nodes])).max() <= TOL, name
        assert len(nodes) >= 8, name
    for name, chord_position in (("leading_edge", 0.0), ("trailing_edge", CHORD)):
        nodes = sets[name]
        assert np.abs(x[nodes] - chord_position).max() <= TOL, name
        assert np.abs(y[nodes]).max() <= TOL, name
        if exact_edges:  # the lines run from root to tip
            assert z[nodes].min() <= TOL and z[nodes].max() >= SPAN - TOL, name
    wing = sets["wing"]
    assert set(sets["upper"]) | set(sets["lower"]) | set(sets["tip"]) <= set(wing)
    if case == "fluid_wing":
        # the wing is a hole: no node strictly inside it (but where it is thinner than the envelope)
        inside = (x > 1e-6) & (x < CHORD - 1e-6) & (z > 1e-6) & (z < SPAN - 1e-6)
        thickness = naca_half_thickness(x[inside])
        assert np.all((np.abs(y[inside]) >= thickness - TOL) | (thickness <= envelope))
        # the root profile is where the wing meets the wall z = 0
        assert set(sets["root_profile"]) <= set(sets["wall_z0"])


def check_hull(points: np.ndarray, sets: dict, *, exact_edges: bool, envelope: float) -> None:
    x, y, z = points.T
    half = HULL_LENGTH / 2.0
    hull = sets["hull"]
    assert np.abs(np.abs(z[hull]) - wigley_half_breadth(x[hull], y[hull])).max() <= TOL
    assert np.abs(x[hull]).max() <= half + TOL and np.abs(y[hull]).max() <= HULL_DRAFT + TOL
    assert np.all(z[sets["starboard"]] >= -TOL) and np.all(z[sets["port"]] <= TOL)
    for name, axis, value in (
        ("stem", 0, half),
        ("stern", 0, -half),
        ("keel", 1, -HULL_DRAFT),
        ("keel_top", 1, HULL_DRAFT),
    ):
        nodes = sets[name]
        assert np.abs(points[nodes, axis] - value).max() <= TOL, name
        assert np.abs(z[nodes]).max() <= TOL, name
        assert set(nodes) <= set(sets["hull_edges"]) <= set(hull)
    if exact_edges:
        assert len(sets["keel"]) >= 8 and len(sets["stem"]) >= 2
    # the hull is a hole: no node strictly inside it (but where it is thinner than the envelope)
    inside = (np.abs(x) < half - 1e-6) & (np.abs(y) < HULL_DRAFT - 1e-6)
    breadth = wigley_half_breadth(x[inside], y[inside])
    assert np.all((np.abs(z[inside]) >= breadth - TOL) | (breadth <= envelope))


# --------------------------------------------------------------------------- gmsh (default)


@pytest.fixture(scope="module")
def gmsh_small() -> dict[str, data_gen.MeshArrays]:
    pytest.importorskip("gmsh")
    return {case: data_gen.build_arrays(case, "small", cache=False) for case in data_gen.CASES}


@pytest.mark.parametrize("case", data_gen.CASES)
def test_gmsh_small_mesh_is_valid_and_tagged(gmsh_small, case):
    mesh = gmsh_small[case]
    check_mesh(mesh, case)
    low, high = SMALL_NODES[case]
    assert low <= len(mesh.points) <= high
    assert mesh.info["figures"]["interior"] > 100  # interior nodes to interpolate


@pytest.mark.parametrize("case", data_gen.CASES)
def test_gmsh_is_deterministic(gmsh_small, case):
    again = data_gen.build_arrays(case, "small", cache=False)
    first = gmsh_small[case]
    assert np.array_equal(again.points, first.points)
    assert np.array_equal(again.tets, first.tets)
    assert again.node_sets.keys() == first.node_sets.keys()
    for name in first.node_sets:
        assert np.array_equal(again.node_sets[name], first.node_sets[name])


def test_gmsh_leaves_a_callers_session_alone(gmsh_small):
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.model.add("mine")
        data_gen.build_arrays("wing", "small", cache=False)
        assert gmsh.isInitialized()
        assert "mine" in gmsh.model.list()
    finally:
        gmsh.finalize()


@pytest.mark.slow
@pytest.mark.parametrize("case", ["wing", "hull"])
def test_gmsh_paper_sizes_match_the_paper(case, tmp_path):
    pytest.importorskip("gmsh")
    mesh = data_gen.build_arrays(case, "paper", cache=False)
    check_mesh(mesh, case)
    figures, paper = mesh.info["figures"], data_gen.PAPER_MESHES[case]
    for key in ("nodes", "boundary", "tets"):
        assert figures[key] == pytest.approx(paper[key], rel=0.25), key


@pytest.mark.slow
def test_gmsh_paper_fluid_wing_matches_the_paper():
    pytest.importorskip("gmsh")
    mesh = data_gen.build_arrays("fluid_wing", "paper", cache=False)
    check_mesh(mesh, "fluid_wing")
    figures, paper = mesh.info["figures"], data_gen.PAPER_MESHES["fluid_wing"]
    for key in ("nodes", "interior", "boundary", "tets"):
        assert figures[key] == pytest.approx(paper[key], rel=0.25), key
    assert figures["max_q"] < 6.0


def test_build_returns_a_tetmesh(tmp_path):
    pytest.importorskip("gmsh")
    torchmorph_mesh = pytest.importorskip("torchmorph.mesh")
    mesh = data_gen.build("A", "small", cache_dir=tmp_path)
    assert isinstance(mesh, torchmorph_mesh.TetMesh)
    assert mesh.name == "wing-small-gmsh"
    assert mesh.volumes.min() > 0
    tagged = mesh.nodes_of(list(mesh.node_sets))
    assert np.array_equal(tagged.numpy(), mesh.boundary_nodes.numpy())
    assert np.array_equal(data_gen.wing(cache_dir=tmp_path).points.numpy(), mesh.points.numpy())


# --------------------------------------------------------------------------- cache


def test_cache_round_trip_and_keys(tmp_path, monkeypatch):
    pytest.importorskip("gmsh")
    path = data_gen.cache_path("wing", "small", cache_dir=tmp_path)
    assert not path.exists()
    built = data_gen.build_arrays("wing", "small", cache_dir=tmp_path)
    assert path.exists() and path.parent == tmp_path and path.name.startswith("wing-small-gmsh-")

    def no_meshing(*args, **kwargs):
        raise AssertionError("the cached mesh should have been used")

    monkeypatch.setattr(cases, "_generate", no_meshing)
    loaded = data_gen.build_arrays("A", "small", cache_dir=tmp_path)
    assert np.array_equal(loaded.points, built.points) and np.array_equal(loaded.tets, built.tets)
    for name, nodes in built.node_sets.items():
        assert np.array_equal(loaded.node_sets[name], nodes)
    assert loaded.info["params"] == built.info["params"]
    # keyed by size, mesher, parameters and seed
    others = {
        data_gen.cache_path("wing", "paper", cache_dir=tmp_path),
        data_gen.cache_path("wing", "small", "pytetwild", cache_dir=tmp_path),
        data_gen.cache_path("wing", "small", mesh_scale=1.5, cache_dir=tmp_path),
        data_gen.cache_path("wing", "small", seed=2, cache_dir=tmp_path),
        data_gen.cache_path("hull", "small", cache_dir=tmp_path),
    }
    assert path not in others and len(others) == 5
    with pytest.raises(AssertionError, match="cached mesh"):
        data_gen.build_arrays("wing", "small", cache=False, cache_dir=tmp_path)


def test_cache_directory_choice(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHMORPH_CACHE", str(tmp_path / "env"))
    assert data_gen.default_cache_dir() == tmp_path / "env"
    assert data_gen.cache_path("hull", "small").parent == tmp_path / "env"
    assert data_gen.cache_path("hull", "small", cache_dir=tmp_path).parent == tmp_path
    monkeypatch.delenv("TORCHMORPH_CACHE")
    assert data_gen.default_cache_dir().parts[-3:] == (".cache", "torchmorph", "meshes")


def test_no_cache_writes_nothing(tmp_path):
    pytest.importorskip("gmsh")
    data_gen.build_arrays("wing", "small", cache=False, cache_dir=tmp_path)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- arguments, CLI


def test_case_names_and_bad_arguments():
    assert [data_gen.canonical_case(c) for c in ("A", "b", "C", "Fluid_Wing")] == [
        "wing",
        "fluid_wing",
        "hull",
        "fluid_wing",
    ]
    with pytest.raises(ValueError, match="case must be one of"):
        data_gen.build_arrays("D")
    with pytest.raises(ValueError, match="size must be one of"):
        data_gen.build_arrays("wing", "huge")
    with pytest.raises(ValueError, match="mesher must be one of"):
        data_gen.build_arrays("wing", "small", "netgen")
    with pytest.raises(ValueError, match="mesh_scale must be a positive number"):
        data_gen.build_arrays("wing", "small", mesh_scale=0.0)


def test_paper_meshes_constant():
    assert data_gen.PAPER_MESHES["wing"]["nodes"] == 2463
    assert data_gen.PAPER_MESHES["fluid_wing"]["max_q"] == 4.31
    assert data_gen.PAPER_MESHES["hull"]["mean_q"] == 1.62
    for figures in data_gen.PAPER_MESHES.values():
        assert figures["interior"] + figures["boundary"] == figures["nodes"]


def test_cli_writes_and_prints(tmp_path, capsys):
    pytest.importorskip("gmsh")
    meshio = pytest.importorskip("meshio")
    from data_gen.__main__ import main

    output = tmp_path / "wing.vtu"
    assert main(["A", "--size", "small", "--cache-dir", str(tmp_path), "-o", str(output)]) == 0
    text = capsys.readouterr().out
    assert "wing (small, gmsh): built" in text and "2,463" in text and "boundary nodes" in text
    written = meshio.read(output)
    assert written.points.shape[1] == 3 and "tetra" in written.cells_dict
    flags = written.point_data["set:trailing_edge"]
    assert np.allclose(written.points[flags > 0, 0], CHORD)
    assert main(["A", "--size", "small", "--cache-dir", str(tmp_path)]) == 0
    assert "loaded from the cache" in capsys.readouterr().out
    assert main(["nope"]) == 2
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0


# --------------------------------------------------------------------------- geometry, helpers


def test_naca_profile_closed_trailing_edge():
    assert naca_half_thickness(np.array([0.0]))[0] == 0.0
    assert abs(naca_half_thickness(np.array([CHORD]))[0]) < 1e-15
    x, y = naca_profile(2001)
    assert x[0] == 0.0 and x[-1] == CHORD
    assert 2 * y.max() == pytest.approx(0.12 * CHORD, rel=1e-3)
    assert x[np.argmax(y)] == pytest.approx(0.3 * CHORD, abs=0.01)


def test_gmsh_profile_curves_follow_the_naca_profile():
    """Both OpenCASCADE splines of the profile stay on their side of the chord, end at the
    sharp trailing edge and follow the closed-form half-thickness (a spline interpolated
    towards the trailing edge with its end tangent prescribed overshot it to x = 1.012 c
    and crossed the chord line)."""
    pytest.importorskip("gmsh")
    from data_gen._gmsh import _profile_splines
    from torchmorph.meshing.gmsh_model import gmsh_session

    with gmsh_session("profile", seed=0, verbose=False) as gmsh:
        face = _profile_splines(gmsh.model.occ, 121)
        gmsh.model.occ.synchronize()
        sides = []
        for _, curve in gmsh.model.getBoundary([(2, face)]):
            (low,), (high,) = gmsh.model.getParametrizationBounds(1, abs(curve))
            t = np.linspace(low, high, 20001)
            xyz = np.reshape(gmsh.model.getValue(1, abs(curve), t), (-1, 3))
            x, y = xyz[:, 0], xyz[:, 1]
            side = np.sign(y[len(y) // 2])
            sides.append(side)
            assert x.min() >= -1e-12 and x.max() <= CHORD * (1 + 1e-12)
            assert (side * y).min() >= -1e-12  # never across the chord line
            assert np.abs(np.abs(y) - naca_half_thickness(x)).max() < 5e-5 * CHORD
    assert sorted(sides) == [-1.0, 1.0]


def test_project_to_profile_finds_the_nearest_point():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.05, 1.06, 300), rng.uniform(-0.1, 0.1, 300)
    side = np.where(y >= 0, 1.0, -1.0)
    px, py = project_to_profile(x, y, side)
    assert np.abs(py - side * naca_half_thickness(px)).max() <= 1e-15
    theta = np.linspace(0.0, math.pi, 400001)
    sx = CHORD * (1 - np.cos(theta)) / 2
    sy = naca_half_thickness(sx)
    for k in range(0, 300, 37):
        brute = np.min(np.hypot(sx - x[k], side[k] * sy - y[k]))
        assert np.hypot(px[k] - x[k], py[k] - y[k]) <= brute + 1e-9


def test_wigley_hull_formula():
    half = HULL_LENGTH / 2
    assert wigley_half_breadth(np.array([0.0]), np.array([0.0]))[0] == pytest.approx(HULL_BEAM / 2)
    edges = wigley_half_breadth(
        np.array([half, -half, 0.0, 0.0]), np.array([0.0, 0.0, HULL_DRAFT, -HULL_DRAFT])
    )
    assert np.all(edges == 0.0)
    assert HULL_BEAM / HULL_LENGTH == pytest.approx(
        0.1
    ) and HULL_DRAFT / HULL_LENGTH == pytest.approx(0.0625)


def test_untangle_repairs_a_folded_node():
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(3)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
    points = np.concatenate([corners, rng.uniform(0.2, 0.8, (30, 3))])
    tets = data_gen._arrays.orient(points, Delaunay(points).simplices)
    fixed = np.zeros(len(points), dtype=bool)
    fixed[:8] = True
    moved = points.copy()
    moved[10] += [0.5, 0.3, 0.0]
    assert (signed_volumes(moved, tets) <= 0).any()
    repaired, bad = untangle(moved, tets, fixed)
    assert bad == 0 and signed_volumes(repaired, tets).min() > 0
    assert np.array_equal(repaired[:8], corners)


# --------------------------------------------------------------------------- pytetwild


@pytest.mark.slow
@pytest.mark.parametrize("case", data_gen.CASES)
def test_pytetwild_small_mesh_is_valid_and_tagged(case, tmp_path):
    pytest.importorskip("pytetwild")
    start = time.perf_counter()
    mesh = data_gen.build_arrays(case, "small", "pytetwild", cache_dir=tmp_path)
    seconds = time.perf_counter() - start
    params = mesh.info["params"]
    envelope = params["epsilon"] * np.linalg.norm(np.ptp(mesh.points, axis=0))
    check_mesh(mesh, case, exact_edges=False, envelope=envelope)
    low, high = SMALL_NODES[case]
    assert low <= len(mesh.points) <= high
    # written to the cache, read back identical (the mesher itself is not reproducible)
    start = time.perf_counter()
    again = data_gen.build_arrays(case, "small", "pytetwild", cache_dir=tmp_path)
    assert time.perf_counter() - start < seconds
    assert np.array_equal(again.points, mesh.points) and np.array_equal(again.tets, mesh.tets)


# --------------------------------------------------------------------------- robustness


def tiny_mesh():
    from data_gen._arrays import MeshArrays

    return MeshArrays(
        points=np.eye(4, 3),
        tets=np.array([[0, 1, 2, 3]]),
        node_sets={"all": np.arange(4)},
        info={"case": "tiny"},
    )


def test_cache_files_are_readable_and_round_trip(tmp_path):
    import os
    import stat

    from data_gen import cache

    path = tmp_path / "nested" / "tiny.npz"
    umask = os.umask(0o022)
    try:
        assert cache.save(path, tiny_mesh())
    finally:
        os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [item.name for item in path.parent.iterdir()] == ["tiny.npz"]  # no temporary left
    loaded = cache.load(path)
    assert np.array_equal(loaded.tets, [[0, 1, 2, 3]]) and loaded.info == {"case": "tiny"}


def test_unwritable_cache_warns_and_keeps_the_mesh(tmp_path):
    from data_gen import cache

    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.warns(RuntimeWarning, match=r"could not write the mesh cache entry .*file"):
        assert cache.save(blocker / "tiny.npz", tiny_mesh()) is False


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 truncated", b"garbage"])
def test_corrupt_cache_entry_is_reported_removed_and_rebuilt(tmp_path, monkeypatch, content):
    from data_gen import cache

    path = data_gen.cache_path("wing", "small", cache_dir=tmp_path)
    path.write_bytes(content)
    with pytest.raises(ValueError, match=r"mesh cache entry .* is unreadable"):
        cache.load(path)

    def meshing(*args, **kwargs):
        raise RuntimeError("meshing again")

    monkeypatch.setattr(cases, "_generate", meshing)
    with (
        pytest.warns(RuntimeWarning, match="is unreadable .*building the mesh again"),
        pytest.raises(RuntimeError, match="meshing again"),
    ):
        data_gen.build_arrays("wing", "small", cache_dir=tmp_path)
    assert not path.exists()


def test_read_only_cache_still_returns_the_built_mesh(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setattr(cases, "_generate", lambda *a, **k: (None, None, None))
    monkeypatch.setattr(
        cases,
        "_finish",
        lambda *a, **k: (np.eye(4, 3), np.array([[0, 1, 2, 3]]), {"all": np.arange(4)}, 0),
    )
    monkeypatch.setattr(cases, "mesh_figures", lambda points, tets: {})
    with pytest.warns(RuntimeWarning, match="could not write the mesh cache entry"):
        mesh = data_gen.build_arrays("wing", "small", cache_dir=blocker / "cache")
    assert np.array_equal(mesh.tets, [[0, 1, 2, 3]])


@pytest.mark.parametrize(
    ("case", "inside", "on_surface", "thin_end"),
    [
        # case B: the wing's thickness is along y; its thin end is the trailing edge
        ("fluid_wing", [0.3, 0, 0.5], [0.3, naca_half_thickness(0.3), 0.5], [CHORD - 1e-4, 0, 0.5]),
        # case C: the hull's breadth is along z; its thin ends are the stem and the stern
        ("hull", [0.0, 0.0, 0.0], [0.0, 0.0, HULL_BEAM / 2.0], [HULL_LENGTH / 2.0 - 1e-4, 0, 0]),
    ],
)
def test_a_fluid_node_inside_the_body_fails_the_pytetwild_check(case, inside, on_surface, thin_end):
    box = np.array(
        [[x, y, z] for x in (-3.0, 3.0) for y in (-2.0, 2.0) for z in (-1.0, 2.0)], dtype=float
    )
    epsilon = 1e-3  # envelope = 1e-3 * the box's diagonal ~ 7.8e-3
    cases._check_body_is_a_hole(case, np.vstack([box, on_surface, thin_end]), epsilon)
    with pytest.raises(RuntimeError, match=rf"^{case} \(pytetwild\): 1 fluid nodes lie inside"):
        cases._check_body_is_a_hole(case, np.vstack([box, on_surface, inside]), epsilon)


def test_a_pytetwild_mesh_that_fails_a_check_is_made_again(tmp_path, monkeypatch):
    calls = []

    def finish(*args, failures):
        calls.append(args[1])
        if len(calls) <= failures:
            raise RuntimeError("hull (pytetwild): 1 fluid nodes lie inside the hull")
        return np.eye(4, 3), np.array([[0, 1, 2, 3]]), {"all": np.arange(4)}, 0

    monkeypatch.setattr(cases, "_generate", lambda *a, **k: (None, None, None))
    monkeypatch.setattr(cases, "mesh_figures", lambda points, tets: {})
    attempts = cases._TETWILD_ATTEMPTS
    monkeypatch.setattr(cases, "_finish", lambda *a: finish(*a, failures=attempts - 1))
    mesh = data_gen.build_arrays("hull", "small", "pytetwild", cache_dir=tmp_path)
    assert calls == ["pytetwild"] * attempts and mesh.info["attempts"] == attempts
    calls.clear()
    monkeypatch.setattr(cases, "_finish", lambda *a: finish(*a, failures=attempts))
    with pytest.raises(RuntimeError, match="fluid nodes lie inside the hull"):
        data_gen.build_arrays("hull", "small", "pytetwild", cache=False)
    assert len(calls) == attempts


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["D"], r"^error: case: case must be one of"),
        (["A", "--mesh-scale", "0"], r"^error: --mesh-scale must be a finite number > 0, got 0.0$"),
        (["A", "--mesh-scale", "nan"], r"^error: --mesh-scale must be a finite number > 0"),
        (["A", "--seed", "-1"], r"^error: --seed must be >= 0, got -1$"),
        (
            ["A", "-o", "{tmp}/mesh.stl"],
            r"^error: --output: unsupported mesh file extension '.stl'",
        ),
        (["A", "-o", "{tmp}/missing/mesh.vtu"], r"^error: --output: directory .*' does not exist$"),
        (["A", "-o", "{tmp}"], r"^error: --output: .* is a directory$"),
        (["A", "--cache-dir", "{tmp}/file"], r"^error: --cache-dir: .*file' is not a directory$"),
    ],
)
def test_cli_bad_arguments_are_one_line_errors_before_meshing(
    tmp_path, monkeypatch, capsys, arguments, message
):
    from data_gen.__main__ import main

    (tmp_path / "file").write_text("x")

    def no_meshing(*args, **kwargs):
        raise AssertionError("meshing started")

    monkeypatch.setattr(cases, "_generate", no_meshing)
    arguments = [argument.replace("{tmp}", str(tmp_path)) for argument in arguments]
    assert main(arguments) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1, error
    assert re.search(message, error.strip()), error


def test_cli_failure_while_meshing_is_one_line(tmp_path, monkeypatch, capsys):
    pytest.importorskip("gmsh")
    from data_gen.__main__ import main

    def failing(*args, **kwargs):
        raise RuntimeError("the mesher gave up")

    monkeypatch.setattr(cases, "_generate", failing)
    assert main(["A", "--size", "small", "--cache-dir", str(tmp_path)]) == 1
    assert capsys.readouterr().err == "error: RuntimeError: the mesher gave up\n"
