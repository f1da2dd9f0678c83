"""Tile-shape sweep of the fused Triton IDW kernels on a CUDA device.

For each kernel of :mod:`torchmorph.idw.backends.triton.kernels` and each candidate
(BLOCK_rows, BLOCK_cols, num_warps), the median time (CUDA events, after warm-up) at
the paper's case-B counts (14,126 controls on a sphere, 21,910 targets inside it: a
graded cloud), float32 and float64, with the error of each candidate against a
float64 torch reference. The fastest candidates go into ``_TILES`` of that module.

    python benchmarks/gpu_tiles.py [--quick]
"""

from __future__ import annotations

import argparse
import sys

import torch

from torchmorph.idw.backends.triton import kernels

N_CONTROLS, N_TARGETS = 14126, 21910


def graded_cloud(
    n_controls: int, n_targets: int, dtype: torch.dtype, device: str, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Controls on the unit sphere, targets inside it (denser near the surface)."""
    generator = torch.Generator().manual_seed(seed)
    controls = torch.randn(n_controls, 3, generator=generator, dtype=torch.float64)
    controls /= controls.norm(dim=1, keepdim=True)
    directions = torch.randn(n_targets, 3, generator=generator, dtype=torch.float64)
    directions /= directions.norm(dim=1, keepdim=True)
    radii = torch.rand(n_targets, 1, generator=generator, dtype=torch.float64) ** 0.25 * 0.999
    return controls.to(device, dtype), (directions * radii).to(device, dtype)


def normalise(targets: torch.Tensor, controls: torch.Tensor):
    both = torch.cat([targets, controls])
    low, high = both.amin(0), both.amax(0)
    centre, scale = (low + high) / 2, (high - low).norm()
    return (
        ((targets - centre) / scale).T.contiguous(),
        ((controls - centre) / scale).T.contiguous(),
    )


def reference_apply(
    targets: torch.Tensor,
    controls: torch.Tensor,
    values: torch.Tensor,
    power: float = 4.0,
    rows: int = 2048,
) -> torch.Tensor:
    """float64 brute force ``W @ values`` (no coincident points in these clouds)."""
    t, c, v = targets.double(), controls.double(), values.double()
    out = []
    for start in range(0, t.shape[0], rows):
        d2 = (t[start : start + rows, None, :] - c[None, :, :]).square().sum(-1)
        r = (d2.amin(1, keepdim=True) / d2) ** (power / 2)
        out.append((r @ v) / r.sum(1, keepdim=True))
    return torch.cat(out)


def event_time(function, repeats: int = 10, warmup: int = 2) -> float:
    for _ in range(warmup):
        function()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        start, stop = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        function()
        stop.record()
        stop.synchronize()
        times.append(start.elapsed_time(stop) / 1e3)
    times.sort()
    return times[len(times) // 2]


def relative_error(got: torch.Tensor, expected: torch.Tensor) -> float:
    return float((got.double() - expected).norm() / expected.norm())


def sweep(kernel: str, run, candidates, label: str) -> tuple[tuple[int, int, int], float]:
    best = None
    for candidate in candidates:
        if candidate is None:
            kernels._OVERRIDE.pop(kernel, None)
            candidate = kernels.tile_shapes(kernel, torch.float32)
        else:
            kernels._OVERRIDE[kernel] = candidate
        try:
            seconds, error = run()
        except Exception as failure:  # noqa: BLE001 (a shape the compiler rejects: registers, shared memory)
            print(f"| {label} | {candidate} | failed: {type(failure).__name__} | |")
            continue
        print(f"| {label} | {candidate} | {seconds * 1e3:.3f} ms | {error:.1e} |")
        if best is None or seconds < best[1]:
            best = (candidate, seconds)
    kernels._OVERRIDE.pop(kernel, None)
    print(f"| **{label} best** | {best[0]} | {best[1] * 1e3:.3f} ms | |")
    return best


def sweep_columns(geometry, dtype, columns: int, candidates, best: dict) -> None:
    """Sweep pass 2 (``apply``) and the transposed pass at ``columns`` value columns:
    the one-by-one kernels up to ``SMALL_COLUMNS``, the ``tl.dot`` kernels above."""
    targets, controls, targets_t, controls_t, nearest = geometry
    name = str(dtype)[6:]
    values = torch.randn(N_CONTROLS, columns, dtype=dtype, device="cuda")
    expected = reference_apply(targets, controls, values)
    small = columns <= kernels.SMALL_COLUMNS
    kernel, tkernel = ("apply", "transposed") if small else ("apply_dot", "transposed_dot")

    def run_apply():
        out = kernels.apply(targets_t, controls_t, values, 4.0, 1e-20, nearest)[0]
        return (
            event_time(lambda: kernels.apply(targets_t, controls_t, values, 4.0, 1e-20, nearest)),
            relative_error(out, expected),
        )

    best[(kernel, name)] = sweep(
        kernel, run_apply, candidates, f"{kernel} (pass 2) {name} K={columns}"
    )
    grad = torch.randn(N_TARGETS, columns, dtype=dtype, device="cuda")
    _, _, sums = kernels.apply(targets_t, controls_t, values, 4.0, 1e-20, nearest)

    def run_transposed():
        return (
            event_time(
                lambda: kernels.apply_transposed(
                    targets_t, controls_t, grad, nearest, sums, 4.0, 1e-20
                )
            ),
            0.0,
        )

    best[(tkernel, name)] = sweep(
        tkernel, run_transposed, candidates, f"{tkernel} {name} K={columns}"
    )


def case_b_geometry(dtype):
    """(targets, controls, their normalised (D, N) layouts, the nearest distances)."""
    controls, targets = graded_cloud(N_CONTROLS, N_TARGETS, dtype, "cuda")
    targets_t, controls_t = normalise(targets, controls)
    return targets, controls, targets_t, controls_t, kernels.nearest_squared(targets_t, controls_t)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the current tiles only")
    parser.add_argument(
        "--dot",
        action="store_true",
        help="only the tl.dot kernels (a batch of 16: 48 columns), both dtypes",
    )
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("no CUDA device: nothing to sweep")
        return 0
    print(
        f"device: {torch.cuda.get_device_name()}, torch {torch.__version__}, "
        f"CUDA {torch.version.cuda}"
    )
    square = [
        (32, 64, 4),
        (32, 128, 4),
        (64, 64, 4),
        (64, 128, 4),
        (64, 64, 8),
        (128, 64, 8),
        (16, 128, 4),
    ]
    dots = [(32, 32, 4), (64, 32, 4), (64, 64, 4), (128, 32, 8), (64, 64, 8)]
    wide = [(32, 128, 4), (64, 128, 4), (32, 256, 4)]
    rows = [(8, 512, 4), (4, 512, 4), (8, 1024, 4), (4, 1024, 4), (16, 512, 4), (8, 512, 8)]
    if args.quick:
        square = dots = wide = rows = [None]
    print("| kernel | (rows, cols, warps) | median | rel. error vs float64 |")
    print("|---|---|---|---|")
    best = {}
    if args.dot and not args.quick:
        dots += [(128, 16, 4), (64, 16, 4), (32, 16, 4), (128, 32, 4), (32, 64, 4)]
    for dtype in (torch.float32, torch.float64):
        name = str(dtype)[6:]
        geometry = case_b_geometry(dtype)
        targets, controls, targets_t, controls_t, nearest = geometry
        if args.dot:
            sweep_columns(geometry, dtype, 48, dots, best)
            small = torch.randn(N_CONTROLS, 3, dtype=dtype, device="cuda")
            one = event_time(
                lambda: kernels.apply(targets_t, controls_t, small, 4.0, 1e-20, nearest)
            )
            print(f"{name}: one displacement (pass 2) {one * 1e3:.3f} ms")
            continue
        sweep_columns(geometry, dtype, 3, square, best)
        sweep_columns(geometry, dtype, 48, dots, best)

        def run_nearest():
            return event_time(lambda: kernels.nearest_squared(targets_t, controls_t)), 0.0

        best[("nearest", name)] = sweep("nearest", run_nearest, square, f"nearest {name}")
        out = torch.empty(N_TARGETS, N_CONTROLS, dtype=dtype, device="cuda")
        values = torch.randn(N_CONTROLS, 3, dtype=dtype, device="cuda")
        expected = reference_apply(targets, controls, values)

        def run_weights():
            kernels.weights(targets_t, controls_t, 4.0, 1e-20, out=out)
            error = relative_error(out @ values, expected)
            return event_time(
                lambda: kernels.weights(targets_t, controls_t, 4.0, 1e-20, out=out)
            ), error

        best[("weights", name)] = sweep("weights", run_weights, wide, f"W assembly {name}")
        gib = out.numel() * out.element_size() / 1e9
        print(f"(W is {gib:.2f} GB: {gib / best[('weights', name)][1]:.0f} GB/s written)")

        def run_dense():
            got = kernels.dense_apply(out, values)
            return event_time(lambda: kernels.dense_apply(out, values)), relative_error(
                got, expected
            )

        best[("dense_apply", name)] = sweep(
            "dense_apply", run_dense, rows, f"dense apply K=3 {name}"
        )
        print(
            f"(reads {gib:.2f} GB: {gib / best[('dense_apply', name)][1]:.0f} GB/s; "
            f"cuBLAS W@d {event_time(lambda: out @ values) * 1e3:.3f} ms, "
            f"(dT WT)T {event_time(lambda: (values.T.contiguous() @ out.T).T) * 1e3:.3f} ms)"
        )
        out = None  # free W before the next dtype
    print()
    for key, (candidate, seconds) in best.items():
        print(f"best {key}: {candidate} {seconds * 1e3:.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
