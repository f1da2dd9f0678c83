"""Parametrized displacement families and the morphs they drive, shared by the gradient and
torch.func tests (tests/idw/test_gradients.py, tests/idw/test_func.py)."""

from __future__ import annotations

import torch

from torchmorph.idw import IDW
from torchmorph.mesh import box_mesh
from torchmorph.morph import MeshMorph
from torchmorph.pod import PODReducer
from torchmorph.selection import SelectionPlan

F64 = torch.float64
FACES = ("x0", "x1", "y0", "y1", "z0", "z1")
KINDS = (
    "idw-dense",
    "idw-matrix-free",
    "morph-dense",
    "morph-matrix-free",
    "morph-selective",
    "pod",
)


def vector_family(points: torch.Tensor):
    """μ (P=3,) or (B, 3) -> displacement of ``points``, (n, 3) or (B, n, 3); nonlinear in μ."""
    x, y, z = points.unbind(-1)

    def family(mu: torch.Tensor) -> torch.Tensor:
        a, b, c = (mu[..., k, None] for k in range(3))
        dx = a * z * z + 0.1 * torch.sin(c) * y
        dy = b * z**3 * x
        dz = 0.1 * (torch.cos(c) - 1.0) * x * y + 0.05 * a * b * z
        return torch.stack([dx, dy, dz], -1)

    return family


def scalar_family(points: torch.Tensor):
    """μ () or (B,) -> displacement: the vector family along a line of parameter space."""
    family = vector_family(points)
    return lambda mu: family(torch.stack([mu, 0.5 * mu, 2.0 * mu], -1))


def build(kind: str, *, idw_seed: int, num_controls: int, num_targets: int):
    """(morph, reference points of its inputs, reference points of its outputs).

    The IDW kinds morph ``num_controls`` random controls onto ``num_targets`` random
    targets drawn from a generator seeded with ``idw_seed``; the others morph
    ``box_mesh(3)``.
    """
    if kind.startswith("idw"):
        generator = torch.Generator().manual_seed(idw_seed)
        controls = torch.rand(num_controls, 3, generator=generator, dtype=F64)
        targets = torch.rand(num_targets, 3, generator=generator, dtype=F64)
        mode = "dense" if kind == "idw-dense" else "matrix_free"
        return IDW(controls, targets, mode=mode, block_bytes=2000), controls, targets
    cube = box_mesh(3)
    if kind == "morph-selective":
        morph = MeshMorph(
            cube,
            SelectionPlan(dict.fromkeys(FACES, 0.5)),
            generator=torch.Generator().manual_seed(0),
            mode="dense",
        )
    else:
        morph = MeshMorph(cube, mode="matrix_free" if kind == "morph-matrix-free" else "dense")
    if kind == "pod":
        training = torch.rand(25, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
        reducer = PODReducer(energy_tolerance=1e-10)
        reducer.fit(morph, family=vector_family(morph.boundary_points), parameters=training)
        return reducer, morph.boundary_points, morph.points
    return morph, morph.boundary_points, morph.points
