"""The torch implementation of IDW (the paper's eqs. 1–2) in blocks of tensor operations.

It runs everywhere, differentiates with respect to everything, and traces under
``torch.compile`` and ``torch.func``; :mod:`torchmorph.idw` dispatches to it where the
fused kernels (:mod:`torchmorph._idw_fused`) do not apply. Points arrive already
scaled by :func:`torchmorph.idw._normalise`. Each function is the plain twin of a
fused kernel; the tests compare the two.
"""

from __future__ import annotations

import contextlib
import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from ._checks import check_positive, is_traced, plain_tensor

__all__ = ["DEFAULT_BLOCK_BYTES", "DEFAULT_CUDA_BLOCK_BYTES"]

DEFAULT_BLOCK_BYTES = 4 * 2**20
"""Working-set size of one block of pairwise temporaries of the torch implementation
on the CPU (bytes). Blocks of a few MB stay in cache; much larger ones were slower."""

DEFAULT_CUDA_BLOCK_BYTES = 256 * 2**20
"""The same on a CUDA device, where a block is one launch: large blocks keep the
device busy between launches (64 MiB to 1 GiB measured alike on an H100)."""


def _functional(*tensors: Tensor) -> bool:
    """Whether to compute out of place: autograd records through one of ``tensors``,
    or the call is traced (``torch.compile``, or functorch-wrapped tensors)."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return True
    return any(is_traced(t) for t in tensors)


def _squared_distances(
    targets: Tensor,
    controls: Tensor,
    out: Tensor | None = None,
    *,
    floor: float = 0.0,
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


def _block_bytes(block_bytes: int | None, device: torch.device) -> int:
    """The caller's block budget, or the device's default."""
    if block_bytes is not None:
        return int(check_positive(block_bytes, "block_bytes"))
    return DEFAULT_CUDA_BLOCK_BYTES if device.type == "cuda" else DEFAULT_BLOCK_BYTES


def _coincident_weights(dist2: Tensor, radius2: float) -> Tensor:
    """Rows of W for coincident targets: the mean over the controls within the radius."""
    indicator = (dist2 <= radius2).to(dist2.dtype)
    return indicator / indicator.sum(1, keepdim=True)


def _weights_block(
    targets: Tensor,
    controls: Tensor,
    power: float,
    radius2: float,
    out: Tensor | None = None,
    controls_t: Tensor | None = None,
) -> Tensor:
    """Rows of W for a block of (normalised) targets against all controls; in place
    into ``out`` when autograd is off.

    With autograd, or traced (``torch.compile``, ``torch.func``), coincident rows are
    selected with ``torch.where``; their ordinary-weight branch is computed from
    harmless values so that no NaN reaches the gradient.
    """
    tiny = torch.finfo(controls.dtype).tiny
    if _functional(targets, controls):
        dist2 = _squared_distances(targets, controls).clamp_min(tiny)
        nearest2 = dist2.detach().amin(1, keepdim=True)
        coincident = nearest2 <= radius2  # (n, 1)
        exact = _coincident_weights(dist2.detach(), radius2)
        safe = torch.where(coincident, torch.ones_like(dist2), dist2)
        ratio = _ratio_powers(
            torch.where(coincident, torch.ones_like(nearest2), nearest2), safe, power
        )
        return torch.where(coincident, exact, ratio / ratio.sum(1, keepdim=True))
    dist2 = _squared_distances(targets, controls, out, floor=tiny, controls_t=controls_t)
    nearest2 = dist2.amin(1, keepdim=True)
    coincident = (nearest2 <= radius2).flatten()
    rows = torch.nonzero(coincident).flatten() if bool(coincident.any()) else None
    exact = _coincident_weights(dist2[rows], radius2) if rows is not None else None
    weights = _ratio_powers(nearest2, dist2, power)
    weights.div_(weights.sum(1, keepdim=True))
    if rows is not None:
        weights[rows] = exact
    return weights


def _nearest_squared_distance(targets: Tensor, controls: Tensor, tiles: tuple[int, int]) -> Tensor:
    """Squared distance from each target to its nearest control, shape (N_t, 1).

    On the CPU a KD-tree (queried on torch's threads) finds the nearest control and the
    distance is recomputed with the same arithmetic as the tiles; elsewhere a tiled min
    pass is used.
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
                tree = cKDTree(plain_c.detach().numpy())
                workers = torch.get_num_threads()
                _, nearest = tree.query(plain_t.detach().numpy(), k=1, workers=workers)
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


def _tile_shape(
    n_targets: int, n_controls: int, itemsize: int, block_bytes: int
) -> tuple[int, int]:
    """(rows, columns) of a tile whose two pairwise temporaries fit ``block_bytes``."""
    elements = max(1, int(block_bytes) // (2 * itemsize))
    columns = min(n_controls, max(256, elements // 256))
    rows = max(1, elements // columns)
    return rows, columns


def _matrix_free_rows(
    targets: Tensor,
    controls: Tensor,
    augmented: Tensor,
    nearest2: Tensor,
    power: float,
    radius2: float,
    columns: int,
) -> Tensor:
    """IDW at a block of targets, tiling over controls (torch implementation).

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
    coincident = (nearest2.clamp_min(floor) <= radius2).flatten()
    if bool(coincident.any()):
        rows = torch.nonzero(coincident).flatten()
        dist2 = _squared_distances(targets[rows].detach(), controls.detach()).clamp_min(floor)
        exact = _coincident_weights(dist2, radius2) @ augmented[:, :-1]
        result = result.index_put((rows,), exact)
    return result


def _torch_apply(
    targets: Tensor,
    controls: Tensor,
    values: Tensor,
    power: float,
    radius2: float,
    block_bytes: int | None,
) -> Tensor:
    """The torch implementation of matrix-free ``W @ values`` (normalised points)."""
    rows, columns = _tile_shape(
        targets.shape[0],
        controls.shape[0],
        controls.element_size(),
        _block_bytes(block_bytes, controls.device),
    )
    nearest2 = _nearest_squared_distance(targets, controls, (rows, columns))
    inputs = (targets, controls, values)
    needs_graph = torch.is_grad_enabled() and any(x.requires_grad for x in inputs)
    needs_graph = needs_graph and not any(is_traced(x) for x in inputs)
    augmented = torch.cat([values, values.new_ones(values.shape[0], 1)], 1)
    blocks = []
    for start in range(0, targets.shape[0], rows):
        args = (
            targets[start : start + rows],
            controls,
            augmented,
            nearest2[start : start + rows],
            power,
            radius2,
            columns,
        )
        if needs_graph:
            blocks.append(checkpoint(_matrix_free_rows, *args, use_reentrant=False))
        else:
            blocks.append(_matrix_free_rows(*args))
    if not blocks:  # no targets: an empty result that still carries the inputs' graph
        return values[:0] + (targets.sum() + controls.sum()) * 0
    return torch.cat(blocks)
