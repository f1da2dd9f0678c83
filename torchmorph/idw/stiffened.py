"""Near-wall stiffening of IDW: two-term weights that keep the cells next to a moving
wall nearly rigid.

Plain IDW weighs control k by ``|x - x_k|^-p``. Luke, Collins and Blades (2012, "A fast
mesh deformation method using explicit interpolation", J. Comput. Phys. 231) add a
second, steeper term,

    w_k(x) = r_k^-p + ℓ^(q-p) r_k^-q,      r_k = |x - x_k|,  q > p,

so that within about the *stiffening length* ℓ of the controls the ``q`` term dominates:
there the nearest controls alone move a node, as a rigid body moves, and the cells of a
boundary layer keep their shape; farther than ℓ the weights are plain IDW's. The morph
stays linear in the control displacements, exact at the controls and a convex
combination of them (rows of W sum to 1).

Because both terms share the normalisation, the morph is a per-target blend of two
plain IDW morphs,

    u(x) = λ(x) u_p(x) + (1 - λ(x)) u_q(x),   λ = S_p / (S_p + ℓ^(q-p) S_q),
    S_m(x) = Σ_k r_k^-m,

so :class:`StiffenedIDW` holds two :class:`~torchmorph.idw.IDW` modules (powers p and q,
each with its fused kernels, dense or matrix-free) and the geometric blend λ, computed
once (:func:`stiffening_blend`) in a numerically safe form
``λ = 1 / (1 + (ℓ / r_min)^(q-p) · Σ (r_min/r_k)^q / Σ (r_min/r_k)^p)``.

Choosing the parameters: ``q`` about ``p + 2`` (the default; Luke et al. use p = 3,
q = 5) to ``p + 4``; ``ℓ`` the thickness of the layer that should
move rigidly: a few first-cell heights of a boundary layer, or a fraction (e.g. 0.05–0.2)
of the moving body's size. ``ℓ → 0`` gives plain IDW of power p; ``ℓ → ∞`` plain IDW of
power q.
"""

from __future__ import annotations

import time

import torch
from torch import Tensor, nn

from torchmorph._checks import as_points, check_positive, check_same_device_dtype, dim_of
from torchmorph._state import check_saved_hyperparameters, resize_buffers_for_load
from torchmorph.idw._geometry import check_power, check_tolerance
from torchmorph.idw.functional import DEFAULT_COINCIDENCE_TOLERANCE, Implementation
from torchmorph.idw.module import DEFAULT_DENSE_BYTES, IDW

__all__ = ["StiffenedIDW", "check_stiffening", "stiffening_blend"]

# Bytes of pairwise temporaries per block of targets in stiffening_blend.
_BLOCK_BYTES = 8 * 2**20


def check_stiffening(power: float, stiffening_power: float, stiffening_length: float) -> None:
    """``ValueError`` naming the argument unless ``stiffening_power > power > 0`` and
    ``stiffening_length`` is finite and > 0."""
    power = check_power(power)
    stiffening_power = check_positive(stiffening_power, "stiffening_power")
    check_positive(stiffening_length, "stiffening_length")
    if stiffening_power <= power:
        raise ValueError(
            f"stiffening_power must be larger than power ({power:g}) for the near-wall term "
            f"to dominate near the controls, got {stiffening_power:g}"
        )


def stiffening_blend(
    controls: Tensor,
    targets: Tensor,
    *,
    power: float,
    stiffening_power: float,
    stiffening_length: float,
    coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
) -> Tensor:
    """The blend λ (N_t,) of the two-term weights (see the module's notes): the share of
    the plain power ``power`` in each target's morph, in [0, 1]. Differentiable with
    respect to the points; 0 at targets within the coincidence radius of a control
    (where both morphs give that control's value)."""
    check_stiffening(power, stiffening_power, stiffening_length)
    tolerance = check_tolerance(coincidence_tolerance)
    controls = as_points(controls, "controls", dim=dim_of(controls))
    targets = as_points(targets, "targets", dim=controls.shape[1], allow_empty=True)
    check_same_device_dtype(controls, "controls", targets, "targets")
    dtype = controls.dtype
    tiny = torch.finfo(dtype).tiny
    with torch.no_grad():
        both = torch.cat([controls.detach(), targets.detach()])
        diagonal = float(torch.linalg.vector_norm(both.amax(0) - both.amin(0)))
    radius2 = max((tolerance * diagonal) ** 2, tiny)
    rows = max(1, _BLOCK_BYTES // (4 * max(1, controls.shape[0]) * controls.element_size()))
    length2 = float(stiffening_length) ** 2
    half_gap = (stiffening_power - power) / 2
    blends = []
    for begin in range(0, targets.shape[0], rows):
        block = targets[begin : begin + rows]
        squared = (block[:, None, :] - controls[None, :, :]).square().sum(-1)
        nearest2 = squared.amin(1)
        coincident = nearest2 <= radius2
        safe_nearest2 = torch.where(coincident, torch.ones_like(nearest2), nearest2)
        ratio = safe_nearest2[:, None] / squared.clamp_min(tiny)  # (r_min / r_k)², <= 1
        plain = ratio.pow(power / 2).sum(1)
        steep = ratio.pow(stiffening_power / 2).sum(1)
        share = (length2 / safe_nearest2).pow(half_gap) * steep / plain
        blend = 1.0 / (1.0 + share)
        blends.append(torch.where(coincident, torch.zeros_like(blend), blend))
    if not blends:
        return targets.new_zeros(0)
    return torch.cat(blends)


class StiffenedIDW(nn.Module):
    """IDW with near-wall stiffening: weights ``r^-p + ℓ^(q-p) r^-q`` (see the module's
    notes), as the blend of two :class:`~torchmorph.idw.IDW` morphs.

    Parameters
    ----------
    controls : Tensor, shape (N_c, D)
    targets : Tensor, shape (N_t, D)
    power : float, default 4
        p, the exponent far from the controls (the paper's IDW).
    stiffening_power : float, optional
        q > p, the exponent that dominates within ``stiffening_length`` of the controls
        (default ``power + 2``).
    stiffening_length : float, keyword
        ℓ > 0, in the points' units: the thickness of the layer that moves nearly
        rigidly with its wall.
    mode, block_bytes, dense_bytes, coincidence_tolerance, implementation
        As :class:`~torchmorph.idw.IDW` (both of its morphs take them; ``mode="tree"``
        is refused).

    Attributes
    ----------
    far, near : IDW
        The morphs of powers p and q.
    blend : buffer, shape (N_t,)
        λ, the share of ``far`` in each target's displacement.

    Notes
    -----
    Linear in the displacements, batched, differentiable (to the displacements; to the
    positions when new ``controls``/``targets`` are passed to :meth:`forward`, which then
    recomputes λ too). The whole state is in :meth:`state_dict`; loading a state saved
    with other powers or another length raises.
    """

    blend: Tensor

    def __init__(
        self,
        controls: Tensor,
        targets: Tensor,
        *,
        stiffening_length: float,
        power: float = 4.0,
        stiffening_power: float | None = None,
        mode: str = "auto",
        block_bytes: int | None = None,
        dense_bytes: int | None = DEFAULT_DENSE_BYTES,
        coincidence_tolerance: float = DEFAULT_COINCIDENCE_TOLERANCE,
        implementation: Implementation = "auto",
    ) -> None:
        super().__init__()
        power = check_power(power)
        if stiffening_power is None:
            stiffening_power = power + 2.0
        check_stiffening(power, stiffening_power, stiffening_length)
        if mode == "tree":
            raise ValueError(
                "mode: StiffenedIDW has no tree mode; use 'auto', 'dense' or 'matrix_free'"
            )
        options = dict(
            mode=mode,
            block_bytes=block_bytes,
            dense_bytes=dense_bytes,
            coincidence_tolerance=coincidence_tolerance,
            implementation=implementation,
        )
        self.far = IDW(controls, targets, power=power, **options)  # type: ignore[arg-type]
        self.near = IDW(controls, targets, power=stiffening_power, **options)  # type: ignore[arg-type]
        self.stiffening_length = float(stiffening_length)
        start = time.perf_counter()
        self.register_buffer("blend", self._blend(self.far.controls, self.far.targets))
        self.blend_time = time.perf_counter() - start

    def _blend(self, controls: Tensor, targets: Tensor) -> Tensor:
        return stiffening_blend(
            controls,
            targets,
            power=self.power,
            stiffening_power=self.stiffening_power,
            stiffening_length=self.stiffening_length,
            coincidence_tolerance=self.far.coincidence_tolerance,
        )

    @property
    def power(self) -> float:
        """p, the far morph's exponent."""
        return self.far.power

    @property
    def stiffening_power(self) -> float:
        """q, the near morph's exponent."""
        return self.near.power

    @property
    def num_controls(self) -> int:
        return self.far.num_controls

    @property
    def num_targets(self) -> int:
        return self.far.num_targets

    @property
    def mode(self) -> str:
        return self.far.mode

    @property
    def controls(self) -> Tensor:
        return self.far.controls

    @property
    def targets(self) -> Tensor:
        return self.far.targets

    @property
    def coincidence_tolerance(self) -> float:
        return self.far.coincidence_tolerance

    @property
    def assembly_time(self) -> float:
        """Seconds spent on the two morphs' W (dense mode) and the blend."""
        return self.far.assembly_time + self.near.assembly_time + self.blend_time

    def forward(
        self,
        displacements: Tensor,
        *,
        controls: Tensor | None = None,
        targets: Tensor | None = None,
    ) -> Tensor:
        """Interpolate control displacements (N_c, D) or (B, N_c, D) to the targets,
        (N_t, D) or (B, N_t, D); ``controls``/``targets`` as :meth:`IDW.forward`."""
        far = self.far(displacements, controls=controls, targets=targets)
        near = self.near(displacements, controls=controls, targets=targets)
        blend = self.blend
        if controls is not None or targets is not None:
            blend = self._blend(
                self.far.controls if controls is None else controls,
                self.far.targets if targets is None else targets,
            )
        blend = blend[:, None].to(far.dtype)
        return near + blend * (far - near)

    def weights_matrix(self) -> Tensor:
        """W (N_t, N_c) of the two-term weights: ``λ W_p + (1 - λ) W_q``."""
        blend = self.blend[:, None]
        return blend * self.far.weights_matrix() + (1 - blend) * self.near.weights_matrix()

    def get_extra_state(self) -> dict:
        return {
            "power": self.power,
            "stiffening_power": self.stiffening_power,
            "stiffening_length": self.stiffening_length,
        }

    def set_extra_state(self, state: dict) -> None:
        check_saved_hyperparameters("StiffenedIDW", state, self.get_extra_state())

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if prefix + "_extra_state" in state_dict:  # before anything is loaded
            self.set_extra_state(state_dict[prefix + "_extra_state"])
        resize_buffers_for_load(self, state_dict, prefix, ("blend",))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return (
            f"power={self.power:g}, stiffening_power={self.stiffening_power:g}, "
            f"stiffening_length={self.stiffening_length:g}"
        )
