"""The partition-of-unity RBF (:class:`PartitionRBF`): a global fit on a coarse subset of
the controls plus local fits of its residual on overlapping patches, blended, for more
controls than a dense factorisation affords (:func:`~torchmorph.rbf.solvers.build_rbf`
picks it, the sparse or the dense fit)."""

from __future__ import annotations

import numbers
import time

import numpy as np
import torch
from torch import Tensor, nn

from torchmorph._checks import (
    as_points,
    check_choice,
    check_positive,
    check_same_device_dtype,
    check_vectors,
)
from torchmorph._state import (
    check_saved_hyperparameters,
    pack_tensors,
    resize_buffers_for_load,
    unpack_tensor,
)
from torchmorph.rbf import _numba, _parallel
from torchmorph.rbf._parallel import kernel_sum
from torchmorph.rbf.functional import (
    check_distinct,
    check_options,
    columns_of,
    dim_of,
    from_columns,
)
from torchmorph.rbf.kernels import (
    monomial_powers,
    polynomial_matrix,
    polynomial_scaling,
)
from torchmorph.rbf.patches import blend_weights, build_patches, coarse_subset, wendland_weight
from torchmorph.rbf.refine import SUMMATIONS, GlobalFit
from torchmorph.rbf.system import FACTOR_NAMES, KINDS, factorise, solve

__all__ = [
    "DEFAULT_COARSE_SIZE",
    "DEFAULT_MAX_ITERATIONS",
    "DEFAULT_OVERLAP",
    "DEFAULT_PATCH_SIZE",
    "PartitionRBF",
]

#: Most controls in a cell of the patches' kd-split (a patch holds about 3 times as many).
DEFAULT_PATCH_SIZE = 100
#: A patch's radius over the distance from its cell's centre to the cell's farthest control.
DEFAULT_OVERLAP = 1.5
#: Controls of the global coarse fit (it sets the error against the global fit: 2.5e-3 at
#: 10⁴ controls, 4.2e-3 at 3·10⁴ in ``benchmarks/rbf_scale.py``; 10⁵ × 10⁶ in 38 s).
DEFAULT_COARSE_SIZE = 6000
#: Most iterations of the global fit (``tolerance``): 4 reached 1e-4 on the benchmark's
#: wing in a box of walls at 10⁴ and 3·10⁴ controls, 6 at 10⁵.
DEFAULT_MAX_ITERATIONS = 100

#: The per-patch buffers of the local factorisations, packed: ``patch_<name>`` (all the
#: patches' factors flattened, concatenated) with ``patch_<name>_shapes`` (P, 2) (a
#: second size of -1 for a vector) and ``patch_<name>_offsets`` (P + 1,).
_PACKED = tuple(f"patch_{name}" for name in FACTOR_NAMES)


class PartitionRBF(GlobalFit, nn.Module):
    """RBF interpolation by a partition of unity: a global fit on a coarse subset of the
    controls, and local fits of its residual on overlapping patches, blended.

    With s_c the RBF interpolant (same kernel and polynomial tail as
    :class:`~torchmorph.rbf.RBF`) of the displacements at ``coarse_size`` controls spread
    over the cloud (one per cell of a balanced kd-split), and r = d − s_c the residual at
    all the controls, the morph is

        s(x) = s_c(x) + Σ_j ŵ_j(x) s_j(x),

    s_j the RBF interpolant of r at the controls inside patch j (a ball about a cell of
    a kd-split of the controls into cells of at most ``patch_size``, radius ``overlap``
    times the cell's, or enough to hold ``patch_size // 2`` controls; Wendland's
    partition-of-unity method, *Scattered Data Approximation*, §15.4), ŵ_j = w_j /
    max(Σ_i w_i, w_min) with w_j Wendland's C² function of the scaled distance to the
    patch's centre and w_min = w(1 / overlap) (:func:`~torchmorph.rbf.patches.blend_weights`).
    Every control is inside its own cell's patch at a scaled distance <= 1 / overlap, so
    the weights sum to 1 there, and every patch with a non-zero weight at a control holds
    it: s interpolates the controls exactly. Far from every control (Σ w < w_min) the
    residual fades out and s is the coarse fit. s_c is in the span of the global fit (its
    centres are controls), so the global interpolant is s_c plus the global interpolant of
    r: the approximation is only that of r, whose size is the coarse fit's error.

    Each local fit has the polynomial tail of ``degree`` in the patch's principal frame,
    flat axes dropped (controls on a wall are coplanar); affine displacements are
    reproduced by the coarse fit (r = 0) whatever the patches.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
    targets : Tensor, shape (N_t, D)
    kernel, epsilon, degree, support_radius
        As :class:`~torchmorph.rbf.RBF`.
    patch_size : int
        Most controls in a cell of the patches' kd-split (>= 2 · the monomial count and
        4); a patch holds about 3 times as many.
    overlap : float
        A patch's radius over its cell's (> 1).
    coarse_size : int
        Controls of the coarse global fit (all of them when N_c is not larger: s = s_c,
        the global fit).
    tolerance : float, optional
        Fit the global interpolant instead (the dense :class:`~torchmorph.rbf.RBF`'s, to
        this tolerance): flexible GMRES on the whole interpolation system, preconditioned
        by the coarse fit and the patches (:mod:`~torchmorph.rbf.refine`), until its
        residual at the controls is below ``tolerance`` times the displacements' norm,
        per column; the last residual is then blended by the patches as above, so the
        morph stays exact at the controls. Each call iterates (one product with the
        N_c × N_c kernel matrix per iteration) and then sums all the controls at every
        target, exactly or by a treecode (``summation``). The residual bounds the error
        at the controls, not in the volume: on the wing in a box of walls (Notes) 1e-4
        came to 2e-6 of the global fit, 1e-3 to 2.5e-3. Gradients solve the same system
        again (the treecode's products at the controls are symmetric to its error only,
        so the gradients are exact to that error).
        ``None`` (default): the partition alone.
    max_iterations : int
        Most iterations for ``tolerance`` (a call that stops short warns, naming the
        residual reached).
    summation : {"auto", "exact", "treecode"}
        How the global fit sums the kernel over the controls: exactly, or by the
        treecode of :mod:`~torchmorph._treecode` (the thin-plate spline on the CPU; its
        degree from ``tolerance``, :func:`~torchmorph.rbf.refine.treecode_degree`), each of
        the two sums (at the controls, at the targets) by itself; ``"auto"`` takes the
        treecode for the thin-plate spline from 10⁹ target-control pairs up. With the
        treecode at the targets, targets on a control take its displacement, and every
        call checks the sums at 32 targets against exact ones (``last_treecode_error_``;
        above ``tolerance`` it warns).
    block_bytes : int, optional
        Byte budget of the torch blocks of pairwise temporaries.

    Attributes
    ----------
    fit_time : float
        Seconds of the fit (patches, factorisations, blend weights).
    last_iterations_, last_residual_ : int, Tensor
        With ``tolerance``: the last call's iterations and relative residual per column.
    last_treecode_error_ : float
        With the treecode at the targets: the relative error its sums made in the last
        call's morph at the sampled targets (0 otherwise).

    Raises
    ------
    ValueError
        As :class:`~torchmorph.rbf.RBF` for the points and the kernel's options; naming
        ``patch_size``, ``overlap``, ``coarse_size``, ``tolerance``, ``max_iterations``
        or ``summation`` when out of range (``"treecode"`` without a tolerance, or with
        another kernel than the thin-plate spline).

    Notes
    -----
    The approximation error against the global fit is set by ``coarse_size`` and
    ``overlap``: far from every control (volume targets between a body and outer walls)
    the global thin-plate interpolant depends on all the controls, the patches' weights
    fade and the coarse fit is what remains; near the controls the patches reproduce the
    global fit. Measured (``benchmarks/rbf_scale.py``, a wing in a box of walls, volume
    targets, relative 2-norm): 6.6e-3 at 10⁴ controls and 8.7e-3 at 3·10⁴ with 3,000
    coarse; 2.5e-3 and 4.2e-3 with 6,000 (the default); at 10⁴ with 6,000 coarse, 1.1e-3
    with overlap 2.0 and 3.8e-4 with 2.5, at 3 and 12 times the fit time (patches of up
    to 7,000 controls where sparse wall cells reach a dense body). Exact at the controls
    and for affine motions whatever the settings. With ``tolerance=1e-4`` the global
    fit itself: 1.9e-6 at 10⁴ and 8.4e-6 at 3·10⁴ controls (4 iterations; fit and morph
    11.5 s where the dense global fit took 195 s), and 10⁵ controls × 10⁶ targets fit
    and morph in 45 s and 3.7 GB on two threads (6 iterations, the treecode at the
    controls and at the targets; a later morph 28 s).

    The geometry is built on the CPU (NumPy, scipy's ``cKDTree``) and the fit and the
    solves are in float64; the forward pass is torch (any device once moved) with the
    thin-plate spline's float64 CPU sums in numba on ``torch.get_num_threads()`` threads.
    The patches' factorisations (torch's Cholesky below order 1,000,
    :data:`~torchmorph.rbf.system.LAPACK_CHOLESKY_ORDER`) and solves run on one torch
    thread: small operations on two threads of a loaded machine wait for a descheduled
    sibling (0.2 s instead of 2 ms per patch). The coarse factorisation is scipy's LAPACK
    on OpenBLAS's own thread count (``OPENBLAS_NUM_THREADS``).

    Gradients flow to the displacements, not to the positions (the geometry is fixed:
    build another module for moved points). The Wendland kernels' compact support is not
    exploited (dense local systems). :meth:`state_dict` holds the whole fit; a
    state loads into a module built with the same hyper-parameters (any points),
    otherwise loading raises naming the field.
    """

    controls: Tensor
    targets: Tensor
    coarse_indices: Tensor
    coarse_shift: Tensor
    coarse_scale: Tensor
    coarse_solver: Tensor
    patch_centres: Tensor
    patch_radii: Tensor
    patch_frames: Tensor
    patch_spreads: Tensor
    patch_flat: Tensor
    patch_members: Tensor
    patch_member_offsets: Tensor
    patch_owner: Tensor
    patch_solver: Tensor
    blend_targets: Tensor
    blend_offsets: Tensor
    blend_weights: Tensor

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        kernel: str = "thin_plate_spline",
        epsilon: float | None = None,
        degree: int = 1,
        support_radius: float | None = None,
        patch_size: int = DEFAULT_PATCH_SIZE,
        overlap: float = DEFAULT_OVERLAP,
        coarse_size: int = DEFAULT_COARSE_SIZE,
        tolerance: float | None = None,
        max_iterations: int = DEFAULT_MAX_ITERATIONS,
        summation: str = "auto",
        block_bytes: int | None = None,
    ) -> None:
        super().__init__()
        controls = as_points(controls, "controls", dim=dim_of(controls))
        targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True)
        check_same_device_dtype(controls, "controls", targets, "targets")
        dim = controls.shape[1]
        self.kernel, self.epsilon, self.degree, self.support_radius, self.scale = check_options(
            kernel, epsilon, degree, support_radius, controls.shape[0], dim
        )
        self.powers = monomial_powers(dim, self.degree)
        minimum = max(2 * len(self.powers), 4)
        self.patch_size = _integer(patch_size, "patch_size", minimum)
        self.coarse_size = _integer(coarse_size, "coarse_size", max(len(self.powers), 1))
        self.overlap = check_positive(overlap, "overlap")
        self.tolerance = None if tolerance is None else check_positive(tolerance, "tolerance")
        self.max_iterations = _integer(max_iterations, "max_iterations", 1)
        self.summation = check_choice(summation, "summation", SUMMATIONS)
        if self.summation == "treecode" and self.tolerance is None:
            raise ValueError("summation='treecode' needs a tolerance (the global fit's)")
        if self.summation == "treecode" and not _numba.available():
            raise ValueError("summation='treecode' needs numba, which is not installed")
        if self.summation == "treecode" and self.kernel != "thin_plate_spline":
            raise ValueError(
                f"summation='treecode' serves kernel='thin_plate_spline', got {self.kernel!r}"
            )
        self.last_iterations_ = 0
        self.last_residual_: Tensor | None = None
        self.last_treecode_error_ = 0.0
        self._sums = None
        if not self.overlap > 1.0:
            raise ValueError(f"overlap must be > 1 (patches must overlap), got {overlap!r}")
        self.block_bytes = (
            None if block_bytes is None else int(check_positive(block_bytes, "block_bytes"))
        )
        check_distinct(controls)
        self.register_buffer("controls", controls.detach().clone())
        self.register_buffer("targets", targets.detach().clone())
        start = time.perf_counter()
        with torch.no_grad():
            self._fit()
        self.fit_time = time.perf_counter() - start

    # ------------------------------------------------------------------ fit
    def _fit(self) -> None:
        device = self.controls.device
        work = self.controls.double().cpu()
        points = work.numpy()
        coarse = torch.from_numpy(coarse_subset(points, self.coarse_size))
        coarse_points = work[coarse]
        shift, poly_scale = polynomial_scaling(coarse_points)
        kind, factors = factorise(
            coarse_points, self.kernel, self.scale, self.degree, self.powers, shift, poly_scale
        )
        buffers = {"coarse_indices": coarse, "coarse_shift": shift, "coarse_scale": poly_scale}
        buffers["coarse_solver"] = torch.tensor(KINDS.index(kind), dtype=torch.int8)
        buffers.update({f"coarse_{name}": factors[name] for name in FACTOR_NAMES})
        partial = coarse.shape[0] < points.shape[0]
        patches = (
            build_patches(
                points, self.patch_size, self.overlap, self.patch_size // 2, len(self.powers)
            )
            if partial
            else None
        )
        count = 0 if patches is None else patches.centres.shape[0]
        kinds: list[int] = []
        packed: dict[str, list[Tensor]] = {name: [] for name in FACTOR_NAMES}
        with _parallel.one_torch_thread():
            for index in range(count):
                assert patches is not None
                kind, local = self._local_factors(patches, index, work)
                kinds.append(KINDS.index(kind))
                for name in FACTOR_NAMES:
                    packed[name].append(local[name])
        for name in FACTOR_NAMES:
            flat, shapes, offsets = pack_tensors(packed[name], work)
            if name == "pivots":
                flat = flat.to(torch.int32)
            buffers[f"patch_{name}"] = flat
            buffers[f"patch_{name}_shapes"] = shapes
            buffers[f"patch_{name}_offsets"] = offsets
        dim = points.shape[1]
        if patches is None:
            buffers["patch_centres"] = work.new_zeros(0, dim)
            buffers["patch_radii"] = work.new_zeros(0)
            buffers["patch_frames"] = work.new_zeros(0, dim, dim)
            buffers["patch_spreads"] = work.new_zeros(0, dim)
            buffers["patch_flat"] = torch.zeros(0, dim, dtype=torch.bool)
            buffers["patch_members"] = torch.zeros(0, dtype=torch.int64)
            buffers["patch_member_offsets"] = torch.zeros(1, dtype=torch.int64)
            buffers["patch_owner"] = torch.zeros(0, dtype=torch.int64)
            radii = np.zeros(0)
            centres = np.zeros((0, dim))
        else:
            buffers["patch_centres"] = torch.from_numpy(patches.centres)
            buffers["patch_radii"] = torch.from_numpy(patches.radii)
            buffers["patch_frames"] = torch.from_numpy(patches.frames)
            buffers["patch_spreads"] = torch.from_numpy(patches.spreads)
            buffers["patch_flat"] = torch.from_numpy(patches.flat)
            buffers["patch_members"] = torch.from_numpy(patches.members)
            buffers["patch_member_offsets"] = torch.from_numpy(patches.member_offsets)
            buffers["patch_owner"] = torch.from_numpy(patches.owner)
            radii, centres = patches.radii, patches.centres
        buffers["patch_solver"] = torch.tensor(kinds, dtype=torch.int8)
        floor = float(wendland_weight(np.array(1.0 / self.overlap)))
        targets = self.targets.double().cpu().numpy()
        chosen, spans, weights = blend_weights(targets, centres, radii, floor)
        buffers["blend_targets"] = torch.from_numpy(chosen)
        buffers["blend_offsets"] = torch.from_numpy(spans)
        buffers["blend_weights"] = torch.from_numpy(weights)
        for name, value in buffers.items():
            self.register_buffer(name, value.to(device))

    def _local_factors(self, patches, index: int, work: Tensor) -> tuple[str, dict[str, Tensor]]:
        begin, end = patches.member_offsets[index], patches.member_offsets[index + 1]
        held = torch.from_numpy(patches.members[begin:end])
        frame = torch.from_numpy(patches.frames[index])
        centre = torch.from_numpy(patches.centres[index])
        local = (work[held] - centre) @ frame
        powers = self._local_powers(patches.flat[index].tolist())
        spread = torch.from_numpy(patches.spreads[index])
        return factorise(
            local,
            self.kernel,
            self.scale,
            self.degree,
            powers,
            local.new_zeros(len(spread)),
            spread,
        )

    def _local_powers(self, flat: list[bool]) -> list[tuple[int, ...]]:
        """The monomials of the tail without the flat axes."""
        return [p for p in self.powers if not any(e and f for e, f in zip(p, flat, strict=True))]

    # ------------------------------------------------------------------ views
    @property
    def num_controls(self) -> int:
        return self.controls.shape[0]

    @property
    def num_targets(self) -> int:
        return self.targets.shape[0]

    @property
    def num_patches(self) -> int:
        return self.patch_centres.shape[0]

    def members_of(self, index: int) -> Tensor:
        """Indices of the controls that patch ``index`` fits."""
        offsets = self.patch_member_offsets
        return self._buffers["patch_members"][offsets[index] : offsets[index + 1]]  # type: ignore[index]

    def _patch_factors(self, index: int, layout) -> dict[str, Tensor]:
        return {
            name: unpack_tensor(
                self._buffers[f"patch_{name}"],  # type: ignore[arg-type]
                layout[name][0],
                layout[name][1],
                index,
            )
            for name in FACTOR_NAMES
        }

    # ------------------------------------------------------------------ state
    def _hyperparameters(self) -> dict[str, object]:
        return {
            "kernel": self.kernel,
            "epsilon": self.epsilon,
            "degree": self.degree,
            "support_radius": self.support_radius,
            "patch_size": self.patch_size,
            "overlap": self.overlap,
            "coarse_size": self.coarse_size,
            "tolerance": self.tolerance,
            "max_iterations": self.max_iterations,
            "summation": self.summation,
        }

    def get_extra_state(self) -> dict:
        return self._hyperparameters()

    def set_extra_state(self, state: dict) -> None:
        check_saved_hyperparameters("PartitionRBF", _with_defaults(state), self._hyperparameters())

    def _apply(self, fn, recurse=True):
        self._sums = None  # the treecode's lists hold the points: made again after a move
        return super()._apply(fn, recurse)

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        self._sums = None
        extra = state_dict.get(prefix + "_extra_state")
        if extra is not None:  # before anything is loaded
            check_saved_hyperparameters(
                "PartitionRBF", _with_defaults(extra), self._hyperparameters()
            )
        resize_buffers_for_load(self, state_dict, prefix, list(self._buffers))
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        sizes = {
            "coarse_indices": None,
            "patch_members": self.patch_member_offsets[-1],
            "patch_owner": self.num_controls if self.num_patches else 0,
            "blend_targets": self.blend_offsets[-1],
        }
        for name, size in sizes.items():
            held = self._buffers[name]
            assert held is not None
            if size is not None and held.shape[0] != int(size):
                error_msgs.append(f"{name}: {held.shape[0]} entries, its offsets say {int(size)}")
            bound = {"blend_targets": self.num_targets, "patch_owner": self.num_patches}
            if held.numel() and int(held.max()) >= bound.get(name, self.num_controls):
                error_msgs.append(f"{name}: indices beyond the stored points")

    # ---------------------------------------------------------------- forward
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
        values = columns_of(displacements).double()
        controls, targets = self.controls.double(), self.targets.double()
        coarse = controls[self.coarse_indices]
        kind = KINDS[int(self.coarse_solver)]
        factors = {name: self._buffers[f"coarse_{name}"] for name in FACTOR_NAMES}
        threads = torch.get_num_threads()
        if self.tolerance is not None and self.num_patches:
            result = self._global(values, controls, targets, threads)
            return from_columns(result.to(displacements.dtype), displacements)
        weights, tail = solve(kind, factors, values[self.coarse_indices])  # type: ignore[arg-type]
        result = self._coarse_value(targets, coarse, weights, tail, threads)
        if self.num_patches:
            residual = values - self._coarse_value(controls, coarse, weights, tail, threads)
            with _parallel.one_torch_thread():
                result = result + self._blend(residual, controls, targets, threads)
        return from_columns(result.to(displacements.dtype), displacements)

    def _coarse_value(self, points: Tensor, coarse: Tensor, weights, tail, threads) -> Tensor:
        value = kernel_sum(
            points, coarse, weights, self.kernel, self.scale, self.block_bytes, threads
        )
        if self.powers:
            poly = polynomial_matrix(points, self.powers, self.coarse_shift, self.coarse_scale)
            value = value + poly @ tail
        return value

    def _layout(self) -> dict[str, tuple[list, list]]:
        return {
            name: (
                self._buffers[f"patch_{name}_shapes"].tolist(),  # type: ignore[union-attr]
                self._buffers[f"patch_{name}_offsets"].tolist(),  # type: ignore[union-attr]
            )
            for name in FACTOR_NAMES
        }

    def _blend(self, residual: Tensor, controls: Tensor, targets: Tensor, threads: int) -> Tensor:
        """Σ_j ŵ_j s_j at the targets, s_j the local fit of the residual in patch j (the
        kernel sums on ``threads`` of numba's threads)."""
        layout = self._layout()
        members = self.patch_member_offsets.tolist()
        blends = self.blend_offsets.tolist()
        solvers = self.patch_solver.tolist()
        flat_axes = self.patch_flat.tolist()
        out = residual.new_zeros(targets.shape[0], residual.shape[1])
        for index in range(self.num_patches):
            begin, end = blends[index], blends[index + 1]
            if begin == end:
                continue
            held = self._buffers["patch_members"][members[index] : members[index + 1]]  # type: ignore[index]
            chosen = self.blend_targets[begin:end]
            centre, frame = self.patch_centres[index], self.patch_frames[index]
            weights, tail = solve(
                KINDS[solvers[index]], self._patch_factors(index, layout), residual[held]
            )
            local_controls = (controls[held] - centre) @ frame
            local_targets = (targets[chosen] - centre) @ frame
            value = kernel_sum(
                local_targets,
                local_controls,
                weights,
                self.kernel,
                self.scale,
                self.block_bytes,
                threads,
            )
            powers = self._local_powers(flat_axes[index])
            if powers:
                zero = centre.new_zeros(centre.shape[0])
                spread = self.patch_spreads[index]
                value = value + polynomial_matrix(local_targets, powers, zero, spread) @ tail
            out.index_add_(0, chosen, value * self.blend_weights[begin:end, None])
        return out

    def extra_repr(self) -> str:
        return (
            f"num_controls={self.num_controls}, num_targets={self.num_targets}, "
            f"kernel={self.kernel!r}, degree={self.degree}, patches={self.num_patches}, "
            f"coarse_size={int(self.coarse_indices.shape[0])}"
        )


def _with_defaults(saved):
    """A saved extra state with the fields added since 0.3.0's first partition of unity
    (``tolerance``, ``max_iterations``, ``summation``) at their defaults when absent."""
    if not isinstance(saved, dict):
        return saved
    defaults = {"tolerance": None, "max_iterations": DEFAULT_MAX_ITERATIONS, "summation": "auto"}
    return {**defaults, **saved}


def _integer(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)
