"""Tree-approximated IDW: the paper's eq. (2), ``u(x) = Σ_k w_k(x) d_k / Σ_k w_k(x)`` with
``w_k = |x - x_k|^-p``, where far clusters of controls are summed by a second-order
(quadrupole) expansion of the weight about their centroid, near ones exactly, to a
requested relative error of the result.

:func:`idw_tree_apply` is the functional entry; :class:`TreeIDW` builds the trees once for
a fixed pair of clouds and applies the operator to any number of displacement fields.
CPU only (numba kernels in :mod:`torchmorph.idw.backends.numba._tree_jit`); there is no
CUDA version.

The error bound
---------------
Controls go into a kd-tree (median splits on the widest axis, leaves of ``leaf_size``),
targets into another whose leaves are the blocks of work. A node of ``n`` controls
about their centroid ``c`` within radius ``ρ`` seen from a target at ``R = |x - c| > ρ``
(``θ = ρ/R``) has its weights replaced by the degree-2 Gegenbauer (Taylor) polynomial
``P_k`` about ``c``; since ``|C_m^(p/2)(t)| <= C_m^(p/2)(1)`` and
``Σ_m C_m^(p/2)(1) θ^m = (1-θ)^-p``, every weight's error obeys

    |P_k - w_k| <= δ = R^-p T2(θ),   T2(θ) = (1-θ)^-p - 1 - pθ - p(p+1)θ²/2,

for every p > 0. The approximation is again a weighted mean with weights
``w'_k = w_k + ε_k``, so the error of the result at a target is

    u' - u = Σ_k ε_k (d_k - u) / S',   |u' - u| <= Δ E / (S - E),

with ``E`` the accumulated bound, ``S`` the exact weight sum and ``Δ`` the diameter of
the displacements' bounding box (``|d_k - u| <= Δ`` as ``u`` is a mean of the ``d_k``).
Every term of the remainder has degree >= 3 in ``|s|``, so a node contributes at most
``m δ`` to ``E`` with the effective count ``m = Σ_k |s_k|³ / ρ³ <= n``. The traversal
(near nodes first) accepts a node for a block of targets when every target of the block
satisfies ``m δ_t <= (η/2) n max(L_t / N_c, (R_t + ρ)^-p)``: ``L_t`` is the target's
running lower bound of ``S`` (exact leaf sums and ``n (R + ρ)^-p`` per accepted node).
The test is made first for the whole block at once (``δ`` at its nearest target, the
smallest ``L_t``, its farthest target), then target by target when that fails. Summed
over the accepted nodes, each term stays below ``(η/2) S``, so ``E <= η S`` for every
target and ``|u' - u| <= Δ η / (1 - η)``.

With ``error_control="certified"`` (the default) ``η`` starts from the tolerance,
``η = tolerance · rms(u) / (2 Δ)`` with ``rms(u)``
estimated by exact sums at up to :data:`SAMPLE_TARGETS` targets. After the traversal
the bound is certified over all targets: with ``b_i = Δ E_i / (S'_i - E_i)`` the
per-target bound, ``B = (Σ_i b_i²)^½`` and ``‖u'‖ - B <= ‖u‖``, the certified relative
bound ``B / (‖u'‖ - B) <= tolerance`` implies ``‖u' - u‖ / ‖u‖ <= tolerance`` in the
2-norm over all targets, for each displacement field of a batch. When the certificate
fails ``η`` is lowered (aiming at half the tolerance) and the traversal repeated; when
it holds with room (below ``tolerance / LOOSEN``, :mod:`~torchmorph.idw._tree_threshold`),
``η`` is raised towards the tolerance and the traversal repeated, keeping the last
certified result. A :class:`TreeIDW` starts its next call from the ``η`` it kept, and
remembers the lowest that failed: later raises go halfway to it (geometrically), one
per call, none within 1.25 times it, so that calls settle to one traversal each; after
``CEILING_CALLS`` calls without a failure it is raised by half (the field may be easier).
The bound is worst-case (it ignores the cancellations of the odd Gegenbauer terms and
the smoothness of ``d``): measured errors are 100-3000 times below the certified bound
on the clouds of the tests and benchmarks, so the tree accepts far fewer nodes than an
error estimate would allow, and a certified call is slower than the exact fused sum at
every size measured (``benchmarks/tree.py``).

Sampled error control
---------------------
``error_control="sampled"`` uses the same traversal with a larger ``η``, tuned until the
relative 2-norm error at :data:`SAMPLE_TARGETS` targets (evenly spaced in the targets'
order), measured against exact sums of the fused kernels (float64; for float32 inputs
the float32 kernels, whose partial sums are float64, from :data:`SINGLE_REFERENCE` up),
is below ``tolerance / SAMPLE_SAFETY`` (``η`` is raised while it is below a further
factor ``SAMPLED_LOOSEN``, :mod:`~torchmorph.idw._tree_threshold`). That is an estimate of
the error over all targets, not a bound: it holds on the clouds of the tests (uniform;
surface controls with targets filling the volume; graded by 10^4) and of the benchmark,
where the error at 2,000 targets came out 1.5-3 times below the tolerance (1e-3 to
1e-6), but a field whose error concentrates on a few targets missed by the sample can
exceed it. ``last_bound_`` still reports the certified bound of the result. A module's
first call tunes ``η`` by traversing only the blocks of targets that hold the sampled
ones (a block's results do not depend on the others, so the sampled rows come out as in
a whole traversal; up to :data:`SAMPLE_ATTEMPTS` of these cheap trials, halving the gap
to a threshold that failed), where those are at most a :data:`SAMPLE_BLOCKS`-th of the
blocks, and then traverses every block once; later calls start from the tuned ``η``
with a whole traversal.

Exactness and gradients
-----------------------
A target within ``coincidence_tolerance`` times the bounding-box diagonal of a control
takes that control's displacement (the mean over several), the rule of
:func:`~torchmorph.idw.idw_apply`. The map is linear in the displacements for a given
``η``: the gradient to the displacements applies the exact transpose of the operator
the forward pass used (the same traversal, with the far-field coefficients gathered per
node and spread to its controls). ``η`` depends on the displacements' spread and size;
that choice is piecewise constant and not differentiated. No gradients to the point
positions: inputs that require them are refused (use :func:`~torchmorph.idw.idw_apply`);
the expansion is differentiable in ``x`` and ``c`` in principle, not implemented.

Precision
---------
Geometry, moments, expansions and the running sums are float64. The leaves' exact sums
(a target against the controls of one leaf) run in the inputs' dtype, as the exact
fused kernels do: for float32 inputs in float32, twice the vector lanes (1.14× faster
at 10^6 × 10^5, 1e-4), each leaf's sums then added in float64. That rounding, about
1e-7 of a leaf's sum, is not part of the certified bound; it is below the float32
result's own resolution.

Not done here: CUDA (Triton) kernels; gradients to the points; targets coinciding with
a control are found only by leaves summed exactly, which always holds (a node containing
the control has ``ρ >= R``). :class:`TreeIDW` is also ``IDW(mode="tree")`` and
``MeshMorph(mode="tree")`` with certified error control (with sampled control those take
the faster :class:`~torchmorph.idw.treecode.TreecodeIDW`); :meth:`TreeIDW.transposed` applies ``Aᵀ`` (the morph's
adjoint), and a call on all-zero fields keeps the threshold of the last call (or of a
probe call), so that a vector-Jacobian product taken there is as accurate as elsewhere.
"""

from __future__ import annotations

import math
import warnings
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchmorph._checks import (
    as_points,
    check_same_device_dtype,
    check_vectors,
    dim_of,
)
from torchmorph.idw._geometry import check_error_control, check_tolerance, normalise
from torchmorph.idw._tree_operator import TARGET_BLOCK, _TreeApply, _TreeOperator
from torchmorph.idw._tree_sample import SAMPLE_TARGETS, CloudPair
from torchmorph.idw._tree_threshold import CEILING_CALLS, CEILING_EASE, search
from torchmorph.idw.backends.numba.kernels import available
from torchmorph.idw.functional import DEFAULT_COINCIDENCE_TOLERANCE

__all__ = [
    "DEFAULT_LEAF_SIZE",
    "DEFAULT_TOLERANCE",
    "SAMPLE_BLOCKS",
    "SAMPLE_SAFETY",
    "SAMPLE_TARGETS",
    "TARGET_BLOCK",
    "TRANSPOSE_MARGIN",
    "ErrorControl",
    "TreeIDW",
    "idw_tree_apply",
]

ErrorControl = Literal["certified", "sampled"]

DEFAULT_TOLERANCE = 1e-4
"""The relative error ``‖u_tree - u_exact‖ / ‖u_exact‖`` (2-norm over all targets)."""

DEFAULT_LEAF_SIZE = 64
"""Controls per leaf of the control tree (summed exactly when not accepted)."""

SAMPLE_SAFETY = 1.5
"""``error_control="sampled"``: the error measured at the sampled targets must stay
below ``tolerance / SAMPLE_SAFETY``."""

SAMPLED_START = 300.0
"""``error_control="sampled"``: the first ``η`` of a :class:`TreeIDW`, ``SAMPLED_START``
times the tolerance (on the benchmark's clouds at p = 4 the error measured was about
1e-4 η); later calls start from the last call's ``η``."""

TRANSPOSE_MARGIN = 8.0
"""``error_control="sampled"``: :meth:`TreeIDW.transposed` applies the transpose at the
last call's ``η`` divided by this (the sampled check is on ``A d``, not on ``Aᵀ g``,
whose measured error was up to 3 times the forward's at the same ``η``)."""

SAMPLE_BLOCKS = 4
"""``error_control="sampled"``: a first call tunes ``η`` on the blocks of targets that hold
the sampled targets alone (then traverses all blocks once) when they are at most
``1 / SAMPLE_BLOCKS`` of the blocks."""

SAMPLE_ATTEMPTS = 8
"""``error_control="sampled"``: a first call's cheap trials on the sampled targets' blocks
at most (they may halve the gap to a threshold that failed, so later calls need not)."""

SAMPLED_ETA_LIMIT = 100.0
"""``error_control="sampled"``: the largest ``η`` tried (nodes still need ``ρ < R``)."""


def _check_tolerance(tolerance: float) -> float:
    tolerance = float(tolerance)
    if not (0 < tolerance < 1):
        raise ValueError(f"tolerance must lie in (0, 1), got {tolerance!r}")
    return tolerance


def _check_leaf_size(leaf_size: int) -> int:
    if isinstance(leaf_size, bool) or not isinstance(leaf_size, int) or leaf_size < 1:
        raise ValueError(f"leaf_size must be a positive integer, got {leaf_size!r}")
    return leaf_size


def _check_cpu(points: Tensor, name: str) -> None:
    if points.device.type != "cpu":
        raise ValueError(
            f"{name} must be on the CPU (the tree has no CUDA kernels), got {points.device}"
        )
    if points.requires_grad and torch.is_grad_enabled():
        raise ValueError(
            f"{name} requires grad: the tree gives gradients to the displacements only; "
            "use idw_apply for gradients to the points"
        )


class TreeIDW(CloudPair):
    """Tree-approximated IDW between fixed clouds: ``TreeIDW(controls, targets)(d)``.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
    targets : Tensor, shape (N_t, D)
    power : float
        The exponent p > 0 (the paper's p = 4).
    tolerance : float
        The relative error ``‖u_tree - u_exact‖ / ‖u_exact‖`` (2-norm over all targets and
        components, for each displacement field of a batch), in (0, 1). See the module's
        notes for the bound that enforces it.
    coincidence_tolerance : float
        As in :func:`~torchmorph.idw.idw_apply`.
    leaf_size : int
        Controls per leaf of the control tree.
    error_control : {"certified", "sampled"}
        ``"certified"``: the rigorous bound of the module's notes holds below
        ``tolerance`` (slow: the bound is worst-case). ``"sampled"``: the acceptance
        threshold ``η`` is tuned until the error measured against exact float64 sums at
        :data:`SAMPLE_TARGETS` targets is below ``tolerance / SAMPLE_SAFETY`` — an
        estimate of the error over all targets, not a guarantee.

    Notes
    -----
    The trees are built once here (numpy and numba, float64 geometry); each call costs a
    pass over the control tree for the displacement moments, the exact sums at
    :data:`SAMPLE_TARGETS` targets that scale the tolerance, and one traversal (rarely
    more, see the module's notes). CPU only; float32 and float64 in, the same out (the
    sums run in float64, the leaves' exact sums in the inputs' dtype: see the module's
    notes). ``last_bound_`` holds the certified relative bound of the
    last call, one value per displacement field, ``last_sampled_error_`` the
    sampled error (``error_control="sampled"``) and ``last_traversals_`` how many
    traversals of all the blocks the call made (1 but where ``η`` was raised or lowered;
    a first call's traversals of the sampled targets' blocks alone are not counted).
    """

    controls: Tensor
    targets: Tensor

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        power: float = 4.0,
        tolerance: float = DEFAULT_TOLERANCE,
        coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
        leaf_size: int = DEFAULT_LEAF_SIZE,
        error_control: ErrorControl = "certified",
    ) -> None:
        super().__init__()
        if not available():
            raise RuntimeError("TreeIDW needs numba: pip install numba")
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
        self.leaf_size = _check_leaf_size(leaf_size)
        self.error_control = check_error_control(error_control)
        self.register_buffer("controls", controls.detach().clone())
        self.register_buffer("targets", targets.detach().clone())
        self._build()
        self.last_bound_: list[float] = []
        self.last_sampled_error_: list[float] = []
        self.last_traversals_ = 0

    _calibration: float
    """η over its first value, learnt from the checks of earlier calls."""

    def _build(self) -> None:
        """The trees of the current ``controls`` and ``targets`` (again after a state is
        loaded, which may bring other clouds)."""
        with torch.no_grad():
            scaled_targets, scaled_controls, radius2 = normalise(
                self.targets, self.controls, self.coincidence_tolerance
            )
        self._operator = _TreeOperator(
            scaled_controls.double().numpy(),
            scaled_targets.double().numpy(),
            self.power,
            float(radius2),
            self.leaf_size,
        )
        self._calibration = 1.0
        self._ceiling: float | None = None  # η that failed, over the calibration's unit
        self._quiet = 0  # calls since a trial last failed
        self._applied: tuple[float, dict] | None = None  # η and sums of the last result
        # the blocks holding the sampled targets, where they are a small part of all
        positions = self._operator.target_rank[self._sample_rows().numpy()]
        starts = self._operator.block_starts
        blocks = np.unique(np.searchsorted(starts, positions, side="right") - 1)
        self._sample_blocks = blocks if SAMPLE_BLOCKS * blocks.size <= starts.size - 1 else None
        self._transposed_sums: tuple[float, np.ndarray, np.ndarray] | None = None

    def _scale(self, values64: Tensor, batch: int, dim: int):
        """Per field: Δ, the diameter of its bounding box; rms(u) at sampled targets; and
        (the sampled rows, their exact values (B, rows, D) in float64)."""
        fields = values64.reshape(-1, batch, dim)
        spread = (fields.amax(0) - fields.amin(0)).norm(dim=1).numpy()
        rows, sample = self._exact_sample(fields)
        rms = sample.square().sum(-1).mean(-1).sqrt().numpy()
        return spread, rms, (rows, sample)

    def _sample_calibration(
        self, values, eta, exact, goal, largest, dim, unit
    ) -> tuple[float, bool]:
        """``error_control="sampled"``, first call: ``η`` tuned as :meth:`forward` tunes it,
        by traversals of the blocks that hold the sampled targets only (each block's results
        are those of a whole traversal, to the bit: 1/15 of the work at 10^6 targets).
        Returns the last ``η`` within ``goal`` there and True, or the next ``η`` the
        search would try and False where none was."""
        operator = self._operator
        flat = values.detach().double().numpy()
        single = values.dtype == torch.float32
        positions = operator.target_rank[self._sample_rows().numpy()]

        def trial(eta: float) -> tuple[float, None]:
            result = operator.apply(flat, eta, single, blocks=self._sample_blocks)[0]
            rows = torch.from_numpy(result[positions]).to(values.dtype)  # as forward's
            return max(_sampled(rows, exact, dim)), None

        best, _ = self._tune(
            eta, trial, goal, largest, certified=False, stop=False, unit=unit,
            attempts=SAMPLE_ATTEMPTS, probes=None,
        )  # fmt: skip
        if best is None:  # from the lowered η the search would try next
            return min(largest, self._calibration * unit), False
        return best[0], True

    def _tune(self, eta, trial, goal, largest, *, certified, stop, unit, **limits):
        """:func:`~torchmorph.idw._tree_threshold.search`; ``self._calibration`` and
        ``self._ceiling`` follow in units of ``unit`` (the ``η`` a calibration of 1 stands
        for in this call; None: they stay). Returns ``(η, kept)`` of the last trial within
        ``goal`` (None if none was) and of the last trial."""
        if unit is None:  # all-zero fields: nothing learnt
            return search(eta, trial, goal, largest, certified=certified, stop=stop)[:2]
        ceiling = None if self._ceiling is None else self._ceiling * unit
        best, last, start, found = search(
            eta, trial, goal, largest, certified=certified, stop=stop, ceiling=ceiling, **limits
        )
        if found != ceiling:
            self._quiet = 0
        self._calibration = start / unit
        self._ceiling = None if found is None else found / unit
        return best, last

    def forward(self, displacements: Tensor) -> Tensor:
        """u at the targets, shape (N_t, D) or (B, N_t, D) like ``displacements``
        ((N_c, D) or (B, N_c, D)); differentiable to ``displacements``."""
        n_controls, dim = self.controls.shape
        batched = check_vectors(
            displacements, "displacements", n_controls, dim=dim, what="control points"
        )
        check_same_device_dtype(self.controls, "controls", displacements, "displacements")
        batch = displacements.shape[0] if batched else 1
        values = (displacements.permute(1, 0, 2) if batched else displacements[:, None]).reshape(
            n_controls, batch * dim
        )
        n_targets = self.targets.shape[0]
        if n_targets == 0:
            self.last_bound_, self.last_traversals_ = [0.0] * batch, 0
            empty = displacements.new_zeros((batch, 0, dim))
            return empty if batched else empty[0]
        with torch.no_grad():
            spread, rms, (rows, exact) = self._scale(values.detach().double(), batch, dim)
        live = spread > 0
        certified = self.error_control == "certified"
        largest = 0.5 if certified else SAMPLED_ETA_LIMIT
        eta = largest if live.any() else self._threshold(largest)
        unit = None  # η over the calibration (all-zero fields leave both alone)
        if live.any():
            scale = 0.5 * self.tolerance * float((rms[live] / spread[live]).min())
            if not certified:  # measured: errors ~1e-4 η at p = 4, far below the bound's
                scale = SAMPLED_START * self.tolerance
            unit = max(scale, 1e-300)
            eta = min(largest, unit * self._calibration)
            self._quiet += 1
            if self._ceiling is not None and self._quiet > CEILING_CALLS:  # look above again
                self._ceiling, self._quiet = CEILING_EASE * self._ceiling, 0
        operator = self._operator
        sampled_rows = torch.from_numpy(operator.target_rank)[rows]
        goal = self.tolerance if certified else self.tolerance / SAMPLE_SAFETY
        settled = False  # η already tuned on the sampled targets' blocks
        if (
            not certified
            and live.any()
            and self._applied is None
            and self._sample_blocks is not None
        ):
            eta, settled = self._sample_calibration(values, eta, exact, goal, largest, dim, unit)

        traversals = []

        def trial(eta: float):
            state: dict = {}
            traversals.append(eta)
            result = _TreeApply.apply(values, operator, eta, state)
            with torch.no_grad():
                bounds = self._certify(result, spread, batch, dim, state)
                errors = bounds if certified else _sampled(result[sampled_rows], exact, dim)
            return max(errors), (result, bounds, errors, state)

        stop = settled or not live.any()
        best, (eta, (result, bounds, errors, state)) = self._tune(
            eta, trial, goal, largest, certified=certified, stop=stop, unit=unit
        )
        if best is not None:
            eta, (result, bounds, errors, state) = best
        else:
            what = "error bound" if certified else "sampled error"
            warnings.warn(
                f"tolerance: the {what} could not be brought below {goal:g} "
                f"({max(errors):.3g}); the result is the last traversal's",
                stacklevel=2,
            )
        self.last_sampled_error_ = [] if certified else errors
        self.last_bound_ = bounds
        self.last_traversals_ = len(traversals)
        self._applied = (eta, state)
        out = result[torch.from_numpy(operator.target_rank)].reshape(n_targets, batch, dim)
        return out.permute(1, 0, 2) if batched else out[:, 0]

    def _threshold(self, largest: float) -> float:
        """``η`` for a call on all-zero fields (whose result is zero whatever ``η``, but
        whose transpose is not): the last result's, or that of a call on a probe field,
        the controls' centred coordinates, when there was none."""
        if self._applied is None:
            probe = self.controls - self.controls.mean(0)
            if not bool(probe.abs().amax() > 0):  # one control point: no far field
                return largest
            with torch.no_grad():
                self(probe)
        assert self._applied is not None
        return self._applied[0]

    def transposed(self, values: Tensor) -> Tensor:
        """``Aᵀ values``: the transpose of the approximated operator, from the targets
        back to the controls (the adjoint of :meth:`forward`).

        Parameters
        ----------
        values : Tensor, shape (N_t, D) or (B, N_t, D)
            A field at the targets.

        Returns
        -------
        Tensor, shape (N_c, D) or (B, N_c, D)
            ``Σ_t A_tk values_t`` for each control ``k``, where ``A`` is the operator at
            the acceptance threshold ``η`` the tolerance chose for the last call (or for a
            call on the controls' centred coordinates when the module was not called
            yet), divided by :data:`TRANSPOSE_MARGIN` with ``error_control="sampled"``.
            With ``"certified"`` it is the exact transpose of the last call's operator,
            ``<A d, g> = <d, Aᵀ g>`` to rounding.

        Notes
        -----
        The error of ``Aᵀ g`` against the exact ``Wᵀ g`` is not certified (the bound of
        the module's notes is on ``A d``): measured below the tolerance on the clouds of
        the tests, for smooth and random ``g``. One traversal (two the first time at a
        new threshold in sampled mode). No gradients (``values`` is detached).
        """
        n_controls, dim = self.controls.shape
        n_targets = self.targets.shape[0]
        batched = check_vectors(values, "values", n_targets, dim=dim, what="targets")
        check_same_device_dtype(self.controls, "controls", values, "values")
        batch = values.shape[0] if batched else 1
        if n_targets == 0:
            zeros = values.new_zeros((batch, n_controls, dim))
            return zeros if batched else zeros[0]
        eta, sums, coincident = self._transposed_operator()
        flat = (values.permute(1, 0, 2) if batched else values[:, None]).reshape(n_targets, -1)
        operator = self._operator
        grad = np.ascontiguousarray(flat.detach().double().numpy()[operator.target_order])
        single = self.controls.dtype == torch.float32
        total = operator.apply_transposed(grad, eta, sums, coincident, single)
        out = torch.from_numpy(total).to(values.dtype).reshape(n_controls, batch, dim)
        return out.permute(1, 0, 2) if batched else out[:, 0]

    def _transposed_operator(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(η, S', coincident counts) of the operator :meth:`transposed` applies."""
        certified = self.error_control == "certified"
        eta = self._threshold(0.5 if certified else SAMPLED_ETA_LIMIT)
        assert self._applied is not None
        if certified:
            state = self._applied[1]
            return eta, state["sums"], state["coincident"]
        eta /= TRANSPOSE_MARGIN
        if self._transposed_sums is None or self._transposed_sums[0] != eta:
            zeros = np.zeros((self.controls.shape[0], 1))
            single = self.controls.dtype == torch.float32
            _, sums, _, coincident = self._operator.apply(zeros, eta, single)
            self._transposed_sums = (eta, sums, coincident)
        return self._transposed_sums

    def _certify(self, result: Tensor, spread, batch: int, dim: int, state: dict) -> list[float]:
        """Per field: the certified bound on ‖u' - u‖ / ‖u‖ (see the module's notes)."""
        relative = torch.from_numpy(state["relative"])
        norms = result.double().reshape(-1, batch, dim).square().sum((0, 2)).sqrt()
        bounds = []
        for field in range(batch):
            error = float(spread[field]) * float(relative.square().sum().sqrt())
            if error == 0:
                bounds.append(0.0)
            elif error >= float(norms[field]):
                bounds.append(math.inf)
            else:
                bounds.append(error / (float(norms[field]) - error))
        return bounds

    def extra_repr(self) -> str:
        return (
            f"controls={self.controls.shape[0]}, targets={self.targets.shape[0]}, "
            f"power={self.power:g}, tolerance={self.tolerance:g}"
        )


def _sampled(result: Tensor, exact: Tensor, dim: int) -> list[float]:
    """Per field: ‖u' - u‖ / ‖u‖ over the sampled rows (``result`` (rows, B·D) in float,
    ``exact`` (B, rows, D) float64)."""
    approximate = result.double().reshape(result.shape[0], -1, dim).permute(1, 0, 2)
    difference = (approximate - exact).square().sum((1, 2)).sqrt()
    norms = exact.square().sum((1, 2)).sqrt()
    return [
        float(d / n) if n > 0 else (0.0 if d == 0 else math.inf)
        for d, n in zip(difference, norms, strict=True)
    ]


def idw_tree_apply(
    *,
    controls: Tensor,
    targets: Tensor,
    displacements: Tensor,
    power: float = 4.0,
    tolerance: float = DEFAULT_TOLERANCE,
    coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
    leaf_size: int = DEFAULT_LEAF_SIZE,
    error_control: ErrorControl = "certified",
) -> Tensor:
    """Tree-approximated ``idw_apply``: eq. (2) to a relative error ``tolerance``.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D), keyword
    targets : Tensor, shape (N_t, D), keyword
    displacements : Tensor, shape (N_c, D) or (B, N_c, D), keyword
    power, tolerance, coincidence_tolerance, leaf_size, error_control
        As in :class:`TreeIDW`.

    Returns
    -------
    Tensor, shape (N_t, D) or (B, N_t, D)
        ``‖u - u_exact‖ / ‖u_exact‖ <= tolerance`` for each field (2-norm over all
        targets), exact at targets on controls; differentiable to ``displacements``.

    Raises
    ------
    ValueError
        For a tolerance outside (0, 1), power <= 0, wrong shapes, NaN/inf, points off
        the CPU or points that require grad.
    """
    return TreeIDW(
        controls,
        targets,
        power=power,
        tolerance=tolerance,
        coincidence_tolerance=coincidence_tolerance,
        leaf_size=leaf_size,
        error_control=error_control,
    )(displacements)
