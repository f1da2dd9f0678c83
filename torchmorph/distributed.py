"""Sharded IDW, mesh morph and POD on ``torch.distributed`` (gloo on the CPU, NCCL on GPUs).

A mesh too large for one process is partitioned: each rank owns a slice of the
nodes (its partition of the mesh). The control points and their displacements are
small (the boundary, or the selected part of it) and are replicated on every rank;
each rank assembles only its own rows of W (dense, or matrix-free through
:func:`torchmorph.idw.idw_apply`), so memory and work per rank are
O(N_owned · N_c). The forward pass returns the rank's own rows: no communication.

Launch with ``torchrun`` (or ``torch.multiprocessing``) and call
``torch.distributed.init_process_group`` first::

    dist.init_process_group("gloo")            # "nccl" with one GPU per rank
    morph = ShardedMeshMorph(mesh, plan)       # every rank: the same mesh and plan
    local = morph(boundary_displacement)       # (N_owned, 3): rows morph.owned_nodes
    full = morph.gather(local)                 # (N, 3) on rank 0, None elsewhere

What the ranks exchange
-----------------------
* Building a module: the global bounding box of the targets (two all-reduces of
  three numbers; it sets the coincidence radius exactly as the single-process
  module does), the ranks' target counts, the selected control points (a
  broadcast from rank 0) and, for a mesh, one check that the owned nodes
  partition the mesh (an all-reduce of N integers).
* Backward: one all-reduce of the gradients to the replicated inputs
  (displacements, moved control or mesh positions).
* :class:`ShardedPOD` fit: one all-gather of an n × n triangle per rank and one
  all-reduce of the online matrix; its online phase is local.
* :func:`gather_rows` / :func:`save_partitioned`: only when asked.

Boundary data known only on the ranks that own the boundary nodes is replicated
with ``gather_rows(values, rows, N_b, dst=None)`` (an all-gather; not
differentiable) before the forward pass.

Autograd
--------
Replicated inputs pass through :func:`replicate`, a custom autograd function that
is the identity forward and all-reduces (sums) the gradients backward: when every
rank backpropagates its part of a loss that is a sum over the nodes (its own
nodes' terms), every rank then holds the gradient of the total loss — the
single-process gradient — so an optimiser step on any rank takes the same step.
``torch.distributed.nn.functional.all_reduce`` is not used: it sums in the forward
pass as well (applied to a replicated input it would multiply it by the world
size), and one function over all replicated inputs issues one collective per
backward pass in a fixed order, whatever each rank's graph looks like.

Caveats: every rank must call ``backward`` (a rank with no nodes too: its output
is empty but connected to the inputs); a loss term on the replicated inputs
themselves (a regulariser on the displacement) must be added on one rank only,
or it is counted once per rank; replicated inputs must require grad on every
rank alike.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import torch.distributed as dist
from torch import Tensor, nn

from ._atomic import atomic_output
from ._checks import check_vectors
from .idw import DEFAULT_COINCIDENCE_TOLERANCE, IDW, Implementation, Mode
from .mesh import TetMesh
from .pod import (
    _check_energy_tolerance,
    _check_num_modes,
    _idw_transpose_apply,
    _num_modes_for_energy,
    _numerical_rank,
)

if TYPE_CHECKING:
    from .selection import SelectionPlan

__all__ = [
    "ShardedIDW",
    "ShardedMeshMorph",
    "ShardedPOD",
    "gather_rows",
    "load_partitioned",
    "replicate",
    "save_partitioned",
    "shard_rows",
    "sharded_pod_basis",
]


# --------------------------------------------------------------------------- #
# process group helpers
# --------------------------------------------------------------------------- #
def _group_info(group) -> tuple[int, int]:
    """(rank, world size) in ``group``, with a clear error when there is no process group."""
    if not (dist.is_available() and dist.is_initialized()):
        raise RuntimeError("torch.distributed is not initialized: call "
                           "torch.distributed.init_process_group first (or launch with torchrun)")
    return dist.get_rank(group), dist.get_world_size(group)


def _comm_device(group, like: Tensor) -> torch.device:
    """The device collectives run on: the current CUDA device for NCCL, else the CPU
    (gloo, whatever device ``like`` lives on)."""
    del like
    if dist.get_backend(group) == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def shard_rows(count: int, *, rank: int | None = None, world_size: int | None = None,
               group=None) -> slice:
    """The contiguous slice of ``count`` rows that ``rank`` owns.

    Rows are split as evenly as possible: the first ``count % world_size`` ranks own
    one row more (``numpy.array_split``'s rule). Ranks past ``count`` own none.

    Parameters
    ----------
    count : int
        Number of rows to split (targets, or mesh nodes).
    rank, world_size : int, optional
        Default: this process's rank and the world size of ``group``.
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise ValueError(f"count must be a non-negative integer, got {count!r}")
    if rank is None or world_size is None:
        own_rank, own_world = _group_info(group)
        rank = own_rank if rank is None else rank
        world_size = own_world if world_size is None else world_size
    if not (0 <= rank < world_size):
        raise ValueError(f"rank must be in [0, {world_size}), got {rank}")
    base, extra = divmod(count, world_size)
    start = rank * base + min(rank, extra)
    return slice(start, start + base + (1 if rank < extra else 0))


class _Replicate(torch.autograd.Function):
    """Identity forward; backward all-reduces (sums) each gradient over the group."""

    @staticmethod
    def forward(ctx, group, *tensors):
        ctx.group = group
        return tuple(t.view_as(t) for t in tensors)

    @staticmethod
    def backward(ctx, *grads):
        reduced = []
        for grad in grads:  # one collective per input, in argument order on every rank
            grad = grad.contiguous().clone()
            device = _comm_device(ctx.group, grad)
            buffer = grad.to(device)
            dist.all_reduce(buffer, op=dist.ReduceOp.SUM, group=ctx.group)
            reduced.append(buffer.to(grad.device))
        return (None, *reduced)


def replicate(*tensors: Tensor | None, group=None) -> tuple[Tensor | None, ...]:
    """Mark tensors as replicated on every rank: identity forward, summed gradients.

    After ``backward``, the gradient of a replicated leaf is the sum over ranks of
    each rank's gradient: the gradient of the sum of the ranks' losses. All tensors
    go through one autograd node, so the gradients are reduced in one fixed order.

    Parameters
    ----------
    *tensors : Tensor or None
        The same values on every rank (``None`` entries are passed through).

    Returns
    -------
    tuple of Tensor or None
        The inputs (as views) in the same order.
    """
    _group_info(group)
    present = [t for t in tensors if t is not None]
    if not (torch.is_grad_enabled() and any(t.requires_grad for t in present)):
        return tensors
    outputs = iter(_Replicate.apply(group, *present))
    return tuple(None if t is None else next(outputs) for t in tensors)


def _attach(output: Tensor, *inputs: Tensor | None) -> Tensor:
    """``output``, connected to the inputs that require grad when it is not already
    (an empty slice): a rank with no rows must still take part in the backward
    all-reduce."""
    if not torch.is_grad_enabled() or output.requires_grad:
        return output
    linked = [t for t in inputs if t is not None and t.requires_grad]
    if not linked:
        return output
    zero = sum(t.sum() for t in linked) * 0
    return output + zero.to(output.dtype)


def _global_tolerance(controls: Tensor, targets: Tensor, tolerance: float, group) -> float:
    """The coincidence tolerance that gives this rank's IDW the radius of the single-
    process IDW over all ranks' targets.

    :class:`~torchmorph.idw.IDW` measures the coincidence radius as a fraction of the
    bounding-box diagonal of its controls and targets; a rank sees only its targets,
    so its fraction is rescaled by (global diagonal / local diagonal).
    """
    device = _comm_device(group, controls)
    with torch.no_grad():
        c = controls.detach().double()
        t = targets.detach().double()
        inf = torch.full((3,), torch.inf, dtype=torch.float64)
        low = t.amin(0).cpu() if t.shape[0] else inf.clone()
        high = t.amax(0).cpu() if t.shape[0] else -inf
        global_low, global_high = low.to(device), high.to(device)
        dist.all_reduce(global_low, op=dist.ReduceOp.MIN, group=group)
        dist.all_reduce(global_high, op=dist.ReduceOp.MAX, group=group)
        c_low, c_high = c.amin(0).cpu(), c.amax(0).cpu()
        local = torch.maximum(c_high, high) - torch.minimum(c_low, low)
        whole = (torch.maximum(c_high, global_high.cpu())
                 - torch.minimum(c_low, global_low.cpu()))
        local_diagonal = float(torch.linalg.vector_norm(local))
        global_diagonal = float(torch.linalg.vector_norm(whole))
    if local_diagonal == 0.0:
        return tolerance
    return tolerance * global_diagonal / local_diagonal


# --------------------------------------------------------------------------- #
# gathering and writing distributed fields
# --------------------------------------------------------------------------- #
def _as_rows(rows: Tensor | Sequence[int], name: str, count: int, num_rows: int) -> Tensor:
    rows = torch.as_tensor(rows).detach().cpu()
    if rows.ndim != 1 or rows.shape[0] != count or (rows.numel() and rows.is_floating_point()):
        raise ValueError(f"{name} must be a 1-D integer tensor of {count} global row ids, got "
                         f"shape {tuple(rows.shape)} and dtype {rows.dtype}")
    rows = rows.long()
    if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= num_rows):
        raise ValueError(f"{name} must lie in [0, {num_rows}), got ids from {int(rows.min())} "
                         f"to {int(rows.max())}")
    return rows


def gather_rows(
    local: Tensor,
    rows: Tensor | Sequence[int],
    num_rows: int,
    *,
    dst: int | None = 0,
    group=None,
) -> Tensor | None:
    """Assemble a row-distributed field on one rank (or on all).

    Parameters
    ----------
    local : Tensor, shape (n_local, K) or (B, n_local, K)
        This rank's rows (e.g. the output of a sharded forward pass).
    rows : Tensor, shape (n_local,)
        Their global row ids (``morph.owned_nodes``, or ``morph.target_rows``).
    num_rows : int
        Rows of the full field; rows no rank provides are zero.
    dst : int or None
        The rank that receives the field; ``None``: every rank does.

    Returns
    -------
    Tensor, shape (num_rows, K) or (B, num_rows, K), on ``dst`` (every rank when
    ``dst`` is None); None on the other ranks. Not differentiable.
    """
    rank, world = _group_info(group)
    if not isinstance(local, Tensor) or local.ndim not in (2, 3):
        shape = tuple(local.shape) if isinstance(local, Tensor) else type(local).__name__
        raise ValueError(f"local must be a tensor of shape (n_local, K) or (B, n_local, K), "
                         f"got {shape}")
    rows = _as_rows(rows, "rows", local.shape[-2], num_rows)
    device = _comm_device(group, local)
    with torch.no_grad():
        moved = local.detach().movedim(-2, 0)  # (n_local, [B,] K)
        counts = torch.tensor([moved.shape[0]], dtype=torch.int64, device=device)
        sizes = [torch.zeros_like(counts) for _ in range(world)]
        dist.all_gather(sizes, counts, group=group)
        sizes = [int(s) for s in sizes]
        longest = max(sizes)
        padded = moved.new_zeros(longest, *moved.shape[1:]).to(device)
        padded[: moved.shape[0]] = moved.to(device)
        padded_rows = torch.zeros(longest, dtype=torch.int64, device=device)
        padded_rows[: rows.shape[0]] = rows.to(device)
        if dst is None:
            values = [torch.empty_like(padded) for _ in range(world)]
            ids = [torch.empty_like(padded_rows) for _ in range(world)]
            dist.all_gather(values, padded, group=group)
            dist.all_gather(ids, padded_rows, group=group)
        else:
            receiving = rank == dst
            values = [torch.empty_like(padded) for _ in range(world)] if receiving else None
            ids = [torch.empty_like(padded_rows) for _ in range(world)] if receiving else None
            dist.gather(padded, values, dst=dst, group=group)
            dist.gather(padded_rows, ids, dst=dst, group=group)
            if not receiving:
                return None
        full = moved.new_zeros(num_rows, *moved.shape[1:])
        for size, value, index in zip(sizes, values, ids, strict=True):
            full[index[:size].to(full.device)] = value[:size].to(full.device)
    return full.movedim(0, -2)


_PART = re.compile(r"part-(\d{5})-of-(\d{5})\.pt$")


def save_partitioned(
    directory: str | os.PathLike,
    local: Tensor,
    rows: Tensor | Sequence[int],
    num_rows: int,
    *,
    group=None,
) -> Path:
    """Write each rank's rows of a field to its own file, atomically.

    Rank r writes ``directory/part-{r:05d}-of-{world:05d}.pt`` (a ``torch.save`` dict
    with ``rows``, ``values`` and ``num_rows``) through a temporary file renamed over
    the target, so a crash never leaves a half-written part; all ranks then wait for
    each other (a barrier). :func:`load_partitioned` reads the parts back.

    Returns
    -------
    Path
        This rank's file.
    """
    rank, world = _group_info(group)
    if not isinstance(local, Tensor) or local.ndim not in (2, 3):
        shape = tuple(local.shape) if isinstance(local, Tensor) else type(local).__name__
        raise ValueError(f"local must be a tensor of shape (n_local, K) or (B, n_local, K), "
                         f"got {shape}")
    rows = _as_rows(rows, "rows", local.shape[-2], num_rows)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"part-{rank:05d}-of-{world:05d}.pt"
    with atomic_output(path) as temporary:
        torch.save({"rows": rows, "values": local.detach().cpu(), "num_rows": int(num_rows)},
                   temporary)
    dist.barrier(group=group)
    return path


def load_partitioned(directory: str | os.PathLike) -> Tensor:
    """The full field from the parts :func:`save_partitioned` wrote (any process).

    Raises
    ------
    FileNotFoundError
        If ``directory`` holds no parts.
    ValueError
        If parts are missing or come from runs with different world sizes or sizes.
    """
    directory = Path(directory)
    parts = sorted(p for p in directory.iterdir() if _PART.search(p.name)) \
        if directory.is_dir() else []
    if not parts:
        raise FileNotFoundError(f"directory {str(directory)!r} holds no part-*-of-*.pt files")
    worlds = {int(_PART.search(p.name).group(2)) for p in parts}
    if len(worlds) != 1:
        raise ValueError(f"directory {str(directory)!r} mixes parts of runs with world sizes "
                         f"{sorted(worlds)}")
    (world,) = worlds
    ranks = sorted(int(_PART.search(p.name).group(1)) for p in parts)
    if ranks != list(range(world)):
        missing = sorted(set(range(world)) - set(ranks))
        raise ValueError(f"directory {str(directory)!r}: parts of ranks {missing} are missing "
                         f"(world size {world})")
    pieces = [torch.load(p, weights_only=True) for p in parts]
    num_rows = {piece["num_rows"] for piece in pieces}
    if len(num_rows) != 1:
        raise ValueError(f"directory {str(directory)!r}: parts disagree on the number of rows "
                         f"({sorted(num_rows)})")
    first = pieces[0]["values"]
    full = first.new_zeros(*first.shape[:-2], num_rows.pop(), first.shape[-1])
    for piece in pieces:
        full.index_copy_(-2, piece["rows"], piece["values"])
    return full


# --------------------------------------------------------------------------- #
# sharded IDW
# --------------------------------------------------------------------------- #
class ShardedIDW(nn.Module):
    """IDW (the paper's eqs. 1–2) with the targets split across ranks.

    Every rank holds all controls and its own targets, and builds an
    :class:`~torchmorph.idw.IDW` over them: its rows of W, dense or matrix-free.
    The result of a rank equals the single-process IDW's rows for its targets.

    Parameters
    ----------
    controls : Tensor, shape (N_c, 3)
        Control points, the same on every rank.
    targets : Tensor, shape (n_local, 3)
        This rank's targets (may be empty).
    target_rows : Tensor, shape (n_local,), optional
        Global ids of this rank's targets (for :meth:`gather`); default: ranks in
        order, each continuing the previous rank's count.
    power, mode, block_bytes, dense_bytes, coincidence_tolerance, implementation
        As in :class:`~torchmorph.idw.IDW`; ``mode="auto"`` decides per rank.
    group : ProcessGroup, optional
        Default: the world.

    Attributes
    ----------
    idw : IDW
        This rank's IDW (its ``coincidence_tolerance`` is rescaled so that the
        coincidence radius equals the single-process one, see Notes).
    num_global_targets : int
        Targets over all ranks.

    Notes
    -----
    :class:`~torchmorph.idw.IDW` measures the coincidence radius relative to the
    bounding box of its points; the constructor all-reduces the targets' global box
    so that every rank uses the radius of the single-process module (W does not
    depend on the box otherwise: the points are scaled by a power of two).
    """

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        target_rows: Tensor | Sequence[int] | None = None,
        power: float = 4.0,
        mode: Mode = "auto",
        block_bytes: int | None = None,
        dense_bytes: int | None = None,
        coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
        implementation: Implementation = "auto",
        group=None,
    ) -> None:
        super().__init__()
        self.rank, self.world_size = _group_info(group)
        self.group = group
        if not isinstance(targets, Tensor) or not isinstance(controls, Tensor):
            raise TypeError("controls and targets must be tensors")
        tolerance = _global_tolerance(controls, targets, float(coincidence_tolerance), group)
        self.idw = IDW(controls, targets, power=power, mode=mode, block_bytes=block_bytes,
                       dense_bytes=dense_bytes, coincidence_tolerance=tolerance,
                       implementation=implementation)
        device = _comm_device(group, controls)
        counts = torch.zeros(self.world_size, dtype=torch.int64, device=device)
        counts[self.rank] = self.idw.num_targets
        dist.all_reduce(counts, group=group)
        counts = counts.cpu()
        self.num_global_targets = int(counts.sum())
        if target_rows is None:
            start = int(counts[: self.rank].sum())
            target_rows = torch.arange(start, start + self.idw.num_targets)
        target_rows = _as_rows(target_rows, "target_rows", self.idw.num_targets,
                               self.num_global_targets)
        self.register_buffer("target_rows", target_rows.to(controls.device))

    @property
    def num_controls(self) -> int:
        return self.idw.num_controls

    @property
    def num_targets(self) -> int:
        """This rank's targets."""
        return self.idw.num_targets

    def forward(
        self,
        displacements: Tensor,
        *,
        controls: Tensor | None = None,
        targets: Tensor | None = None,
    ) -> Tensor:
        """This rank's rows of ``W @ displacements``.

        Parameters
        ----------
        displacements : Tensor, shape (N_c, 3) or (B, N_c, 3)
            Control displacements, the same on every rank (replicated: their
            gradient is summed over ranks).
        controls : Tensor, shape (N_c, 3), optional
            Moved control positions, the same on every rank (replicated).
        targets : Tensor, shape (n_local, 3), optional
            Moved positions of this rank's targets (local: not reduced).

        Returns
        -------
        Tensor, shape (n_local, 3) or (B, n_local, 3)
        """
        displacements, controls = replicate(displacements, controls, group=self.group)
        if self.num_targets == 0:  # no rows here (IDW's functional path needs one block)
            out = displacements.new_zeros(*displacements.shape[:-2], 0, 3)
        else:
            out = self.idw(displacements, controls=controls, targets=targets)
        return _attach(out, displacements, controls, targets)

    def gather(self, local: Tensor, *, dst: int | None = 0) -> Tensor | None:
        """The full (N_t, 3) field on ``dst`` (all ranks if None), from each rank's rows."""
        return gather_rows(local, self.target_rows, self.num_global_targets, dst=dst,
                           group=self.group)

    def extra_repr(self) -> str:
        return (f"rank={self.rank}, world_size={self.world_size}, "
                f"num_global_targets={self.num_global_targets}")


# --------------------------------------------------------------------------- #
# sharded mesh morph
# --------------------------------------------------------------------------- #
def _broadcast_ids(ids: Tensor | None, group, device: torch.device) -> Tensor:
    """Rank 0's 1-D int64 tensor on every rank."""
    rank, _ = _group_info(group)
    source = dist.get_global_rank(group, 0) if group is not None else 0
    count = torch.tensor([0 if ids is None else ids.numel()], dtype=torch.int64, device=device)
    dist.broadcast(count, src=source, group=group)
    buffer = ids.to(device) if rank == 0 else torch.empty(int(count), dtype=torch.int64,
                                                          device=device)
    dist.broadcast(buffer, src=source, group=group)
    return buffer.cpu()


class ShardedMeshMorph(nn.Module):
    """Algorithm 2 of the paper on a mesh partitioned across ranks.

    The selection phase runs on rank 0 (its control points are broadcast); every
    rank then builds W only for the interior nodes it owns. The deformation phase
    returns the displacement of the rank's own nodes: boundary nodes take their
    prescribed value exactly, interior nodes ``W d_selected``; rows equal those of
    :class:`~torchmorph.morph.MeshMorph` for the same nodes.

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh, the same on every rank.
    plan : SelectionPlan, optional
        Control-point selection (SIDW/ESIDW); None: every boundary node.
    owned_nodes : Tensor, shape (n_owned,), optional
        Global ids of the nodes this rank owns (its partition); together the
        ranks' sets must partition the mesh nodes. Default: an even share of the
        interior nodes (where the work is) and of the boundary nodes, each a
        contiguous slice (:func:`shard_rows`) of the sorted ids.
    power, mode, generator, block_bytes, dense_bytes, coincidence_tolerance, implementation
        As in :class:`~torchmorph.morph.MeshMorph` and :class:`~torchmorph.idw.IDW`
        (``generator`` is used on rank 0 only).
    group : ProcessGroup, optional
        Default: the world.

    Attributes
    ----------
    owned_nodes : buffer (n_owned,)
        The rows of this rank's output, as global node ids.
    boundary_nodes, control_nodes, selected : buffers
        As in :class:`~torchmorph.morph.MeshMorph` (global, the same on every rank).
    local_interior : buffer (n_int_local,)
        Global ids of the interior nodes this rank interpolates.
    idw : IDW
        This rank's rows of W.

    Raises
    ------
    ValueError
        If ``owned_nodes`` are not integers in [0, N), or the ranks' sets do not
        partition the nodes (the message counts the nodes owned by no rank and by
        several); if the plan selects no control points or non-boundary nodes.
    """

    def __init__(
        self,
        mesh: TetMesh,
        plan: SelectionPlan | None = None,
        *,
        owned_nodes: Tensor | Sequence[int] | None = None,
        power: float = 4.0,
        mode: Mode = "auto",
        generator: torch.Generator | None = None,
        block_bytes: int | None = None,
        dense_bytes: int | None = None,
        coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
        implementation: Implementation = "auto",
        group=None,
    ) -> None:
        super().__init__()
        if not isinstance(mesh, TetMesh):
            raise TypeError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
        self.rank, self.world_size = _group_info(group)
        self.group = group
        points = mesh.points.detach()
        num_nodes = points.shape[0]
        device = _comm_device(group, points)
        boundary = mesh.boundary_nodes.cpu()
        interior = mesh.interior_nodes.cpu()
        control_nodes = None
        if self.rank == 0:
            if plan is None:
                control_nodes = boundary
            else:
                control_nodes = torch.as_tensor(plan.select(mesh, generator=generator),
                                                dtype=torch.long).unique()
        control_nodes = _broadcast_ids(control_nodes, group, device)
        if control_nodes.numel() == 0:
            raise ValueError("plan selected no control points")
        selected = torch.searchsorted(boundary, control_nodes)
        if (selected >= boundary.numel()).any() or not torch.equal(
                boundary[selected.clamp_max(boundary.numel() - 1)], control_nodes):
            raise ValueError("plan selected nodes that are not boundary nodes")

        if owned_nodes is None:  # an even share of the interior (the work) and of the boundary
            owned = torch.cat([boundary[shard_rows(boundary.numel(), group=group)],
                               interior[shard_rows(interior.numel(), group=group)]]).sort().values
        else:
            owned = torch.as_tensor(owned_nodes).detach().cpu()
            if owned.ndim != 1 or (owned.numel() and owned.is_floating_point()):
                raise ValueError(f"owned_nodes must be a 1-D integer tensor of node ids, got "
                                 f"shape {tuple(owned.shape)} and dtype {owned.dtype}")
            owned = owned.long()
            if owned.numel() and (int(owned.min()) < 0 or int(owned.max()) >= num_nodes):
                raise ValueError(f"owned_nodes must lie in [0, {num_nodes}), got ids from "
                                 f"{int(owned.min())} to {int(owned.max())}")
        owners = torch.zeros(num_nodes, dtype=torch.int32)
        owners.index_add_(0, owned, torch.ones_like(owned, dtype=torch.int32))
        owners = owners.to(device)
        dist.all_reduce(owners, group=group)
        owners = owners.cpu()
        orphans, shared = int((owners == 0).sum()), int((owners > 1).sum())
        if orphans or shared:
            raise ValueError(f"owned_nodes must partition the {num_nodes} mesh nodes across "
                             f"the ranks: {orphans} nodes are owned by no rank and {shared} by "
                             f"several")

        is_boundary = torch.zeros(num_nodes, dtype=torch.bool)
        is_boundary[boundary] = True
        owned_is_boundary = is_boundary[owned]
        local_boundary = owned[owned_is_boundary]
        local_interior = owned[~owned_is_boundary]
        target_device = points.device
        self.register_buffer("points", points.clone())
        self.register_buffer("owned_nodes", owned.to(target_device))
        self.register_buffer("boundary_nodes", boundary.to(target_device))
        self.register_buffer("control_nodes", control_nodes.to(target_device))
        self.register_buffer("selected", selected.to(target_device))
        self.register_buffer("local_interior", local_interior.to(target_device))
        # positions of the owned boundary / interior nodes among the output rows, and the
        # rows of the boundary displacement the owned boundary nodes take
        self.register_buffer("_boundary_slots",
                             torch.nonzero(owned_is_boundary).flatten().to(target_device),
                             persistent=False)
        self.register_buffer("_interior_slots",
                             torch.nonzero(~owned_is_boundary).flatten().to(target_device),
                             persistent=False)
        self.register_buffer("_boundary_rows",
                             torch.searchsorted(boundary, local_boundary).to(target_device),
                             persistent=False)
        self.node_sets = {name: nodes.clone() for name, nodes in mesh.node_sets.items()}
        self.num_interior = int(interior.numel())
        self.sharded = ShardedIDW(points[self.control_nodes], points[self.local_interior],
                                  target_rows=torch.searchsorted(interior, local_interior),
                                  power=power, mode=mode, block_bytes=block_bytes,
                                  dense_bytes=dense_bytes,
                                  coincidence_tolerance=coincidence_tolerance,
                                  implementation=implementation, group=group)
        self.idw = self.sharded.idw

    # ------------------------------------------------------------------ sizes
    @property
    def num_nodes(self) -> int:
        return self.points.shape[0]

    @property
    def num_boundary(self) -> int:
        return self.boundary_nodes.shape[0]

    @property
    def num_controls(self) -> int:
        return self.selected.shape[0]

    @property
    def num_owned(self) -> int:
        return self.owned_nodes.shape[0]

    def controls_from_boundary(self, boundary_displacement: Tensor) -> Tensor:
        """The displacement of the selected control points, (N_sel, 3) or (B, N_sel, 3)."""
        return boundary_displacement.index_select(-2, self.selected)

    def _assemble(self, boundary_displacement: Tensor, interior: Tensor) -> Tensor:
        """This rank's rows: boundary values copied, interior values from ``interior``."""
        shape = (*boundary_displacement.shape[:-2], self.num_owned, 3)
        out = boundary_displacement.new_zeros(shape)
        out = out.index_copy(-2, self._boundary_slots,
                             boundary_displacement.index_select(-2, self._boundary_rows))
        return out.index_copy(-2, self._interior_slots, interior)

    def forward(self, boundary_displacement: Tensor, *, points: Tensor | None = None) -> Tensor:
        """Morph: displacement of this rank's nodes (rows ``owned_nodes``).

        Parameters
        ----------
        boundary_displacement : Tensor, shape (N_b, 3) or (B, N_b, 3)
            Prescribed displacement of every boundary node (ordered as
            ``boundary_nodes``), the same on every rank (replicated).
        points : Tensor, shape (N, 3), optional
            Moved reference coordinates of all nodes, the same on every rank
            (replicated; shape optimisation): this rank's W rows are rebuilt
            differentiably from them.

        Returns
        -------
        Tensor, shape (n_owned, 3) or (B, n_owned, 3)
        """
        check_vectors(boundary_displacement, "boundary_displacement", self.num_boundary,
                      what="boundary nodes")
        if points is not None and (not isinstance(points, Tensor)
                                   or points.shape != self.points.shape):
            shape = tuple(points.shape) if isinstance(points, Tensor) else type(points)
            raise ValueError(f"points must have shape {tuple(self.points.shape)}, got {shape}")
        boundary_displacement, points = replicate(boundary_displacement, points,
                                                  group=self.group)
        controls = self.controls_from_boundary(boundary_displacement)
        if self.idw.num_targets == 0:
            interior = controls.new_zeros(*controls.shape[:-2], 0, 3)
        elif points is None:
            interior = self.idw(controls)
        else:
            interior = self.idw(controls, controls=points[self.control_nodes],
                                targets=points[self.local_interior])
        out = self._assemble(boundary_displacement, interior)
        return _attach(out, boundary_displacement, points)

    def gather(self, local: Tensor, *, dst: int | None = 0) -> Tensor | None:
        """The full nodal field (N, 3) or (B, N, 3) on ``dst`` (all ranks if None)."""
        return gather_rows(local, self.owned_nodes, self.num_nodes, dst=dst, group=self.group)

    def save(self, directory: str | os.PathLike, local: Tensor) -> Path:
        """Write this rank's rows with :func:`save_partitioned` (atomically)."""
        return save_partitioned(directory, local, self.owned_nodes, self.num_nodes,
                                group=self.group)

    def extra_repr(self) -> str:
        return (f"rank={self.rank}, world_size={self.world_size}, num_nodes={self.num_nodes}, "
                f"num_owned={self.num_owned}, num_controls={self.num_controls}, "
                f"mode={self.idw.mode!r}")


# --------------------------------------------------------------------------- #
# sharded POD
# --------------------------------------------------------------------------- #
def sharded_pod_basis(
    snapshots: Tensor,
    *,
    energy_tolerance: float = 1e-5,
    num_modes: int | None = None,
    group=None,
) -> tuple[Tensor, Tensor, Tensor]:
    """POD basis of snapshots whose points are split across ranks (paper eqs. 9–12).

    A distributed thin SVD by TSQR: each rank factors its rows of the snapshot
    matrix, ``U_r = Q_r R_r`` (Householder QR, float64); the n × n triangles are
    all-gathered, every rank takes the SVD of their stack, ``[R_1; …; R_P] =
    Ũ Σ Vᵀ``, and its modes are ``Q_r Ũ_r``.

    Why TSQR and not the Gram matrix (method of snapshots): the Gram route
    eigen-decomposes ``Σ_r U_rᵀ U_r`` and squares the condition number — singular
    values below ``sqrt(eps) · σ_1`` (1e-8 σ_1 in float64) come out as noise and
    their modes lose orthogonality, while TSQR is backward stable (errors of
    order ``eps · σ_1``, as the single-process SVD). Both exchange one n × n
    matrix per rank; TSQR costs twice the local flops (a QR instead of a Gram
    product), negligible next to the snapshots' morph.

    Parameters
    ----------
    snapshots : Tensor, shape (n, m_local, 3)
        This rank's points of the n snapshot fields (m_local may be 0).
    energy_tolerance, num_modes
        As in :func:`torchmorph.pod.pod_basis`.

    Returns
    -------
    modes : Tensor, shape (N, m_local, 3)
        This rank's rows of the orthonormal modes (orthonormal over all ranks).
    singular_values, energy_captured : Tensor, shape (min(n, 3M),)
        As in :func:`~torchmorph.pod.pod_basis`, the same on every rank.

    Notes
    -----
    Signs are fixed so that the largest entry of each right singular vector is
    positive (the single-process :func:`~torchmorph.pod.pod_basis` keeps the
    SVD's arbitrary signs: compare modes up to sign).
    """
    rank, world = _group_info(group)
    if not isinstance(snapshots, Tensor) or snapshots.ndim != 3 or snapshots.shape[-1] != 3 \
            or snapshots.shape[0] == 0:
        shape = tuple(snapshots.shape) if isinstance(snapshots, Tensor) else \
            type(snapshots).__name__
        raise ValueError(f"snapshots must have shape (n, m_local, 3) with n >= 1, got {shape}")
    energy_tolerance = _check_energy_tolerance(energy_tolerance)
    num_modes = _check_num_modes(num_modes)
    count, num_points = snapshots.shape[0], snapshots.shape[1]
    device = _comm_device(group, snapshots)
    matrix = snapshots.detach().reshape(count, 3 * num_points).double().mT.to(device)
    stats = torch.tensor([float(num_points), float(not bool(matrix.isfinite().all()))],
                         dtype=torch.float64, device=device)
    dist.all_reduce(stats, group=group)
    total_points = int(stats[0])
    if float(stats[1]):
        raise ValueError("snapshots must be finite; NaN or inf on at least one rank")

    if matrix.shape[0] >= count:
        q, r = torch.linalg.qr(matrix, mode="reduced")  # (3m, n), (n, n)
    else:
        q, r = torch.linalg.qr(matrix, mode="complete")  # (3m, 3m), (3m, n)
        q = torch.cat([q, q.new_zeros(q.shape[0], count - q.shape[1])], 1)
        r = torch.cat([r, r.new_zeros(count - r.shape[0], count)], 0)
    triangles = [torch.empty_like(r) for _ in range(world)]
    dist.all_gather(triangles, r.contiguous(), group=group)
    left, singular_values, vh = torch.linalg.svd(torch.cat(triangles), full_matrices=False)
    # deterministic signs: the largest entry of each right singular vector positive
    pivot = vh.abs().argmax(1, keepdim=True)
    signs = torch.sign(vh.gather(1, pivot)).flatten()
    signs[signs == 0] = 1.0
    left = left * signs

    total = float(singular_values.square().sum())
    if total == 0.0:
        raise ValueError("snapshots are all zero: there is no displacement to reduce")
    energy_captured = torch.cumsum(singular_values.square(), 0) / total
    singular_values = singular_values[: min(count, 3 * total_points)]
    energy_captured = energy_captured[: singular_values.shape[0]]
    numerical_rank = _numerical_rank(singular_values, (count, 3 * total_points),
                                     snapshots.dtype)
    if num_modes is None:
        kept = _num_modes_for_energy(singular_values, energy_tolerance)
    else:
        if num_modes > count:
            raise ValueError(f"num_modes={num_modes} exceeds the number of snapshots ({count})")
        if num_modes > numerical_rank:
            raise ValueError(f"num_modes={num_modes} exceeds the numerical rank "
                             f"{numerical_rank} of the snapshots (singular values "
                             f"{singular_values[:num_modes].tolist()})")
        kept = num_modes
    block = left[rank * count : (rank + 1) * count, :kept]
    columns = q @ block  # (3m, N)
    modes = columns.mT.reshape(kept, num_points, 3).to(snapshots.device, snapshots.dtype)
    return (modes.contiguous(), singular_values.to(snapshots.device, snapshots.dtype),
            energy_captured.to(snapshots.device, snapshots.dtype))


class ShardedPOD(nn.Module):
    """POD-reduced morph (Algorithm 3 of the paper, ``projection`` online variant) of a
    sharded IDW or mesh morph.

    Offline (:meth:`fit`): the snapshots are morphed shard by shard, the basis comes
    from :func:`sharded_pod_basis` (TSQR), and the online matrix ``P = Zᵀ W`` is
    summed over ranks (each rank applies its rows of Wᵀ to its rows of the modes).
    Online (:meth:`forward`): β = P d from the replicated input, then this rank's
    rows ``Z_r β`` — no communication.

    Parameters
    ----------
    energy_tolerance, num_modes
        As in :class:`~torchmorph.pod.PODReducer`.

    Attributes
    ----------
    modes_ : Tensor (N, n_local, 3)
        This rank's rows of the basis.
    singular_values_, energy_captured_ : Tensor
        As in :class:`~torchmorph.pod.PODReducer` (the same on every rank).
    projection_ : Tensor (N, N_sel, 3)
        P, the same on every rank.

    Notes
    -----
    The paper's own online variant (eq. 16) needs the pseudo-inverse of the whole W
    and is not offered here. The reduced output equals what
    :class:`~torchmorph.pod.PODReducer` (``online="projection"``) fitted to the
    single-process morph returns for the same rows (the projection does not depend
    on the modes' signs).
    """

    def __init__(self, *, energy_tolerance: float = 1e-5, num_modes: int | None = None) -> None:
        super().__init__()
        self.energy_tolerance = _check_energy_tolerance(energy_tolerance)
        self.num_modes = _check_num_modes(num_modes)
        for name in ("modes_", "singular_values_", "energy_captured_", "projection_"):
            self.register_buffer(name, torch.empty(0))
        self.num_modes_: int | None = None
        self._morph: nn.Module | None = None

    @property
    def is_fitted(self) -> bool:
        return self.num_modes_ is not None

    def fit(self, morph: ShardedIDW | ShardedMeshMorph, displacements: Tensor) -> ShardedPOD:
        """Offline phase on every rank (collective: all ranks call it).

        Parameters
        ----------
        morph : ShardedIDW or ShardedMeshMorph
        displacements : Tensor, shape (n_train, N_in, 3)
            Training inputs, the same on every rank: control displacements
            (ShardedIDW) or boundary displacements (ShardedMeshMorph).

        Returns
        -------
        ShardedPOD
            ``self``, fitted.
        """
        if isinstance(morph, ShardedMeshMorph):
            count_in, idw = morph.num_boundary, morph.idw
        elif isinstance(morph, ShardedIDW):
            count_in, idw = morph.num_controls, morph.idw
        else:
            raise TypeError(f"morph must be a ShardedIDW or a ShardedMeshMorph, got "
                            f"{type(morph).__name__}")
        if not isinstance(displacements, Tensor) or displacements.ndim != 3 or \
                displacements.shape[1:] != (count_in, 3):
            shape = tuple(displacements.shape) if isinstance(displacements, Tensor) else \
                type(displacements).__name__
            raise ValueError(f"displacements must have shape (n_train, {count_in}, 3), got "
                             f"{shape}")
        group = morph.group
        with torch.no_grad():
            inputs = displacements.to(idw.controls.device, idw.controls.dtype)
            if isinstance(morph, ShardedMeshMorph):
                inputs = morph.controls_from_boundary(inputs)
            snapshots = idw(inputs)
            modes, singular_values, energy = sharded_pod_basis(
                snapshots, energy_tolerance=self.energy_tolerance, num_modes=self.num_modes,
                group=group)
            if idw.num_targets:
                projection = _idw_transpose_apply(idw, modes)
            else:
                projection = modes.new_zeros(modes.shape[0], idw.num_controls, 3)
            device = _comm_device(group, projection)
            summed = projection.contiguous().to(device)
            dist.all_reduce(summed, group=group)
            projection = summed.to(projection.device)
        self.modes_, self.singular_values_, self.energy_captured_ = modes, singular_values, energy
        self.projection_ = projection
        self.num_modes_ = int(modes.shape[0])
        self.__dict__["_morph"] = morph
        return self

    def coefficients(self, displacement: Tensor) -> Tensor:
        """β = P d_sel, shape (N,) or (B, N), from a replicated input (no communication)."""
        if not self.is_fitted:
            raise RuntimeError("this ShardedPOD is not fitted yet: call fit(morph, "
                               "displacements) first")
        morph = self.__dict__["_morph"]
        if isinstance(morph, ShardedMeshMorph):
            check_vectors(displacement, "displacement", morph.num_boundary,
                          what="boundary nodes")
            displacement = morph.controls_from_boundary(displacement)
        else:
            check_vectors(displacement, "displacement", morph.num_controls,
                          what="control points")
        flat = displacement.reshape(*displacement.shape[:-2], -1)
        return flat @ self.projection_.reshape(self.num_modes_, -1).mT

    def forward(self, displacement: Tensor) -> Tensor:
        """This rank's rows of the reduced morph (what the sharded morph returns).

        Parameters
        ----------
        displacement : Tensor, shape (N_in, 3) or (B, N_in, 3)

        Returns
        -------
        Tensor, shape (n_local, 3) or (B, n_local, 3)
            ShardedIDW: its targets; ShardedMeshMorph: its owned nodes (boundary
            rows exactly ``displacement``'s).
        """
        beta = self.coefficients(displacement)
        interior = (beta @ self.modes_.reshape(self.num_modes_, -1)).reshape(
            *beta.shape[:-1], -1, 3)
        morph = self.__dict__["_morph"]
        if isinstance(morph, ShardedMeshMorph):
            return morph._assemble(displacement, interior)
        return interior

    def extra_repr(self) -> str:
        return (f"energy_tolerance={self.energy_tolerance:g}, num_modes={self.num_modes}, "
                f"num_modes_={self.num_modes_}")
