"""States saved by torchmorph 0.1.0 (before the package was split into subpackages) load
into today's modules and give the same results."""

from pathlib import Path

import pytest
import torch

from torchmorph import IDW, MeshMorph, PODReducer, box_mesh

SAVED = Path(__file__).with_name("data") / "saved_states_0_1_0.pt"


@pytest.fixture(scope="module")
def saved():
    return torch.load(SAVED, weights_only=True)


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize("saved_as", ["idw_dense", "idw_matrix_free"])
def test_idw_state_of_0_1_0_loads(saved, mode, saved_as):
    inputs = saved["inputs"]
    # built on other points: the geometry comes from the state
    idw = IDW(inputs["controls"] + 1, inputs["targets"] * 2, mode=mode)
    idw.load_state_dict(saved[saved_as])
    torch.testing.assert_close(idw(inputs["d"]), saved["expected"]["idw"], rtol=0, atol=1e-15)


def test_mesh_morph_state_of_0_1_0_loads(saved):
    morph = MeshMorph(box_mesh(2), mode="dense")
    morph.load_state_dict(saved["mesh_morph"])
    assert morph.num_nodes == 125 and morph.num_controls == 49
    torch.testing.assert_close(
        morph(saved["inputs"]["boundary"]), saved["expected"]["mesh_morph"], rtol=0, atol=1e-15
    )


def test_mesh_morph_state_of_0_1_0_is_an_idw_morph(saved):
    morph = MeshMorph(box_mesh(2), mode="dense")
    morph.load_state_dict(saved["mesh_morph"])
    assert morph.method == "idw" and morph.state_dict()["_extra_state"]["method"] == "idw"
    with pytest.raises(ValueError, match="method: the state was saved with method='idw'"):
        MeshMorph(box_mesh(2), method="rbf").load_state_dict(saved["mesh_morph"])


def test_pod_reducer_state_of_0_1_0_loads(saved):
    with pytest.raises(ValueError, match="energy_tolerance: the state was saved with"):
        PODReducer().load_state_dict(saved["pod_reducer"])  # the load rule: same hyper-parameters
    reducer = PODReducer(energy_tolerance=1e-8)
    reducer.load_state_dict(saved["pod_reducer"])
    assert reducer.is_fitted and reducer.energy_tolerance == 1e-8
    torch.testing.assert_close(
        reducer(1.3 * saved["inputs"]["boundary"]),
        saved["expected"]["pod_reducer"],
        rtol=0,
        atol=1e-15,
    )


@pytest.mark.parametrize(
    ("old", "new", "name"),
    [
        ("torchmorph.quality", "torchmorph.mesh.quality", "edge_ratio"),
        ("torchmorph.quality", "torchmorph.mesh.norms", "mass_matrix"),
        ("torchmorph.io", "torchmorph.mesh.io", "read_mesh"),
        ("torchmorph.pod_functional", "torchmorph.pod.functional", "pod_basis"),
    ],
)
def test_modules_of_0_1_0_import_with_a_deprecation_warning(old, new, name):
    import importlib
    import sys

    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=f"{old} moved to .*{new}"):
        module = importlib.import_module(old)
    assert getattr(module, name) is getattr(importlib.import_module(new), name)
    assert name in module.__all__
