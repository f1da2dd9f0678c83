"""Sharded morph of the fluid wing (the paper's case B) on several processes.

    torchrun --standalone --nproc-per-node 2 demos/distributed_morph.py --size small
    torchrun --standalone --nproc-per-node 2 demos/distributed_morph.py --size large

Every rank loads the same mesh (rank 0 builds it into the cache first), the ESIDW
control points of case B are selected on rank 0 and broadcast, and each rank builds
the matrix-free IDW of its slice of the nodes only (ShardedMeshMorph). The wing is
bent by the case's displacement at μ*; every rank morphs its nodes. Rank 0 then
morphs the whole mesh alone (the single-process cost, one thread like each rank),
checks the gathered sharded field against it on a sample of nodes, and reports the
speed-up and the speed-up per rank (parallel efficiency). Uses gloo on the CPU
(one thread per rank) and NCCL with one GPU per rank when CUDA is available.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.distributed as dist

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import data_gen
from torchmorph import IDW
from torchmorph.distributed import ShardedMeshMorph
from torchmorph.paper import get_case


def boundary_displacement(mesh, spec, mu: float, device, dtype) -> torch.Tensor:
    """Case B's prescribed displacement at ``mu`` on every boundary node (the moving sets
    bent, the rest fixed), rows ordered as ``mesh.boundary_nodes``."""
    boundary = mesh.boundary_nodes
    moving = torch.cat([mesh.node_sets[name] for name in spec.moving]).unique()
    rows = torch.searchsorted(boundary, moving)
    values = torch.zeros(boundary.numel(), 3, dtype=torch.float64)
    values[rows] = spec.displacement(mesh.points[moving].double(), torch.tensor(mu))
    return values.to(device, dtype)


def timed(function, repeats: int, device) -> float:
    times = []
    for _ in range(repeats):
        dist.barrier()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        function()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        dist.barrier()  # the time of the slowest rank
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--size",
        choices=data_gen.SIZES,
        default="large",
        help="fluid-wing mesh size (default: %(default)s, ~10^6 nodes)",
    )
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument("--repeats", type=int, default=3, help="timed morphs (median)")
    parser.add_argument(
        "--sample", type=int, default=2000, help="nodes checked against the single-process morph"
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="largest relative difference allowed (default 1e-12 in float64, 1e-5 in float32)",
    )
    args = parser.parse_args(argv)

    cuda = torch.cuda.is_available()
    dist.init_process_group("nccl" if cuda else "gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    if cuda:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", rank)))
        torch.cuda.set_device(device)
    else:
        device = torch.device("cpu")
        torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    tolerance = args.tolerance or (1e-12 if dtype == torch.float64 else 1e-5)
    say = print if rank == 0 else (lambda *a, **k: None)
    try:
        spec = get_case("B")
        if rank == 0:  # build into the cache once; the other ranks then load it
            data_gen.fluid_wing(args.size, verbose=True)
        dist.barrier()
        mesh = data_gen.fluid_wing(args.size)
        if mesh.points.device != device or mesh.points.dtype != dtype:
            mesh = type(mesh)(mesh.points.to(device, dtype), mesh.tets.to(device), mesh.node_sets)
        say(
            f"fluid wing ({args.size}): {mesh.points.shape[0]:,} nodes, "
            f"{len(mesh.boundary_nodes):,} boundary; {world} ranks on {device.type}"
        )

        start = time.perf_counter()
        morph = ShardedMeshMorph(
            mesh, spec.plan(), mode="matrix_free", generator=torch.Generator().manual_seed(0)
        )
        setup = time.perf_counter() - start
        say(
            f"selection (rank 0) and set-up: {setup:.2f} s; {morph.num_controls:,} control "
            f"points; rank 0 owns {morph.num_owned:,} nodes"
        )
        d_b = boundary_displacement(mesh, spec, spec.mu_star, device, dtype)
        outputs = [morph(d_b)]  # warm-up
        sharded_seconds = timed(lambda: outputs.append(morph(d_b)), args.repeats, device)
        field = morph.gather(outputs[-1])

        # the single-process morph on rank 0: every interior node from the same controls
        single_seconds = torch.zeros((), dtype=torch.float64, device=device)
        if rank == 0:
            idw = IDW(
                mesh.points[morph.control_nodes],
                mesh.points[mesh.interior_nodes],
                mode="matrix_free",
            )
            controls = morph.controls_from_boundary(d_b)
            idw(controls)
            times = []
            for _ in range(args.repeats):
                begin = time.perf_counter()
                interior = idw(controls)
                if cuda:
                    torch.cuda.synchronize(device)
                times.append(time.perf_counter() - begin)
            single_seconds.fill_(statistics.median(times))
            reference = torch.zeros_like(field)
            reference[mesh.boundary_nodes] = d_b
            reference[mesh.interior_nodes] = interior
            generator = torch.Generator().manual_seed(1)
            sample = torch.randperm(mesh.points.shape[0], generator=generator)[: args.sample]
            sample = sample.to(device)
            scale = reference.abs().max()
            error = float((field[sample] - reference[sample]).abs().max() / scale)
            say(
                f"check on {sample.numel():,} sampled nodes: max |sharded - single| / max |d| "
                f"= {error:.2e} (tolerance {tolerance:g})"
            )
            if not error <= tolerance:
                raise RuntimeError(f"sharded and single-process morphs differ: {error:.2e}")
        dist.broadcast(single_seconds, src=0)
        single = float(single_seconds)
        speedup = single / sharded_seconds
        say("\n| ranks | morph (s) | speed-up | speed-up per rank |\n|---|---|---|---|")
        say(f"| 1 (single process) | {single:.3f} | 1.00 | 1.00 |")
        say(f"| {world} | {sharded_seconds:.3f} | {speedup:.2f} | {speedup / world:.2f} |")
    finally:
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
