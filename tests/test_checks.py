"""Argument checks shared by every entry point: half precision is refused everywhere."""

from __future__ import annotations

import pytest
import torch

from torchmorph import IDW, MeshMorph, TetMesh
from torchmorph.mesh import box_mesh
from torchmorph.pod import pod_basis
from torchmorph.quality import edge_ratio, signed_volumes
from torchmorph.selection import select_control_points

HALF = [torch.float16, torch.bfloat16]


@pytest.mark.parametrize("dtype", HALF)
def test_half_precision_is_refused_with_the_argument_named(dtype):
    cube = box_mesh(2)
    points = cube.points.to(dtype)
    morph = MeshMorph(cube)
    idw = IDW(cube.points[:5], cube.points[5:9])
    calls = {
        "points": lambda: TetMesh(points, cube.tets),
        "controls": lambda: IDW(points[:5], points[5:9]),
        "displacements": lambda: idw(torch.zeros(5, 3, dtype=dtype)),
        "boundary_displacement": lambda: morph(torch.zeros(morph.num_boundary, 3, dtype=dtype)),
        "displacement": lambda: cube.deformed(torch.zeros(cube.num_nodes, 3, dtype=dtype)),
        "snapshots": lambda: pod_basis(torch.ones(2, 4, 3, dtype=dtype)),
    }
    for name, call in calls.items():
        with pytest.raises(
            ValueError,
            match=rf"^{name} has dtype {dtype}: half precision is "
            r"not supported",
        ):
            call()
    with pytest.raises(ValueError, match=rf"^points has dtype {dtype}: half precision"):
        select_control_points(points, 0.3)
    for function in (signed_volumes, edge_ratio):
        with pytest.raises(ValueError, match=rf"^points has dtype {dtype}: half precision"):
            function(points, cube.tets)


def test_float32_and_float64_are_accepted():
    cube = box_mesh(2)
    for dtype in (torch.float32, torch.float64):
        assert signed_volumes(cube.points.to(dtype), cube.tets).dtype == dtype
