"""demos/distributed_morph.py under torchrun: 2 gloo ranks on the small fluid wing."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_distributed_demo_small(tmp_path):
    pytest.importorskip("gmsh")
    environment = {
        **os.environ,
        "TORCHMORPH_CACHE": str(tmp_path / "meshes"),
        "OMP_NUM_THREADS": "1",
    }
    completed = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc-per-node",
            "2",
            str(ROOT / "demos" / "distributed_morph.py"),
            "--size",
            "small",
            "--repeats",
            "1",
        ],
        cwd=tmp_path,
        env=environment,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert completed.returncode == 0, completed.stdout[-3000:] + completed.stderr[-3000:]
    out = completed.stdout
    assert "2 ranks on cpu" in out
    assert "check on 2,000 sampled nodes" in out and "(tolerance 1e-12)" in out
    assert "| 2 | " in out and "| 1 (single process) |" in out
