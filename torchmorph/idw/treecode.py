"""IDW by an interpolating treecode: the paper's eq. (2), ``u(x) = Σ_k w_k(x) d_k / Σ_k
w_k(x)`` with ``w_k = |x - x_k|^-p``, its two kernel sums (the weights against the
displacements, and the weights alone) taken by :mod:`torchmorph._treecode`: barycentric
Lagrange interpolation of ``r^-p`` on both sides with a dual tree traversal (Wang,
Krasny and Tlupova 2020; Wilson, Vaughn and Krasny 2021), near pairs summed exactly.

The weight sum ``S(x)`` depends on the geometry alone: it is taken once, when the module
is built, and a call costs one treecode sum of the displacements (a 3-D field's three
columns in one fused pass at p = 4). Far from its singularity ``r^-p`` is analytic, so
the interpolation error of degree n falls geometrically with n (the Bernstein ellipse
of the opening angle θ); it is relative to each far pair's own weight, which the near
pairs, summed exactly, dominate.

Error control
-------------
The tolerance sets the starting degree from :data:`DEGREE_ERRORS`, the relative 2-norm
errors measured per degree; every call then measures the error at
:data:`~torchmorph.idw._tree_sample.SAMPLE_TARGETS` targets against exact sums of the fused
kernels, as ``TreeIDW(error_control="sampled")`` does, and where it exceeds
``tolerance / SAMPLE_SAFETY`` raises the degree (new lists, a new weight sum) and sums
again, up to :data:`MAX_DEGREE`, with a warning where that does not suffice. It is an
estimate over all targets, not a bound: a field whose error concentrates on targets the
sample misses can exceed it (``last_sampled_error_`` reports it per field).

Exactness and gradients
-----------------------
A target within ``coincidence_tolerance`` times the bounding-box diagonal of a control
takes that control's displacement (the mean over several), the rule of
:func:`~torchmorph.idw.idw_apply`. For a given degree the map is linear in the
displacements, ``u = A d`` with ``A = diag(1/S) K``: the gradient to the displacements
applies ``Aᵀ`` exactly (the treecode's transpose, :meth:`TreecodeIDW.transposed`). The
degree is piecewise constant and not differentiated. No gradients to the point
positions (inputs that require them are refused). CPU only (numba), float64 sums for
float32 and float64 inputs, the result in the inputs' dtype.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from torchmorph._checks import as_points, check_same_device_dtype, check_vectors, dim_of
from torchmorph._treecode import DEFAULT_THETA, TreeCode
from torchmorph.idw._geometry import check_tolerance, normalise
from torchmorph.idw._tree_sample import CloudPair
from torchmorph.idw.backends.numba.kernels import available
from torchmorph.idw.functional import DEFAULT_COINCIDENCE_TOLERANCE
from torchmorph.idw.tree import (
    DEFAULT_TOLERANCE,
    SAMPLE_SAFETY,
    _check_cpu,
    _check_tolerance,
    _sampled,
)

__all__ = ["DEGREE_ERRORS", "MAX_DEGREE", "TreecodeIDW", "start_degree"]

DEGREE_ERRORS: dict[int, float] = {2: 3e-3, 3: 5e-4, 4: 6e-5, 5: 1e-5, 6: 3e-6, 7: 4e-7}
"""The relative 2-norm error per interpolation degree (θ = 0.7, p = 4), rounded up from
``benchmarks/tree.py``'s clouds (controls on a sphere, targets graded towards it by
10^4) at 10^5 × 10^4 and 10^6 × 10^5: 3.7e-4 and 4.1e-4 at degree 3, 4.1e-5 and 4.9e-5
at 4, 6.0e-6 and 7.8e-6 at 5, 2.0e-6 at 6, 1.8e-7 and 2.7e-7 at 7; each degree above
these is taken to divide the error by 7."""

MAX_DEGREE = 14
"""The highest degree the sampled check raises to."""


def start_degree(tolerance: float) -> int:
    """The lowest degree whose measured error (:data:`DEGREE_ERRORS`) is within
    ``tolerance / SAMPLE_SAFETY``."""
    goal = tolerance / SAMPLE_SAFETY
    for degree, error in DEGREE_ERRORS.items():
        if error <= goal:
            return degree
    last = max(DEGREE_ERRORS)
    steps = math.ceil(math.log(goal / DEGREE_ERRORS[last]) / math.log(1 / 7) - 1e-9)
    return min(MAX_DEGREE, last + steps)


class TreecodeIDW(CloudPair):
    """IDW (eq. 2) with both kernel sums by an interpolating treecode (see the module's
    notes), for a fixed pair of clouds; ``forward`` applies it to displacement fields.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
        D = 2 or 3, float32 or float64, on the CPU, not requiring grad.
    targets : Tensor, shape (N_t, D)
    power : float
        The IDW exponent p > 0.
    tolerance : float
        The relative 2-norm error ``‖u' - u‖ / ‖u‖`` aimed at, in (0, 1), estimated at
        sampled targets (the module's notes).
    coincidence_tolerance : float
        As in :func:`~torchmorph.idw.idw_apply`.

    Attributes
    ----------
    degree : int
        The interpolation degree in use (:func:`start_degree`, raised by the check).
    last_sampled_error_ : list of float
        The sampled relative error of the last call, per displacement field.

    Raises
    ------
    ValueError
        For a tolerance outside (0, 1), power <= 0 or not finite, wrong shapes,
        NaN/inf, points off the CPU or points that require grad.
    RuntimeError
        Without numba.
    """

    controls: Tensor
    targets: Tensor
    error_control = "sampled"
    """How the tolerance is kept (the name ``IDW(error_control=...)`` takes)."""

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        power: float = 4.0,
        tolerance: float = DEFAULT_TOLERANCE,
        coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
    ) -> None:
        super().__init__()
        if not available():
            raise RuntimeError("TreecodeIDW needs numba: pip install numba")
        controls = as_points(controls, "controls", dim=dim_of(controls))
        targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True)
        check_same_device_dtype(controls, "controls", targets, "targets")
        _check_cpu(controls, "controls")
        _check_cpu(targets, "targets")
        self.power = float(power)
        if not (self.power > 0 and math.isfinite(self.power)):
            raise ValueError(f"power must be finite and > 0, got {power!r}")
        self.tolerance = _check_tolerance(tolerance)
        self.coincidence_tolerance = check_tolerance(coincidence_tolerance)
        self.register_buffer("controls", controls.detach().clone())
        self.register_buffer("targets", targets.detach().clone())
        self.last_sampled_error_: list[float] = []
        self._build()

    def _build(self) -> None:
        """The treecode of the current clouds at the tolerance's start degree, the weight
        sums at the targets and the coincident targets (again after a state is loaded)."""
        with torch.no_grad():
            targets, controls, radius2 = normalise(
                self.targets, self.controls, self.coincidence_tolerance
            )
        self._points = (controls.double().numpy(), targets.double().numpy())
        self._radius2 = float(radius2)
        self._coincident = _coincident(*self._points, self._radius2)
        self._raise_to(start_degree(self.tolerance))

    def _raise_to(self, degree: int) -> None:
        """The treecode at ``degree`` and the weight sums at the targets through it."""
        controls, targets = self._points
        tree = TreeCode(
            controls, targets, 1.0, degree, DEFAULT_THETA, power=self.power, floor=self._radius2
        )
        sums = tree.apply(np.ones((controls.shape[0], 1)))[:, 0]
        self.degree = int(degree)
        self._operator = (tree, np.where(sums > 0, sums, 1.0), self._coincident)

    # ----------------------------------------------------------------- calls
    def _flat(self, values: Tensor, count: int, name: str, what: str):
        """(values as (count, B·D), B, batched)."""
        dim = self.controls.shape[1]
        batched = check_vectors(values, name, count, dim=dim, what=what)
        check_same_device_dtype(self.controls, "controls", values, name)
        batch = values.shape[0] if batched else 1
        flat = (values.permute(1, 0, 2) if batched else values[:, None]).reshape(count, -1)
        return flat, batch, batched

    def _unflat(self, flat: Tensor, count: int, batch: int, batched: bool) -> Tensor:
        out = flat.reshape(count, batch, self.controls.shape[1])
        return out.permute(1, 0, 2) if batched else out[:, 0]

    def forward(self, displacements: Tensor) -> Tensor:
        """u at the targets, shape (N_t, D) or (B, N_t, D) like ``displacements``
        ((N_c, D) or (B, N_c, D)); differentiable to ``displacements``."""
        n_controls, dim = self.controls.shape
        values, batch, batched = self._flat(
            displacements, n_controls, "displacements", "control points"
        )
        n_targets = int(self.targets.shape[0])
        if n_targets == 0:
            self.last_sampled_error_ = [0.0] * batch
            return self._unflat(values[:0], 0, batch, batched)
        with torch.no_grad():
            rows, exact = self._exact_sample(values.reshape(n_controls, batch, dim))
        goal = self.tolerance / SAMPLE_SAFETY
        while True:
            result = _TreecodeApply.apply(values, self._operator)
            with torch.no_grad():
                errors = _sampled(result[rows], exact, dim)
            if max(errors) <= goal or self.degree >= MAX_DEGREE:
                break
            self._raise_to(self.degree + 1)
        if max(errors) > goal:
            warnings.warn(
                f"tolerance: the sampled error could not be brought below {goal:g} "
                f"({max(errors):.3g}) by degree {MAX_DEGREE}",
                stacklevel=2,
            )
        self.last_sampled_error_ = errors
        return self._unflat(result, n_targets, batch, batched)

    def transposed(self, values: Tensor) -> Tensor:
        """``Aᵀ values``: the exact transpose of the operator at the current degree, from
        the targets back to the controls (the adjoint of :meth:`forward`); ``values``
        (N_t, D) or (B, N_t, D), no gradients."""
        n_controls = self.controls.shape[0]
        n_targets = int(self.targets.shape[0])
        flat, batch, batched = self._flat(values, n_targets, "values", "targets")
        if n_targets == 0:
            return self._unflat(flat.new_zeros(n_controls, flat.shape[1]), n_controls, batch,
                                batched)  # fmt: skip
        total = _transposed(self._operator, flat.detach().double().numpy())
        return self._unflat(torch.from_numpy(total).to(values.dtype), n_controls, batch, batched)

    def extra_repr(self) -> str:
        return (
            f"controls={self.controls.shape[0]}, targets={self.targets.shape[0]}, "
            f"power={self.power:g}, tolerance={self.tolerance:g}, degree={self.degree}"
        )


def _coincident(controls: np.ndarray, targets: np.ndarray, radius2: float):
    """(target rows, control rows) of the pairs within the coincidence radius, a pair
    per control a target coincides with."""
    if targets.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    searcher = cKDTree(controls)
    radius = math.sqrt(radius2)
    nearest, _ = searcher.query(targets, k=1, distance_upper_bound=radius * (1 + 1e-9))
    hits = np.flatnonzero(nearest**2 <= radius2)
    found = searcher.query_ball_point(targets[hits], radius * (1 + 1e-9))
    pairs = [
        (row, column)
        for row, columns in zip(hits, found, strict=True)
        for column in columns
        if ((targets[row] - controls[column]) ** 2).sum() <= radius2
    ]
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows, columns = np.array(pairs, dtype=np.int64).T
    return rows, columns


def _applied(operator, values: np.ndarray) -> np.ndarray:
    """A d for ``values`` (N_c, K), float64; ``operator`` (treecode, weight sums,
    coincident pairs)."""
    tree, sums, (targets, controls) = operator
    result = tree.apply(values) / sums[:, None]
    if targets.size:
        counts = np.bincount(targets, minlength=result.shape[0])[targets]
        result[targets] = 0.0
        np.add.at(result, targets, values[controls] / counts[:, None])
    return result


def _transposed(operator, grads: np.ndarray) -> np.ndarray:
    """Aᵀ g for ``grads`` (N_t, K), float64 (the exact transpose of :func:`_applied`)."""
    tree, sums, (targets, controls) = operator
    scaled = grads / sums[:, None]
    if targets.size:
        scaled[targets] = 0.0
    out = tree.apply_transposed(scaled)
    if targets.size:
        counts = np.bincount(targets, minlength=grads.shape[0])[targets]
        np.add.at(out, controls, grads[targets] / counts[:, None])
    return out


class _TreecodeApply(torch.autograd.Function):
    """u = A d for the operator of the call; backward: Aᵀ grad."""

    @staticmethod
    def forward(ctx, values: Tensor, operator):  # type: ignore[override]
        ctx.operator = operator
        result = _applied(operator, values.detach().double().numpy())
        return torch.from_numpy(result).to(values.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        total = _transposed(ctx.operator, grad.detach().double().numpy())
        return torch.from_numpy(total).to(grad.dtype), None
