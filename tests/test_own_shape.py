"""The own-shape demo: a car-like STL meshed in a tunnel, morphed by IDW and ESIDW, written."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from torchmorph.mesh.io import read_mesh

pytest.importorskip("pytetwild")
pytest.importorskip("trimesh")
pytest.importorskip("matplotlib")

DEMO = Path(__file__).resolve().parents[1] / "demos" / "own_shape.py"


def load_demo():
    spec = importlib.util.spec_from_file_location("demo_own_shape", DEMO)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_own_shape_end_to_end(tmp_path, one_thread):
    demo = load_demo()
    result = demo.main(["--size", "small", "--out", str(tmp_path), "--quiet"])
    mesh, body = result["mesh"], result["body"]
    assert body == "car"
    assert {"car", "car_edges", "car_patch0", "wall_x0", "wall_z1"} <= set(mesh.node_sets)
    idw, esidw = result["results"]["IDW"], result["results"]["ESIDW"]
    assert idw["controls"] == mesh.boundary_nodes.numel() > esidw["controls"]
    assert idw["num_inverted"] == esidw["num_inverted"] == 0
    assert idw["error"] == 0.0 and 0.0 < esidw["error"] < 0.5
    for path in result["files"]:
        assert path.is_file() and path.stat().st_size > 0
    written, point_data, _ = read_mesh(tmp_path / "reference.vtu", return_data=True)
    assert set(written.node_sets) == set(mesh.node_sets)
    assert int(point_data["control_point"].sum()) == esidw["controls"]
    # the body moved exactly as prescribed: its lowest nodes stay, its top rises by mu * height
    points = mesh.points[mesh.node_set("car")]
    moved = points + point_data["displacement"][mesh.node_set("car")]
    height = points[:, 2].max() - points[:, 2].min()
    assert float(moved[:, 2].max() - moved[:, 2].min()) == pytest.approx(1.1 * float(height))
    assert (tmp_path / "car.stl").is_file()
