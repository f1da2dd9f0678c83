"""Benchmark of the POD-reduced morph (Algorithm 3 of Ballarin et al. 2017, section 3) at the size of case B.

A problem of the size of the paper's case B (fluid wing in a tunnel): 14,126
control points (tunnel walls, random points, plus a NACA0012 wing surface of span 2π
with its root on the z = 0 wall) and 21,910 interior targets, morphed by the paper's
family ``δy = μ z²`` on the wing (walls fixed), μ in D = [0, 0.05]; 20 random training
values as in the paper. With ``--mesh`` the generated case-B mesh
(``data_gen.build("fluid_wing", size="paper")``) and a :class:`MeshMorph` with every
boundary node a control point are used instead.

Printed (markdown): the offline phase (W assembly by the IDW module, then the POD
fit: snapshots, SVD, online matrices; ``projection_matrix`` alone), the POD basis of
the same snapshots by ``pod_basis`` and by EZyRB's ``POD`` (when ``ezyrb`` is
installed), the online phase per μ (one value) and per
batch of 1000 values, the full IDW morph for one value and for a batch of 100
(a batch of 1000 would take ~10x that and 1.3 GB of output per 100 values in
float64; it is extrapolated, and said so), the ratios, and the relative error of
the reduced morph against the full one on fresh μ. Times are medians of repeats
after a warm-up.

A fresh 264 MB output costs more in page faults than the product itself: reuse one
with ``reducer(d, out=buffer)``, or let PyTorch allocate with transparent huge pages
(``THP_MEM_ALLOC_ENABLE=1`` in the environment, Linux).

Run ``python benchmarks/pod.py`` (about 1-2 minutes on 2 cores);
``--dtype float64``, ``--paper`` to also fit the paper's variant (eq. 16: a
least-squares solve with the 21,910 × 14,126 W; minutes), ``--quick`` for a small run.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _timing import median_and_min, median_time

from torchmorph.idw import IDW
from torchmorph.pod import PODReducer, pod_basis, projection_matrix

BOX = np.array([10.0, 5.0, 4.0 * math.pi])  # tunnel, x along the flow, z span-wise
CHORD, SPAN = 1.01, 2.0 * math.pi
WING_X, WING_Y = 3.0, 2.5  # leading edge position in the tunnel
DOMAIN = (0.0, 0.05)  # the paper's D for case B
PAPER = {"offline": 2479.51, "online": 0.55, "idw": 83.09}  # POD-IDW and IDW, case B


def naca0012_half_thickness(x: np.ndarray) -> np.ndarray:
    t = np.clip(x / CHORD, 0.0, 1.0)
    return (
        0.6
        * CHORD
        * (0.2969 * np.sqrt(t) - 0.1260 * t - 0.3516 * t**2 + 0.2843 * t**3 - 0.1036 * t**4)
    )


def inside_wing(points: np.ndarray) -> np.ndarray:
    x = points[:, 0] - WING_X
    within = (x >= 0) & (x <= CHORD) & (points[:, 2] <= SPAN)
    return within & (np.abs(points[:, 1] - WING_Y) <= naca0012_half_thickness(x))


def synthetic_case_b(num_controls: int, num_targets: int, seed: int = 0):
    """Controls (N_c, 3) with a wing mask, and targets (N_t, 3), as float64 arrays."""
    rng = np.random.default_rng(seed)
    # wing surface: cosine-spaced chord-wise stations, uniform span-wise, upper and lower
    chordwise, spanwise = 80, round(0.35 * num_controls / 160)
    t = 0.5 * (1 - np.cos(np.linspace(0.0, np.pi, chordwise)))
    x = t * CHORD
    z = np.linspace(0.0, SPAN, spanwise)
    half = naca0012_half_thickness(x)
    xx = np.concatenate([x, x[1:-1]])
    yy = np.concatenate([half, -half[1:-1]])
    wing = np.stack(
        np.broadcast_arrays(xx[:, None] + WING_X, yy[:, None] + WING_Y, z[None, :]), -1
    ).reshape(-1, 3)
    # walls: random points in proportion to the wall areas
    count = num_controls - len(wing)
    areas = np.array([np.prod(np.delete(BOX, axis)) for axis in (0, 0, 1, 1, 2, 2)])
    per_wall = np.floor(count * areas / areas.sum()).astype(int)
    per_wall[0] += count - per_wall.sum()
    walls = []
    for wall, size in enumerate(per_wall):
        block = rng.random((size, 3)) * BOX
        block[:, wall // 2] = 0.0 if wall % 2 == 0 else BOX[wall // 2]
        walls.append(block)
    controls = np.concatenate([wing, *walls])
    is_wing = np.zeros(len(controls), dtype=bool)
    is_wing[: len(wing)] = True
    # targets: half uniform in the tunnel, half clustered around the wing, none inside it
    targets = np.empty((0, 3))
    while len(targets) < num_targets:
        uniform = rng.random((num_targets, 3)) * BOX
        near = np.column_stack(
            [
                rng.uniform(WING_X - 0.5, WING_X + CHORD + 1.0, num_targets),
                WING_Y + rng.normal(0.0, 0.4, num_targets),
                rng.uniform(0.0, SPAN + 0.5, num_targets),
            ]
        )
        fresh = np.concatenate([uniform[: num_targets // 2], near[: num_targets // 2]])
        fresh = fresh[~inside_wing(fresh) & np.all((fresh > 0) & (fresh < BOX), 1)]
        targets = np.concatenate([targets, fresh])
    return controls, is_wing, targets[:num_targets]


def build_problem(args, dtype):
    """(morph, family, kind label, sizes) for the synthetic cloud or the generated mesh."""
    if args.mesh:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's data_gen
        import data_gen
        from torchmorph.morph import MeshMorph

        mesh = data_gen.build("fluid_wing", size="paper").to(dtype=dtype)
        start = time.perf_counter()
        morph = MeshMorph(mesh)
        setup = time.perf_counter() - start
        wing = morph.boundary_mask([n for n in mesh.node_sets if "wing" in n] or ["wing"])
        z2 = morph.boundary_points[:, 2].square() * wing

        label = (
            f"case-B mesh: {mesh.num_nodes} nodes, {morph.num_boundary} boundary "
            f"(all controls), {morph.num_interior} interior"
        )
        sizes = (morph.num_controls, morph.num_interior)
    else:
        controls, is_wing, targets = synthetic_case_b(args.controls, args.targets)
        controls_t = torch.from_numpy(controls).to(dtype)
        targets_t = torch.from_numpy(targets).to(dtype)
        IDW(controls_t[:100], targets_t[:100])  # warm-up
        start = time.perf_counter()
        morph = IDW(controls_t, targets_t)
        setup = time.perf_counter() - start
        z2 = controls_t[:, 2].square() * torch.from_numpy(is_wing).to(dtype)
        label = (
            f"synthetic case-B cloud: {len(controls)} controls ({int(is_wing.sum())} on "
            f"the wing), {len(targets)} targets"
        )
        sizes = (len(controls), len(targets))

    def family(mu: torch.Tensor) -> torch.Tensor:
        """δy = μ z² on the wing, zero elsewhere; mu () or (B,)."""
        d = mu.new_zeros(*mu.shape, z2.shape[0], 3)
        d[..., 1] = mu[..., None] * z2
        return d

    return morph, family, label, sizes, setup


def seconds(value: float) -> str:
    return f"{value * 1e3:,.3f} ms" if value < 1 else f"{value:,.2f} s"


def pod_versus_ezyrb(snapshots: torch.Tensor, energy_tolerance: float, repeats: int) -> list[str]:
    """Rows: the POD basis of the same snapshots by ``pod_basis`` and by EZyRB's ``POD``.

    EZyRB keeps the modes reaching a cumulative energy ``1 - ε`` and gets the
    snapshots as a float64 NumPy array, one snapshot per column (its layout; the
    conversion is not timed); ``pod_basis`` gets them as the morph returned them.
    The contenders are timed in turns (one call each per round, after a warm-up
    round), so that a change in the machine's load hits all of them alike.
    """
    snapshots64 = snapshots.double().contiguous()
    contenders = {
        "pod_basis (auto)": lambda: pod_basis(snapshots, energy_tolerance=energy_tolerance),
        "pod_basis (auto), float64 contiguous copy (what EZyRB gets)": lambda: pod_basis(
            snapshots64, energy_tolerance=energy_tolerance
        ),
        "pod_basis(method='svd')": lambda: pod_basis(
            snapshots, method="svd", energy_tolerance=energy_tolerance
        ),
    }
    try:
        from ezyrb import POD
    except ImportError:
        POD = None
    if POD is not None:
        columns = snapshots.double().reshape(snapshots.shape[0], -1).T.contiguous().numpy()
        for method in ("svd", "correlation_matrix"):
            contenders[f"EZyRB POD('{method}').fit"] = lambda method=method: POD(
                method, rank=1.0 - energy_tolerance
            ).fit(columns)
    times: dict[str, list[float]] = {name: [] for name in contenders}
    for round_ in range(repeats + 1):
        for name, call in contenders.items():
            start = time.perf_counter()
            call()
            if round_:
                times[name].append(time.perf_counter() - start)
    median = {name: statistics.median(values) for name, values in times.items()}
    if POD is None:
        return [
            row("POD basis, pod_basis (auto)", median["pod_basis (auto)"]),
            "",
            "EZyRB is not installed (pip install ezyrb): no comparison row.",
        ]
    fastest = min(value for name, value in median.items() if name.startswith("EZyRB"))
    rows = []
    for name, value in median.items():
        label = f"POD fit vs EZyRB on the same snapshots: {name}" if not rows else name
        rows.append(row(label, value, "", f"{fastest / value:,.2f}x EZyRB's fastest"))
    return rows


def row(name: str, timing, paper: str = "", ratio: str = "") -> str:
    """A table row; ``timing`` is seconds or (median, minimum)."""
    if isinstance(timing, tuple):
        text = f"{seconds(timing[0])} (min {seconds(timing[1])})"
    else:
        text = seconds(timing)
    return f"| {name} | {text} | {paper} | {ratio} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--controls", type=int, default=14126)
    parser.add_argument("--targets", type=int, default=21910)
    parser.add_argument("--train", type=int, default=20)
    parser.add_argument("--batch", type=int, default=1000)
    parser.add_argument("--full-batch", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--paper", action="store_true", help="also fit online='paper'")
    parser.add_argument("--mesh", action="store_true", help="use data_gen's case-B mesh")
    parser.add_argument("--quick", action="store_true", help="a 10x smaller problem")
    args = parser.parse_args()
    if args.quick:
        args.controls, args.targets, args.batch, args.full_batch = 1412, 2191, 100, 20
    dtype = getattr(torch, args.dtype)
    generator = torch.Generator().manual_seed(0)

    def random_mu(count: int) -> torch.Tensor:
        low, high = DOMAIN
        return low + (high - low) * torch.rand(count, generator=generator, dtype=dtype)

    morph, family, label, (num_controls, num_targets), setup = build_problem(args, dtype)
    training = random_mu(args.train)

    # ---------------------------------------------------------------- offline
    load_before = os.getloadavg()[0]
    fits = []
    for _ in range(max(1, args.repeats // 2)):
        fits.append(PODReducer().fit(morph, family=family, parameters=training))
    reducer = fits[-1]
    offline = {
        key: statistics.median(f.offline_time_[key] for f in fits) for key in reducer.offline_time_
    }
    paper_fit = None
    if args.paper:
        paper_fit = PODReducer(online="paper").fit(morph, family=family, parameters=training)

    with torch.no_grad():
        snapshots = (
            morph(family(training))
            if not args.mesh
            else morph.idw(morph.controls_from_boundary(family(training)))
        )
        comparison = pod_versus_ezyrb(snapshots, reducer.energy_tolerance, args.repeats)
        weights = morph.idw.weights_matrix() if args.mesh else morph.weights_matrix()
        modes = reducer.modes_
        projection = median_time(lambda: projection_matrix(modes, weights), args.repeats)

    # ---------------------------------------------------------------- online
    mu_one = random_mu(1)[0]
    d_one = family(mu_one)
    mu_batch = random_mu(args.batch)
    d_batch = family(mu_batch)
    with torch.no_grad():
        single = median_and_min(lambda: reducer(d_one), 1000, warmup=20)
        single_mu = median_and_min(lambda: reducer.morph_parameters(mu_one), 1000, warmup=20)
        batch = median_and_min(lambda: reducer(d_batch), args.repeats)
        buffer = torch.empty(args.batch, reducer.num_outputs, 3, dtype=dtype)
        batch_out = median_and_min(lambda: reducer(d_batch, out=buffer), args.repeats)
        batch_mu = median_and_min(lambda: reducer.morph_parameters(mu_batch), args.repeats)
        full_single = median_and_min(lambda: morph(d_one), args.repeats * 2)
        d_full_batch = d_batch[: args.full_batch]
        full_batch = median_and_min(lambda: morph(d_full_batch), max(1, args.repeats // 2))
        error = reducer.relative_error(family(random_mu(20)))
        paper_error = paper_single = None
        if paper_fit is not None:
            paper_error = paper_fit.relative_error(family(random_mu(20)))
            paper_single = median_and_min(lambda: paper_fit(d_one), 1000, warmup=20)
    full_extrapolated = full_batch[0] * args.batch / args.full_batch
    load_after = os.getloadavg()[0]

    # ---------------------------------------------------------------- table
    thp = os.environ.get("THP_MEM_ALLOC_ENABLE", "unset")
    print(f"## POD benchmark: {label}")
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{platform.processor() or platform.machine()}, {args.dtype}, "
        f"THP_MEM_ALLOC_ENABLE={thp}, load average {load_before:.1f} -> {load_after:.1f}; "
        f"n_train = {args.train}, N = {reducer.num_modes_} mode(s), "
        f"σ = {', '.join(f'{s:.3g}' for s in reducer.singular_values_[:3].tolist())} ..."
    )
    print()
    print("| step | ours: median (min) | paper (case B, POD-IDW) | ratio (medians) |")
    print("|---|---|---|---|")
    print(row("morph setup: W assembly (not in the paper's offline)", setup))
    print(row("offline: snapshots (one batched morph)", offline["snapshots"]))
    print(row("offline: SVD", offline["svd"]))
    print(row("offline: online matrices P = Zᵀ W", offline["online_matrices"]))
    print(
        row(
            f"offline: projection_matrix (one GEMM, {reducer.num_modes_} mode(s), "
            f"{num_controls} -> {num_targets})",
            projection,
        )
    )
    print(
        row(
            "offline: total fit",
            offline["total"],
            f"{PAPER['offline']:,.0f} s",
            f"{PAPER['offline'] / offline['total']:,.0f}x faster",
        )
    )
    print(
        row(
            "offline: setup + fit",
            setup + offline["total"],
            f"{PAPER['offline']:,.0f} s",
            f"{PAPER['offline'] / (setup + offline['total']):,.0f}x faster",
        )
    )
    if paper_fit is not None:
        print(
            row(
                "offline: total fit, online='paper' (eq. 16)",
                paper_fit.offline_time_["total"],
                f"{PAPER['offline']:,.0f} s",
            )
        )
    print(
        row(
            "online: one μ, reducer(d)",
            single,
            f"{PAPER['online']} s",
            f"{PAPER['online'] / single[0]:,.0f}x faster",
        )
    )
    print(row("online: one μ, morph_parameters(μ) (with family)", single_mu))
    if paper_single is not None:
        print(row("online: one μ, online='paper'", paper_single))
    print(row(f"online: batch of {args.batch} μ, reducer(d)", batch))
    print(row(f"online: batch of {args.batch} μ, reducer(d, out=buffer)", batch_out))
    print(row(f"online: batch of {args.batch} μ, morph_parameters(μ)", batch_mu))
    print(
        row(
            "full IDW: one μ",
            full_single,
            f"{PAPER['idw']} s",
            f"POD {full_single[0] / single[0]:,.0f}x faster than full",
        )
    )
    print(row(f"full IDW: batch of {args.full_batch} μ", full_batch))
    print(
        row(
            f"full IDW: batch of {args.batch} μ (extrapolated ×{args.batch / args.full_batch:g})",
            full_extrapolated,
            "",
            f"POD {full_extrapolated / batch[0]:,.0f}x faster",
        )
    )
    print()
    print("| POD basis of the fit's snapshots | median | | ratio |")
    print("|---|---|---|---|")
    for line in comparison:
        print(line)
    print()
    print(
        f"relative nodal error of the reduced morph on 20 fresh μ: max {float(error.max()):.2e}"
        + (
            f"; paper variant: max {float(paper_error.max()):.2e}"
            if paper_error is not None
            else ""
        )
    )
    verdict = {True: "met", False: "MISSED"}
    print(
        f"targets (medians): offline <= 10 s: {verdict[offline['total'] <= 10]} "
        f"(fit {offline['total']:.2f} s, with W assembly {setup + offline['total']:.2f} s); "
        f"online <= 1 ms per μ: {verdict[single[0] <= 1e-3]}; "
        f"<= 0.1 s per {args.batch} μ: {verdict[batch[0] <= 0.1]} (fresh output), "
        f"{verdict[batch_out[0] <= 0.1]} (out=)"
    )
    print(f"sizes: {num_controls} controls, {num_targets} targets")


if __name__ == "__main__":
    main()
