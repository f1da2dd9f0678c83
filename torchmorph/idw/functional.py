"""The functional core of IDW (the paper's eqs. 1–2): :func:`idw_weights` assembles the
dense W, :func:`idw_apply` applies it matrix-free. Both take keyword points, validate and
normalise them (:mod:`torchmorph.idw._geometry`) and hand the kernel work to a backend
(:mod:`torchmorph.idw._dispatch`).

Numerics
--------
Both point clouds are scaled by the same power of two so that every coordinate lies in
[-1, 1] (exact, and W is invariant under it; the points are not translated), so
coordinates from 1e-30 to 1e30 give the same weights. Row ``i`` of ``W`` is then
``(m_i / d²_ik)^(p/2)`` normalised by its sum, with ``d²_ik`` the squared distance from
target ``i`` to control ``k`` (direct coordinate differences, never the
``|x|² + |c|² − 2x·c`` expansion, which cancels catastrophically) and ``m_i`` the row's
smallest squared distance. This equals eq. (2) exactly, and every term lies in [0, 1], so
nothing overflows or underflows harmfully in float32 or float64.

A target closer than ``coincidence_tolerance`` times the bounding-box diagonal to a
control takes that control's displacement exactly (exact interpolation). If it lies that
close to several controls (duplicated control points), it takes the mean of their
displacements, whatever their order; :class:`~torchmorph.idw.IDW` warns about such
duplicates when it is built.

Implementations
---------------
``implementation="fused"`` runs kernels that compute the weights in registers and never
store a pairwise tile: Triton on CUDA devices (:mod:`torchmorph.idw.backends.triton`) and
numba on the CPU (:mod:`torchmorph.idw.backends.numba`). On the CPU a batch of more than
24 value columns (nine displacements or more) is applied by blocks of W rows from the
fused assembly kernel, each multiplied by torch's GEMM while in cache (W is never stored
whole). ``"torch"`` (:mod:`torchmorph.idw.backends.torch`) runs the same arithmetic in
blocks of torch operations, which works everywhere and under ``torch.compile`` and
``torch.func``. ``"auto"`` (the default) takes the fused kernels where they apply and
torch elsewhere.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmorph._checks import check_finite, check_same_device_dtype, check_vectors, is_traced
from torchmorph.idw._dispatch import Implementation, apply_with, assemble_weights, backend_for
from torchmorph.idw._geometry import points_arguments, prepare

__all__ = ["DEFAULT_COINCIDENCE_TOLERANCE", "Implementation", "idw_apply", "idw_weights"]

DEFAULT_COINCIDENCE_TOLERANCE = 1e-10
"""Targets closer to a control than this fraction of the cloud's bounding-box
diagonal take that control's displacement exactly."""


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
    controls, targets = points_arguments("idw_weights", points, controls, targets)
    targets, controls, power, radius2 = prepare(targets, controls, power, coincidence_tolerance)
    graph = (torch.is_grad_enabled() and (targets.requires_grad or controls.requires_grad)) or (
        is_traced(targets) or is_traced(controls)
    )
    if not graph:
        return assemble_weights(targets, controls, power, radius2, block_bytes, implementation)
    if implementation == "fused":
        raise ValueError(
            "implementation='fused' cannot run here: a W that carries gradients to "
            "the points (or is traced) is built by the torch implementation"
        )
    backend = backend_for("torch", targets, controls, block_bytes=block_bytes)
    return backend.weights(targets, controls, power, radius2)


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
    displacements : Tensor, shape (N_c, D) or (B, N_c, D), keyword
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
    Tensor, shape (N_t, D) or (B, N_t, D)
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
        controls, targets, displacements = points_arguments(
            "idw_apply", points, controls, targets, count=3
        )
    else:
        controls, targets = points_arguments("idw_apply", points, controls, targets)
        if displacements is None:
            raise TypeError("idw_apply() needs displacements=")
    targets, controls, power, radius2 = prepare(targets, controls, power, coincidence_tolerance)
    dim = controls.shape[1]
    batched = check_vectors(
        displacements,
        "displacements",
        controls.shape[0],
        dim=dim,
        what="control points",
        finite=False,
    )
    magnitude = check_finite(displacements, "displacements")
    check_same_device_dtype(controls, "controls", displacements, "displacements")
    batch = displacements.shape[0] if batched else 1
    values = (displacements.permute(1, 0, 2) if batched else displacements).reshape(
        controls.shape[0], dim * batch
    )
    positions_grad = torch.is_grad_enabled() and (targets.requires_grad or controls.requires_grad)
    backend = backend_for(
        implementation,
        targets,
        controls,
        displacements,
        positions_grad=positions_grad,
        shape=(dim, values.shape[1]),
        block_bytes=block_bytes,
    )
    layout = backend.layout
    result = apply_with(
        backend, layout(targets), layout(controls), values, power, radius2, magnitude=magnitude
    )
    result = result.reshape(targets.shape[0], batch, dim)
    return result.permute(1, 0, 2) if batched else result[:, 0]
