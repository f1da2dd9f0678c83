"""Fused CPU kernels for Inverse Distance Weighting (numba), matrix-free and dense.

The weights are those of the paper's eqs. (1)–(2) (Ballarin, D'Amario, Perotto and
Rozza 2017, Section 2.1), written in the ratio form used throughout
:mod:`torchmorph.idw`: for target ``i`` and control ``k``, with ``d²_ik`` the squared
distance (direct coordinate differences, never the ``|x|² + |c|² − 2x·c``
expansion) and ``m_i = max(min_k d²_ik, tiny)`` (``tiny`` the dtype's smallest
normal number),

- an ordinary row (``m_i > radius2``) has ``r_ik = (m_i / max(d²_ik, tiny))^(p/2)``,
  every term in [0, 1], and ``w_ik = r_ik / s_i`` with ``s_i = Σ_k r_ik``;
- a coincident row (``m_i <= radius2``) has ``r_ik = 1`` where ``d²_ik <= radius2``
  and 0 elsewhere, so a target on one control takes its value exactly and a
  target on several coincident controls the mean of their values.

Inputs are contiguous CPU tensors of one floating dtype (float32 or float64), of any
dimension ``D >= 1``, already normalised by the caller (both clouds scaled by one power
of two so that every coordinate lies in [-1, 1]; not translated). Nothing here validates geometry (finite values,
shapes against each other beyond what indexing needs): that is the caller's job.

Kernels
-------
Each kernel is one parallel region (``prange`` over blocks of rows, no
synchronisation between blocks) in which a block of ``ROWS`` rows walks the other
point set in chunks of ``CHUNK`` points. A chunk's coordinates and values are loaded
once per block and reused by every row of the block from the L1 cache; inside a
chunk each step (squared distances axis by axis, the ratio power, the products
with each value column) is a separate unit-stride loop over the chunk, which LLVM
vectorises. Coordinates and values are passed transposed, (D, N) and (K, N), so
that those loops read contiguous memory. The nearest distance is a minimum over
the integer bit patterns of the squared distances (ordered like the values, as
they are >= +0), which vectorises where a float minimum does not.

- :func:`nearest_squared`: ``min_k d²_ik`` (one pass).
- :func:`apply`: ``W @ values`` and the row sums ``s_i`` (the caller gives ``m_i``);
  no pairwise tile is ever written to memory.
- :func:`apply_transposed`: ``Wᵀ @ grad`` (the backward pass to the values),
  parallel over controls, recomputing ``r_ik`` and dividing by the saved ``s_i``.
- :func:`weights`: the dense ``W``, written row block by row block in one fused
  pass: squared distances into the block's rows of W and the nearest distance, then
  the unnormalised weights in place, then the scaling by ``1/s_i``, while the block
  is still in cache.
- :func:`dense_apply`: ``W @ values`` for a stored W (:mod:`torchmorph._dense`).

Precision: distances, ratios and products are computed in the input dtype; partial
sums over one chunk (``CHUNK`` terms spread over the SIMD lanes) are added into
float64 accumulators. In float32 this keeps the summation error of ``W @ d`` below
the rounding of the ratios themselves: 5e-8 of ``max |d|`` against a float64
reference at the paper's case-B counts (14,126 controls × 21,910 targets), at no
measurable cost.

Threads follow ``torch.get_num_threads()`` (capped by numba's pool,
``NUMBA_NUM_THREADS``), set per call and restored after it, and blocks are handed
out one at a time (``numba.set_parallel_chunksize(1)`` for the call). With one
parallel region per call and no spin-wait per block, a process competing for the
cores slows a call by about the share of the cores it takes. The kernels run on
numba's threading layer (``omp`` where GNU OpenMP is found, as here): numba documents
that layer as unsafe to use in a process forked after it started, so forked workers
(a ``fork`` start method, e.g. data-loader workers) should not call the kernels
unless ``NUMBA_THREADING_LAYER=workqueue`` (or ``tbb``) is set.

Dependency
----------
numba (``pip install numba``: numba 0.68.1 and llvmlite 0.50 wheels, 64 MB download,
210 MB installed, no change to numpy, scipy or torch) buys kernels of the same class
as the GPU ones. Measured on one core of the shared 2-core development machine
(``benchmarks/idw_cpu.py``, p = 4, one field): ``apply`` runs at 1.2–1.3 Gpair/s in
float32 and 0.6–0.75 Gpair/s in float64, 5.4–6.3× (float32) and 2.4–2.5× (float64) a
plain two-pass numba loop and about 4× torchmorph's tiled torch path; beside a busy process
the fused paths take 1.3–2.3× their quiet time (about what a plain 2-thread GEMM takes
there, 2.2–2.9×) where the torch path has taken up to 12×.
The price is compilation: lazy, once per kernel and dtype, 2–3 s each on first use
(about 13 s for all five kernels in one dtype), then cached on disk by numba
(``cache=True``: in ``__pycache__`` beside this file, or under ``NUMBA_CACHE_DIR``),
so that later processes load the machine code in well under a second. Without numba
:func:`available` is False and torchmorph uses its torch path.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "CHUNK",
    "ROWS",
    "WEIGHT_ROWS",
    "apply",
    "apply_streaming",
    "apply_transposed",
    "available",
    "dense_apply",
    "nearest_squared",
    "weights",
]

from torchmorph._dense import dense_product
from torchmorph._threads import numba_threads
from torchmorph.idw.backends._protocol import power_code
from torchmorph.idw.backends.numba._jit import (
    CHUNK,
    ROWS,
    WEIGHT_ROWS,
    _apply_kernel,
    _apply_streaming_kernel,
    _nearest_kernel,
    _transposed_kernel,
    _weights_kernel,
    numba,
)


def available() -> bool:
    """Whether the kernels can run compiled: numba imports and its JIT is not disabled.

    Cheap (nothing is compiled): each kernel compiles on its first call for a dtype, or
    loads from numba's on-disk cache.
    """
    # DISABLE_JIT is set from the environment when numba imports: numba's annotations lack it
    return numba is not None and not numba.config.DISABLE_JIT  # type: ignore[attr-defined]


def _require_numba() -> None:
    if numba is None:
        raise RuntimeError("the fused CPU kernels need numba: pip install numba")


def _largest_integer(dtype: np.dtype) -> np.ndarray:
    """[the largest integer as wide as ``dtype``]: the start of an integer-pattern minimum."""
    integer = np.int32 if dtype == np.float32 else np.int64
    return np.array([np.iinfo(integer).max], dtype=integer)


# --------------------------------------------------------------------------- #
# argument handling
# --------------------------------------------------------------------------- #
def _array(tensor: Tensor, name: str, ndim: int, dtype: torch.dtype | None = None) -> np.ndarray:
    if not isinstance(tensor, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    if tensor.device.type != "cpu":
        raise ValueError(f"{name} must be on the CPU, got device {tensor.device}")
    if tensor.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name} must be float32 or float64, got {tensor.dtype}")
    if dtype is not None and tensor.dtype != dtype:
        raise ValueError(f"{name} must have dtype {dtype} like targets, got {tensor.dtype}")
    if tensor.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {tuple(tensor.shape)}")
    return tensor.detach().contiguous().numpy()


def _points(targets: Tensor, controls: Tensor) -> tuple[np.ndarray, np.ndarray]:
    target_array = _array(targets, "targets", 2)
    control_array = _array(controls, "controls", 2, targets.dtype)
    if control_array.shape[1] != target_array.shape[1] or control_array.shape[1] < 1:
        raise ValueError(
            f"controls must have shape (N_c, {target_array.shape[1]}) like "
            f"targets, got {tuple(control_array.shape)}"
        )
    if control_array.shape[0] == 0:
        raise ValueError("controls must hold at least one point, got 0")
    return target_array, control_array


def _power_mode(power: float) -> int:
    power = float(power)
    if not (power > 0 and math.isfinite(power)):
        raise ValueError(f"power must be finite and > 0, got {power!r}")
    return power_code(power)


def _params(dtype: np.dtype, power: float, radius2: float) -> np.ndarray:
    radius2 = float(radius2)
    if not (radius2 >= 0 and math.isfinite(radius2)):
        raise ValueError(f"radius2 must be finite and >= 0, got {radius2!r}")
    return np.array([np.finfo(dtype).tiny, radius2, float(power) / 2, 0.0, 1.0], dtype=dtype)


def _vector(tensor: Tensor, name: str, length: int, dtype: torch.dtype) -> np.ndarray:
    array = _array(tensor, name, 1, dtype)
    if array.shape[0] != length:
        raise ValueError(f"{name} must have shape ({length},), got {tuple(array.shape)}")
    return array


def _matrix(tensor: Tensor, name: str, rows: int, what: str, dtype: torch.dtype) -> np.ndarray:
    array = _array(tensor, name, 2, dtype)
    if array.shape[0] != rows:
        raise ValueError(
            f"{name} must have shape ({rows}, K): one row per {what}, got {tuple(array.shape)}"
        )
    return array


# --------------------------------------------------------------------------- #
# public functions
# --------------------------------------------------------------------------- #
def nearest_squared(targets: Tensor, controls: Tensor) -> Tensor:
    """Squared distance from each target to its nearest control (not floored).

    Parameters
    ----------
    targets : Tensor, shape (N_t, D)
    controls : Tensor, shape (N_c, D)
        Same dtype (float32 or float64), CPU, N_c >= 1.

    Returns
    -------
    Tensor, shape (N_t,)
        ``min_k |t_i - c_k|²`` by direct coordinate differences.

    Notes
    -----
    A brute-force pass, O(N_t N_c), for any D. With many controls scipy's KD-tree is
    faster (up to 2.4× at 10^4 controls); with few controls and targets far from them
    (a boundary's controls, a volume's targets) this pass is: the IDW backend picks by
    the controls' size (``KD_TREE_BYTES`` in :mod:`torchmorph.idw.backends.numba`).
    """
    target_array, control_array = _points(targets, controls)
    out = torch.empty(target_array.shape[0], dtype=targets.dtype)
    if target_array.shape[0]:
        _require_numba()
        with numba_threads():
            _nearest_kernel(
                target_array,
                np.ascontiguousarray(control_array.T),
                _largest_integer(target_array.dtype),
                out.numpy(),
            )
    return out


def apply(
    targets: Tensor,
    controls: Tensor,
    values: Tensor,
    power: float,
    radius2: float,
    nearest2: Tensor,
) -> tuple[Tensor, Tensor]:
    """Matrix-free ``W @ values`` and the row sums ``s_i`` (paper eqs. (1)–(2)).

    Parameters
    ----------
    targets : Tensor, shape (N_t, D)
    controls : Tensor, shape (N_c, D)
    values : Tensor, shape (N_c, K)
        Values at the controls (K columns: displacement components of a batch).
    power : float
        The exponent p > 0.
    radius2 : float
        Squared coincidence radius: rows with ``m_i <= radius2`` are coincident.
    nearest2 : Tensor, shape (N_t,)
        ``min_k d²_ik``, e.g. from :func:`nearest_squared` (floored here at ``tiny``).

    Returns
    -------
    out : Tensor, shape (N_t, K)
        ``W @ values``.
    sums : Tensor, shape (N_t,)
        ``s_i = Σ_k r_ik``, the normalisation that :func:`apply_transposed` needs.
    """
    target_array, control_array = _points(targets, controls)
    value_array = _matrix(values, "values", control_array.shape[0], "control", targets.dtype)
    nearest_array = _vector(nearest2, "nearest2", target_array.shape[0], targets.dtype)
    mode = _power_mode(power)
    params = _params(target_array.dtype, power, radius2)
    out = torch.empty(target_array.shape[0], value_array.shape[1], dtype=targets.dtype)
    sums = torch.empty(target_array.shape[0], dtype=targets.dtype)
    if target_array.shape[0]:
        _require_numba()
        with numba_threads():
            _apply_kernel(
                target_array,
                np.ascontiguousarray(control_array.T),
                np.ascontiguousarray(value_array.T),
                nearest_array,
                params,
                mode,
                out.numpy(),
                sums.numpy(),
            )
    return out, sums


def apply_streaming(
    targets: Tensor,
    controls: Tensor,
    values: Tensor,
    power: float,
    radius2: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`apply` in one pass over the controls, without ``nearest2``: the smallest
    distance is found on the way and the partial sums rescaled when it falls.

    Returns
    -------
    out, sums : as :func:`apply`
    nearest2 : Tensor, shape (N_t,)
        ``min_k d²_ik`` floored at the dtype's smallest normal, as :func:`apply` takes it
        (for :func:`apply_transposed` and later calls).
    """
    target_array, control_array = _points(targets, controls)
    value_array = _matrix(values, "values", control_array.shape[0], "control", targets.dtype)
    mode = _power_mode(power)
    params = _params(target_array.dtype, power, radius2)
    out = torch.empty(target_array.shape[0], value_array.shape[1], dtype=targets.dtype)
    sums = torch.empty(target_array.shape[0], dtype=targets.dtype)
    nearest2 = torch.empty(target_array.shape[0], dtype=targets.dtype)
    if target_array.shape[0]:
        _require_numba()
        with numba_threads():
            _apply_streaming_kernel(
                target_array,
                np.ascontiguousarray(control_array.T),
                np.ascontiguousarray(value_array.T),
                params,
                mode,
                _largest_integer(target_array.dtype),
                out.numpy(),
                sums.numpy(),
                nearest2.numpy(),
            )
    return out, sums, nearest2


def apply_transposed(
    targets: Tensor,
    controls: Tensor,
    grad: Tensor,
    power: float,
    radius2: float,
    nearest2: Tensor,
    sums: Tensor,
) -> Tensor:
    """``Wᵀ @ grad``: the backward pass of :func:`apply` to its values.

    Parameters
    ----------
    targets, controls, power, radius2, nearest2
        As given to :func:`apply`.
    grad : Tensor, shape (N_t, K)
        Gradient with respect to :func:`apply`'s ``out``.
    sums : Tensor, shape (N_t,)
        The row sums :func:`apply` returned.

    Returns
    -------
    Tensor, shape (N_c, K)
        ``Σ_i w_ik grad_i``, computed in parallel over controls: ``r_ik`` is
        recomputed and divided by the saved ``s_i`` (W is never stored).
    """
    target_array, control_array = _points(targets, controls)
    grad_array = _matrix(grad, "grad", target_array.shape[0], "target", targets.dtype)
    nearest_array = _vector(nearest2, "nearest2", target_array.shape[0], targets.dtype)
    sum_array = _vector(sums, "sums", target_array.shape[0], targets.dtype)
    mode = _power_mode(power)
    params = _params(target_array.dtype, power, radius2)
    out = torch.empty(control_array.shape[0], grad_array.shape[1], dtype=targets.dtype)
    if target_array.shape[0] == 0:
        return out.zero_()
    scaled_t = np.ascontiguousarray((grad_array / sum_array[:, None]).T)
    _require_numba()
    with numba_threads():
        _transposed_kernel(
            control_array,
            np.ascontiguousarray(target_array.T),
            scaled_t,
            nearest_array,
            params,
            mode,
            out.numpy(),
        )
    return out


def weights(
    targets: Tensor, controls: Tensor, power: float, radius2: float, out: Tensor | None = None
) -> Tensor:
    """Dense ``W`` (paper eq. (2)), row-major, in one fused pass per block of rows.

    Parameters
    ----------
    targets : Tensor, shape (N_t, D)
    controls : Tensor, shape (N_c, D)
    power, radius2
        As in :func:`apply`.
    out : Tensor, shape (N_t, N_c), optional
        Contiguous tensor of the same dtype to write W into.

    Returns
    -------
    Tensor, shape (N_t, N_c)
        Rows sum to 1; ``out`` when given.
    """
    target_array, control_array = _points(targets, controls)
    shape = (target_array.shape[0], control_array.shape[0])
    if out is None:
        out = torch.empty(shape, dtype=targets.dtype)
    else:
        _array(out, "out", 2, targets.dtype)
        if tuple(out.shape) != shape or not out.is_contiguous():
            raise ValueError(
                f"out must be a contiguous tensor of shape {shape}, got "
                f"{tuple(out.shape)}{'' if out.is_contiguous() else ' (strided)'}"
            )
    mode = _power_mode(power)
    params = _params(target_array.dtype, power, radius2)
    if shape[0]:
        _require_numba()
        with numba_threads():
            _weights_kernel(
                target_array,
                np.ascontiguousarray(control_array.T),
                params,
                mode,
                _largest_integer(target_array.dtype),
                out.detach().numpy(),
            )
    return out


def dense_apply(weights: Tensor, values: Tensor) -> Tensor:
    """``weights @ values`` for a dense W, reading W once per three columns.

    Parameters
    ----------
    weights : Tensor, shape (N_t, N_c)
        Row-major W (e.g. from :func:`weights`).
    values : Tensor, shape (N_c, K)
        Same dtype.

    Returns
    -------
    Tensor, shape (N_t, K)

    Notes
    -----
    The pass of :mod:`torchmorph._dense` (float64 sums, four rows of W at a time): at
    case C's W (3,322 × 3,864, float64, one thread) 6.3 ms against 18 ms for torch's
    ``mm``, at case B's (19,852 × 13,616) 111 ms against 375 ms. For large K prefer
    torch's GEMM.
    """
    weight_array = _array(weights, "weights", 2)
    if not weights.is_contiguous():
        raise ValueError("weights must be contiguous (row-major)")
    _matrix(values, "values", weight_array.shape[1], "column of weights", weights.dtype)
    _require_numba()
    with numba_threads(), torch.no_grad():
        return dense_product(weights.detach(), values.detach())
