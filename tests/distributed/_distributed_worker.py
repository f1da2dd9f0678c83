"""What each of the 2 gloo ranks of tests/distributed/test_distributed.py runs.

Every rank builds the sharded modules from the same seeded data, runs forward and
backward passes, and saves what it computed to ``<outdir>/rank<r>.pt``; the test
then compares those with the single-process modules, in the test process.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import torch
import torch.distributed as dist

SPLITS = {  # targets per rank: uneven, and a rank with none
    "uneven": (23, 8),
    "empty": (31, 0),
}


def idw_data(seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    controls = torch.rand(40, 3, generator=generator, dtype=torch.float64)
    targets = torch.rand(31, 3, generator=generator, dtype=torch.float64) * 0.8 + 0.1
    targets[3] = controls[5]  # one coincident target: exact interpolation, same radius
    displacements = torch.randn(2, 40, 3, generator=generator, dtype=torch.float64)
    weights = torch.randn(2, 31, 3, generator=generator, dtype=torch.float64)
    return controls, targets, displacements, weights


def mesh_data(seed: int = 1):
    from torchmorph.mesh import box_mesh

    mesh = box_mesh(4)
    generator = torch.Generator().manual_seed(seed)
    boundary = (
        torch.randn(len(mesh.boundary_nodes), 3, generator=generator, dtype=torch.float64) * 0.01
    )
    weights = torch.randn(mesh.points.shape[0], 3, generator=generator, dtype=torch.float64)
    return mesh, boundary, weights


def owned_nodes(count: int, rank: int, layout: str) -> torch.Tensor:
    """Node ids per rank: the default slices (None), interleaved, or all on rank 0."""
    if layout == "interleaved":
        return torch.arange(rank, count, 2)
    if layout == "empty":
        return torch.arange(count) if rank == 0 else torch.arange(0)
    raise ValueError(layout)


def run(rank: int, world: int, port: int, outdir: str) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    torch.set_num_threads(1)
    dist.init_process_group(
        "gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world
    )
    try:
        _run(rank, outdir)
    finally:
        dist.destroy_process_group()


def _run(rank: int, outdir: str) -> None:
    from torchmorph.distributed import (
        ShardedIDW,
        ShardedMeshMorph,
        ShardedPOD,
        gather_rows,
        save_partitioned,
    )

    results: dict[str, object] = {}
    controls, targets, displacements, weights = idw_data()
    for split, sizes in SPLITS.items():
        start = sum(sizes[:rank])
        rows = torch.arange(start, start + sizes[rank])
        for mode in ("dense", "matrix_free"):
            sharded = ShardedIDW(controls, targets[rows], mode=mode)
            out = sharded(displacements)
            results[f"idw/{split}/{mode}/forward"] = out
            results[f"idw/{split}/{mode}/rows"] = sharded.target_rows
            results[f"idw/{split}/{mode}/gathered"] = sharded.gather(out, dst=None)
            # backward through displacements, control and target positions
            d = displacements.clone().requires_grad_()
            c = controls.clone().requires_grad_()
            t = targets[rows].clone().requires_grad_()
            loss = (sharded(d, controls=c, targets=t) * weights[:, rows]).sum()
            loss.backward()
            results[f"idw/{split}/{mode}/grad_d"] = d.grad
            results[f"idw/{split}/{mode}/grad_c"] = c.grad
            results[f"idw/{split}/{mode}/grad_t"] = t.grad
        # POD of the sharded snapshots (n = 6 fields)
        pod = ShardedPOD(num_modes=4).fit(
            ShardedIDW(controls, targets[rows], mode="dense"), _training(controls)
        )
        results[f"pod/{split}/modes"] = pod.modes_
        results[f"pod/{split}/singular_values"] = pod.singular_values_
        results[f"pod/{split}/projection"] = pod.projection_
        results[f"pod/{split}/forward"] = pod(displacements)

    mesh, boundary, node_weights = mesh_data()
    for layout in ("default", "interleaved", "empty"):
        owned = None if layout == "default" else owned_nodes(mesh.points.shape[0], rank, layout)
        for mode in ("dense", "matrix_free"):
            morph = ShardedMeshMorph(mesh, owned_nodes=owned, mode=mode)
            out = morph(boundary)
            key = f"mesh/{layout}/{mode}"
            results[f"{key}/owned"] = morph.owned_nodes
            results[f"{key}/forward"] = out
            results[f"{key}/gathered"] = morph.gather(out)
            d = boundary.clone().requires_grad_()
            points = mesh.points.clone().requires_grad_()
            loss = (morph(d, points=points) * node_weights[morph.owned_nodes]).sum()
            loss.backward()
            results[f"{key}/grad_d"] = d.grad
            results[f"{key}/grad_points"] = points.grad
            if mode == "dense":
                training = torch.stack(
                    [boundary * k for k in (1.0, -0.5, 2.0)]
                    + [boundary.flip(0) * 0.3, boundary.roll(5, 0)]
                )
                pod = ShardedPOD(num_modes=3).fit(morph, training)
                results[f"{key}/pod_forward"] = pod(boundary)
            if layout == "interleaved" and mode == "dense":
                morph.save(Path(outdir) / "parts", out)
    try:
        ShardedMeshMorph(mesh, owned_nodes=torch.arange(10))
    except ValueError as error:
        results["partition_error"] = str(error)
    results["gather_batched"] = gather_rows(
        torch.full((2, 3 - rank, 2), float(rank)), torch.arange(3 - rank) * 2 + rank, 5
    )
    save_partitioned(
        Path(outdir) / "batched",
        torch.full((2, 3 - rank, 2), float(rank + 1)),
        torch.arange(3 - rank) * 2 + rank,
        5,
    )
    torch.save(results, Path(outdir) / f"rank{rank}.pt")


def _training(controls: torch.Tensor) -> torch.Tensor:
    """Six control displacements: smooth functions of the positions."""
    x = controls
    return torch.stack(
        [
            x,
            x.square(),
            torch.sin(3 * x),
            x.roll(1, 1) * x,
            torch.cos(2 * x) - 1,
            x.sum(1, keepdim=True).expand(-1, 3) * x,
        ]
    )


if __name__ == "__main__":  # torchrun tests/distributed/_distributed_worker.py OUTDIR
    dist.init_process_group("gloo")
    try:
        _run(dist.get_rank(), sys.argv[1])
    finally:
        dist.destroy_process_group()
