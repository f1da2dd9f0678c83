"""Argument checks shared by every entry point: half precision is refused everywhere."""

from __future__ import annotations

import pytest
import torch

from torchmorph import IDW, MeshMorph, TetMesh
from torchmorph.mesh import box_mesh
from torchmorph.mesh.quality import edge_ratio, signed_volumes
from torchmorph.pod import pod_basis
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


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_check_finite_counts_nan_and_inf_and_passes_the_extreme_finite_values(device, dtype):
    from torchmorph._checks import check_finite

    largest = torch.finfo(dtype).max
    values = torch.tensor([[largest, -largest, 1.0], [0.0, -0.0, 5e-45]], dtype=dtype)
    check_finite(values.to(device), "values")  # the hot path's maximum is finite here
    for bad, count in (
        ([float("nan")], 1),
        ([float("inf"), float("-inf")], 2),
        ([float("nan"), float("inf"), float("nan")], 3),
    ):
        broken = values.flatten().clone()
        broken[: len(bad)] = torch.tensor(bad, dtype=dtype)
        with pytest.raises(ValueError, match=f"values holds {count} NaN or infinite"):
            check_finite(broken.to(device), "values")


@pytest.mark.parametrize("device", DEVICES)
def test_idw_points_with_nan_or_inf_are_reported_by_name(device):
    from torchmorph import idw_apply

    generator = torch.Generator().manual_seed(0)
    controls = torch.rand(30, 3, generator=generator, dtype=torch.float64)
    targets = torch.rand(40, 3, generator=generator, dtype=torch.float64)
    displacements = torch.rand(30, 3, generator=generator, dtype=torch.float64)
    for name, index, value in (
        ("controls", (4, 2), float("nan")),
        ("controls", (0, 0), float("-inf")),
        ("targets", (39, 1), float("inf")),
        ("targets", (7, 0), float("nan")),
    ):
        points = {"controls": controls.clone(), "targets": targets.clone()}
        points[name][index] = value
        with pytest.raises(ValueError, match=f"{name} holds 1 NaN or infinite"):
            idw_apply(
                controls=points["controls"].to(device),
                targets=points["targets"].to(device),
                displacements=displacements.to(device),
            )
    # the largest finite coordinates are not mistaken for infinite ones
    huge = torch.finfo(torch.float64).max / 4
    moved = idw_apply(
        controls=(controls * huge).to(device),
        targets=(targets * huge).to(device),
        displacements=displacements.to(device),
    )
    expected = idw_apply(controls=controls, targets=targets, displacements=displacements)
    torch.testing.assert_close(moved.cpu(), expected)
