"""RBF morphing at scale: the partition-of-unity RBF (:class:`torchmorph.rbf.PartitionRBF`)
against the global dense fit (:class:`torchmorph.rbf.RBF`), and at 10⁵ controls × 10⁶
targets alone.

Two threads (torch and numba; scipy's OpenBLAS one), float64; thin-plate spline with the linear
polynomial (``degree=1``). The case: a wing-like body (the ellipsoid x²/1 + y²/0.12² +
z²/3² = 1, its surface a Fibonacci lattice stretched onto it) inside a box of outer
walls [-3, 3] × [-2, 2] × [-5, 5] (uniform random points on its faces, a quarter of the
controls); targets uniform in the box outside the body (the volume mesh). The body
bends (y += 0.3 (z/3)²) and twists about the span (10° at the tips, growing linearly
along z); the walls do not move.

Printed (markdown):

(a) for each control count of ``--compare`` (default 10⁴ and 3·10⁴; ``--compare-targets``
targets, default 10⁵): the fit and one morph of the global dense fit and of the
partition of unity for each ``--coarse`` size (default 3,000 and 6,000), then of its
global fit to each of ``--tolerances`` (``PartitionRBF(tolerance=...)``, the last
``--coarse`` size), the ratios, and the relative 2-norm error ‖u − u_global‖ /
‖u_global‖ over all targets;

(b) ``--controls`` × ``--targets`` (default 10⁵ × 10⁶; the last ``--coarse`` size; the
global fit to the first of ``--tolerances`` if any): the fit, the first morph and the
median of ``--repeats`` later morphs, the process's peak resident memory
(``ru_maxrss``) and the size of its state;

(c) with ``--sparse RADIUS ...`` (alone): :class:`torchmorph.rbf.SparseRBF` with
Wendland's C2 at those support radii, against the dense global fit with the same kernel
and radius at the ``--compare`` counts up to 10⁴, then at ``--controls`` × ``--targets``
(fit, first and later morphs, peak memory, state, and the share of the targets within
the support radius of a control, the others moving by the polynomial tail alone).

numba's kernels are loaded from its cache by a tiny morph before the timings.

Run ``python benchmarks/rbf_scale.py`` (about 15 minutes on two cores, most of it the
global fit at 3·10⁴ controls: 7 GB of kernel matrix) or ``--compare`` with smaller counts.
"""

from __future__ import annotations

import os

THREADS = 2
for _variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_variable] = str(THREADS)  # before numpy, scipy and numba load
# scipy's OpenBLAS (the Cholesky factorisations) on one thread: the patches' small
# factorisations lose far more to a descheduled second thread than they gain
os.environ["OPENBLAS_NUM_THREADS"] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _timing import median_time, seconds  # noqa: E402

from torchmorph.rbf import RBF, PartitionRBF, SparseRBF  # noqa: E402

SEMI_AXES = np.array([1.0, 0.12, 3.0])
BOX = np.array([3.0, 2.0, 5.0])


def body(count: int) -> np.ndarray:
    """``count`` points on the wing-like ellipsoid (a stretched Fibonacci lattice)."""
    index = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * index / count)
    azimuth = math.pi * (1 + 5**0.5) * index
    unit = np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
    )
    return unit * SEMI_AXES


def walls(count: int, seed: int = 1) -> np.ndarray:
    """``count`` points uniform on the faces of the box [-BOX, BOX]."""
    rng = np.random.default_rng(seed)
    areas = np.array([BOX[1] * BOX[2], BOX[0] * BOX[2], BOX[0] * BOX[1]])
    axis = rng.choice(3, size=count, p=areas / areas.sum())
    points = rng.uniform(-1, 1, size=(count, 3)) * BOX
    side = rng.choice([-1.0, 1.0], size=count)
    points[np.arange(count), axis] = side * BOX[axis]
    return points


def volume(count: int, seed: int = 2) -> np.ndarray:
    """``count`` points uniform in the box outside the body (scaled by 1.02)."""
    rng = np.random.default_rng(seed)
    found, total = [], 0
    while total < count:
        points = rng.uniform(-1, 1, size=(2 * count, 3)) * BOX
        outside = points[(((points / SEMI_AXES) ** 2).sum(axis=1)) > 1.02**2]
        found.append(outside)
        total += outside.shape[0]
    return np.concatenate(found)[:count]


def case(controls: int, targets: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(controls, targets, displacements): a quarter of the controls on the walls."""
    on_walls = controls // 4
    surface = body(controls - on_walls)
    span = surface[:, 2] / SEMI_AXES[2]
    angle = math.radians(10.0) * span
    moved = surface.copy()
    moved[:, 0] = np.cos(angle) * surface[:, 0] - np.sin(angle) * surface[:, 1]
    moved[:, 1] = np.sin(angle) * surface[:, 0] + np.cos(angle) * surface[:, 1]
    moved[:, 1] += 0.3 * span**2
    wall_points = walls(on_walls)
    points = np.concatenate([surface, wall_points])
    values = np.concatenate([moved - surface, np.zeros_like(wall_points)])
    return tuple(torch.from_numpy(a) for a in (points, volume(targets), values))  # type: ignore[return-value]


def peak_memory_gb() -> float:
    """The process's peak resident memory (``ru_maxrss``, KiB on Linux), GB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def timed(function):
    start = time.perf_counter()
    result = function()
    return result, time.perf_counter() - start


def compare(
    counts, targets: int, coarse_sizes, patch_size: int, overlap: float, tolerances
) -> None:
    print(
        f"(a) Against the global fit, {targets:,} targets, patch_size={patch_size}, "
        f"overlap={overlap:g}\n"
    )
    print(
        "| controls | solver | fit | one morph | fit + morph | ratio to global | error vs global |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|")
    for count in counts:
        points, volume_points, values = case(count, targets)
        dense, fit = timed(lambda: RBF(points, volume_points, mode="matrix_free"))
        reference, morph = timed(lambda dense=dense: dense(values))
        del dense
        total = fit + morph
        print(
            f"| {count:,} | global dense | {seconds(fit)} | "
            f"{seconds(morph)} | {seconds(total)} | 1 | — |"
        )
        runs = [(coarse, None) for coarse in coarse_sizes]
        runs += [(coarse_sizes[-1], tolerance) for tolerance in tolerances]
        for coarse, tolerance in runs:
            module, fit = timed(
                lambda coarse=coarse, tolerance=tolerance: PartitionRBF(
                    points,
                    volume_points,
                    patch_size=patch_size,
                    overlap=overlap,
                    coarse_size=coarse,
                    tolerance=tolerance,
                )
            )
            result, morph = timed(lambda module=module: module(values))
            error = float((result - reference).norm() / reference.norm())
            refined = (
                "" if tolerance is None
                else f", global to {tolerance:g} ({module.last_iterations_} iterations)"
            )  # fmt: skip
            print(
                f"| {count:,} | partition, coarse {coarse:,}, {module.num_patches} patches"
                f"{refined} | "
                f"{seconds(fit)} | {seconds(morph)} | {seconds(fit + morph)} | "
                f"{(fit + morph) / total:.3f} | {error:.1e} |"
            )
            del module
        print("", flush=True)


def large(
    controls: int, targets: int, coarse: int, patch_size: int, overlap: float, repeats, tolerance
):
    points, volume_points, values = case(controls, targets)
    before = peak_memory_gb()
    module, fit = timed(
        lambda: PartitionRBF(
            points,
            volume_points,
            patch_size=patch_size,
            overlap=overlap,
            coarse_size=coarse,
            tolerance=tolerance,
        )
    )
    _, first = timed(lambda: module(values))
    later = median_time(lambda: module(values), repeats, warmup=0)
    state = sum(
        t.numel() * t.element_size()
        for t in module.state_dict().values()
        if t is not None and hasattr(t, "numel")
    )
    print(
        f"(b) {controls:,} controls x {targets:,} targets, coarse {coarse:,}, "
        f"patch_size={patch_size}, overlap={overlap:g}, {module.num_patches} patches"
        + ("" if tolerance is None else f", global fit to {tolerance:g} "
           f"({module.last_iterations_} iterations)")
        + "\n"
    )  # fmt: skip
    print("| fit | first morph | fit + first morph | later morph (median) | peak memory | state |")
    print("|---:|---:|---:|---:|---:|---:|")
    print(
        f"| {seconds(fit)} | {seconds(first)} | {seconds(fit + first)} | {seconds(later)} | "
        f"{peak_memory_gb():.2f} GB (inputs: {before:.2f} GB) | {state / 1e9:.2f} GB |"
    )


def sparse(radii, counts, compare_targets: int, controls: int, targets: int, repeats) -> None:
    """(c) :class:`SparseRBF` (Wendland C2, degree 1): the error against the dense global
    fit with the same kernel and radius, then ``controls`` x ``targets``."""
    print(
        f"(c) SparseRBF, wendland_c2, against the dense global fit, {compare_targets:,} targets\n"
    )
    print("| controls | support radius | neighbours per control | global dense fit + morph "
          "| sparse fit + morph | error vs global |")  # fmt: skip
    print("|---:|---:|---:|---:|---:|---:|")
    for count in counts:
        points, volume_points, values = case(count, compare_targets)
        for radius in radii:
            options = {"kernel": "wendland_c2", "support_radius": radius}
            dense, fit = timed(lambda: RBF(points, volume_points, mode="matrix_free", **options))
            reference, morph = timed(lambda dense=dense: dense(values))
            del dense
            module, sparse_fit = timed(lambda: SparseRBF(points, volume_points, **options))
            result, sparse_morph = timed(lambda module=module: module(values))
            error = float((result - reference).norm() / reference.norm())
            print(
                f"| {count:,} | {radius:g} | {module.kernel_columns.shape[0] / count:.0f} | "
                f"{seconds(fit + morph)} | {seconds(sparse_fit + sparse_morph)} | {error:.1e} |",
                flush=True,
            )
    if not controls:
        return
    print(f"\n{controls:,} controls x {targets:,} targets\n")
    print("| support radius | neighbours per control | targets within the support | fit "
          "| first morph | later morph (median) | peak memory | state |")  # fmt: skip
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    points, volume_points, values = case(controls, targets)
    for radius in radii:
        module, fit = timed(
            lambda radius=radius: SparseRBF(
                points, volume_points, kernel="wendland_c2", support_radius=radius
            )
        )
        _, first = timed(lambda module=module: module(values))
        later = median_time(lambda module=module: module(values), repeats, warmup=0)
        reached = float((module.eval_indptr.diff() > 0).double().mean())
        state = sum(t.numel() * t.element_size() for t in module.state_dict().values()
                    if isinstance(t, torch.Tensor))  # fmt: skip
        print(
            f"| {radius:g} | {module.kernel_columns.shape[0] / controls:.0f} | {reached:.1%} | "
            f"{seconds(fit)} | {seconds(first)} | {seconds(later)} | "
            f"{peak_memory_gb():.2f} GB | {state / 1e9:.2f} GB |",
            flush=True,
        )
        del module


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--compare", type=int, nargs="*", default=[10_000, 30_000])
    parser.add_argument("--compare-targets", type=int, default=100_000)
    parser.add_argument("--coarse", type=int, nargs="*", default=[3000, 6000])
    parser.add_argument("--controls", type=int, default=100_000)
    parser.add_argument("--targets", type=int, default=1_000_000)
    parser.add_argument("--patch-size", type=int, default=100)
    parser.add_argument("--overlap", type=float, default=1.5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--tolerances",
        type=float,
        nargs="*",
        default=[],
        metavar="TOL",
        help="(a): rows of the global fit to these tolerances (PartitionRBF(tolerance=...), "
        "the last --coarse); (b): the first of them",
    )
    parser.add_argument(
        "--sparse",
        type=float,
        nargs="*",
        default=None,
        metavar="RADIUS",
        help="run (c) alone: SparseRBF (wendland_c2) at these support radii",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(THREADS)
    kernel = "wendland_c2" if args.sparse else "thin_plate_spline"
    print(
        f"{platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{THREADS} threads, float64, {kernel}, degree=1\n"
    )
    warm = case(40, 10)
    PartitionRBF(warm[0], warm[1], patch_size=8, coarse_size=10)(warm[2])
    RBF(warm[0], warm[1])(warm[2])
    if args.sparse:
        SparseRBF(warm[0], warm[1], support_radius=1.0)(warm[2])
        compared = [count for count in args.compare if count <= 10_000]
        sparse(args.sparse, compared, args.compare_targets, args.controls, args.targets,
               args.repeats)  # fmt: skip
        return
    if args.compare:
        compare(args.compare, args.compare_targets, args.coarse, args.patch_size, args.overlap,
                args.tolerances)  # fmt: skip
    if args.controls:
        large(
            args.controls,
            args.targets,
            args.coarse[-1],
            args.patch_size,
            args.overlap,
            args.repeats,
            args.tolerances[0] if args.tolerances else None,
        )


if __name__ == "__main__":
    main()
