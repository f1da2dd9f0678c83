"""Morphing methods side by side on the paper's cases A, B and C: IDW, RBF of every
kernel family, FFD, scipy's ``RBFInterpolator`` and mathLab's PyGeM.

Each case at its paper displacement μ* (A and B: the wing bent by δy = μ* z², C: the
hull turned by μ* = −5°), every boundary node a control point (full interpolants), the
interior moved by:

- **IDW**: :class:`torchmorph.MeshMorph` on its default path (p = 4, ``mode="auto"``);
- **RBF**: ``MeshMorph(method="rbf")`` with each kernel family and the linear
  polynomial (``degree=1``): thin-plate spline, cubic and quintic (scale invariant),
  Wendland C2 with ``support_radius`` = ``--support-fraction`` (0.25) × the mesh's
  bounding-box diagonal, and gaussian / multiquadric / inverse multiquadric with
  ``epsilon = 1 / (--shape-spacings × h)``, h the median distance of a control point to
  its nearest neighbour (flatter kernels are singular in float64: the shape-parameter
  table gives their measured condition numbers);
- **FFD → IDW**: a Bernstein 3 × 3 × 3 lattice on the moving body's bounding box (2 %
  margin), its displacements fitted by least squares to the body's prescribed motion;
  the body moved by the lattice, the rest of the mesh by IDW from every boundary node.
  Quadratic Bernstein polynomials contain the bending μ z² and the rotation (affine), so
  the fit is exact to rounding and the morph is IDW's: the row shows the parametrisation's
  cost and its fit;
- **FFD volume**: the mesh moved by the lattice alone, no IDW. Case A (the mesh is the
  wing): the same lattice on every node. B and C: a cubic B-spline 7 × 7 × 7 lattice on
  the body's box widened by half the body's largest extent on each side (clipped to the
  mesh), the control points on the lattice's faces fixed (the map is then continuous
  with the still mesh outside), the 5 × 5 × 5 inner ones fitted by least squares to the
  body's motion: the body moves only approximately (its residual is given).

References on the same clouds: scipy's ``RBFInterpolator(boundary points, boundary
displacements, kernel, epsilon, degree=1)`` at the interior nodes, and PyGeM's ``RBF``
(same kernel: its radius is 1/ε or the support radius; always the linear polynomial)
and ``FFD`` (``--pygem PATH``, the folder holding the ``pygem`` package of a checkout of
github.com/mathLab/PyGeM, which is not on PyPI). A reference is left out, with a note,
when it cannot be imported. Agreement is the largest difference of the interior
displacements from ours over the largest boundary displacement; the ratios are the
reference's time over ours. scipy and PyGeM solve for the coefficients when they are
built, so a new displacement is a new fit: their time per morph is fit plus evaluation
(PyGeM refits on every call), ours a solve with the stored factorisation and the
evaluation.

Columns: fit (building the morph: W, or the factorisation and, dense, the evaluation
matrix; FFD: the least squares and the bases), time per morph (median of ``--repeats``,
one fit when it takes more than 2 s), inverted cells, the smallest scaled Jacobian and
the largest edge ratio Q after the morph (:func:`torchmorph.mesh.quality_summary`), and
the estimated 1-norm condition number of the RBF's interpolation matrix [[Φ, P], [Pᵀ, 0]]
(LAPACK ``dgecon``; up to ``--cond-controls`` controls).

Above ``--dense-controls`` (5,000) controls, case B's 13,616, only thin-plate and
Wendland C2 are fitted (``--all-kernels`` for every family): a dense fit is O(N_c³) and
the others cost what thin-plate costs; PyGeM's RBF is timed on ``--pygem-targets``
interior nodes there and its evaluation extrapolated to all (said so).

Then the rotation sweep of ``benchmarks/large_motions.py`` (hull pitch, 2-D NACA0012
section, wing twist) for RBF kernels beyond the thin-plate spline: the first angle with
an inverted cell, to 0.5°.

Everything on one thread (torch, numba, BLAS), float64. Run
``python benchmarks/methods.py --pygem /path/to/PyGeM`` (paper size, about 13 minutes
on one core); ``--cases A --size small`` for a quick run; ``--no-sweep`` without the
rotation sweep.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"  # before numpy, scipy and torch load their BLAS
os.environ["NUMBA_NUM_THREADS"] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import importlib  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch import Tensor  # noqa: E402

from torchmorph import MeshMorph  # noqa: E402
from torchmorph.ffd import FFD  # noqa: E402
from torchmorph.mesh import Mesh, quality_summary  # noqa: E402
from torchmorph.paper import get_case, load_mesh  # noqa: E402
from torchmorph.rbf import RBF  # noqa: E402

#: The RBF rows: (kernel, how its scale is set).
RBF_KERNELS = (
    "thin_plate_spline",
    "cubic",
    "quintic",
    "wendland_c2",
    "gaussian",
    "multiquadric",
    "inverse_multiquadric",
)
#: Kernels fitted above ``--dense-controls`` controls without ``--all-kernels``.
LARGE_KERNELS = ("thin_plate_spline", "wendland_c2")
#: PyGeM's names (``RBFFactory``) and extra parameters for ours.
PYGEM_KERNELS = {
    "thin_plate_spline": ("thin_plate_spline", {}),
    "cubic": ("polyharmonic_spline", {"k": 3}),
    "quintic": ("polyharmonic_spline", {"k": 5}),
    "wendland_c2": ("beckert_wendland_c2_basis", {}),
    "gaussian": ("gaussian_spline", {}),
    "multiquadric": ("multi_quadratic_biharmonic_spline", {}),
    "inverse_multiquadric": ("inv_multi_quadratic_biharmonic_spline", {}),
}
SCIPY_KERNELS = (
    "thin_plate_spline",
    "cubic",
    "quintic",
    "gaussian",
    "multiquadric",
    "inverse_multiquadric",
)
SHAPE_KERNELS = ("gaussian", "multiquadric", "inverse_multiquadric")
SWEEP_KERNELS = ("thin_plate_spline", "wendland_c2", "multiquadric", "gaussian")


# ----------------------------------------------------------------------------- helpers
def measure(function: Callable[[], object], repeats: int, slow: float = 2.0):
    """(result, seconds): one call when it takes more than ``slow`` seconds, else the
    median of ``repeats`` further calls (the first a warm-up)."""
    start = time.perf_counter()
    result = function()
    first = time.perf_counter() - start
    if first > slow or repeats < 1:
        return result, first
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return result, statistics.median(times)


def seconds(value: float | None) -> str:
    if value is None or not math.isfinite(value):
        return "–"
    if value < 1e-3:
        return f"{value * 1e6:,.0f} µs"
    return f"{value * 1e3:,.1f} ms" if value < 1 else f"{value:,.2f} s"


def ratio(reference: float | None, ours: float | None) -> str:
    if reference is None or ours is None or ours <= 0:
        return "–"
    return f"{reference / ours:,.1f}×"


def scales(points: Tensor, controls: Tensor) -> tuple[float, float]:
    """(bounding-box diagonal of ``points``, median nearest-neighbour distance of the
    controls)."""
    from scipy.spatial import cKDTree

    diagonal = float((points.max(0).values - points.min(0).values).norm())
    distances = cKDTree(controls.numpy()).query(controls.numpy(), 2)[0][:, 1]
    return diagonal, float(np.median(distances))


def kernel_options(
    kernel: str, diagonal: float, spacing: float, support_fraction: float, spacings: float
) -> dict:
    """``epsilon`` / ``support_radius`` of a kernel by the rule of the module docstring."""
    if kernel == "wendland_c2":
        return {"support_radius": support_fraction * diagonal}
    if kernel in SHAPE_KERNELS:
        return {"epsilon": 1.0 / (spacings * spacing)}
    return {}


def _phi(kernel: str, r: np.ndarray) -> np.ndarray:
    """scipy's kernels (and Wendland C2) of the scaled distance r, in NumPy."""
    if kernel == "thin_plate_spline":
        return np.where(r > 0, r * r * np.log(np.where(r > 0, r, 1.0)), 0.0)
    table = {
        "cubic": lambda: r**3,
        "quintic": lambda: -(r**5),
        "gaussian": lambda: np.exp(-r * r),
        "multiquadric": lambda: -np.sqrt(1 + r * r),
        "inverse_multiquadric": lambda: 1 / np.sqrt(1 + r * r),
        "wendland_c2": lambda: np.clip(1 - r, 0, None) ** 4 * (4 * r + 1),
    }
    return table[kernel]()


def condition_number(controls: np.ndarray, kernel: str, options: dict, degree: int = 1) -> float:
    """1-norm condition number of [[Φ, P], [Pᵀ, 0]] (P: the monomials of ``degree`` in
    the coordinates scaled to [-1, 1] as scipy's), estimated by LAPACK's ``dgecon`` after
    an LU."""
    from itertools import combinations_with_replacement

    from scipy.linalg import lapack
    from scipy.spatial.distance import cdist

    scale = (
        1.0 / options["support_radius"]
        if "support_radius" in options
        else options.get("epsilon", 1.0)
    )
    count, dim = controls.shape
    low, high = controls.min(0), controls.max(0)
    scaled = (controls - (low + high) / 2) / ((high - low) / 2)
    columns = [np.ones(count)] + [
        np.prod(scaled[:, list(axes)], axis=1)
        for order in range(1, degree + 1)
        for axes in combinations_with_replacement(range(dim), order)
    ]
    polynomial = np.stack(columns, 1)
    size = count + polynomial.shape[1]
    matrix = np.zeros((size, size))
    matrix[:count, :count] = _phi(kernel, scale * cdist(controls, controls))
    matrix[:count, count:] = polynomial
    matrix[count:, :count] = polynomial.T
    norm = np.abs(matrix).sum(0).max()
    factor, _, info = lapack.dgetrf(matrix, overwrite_a=True)
    if info > 0:
        return math.inf
    reciprocal, _ = lapack.dgecon(factor, norm, norm="1")
    return math.inf if reciprocal == 0 else 1.0 / reciprocal


def load_pygem(path: str | None):
    """mathLab's ``pygem`` module, or None, and a note."""
    if path is not None:
        sys.path.insert(0, path)
    try:
        module = importlib.import_module("pygem")
    except Exception as error:  # noqa: BLE001 - an optional reference, any failure skips it
        return None, f"not available ({type(error).__name__}: {error})"
    if not (hasattr(module, "RBF") and hasattr(module, "FFD")):
        return None, f"{module.__file__} is not mathLab's PyGeM"
    return module, f"PyGeM from {os.path.dirname(module.__file__)}"


def load_scipy():
    try:
        import scipy
        from scipy.interpolate import RBFInterpolator
    except ImportError as error:
        return None, f"scipy not available ({error})"
    return RBFInterpolator, f"scipy {scipy.__version__}"


# ------------------------------------------------------------------------------ a case
@dataclass
class Row:
    case: str
    method: str
    options: str = ""
    fit: float | None = None
    morph: float | None = None
    quality: dict | None = None
    cond: float | None = None
    note: str = ""
    #: name -> (agreement, fit, per morph, note[, our fit, our per morph])
    references: dict = field(default_factory=dict)


@dataclass
class Case:
    """A paper case: its mesh, the moving body and the boundary displacement at μ*."""

    letter: str
    mesh: Mesh
    moving: Tensor  # global ids of the moving body's nodes
    boundary_displacement: Tensor  # (N_b, 3), rows as mesh.boundary_nodes
    displacement: Callable[[Tensor], Tensor]  # body points -> displacement

    @classmethod
    def load(cls, letter: str, size: str) -> Case:
        spec = get_case(letter)
        mesh = load_mesh(spec, size=size)
        moving = torch.unique(torch.cat([mesh.node_set(name) for name in spec.moving]))
        mu = torch.tensor(spec.mu_star, dtype=mesh.dtype)

        def displacement(points: Tensor) -> Tensor:
            return spec.displacement(points, mu)

        boundary = mesh.boundary_nodes
        values = torch.zeros(len(boundary), 3, dtype=mesh.dtype)
        rows = torch.searchsorted(boundary, moving)
        values[rows] = displacement(mesh.points[moving])
        return cls(letter, mesh, moving, values, displacement)

    @property
    def boundary_points(self) -> Tensor:
        return self.mesh.points[self.mesh.boundary_nodes]

    @property
    def interior_points(self) -> Tensor:
        return self.mesh.points[self.mesh.interior_nodes]


def seeded() -> torch.Generator:
    """The selection's randomness (ESIDW rows): seed 0, as the reproduction."""
    return torch.Generator().manual_seed(0)


def interior_of(morph: MeshMorph, displacement: Tensor) -> Tensor:
    return displacement[morph.interior_nodes]


def idw_row(case: Case, repeats: int, plan=None, label: str = "IDW") -> tuple[Row, Tensor]:
    morph, fit = measure(lambda: MeshMorph(case.mesh, plan, generator=seeded()), repeats)
    field_, per_morph = measure(lambda morph=morph: morph(case.boundary_displacement), repeats)
    options = "p = 4" + (f", {len(morph.selected):,} controls" if plan is not None else "")
    row = Row(case.letter, label, options, fit, per_morph, quality_summary(case.mesh, field_))
    return row, field_


def rbf_row(
    case: Case,
    kernel: str,
    options: dict,
    repeats: int,
    *,
    references: dict,
    cond_controls: int,
    pygem_targets: int,
    degree: int = 1,
    plan=None,
) -> Row:
    described = ", ".join(f"{k} = {v:.4g}" for k, v in options.items()) or "scale invariant"
    label = f"RBF {kernel}" + ("" if degree == 1 else f" (degree {degree})")
    row = Row(case.letter, label, described + f", degree {degree}")
    try:
        morph, fit = measure(
            lambda: MeshMorph(
                case.mesh,
                plan,
                method="rbf",
                kernel=kernel,
                degree=degree,
                generator=seeded(),
                **options,
            ),
            repeats,
        )
        field_, per_morph = measure(lambda morph=morph: morph(case.boundary_displacement), repeats)
    except (ValueError, RuntimeError, torch.linalg.LinAlgError) as error:
        row.note = f"fit failed: {type(error).__name__}: {error}"
        row.note += scipy_on_failure(case, kernel, options, degree, references.get("scipy"))
        if len(case.boundary_points) <= cond_controls:
            row.cond = condition_number(case.boundary_points.numpy(), kernel, options, degree)
        return row
    row.fit, row.morph = fit, per_morph
    row.quality = quality_summary(case.mesh, field_)
    if plan is not None:
        row.options += f", {len(morph.selected):,} controls"
        return row
    controls = case.boundary_points.numpy()
    if len(controls) <= cond_controls:
        row.cond = condition_number(controls, kernel, options, degree)
    ours = interior_of(morph, field_).numpy()
    scale = float(case.boundary_displacement.norm(dim=1).max())
    values = case.boundary_displacement.numpy()
    targets = case.interior_points.numpy()
    del morph
    interpolator = references.get("scipy")
    if interpolator is not None and kernel in SCIPY_KERNELS:
        scipy_options = {"epsilon": options["epsilon"]} if "epsilon" in options else {}
        fitted, fit = measure(
            lambda: interpolator(controls, values, kernel=kernel, degree=degree, **scipy_options),
            0,
        )
        moved, evaluation = measure(lambda: fitted(targets), 0)
        agreement = float(np.abs(moved - ours).max()) / scale
        row.references["scipy"] = (agreement, fit, fit + evaluation, "")
        del fitted
    pygem = references.get("pygem")
    if pygem is not None and degree == 1:  # PyGeM's polynomial is always linear
        name, extra = PYGEM_KERNELS[kernel]
        radius = options.get("support_radius", 1.0 / options.get("epsilon", 1.0))
        part = targets
        if len(targets) > pygem_targets and len(controls) > cond_controls:
            part = targets[:: math.ceil(len(targets) / pygem_targets)]

        def build():
            return pygem.RBF(
                controls, controls + values, func=name, radius=radius, extra_parameter=extra
            )

        fitted, fit = measure(build, 0)
        index = np.arange(len(targets))
        if len(part) < len(targets):
            # a call is compute_weights() (the fit again) and the evaluation: the
            # evaluation timed alone on the subsample, the call as fit + evaluation × N / n
            index = index[:: math.ceil(len(targets) / pygem_targets)]
            fitted.compute_weights = lambda: None
            moved, evaluation = measure(lambda: fitted(part) - part, 0)
            per_call = fit + evaluation * len(targets) / len(part)
            note = (
                f"a call (refit + evaluation) from the fit and the evaluation at {len(part):,} "
                f"nodes ({seconds(evaluation)}), extrapolated to {len(targets):,}"
            )
        else:
            moved, per_call = measure(lambda: fitted(part) - part, 0)
            note = ""
        agreement = float(np.abs(moved - ours[index]).max()) / scale
        row.references["PyGeM"] = (agreement, fit, per_call, note)
    return row


def scipy_on_failure(case: Case, kernel: str, options: dict, degree: int, interpolator) -> str:
    """What scipy's ``RBFInterpolator`` does with a system ours refused."""
    if interpolator is None or kernel not in SCIPY_KERNELS:
        return ""
    import warnings

    scipy_options = {"epsilon": options["epsilon"]} if "epsilon" in options else {}
    controls = case.boundary_points.numpy()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            fitted = interpolator(
                controls,
                case.boundary_displacement.numpy(),
                kernel=kernel,
                degree=degree,
                **scipy_options,
            )
        except Exception as error:  # noqa: BLE001 - reported, whatever it is
            return f"; scipy: {type(error).__name__}: {error}"
    moved = fitted(case.interior_points.numpy())
    warned = "; ".join(str(w.message).split(".")[0] for w in caught)
    return (
        f"; scipy fits it{' (' + warned + ')' if warned else ''}, interior displacement up "
        f"to {np.abs(moved).max():.2g} (boundary's max {case.boundary_displacement.abs().max():.2g})"
    )


def lattice_matrix(ffd: FFD) -> Tensor:
    """(N, n_lattice) matrix of the tensor-product bases: the FFD's map from the lattice
    displacements (flattened, one component) to the displacements of its points."""
    bases = ffd.bases
    product = bases[0]
    for basis in bases[1:]:
        product = (product[:, :, None] * basis[:, None, :]).reshape(product.shape[0], -1)
    matrix = product.new_zeros(ffd.num_points, product.shape[1])
    matrix[ffd.inside] = product
    return matrix


def fit_lattice(ffd: FFD, target: Tensor, free: Tensor | None = None) -> Tensor:
    """Lattice displacements (n_1, n_2, n_3, 3) whose FFD of the module's points best
    fits ``target`` (N, 3) in least squares; only the ``free`` control points (a mask
    over the lattice) move."""
    matrix = lattice_matrix(ffd)
    columns = torch.arange(matrix.shape[1]) if free is None else free.reshape(-1).nonzero()[:, 0]
    solution = torch.linalg.lstsq(matrix[:, columns], target, driver="gelsd").solution
    lattice = target.new_zeros(matrix.shape[1], 3)
    lattice[columns] = solution
    return lattice.reshape(*ffd.shape, 3)


def body_box(case: Case, margin: float, *, clip: bool) -> tuple[Tensor, Tensor]:
    """(origin, lengths) of the body's bounding box widened by ``margin`` × its largest
    extent on each side (at least 2 % of each extent, so that no node lies on a face of
    the box, where rounding decides whether PyGeM counts it inside), clipped to the
    mesh's box if ``clip``."""
    body = case.mesh.points[case.moving]
    low, high = body.min(0).values, body.max(0).values
    pad = torch.maximum(margin * (high - low).max(), 0.02 * (high - low))
    low, high = low - pad, high + pad
    if clip:
        low = torch.maximum(low, case.mesh.points.min(0).values)
        high = torch.minimum(high, case.mesh.points.max(0).values)
    return low, high - low


def ffd_rows(case: Case, repeats: int, pygem) -> list[Row]:
    rows = []
    mesh, boundary = case.mesh, case.mesh.boundary_nodes
    body = mesh.points[case.moving]
    target = case.displacement(body)
    scale = float(target.norm(dim=1).max())
    moving_rows = torch.searchsorted(boundary, case.moving)
    origin, lengths = body_box(case, 0.0, clip=False)

    # FFD -> IDW: the lattice moves the body, IDW the rest
    def fit():
        ffd = FFD(body, origin=origin, lengths=lengths, shape=(3, 3, 3))
        return ffd, fit_lattice(ffd, target)

    (ffd, lattice), fit_time = measure(fit, repeats)
    _, build_time = measure(
        lambda: FFD(body, origin=origin, lengths=lengths, shape=(3, 3, 3)), repeats
    )
    morph, idw_fit = measure(lambda: MeshMorph(mesh), repeats)

    def apply():
        values = case.boundary_displacement.new_zeros(case.boundary_displacement.shape)
        values[moving_rows] = ffd(lattice)
        return morph(values), values

    (field_, values), per_morph = measure(apply, repeats)
    residual = float((values[moving_rows] - target).norm(dim=1).max()) / scale
    row = Row(
        case.letter,
        "FFD → IDW",
        "Bernstein 3³ on the body's box, least squares; IDW p = 4",
        fit_time + idw_fit,
        per_morph,
        quality_summary(mesh, field_),
        note=f"fit residual {residual:.1e}",
    )
    if pygem is not None:
        reference = pygem.FFD([3, 3, 3])
        reference.box_origin, reference.box_length = origin.numpy(), lengths.numpy()
        reference.rot_angle = np.zeros(3)
        mu = (lattice / lengths).numpy()
        reference.array_mu_x, reference.array_mu_y, reference.array_mu_z = (
            mu[..., 0],
            mu[..., 1],
            mu[..., 2],
        )
        points = body.numpy()
        moved, call = measure(lambda: reference(points) - points, repeats)
        ours, ours_time = measure(lambda: ffd(lattice), repeats)
        agreement = float(np.abs(moved - ours.numpy()).max()) / scale
        row.references["PyGeM"] = (
            agreement,
            None,
            call,
            (
                f"the FFD of the body's {len(points):,} nodes alone (ours: the bases built, "
                "one forward)"
            ),
            build_time,
            ours_time,
        )
    rows.append(row)

    # FFD volume: the lattice moves the mesh, no IDW
    if case.letter == "A":
        shape, basis, free, description = (3, 3, 3), "bernstein", None, "Bernstein 3³, every node"
        box = (origin, lengths)
    else:
        shape, basis = (7, 7, 7), "bspline"
        free = torch.zeros(shape, dtype=torch.bool)
        free[1:-1, 1:-1, 1:-1] = True
        box = body_box(case, 0.5, clip=True)
        description = "cubic B-spline 7³ on the body's box + 0.5 × its size, faces fixed"

    def fit_volume():
        ffd = FFD(mesh.points, origin=box[0], lengths=box[1], shape=shape, basis=basis)
        on_body = FFD(body, origin=box[0], lengths=box[1], shape=shape, basis=basis)
        return ffd, fit_lattice(on_body, target, free)

    (ffd, lattice), fit_time = measure(fit_volume, repeats)
    field_, per_morph = measure(lambda: ffd(lattice), repeats)
    residual = float((field_[case.moving] - target).norm(dim=1).max()) / scale
    rows.append(
        Row(
            case.letter,
            "FFD volume",
            description,
            fit_time,
            per_morph,
            quality_summary(mesh, field_),
            note=(
                f"fit residual {residual:.1e}; {ffd.num_inside:,} nodes in the box, largest "
                f"displacement {float(field_.norm(dim=1).max()):.3g} (on the body {scale:.3g})"
            ),
        )
    )
    return rows


def compare_methods(
    letter: str,
    *,
    size: str = "paper",
    kernels=RBF_KERNELS,
    repeats: int = 3,
    references: dict | None = None,
    support_fraction: float = 0.25,
    shape_spacings: float = 1.0,
    dense_controls: int = 5000,
    cond_controls: int = 5000,
    pygem_targets: int = 2000,
    ffd: bool = True,
    esidw: bool = False,
    log=print,
) -> tuple[list[Row], dict]:
    """The rows of one case, and its facts (counts, scales, skipped kernels)."""
    references = references or {}
    case = Case.load(letter, size)
    diagonal, spacing = scales(case.mesh.points, case.boundary_points)
    facts = {
        "nodes": case.mesh.num_nodes,
        "cells": case.mesh.num_cells,
        "boundary": len(case.mesh.boundary_nodes),
        "interior": len(case.mesh.interior_nodes),
        "diagonal": diagonal,
        "spacing": spacing,
        "max_displacement": float(case.boundary_displacement.norm(dim=1).max()),
        "reference": quality_summary(case.mesh),
        "skipped": [],
    }
    rows = []
    row, _ = idw_row(case, repeats)
    rows.append(row)
    log(format_row(row))
    large = facts["boundary"] > dense_controls
    for kernel in kernels:
        if large and kernel not in LARGE_KERNELS:
            facts["skipped"].append(kernel)
            continue
        options = kernel_options(kernel, diagonal, spacing, support_fraction, shape_spacings)
        scoped = dict(references)
        if large and kernel != "thin_plate_spline":
            scoped.pop("pygem", None)
        for degree in (1, 2) if kernel == "quintic" else (1,):  # 2: quintic's minimum
            rows.append(
                rbf_row(
                    case,
                    kernel,
                    options,
                    repeats,
                    references=scoped,
                    cond_controls=cond_controls,
                    pygem_targets=pygem_targets,
                    degree=degree,
                )
            )
            log(format_row(rows[-1]))
    if ffd:
        for row in ffd_rows(case, repeats, references.get("pygem")):
            rows.append(row)
            log(format_row(row))
    if esidw:
        plan = get_case(letter).plan()
        row, _ = idw_row(case, repeats, plan, "ESIDW")
        rows.append(row)
        log(format_row(row))
        rows.append(
            rbf_row(
                case,
                "thin_plate_spline",
                {},
                repeats,
                references={},
                cond_controls=0,
                pygem_targets=pygem_targets,
                plan=plan,
            )
        )
        rows[-1].method = "ESIDW-selected RBF thin_plate_spline"
        log(format_row(rows[-1]))
    return rows, facts


# ------------------------------------------------------------------------------ tables
def format_row(row: Row) -> str:
    if row.quality is None:
        quality = "– | – | –"
    else:
        quality = (
            f"{row.quality['num_inverted']} | {row.quality['min_scaled_jacobian']:.3f} | "
            f"{row.quality['max_edge_ratio']:.2f}"
        )
    cond = "–" if row.cond is None else f"{row.cond:.1e}"
    return (
        f"| {row.case} | {row.method} | {row.options} | {seconds(row.fit)} | "
        f"{seconds(row.morph)} | {quality} | {cond} | {row.note} |"
    )


METHOD_HEADER = (
    "| case | method | options | fit | per morph | inverted | min scaled Jacobian | max Q | "
    "cond₁ | note |\n|---|---|---|---:|---:|---:|---:|---:|---:|---|"
)
REFERENCE_HEADER = (
    "| case | method | reference | max ‖Δ‖ / max ‖d‖ | reference fit | reference per morph | "
    "ours fit + morph | reference / ours (fit + morph) | reference per morph / ours per "
    "morph | note |\n|---|---|---|---:|---:|---:|---:|---:|---:|---|"
)


def reference_lines(rows: list[Row]) -> list[str]:
    lines = []
    for row in rows:
        for name, (agreement, fit, per_morph, note, *ours) in row.references.items():
            ours_fit, ours_morph = ours or (row.fit, row.morph)
            ours_total = None if ours_fit is None else ours_fit + (ours_morph or 0.0)
            lines.append(
                f"| {row.case} | {row.method} | {name} | {agreement:.1e} | {seconds(fit)} | "
                f"{seconds(per_morph)} | {seconds(ours_total)} | "
                f"{ratio(per_morph, ours_total)} | {ratio(per_morph, ours_morph)} | {note} |"
            )
    return lines


def shape_parameter_table(letters, size: str, factors=(1.0, 3.0, 10.0), limit: int = 5000):
    """Condition numbers of the shape-parameter kernels for ε = 1 / (f h)."""
    print("\n### Shape parameter: condition numbers (ε = 1 / (f · h))\n")
    print("| case | h | kernel | " + " | ".join(f"f = {f:g}" for f in factors) + " |")
    print("|---|---:|---|" + "---:|" * len(factors))
    for letter in letters:
        case = Case.load(letter, size)
        controls = case.boundary_points.numpy()
        if len(controls) > limit:
            print(f"| {letter} | | (N_c = {len(controls):,} > {limit:,}: not computed) |")
            continue
        _, spacing = scales(case.mesh.points, case.boundary_points)
        for kernel in SHAPE_KERNELS:
            values = [
                condition_number(controls, kernel, {"epsilon": 1 / (f * spacing)}) for f in factors
            ]
            print(
                f"| {letter} | {spacing:.4f} | {kernel} | "
                + " | ".join(f"{v:.1e}" for v in values)
                + " |"
            )


# ------------------------------------------------------------------------ rotation sweep
def rotation_sweep(size: str, step: float, support_fraction: float, shape_spacings: float):
    """First angle with an inverted cell for RBF kernels on large_motions.py's bodies."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import large_motions

    print(
        f"\n### Rotation sweep: first angle with an inverted cell (every {step:g}°, then "
        "bisection to 0.5°; one shot, every boundary node a control)\n"
    )
    try:
        bodies = large_motions.cases(size, step)
    except ImportError as error:  # the 2-D section is meshed with gmsh
        print(f"Skipped: {error}")
        return
    print("| body | " + " | ".join(["IDW p = 4", *SWEEP_KERNELS]) + " |")
    print("|---|" + "---:|" * (len(SWEEP_KERNELS) + 1))
    for case in bodies:
        morph = MeshMorph(case.mesh)
        controls = morph.points[morph.boundary_nodes]
        targets = morph.points[morph.interior_nodes]
        diagonal, spacing = scales(case.mesh.points, controls)

        def path(angle: float, case=case, morph=morph) -> Tensor:
            return morph.boundary_displacement(case.moving, lambda p: case.turn(p, angle))

        interpolants: dict[str, Callable[[Tensor], Tensor]] = {
            "IDW p = 4": lambda d, morph=morph: morph(d)
        }
        for kernel in SWEEP_KERNELS:
            options = kernel_options(kernel, diagonal, spacing, support_fraction, shape_spacings)
            rbf = RBF(controls, targets, kernel=kernel, degree=1, **options)
            interpolants[kernel] = lambda d, rbf=rbf, morph=morph: morph.assemble(d, rbf(d))
        cells = []
        for interpolate in interpolants.values():

            def folds(angle: float, interpolate=interpolate, morph=morph, path=path) -> bool:
                return morph.count_inverted(interpolate(path(angle))) > 0

            good, bad = 0.0, None
            for angle in case.angles:
                if folds(angle):
                    bad = angle
                    break
                good = angle
            if bad is None:
                cells.append(f"none to {case.angles[-1]:.0f}°")
                continue
            while bad - good > 0.5:
                middle = 0.5 * (good + bad)
                good, bad = (good, middle) if folds(middle) else (middle, bad)
            cells.append(f"{bad:.1f}°")
        print(f"| {case.name} | " + " | ".join(cells) + " |", flush=True)


# -------------------------------------------------------------------------------- main
def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["A", "B", "C"])
    parser.add_argument("--size", choices=("small", "paper"), default="paper")
    parser.add_argument("--kernels", nargs="+", default=list(RBF_KERNELS), choices=RBF_KERNELS)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--pygem", help="folder holding mathLab's pygem package")
    parser.add_argument("--support-fraction", type=float, default=0.25)
    parser.add_argument("--shape-spacings", type=float, default=1.0)
    parser.add_argument("--dense-controls", type=int, default=5000)
    parser.add_argument("--all-kernels", action="store_true")
    parser.add_argument("--cond-controls", type=int, default=5000)
    parser.add_argument("--pygem-targets", type=int, default=2000)
    parser.add_argument("--esidw", action="store_true", help="add ESIDW-selected rows")
    parser.add_argument("--no-ffd", action="store_true")
    parser.add_argument("--no-sweep", action="store_true")
    parser.add_argument("--sweep-step", type=float, default=5.0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        import numba

        numba.set_num_threads(1)
    except ImportError:
        pass
    references = {}
    interpolator, scipy_note = load_scipy()
    if interpolator is not None:
        references["scipy"] = interpolator
    pygem, pygem_note = load_pygem(args.pygem)
    if pygem is not None:
        references["pygem"] = pygem
    print(
        f"{datetime.date.today().isoformat()}; {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores shared; Python {platform.python_version()}, torch "
        f"{torch.__version__}, numpy {np.__version__}, {scipy_note}; {pygem_note}; one thread "
        f"(torch, numba, BLAS), float64, size {args.size}\n"
    )
    # numba's kernels loaded from its cache before anything is timed
    warm = torch.rand(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    RBF(warm[:30], warm[30:])(warm[:30])
    dense_controls = math.inf if args.all_kernels else args.dense_controls
    all_rows, facts = [], {}
    for letter in args.cases:
        rows, facts[letter] = compare_methods(
            letter,
            size=args.size,
            kernels=args.kernels,
            repeats=args.repeats,
            references=references,
            support_fraction=args.support_fraction,
            shape_spacings=args.shape_spacings,
            dense_controls=dense_controls,
            cond_controls=args.cond_controls,
            pygem_targets=args.pygem_targets,
            ffd=not args.no_ffd,
            esidw=args.esidw,
            log=lambda line: print(line, file=sys.stderr, flush=True),
        )
        all_rows += rows

    print("### The cases\n")
    print(
        "| case | nodes | cells | boundary (controls) | interior | max ‖d‖ | bbox diagonal | "
        "h (median control spacing) | reference min SJ / max Q |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for letter, fact in facts.items():
        print(
            f"| {letter} | {fact['nodes']:,} | {fact['cells']:,} | {fact['boundary']:,} | "
            f"{fact['interior']:,} | {fact['max_displacement']:.4g} | {fact['diagonal']:.3g} | "
            f"{fact['spacing']:.3g} | {fact['reference']['min_scaled_jacobian']:.3f} / "
            f"{fact['reference']['max_edge_ratio']:.2f} |"
        )
    print(
        f"\nRBF scales: Wendland C2 support radius {args.support_fraction:g} × the bounding-box "
        f"diagonal; gaussian, multiquadric, inverse multiquadric ε = 1 / "
        f"({args.shape_spacings:g} h).\n"
    )
    print("### Methods: time and mesh quality after the morph\n")
    print(METHOD_HEADER)
    print("\n".join(format_row(row) for row in all_rows))
    for letter, fact in facts.items():
        if fact["skipped"]:
            fits = [r.fit for r in all_rows if r.case == letter and r.method.startswith("RBF")]
            print(
                f"\nCase {letter}: {', '.join(fact['skipped'])} not fitted: "
                f"{fact['boundary']:,} controls, a dense O(N_c³) fit each "
                f"(measured here {', '.join(seconds(f) for f in fits if f)} for "
                f"{', '.join(k for k in args.kernels if k in LARGE_KERNELS)}); "
                "--all-kernels fits them."
            )
    print("\n### Agreement with scipy and PyGeM (same kernel, same clouds) and time ratios\n")
    lines = reference_lines(all_rows)
    if lines:
        print(REFERENCE_HEADER)
        print("\n".join(lines))
    print(f"\nscipy: {scipy_note}. PyGeM: {pygem_note}.")
    shape_parameter_table(args.cases, args.size, limit=args.cond_controls)
    if not args.no_sweep:
        rotation_sweep(args.size, args.sweep_step, args.support_fraction, args.shape_spacings)


if __name__ == "__main__":
    main()
