"""The sharded POD of :mod:`torchmorph.distributed`: a distributed thin SVD (TSQR) of
row-sharded snapshots and the reducer built on it (the paper's Algorithm 3)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.distributed as dist
from torch import Tensor, nn

from torchmorph._checks import check_vectors
from torchmorph.pod.functional import (
    _num_modes_for_energy,
    _numerical_rank,
    check_energy_tolerance,
    check_num_modes,
    projection_matrix,
)

if TYPE_CHECKING:
    pass

from torchmorph.distributed._common import (
    _comm_device,
    _group_info,
)
from torchmorph.distributed.morph import ShardedIDW, ShardedMeshMorph


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
    if (
        not isinstance(snapshots, Tensor)
        or snapshots.ndim != 3
        or snapshots.shape[-1] != 3
        or snapshots.shape[0] == 0
    ):
        shape = (
            tuple(snapshots.shape) if isinstance(snapshots, Tensor) else type(snapshots).__name__
        )
        raise ValueError(f"snapshots must have shape (n, m_local, 3) with n >= 1, got {shape}")
    energy_tolerance = check_energy_tolerance(energy_tolerance)
    num_modes = check_num_modes(num_modes)
    count, num_points = snapshots.shape[0], snapshots.shape[1]
    device = _comm_device(group, snapshots)
    matrix = snapshots.detach().reshape(count, 3 * num_points).double().mT.to(device)
    stats = torch.tensor(
        [float(num_points), float(not bool(matrix.isfinite().all()))],
        dtype=torch.float64,
        device=device,
    )
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
    numerical_rank = _numerical_rank(singular_values, (count, 3 * total_points), snapshots.dtype)
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
    columns = q @ block  # (3m, N)
    modes = columns.mT.reshape(kept, num_points, 3).to(snapshots.device, snapshots.dtype)
    return (
        modes.contiguous(),
        singular_values.to(snapshots.device, snapshots.dtype),
        energy_captured.to(snapshots.device, snapshots.dtype),
    )


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
        self.energy_tolerance = check_energy_tolerance(energy_tolerance)
        self.num_modes = check_num_modes(num_modes)
        for name in self._BUFFERS:
            self.register_buffer(name, torch.empty(0))
        self.num_modes_: int | None = None
        self._morph: nn.Module | None = None

    @property
    def is_fitted(self) -> bool:
        return self.num_modes_ is not None

    # ---------------------------------------------------------------- state
    _BUFFERS = ("modes_", "singular_values_", "energy_captured_", "projection_")

    def get_extra_state(self) -> dict:
        return {
            "energy_tolerance": self.energy_tolerance,
            "num_modes": self.num_modes,
            "num_modes_": self.num_modes_,
        }

    def set_extra_state(self, state: dict) -> None:
        if not isinstance(state, dict) or "num_modes_" not in state:
            raise ValueError("ShardedPOD state: the extra state is missing or not a dict")
        for field in ("energy_tolerance", "num_modes"):
            if state.get(field) != getattr(self, field):
                raise ValueError(
                    f"{field}: the state was saved with {field}={state.get(field)!r} but this "
                    f"module has {field}={getattr(self, field)!r}"
                )
        self.num_modes_ = state["num_modes_"]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        for name in self._BUFFERS:  # the state's shapes and dtype, on this module's device
            incoming, current = state_dict.get(prefix + name), self._buffers.get(name)
            if isinstance(incoming, Tensor) and current is not None:
                self._buffers[name] = torch.empty(
                    incoming.shape, dtype=incoming.dtype, device=current.device
                )
        modes, projection = (
            state_dict.get(prefix + "modes_"),
            state_dict.get(prefix + "projection_"),
        )
        extra = state_dict.get(prefix + "_extra_state")
        if isinstance(modes, Tensor) and isinstance(projection, Tensor) and isinstance(extra, dict):
            count = extra.get("num_modes_")
            fitted = count is not None
            if fitted and (modes.shape[:1] != (count,) or projection.shape[:1] != (count,)):
                raise ValueError(
                    f"ShardedPOD state: modes_ {tuple(modes.shape)} and projection_ "
                    f"{tuple(projection.shape)} do not both hold num_modes_={count} modes"
                )
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

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
            raise TypeError(
                f"morph must be a ShardedIDW or a ShardedMeshMorph, got {type(morph).__name__}"
            )
        if (
            not isinstance(displacements, Tensor)
            or displacements.ndim != 3
            or displacements.shape[1:] != (count_in, 3)
        ):
            shape = (
                tuple(displacements.shape)
                if isinstance(displacements, Tensor)
                else type(displacements).__name__
            )
            raise ValueError(f"displacements must have shape (n_train, {count_in}, 3), got {shape}")
        group = morph.group
        with torch.no_grad():
            inputs = displacements.to(idw.controls.device, idw.controls.dtype)
            if isinstance(morph, ShardedMeshMorph):
                inputs = morph.controls_from_boundary(inputs)
            snapshots = idw(inputs)
            modes, singular_values, energy = sharded_pod_basis(
                snapshots,
                energy_tolerance=self.energy_tolerance,
                num_modes=self.num_modes,
                group=group,
            )
            if idw.num_targets:
                projection = _transpose_apply(idw, modes)
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
            raise RuntimeError(
                "this ShardedPOD is not fitted yet: call fit(morph, displacements) first"
            )
        morph = self.__dict__["_morph"]
        if isinstance(morph, ShardedMeshMorph):
            check_vectors(displacement, "displacement", morph.num_boundary, what="boundary nodes")
            displacement = morph.controls_from_boundary(displacement)
        else:
            check_vectors(displacement, "displacement", morph.num_controls, what="control points")
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
            *beta.shape[:-1], -1, 3
        )
        morph = self.__dict__["_morph"]
        if isinstance(morph, ShardedMeshMorph):
            return morph._assemble(displacement, interior)
        return interior

    def extra_repr(self) -> str:
        return (
            f"energy_tolerance={self.energy_tolerance:g}, num_modes={self.num_modes}, "
            f"num_modes_={self.num_modes_}"
        )


def _transpose_apply(idw, modes: Tensor) -> Tensor:
    """P = Zᵀ (W ⊗ I_3) for a local IDW's rows, in the (N, N_c, 3) layout: one GEMM with a
    stored W, else the vector-Jacobian product of the (linear) morph for all N modes in
    one batched call (W is never formed)."""
    weights = getattr(idw, "weights", None)
    if isinstance(weights, Tensor):
        return projection_matrix(modes, weights)
    with torch.enable_grad():
        probe = modes.new_zeros(modes.shape[0], idw.num_controls, 3, requires_grad=True)
        (projection,) = torch.autograd.grad(idw(probe), probe, grad_outputs=modes)
    return projection.contiguous()
