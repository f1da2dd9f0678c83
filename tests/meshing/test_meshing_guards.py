"""Guards on meshing: threads and sizes checked, estimates refused above the budget,
bodies that overlap, touch or nest refused, coordinates far from the origin, units of
CAD files, progress lines.

Every refusal is checked with meshing disabled (``no_meshing``): were a refusal to go
missing, the test fails at once instead of meshing for minutes.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from conftest import write_cad

from torchmorph import meshing
from torchmorph.meshing import Surface, box_surface, cad, mesh_cad, mesh_surfaces
from torchmorph.meshing.estimate import TETS_PER_REGULAR
from torchmorph.meshing.snapping import signed_volumes

trimesh = pytest.importorskip("trimesh")
gmsh = pytest.importorskip("gmsh")


def ball(radius: float = 0.5, centre=(0.0, 0.0, 0.0), name: str = "ball", subdivisions=2):
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Surface(np.asarray(sphere.vertices) + centre, np.asarray(sphere.faces), name)


@pytest.fixture
def no_meshing(monkeypatch):
    """fTetWild and gmsh's 3-D meshing fail at once (the estimate's coarse surface mesh runs)."""
    pytetwild = pytest.importorskip("pytetwild")

    def refuse(*args, **kwargs):
        raise AssertionError("meshing started: the refusal is missing")

    monkeypatch.setattr(pytetwild, "tetrahedralize", refuse)
    monkeypatch.setattr(cad, "collect_tets", refuse)


@pytest.fixture(scope="module")
def cube_step(tmp_path_factory):
    return write_cad(
        tmp_path_factory.mktemp("cube") / "cube.step", lambda occ: occ.addBox(0, 0, 0, 1, 1, 1)
    )


def _volume(mesh) -> float:
    return float(signed_volumes(mesh.points.numpy(), mesh.tets.numpy()).sum())


# --------------------------------------------------------------------------- threads, sizes


@pytest.mark.parametrize("threads", [-5, -3, 0, 1.5, True, "2"])
def test_threads_must_be_an_integer_of_at_least_one(no_meshing, cube_step, threads):
    surface = ball()
    calls = [
        lambda: mesh_surfaces(surface, threads=threads),
        lambda: meshing.tetrahedralize(
            surface.vertices, surface.faces, edge_length=0.2, threads=threads
        ),
        lambda: mesh_cad(cube_step, threads=threads),
    ]
    for call in calls:
        with pytest.raises(
            ValueError,
            match=r"^threads must be an integer >= 1 \(or None for the default, 1\), got "
            + re.escape(repr(threads)),
        ):
            call()


@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf, "0.1"])
@pytest.mark.parametrize("label", ["edge_length", "body_edge_length", "grading"])
def test_sizes_must_be_finite_and_positive(no_meshing, cube_step, label, value):
    message = rf"^{label} must be a finite number > 0, got {re.escape(repr(value))}"
    with pytest.raises(ValueError, match=message):
        mesh_surfaces(ball(), box=1, **{label: value})
    with pytest.raises(ValueError, match=message):
        mesh_surfaces(cube_step, box=1, **{label: value})  # the CAD path, named the same
    cad_label = {"edge_length": "mesh_size", "body_edge_length": "body_mesh_size"}.get(label, label)
    with pytest.raises(ValueError, match=rf"^{cad_label} must be a finite number > 0"):
        mesh_cad(cube_step, box=1, **{cad_label: value})


def test_a_size_larger_than_the_body_is_refused(no_meshing, cube_step):
    surface = ball()  # diameter 1
    extent = float(np.ptp(surface.vertices, axis=0).max())
    too_large = (
        rf"the domain's largest extent {extent:.4g} \(less than one element across it\), got 10"
    )
    with pytest.raises(ValueError, match=rf"^edge_length must be at most {too_large}"):
        mesh_surfaces(surface, edge_length=10.0)
    with pytest.raises(ValueError, match=rf"^edge_length must be at most {too_large}"):
        meshing.tetrahedralize(surface.vertices, surface.faces, edge_length=10.0)
    with pytest.raises(ValueError, match=r"^body_edge_length must be at most the bodies' largest"):
        mesh_surfaces(surface, box=1, body_edge_length=2.0)
    with pytest.raises(
        ValueError, match=r"^mesh_size must be at most the domain's largest extent 1 "
    ):
        mesh_cad(cube_step, mesh_size=10.0)
    with pytest.raises(
        ValueError, match=r"^body_mesh_size must be at most the bodies' largest extent 1 "
    ):
        mesh_cad(cube_step, box=1, body_mesh_size=5.0)


@pytest.mark.parametrize("value", [0, -1, 2.5, "many", math.inf])
def test_max_elements_must_be_an_integer_or_none(no_meshing, cube_step, value):
    with pytest.raises(ValueError, match=r"^max_elements must be an integer >= 1 or None"):
        mesh_surfaces(ball(), max_elements=value)
    with pytest.raises(ValueError, match=r"^max_elements must be an integer >= 1 or None"):
        mesh_cad(cube_step, max_elements=value)


# --------------------------------------------------------------------------- estimate


def test_an_edge_length_far_too_small_is_refused_with_the_estimate(no_meshing):
    surface = ball()
    expected = TETS_PER_REGULAR["ftetwild"] * 6 * math.sqrt(2) * surface.volume / 1e-9
    assert 3e9 < expected < 1e10  # a unit body at 1e-3: billions
    message = (
        rf"^edge_length: the mesh would have about {expected:.2g} tetrahedra \(estimated from the "
        rf"domain's volume {surface.volume:.3g} and edge_length 0.001\), more than max_elements = "
        r"3,000,000; raise edge_length to about 0.01\d*, or raise max_elements \(None: no limit\)"
    ).replace("+", r"\+")
    with pytest.raises(ValueError, match=message):
        mesh_surfaces(surface, edge_length=1e-3)
    with pytest.raises(ValueError, match=r"^edge_length: the mesh would have about"):
        meshing.tetrahedralize(surface.vertices, surface.faces, edge_length=1e-3)


def test_a_cad_mesh_size_far_too_small_is_refused(no_meshing, cube_step):
    expected = TETS_PER_REGULAR["gmsh-hxt"] * 6 * math.sqrt(2) / 1e-9
    with pytest.raises(
        ValueError,
        match=rf"^mesh_size: the mesh would have about {expected:.2g}".replace("+", r"\+"),
    ):
        mesh_cad(cube_step, mesh_size=1e-3)
    with pytest.raises(ValueError, match=r"^edge_length: the mesh would have about 4.2e\+09"):
        mesh_surfaces(cube_step, edge_length=1e-3)
    with pytest.raises(ValueError, match=r"more than max_elements = 100; raise mesh_size"):
        mesh_cad(cube_step, mesh_size=0.1, max_elements=100)


def test_a_graded_body_size_far_too_small_names_the_body_size(no_meshing):
    with pytest.raises(
        ValueError,
        match=r"^body_edge_length: the mesh would have about .* tetrahedra \(estimated from the "
        r"domain's volume .* and edge_length 0.5, body_edge_length 0.0001, grading 1\), more "
        r"than max_elements = 3,000,000; raise body_edge_length to about 0.00\d+ \(or shorten "
        r"grading\)",
    ):
        mesh_surfaces(ball(), box=1, edge_length=0.5, body_edge_length=1e-4, grading=1.0)


def test_max_elements_none_meshes_what_the_budget_refuses(cube_step):
    with pytest.raises(ValueError, match=r"more than max_elements = 10;"):
        mesh_cad(cube_step, mesh_size=0.5, max_elements=10)
    mesh = mesh_cad(cube_step, mesh_size=0.5, max_elements=None)
    assert _volume(mesh) == pytest.approx(1.0, rel=1e-12)


# --------------------------------------------------------------------------- far coordinates


def test_a_surface_far_from_the_origin_is_meshed_about_its_centre(monkeypatch):
    pytetwild = pytest.importorskip("pytetwild")
    real = pytetwild.tetrahedralize
    seen = []

    def centred_only(vertices, faces, **options):  # fTetWild stalls on coordinates at 1e7
        seen.append(np.abs(vertices).max())
        assert seen[-1] < 10, "fTetWild was given the far coordinates"
        return real(vertices, faces, **options)

    monkeypatch.setattr(pytetwild, "tetrahedralize", centred_only)
    centre = np.array([1e7, -2e7, 3e7])
    far, near = ball(centre=centre, subdivisions=1), ball(subdivisions=1)
    mesh = mesh_surfaces(far, edge_length=0.4)
    assert seen and seen[-1] < 1
    points = mesh.points.numpy()
    from torchmorph.meshing import closest_points

    boundary = points[mesh.boundary_nodes.numpy()]
    assert closest_points(boundary, far.vertices, far.faces)[2].max() < 1e-7
    assert _volume(mesh) == pytest.approx(near.volume, rel=3e-2)
    assert (signed_volumes(points - centre, mesh.tets.numpy()) > 0).all()


def test_a_cad_body_far_from_the_origin_is_meshed_like_one_at_the_origin(tmp_path):
    far = write_cad(tmp_path / "far.step", lambda occ: occ.addBox(1e7, 1e7, 1e7, 1, 1, 2))
    mesh = mesh_cad(far, box=1, mesh_size=0.8)
    points = mesh.points.numpy()
    np.testing.assert_allclose(points.min(0), [1e7 - 2, 1e7 - 2, 1e7 - 2], atol=1e-6)
    np.testing.assert_allclose(points.max(0), [1e7 + 3, 1e7 + 3, 1e7 + 4], atol=1e-6)
    body = points[mesh.node_sets["far"].numpy()]
    np.testing.assert_allclose(body.max(0) - body.min(0), [1, 1, 2], atol=1e-6)
    assert _volume(mesh) == pytest.approx(5 * 5 * 6 - 2, rel=1e-6)


# --------------------------------------------------------------------------- overlap, touch, nest


def _boxes(tmp_path, name, *boxes):
    return write_cad(tmp_path / f"{name}.step", lambda occ: [occ.addBox(*b) for b in boxes])


def test_two_overlapping_solids_in_one_step_file_are_refused(no_meshing, tmp_path):
    pair = _boxes(tmp_path, "pair", (0, 0, 0, 1, 1, 1), (0.5, 0.5, 0.5, 1, 1, 1))
    message = (
        r"^files: bodies 'pair' \(solid 1 of 2\) and 'pair' \(solid 2 of 2\) overlap \(common "
        r"volume 0.125\): bodies must be disjoint"
    )
    with pytest.raises(ValueError, match=message):
        mesh_cad(pair)
    with pytest.raises(ValueError, match=message):
        mesh_cad(pair, box=1)


@pytest.mark.parametrize("box", [None, 1.0])
def test_two_files_whose_bodies_overlap_or_touch_are_refused(no_meshing, tmp_path, box):
    a = _boxes(tmp_path, "a", (0, 0, 0, 1, 1, 1))
    b = _boxes(tmp_path, "b", (0.5, 0.5, 0.5, 1, 1, 1))
    touching = _boxes(tmp_path, "c", (1, 0, 0, 1, 1, 1))
    edge_on = _boxes(tmp_path, "d", (1, 1, 0, 1, 1, 1))  # only an edge in common
    with pytest.raises(
        ValueError, match=r"^files: bodies 'a' and 'b' overlap \(common volume 0.125\)"
    ):
        mesh_cad([a, b], box=box)
    for other, name in ((touching, "c"), (edge_on, "d")):
        with pytest.raises(
            ValueError, match=rf"^files: bodies 'a' and '{name}' touch \(closer than [\d.]+e-06\)"
        ):
            mesh_cad([a, other], box=box)


def test_a_box_inside_a_box_is_refused_but_where_it_is_a_hole(no_meshing, tmp_path):
    nested = _boxes(tmp_path, "nest", (0, 0, 0, 2, 2, 2), (0.5, 0.5, 0.5, 1, 1, 1))
    with pytest.raises(
        ValueError,
        match=r"^files: body 'nest' \(solid 2 of 2\) lies inside body 'nest' \(solid 1 of 2\): a "
        r"body inside another is a hole only without box/bounds",
    ):
        mesh_cad(nested)
    outer = _boxes(tmp_path, "outer", (0, 0, 0, 2, 2, 2))
    inner = _boxes(tmp_path, "inner", (0.5, 0.5, 0.5, 1, 1, 1))
    with pytest.raises(ValueError, match=r"^files: body 'inner' lies inside body 'outer'"):
        mesh_cad([outer, inner], box=1)
    # without a box the outer file is the wall and the inner one a hole: checked, then meshed
    with pytest.raises(AssertionError, match="meshing started"):
        mesh_cad([outer, inner])
    touching = write_cad(tmp_path / "shell.step", lambda occ: occ.addSphere(0, 0, 0, 1.0))
    corner = _boxes(tmp_path, "corner", *[(-(3**-0.5),) * 3 + (2 * 3**-0.5,) * 3])
    with pytest.raises(
        ValueError, match=r"^files: body 'corner' touches the inside of body 'shell'"
    ):
        mesh_cad([touching, corner])


def test_overlapping_touching_or_nested_surfaces_are_refused(no_meshing):
    first, second = ball(name="a"), ball(centre=(0.6, 0, 0), name="b")  # mirror images
    assert meshing.checks.surface_contacts(first, ball(centre=(0.6, 0.05, 0.02)), 1e-6) == "cross"
    for box in (None, 1.0):
        with pytest.raises(
            ValueError, match=r"^surfaces: 'a' and 'b' overlap \(their surfaces cross\)"
        ):
            mesh_surfaces([first, second], box=box)
    left = box_surface([[0, 0, 0], [1, 1, 1]], name="left")
    right = box_surface([[1, 0.2, 0.2], [1.5, 0.8, 0.8]], name="right")  # on left's face
    with pytest.raises(ValueError, match=r"^surfaces: 'left' and 'right' touch \(a vertex of one"):
        mesh_surfaces([left, right], box=1)
    outer = box_surface([[-1, -1, -1], [1, 1, 1]], name="outer")
    inner = ball(0.3, name="inner")
    with pytest.raises(ValueError, match=r"^surfaces: 'inner' lies inside 'outer': a body"):
        mesh_surfaces([outer, inner], box=1)
    # outer holding inner and a third body that crosses inner
    with pytest.raises(ValueError, match=r"^surfaces: 'inner' and 'third' overlap"):
        mesh_surfaces([outer, inner, ball(0.3, centre=(0.2, 0, 0), name="third")])
    with pytest.raises(AssertionError, match="meshing started"):  # a hole: accepted
        mesh_surfaces([outer, inner])


def test_a_body_touching_the_box_wall_is_refused(no_meshing, cube_step):
    """A box padded by 0 below: the body's face is on the wall (a half model on a symmetry
    plane is not supported: the wall and the body would share faces)."""
    with pytest.raises(
        ValueError,
        match=r"^bounds: the box .* does not contain surface 'ball' .*; bodies must lie strictly "
        r"inside the box, not touching its walls",
    ):
        mesh_surfaces(ball(centre=(1e7, 0, 0)), box=(0, 1, 1, 1, 1, 1))
    with pytest.raises(
        ValueError,
        match=r"^bounds: the box \[\[0.0, -1.0, -1.0\], \[2.0, 2.0, 2.0\]\] does not contain body "
        r"'cube' .*not touching its walls",
    ):
        mesh_cad(cube_step, bounds=[[0, -1, -1], [2, 2, 2]])


# --------------------------------------------------------------------------- units, progress


STEP_INCH = """ISO-10303-21;
DATA;
#10 = ( LENGTH_UNIT() NAMED_UNIT(*) SI_UNIT(.MILLI.,.METRE.) );
#11 = LENGTH_MEASURE_WITH_UNIT(LENGTH_MEASURE(25.4),#10);
#12 = DIMENSIONAL_EXPONENTS(1.,0.,0.,0.,0.,0.,0.);
#13 = ( CONVERSION_BASED_UNIT('INCH',#11) LENGTH_UNIT() NAMED_UNIT(#12) );
#14 = ( NAMED_UNIT(*) PLANE_ANGLE_UNIT() SI_UNIT($,.RADIAN.) );
#20 = ( GEOMETRIC_REPRESENTATION_CONTEXT(3)
  GLOBAL_UNCERTAINTY_ASSIGNED_CONTEXT((#21)) GLOBAL_UNIT_ASSIGNED_CONTEXT((#13,#14))
  REPRESENTATION_CONTEXT('Context #1','3D Context') );
ENDSEC;
END-ISO-10303-21;
"""


def test_the_length_unit_of_step_and_iges_files_is_read(tmp_path, cube_step):
    from torchmorph.meshing.cad_units import file_unit

    assert file_unit(cube_step) == "MM"  # gmsh writes millimetres
    metres = tmp_path / "metres.step"
    metres.write_text(
        cube_step.read_text().replace("SI_UNIT(.MILLI.,.METRE.)", "SI_UNIT($,.METRE.)")
    )
    assert file_unit(metres) == "M"
    (tmp_path / "inch.stp").write_text(STEP_INCH)
    assert file_unit(tmp_path / "inch.stp") == "INCH"
    (tmp_path / "none.step").write_text("ISO-10303-21;\nDATA;\nENDSEC;\n")
    assert file_unit(tmp_path / "none.step") is None
    iges = write_cad(tmp_path / "faces.iges", lambda occ: occ.addBox(0, 0, 0, 1, 1, 1))
    assert file_unit(iges) == "MM"
    assert (
        file_unit(write_cad(tmp_path / "cube.brep", lambda occ: occ.addBox(0, 0, 0, 1, 1, 1)))
        is None
    )


def test_a_step_file_in_metres_keeps_its_numbers(tmp_path, capsys):
    from _wing import SPAN, write_wing

    wing = write_wing(tmp_path / "m6.step", metres=True)
    capsys.readouterr()
    mesh = mesh_cad(wing, progress=True)  # OpenCASCADE alone: 1196 units of span
    assert float(np.ptp(mesh.points[:, 1].numpy())) == pytest.approx(SPAN, rel=1e-6)
    assert "CAD: m6: 1 solid(s) (lengths in metres, as in the file)" in capsys.readouterr().err
    # sizes in the file's unit: a span of 1196 would have made this 10^10 tetrahedra
    mesh = mesh_cad(wing, box=1, body_mesh_size=0.1)
    assert 2_000 < mesh.num_tets < 50_000


def test_progress_lines_say_the_estimate_the_steps_and_the_time(cube_step, capsys):
    capsys.readouterr()
    mesh = mesh_cad(cube_step, box=1, mesh_size=0.5, body_mesh_size=0.2)
    assert capsys.readouterr().err == ""  # silent by default
    mesh = mesh_cad(cube_step, box=1, mesh_size=0.5, body_mesh_size=0.2, progress=True)
    lines = capsys.readouterr().err.splitlines()
    assert all(re.match(r"\[ *\d+\.\d s\] ", line) for line in lines), lines
    text = "\n".join(line.split("] ", 1)[1] for line in lines)
    assert re.search(r"^estimate: about [\d,]+ tetrahedra \(max_elements 3,000,000\)$", text, re.M)
    for step in ("curves", "surfaces"):
        assert f"gmsh: meshed the {step}: " in text
    assert f"gmsh: meshed the volumes: {mesh.num_tets:,} tetrahedra" in text
    assert text.splitlines()[-1].startswith(f"mesh: {mesh.num_nodes} nodes, {mesh.num_tets} tetra")
