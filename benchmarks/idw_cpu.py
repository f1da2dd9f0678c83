"""Fused CPU IDW kernels (``torchmorph.idw.backends.numba.kernels``, numba) against a plain numba loop.

Prints three markdown tables (medians of repeats after a warm-up, all ratios taken
against a baseline measured in the same run):

1. matrix-free apply of one displacement field (K = 3 columns), Gpair/s, at the
   paper's case-B counts (21,910 targets × 14,126 controls) and at 5,000 × 10,000,
   float32 and float64, one thread and two: (a) the fused ``apply``, (b) a plain
   two-pass numba loop written below (nearest pass, then ratio weights against
   ``[d, 1]``; p = 4 written as a square) — the baseline, (c) today's torch
   matrix-free path ``torchmorph.idw.idw_apply``; plus the fused ``apply_transposed``
   (``Wᵀ g``) and ``nearest_squared`` beside scipy's KD-tree; and the float32 error of (a) in units of
   ``max |d|`` against a float64 brute force on a sample of targets;
2. dense assembly: the fused ``weights`` against ``torchmorph.idw.idw_weights``,
   GB/s of W written;
   and the dense apply of one field: torch's ``W @ d`` against the fused ``dense_apply``,
   GB/s of W read;
3. shared cores, two threads: each path timed quiet and with a competing busy
   process (a Python subprocess spinning, started before and killed after each
   timed block, bounded in time); the busy / quiet ratio. Includes a batch of 16
   displacements (48 columns): blocks of W times GEMM (the default) and the fused kernel,
   and a baseline that is not IDW (a plain torch GEMM), whose ratio is what the machine's
   scheduler gives any 2-thread computation beside the busy process in that run.

Point clouds: controls on a box's walls and on an inner thin ellipsoid, targets in
between (as in ``benchmarks/idw.py``), normalised to a unit bounding-box diagonal.
p = 4 throughout.

Usage: ``python benchmarks/idw_cpu.py [--repeats 5] [--sizes 0 1] [--tables 1 2 3]
[--shared-paths "48 columns"]``
"""

from __future__ import annotations

import argparse
import contextlib
import platform
import subprocess
import sys
import time
from functools import partial

import numba
import numpy as np
import torch
from _timing import median_time, seconds
from idw import point_clouds as idw_point_clouds
from numba import njit, prange

from torchmorph.idw import idw_apply, idw_weights
from torchmorph.idw._dispatch import _NumbaBackend
from torchmorph.idw.backends.numba import kernels

SIZES = [(21910, 14126), (5000, 10000)]  # (N_t, N_c): case-B counts, and a rounder one
POWER = 4.0


@njit(parallel=True, cache=True, fastmath=True)
def two_pass_loop(targets, controls, values, out):
    """The baseline, as a user would write it for 3-D points, one field and p = 4: per
    target a nearest pass, then ratio weights accumulated against [d, 1]."""
    tiny = np.finfo(targets.dtype).tiny
    for i in prange(targets.shape[0]):
        x, y, z = targets[i, 0], targets[i, 1], targets[i, 2]
        nearest = np.inf
        for k in range(controls.shape[0]):
            dx, dy, dz = x - controls[k, 0], y - controls[k, 1], z - controls[k, 2]
            nearest = min(nearest, dx * dx + dy * dy + dz * dz)
        nearest = max(nearest, tiny)
        total = sum_x = sum_y = sum_z = 0.0
        for k in range(controls.shape[0]):
            dx, dy, dz = x - controls[k, 0], y - controls[k, 1], z - controls[k, 2]
            ratio = nearest / max(dx * dx + dy * dy + dz * dz, tiny)
            ratio = ratio * ratio
            total += ratio
            sum_x += ratio * values[k, 0]
            sum_y += ratio * values[k, 1]
            sum_z += ratio * values[k, 2]
        out[i, 0], out[i, 1], out[i, 2] = sum_x / total, sum_y / total, sum_z / total


def nearest_then_apply(targets, controls, values):
    """The fused matrix-free path as a caller runs it: nearest pass, then apply."""
    return kernels.apply(
        targets, controls, values, POWER, 0.0, kernels.nearest_squared(targets, controls)
    )


def kdtree_nearest(targets, controls, workers):
    """The alternative for the nearest pass: scipy's KD-tree, then d² recomputed."""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(controls.numpy()).query(targets.numpy(), k=1, workers=workers)
    return (targets - controls[torch.from_numpy(nearest)]).square().sum(1)


def point_clouds(n_targets: int, n_controls: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """benchmarks/idw.py's clouds (controls on a box's walls and an inner ellipsoid, targets
    in between), scaled to a unit diagonal."""
    targets, controls = idw_point_clouds(n_targets, n_controls, seed)
    both = np.concatenate([targets, controls])
    low, diagonal = both.min(0), np.linalg.norm(both.max(0) - both.min(0))
    return (targets - low) / diagonal, (controls - low) / diagonal


@contextlib.contextmanager
def threads(count: int):
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@contextlib.contextmanager
def busy_process(limit_s: float = 300.0):
    """A competing process spinning in pure Python for the block's duration (at most limit_s)."""
    spinner = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import time\nend = time.time() + {limit_s}\nwhile time.time() < end:\n    pass",
        ]
    )
    time.sleep(0.2)  # let it reach its loop
    try:
        yield
    finally:
        spinner.kill()
        spinner.wait()


def reference_error(targets, controls, values, out, sample: int = 256) -> float:
    """max |out - W d| / max |d| on ``sample`` targets, W from a float64 brute force."""
    rows = np.linspace(0, targets.shape[0] - 1, sample).astype(int)
    t = targets[rows].double()
    d2 = (t[:, None, :] - controls.double()[None]).square().sum(-1)
    ratio = (d2.amin(1, keepdim=True) / d2).square()
    exact = (ratio / ratio.sum(1, keepdim=True)) @ values.double()
    return float((out[rows].double() - exact).abs().max() / values.double().abs().max())


def problem(size, dtype):
    targets_np, controls_np = point_clouds(*size)
    values_np = np.random.default_rng(1).normal(size=(controls_np.shape[0], 3))
    return (
        torch.from_numpy(targets_np).to(dtype),
        torch.from_numpy(controls_np).to(dtype),
        torch.from_numpy(values_np).to(dtype),
    )


def matrix_free_table(sizes, repeats) -> None:
    print("\n## Matrix-free apply, one displacement field (K = 3), p = 4\n")
    print(
        "| N_t × N_c | dtype | threads | path | time | Gpair/s | vs two-pass loop |"
        " float32 error / max|d| |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for size in sizes:
        pairs = size[0] * size[1]
        for dtype in (torch.float32, torch.float64):
            targets, controls, values = problem(size, dtype)
            nearest2 = kernels.nearest_squared(targets, controls)
            radius2 = 0.0
            grad = torch.randn(
                targets.shape[0], 3, dtype=dtype, generator=torch.Generator().manual_seed(2)
            )
            out = torch.empty(targets.shape[0], 3, dtype=dtype)
            t_np, c_np, v_np, o_np = targets.numpy(), controls.numpy(), values.numpy(), out.numpy()
            _, sums = kernels.apply(targets, controls, values, POWER, radius2, nearest2)
            for count in (1, 2):
                with threads(count):
                    numba.set_num_threads(count)
                    baseline = median_time(partial(two_pass_loop, t_np, c_np, v_np, o_np), repeats)
                    paths = {
                        "fused apply (nearest given)": partial(
                            kernels.apply, targets, controls, values, POWER, radius2, nearest2
                        ),
                        "fused nearest + apply": partial(
                            nearest_then_apply, targets, controls, values
                        ),
                        "two-pass numba loop": None,
                        "fused nearest_squared": partial(
                            kernels.nearest_squared, targets, controls
                        ),
                        "KD-tree nearest (scipy, workers=threads)": partial(
                            kdtree_nearest, targets, controls, count
                        ),
                        "fused apply_transposed": partial(
                            kernels.apply_transposed,
                            targets,
                            controls,
                            grad,
                            POWER,
                            radius2,
                            nearest2,
                            sums,
                        ),
                        "torch idw_apply": partial(
                            idw_apply,
                            controls=controls,
                            targets=targets,
                            displacements=values,
                            power=POWER,
                            implementation="torch",
                        ),
                    }
                    for name, function in paths.items():
                        elapsed = (
                            baseline
                            if function is None
                            else median_time(
                                function, max(1, repeats // 2) if "torch" in name else repeats
                            )
                        )
                        error = ""
                        if dtype == torch.float32 and name == "fused apply (nearest given)":
                            result, _ = function()
                            error = f"{reference_error(targets, controls, values, result):.1e}"
                        print(
                            f"| {size[0]:,} × {size[1]:,} | {str(dtype)[6:]} | {count} | "
                            f"{name} | {seconds(elapsed)} | {pairs / elapsed / 1e9:.2f} | "
                            f"{baseline / elapsed:.2f}× | {error} |",
                            flush=True,
                        )


def dense_table(sizes, repeats) -> None:
    print("\n## Dense W, p = 4: assembly (GB/s written) and apply of one field (GB/s read)\n")
    print("| N_t × N_c | dtype | threads | path | time | GB/s | vs torch |")
    print("|---|---|---|---|---|---|---|")
    for size in sizes:
        for dtype in (torch.float32, torch.float64):
            targets, controls, values = problem(size, dtype)
            size_gb = size[0] * size[1] * targets.element_size() / 1e9
            out = torch.empty(size, dtype=dtype)
            dense = kernels.weights(targets, controls, POWER, 0.0)
            for count in (1, 2):
                with threads(count):
                    build = median_time(
                        partial(
                            idw_weights,
                            controls=controls,
                            targets=targets,
                            power=POWER,
                            implementation="torch",
                        ),
                        max(1, repeats // 2),
                    )
                    apply = median_time(partial(torch.matmul, dense, values), repeats)
                    rows = (
                        ("build, torch idw_weights", build, build),
                        (
                            "build, fused weights (into out)",
                            median_time(
                                partial(kernels.weights, targets, controls, POWER, 0.0, out=out),
                                repeats,
                            ),
                            build,
                        ),
                        ("apply, torch W @ d", apply, apply),
                        (
                            "apply, fused dense_apply",
                            median_time(partial(kernels.dense_apply, dense, values), repeats),
                            apply,
                        ),
                    )
                    for name, elapsed, reference in rows:
                        print(
                            f"| {size[0]:,} × {size[1]:,} | {str(dtype)[6:]} | {count} | "
                            f"{name} | {seconds(elapsed)} | {size_gb / elapsed:.1f} | "
                            f"{reference / elapsed:.2f}× |",
                            flush=True,
                        )


def shared_table(size, repeats, only: str = "") -> None:
    print(
        f"\n## Shared cores: 2 threads, quiet and beside a busy process, "
        f"{size[0]:,} × {size[1]:,}, p = 4\n"
    )
    print("| dtype | path | quiet | busy | busy / quiet |")
    print("|---|---|---|---|---|")
    for dtype in (torch.float32, torch.float64):
        targets, controls, values = problem(size, dtype)
        nearest2 = kernels.nearest_squared(targets, controls)
        _, sums = kernels.apply(targets, controls, values, POWER, 0.0, nearest2)
        dense = kernels.weights(targets, controls, POWER, 0.0)
        out = torch.empty_like(dense)
        grad = torch.randn(
            targets.shape[0], 3, dtype=dtype, generator=torch.Generator().manual_seed(2)
        )
        batch = torch.randn(  # a batch of 16 displacements: 48 value columns
            controls.shape[0], 48, dtype=dtype, generator=torch.Generator().manual_seed(3)
        )
        square = torch.rand(768, 768, dtype=dtype, generator=torch.Generator().manual_seed(4))
        paths = {
            # not IDW: what the machine itself allows a 2-thread computation beside the
            # busy process (a GEMM split statically between the threads)
            "baseline: a plain torch GEMM (768², no IDW)": partial(torch.mm, square, square),
            "dense build, fused weights": partial(
                kernels.weights, targets, controls, POWER, 0.0, out=out
            ),
            "dense build, torch idw_weights": partial(
                idw_weights, controls=controls, targets=targets, power=POWER, implementation="torch"
            ),
            "dense apply, torch W @ d": partial(torch.matmul, dense, values),
            "dense apply, fused dense_apply": partial(kernels.dense_apply, dense, values),
            "matrix-free, fused nearest + apply": partial(
                nearest_then_apply, targets, controls, values
            ),
            "matrix-free, fused apply_transposed": partial(
                kernels.apply_transposed, targets, controls, grad, POWER, 0.0, nearest2, sums
            ),
            "matrix-free, 48 columns, blocks of W and GEMM (the default)": partial(
                _NumbaBackend().apply, targets, controls, batch, POWER, 0.0, None
            ),
            "matrix-free, 48 columns, fused kernel": partial(
                kernels.apply, targets, controls, batch, POWER, 0.0, nearest2
            ),
            "matrix-free, torch idw_apply": partial(
                idw_apply,
                controls=controls,
                targets=targets,
                displacements=values,
                power=POWER,
                implementation="torch",
            ),
        }
        with threads(2):
            for name, function in paths.items():
                if only not in name:
                    continue
                reps = max(1, repeats // 2) if "torch idw" in name else repeats
                quiet = median_time(function, reps)
                with busy_process():
                    busy = median_time(function, reps)
                print(
                    f"| {str(dtype)[6:]} | {name} | {seconds(quiet)} | {seconds(busy)} | "
                    f"{busy / quiet:.2f}× |",
                    flush=True,
                )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="*",
        default=[0, 1],
        help="indices into SIZES (0: case-B counts, 1: 5,000 × 10,000)",
    )
    parser.add_argument("--tables", type=int, nargs="*", default=[1, 2, 3])
    parser.add_argument("--shared-size", type=int, default=1, help="index into SIZES")
    parser.add_argument(
        "--shared-paths", default="", help="only the shared-core paths whose name holds this"
    )
    args = parser.parse_args(argv)
    if not kernels.available():
        sys.exit("numba is not installed: pip install numba")
    kernels.nearest_squared(torch.zeros(1, 3), torch.zeros(1, 3))  # starts numba's threads
    print(
        f"# Fused CPU IDW kernels: {platform.processor() or platform.machine()}, "
        f"torch {torch.__version__}, numba {numba.__version__} "
        f"(threading layer {numba.threading_layer()}),"
        f" numpy {np.__version__}; median of {args.repeats} repeats after a warm-up"
    )
    sizes = [SIZES[i] for i in args.sizes]
    if 1 in args.tables:
        matrix_free_table(sizes, args.repeats)
    if 2 in args.tables:
        dense_table(sizes, args.repeats)
    if 3 in args.tables:
        shared_table(SIZES[args.shared_size], args.repeats, args.shared_paths)


if __name__ == "__main__":
    main()
