"""The sharded IDW of :mod:`torchmorph.distributed`: the paper's eqs. 1–2 with the
targets split across ranks.

It follows the morph protocol of :class:`~torchmorph.pod.PODReducer` for its own rows
(``weights``, ``adjoint``): the transpose of the whole map is the sum over ranks of the
ranks' ``adjoint`` (what :class:`~torchmorph.distributed.ShardedPOD` computes), and
``add_fingerprint`` adds what the ranks must share to an agreement check.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchmorph._checks import as_points, check_positive, check_same_device_dtype, check_vectors
from torchmorph.distributed._agreement import (
    Agreement,
    _group_info,
    agree_on_rows,
    local_rows,
)
from torchmorph.distributed._common import (
    _attach,
    _global_tolerance,
    gather_rows,
    replicate,
)
from torchmorph.idw.module import DEFAULT_COINCIDENCE_TOLERANCE, IDW, Implementation, Mode

__all__ = ["ShardedIDW"]


def _points(value: Any, name: str, like: Tensor | None = None) -> Tensor:
    """Points (N, D) (D read from ``value``, or ``like``'s), finite; with ``like`` (the
    controls) possibly empty and on its device and dtype."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    dim = like.shape[1] if like is not None else (value.shape[1] if value.ndim == 2 else 3)
    points = as_points(value, name, dim=dim, allow_empty=like is not None)
    if like is not None:
        check_same_device_dtype(like, "controls", points, name)
    return points


def _check_tree_options(tolerance: Any, error_control: Any) -> tuple[float | None, int]:
    """The tree's ``tolerance`` (None, or in (0, 1)) and ``error_control`` as a number
    the ranks can compare (-1 for None, 0 certified, 1 sampled)."""
    from torchmorph.idw._geometry import check_error_control
    from torchmorph.idw.tree import _check_tolerance as check_tree_tolerance

    checked = None if tolerance is None else check_tree_tolerance(tolerance)
    if error_control is None:
        return checked, -1
    return checked, ("certified", "sampled").index(check_error_control(error_control))


def _check_tolerance(value: Any) -> float:
    tolerance = float(value)
    if not math.isfinite(tolerance) or tolerance < 0:
        raise ValueError(f"coincidence_tolerance must be finite and >= 0, got {value!r}")
    return tolerance


def _local_transpose(idw: IDW, fields: Tensor) -> Tensor:
    """Wᵀ of one rank's IDW rows per component: (B, n_local, D) -> (B, N_c, D). One
    GEMM with a stored W, else a vector-Jacobian product of the (linear) IDW for the
    whole batch (W is never formed). No communication."""
    batch, count, dim = fields.shape
    if idw.num_targets == 0:
        return fields.new_zeros(batch, idw.num_controls, dim)
    weights = idw.weights
    if isinstance(weights, Tensor):
        columns = fields.permute(1, 0, 2).reshape(count, batch * dim)
        return (columns.mT @ weights).reshape(batch, dim, -1).mT.contiguous()
    if idw.mode == "tree":  # the tree's own transpose at its tolerance's threshold
        return idw.transposed(fields)
    with torch.enable_grad():
        probe = fields.new_zeros(batch, idw.num_controls, dim, requires_grad=True)
        (result,) = torch.autograd.grad(idw(probe), probe, grad_outputs=fields)
    return result.detach()


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
    controls : Tensor, shape (N_c, D)
        Control points, the same on every rank (bit for bit); D = 2 or 3.
    targets : Tensor, shape (n_local, D)
        This rank's targets (may be empty), in the controls' dtype and device.
    target_rows : Tensor, shape (n_local,), optional
        Global ids of this rank's targets (for :meth:`gather`): given on every rank
        or on none, and together the ranks' ids hold each of the N_t = Σ n_local
        rows exactly once. Default: ranks in order, each continuing the previous
        rank's count.
    power, mode, block_bytes, dense_bytes, coincidence_tolerance, implementation
        As in :class:`~torchmorph.idw.IDW`; ``power`` and ``coincidence_tolerance``
        must be the same on every rank, ``mode="auto"`` decides per rank.
    tolerance, error_control : optional
        As in :class:`~torchmorph.idw.IDW` (the tree's), the same on every rank: each
        rank's tree keeps the relative error on its own targets, so the gathered result
        keeps it too (the squared errors and norms add up over the ranks); with
        ``mode="auto"`` each rank takes the tree by its own pairs.
    group : ProcessGroup, optional
        Default: the world.

    Attributes
    ----------
    idw : IDW
        This rank's IDW (its ``coincidence_tolerance`` is rescaled so that the
        coincidence radius equals the single-process one, see Notes).
    coincidence_tolerance : float
        The tolerance given (relative to the bounding box of all ranks' points).
    num_global_targets : int
        Targets over all ranks.
    target_rows : buffer (n_local,)
        The global ids of this rank's rows.

    Raises
    ------
    ValueError
        On every rank at once (no rank is left waiting for another): if
        ``controls``, ``power``, ``coincidence_tolerance``, ``tolerance`` or
        ``error_control`` differ across ranks (in shape, dtype or value; the message
        names each), ``target_rows`` is given on some ranks only or does not partition
        the targets, or a rank's own inputs are malformed (NaN targets on one rank,
        say): that rank raises its own error, the others one naming the argument and
        the rank.

    Notes
    -----
    :class:`~torchmorph.idw.IDW` measures the coincidence radius relative to the
    bounding box of its points; the constructor all-reduces the targets' global box
    so that every rank uses the radius of the single-process module (W does not
    depend on the box otherwise: the points are scaled by a power of two).

    Communication when built: an all-reduce of a fingerprint (checksums of the
    controls, the hyper-parameters, each rank's count), one of the bounding box (2·D
    numbers) and one of the target rows' partition (N_t 32-bit counts when
    ``target_rows`` is given, else a few numbers).
    """

    target_rows: Tensor  # a buffer, registered in __init__

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
        tolerance: float | None = None,
        error_control: str | None = None,
        group: Any = None,
    ) -> None:
        super().__init__()
        self.rank, self.world_size = _group_info(group)
        self.group = group
        context = "building a ShardedIDW"
        agreement = Agreement(group, context)
        checked_controls = agreement.attempt("controls", _points, controls, "controls")
        checked_targets = agreement.attempt(
            "targets", _points, targets, "targets", checked_controls
        )
        checked_power = agreement.attempt("power", check_positive, power, "power")
        coincidence = agreement.attempt(
            "coincidence_tolerance", _check_tolerance, coincidence_tolerance
        )
        options = agreement.attempt("tolerance", _check_tree_options, tolerance, error_control)
        tree_tolerance, tree_control = options or (None, -1)
        count = 0 if checked_targets is None else checked_targets.shape[0]
        rows = None
        if target_rows is not None:
            rows = agreement.attempt(
                "target_rows", local_rows, target_rows, "target_rows", count, None
            )
        agreement.same_tensor("controls", checked_controls)
        agreement.same("power", checked_power)
        agreement.same("coincidence_tolerance", coincidence)
        agreement.same("tolerance", tree_tolerance)
        agreement.same("error_control (-1: None, 0: 'certified', 1: 'sampled')", tree_control)
        agreement.same_presence("target_rows", target_rows is not None)
        agreement.per_rank("targets", count)
        counts = [int(value) for value in agreement.exchange()["targets"]]
        # exchange() raised on every rank if a check above failed on one
        assert checked_controls is not None and checked_targets is not None
        assert checked_power is not None and coincidence is not None
        controls, targets, power = checked_controls, checked_targets, checked_power

        self.num_global_targets = sum(counts)
        self.coincidence_tolerance = coincidence
        scaled = _global_tolerance(controls, targets, coincidence, group)
        failure: tuple[str, Exception] | None = None
        if rows is None:
            start = sum(counts[: self.rank])
            rows = torch.arange(start, start + count)
        elif rows.numel() and int(rows.max()) >= self.num_global_targets:
            error = ValueError(
                f"target_rows must lie in [0, {self.num_global_targets}), got ids from "
                f"{int(rows.min())} to {int(rows.max())}"
            )
            failure, rows = ("target_rows", error), None
        if failure is None:
            try:
                self.idw = IDW(
                    controls,
                    targets,
                    power=power,
                    mode=mode,
                    block_bytes=block_bytes,
                    dense_bytes=dense_bytes,
                    coincidence_tolerance=scaled,
                    implementation=implementation,
                    tolerance=tree_tolerance,
                    error_control=error_control,
                )
            except Exception as error:  # noqa: BLE001  raised below, on every rank
                failure = ("IDW(controls, targets)", error)
        checked = target_rows is not None  # the default rows partition by construction
        agree_on_rows(
            rows if checked else None,
            self.num_global_targets if checked else 0,
            name="target_rows",
            what="target rows",
            group=group,
            context=context,
            failure=failure,
            steps=("IDW(controls, targets)",),
        )
        assert rows is not None  # None only after a failure, which agree_on_rows raised
        self.register_buffer("target_rows", rows.to(controls.device))

    @property
    def num_controls(self) -> int:
        return self.idw.num_controls

    @property
    def num_targets(self) -> int:
        """This rank's targets."""
        return self.idw.num_targets

    @property
    def dim(self) -> int:
        """D, the points' dimension."""
        return self.idw.controls.shape[1]

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
        displacements : Tensor, shape (N_c, D) or (B, N_c, D)
            Control displacements, the same on every rank (replicated: their
            gradient is summed over ranks).
        controls : Tensor, shape (N_c, D), optional
            Moved control positions, the same on every rank (replicated).
        targets : Tensor, shape (n_local, D), optional
            Moved positions of this rank's targets (local: not reduced).

        Returns
        -------
        Tensor, shape (n_local, D) or (B, n_local, D)
        """
        displacements, controls = replicate(displacements, controls, group=self.group)
        if self.num_targets == 0:  # no rows here (IDW's functional path needs one block)
            out = displacements.new_zeros(*displacements.shape[:-2], 0, displacements.shape[-1])
        else:
            out = self.idw(displacements, controls=controls, targets=targets)
        return _attach(out, displacements, controls, targets)

    # ---------------------------------------------------- the morph protocol, per rank
    @property
    def weights(self) -> Tensor | None:
        """This rank's rows of W, (n_local, N_c), in dense mode; None in matrix-free mode."""
        return self.idw.weights

    def adjoint(self, fields: Tensor) -> Tensor:
        """This rank's share of the transpose: fields on its targets, (n_local, D) or
        (B, n_local, D), to (N_c, D) or (B, N_c, D) by W_rᵀ per component. Summed
        over ranks it is the transpose of the whole map. No communication."""
        check_vectors(fields, "fields", self.num_targets, dim=self.dim, what="targets of this rank")
        batch = fields if fields.ndim == 3 else fields.unsqueeze(0)
        result = _local_transpose(self.idw, batch)
        return result if fields.ndim == 3 else result[0]

    @property
    def output_rows(self) -> Tensor:
        """The global ids of this rank's output rows (``target_rows``)."""
        return self.target_rows

    @property
    def num_global_outputs(self) -> int:
        """Output rows over all ranks (``num_global_targets``)."""
        return self.num_global_targets

    def add_fingerprint(self, agreement: Agreement) -> None:
        """Add what the ranks' modules must share (controls, power, tolerance, size)."""
        agreement.same_tensor("morph.controls", self.idw.controls)
        agreement.same("morph.power", self.idw.power)
        agreement.same("morph.coincidence_tolerance", self.coincidence_tolerance)
        agreement.same("morph.num_global_targets", self.num_global_targets)

    def gather(self, local: Tensor, *, dst: int | None = 0) -> Tensor | None:
        """The full (N_t, D) field on ``dst`` (all ranks if None), from each rank's rows."""
        return gather_rows(
            local, self.target_rows, self.num_global_targets, dst=dst, group=self.group
        )

    def extra_repr(self) -> str:
        return (
            f"rank={self.rank}, world_size={self.world_size}, "
            f"num_global_targets={self.num_global_targets}"
        )
