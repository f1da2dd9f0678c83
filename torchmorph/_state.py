"""What every module of torchmorph does with its state: one error for use before
``fit`` (:class:`NotFittedError`), one rule for loading a saved state
(:func:`check_saved_hyperparameters`), buffers that take the saved shapes
(:func:`resize_buffers_for_load`), and lists of tensors packed into one buffer
(:func:`pack_tensors`, :func:`unpack_tensor`).

The load rule: a state holds the module's hyper-parameters beside its buffers. Those
that change the result (``power``, ``coincidence_tolerance``, ``energy_tolerance``,
``num_modes``, ``online`` …) must equal the loading module's, or loading raises
``ValueError`` naming the field; build the module with the saved values, then load.
Choices of storage and speed (IDW's ``mode``, block sizes, ``implementation``) may
differ. Data learned or derived from the geometry (W, a selection, a POD basis) is
taken from the state whatever its size.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import torch
from torch import Tensor, nn

__all__ = [
    "NotFittedError",
    "apply_keeping_dtypes",
    "check_saved_hyperparameters",
    "pack_tensors",
    "resize_buffers_for_load",
    "unpack_tensor",
]


class NotFittedError(RuntimeError):
    """A fitted quantity was asked of an estimator (:class:`~torchmorph.PODReducer`,
    :class:`~torchmorph.distributed.ShardedPOD`) before ``fit`` or before a fitted state
    was loaded."""


def check_saved_hyperparameters(
    module: str, saved: Mapping[str, Any], current: Mapping[str, Any]
) -> None:
    """Raise ``ValueError`` unless every hyper-parameter in ``current`` was saved with the
    same value (the load rule of the module docstring); ``module`` names the class."""
    if not isinstance(saved, Mapping):
        raise ValueError(
            f"{module} state: the extra state must be a dict, got {type(saved).__name__}"
        )
    for field, value in current.items():
        if field not in saved:
            raise ValueError(f"{module} state: the extra state lacks {field!r}")
        if saved[field] != value:
            raise ValueError(
                f"{field}: the state was saved with {field}={saved[field]!r} but this "
                f"{module} has {field}={value!r}; build the module with the saved value"
            )


def resize_buffers_for_load(
    module: nn.Module,
    state_dict: Mapping[str, Tensor],
    prefix: str,
    names: Iterable[str],
    *,
    take_dtype: bool = False,
) -> None:
    """Give the named buffers of ``module`` the shapes stored in ``state_dict`` (and, with
    ``take_dtype``, their floating dtype), on the module's device.

    Call from ``_load_from_state_dict`` before delegating to ``nn.Module``: a
    selection, a fitted basis or a W whose size depends on data then loads into
    a module built with other data instead of failing on a size mismatch.
    """
    for name in names:
        current = module._buffers.get(name)
        incoming = state_dict.get(prefix + name)
        if not isinstance(incoming, Tensor) or current is None:
            continue
        dtype = current.dtype
        if take_dtype and incoming.is_floating_point():
            dtype = incoming.dtype
        if current.shape != incoming.shape or current.dtype != dtype:
            module._buffers[name] = torch.empty(incoming.shape, dtype=dtype, device=current.device)


def apply_keeping_dtypes(module: nn.Module, fn, recurse: bool, names: Iterable[str]) -> None:
    """``nn.Module._apply`` (``.to``, ``.float()``, ``.cuda()`` …) for ``module``, with the
    named buffers moved to the new device but kept in their dtype (a fit computed in
    float64 stays float64 when the points go to float32)."""
    kept = {name: module._buffers[name] for name in names}
    nn.Module._apply(module, fn, recurse)
    for name, before in kept.items():
        after = module._buffers[name]
        if before is not None and after is not None and after.dtype != before.dtype:
            module._buffers[name] = before.to(device=after.device)


def pack_tensors(tensors: list[Tensor], like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Tensors of one or two dimensions packed for a module's state: (flat, shapes (P, 2)
    with a second size of -1 for a vector, offsets (P + 1,))."""
    shapes = torch.tensor(
        [[t.shape[0], t.shape[1] if t.ndim == 2 else -1] for t in tensors], dtype=torch.int64
    ).reshape(-1, 2)
    sizes = torch.tensor([t.numel() for t in tensors], dtype=torch.int64)
    offsets = torch.zeros(len(tensors) + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(sizes, 0)
    flat = torch.cat([t.reshape(-1) for t in tensors]) if tensors else like.new_zeros(0)
    return flat, shapes, offsets


def unpack_tensor(flat: Tensor, shapes: list[list[int]], offsets: list[int], index: int) -> Tensor:
    """Tensor ``index`` of :func:`pack_tensors`'s flat buffer."""
    rows, columns = shapes[index]
    part = flat[offsets[index] : offsets[index + 1]]
    return part.reshape(rows) if columns < 0 else part.reshape(rows, columns)
