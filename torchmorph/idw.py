"""Inverse Distance Weighting (the paper's Section 2, eqs. 1–4).

Pure functions (:func:`idw_weights`, :func:`idw_apply`) over point tensors, and
the :class:`IDW` module that holds the reference geometry and, in dense mode,
the weight matrix ``W`` as registered buffers.

Numerics
--------
Both point clouds are first translated and scaled so that their joint bounding
box has diagonal 1 (W is invariant under that map), so coordinates from 1e-30 to
1e30 give the same weights. Row ``i`` of ``W`` is then ``(m_i / d²_ik)^(p/2)``
normalised by its sum, with ``d²_ik`` the squared distance from target ``i`` to
control ``k`` (direct coordinate differences, never the ``|x|² + |c|² − 2x·c``
expansion, which cancels catastrophically) and ``m_i`` the row's smallest
squared distance. This equals eq. (2) exactly, and every term lies in [0, 1], so
nothing overflows or underflows harmfully in float32 or float64.

A target closer than ``coincidence_tolerance`` times the bounding-box diagonal to
a control takes that control's displacement exactly (exact interpolation). If it
lies that close to several controls (duplicated control points), it takes the
mean of their displacements, whatever their order; :class:`IDW` warns about such
duplicates when it is built.

Implementations
---------------
``implementation="fused"`` runs kernels that compute the weights in registers and
never store a pairwise tile: Triton on CUDA devices (:mod:`torchmorph._triton_kernels`)
and numba on the CPU (:mod:`torchmorph._cpu_kernels`, when numba is installed). On
the CPU a batch of more than 24 value columns (nine displacements or more) is applied
by blocks of W rows from the fused assembly kernel, each multiplied by torch's GEMM
while in cache (W is never stored whole): the GEMM's cost hardly grows with the
columns. ``"torch"`` runs the same arithmetic in blocks of torch operations, which works
everywhere and under ``torch.compile`` and ``torch.func``. ``"auto"`` (the
default) takes the fused kernels where they apply and torch elsewhere.
"""

from __future__ import annotations

import time
from typing import Literal

import torch
from torch import Tensor, nn

from ._checks import (
    as_points,
    check_positive,
    check_same_device_dtype,
    check_vectors,
)
from ._idw_fused import (
    IMPLEMENTATIONS,
    _assemble_weights,
    _check_implementation,
    _dense_apply,
    _fused_for,
    _FusedApply,
    fused_available,
)
from ._idw_geometry import (
    _check_power,
    _check_tolerance,
    _free_memory,
    _points_arguments,
    _prepare,
    _warn_duplicate_controls,
)
from ._idw_torch import (
    DEFAULT_BLOCK_BYTES,
    DEFAULT_CUDA_BLOCK_BYTES,
    _block_bytes,
    _functional,
    _rows_per_block,
    _torch_apply,
    _weights_block,
)
from ._state import resize_buffers_for_load

__all__ = [
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_CUDA_BLOCK_BYTES",
    "DEFAULT_DENSE_BYTES",
    "IDW",
    "IMPLEMENTATIONS",
    "fused_available",
    "idw_apply",
    "idw_weights",
]

DEFAULT_DENSE_BYTES: int | None = None
"""``mode="auto"`` stores W (dense) when it takes at most this many bytes; ``None``
means half of the memory the device has free when the module is built."""

DEFAULT_COINCIDENCE_TOLERANCE = 1e-10
"""Targets closer to a control than this fraction of the cloud's bounding-box
diagonal take that control's displacement exactly."""

Mode = Literal["auto", "dense", "matrix_free"]
Implementation = Literal["auto", "fused", "torch"]


# --------------------------------------------------------------------------- #
# helpers
# --------------------------------------------------------------------------- #
# --------------------------------------------------------------------------- #
# functional API
# --------------------------------------------------------------------------- #
def idw_weights(
    *points: Tensor,
    controls: Tensor | None = None,
    targets: Tensor | None = None,
    power: float = 4.0,
    coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
    block_bytes: int | None = None,
    implementation: Implementation = "auto",
) -> Tensor:
    """Dense IDW weight matrix, the paper's eq. (2).

    Parameters
    ----------
    controls : Tensor, shape (N_c, D), keyword
        Control points with known displacements.
    targets : Tensor, shape (N_t, D), keyword
        Points to interpolate to (the interior nodes).
    power : float
        The exponent p > 0 (the paper's p = 4).
    coincidence_tolerance : float
        A target within this fraction of the clouds' bounding-box diagonal of a
        control takes that control's row exactly (1 there, 0 elsewhere; the mean
        over several controls that close).
    block_bytes : int, optional
        Size of the pairwise temporaries of one block of rows in the torch
        implementation (default: 4 MiB on the CPU, 256 MiB on a CUDA device).
    implementation : {"auto", "fused", "torch"}
        Fused kernels write W once (Triton on CUDA, numba on the CPU); see the
        module's notes. Gradients to the points always use the torch implementation.

    Returns
    -------
    Tensor, shape (N_t, N_c)
        Rows sum to 1. Differentiable with respect to ``targets`` and
        ``controls`` when they require grad.

    Raises
    ------
    ValueError
        For wrong shapes, empty controls, NaN/inf, power <= 0, mismatched
        dtype or device, or an implementation that cannot run.

    Notes
    -----
    The points are keywords, in the order of :class:`IDW` (controls, then targets).
    The former positional call ``idw_weights(targets, controls)`` still works, with a
    ``DeprecationWarning``.
    """
    controls, targets = _points_arguments("idw_weights", points, controls, targets)
    targets, controls, power, radius2 = _prepare(targets, controls, power, coincidence_tolerance)
    if not _functional(targets, controls):
        return _assemble_weights(targets, controls, power, radius2, block_bytes, implementation)
    if _check_implementation(implementation) == "fused":
        raise ValueError(
            "implementation='fused' cannot run here: a W that carries gradients to "
            "the points (or is traced) is built by the torch implementation"
        )
    if targets.shape[0] == 0:  # an empty W that still carries the inputs' graph
        return (targets.sum() + controls.sum()) * 0 + controls.new_zeros(0, controls.shape[0])
    rows = _rows_per_block(
        controls.shape[0],
        controls.element_size(),
        _block_bytes(block_bytes, controls.device),
        copies=4,
    )
    return torch.cat(
        [
            _weights_block(targets[s : s + rows], controls, power, radius2)
            for s in range(0, targets.shape[0], rows)
        ]
    )


def idw_apply(
    *points: Tensor,
    controls: Tensor | None = None,
    targets: Tensor | None = None,
    displacements: Tensor | None = None,
    power: float = 4.0,
    coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
    block_bytes: int | None = None,
    implementation: Implementation = "auto",
) -> Tensor:
    """Matrix-free IDW: ``W @ displacements`` without ever storing ``W``.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D), keyword
    targets : Tensor, shape (N_t, D), keyword
    displacements : Tensor, shape (N_c, 3) or (B, N_c, 3), keyword
    power, coincidence_tolerance
        As in :func:`idw_weights`.
    block_bytes : int, optional
        Byte budget of one tile of pairwise temporaries of the torch
        implementation; its peak memory is about this plus
        O((N_t + N_c) · (3B + 1)). The fused kernels need no temporaries.
    implementation : {"auto", "fused", "torch"}
        See the module's notes.

    Returns
    -------
    Tensor, shape (N_t, 3) or (B, N_t, 3)
        Same values as ``idw_weights(controls=..., targets=...) @ displacements``.

    Notes
    -----
    The points and displacements are keywords (the former positional call
    ``idw_apply(targets, controls, displacements)`` still works, with a
    ``DeprecationWarning``). The fused kernels (two passes over the controls: the nearest distance, then
    the ratio weights against ``[d, 1]``, divided at the end) serve the forward
    pass and the backward pass: the gradient to the displacements is a second
    fused pass applying Wᵀ to the incoming gradient, and on CUDA the gradients to
    the point positions are two more fused passes (for D <= 3 and at most 24 value
    columns, i.e. 8 displacements; coincident rows, whose weights are locally
    constant, contribute none). Elsewhere (the CPU kernels, more columns), when
    ``targets`` or ``controls`` require grad the torch implementation runs,
    recomputing each block of rows in the backward pass (activation
    checkpointing), so W is never stored either. Inside ``torch.func`` transforms
    (``grad``, ``jacrev``: no saved-tensor hooks there) blocks are not
    checkpointed, so the graph holds the weights of every tile. The torch
    implementation's KD-tree and coincident-row branch read values in Python:
    matrix-free mode is not traceable by ``torch.compile`` without graph breaks
    (use dense mode there).
    """
    if points:
        controls, targets, displacements = _points_arguments(
            "idw_apply", points, controls, targets, count=3
        )
    else:
        controls, targets = _points_arguments("idw_apply", points, controls, targets)
        if displacements is None:
            raise TypeError("idw_apply() needs displacements=")
    targets, controls, power, radius2 = _prepare(targets, controls, power, coincidence_tolerance)
    batched = check_vectors(
        displacements, "displacements", controls.shape[0], what="control points"
    )
    check_same_device_dtype(controls, "controls", displacements, "displacements")
    batch = displacements.shape[0] if batched else 1
    values = (displacements.permute(1, 0, 2) if batched else displacements).reshape(
        controls.shape[0], 3 * batch
    )
    inputs = (targets, controls, displacements)
    positions_grad = torch.is_grad_enabled() and (targets.requires_grad or controls.requires_grad)
    backend = _fused_for(
        implementation,
        *inputs,
        positions_grad=positions_grad,
        shape=(controls.shape[1], values.shape[1]),
    )
    if backend is not None:
        result = _FusedApply.apply(
            backend.layout(targets), backend.layout(controls), values, backend, power, radius2, None
        )
    else:
        result = _torch_apply(targets, controls, values, power, radius2, block_bytes)
    result = result.reshape(targets.shape[0], batch, 3)
    return result.permute(1, 0, 2) if batched else result[:, 0]


# --------------------------------------------------------------------------- #
# module
# --------------------------------------------------------------------------- #
class IDW(nn.Module):
    """IDW interpolation from control points to target points (the paper's eq. 1–2).

    Parameters
    ----------
    controls : Tensor, shape (N_c, 3)
        Control points (e.g. the selected boundary nodes).
    targets : Tensor, shape (N_t, 3)
        Points whose displacement is interpolated (e.g. the interior nodes).
    power : float
        IDW exponent p > 0; default 4 (the paper's).
    mode : {"auto", "dense", "matrix_free"}
        ``dense`` assembles and stores W (N_t, N_c) once; ``matrix_free``
        recomputes weights on every call and never stores W; ``auto`` picks
        dense when W takes at most ``dense_bytes``.
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
        Seconds spent assembling W (0 in matrix-free mode).

    Raises
    ------
    ValueError
        For bad points or options; ``mode="dense"`` when W does not fit in the
        memory the device has free (before allocating; the message names
        ``mode="matrix_free"``).

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

    The forward composes with ``torch.func``: ``vmap`` over displacements (a
    per-value family mapped over μ equals the batched call), ``grad``, ``jacrev``
    and ``jacfwd`` in both modes; in dense mode also over moved positions. Dense
    mode traces under ``torch.compile(fullgraph=True)`` without graph breaks (the
    finiteness check of the inputs is skipped while compiling); matrix-free mode
    does not (its KD-tree search runs in NumPy), nor does it ``vmap`` over positions.
    """

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
    ) -> None:
        super().__init__()
        controls = as_points(controls, "controls")
        targets = as_points(targets, "targets", allow_empty=True)
        check_same_device_dtype(controls, "controls", targets, "targets")
        if mode not in ("auto", "dense", "matrix_free"):
            raise ValueError(f"mode must be 'auto', 'dense' or 'matrix_free', got {mode!r}")
        self.power = _check_power(power)
        self.block_bytes = (
            None if block_bytes is None else int(check_positive(block_bytes, "block_bytes"))
        )
        self.dense_bytes = (
            None if dense_bytes is None else int(check_positive(dense_bytes, "dense_bytes"))
        )
        self.coincidence_tolerance = _check_tolerance(coincidence_tolerance)
        self.implementation = _check_implementation(implementation)
        size = targets.shape[0] * controls.shape[0] * controls.element_size()
        if mode == "auto":
            budget = self.dense_bytes
            if budget is None:
                budget = _free_memory(controls.device) // 2
            mode = "dense" if size <= budget else "matrix_free"
        elif mode == "dense":
            free = _free_memory(controls.device)
            if size > free:
                raise ValueError(
                    f"mode='dense': W ({targets.shape[0]:,} x {controls.shape[0]:,}, "
                    f"{size / 2**30:.1f} GiB) does not fit in the {free / 2**30:.1f} GiB free on "
                    f"{controls.device}; use mode='matrix_free'"
                )
        self.mode: str = mode
        _warn_duplicate_controls(controls, self.coincidence_tolerance)
        # copies, so that later in-place edits of the caller's tensors cannot leave W stale
        self.register_buffer("controls", controls if controls.requires_grad else controls.clone())
        self.register_buffer("targets", targets if targets.requires_grad else targets.clone())
        self.assembly_time = 0.0
        self._fused_cache: tuple | None = None
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
        targets, controls, power, radius2 = _prepare(
            targets, controls, self.power, self.coincidence_tolerance
        )
        return _assemble_weights(
            targets, controls, power, radius2, self.block_bytes, self.implementation
        )

    def weights_matrix(self) -> Tensor:
        """W of shape (N_t, N_c): the stored buffer, or assembled now (matrix-free)."""
        if self.weights is not None:
            return self.weights
        with torch.no_grad():
            return self._assemble(self.targets.detach(), self.controls.detach())

    # ----------------------------------------------------------------- state
    def get_extra_state(self) -> dict:
        return {
            "power": self.power,
            "coincidence_tolerance": self.coincidence_tolerance,
            "mode": self.mode,
        }

    def set_extra_state(self, state: dict) -> None:
        if not isinstance(state, dict):
            raise ValueError(f"IDW state: extra state must be a dict, got {type(state).__name__}")
        for field in ("power", "coincidence_tolerance"):
            if field not in state:
                raise ValueError(f"IDW state: the extra state lacks {field!r}")
            if float(state[field]) != getattr(self, field):
                raise ValueError(
                    f"{field}: the state was saved with {field}={state[field]!r} but this module "
                    f"has {field}={getattr(self, field)!r}; build the module with the saved value"
                )

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        key = prefix + "weights"
        has_weights = key in state_dict
        if self.mode == "matrix_free" and has_weights:  # a dense state: W is not needed
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
                targets, controls, _, radius2 = _prepare(
                    self.targets.detach(),
                    self.controls.detach(),
                    self.power,
                    self.coincidence_tolerance,
                )
                targets, controls = backend.layout(targets), backend.layout(controls)
                nearest2 = backend.nearest(targets, controls)
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
        displacements : Tensor, shape (N_c, 3) or (B, N_c, 3)
        controls, targets : Tensor, optional
            Moved positions (same shapes as the reference) to use instead of the
            stored geometry; W is then rebuilt differentiably from them.

        Returns
        -------
        Tensor, shape (N_t, 3) or (B, N_t, 3)
        """
        check_vectors(displacements, "displacements", self.num_controls, what="control points")
        check_same_device_dtype(
            self.controls, "the module's controls", displacements, "displacements"
        )
        new_geometry = controls is not None or targets is not None
        if controls is not None:
            controls = self._check_moved(controls, self.controls, "controls")
        if targets is not None:
            targets = self._check_moved(targets, self.targets, "targets")
        controls = self.controls if controls is None else controls
        targets = self.targets if targets is None else targets
        rebuild = new_geometry or (torch.is_grad_enabled() and self._geometry_requires_grad())
        options = {
            "power": self.power,
            "coincidence_tolerance": self.coincidence_tolerance,
            "block_bytes": self.block_bytes,
            "implementation": self.implementation,
        }
        if self.mode == "matrix_free":
            if not rebuild:
                backend = _fused_for(self.implementation, self.controls, displacements)
                if backend is not None and self.num_targets:
                    return self._fused_matrix_free(backend, displacements)
            return idw_apply(
                controls=controls, targets=targets, displacements=displacements, **options
            )
        if rebuild:
            return idw_weights(controls=controls, targets=targets, **options) @ displacements
        return _dense_apply(self.weights, displacements, self.implementation)

    def _fused_matrix_free(self, backend, displacements: Tensor) -> Tensor:
        targets, controls, radius2, nearest2 = self._fused_geometry(backend)
        batched = displacements.ndim == 3
        batch = displacements.shape[0] if batched else 1
        values = (displacements.permute(1, 0, 2) if batched else displacements).reshape(
            self.num_controls, 3 * batch
        )
        if torch.is_grad_enabled() and values.requires_grad:
            result = _FusedApply.apply(
                targets, controls, values, backend, self.power, radius2, nearest2
            )
        else:
            result = backend.apply(
                targets, controls, values.contiguous(), self.power, radius2, nearest2
            )[0]
        result = result.reshape(self.num_targets, batch, 3)
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
        return as_points(moved, name, allow_empty=True)

    def extra_repr(self) -> str:
        return (
            f"num_controls={self.num_controls}, num_targets={self.num_targets}, "
            f"power={self.power:g}, mode={self.mode!r}, "
            f"implementation={self.implementation!r}"
        )
