"""What every POD reducer of torchmorph shares: :class:`PODBase`.

The online phase of Algorithm 3 (steps (f)–(g) of the paper) needs only the fitted
state: the basis over the reduced output rows, the online matrix over every input row
(zero on the rows the map does not read) and the output rows the map copies from
input rows. :class:`~torchmorph.pod.PODReducer` (one process) and
:class:`~torchmorph.distributed.ShardedPOD` (one rank's rows of a sharded map) differ
only in how ``fit`` computes that state; hyper-parameters, the fitted state, the load
rule of :mod:`torchmorph._state` and the online phase live here, once.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from torchmorph._checks import check_same_device_dtype, is_traced
from torchmorph._state import (
    NotFittedError,
    check_saved_hyperparameters,
    resize_buffers_for_load,
)
from torchmorph.pod._protocol import (
    check_out,
    check_reducer_state,
    expand,
    expand_by_runs,
    index_runs,
)
from torchmorph.pod.functional import check_energy_tolerance, check_num_modes

__all__ = ["PODBase"]


class PODBase(nn.Module):
    """Hyper-parameters, fitted state and online phase of a POD-reduced linear map.

    Subclasses implement ``fit`` and end it with :meth:`_store_fit`. The state is in
    buffers (see :class:`~torchmorph.pod.PODReducer` for their meaning): a
    ``state_dict`` is enough to run :meth:`forward` after ``load_state_dict``, without
    the map it was fitted to.

    Parameters
    ----------
    energy_tolerance : float
        ε in (0, 1) of the energy criterion (the paper's eq. 12).
    num_modes : int, optional
        Keep exactly this many modes instead.
    """

    _FLOAT_BUFFERS: tuple[str, ...] = (
        "modes_",
        "singular_values_",
        "energy_captured_",
        "projection_",
        "system_matrix_",
        "rhs_matrix_",
    )
    _INDEX_BUFFERS: tuple[str, ...] = (
        "copied_output_rows_",
        "copied_input_rows_",
        "reduced_rows_",
    )
    _FITTED: tuple[str, ...] = ("num_modes_", "num_inputs_", "num_outputs_")
    """Fitted numbers saved in the extra state beside the buffers (None until fitted)."""
    _STATE_VERSION = 2
    _FIT_HINT = "call fit(morph, displacements) first"
    online: str = "projection"

    def __init__(self, *, energy_tolerance: float = 1e-5, num_modes: int | None = None) -> None:
        super().__init__()
        self.energy_tolerance = check_energy_tolerance(energy_tolerance)
        self.num_modes = check_num_modes(num_modes)
        for name in self._FLOAT_BUFFERS:
            self.register_buffer(name, torch.empty(0))
        for name in self._INDEX_BUFFERS:
            self.register_buffer(name, torch.empty(0, dtype=torch.int64))
        # derived from the buffers above (rebuilt by fit and load_state_dict, moved by .to):
        # the online matrix over the input rows and the basis over the output rows
        self.register_buffer("_input_matrix", torch.empty(0), persistent=False)
        self.register_buffer("_output_basis", torch.empty(0), persistent=False)
        for name in self._FITTED:
            setattr(self, name, None)
        self.offline_time_: dict[str, float] = {}
        # contiguous runs of (output row, source row, length) for slice copies, or None
        self._runs: tuple[list[tuple[int, int, int]], list[tuple[int, int, int]]] | None = None

    # ---------------------------------------------------------------- fitted state

    @property
    def is_fitted(self) -> bool:
        """Whether ``fit`` (or ``load_state_dict`` of a fitted state) has run."""
        return self.num_modes_ is not None

    def _check_fitted(self) -> None:
        if not self.is_fitted:
            raise NotFittedError(
                f"this {type(self).__name__} is not fitted yet: {self._FIT_HINT}, or load a "
                "fitted state_dict"
            )

    @property
    def num_inputs(self) -> int:
        """Rows of an input displacement: control points (IDW) or boundary nodes (mesh)."""
        self._check_fitted()
        return int(self.num_inputs_)

    @property
    def num_outputs(self) -> int:
        """Rows of an output field: targets (IDW) or mesh nodes (mesh)."""
        self._check_fitted()
        return int(self.num_outputs_)

    @property
    def dim(self) -> int:
        """D, the number of components of the fields (2 or 3 for a 2-D or 3-D mesh)."""
        self._check_fitted()
        return int(self.modes_.shape[-1])

    def _hyperparameters(self) -> dict[str, Any]:
        """What changes the result, saved with the state and checked on load."""
        return {name: getattr(self, name) for name in ("energy_tolerance", "num_modes", "online")}

    def get_extra_state(self) -> dict[str, Any]:
        fitted = {name: getattr(self, name) for name in self._FITTED}
        return {"version": self._STATE_VERSION, **self._hyperparameters(), **fitted} | {
            "offline_time_": dict(self.offline_time_)
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        check_saved_hyperparameters(type(self).__name__, state, self._hyperparameters())
        for name in self._FITTED:
            setattr(self, name, state.get(name))
        self.offline_time_ = dict(state.get("offline_time_") or {})

    def _check_state(self, state_dict, prefix: str) -> None:
        """Raise ``ValueError`` naming the entry unless the state fits together and was
        saved with this module's hyper-parameters (before anything is loaded)."""
        check_reducer_state(state_dict, prefix, self._STATE_VERSION)
        check_saved_hyperparameters(
            type(self).__name__, state_dict[prefix + "_extra_state"], self._hyperparameters()
        )

    def _load_from_state_dict(
        self,
        state_dict,
        prefix,
        local_metadata,
        strict,
        missing_keys,
        unexpected_keys,
        error_msgs,
    ) -> None:
        if prefix + "_extra_state" in state_dict:
            self._check_state(state_dict, prefix)
        # the buffers' shapes are only known after fit: take the incoming shape and
        # (floating) dtype, keep this module's device
        resize_buffers_for_load(
            self, state_dict, prefix, (*self._FLOAT_BUFFERS, *self._INDEX_BUFFERS), take_dtype=True
        )
        super()._load_from_state_dict(
            state_dict,
            prefix,
            local_metadata,
            strict,
            missing_keys,
            unexpected_keys,
            error_msgs,
        )
        if self.is_fitted and not error_msgs:
            self._build_online_cache()

    def _store_fit(
        self,
        *,
        modes: Tensor,
        singular_values: Tensor,
        energy_captured: Tensor,
        copied_rows: tuple[Tensor, Tensor, Tensor],
        num_inputs: int,
        num_outputs: int,
        projection: Tensor | None = None,
        system_matrix: Tensor | None = None,
        rhs_matrix: Tensor | None = None,
    ) -> None:
        """Keep what ``fit`` computed and prepare the online phase."""
        empty = modes.new_empty(0)
        self.modes_ = modes
        self.singular_values_ = singular_values
        self.energy_captured_ = energy_captured
        self.projection_ = empty if projection is None else projection
        self.system_matrix_ = empty if system_matrix is None else system_matrix
        self.rhs_matrix_ = empty if rhs_matrix is None else rhs_matrix
        self.copied_output_rows_, self.copied_input_rows_, self.reduced_rows_ = copied_rows
        self.num_modes_ = int(modes.shape[0])
        self.num_inputs_ = int(num_inputs)
        self.num_outputs_ = int(num_outputs)
        self._build_online_cache()

    def _build_online_cache(self) -> None:
        """Spread the basis over all output rows (zeros on the copied rows) and find the
        contiguous runs of the copied and reduced rows, for the online phase."""
        self._input_matrix = self.projection_ if self.online == "projection" else self.rhs_matrix_
        count, reduced = self.num_modes_, self.reduced_rows_
        whole = reduced.numel() == self.num_outputs_ and self.copied_output_rows_.numel() == 0
        if whole and bool((reduced == torch.arange(reduced.numel(), device=reduced.device)).all()):
            self._output_basis, self._runs = self.modes_, None
            return
        basis = self.modes_.new_zeros(count, self.num_outputs_, self.modes_.shape[-1])
        self._output_basis = basis.index_copy_(1, reduced, self.modes_)
        copied_runs = index_runs(self.copied_output_rows_, self.copied_input_rows_)
        reduced_runs = index_runs(reduced, torch.arange(reduced.numel()))
        self._runs = (
            None if copied_runs is None or reduced_runs is None else (copied_runs, reduced_runs)
        )

    def extra_repr(self) -> str:
        text = ", ".join(
            f"{name}={value:g}" if isinstance(value, float) else f"{name}={value!r}"
            for name, value in self._hyperparameters().items()
        )
        if self.is_fitted:
            text += (
                f", num_modes_={self.num_modes_}, num_inputs_={self.num_inputs_}, "
                f"num_outputs_={self.num_outputs_}"
            )
        return text

    # ---------------------------------------------------------------- online phase

    def _check_input(self, displacement: Tensor, name: str) -> bool:
        self._check_fitted()
        if not isinstance(displacement, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(displacement).__name__}")
        count, dim = self.num_inputs_, self.modes_.shape[-1]
        if displacement.ndim not in (2, 3) or displacement.shape[-2:] != (count, dim):
            raise ValueError(
                f"{name} must have shape ({count}, {dim}) or (B, {count}, {dim}) for the "
                f"{count} input rows of the fitted morph, got {tuple(displacement.shape)}"
            )
        check_same_device_dtype(self.modes_, "the reducer", displacement, name)
        return displacement.ndim == 3

    def coefficients(self, displacement: Tensor) -> Tensor:
        """Reduced coefficients β of ``Z β ≈ L d`` (online step (f)).

        Parameters
        ----------
        displacement : Tensor, shape (N_in, D) or (B, N_in, D)
            Control displacements (IDW) or boundary displacements (mesh).

        Returns
        -------
        Tensor, shape (N,) or (B, N)
        """
        batched = self._check_input(displacement, "displacement")
        beta = self._coefficients(displacement if batched else displacement.unsqueeze(0))
        return beta if batched else beta[0]

    def _coefficients(self, displacement: Tensor) -> Tensor:
        """(B, N_in, D) -> (B, N): one GEMM (plus an N × N solve for ``paper``)."""
        count = self.num_modes_
        flat = displacement.reshape(displacement.shape[0], -1)
        rhs = flat @ self._input_matrix.reshape(count, -1).mT  # P d, or B d of eq. 16
        if self.online == "projection":
            return rhs
        return torch.linalg.solve(self.system_matrix_, rhs.mT).mT

    def forward(self, displacement: Tensor, *, out: Tensor | None = None) -> Tensor:
        """Reduced morph: what the fitted morph's ``forward`` returns, from N modes.

        Parameters
        ----------
        displacement : Tensor, shape (N_in, D) or (B, N_in, D)
            Control displacements (IDW: N_in = N_c) or boundary displacements
            (mesh morph: N_in = N_b), in the reducer's dtype and device.
        out : Tensor, shape (N_out, D) or (B, N_out, D), optional
            Contiguous tensor to write the result into (no autograd). Reusing one
            output for many batches saves the page faults of a fresh allocation,
            which dominate a large batch (3x at case-B size, see benchmarks).

        Returns
        -------
        Tensor, shape (N_out, D) or (B, N_out, D)
            IDW: the targets' displacement ``Z β``. Mesh morph: its nodal field,
            boundary nodes exactly ``displacement``'s rows, interior nodes ``Z β``.
            Differentiable with respect to ``displacement`` (without ``out``).

        Raises
        ------
        NotFittedError
            If the reducer is not fitted.
        ValueError
            On a wrong shape, dtype or device of ``displacement`` or ``out``, or
            ``out`` with a ``displacement`` that requires grad.
        """
        batched = self._check_input(displacement, "displacement")
        inputs = displacement if batched else displacement.unsqueeze(0)
        if out is not None:
            out = check_out(out, displacement, self.num_outputs_, self.modes_)
            out = out if batched else out.unsqueeze(0)
        beta = self._coefficients(inputs)
        # the slice copies write into out= tensors: not for autograd, vmap, jvp or compile
        runs = self._runs
        if (
            runs is not None
            and not is_traced(beta)
            and not (torch.is_grad_enabled() and beta.requires_grad)
        ):
            result = expand_by_runs(beta, self.modes_, inputs, runs, self.num_outputs_, out)
        else:
            result = expand(
                beta,
                self._output_basis,
                inputs,
                self.copied_output_rows_,
                self.copied_input_rows_,
                out,
            )
        return result if batched else result[0]
