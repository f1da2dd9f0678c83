"""IDW assembly and apply times, dense and matrix-free, against a NumPy baseline.

Prints a markdown table: for each problem size (N_t targets, N_c controls) of the
paper's three cases, each dtype and mode, the median time (after a warm-up) of

- ``build+morph``: assemble (dense: store W) and morph one displacement field;
- ``morph B=1/10/100``: one more morph of a batch of B fields (dense: stored W;
  matrix-free: recomputed weights);
- ``peak MB``: peak resident memory above the process's baseline (inputs made),
  measured in a fresh child process per configuration, over all its calls;
- ``B=1 apply MB`` (matrix-free): the peak of one single-field apply, measured
  first in that process: the tile budget plus O(N_t + N_c) vectors;

and the same for a plain NumPy dense implementation (cdist, power, normalise,
matmul) with the ratio NumPy / torch. The point clouds are synthetic: controls
on the surface of an ellipsoid inside a box, targets in the volume between,
sized like the paper's meshes.

Usage: ``python benchmarks/idw.py [--sizes 0 1 2] [--repeats 5] [--batches 1 10 100]``

``--kernels`` prints instead the kernel table of ``benchmarks/gpu.py`` on the CPU: at
case-B counts (controls on a sphere, targets inside), float32 and float64, the fused
(numba) paths beside the torch implementation and the naive ``torch.cdist`` code, with
Gpair/s or GB/s, the fraction of the CPU's floor and the error against a float64
reference, in one run (``--threads`` sets torch's thread count; default 1).
``benchmarks/idw_cpu.py`` compares the fused CPU kernels with a plain two-pass numba
loop and measures them beside a competing busy process.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import platform
import resource

import numpy as np
import scipy.spatial  # noqa: F401  (imported before any memory baseline is taken)
import torch
from _timing import median_time

from torchmorph.idw import IDW, idw_apply

SIZES = [  # (N_t, N_c): the paper's cases A, C, B
    (797, 1666),
    (3322, 3864),
    (21910, 14126),
]


def point_clouds(n_targets: int, n_controls: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Controls on a box's walls and an inner ellipsoid; targets in between."""
    rng = np.random.default_rng(seed)
    n_body = n_controls // 2
    directions = rng.normal(size=(n_body, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    body = directions * np.array([0.5, 0.06, 3.0])
    n_wall = n_controls - n_body
    walls = rng.uniform(-1, 1, size=(n_wall, 3))
    face = rng.integers(0, 3, n_wall)
    walls[np.arange(n_wall), face] = np.sign(rng.uniform(-1, 1, n_wall))
    walls *= np.array([5.0, 2.5, 6.3])
    controls = np.concatenate([body, walls])
    targets = rng.uniform(-1, 1, size=(4 * n_targets, 3)) * np.array([5.0, 2.5, 6.3])
    outside = ((targets / np.array([0.5, 0.06, 3.0])) ** 2).sum(1) > 1.05
    return targets[outside][:n_targets], controls


def numpy_dense(targets, controls, displacements):
    """The plain baseline: cdist, power, normalise, matmul."""
    from scipy.spatial.distance import cdist

    inverse = cdist(targets, controls) ** -4.0
    inverse /= inverse.sum(1, keepdims=True)
    return inverse @ displacements


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_config(args) -> dict:
    """One configuration, in a fresh process so that peak memory is its own."""
    size, dtype_name, mode, batches, repeats, block_bytes = args
    torch.set_num_threads(torch.get_num_threads())
    n_targets, n_controls = size
    targets_np, controls_np = point_clouds(n_targets, n_controls)
    rng = np.random.default_rng(1)
    fields = {b: rng.normal(size=(b, n_controls, 3)) for b in batches}
    result = {"size": size, "dtype": dtype_name, "mode": mode}
    baseline = peak_rss_mb()
    if mode == "numpy":
        dtype = np.float64 if dtype_name == "float64" else np.float32
        targets, controls = targets_np.astype(dtype), controls_np.astype(dtype)
        single = fields[batches[0]][0].astype(dtype)
        result["build+morph"] = median_time(lambda: numpy_dense(targets, controls, single), repeats)
        result["peak MB"] = peak_rss_mb() - baseline
        return result
    dtype = getattr(torch, dtype_name)
    targets = torch.from_numpy(targets_np).to(dtype)
    controls = torch.from_numpy(controls_np).to(dtype)
    single = torch.from_numpy(fields[batches[0]][0]).to(dtype)
    with torch.no_grad():
        if mode == "matrix_free":  # first, so the process's peak is this apply's
            before = peak_rss_mb()
            idw_apply(
                controls=controls, targets=targets, displacements=single, block_bytes=block_bytes
            )
            result["apply MB"] = peak_rss_mb() - before

        def build_and_morph():
            return IDW(controls, targets, mode=mode, block_bytes=block_bytes)(single)

        result["build+morph"] = median_time(build_and_morph, max(1, repeats // 2))
        morph = IDW(controls, targets, mode=mode, block_bytes=block_bytes)
        result["assembly"] = morph.assembly_time
        for batch in batches:
            field = torch.from_numpy(fields[batch]).to(dtype)
            if batch == 1:
                field = field[0]
            reps = repeats if (batch < 100 or mode == "dense") else max(1, repeats // 2)
            result[f"morph B={batch}"] = median_time(lambda f=field: morph(f), reps)
    result["peak MB"] = peak_rss_mb() - baseline
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="*",
        default=[0, 1, 2],
        help="indices into SIZES (0: case A, 1: case C, 2: case B)",
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batches", type=int, nargs="*", default=[1, 10, 100])
    parser.add_argument("--dtypes", nargs="*", default=["float32", "float64"])
    parser.add_argument("--block-bytes", type=int, default=4 * 2**20)
    parser.add_argument(
        "--kernels",
        action="store_true",
        help="the kernel table (fused / torch / naive cdist) on the CPU",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads for --kernels")
    args = parser.parse_args(argv)
    if args.kernels:
        from gpu import idw_table, print_idw_table

        torch.set_num_threads(args.threads)
        rows, bandwidth = idw_table(torch.device("cpu"), args.repeats, False)
        print(
            f"# IDW kernels on the CPU: {platform.processor() or platform.machine()}, "
            f"{args.threads} thread(s), torch {torch.__version__}; 14,126 controls on a "
            f"sphere x 21,910 targets inside; floor: ~2.5 Gpair/s per thread (float32), "
            f"half in float64, for matrix-free rows, the copy bandwidth "
            f"({bandwidth / 1e9:.1f} GB/s) for dense rows\n"
        )
        print_idw_table(rows)
        return

    print(
        f"# IDW benchmark: {platform.processor() or platform.machine()}, "
        f"{torch.get_num_threads()} threads, torch {torch.__version__}, numpy {np.__version__}"
    )
    print(
        f"median of {args.repeats} repeats after a warm-up; matrix-free tiles of "
        f"{args.block_bytes / 2**20:g} MiB; peak MB = peak RSS above the process baseline\n"
    )
    columns = ["build+morph", *[f"morph B={b}" for b in args.batches], "peak MB", "apply MB"]
    print(
        "| N_t × N_c | dtype | mode | build+morph | "
        + " | ".join(f"morph B={b}" for b in args.batches)
        + " | peak MB | B=1 apply MB | NumPy / torch (build+morph) |"
    )
    print("|---" * (len(columns) + 4) + "|")
    context = mp.get_context("spawn")
    for index in args.sizes:
        size = SIZES[index]
        for dtype_name in args.dtypes:
            with context.Pool(1, maxtasksperchild=1) as pool:
                numpy_row = pool.apply(
                    run_config,
                    (
                        (
                            size,
                            dtype_name,
                            "numpy",
                            args.batches,
                            max(1, args.repeats // 2),
                            args.block_bytes,
                        ),
                    ),
                )
            for mode in ("dense", "matrix_free"):
                with context.Pool(1, maxtasksperchild=1) as pool:
                    row = pool.apply(
                        run_config,
                        ((size, dtype_name, mode, args.batches, args.repeats, args.block_bytes),),
                    )
                cells = [
                    f"{row[c]:.0f}" if c.endswith("MB") else f"{row[c]:.4f}"
                    for c in columns
                    if c in row
                ]
                cells += ["–"] * (len(columns) - len(cells))
                ratio = numpy_row["build+morph"] / row["build+morph"]
                print(
                    f"| {size[0]} × {size[1]} | {dtype_name} | {mode} | "
                    + " | ".join(cells)
                    + f" | {ratio:.1f}× |",
                    flush=True,
                )
            print(
                f"| {size[0]} × {size[1]} | {dtype_name} | NumPy dense | "
                f"{numpy_row['build+morph']:.4f} | "
                + " | ".join("–" for _ in args.batches)
                + f" | {numpy_row['peak MB']:.0f} | – | 1.0× |",
                flush=True,
            )


if __name__ == "__main__":
    main()
