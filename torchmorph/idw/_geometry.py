"""Argument handling and geometry preparation shared by the IDW entry points of
:mod:`torchmorph.idw`: checks, the power-of-two scaling of both point clouds with the
coincidence radius, the keyword points and their deprecated positional order, the memory
a device has free, and the warning about duplicated control points."""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from torchmorph._checks import (
    as_points,
    check_finite,
    check_positive,
    check_same_device_dtype,
    dim_of,
    is_traced,
)

__all__: list[str] = []


def check_power(power: float) -> float:
    return check_positive(power, "power")


def check_tolerance(tolerance: float) -> float:
    tolerance = float(tolerance)
    if tolerance < 0 or not math.isfinite(tolerance):
        raise ValueError(f"coincidence_tolerance must be finite and >= 0, got {tolerance!r}")
    return tolerance


def check_error_control(error_control: str) -> str:
    """The tree's error control, ``"certified"`` or ``"sampled"``; else ``ValueError``."""
    if error_control not in ("certified", "sampled"):
        raise ValueError(f"error_control must be 'certified' or 'sampled', got {error_control!r}")
    return error_control


def normalise(
    targets: Tensor, controls: Tensor, tolerance: float
) -> tuple[Tensor, Tensor, float | Tensor]:
    """Both clouds scaled by a power of two so that every coordinate lies in [-1, 1],
    and the squared coincidence radius ``(tolerance · bounding-box diagonal)²`` in
    those units (at least the dtype's smallest normal, so that a target exactly on a
    control always counts as coincident).

    Scaling by a power of two is exact, and W is invariant under it (gradients
    included: the factor is a constant), so coordinates from 1e-30 to 1e30 give the
    same weights; squared distances then neither overflow nor underflow. The points
    are not translated: a translation would round the coordinates of a cloud
    centred away from its own fine details. The radius is a Python float, or a
    0-d tensor when the call is traced (no value is read in Python then).

    Raises ``ValueError`` naming the cloud when one holds NaN or infinite
    coordinates: the bounds that set the scale are read in one go with that check
    (one device synchronisation per call), so callers validate the points with
    ``as_points(..., finite=False)``.
    """
    tiny = torch.finfo(controls.dtype).tiny
    with torch.no_grad():
        t, c = targets.detach(), controls.detach()
        if is_traced(t) or is_traced(c):
            return _normalise_traced(targets, controls, tolerance)
        extremes = [*torch.aminmax(c, dim=0)]
        if t.shape[0]:
            extremes += torch.aminmax(t, dim=0)
        bounds = torch.stack(extremes).tolist()  # the one read: NaN propagates
    if not all(math.isfinite(value) for row in bounds for value in row):
        check_finite(controls, "controls")
        check_finite(targets, "targets")
    low = [min(column) for column in zip(*bounds[0::2], strict=True)]
    high = [max(column) for column in zip(*bounds[1::2], strict=True)]
    _, exponent = math.frexp(max(map(abs, low + high)))
    scale = math.ldexp(1.0, -exponent)
    diagonal = math.hypot(*(b * scale - a * scale for a, b in zip(low, high, strict=True)))
    _check_resolution(bounds, scale, controls.dtype, (controls.shape[0], targets.shape[0]))
    radius2 = max((tolerance * diagonal) ** 2, tiny)
    return targets * scale, controls * scale, radius2


def _normalise_traced(
    targets: Tensor, controls: Tensor, tolerance: float
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`normalise` in tensor operations only (no value read in Python), for traced
    calls; called under ``torch.no_grad()``."""
    tiny = torch.finfo(controls.dtype).tiny
    t, c = targets.detach(), controls.detach()
    check_finite(controls, "controls")
    check_finite(targets, "targets")
    low, high, largest = c.amin(0), c.amax(0), c.abs().amax()
    if t.shape[0]:
        low = torch.minimum(low, t.amin(0))
        high = torch.maximum(high, t.amax(0))
        largest = torch.maximum(largest, t.abs().amax())
    _, exponent = torch.frexp(largest)
    scale = torch.ldexp(torch.ones_like(largest), -exponent)
    diagonal = torch.linalg.vector_norm(high * scale - low * scale)
    radius2 = (tolerance * diagonal).square().clamp_min(tiny)
    return targets * scale, controls * scale, radius2


def _check_resolution(bounds, scale: float, dtype: torch.dtype, counts) -> None:
    """Raise ``ValueError`` if a cloud spans so little of the coordinates' range that the
    squared distances between its points underflow in ``dtype`` (a float32 cloud of unit
    size beside a point at 1e25): its weights would come out of rounding alone."""
    finfo = torch.finfo(dtype)
    smallest = math.sqrt(finfo.tiny / finfo.eps)  # squared, resolved to eps at least
    for name, rows, count in (
        ("controls", bounds[0:2], counts[0]),
        ("targets", bounds[2:4], counts[1]),
    ):
        if count < 2 or not rows:
            continue
        extent = max(b - a for a, b in zip(rows[0], rows[1], strict=True)) * scale
        if 0 < extent < smallest:
            raise ValueError(
                f"{name} span {extent / scale:.3g} beside coordinates as large as "
                f"{1 / scale:.3g}: {dtype} cannot resolve the squared distances at that "
                "ratio; use float64 (or move the far points closer)"
            )


def points_arguments(function: str, positional: tuple, controls, targets, count: int = 2):
    """``(controls, targets[, displacements])`` from keywords, or from the deprecated
    positional order ``(targets, controls[, displacements])`` with a warning."""
    if positional:
        if len(positional) != count or controls is not None or targets is not None:
            names = "controls=..., targets=..." + (", displacements=..." if count == 3 else "")
            raise TypeError(f"{function}() takes its points as keywords: {function}({names})")
        warnings.warn(
            f"{function}(targets, controls, ...) with positional points is deprecated and will "
            f"be removed: pass controls=... and targets=... as keywords (the order of IDW)",
            DeprecationWarning,
            stacklevel=3,
        )
        targets, controls = positional[:2]
        return (controls, targets, *positional[2:])
    if controls is None or targets is None:
        raise TypeError(f"{function}() needs controls= and targets=")
    return controls, targets


def prepare(targets, controls, power, coincidence_tolerance):
    """Validated, normalised points, the power and the squared coincidence radius."""
    controls = as_points(controls, "controls", dim=dim_of(controls), finite=False)
    targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True, finite=False)
    check_same_device_dtype(controls, "controls", targets, "targets")
    power = check_power(power)
    targets, controls, radius2 = normalise(
        targets, controls, check_tolerance(coincidence_tolerance)
    )
    return targets, controls, power, radius2


def warn_duplicate_controls(controls: Tensor, tolerance: float, targets: Tensor) -> None:
    """Warn when controls lie within the coincidence radius of one another: a target on
    them takes the mean of their displacements. Both clouds are normalised together
    first, so that clouds the dtype cannot resolve are refused before any warning."""
    if controls.shape[0] < 2 or is_traced(controls) or is_traced(targets):
        return
    from scipy.spatial import cKDTree

    with torch.no_grad():
        _, normalised, radius2 = normalise(targets.detach(), controls.detach(), tolerance)
        points = normalised.double().cpu().numpy()
    distances, _ = cKDTree(points).query(points, k=2)
    close = int((distances[:, 1] ** 2 <= radius2).sum())
    if close:
        warnings.warn(
            f"controls: {close} control points lie within the coincidence radius of another "
            f"one (duplicated points); a target there takes the mean of their displacements",
            stacklevel=3,
        )
