"""The :class:`IDW` module: the reference geometry and, in dense mode, W as registered
buffers, over the functional core of :mod:`torchmorph.idw.functional` (the paper's
eqs. 1–2; numerics and implementations are described there)."""

from __future__ import annotations

import time
from typing import Literal

import torch
from torch import Tensor, nn

from torchmorph._checks import (
    as_points,
    check_choice,
    check_finite,
    check_positive,
    check_same_device_dtype,
    check_vectors,
    dim_of,
)
from torchmorph._memory import free_memory
from torchmorph._state import check_saved_hyperparameters, resize_buffers_for_load
from torchmorph.idw._dispatch import (
    apply_with,
    assemble_weights,
    backend_for,
    dense_apply,
    fused_available,
)
from torchmorph.idw._dispatch import check_implementation as _check_implementation
from torchmorph.idw._geometry import (
    check_power,
    check_tolerance,
    prepare,
    warn_duplicate_controls,
)
from torchmorph.idw._tree_mode import TreeOperator, tree_pays
from torchmorph.idw.functional import (
    DEFAULT_COINCIDENCE_TOLERANCE,
    Implementation,
    idw_apply,
    idw_weights,
)

__all__ = ["DEFAULT_DENSE_BYTES", "IDW", "Mode", "auto_mode"]

DEFAULT_DENSE_BYTES: int | None = None
"""``mode="auto"`` stores W (dense) when it takes at most this many bytes; ``None``
means half of the memory the device has free when the module is built."""

Mode = Literal["auto", "dense", "matrix_free", "tree"]


def auto_mode(
    num_targets: int,
    num_controls: int,
    *,
    dtype: torch.dtype,
    device: torch.device,
    dense_bytes: int | None = DEFAULT_DENSE_BYTES,
    implementation: str = "auto",
    tolerance: float | None = None,
    power: float = 4.0,
    dim: int = 3,
    requires_grad: bool = False,
) -> Literal["dense", "matrix_free", "tree"]:
    """What ``mode="auto"`` resolves to: ``"dense"``, ``"matrix_free"`` or ``"tree"``.

    ``"tree"`` only when a ``tolerance`` is given, where the fused CPU kernels run, for
    points that do not require grad, and where the tree was measured faster than the
    exact sum (:func:`~torchmorph.idw._tree_mode.tree_pays`: p = 4, 3-D, from 10^9
    target–control pairs at tolerances from 1e-5 up, from 10^10 at 1e-7 up).
    Matrix-free when W (num_targets × num_controls) would take more than ``dense_bytes``
    (default: half the device's free memory), in float32 (on a GPU a stored float32 W is
    applied by float32 BLAS, 5–17× less accurate than the fused kernels, measured against
    float64 sums; on the CPU the stored-W pass of :mod:`torchmorph._dense` sums in float64,
    as accurate as they are), and on the CPU where the fused numba kernels run: there a
    stored W first costs its assembly, which a later morph repays only by the difference
    of one matrix-free call and one stored-W product (12.1 ms against 8.5 ms at case C's
    counts, float64, one thread) — ``IDW(controls, targets)(d)`` at 3,322 × 3,864 in
    float64 took 13.6× less than a NumPy ``cdist`` version matrix-free against 2.3×
    dense, and a matrix-free module's first call finds the nearest distances within its
    one pass. Pass ``mode="dense"`` for thousands of morphs of one geometry.
    Dense otherwise (a GPU in float64, the torch implementation), where a stored W is
    applied by one GEMM.
    """
    fused = device.type == "cpu" and implementation != "torch" and fused_available(device)
    if tolerance is not None and fused and not requires_grad:
        pairs = num_targets * num_controls
        if tree_pays(pairs, tolerance=tolerance, power=power, dim=dim):
            return "tree"
    budget = free_memory(device) // 2 if dense_bytes is None else dense_bytes
    size = num_targets * num_controls * torch.finfo(dtype).bits // 8
    if size > budget or dtype == torch.float32:
        return "matrix_free"
    return "matrix_free" if fused else "dense"


class IDW(nn.Module):
    """IDW interpolation from control points to target points (the paper's eq. 1–2).

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
        Control points (e.g. the selected boundary nodes), D = 2 or 3.
    targets : Tensor, shape (N_t, D)
        Points whose displacement is interpolated (e.g. the interior nodes).
    power : float
        IDW exponent p > 0; default 4 (the paper's).
    mode : {"auto", "dense", "matrix_free", "tree"}
        ``dense`` assembles and stores W (N_t, N_c) once; ``matrix_free``
        recomputes weights on every call and never stores W; ``tree`` applies a tree
        operator built once, to the relative error ``tolerance`` (CPU only): with
        ``error_control="certified"`` a :class:`~torchmorph.idw.tree.TreeIDW` (far
        clusters of controls by a quadrupole expansion, with a bound), with
        ``"sampled"`` a :class:`~torchmorph.idw.treecode.TreecodeIDW` (far pairs by
        barycentric interpolation on both sides);
        ``auto`` with a ``tolerance`` takes the tree, with sampled error control, where it
        was measured faster than the exact sum (:func:`auto_mode`: the fused CPU kernels,
        p = 4, 3-D, from 10^9 target–control pairs at tolerances from 1e-5 up and from
        10^10 at 1e-7 up; its first call then costs about the exact sum's, later ones a
        third at 1e-4), and otherwise one of the two exact modes, which meet any
        tolerance: matrix-free where the fused CPU kernels run (a fused
        pass costs about 1.4× a stored-W product, so W repays its assembly only over
        many morphs) and in float32 (on a GPU a float32 W sums in float32 BLAS, 5–17×
        less accurately than the kernels' float64 partial sums); elsewhere dense when W
        takes at most ``dense_bytes``. Pass ``mode="dense"`` for W itself
        (``torch.compile``, thousands of morphs of one geometry, repeated large batches
        on a GPU).
    tolerance : float, optional
        ``mode="tree"`` (default :data:`~torchmorph.idw.tree.DEFAULT_TOLERANCE`, 1e-4) or
        ``"auto"``: the relative error ``‖u_tree - u‖ / ‖u‖`` (2-norm over the targets,
        per displacement field) that the tree keeps. With ``"auto"`` it allows the tree
        (above), whose sampled error control estimates that error at sampled targets
        rather than bounding it (:class:`~torchmorph.idw.treecode.TreecodeIDW`); where
        auto picks an exact mode, ``tolerance`` is ``None`` afterwards.
    error_control : {"certified", "sampled"}, optional
        ``mode="tree"`` only: how the tree keeps ``tolerance``. ``"certified"`` (default)
        by a worst-case bound (:class:`~torchmorph.idw.tree.TreeIDW`) — slower than the
        exact sum at the sizes measured; ``"sampled"`` by exact sums at sampled targets
        (:class:`~torchmorph.idw.treecode.TreecodeIDW`) — an estimate, and the fast one:
        see ``benchmarks/README.md``, "Tree-approximated IDW", for its speed-ups.
    block_bytes : int, optional
        Byte budget of one block of pairwise temporaries of the torch
        implementation (default: 4 MiB on the CPU, 256 MiB on CUDA).
    dense_bytes : int, optional
        Threshold for ``mode="auto"`` (default: half the memory the device has
        free when the module is built).
    coincidence_tolerance : float
        Relative distance under which a target takes a control's value exactly.
    implementation : {"auto", "fused", "torch"}
        Fused kernels (Triton on CUDA, numba on the CPU) or torch operations; see
        :mod:`torchmorph.idw`. Chosen per call, so ``.to("cuda")`` just works.

    Attributes
    ----------
    controls, targets : buffers
        The reference geometry (copies of the inputs, unless these require grad:
        then they are kept, borrowed, so that W can be rebuilt from them).
    weights : buffer, shape (N_t, N_c), dense mode only
        W (rows sum to 1).
    assembly_time : float
        Seconds spent assembling W, or building the trees in tree mode (0 in
        matrix-free mode).

    Raises
    ------
    ValueError
        For bad points or options; ``mode="dense"`` when W does not fit in the
        memory the device has free (before allocating; the message names
        ``mode="matrix_free"``); ``tolerance`` given with a mode other than ``"tree"``
        or ``"auto"``, ``error_control`` with a mode other than ``"tree"``; in tree mode,
        points off the CPU or that require grad.

    Notes
    -----
    Gradients always flow to the displacements. To differentiate with respect
    to geometry, either pass ``controls``/``targets`` that require grad to the
    constructor (the module then rebuilds W differentiably from them on every
    call made with grad enabled) or pass new positions to :meth:`forward`; those
    calls use the torch implementation. ``.to(device)`` of a module built from
    tensors that require grad makes copies: the link to the caller's tensors is
    then lost.

    The whole state is in :meth:`state_dict`: the geometry, W in dense mode, and
    ``power``, ``coincidence_tolerance`` and ``mode`` as extra state. Loading a
    state saved with another power or tolerance raises; a dense state loads into
    a matrix-free module (W is dropped) and a matrix-free one into a dense module
    (W is assembled from the loaded geometry).

    Tree mode (:mod:`torchmorph.idw.tree`, :mod:`torchmorph.idw.treecode`) approximates:
    gradients flow to the displacements only (the backward applies the transpose of the
    operator that the forward used; with ``"certified"`` its accuracy follows the
    forward's displacements: an all-zero field gets the loosest threshold, and a
    vector-Jacobian product taken at zeros is not held to ``tolerance``), moved ``controls``/``targets`` in :meth:`forward` are
    refused, and :meth:`weights_matrix` raises — the tree stores no W, and an exact W
    would not be the map that :meth:`forward` applies. Its state holds ``tolerance``
    beside ``mode``; two tree states must agree on it, and a tree state loads into a
    dense or matrix-free module and back (the geometry is the state; the trees are
    rebuilt from it). ``.to("cuda")`` of a tree module moves its buffers, but its
    forward then raises: the tree has no CUDA kernels. Tree mode does not compose with
    ``torch.func`` nor trace under ``torch.compile``.

    The forward composes with ``torch.func``: ``vmap`` over displacements (a
    per-value family mapped over μ equals the batched call), ``grad``, ``jacrev``
    and ``jacfwd`` in the exact modes; in dense mode also over moved positions. Dense
    mode traces under ``torch.compile(fullgraph=True)`` without graph breaks (the
    finiteness check of the inputs is skipped while compiling); matrix-free mode
    does not (its KD-tree search runs in NumPy), nor does it ``vmap`` over positions.
    """

    controls: Tensor
    targets: Tensor
    weights: Tensor | None

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        power: float = 4.0,
        mode: Mode = "auto",
        block_bytes: int | None = None,
        dense_bytes: int | None = DEFAULT_DENSE_BYTES,
        coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
        implementation: Implementation = "auto",
        tolerance: float | None = None,
        error_control: str | None = None,
    ) -> None:
        super().__init__()
        controls = as_points(controls, "controls", dim=dim_of(controls))
        targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True)
        check_same_device_dtype(controls, "controls", targets, "targets")
        check_choice(mode, "mode", ("auto", "dense", "matrix_free", "tree"))
        takes = {"tolerance": ("tree", "auto"), "error_control": ("tree",)}
        for name, value in (("tolerance", tolerance), ("error_control", error_control)):
            if value is not None and mode not in takes[name]:
                modes = " or ".join(repr(kind) for kind in takes[name])
                raise ValueError(
                    f"{name}: only mode={modes} takes {name} (the other modes are exact), "
                    f"got mode={mode!r}"
                )
        self.power = check_power(power)
        self.block_bytes = (
            None if block_bytes is None else int(check_positive(block_bytes, "block_bytes"))
        )
        self.dense_bytes = (
            None if dense_bytes is None else int(check_positive(dense_bytes, "dense_bytes"))
        )
        self.coincidence_tolerance = check_tolerance(coincidence_tolerance)
        self.implementation = _check_implementation(implementation)
        size = targets.shape[0] * controls.shape[0] * controls.element_size()
        if mode == "auto":
            if tolerance is not None:
                from torchmorph.idw.tree import _check_tolerance as _check_tree_tolerance

                tolerance = _check_tree_tolerance(tolerance)
            mode = auto_mode(
                targets.shape[0],
                controls.shape[0],
                dtype=controls.dtype,
                device=controls.device,
                dense_bytes=self.dense_bytes,
                implementation=self.implementation,
                tolerance=tolerance,
                power=self.power,
                dim=controls.shape[1],
                requires_grad=controls.requires_grad or targets.requires_grad,
            )
            if mode == "tree":  # the fast error control; the exact modes ignore tolerance
                error_control = "sampled"
            else:
                tolerance = None
        elif mode == "dense":
            free = free_memory(controls.device)
            if size > free:
                raise ValueError(
                    f"mode='dense': W ({targets.shape[0]:,} x {controls.shape[0]:,}, "
                    f"{size / 2**30:.1f} GiB) does not fit in the {free / 2**30:.1f} GiB free on "
                    f"{controls.device}; use mode='matrix_free'"
                )
        self.mode: str = mode
        warn_duplicate_controls(controls, self.coincidence_tolerance, targets)
        # copies, so that later in-place edits of the caller's tensors cannot leave W stale
        self.register_buffer("controls", controls if controls.requires_grad else controls.clone())
        self.register_buffer("targets", targets if targets.requires_grad else targets.clone())
        self.assembly_time = 0.0
        self._fused_cache: tuple | None = None
        self.tolerance: float | None = None
        self.error_control: str | None = None
        self._tree: TreeOperator | None = None
        if mode == "tree":
            self._tree = TreeOperator(
                self.power, self.coincidence_tolerance, tolerance, error_control
            )
            self.tolerance = self._tree.tolerance
            self.error_control = self._tree.error_control
            start = time.perf_counter()
            self._tree.operator(self.controls, self.targets)
            self.assembly_time = time.perf_counter() - start
        if mode == "dense":
            start = time.perf_counter()
            with torch.no_grad():
                weights = self._assemble(self.targets.detach(), self.controls.detach())
            self.assembly_time = time.perf_counter() - start
            self.register_buffer("weights", weights)
        else:
            self.weights = None

    @property
    def num_controls(self) -> int:
        return self.controls.shape[0]

    @property
    def num_targets(self) -> int:
        return self.targets.shape[0]

    def _assemble(self, targets: Tensor, controls: Tensor) -> Tensor:
        targets, controls, power, radius2 = prepare(
            targets, controls, self.power, self.coincidence_tolerance
        )
        return assemble_weights(
            targets, controls, power, radius2, self.block_bytes, self.implementation
        )

    def weights_matrix(self) -> Tensor:
        """W of shape (N_t, N_c): the stored buffer, or assembled now (matrix-free).

        Raises ``RuntimeError`` in tree mode, which has no W (see the class notes)."""
        if self._tree is not None:
            raise RuntimeError(
                "weights_matrix: mode='tree' stores no W and applies an approximation of "
                "it; build the IDW with mode='dense' or 'matrix_free' for W"
            )
        if self.weights is not None:
            return self.weights
        with torch.no_grad():
            return self._assemble(self.targets.detach(), self.controls.detach())

    def transposed(self, values: Tensor) -> Tensor:
        """``Wᵀ values`` for a field at the targets, (N_t, D) or (B, N_t, D) -> (N_c, D) or
        (B, N_c, D): the adjoint of :meth:`forward` at the stored geometry.

        In tree mode the transpose of the tree's operator at the threshold its tolerance
        chose (:meth:`~torchmorph.idw.tree.TreeIDW.transposed`); otherwise the exact one
        (a vector-Jacobian product). No gradients flow through it in tree mode.
        """
        if self._tree is not None:
            return self._tree.operator(self.controls, self.targets).transposed(values)
        with torch.enable_grad():
            shape = (*values.shape[:-2], self.num_controls, values.shape[-1])
            probe = values.new_zeros(shape, requires_grad=True)
            (result,) = torch.autograd.grad(self(probe), probe, grad_outputs=values)
        return result

    # ----------------------------------------------------------------- state
    def get_extra_state(self) -> dict:
        state = {
            "power": self.power,
            "coincidence_tolerance": self.coincidence_tolerance,
            "mode": self.mode,
        }
        if self.tolerance is None:
            return state
        return {**state, "tolerance": self.tolerance, "error_control": self.error_control}

    def set_extra_state(self, state: dict) -> None:
        self._check_saved(state)

    def _hyperparameters(self) -> dict[str, float]:
        return {"power": self.power, "coincidence_tolerance": self.coincidence_tolerance}

    def _check_saved(self, state: dict) -> None:
        """The load rule; ``tolerance`` is compared between two tree states only."""
        check_saved_hyperparameters("IDW", state, self._hyperparameters())
        if self.mode == "tree" and state.get("mode") == "tree":
            saved = {"error_control": "certified", **state}  # states before it: certified
            current = {"tolerance": self.tolerance, "error_control": self.error_control}
            check_saved_hyperparameters("IDW", saved, current)

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        if prefix + "_extra_state" in state_dict:  # before anything is loaded
            self._check_saved(state_dict[prefix + "_extra_state"])
        key = prefix + "weights"
        has_weights = key in state_dict
        if self.mode in ("matrix_free", "tree") and has_weights:  # a dense state: W is not needed
            state_dict = {k: v for k, v in state_dict.items() if k != key}
        resize_buffers_for_load(self, state_dict, prefix, ("controls", "targets", "weights"))
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        self._fused_cache = None
        if self.mode == "dense" and not has_weights:  # a matrix-free state: assemble W
            if key in missing_keys:
                missing_keys.remove(key)
            with torch.no_grad():
                self._buffers["weights"] = self._assemble(
                    self.targets.detach(), self.controls.detach()
                )
        for name in ("controls", "targets"):
            incoming = state_dict.get(prefix + name)
            if incoming is not None and incoming.shape[-1:] != self._buffers[name].shape[-1:]:
                error_msgs.append(
                    f"{name}: the state holds points of shape {tuple(incoming.shape)}"
                )
        weights = self._buffers.get("weights")
        if weights is not None and weights.shape != (self.num_targets, self.num_controls):
            error_msgs.append(
                f"weights: shape {tuple(weights.shape)} does not match "
                f"{self.num_targets} targets x {self.num_controls} controls"
            )

    def _geometry_requires_grad(self) -> bool:
        return self.controls.requires_grad or self.targets.requires_grad

    def _fused_geometry(self, backend):
        """Normalised geometry in the backend's layout and the nearest distances of the
        stored points, computed once per geometry (and again after it changes)."""
        key = (
            backend,
            self.controls.data_ptr(),
            self.targets.data_ptr(),
            self.controls._version,
            self.targets._version,
            self.controls.device,
            self.controls.dtype,
        )
        if self._fused_cache is None or self._fused_cache[0] != key:
            with torch.no_grad():
                targets, controls, _, radius2 = prepare(
                    self.targets.detach(),
                    self.controls.detach(),
                    self.power,
                    self.coincidence_tolerance,
                )
                targets, controls = backend.layout(targets), backend.layout(controls)
                # a streaming backend finds the nearest distances in the first call's pass
                streams = getattr(backend, "apply_streaming", None) is not None
                nearest2 = None if streams else backend.nearest(targets, controls)
            self._fused_cache = (key, targets, controls, radius2, nearest2)
        return self._fused_cache[1:]

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
            Moved positions (same shapes as the reference) to use instead of the
            stored geometry; W is then rebuilt differentiably from them.

        Returns
        -------
        Tensor, shape (N_t, D) or (B, N_t, D)
        """
        dim = self.controls.shape[1]
        check_vectors(
            displacements,
            "displacements",
            self.num_controls,
            dim=dim,
            what="control points",
            finite=False,
        )
        magnitude = check_finite(displacements, "displacements")
        check_same_device_dtype(
            self.controls, "the module's controls", displacements, "displacements"
        )
        if self._tree is not None:
            for name, moved in (("controls", controls), ("targets", targets)):
                if moved is not None:
                    raise ValueError(
                        f"{name}: mode='tree' applies the operator of the stored geometry; "
                        "moved positions need mode='dense' or 'matrix_free'"
                    )
            return self._tree.operator(self.controls, self.targets)(displacements)
        new_geometry = controls is not None or targets is not None
        if controls is not None:
            controls = self._check_moved(controls, self.controls, "controls")
        if targets is not None:
            targets = self._check_moved(targets, self.targets, "targets")
        controls = self.controls if controls is None else controls
        targets = self.targets if targets is None else targets
        rebuild = new_geometry or (torch.is_grad_enabled() and self._geometry_requires_grad())
        if self.mode == "matrix_free":
            if not rebuild:
                backend = backend_for(self.implementation, self.controls, displacements)
                if not backend.differentiable and self.num_targets:
                    return self._fused_matrix_free(backend, displacements, magnitude)
            return idw_apply(
                controls=controls,
                targets=targets,
                displacements=displacements,
                power=self.power,
                coincidence_tolerance=self.coincidence_tolerance,
                block_bytes=self.block_bytes,
                implementation=self.implementation,
            )
        if rebuild:
            weights = idw_weights(
                controls=controls,
                targets=targets,
                power=self.power,
                coincidence_tolerance=self.coincidence_tolerance,
                block_bytes=self.block_bytes,
                implementation=self.implementation,
            )
            return weights @ displacements
        assert self.weights is not None  # dense mode keeps W
        return dense_apply(self.weights, displacements, self.implementation)

    def _fused_matrix_free(self, backend, displacements: Tensor, magnitude: float) -> Tensor:
        targets, controls, radius2, nearest2 = self._fused_geometry(backend)
        batched, dim = displacements.ndim == 3, displacements.shape[-1]
        batch = displacements.shape[0] if batched else 1
        values = (displacements.permute(1, 0, 2) if batched else displacements).reshape(
            self.num_controls, dim * batch
        )
        streaming = getattr(backend, "apply_streaming", None)
        finite = magnitude * max(1, values.shape[0]) <= torch.finfo(values.dtype).max / 4
        plain = finite and not (torch.is_grad_enabled() and values.requires_grad)
        if nearest2 is None and streaming and backend.needs_nearest(values.shape[1]) and plain:
            result, _, nearest2 = streaming(
                targets, controls, values.contiguous(), self.power, radius2
            )
            assert self._fused_cache is not None
            self._fused_cache = (*self._fused_cache[:4], nearest2)  # later calls: one pass
        else:
            result = apply_with(
                backend, targets, controls, values, self.power, radius2, nearest2, magnitude
            )
        result = result.reshape(self.num_targets, batch, dim)
        return result.permute(1, 0, 2) if batched else result[:, 0]

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
        return (
            f"num_controls={self.num_controls}, num_targets={self.num_targets}, "
            f"power={self.power:g}, mode={self.mode!r}, "
            + ("" if self.tolerance is None else f"tolerance={self.tolerance:g}, ")
            + f"implementation={self.implementation!r}"
        )
