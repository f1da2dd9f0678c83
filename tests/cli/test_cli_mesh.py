"""``torchmorph mesh``: its guards (threads, the estimate and --max-elements, bodies that
overlap) and progress lines, run in-process through ``main``."""

from __future__ import annotations

import re

import pytest
from conftest import write_cad

from torchmorph.cli import EXIT_ERROR, EXIT_OK, EXIT_USAGE, main
from torchmorph.meshing import cad

pytest.importorskip("gmsh")


@pytest.fixture
def no_meshing(monkeypatch):
    """fTetWild and gmsh's 3-D meshing fail at once: a missing refusal cannot run for long."""
    pytetwild = pytest.importorskip("pytetwild")

    def refuse(*args, **kwargs):
        raise AssertionError("meshing started: the refusal is missing")

    monkeypatch.setattr(pytetwild, "tetrahedralize", refuse)
    monkeypatch.setattr(cad, "collect_tets", refuse)


@pytest.fixture
def ball_obj(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in sphere.vertices]
    lines += ["f " + " ".join(str(v + 1) for v in face) for face in sphere.faces]
    path = tmp_path / "ball.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def cube_step(tmp_path):
    return write_cad(tmp_path / "cube.step", lambda occ: occ.addBox(0, 0, 0, 1, 1, 1))


def _run(capsys, *arguments):
    code = main(["mesh", *[str(a) for a in arguments]])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return code, captured.out, captured.err


@pytest.mark.parametrize(
    ("value", "why"),
    [
        ("-5", "must be an integer >= 1"),
        ("0", "must be an integer >= 1"),
        ("two", "expected an integer"),
    ],
)
def test_threads_below_one_is_a_usage_error(no_meshing, ball_obj, tmp_path, capsys, value, why):
    code, _, err = _run(capsys, ball_obj, "--threads", value, "-o", tmp_path / "o.vtu")
    assert code == EXIT_USAGE
    assert f"argument --threads: {why}, got '{value}'" in err


@pytest.mark.parametrize("value", ["0", "-3", "2.5", "lots"])
def test_max_elements_must_be_a_count_or_none(no_meshing, ball_obj, tmp_path, capsys, value):
    code, _, err = _run(capsys, ball_obj, "--max-elements", value, "-o", tmp_path / "o.vtu")
    assert code == EXIT_USAGE
    assert "argument --max-elements: " in err and f"got '{value}'" in err


def test_an_edge_length_far_too_small_is_refused_naming_the_option(
    no_meshing, ball_obj, tmp_path, capsys
):
    code, _, err = _run(capsys, ball_obj, "--edge-length", "0.001", "-o", tmp_path / "o.vtu")
    assert code == EXIT_ERROR
    assert re.search(
        r"--edge-length: the mesh would have about [\d.]+e\+09 tetrahedra \(estimated from the "
        r"domain's volume 0.5\d* and --edge-length 0.001\), more than --max-elements = "
        r"3,000,000; raise --edge-length to about 0.01\d*, or raise --max-elements \('none': no "
        r"limit\) to mesh it anyway",
        err,
    ), err
    assert not (tmp_path / "o.vtu").exists()


def test_an_edge_length_larger_than_the_body_is_refused(no_meshing, ball_obj, tmp_path, capsys):
    code, _, err = _run(capsys, ball_obj, "--edge-length", "10", "-o", tmp_path / "o.vtu")
    assert code == EXIT_ERROR
    assert "--edge-length must be at most the domain's largest extent 1 " in err


def test_max_elements_refuses_and_none_lifts_the_limit(cube_step, tmp_path, capsys):
    out = tmp_path / "cube.vtu"
    code, _, err = _run(
        capsys, cube_step, "--edge-length", "0.5", "--max-elements", "10", "-o", out
    )
    assert code == EXIT_ERROR
    assert "more than --max-elements = 10; raise --edge-length to about" in err
    assert not out.exists()
    code, printed, _ = _run(
        capsys, cube_step, "--edge-length", "0.5", "--max-elements", "none", "-o", out
    )
    assert code == EXIT_OK and out.exists() and "tetrahedra" in printed


def test_overlapping_bodies_are_an_error_naming_them(no_meshing, tmp_path, capsys):
    a = write_cad(tmp_path / "a.step", lambda occ: occ.addBox(0, 0, 0, 1, 1, 1))
    b = write_cad(tmp_path / "b.step", lambda occ: occ.addBox(0.5, 0.5, 0.5, 1, 1, 1))
    code, _, err = _run(capsys, a, b, "--box", "1", "-o", tmp_path / "o.vtu")
    assert code == EXIT_ERROR
    assert "bodies 'a' and 'b' overlap (common volume 0.125)" in err


def test_progress_is_on_by_default_and_off_with_no_progress(cube_step, tmp_path, capsys):
    out = tmp_path / "cube.vtu"
    code, _, err = _run(capsys, cube_step, "--box", "1", "--body-edge-length", "0.2", "-o", out)
    assert code == EXIT_OK
    lines = err.splitlines()
    assert all(re.match(r"\[ *\d+\.\d s\] ", line) for line in lines), lines
    assert any(
        re.search(r"\] estimate: about [\d,]+ tetrahedra \(max_elements 3,000,000\)$", line)
        for line in lines
    )
    assert any("gmsh: meshed the volumes: " in line for line in lines)
    code, _, err = _run(capsys, cube_step, "--box", "1", "--no-progress", "-o", out)
    assert code == EXIT_OK and err == ""


def test_threads_reach_gmsh(cube_step, tmp_path, capsys, monkeypatch):
    seen = []
    session = cad.gmsh_session

    def spy(name, **options):
        seen.append(options["threads"])
        return session(name, **options)

    monkeypatch.setattr(cad, "gmsh_session", spy)
    code, _, _ = _run(
        capsys, cube_step, "--threads", "2", "--no-progress", "-o", tmp_path / "c.vtu"
    )
    assert code == EXIT_OK and seen == [2]
