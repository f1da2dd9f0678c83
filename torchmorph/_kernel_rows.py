"""The kernel rows the numba kernels share (float64, one target against a row of points,
each a loop that LLVM vectorises): squared distances from direct coordinate
differences (:func:`squared_row`), then the kernel of them in place: the thin-plate
spline's ``φ = s log(s) / 2`` (:func:`tps_row`, the RBF kernels and the treecode) or the
IDW weight ``s^(-p/2) = r^-p`` (:func:`inverse_power_row`, the treecode).

:func:`tps_row` writes ``log`` out (exponent and mantissa from the bits, ``log m =
2 atanh((m − 1)/(m + 1))`` by its series, 12 terms for |t| <= 0.1716: within 2 ulp of
libm, measured below 1e-15 relative in the tests), so that it vectorises where libm's
``log`` is a scalar call.
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is optional: the callers check for it
    from numba import njit
except ImportError:  # pragma: no cover - exercised where numba is missing
    njit = None  # type: ignore[assignment]

__all__ = ["FLAGS", "inverse_power_row", "squared_row", "tps_row"]

_LN2_HIGH = 6.93147180369123816490e-01  # fdlibm's split of log(2): high bits exact
_LN2_LOW = 1.90821492927058770002e-10
_SQRT2 = math.sqrt(2.0)
FLAGS = {"reassoc", "contract", "nsz", "arcp"}
"""numba's fastmath flags for the kernels: reassociation lets LLVM vectorise reductions."""


def squared_row(x, y, z, cx, cy, cz, scale2, row):  # pass 1
    for j in range(cx.shape[0]):
        dx = x - cx[j]
        dy = y - cy[j]
        dz = z - cz[j]
        row[j] = (dx * dx + dy * dy + dz * dz) * scale2


def tps_row(row, exponent, mantissa_bits):  # pass 2: row <- s log(s) / 2
    bits = row.view(np.int64)
    for j in range(row.shape[0]):
        word = bits[j]
        exponent[j] = np.float64((word >> 52) - 1023)
        mantissa_bits[j] = (word & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000
    mantissa = mantissa_bits.view(np.float64)
    for j in range(row.shape[0]):
        m = mantissa[j]
        e = exponent[j]
        big = m > _SQRT2
        m = m * 0.5 if big else m
        e = e + 1.0 if big else e
        t = (m - 1.0) / (m + 1.0)
        t2 = t * t
        series = 1.0 / 23.0
        series = series * t2 + 1.0 / 21.0
        series = series * t2 + 1.0 / 19.0
        series = series * t2 + 1.0 / 17.0
        series = series * t2 + 1.0 / 15.0
        series = series * t2 + 1.0 / 13.0
        series = series * t2 + 1.0 / 11.0
        series = series * t2 + 1.0 / 9.0
        series = series * t2 + 1.0 / 7.0
        series = series * t2 + 1.0 / 5.0
        series = series * t2 + 1.0 / 3.0
        series = series * t2 + 1.0
        s = row[j]
        logarithm = e * _LN2_HIGH + (2.0 * t * series + e * _LN2_LOW)
        row[j] = 0.5 * s * logarithm if s > 0.0 else 0.0


def inverse_power_row(row, power, floor):  # the IDW weight of squared distances
    """``row[j] <- max(row[j], floor)^(-power / 2)``: the weight ``r^-p`` of squared
    distances, as products for p = 2, 4, 6 and 8, the general power otherwise; ``floor``
    (> 0) keeps a point on a target finite (its caller replaces that target's result)."""
    if power == 4.0:
        for j in range(row.shape[0]):
            s = max(row[j], floor)
            row[j] = 1.0 / (s * s)
    elif power == 2.0:
        for j in range(row.shape[0]):
            row[j] = 1.0 / max(row[j], floor)
    elif power == 6.0:
        for j in range(row.shape[0]):
            s = max(row[j], floor)
            row[j] = 1.0 / (s * s * s)
    elif power == 8.0:
        for j in range(row.shape[0]):
            s = max(row[j], floor)
            s = s * s
            row[j] = 1.0 / (s * s)
    else:
        half = -0.5 * power
        for j in range(row.shape[0]):
            row[j] = max(row[j], floor) ** half


if njit is not None:
    _compile = njit(fastmath=FLAGS, error_model="numpy", cache=True)
    squared_row = _compile(squared_row)
    tps_row = _compile(tps_row)
    inverse_power_row = _compile(inverse_power_row)
