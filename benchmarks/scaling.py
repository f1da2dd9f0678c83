"""How the cost grows with the mesh: a sweep of the node count over two decades or more.

For each size N the "mesh" is a synthetic point cloud, a c × c × c grid of the unit
cube (N = c³; no meshing, so the sweep runs in minutes): its 6(c-2)² + 12(c-2) + 8
surface points are the boundary nodes, the others the interior nodes (the IDW
targets). Timed, one thread on the CPU:

* selection: Algorithm 1 (SIDW) on the boundary nodes, radius R = 4 grid steps
  (about one boundary node in 25 is selected, N_c ∝ N^(2/3));
* dense IDW: assembling W (N_int × N_c), and applying it to one displacement
  (only while W fits a budget: 2 GiB on the CPU, a quarter of the GPU);
* matrix-free IDW: one displacement through the IDW module;
* Algorithm 2 morph: selection, building the matrix-free IDW and one deformation,
  scattered into the nodal field;
* POD online: one displacement through a fitted PODReducer (8 modes; the online
  cost does not depend on W, so the reducer is fitted on a coarser selection to
  keep the offline phase short);
* sharded matrix-free IDW on 1..K gloo ranks (CPU only): the slowest rank's time.

For each configuration the script fits the growth exponent k of t ∝ N^k (least
squares in log-log over the sizes measured), measures memory (the CPU's peak
resident set above the level before the configuration, by resetting the kernel's
high-water mark; on CUDA torch's peak allocation) and extrapolates the largest N
that fits 24 GB of RAM, or the GPU's memory, from a power law fitted to it
(exponent at least 1, anchored at the largest size measured).
It prints a Markdown table and writes a log-log plot with O(N_t·N_c) and
O(N log N) guide lines (docs/scaling_<device>.png).

    python benchmarks/scaling.py                         # CPU, 10^4 -> 10^6
    python benchmarks/scaling.py --device cuda --quick   # GPU, ~3 minutes on an H100
    python benchmarks/scaling.py --tree                  # exact against tree, CPU

``--tree`` sweeps instead the tree-approximated IDW against the exact fused sum: the
interpolating treecode (``torchmorph.idw.treecode.TreecodeIDW``, what ``IDW(mode="tree",
error_control="sampled")`` and ``auto`` take; rows "treecode") and the quadrupole
traversal (``torchmorph.idw.tree.TreeIDW``, sampled error control; rows "tree"),
``--tree-engines`` choosing, on the clouds of
``benchmarks/tree.py`` (N_c = N_t / 10 controls on a sphere, targets graded towards it),
N_t from 10^4 (``--tree-sizes``), tolerances 1e-3, 1e-4 and 1e-6, CPU only (the tree has
no CUDA kernels), one thread: the exact sum's time (on ``--exact-limit`` targets and
scaled beyond), the tree's build and the better of two calls once the threshold's
search has settled (the first call calibrates it; where a raise failed, up to five more
may each probe a threshold between, a second traversal: the calls are made until one
traverses once, ``TreeIDW.last_traversals_``; the treecode's build includes its weight
sums, and its first call is timed apart), the measured error at 2,000 targets
against float64 exact sums, the peak memory of the build and the calls per mesh node (N_t + N_c), fitted exponents
and the largest mesh in 24 GB extrapolated from that memory; plot
docs/scaling_tree_cpu.png (``--png``).

Needs matplotlib for the plot (``--no-plot`` without it); never meshio or gmsh.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import json
import math
import os
import socket
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import seconds, synchronise

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's torchmorph, not an installed one
CPU_MEMORY = 24 * 10**9
"""The RAM budget the issue asks about (bytes)."""
DENSE_CAP_CPU = 2 * 2**30
SELECTION_STEPS = 4.0
"""Selection radius in grid steps."""
POD_STEPS = 12.0
"""Selection radius of the coarser controls the POD reducer is fitted on."""

CONFIGS = {
    "selection": "selection (Algorithm 1)",
    "dense_assemble": "dense IDW: assemble W",
    "dense_apply": "dense IDW: apply W",
    "matrix_free": "matrix-free IDW: apply",
    "morph": "Algorithm 2 morph (matrix-free)",
    "pod_online": "POD online",
}


# --------------------------------------------------------------------------- #
# synthetic clouds
# --------------------------------------------------------------------------- #
def grid_cloud(side: int, dtype: torch.dtype, device: torch.device):
    """(boundary points, interior points) of a side³ grid of the unit cube."""
    axis = torch.linspace(0.0, 1.0, side, dtype=torch.float64)
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")
    points = torch.stack([x.flatten(), y.flatten(), z.flatten()], 1)
    index = torch.arange(side)
    on_face = (index == 0) | (index == side - 1)
    i, j, k = torch.meshgrid(on_face, on_face, on_face, indexing="ij")
    boundary = (i | j | k).flatten()
    return (points[boundary].to(device, dtype), points[~boundary].to(device, dtype))


def smooth_displacement(points: torch.Tensor, phase: float = 0.0) -> torch.Tensor:
    """A smooth boundary displacement (a bump and a twist)."""
    x, y, z = points.unbind(1)
    return 0.02 * torch.stack(
        [torch.sin(3 * y + phase) * z, torch.cos(2 * x) * (1 - z), x * y + phase], 1
    )


def select(boundary: torch.Tensor, steps: float, side: int) -> torch.Tensor:
    from torchmorph.selection import select_control_points

    generator = torch.Generator().manual_seed(0)
    chosen = select_control_points(
        boundary.detach().cpu().double(), steps / (side - 1), generator=generator
    )
    return torch.as_tensor(chosen, dtype=torch.long)


# --------------------------------------------------------------------------- #
# memory
# --------------------------------------------------------------------------- #
def _status_kib(field: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


class Memory:
    """Peak memory of a block: CUDA peak allocation, or the CPU's resident high-water mark
    above the level at entry (``/proc/self/clear_refs`` resets it; Linux)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.peak = 0

    def __enter__(self):
        gc.collect()
        if self.device.type == "cuda":
            torch.cuda.synchronize()
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
            self.base = torch.cuda.memory_allocated()
        else:
            with contextlib.suppress(OSError):
                ctypes.CDLL("libc.so.6").malloc_trim(0)
            with contextlib.suppress(OSError), open("/proc/self/clear_refs", "w") as refs:
                refs.write("5")
            self.base = _status_kib("VmRSS") * 1024
        return self

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            torch.cuda.synchronize()
            self.peak = torch.cuda.max_memory_allocated() - self.base
        else:
            self.peak = max(0, _status_kib("VmHWM") * 1024 - self.base)
        return False


# --------------------------------------------------------------------------- #
# one size
# --------------------------------------------------------------------------- #
def timed(function, device, repeats):
    """(median seconds, last result): one untimed warm-up call unless a call is slow."""
    start = time.perf_counter()
    result = function()
    synchronise(device)
    first = time.perf_counter() - start
    if first > 2.0 or repeats <= 1:
        return first, result
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        synchronise(device)
        times.append(time.perf_counter() - start)
    times.sort()
    return times[len(times) // 2], result


def warm_up(device: torch.device, dtype: torch.dtype) -> None:
    """Compile the device's kernels (Triton's first launch of each takes seconds) on a small
    cloud, so that no timed row includes a one-time compilation."""
    from torchmorph import IDW

    boundary, interior = grid_cloud(8, dtype, device)
    displacement = smooth_displacement(boundary)
    for mode in ("dense", "matrix_free"):
        idw = IDW(boundary, interior, mode=mode)
        idw(displacement)
        idw(torch.stack([displacement, displacement]))
    synchronise(device)


def measure_size(side: int, args, skip: set[str]) -> dict:
    from torchmorph import IDW
    from torchmorph.pod import PODReducer

    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    boundary, interior = grid_cloud(side, dtype, device)
    row = {
        "side": side,
        "nodes": side**3,
        "boundary": boundary.shape[0],
        "interior": interior.shape[0],
        "time": {},
        "memory": {},
    }
    repeats = 3
    with Memory(device) as memory:
        seconds_, selected = timed(lambda: select(boundary, SELECTION_STEPS, side), None, repeats)
    row["time"]["selection"], row["memory"]["selection"] = seconds_, memory.peak
    row["controls"] = int(selected.numel())
    controls = boundary[selected.to(device)]
    displacement = smooth_displacement(controls)
    itemsize = torch.empty(0, dtype=dtype).element_size()
    w_bytes = interior.shape[0] * controls.shape[0] * itemsize
    dense_cap = (
        DENSE_CAP_CPU
        if device.type == "cpu"
        else (torch.cuda.get_device_properties(device).total_memory // 4)
    )

    if "dense" not in skip and w_bytes <= dense_cap:
        with Memory(device) as memory:
            build, idw = timed(lambda: IDW(controls, interior, mode="dense"), device, repeats)
            apply, _ = timed(lambda: idw(displacement), device, repeats)
        row["time"]["dense_assemble"], row["time"]["dense_apply"] = build, apply
        row["memory"]["dense_assemble"] = row["memory"]["dense_apply"] = memory.peak
        del idw
    if "matrix_free" not in skip:
        with Memory(device) as memory:
            idw = IDW(controls, interior, mode="matrix_free")
            idw(displacement)  # untimed: the nearest distances, once per geometry (see "morph")
            apply, _ = timed(lambda: idw(displacement), device, repeats)
        row["time"]["matrix_free"], row["memory"]["matrix_free"] = apply, memory.peak
        del idw
    if "morph" not in skip:
        full_boundary = smooth_displacement(boundary)

        def morph():
            chosen = select(boundary, SELECTION_STEPS, side).to(device)
            idw = IDW(boundary[chosen], interior, mode="matrix_free")
            field = full_boundary.new_empty(boundary.shape[0] + interior.shape[0], 3)
            field[: boundary.shape[0]] = full_boundary
            field[boundary.shape[0] :] = idw(full_boundary[chosen])
            return field

        with Memory(device) as memory:
            total, _ = timed(morph, device, 1)
        row["time"]["morph"], row["memory"]["morph"] = total, memory.peak
    if "pod_online" not in skip:
        coarse = select(boundary, POD_STEPS, side).to(device)
        idw = IDW(boundary[coarse], interior, mode="matrix_free")
        generator = torch.Generator().manual_seed(1)
        training = torch.randn(8, coarse.numel(), 3, generator=generator, dtype=torch.float64).to(
            device, dtype
        )
        reducer = PODReducer(energy_tolerance=1e-9).fit(idw, training)  # <= 8 modes
        with Memory(device) as memory:
            online, _ = timed(lambda: reducer(training[3]), device, 5)
        row["time"]["pod_online"], row["memory"]["pod_online"] = online, memory.peak
        del idw, reducer
    return row


# --------------------------------------------------------------------------- #
# sharded runs (gloo ranks on the CPU)
# --------------------------------------------------------------------------- #
def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _sharded_rank(
    rank: int, world: int, port: int, side: int, dtype_name: str, output: str
) -> None:
    import torch.distributed as dist

    from torchmorph.distributed import ShardedIDW, shard_rows

    torch.set_num_threads(1)
    dist.init_process_group(
        "gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world
    )
    try:
        dtype = getattr(torch, dtype_name)
        boundary, interior = grid_cloud(side, dtype, torch.device("cpu"))
        controls = boundary[select(boundary, SELECTION_STEPS, side)]
        local = interior[shard_rows(interior.shape[0])]
        sharded = ShardedIDW(controls, local, mode="matrix_free")
        displacement = smooth_displacement(controls)
        sharded(displacement)  # warm-up (nearest pass cached)
        elapsed = []
        for _ in range(2):
            dist.barrier()
            start = time.perf_counter()
            sharded(displacement)
            dist.barrier()  # the slowest rank
            elapsed.append(time.perf_counter() - start)
        if rank == 0:
            Path(output).write_text(json.dumps({"seconds": min(elapsed)}))
    finally:
        dist.destroy_process_group()


def measure_sharded(side: int, world: int, dtype_name: str) -> float:
    import torch.multiprocessing as mp

    with tempfile.TemporaryDirectory() as folder:
        output = os.path.join(folder, "result.json")
        mp.spawn(
            _sharded_rank,
            args=(world, _free_port(), side, dtype_name, output),
            nprocs=world,
            join=True,
        )
        return json.loads(Path(output).read_text())["seconds"]


# --------------------------------------------------------------------------- #
# the tree-approximated IDW against the exact sum (--tree)
# --------------------------------------------------------------------------- #
TREE_TOLERANCES = (1e-3, 1e-4, 1e-6)


def _tree_calls(engine, controls, targets, displacements, tolerance, row, key):
    """Build one tree operator ("tree": TreeIDW, sampled; "treecode": TreecodeIDW), call it
    until it settles, time the better of two calls; (the last result, what settled)."""
    from torchmorph.idw.tree import TreeIDW
    from torchmorph.idw.treecode import TreecodeIDW

    start = time.perf_counter()
    if engine == "tree":
        module = TreeIDW(controls, targets, tolerance=tolerance, error_control="sampled")
    else:
        module = TreecodeIDW(controls, targets, tolerance=tolerance)
    row["time"][f"{key} build"] = time.perf_counter() - start
    start = time.perf_counter()
    module(displacements)
    row["time"][f"{key} first"] = time.perf_counter() - start
    settling = 1  # calls until the threshold's search settles (one traversal)
    while engine == "tree" and settling < 6 and module.last_traversals_ > 1:
        module(displacements)
        settling += 1
    calls = []
    for _ in range(2):  # the better of two calibrated calls (shared cores)
        start = time.perf_counter()
        result = module(displacements)
        calls.append(time.perf_counter() - start)
    row["time"][key] = min(calls)
    what = f"settled after {settling} call(s)" if engine == "tree" else f"degree {module.degree}"
    return result, what


def measure_tree_size(n_targets: int, tolerances, exact_limit: int, engines) -> dict:
    """Times, errors and peak memory of the exact fused sum and of the tree operators at
    one size."""
    from tree import fibonacci_sphere, field, graded_ball

    from torchmorph.idw import idw_apply

    n_controls = n_targets // 10
    controls64, targets64 = fibonacci_sphere(n_controls), graded_ball(n_targets, 1)
    controls, targets = controls64.float(), targets64.float()
    displacements = field(controls64).float()
    row: dict = {"targets": n_targets, "controls": n_controls, "nodes": n_targets + n_controls}
    row.update(time={}, memory={}, error={})
    measured = min(n_targets, exact_limit)
    subset = targets[:: max(1, n_targets // measured)][:measured]
    idw_apply(controls=controls, targets=subset[:100], displacements=displacements)
    with Memory(torch.device("cpu")) as memory:
        start = time.perf_counter()
        idw_apply(controls=controls, targets=subset, displacements=displacements)
        row["time"]["exact"] = (time.perf_counter() - start) * n_targets / subset.shape[0]
    if measured == n_targets:
        row["memory"]["exact"] = memory.peak
    row["exact_scaled"] = measured != n_targets
    sample = torch.linspace(0, n_targets - 1, min(2000, n_targets)).long()
    reference = idw_apply(
        controls=controls.double(), targets=targets.double()[sample],
        displacements=displacements.double(),
    )  # fmt: skip
    for engine in engines:
        for tolerance in tolerances:
            key = f"{engine} {tolerance:g}"
            with Memory(torch.device("cpu")) as memory:
                result, settling = _tree_calls(
                    engine, controls, targets, displacements, tolerance, row, key
                )
            row["memory"][key] = memory.peak
            error = (result[sample].double() - reference).norm() / reference.norm()
            row["error"][key] = float(error)
            del result
            print(
                f"[scaling --tree] N_t={n_targets:,} {key}: "
                f"build {row['time'][key + ' build']:.3g} s, "
                f"call {row['time'][key]:.3g} s (exact {row['time']['exact']:.3g} s), "
                f"error {row['error'][key]:.2e}, peak {memory.peak / 1e6:.0f} MB, "
                f"{settling}",
                flush=True,
            )
    return row


def _label(key: str) -> str:
    engine, tolerance = key.split(" ")
    if engine == "treecode":
        return f"treecode {tolerance} (TreecodeIDW, a later call)"
    return f"tree, sampled {tolerance} (TreeIDW, calibrated call)"


def summarise_tree(rows: list[dict], tolerances, engines) -> tuple[str, dict]:
    sizes = [r["targets"] for r in rows]
    header = [
        "configuration", *[f"N_t={n:,}" for n in sizes], "exponent k", "bytes/node at max N",
        "largest N in 24 GB RAM",
    ]  # fmt: skip
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    fits = {}
    keys = ["exact"] + [f"{e} {t:g}" for e in engines for t in tolerances]
    for key in keys:
        k, _ = power_fit(sizes, [r["time"][key] for r in rows])
        fits[key] = k
        cells = []
        for r in rows:
            cell = seconds(r["time"][key])
            if key == "exact" and r["exact_scaled"]:
                cell += " (scaled)"
            elif key != "exact":
                cell += f", {r['time']['exact'] / r['time'][key]:.1f}×, err {r['error'][key]:.1e}"
            cells.append(cell)
        memory = [(r["nodes"], r["memory"][key]) for r in rows if key in r["memory"]]
        per_node = memory[-1][1] / memory[-1][0] if memory else float("nan")
        biggest = largest_nodes(*zip(*memory, strict=True), CPU_MEMORY) if memory else math.nan
        label = "exact fused sum" if key == "exact" else _label(key)
        lines.append(
            f"| {label} | " + " | ".join(cells)
            + f" | {k:.2f} | {per_node:,.0f} | {biggest:.2g} |"
        )  # fmt: skip
    for engine in engines:
        for tolerance in tolerances:
            for part in ("build", "first"):
                key = f"{engine} {tolerance:g} {part}"
                k, _ = power_fit(sizes, [r["time"][key] for r in rows])
                cells = [seconds(r["time"][key]) for r in rows]
                name = "build" if part == "build" else "first call"
                lines.append(
                    f"| {engine} {name} ({tolerance:g}) | " + " | ".join(cells)
                    + f" | {k:.2f} | – | – |"
                )  # fmt: skip
    return "\n".join(lines), fits


def plot_tree(rows: list[dict], fits: dict, tolerances, engines, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7.5, 5.5))
    sizes = [r["targets"] for r in rows]
    for key in ["exact"] + [f"{e} {t:g}" for e in engines for t in tolerances]:
        label = "exact fused sum" if key == "exact" else _label(key)
        axes.loglog(
            sizes, [r["time"][key] for r in rows], "o-", label=f"{label} (k={fits[key]:.2f})"
        )
    guide = f"{engines[0]} 0.0001"
    n0, t0 = sizes[0], rows[0]["time"][guide] if guide in rows[0]["time"] else 1.0
    axes.loglog(
        sizes, [t0 * n * math.log(n) / (n0 * math.log(n0)) for n in sizes], "k-.",
        label="O(N log N) guide",
    )  # fmt: skip
    axes.loglog(
        sizes, [rows[0]["time"]["exact"] * (n / n0) ** 2 for n in sizes], "k:",
        label="O(N_t·N_c) guide",
    )  # fmt: skip
    axes.set_xlabel("targets N_t (N_c = N_t / 10)")
    axes.set_ylabel("seconds")
    axes.set_title("tree-approximated IDW against the exact sum (CPU, float32, one thread)")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7)
    figure.tight_layout()
    from torchmorph._atomic import atomic_output

    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=120, format="png")
    plt.close(figure)


def tree_main(args) -> int:
    tolerances = args.tree_tolerances
    rows = []
    for size in args.tree_sizes:
        rows.append(measure_tree_size(int(size), tolerances, args.exact_limit, args.tree_engines))
    table, fits = summarise_tree(rows, tolerances, args.tree_engines)
    print(f"\n## Scaling: tree against exact (CPU, {os.cpu_count()} cores, 1 thread, float32)")
    print(f"\n{table}\n")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "fits": fits}, indent=1))
    if not args.no_plot:
        path = args.png or ROOT / "docs" / "scaling_tree_cpu.png"
        try:
            plot_tree(rows, fits, tolerances, args.tree_engines, path)
        except ImportError as error:
            print(f"no plot ({error}); pip install matplotlib, or pass --no-plot")
        else:
            print(f"plot: {path}")
    return 0


# --------------------------------------------------------------------------- #
# fits, table, plot
# --------------------------------------------------------------------------- #
def power_fit(sizes: list[float], values: list[float]) -> tuple[float, float]:
    """(k, a) of values ≈ a · sizes^k, least squares in log-log."""
    xs = [math.log(s) for s in sizes]
    ys = [math.log(max(v, 1e-12)) for v in values]
    if len(xs) < 2:
        return float("nan"), float("nan")
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    k = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sxx
    return k, math.exp(my - k * mx)


def largest_nodes(sizes, memory, budget):
    """N at which the memory reaches ``budget``: the power law fitted to the measured
    peaks, anchored at the largest size and with an exponent of at least 1 (the points
    themselves take O(N), however small the sizes' peaks look)."""
    points = [(s, m) for s, m in zip(sizes, memory, strict=True) if m > 0]
    if not points:
        return float("nan")
    k, _ = (
        power_fit([p[0] for p in points], [p[1] for p in points])
        if len(points) > 1
        else (1.0, None)
    )
    k = max(k, 1.0) if math.isfinite(k) else 1.0
    size, peak = points[-1]
    return size * (budget / peak) ** (1.0 / k)


def summarise(rows: list[dict], sharded: dict, device: torch.device) -> tuple[str, dict]:
    budget = (
        CPU_MEMORY
        if device.type == "cpu"
        else torch.cuda.get_device_properties(device).total_memory
    )
    budget_name = (
        "24 GB RAM"
        if device.type == "cpu"
        else f"{budget / 1e9:.0f} GB ({torch.cuda.get_device_name(device)})"
    )
    sizes = [r["nodes"] for r in rows]
    header = [
        "configuration",
        *[f"N={n:,}" for n in sizes],
        "exponent k",
        "bytes/node at max N",
        f"largest N in {budget_name}",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    fits = {}
    for key, label in CONFIGS.items():
        measured = [
            (r["nodes"], r["time"][key], r["memory"].get(key, 0)) for r in rows if key in r["time"]
        ]
        if not measured:
            continue
        k, _ = power_fit([m[0] for m in measured], [m[1] for m in measured])
        biggest = largest_nodes([m[0] for m in measured], [m[2] for m in measured], budget)
        fits[key] = k
        cells = [seconds(r["time"][key]) if key in r["time"] else "–" for r in rows]
        per_node = measured[-1][2] / measured[-1][0]
        lines.append(
            f"| {label} | " + " | ".join(cells) + f" | {k:.2f} | {per_node:,.0f} | {biggest:.2g} |"
        )
    for world, times in sorted(sharded.items()):
        cells = [seconds(times[n]) if n in times else "–" for n in sizes]
        measured = [(n, times[n]) for n in sizes if n in times]
        k, _ = power_fit([m[0] for m in measured], [m[1] for m in measured])
        fits[f"sharded_{world}"] = k
        lines.append(
            f"| sharded matrix-free, {world} rank{'s' if world > 1 else ''} | "
            + " | ".join(cells)
            + f" | {k:.2f} | – | – |"
        )
    extra = ["", "| N | boundary | interior | controls N_c |", "|---|---|---|---|"]
    extra += [
        f"| {r['nodes']:,} | {r['boundary']:,} | {r['interior']:,} | {r['controls']:,} |"
        for r in rows
    ]
    if 1 in sharded:
        for world in sorted(sharded):
            if world == 1:
                continue
            ratios = [
                f"N={n:,}: {sharded[1][n] / sharded[world][n]:.2f}x"
                for n in sizes
                if n in sharded[1] and n in sharded[world]
            ]
            extra.append(f"\nspeed-up of {world} ranks over 1: " + ", ".join(ratios))
    return "\n".join(lines + extra), fits


def plot(rows, sharded, fits, path: Path, device: torch.device, dtype: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7.5, 5.5))
    for key, label in CONFIGS.items():
        points = [(r["nodes"], r["time"][key]) for r in rows if key in r["time"]]
        if points:
            xs, ys = zip(*points, strict=True)
            axes.loglog(xs, ys, "o-", label=f"{label} (k={fits.get(key, float('nan')):.2f})")
    for world, times in sorted(sharded.items()):
        points = sorted(times.items())
        xs, ys = zip(*points, strict=True)
        axes.loglog(xs, ys, "s--", label=f"sharded matrix-free, {world} rank(s)")
    anchor = [
        (r["nodes"], r["interior"] * r["controls"], r["time"]["matrix_free"])
        for r in rows
        if "matrix_free" in r["time"]
    ]
    if anchor:
        n0, pairs0, t0 = anchor[0]
        xs = [r["nodes"] for r in rows]
        axes.loglog(
            xs,
            [t0 * r["interior"] * r["controls"] / pairs0 for r in rows],
            "k:",
            label="O(N_t·N_c) guide",
        )
    selection = [(r["nodes"], r["time"]["selection"]) for r in rows]
    n0, t0 = selection[0]
    xs = [r["nodes"] for r in rows]
    axes.loglog(
        xs,
        [t0 * n * math.log(n) / (n0 * math.log(n0)) for n in xs],
        "k-.",
        label="O(N log N) guide",
    )
    axes.set_xlabel("mesh nodes N")
    axes.set_ylabel("seconds")
    axes.set_title(
        f"torchmorph cost growth ({device.type}, {dtype}, one "
        f"{'thread' if device.type == 'cpu' else 'device'})"
    )
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7)
    figure.tight_layout()
    from torchmorph._atomic import atomic_output

    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=120, format="png")
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    parser.add_argument(
        "--quick", action="store_true", help="fewer sizes (CPU: up to 3·10^5; CUDA: up to 3·10^6)"
    )
    parser.add_argument(
        "--sides", type=int, nargs="*", help="grid sides c (N = c³) instead of the default sweep"
    )
    parser.add_argument(
        "--max-ranks", type=int, default=2, help="sharded runs on 1..K gloo ranks (CPU; 0 to skip)"
    )
    parser.add_argument(
        "--sharded-max-side", type=int, default=68, help="largest grid side of the sharded runs"
    )
    parser.add_argument(
        "--budget",
        type=float,
        default=120.0,
        help="skip a configuration at the next size once it took this many seconds",
    )
    parser.add_argument(
        "--png", type=Path, default=None, help="plot path (default docs/scaling_<device>.png)"
    )
    parser.add_argument("--no-plot", action="store_true")
    parser.add_argument("--json", type=Path, default=None, help="also write the raw results")
    parser.add_argument("--tree", action="store_true", help="the tree against the exact sum")
    parser.add_argument(
        "--tree-sizes", type=float, nargs="+", default=[1e4, 3e4, 1e5, 3e5, 1e6],
        help="--tree: target counts N_t (N_c = N_t / 10)",
    )  # fmt: skip
    parser.add_argument(
        "--tree-tolerances",
        type=float,
        nargs="+",
        default=list(TREE_TOLERANCES),
        help="--tree: tolerances of the tree",
    )
    parser.add_argument(
        "--tree-engines", nargs="+", choices=("treecode", "tree"), default=["treecode", "tree"],
        help="--tree: the interpolating treecode (TreecodeIDW) and/or the quadrupole "
        "traversal (TreeIDW, sampled)",
    )  # fmt: skip
    parser.add_argument(
        "--exact-limit", type=int, default=100_000,
        help="--tree: the exact sum is timed on this many targets at most and scaled",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.tree:
        torch.set_num_threads(1)
        return tree_main(args)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device")
    torch.set_num_threads(1)
    if args.sides:
        sides = args.sides
    elif device.type == "cuda":
        sides = [22, 46, 100, 146] if args.quick else [22, 46, 100, 146, 215]
    else:
        sides = [22, 46, 68] if args.quick else [22, 32, 46, 68, 100]
    rows: list[dict] = []
    skip: set[str] = set()
    warm_up(torch.device(args.device), getattr(torch, args.dtype))
    for side in sides:
        start = time.perf_counter()
        row = measure_size(side, args, skip)
        rows.append(row)
        for key, value in row["time"].items():
            if value > args.budget:
                skip.add("dense" if key.startswith("dense") else key)
        print(
            f"[scaling] N={row['nodes']:,} (N_c={row['controls']:,}) in "
            f"{time.perf_counter() - start:.1f} s: "
            + ", ".join(f"{k} {seconds(v)}" for k, v in row["time"].items()),
            flush=True,
        )
    sharded: dict[int, dict[int, float]] = {}
    if device.type == "cpu" and args.max_ranks > 0:
        for world in range(1, args.max_ranks + 1):
            sharded[world] = {}
            for side in sides:
                if side > args.sharded_max_side:
                    continue
                sharded[world][side**3] = measure_sharded(side, world, args.dtype)
                print(
                    f"[scaling] sharded, {world} rank(s), N={side**3:,}: "
                    f"{seconds(sharded[world][side**3])}",
                    flush=True,
                )
    table, fits = summarise(rows, sharded, device)
    name = (
        torch.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"CPU, {os.cpu_count()} cores, 1 thread per process"
    )
    print(f"\n## Scaling ({name}, {args.dtype})\n\n{table}\n")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "sharded": sharded, "fits": fits}, indent=1))
    if not args.no_plot:
        path = args.png or ROOT / "docs" / f"scaling_{device.type}.png"
        try:
            plot(rows, sharded, fits, path, device, args.dtype)
        except ImportError as error:  # the table above is the result; the plot is extra
            print(f"no plot ({error}); pip install matplotlib, or pass --no-plot")
        else:
            print(f"plot: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
