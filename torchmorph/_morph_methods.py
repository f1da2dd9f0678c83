"""The interpolants a :class:`~torchmorph.morph.MeshMorph` moves its interior nodes with:
IDW (the paper's eq. 2, :class:`~torchmorph.idw.IDW`) or radial basis functions
(:class:`~torchmorph.rbf.RBF`). Each method's options are checked here (an option of the
other method is an error naming it) and the module is built from them."""

from __future__ import annotations

from typing import Any, Literal

import torch
from torch import Tensor, nn

from torchmorph._checks import check_choice, check_positive
from torchmorph.idw.functional import DEFAULT_COINCIDENCE_TOLERANCE
from torchmorph.idw.module import IDW
from torchmorph.idw.stiffened import StiffenedIDW
from torchmorph.rbf import partition
from torchmorph.rbf.kernels import WENDLAND
from torchmorph.rbf.module import RBF
from torchmorph.rbf.partition import PartitionRBF
from torchmorph.rbf.solvers import PARTITION_CONTROLS, sparse_fits
from torchmorph.rbf.sparse import SparseRBF

__all__ = [
    "IDW_OPTIONS",
    "METHODS",
    "RBF_OPTIONS",
    "Method",
    "build_interpolant",
    "check_method_options",
    "check_moved_points",
    "check_transforms",
    "interpolation_matrix",
    "solver_of",
]

Method = Literal["idw", "rbf"]

METHODS = ("idw", "rbf")
#: Options that only IDW takes, with their defaults.
IDW_OPTIONS: dict[str, Any] = {
    "power": 4.0,
    "implementation": "auto",
    "coincidence_tolerance": DEFAULT_COINCIDENCE_TOLERANCE,
    "stiffening_length": None,
    "stiffening_power": None,
    "tolerance": None,
    "error_control": None,
}
#: Options that only RBF takes, with their defaults (epsilon and support_radius: RBF's).
RBF_OPTIONS: dict[str, Any] = {
    "kernel": "thin_plate_spline",
    "epsilon": None,
    "degree": 1,
    "support_radius": None,
    "solver": None,
    "fit_tolerance": None,
}
#: The storage modes of each method.
MODES = {"idw": ("auto", "dense", "matrix_free", "tree"), "rbf": ("auto", "dense", "matrix_free")}


def check_method_options(method: str, mode: str, options: dict[str, Any]) -> dict[str, Any]:
    """The options of ``method`` with their defaults filled in.

    ``options`` maps every IDW and RBF option to the value given, None where it was not
    given. Raises ``ValueError`` naming the argument for an unknown method, an option of
    the other method, or a mode the method does not have.
    """
    check_choice(method, "method", METHODS)
    own, other = (IDW_OPTIONS, RBF_OPTIONS) if method == "idw" else (RBF_OPTIONS, IDW_OPTIONS)
    for name in other:
        if options.get(name) is not None:
            raise ValueError(
                f"{name}: an option of method={'rbf' if method == 'idw' else 'idw'!r}, not of "
                f"method={method!r} (which takes {', '.join(own)})"
            )
    if method != "idw" and mode in MODES["idw"] and mode not in MODES[method]:
        kinds = ", ".join(repr(kind) for kind in MODES[method])
        raise ValueError(f"mode: {mode!r} is IDW's; method={method!r} takes {kinds}")
    check_choice(mode, "mode", MODES[method])
    if options.get("stiffening_power") is not None and options.get("stiffening_length") is None:
        raise ValueError(
            "stiffening_power: near-wall stiffening needs stiffening_length (the thickness "
            "of the layer that moves rigidly); give both, or neither for plain IDW"
        )
    solver = options.get("solver")
    if solver is not None:
        check_choice(solver, "solver", ("auto", "dense", "partition", "sparse"))
        if solver != "dense" and mode != "auto":
            raise ValueError(
                f"mode: solver={solver!r} may fit the partition-of-unity or the sparse RBF, "
                f"which have no dense or matrix-free choice; leave mode='auto' (got {mode!r})"
            )
    if options.get("fit_tolerance") is not None:
        check_positive(options["fit_tolerance"], "fit_tolerance")
    if options.get("fit_tolerance") is not None and solver not in ("partition", "auto"):
        raise ValueError(
            "fit_tolerance: the partition of unity's global fit (solver='partition' or "
            f"'auto'); solver={solver or 'dense'!r} is the global fit already"
        )
    if options.get("stiffening_length") is not None:
        if mode == "tree":
            raise ValueError("mode: near-wall stiffening (stiffening_length) has no tree mode")
        for name in ("tolerance", "error_control"):  # auto with a tolerance: exact
            if options.get(name) is not None and (name, mode) != ("tolerance", "auto"):
                raise ValueError(
                    f"{name}: the tree's, and near-wall stiffening (stiffening_length) has "
                    f"no tree mode (got mode={mode!r})"
                )
    return {
        name: default if options.get(name) is None else options[name]
        for name, default in own.items()
    }


def solver_of(interpolant: nn.Module) -> str:
    """The kind of an RBF fit: "partition", "sparse" or "dense" (IDW's too)."""
    if isinstance(interpolant, PartitionRBF):
        return "partition"
    return "sparse" if isinstance(interpolant, SparseRBF) else "dense"


def check_moved_points(interpolant: nn.Module) -> None:
    """``ValueError`` naming ``points`` when ``interpolant`` is fitted to the reference
    positions once (the partition-of-unity and the sparse RBF)."""
    solver = solver_of(interpolant)
    if solver != "dense":
        name = "partition-of-unity" if solver == "partition" else solver
        raise ValueError(
            f"points: the {name} RBF (solver={solver!r}) is fitted to the reference "
            "positions once; moved points need solver='dense' or method='idw'"
        )


def build_interpolant(
    method: str,
    controls: Tensor,
    targets: Tensor,
    *,
    mode: str,
    block_bytes: int | None,
    dense_bytes: int | None,
    options: dict[str, Any],
) -> IDW | StiffenedIDW | RBF | PartitionRBF | SparseRBF:
    """The interpolation from ``controls`` (N_c, D) to ``targets`` (N_t, D) of ``method``,
    with the options of :func:`check_method_options` (IDW with near-wall stiffening,
    :class:`~torchmorph.idw.StiffenedIDW`, when ``stiffening_length`` is given; RBF by a
    partition of unity, :class:`~torchmorph.rbf.PartitionRBF`, with ``solver="partition"``;
    the sparse fit of a Wendland kernel, :class:`~torchmorph.rbf.SparseRBF`, with
    ``"sparse"``; ``"auto"`` takes one of them beyond
    :data:`~torchmorph.rbf.PARTITION_CONTROLS` controls, as
    :func:`~torchmorph.rbf.build_rbf` does)."""
    kind: type[IDW] | type[StiffenedIDW] | type[RBF] = RBF
    if method == "rbf":
        options = dict(options)
        solver = options.pop("solver") or "dense"
        fit_tolerance = options.pop("fit_tolerance")
        if solver == "auto" and controls.shape[0] > PARTITION_CONTROLS:
            solver = "sparse" if sparse_fits(controls, options) else "partition"
        if solver == "sparse":
            if options.pop("epsilon") is not None and options["kernel"] in WENDLAND:
                raise ValueError(
                    f"epsilon must be None for kernel={options['kernel']!r}: its scale is "
                    "support_radius"
                )
            return SparseRBF(controls, targets, **options)
        if solver == "partition":  # the module's defaults, read now
            return PartitionRBF(
                controls,
                targets,
                block_bytes=block_bytes,
                patch_size=partition.DEFAULT_PATCH_SIZE,
                coarse_size=partition.DEFAULT_COARSE_SIZE,
                tolerance=fit_tolerance,
                **options,
            )
    if method == "idw":
        options = dict(options)
        length, steep = options.pop("stiffening_length"), options.pop("stiffening_power")
        kind = IDW
        if length is not None:
            kind = StiffenedIDW
            options.update(stiffening_length=length, stiffening_power=steep)
            for name in ("tolerance", "error_control"):  # exact; refused above but in auto
                options.pop(name)
    return kind(
        controls,
        targets,
        mode=mode,  # type: ignore[arg-type]
        block_bytes=block_bytes,
        dense_bytes=dense_bytes,
        **options,
    )


def interpolation_matrix(interpolant: nn.Module, num_controls: int, dim: int) -> Tensor:
    """W (N_t, N_c) of a linear interpolant that maps every component alike
    (``interpolant(d)[:, k] = W @ d[:, k]``): the interpolant applied to the unit columns,
    ``dim`` of them per batch member, in one batched call."""
    reference = next(interpolant.buffers())
    count = -(-num_controls // dim)
    unit = torch.eye(count * dim, num_controls, dtype=reference.dtype, device=reference.device)
    probe = unit.reshape(count, dim, num_controls).transpose(1, 2)  # (count, N_c, D)
    with torch.no_grad():
        values = interpolant(probe.contiguous())  # values[b, :, k] = W[:, b * dim + k]
    return values.transpose(1, 2).reshape(count * dim, -1)[:num_controls].T.contiguous()


def check_transforms(method: str, boundary_displacement: Tensor, points: Tensor | None) -> None:
    """Raise ``ValueError`` naming the argument where ``method`` cannot follow a
    ``torch.func`` transform: an RBF's stored factorisation is solved by LAPACK calls that
    neither ``vmap`` nor forward-mode differentiation pass through, so a transformed
    displacement, or moved points under ``vmap``, are refused (reverse-mode transforms of
    the points, ``grad`` and ``jacrev``, re-solve the system in torch and work)."""
    functorch = getattr(torch._C, "_functorch", None)
    if method == "idw" or functorch is None:
        return
    hint = (
        "differentiate with torch.autograd (backward(), torch.autograd.functional.jacobian) "
        "or use method='idw'"
    )
    if functorch.is_functorch_wrapped_tensor(boundary_displacement):
        raise ValueError(
            "boundary_displacement: torch.func transforms (vmap, grad, jacrev, jacfwd) of the "
            f"displacement of a method={method!r} morph are not supported; {hint}"
        )
    if points is not None and functorch.is_batchedtensor(points):
        raise ValueError(
            f"points: vmap over the points of a method={method!r} morph is not supported; "
            "batch the displacement instead, or loop over the points"
        )
