"""The README's code runs as written, and CI runs the README's test command."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def code_blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README, flags=re.DOTALL)


def test_python_examples_run_as_written(capsys):
    blocks = code_blocks("python")
    assert len(blocks) >= 2
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {"__name__": "readme"})  # noqa: S102
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
