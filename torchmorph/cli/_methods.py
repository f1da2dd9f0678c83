"""``torchmorph morph``'s interpolation methods: IDW (``--power``, near-wall
``--stiffening``) or radial basis functions
(``--method rbf`` with ``--kernel``, ``--shape-parameter``, ``--support-radius``,
``--degree``), checked together and turned into :class:`~torchmorph.morph.MeshMorph`'s
keyword arguments.

The RBF's shape parameter is ``--shape-parameter`` (the library's ``epsilon``):
``--epsilon`` is fTetWild's envelope in ``torchmorph mesh``, and a flag means one thing in
every subcommand."""

from __future__ import annotations

import argparse
from typing import Any

from torchmorph.cli._common import _positive_float
from torchmorph.rbf.kernels import KERNELS, SCALE_INVARIANT, WENDLAND

__all__: list[str] = []

#: IDW's exponent when ``--power`` is not given (the paper's).
DEFAULT_POWER = 4.0
#: The RBF options and the library argument each one sets.
RBF_FLAGS = {
    "--kernel": "kernel",
    "--shape-parameter": "epsilon",
    "--support-radius": "support_radius",
    "--degree": "degree",
}


def _degree(text: str) -> int:
    try:
        number = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if number < -1:
        raise argparse.ArgumentTypeError(f"must be an integer >= -1 (-1: none), got {text!r}")
    return number


def add_method_arguments(parser: argparse.ArgumentParser) -> None:
    """The interpolation-method options of ``torchmorph morph``."""
    group = parser.add_argument_group(
        "interpolation method (default: IDW, the paper's eq. 2)",
        "--method rbf moves the interior by radial basis functions from the same controls",
    )
    group.add_argument(
        "--method",
        choices=("idw", "rbf"),
        default="idw",
        help="inverse distance weighting (idw, default) or radial basis functions with a "
        "polynomial tail (rbf: exact at the controls, affine motions reproduced)",
    )
    group.add_argument(
        "--power",
        type=_positive_float,
        default=None,
        help=f"IDW exponent p (default {DEFAULT_POWER:g}, the paper's); IDW only",
    )
    group.add_argument(
        "--stiffening",
        type=_positive_float,
        default=None,
        metavar="LENGTH",
        help="IDW with near-wall stiffening: weights r^-p + L^(q-p) r^-q, so that nodes "
        "within about LENGTH (mesh units) of the controls move nearly rigidly with them "
        "(a boundary layer's thickness); IDW only",
    )
    group.add_argument(
        "--stiffening-power",
        type=_positive_float,
        default=None,
        metavar="Q",
        help="with --stiffening: the near-wall exponent q > p (default p + 2)",
    )
    group.add_argument(
        "--mode",
        choices=("auto", "dense", "matrix_free", "tree"),
        default="auto",
        help="store W (dense; RBF: its evaluation matrix), recompute it in tiles "
        "(matrix_free), choose by size (auto), or (IDW, CPU, large meshes) sum far "
        "controls by clusters to --tree-tolerance (tree)",
    )
    group.add_argument(
        "--tree-tolerance",
        type=_positive_float,
        default=None,
        metavar="TOL",
        help="with --mode tree: the relative error of the morph (default 1e-4), kept by "
        "exact sums at sampled nodes (the library's error_control='sampled'); with --mode "
        "auto: lets auto take the tree where it was measured faster than the exact sum",
    )
    group.add_argument(
        "--rbf-solver",
        choices=("dense", "partition", "sparse", "auto"),
        default=None,
        help="with --method rbf: the dense fit (default), the partition of unity for "
        "10^4 controls and more (a coarse global fit plus local patches), the sparse global "
        "fit of a Wendland kernel (--kernel wendland_c2 --support-radius R), or auto",
    )
    group.add_argument(
        "--fit-tolerance",
        type=_positive_float,
        default=None,
        metavar="TOL",
        help="with --method rbf --rbf-solver partition (or auto where it takes the "
        "partition): fit the global interpolant itself to this tolerance, by iterations the "
        "partition preconditions and a treecode for the thin-plate sums (1e-4 came within "
        "1e-5 of the dense fit on a wing in a box)",
    )
    group.add_argument(
        "--kernel",
        choices=tuple(KERNELS),
        default=None,
        metavar="NAME",
        help="with --method rbf: the radial function (default thin_plate_spline); "
        f"{', '.join(KERNELS)}",
    )
    group.add_argument(
        "--shape-parameter",
        type=_positive_float,
        default=None,
        metavar="E",
        help="with --method rbf: the shape parameter scaling distances (scipy's epsilon); "
        f"default 1 for {', '.join(SCALE_INVARIANT)}, required for the other global "
        "kernels, not taken by the Wendland kernels",
    )
    group.add_argument(
        "--support-radius",
        type=_positive_float,
        default=None,
        metavar="R",
        help=f"with --method rbf: the support radius, required by (and only by) "
        f"{', '.join(WENDLAND)}",
    )
    group.add_argument(
        "--degree",
        type=_degree,
        default=None,
        metavar="K",
        help="with --method rbf: degree of the polynomial tail (default 1; -1: none)",
    )


def method_options(args: argparse.Namespace) -> dict[str, Any]:
    """MeshMorph's method keyword arguments from the options; ``args.parser.error`` (exit
    code 2) for a combination that does not go together."""
    error = args.parser.error
    if args.tree_tolerance is not None and args.mode not in ("tree", "auto"):
        error("argument --tree-tolerance: needs --mode tree or auto")
    if args.tree_tolerance is not None and args.method != "idw":
        error("argument --tree-tolerance: the IDW tree's; not with --method rbf")
    if args.method == "idw" and args.rbf_solver is not None:
        error("argument --rbf-solver: an RBF option; needs --method rbf")
    if args.method == "idw" and args.fit_tolerance is not None:
        error("argument --fit-tolerance: an RBF option; needs --method rbf")
    if args.fit_tolerance is not None and args.rbf_solver not in ("partition", "auto"):
        error(
            "argument --fit-tolerance: the partition of unity's global fit; needs "
            "--rbf-solver partition or auto"
        )
    if args.method == "idw":
        for flag, name in RBF_FLAGS.items():
            if getattr(args, name if name != "epsilon" else "shape_parameter") is not None:
                error(f"argument {flag}: an RBF option; needs --method rbf")
        power = DEFAULT_POWER if args.power is None else args.power
        options: dict[str, Any] = {"method": "idw", "power": power}
        if args.mode == "tree":
            if args.stiffening is not None:
                error("argument --stiffening: near-wall stiffening has no --mode tree")
            options.update(tolerance=args.tree_tolerance or 1e-4, error_control="sampled")
        elif args.tree_tolerance is not None:  # auto: the tree where it pays, else exact
            options.update(tolerance=args.tree_tolerance)
        if args.stiffening_power is not None and args.stiffening is None:
            error("argument --stiffening-power: needs --stiffening LENGTH")
        if args.stiffening is not None:
            steep = power + 2.0 if args.stiffening_power is None else args.stiffening_power
            if steep <= power:
                error(f"argument --stiffening-power: must be larger than --power ({power:g})")
            options.update(stiffening_length=args.stiffening, stiffening_power=steep)
        return options
    if args.power is not None:
        error("argument --power: the IDW exponent; --method rbf takes --kernel and its options")
    if args.mode == "tree":
        error("argument --mode: tree is IDW's; --method rbf takes auto, dense or matrix_free")
    if args.rbf_solver not in (None, "dense") and args.mode != "auto":
        error(
            f"argument --mode: --rbf-solver {args.rbf_solver} may fit the partition of unity "
            "or the sparse RBF, which have no storage mode; leave --mode auto"
        )
    if args.stiffening is not None or args.stiffening_power is not None:
        flag = "--stiffening" if args.stiffening is not None else "--stiffening-power"
        error(f"argument {flag}: near-wall stiffening of IDW weights; not with --method rbf")
    if args.rotations:
        error(
            "argument --rotations: rotation-aware morphing blends IDW weights; not with "
            "--method rbf (--steps K is)"
        )
    kernel = args.kernel or "thin_plate_spline"
    if args.rbf_solver == "sparse" and kernel not in WENDLAND:
        error(
            f"argument --rbf-solver: sparse needs a compactly supported --kernel "
            f"({', '.join(WENDLAND)}) with --support-radius; --kernel is {kernel}"
        )
    if kernel in WENDLAND:
        if args.support_radius is None:
            error(f"argument --support-radius: required with --kernel {kernel}")
        if args.shape_parameter is not None:
            error(
                f"argument --shape-parameter: --kernel {kernel} is scaled by --support-radius, "
                "not a shape parameter"
            )
    else:
        if args.support_radius is not None:
            error(
                f"argument --support-radius: only the compactly supported kernels "
                f"({', '.join(WENDLAND)}) take one; --kernel is {kernel}"
            )
        if args.shape_parameter is None and kernel not in SCALE_INVARIANT:
            error(
                f"argument --shape-parameter: required with --kernel {kernel} (only "
                f"{', '.join(SCALE_INVARIANT)} default to 1)"
            )
    return {
        "method": "rbf",
        "kernel": kernel,
        "epsilon": args.shape_parameter,
        "support_radius": args.support_radius,
        "degree": 1 if args.degree is None else args.degree,
        "solver": args.rbf_solver,
        "fit_tolerance": args.fit_tolerance,
    }


def method_summary(morph: Any) -> str:
    """What the morph interpolates with, for the command's report."""
    if morph.method == "idw":
        idw = morph.idw
        stiffening = getattr(idw, "stiffening_length", None)
        if stiffening is not None:
            return (
                f"IDW, p={idw.power:g}, stiffened near the walls (q={idw.stiffening_power:g}, "
                f"length {stiffening:g})"
            )
        return f"IDW, p={idw.power:g}"
    rbf = morph.rbf
    fit = "" if getattr(rbf, "num_patches", None) is None else f", {rbf.num_patches} patches"
    if getattr(rbf, "tolerance", None) is not None:
        fit += f", the global fit to {rbf.tolerance:g}"
    scale = (
        f"support radius {rbf.support_radius:g}"
        if rbf.support_radius is not None
        else f"shape parameter {rbf.epsilon:g}"
    )
    return f"RBF {rbf.kernel}, {scale}, polynomial degree {rbf.degree}{fit}"
