"""The reducers' side of the linear-map protocol, and the checks of a saved state.

:class:`torchmorph.pod.PODReducer` (and :class:`~torchmorph.distributed.ShardedPOD`)
reduce any linear map ``morph(d)``, (B, N_in, D) to (B, N_out, D), D the fields'
dimension (2 or 3). These helpers evaluate training families, ask the map for its
optional parts (``copied_rows``, ``adjoint``, ``weights``, ``weights_matrix`` /
``weight_columns``) and check a state before it is loaded; none of them asks which
class the map is.
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from torchmorph._checks import (
    check_choice,
    check_finite,
    check_float_dtype,
    check_same_device_dtype,
    is_traced,
)
from torchmorph.pod.functional import projection_matrix

__all__ = [
    "ONLINE_VARIANTS",
    "adjoint",
    "as_parameters",
    "check_online",
    "check_reducer_state",
    "copied_rows",
    "evaluate_family",
    "expand",
    "expand_by_runs",
    "index_runs",
    "is_single_value",
    "morph_snapshots",
    "reference_tensor",
    "spread_modes",
    "training_data",
    "training_inputs",
    "weights_of",
]

Family = Callable[[Tensor], Tensor]

ONLINE_VARIANTS = ("projection", "paper")


def check_online(value: str) -> str:
    return check_choice(value, "online", ONLINE_VARIANTS)


def as_parameters(parameters: Any) -> Tensor:
    """Training parameters as a tensor (n,) or (n, P), finite."""
    if parameters is None:
        raise ValueError("parameters must be given with family: shape (n_train,) or (n_train, P)")
    if not isinstance(parameters, Tensor):
        parameters = torch.as_tensor(np.asarray(parameters, dtype=np.float64))
    if parameters.ndim not in (1, 2) or parameters.shape[0] == 0:
        raise ValueError(
            f"parameters must have shape (n_train,) or (n_train, P) with n_train >= 1, "
            f"got {tuple(parameters.shape)}"
        )
    check_finite(parameters, "parameters")
    return parameters


# --------------------------------------------------------------------------------------
# helpers that talk to the morph (through the protocol of the class notes)
# --------------------------------------------------------------------------------------


def reference_tensor(morph: Any) -> Tensor | None:
    """The morph's first floating buffer or parameter (its dtype and device), if any."""
    if not isinstance(morph, nn.Module):
        return None
    for tensor in itertools.chain(morph.buffers(), morph.parameters()):
        if tensor.is_floating_point():
            return tensor
    return None


def training_inputs(value: Any, name: str) -> Tensor:
    """Training inputs (n_train, N_in, D), floating, finite, detached."""
    if not isinstance(value, Tensor):
        value = torch.as_tensor(np.asarray(value, dtype=np.float64))
    if value.ndim != 3 or 0 in value.shape:
        raise ValueError(
            f"{name} must have shape (n_train, N_in, D) with n_train >= 1, got {tuple(value.shape)}"
        )
    check_float_dtype(value, name)
    check_finite(value, name)
    return value.detach()


def training_data(
    displacements: Any, family: Family | None, parameters: Any, batched: bool
) -> tuple[Tensor, int | None]:
    """Training inputs (n, N_in, D) from displacements or a family, and the number of
    parameters P (0 for scalars, None without a family), with every argument checked."""
    if family is None:
        if parameters is not None:
            raise ValueError(
                "parameters given without family: pass family=callable or training displacements"
            )
        if displacements is None:
            raise ValueError(
                "no training data: pass displacements (n_train, N_in, D) or family= and parameters="
            )
        return training_inputs(displacements, "displacements"), None
    if displacements is not None:
        raise ValueError("pass either displacements or family= with parameters=, not both")
    if not callable(family):
        raise ValueError(f"family must be callable, got {type(family).__name__}")
    if not isinstance(batched, bool):
        raise ValueError(f"batched must be True or False, got {batched!r}")
    parameters = as_parameters(parameters)
    inputs = training_inputs(
        evaluate_family(family, parameters, None, batched), "family(parameters)"
    )
    return inputs, 0 if parameters.ndim == 1 else int(parameters.shape[1])


def is_single_value(mu: Tensor, num_parameters: int | None) -> bool:
    """Whether ``mu`` is one parameter value (else a batch), after checking its shape
    against the P parameters of the fitted family (None: fitted from displacements,
    where only a 0-d ``mu`` is one value)."""
    if num_parameters is None:
        if mu.ndim not in (0, 1, 2):
            raise ValueError(f"mu must have shape (), (B,) or (B, P), got {tuple(mu.shape)}")
        return mu.ndim == 0
    single_ndim = 1 if num_parameters else 0
    if mu.ndim not in (single_ndim, single_ndim + 1) or (
        num_parameters and mu.shape[-1] != num_parameters
    ):
        expected = (
            "() or (B,)"
            if num_parameters == 0
            else (f"({num_parameters},) or (B, {num_parameters})")
        )
        raise ValueError(f"mu must have shape {expected}, got {tuple(mu.shape)}")
    return mu.ndim == single_ndim


def evaluate_family(
    family: Family, parameters: Tensor, count: int | None, batched: bool, *, dim: int | None = None
) -> Tensor:
    """Inputs (n, count, dim) for a batch of parameter values: one call with the whole
    batch (``batched``) or one call per value. Exceptions of the family propagate.
    ``count`` or ``dim`` None: any, the same for every value."""
    rows = "N_in" if count is None else count
    width = "D" if dim is None else dim
    if batched:
        out = family(parameters)
        if (
            not isinstance(out, Tensor)
            or out.ndim != 3
            or out.shape[0] != parameters.shape[0]
            or (count is not None and out.shape[1] != count)
            or (dim is not None and out.shape[2] != dim)
        ):
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"family(parameters) must return shape ({parameters.shape[0]}, "
                f"{rows}, {width}) when batched=True, got {got}; for a family of one "
                "parameter value at a time pass batched=False"
            )
        return out
    outputs = []
    for value in parameters:
        out = family(value)
        if isinstance(out, Tensor) and out.ndim == 2:
            count = out.shape[0] if count is None else count
            dim = out.shape[1] if dim is None else dim
        if not isinstance(out, Tensor) or tuple(out.shape) != (count, dim):
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"family(mu) must return a tensor of shape ({rows}, {width}) for one "
                f"parameter value, the same for every value, got {got}"
            )
        outputs.append(out)
    return torch.stack(outputs)


def copied_rows(
    morph: Any, num_inputs: int, num_outputs: int, device: torch.device
) -> tuple[Tensor, Tensor, Tensor]:
    """(copied output rows, their input rows, reduced output rows) of the morph."""
    everything = torch.arange(num_outputs, device=device)
    empty = everything[:0]
    method = getattr(morph, "copied_rows", None)
    if method is None:
        return empty, empty.clone(), everything
    output_rows, input_rows = (
        torch.as_tensor(rows, device=device).long().reshape(-1) for rows in method()
    )
    if output_rows.shape != input_rows.shape:
        raise ValueError(
            "morph.copied_rows() must return output and input rows of one length, "
            f"got {tuple(output_rows.shape)} and {tuple(input_rows.shape)}"
        )
    for rows, size, what in (
        (output_rows, num_outputs, "output"),
        (input_rows, num_inputs, "input"),
    ):
        if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= size):
            raise ValueError(f"morph.copied_rows(): {what} rows outside [0, {size})")
    keep = torch.ones(num_outputs, dtype=torch.bool, device=device)
    keep[output_rows] = False
    if int(keep.sum()) + output_rows.numel() != num_outputs:
        raise ValueError("morph.copied_rows(): an output row is listed twice")
    return output_rows.clone(), input_rows.clone(), torch.nonzero(keep).flatten()


def morph_snapshots(
    morph: Any, inputs: Tensor
) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor], int]:
    """Step (b) of Algorithm 3: the morph of the training inputs (n, N_in, D).

    Returns
    -------
    snapshots : Tensor, shape (n, N_red, D)
        The outputs on the reduced rows (checked finite).
    rows : (Tensor, Tensor, Tensor)
        The copied output rows, their input rows and the reduced rows
        (:func:`copied_rows`).
    num_outputs : int
        N_out.
    """
    outputs = morph(inputs)
    count, dim = inputs.shape[0], inputs.shape[2]
    if (
        not isinstance(outputs, Tensor)
        or outputs.ndim != 3
        or outputs.shape[0] != count
        or outputs.shape[2] != dim
    ):
        got = tuple(outputs.shape) if isinstance(outputs, Tensor) else type(outputs).__name__
        raise ValueError(
            f"morph(displacements) must return shape ({count}, N_out, {dim}), got {got}"
        )
    num_outputs = outputs.shape[1]
    rows = copied_rows(morph, inputs.shape[1], num_outputs, outputs.device)
    snapshots = outputs if rows[0].numel() == 0 else outputs.index_select(1, rows[2])
    check_finite(snapshots, "snapshots (the morph of the training data)")
    return snapshots, rows, num_outputs


def spread_modes(modes: Tensor, reduced: Tensor, num_outputs: int) -> Tensor:
    """Modes (N, N_red, D) of the reduced rows as fields over all N_out output rows,
    zero on the copied rows."""
    if reduced.numel() == num_outputs:
        return modes
    fields = modes.new_zeros(modes.shape[0], num_outputs, modes.shape[-1])
    return fields.index_copy_(1, reduced, modes)


def adjoint(morph: Any, fields: Tensor, num_inputs: int, reduced: Tensor) -> Tensor:
    """Lᵀ applied to N output fields (N, N_out, D) that are zero outside the reduced
    rows: (N, N_in, D), the projection matrix P = Zᵀ L.

    In order of preference: the morph's stored W (a tensor attribute ``weights``,
    reading the inputs ``weight_columns``): one GEMM; the morph's own ``adjoint``;
    otherwise, since the morph is linear, the vector-Jacobian product at any input,
    by autograd for all N fields in one batched call (a matrix-free IDW never forms W).
    A sharded map's ``weights`` and ``adjoint`` are its rank's share (no
    communication); :class:`~torchmorph.distributed.ShardedPOD` sums them over ranks.
    """
    stored = getattr(morph, "weights", None)
    method = getattr(morph, "adjoint", None)
    if isinstance(stored, Tensor) and stored.ndim == 2 and stored.shape[0] == reduced.numel():
        columns = getattr(morph, "weight_columns", None)
        columns = torch.arange(num_inputs) if columns is None else torch.as_tensor(columns)
        result = fields.new_zeros(fields.shape[0], num_inputs, fields.shape[-1])
        result.index_copy_(
            1,
            columns.long().to(result.device),
            projection_matrix(fields.index_select(1, reduced), stored),
        )
    elif method is not None:
        result = method(fields)
    else:
        with torch.enable_grad():
            probe = fields.new_zeros(
                fields.shape[0], num_inputs, fields.shape[-1], requires_grad=True
            )
            (result,) = torch.autograd.grad(morph(probe), probe, grad_outputs=fields)
    expected = (fields.shape[0], num_inputs, fields.shape[-1])
    if not isinstance(result, Tensor) or tuple(result.shape) != expected:
        got = tuple(result.shape) if isinstance(result, Tensor) else type(result).__name__
        raise ValueError(f"the morph's adjoint must return shape {expected}, got {got}")
    return result.detach().contiguous()


def weights_of(morph: Any, num_inputs: int, num_reduced: int) -> tuple[Tensor, Tensor]:
    """(W, the input rows it reads) for online='paper'."""
    method = getattr(morph, "weights_matrix", None)
    if method is None:
        raise ValueError(
            "online='paper' needs the morph's matrix W: a morph with a "
            "weights_matrix() method (IDW, MeshMorph)"
        )
    try:
        weights = method()
    except RuntimeError as error:  # a tree-mode IDW or MeshMorph stores no W
        raise ValueError(
            f"online='paper' needs the morph's matrix W, which it cannot give ({error}); "
            "use online='projection' (the default), which needs only its adjoint"
        ) from error
    columns = getattr(morph, "weight_columns", None)
    columns = torch.arange(num_inputs) if columns is None else torch.as_tensor(columns).long()
    if not isinstance(weights, Tensor) or tuple(weights.shape) != (num_reduced, columns.numel()):
        got = tuple(weights.shape) if isinstance(weights, Tensor) else type(weights).__name__
        raise ValueError(
            f"morph.weights_matrix() must have shape ({num_reduced}, "
            f"{columns.numel()}) (reduced rows x weight columns), got {got}"
        )
    return weights, columns


MAX_RUNS = 16
"""Rows splitting into more contiguous runs than this are scattered by index."""


def index_runs(rows: Tensor, sources: Tensor) -> list[tuple[int, int, int]] | None:
    """Runs where both ``rows`` and ``sources`` step by one, as (first row, first source,
    length), or None if there are more than ``MAX_RUNS``."""
    rows, sources = rows.detach().cpu(), sources.detach().cpu()
    if rows.numel() == 0:
        return []
    breaks = torch.nonzero((rows[1:] != rows[:-1] + 1) | (sources[1:] != sources[:-1] + 1))
    breaks = breaks.flatten() + 1
    if breaks.numel() >= MAX_RUNS:
        return None
    starts = [0, *breaks.tolist()]
    ends = [*breaks.tolist(), rows.numel()]
    return [
        (int(rows[start]), int(sources[start]), end - start)
        for start, end in zip(starts, ends, strict=True)
    ]


# --------------------------------------------------------------------------------------
# the online expansion (step (g) of Algorithm 3)
# --------------------------------------------------------------------------------------


def expand(
    beta: Tensor,
    output_basis: Tensor,
    displacement: Tensor,
    copied_output_rows: Tensor,
    copied_input_rows: Tensor,
    out: Tensor | None,
) -> Tensor:
    """(B, N) coefficients -> output fields (B, N_out, D): ``beta @ basis`` over every
    output row (the basis is zero on the copied rows), then the copied rows."""
    count, batch, dim = output_basis.shape[0], beta.shape[0], output_basis.shape[-1]
    basis = output_basis.reshape(count, -1)
    # one mode: a broadcast product (BLAS with an inner dimension of 1 is slower)
    product = torch.mul if count == 1 else torch.matmul
    if out is None:
        field = product(beta, basis).reshape(batch, -1, dim)
    else:
        product(beta, basis, out=out.view(batch, -1))
        field = out
    if copied_output_rows.numel():
        copied = displacement.index_select(1, copied_input_rows)
        if is_traced(field):  # vmap has no batching rule for the in-place index_copy_
            field = field.index_copy(1, copied_output_rows, copied)
        else:
            field.index_copy_(1, copied_output_rows, copied)
    return field


def expand_by_runs(
    beta: Tensor,
    modes: Tensor,
    displacement: Tensor,
    runs: tuple[list[tuple[int, int, int]], list[tuple[int, int, int]]],
    num_outputs: int,
    out: Tensor | None,
) -> Tensor:
    """:func:`expand` when the copied and reduced rows form a few contiguous runs
    (``(copied runs, reduced runs)`` of :func:`index_runs`): slice products and copies
    instead of a full-size product and an indexed scatter. No autograd."""
    count, batch, dim = modes.shape[0], beta.shape[0], modes.shape[-1]
    if out is None:
        out = beta.new_empty(batch, num_outputs, dim)
    flat_out = out.view(batch, -1)
    flat_in = displacement.reshape(batch, -1)
    modes = modes.reshape(count, -1)
    product = torch.mul if count == 1 else torch.matmul
    copied_runs, reduced_runs = runs
    for node, row, length in reduced_runs:
        product(
            beta,
            modes[:, dim * row : dim * (row + length)],
            out=flat_out[:, dim * node : dim * (node + length)],
        )
    for node, row, length in copied_runs:
        flat_out[:, dim * node : dim * (node + length)].copy_(
            flat_in[:, dim * row : dim * (row + length)]
        )
    return out


# --------------------------------------------------------------------------------------
# loading a state
# --------------------------------------------------------------------------------------


def check_reducer_state(state_dict, prefix: str, version: int) -> None:
    """Raise ``ValueError`` naming the entry if a fitted PODReducer state does not fit
    together (before anything is loaded). An unfitted state is not checked further."""

    def fail(name: str, message: str) -> None:
        raise ValueError(f"state_dict[{prefix + name!r}]: {message}")

    extra = state_dict.get(prefix + "_extra_state")
    if extra is None:
        return
    if not isinstance(extra, dict):
        fail("_extra_state", f"must be a dict, got {type(extra).__name__}")
    if extra.get("version") != version:
        fail(
            "_extra_state",
            f"version {extra.get('version')!r} is not {version} (a state "
            "saved by another torchmorph version)",
        )
    if extra.get("online") not in ONLINE_VARIANTS:
        listed = ", ".join(map(repr, ONLINE_VARIANTS))
        fail("_extra_state", f"online must be one of {listed}; got {extra.get('online')!r}")
    count = extra.get("num_modes_")
    if count is None:
        return
    sizes = {key: extra.get(key) for key in ("num_modes_", "num_inputs_", "num_outputs_")}
    for key, value in sizes.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            fail("_extra_state", f"{key} must be a positive integer, got {value!r}")
    num_inputs, num_outputs = sizes["num_inputs_"], sizes["num_outputs_"]

    def tensor(name: str) -> Tensor:
        value = state_dict.get(prefix + name)
        if not isinstance(value, Tensor):
            fail(name, "is missing from a fitted state")
        return value

    def shape(name: str, expected: tuple[int, ...]) -> Tensor:
        value = tensor(name)
        if tuple(value.shape) != expected:
            fail(
                name,
                f"has shape {tuple(value.shape)}, expected {expected} for "
                f"{count} mode(s), {num_inputs} input and {num_outputs} output rows",
            )
        return value

    reduced = tensor("reduced_rows_")
    copied_out, copied_in = tensor("copied_output_rows_"), tensor("copied_input_rows_")
    for name, value, size in (
        ("reduced_rows_", reduced, num_outputs),
        ("copied_output_rows_", copied_out, num_outputs),
        ("copied_input_rows_", copied_in, num_inputs),
    ):
        if value.ndim != 1 or value.is_floating_point():
            fail(name, "must be a 1-D integer tensor")
        if value.numel() and (int(value.min()) < 0 or int(value.max()) >= size):
            fail(name, f"holds rows outside [0, {size})")
    if copied_in.shape != copied_out.shape:
        fail("copied_input_rows_", "must have the length of copied_output_rows_")
    together = torch.cat([reduced, copied_out]).cpu()
    if together.numel() != num_outputs or not torch.equal(
        together.sort().values, torch.arange(num_outputs)
    ):
        fail(
            "reduced_rows_",
            f"reduced_rows_ and copied_output_rows_ must split the {num_outputs} output rows",
        )
    modes = tensor("modes_")
    if modes.ndim != 3 or modes.shape[-1] < 1:
        fail("modes_", f"must have shape (N, N_red, D), got {tuple(modes.shape)}")
    dim = modes.shape[-1]
    shape("modes_", (count, reduced.numel(), dim))
    values = tensor("singular_values_")
    if values.ndim != 1 or values.numel() < count:
        fail("singular_values_", f"must be 1-D with at least {count} values")
    shape("energy_captured_", tuple(values.shape))
    if extra["online"] == "projection":
        shape("projection_", (count, num_inputs, dim))
    else:
        shape("system_matrix_", (count, count))
        shape("rhs_matrix_", (count, num_inputs, dim))


def relative_field_error(reduced: Tensor, full: Tensor, norm: str, mesh: Any, morph: Any) -> Tensor:
    """Per-sample relative error of ``reduced`` against ``full`` (B, N, D) in the nodal
    or the P1 mass-matrix norm (``mesh``, or the morph's own points and tets)."""
    from torchmorph.mesh.norms import relative_l2_error
    from torchmorph.mesh.tetmesh import TetMesh

    if norm == "l2":
        warnings.warn(
            "relative_error(norm='l2') is deprecated: use norm='mass' (the P1 "
            "mass-matrix norm) or norm='nodal'",
            DeprecationWarning,
            stacklevel=3,
        )
        norm = "mass"
    check_choice(norm, "norm", ("nodal", "mass"))
    if norm == "mass":
        if mesh is None and callable(getattr(morph, "reference_mesh", None)):
            mesh = morph.reference_mesh()
        if mesh is None:
            points, tets = getattr(morph, "points", None), getattr(morph, "tets", None)
            if not isinstance(points, Tensor) or not isinstance(tets, Tensor):
                raise ValueError(
                    "norm='mass' needs mesh= (the mass matrix lives on a "
                    "mesh) for a morph without points and tets"
                )
            mesh = TetMesh(points, tets)
        return relative_l2_error(mesh, reduced, full, norm="mass").to(full.dtype)
    difference = (reduced - full).flatten(1).norm(dim=1)
    scale = full.flatten(1).norm(dim=1)
    return torch.where(difference == 0, torch.zeros_like(difference), difference / scale)


def check_out(out: Tensor, displacement: Tensor, num_outputs: int, reference: Tensor) -> Tensor:
    """``out=`` of a reduced morph: the output's shape, the reducer's dtype and device,
    contiguous, and no autograd."""
    expected = (*displacement.shape[:-2], num_outputs, displacement.shape[-1])
    if not isinstance(out, Tensor) or tuple(out.shape) != expected:
        got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
        raise ValueError(f"out must have shape {expected}, got {got}")
    check_same_device_dtype(reference, "the reducer", out, "out")
    if not out.is_contiguous():
        raise ValueError("out must be contiguous")
    if torch.is_grad_enabled() and displacement.requires_grad:
        raise ValueError("out= does not support autograd: displacement requires grad")
    return out
