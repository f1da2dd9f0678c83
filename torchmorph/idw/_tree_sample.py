"""What the two tree operators (:class:`~torchmorph.idw.tree.TreeIDW`,
:class:`~torchmorph.idw.treecode.TreecodeIDW`) share: the state of one pair of clouds
(the points as buffers, the power and coincidence tolerance checked on load, the trees
rebuilt after it) and the exact sums at the sampled targets that their error control
measures against."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchmorph._state import check_saved_hyperparameters, resize_buffers_for_load
from torchmorph.idw.functional import idw_apply

__all__ = ["SAMPLE_TARGETS", "SINGLE_REFERENCE", "CloudPair"]

SAMPLE_TARGETS = 1024
"""Targets at which the sampled error is measured (and ``rms(u)`` estimated)."""

SINGLE_REFERENCE = 1e-5
"""From this tolerance up, float32 inputs are checked against the float32 fused kernels
(float64 partial sums; 7e-8 from float64 sums on the benchmark's clouds, half the time)."""


class CloudPair(nn.Module):
    """A module over fixed ``controls`` and ``targets`` buffers, with ``power``,
    ``coincidence_tolerance`` and ``tolerance`` attributes and a ``_build()`` that derives
    its operator from them (called again after a state is loaded)."""

    controls: Tensor
    targets: Tensor
    power: float
    coincidence_tolerance: float
    tolerance: float

    def _build(self) -> None:  # pragma: no cover - every subclass has its own
        raise NotImplementedError

    # ----------------------------------------------------------------- state
    def get_extra_state(self) -> dict:
        return {**self._hyperparameters(), "tolerance": self.tolerance}

    def set_extra_state(self, state: dict) -> None:
        check_saved_hyperparameters(type(self).__name__, state, self._hyperparameters())

    def _hyperparameters(self) -> dict[str, float]:
        return {"power": self.power, "coincidence_tolerance": self.coincidence_tolerance}

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        if prefix + "_extra_state" in state_dict:  # before anything is loaded
            check_saved_hyperparameters(
                type(self).__name__, state_dict[prefix + "_extra_state"], self._hyperparameters()
            )
        resize_buffers_for_load(self, state_dict, prefix, ("controls", "targets"))
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        self._build()

    # ----------------------------------------------------------- the sample
    def _sample_rows(self) -> Tensor:
        """The sampled targets: up to :data:`SAMPLE_TARGETS`, evenly spaced in their order."""
        n_targets = int(self.targets.shape[0])
        return torch.linspace(0, n_targets - 1, min(SAMPLE_TARGETS, n_targets)).round().long()

    def _exact_sample(self, fields: Tensor) -> tuple[Tensor, Tensor]:
        """(the sampled rows, the exact values there (B, rows, D) in float64) of ``fields``
        (N_c, B, D): the fused kernels' sums, float32 ones for float32 inputs at
        tolerances from :data:`SINGLE_REFERENCE` up."""
        rows = self._sample_rows()
        single = self.controls.dtype == torch.float32 and self.tolerance >= SINGLE_REFERENCE
        dtype = torch.float32 if single else torch.float64
        exact = idw_apply(
            controls=self.controls.to(dtype),
            targets=self.targets[rows].to(dtype),
            displacements=fields.detach().permute(1, 0, 2).to(dtype),
            power=self.power,
            coincidence_tolerance=self.coincidence_tolerance,
        ).double()
        return rows, exact
