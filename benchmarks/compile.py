"""Eager versus ``torch.compile`` (inductor, ``fullgraph=True``) for the morphs' forward.

Problems (the paper's meshes from ``data_gen``, every boundary node a control point):

- dense IDW forward ``W d``, case A (structural wing) and case C (hull) sizes, one
  displacement and a batch of 100;
- POD online forward of a :class:`MeshMorph`-fitted reducer (POD-IDW, case C, hull
  rotation, two modes), one μ and a batch of 1000 — from the boundary displacement
  to the full nodal field.

Each row: median wall time of ``--repeats`` calls after warm-up (the first compiled
call compiles; its time is reported separately), under ``torch.no_grad()``, and the
speed-up. ``fullgraph=True`` makes a graph break an error: a row reads "graph break"
instead of a time when that happens. Timings on a shared 2-core machine are noisy.

Run ``python benchmarks/compile.py`` (a few minutes, mostly compilation);
``--dtype float32``, ``--size small`` for the small meshes, ``--threads N``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's data_gen

from _timing import median_time, seconds

from torchmorph.morph import MeshMorph
from torchmorph.paper import CASES, load_mesh
from torchmorph.pod import PODReducer


def compare(module: torch.nn.Module, argument: torch.Tensor, repeats: int) -> dict:
    """Eager and compiled medians, compile time, and the largest difference."""
    torch._dynamo.reset()
    with torch.no_grad():
        eager_result = module(argument)
        module(argument)
        eager = median_time(lambda: module(argument), repeats, warmup=0)
        compiled = torch.compile(module, fullgraph=True)
        start = time.perf_counter()
        try:
            compiled_result = compiled(argument)
        except (torch._dynamo.exc.TorchDynamoException, RuntimeError) as error:
            # a graph break under fullgraph=True, or no working C++ compiler
            return {"eager": eager, "error": f"{type(error).__name__}: {str(error)[:200]}"}
        compile_time = time.perf_counter() - start
        compiled(argument)
        fast = median_time(lambda: compiled(argument), repeats, warmup=0)
    difference = float((compiled_result - eager_result).abs().max())
    scale = float(eager_result.abs().max())
    return {
        "eager": eager,
        "compiled": fast,
        "compile": compile_time,
        "difference": difference / scale if scale else difference,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", choices=("small", "paper"), default="paper")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--batch", type=int, default=1000, help="POD batch (default 1000)")
    parser.add_argument("--idw-batch", type=int, default=100, help="IDW batch (default 100)")
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    generator = torch.Generator().manual_seed(0)
    load_before = os.getloadavg()[0]

    rows = []
    for key, letter in (("wing", "A"), ("hull", "C")):
        spec = CASES[key]
        mesh = load_mesh(key, size=args.size).to(dtype=dtype)
        morph = MeshMorph(mesh)
        idw = morph.idw
        family = spec.family(morph)
        mus = spec.domain[0] + (spec.domain[1] - spec.domain[0]) * torch.rand(
            max(args.batch, args.idw_batch), generator=generator, dtype=dtype
        )
        label = f"case {letter}: {idw.num_controls} controls x {idw.num_targets} targets"
        controls = morph.controls_from_boundary(family(mus[: args.idw_batch]))
        rows.append(
            (
                f"IDW dense forward, {label}, one displacement",
                compare(idw, controls[0].contiguous(), args.repeats),
            )
        )
        rows.append(
            (
                f"IDW dense forward, {label}, batch of {args.idw_batch}",
                compare(idw, controls, max(3, args.repeats // 4)),
            )
        )
        if key == "hull":
            training = spec.training_parameters(0, dtype=dtype)
            reducer = PODReducer().fit(morph, family=family, parameters=training)
            boundary = family(mus[: args.batch])
            pod_label = (
                f"POD online forward, case C mesh ({mesh.num_nodes} nodes, "
                f"{reducer.num_modes_} modes)"
            )
            rows.append(
                (
                    f"{pod_label}, one μ",
                    compare(reducer, boundary[0].contiguous(), args.repeats * 5),
                )
            )
            rows.append(
                (
                    f"{pod_label}, batch of {args.batch}",
                    compare(reducer, boundary, max(3, args.repeats // 4)),
                )
            )
    load_after = os.getloadavg()[0]

    print(f"## torch.compile: eager vs inductor (fullgraph=True), {args.size} meshes")
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{platform.processor() or platform.machine()}, {args.dtype}, CPU, load average "
        f"{load_before:.1f} -> {load_after:.1f}; medians of {args.repeats} (batches: fewer)"
    )
    print()
    print("| forward | eager | compiled | speed-up | first call (compile) | max rel. difference |")
    print("|---|---|---|---|---|---|")
    for name, row in rows:
        if "error" in row:
            print(f"| {name} | {seconds(row['eager'])} | graph break | – | – | {row['error']} |")
            continue
        print(
            f"| {name} | {seconds(row['eager'])} | {seconds(row['compiled'])} | "
            f"{row['eager'] / row['compiled']:.2f}x | {row['compile']:.1f} s | "
            f"{row['difference']:.1e} |"
        )


if __name__ == "__main__":
    main()
