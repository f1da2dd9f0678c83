"""Inverse Distance Weighting (SPEC.md §1, paper eqs. 1–4).

Pure functions (:func:`idw_weights`, :func:`idw_apply`) over point tensors, and
the :class:`IDW` module that holds the reference geometry and, in dense mode,
the weight matrix ``W`` as registered buffers.

Numerics
--------
Row ``i`` of ``W`` is computed as ``(m_i / d²_ik)^(p/2)`` normalised by its sum,
with ``d²_ik`` the squared distance from target ``i`` to control ``k`` (direct
coordinate differences, never the ``|x|² + |c|² − 2x·c`` expansion, which
cancels catastrophically) and ``m_i`` the row's smallest squared distance.
This equals eq. (2) exactly, and every term lies in [0, 1], so nothing
overflows or underflows harmfully in float32 or float64. A target closer to a
control than ``coincidence_tolerance`` times the point cloud's size takes that
control's row exactly (1 there, 0 elsewhere): exact interpolation.
"""

from __future__ import annotations

import contextlib
import math
import time
from typing import Literal

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from ._checks import (
    as_points,
    check_positive,
    check_same_device_dtype,
    check_vectors,
    is_traced,
    plain_tensor,
)
from ._state import resize_buffers_for_load

__all__ = [
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_DENSE_BYTES",
    "IDW",
    "idw_apply",
    "idw_weights",
]

DEFAULT_BLOCK_BYTES = 4 * 2**20
"""Working-set size of one block of pairwise temporaries (bytes). Blocks of a few
MB stay in cache; much larger blocks were measured slower."""

DEFAULT_DENSE_BYTES = 4 * 2**30
"""``mode="auto"`` stores W (dense) when it takes at most this many bytes."""

DEFAULT_COINCIDENCE_TOLERANCE = 1e-10
"""Targets closer to a control than this fraction of the cloud's bounding-box
diagonal take that control's displacement exactly."""

Mode = Literal["auto", "dense", "matrix_free"]


# --------------------------------------------------------------------------- #
# helpers
# --------------------------------------------------------------------------- #
def _check_power(power: float) -> float:
    return check_positive(power, "power")


def _functional(*tensors: Tensor) -> bool:
    """Whether to compute out of place: autograd records through one of ``tensors``,
    or the call is traced (``torch.compile``, or functorch-wrapped tensors)."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return True
    return any(is_traced(t) for t in tensors)


def _coincidence_radius2(targets: Tensor, controls: Tensor, tolerance: float) -> float | Tensor:
    """Squared absolute coincidence radius: ``(tolerance * bbox diagonal)²``.

    A Python float, or a 0-d tensor when the geometry is traced (``torch.compile``,
    ``torch.func`` transforms of the positions), so that no value is read in Python.
    """
    if tolerance < 0 or not math.isfinite(tolerance):
        raise ValueError(f"coincidence_tolerance must be finite and >= 0, got {tolerance!r}")
    with torch.no_grad():
        both = torch.cat([targets.detach(), controls.detach()]) if targets.numel() else controls
        diagonal = torch.linalg.vector_norm(both.amax(0) - both.amin(0))
        if is_traced(both):
            return (tolerance * diagonal.detach()) ** 2
    return (tolerance * float(diagonal)) ** 2


def _squared_distances(
    targets: Tensor, controls: Tensor, out: Tensor | None = None, *, floor: float = 0.0,
    controls_t: Tensor | None = None,
) -> Tensor:
    """(n_t, n_c) squared distances from direct coordinate differences, plus ``floor``.

    Without autograd the passes run in place (into ``out`` when given); a
    ``floor`` (the dtype's smallest normal) then costs no extra pass. With autograd,
    or when traced, the result is computed out of place and ``floor`` is not added.
    ``controls_t`` is ``controls.T.contiguous()`` when the caller has it: contiguous
    coordinate rows make the broadcast subtractions about 1.6x faster.
    """
    if _functional(targets, controls):
        return (targets[:, None, :] - controls[None, :, :]).square().sum(-1)
    shape = (targets.shape[0], controls.shape[0])
    dist2 = out if out is not None else targets.new_empty(shape)
    dist2.fill_(floor)
    diff = targets.new_empty(shape)
    columns = controls.T.contiguous() if controls_t is None else controls_t
    for axis in range(targets.shape[1]):
        torch.sub(targets[:, axis : axis + 1], columns[axis], out=diff)
        dist2.addcmul_(diff, diff)
    return dist2


def _ratio_powers(nearest2: Tensor, dist2: Tensor, power: float) -> Tensor:
    """Unnormalised weights ``(m_i / d²_ik)^(p/2)``, every entry in [0, 1].

    Both ``m`` and ``d²`` are kept at or above the dtype's smallest normal
    number (``dist2`` must come from :func:`_squared_distances` with that
    ``floor`` when autograd is off), so a control that coincides exactly with
    its target gets ratio 1 and all others underflow to 0 without a branch.
    ``nearest2`` carries no gradient: the normalised weights do not depend on
    the common scale ``m_i``. Without autograd ``dist2`` is overwritten.
    """
    tiny = torch.finfo(dist2.dtype).tiny
    nearest2 = nearest2.detach().clamp_min(tiny)
    if _functional(dist2):
        ratio = nearest2 / dist2.clamp_min(tiny)
        return ratio.square() if power == 4.0 else ratio.pow(power / 2)
    ratio = dist2  # already floored at ``tiny`` by _squared_distances
    torch.div(nearest2, ratio, out=ratio)
    return ratio.square_() if power == 4.0 else ratio.pow_(power / 2)


def _rows_per_block(columns: int, itemsize: int, block_bytes: int, copies: int = 2) -> int:
    return max(1, int(block_bytes) // max(1, columns * itemsize * copies))


def _weights_block(
    targets: Tensor, controls: Tensor, power: float, radius2: float | Tensor,
    out: Tensor | None = None, controls_t: Tensor | None = None,
) -> Tensor:
    """Rows of W for a block of targets (all controls); in place into ``out`` if given.

    Traced calls (``torch.compile``, functorch transforms of the positions) replace
    the coincident rows with ``torch.where`` instead of a data-dependent branch.
    """
    functional = _functional(targets, controls)
    dist2 = _squared_distances(targets, controls, out, floor=torch.finfo(controls.dtype).tiny,
                               controls_t=controls_t)
    nearest2 = dist2.detach().amin(1, keepdim=True)
    coincident = nearest2 <= radius2  # (n, 1)
    if functional and (is_traced(coincident) or isinstance(radius2, Tensor)):
        nearest = dist2.detach().argmin(1, keepdim=True)
        weights = _ratio_powers(nearest2, dist2, power)
        weights = weights / weights.sum(1, keepdim=True)
        one_hot = torch.zeros_like(weights).scatter(1, nearest, 1.0)
        return torch.where(coincident, one_hot, weights)
    coincident = coincident.flatten()
    rows = torch.nonzero(coincident).flatten() if bool(coincident.any()) else None
    # the nearest control of a coincident row, found before dist2 is overwritten
    nearest = dist2.detach()[rows].argmin(1, keepdim=True) if rows is not None else None
    weights = _ratio_powers(nearest2, dist2, power)
    if functional:
        weights = weights / weights.sum(1, keepdim=True)
    else:
        weights.div_(weights.sum(1, keepdim=True))
    if rows is not None:
        one_hot = torch.zeros(rows.numel(), controls.shape[0], dtype=weights.dtype,
                              device=weights.device)
        one_hot.scatter_(1, nearest, 1.0)
        if functional:
            weights = weights.index_put((rows,), one_hot)
        else:
            weights[rows] = one_hot
    return weights


def _assemble_weights(
    targets: Tensor, controls: Tensor, power: float, radius2: float, block_bytes: int
) -> Tensor:
    """Dense W (N_t, N_c), row-major, filled block by block in place (no autograd)."""
    weights = torch.empty(targets.shape[0], controls.shape[0], dtype=controls.dtype,
                          device=controls.device)
    rows = _rows_per_block(controls.shape[0], controls.element_size(), block_bytes)
    with torch.no_grad():
        controls_t = controls.T.contiguous()
        for start in range(0, targets.shape[0], rows):
            _weights_block(targets[start : start + rows], controls, power, radius2,
                           out=weights[start : start + rows], controls_t=controls_t)
    return weights


# --------------------------------------------------------------------------- #
# functional API
# --------------------------------------------------------------------------- #
def idw_weights(
    targets: Tensor,
    controls: Tensor,
    *,
    power: float = 4.0,
    coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
    block_bytes: int = DEFAULT_BLOCK_BYTES,
) -> Tensor:
    """Dense IDW weight matrix, SPEC.md eq. (2).

    Parameters
    ----------
    targets : Tensor, shape (N_t, D)
        Points to interpolate to (the interior nodes).
    controls : Tensor, shape (N_c, D)
        Control points with known displacements.
    power : float
        The exponent p > 0 (the paper's p = 4).
    coincidence_tolerance : float
        A target within this fraction of the cloud's bounding-box diagonal of
        a control takes that control's row exactly (1 there, 0 elsewhere).
    block_bytes : int
        Size of the pairwise temporaries of one block of rows.

    Returns
    -------
    Tensor, shape (N_t, N_c)
        Rows sum to 1. Differentiable with respect to ``targets`` and
        ``controls`` when they require grad.

    Raises
    ------
    ValueError
        For wrong shapes, empty controls, NaN/inf, power <= 0, mismatched
        dtype or device.
    """
    targets, controls, power, radius2 = _prepare(targets, controls, power, coincidence_tolerance)
    if not _functional(targets, controls):
        return _assemble_weights(targets, controls, power, radius2, block_bytes)
    rows = _rows_per_block(controls.shape[0], controls.element_size(), block_bytes, copies=4)
    return torch.cat([_weights_block(targets[s : s + rows], controls, power, radius2)
                      for s in range(0, targets.shape[0], rows)])


def _prepare(targets, controls, power, coincidence_tolerance):
    controls = as_points(controls, "controls", dim=_dim_of(controls))
    targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True)
    check_same_device_dtype(controls, "controls", targets, "targets")
    power = _check_power(power)
    radius2 = _coincidence_radius2(targets, controls, float(coincidence_tolerance))
    return targets, controls, power, radius2


def _dim_of(points) -> int:
    shape = getattr(points, "shape", None)
    if shape is not None and len(shape) == 2 and shape[1] >= 1:
        return int(shape[1])
    return 3


def _nearest_squared_distance(targets: Tensor, controls: Tensor, tiles: tuple[int, int]) -> Tensor:
    """Squared distance from each target to its nearest control, shape (N_t, 1).

    On the CPU a KD-tree finds the nearest control and the distance is recomputed
    with the same arithmetic as the tiles; elsewhere a tiled min pass is used.
    Inside ``torch.func`` transforms the KD-tree runs on the plain tensors under the
    wrappers (positions batched by ``vmap`` take the tiled pass, which does not
    support them: matrix-free mode does not ``vmap`` over positions).
    """
    with torch.no_grad():
        t, c = targets.detach(), controls.detach()
        plain_t, batched_t = plain_tensor(targets)
        plain_c, batched_c = plain_tensor(controls)
        if t.device.type == "cpu" and not (batched_t or batched_c):
            from scipy.spatial import cKDTree

            with _functorch_disabled():
                _, nearest = cKDTree(plain_c.detach().numpy()).query(
                    plain_t.detach().numpy(), k=1)
                nearest = torch.from_numpy(nearest).long()
            return (t - c[nearest]).square().sum(1, keepdim=True)
        rows, cols = tiles
        best = torch.full((t.shape[0], 1), math.inf, dtype=t.dtype, device=t.device)
        for r in range(0, t.shape[0], rows):
            for k in range(0, c.shape[0], cols):
                block = _squared_distances(t[r : r + rows], c[k : k + cols]).amin(1, keepdim=True)
                torch.minimum(best[r : r + rows], block, out=best[r : r + rows])
        return best


def _functorch_disabled():
    """A context in which tensors are plain (NumPy conversions allowed) inside
    ``torch.func`` transforms."""
    disable = getattr(torch._C, "_DisableFuncTorch", None)
    return disable() if disable is not None else contextlib.nullcontext()


def _tile_shape(n_targets: int, n_controls: int, itemsize: int, block_bytes: int) -> tuple[int, int]:
    """(rows, columns) of a tile whose two pairwise temporaries fit ``block_bytes``."""
    elements = max(1, int(block_bytes) // (2 * itemsize))
    columns = min(n_controls, max(256, elements // 256))
    rows = max(1, elements // columns)
    return rows, columns


def _matrix_free_rows(
    targets: Tensor, controls: Tensor, augmented: Tensor, nearest2: Tensor,
    power: float, radius2: float, columns: int,
) -> Tensor:
    """IDW at a block of targets, tiling over controls.

    ``augmented`` is ``[values, 1]`` of shape (N_c, K + 1): the last column
    accumulates the weights' sum, by which the first K are divided at the end.
    """
    accumulated = targets.new_zeros(targets.shape[0], augmented.shape[1])
    floor = torch.finfo(controls.dtype).tiny
    for k in range(0, controls.shape[0], columns):
        dist2 = _squared_distances(targets, controls[k : k + columns], floor=floor)
        ratio = _ratio_powers(nearest2, dist2, power)
        accumulated = accumulated + ratio @ augmented[k : k + columns]
    result = accumulated[:, :-1] / accumulated[:, -1:]
    coincident = (nearest2 <= radius2).flatten()
    if bool(coincident.any()):
        rows = torch.nonzero(coincident).flatten()
        nearest = _squared_distances(targets[rows].detach(), controls.detach()).argmin(1)
        result = result.index_put((rows,), augmented[nearest, :-1])
    return result


def idw_apply(
    targets: Tensor,
    controls: Tensor,
    displacements: Tensor,
    *,
    power: float = 4.0,
    coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
    block_bytes: int = DEFAULT_BLOCK_BYTES,
) -> Tensor:
    """Matrix-free IDW: ``W @ displacements`` without ever storing ``W``.

    Parameters
    ----------
    targets : Tensor, shape (N_t, D)
    controls : Tensor, shape (N_c, D)
    displacements : Tensor, shape (N_c, 3) or (B, N_c, 3)
    power, coincidence_tolerance
        As in :func:`idw_weights`.
    block_bytes : int
        Byte budget of one tile of pairwise temporaries; peak memory is about
        this plus O((N_t + N_c) · (3B + 1)).

    Returns
    -------
    Tensor, shape (N_t, 3) or (B, N_t, 3)
        Same values as ``idw_weights(targets, controls) @ displacements``.

    Notes
    -----
    Tiles both rows and columns, accumulates unnormalised weights against
    ``[d, 1]`` and divides at the end. With autograd on, each block of rows is
    recomputed in the backward pass (activation checkpointing), so gradients to
    displacements and positions never store W either. Inside ``torch.func``
    transforms (``grad``, ``jacrev``: no saved-tensor hooks there) blocks are not
    checkpointed, so the graph holds the weights of every tile. The KD-tree and the
    coincident-row branch read values in Python: this function is not traceable by
    ``torch.compile`` without graph breaks (use dense mode there).
    """
    targets, controls, power, radius2 = _prepare(targets, controls, power, coincidence_tolerance)
    batched = check_vectors(displacements, "displacements", controls.shape[0],
                            what="control points")
    check_same_device_dtype(controls, "controls", displacements, "displacements")
    batch = displacements.shape[0] if batched else 1
    values = (displacements.permute(1, 0, 2) if batched else displacements).reshape(
        controls.shape[0], 3 * batch)
    rows, columns = _tile_shape(targets.shape[0], controls.shape[0], controls.element_size(),
                                block_bytes)
    nearest2 = _nearest_squared_distance(targets, controls, (rows, columns))
    inputs = (targets, controls, displacements)
    needs_graph = torch.is_grad_enabled() and any(x.requires_grad for x in inputs)
    needs_graph = needs_graph and not any(is_traced(x) for x in inputs)
    augmented = torch.cat([values, values.new_ones(values.shape[0], 1)], 1)
    blocks = []
    for start in range(0, targets.shape[0], rows):
        args = (targets[start : start + rows], controls, augmented, nearest2[start : start + rows],
                power, radius2, columns)
        if needs_graph:
            blocks.append(checkpoint(_matrix_free_rows, *args, use_reentrant=False))
        else:
            blocks.append(_matrix_free_rows(*args))
    result = torch.cat(blocks) if blocks else values.new_zeros(0, 3 * batch)
    result = result.reshape(targets.shape[0], batch, 3)
    return result.permute(1, 0, 2) if batched else result[:, 0]


def _dense_apply(weights: Tensor, displacements: Tensor) -> Tensor:
    """``W @ d`` for d of shape (N_c, 3) or (B, N_c, 3), as one contraction.

    Under ``vmap`` a single (N_c, 3) displacement is a batch in disguise: written as
    ``(dᵀ Wᵀ)ᵀ`` with a contiguous ``dᵀ`` the batch folds into the rows of one GEMM,
    where ``W @ d`` becomes a batched product that reads W once per batch entry
    (7x slower for 2,000 values at case-C size).
    """
    if displacements.ndim == 2:
        if not torch.compiler.is_compiling() and plain_tensor(displacements)[1]:
            return (displacements.mT.contiguous() @ weights.mT).mT
        return weights @ displacements
    batch, n_controls, _ = displacements.shape
    stacked = displacements.permute(1, 0, 2).reshape(n_controls, batch * 3)
    return (weights @ stacked).reshape(-1, batch, 3).permute(1, 0, 2)


# --------------------------------------------------------------------------- #
# module
# --------------------------------------------------------------------------- #
class IDW(nn.Module):
    """IDW interpolation from control points to target points (SPEC.md §1).

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
        recomputes weights in tiles on every call and never stores W; ``auto``
        picks dense when W takes at most ``dense_bytes``.
    block_bytes : int
        Byte budget of one block of pairwise temporaries (assembly and
        matrix-free tiles).
    dense_bytes : int
        Threshold for ``mode="auto"``.
    coincidence_tolerance : float
        Relative distance under which a target takes a control's value exactly.

    Attributes
    ----------
    controls, targets : buffers
        The reference geometry.
    weights : buffer, shape (N_t, N_c), dense mode only
        W (rows sum to 1).
    assembly_time : float
        Seconds spent assembling W (0 in matrix-free mode).

    Notes
    -----
    Gradients always flow to the displacements. To differentiate with respect
    to geometry, either pass ``controls``/``targets`` that require grad to the
    constructor (the module then rebuilds W differentiably from them on every
    call made with grad enabled) or pass new positions to :meth:`forward`.
    ``.to(device)`` of a module built from tensors that require grad makes
    copies: the link to the caller's tensors is then lost.

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
        block_bytes: int = DEFAULT_BLOCK_BYTES,
        dense_bytes: int = DEFAULT_DENSE_BYTES,
        coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
    ) -> None:
        super().__init__()
        controls = as_points(controls, "controls")
        targets = as_points(targets, "targets", allow_empty=True)
        check_same_device_dtype(controls, "controls", targets, "targets")
        if mode not in ("auto", "dense", "matrix_free"):
            raise ValueError(f"mode must be 'auto', 'dense' or 'matrix_free', got {mode!r}")
        self.power = _check_power(power)
        self.block_bytes = int(check_positive(block_bytes, "block_bytes"))
        self.dense_bytes = int(check_positive(dense_bytes, "dense_bytes"))
        self.coincidence_tolerance = float(coincidence_tolerance)
        _coincidence_radius2(targets, controls, self.coincidence_tolerance)  # validates
        if mode == "auto":
            size = targets.shape[0] * controls.shape[0] * controls.element_size()
            mode = "dense" if size <= self.dense_bytes else "matrix_free"
        self.mode: str = mode
        self.register_buffer("controls", controls)
        self.register_buffer("targets", targets)
        self.assembly_time = 0.0
        if mode == "dense":
            start = time.perf_counter()
            with torch.no_grad():
                weights = self._assemble(targets.detach(), controls.detach())
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
        radius2 = _coincidence_radius2(targets, controls, self.coincidence_tolerance)
        return _assemble_weights(targets, controls, self.power, radius2, self.block_bytes)

    def weights_matrix(self) -> Tensor:
        """W of shape (N_t, N_c): the stored buffer, or assembled now (matrix-free)."""
        if self.weights is not None:
            return self.weights
        with torch.no_grad():
            return self._assemble(self.targets.detach(), self.controls.detach())

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        resize_buffers_for_load(self, state_dict, prefix, ("controls", "targets", "weights"))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _geometry_requires_grad(self) -> bool:
        return self.controls.requires_grad or self.targets.requires_grad

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
        check_same_device_dtype(self.controls, "the module's controls", displacements,
                                "displacements")
        new_geometry = controls is not None or targets is not None
        if controls is not None:
            controls = self._check_moved(controls, self.controls, "controls")
        if targets is not None:
            targets = self._check_moved(targets, self.targets, "targets")
        controls = self.controls if controls is None else controls
        targets = self.targets if targets is None else targets
        rebuild = new_geometry or (torch.is_grad_enabled() and self._geometry_requires_grad())
        if self.mode == "matrix_free":
            return idw_apply(targets, controls, displacements, power=self.power,
                             coincidence_tolerance=self.coincidence_tolerance,
                             block_bytes=self.block_bytes)
        if rebuild:
            weights = idw_weights(targets, controls, power=self.power,
                                  coincidence_tolerance=self.coincidence_tolerance,
                                  block_bytes=self.block_bytes)
            return weights @ displacements
        return _dense_apply(self.weights, displacements)

    @staticmethod
    def _check_moved(moved: Tensor, reference: Tensor, name: str) -> Tensor:
        if not isinstance(moved, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(moved).__name__}")
        if moved.shape != reference.shape:
            raise ValueError(f"{name} must have shape {tuple(reference.shape)}, "
                             f"got {tuple(moved.shape)}")
        check_same_device_dtype(reference, f"the module's {name}", moved, name)
        return as_points(moved, name, allow_empty=True)

    def extra_repr(self) -> str:
        return (f"num_controls={self.num_controls}, num_targets={self.num_targets}, "
                f"power={self.power:g}, mode={self.mode!r}")
