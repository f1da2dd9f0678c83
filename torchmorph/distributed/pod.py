"""The sharded POD of :mod:`torchmorph.distributed`: a distributed thin SVD (TSQR) of
row-sharded snapshots and the reducer built on it (the paper's Algorithm 3)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor

from torchmorph._checks import check_finite, check_float_dtype
from torchmorph.distributed._agreement import (
    Agreement,
    _comm_device,
    _group_info,
    agree_on_rows,
    local_rows,
)
from torchmorph.distributed._common import gather_rows
from torchmorph.pod._base import PODBase
from torchmorph.pod._protocol import (
    adjoint,
    morph_snapshots,
    reference_tensor,
    spread_modes,
    training_inputs,
)
from torchmorph.pod.functional import (
    _num_modes_for_energy,
    _numerical_rank,
    check_energy_tolerance,
    check_num_modes,
)

__all__ = ["ShardedPOD", "sharded_pod_basis"]


# --------------------------------------------------------------------------- #
# sharded POD basis
# --------------------------------------------------------------------------- #
def _check_snapshots(snapshots: Any) -> Tensor:
    if not isinstance(snapshots, Tensor) or snapshots.ndim != 3 or 0 in snapshots.shape[::2]:
        shape = (
            tuple(snapshots.shape) if isinstance(snapshots, Tensor) else type(snapshots).__name__
        )
        raise ValueError(f"snapshots must have shape (n, m_local, D) with n >= 1, got {shape}")
    check_float_dtype(snapshots, "snapshots")
    check_finite(snapshots, "snapshots")
    return snapshots


def sharded_pod_basis(
    snapshots: Tensor,
    *,
    energy_tolerance: float = 1e-5,
    num_modes: int | None = None,
    group: Any = None,
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
    snapshots : Tensor, shape (n, m_local, D)
        This rank's points of the n snapshot fields (m_local may be 0); n, D and
        the dtype are the same on every rank.
    energy_tolerance, num_modes
        As in :func:`torchmorph.pod.pod_basis`, the same on every rank.

    Returns
    -------
    modes : Tensor, shape (N, m_local, D)
        This rank's rows of the orthonormal modes (orthonormal over all ranks).
    singular_values, energy_captured : Tensor, shape (min(n, D·M),)
        As in :func:`~torchmorph.pod.pod_basis`, the same on every rank.

    Raises
    ------
    ValueError
        On every rank at once: snapshots malformed or not finite on a rank (that
        rank raises its own error, the others name it), n, D, the dtype,
        ``energy_tolerance`` or ``num_modes`` that differ across ranks, all-zero
        snapshots, or ``num_modes`` above the snapshots' count or rank.

    Notes
    -----
    Signs are fixed so that the largest entry of each right singular vector is
    positive (the single-process :func:`~torchmorph.pod.pod_basis` keeps the
    SVD's arbitrary signs: compare modes up to sign).
    """
    agreement = Agreement(group, "computing a sharded POD basis")
    checked = agreement.attempt("snapshots", _check_snapshots, snapshots)
    tolerance = agreement.attempt("energy_tolerance", check_energy_tolerance, energy_tolerance)
    num_modes = agreement.attempt("num_modes", check_num_modes, num_modes)
    agreement.same_tensor("snapshots", checked, rows_dim=1)
    agreement.same("energy_tolerance", tolerance)
    agreement.same("num_modes", num_modes)
    agreement.per_rank("points", 0 if checked is None else checked.shape[1])
    points = agreement.exchange()["points"]
    # exchange() raised on every rank if a check above failed on one
    assert checked is not None and tolerance is not None
    return _tsqr_basis(checked, int(sum(points)), tolerance, num_modes, group)


def _tsqr_basis(
    snapshots: Tensor,
    total_points: int,
    energy_tolerance: float,
    num_modes: int | None,
    group: Any,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`sharded_pod_basis` on checked snapshots the ranks agree on (collective:
    one all-gather of n × n triangles); ``total_points`` = Σ m_local."""
    rank, world = _group_info(group)
    count, num_points, dim = snapshots.shape
    device = _comm_device(group, snapshots)
    matrix = snapshots.detach().reshape(count, dim * num_points).double().mT.to(device)
    if matrix.shape[0] >= count:
        q, r = torch.linalg.qr(matrix, mode="reduced")  # (D·m, n), (n, n)
    else:
        q, r = torch.linalg.qr(matrix, mode="complete")  # (D·m, D·m), (D·m, n)
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
    length = dim * total_points
    singular_values = singular_values[: min(count, length)]
    energy_captured = energy_captured[: singular_values.shape[0]]
    numerical_rank = _numerical_rank(singular_values, (count, length), snapshots.dtype)
    if num_modes is None:
        kept = _num_modes_for_energy(singular_values.square(), energy_tolerance)
    else:
        if num_modes > count:
            raise ValueError(f"num_modes={num_modes} exceeds the number of snapshots ({count})")
        if num_modes > numerical_rank:
            raise ValueError(
                f"num_modes={num_modes} exceeds the numerical rank "
                f"{numerical_rank} of the snapshots (singular values "
                f"{singular_values[:num_modes].tolist()})"
            )
        kept = num_modes
    block = left[rank * count : (rank + 1) * count, :kept]
    columns = q @ block  # (D·m, N)
    modes = columns.mT.reshape(kept, num_points, dim).to(snapshots.device, snapshots.dtype)
    return (
        modes.contiguous(),
        singular_values.to(snapshots.device, snapshots.dtype),
        energy_captured.to(snapshots.device, snapshots.dtype),
    )


# --------------------------------------------------------------------------- #
# sharded POD reducer
# --------------------------------------------------------------------------- #
def _sum_over_ranks(value: Tensor, failure: Exception | None, group: Any, context: str) -> Tensor:
    """``value`` summed over ranks (collective: one all-reduce, with one more entry that
    counts the ranks where computing ``value`` failed; then every rank raises)."""
    flat = value.reshape(-1)
    flag = flat.new_tensor([0.0 if failure is None else 1.0])
    summed = torch.cat([flat, flag]).to(_comm_device(group, flat))
    dist.all_reduce(summed, group=group)
    if float(summed[-1]) > 0:
        if failure is not None:
            raise failure
        raise ValueError(
            f"morph.adjoint failed on another rank (it raised the error that says why); "
            f"every rank stops {context}"
        )
    return summed[:-1].to(value.device).reshape(value.shape)


class ShardedPOD(PODBase):
    """POD-reduced morph (Algorithm 3 of the paper, ``projection`` online variant) of a
    sharded IDW or mesh morph: each rank keeps the reduced morph of its own rows.

    Offline (:meth:`fit`, every rank at once): the snapshots are morphed shard by
    shard, the basis comes from :func:`sharded_pod_basis` (TSQR), and the online
    matrix ``P = Zᵀ L`` is summed over ranks (each rank applies its share of the
    transpose, the morph's ``weights`` or ``adjoint``, to its rows of the modes).
    Online (:meth:`forward`): β = P d from the replicated input, then this rank's
    rows ``Z_r β`` and the rows its morph copies — no communication, and nothing
    but the state: a ``ShardedPOD`` restored by ``load_state_dict`` runs without
    its morph. The state, the load rule and the online phase are those of
    :class:`~torchmorph.pod.PODReducer` (one base, :mod:`torchmorph.pod._base`).

    Parameters
    ----------
    energy_tolerance, num_modes
        As in :class:`~torchmorph.pod.PODReducer`; the same on every rank.

    Attributes
    ----------
    modes_ : Tensor (N, n_red, D)
        This rank's rows of the basis (its output rows ``reduced_rows_``).
    singular_values_, energy_captured_ : Tensor
        As in :class:`~torchmorph.pod.PODReducer` (the same on every rank).
    projection_ : Tensor (N, N_in, D)
        P over every input row (zero where W reads nothing), the same on every rank.
    copied_output_rows_, copied_input_rows_, reduced_rows_ : Tensor
        As in :class:`~torchmorph.pod.PODReducer`, among this rank's output rows.
    output_rows_ : Tensor (n_out,)
        The global ids of this rank's output rows (the morph's ``output_rows``:
        ``target_rows`` or ``owned_nodes``), for :meth:`gather`.
    num_global_outputs_ : int
        Output rows over all ranks.
    rank_, world_size_ : int
        The rank that fitted this state, and the group's size.

    Notes
    -----
    The morph protocol of :class:`~torchmorph.pod.PODReducer`, per rank: ``morph(d)``
    returns the rank's rows; ``copied_rows()``, ``weights``/``weight_columns`` and
    ``adjoint`` describe them, and the sum of the ranks' ``adjoint`` is the
    transpose (no communication inside them: ``fit`` sums them in one all-reduce). :class:`~torchmorph.distributed.ShardedIDW` and
    :class:`~torchmorph.distributed.ShardedMeshMorph` follow it; their
    ``add_fingerprint`` lets ``fit`` check that the ranks hold the same morph, and
    their ``group`` is the group ``fit`` works in.

    Communication in ``fit``: the agreement of the ranks (a fingerprint of the
    training displacements, the hyper-parameters and the morph, then the partition
    of the output rows), an all-gather of one n × n triangle per rank (TSQR) and an
    all-reduce of P.

    The paper's own online variant (eq. 16) needs the pseudo-inverse of the whole W
    and is not offered here. The reduced output equals what
    :class:`~torchmorph.pod.PODReducer` (``online="projection"``) fitted to the
    single-process morph returns for the same rows (the projection does not depend
    on the modes' signs). States saved before version 2 (without the rows the
    morph copies) cannot run without their morph and are refused: fit again.
    """

    _FITTED = (*PODBase._FITTED, "num_global_outputs_", "rank_", "world_size_")
    _INDEX_BUFFERS = (*PODBase._INDEX_BUFFERS, "output_rows_")
    _FIT_HINT = "call fit(morph, displacements) on every rank first"

    def __init__(self, *, energy_tolerance: float = 1e-5, num_modes: int | None = None) -> None:
        super().__init__(energy_tolerance=energy_tolerance, num_modes=num_modes)
        self.group: Any = None

    def _check_state(self, state_dict, prefix: str) -> None:
        extra = state_dict[prefix + "_extra_state"]
        if isinstance(extra, dict) and "version" not in extra and "num_modes_" in extra:
            raise ValueError(
                f"state_dict[{prefix + '_extra_state'!r}]: a ShardedPOD state saved before "
                "version 2 holds neither the rows its morph copies nor the input rows W "
                "reads, so it cannot run without its morph; fit the ShardedPOD again"
            )
        super()._check_state(state_dict, prefix)
        if extra.get("num_modes_") is None:
            return
        for name in ("num_global_outputs_", "rank_", "world_size_"):
            value = extra.get(name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
                raise ValueError(
                    f"state_dict[{prefix + '_extra_state'!r}]: {name} must be an integer or "
                    f"None, got {value!r}"
                )
        rows = state_dict.get(prefix + "output_rows_")
        if not isinstance(rows, Tensor) or rows.numel() not in (0, extra["num_outputs_"]):
            raise ValueError(
                f"state_dict[{prefix + 'output_rows_'!r}]: must hold the global ids of the "
                f"{extra['num_outputs_']} output rows (or none)"
            )

    def fit(self, morph: Callable[[Tensor], Tensor], displacements: Tensor) -> ShardedPOD:
        """Offline phase on every rank (collective: all ranks of ``morph.group`` call it).

        Parameters
        ----------
        morph : sharded linear map
            A :class:`~torchmorph.distributed.ShardedIDW`,
            :class:`~torchmorph.distributed.ShardedMeshMorph` or another map that
            follows the protocol of the class notes; its ``group`` (default: the
            world) is the group the ranks work in.
        displacements : Tensor, shape (n_train, N_in, D)
            Training inputs, the same on every rank (bit for bit): control
            displacements (ShardedIDW) or boundary displacements (ShardedMeshMorph).

        Returns
        -------
        ShardedPOD
            ``self``, fitted.

        Raises
        ------
        ValueError
            On every rank at once: training displacements, ``energy_tolerance``,
            ``num_modes`` or the morph (its fingerprint) that differ across ranks;
            output rows (``morph.output_rows``) that do not partition the
            ``morph.num_global_outputs`` rows; a rank whose own data or morph fails
            (NaN snapshots on one rank, say: that rank raises its own error, the
            others name it); all-zero snapshots, or ``num_modes`` above the
            snapshots' count or rank.
        """
        group = getattr(morph, "group", None)
        context = "fitting a ShardedPOD"
        start = time.perf_counter()
        agreement = Agreement(group, context)
        agreement.attempt("morph", _check_callable, morph)
        reference = reference_tensor(morph)
        with torch.no_grad():
            inputs = agreement.attempt(
                "displacements", training_inputs, displacements, "displacements"
            )
            if inputs is not None and reference is not None:
                inputs = inputs.to(device=reference.device, dtype=reference.dtype)
            fitted = None
            if inputs is not None:
                fitted = agreement.attempt("morph(displacements)", morph_snapshots, morph, inputs)
        agreement.same_tensor(
            "displacements", displacements if isinstance(displacements, Tensor) else None
        )
        agreement.same("energy_tolerance", self.energy_tolerance)
        agreement.same("num_modes", self.num_modes)
        fingerprint = getattr(morph, "add_fingerprint", None)
        if fingerprint is not None:
            fingerprint(agreement)
        # the global ids of the ranks' rows (for gather) must partition the map's rows
        total = getattr(morph, "num_global_outputs", None)
        output_rows = None
        if total is not None:
            output_rows = agreement.attempt(
                "morph.output_rows",
                local_rows,
                getattr(morph, "output_rows", None),
                "morph.output_rows",
                None if fitted is None else fitted[2],
                total,
            )
        agreement.same_presence("morph.num_global_outputs", total is not None)
        agreement.same("morph.num_global_outputs", total)
        agreement.per_rank("rows", 0 if fitted is None else fitted[0].shape[1])
        total_rows = int(sum(agreement.exchange()["rows"]))
        # exchange() raised on every rank if a check above failed on one
        assert inputs is not None and fitted is not None
        if total is not None:
            agree_on_rows(
                output_rows,
                total,
                name="morph.output_rows",
                what="output rows",
                group=group,
                context=context,
            )
        snapshots, rows, num_outputs = fitted
        after_snapshots = time.perf_counter()

        with torch.no_grad():
            modes, singular_values, energy_captured = _tsqr_basis(
                snapshots, total_rows, self.energy_tolerance, self.num_modes, group
            )
            after_svd = time.perf_counter()
            num_inputs = inputs.shape[1]
            share, failure = None, None
            try:  # this rank's share of P = Zᵀ L
                share = adjoint(
                    morph, spread_modes(modes, rows[2], num_outputs), num_inputs, rows[2]
                )
            except Exception as error:  # noqa: BLE001  raised by _sum_over_ranks, on every rank
                failure = error
                share = modes.new_zeros(modes.shape[0], num_inputs, modes.shape[-1])
            projection = _sum_over_ranks(share, failure, group, context)
            after_online = time.perf_counter()

        self._store_fit(
            modes=modes,
            singular_values=singular_values,
            energy_captured=energy_captured,
            copied_rows=rows,
            num_inputs=num_inputs,
            num_outputs=num_outputs,
            projection=projection,
        )
        if output_rows is None:
            output_rows = torch.empty(0, dtype=torch.int64)
        self.output_rows_ = output_rows.to(modes.device)
        self.num_global_outputs_ = total
        self.rank_, self.world_size_ = _group_info(group)
        self.group = group
        self.offline_time_ = {
            "snapshots": after_snapshots - start,
            "svd": after_svd - after_snapshots,
            "online_matrices": after_online - after_svd,
            "total": after_online - start,
        }
        return self

    def gather(self, local: Tensor, *, dst: int | None = 0, group: Any = None) -> Tensor | None:
        """The full field (N_global, D) or (B, N_global, D) on ``dst`` (all ranks if None)
        from each rank's output (collective, :func:`gather_rows` over ``output_rows_``;
        ``group`` defaults to the one of ``fit``, or the world after loading a state)."""
        self._check_fitted()
        if self.num_global_outputs_ is None:
            raise ValueError(
                "gather needs the global ids of the output rows: the morph given to fit "
                "had no output_rows / num_global_outputs"
            )
        return gather_rows(
            local,
            self.output_rows_,
            self.num_global_outputs_,
            dst=dst,
            group=self.group if group is None else group,
        )


def _check_callable(morph: Any) -> None:
    if not callable(morph):
        raise TypeError(f"morph must be a callable linear map, got {type(morph).__name__}")
