"""The optimisation and batched-morph demos run end to end on the small meshes.

demos/shape_optimisation.py must converge (the objective falls by orders of
magnitude, the tip reaches its target) with no inverted tet, and
demos/batched_morph.py must give the same numbers batched, looped and vmapped, and
train its network through the morph. Meshes come from the default cache (built by
the first run); outputs go to a temporary directory.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest

pytest.importorskip("gmsh")
pytest.importorskip("matplotlib")

DEMOS = Path(__file__).resolve().parents[1] / "demos"

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]


def load_demo(name: str):
    spec = importlib.util.spec_from_file_location(f"demo_{name}", DEMOS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_shape_optimisation_converges_to_a_valid_wing(tmp_path):
    result = load_demo("shape_optimisation").main(
        ["--size", "small", "--out", str(tmp_path), "--quiet", "--repeats", "3"]
    )
    assert result["objective_final"] < 1e-5 * result["objective_initial"]
    history = result["history"].objective
    assert all(math.isfinite(value) for value in history)
    # the targets: tip deflection 1 m, tip twist 5 degrees
    assert abs(result["deflection"] - 1.0) < 2e-3
    assert abs(result["twist"] - 5.0) < 2e-2
    # every tet valid, in the reduced morph and in the full ESIDW morph at the optimum
    assert result["inverted"] == 0 and result["full_inverted"] == 0
    assert result["min_volume_ratio"] > 0 and result["full_min_volume_ratio"] > 0
    assert abs(result["full_deflection"] - result["deflection"]) < 1e-3
    assert result["pod_error"] < 1e-3
    # without the barrier the same targets are met by a bending that inverts tets
    assert result["unconstrained_inverted"] > 0
    for costs in result["costs_s"].values():
        assert costs["morph"] > 0 and costs["objective"] > 0
    assert result["figure"].is_file() and result["figure"].stat().st_size > 10_000


def test_batched_morph_equals_looped_and_trains_through_the_morph(tmp_path):
    result = load_demo("batched_morph").main(
        [
            "--size",
            "small",
            "--out",
            str(tmp_path),
            "--quiet",
            "--batch",
            "300",
            "--loop",
            "5",
            "--repeats",
            "1",
            "--train-steps",
            "200",
            "--train-batch",
            "64",
        ]
    )
    assert result["looped_error"] < 1e-12
    assert result["vmap_error"] < 1e-12
    assert result["pod_error"] < 1e-10  # two POD modes span the rotation exactly
    assert result["inverted_angles"] == 0 and result["min_volume_ratio"] > 0
    for rates in result["rates"].values():
        assert all(rate > 0 for key, rate in rates.items() if key != "batched_s")
    losses = result["losses"]
    assert losses[-1] < 1e-2 * losses[0]
    assert result["test_error"] < 2e-2 and result["test_error_idw"] < 2e-2
    assert result["figure"].is_file() and result["figure"].stat().st_size > 10_000
