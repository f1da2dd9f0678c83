"""The surrogate-training demo (``demos/surrogate_training.py``) at its small size: a
network learns μ -> the cells' volumetric strain of case B's tunnel mesh from batches
morphed inside the training loop, and from a bank of meshes morphed beforehand.

The demo runs once for the module (about 10 s on one thread); each test checks one
property of its result. Its two building blocks are checked against independent
references.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("gmsh")
pytest.importorskip("matplotlib")

DEMOS = Path(__file__).resolve().parents[1] / "demos"

pytestmark = pytest.mark.slow

LOOPS = ("morph in the loop", "precomputed meshes")


def load_demo(name: str):
    spec = importlib.util.spec_from_file_location(f"demo_{name}", DEMOS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """(the demo module, its result, the output directory), run on one torch thread."""
    module = load_demo("surrogate_training")
    out = tmp_path_factory.mktemp("surrogate")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = module.main(
            ["--size", "small", "--out", str(out), "--quiet", "--steps", "400", "--batch", "8"]
            + ["--bank", "256", "--repeats", "5"]
        )
    finally:
        torch.set_num_threads(threads)
    return module, result, out


def test_the_surrogate_predicts_held_out_strains(demo):
    _, result, _ = demo
    for name in LOOPS:  # relative L2 over 64 fresh μ; V / V0 spans about [0.5, 1.4]
        assert result["held_out"][name]["relative"] < 0.03, name
        assert result["held_out"][name]["ratio_max"] < 0.03, name


def test_both_loops_train_and_report_their_rates(demo):
    _, result, _ = demo
    for name in LOOPS:
        losses = result["losses"][name]
        assert len(losses) == 400 and all(math.isfinite(value) for value in losses)
        assert sum(losses[-20:]) / 20 < 1e-2 * sum(losses[:5]) / 5, name
        assert result["batches_per_s"][name] > 0
        assert result["meshes_per_s"][name] == pytest.approx(8 * result["batches_per_s"][name])
    # the morph is timed alone, and is part of a training step of the first loop
    assert 0 < result["morph_share"] < 1
    assert result["morph_s"] > 0 and result["full_morph_s"] > 0 and result["strain_s"] > 0
    assert result["slowdown"] == pytest.approx(
        result["batches_per_s"]["precomputed meshes"] / result["batches_per_s"][LOOPS[0]]
    )


def test_the_meshes_stay_valid_and_the_pod_follows_esidw(demo):
    _, result, out = demo
    assert 0.3 < result["smallest_volume_ratio"] < 1  # the wing squeezes cells, none inverts
    assert result["pod_error"] < 1e-2
    assert result["num_modes"] >= 3  # two bendings and a twist
    assert result["figure"] == out / "surrogate_training.png"
    assert result["figure"].stat().st_size > 10_000


def test_cell_strain_of_a_uniform_scaling_is_its_cube_minus_one(demo, cube):
    module, _, _ = demo
    mesh = cube.to(dtype=torch.float64)
    strain = module.CellStrain(mesh)
    factors = torch.tensor([1.0, 1.1, 0.7], dtype=torch.float64)
    displacement = (factors[:, None, None] - 1.0) * mesh.points
    expected = (factors**3 - 1.0)[:, None].expand(-1, mesh.num_tets)
    torch.testing.assert_close(strain(displacement), expected, rtol=0, atol=1e-13)


def test_the_family_moves_the_wing_only(demo):
    module, _, _ = demo
    from torchmorph.morph import MeshMorph
    from torchmorph.paper import load_mesh

    mesh = load_mesh("fluid-wing", size="small")
    morph = MeshMorph(mesh)
    mu = torch.tensor([[0.4, 0.0, 0.0], [0.0, -0.3, 6.0]], dtype=torch.float64)
    displacement = module.tunnel_wing_family(morph, mesh)(mu)
    on_wing = torch.isin(morph.boundary_nodes, mesh.node_set("wing"))
    assert bool((displacement[:, ~on_wing] == 0).all())  # the tunnel's walls stay
    z = morph.boundary_points[on_wing, 2]
    tip = z == z.max()
    # μ1 = 0.4 m of bending s²: the tip rises by 0.4 m, the wing does not stretch along z
    torch.testing.assert_close(
        displacement[0, on_wing][tip, 1], torch.full((int(tip.sum()),), 0.4, dtype=torch.float64)
    )
    assert bool((displacement[:, on_wing, 2] == 0).all())
    # a twist keeps every section's shape: distances within the tip profile are kept
    moved = morph.boundary_points[on_wing][tip] + displacement[1, on_wing][tip]
    reference = morph.boundary_points[on_wing][tip]
    torch.testing.assert_close(torch.cdist(moved, moved), torch.cdist(reference, reference))
