"""GPU timings of IDW and the morphs at case-B size (fluid wing in a tunnel).

First table, the IDW kernels (median of ``--repeats`` after warm-up, CUDA-synchronised),
float32 and float64, at the paper's case-B counts (14,126 controls on a sphere, 21,910
targets inside it): the fused Triton kernels (matrix-free one displacement, batches of
16 and, on a GPU, 100, forward + backward; dense assembly and apply), beside the torch implementation and
the naive five-line ``torch.cdist`` code a user would write, with the rate (Gpair/s or
GB/s), the fraction of the device's floor and the error against a float64 reference;
and a 1e5 x 1e6 matrix-free row.

Second table, the morphs: dense IDW on a batch of ``--batch``, POD fit and online
(POD-IDW fitted to the case-B family δy = μ z² on the wing), and the full Algorithm 2
morph (``MeshMorph.forward``). The mesh is the case-B mesh of ``data_gen``; without the
``mesh`` extra (gmsh) a random point cloud of the paper's counts is used (said so).

Run ``python benchmarks/gpu.py`` on a machine with a CUDA device; it prints markdown
tables headed with the device's name. Without a GPU it says so and exits with status
0. ``--device cpu --counts 300 500 --no-large`` runs the same code on the CPU (a smoke
test of the script, not a benchmark).
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's data_gen

from _timing import median_time, seconds, synchronise

from torchmorph.idw import IDW, fused_available, idw_apply, idw_weights
from torchmorph.morph import MeshMorph
from torchmorph.pod import PODReducer

PAPER_COUNTS = (14126, 21910)  # case B: boundary (control) and interior nodes
DOMAIN = (0.0, 0.05)  # the paper's D for case B


def load_problem(size: str, dtype: torch.dtype):
    """(MeshMorph or None, controls, targets, family on the controls, label)."""
    try:
        from torchmorph.paper import CASES, load_mesh

        mesh = load_mesh("fluid-wing", size=size).to(dtype=dtype)
    except ImportError as error:
        print(f"(no case-B mesh: {error}; using a random cloud of the paper's counts)")
        generator = torch.Generator().manual_seed(0)
        controls = torch.rand(PAPER_COUNTS[0], 3, generator=generator, dtype=dtype)
        targets = torch.rand(PAPER_COUNTS[1], 3, generator=generator, dtype=dtype)
        z2 = controls[:, 2].square()

        def family(mu: torch.Tensor) -> torch.Tensor:
            d = torch.zeros(*mu.shape, z2.shape[0], 3, dtype=dtype, device=mu.device)
            d[..., 1] = mu[..., None] * z2.to(mu.device)
            return d

        return None, controls, targets, family, "random cloud of case-B size"
    morph = MeshMorph(mesh, mode="matrix_free")  # no W on the CPU; assembled on the device
    family = CASES["fluid-wing"].family(morph)
    label = (
        f"case-B mesh ({size}): {mesh.num_nodes} nodes, {morph.num_controls} controls, "
        f"{morph.num_interior} interior nodes"
    )
    controls = morph.points[morph.control_nodes]
    targets = morph.points[morph.interior_nodes]
    return morph, controls, targets, family, label


def naive_cdist(
    targets: torch.Tensor, controls: torch.Tensor, values: torch.Tensor, power: float = 4.0
) -> torch.Tensor:
    """IDW as a user would write it in five lines of torch (W materialised; cdist's
    |x|² + |c|² − 2x·c expansion cancels for near points)."""
    weights = torch.cdist(targets, controls).pow(-power)
    return (weights / weights.sum(1, keepdim=True)) @ values


def sphere_cloud(n_controls: int, n_targets: int, dtype: torch.dtype, device: torch.device):
    """Controls on the unit sphere, targets inside it, graded towards it (seed 0)."""
    generator = torch.Generator().manual_seed(0)
    controls = torch.randn(n_controls, 3, generator=generator, dtype=torch.float64)
    controls /= controls.norm(dim=1, keepdim=True)
    targets = torch.randn(n_targets, 3, generator=generator, dtype=torch.float64)
    targets *= (
        torch.rand(n_targets, 1, generator=generator, dtype=torch.float64) ** 0.25
        * 0.999
        / targets.norm(dim=1, keepdim=True)
    )
    return controls.to(device, dtype), targets.to(device, dtype)


def copy_bandwidth(device: torch.device) -> float:
    """Device-memory bandwidth (bytes read + written per second) of a 2 GB copy."""
    source = torch.empty(2**28, dtype=torch.float32, device=device)
    target = torch.empty_like(source)
    elapsed = median_time(lambda: target.copy_(source), 10, warmup=2, device=device)
    return 2 * source.numel() * 4 / elapsed


#: Matrix-free floors (target-control pairs per second): a pair costs ~15 operations.
#: CUDA (H100): ~1e12 in float32, half in float64. CPU: ~1 pair per cycle and core in
#: float32 (two 8-lane FMA units), half in float64, at ~2.5 GHz.
PAIR_FLOORS = {
    "cuda": {torch.float32: 1e12, torch.float64: 0.5e12},
    "cpu": {torch.float32: 2.5e9, torch.float64: 1.25e9},
}


def idw_table(
    device: torch.device, repeats: int, large: bool, counts: tuple[int, int] = PAPER_COUNTS
) -> tuple[list[tuple], float]:
    """Rows (path, dtype, seconds, rate, floor fraction, error) and the copy bandwidth."""
    n_controls, n_targets = counts
    threads = torch.get_num_threads() if device.type == "cpu" else 1
    fused_kind = "fused" if fused_available(device) else "auto"  # a CPU smoke test without numba
    pairs = n_controls * n_targets
    bandwidth = copy_bandwidth(device)
    timed = partial(median_time, warmup=2, device=device)
    rows = []
    for dtype in (torch.float32, torch.float64):
        name = str(dtype)[6:]
        floor = PAIR_FLOORS.get(device.type, PAIR_FLOORS["cpu"])[dtype] * threads
        controls, targets = sphere_cloud(n_controls, n_targets, dtype, device)
        generator = torch.Generator().manual_seed(1)
        one = torch.randn(n_controls, 3, generator=generator, dtype=torch.float64)
        sixteen = torch.randn(16, n_controls, 3, generator=generator, dtype=torch.float64)
        reference = idw_apply(
            controls=controls.double(),
            targets=targets.double(),
            displacements=one.to(device),
            implementation="torch",
        )
        scale = reference.norm()
        hundred = torch.randn(100, n_controls, 3, generator=generator, dtype=torch.float64)
        sixteen[0] = hundred[0] = one  # the batch rows' error is that of their first entry
        one, sixteen = one.to(device, dtype), sixteen.to(device, dtype)
        hundred = hundred.to(device, dtype)

        def error(result):
            return float((result.double() - reference).norm() / scale)

        with torch.no_grad():
            fused = IDW(controls, targets, mode="matrix_free", implementation=fused_kind)
            plain = IDW(controls, targets, mode="matrix_free", implementation="torch")
            for label, run in (
                ("matrix-free, one displacement (module)", lambda: fused(one)),
                (
                    "matrix-free, one displacement (idw_apply)",
                    lambda: idw_apply(
                        controls=controls,
                        targets=targets,
                        displacements=one,
                        implementation=fused_kind,
                    ),
                ),
                ("matrix-free, batch of 16 (module)", lambda: fused(sixteen)),
                # wider than one launch of the batched pass (groups of columns); on the
                # CPU the same blocks-of-W path as the batch of 16, so not timed there
                *(
                    [("matrix-free, batch of 100 (module)", lambda: fused(hundred))]
                    if device.type == "cuda"
                    else []
                ),
                ("matrix-free, one displacement, torch implementation", lambda: plain(one)),
                (
                    "matrix-free, one displacement, naive cdist code",
                    lambda: naive_cdist(targets, controls, one),
                ),
            ):
                seconds_ = timed(run, repeats if "torch" not in label else 3)
                result = run()
                count = pairs  # geometry pairs, whatever the batch
                rows.append(
                    (
                        label,
                        name,
                        seconds_,
                        f"{count / seconds_ / 1e9:,.2f} Gpair/s",
                        f"{count / seconds_ / floor:.2f}",
                        error(result[0] if result.ndim == 3 else result),
                    )
                )
        probe = one.clone().requires_grad_(True)

        def backward():
            (fused(probe) * 1.0).sum().backward()

        seconds_ = timed(backward, repeats)
        rows.append(
            (
                "matrix-free, forward + backward to d (module)",
                name,
                seconds_,
                f"{2 * pairs / seconds_ / 1e9:,.2f} Gpair/s",
                f"{2 * pairs / seconds_ / floor:.2f}",
                float("nan"),
            )
        )
        moving_targets = targets.clone().requires_grad_(True)
        moving_controls = controls.clone().requires_grad_(True)
        for label, implementation in (
            ("matrix-free, forward + backward to d and positions (idw_apply)", "auto"),
            ("matrix-free, forward + backward to d and positions, torch implementation", "torch"),
        ):

            def position_backward():
                idw_apply(
                    controls=moving_controls,
                    targets=moving_targets,
                    displacements=probe,
                    implementation=implementation,
                ).sum().backward()

            seconds_ = timed(position_backward, repeats if implementation != "torch" else 3)
            rows.append(
                (
                    label,
                    name,
                    seconds_,
                    f"{4 * pairs / seconds_ / 1e9:,.2f} Gpair/s",
                    f"{4 * pairs / seconds_ / floor:.2f}",
                    float("nan"),
                )
            )
        with torch.no_grad():
            w_bytes = pairs * controls.element_size()
            for label, implementation in (
                ("dense: assemble W", fused_kind),
                ("dense: assemble W, torch implementation", "torch"),
            ):
                seconds_ = timed(
                    lambda: idw_weights(
                        controls=controls, targets=targets, implementation=implementation
                    ),
                    3,
                    warmup=1,
                )
                rows.append(
                    (
                        label,
                        name,
                        seconds_,
                        f"{w_bytes / seconds_ / 1e9:,.0f} GB/s",
                        f"{w_bytes / seconds_ / bandwidth:.2f}",
                        float("nan"),
                    )
                )
            dense = IDW(controls, targets, mode="dense", implementation=fused_kind)
            for label, run in (
                ("dense: apply one displacement", lambda: dense(one)),
                ("dense: apply one displacement, plain W @ d", lambda: dense.weights @ one),
                ("dense: apply a batch of 16", lambda: dense(sixteen)),
            ):
                seconds_ = timed(run, repeats * 3)
                result = run()
                rows.append(
                    (
                        label,
                        name,
                        seconds_,
                        f"{w_bytes / seconds_ / 1e9:,.0f} GB/s",
                        f"{w_bytes / seconds_ / bandwidth:.2f}",
                        error(result[0] if result.ndim == 3 else result),
                    )
                )
            dense = None  # free W before the next dtype
        if device.type == "cuda":
            torch.cuda.empty_cache()
    if large and device.type == "cuda":
        controls, targets = sphere_cloud(100_000, 1_000_000, torch.float32, device)
        one = torch.randn(100_000, 3, dtype=torch.float32, device=device)
        with torch.no_grad():
            seconds_ = timed(
                lambda: idw_apply(
                    controls=controls, targets=targets, displacements=one, implementation=fused_kind
                ),
                3,
                warmup=1,
            )
        count = 100_000 * 1_000_000
        rows.append(
            (
                "matrix-free, 1e5 controls x 1e6 targets (idw_apply)",
                "float32",
                seconds_,
                f"{count / seconds_ / 1e9:,.0f} Gpair/s",
                f"{count / seconds_ / PAIR_FLOORS['cuda'][torch.float32]:.2f}",
                float("nan"),
            )
        )
    return rows, bandwidth


def print_idw_table(rows: list[tuple]) -> None:
    print("| path | dtype | time | rate | fraction of floor | error |")
    print("|---|---|---|---|---|---|")
    for label, dtype_name, value, rate, fraction, err in rows:
        shown = "–" if err != err else f"{err:.1e}"
        print(f"| {label} | {dtype_name} | {seconds(value)} | {rate} | {fraction} | {shown} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", help="default cuda")
    parser.add_argument("--size", choices=("small", "paper"), default="paper")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--batch", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--no-large", action="store_true", help="skip the 1e5 x 1e6 row")
    parser.add_argument("--idw-only", action="store_true", help="only the IDW kernel table")
    parser.add_argument(
        "--counts",
        type=int,
        nargs=2,
        metavar=("CONTROLS", "TARGETS"),
        default=PAPER_COUNTS,
        help="point counts of the IDW table",
    )
    args = parser.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print(
            "benchmarks/gpu.py: no CUDA device is available (torch "
            f"{torch.__version__}, CUDA build: {torch.version.cuda or 'none'}); nothing to "
            "time. Run it on a machine with a GPU."
        )
        return 0
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"## GPU: {name}")
    print(
        f"torch {torch.__version__}, CUDA {torch.version.cuda or '-'}; medians of "
        f"{args.repeats}+ after warm-up"
    )
    print()
    rows, bandwidth = idw_table(device, args.repeats, not args.no_large, tuple(args.counts))
    print(
        f"IDW kernels ({args.counts[0]:,} controls on a sphere x "
        f"{args.counts[1]:,} targets inside); error = ‖result − float64 reference‖ / "
        f"‖reference‖; floor: {PAIR_FLOORS['cuda'][torch.float32] / 1e12:g} Tpair/s (float32) "
        f"and half that (float64) for matrix-free rows, the measured copy bandwidth "
        f"({bandwidth / 1e12:.2f} TB/s) for dense rows"
    )
    print()
    print_idw_table(rows)
    if args.idw_only:
        return 0
    print()
    return morph_table(args, device, name)


def morph_table(args, device: torch.device, name: str) -> int:
    """The morph-level rows: dense IDW, POD and Algorithm 2 on the case-B mesh."""
    dtype = getattr(torch, args.dtype)
    generator = torch.Generator().manual_seed(0)
    morph, controls, targets, family, label = load_problem(args.size, dtype)
    controls, targets = controls.to(device), targets.to(device)
    mus = DOMAIN[0] + (DOMAIN[1] - DOMAIN[0]) * torch.rand(
        args.batch, generator=generator, dtype=dtype
    )
    mus = mus.to(device)
    if morph is not None:
        morph = morph.to(device)
        boundary = family(mus)  # (B, N_b, 3)
        inputs = morph.controls_from_boundary(boundary)  # every boundary node: the same
    else:
        inputs = family(mus)
    rows: list[tuple[str, float]] = []
    timed = partial(median_time, warmup=2, device=device)
    with torch.no_grad():
        dense = IDW(controls, targets, mode="dense")
        rows.append(
            (f"IDW dense: apply, batch of {args.batch}", timed(lambda: dense(inputs), args.repeats))
        )
        if morph is not None:
            dense_morph = _with_dense_weights(morph)
            training = DOMAIN[0] + (DOMAIN[1] - DOMAIN[0]) * torch.rand(
                20, generator=generator, dtype=dtype
            )
            start = time.perf_counter()
            reducer = PODReducer().fit(dense_morph, family=family, parameters=training.to(device))
            synchronise(device)
            rows.append(
                (
                    f"POD fit (20 snapshots, {reducer.num_modes_} mode(s))",
                    time.perf_counter() - start,
                )
            )
            single = boundary[0].contiguous()
            rows.append(("POD online: one μ", timed(lambda: reducer(single), args.repeats * 10)))
            rows.append(
                (
                    f"POD online: batch of {args.batch}",
                    timed(lambda: reducer(boundary), args.repeats),
                )
            )
            rows.append(
                (
                    "MeshMorph (Algorithm 2, dense W): one μ",
                    timed(lambda: dense_morph(single), args.repeats * 10),
                )
            )
    print(f"Morphs, {args.dtype}; {label}")
    print()
    print("| step | time |")
    print("|---|---|")
    for step, value in rows:
        print(f"| {step} | {seconds(value)} |")
    return 0


def _with_dense_weights(morph: MeshMorph) -> MeshMorph:
    """``morph`` with its IDW replaced by a dense one, W assembled on the morph's device."""
    morph.idw = IDW(morph.idw.controls, morph.idw.targets, mode="dense", power=morph.idw.power)
    morph.assembly_time = morph.idw.assembly_time
    return morph


if __name__ == "__main__":
    sys.exit(main())
