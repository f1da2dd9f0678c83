"""GPU timings of the morphs at case-B size (fluid wing in a tunnel).

Rows (median of ``--repeats`` after warm-up, CUDA-synchronised):

- IDW dense: assembly of W (every boundary node a control point, every interior
  node a target), apply to one displacement, to a batch of ``--batch``, and one
  apply with its backward pass (gradient to the displacement);
- IDW matrix-free: one displacement, and a batch of 10;
- POD online forward (POD-IDW fitted to the case-B family δy = μ z² on the wing):
  one μ, and a batch of ``--batch``;
- the full Algorithm 2 morph (``MeshMorph.forward``), one μ.

The mesh is ``data_gen.build("fluid_wing", size)``; without the ``mesh`` extra (gmsh)
a random point cloud of the paper's case-B counts is used instead (14,126 controls,
21,910 targets; IDW rows only, said so in the title).

Run ``python benchmarks/gpu.py`` on a machine with a CUDA device; it prints a
markdown table headed with the device's name. Without a GPU it says so and exits
with status 0. ``--device cpu --size small`` runs the same code on the CPU (a smoke
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

from torchmorph.idw import IDW
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
    label = (f"case-B mesh ({size}): {mesh.num_nodes} nodes, {morph.num_controls} controls, "
             f"{morph.num_interior} interior nodes")
    controls = morph.points[morph.control_nodes]
    targets = morph.points[morph.interior_nodes]
    return morph, controls, targets, family, label


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", help="default cuda")
    parser.add_argument("--size", choices=("small", "paper"), default="paper")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--batch", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("benchmarks/gpu.py: no CUDA device is available (torch "
              f"{torch.__version__}, CUDA build: {torch.version.cuda or 'none'}); nothing to "
              "time. Run it on a machine with a GPU.")
        return 0
    dtype = getattr(torch, args.dtype)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    generator = torch.Generator().manual_seed(0)

    morph, controls, targets, family, label = load_problem(args.size, dtype)
    controls, targets = controls.to(device), targets.to(device)
    mus = DOMAIN[0] + (DOMAIN[1] - DOMAIN[0]) * torch.rand(args.batch, generator=generator,
                                                           dtype=dtype)
    mus = mus.to(device)
    if morph is not None:
        morph = morph.to(device)
        boundary = family(mus)  # (B, N_b, 3)
        inputs = morph.controls_from_boundary(boundary)  # every boundary node: the same
    else:
        inputs = family(mus)
    rows: list[tuple[str, float]] = []
    # median of the repeats after two warm-up calls, CUDA-synchronised
    timed = partial(median_time, warmup=2, device=device)

    with torch.no_grad():
        assembly = timed(lambda: IDW(controls, targets, mode="dense"),
                         max(1, args.repeats // 3), warmup=1)
        rows.append((f"IDW dense: assemble W ({targets.shape[0]:,} x {controls.shape[0]:,})",
                     assembly))
        dense = IDW(controls, targets, mode="dense")
        one = inputs[0].contiguous()
        rows.append(("IDW dense: apply, one displacement",
                     timed(lambda: dense(one), args.repeats * 10)))
        rows.append((f"IDW dense: apply, batch of {args.batch}",
                     timed(lambda: dense(inputs), args.repeats)))
    probe = one.clone().requires_grad_(True)

    def apply_backward():
        dense(probe).square().sum().backward()

    rows.append(("IDW dense: apply + backward, one displacement",
                 timed(apply_backward, args.repeats * 10)))
    with torch.no_grad():
        free = IDW(controls, targets, mode="matrix_free")
        rows.append(("IDW matrix-free: one displacement",
                     timed(lambda: free(one), args.repeats)))
        ten = inputs[:10].contiguous()
        rows.append(("IDW matrix-free: batch of 10",
                     timed(lambda: free(ten), max(1, args.repeats // 2))))
        if morph is not None:
            dense_morph = _with_dense_weights(morph)
            training = DOMAIN[0] + (DOMAIN[1] - DOMAIN[0]) * torch.rand(
                20, generator=generator, dtype=dtype)
            start = time.perf_counter()
            reducer = PODReducer().fit(dense_morph, family=family,
                                       parameters=training.to(device))
            synchronise(device)
            rows.append((f"POD fit (20 snapshots, {reducer.num_modes_} mode(s))",
                         time.perf_counter() - start))
            single = boundary[0].contiguous()
            rows.append(("POD online: one μ",
                         timed(lambda: reducer(single), args.repeats * 10)))
            rows.append((f"POD online: batch of {args.batch}",
                         timed(lambda: reducer(boundary), args.repeats)))
            rows.append(("MeshMorph (Algorithm 2, dense W): one μ",
                         timed(lambda: dense_morph(single), args.repeats * 10)))

    print(f"## GPU: {name}")
    print(f"torch {torch.__version__}, CUDA {torch.version.cuda or '-'}, {args.dtype}; {label}; "
          f"medians of {args.repeats} (single applies: {args.repeats * 10})")
    print()
    print("| step | time |")
    print("|---|---|")
    for step, value in rows:
        print(f"| {step} | {seconds(value)} |")
    return 0


def _with_dense_weights(morph: MeshMorph) -> MeshMorph:
    """``morph`` with its IDW replaced by a dense one, W assembled on the morph's device."""
    morph.idw = IDW(morph.idw.controls, morph.idw.targets, mode="dense",
                    power=morph.idw.power)
    morph.assembly_time = morph.idw.assembly_time
    return morph


if __name__ == "__main__":
    sys.exit(main())
