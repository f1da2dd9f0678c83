"""Free-form deformation (:class:`torchmorph.ffd.FFD`) against PyGeM's formula and PyGeM.

One torch thread, float64. The box: origin (0.1, −0.2, 0.3), lengths (1.2, 0.7, 0.9),
rotated by PyGeM's angles (10°, −20°, 35°); the points uniform in the box's local
coordinates [−0.1, 1.1]³ (58 % of them inside), N = 10^5 and 10^6; lattices 5 × 5 × 5 and
10 × 10 × 10, Bernstein and cubic clamped B-spline bases.

Printed (markdown), medians of repeats after a warm-up:

1. torchmorph: ``build`` (the module: checks, local coordinates, the per-axis bases),
   ``forward`` of one lattice field and of a batch of B = 16 fields, and the batch's
   time per field.
2. references, Bernstein and B-spline:
   * the NumPy loop formula (PyGeM's formula written out: for each point, a loop over every
     control point of the lattice; B-spline bases from SciPy's design matrix) on a
     subsample of points: seconds per 1,000 points, and the largest difference of the
     moved points from torchmorph's;
   * mathLab's PyGeM ``FFD`` (Bernstein only; ``--pygem PATH``, the folder holding the
     ``pygem`` package of a checkout of github.com/mathLab/PyGeM: it is not on PyPI, whose
     ``pygem`` is another project): one call on all N points (``--pygem-points`` for
     fewer, then extrapolated linearly to N and said so in the table), 16 calls for a
     batch of 16; the ratios to torchmorph's build and one forward (a PyGeM call
     evaluates the bases too) and to torchmorph's batch of 16 (the module built once);
     and the largest difference from torchmorph's moved points (PyGeM's
     parameters are torchmorph's displacements divided by the lengths, in the box's
     axes).

Run ``python benchmarks/ffd.py [--pygem PATH] [--quick]`` (about 3 minutes on one core
with PyGeM; ``--quick``: N = 10^4 and 10^5 only).
"""

from __future__ import annotations

import argparse
import importlib
import math
import platform
import sys
import time

import numpy as np
import torch
from _timing import median_time, seconds
from scipy.interpolate import BSpline

from torchmorph.ffd import FFD, clamped_uniform_knots

ORIGIN = np.array([0.1, -0.2, 0.3])
LENGTHS = np.array([1.2, 0.7, 0.9])
ANGLES = np.array([10.0, -20.0, 35.0])  # PyGeM's rot_angle (degrees, about x, y, z)
BATCH = 16


def rotation_matrix(angles_degrees: np.ndarray) -> np.ndarray:
    """PyGeM's ``angles2matrix``: R = R_x R_y R_z."""
    x, y, z = np.radians(angles_degrees)
    rx = np.array([[1, 0, 0], [0, math.cos(x), -math.sin(x)], [0, math.sin(x), math.cos(x)]])
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rz = np.array([[math.cos(z), -math.sin(z), 0], [math.sin(z), math.cos(z), 0], [0, 0, 1]])
    return rx @ ry @ rz


ROTATION = rotation_matrix(ANGLES)


def sample_points(count: int, seed: int = 0) -> np.ndarray:
    local = np.random.default_rng(seed).uniform(-0.1, 1.1, size=(count, 3))
    return ORIGIN + (local * LENGTHS) @ ROTATION.T


def normalised_weights(size: int, batch: int, seed: int = 1) -> np.ndarray:
    """PyGeM's parameters: (batch, n, n, n, 3), along the box axes, over the lengths."""
    return np.random.default_rng(seed).normal(size=(batch, size, size, size, 3)) * 0.05


def physical(mu: np.ndarray) -> np.ndarray:
    return (mu * LENGTHS) @ ROTATION.T


def loop_formula(points: np.ndarray, mu: np.ndarray, basis: str) -> np.ndarray:
    """Moved points by PyGeM's formula, a loop over the lattice for each point."""
    sizes = mu.shape[:3]
    local = (points - ORIGIN) @ ROTATION / LENGTHS
    moved = points.copy()
    for p, s in enumerate(local):
        if not ((s >= 0) & (s <= 1)).all():
            continue
        if basis == "bernstein":
            factors = [
                [math.comb(n - 1, i) * x**i * (1 - x) ** (n - 1 - i) for i in range(n)]
                for n, x in zip(sizes, s, strict=True)
            ]
        else:
            factors = [
                BSpline.design_matrix(np.array([x]), np.array(clamped_uniform_knots(n, 3)), 3)
                .toarray()[0]
                .tolist()
                for n, x in zip(sizes, s, strict=True)
            ]
        shift = np.zeros(3)
        for i, j, k in np.ndindex(*sizes):
            shift += factors[0][i] * factors[1][j] * factors[2][k] * mu[i, j, k]
        moved[p] = points[p] + ROTATION @ (LENGTHS * shift)
    return moved


def load_pygem(path: str | None):
    """mathLab's ``pygem.FFD`` from a checkout, or None (with the reason)."""
    if path is None:
        return None, "no --pygem path given"
    sys.path.insert(0, path)
    try:
        module = importlib.import_module("pygem")
    except ImportError as error:
        return None, f"import failed: {error}"
    if not hasattr(module, "FFD"):
        return None, f"{module.__file__} is not mathLab's PyGeM (no FFD)"
    return module.FFD, module.__file__


def pygem_morph(pygem_ffd, points: np.ndarray, mu: np.ndarray) -> np.ndarray:
    ffd = pygem_ffd(list(mu.shape[:3]))
    ffd.box_origin, ffd.box_length, ffd.rot_angle = ORIGIN.copy(), LENGTHS.copy(), ANGLES.copy()
    ffd.array_mu_x, ffd.array_mu_y, ffd.array_mu_z = mu[..., 0], mu[..., 1], mu[..., 2]
    return ffd(points)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pygem", help="folder holding mathLab's pygem package")
    parser.add_argument("--pygem-points", type=int, help="default: all N points")
    parser.add_argument("--loop-points", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    counts = (10**4, 10**5) if args.quick else (10**5, 10**6)
    pygem_ffd, pygem_note = load_pygem(args.pygem)
    print(
        f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, "
        f"torch {torch.__version__}, numpy {np.__version__}, 1 thread, float64; "
        f"PyGeM: {pygem_note}\n"
    )
    timings, references = [], []
    for count in counts:
        points = sample_points(count)
        for size in (5, 10):
            mu = normalised_weights(size, BATCH)
            batch = torch.from_numpy(physical(mu))
            for basis in ("bernstein", "bspline"):
                tensor = torch.from_numpy(points)

                def build(tensor=tensor, size=size, basis=basis):
                    return FFD(
                        tensor,
                        origin=ORIGIN,
                        lengths=LENGTHS,
                        shape=(size,) * 3,
                        basis=basis,
                        rotation=ROTATION,
                    )

                build_time = median_time(build, args.repeats)
                morph = build()
                single = median_time(lambda m=morph: m(batch[0]), args.repeats)
                batched = median_time(lambda m=morph: m(batch), args.repeats)
                timings.append(
                    f"| {count:,} | {size}³ | {basis} | {morph.num_inside / count:.0%} | "
                    f"{seconds(build_time)} | {seconds(single)} | {seconds(batched)} | "
                    f"{seconds(batched / BATCH)} |"
                )
                moved = points + morph(batch[0]).numpy()
                subsample = slice(0, args.loop_points)
                start = time.perf_counter()
                looped = loop_formula(points[subsample], mu[0], basis)
                loop_time = (time.perf_counter() - start) / args.loop_points * 1000
                loop_error = np.abs(looped - moved[subsample]).max()
                pygem_cells = "– | – | – | –"
                if pygem_ffd is not None and basis == "bernstein":
                    part = points[: args.pygem_points or count]
                    call = median_time(
                        lambda p=part: pygem_morph(pygem_ffd, p, mu[0]), args.repeats
                    )
                    per_call = call * count / len(part)
                    error = np.abs(pygem_morph(pygem_ffd, part, mu[0]) - moved[: len(part)]).max()
                    pygem_cells = (
                        f"{seconds(per_call)}{'' if len(part) == count else ' (extrapolated)'} | "
                        f"{per_call / (build_time + single):,.1f}× | "
                        f"{BATCH * per_call / batched:,.0f}× | {error:.1e}"
                    )
                references.append(
                    f"| {count:,} | {size}³ | {basis} | {seconds(loop_time)} | "
                    f"{loop_error:.1e} | {pygem_cells} |"
                )
                print(timings[-1], file=sys.stderr)
    print("## torchmorph FFD\n")
    print(
        "| N | lattice | basis | inside | build | forward B=1 | forward B=16 | per field (B=16) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(timings))
    print(f"\n## References (NumPy loop on {args.loop_points} points; PyGeM per call)\n")
    print(
        "| N | lattice | basis | loop per 1,000 points | max |Δ| loop | PyGeM per call | "
        "PyGeM / torchmorph build + B=1 | PyGeM ×16 / torchmorph B=16 | max |Δ| PyGeM |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(references))


if __name__ == "__main__":
    main()
