"""The default path: what a user's first ``IDW(controls, targets)(d)`` costs.

Two clouds, one thread, medians of ``--repeats`` (ratios within the same run):

1. case C's counts (3,864 surface controls on a sphere, 3,322 targets in the box around
   it), float64: a plain NumPy version (``cdist``, ``w = D**-4``, normalise, ``w @ d``)
   against ``IDW(controls, targets)(d)`` with default arguments (build plus one morph),
   ``idw_apply`` (one shot), a cached matrix-free call and a stored dense W's product;
2. 20,000 controls on a sphere and 100,000 targets in the box around it, float32:
   ``idw_apply`` and the default module's build plus first call against a cached
   matrix-free call.

    python benchmarks/default_path.py
"""

from __future__ import annotations

import argparse
import platform

import torch
from _timing import median_time
from scipy.spatial.distance import cdist

from torchmorph.idw import IDW, idw_apply


def cloud(n_controls: int, n_targets: int, dtype: torch.dtype, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    controls = torch.randn(n_controls, 3, generator=generator, dtype=torch.float64)
    controls /= controls.norm(dim=1, keepdim=True)
    targets = 4 * torch.rand(n_targets, 3, generator=generator, dtype=torch.float64) - 2
    displacement = 0.01 * torch.randn(n_controls, 3, generator=generator, dtype=torch.float64)
    return controls.to(dtype), targets.to(dtype), displacement.to(dtype)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, {platform.machine()}, one thread\n")

    controls, targets, d = cloud(3864, 3322, torch.float64)
    c, t, dn = controls.numpy(), targets.numpy(), d.numpy()

    def numpy_version():
        w = cdist(t, c) ** -4
        w /= w.sum(1, keepdims=True)
        return w @ dn

    cached = IDW(controls, targets, mode="matrix_free")
    dense = IDW(controls, targets, mode="dense")
    rows = {
        "NumPy (cdist, D**-4, normalise, w @ d)": median_time(numpy_version, args.repeats),
        f"IDW(c, t)(d), default (mode {IDW(controls, targets).mode!r})": median_time(
            lambda: IDW(controls, targets)(d), args.repeats
        ),
        "idw_apply, one shot": median_time(
            lambda: idw_apply(controls=controls, targets=targets, displacements=d), args.repeats
        ),
        "cached matrix-free call": median_time(lambda: cached(d), args.repeats),
        "stored dense W, one product": median_time(lambda: dense(d), args.repeats),
        "IDW(c, t, mode='dense')(d): assembly + product": median_time(
            lambda: IDW(controls, targets, mode="dense")(d), args.repeats
        ),
    }
    base = rows["NumPy (cdist, D**-4, normalise, w @ d)"]
    print("3,864 controls x 3,322 targets, float64\n")
    print("| | ms | speed-up over NumPy |\n|---|---:|---:|")
    for name, seconds in rows.items():
        print(f"| {name} | {1e3 * seconds:.1f} | {base / seconds:.1f}x |")

    controls, targets, d = cloud(20_000, 100_000, torch.float32)
    cached = IDW(controls, targets, mode="matrix_free")
    repeats = max(1, args.repeats // 2)
    rows = {
        "cached matrix-free call": median_time(lambda: cached(d), repeats),
        "idw_apply, one shot": median_time(
            lambda: idw_apply(controls=controls, targets=targets, displacements=d), repeats
        ),
        f"IDW(c, t)(d), default (mode {IDW(controls, targets).mode!r})": median_time(
            lambda: IDW(controls, targets)(d), repeats
        ),
    }
    base = rows["cached matrix-free call"]
    print("\n20,000 controls x 100,000 targets, float32\n")
    print("| | s | against a cached call |\n|---|---:|---:|")
    for name, seconds in rows.items():
        print(f"| {name} | {seconds:.3f} | {seconds / base:.2f}x |")
    exact = IDW(controls.double(), targets.double(), mode="matrix_free")(d.double())
    error = (cached(d).double() - exact).abs().max() / d.double().abs().max()
    print(f"\nfloat32 matrix-free error against float64: {float(error):.1e} of max|d|")


if __name__ == "__main__":
    main()
