"""Loading state into modules whose buffer shapes depend on fitted data."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import torch
from torch import Tensor, nn

__all__ = ["resize_buffers_for_load"]


def resize_buffers_for_load(
    module: nn.Module, state_dict: Mapping[str, Tensor], prefix: str, names: Iterable[str]
) -> None:
    """Give the named buffers of ``module`` the shapes stored in ``state_dict``.

    Call from ``_load_from_state_dict`` before delegating to ``nn.Module``: a
    selection, a fitted basis or a W whose size depends on data then loads into
    a module built with other data instead of failing on a size mismatch.
    """
    for name in names:
        key = prefix + name
        current = module._buffers.get(name)
        incoming = state_dict.get(key)
        if incoming is None or current is None or current.shape == incoming.shape:
            continue
        module._buffers[name] = torch.empty(
            incoming.shape, dtype=current.dtype, device=current.device
        )
