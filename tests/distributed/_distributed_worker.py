"""What each of the 2 gloo ranks of tests/distributed/test_distributed.py runs.

Every rank builds the sharded modules from the same seeded data, runs forward and
backward passes, then the same calls with data that differs between the ranks
(each rank keeps the message it raised), and saves what it computed to
``<outdir>/rank<r>.pt``; the test then compares those with the single-process modules
and the expected messages, in the test process.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from datetime import timedelta
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


def mesh_training(boundary: torch.Tensor) -> torch.Tensor:
    """Five boundary displacements spanning three directions."""
    return torch.stack(
        [boundary * k for k in (1.0, -0.5, 2.0)] + [boundary.flip(0) * 0.3, boundary.roll(5, 0)]
    )


def planar_data(seed: int = 2):
    """A 2-D linear map: 30 controls on the unit square's sides, 24 targets inside, W
    from idw_weights (rows 0-1 copy inputs 0-1), 6 training fields of rank 3."""
    from torchmorph.idw import idw_weights

    generator = torch.Generator().manual_seed(seed)
    side = torch.rand(30, generator=generator, dtype=torch.float64)
    controls = torch.stack(
        [
            torch.cat([side[:8], side.new_ones(7), side[15:23], side.new_zeros(7)]),
            torch.cat([side.new_zeros(8), side[8:15], side.new_ones(8), side[23:]]),
        ],
        1,
    )
    targets = torch.rand(24, 2, generator=generator, dtype=torch.float64) * 0.8 + 0.1
    weights = idw_weights(controls=controls, targets=targets)
    basis = torch.randn(3, 30, 2, generator=generator, dtype=torch.float64)
    mix = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    training = torch.einsum("nk,kij->nij", mix, basis)
    probe = torch.einsum("k,kij->ij", torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64), basis)
    return controls, targets, weights, training, probe


PLANAR_SPLIT = (torch.arange(0, 26, 2), torch.arange(1, 26, 2))
"""The output rows (2 copied + 24 targets) of each rank of the 2-D map: interleaved."""


class PlanarRows(torch.nn.Module):
    """A user's sharded linear map on 2-D fields: rows 0, 1 copy inputs 0, 1, rows
    2.. are ``W d``; each rank holds the rows ``output_rows`` (the sharded protocol:
    ``weights`` of its reduced rows, ``copied_rows()``, ``output_rows``)."""

    def __init__(self, weights: torch.Tensor, rows: torch.Tensor) -> None:
        super().__init__()
        copied = rows < 2
        self.register_buffer("weights", weights[rows[~copied] - 2])
        self.register_buffer("output_rows", rows)
        self.register_buffer("_copied", torch.nonzero(copied).flatten())
        self.register_buffer("_reduced", torch.nonzero(~copied).flatten())
        self._sources = rows[copied]
        self.num_global_outputs = weights.shape[0] + 2
        self.group = None

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        out = d.new_zeros(d.shape[0], self.output_rows.numel(), d.shape[-1])
        out[:, self._copied] = d[:, self._sources]
        out[:, self._reduced] = torch.einsum("ij,bjc->bic", self.weights, d)
        return out

    def copied_rows(self):
        return self._copied, self._sources


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
        "gloo",
        init_method=f"tcp://127.0.0.1:{port}",
        rank=rank,
        world_size=world,
        timeout=timedelta(seconds=60),  # a rank left waiting fails the test, not hangs it
    )
    try:
        _run(rank, outdir)
    finally:
        dist.destroy_process_group()


def _run(rank: int, outdir: str) -> None:
    results: dict[str, object] = {}
    _equivalence(rank, outdir, results)
    _mismatches(rank, outdir, results)
    _planar(rank, results)
    torch.save(results, Path(outdir) / f"rank{rank}.pt")


def _equivalence(rank: int, outdir: str, results: dict) -> None:
    """Sharded results, to compare with the single-process modules."""
    from torchmorph.distributed import (
        ShardedIDW,
        ShardedMeshMorph,
        ShardedPOD,
        gather_rows,
        save_partitioned,
        sharded_pod_basis,
    )
    from torchmorph.idw import _tree_mode as tree_mode

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
            # POD of the sharded snapshots (n = 6 fields), dense W or the adjoint
            pod = ShardedPOD(num_modes=4).fit(sharded, training(controls))
            results[f"pod/{split}/{mode}/forward"] = pod(displacements)
            if mode == "dense":
                results[f"pod/{split}/modes"] = pod.modes_
                results[f"pod/{split}/singular_values"] = pod.singular_values_
                results[f"pod/{split}/projection"] = pod.projection_
                results[f"pod/{split}/state"] = pod.state_dict()
                results[f"pod/{split}/gathered"] = pod.gather(pod(displacements))
                snapshots = sharded(training(controls))
                results[f"basis/{split}"] = sharded_pod_basis(snapshots, num_modes=4)
        # tree mode: each rank's tree on its own targets; adjoint and POD through it
        sharded = ShardedIDW(controls, targets[rows], mode="tree")
        results[f"idw/{split}/tree/gathered"] = sharded.gather(sharded(displacements), dst=None)
        results[f"idw/{split}/tree/adjoint"] = sharded.adjoint(weights[:, rows])
        pod = ShardedPOD(num_modes=4).fit(sharded, training(controls))
        results[f"pod/{split}/tree/forward"] = pod.gather(pod(displacements))
        # a tolerance with auto: each rank's sampled tree by its own pairs (threshold lowered)
        saved = tree_mode.AUTO_TREE_PAIRS
        tree_mode.AUTO_TREE_PAIRS = ((1e-5, 1),)
        sharded = ShardedIDW(controls, targets[rows], tolerance=1e-3)
        tree_mode.AUTO_TREE_PAIRS = saved
        gathered = sharded.gather(sharded(displacements), dst=None)
        results[f"idw/{split}/auto_tree/gathered"] = gathered
        results[f"idw/{split}/auto_tree/kind"] = (sharded.idw.mode, sharded.idw.error_control)

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
            pod = ShardedPOD(num_modes=3).fit(morph, mesh_training(boundary))
            results[f"{key}/pod_forward"] = pod(boundary)
            if mode == "matrix_free":
                results[f"{key}/pod_state"] = pod.state_dict()
            if layout == "interleaved" and mode == "dense":
                morph.save(Path(outdir) / "parts", out)
    # a tolerance under auto (threshold lowered): each rank's sampled tree, gathered
    saved = tree_mode.AUTO_TREE_PAIRS
    tree_mode.AUTO_TREE_PAIRS = ((1e-5, 1),)
    morph = ShardedMeshMorph(mesh, tolerance=1e-3)
    tree_mode.AUTO_TREE_PAIRS = saved
    results["mesh/auto_tree/gathered"] = morph.gather(morph(boundary), dst=None)
    results["mesh/auto_tree/kind"] = (morph.idw.mode, morph.idw.error_control)
    results["gather_batched"] = gather_rows(
        torch.full((2, 3 - rank, 2), float(rank)), torch.arange(3 - rank) * 2 + rank, 5
    )
    for run, scale in (("batched", 1.0), ("other_run", 2.0)):
        save_partitioned(
            Path(outdir) / run,
            torch.full((2, 3 - rank, 2), scale * (rank + 1)),
            torch.arange(3 - rank) * 2 + rank,
            5,
        )


def _message(call: Callable[[], object]) -> str:
    """The message of the error ``call`` raises (every case below must raise)."""
    try:
        call()
    except (ValueError, TypeError) as error:
        return f"{type(error).__name__}: {error}"
    return "no error"


def _mismatches(rank: int, outdir: str, results: dict) -> None:
    """The same calls with data that differs between the ranks: every rank must raise."""
    from torchmorph.distributed import (
        ShardedIDW,
        ShardedMeshMorph,
        ShardedPOD,
        gather_rows,
        save_partitioned,
        sharded_pod_basis,
    )
    from torchmorph.pod import PODReducer

    controls, targets, _, _ = idw_data()
    mine = targets[:23] if rank == 0 else targets[23:]
    other = int(rank == 1)
    nan_targets = mine.clone()
    if other:
        nan_targets[2, 1] = float("nan")
    cases: dict[str, Callable[[], object]] = {
        "controls_shifted": lambda: ShardedIDW(controls + 0.1 * other, mine),
        "control_fewer": lambda: ShardedIDW(controls[: 40 - other], mine),
        "dtype": lambda: ShardedIDW(
            controls.float() if other else controls, mine.float() if other else mine
        ),
        "power": lambda: ShardedIDW(controls, mine, power=2.0 if other else 4.0),
        "tolerance": lambda: ShardedIDW(
            controls, mine, coincidence_tolerance=1e-6 if other else 1e-9
        ),
        "overlapping_rows": lambda: ShardedIDW(
            controls, mine, target_rows=torch.arange(23) if not other else torch.arange(20, 28)
        ),
        "rows_on_one_rank": lambda: ShardedIDW(
            controls, mine, target_rows=torch.arange(23, 31) if other else None
        ),
        "nan_target": lambda: ShardedIDW(controls, nan_targets),
        "mode": lambda: ShardedIDW(controls, mine, mode="bogus" if other else "dense"),
        "tree_tolerance": lambda: ShardedIDW(
            controls, mine, mode="tree", tolerance=1e-3 if other else 1e-4
        ),
        "error_control": lambda: ShardedIDW(
            controls, mine, mode="tree", error_control="sampled" if other else None
        ),
        "not_a_tensor": lambda: ShardedIDW(controls, mine.tolist() if other else mine),
    }

    mesh, boundary, _ = mesh_data()
    moved = type(mesh)(mesh.points + 1e-3 * other, mesh.tets)
    cases["mesh_points"] = lambda: ShardedMeshMorph(moved)

    class FailingPlan:
        def select(self, mesh, generator=None):
            raise ValueError("plan: no face named 'inlet'")

    cases["selection"] = lambda: ShardedMeshMorph(mesh, FailingPlan())
    cases["mesh_owned_overlap"] = lambda: ShardedMeshMorph(mesh, owned_nodes=torch.arange(10))

    sharded = ShardedIDW(controls, mine, mode="dense")
    train = training(controls)
    changed = train * (1.0 + 0.01 * other)
    half = train.float() if other else train
    with_nan = train.clone()
    if other:
        with_nan[1, 4, 0] = float("inf")
    cases["pod_displacements"] = lambda: ShardedPOD(num_modes=3).fit(sharded, changed)
    cases["pod_dtype"] = lambda: ShardedPOD(num_modes=3).fit(sharded, half)
    cases["pod_num_modes"] = lambda: ShardedPOD(num_modes=3 + other).fit(sharded, train)
    cases["pod_inf"] = lambda: ShardedPOD(num_modes=3).fit(sharded, with_nan)
    morph = ShardedMeshMorph(mesh, mode="dense")
    cases["pod_reducer_on_a_shard"] = lambda: PODReducer(num_modes=3).fit(sharded, train)
    cases["basis_dim"] = lambda: sharded_pod_basis(torch.ones(4, 3 - rank, 2 + other))
    cases["pod_mesh_points_moved"] = lambda: ShardedPOD(num_modes=3).fit(
        _moved_on_rank_one(morph, other), mesh_training(boundary)
    )

    ids = torch.arange(3 - rank) * 2 + rank  # rows 0, 2, 4 and 1, 3
    field = torch.ones(3 - rank, 2)
    cases["gather_width"] = lambda: gather_rows(torch.ones(3 - rank, 2 + other), ids, 5)
    cases["gather_dtype"] = lambda: gather_rows(field.double() if other else field, ids, 5)
    cases["gather_gap"] = lambda: gather_rows(field[:1] if other else field, ids[: 3 - 2 * rank], 5)
    cases["gather_overlap"] = lambda: gather_rows(field, ids - other, 5)
    cases["gather_num_rows"] = lambda: gather_rows(field, ids, 5 + other)
    cases["save_gap"] = lambda: save_partitioned(
        Path(outdir) / "gap", field[:1] if other else field, ids[: 3 - 2 * rank], 5
    )
    for name, call in cases.items():
        results[f"error/{name}"] = _message(call)


def _moved_on_rank_one(morph, other: bool):
    """``morph`` with its reference points moved on rank 1 only (after it was built)."""
    if other:
        morph.points.add_(1e-3)
    return morph


def _planar(rank: int, results: dict) -> None:
    """2-D: a user's sharded map reduced by ShardedPOD, and ShardedIDW on 2-D points."""
    from torchmorph.distributed import ShardedIDW, ShardedPOD

    controls, targets, weights, train, probe = planar_data()
    rows = PLANAR_SPLIT[rank]
    pod = ShardedPOD(num_modes=3).fit(PlanarRows(weights, rows), train)
    results["planar/pod_forward"] = pod(probe)
    results["planar/pod_gathered"] = pod.gather(pod(probe))
    overlapping = PlanarRows(weights, PLANAR_SPLIT[0])  # rank 0's rows on both ranks
    results["error/pod_output_rows"] = _message(
        lambda: ShardedPOD(num_modes=3).fit(overlapping, train)
    )
    local = targets[rank::2]
    try:
        sharded = ShardedIDW(controls, local, target_rows=torch.arange(rank, 24, 2))
    except ValueError as error:  # the IDW module before it took 2-D points
        results["planar/idw_error"] = str(error)
        return
    results["planar/idw_forward"] = sharded(probe)
    results["planar/idw_pod_forward"] = ShardedPOD(num_modes=3).fit(sharded, train)(probe)


def training(controls: torch.Tensor) -> torch.Tensor:
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
