"""The torch backend of IDW (the paper's eqs. 1–2): blocks of tensor operations.

It runs everywhere, differentiates with respect to everything, and traces under
``torch.compile`` and ``torch.func``: the baseline that the fused backends (Triton, numba)
are compared with, and the one :mod:`torchmorph.idw._dispatch` takes where they do not
apply. Points arrive already normalised (:mod:`torchmorph.idw._geometry`). Each function
is the plain twin of a fused kernel; the tests compare the two.
"""

from __future__ import annotations

import contextlib
import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from torchmorph._checks import check_positive, is_traced, plain_tensor

__all__ = [
    "DEFAULT_BLOCK_BYTES",
    "DEFAULT_CUDA_BLOCK_BYTES",
    "TorchBackend",
    "nearest_by_kd_tree",
    "rows_per_block",
]

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


def rows_per_block(columns: int, itemsize: int, block_bytes: int, copies: int = 2) -> int:
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
    exact_rows = _coincident_weights(dist2[rows], radius2) if rows is not None else None
    weights = _ratio_powers(nearest2, dist2, power)
    weights.div_(weights.sum(1, keepdim=True))
    if rows is not None and exact_rows is not None:
        weights[rows] = exact_rows
    return weights


def nearest_by_kd_tree(targets: Tensor, controls: Tensor) -> Tensor:
    """Squared distance from each target to its nearest control, shape (N_t,), CPU points:
    scipy's KD-tree (queried on torch's threads) finds the control and the distance is
    recomputed with the same arithmetic as the tiles. Inside ``torch.func`` transforms it
    runs on the plain tensors under the wrappers."""
    from scipy.spatial import cKDTree

    with torch.no_grad(), _functorch_disabled():
        plain_t, plain_c = plain_tensor(targets)[0].detach(), plain_tensor(controls)[0].detach()
        tree = cKDTree(plain_c.numpy())
        _, nearest = tree.query(plain_t.numpy(), k=1, workers=torch.get_num_threads())
        nearest = torch.from_numpy(nearest).long()
    with torch.no_grad():
        return (targets.detach() - controls.detach()[nearest]).square().sum(1)


def _nearest_squared_distance(targets: Tensor, controls: Tensor, tiles: tuple[int, int]) -> Tensor:
    """Squared distance from each target to its nearest control, shape (N_t, 1).

    On the CPU a KD-tree (:func:`nearest_by_kd_tree`); elsewhere a tiled min pass.
    Positions batched by ``vmap`` take the tiled pass, which does not support them:
    matrix-free mode does not ``vmap`` over positions.
    """
    with torch.no_grad():
        t, c = targets.detach(), controls.detach()
        batched = plain_tensor(targets)[1] or plain_tensor(controls)[1]
        if t.device.type == "cpu" and not batched:
            return nearest_by_kd_tree(targets, controls)[:, None]
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


def _weights(
    targets: Tensor, controls: Tensor, power: float, radius2: float, block_bytes: int | None
) -> Tensor:
    """Dense W out of place, differentiable to the points (blocks of rows, concatenated)."""
    if targets.shape[0] == 0:  # an empty W that still carries the inputs' graph
        return (targets.sum() + controls.sum()) * 0 + controls.new_zeros(0, controls.shape[0])
    rows = rows_per_block(
        controls.shape[0], controls.element_size(), _block_bytes(block_bytes, controls.device), 4
    )
    return torch.cat(
        [
            _weights_block(targets[s : s + rows], controls, power, radius2)
            for s in range(0, targets.shape[0], rows)
        ]
    )


class TorchBackend:
    """Blocks of torch operations on any device; geometry as given, (N, D) rows.

    Its results carry autograd graphs (``differentiable``), so the dispatch calls it
    directly; ``block_bytes`` bounds its pairwise temporaries (default: 4 MiB on the
    CPU, 256 MiB on a CUDA device).
    """

    name = "torch"
    differentiable = True

    def __init__(self, block_bytes: int | None = None) -> None:
        self.block_bytes = block_bytes

    @staticmethod
    def layout(points: Tensor) -> Tensor:
        return points

    def _tiles(self, targets: Tensor, controls: Tensor) -> tuple[int, int]:
        block = _block_bytes(self.block_bytes, controls.device)
        return _tile_shape(targets.shape[0], controls.shape[0], controls.element_size(), block)

    def nearest(self, targets: Tensor, controls: Tensor) -> Tensor:
        nearest2 = _nearest_squared_distance(targets, controls, self._tiles(targets, controls))
        return nearest2.flatten().clamp_min(torch.finfo(targets.dtype).tiny)

    @staticmethod
    def needs_nearest(columns: int) -> bool:
        return False  # found per call, with the same tiles

    def apply(self, targets, controls, values, power, radius2, nearest2=None):
        return _torch_apply(targets, controls, values, power, radius2, self.block_bytes), None

    def apply_transposed(self, targets, controls, grad, power, radius2, nearest2=None, sums=None):
        block = _block_bytes(self.block_bytes, controls.device)
        rows = rows_per_block(controls.shape[0], controls.element_size(), block)
        out = grad.new_zeros(controls.shape[0], grad.shape[1])
        for start in range(0, targets.shape[0], rows):
            weights = _weights_block(targets[start : start + rows], controls, power, radius2)
            out = out + weights.mT @ grad[start : start + rows]
        return out

    def weights(self, targets, controls, power, radius2, out=None):
        if _functional(targets, controls):
            return _weights(targets, controls, power, radius2, self.block_bytes)
        if out is None:
            out = controls.new_empty(targets.shape[0], controls.shape[0])
        block = _block_bytes(self.block_bytes, controls.device)
        rows = rows_per_block(controls.shape[0], controls.element_size(), block)
        controls_t = controls.T.contiguous()
        for start in range(0, targets.shape[0], rows):
            _weights_block(
                targets[start : start + rows],
                controls,
                power,
                radius2,
                out=out[start : start + rows],
                controls_t=controls_t,
            )
        return out

    @staticmethod
    def dense_columns() -> int:
        return 0

    @staticmethod
    def dense_apply(weights: Tensor, values: Tensor) -> Tensor:
        return weights @ values

    @staticmethod
    def position_gradients_for(dim: int, columns: int) -> bool:
        return True  # by autograd through :meth:`apply`

    def position_gradients(
        self,
        targets,
        controls,
        values,
        grad,
        out,
        nearest2,
        sums,
        power,
        radius2,
        need_targets,
        need_controls,
    ):
        with torch.enable_grad():
            targets = targets.detach().requires_grad_(need_targets)
            controls = controls.detach().requires_grad_(need_controls)
            result, _ = self.apply(targets, controls, values.detach(), power, radius2)
            wanted = [x for x, need in ((targets, need_targets), (controls, need_controls)) if need]
            found = iter(torch.autograd.grad(result, wanted, grad) if wanted else ())
        return (
            next(found) if need_targets else None,
            next(found) if need_controls else None,
        )
