"""POD-reduced IDW morphing: POD-(E)SIDW, Algorithm 3 of SPEC.md §4.

The IDW (or selective IDW) map ``d_int = W d_sel`` is linear, but ``W`` is large:
N_int × N_sel entries, read once per parameter value. For a parametrized family of
control displacements ``d_sel(μ)`` the interior fields ``W d_sel(μ)`` usually lie
close to a space of very few dimensions. :class:`PODReducer` finds that space
offline (proper orthogonal decomposition of snapshots) and, online, maps a control
displacement to the reduced coefficients with an N × 3N_sel matrix, so that a new
parameter value costs O(N·N_sel + N·N_int) instead of O(N_int·N_sel).

The maths lives in plain functions over dense tensors (:func:`pod_basis`,
:func:`projection_matrix`, :func:`paper_matrices`); :class:`PODReducer` is the
estimator on top (``fit`` / ``forward``) whose state is held in buffers.

Layout. A displacement field on M points is a tensor (M, 3); flattened it is the
component-interleaved vector of length 3M (x1, y1, z1, x2, ...). The POD basis
``Z`` (3·N_int × N in SPEC.md) is stored as ``modes`` of shape (N, N_int, 3):
``modes[l]`` is the l-th mode as a displacement field. ``W`` acts on each component
separately (the operator on flattened fields is W ⊗ I_3); no Kronecker matrix is
ever formed.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor, nn

from ._checks import check_finite, check_float_dtype, check_same_device_dtype, is_traced
from .idw import IDW
from .mesh import TetMesh
from .morph import MeshMorph
from .quality import relative_l2_error

__all__ = [
    "PODReducer",
    "paper_matrices",
    "pod_basis",
    "projection_matrix",
]

OnlineVariant = Literal["projection", "paper"]
_ONLINE_VARIANTS = ("projection", "paper")

Family = Callable[[Tensor], Tensor]



# --------------------------------------------------------------------------------------
# functional core
# --------------------------------------------------------------------------------------


def _num_modes_for_energy(energies: Tensor, energy_tolerance: float) -> int:
    """Smallest N with sum_{i>N} σ_i² <= ε sum_i σ_i² (paper eq. 12), from the σ_i²."""
    energy = energies.double()
    total = float(energy.sum())
    # tail[N] = sum_{i>N} σ_i², summed from the small end for accuracy
    tail = torch.flip(torch.cumsum(torch.flip(energy, (0,)), 0), (0,))
    tail = torch.cat([tail[1:], tail.new_zeros(1)])
    below = torch.nonzero(tail <= energy_tolerance * total).flatten()
    return int(below[0]) + 1


def _numerical_rank(singular_values: Tensor, shape: tuple[int, int], dtype: torch.dtype) -> int:
    """Number of singular values above σ_1 · sqrt(m·n) · eps(dtype)."""
    if singular_values.numel() == 0 or float(singular_values[0]) == 0.0:
        return 0
    eps = torch.finfo(dtype).eps
    tolerance = float(singular_values[0]) * math.sqrt(shape[0] * shape[1]) * eps
    return int((singular_values > tolerance).sum())


_CORRELATION_MIN_ASPECT = 4
"""The method of snapshots is tried when the snapshots' length is at least this many
times their number (a 20 × 66,000 matrix: the correlation matrix is 20 × 20)."""

_SAFE_SQUARES = (1e-250, 1e250)
"""Largest squared snapshot norm for which the snapshots are used unscaled."""

_SUBSPACE_TOLERANCE = 1e-10
"""Largest error of the kept modes' span (float64 outputs; float32 outputs allow their
own eps) for which the method of snapshots is used rather than the thin SVD."""


def _kept_modes(energies: Tensor, energy_tolerance: float, num_modes: int | None,
                count: int) -> int:
    if num_modes is None:
        return _num_modes_for_energy(energies, energy_tolerance)
    if num_modes > count:
        raise ValueError(f"num_modes={num_modes} exceeds the number of snapshots ({count})")
    return num_modes


def _check_rank(num_modes: int | None, singular_values: Tensor, shape: tuple[int, int],
                dtype: torch.dtype) -> None:
    if num_modes is None:
        return
    rank = _numerical_rank(singular_values, shape, dtype)
    if num_modes > rank:
        raise ValueError(
            f"num_modes={num_modes} exceeds the numerical rank {rank} of the snapshots "
            f"(singular values {singular_values[:num_modes].tolist()})"
        )


def _svd_basis(matrix: Tensor, energy_tolerance: float, num_modes: int | None,
               dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Thin SVD of the (scaled, float64) n × 3M matrix Uᵀ: rows of modes, all σ."""
    _, singular_values, vh = torch.linalg.svd(matrix, full_matrices=False)
    kept = _kept_modes(singular_values.square(), energy_tolerance, num_modes, matrix.shape[0])
    _check_rank(num_modes, singular_values, tuple(matrix.shape), dtype)
    return vh[:kept], singular_values


def _correlation_basis(matrix: Tensor, correlation: Tensor, energy_tolerance: float,
                       num_modes: int | None, dtype: torch.dtype
                       ) -> tuple[Tensor, Tensor] | None:
    """Method of snapshots on the float64 n × 3M matrix Uᵀ and its correlation
    matrix UᵀU, or None where it would lose accuracy on the kept modes.

    The eigen-decomposition UᵀU = V Σ² Vᵀ gives the modes as Σ⁻¹ Vᵀ Uᵀ at the cost of
    two passes over U, but squares the condition number: the span of the first N
    modes is accurate to about eps · σ_1² / (σ_N² − σ_{N+1}²). Where that exceeds the
    tolerance, None is returned (the caller runs the thin SVD). The modes are
    re-orthonormalised by a QR factorisation (3M × N, cheap for few modes).
    """
    count = matrix.shape[0]
    eigenvalues, vectors = torch.linalg.eigh(correlation)
    eigenvalues = eigenvalues.flip(0).clamp_min(0.0)
    kept = _kept_modes(eigenvalues, energy_tolerance, num_modes, count)
    following = float(eigenvalues[kept]) if kept < count else 0.0
    gap = float(eigenvalues[kept - 1]) - following
    tolerance = max(_SUBSPACE_TOLERANCE, torch.finfo(dtype).eps)
    if gap <= 0.0 or torch.finfo(torch.float64).eps * float(eigenvalues[0]) > tolerance * gap:
        return None
    singular_values = eigenvalues.sqrt()
    _check_rank(num_modes, singular_values, tuple(matrix.shape), dtype)
    leading = vectors[:, count - kept :].flip(1)  # (n, N), descending
    rough = (leading.mT @ matrix) / singular_values[:kept].unsqueeze(1)  # (N, 3M)
    basis, triangle = torch.linalg.qr(rough.mT)  # (3M, N): orthonormal columns
    signs = torch.sign(triangle.diagonal())  # QR may flip a column: keep each mode's sign
    basis = basis * torch.where(signs == 0, 1.0, signs)
    return basis.mT, singular_values


def pod_basis(
    snapshots: Tensor,
    *,
    energy_tolerance: float = 1e-5,
    num_modes: int | None = None,
    method: Literal["auto", "svd", "correlation"] = "auto",
) -> tuple[Tensor, Tensor, Tensor]:
    """POD basis of a set of displacement fields (the paper's section 3, eqs. 9–12).

    Parameters
    ----------
    snapshots : Tensor, shape (n, M, 3)
        ``n`` fields on ``M`` points, the columns of the snapshot matrix ``U``
        (each flattened component-interleaved to length 3M).
    energy_tolerance : float
        ε in (0, 1): N is the smallest number of modes with
        ``sum_{i>N} σ_i² <= ε · sum_i σ_i²``. Ignored when ``num_modes`` is given.
    num_modes : int, optional
        Keep exactly this many modes.
    method : {"auto", "svd", "correlation"}
        ``"svd"``: thin SVD of Uᵀ. ``"correlation"``: the method of snapshots
        (eigen-decomposition of the n × n correlation matrix, then a Rayleigh–Ritz
        step), falling back to the SVD when it would lose accuracy on the kept
        modes (see Notes). ``"auto"`` (default): ``"correlation"`` when 3M >= 4n.

    Returns
    -------
    modes : Tensor, shape (N, M, 3)
        Orthonormal modes (the first N left singular vectors of U), in the
        snapshots' dtype.
    singular_values : Tensor, shape (min(n, 3M),)
        All singular values of U, descending (float64 arithmetic, snapshots' dtype).
    energy_captured : Tensor, shape (min(n, 3M),)
        ``energy_captured[k] = sum_{i<=k+1} σ_i² / sum_i σ_i²``: the energy fraction
        kept by k + 1 modes.

    Raises
    ------
    ValueError
        If the snapshots are not (n, M, 3), are half precision, hold NaN/inf, are
        all zero, if ε is outside (0, 1), or ``num_modes`` exceeds the number of
        snapshots or their numerical rank (singular values above
        σ_1 · sqrt(3M·n) · eps).

    Notes
    -----
    Computed in float64 whatever the input dtype. Snapshots whose squared norms
    leave [1e-250, 1e250] are first divided by a power of two near their largest
    entry (exactly), so that norms from 1e-300 to 1e300 neither underflow nor
    overflow when squared; the singular values are scaled back.

    The correlation route squares the condition number: the span of the N kept
    modes is accurate to about eps · σ_1² / (σ_N² − σ_{N+1}²). It is used only
    where that is below 1e-10 (float64 snapshots) or float32's eps (float32
    snapshots); otherwise the thin SVD runs. At case-B size (20 × 66,000) it takes
    a few milliseconds against about 0.1 s for the SVD. Its singular values are
    those of the correlation matrix: σ_i is accurate to about eps · σ_1² / σ_i, so
    values below about 1e-7 · σ_1 are rounding noise (use ``method="svd"`` to
    resolve them). The signs of the modes are arbitrary.
    """
    if not isinstance(snapshots, Tensor):
        raise TypeError(f"snapshots must be a torch.Tensor, got {type(snapshots).__name__}")
    if snapshots.ndim != 3 or snapshots.shape[-1] != 3 or snapshots.shape[0] == 0:
        raise ValueError(f"snapshots must have shape (n, M, 3) with n >= 1, got "
                         f"{tuple(snapshots.shape)}")
    check_float_dtype(snapshots, "snapshots")
    energy_tolerance = _check_energy_tolerance(energy_tolerance)
    num_modes = _check_num_modes(num_modes)
    if method not in ("auto", "svd", "correlation"):
        raise ValueError(f"method must be 'auto', 'svd' or 'correlation', got {method!r}")
    count, num_points = snapshots.shape[0], snapshots.shape[1]

    # U^T = V Σ Z^T: the rows of Vh are the modes, already in the (N, M·3) layout
    matrix = snapshots.detach().reshape(count, 3 * num_points)
    work = matrix if matrix.dtype == torch.float64 else matrix.double()
    correlation = work @ work.mT
    largest = float(correlation.diagonal().max())  # the largest squared snapshot norm
    extent = 1.0
    if not math.isfinite(largest) or not (_SAFE_SQUARES[0] <= largest <= _SAFE_SQUARES[1]):
        # NaN/inf entries, all zero, or squares outside float64's comfortable range:
        # divide by a power of two near the largest entry (exact) and start again
        check_finite(snapshots, "snapshots")
        low, high = torch.aminmax(matrix)
        if max(-float(low), float(high)) == 0.0:
            raise ValueError("snapshots are all zero: there is no displacement to reduce")
        extent = 2.0 ** math.frexp(max(-float(low), float(high)))[1]
        work = matrix.to(torch.float64, copy=True).div_(extent)
        correlation = work @ work.mT
    result = None
    if method == "correlation" or (
        method == "auto" and 3 * num_points >= _CORRELATION_MIN_ASPECT * count
    ):
        result = _correlation_basis(work, correlation, energy_tolerance, num_modes,
                                    snapshots.dtype)
    if result is None:
        result = _svd_basis(work, energy_tolerance, num_modes, snapshots.dtype)
    rows, scaled_values = result
    kept = rows.shape[0]
    energy = scaled_values.square()
    energy_captured = torch.cumsum(energy, 0) / energy.sum()
    modes = rows.reshape(kept, num_points, 3).to(snapshots.dtype).contiguous()
    return (
        modes,
        (scaled_values * extent).to(snapshots.dtype),
        energy_captured.to(snapshots.dtype),
    )


def _fields_as_columns(fields: Tensor) -> Tensor:
    """(N, M, 3) -> (M, 3N): column c·... of each component side by side, per row point."""
    count, num_points, _ = fields.shape
    return fields.permute(1, 0, 2).reshape(num_points, 3 * count)


def _columns_as_fields(columns: Tensor, count: int) -> Tensor:
    """Inverse of :func:`_fields_as_columns`: (M, 3N) -> (N, M, 3), contiguous."""
    num_points = columns.shape[0]
    return columns.reshape(num_points, count, 3).permute(1, 0, 2).contiguous()


def _check_modes_weights(modes: Tensor, weights: Tensor) -> None:
    if modes.ndim != 3 or modes.shape[-1] != 3:
        raise ValueError(f"modes must have shape (N, N_int, 3), got {tuple(modes.shape)}")
    if weights.ndim != 2 or weights.shape[0] != modes.shape[1]:
        raise ValueError(
            f"weights must have shape ({modes.shape[1]}, N_sel) to match modes "
            f"{tuple(modes.shape)}, got {tuple(weights.shape)}"
        )


def projection_matrix(modes: Tensor, weights: Tensor) -> Tensor:
    """Online matrix of the ``projection`` variant: P = Zᵀ (W ⊗ I_3) (SPEC.md §4).

    Parameters
    ----------
    modes : Tensor, shape (N, N_int, 3)
        Orthonormal POD modes (``Z``).
    weights : Tensor, shape (N_int, N_sel)
        The (S)IDW matrix ``W``.

    Returns
    -------
    Tensor, shape (N, N_sel, 3)
        ``P[l, k, c] = sum_i modes[l, i, c] · W[i, k]``, so that for a control
        displacement ``d`` (N_sel, 3) the coefficients are
        ``β = P.reshape(N, -1) @ d.reshape(-1) = Zᵀ vec(W d)``: the orthogonal
        projection of the full morph onto the POD space.

    Notes
    -----
    One GEMM, (3N × N_int) · (N_int × N_sel): W is streamed once for all 3N
    columns (mat-vecs per column would stream it 3N times).
    """
    _check_modes_weights(modes, weights)
    fields = _fields_as_columns(modes.to(weights.dtype))  # (N_int, 3N)
    columns = (fields.mT @ weights).mT  # (N_sel, 3N)
    return _columns_as_fields(columns, modes.shape[0])


def _pseudo_inverse_apply(weights: Tensor, columns: Tensor) -> Tensor:
    """W⁺ @ columns (minimum-norm least squares), float64."""
    weights = weights.double()
    columns = columns.double()
    if weights.device.type == "cpu":
        # rank-revealing complete orthogonal factorisation; minimum-norm solution
        return torch.linalg.lstsq(weights, columns, driver="gelsy").solution
    return torch.linalg.pinv(weights) @ columns


def paper_matrices(modes: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Online matrices of the paper's variant (paper eq. 16, SPEC.md §4).

    The paper writes the control displacement as the least-squares preimage of
    the interior field, ``d_sel ≈ W⁺ Z β`` (eq. 15), and computes β from the
    normal equations of that system:

        Zᵀ (W⁺)ᵀ W⁺ Z β = Zᵀ (W⁺)ᵀ d_sel.                      (16)

    Parameters
    ----------
    modes : Tensor, shape (N, N_int, 3)
        Orthonormal POD modes (``Z``).
    weights : Tensor, shape (N_int, N_sel)
        The (S)IDW matrix ``W``; ``W⁺`` (N_sel × N_int) is its Moore–Penrose
        pseudo-inverse, applied per component.

    Returns
    -------
    system_matrix : Tensor, shape (N, N)
        ``A = Zᵀ (W⁺)ᵀ W⁺ Z`` (symmetric positive definite).
    rhs_matrix : Tensor, shape (N, N_sel, 3)
        ``B = Zᵀ (W⁺)ᵀ`` in the displacement layout: the right-hand side of (16)
        is ``B.reshape(N, -1) @ d_sel.reshape(-1)``.

    Notes
    -----
    ``W⁺ Z`` is computed without forming W⁺ (minimum-norm least squares with a
    rank-revealing QR, LAPACK ``gelsy``, in float64; on other devices through
    ``torch.linalg.pinv``). This costs O(N_int · N_sel · min(N_int, N_sel)) — the
    dominant offline cost of the paper's method (minutes at case-B size) and the
    reason ``projection`` is the default. Results are returned in ``weights``'
    dtype. When W has full rank and the field lies in the POD space, (16) gives
    the exact coefficients; otherwise it weights the error by (W⁺)ᵀW⁺ and is never
    more accurate (in the Euclidean norm of the interior field) than the
    projection.
    """
    _check_modes_weights(modes, weights)
    count = modes.shape[0]
    preimage = _pseudo_inverse_apply(weights, _fields_as_columns(modes))  # (N_sel, 3N)
    rhs = _columns_as_fields(preimage, count)  # (N, N_sel, 3) = Z^T (W^+)^T
    flat = rhs.reshape(count, -1)
    system = flat @ flat.mT
    system = 0.5 * (system + system.mT)
    return system.to(weights.dtype), rhs.to(weights.dtype)


# --------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------


def _check_energy_tolerance(value: float) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"energy_tolerance must be a number in (0, 1), got {value!r}") from None
    if not (0.0 < number < 1.0):
        raise ValueError(f"energy_tolerance must be in (0, 1), got {value!r}")
    return number


def _check_num_modes(value: int | None) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"num_modes must be a positive integer or None, got {value!r}")
    return int(value)


def _check_online(value: str) -> str:
    if value not in _ONLINE_VARIANTS:
        raise ValueError(f"online must be one of {', '.join(map(repr, _ONLINE_VARIANTS))}, "
                         f"got {value!r}")
    return value


def _as_parameters(parameters: Any) -> Tensor:
    """Training parameters as a tensor (n,) or (n, P), finite."""
    if parameters is None:
        raise ValueError("parameters must be given with family: shape (n_train,) or "
                         "(n_train, P)")
    if not isinstance(parameters, Tensor):
        parameters = torch.as_tensor(np.asarray(parameters, dtype=np.float64))
    if parameters.ndim not in (1, 2) or parameters.shape[0] == 0:
        raise ValueError(
            f"parameters must have shape (n_train,) or (n_train, P) with n_train >= 1, "
            f"got {tuple(parameters.shape)}"
        )
    check_finite(parameters, "parameters")
    return parameters


# --------------------------------------------------------------------------------------
# the estimator
# --------------------------------------------------------------------------------------


class PODReducer(nn.Module):
    """POD-reduced (S)IDW morph: POD-(E)SIDW, Algorithm 3 (SPEC.md §4).

    Construct with hyper-parameters only, then :meth:`fit` to a morph and training
    data; afterwards ``reducer(displacement)`` returns what ``morph(displacement)``
    would, computed from the N-dimensional POD space.

    Parameters
    ----------
    energy_tolerance : float, default 1e-5
        ε in (0, 1): the number of modes N is the smallest with
        ``sum_{i>N} σ_i² <= ε · sum_i σ_i²`` (the paper's relative energy criterion).
    num_modes : int, optional
        Keep exactly this many modes instead (``fit`` raises if the snapshots have
        fewer, or lower rank).
    online : {"projection", "paper"}, default "projection"
        How the coefficients β of ``d_int ≈ Z β`` are obtained online:
        ``"projection"``: ``β = Zᵀ W d_sel`` through the precomputed
        P = Zᵀ W (N × 3N_sel) — the orthogonal projection of the full morph onto the
        POD space; ``"paper"``: solve ``A β = B d_sel`` of paper eq. 16 with
        A = Zᵀ(W⁺)ᵀW⁺Z and B = Zᵀ(W⁺)ᵀ (needs the pseudo-inverse of W offline).

    Attributes
    ----------
    modes_ : Tensor (N, N_int, 3)
        (This and the following are set by ``fit``.) Orthonormal POD basis (``Z``), mode l as a displacement field of the
        reduced points (the IDW targets, or the mesh's interior nodes).
    singular_values_ : Tensor (k,)
        All singular values of the snapshot matrix, descending (k = min(n_train, 3N_int)).
    energy_captured_ : Tensor (k,)
        Cumulative energy fraction kept by 1, 2, ..., k modes.
    num_modes_ : int
        N, the number of modes kept.
    projection_ : Tensor (N, N_sel, 3)
        P for ``online="projection"`` (empty otherwise).
    system_matrix_, rhs_matrix_ : Tensor (N, N), (N, N_sel, 3)
        A and B of eq. 16 for ``online="paper"`` (empty otherwise).
    offline_time_ : dict[str, float]
        Wall-clock seconds of the offline phase: ``"snapshots"``, ``"svd"``,
        ``"online_matrices"``, ``"total"``.
    kind_ : {"idw", "mesh"}
        The kind of morph fitted.
    family : callable or None
        The displacement family given to ``fit`` (not saved by ``state_dict``).

    Notes
    -----
    * State is in buffers: ``state_dict()`` saves a fitted reducer (the morph and
      ``W`` are not part of it) and ``load_state_dict`` into a fresh
      ``PODReducer()`` restores it, including the hyper-parameters it was fitted
      with and the loaded tensors' dtype; ``.to(device, dtype)`` moves it.
    * For a :class:`~torchmorph.morph.MeshMorph`, the reducer keeps the boundary
      and interior node indices and the selected control rows: boundary nodes
      take the prescribed displacement exactly, only the interior field is
      reduced, and the output equals ``morph.assemble(d_b, Z β)``.
    * ``forward`` checks shapes, dtype and device but not finiteness (that would
      cost more than the reduced product); NaN inputs give NaN outputs.
    * The reduced morph is exact only on the span of the training fields; check
      new parameter ranges with :meth:`relative_error`.
    * Offline cost: one batched morph of the training inputs, a thin SVD, and
      ``Wᵀ`` applied to 3N vectors (``projection``; with a matrix-free IDW through
      autograd, never forming W) — seconds at case-B size. ``paper`` needs
      ``W⁺ Z``: a least-squares solve with the dense W, O(N_int·N_sel²), about
      20 minutes at case-B size on 2 cores (extrapolated, benchmarks/README.md).
    * Online cost: one (B × 3N_in) · (3N_in × N) product and one (B × N) ·
      (N × 3N_out) product (for ``paper`` also an N × N solve). A large batch is
      bound by writing its output; pass ``out=`` to reuse one.
    * ``fit`` keeps a plain reference to the morph (for :meth:`relative_error`); it
      is not part of ``state_dict`` but is copied by ``copy.deepcopy`` / pickling.
    """

    _BUFFERS = (
        "modes_",
        "singular_values_",
        "energy_captured_",
        "projection_",
        "system_matrix_",
        "rhs_matrix_",
        "control_index_",
        "boundary_nodes_",
        "interior_nodes_",
    )

    def __init__(
        self,
        *,
        energy_tolerance: float = 1e-5,
        num_modes: int | None = None,
        online: OnlineVariant = "projection",
    ) -> None:
        super().__init__()
        self.energy_tolerance = _check_energy_tolerance(energy_tolerance)
        self.num_modes = _check_num_modes(num_modes)
        self.online = _check_online(online)
        for name in self._BUFFERS:
            dtype = torch.int64 if name.endswith(("_index_", "_nodes_")) else None
            self.register_buffer(name, torch.empty(0, dtype=dtype))
        # derived from the buffers above (rebuilt by fit and load_state_dict, moved by .to):
        # the online matrix over the input rows and the basis over the output rows
        self.register_buffer("_input_matrix", torch.empty(0), persistent=False)
        self.register_buffer("_output_basis", torch.empty(0), persistent=False)
        self.num_modes_: int | None = None
        self.kind_: str | None = None
        self.num_inputs_: int | None = None
        self.num_outputs_: int | None = None
        self.num_parameters_: int | None = None
        self.offline_time_: dict[str, float] = {}
        self.family: Family | None = None
        self._family_batched: bool | None = None
        # contiguous runs of the boundary / interior node ids (mesh), for slice copies
        self._runs: tuple[list[tuple[int, int, int]], list[tuple[int, int, int]]] | None = None
        self._morph: nn.Module | None = None

    # ---------------------------------------------------------------- fitted state

    @property
    def is_fitted(self) -> bool:
        """Whether :meth:`fit` (or ``load_state_dict`` of a fitted reducer) has run."""
        return self.num_modes_ is not None

    def _check_fitted(self) -> None:
        if not self.is_fitted:
            raise RuntimeError(
                "this PODReducer is not fitted yet: call fit(morph, displacements) or "
                "fit(morph, family=..., parameters=...) first, or load a fitted state_dict"
            )

    @property
    def num_inputs(self) -> int:
        """Rows of an input displacement: control points (IDW) or boundary nodes (mesh)."""
        self._check_fitted()
        return int(self.num_inputs_)

    @property
    def num_outputs(self) -> int:
        """Rows of an output field: targets (IDW) or all mesh nodes (mesh)."""
        self._check_fitted()
        return int(self.num_outputs_)

    def get_extra_state(self) -> dict[str, Any]:
        return {
            "energy_tolerance": self.energy_tolerance,
            "num_modes": self.num_modes,
            "online": self.online,
            "num_modes_": self.num_modes_,
            "kind_": self.kind_,
            "num_inputs_": self.num_inputs_,
            "num_outputs_": self.num_outputs_,
            "num_parameters_": self.num_parameters_,
            "offline_time_": dict(self.offline_time_),
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.energy_tolerance = _check_energy_tolerance(state["energy_tolerance"])
        self.num_modes = _check_num_modes(state["num_modes"])
        self.online = _check_online(state["online"])
        self.num_modes_ = state["num_modes_"]
        self.kind_ = state["kind_"]
        self.num_inputs_ = state["num_inputs_"]
        self.num_outputs_ = state["num_outputs_"]
        self.num_parameters_ = state["num_parameters_"]
        self.offline_time_ = dict(state["offline_time_"])

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
        error_msgs,
    ) -> None:
        # the buffers' shapes are only known after fit: take the incoming shape and
        # (floating) dtype, keep this module's device
        for name in self._BUFFERS:
            key = prefix + name
            current = self._buffers.get(name)
            incoming = state_dict.get(key)
            if current is None or not isinstance(incoming, Tensor):
                continue
            dtype = incoming.dtype if incoming.is_floating_point() else current.dtype
            if incoming.shape != current.shape or dtype != current.dtype:
                self._buffers[name] = torch.empty(
                    incoming.shape, dtype=dtype, device=current.device
                )
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
            error_msgs,
        )
        if self.is_fitted and not error_msgs:
            self._build_online_cache()

    def _build_online_cache(self) -> None:
        """Fold the mesh's gather and scatter into the online matrices.

        For a MeshMorph the input matrix (P, or B of eq. 16) is spread over all
        boundary rows (zeros for boundary nodes that are not control points) and the
        basis over all mesh nodes (zeros on the boundary), so that the online phase
        is two products and one boundary copy, with no temporary gathers.
        """
        online = self.projection_ if self.online == "projection" else self.rhs_matrix_
        self._runs = None
        if self.kind_ != "mesh":
            self._input_matrix, self._output_basis = online, self.modes_
            return
        boundary_runs = _index_runs(self.boundary_nodes_)
        interior_runs = _index_runs(self.interior_nodes_)
        if boundary_runs is not None and interior_runs is not None:
            self._runs = (boundary_runs, interior_runs)
        count = self.num_modes_
        spread = online.new_zeros(count, self.num_inputs_, 3)
        self._input_matrix = spread.index_copy_(1, self.control_index_, online)
        basis = self.modes_.new_zeros(count, self.num_outputs_, 3)
        self._output_basis = basis.index_copy_(1, self.interior_nodes_, self.modes_)

    def extra_repr(self) -> str:
        text = (f"energy_tolerance={self.energy_tolerance:g}, num_modes={self.num_modes}, "
                f"online={self.online!r}")
        if self.is_fitted:
            text += f", kind_={self.kind_!r}, num_modes_={self.num_modes_}"
        return text

    # ---------------------------------------------------------------- offline phase

    def fit(
        self,
        morph: nn.Module,
        displacements: Tensor | None = None,
        *,
        family: Family | None = None,
        parameters: Tensor | None = None,
        batched: bool = True,
    ) -> PODReducer:
        """Offline phase of Algorithm 3: snapshots, POD basis, online matrices.

        Parameters
        ----------
        morph : IDW or MeshMorph
            The full morph. For an :class:`~torchmorph.idw.IDW` the inputs are
            control displacements (N_c, 3) and the reduced field is the targets'
            (N_t, 3). For a :class:`~torchmorph.morph.MeshMorph` the inputs are
            boundary displacements (N_b, 3) and the reduced field is the interior
            one, ``W d_sel``; the boundary is reproduced exactly.
        displacements : Tensor, shape (n_train, N_in, 3), optional
            Training inputs. Converted to the morph's dtype and device.
        family : callable, optional
            Instead of ``displacements``: ``family(mu)`` returns the input
            displacement for parameter value(s) ``mu``. Kept as ``self.family`` for
            :meth:`morph_parameters`.
        parameters : Tensor, shape (n_train,) or (n_train, P)
            Training parameter values for ``family``.
        batched : bool, default True
            How ``family`` is called. ``True``: once with all parameters, returning
            (n_train, N_in, 3); an exception of the family propagates, and another
            shape is a ``ValueError``. ``False``: once per parameter value (a 0-d
            tensor or a (P,) tensor), returning (N_in, 3); the results are stacked.
            Either way the morph is applied once, to the whole batch. (To vectorise
            a per-value family without a loop, pass ``torch.func.vmap(family)``.)
            :meth:`morph_parameters` calls the fitted family the same way.

        Returns
        -------
        PODReducer
            ``self``, fitted.

        Raises
        ------
        TypeError
            If ``morph`` is neither an IDW nor a MeshMorph.
        ValueError
            For missing / conflicting training data, wrong shapes, NaN or inf in the
            training data, all-zero snapshots, or ``num_modes`` larger than the
            number or rank of the snapshots.
        """
        start = time.perf_counter()
        kind, idw = self._morph_kind(morph)
        reference = idw.controls
        num_inputs, num_outputs = self._morph_sizes(morph, kind)

        with torch.no_grad():
            if family is None:
                if parameters is not None:
                    raise ValueError("parameters given without family: pass family=callable "
                                     "or training displacements")
                if displacements is None:
                    raise ValueError("no training data: pass displacements (n_train, N_in, 3) "
                                     "or family= and parameters=")
                inputs = self._training_inputs(displacements, num_inputs, "displacements")
                num_parameters, family_batched = None, None
            else:
                if displacements is not None:
                    raise ValueError("pass either displacements or family= with parameters=, "
                                     "not both")
                if not callable(family):
                    raise ValueError(f"family must be callable, got {type(family).__name__}")
                parameters = _as_parameters(parameters)
                if not isinstance(batched, bool):
                    raise ValueError(f"batched must be True or False, got {batched!r}")
                inputs = _evaluate_family(family, parameters, num_inputs, batched)
                family_batched = batched
                inputs = self._training_inputs(inputs, num_inputs, "family(parameters)")
                num_parameters = 0 if parameters.ndim == 1 else int(parameters.shape[1])
            inputs = inputs.to(device=reference.device, dtype=reference.dtype)

            # (b) snapshots: one batched application of W
            if kind == "mesh":
                snapshots = idw(morph.controls_from_boundary(inputs))
            else:
                snapshots = idw(inputs)
            check_finite(snapshots, "snapshots (the morph of the training data)")
            after_snapshots = time.perf_counter()

            # (c)-(d) POD basis
            modes, singular_values, energy_captured = pod_basis(
                snapshots, energy_tolerance=self.energy_tolerance, num_modes=self.num_modes
            )
            after_svd = time.perf_counter()

            # (e) online matrices
            empty = modes.new_empty(0)
            if self.online == "projection":
                projection = _idw_transpose_apply(idw, modes)
                system, rhs = empty, empty
            else:
                system, rhs = paper_matrices(modes, _dense_weights(idw))
                projection = empty
            after_online = time.perf_counter()

        self.modes_ = modes
        self.singular_values_ = singular_values
        self.energy_captured_ = energy_captured
        self.projection_ = projection
        self.system_matrix_ = system
        self.rhs_matrix_ = rhs
        index = torch.empty(0, dtype=torch.int64, device=reference.device)
        if kind == "mesh":
            self.control_index_ = morph.selected.to(reference.device)
            self.boundary_nodes_ = morph.boundary_nodes.to(reference.device)
            self.interior_nodes_ = morph.interior_nodes.to(reference.device)
        else:
            self.control_index_ = index
            self.boundary_nodes_ = index.clone()
            self.interior_nodes_ = index.clone()
        self.num_modes_ = int(modes.shape[0])
        self.kind_ = kind
        self.num_inputs_ = num_inputs
        self.num_outputs_ = num_outputs
        self.num_parameters_ = num_parameters
        self.family = family
        self._family_batched = family_batched
        self.__dict__["_morph"] = morph  # a reference, not a submodule: not in state_dict
        self._build_online_cache()
        self.offline_time_ = {
            "snapshots": after_snapshots - start,
            "svd": after_svd - after_snapshots,
            "online_matrices": after_online - after_svd,
            "total": after_online - start,
        }
        return self

    @staticmethod
    def _morph_kind(morph: Any) -> tuple[str, IDW]:
        if isinstance(morph, IDW):
            return "idw", morph
        if isinstance(morph, MeshMorph):
            return "mesh", morph.idw
        raise TypeError(f"morph must be an IDW or a MeshMorph, got {type(morph).__name__}")

    @staticmethod
    def _morph_sizes(morph: Any, kind: str) -> tuple[int, int]:
        if kind == "mesh":
            return int(morph.num_boundary), int(morph.num_nodes)
        return int(morph.num_controls), int(morph.num_targets)

    @staticmethod
    def _training_inputs(value: Any, count: int, name: str) -> Tensor:
        if not isinstance(value, Tensor):
            value = torch.as_tensor(np.asarray(value, dtype=np.float64))
        if value.ndim != 3 or value.shape[1:] != (count, 3) or value.shape[0] == 0:
            raise ValueError(
                f"{name} must have shape (n_train, {count}, 3) with n_train >= 1, "
                f"got {tuple(value.shape)}"
            )
        check_float_dtype(value, name)
        check_finite(value, name)
        return value.detach()

    # ---------------------------------------------------------------- online phase

    def _check_input(self, displacement: Tensor, name: str) -> bool:
        self._check_fitted()
        if not isinstance(displacement, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(displacement).__name__}")
        what = "boundary nodes" if self.kind_ == "mesh" else "control points"
        count = self.num_inputs_
        if displacement.ndim not in (2, 3) or displacement.shape[-2:] != (count, 3):
            raise ValueError(
                f"{name} must have shape ({count}, 3) or (B, {count}, 3) for {count} {what}, "
                f"got {tuple(displacement.shape)}"
            )
        check_same_device_dtype(self.modes_, "the reducer", displacement, name)
        return displacement.ndim == 3

    def coefficients(self, displacement: Tensor) -> Tensor:
        """Reduced coefficients β of ``Z β ≈ W d_sel`` (online step (f)).

        Parameters
        ----------
        displacement : Tensor, shape (N_in, 3) or (B, N_in, 3)
            Control displacements (IDW) or boundary displacements (mesh).

        Returns
        -------
        Tensor, shape (N,) or (B, N)
        """
        batched = self._check_input(displacement, "displacement")
        beta = self._coefficients(displacement if batched else displacement.unsqueeze(0))
        return beta if batched else beta[0]

    def _coefficients(self, displacement: Tensor) -> Tensor:
        """(B, N_in, 3) -> (B, N): one GEMM (plus an N × N solve for ``paper``)."""
        count = self.num_modes_
        flat = displacement.reshape(displacement.shape[0], -1)
        rhs = flat @ self._input_matrix.reshape(count, -1).mT  # P d, or B d of eq. 16
        if self.online == "projection":
            return rhs
        return torch.linalg.solve(self.system_matrix_, rhs.mT).mT

    def _expand(self, beta: Tensor, displacement: Tensor, out: Tensor | None) -> Tensor:
        """(B, N) coefficients -> output fields (B, N_out, 3) (online step (g))."""
        count, batch = self.num_modes_, beta.shape[0]
        basis = self._output_basis.reshape(count, -1)
        # one mode: a broadcast product (BLAS with an inner dimension of 1 is slower)
        product = torch.mul if count == 1 else torch.matmul
        if out is None:
            field = product(beta, basis).reshape(batch, -1, 3)
        else:
            product(beta, basis, out=out.view(batch, -1))
            field = out
        if self.kind_ == "mesh":
            if is_traced(field):  # vmap has no batching rule for the in-place index_copy_
                field = field.index_copy(1, self.boundary_nodes_, displacement)
            else:
                field.index_copy_(1, self.boundary_nodes_, displacement)
        return field

    def _expand_by_runs(self, beta: Tensor, displacement: Tensor, out: Tensor | None) -> Tensor:
        """:meth:`_expand` for a mesh whose boundary and interior node ids form a few
        contiguous runs (gmsh numbers boundary nodes first): slice products and
        copies instead of a full-size product and an indexed scatter. No autograd."""
        count, batch = self.num_modes_, beta.shape[0]
        if out is None:
            out = beta.new_empty(batch, self.num_outputs_, 3)
        flat_out = out.view(batch, -1)
        flat_in = displacement.reshape(batch, -1)
        modes = self.modes_.reshape(count, -1)
        product = torch.mul if count == 1 else torch.matmul
        boundary_runs, interior_runs = self._runs
        for node, row, length in interior_runs:
            product(beta, modes[:, 3 * row : 3 * (row + length)],
                    out=flat_out[:, 3 * node : 3 * (node + length)])
        for node, row, length in boundary_runs:
            flat_out[:, 3 * node : 3 * (node + length)].copy_(
                flat_in[:, 3 * row : 3 * (row + length)])
        return out

    def forward(self, displacement: Tensor, *, out: Tensor | None = None) -> Tensor:
        """Reduced morph: what the fitted morph's ``forward`` returns, from N modes.

        Parameters
        ----------
        displacement : Tensor, shape (N_in, 3) or (B, N_in, 3)
            Control displacements (IDW: N_in = N_c) or boundary displacements
            (MeshMorph: N_in = N_b), in the reducer's dtype and device.
        out : Tensor, shape (N_out, 3) or (B, N_out, 3), optional
            Contiguous tensor to write the result into (no autograd). Reusing one
            output for many batches saves the page faults of a fresh allocation,
            which dominate a large batch (3x at case-B size, see benchmarks).

        Returns
        -------
        Tensor, shape (N_out, 3) or (B, N_out, 3)
            IDW: the targets' displacement ``Z β``. MeshMorph: the full nodal field,
            boundary nodes exactly ``displacement``, interior nodes ``Z β``.
            Differentiable with respect to ``displacement`` (without ``out``).

        Raises
        ------
        RuntimeError
            If the reducer is not fitted.
        ValueError
            On a wrong shape, dtype or device of ``displacement`` or ``out``, or
            ``out`` with a ``displacement`` that requires grad.
        """
        batched = self._check_input(displacement, "displacement")
        inputs = displacement if batched else displacement.unsqueeze(0)
        if out is not None:
            out = self._check_out(out, displacement)
            out = out if batched else out.unsqueeze(0)
        beta = self._coefficients(inputs)
        # the slice copies write into out= tensors: not for autograd, vmap, jvp or compile
        slices = self._runs is not None and not is_traced(beta) and not (
            torch.is_grad_enabled() and beta.requires_grad)
        if slices:
            result = self._expand_by_runs(beta, inputs, out)
        else:
            result = self._expand(beta, inputs, out)
        return result if batched else result[0]

    def _check_out(self, out: Tensor, displacement: Tensor) -> Tensor:
        expected = (*displacement.shape[:-2], self.num_outputs_, 3)
        if not isinstance(out, Tensor) or tuple(out.shape) != expected:
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(f"out must have shape {expected}, got {got}")
        check_same_device_dtype(self.modes_, "the reducer", out, "out")
        if not out.is_contiguous():
            raise ValueError("out must be contiguous")
        if torch.is_grad_enabled() and displacement.requires_grad:
            raise ValueError("out= does not support autograd: displacement requires grad")
        return out

    def morph_parameters(
        self, mu: Tensor | float, *, family: Family | None = None, batched: bool | None = None
    ) -> Tensor:
        """Reduced morph of parameter value(s): ``forward(family(mu))``, batched over μ.

        Parameters
        ----------
        mu : Tensor or float
            One value (a scalar, or shape (P,) for P parameters) or a batch, shape
            (B,) or (B, P). For a reducer fitted from displacements (no parameter
            shape known), a 1-D ``mu`` is a batch of scalars; pass one vector of P
            parameters as (1, P).
        family : callable, optional
            Defaults to the family given to ``fit`` (``self.family``).
        batched : bool, optional
            How the family is called (see :meth:`fit`). Default: as in ``fit`` for
            the fitted family, ``True`` for another one.

        Returns
        -------
        Tensor, shape (N_out, 3) or (B, N_out, 3)
            Differentiable with respect to ``mu`` when the family is.
        """
        self._check_fitted()
        family = self.family if family is None else family
        if family is None:
            raise RuntimeError("no displacement family: fit with family=... or pass family= "
                               "(a family is not saved by state_dict)")
        if not isinstance(mu, Tensor):
            mu = torch.as_tensor(mu, dtype=self.modes_.dtype, device=self.modes_.device)
        num_parameters = self.num_parameters_
        if num_parameters is None:  # fitted from displacements: scalars or batches only
            if mu.ndim not in (0, 1, 2):
                raise ValueError(f"mu must have shape (), (B,) or (B, P), got {tuple(mu.shape)}")
            single = mu.ndim == 0
        else:
            single_ndim = 1 if num_parameters else 0
            if mu.ndim not in (single_ndim, single_ndim + 1) or (
                num_parameters and mu.shape[-1] != num_parameters
            ):
                expected = "() or (B,)" if num_parameters == 0 else (
                    f"({num_parameters},) or (B, {num_parameters})")
                raise ValueError(f"mu must have shape {expected}, got {tuple(mu.shape)}")
            single = mu.ndim == single_ndim
        batch = mu.unsqueeze(0) if single else mu
        if batched is None:
            batched = self._family_batched if family is self.family else True
        inputs = _evaluate_family(family, batch, self.num_inputs_, batched)
        out = self(inputs)
        return out[0] if single else out

    # ---------------------------------------------------------------- a-posteriori check

    def relative_error(
        self,
        displacements: Tensor,
        *,
        morph: nn.Module | None = None,
        norm: Literal["nodal", "l2"] = "nodal",
        mesh: Any = None,
    ) -> Tensor:
        """Relative error of the reduced morph against the full one, per sample.

        Parameters
        ----------
        displacements : Tensor, shape (N_in, 3) or (B, N_in, 3)
            Inputs to compare on (fresh parameter values, not the training set).
        morph : IDW or MeshMorph, optional
            The full morph; defaults to the one given to ``fit`` (needed after
            ``load_state_dict``, which does not restore it).
        norm : {"nodal", "l2"}
            ``"nodal"``: ``||d_pod - d_full||_F / ||d_full||_F`` over all output
            nodes. ``"l2"``: the L2(Ω_h) norm of SPEC.md §5 (P1 mass matrix) through
            :func:`torchmorph.quality.relative_l2_error` (MeshMorph only).
        mesh : TetMesh, optional
            The reference mesh for ``norm="l2"``; defaults to the morph's
            ``TetMesh(morph.points, morph.tets)``.

        Returns
        -------
        Tensor, shape () or (B,)
            0 where both fields are zero, inf where only the reference is.
        """
        self._check_fitted()
        morph = self.__dict__.get("_morph") if morph is None else morph
        if morph is None:
            raise RuntimeError("no full morph to compare with: pass morph= (load_state_dict "
                               "does not restore it)")
        if norm not in ("nodal", "l2"):
            raise ValueError(f"norm must be 'nodal' or 'l2', got {norm!r}")
        batched = self._check_input(displacements, "displacements")
        inputs = displacements if batched else displacements.unsqueeze(0)
        with torch.no_grad():
            reduced = self(inputs)
            full = morph(inputs)
            if norm == "l2":
                if self.kind_ != "mesh" or not isinstance(morph, MeshMorph):
                    raise ValueError("norm='l2' needs a reducer fitted to a MeshMorph "
                                     "(the mass matrix lives on its mesh)")
                if mesh is None:
                    mesh = TetMesh(morph.points, morph.tets)
                error = relative_l2_error(mesh, reduced, full, norm="l2").to(full.dtype)
            else:
                difference = (reduced - full).flatten(1).norm(dim=1)
                scale = full.flatten(1).norm(dim=1)
                error = torch.where(
                    difference == 0, torch.zeros_like(difference), difference / scale
                )
        return error if batched else error[0]


# --------------------------------------------------------------------------------------
# helpers that talk to the morph
# --------------------------------------------------------------------------------------


_MAX_RUNS = 16
"""A node-id index splitting into more contiguous runs than this is scattered by index."""


def _index_runs(index: Tensor) -> list[tuple[int, int, int]] | None:
    """Runs of consecutive ids in ``index`` as (first id, position, length), or None if
    there are more than ``_MAX_RUNS``."""
    index = index.detach().cpu()
    if index.numel() == 0:
        return []
    breaks = torch.nonzero(index[1:] != index[:-1] + 1).flatten() + 1
    if breaks.numel() >= _MAX_RUNS:
        return None
    starts = [0, *breaks.tolist()]
    ends = [*breaks.tolist(), index.numel()]
    return [(int(index[start]), start, end - start) for start, end in zip(starts, ends,
                                                                          strict=True)]


def _evaluate_family(
    family: Family, parameters: Tensor, count: int, batched: bool
) -> Tensor:
    """Inputs (n, count, 3) for a batch of parameter values: one call with the whole
    batch (``batched``) or one call per value. Exceptions of the family propagate."""
    expected = (parameters.shape[0], count, 3)
    if batched:
        out = family(parameters)
        if not isinstance(out, Tensor) or tuple(out.shape) != expected:
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(f"family(parameters) must return shape {expected} when "
                             f"batched=True, got {got}; for a family of one parameter value "
                             "at a time pass batched=False")
        return out
    outputs = []
    for value in parameters:
        out = family(value)
        if not isinstance(out, Tensor) or tuple(out.shape) != expected[1:]:
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(f"family(mu) must return a tensor of shape {expected[1:]} for one "
                             f"parameter value, got {got}")
        outputs.append(out)
    return torch.stack(outputs)


def _dense_weights(idw: IDW) -> Tensor:
    """The IDW's W (N_t, N_c): its buffer in dense mode, else assembled now."""
    return idw.weights_matrix()


def _idw_transpose_apply(idw: IDW, modes: Tensor) -> Tensor:
    """P = Zᵀ (W ⊗ I_3) for the IDW's W, in the (N, N_c, 3) layout.

    Dense mode: one GEMM with the stored W (:func:`projection_matrix`).
    Matrix-free mode: W is never formed; since the morph is linear in the
    displacement, ``P[l] = Wᵀ modes[l]`` is the vector-Jacobian product of the
    IDW at any input, computed by autograd for all N modes in one batched call.
    """
    weights = getattr(idw, "weights", None)
    if isinstance(weights, Tensor):
        return projection_matrix(modes, weights)
    with torch.enable_grad():
        probe = modes.new_zeros(modes.shape[0], idw.num_controls, 3, requires_grad=True)
        (projection,) = torch.autograd.grad(idw(probe), probe, grad_outputs=modes)
    return projection.contiguous()
