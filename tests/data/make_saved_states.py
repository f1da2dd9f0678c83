"""Writes ``saved_states_0_1_0.pt``: state dicts of torchmorph 0.1.0's modules, kept so that
the tests can check that a state saved by that release still loads (``test_saved_states``).

This script was run once, with the 0.1.0 layout (before the package was split into
subpackages); running it again with a later version would overwrite the fixture with that
version's states, which tests nothing. It is kept to show how the file was made.
"""

from pathlib import Path

import torch

from torchmorph import IDW, MeshMorph, PODReducer, box_mesh
from torchmorph.selection import SelectionPlan


def main() -> None:
    generator = torch.Generator().manual_seed(7)
    controls = torch.rand(40, 3, generator=generator, dtype=torch.float64)
    targets = torch.rand(60, 3, generator=generator, dtype=torch.float64)
    d = 0.01 * torch.randn(40, 3, generator=generator, dtype=torch.float64)

    dense = IDW(controls, targets, mode="dense")
    free = IDW(controls, targets, mode="matrix_free")

    mesh = box_mesh(4)
    faces = ["x0", "x1", "y0", "y1", "z0", "z1"]
    plan = SelectionPlan(dict.fromkeys(faces, 0.3))
    morph = MeshMorph(mesh, plan, mode="dense", generator=torch.Generator().manual_seed(0))
    boundary = morph.boundary_displacement(
        "z1", lambda p: torch.stack([0 * p[:, 0], 0 * p[:, 0], 0.1 * p[:, 0] * p[:, 1]], 1)
    )
    parameters = torch.linspace(0.5, 2.0, 6, dtype=torch.float64)
    reducer = PODReducer(energy_tolerance=1e-8).fit(morph, parameters[:, None, None] * boundary)

    states = {
        "inputs": {"controls": controls, "targets": targets, "d": d, "boundary": boundary},
        "idw_dense": dense.state_dict(),
        "idw_matrix_free": free.state_dict(),
        "mesh_morph": morph.state_dict(),
        "pod_reducer": reducer.state_dict(),
        "expected": {
            "idw": dense(d),
            "mesh_morph": morph(boundary),
            "pod_reducer": reducer(1.3 * boundary),
        },
    }
    torch.save(states, Path(__file__).with_name("saved_states_0_1_0.pt"))


if __name__ == "__main__":
    main()
