"""Tree-approximated IDW (``torchmorph.idw.tree.TreeIDW``) against the exact fused sum
(``torchmorph.idw.idw_apply``), one thread, float32, p = 4.

Clouds: N_c controls on the unit sphere (a Fibonacci lattice, a wall-like surface),
N_t = 10 N_c targets filling the ball, graded by 10^4 (distances to the surface
log-uniform in [1e-4, 1]). Displacements: a smooth field of the surface points.

For each N_t: the exact fused sum's time (measured on all targets up to
``--exact-limit`` targets, beyond it on a sample of that many targets and scaled
linearly, said so in the table); for each tolerance, the tree's build time, its first
call (the tolerance's scale calibrated against the certified bound, up to
``CERTIFY_ATTEMPTS`` traversals) and a second call (the calibrated operator: one
traversal), the transposed operator applied to the result (``TreeIDW.transposed``, the
gradient's pass; its second application), a loop of ``--loop`` calls on fields turning
from that field to a second one over a quarter turn (what a solver's loop hands over:
the mean time per call and the traversals of all blocks in all, ``last_traversals_``;
one per call where the threshold needs no retuning), the speed-up of the second call
over the exact sum, the certified bound and the relative 2-norm error measured at
``--sample`` targets against float64 exact sums.
Exponents: least-squares slopes of log(time) against log(N_t) (N_c grows with N_t, so an
exact sum grows as N_t²).

Usage: ``python benchmarks/tree.py [--sizes 1e4 3e4 1e5 3e5 1e6] [--tolerances 1e-3 1e-4 1e-6]``
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from torchmorph.idw import idw_apply
from torchmorph.idw.tree import TreeIDW


def fibonacci_sphere(count: int) -> torch.Tensor:
    index = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * index / count)
    azimuth = math.pi * (1 + 5**0.5) * index
    points = np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
    )
    return torch.from_numpy(points)


def graded_ball(count: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    directions = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    directions /= directions.norm(dim=1, keepdim=True)
    depth = 10 ** (-4 * torch.rand(count, 1, generator=generator, dtype=torch.float64))
    return directions * (1 - depth)


def field(points: torch.Tensor) -> torch.Tensor:
    x, y, z = points.unbind(1)
    return torch.stack([0.1 * x * y, 0.05 * torch.sin(3 * z), 0.02 + 0.1 * x * z], 1)


def second_field(points: torch.Tensor) -> torch.Tensor:
    """Another smooth field of the surface points (a twist-like mode), for the loop."""
    x, y, z = points.unbind(1)
    return torch.stack([0.05 * torch.sin(4 * x + y), 0.08 * x * z * z, 0.03 * torch.cos(5 * y)], 1)


def timed(function):
    start = time.perf_counter()
    result = function()
    return time.perf_counter() - start, result


def slope(sizes, times) -> float:
    return float(np.polyfit(np.log(sizes), np.log(times), 1)[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1e4, 3e4, 1e5, 3e5, 1e6])
    parser.add_argument("--tolerances", type=float, nargs="+", default=[1e-3, 1e-4, 1e-6])
    parser.add_argument("--exact-limit", type=int, default=100_000)
    parser.add_argument("--sample", type=int, default=2_000)
    parser.add_argument(
        "--certified-limit", type=int, default=100_000,
        help="largest N_t at which error_control='certified' is timed as well",
    )  # fmt: skip
    parser.add_argument(
        "--loop", type=int, default=8,
        help="calls on fields turning from one mode to another over a quarter turn",
    )  # fmt: skip
    arguments = parser.parse_args()
    torch.set_num_threads(1)
    warm = fibonacci_sphere(200).float()  # numba compiles here, not in a timed first call
    for mode in ("sampled", "certified"):
        TreeIDW(warm, warm * 0.5, error_control=mode)(field(warm.double()).float())

    rows, exact_times = [], []
    tree_times: dict[float, list[float]] = {tol: [] for tol in arguments.tolerances}
    sizes = [int(size) for size in arguments.sizes]
    for n_targets in sizes:
        n_controls = n_targets // 10
        controls64, targets64 = fibonacci_sphere(n_controls), graded_ball(n_targets, 1)
        displacements64, second_fields = field(controls64), second_field(controls64)
        controls, targets, displacements = (
            controls64.float(),
            targets64.float(),
            displacements64.float(),
        )
        measured = min(n_targets, arguments.exact_limit)
        subset = targets[:: max(1, n_targets // measured)][:measured]
        idw_apply(controls=controls, targets=subset[:100], displacements=displacements)
        exact_time, _ = timed(
            lambda subset=subset: idw_apply(
                controls=controls, targets=subset, displacements=displacements
            )
        )
        exact_time *= n_targets / subset.shape[0]
        exact_times.append(exact_time)
        rows_sample = torch.linspace(0, n_targets - 1, min(arguments.sample, n_targets)).long()
        reference = idw_apply(
            controls=controls.double(),
            targets=targets.double()[rows_sample],
            displacements=displacements.double(),
        )
        scaled = "" if measured == n_targets else f" (on {measured:,} targets, scaled)"
        controls_modes = ["sampled"]
        if n_targets <= arguments.certified_limit:
            controls_modes.append("certified")
        for mode in controls_modes:
            for tolerance in arguments.tolerances:
                build, module = timed(
                    lambda tolerance=tolerance, mode=mode: TreeIDW(
                        controls, targets, tolerance=tolerance, error_control=mode
                    )
                )
                first, _ = timed(lambda module=module: module(displacements))
                second, result = timed(lambda module=module: module(displacements))
                module.transposed(result)  # sampled: the transpose's own threshold's sums
                transposed, _ = timed(lambda module=module: module.transposed(result))
                loop, traversals = [], 0
                for step in range(1, arguments.loop + 1):
                    angle = 0.5 * math.pi * step / arguments.loop
                    turned = (
                        math.cos(angle) * displacements64 + math.sin(angle) * second_fields
                    ).float()
                    loop.append(timed(lambda module=module, turned=turned: module(turned))[0])
                    traversals += module.last_traversals_
                looped = f"{np.mean(loop):.3g} s, {traversals}" if arguments.loop else "–"
                if mode == "sampled":
                    tree_times[tolerance].append(second)
                measured_rows = result[rows_sample].double()
                error = float((measured_rows - reference).norm() / reference.norm())
                rows.append(
                    f"| {n_targets:,} | {n_controls:,} | {exact_time:.3g} s{scaled} | {mode} "
                    f"| {tolerance:g} | {build:.3g} s | {first:.3g} s | {second:.3g} s "
                    f"| {transposed:.3g} s | {looped} "
                    f"| {exact_time / second:.1f}x | {max(module.last_bound_):.2e} | {error:.2e} |"
                )
                print(rows[-1], flush=True)

    print()
    print(
        "| N_t | N_c | exact fused | error control | tolerance | tree build | first call "
        "| second call | transposed | loop: mean call, traversals | exact / second "
        "| certified bound | measured error |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        print(row)
    if len(sizes) > 1:
        print()
        print(f"exponent of time against N_t: exact {slope(sizes, exact_times):.2f}", end="")
        for tolerance, times in tree_times.items():
            print(f", tree (sampled) {tolerance:g}: {slope(sizes, times):.2f}", end="")
        print()


if __name__ == "__main__":
    main()
