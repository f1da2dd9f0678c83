"""The sparse RBF (:class:`SparseRBF`): the global fit of a compactly supported (Wendland)
kernel, its kernel matrix and evaluation matrix stored sparse and the kernel matrix
factorised sparse, for more controls than a dense factorisation affords."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor, nn

from torchmorph._checks import as_points, check_same_device_dtype, check_vectors
from torchmorph._state import (
    apply_keeping_dtypes,
    check_saved_hyperparameters,
    resize_buffers_for_load,
)
from torchmorph._threads import numba_threads
from torchmorph.rbf import _sparse_jit
from torchmorph.rbf.functional import (
    check_distinct,
    check_options,
    columns_of,
    dim_of,
    from_columns,
)
from torchmorph.rbf.kernels import (
    WENDLAND,
    monomial_powers,
    polynomial_matrix,
    polynomial_scaling,
)
from torchmorph.rbf.system import check_polynomial_rank

__all__ = ["SPARSE_NEIGHBOURS", "SparseRBF", "mean_neighbours"]

#: ``solver="auto"`` (:func:`~torchmorph.rbf.build_rbf`, ``MeshMorph``) takes the sparse
#: fit of a Wendland kernel only up to this many controls within the support radius of a
#: control, on average: the factorisation's fill grows with it (10⁵ controls, measured in
#: ``benchmarks/rbf_scale.py``: 20 s at 153, 60 s at 343, about 2 minutes at 609).
SPARSE_NEIGHBOURS = 400

_GRID_KEYS = 2**62  # the grid's cells are numbered in int64


class _Pairs:
    """The pairs of points within ``radius`` of the indexed ``points`` (float64, N × D), as
    CSR rows of Wendland values, on a uniform grid (:mod:`torchmorph.rbf._sparse_jit`)."""

    def __init__(self, points: np.ndarray, radius: float) -> None:
        dim = points.shape[1]
        self.radius, self.inverse = radius, 1.0 / radius
        self.low = points.min(axis=0)
        extent = points.max(axis=0) - self.low
        cells = np.floor(extent * self.inverse) + 1
        if not float(np.prod(cells)) < _GRID_KEYS:
            raise ValueError(
                f"support_radius: {radius:g} is too small for the controls' extent "
                f"({', '.join(f'{e:.3g}' for e in extent)}): more than 2^62 grid cells"
            )
        self.dims = cells.astype(np.int64)
        keys = np.empty(points.shape[0], np.int64)
        _sparse_jit.grid_keys(points, self.low, self.inverse, self.dims, keys)
        self.order = np.argsort(keys, kind="stable")
        self.points = np.ascontiguousarray(points[self.order])
        sorted_keys = keys[self.order]
        self.keys, first = np.unique(sorted_keys, return_index=True)
        self.starts = np.append(first, points.shape[0]).astype(np.int64)
        grid = np.meshgrid(*([np.arange(-1, 2)] * dim), indexing="ij")
        self.offsets = np.stack([axis.reshape(-1) for axis in grid], axis=1).astype(np.int64)

    def counts(self, queries: np.ndarray) -> np.ndarray:
        """The number of indexed points within the radius of each query."""
        counts = np.empty(queries.shape[0], np.int64)
        queries = np.ascontiguousarray(queries)
        with numba_threads():
            _sparse_jit.count_pairs(queries, *self._common(), counts)
        return counts

    def _common(self) -> tuple[Any, Any, Any, Any, float, Any, Any, float]:
        return (self.points, self.keys, self.starts, self.low, self.inverse, self.dims,
                self.offsets, self.radius**2)  # fmt: skip

    def rows(self, queries: np.ndarray, code: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indptr, columns, values): row q holds the points within the radius of query q."""
        counts = self.counts(queries)
        queries = np.ascontiguousarray(queries)
        with numba_threads():
            indptr = np.zeros(queries.shape[0] + 1, np.int64)
            np.cumsum(counts, out=indptr[1:])
            columns = np.empty(int(indptr[-1]), np.int64)
            values = np.empty(int(indptr[-1]))
            _sparse_jit.fill_pairs(
                queries, *self._common(), code, self.inverse, self.order, indptr, columns, values
            )
        return indptr, columns, values


def mean_neighbours(controls: Tensor, support_radius: float) -> float:
    """The mean number of controls within ``support_radius`` of a control (itself
    included): the kernel matrix's entries per row, counted without forming it."""
    points = controls.detach().double().cpu().numpy()
    return float(_Pairs(points, float(support_radius)).counts(points).mean())


def _product(indptr: Tensor, columns: Tensor, values: Tensor, block: np.ndarray) -> np.ndarray:
    """M @ block for M in CSR, on numba's threads."""
    out = np.empty((indptr.shape[0] - 1, block.shape[1]))
    with numba_threads():
        _sparse_jit.csr_product(
            indptr.numpy(), columns.numpy(), values.numpy(), np.ascontiguousarray(block), out
        )
    return out


class SparseRBF(nn.Module):
    """RBF interpolation by a compactly supported kernel (Wendland's C0, C2 or C4), its
    global fit factorised sparse: for many controls, the interpolant of the dense
    :class:`~torchmorph.rbf.RBF` with the same options, to rounding.

    ``s(x) = Σ_k λ_k φ(|x − x_k| / ρ) + p(x)·β`` with ``Φ λ + P β = d``, ``Pᵀ λ = 0``
    (ρ = ``support_radius``). φ vanishes from ρ on, so Φ (controls within ρ of each
    other) and the evaluation matrix B (targets within ρ of a control) are sparse; they
    are found on a uniform grid of cells ρ wide and stored in CSR. Φ is symmetric
    positive definite (Wendland's functions, in up to 3 dimensions) and is factorised
    once by SuperLU (scipy's ``splu``: a minimum-degree ordering of Φ, no pivoting).
    The system is solved by its Schur complement: ``Z = Φ⁻¹ P`` and ``S = Pᵀ Z`` at the
    fit, then per call ``λ₀ = Φ⁻¹ d``, ``β = S⁻¹ Pᵀ λ₀``, ``λ = λ₀ − Z β`` (the columns
    of a call, a batch's included, in one solve). The morph is ``B λ + P_t β``.

    A target farther than ρ from every control moves by the polynomial tail only (an
    affine motion with ``degree=1``; not at all with ``degree=-1``): choose ρ to cover
    the region that should follow the boundary. The factorisation's fill, hence its time
    and memory, grows with the neighbours per control (ρ over the spacing): measured in
    ``benchmarks/rbf_scale.py`` (10⁵ controls with 150 neighbours each: 20 s; with 600:
    2 minutes). Conjugate gradients were tried and dropped: on a wing in a box of
    walls, 10⁵ controls, 150 neighbours, they needed over 5,000 iterations for smooth
    displacements (Φ is ill-conditioned where controls crowd).

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
        Control points, D = 2 or 3 (float32 or float64), pairwise distinct, on the CPU.
    targets : Tensor, shape (N_t, D)
    kernel : {"wendland_c0", "wendland_c2", "wendland_c4"}
    support_radius : float
        ρ, in the points' units.
    degree : int
        Polynomial tail (-1: none; 0: constant; 1: linear, the default, which reproduces
        affine motions).

    Attributes
    ----------
    fit_time : float
        Seconds of the fit (the two sparse matrices, the factorisation, Z).

    Raises
    ------
    ValueError
        Naming the argument: a kernel that is not compactly supported, ``support_radius``
        not > 0 or too small for the controls' extent, coinciding or non-finite points,
        points on another device than the CPU or requiring grad, a polynomial the
        controls cannot determine.

    Notes
    -----
    The fit and the solves are float64 (numba, NumPy and SuperLU) whatever the points'
    dtype; the result has the displacements' dtype. Gradients flow to the
    displacements: the backward pass solves the same symmetric system for ``Bᵀ g``
    (the operator's exact transpose). Not to the positions (inputs that require grad
    are refused): build another module for moved points. CPU only. :meth:`state_dict`
    holds the whole fit (both matrices in CSR, Z and S); the factorisation is made
    again from the stored Φ on the first call after a load. A state loads into a module
    built with the same hyper-parameters (any points), otherwise loading raises naming
    the field.
    """

    controls: Tensor
    targets: Tensor
    poly_shift: Tensor
    poly_scale: Tensor
    kernel_indptr: Tensor
    kernel_columns: Tensor
    kernel_values: Tensor
    eval_indptr: Tensor
    eval_columns: Tensor
    eval_values: Tensor
    coupling: Tensor
    schur: Tensor

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        kernel: str = "wendland_c2",
        support_radius: float | None = None,
        degree: int = 1,
    ) -> None:
        super().__init__()
        if kernel not in WENDLAND:
            raise ValueError(
                f"kernel must be one of {', '.join(repr(k) for k in WENDLAND)} (compactly "
                f"supported; SparseRBF stores the kernel matrix sparse), got {kernel!r}; "
                "use RBF or PartitionRBF for the others"
            )
        controls = as_points(controls, "controls", dim=dim_of(controls))
        targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True)
        check_same_device_dtype(controls, "controls", targets, "targets")
        for points, name in ((controls, "controls"), (targets, "targets")):
            if points.device.type != "cpu":
                raise ValueError(
                    f"{name} must be on the CPU (SparseRBF's kernels are numba and NumPy), "
                    f"got {points.device}"
                )
            if points.requires_grad and torch.is_grad_enabled():
                raise ValueError(
                    f"{name} requires grad: SparseRBF gives gradients to the displacements "
                    "only; use RBF for gradients to the points"
                )
        self.kernel, _, self.degree, radius, _ = check_options(
            kernel, None, degree, support_radius, controls.shape[0], controls.shape[1]
        )
        assert radius is not None
        self.support_radius = float(radius)
        self.powers = monomial_powers(controls.shape[1], self.degree)
        check_distinct(controls)
        self.register_buffer("controls", controls.detach().clone())
        self.register_buffer("targets", targets.detach().clone())
        self._factor: Any = None  # SuperLU of Φ, made on first use
        start = time.perf_counter()
        with torch.no_grad():
            self._fit()
        self.fit_time = time.perf_counter() - start

    # ------------------------------------------------------------------ fit
    def _fit(self) -> None:
        work = self.controls.double()
        shift, scale = polynomial_scaling(work)
        poly = polynomial_matrix(work, self.powers, shift, scale)
        if self.powers:
            check_polynomial_rank(poly, self.degree)
        code = _sparse_jit.WENDLAND_CODES[self.kernel]
        pairs = _Pairs(work.numpy(), self.support_radius)
        buffers = {"poly_shift": shift, "poly_scale": scale}
        for prefix, points in (("kernel", work), ("eval", self.targets.double())):
            indptr, columns, values = pairs.rows(points.numpy(), code)
            buffers[f"{prefix}_indptr"] = torch.from_numpy(indptr)
            buffers[f"{prefix}_columns"] = torch.from_numpy(columns)
            buffers[f"{prefix}_values"] = torch.from_numpy(values)
        for name, value in buffers.items():
            self.register_buffer(name, value)
        coupling = torch.from_numpy(np.ascontiguousarray(self._solve(poly.numpy())))
        self.register_buffer("coupling", coupling)
        self.register_buffer("schur", poly.T @ coupling)
        self._polynomials()

    def _polynomials(self) -> None:
        """The tail's monomials at the controls and at the targets, float64 NumPy, made once
        per geometry (at the fit and after a state is loaded), not per call."""
        self._poly_controls, self._poly_targets = (
            polynomial_matrix(points.double(), self.powers, self.poly_shift, self.poly_scale)
            .cpu()
            .numpy()
            for points in (self.controls, self.targets)
        )

    def _apply(self, fn, recurse=True):
        """``.to``, ``.float()`` …: the points take the new dtype; the fit (both matrices,
        Z, S, the polynomial's scaling) stays float64."""
        fit = [name for name in self._buffers if name not in ("controls", "targets")]
        apply_keeping_dtypes(self, fn, recurse, fit)
        return self

    # ------------------------------------------------------------------ solves
    def _solve(self, right: np.ndarray) -> np.ndarray:
        """Φ⁻¹ right by the sparse factorisation (made again after a state is loaded)."""
        if self._factor is None:
            matrix = scipy.sparse.csr_matrix(
                (
                    self.kernel_values.numpy(),
                    self.kernel_columns.numpy(),
                    self.kernel_indptr.numpy(),
                ),
                shape=(self.num_controls, self.num_controls),
            )
            # Φ is symmetric positive definite: no pivoting, a symmetric ordering
            self._factor = scipy.sparse.linalg.splu(
                matrix.tocsc(),
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        if right.shape[1] == 0:
            return np.zeros_like(right)
        return self._factor.solve(np.asfortranarray(right))

    def coefficients(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(λ (N_c, K), β (M, K)) of the interpolant of the value columns (N_c, K)."""
        return self._saddle(values, np.zeros((len(self.powers), values.shape[1])))

    def _saddle(self, top: np.ndarray, bottom: np.ndarray):
        """The solution of [[Φ, P], [Pᵀ, 0]] [λ; β] = [top; bottom] (symmetric)."""
        first = self._solve(top)
        if not self.powers:
            return first, bottom
        tail = np.linalg.solve(self.schur.numpy(), self._poly_controls.T @ first - bottom)
        return first - self.coupling.numpy() @ tail, tail

    # ---------------------------------------------------------------- forward
    @property
    def num_controls(self) -> int:
        return self.controls.shape[0]

    @property
    def num_targets(self) -> int:
        return self.targets.shape[0]

    def forward(self, displacements: Tensor) -> Tensor:
        """Interpolate control displacements to the targets.

        Parameters
        ----------
        displacements : Tensor, shape (N_c, D) or (B, N_c, D)

        Returns
        -------
        Tensor, shape (N_t, D) or (B, N_t, D), the dtype of the displacements.
        """
        dim = self.controls.shape[1]
        check_vectors(
            displacements, "displacements", self.num_controls, dim=dim, what="control points"
        )
        check_same_device_dtype(
            self.controls, "the module's controls", displacements, "displacements"
        )
        if self.controls.device.type != "cpu":
            raise ValueError(
                f"displacements: SparseRBF runs on the CPU (numba and SuperLU), but the "
                f"module was moved to {self.controls.device}"
            )
        values = columns_of(displacements)
        result = _SparseApply.apply(values, self)
        return from_columns(result.to(displacements.dtype), displacements)

    def operator(self, values: np.ndarray) -> np.ndarray:
        """B λ + P_t β for the value columns (N_c, K), float64."""
        weights, tail = self.coefficients(values)
        out = _product(self.eval_indptr, self.eval_columns, self.eval_values, weights)
        if self.powers:
            out += self._poly_targets @ tail
        return out

    def transposed(self, grad: np.ndarray) -> np.ndarray:
        """The operator's transpose on target columns (N_t, K): the λ of the saddle system
        with right side [Bᵀ g; P_tᵀ g]."""
        evaluation = scipy.sparse.csr_matrix(
            (self.eval_values.numpy(), self.eval_columns.numpy(), self.eval_indptr.numpy()),
            shape=(self.num_targets, self.num_controls),
        )
        spread = np.asarray(evaluation.T @ grad)
        bottom = self._poly_targets.T @ grad
        weights, _ = self._saddle(spread, bottom)
        return weights

    # ------------------------------------------------------------------ state
    def _hyperparameters(self) -> dict[str, object]:
        return {
            "kernel": self.kernel,
            "support_radius": self.support_radius,
            "degree": self.degree,
        }

    def get_extra_state(self) -> dict:
        return self._hyperparameters()

    def set_extra_state(self, state: dict) -> None:
        check_saved_hyperparameters("SparseRBF", state, self._hyperparameters())

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        extra = state_dict.get(prefix + "_extra_state")
        if extra is not None:  # before anything is loaded
            check_saved_hyperparameters("SparseRBF", extra, self._hyperparameters())
        resize_buffers_for_load(self, state_dict, prefix, list(self._buffers))
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        self._factor = None  # made again from the loaded kernel matrix
        self._polynomials()
        for name, rows in (("kernel", self.num_controls), ("eval", self.num_targets)):
            indptr = self._buffers[f"{name}_indptr"]
            columns = self._buffers[f"{name}_columns"]
            assert indptr is not None and columns is not None
            if indptr.shape[0] != rows + 1 or int(indptr[-1]) != columns.shape[0]:
                error_msgs.append(f"{name}_indptr: does not match {rows} rows and its columns")
            elif columns.numel() and int(columns.max()) >= self.num_controls:
                error_msgs.append(f"{name}_columns: indices beyond the stored controls")
        coupling = self._buffers["coupling"]
        assert coupling is not None
        if coupling.shape != (self.num_controls, len(self.powers)):
            error_msgs.append(
                f"coupling: shape {tuple(coupling.shape)} does not match the controls"
            )

    def extra_repr(self) -> str:
        nnz = int(self.kernel_columns.shape[0])
        return (
            f"num_controls={self.num_controls}, num_targets={self.num_targets}, "
            f"kernel={self.kernel!r}, support_radius={self.support_radius:g}, "
            f"degree={self.degree}, neighbours per control={nnz / max(self.num_controls, 1):.1f}"
        )


class _SparseApply(torch.autograd.Function):
    """u = B λ(d) + P_t β(d); backward: the operator's transpose (same symmetric system)."""

    @staticmethod
    def forward(ctx, values: Tensor, module: SparseRBF):  # type: ignore[override]
        ctx.module, ctx.dtype = module, values.dtype
        return torch.from_numpy(module.operator(values.detach().double().numpy()))

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        total = ctx.module.transposed(grad.detach().double().contiguous().numpy())
        return torch.from_numpy(total).to(ctx.dtype), None
