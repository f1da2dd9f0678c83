"""Sharded IDW and mesh morph (the paper's Algorithm 2) of :mod:`torchmorph.distributed`."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import torch.distributed as dist
from torch import Tensor, nn

from torchmorph._checks import check_vectors
from torchmorph.idw.module import DEFAULT_COINCIDENCE_TOLERANCE, IDW, Implementation, Mode
from torchmorph.mesh.model import TetMesh

if TYPE_CHECKING:
    from torchmorph.selection.plan import SelectionPlan

from torchmorph.distributed._common import (
    _as_rows,
    _attach,
    _comm_device,
    _global_tolerance,
    _group_info,
    gather_rows,
    replicate,
    save_partitioned,
    shard_rows,
)

__all__ = ["ShardedIDW", "ShardedMeshMorph"]


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
        self.idw = IDW(
            controls,
            targets,
            power=power,
            mode=mode,
            block_bytes=block_bytes,
            dense_bytes=dense_bytes,
            coincidence_tolerance=tolerance,
            implementation=implementation,
        )
        device = _comm_device(group, controls)
        counts = torch.zeros(self.world_size, dtype=torch.int64, device=device)
        counts[self.rank] = self.idw.num_targets
        dist.all_reduce(counts, group=group)
        counts = counts.cpu()
        self.num_global_targets = int(counts.sum())
        if target_rows is None:
            start = int(counts[: self.rank].sum())
            target_rows = torch.arange(start, start + self.idw.num_targets)
        target_rows = _as_rows(
            target_rows, "target_rows", self.idw.num_targets, self.num_global_targets
        )
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
        return gather_rows(
            local, self.target_rows, self.num_global_targets, dst=dst, group=self.group
        )

    def extra_repr(self) -> str:
        return (
            f"rank={self.rank}, world_size={self.world_size}, "
            f"num_global_targets={self.num_global_targets}"
        )


# --------------------------------------------------------------------------- #
# sharded mesh morph
# --------------------------------------------------------------------------- #
def _broadcast_ids(ids: Tensor | None, group, device: torch.device) -> Tensor:
    """Rank 0's 1-D int64 tensor on every rank."""
    rank, _ = _group_info(group)
    source = dist.get_global_rank(group, 0) if group is not None else 0
    count = torch.tensor([0 if ids is None else ids.numel()], dtype=torch.int64, device=device)
    dist.broadcast(count, src=source, group=group)
    buffer = (
        ids.to(device) if rank == 0 else torch.empty(int(count), dtype=torch.int64, device=device)
    )
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
                control_nodes = torch.as_tensor(
                    plan.select(mesh, generator=generator), dtype=torch.long
                ).unique()
        control_nodes = _broadcast_ids(control_nodes, group, device)
        if control_nodes.numel() == 0:
            raise ValueError("plan selected no control points")
        selected = torch.searchsorted(boundary, control_nodes)
        if (selected >= boundary.numel()).any() or not torch.equal(
            boundary[selected.clamp_max(boundary.numel() - 1)], control_nodes
        ):
            raise ValueError("plan selected nodes that are not boundary nodes")

        if owned_nodes is None:  # an even share of the interior (the work) and of the boundary
            owned = (
                torch.cat(
                    [
                        boundary[shard_rows(boundary.numel(), group=group)],
                        interior[shard_rows(interior.numel(), group=group)],
                    ]
                )
                .sort()
                .values
            )
        else:
            owned = torch.as_tensor(owned_nodes).detach().cpu()
            if owned.ndim != 1 or (owned.numel() and owned.is_floating_point()):
                raise ValueError(
                    f"owned_nodes must be a 1-D integer tensor of node ids, got "
                    f"shape {tuple(owned.shape)} and dtype {owned.dtype}"
                )
            owned = owned.long()
            if owned.numel() and (int(owned.min()) < 0 or int(owned.max()) >= num_nodes):
                raise ValueError(
                    f"owned_nodes must lie in [0, {num_nodes}), got ids from "
                    f"{int(owned.min())} to {int(owned.max())}"
                )
        owners = torch.zeros(num_nodes, dtype=torch.int32)
        owners.index_add_(0, owned, torch.ones_like(owned, dtype=torch.int32))
        owners = owners.to(device)
        dist.all_reduce(owners, group=group)
        owners = owners.cpu()
        orphans, shared = int((owners == 0).sum()), int((owners > 1).sum())
        if orphans or shared:
            raise ValueError(
                f"owned_nodes must partition the {num_nodes} mesh nodes across "
                f"the ranks: {orphans} nodes are owned by no rank and {shared} by "
                f"several"
            )

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
        self.register_buffer(
            "_boundary_slots",
            torch.nonzero(owned_is_boundary).flatten().to(target_device),
            persistent=False,
        )
        self.register_buffer(
            "_interior_slots",
            torch.nonzero(~owned_is_boundary).flatten().to(target_device),
            persistent=False,
        )
        self.register_buffer(
            "_boundary_rows",
            torch.searchsorted(boundary, local_boundary).to(target_device),
            persistent=False,
        )
        self.node_sets = {name: nodes.clone() for name, nodes in mesh.node_sets.items()}
        self.num_interior = int(interior.numel())
        self.sharded = ShardedIDW(
            points[self.control_nodes],
            points[self.local_interior],
            target_rows=torch.searchsorted(interior, local_interior),
            power=power,
            mode=mode,
            block_bytes=block_bytes,
            dense_bytes=dense_bytes,
            coincidence_tolerance=coincidence_tolerance,
            implementation=implementation,
            group=group,
        )
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
        out = out.index_copy(
            -2, self._boundary_slots, boundary_displacement.index_select(-2, self._boundary_rows)
        )
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
        check_vectors(
            boundary_displacement, "boundary_displacement", self.num_boundary, what="boundary nodes"
        )
        if points is not None and (
            not isinstance(points, Tensor) or points.shape != self.points.shape
        ):
            shape = tuple(points.shape) if isinstance(points, Tensor) else type(points)
            raise ValueError(f"points must have shape {tuple(self.points.shape)}, got {shape}")
        boundary_displacement, points = replicate(boundary_displacement, points, group=self.group)
        controls = self.controls_from_boundary(boundary_displacement)
        if self.idw.num_targets == 0:
            interior = controls.new_zeros(*controls.shape[:-2], 0, 3)
        elif points is None:
            interior = self.idw(controls)
        else:
            interior = self.idw(
                controls, controls=points[self.control_nodes], targets=points[self.local_interior]
            )
        out = self._assemble(boundary_displacement, interior)
        return _attach(out, boundary_displacement, points)

    def gather(self, local: Tensor, *, dst: int | None = 0) -> Tensor | None:
        """The full nodal field (N, 3) or (B, N, 3) on ``dst`` (all ranks if None)."""
        return gather_rows(local, self.owned_nodes, self.num_nodes, dst=dst, group=self.group)

    def save(self, directory: str | os.PathLike, local: Tensor) -> Path:
        """Write this rank's rows with :func:`save_partitioned` (atomically)."""
        return save_partitioned(
            directory, local, self.owned_nodes, self.num_nodes, group=self.group
        )

    def extra_repr(self) -> str:
        return (
            f"rank={self.rank}, world_size={self.world_size}, num_nodes={self.num_nodes}, "
            f"num_owned={self.num_owned}, num_controls={self.num_controls}, "
            f"mode={self.idw.mode!r}"
        )
