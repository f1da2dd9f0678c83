"""The README's code and commands run as written, and CI runs the README's test command."""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import write_cad

from torchmorph.cli import EXIT_OK, main

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def code_blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README, flags=re.DOTALL)


def readme_commands() -> list[str]:
    """The inline commands of the README (``torchmorph ...``, ``python ...``), in order.

    The two set-up commands (bash blocks: install, tests) are not run here; ``pip`` and
    ``pytest`` lines are left out (CI runs the test command).
    """
    spans = re.findall(r"`((?:torchmorph|python) [^`]+)`", README)
    # "`torchmorph mesh`" in a sentence names the command; a command line has arguments
    return [
        span
        for span in spans
        if "pytest" not in span and "pip " not in span and len(span.split()) >= 3
    ]


def test_python_examples_run_as_written(capsys):
    blocks = code_blocks("python")
    assert len(blocks) >= 2
    exec(compile(blocks[0], "README.md", "exec"), {"__name__": "readme"})
    first = capsys.readouterr().out
    match = re.fullmatch(
        r"W \(2000, 500\): 2000 targets from 500 controls; largest interpolated "
        r"move (\S+) \(controls: (\S+)\); batch \(3, 2000, 3\)\n",
        first,
    )
    assert match, first
    assert 0 < float(match[1]) <= float(match[2])  # IDW is a convex combination
    for block in blocks[1:]:
        exec(compile(block, "README.md", "exec"), {"__name__": "readme"})
    printed = capsys.readouterr().out
    controls, _, total, _, _, error = printed.split()[:6]
    assert int(controls) < int(total) == 386
    assert 0.0 < float(error) < 0.1


def test_exactly_two_setup_commands_and_ci_runs_the_test_one():
    commands = [block.strip() for block in code_blocks("bash")]
    assert len(commands) == 2
    install_and_run, test_command = commands
    assert "pip install" in install_and_run and "demos/" in install_and_run
    ci_script = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test_command in [line.strip() for line in ci_script]


def test_the_readme_lists_its_commands():
    commands = readme_commands()
    assert any(command.startswith("torchmorph mesh ") for command in commands)
    assert any(command.startswith("python demos/own_shape.py --mesh") for command in commands)
    assert any(command.startswith("python -m data_gen ") for command in commands)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A directory holding what the README's commands expect: body.stl, d.npy, demos/."""
    trimesh = pytest.importorskip("trimesh")
    directory = tmp_path_factory.mktemp("readme")
    trimesh.creation.icosphere(subdivisions=2, radius=0.5).export(directory / "body.stl")
    np.save(directory / "d.npy", np.array([0.02, 0.0, 0.01]))
    (directory / "demos").symlink_to(ROOT / "demos")
    with contextlib.suppress(ImportError):  # part.step: a box with a cylindrical hole
        write_cad(directory / "part.step")
    return directory


SLOW_DEMOS = ("python demos/fluid_wing.py", "python demos/rotating_hull.py")


def _marks(command: str):
    marks = []
    # the commands share a workspace built by meshing (torchmorph mesh, demos, data_gen)
    meshes = command.startswith(("torchmorph ", "python -m data_gen", "python demos/"))
    if command.startswith(SLOW_DEMOS) or "own_shape.py --size" in command or meshes:
        marks.append(pytest.mark.slow)
    return marks


@pytest.mark.parametrize(
    "command", [pytest.param(c, marks=_marks(c), id=c[:60]) for c in readme_commands()]
)
def test_readme_command_runs_as_printed(command, workspace, monkeypatch, capsys):
    """Commands run in README order in one directory (the mesh one writes body.vtu first)."""
    words = shlex.split(command)
    if any(word.endswith(".step") for word in words):
        pytest.importorskip("gmsh")
    elif words[:2] == ["torchmorph", "mesh"] or "own_shape.py" in command:
        pytest.importorskip("pytetwild")
    if words[0] == "torchmorph":
        if words[1] in ("info", "morph") and not (workspace / "body.vtu").exists():
            assert (
                main(["mesh", "body.stl", "--box", "1", "-o", "body.vtu", "--no-progress"])
                == EXIT_OK
            )
        monkeypatch.chdir(workspace)
        assert main(words[1:]) == EXIT_OK, capsys.readouterr().err
        return
    if "--mesh" in words and not (workspace / "body.vtu").exists():
        monkeypatch.chdir(workspace)
        assert main(["mesh", "body.stl", "--box", "1", "-o", "body.vtu"]) == EXIT_OK
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, *words[1:]],
        cwd=workspace,
        env=environment,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip(), "the command printed nothing"
