"""The :class:`RBF` module: the geometry, the factorised interpolation system and, in dense
mode, the evaluation matrix as registered buffers, over :mod:`torchmorph.rbf.system` and
:mod:`torchmorph.rbf.functional`."""

from __future__ import annotations

import time
from typing import Literal

import torch
from torch import Tensor, nn

from torchmorph import _dense as dense
from torchmorph._checks import (
    as_points,
    check_choice,
    check_positive,
    check_same_device_dtype,
    check_vectors,
)
from torchmorph._memory import free_memory
from torchmorph._state import (
    apply_keeping_dtypes,
    check_saved_hyperparameters,
    resize_buffers_for_load,
)
from torchmorph._threads import numba_threads
from torchmorph.rbf.functional import (
    check_distinct,
    check_options,
    columns_of,
    dim_of,
    evaluate,
    from_columns,
    rbf_interpolate,
)
from torchmorph.rbf.kernels import (
    fused,
    kernel_matrix,
    monomial_powers,
    polynomial_matrix,
    polynomial_scaling,
)
from torchmorph.rbf.system import FACTOR_NAMES, factorise, solve

__all__ = ["RBF", "Mode"]

Mode = Literal["auto", "dense", "matrix_free"]


class RBF(nn.Module):
    """Radial basis function interpolation from control points to target points, with a
    polynomial tail (scipy's :class:`~scipy.interpolate.RBFInterpolator`, no smoothing).

    ``s(x) = Σ_k λ_k φ(r_k) + p(x)·β``, ``r_k = epsilon · |x − x_k|``, with
    ``Φ λ + P β = d`` and ``Pᵀ λ = 0`` at the controls: the morph is linear in the
    control displacements d. The system is factorised once (:mod:`torchmorph.rbf.system`)
    and every call solves it for its displacements and evaluates the interpolant.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
        Control points, D = 2 or 3 (float32 or float64), pairwise distinct.
    targets : Tensor, shape (N_t, D)
        Points whose displacement is interpolated.
    kernel : str
        scipy's names: ``"thin_plate_spline"`` (r² log r, default), ``"linear"`` (−r),
        ``"cubic"`` (r³), ``"quintic"`` (−r⁵), ``"multiquadric"`` (−√(1 + r²)),
        ``"inverse_multiquadric"`` (1/√(1 + r²)), ``"inverse_quadratic"`` (1/(1 + r²)),
        ``"gaussian"`` (exp(−r²)); and Wendland's compactly supported
        ``"wendland_c0"`` ((1 − r)₊²), ``"wendland_c2"`` ((1 − r)₊⁴ (4r + 1)),
        ``"wendland_c4"`` ((1 − r)₊⁶ (35r² + 18r + 3) / 3), r = |x − x_k| / support_radius.
    epsilon : float, optional
        Shape parameter > 0 scaling the distance, as scipy's. Default 1 for the scale
        invariant kernels (linear, thin_plate_spline, cubic, quintic); required for the
        other scipy kernels; not accepted with Wendland's.
    degree : int
        Degree of the polynomial tail, -1 for none; default 1 (affine motions are then
        reproduced exactly). As scipy, the monomials are evaluated in the controls'
        bounding box shifted and scaled to [-1, 1]^D.
    support_radius : float, optional
        Required with (and only with) the Wendland kernels, > 0.
    mode : {"auto", "dense", "matrix_free"}
        ``dense`` stores the evaluation matrix ``[Φ_tc P_t]`` (N_t × (N_c + M)), so a
        call is a solve and one product; ``matrix_free`` evaluates the kernel in blocks of
        targets on every call; ``auto``: matrix-free where the fused numba kernel runs
        (the thin-plate spline in float64 on the CPU: one fused pass, 0.44 s at 5,000 ×
        50,000 on one thread, costs about the product with a stored matrix, 0.35 s, which
        first costs 2 GB and its assembly), else dense when that matrix takes at most
        ``dense_bytes``.
    block_bytes : int, optional
        Byte budget of one block of pairwise temporaries (default 4 MiB on the CPU,
        256 MiB on CUDA).
    dense_bytes : int, optional
        Threshold of ``mode="auto"`` (default half the memory the device has free).

    Attributes
    ----------
    controls, targets : buffers
        The geometry (copies of the inputs, unless these require grad).
    shift, poly_scale : buffers, shape (D,), float64
        The polynomial's centre and half extent (scipy's ``_shift`` and ``_scale``).
    qr, tau, factor, coupling, pivots : buffers, float64
        The factorisation (:mod:`torchmorph.rbf.system`; ``solver`` says which kind).
    evaluation : buffer, shape (N_t, N_c + M), dense mode only
    fit_time, evaluation_time : float
        Seconds spent factorising and (dense mode) assembling the evaluation matrix.

    Raises
    ------
    ValueError
        Naming the argument: points not (N, D), empty, NaN or infinite, or on another
        device or dtype; an unknown kernel; epsilon or support_radius missing, not > 0 or
        given where they do not apply; degree < -1; fewer controls than monomials;
        coinciding controls, or controls on which the polynomial or the system is singular.

    Notes
    -----
    The factorisation and the solves are in float64 whatever the points' dtype (float32
    RBF systems are too ill-conditioned); a float32 module evaluates and returns float32.
    The Wendland kernels' compact support is not exploited: their matrices are dense.
    The thin-plate spline in float64 on the CPU runs fused numba kernels
    (:mod:`torchmorph.rbf._numba`, one thread whatever ``torch.get_num_threads()``);
    the other kernels, float32, CUDA and calls differentiated in the positions run torch
    blocks (the fused pass is differentiable in the displacements: its backward pass is
    the same kernel with targets and controls swapped).
    The factorisation is LAPACK's (Cholesky, or LU), O(N_c³): about 1 s for 5,000
    controls on one thread, most of a fit.

    Dense mode stores ``[Φ_tc P_t]`` and solves for the coefficients on every call
    (O(N_c²) per value column with the stored factor) rather than the operator
    ``[Φ_tc P_t] · (system⁻¹)[:, :N_c]``: the two take the same memory, and forming the
    operator costs N_t · N_c² multiply-adds (2.5 · 10¹² at 5,000 × 50,000), far more
    than every solve a morphing run makes.

    Gradients flow to the displacements. Pass moved ``controls``/``targets`` to
    :meth:`forward` (or build the module from points that require grad) to differentiate
    in the positions: the system is then assembled and solved again (by
    :func:`~torchmorph.rbf.functional.rbf_interpolate`) on that call.

    :meth:`state_dict` holds the geometry, the factorisation, the evaluation matrix in
    dense mode, and as extra state ``kernel``, ``epsilon``, ``degree``,
    ``support_radius`` (loading a state saved with other values raises naming the field),
    ``solver`` and ``mode`` (a dense state loads into a matrix-free module and the
    reverse, the evaluation matrix dropped or assembled).
    """

    controls: Tensor
    targets: Tensor
    shift: Tensor
    poly_scale: Tensor
    evaluation: Tensor | None

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        kernel: str = "thin_plate_spline",
        epsilon: float | None = None,
        degree: int = 1,
        support_radius: float | None = None,
        mode: Mode = "auto",
        block_bytes: int | None = None,
        dense_bytes: int | None = None,
    ) -> None:
        super().__init__()
        controls = as_points(controls, "controls", dim=dim_of(controls))
        targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True)
        check_same_device_dtype(controls, "controls", targets, "targets")
        check_choice(mode, "mode", ("auto", "dense", "matrix_free"))
        self.kernel, self.epsilon, self.degree, self.support_radius, self.scale = check_options(
            kernel, epsilon, degree, support_radius, controls.shape[0], controls.shape[1]
        )
        self.block_bytes = (
            None if block_bytes is None else int(check_positive(block_bytes, "block_bytes"))
        )
        dense_budget = (
            free_memory(controls.device) // 2
            if dense_bytes is None
            else int(check_positive(dense_bytes, "dense_bytes"))
        )
        check_distinct(controls)
        self.powers = monomial_powers(controls.shape[1], self.degree)
        self.register_buffer("controls", controls if controls.requires_grad else controls.clone())
        self.register_buffer("targets", targets if targets.requires_grad else targets.clone())
        size = targets.shape[0] * (controls.shape[0] + len(self.powers)) * controls.element_size()
        if mode == "auto":
            streamed = fused(self.kernel, controls)  # a fused pass costs about a product
            mode = "dense" if size <= dense_budget and not streamed else "matrix_free"
        self.mode: str = mode
        start = time.perf_counter()
        with torch.no_grad():
            work = self.controls.detach().double()
            shift, poly_scale = polynomial_scaling(work)
            self.solver, factors = factorise(
                work, self.kernel, self.scale, self.degree, self.powers, shift, poly_scale
            )
        self.fit_time = time.perf_counter() - start
        self.register_buffer("shift", shift)
        self.register_buffer("poly_scale", poly_scale)
        for name in FACTOR_NAMES:
            self.register_buffer(name, factors[name])
        self.evaluation_time = 0.0
        if mode == "dense":
            self.register_buffer("evaluation", self._assemble())
        else:
            self.evaluation = None

    # ------------------------------------------------------------------ views
    @property
    def num_controls(self) -> int:
        return self.controls.shape[0]

    @property
    def num_targets(self) -> int:
        return self.targets.shape[0]

    def _factors(self) -> dict[str, Tensor]:
        return {name: self._buffers[name] for name in FACTOR_NAMES}  # type: ignore[misc]

    def _apply(self, fn, recurse=True):
        """``.to``, ``.cuda``, ``.float()`` …: the factorisation and the polynomial's
        scaling move with the module but stay float64 (see the class notes); the points
        and the evaluation matrix take the new dtype."""
        apply_keeping_dtypes(self, fn, recurse, (*FACTOR_NAMES, "shift", "poly_scale"))
        return self

    def _assemble(self) -> Tensor:
        """The evaluation matrix [Φ_tc P_t], in blocks, in the points' dtype."""
        start = time.perf_counter()
        with torch.no_grad():
            targets, controls = self.targets.detach(), self.controls.detach()
            work = controls.double()
            count = len(self.powers)
            matrix = torch.empty(
                self.num_targets,
                self.num_controls + count,
                dtype=controls.dtype,
                device=controls.device,
            )
            kernel_part = matrix[:, : self.num_controls]
            if matrix.dtype == torch.float64:  # written in place, block by block
                kernel_matrix(targets, work, self.kernel, self.scale, out=kernel_part)
            else:  # float64 blocks, stored in the points' dtype
                rows = max(1, (self.block_bytes or (64 << 20)) // (8 * (self.num_controls + 1)))
                for begin in range(0, self.num_targets, rows):
                    kernel_part[begin : begin + rows] = kernel_matrix(
                        targets[begin : begin + rows].double(), work, self.kernel, self.scale
                    )
            if count:
                matrix[:, self.num_controls :] = polynomial_matrix(
                    targets.double(), self.powers, self.shift, self.poly_scale
                )
        self.evaluation_time = time.perf_counter() - start
        return matrix

    def coefficients(self, displacements: Tensor) -> tuple[Tensor, Tensor]:
        """(λ (N_c, S), β (M, S)), float64, for control values (N_c, S) or a batch
        (B, N_c, D) (then S = B·D, batch-major): the stored factorisation solved."""
        values = columns_of(displacements).double()
        return solve(self.solver, self._factors(), values)

    # ------------------------------------------------------------------ state
    def _hyperparameters(self) -> dict[str, object]:
        return {
            "kernel": self.kernel,
            "epsilon": self.epsilon,
            "degree": self.degree,
            "support_radius": self.support_radius,
        }

    def get_extra_state(self) -> dict:
        return {**self._hyperparameters(), "solver": self.solver, "mode": self.mode}

    def set_extra_state(self, state: dict) -> None:
        check_saved_hyperparameters("RBF", state, self._hyperparameters())
        self.solver = state.get("solver", self.solver)

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        extra = state_dict.get(prefix + "_extra_state")
        if extra is not None:  # before anything is loaded
            check_saved_hyperparameters("RBF", extra, self._hyperparameters())
        key = prefix + "evaluation"
        has_evaluation = key in state_dict
        if self.mode == "matrix_free" and has_evaluation:
            state_dict = {k: v for k, v in state_dict.items() if k != key}
        names = ("controls", "targets", *FACTOR_NAMES, "evaluation")
        resize_buffers_for_load(self, state_dict, prefix, names)
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        if self.mode == "dense" and not has_evaluation:
            if key in missing_keys:
                missing_keys.remove(key)
            self._buffers["evaluation"] = self._assemble()
        evaluation = self._buffers.get("evaluation")
        width = self.num_controls + len(self.powers)
        if evaluation is not None and evaluation.shape != (self.num_targets, width):
            error_msgs.append(
                f"evaluation: shape {tuple(evaluation.shape)} does not match "
                f"{self.num_targets} targets x {width} columns"
            )

    # ---------------------------------------------------------------- forward
    def forward(
        self,
        displacements: Tensor,
        *,
        controls: Tensor | None = None,
        targets: Tensor | None = None,
    ) -> Tensor:
        """Interpolate control displacements to the targets.

        Parameters
        ----------
        displacements : Tensor, shape (N_c, D) or (B, N_c, D)
        controls, targets : Tensor, optional
            Moved positions (the reference's shapes) to use instead of the stored ones:
            the system is assembled and solved again, differentiably.

        Returns
        -------
        Tensor, shape (N_t, D) or (B, N_t, D)
        """
        dim = self.controls.shape[1]
        check_vectors(
            displacements, "displacements", self.num_controls, dim=dim, what="control points"
        )
        check_same_device_dtype(
            self.controls, "the module's controls", displacements, "displacements"
        )
        moved = controls is not None or targets is not None
        if controls is not None:
            controls = self._check_moved(controls, self.controls, "controls")
        if targets is not None:
            targets = self._check_moved(targets, self.targets, "targets")
        geometry_grad = self.controls.requires_grad or self.targets.requires_grad
        if moved or (torch.is_grad_enabled() and geometry_grad):
            return rbf_interpolate(
                controls=self.controls if controls is None else controls,
                targets=self.targets if targets is None else targets,
                displacements=displacements,
                kernel=self.kernel,
                epsilon=None if self.support_radius is not None else self.epsilon,
                degree=self.degree,
                support_radius=self.support_radius,
                block_bytes=self.block_bytes,
            )
        weights, poly_coefficients = self.coefficients(displacements)
        if self.evaluation is not None:
            both = torch.cat([weights, poly_coefficients]).to(self.evaluation.dtype)
            result = _evaluation_product(self.evaluation, both)
        else:
            result = evaluate(
                self.targets.detach().double(),
                self.controls.detach().double(),
                weights,
                poly_coefficients,
                kernel=self.kernel,
                scale=self.scale,
                powers=self.powers,
                shift=self.shift,
                poly_scale=self.poly_scale,
                block_bytes=self.block_bytes,
            ).to(displacements.dtype)
        return from_columns(result, displacements)

    @staticmethod
    def _check_moved(moved: Tensor, reference: Tensor, name: str) -> Tensor:
        if not isinstance(moved, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(moved).__name__}")
        if moved.shape != reference.shape:
            raise ValueError(
                f"{name} must have shape {tuple(reference.shape)}, got {tuple(moved.shape)}"
            )
        check_same_device_dtype(reference, f"the module's {name}", moved, name)
        return as_points(moved, name, dim=reference.shape[1], allow_empty=True)

    def extra_repr(self) -> str:
        scale = (
            f"support_radius={self.support_radius:g}"
            if self.support_radius is not None
            else f"epsilon={self.epsilon:g}"
        )
        return (
            f"num_controls={self.num_controls}, num_targets={self.num_targets}, "
            f"kernel={self.kernel!r}, {scale}, degree={self.degree}, mode={self.mode!r}, "
            f"solver={self.solver!r}"
        )


def _evaluation_product(matrix: Tensor, values: Tensor) -> Tensor:
    """The stored evaluation matrix times the coefficients (N_c + M, S): the pass of
    :mod:`torchmorph._dense` that reads the matrix once per three columns where it applies
    (torch's ``mm`` took 3.4× as long for three columns at 50,000 × 5,004), on torch's
    thread count; otherwise torch's product."""
    if dense.applies(matrix, values):
        with numba_threads():
            return dense.dense_product(matrix, values)
    return matrix @ values
