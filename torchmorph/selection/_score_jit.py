"""The numba kernels of the IDW error oracle
(:class:`torchmorph.selection.oracle.IDWErrorOracle`): the assembly of its weights,
the pass that scores every candidate, the sums of a set of candidates' rows and the
exact sequential picks.

:func:`weights_transposed` writes full IDW's weights from every candidate to the sampled
targets as ``Wᵀ`` (one row per candidate, contiguous over the targets), each target's
column scaled by its smallest squared distance, ``(m_i / d²_ij)^(p/2)`` in [0, 1]: the
oracle reads only ratios within a column, so the scale cancels, and nothing overflows.
A target within the coincidence radius of candidates gets 1 at those and 0 elsewhere.

:func:`score_rows`: for a candidate j (a row of ``Wᵀ``) and the sampled targets i it
forms ``t_ij = W_ij / (σ_i + W_ij)`` once and returns ``Σ_i t_ij a_ki`` and
``Σ_i t_ij² b_ki`` for the columns ``a_k``, ``b_k`` of two fields on the targets: the
products ``T a`` and ``T² b`` of the oracle's scores, without materialising ``T``.
Four candidates are taken at once over chunks of targets that stay in the L1 cache, so
that each column is read once per four candidates; groups run in parallel.

:func:`accumulate` adds ``Σ_j v_jk W_ji`` over a set of candidates' rows, read in place.
:func:`pick` adds candidates of a pool one at a time, each the one that lowers the
error most given the earlier ones, updating the sums after each (the oracle's
:meth:`~torchmorph.selection.oracle.IDWErrorOracle.pick`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchmorph.idw.backends.numba._jit import _OPTIONS, njit, numba, prange

__all__ = ["accumulate", "available", "score_rows", "weights_transposed"]

# Targets per chunk of the scoring pass: four rows of ratios (8 KiB in float64).
_CHUNK = 256
# Candidates scored together (the ratios of each kept in a row of the scratch).
_GROUP = 4


def available(weights_t: Tensor) -> bool:
    """Whether the kernels serve these weights (numba present, CPU, float32/float64)."""
    return (
        numba is not None
        and weights_t.device.type == "cpu"
        and weights_t.dtype in (torch.float32, torch.float64)
    )


@njit(parallel=True, **_OPTIONS)
def _fill(candidates, targets_t, nearest, half_power, values_t, out, sums):
    """out[j, i] = (nearest[i] / d²_ij)^half_power, and each chunk c of the candidates'
    ``sums[c, k, i] = Σ_j out[j, i] values_t[k, j]`` while its rows are in cache."""
    dim, count = targets_t.shape
    rows = candidates.shape[0]
    chunks = sums.shape[0]
    for chunk in prange(chunks):
        total = sums[chunk]
        for j in range(chunk * rows // chunks, (chunk + 1) * rows // chunks):
            row = out[j]
            for i in range(count):
                row[i] = 0.0
            for axis in range(dim):
                column = targets_t[axis]
                coordinate = candidates[j, axis]
                for i in range(count):
                    diff = coordinate - column[i]
                    row[i] += diff * diff
            if half_power == 2.0:
                for i in range(count):
                    ratio = nearest[i] / row[i]
                    row[i] = ratio * ratio
            elif half_power == 1.0:
                for i in range(count):
                    row[i] = nearest[i] / row[i]
            else:
                for i in range(count):
                    row[i] = math.exp(half_power * math.log(nearest[i] / row[i]))
            for k in range(values_t.shape[0]):
                value = values_t[k, j]
                target = total[k]
                for i in range(count):
                    target[i] += row[i] * value


@njit(**_OPTIONS)
def _coincident(candidates, targets, columns, radius2, out):
    """Columns of targets that lie on candidates: 1 at those candidates, 0 elsewhere."""
    for i in columns:
        for j in range(candidates.shape[0]):
            total = 0.0
            for axis in range(candidates.shape[1]):
                diff = candidates[j, axis] - targets[i, axis]
                total += diff * diff
            out[j, i] = 1.0 if total <= radius2 else 0.0


def weights_transposed(
    candidates: Tensor,
    targets: Tensor,
    nearest: Tensor,
    power: float,
    radius2: float,
    values: Tensor,
    out: Tensor,
) -> Tensor:
    """Write ``Wᵀ`` (N_c, N_s) of the module's notes into ``out`` (float64, contiguous)
    for normalised ``candidates`` (N_c, D) and ``targets`` (N_s, D), each target's
    squared distance to its nearest candidate ``nearest`` (N_s,) and the squared
    coincidence radius ``radius2``; return ``W @ values`` (N_s, K) for ``values``
    (N_c, K), summed while the rows are written."""
    points = np.ascontiguousarray(candidates.to(torch.float64).numpy())
    targets_np = np.ascontiguousarray(targets.to(torch.float64).numpy())
    scale = np.ascontiguousarray(nearest.to(torch.float64).numpy())
    values_t = np.ascontiguousarray(values.to(torch.float64).mT.numpy())
    matrix = out.numpy()
    chunks = min(numba.get_num_threads(), points.shape[0])
    sums = np.zeros((chunks, values_t.shape[0], targets_np.shape[0]))
    _fill(points, np.ascontiguousarray(targets_np.T), scale, power / 2, values_t, matrix, sums)
    product = sums.sum(0)
    columns = np.flatnonzero(scale <= radius2)
    if columns.size:
        _coincident(points, targets_np, columns, radius2, matrix)
        product[:, columns] = values_t @ matrix[:, columns]
    return torch.from_numpy(np.ascontiguousarray(product.T))


@njit(**_OPTIONS)
def _accumulate(weights_t, rows, values, out):
    """out[k, i] += Σ_r values[r, k] weights_t[rows[r], i], row by row (each row read
    once, in full: streamed from memory, ``out`` kept in cache)."""
    count = weights_t.shape[1]
    for r in range(rows.shape[0]):
        row = weights_t[rows[r]]
        for k in range(values.shape[1]):
            value = values[r, k]
            target = out[k]
            for i in range(count):
                target[i] += value * row[i]


def accumulate(weights_t: Tensor, rows: Tensor, values: Tensor, out: Tensor) -> None:
    """``out += (values.mT @ weights_t[rows])``: out (K, N_s) float64, ``values``
    (len(rows), K), the rows read in place."""
    _accumulate(
        weights_t.numpy(),
        np.ascontiguousarray(rows.numpy()),
        np.ascontiguousarray(values.to(torch.float64).numpy()),
        out.numpy(),
    )


@njit(**_OPTIONS)
def _dot4(r0, r1, r2, r3, column, count):
    a0 = a1 = a2 = a3 = 0.0
    for i in range(count):
        value = column[i]
        a0 += r0[i] * value
        a1 += r1[i] * value
        a2 += r2[i] * value
        a3 += r3[i] * value
    return a0, a1, a2, a3


@njit(**_OPTIONS)
def _add_dots(ratio, columns, begin, size, acc):
    """acc[g, k] += Σ_i ratio[g, i] columns[k, begin + i] for the four rows of ratios."""
    r0, r1, r2, r3 = ratio[0], ratio[1], ratio[2], ratio[3]
    for k in range(columns.shape[0]):
        a0, a1, a2, a3 = _dot4(r0, r1, r2, r3, columns[k, begin : begin + size], size)
        acc[0, k] += a0
        acc[1, k] += a1
        acc[2, k] += a2
        acc[3, k] += a3


@njit(parallel=True, **_OPTIONS)
def _score_rows(weights_t, count, sums, linear, square, first, second):
    rows = weights_t.shape[0]
    groups = (rows + _GROUP - 1) // _GROUP
    tiny = np.finfo(sums.dtype).tiny
    for group in prange(groups):
        start = group * _GROUP
        ratio = np.zeros((_GROUP, _CHUNK), dtype=sums.dtype)
        acc_first = np.zeros((_GROUP, linear.shape[0]))
        acc_second = np.zeros((_GROUP, square.shape[0]))
        for begin in range(0, count, _CHUNK):
            size = min(_CHUNK, count - begin)
            for g in range(_GROUP):
                j = start + g
                target = ratio[g]
                if j < rows:
                    row = weights_t[j]
                    part = row[begin : begin + size]
                    base = sums[begin : begin + size]
                    for i in range(size):  # + tiny: 0 where both are 0
                        target[i] = part[i] / (base[i] + part[i] + tiny)
                else:
                    for i in range(size):
                        target[i] = 0.0
            _add_dots(ratio, linear, begin, size, acc_first)
            for g in range(_GROUP):
                target = ratio[g]
                for i in range(size):
                    target[i] *= target[i]
            _add_dots(ratio, square, begin, size, acc_second)
        for g in range(_GROUP):
            j = start + g
            if j < rows:
                for k in range(linear.shape[0]):
                    first[j, k] = acc_first[g, k]
                for k in range(square.shape[0]):
                    second[j, k] = acc_second[g, k]


def score_rows(
    weights_t: Tensor, count: int, sums: Tensor, linear: Tensor, square: Tensor
) -> tuple[Tensor, Tensor]:
    """``(T a, T² b)`` over the first ``count`` columns of ``weights_t`` (N_c, N_s):
    ``t_ij = W_ij / (σ_i + W_ij)``, ``a = linear`` (count, K1), ``b = square`` (count, K2),
    ``σ = sums`` (count,); results (N_c, K1) and (N_c, K2) in float64."""
    dtype = weights_t.dtype
    matrix = weights_t.contiguous().numpy()
    columns_a = np.ascontiguousarray(linear.to(dtype).mT.numpy())
    columns_b = np.ascontiguousarray(square.to(dtype).mT.numpy())
    sums_np = np.ascontiguousarray(sums.to(dtype).numpy())
    rows = matrix.shape[0]
    first = np.empty((rows, columns_a.shape[0]))
    second = np.empty((rows, columns_b.shape[0]))
    _score_rows(matrix, count, sums_np, columns_a, columns_b, first, second)
    return torch.from_numpy(first), torch.from_numpy(second)


@njit(**_OPTIONS)
def _pick(
    weights_t, pool, sums, accumulated, approx, reference, omega, family, totals, goal, limit
):
    """Candidates of ``pool`` one at a time, each the one whose addition lowers
    ``Σ_f totals_f`` most (exactly, at the sampled targets), until the largest of
    ``totals`` is at most ``goal``, ``limit`` are taken or none lowers it. Updates
    ``sums``, ``accumulated``, ``approx`` (the selective field; kept where ``sums`` is
    0) and ``totals`` in place; returns the taken candidates. The fields are stored
    (F, D, N_s): the loops over targets vectorise."""
    members, dim, count = reference.shape
    error = np.empty((members, dim, count))
    for f in range(members):
        for k in range(dim):
            for i in range(count):
                error[f, k, i] = reference[f, k, i] - approx[f, k, i]
    taken = np.zeros(pool.shape[0], dtype=np.bool_)
    ratio = np.empty(count)
    gains = np.empty(members)
    best_gains = np.empty(members)
    out = np.empty(min(limit, pool.shape[0]), dtype=np.int64)
    size = 0
    while size < out.shape[0] and totals.max() > goal:
        best, best_total = -1, 0.0
        for q in range(pool.shape[0]):
            if taken[q]:
                continue
            j = pool[q]
            row = weights_t[j]
            for i in range(count):
                ratio[i] = row[i] / (sums[i] + row[i] + 1e-300)
            for f in range(members):
                gain = 0.0
                weight = omega[f]
                for k in range(dim):
                    value = family[f, j, k]
                    a = approx[f, k]
                    e = error[f, k]
                    for i in range(count):
                        step = ratio[i] * (value - a[i])
                        gain += weight[i] * step * (2.0 * e[i] - step)
                gains[f] = gain
            if gains.sum() > best_total:
                best, best_total = q, gains.sum()
                best_gains[:] = gains
        if best < 0:
            break
        taken[best] = True
        j = pool[best]
        out[size] = j
        size += 1
        totals -= best_gains
        row = weights_t[j]
        for i in range(count):
            sums[i] += row[i]
        for f in range(members):
            for k in range(dim):
                value = family[f, j, k]
                for i in range(count):
                    accumulated[f, k, i] += row[i] * value
                    if sums[i] > 0:
                        approx[f, k, i] = accumulated[f, k, i] / sums[i]
                        error[f, k, i] = reference[f, k, i] - approx[f, k, i]
    return out[:size]


def pick(
    weights_t: Tensor,
    pool: Tensor,
    sums: Tensor,
    accumulated: Tensor,
    approx: Tensor,
    reference: Tensor,
    omega: Tensor,
    family: Tensor,
    totals: Tensor,
    goal: float,
    limit: int,
) -> Tensor:
    """The exact sequential greedy of :func:`_pick` on float64 arrays: ``sums`` (N_s,)
    and ``accumulated`` (F, N_s, D) the selection's ``Σ W`` and ``Σ W d``, ``approx``
    (F, N_s, D) its field, ``reference`` (F, N_s, D) full IDW, ``omega`` (F, N_s) the
    error's weights, ``family``
    (F, N_c, D), ``totals`` (F,) the squared errors; returns the taken candidates
    (int64) and leaves ``totals`` at their squared errors after."""
    array = lambda tensor: np.ascontiguousarray(tensor.to(torch.float64).numpy())  # noqa: E731
    copy = lambda tensor: np.array(tensor.to(torch.float64).numpy(), order="C")  # noqa: E731
    totals_np = copy(totals)
    out = _pick(
        weights_t.numpy(),
        np.ascontiguousarray(pool.numpy().astype(np.int64)),
        copy(sums),  # updated in place: never the caller's
        copy(accumulated.permute(0, 2, 1)),
        copy(approx.permute(0, 2, 1)),
        array(reference.permute(0, 2, 1)),
        array(omega),
        array(family),
        totals_np,
        goal,
        limit,
    )
    totals.copy_(torch.from_numpy(totals_np))
    return torch.from_numpy(out)
