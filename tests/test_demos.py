"""The demo scripts run end to end on the small meshes and report sane numbers.

The meshes come from the default cache (built once by the first run, reused after);
outputs go to a temporary directory.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

pytest.importorskip("gmsh")
pytest.importorskip("matplotlib")

DEMOS = Path(__file__).resolve().parents[1] / "demos"

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]


def load_demo(name: str):
    spec = importlib.util.spec_from_file_location(f"demo_{name}", DEMOS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_demo(name: str, out: Path):
    return load_demo(name).main(["--size", "small", "--out", str(out), "--quiet", "--repeats", "1"])


def check_common(result, out: Path, png: str) -> None:
    for row in result.rows:
        assert row.inverted == 0, f"{row.method}: {row.inverted} inverted tets at mu*"
        assert row.online_s > 0
        assert row.max_q >= row.mean_q >= 1.0
        assert 0 < row.controls <= result.mesh["boundary"]
        if row.method == "IDW":
            assert row.error is None and row.controls == result.mesh["boundary"]
        else:
            assert 0.0 <= row.error < 1.0, f"{row.method}: error {row.error}"
        if row.method.startswith("POD"):
            assert row.modes >= 1 and row.offline_s >= row.fit_s > 0
    assert result.mesh["interior"] + result.mesh["boundary"] == result.mesh["nodes"]
    assert result.quality_deformed["IDW"]["num_inverted"] == 0
    for name in ("reference.vtu", "deformed_idw.vtu", "deformed_esidw.vtu", png, "results.json"):
        path = out / name
        assert path.is_file() and path.stat().st_size > 0, name
        assert str(path) in result.files
    saved = json.loads((out / "results.json").read_text())
    assert [row["method"] for row in saved["rows"]] == [row.method for row in result.rows]
    assert type(result).from_dict(saved).rows == result.rows


def test_structural_wing(tmp_path):
    result = run_demo("structural_wing", tmp_path)
    check_common(result, tmp_path, "wing.png")
    assert [row.method for row in result.rows] == ["IDW", "SIDW", "ESIDW", "POD-IDW", "POD-ESIDW"]
    sidw, esidw = result.row("SIDW"), result.row("ESIDW")
    assert 0 < esidw.error < sidw.error
    assert sidw.controls < esidw.controls < result.row("IDW").controls
    assert result.row("POD-IDW").error < 1e-6
    assert result.row("POD-IDW").modes == 1  # δy = μ z² is linear in μ
    assert result.row("POD-ESIDW").error == pytest.approx(esidw.error, rel=1e-6)


def test_fluid_wing(tmp_path):
    result = run_demo("fluid_wing", tmp_path)
    check_common(result, tmp_path, "fluid-wing.png")
    assert [row.method for row in result.rows] == ["IDW", "ESIDW", "POD-IDW", "POD-ESIDW"]
    assert result.row("POD-IDW").error < 1e-6
    assert result.row("ESIDW").controls < result.row("IDW").controls


def test_rotating_hull(tmp_path):
    result = run_demo("rotating_hull", tmp_path)
    check_common(result, tmp_path, "hull.png")
    methods = [row.method for row in result.rows]
    assert methods == [
        "IDW",
        "ESIDW",
        "POD-IDW",
        "POD-IDW (1 mode)",
        "POD-IDW (2 modes)",
        "POD-ESIDW",
        "POD-ESIDW (1 mode)",
        "POD-ESIDW (2 modes)",
    ]
    # a rigid rotation is exactly a two-dimensional family: sin μ and 1 - cos μ parts
    assert result.row("POD-IDW (2 modes)").error < 1e-6
    assert result.row("POD-IDW").modes == 2
    one_mode = result.row("POD-IDW (1 mode)")
    low, high = one_mode.error_range
    assert 0 <= low <= one_mode.error <= high < 1


def test_sensitivity(tmp_path):
    results = load_demo("sensitivity").main(
        ["--size", "small", "--out", str(tmp_path), "--quiet", "--repeats", "1"]
    )
    for name in (
        "wing_radius.png",
        "wing_factor.png",
        "fluid_wing_radius.png",
        "hull_radius.png",
        "hull_angle.png",
        "spectra.png",
        "sensitivity.json",
    ):
        assert (tmp_path / name).stat().st_size > 0, name
    wing = results["cases"]["wing"]
    sidw = [p for p in wing["radius"] if not p["enrich"]]
    assert sidw[0]["controls"] > sidw[-1]["controls"]  # fewer controls as R grows
    assert all(0 <= p["error"] < 1 for p in wing["radius"])
    assert len(wing["factor"]) == 4
    for case in ("wing", "fluid-wing", "hull"):
        spectrum = results["cases"][case]["spectra"]["POD-IDW"]
        assert spectrum[0] == 1.0 and all(0 <= s <= 1 for s in spectrum)
    angle = results["cases"]["hull"]["angle"]
    assert max(angle["error"]["POD-IDW, 2 modes"]) < 1e-6
    assert len(angle["mu"]) == 36
