"""The sharded mesh morph of :mod:`torchmorph.distributed` (the paper's Algorithm 2 on a
mesh partitioned across ranks).

It follows the morph protocol of :class:`~torchmorph.pod.PODReducer` for its own rows
(``weights``, ``weight_columns``, ``copied_rows()``, ``adjoint``): the transpose of the
whole morph is the sum over ranks of the ranks' ``adjoint`` (what
:class:`~torchmorph.distributed.ShardedPOD` computes), and ``add_fingerprint`` adds
what the ranks must share to an agreement check.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
import torch.distributed as dist
from torch import Tensor, nn

from torchmorph._checks import check_positive, check_vectors
from torchmorph.distributed._agreement import (
    Agreement,
    _comm_device,
    _group_info,
    agree_on_rows,
    local_rows,
)
from torchmorph.distributed._common import (
    _attach,
    gather_rows,
    replicate,
    save_partitioned,
    shard_rows,
)
from torchmorph.distributed.idw import ShardedIDW, _check_tolerance, _local_transpose
from torchmorph.idw.module import DEFAULT_COINCIDENCE_TOLERANCE, Implementation, Mode
from torchmorph.mesh.model import Mesh
from torchmorph.morph import boundary_rows, select_controls

if TYPE_CHECKING:
    from torchmorph.selection.plan import SelectionPlan

__all__ = ["ShardedIDW", "ShardedMeshMorph"]


# --------------------------------------------------------------------------- #
# sharded mesh morph
# --------------------------------------------------------------------------- #
def _broadcast_selection(select: Callable[[], Tensor], group: Any, context: str) -> Tensor:
    """The 1-D int64 tensor ``select()`` returns on rank 0, on every rank (the others do
    not call it); a failure on rank 0 raises on every rank."""
    rank, _ = _group_info(group)
    source = dist.get_global_rank(group, 0) if group is not None else 0
    device = _comm_device(group, torch.empty(0))
    ids: Tensor | None = None
    error: Exception | None = None
    if rank == 0:
        try:
            ids = select()
        except Exception as failure:  # noqa: BLE001  raised below, on every rank
            error = failure
    number = -1 if error is not None else (0 if ids is None else ids.numel())
    count = torch.tensor([number], dtype=torch.int64, device=device)
    dist.broadcast(count, src=source, group=group)
    if int(count) < 0:
        if error is not None:
            raise error
        raise ValueError(
            "plan: the selection failed on rank 0 (that rank raised the error that says "
            f"why); every rank stops {context}"
        )
    if rank == 0:
        assert ids is not None  # select() returned (it raised otherwise, handled above)
        buffer = ids.to(device)
    else:
        buffer = torch.empty(int(count), dtype=torch.int64, device=device)
    dist.broadcast(buffer, src=source, group=group)
    return buffer.cpu()


def _check_mesh(mesh: Any) -> None:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a torchmorph Mesh (or TetMesh), got {type(mesh).__name__}")


class ShardedMeshMorph(nn.Module):
    """Algorithm 2 of the paper on a mesh partitioned across ranks.

    The selection phase runs on rank 0 (its control points are broadcast); every
    rank then builds W only for the interior nodes it owns. The deformation phase
    returns the displacement of the rank's own nodes: boundary nodes take their
    prescribed value exactly, interior nodes ``W d_selected``; rows equal those of
    :class:`~torchmorph.morph.MeshMorph` for the same nodes.

    Parameters
    ----------
    mesh : Mesh
        The reference mesh (any element kinds, 2-D or 3-D), the same on every rank: its points (bit for bit), its
        boundary nodes and its cells' kinds and counts are compared by checksums.
    plan : SelectionPlan, optional
        Control-point selection (SIDW/ESIDW); None: every boundary node. Rank 0's
        plan is the one used.
    owned_nodes : Tensor, shape (n_owned,), optional
        Global ids of the nodes this rank owns (its partition); given on every rank
        or none, and together the ranks' sets must partition the mesh nodes.
        Default: an even share of the interior nodes (where the work is) and of the
        boundary nodes, each a contiguous slice (:func:`shard_rows`) of the sorted ids.
    power, mode, generator, block_bytes, dense_bytes, coincidence_tolerance, implementation
        As in :class:`~torchmorph.morph.MeshMorph` and :class:`~torchmorph.idw.IDW`
        (``generator`` is used on rank 0 only; ``power`` and ``coincidence_tolerance``
        must be the same on every rank).
    tolerance, error_control : optional
        The tree's, as in :class:`~torchmorph.distributed.ShardedIDW` (the same on every
        rank; checked there, after the mesh).
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
        On every rank at once: if the mesh (points, boundary or cells), ``power`` or
        ``coincidence_tolerance`` differ across ranks, ``owned_nodes`` is given on
        some ranks only, is not distinct integers in [0, N) on a rank (that rank
        raises its own error, the others name it), or the ranks' sets do not
        partition the nodes (the message counts the nodes owned by no rank and by
        several); if the plan selects no control points or non-boundary nodes, or
        fails on rank 0.
    """

    # buffers, registered in __init__
    points: Tensor
    owned_nodes: Tensor
    boundary_nodes: Tensor
    control_nodes: Tensor
    selected: Tensor
    local_interior: Tensor
    _boundary_slots: Tensor
    _interior_slots: Tensor
    _boundary_rows: Tensor

    def __init__(
        self,
        mesh: Mesh,
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
        tolerance: float | None = None,
        error_control: str | None = None,
        group: Any = None,
    ) -> None:
        super().__init__()
        self.rank, self.world_size = _group_info(group)
        self.group = group
        context = "building a ShardedMeshMorph"
        agreement = Agreement(group, context)
        agreement.attempt("mesh", _check_mesh, mesh)
        points = None if agreement.error is not None else mesh.points.detach()
        # the morph reads the points and which nodes are on the boundary; of the cells,
        # only kinds and counts are compared (a checksum costs 0.1 s per million cells)
        boundary = None if points is None else mesh.boundary_nodes.cpu()
        cells = () if points is None else [f"{b.kind}:{b.nodes.shape[0]}" for b in mesh.cells]
        num_nodes = 0 if points is None else points.shape[0]
        checked_power = agreement.attempt("power", check_positive, power, "power")
        coincidence = agreement.attempt(
            "coincidence_tolerance", _check_tolerance, coincidence_tolerance
        )
        owned = None
        if owned_nodes is not None:
            owned = agreement.attempt(
                "owned_nodes", local_rows, owned_nodes, "owned_nodes", None, num_nodes
            )
        agreement.same_tensor("mesh.points", points)
        agreement.same_tensor("mesh.boundary_nodes", boundary)
        agreement.same_digest("mesh.cells", *cells)
        agreement.same("power", checked_power)
        agreement.same("coincidence_tolerance", coincidence)
        agreement.same_presence("owned_nodes", owned_nodes is not None)
        agreement.exchange()
        # exchange() raised on every rank if a check above failed on one
        assert points is not None and boundary is not None
        assert checked_power is not None and coincidence is not None

        interior = mesh.interior_nodes.cpu()

        def select() -> Tensor:  # the single-process morph's selection, on rank 0
            return select_controls(mesh, plan, generator).cpu()

        control_nodes = _broadcast_selection(select, group, context)
        selected = boundary_rows(boundary, control_nodes)

        if owned is None:  # an even share of the interior (the work) and of the boundary
            mine = [
                boundary[shard_rows(boundary.numel(), group=group)],
                interior[shard_rows(interior.numel(), group=group)],
            ]
            owned = torch.cat(mine).sort().values
        else:
            agree_on_rows(
                owned,
                num_nodes,
                name="owned_nodes",
                what="mesh nodes",
                verb="owned",
                group=group,
                context=context,
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
        self.node_sets = {name: mesh.node_set(name).clone() for name in mesh.markers}
        self.num_interior = int(interior.numel())
        self.sharded = ShardedIDW(
            points[self.control_nodes],
            points[self.local_interior],
            target_rows=torch.searchsorted(interior, local_interior),
            power=checked_power,
            mode=mode,
            block_bytes=block_bytes,
            dense_bytes=dense_bytes,
            coincidence_tolerance=coincidence,
            implementation=implementation,
            tolerance=tolerance,
            error_control=error_control,
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

    @property
    def dim(self) -> int:
        """D, the mesh's dimension."""
        return self.points.shape[1]

    def controls_from_boundary(self, boundary_displacement: Tensor) -> Tensor:
        """The displacement of the selected control points, (N_sel, D) or (B, N_sel, D)."""
        return boundary_displacement.index_select(-2, self.selected)

    def _assemble(self, boundary_displacement: Tensor, interior: Tensor) -> Tensor:
        """This rank's rows: boundary values copied, interior values from ``interior``."""
        shape = (*boundary_displacement.shape[:-2], self.num_owned, boundary_displacement.shape[-1])
        out = boundary_displacement.new_zeros(shape)
        out = out.index_copy(
            -2, self._boundary_slots, boundary_displacement.index_select(-2, self._boundary_rows)
        )
        return out.index_copy(-2, self._interior_slots, interior)

    def forward(self, boundary_displacement: Tensor, *, points: Tensor | None = None) -> Tensor:
        """Morph: displacement of this rank's nodes (rows ``owned_nodes``).

        Parameters
        ----------
        boundary_displacement : Tensor, shape (N_b, D) or (B, N_b, D)
            Prescribed displacement of every boundary node (ordered as
            ``boundary_nodes``), the same on every rank (replicated).
        points : Tensor, shape (N, D), optional
            Moved reference coordinates of all nodes, the same on every rank
            (replicated; shape optimisation): this rank's W rows are rebuilt
            differentiably from them.

        Returns
        -------
        Tensor, shape (n_owned, D) or (B, n_owned, D)
        """
        check_vectors(
            boundary_displacement,
            "boundary_displacement",
            self.num_boundary,
            dim=self.dim,
            what="boundary nodes",
        )
        if points is not None and (
            not isinstance(points, Tensor) or points.shape != self.points.shape
        ):
            shape = tuple(points.shape) if isinstance(points, Tensor) else type(points)
            raise ValueError(f"points must have shape {tuple(self.points.shape)}, got {shape}")
        boundary_displacement, points = replicate(boundary_displacement, points, group=self.group)
        controls = self.controls_from_boundary(boundary_displacement)
        if self.idw.num_targets == 0:
            interior = controls.new_zeros(*controls.shape[:-2], 0, self.dim)
        elif points is None:
            interior = self.idw(controls)
        else:
            interior = self.idw(
                controls, controls=points[self.control_nodes], targets=points[self.local_interior]
            )
        out = self._assemble(boundary_displacement, interior)
        return _attach(out, boundary_displacement, points)

    # ---------------------------------------------------- the morph protocol, per rank
    def copied_rows(self) -> tuple[Tensor, Tensor]:
        """(output rows, input rows) that :meth:`forward` copies unchanged: this rank's
        boundary nodes, as positions among its output rows and as rows of the boundary
        displacement."""
        return self._boundary_slots, self._boundary_rows

    @property
    def weights(self) -> Tensor | None:
        """This rank's rows of W, (n_int_local, N_sel), in dense mode (else None):
        ``forward(d)[:, reduced rows] = W @ d[:, weight_columns]``."""
        return self.idw.weights

    @property
    def weight_columns(self) -> Tensor:
        """The input rows (boundary indices) that W reads: the selected controls."""
        return self.selected

    def adjoint(self, fields: Tensor) -> Tensor:
        """This rank's share of the transpose: fields on its nodes, (n_owned, D) or
        (B, n_owned, D), to (N_b, D) or (B, N_b, D). Boundary rows pass through,
        interior rows go through W_rᵀ onto the controls; summed over ranks it is the
        transpose of the whole morph. No communication."""
        check_vectors(fields, "fields", self.num_owned, dim=self.dim, what="nodes of this rank")
        batch = fields if fields.ndim == 3 else fields.unsqueeze(0)
        result = batch.new_zeros(batch.shape[0], self.num_boundary, self.dim)
        result.index_add_(1, self._boundary_rows, batch.index_select(1, self._boundary_slots))
        interior = _local_transpose(self.idw, batch.index_select(1, self._interior_slots))
        result.index_add_(1, self.selected, interior)
        return result if fields.ndim == 3 else result[0]

    @property
    def output_rows(self) -> Tensor:
        """The global ids of this rank's output rows (``owned_nodes``)."""
        return self.owned_nodes

    @property
    def num_global_outputs(self) -> int:
        """Output rows over all ranks: the mesh nodes."""
        return self.num_nodes

    def add_fingerprint(self, agreement: Agreement) -> None:
        """Add what the ranks' modules must share (points, controls, IDW settings)."""
        agreement.same_tensor("morph.points", self.points)
        agreement.same_tensor("morph.control_nodes", self.control_nodes)
        self.sharded.add_fingerprint(agreement)

    def gather(self, local: Tensor, *, dst: int | None = 0) -> Tensor | None:
        """The full nodal field (N, D) or (B, N, D) on ``dst`` (all ranks if None)."""
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
