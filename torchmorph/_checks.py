"""Argument validation shared by every torchmorph module.

Each check raises ``ValueError`` (or ``TypeError`` for a wrong kind of object)
with a message that starts with the argument's name, so a user reading a
traceback knows which input was wrong and how.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any, TypeVar

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "as_index",
    "as_points",
    "check_choice",
    "check_finite",
    "check_float_dtype",
    "check_positive",
    "check_same_device_dtype",
    "check_vectors",
    "dim_of",
    "is_traced",
    "plain_tensor",
]

Choice = TypeVar("Choice", bound=str)
"""A choice of :func:`check_choice`: a string, or one of a ``Literal`` of strings."""


def dim_of(points: Any) -> int:
    """The dimension D that a point array of shape (N, D) claims (3 when it has no such
    shape), so that :func:`as_points` reports a bad shape against it."""
    shape = getattr(points, "shape", None)
    if shape is not None and len(shape) == 2 and shape[1] >= 1:
        return int(shape[1])
    return 3


def as_points(
    value: Tensor | np.ndarray | Sequence,
    name: str,
    *,
    dim: int = 3,
    allow_empty: bool = False,
    dtype: torch.dtype | None = None,
    finite: bool = True,
) -> Tensor:
    """Return ``value`` as a floating tensor of shape (N, dim), validated.

    ``finite=False`` leaves the NaN/inf check to the caller (one that reads the
    points' bounds anyway and checks them in the same read).

    Tensors keep their dtype, device and autograd history; NumPy arrays and
    sequences become float64 tensors (float32 arrays stay float32).

    Raises
    ------
    ValueError
        If the shape is not (N, dim), N == 0 (unless ``allow_empty``), the
        dtype is not floating point or is half precision (float16, bfloat16),
        or any entry is NaN or infinite.
    """
    if not isinstance(value, Tensor):
        array = np.asarray(value)
        if array.dtype.kind not in "fiu":
            raise ValueError(f"{name} must hold numbers, got an array of dtype {array.dtype}")
        if array.dtype != np.float32:
            array = array.astype(np.float64)
        value = torch.from_numpy(np.ascontiguousarray(array))
    if dtype is not None:
        value = value.to(dtype)
    check_float_dtype(value, name)
    if value.ndim != 2 or value.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {tuple(value.shape)}")
    if value.shape[0] == 0 and not allow_empty:
        raise ValueError(f"{name} is empty: at least one point is needed")
    if finite:
        check_finite(value, name)
    return value


def as_index(
    value: Tensor | np.ndarray | Sequence, name: str, *, size: int | None = None
) -> Tensor:
    """Return ``value`` as a 1-D int64 tensor of indices, checked against ``size``.

    Boolean masks of length ``size`` are converted to the indices they select.
    """
    if not isinstance(value, Tensor):
        array = np.asarray(value)
        if array.size == 0:
            array = array.astype(np.int64)
        value = torch.from_numpy(np.ascontiguousarray(array))
    if value.dtype == torch.bool:
        if value.ndim != 1 or (size is not None and value.numel() != size):
            raise ValueError(
                f"{name}: a boolean mask must have shape ({size},), got {tuple(value.shape)}"
            )
        value = torch.nonzero(value).flatten()
    if value.is_floating_point() or value.is_complex():
        raise ValueError(f"{name} must hold integer indices, got dtype {value.dtype}")
    value = value.reshape(-1).long() if value.ndim <= 1 else value
    if value.ndim != 1:
        raise ValueError(f"{name} must be a 1-D index array, got shape {tuple(value.shape)}")
    if size is not None and value.numel() > 0:
        low, high = int(value.min()), int(value.max())
        if low < 0 or high >= size:
            raise ValueError(f"{name} holds indices outside [0, {size}): min {low}, max {high}")
    return value


def plain_tensor(value: Tensor) -> tuple[Tensor, bool]:
    """The plain tensor under ``torch.func`` wrappers, and whether one of them is a
    ``vmap`` batch.

    A batched tensor's plain tensor holds the whole batch (an extra dimension);
    ``grad``/``jacrev``/``jvp`` wrappers hold the primal value. A plain ``value`` is
    returned as is, with False.
    """
    functorch = getattr(torch._C, "_functorch", None)
    batched = False
    if functorch is None:
        return value, batched
    while functorch.is_functorch_wrapped_tensor(value):
        batched = batched or bool(functorch.is_batchedtensor(value))
        value = functorch.get_unwrapped(value)
    return value, batched


def is_traced(value: Tensor | None = None) -> bool:
    """Whether the caller runs under ``torch.compile`` tracing, or ``value`` is a
    functorch-wrapped tensor (inside ``vmap``, ``grad``, ``jacrev``, ``jacfwd``).

    Code on a hot path uses this to avoid data-dependent Python control flow
    (``bool(tensor)``), which vmap cannot batch and which breaks a compiled graph.
    """
    if torch.compiler.is_compiling():
        return True
    if value is None:
        return False
    functorch = getattr(torch._C, "_functorch", None)
    return functorch is not None and functorch.is_functorch_wrapped_tensor(value)


def check_finite(value: Tensor, name: str) -> float:
    """Raise ``ValueError`` if ``value`` holds NaN or infinite entries; else return its
    largest magnitude (0.0 for an empty tensor or where the check is skipped).

    Inside ``torch.func`` transforms the check runs on the underlying plain tensor
    (for ``vmap`` the whole batch), so NaN inputs are still reported. Under
    ``torch.compile`` tracing the check is skipped: it would need the tensor's values
    in Python and break the graph; NaN inputs then give NaN outputs.
    """
    if torch.compiler.is_compiling():
        return 0.0
    if value.is_floating_point() and value.numel() > 0:
        plain = plain_tensor(value)[0].detach()
        # one reduction and one read on the hot path: the largest magnitude is finite
        # exactly when every entry is (NaN propagates through the maximum)
        largest = float(torch.linalg.vector_norm(plain, float("inf")))
        if not math.isfinite(largest):
            bad = int((~torch.isfinite(plain)).sum())
            raise ValueError(f"{name} holds {bad} NaN or infinite value(s)")
        return largest
    return 0.0


HALF_DTYPES = (torch.float16, torch.bfloat16)


def check_float_dtype(value: Tensor, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is float32 or float64 (or another
    floating dtype of at least single precision).

    Half precision is refused rather than silently promoted: IDW squares
    distances, and float16 overflows above 65,504 and flushes below 6e-5 (its
    weights come out NaN or uniform); bfloat16 keeps 8 bits of mantissa, too few
    for exact reproduction at the controls. Convert with ``.float()``.
    """
    if not value.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {value.dtype}")
    if value.dtype in HALF_DTYPES:
        raise ValueError(
            f"{name} has dtype {value.dtype}: half precision is not supported (squared "
            "distances leave its range); convert to float32 or float64 with .float() or .double()"
        )


def check_choice(value: object, name: str, choices: Sequence[Choice]) -> Choice:
    """Return ``value`` if it is one of ``choices`` (as that entry of ``choices``, so typed
    as precisely as they are), else raise ``ValueError`` in the one format of every
    enumerated option: ``name must be one of 'a', 'b'; got 'c'``."""
    if isinstance(value, str):
        for choice in choices:
            if value == choice:
                return choice
    listed = ", ".join(repr(choice) for choice in choices)
    raise ValueError(f"{name} must be one of {listed}; got {value!r}")


def check_positive(value: float, name: str) -> float:
    """Return ``value`` as float if it is a real number, finite and > 0, else raise
    ``ValueError`` (a string such as ``"4"`` or a bool is refused, not converted)."""
    is_scalar = isinstance(value, Tensor) and value.numel() == 1 and not value.is_complex()
    if isinstance(value, (bool, np.bool_)) or not (isinstance(value, numbers.Real) or is_scalar):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    number = float(value)
    if not math.isfinite(number) or number <= 0.0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return number


def check_same_device_dtype(
    reference: Tensor, reference_name: str, other: Tensor, name: str
) -> None:
    """Raise ``ValueError`` if ``other`` is not on ``reference``'s device and dtype."""
    if other.device != reference.device:
        raise ValueError(
            f"{name} is on device {other.device} but {reference_name} is on {reference.device}"
        )
    if other.dtype != reference.dtype:
        raise ValueError(
            f"{name} has dtype {other.dtype} but {reference_name} has {reference.dtype}"
        )


def check_vectors(
    value: Tensor, name: str, count: int, *, dim: int = 3, what: str, finite: bool = True
) -> bool:
    """Check a field of ``dim``-vectors, shape (count, dim) or (B, count, dim).

    Returns True when the input is batched. ``what`` names the points the rows
    belong to, for the message (e.g. "control points"). ``finite=False`` leaves the
    NaN/inf check to the caller (one that wants :func:`check_finite`'s magnitude).
    """
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.ndim not in (2, 3) or value.shape[-2:] != (count, dim):
        raise ValueError(
            f"{name} must have shape ({count}, {dim}) or (B, {count}, {dim}) for {count} "
            f"{what}, got {tuple(value.shape)}"
        )
    check_float_dtype(value, name)
    if finite:
        check_finite(value, name)
    return value.ndim == 3
