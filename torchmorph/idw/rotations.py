"""Rotation-aware IDW: large rotations of a body without sheared or inverted cells.

Plain IDW (the paper's eq. 2) interpolates displacements. A body that turns by θ moves
its nodes along chords, and every target around it receives a weighted mean of those
chords: the field shears the cells next to the body and, past some angle, turns them
over. Here every control point k carries a rigid motion — its displacement d_k and a rotation
R_k = exp([ω_k]×), estimated from how its neighbours on the surface moved
(:func:`fit_rotations`) or given by the caller (a rigid part) — and a target x receives
the blended rigid motion

    x' = x + (R(a(x) ω̄(x)) − I) (x − c(x)) + d̄(x),
    ω̄ = Σ_k w_k ω_k,   d̄ = Σ_k w_k d_k,   c = Σ_k w_k |ω_k|² x_k / Σ_k w_k |ω_k|²,
    a(x) = min(1, ℓ / |x − c(x)|),

with the IDW weights w_k(x) of eq. (2). Rotations are blended in the Lie algebra (as
rotation vectors, a log-Euclidean mean), never by averaging matrices, which shrinks
them. The blended rotation turns the target about c, the mean position of the controls
that rotate (weighted by how much they rotate), so fixed controls far away — a
tunnel's walls — dilute the angle without dragging the pivot to them. Within the reach
ℓ of that pivot the turn is the full blended angle; beyond it, the angle falls as
ℓ / |x − c| so that the turn moves a target by about |ω̄| ℓ at most, as plain IDW would
move it by the body's chords: a rotation carried undiminished to a distance r would
move the cells there by |ω̄| r and shear them where the body's weight gives way to the
walls' — measured on the paper's hull turned by 60°, that sheared cells four to six
metres from it, where plain IDW had folded cells at the hull's ends. Properties:

- exact at the controls: at x = x_k the weights are δ_k, so c = x_k and x' = x_k + d_k;
- rigid motions are reproduced within the reach: if every control moves by one
  rotation R about one centre (d_k = (R − I)(x_k − c₀), ω_k = log R), every target
  within ℓ of its pivot moves by that rigid motion, whatever its weights — the property
  plain IDW lacks, which shears the cells next to a turning body;
- it reduces to plain IDW when every ω_k = 0;
- the sums are one IDW product with four value columns per displacement
  (:func:`blend_rigid_motions`), so the fused kernels, batches, dense or matrix-free W
  and gradients carry over unchanged.

The rotation of a control is fitted to the motion of its neighbourhood by Horn's
quaternion method (the eigenvector of the largest eigenvalue of a symmetric 4 × 4
matrix; Horn, J. Opt. Soc. Am. A 4, 1987), which is exact for a rigid motion, needs no
more than three non-collinear points (flat neighbourhoods on a surface are fine), and
is differentiable where that eigenvalue is simple. In 2-D the rotation is an angle,
fitted in closed form. IDWarp's explicit interpolation (Luke, Collins and Blades, J.
Comput. Phys. 231, 2012) carries rotations in the same spirit.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchmorph._checks import check_same_device_dtype

__all__ = [
    "blend_rigid_motions",
    "default_reach",
    "fit_rotations",
    "rotation_matrices",
    "rotation_size",
]

_SMALL = 1e-6  # below this angle (radians) the quaternion logarithm uses its series


def rotation_size(dim: int) -> int:
    """Components of a rotation in ``dim`` dimensions: 1 (an angle) in 2-D, 3 in 3-D."""
    if dim not in (2, 3):
        raise ValueError(f"rotations exist here for 2-D and 3-D points, got dimension {dim}")
    return 1 if dim == 2 else 3


def _coefficients(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """sin θ / θ, (1 − cos θ) / θ², (θ − sin θ) / θ³ and
    (1 − θ sin θ / (2 (1 − cos θ))) / θ² from θ², with their Taylor series below a
    dtype-dependent angle (where the closed forms cancel), so that values and gradients
    stay finite and accurate at and near θ = 0."""
    eps = torch.finfo(theta2.dtype).eps
    small = theta2 < eps ** (1 / 3)  # θ below eps^(1/6): series exact to round-off
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    sin, cos = torch.sin(t), torch.cos(t)
    x2 = theta2
    a = torch.where(small, 1 - x2 / 6 + x2 * x2 / 120, sin / t)
    b = torch.where(small, 0.5 - x2 / 24 + x2 * x2 / 720, (1 - cos) / t2)
    c = torch.where(small, 1 / 6 - x2 / 120 + x2 * x2 / 5040, (t - sin) / (t2 * t))
    e = torch.where(
        small,
        1 / 12 + x2 / 720 + x2 * x2 / 30240,
        (1 - t * sin / (2 * (1 - cos))) / t2,
    )
    return a, b, c, e


def _skew(vectors: Tensor) -> Tensor:
    x, y, z = vectors.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def _planar(cos: Tensor, sin: Tensor) -> Tensor:
    """The 2 × 2 matrices cos I + sin J (J the quarter turn)."""
    return torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)


def rotation_matrices(rotations: Tensor) -> Tensor:
    """The rotation matrices of rotation vectors (…, 3) or angles (…, 1): (…, D, D).

    The exponential map (Rodrigues' formula), with its Taylor series near zero so that
    values and gradients stay finite at and around the identity.
    """
    if rotations.shape[-1] == 1:
        angle = rotations[..., 0]
        return _planar(torch.cos(angle), torch.sin(angle))
    if rotations.shape[-1] != 3:
        raise ValueError(
            f"rotations must have 1 (2-D angle) or 3 (rotation vector) components in the "
            f"last dimension, got shape {tuple(rotations.shape)}"
        )
    a, b, _, _ = _coefficients((rotations * rotations).sum(-1))
    skew = _skew(rotations)
    eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    return eye + a[..., None, None] * skew + b[..., None, None] * (skew @ skew)


def _quaternion_log(quaternion: Tensor) -> Tensor:
    """Rotation vectors (…, 3) of unit quaternions (…, 4) = (w, x, y, z)."""
    w = quaternion[..., 0]
    sign = torch.where(w < 0, -torch.ones_like(w), torch.ones_like(w))  # the short way
    w = w * sign
    v = quaternion[..., 1:] * sign[..., None]
    s2 = (v * v).sum(-1)
    small = s2 < _SMALL**2
    s = torch.sqrt(torch.where(small, torch.ones_like(s2), s2))
    # θ = 2 atan2(s, w); the vector is θ v / s, and 2 / w (1 − s²/(3w²)) near s = 0
    factor = torch.where(small, 2 / w * (1 - s2 / (3 * w * w)), 2 * torch.atan2(s, w) / s)
    return factor[..., None] * v


def fit_rotations(
    reference: Tensor,
    moved: Tensor,
    neighbours: Tensor,
) -> Tensor:
    """The rotation that best carries each point's neighbourhood from ``reference`` to
    ``moved`` (least squares over rigid motions).

    Parameters
    ----------
    reference : Tensor, shape (N, D)
        Positions before the motion (D = 2 or 3).
    moved : Tensor, shape (N, D) or (B, N, D)
        Positions after it (``reference + displacement``).
    neighbours : Tensor, shape (N, K), integer
        Row i lists the points whose motion defines point i's rotation (point i itself
        may be among them); entries of -1 are padding. Fewer than three non-collinear
        points give an undetermined rotation, returned as the one of smallest angle the
        method finds (zero for fewer than two points).

    Returns
    -------
    Tensor, shape (N, 1) in 2-D (angles) or (N, 3) in 3-D (rotation vectors), with a
    leading batch dimension B when ``moved`` has one. Differentiable in ``moved`` and
    ``reference`` (3-D: where the fit is unique).
    """
    if reference.ndim != 2 or reference.shape[1] not in (2, 3):
        raise ValueError(
            f"reference must have shape (N, 2) or (N, 3), got {tuple(reference.shape)}"
        )
    if moved.shape[-2:] != reference.shape or moved.ndim not in (2, 3):
        raise ValueError(
            f"moved must have shape {tuple(reference.shape)} or (B, "
            f"{', '.join(map(str, reference.shape))}), got {tuple(moved.shape)}"
        )
    check_same_device_dtype(reference, "reference", moved, "moved")
    if neighbours.ndim != 2 or neighbours.shape[0] != reference.shape[0]:
        raise ValueError(
            f"neighbours must have shape (N, K) with N = {reference.shape[0]}, got "
            f"{tuple(neighbours.shape)}"
        )
    if neighbours.dtype.is_floating_point or neighbours.dtype == torch.bool:
        raise TypeError(f"neighbours must be an integer tensor, got {neighbours.dtype}")
    if neighbours.numel() and (
        int(neighbours.min()) < -1 or int(neighbours.max()) >= reference.shape[0]
    ):
        raise ValueError(
            f"neighbours: entries must be point indices in [0, {reference.shape[0]}) or -1 "
            "for padding"
        )
    valid = (neighbours >= 0).to(reference.dtype)  # (N, K)
    index = neighbours.clamp(min=0).to(reference.device)
    valid = valid.to(reference.device)
    count = valid.sum(-1).clamp(min=1)[..., None]
    p = reference[index]  # (N, K, D)
    q = moved[..., index, :]  # (…, N, K, D)
    p = p - (valid[..., None] * p).sum(-2, keepdim=True) / count[..., None]
    q = q - (valid[..., None] * q).sum(-2, keepdim=True) / count[..., None]
    p = p * valid[..., None]
    q = q * valid[..., None]
    if reference.shape[1] == 2:
        cross = (p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]).sum(-1)
        dot = (p * q).sum((-1, -2))
        return torch.atan2(cross, dot)[..., None]
    # Horn's method: the rotation's quaternion maximises qᵀ N q, N from the covariance
    s = torch.einsum("...ki,...kj->...ij", p.expand_as(q), q)  # (…, N, 3, 3)
    sxx, sxy, sxz = s[..., 0, 0], s[..., 0, 1], s[..., 0, 2]
    syx, syy, syz = s[..., 1, 0], s[..., 1, 1], s[..., 1, 2]
    szx, szy, szz = s[..., 2, 0], s[..., 2, 1], s[..., 2, 2]
    rows = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ]
    matrix = torch.stack([torch.stack(row, -1) for row in rows], -2)
    scale = matrix.abs().amax((-1, -2), keepdim=True)
    # a neighbourhood that did not move or has no extent: the identity
    unmoved = scale <= torch.finfo(matrix.dtype).tiny
    matrix = matrix / torch.where(unmoved, torch.ones_like(scale), scale)
    identity_quaternion = torch.zeros(4, dtype=matrix.dtype, device=matrix.device)
    identity_quaternion[0] = 1
    matrix = torch.where(unmoved, torch.diag(identity_quaternion), matrix)
    _, vectors = torch.linalg.eigh(matrix)
    return _quaternion_log(vectors[..., -1])


def blend_rigid_motions(
    apply: Callable[[Tensor], Tensor],
    *,
    controls: Tensor,
    targets: Tensor,
    displacements: Tensor,
    rotations: Tensor,
    reach: float,
) -> Tensor:
    """Target displacements of the blended rigid motions of the controls (module notes).

    Parameters
    ----------
    apply : callable
        The IDW product: (B', N_c, D) values at the controls -> (B', N_t, D) at the
        targets (an :class:`~torchmorph.idw.IDW` module, or a closure over
        :func:`~torchmorph.idw.idw_apply`). Called once, on 4B columns of vectors.
    controls : Tensor, shape (N_c, D)
        Control positions before the motion.
    targets : Tensor, shape (N_t, D)
        Target positions before the motion.
    displacements : Tensor, shape (N_c, D) or (B, N_c, D)
    rotations : Tensor, shape (N_c, r) or (B, N_c, r)
        Each control's rotation: r = 1 (angle, 2-D) or 3 (rotation vector, 3-D).
    reach : float
        ℓ > 0: the distance from the pivot within which the blended rotation turns a
        target fully (see :func:`default_reach`).

    Returns
    -------
    Tensor, shape (N_t, D) or (B, N_t, D)
        ``x' − x`` at the targets.
    """
    dim = controls.shape[-1]
    size = rotation_size(dim)
    if not (isinstance(reach, (int, float)) and math.isfinite(reach) and reach > 0):
        raise ValueError(f"reach must be a positive length, got {reach!r}")
    batched = displacements.ndim == 3
    d = displacements if batched else displacements[None]
    omega = rotations if rotations.ndim == 3 else rotations[None].expand(d.shape[0], -1, -1)
    if omega.shape[-1] != size or omega.shape[:2] != d.shape[:2]:
        raise ValueError(
            f"rotations must have shape ({d.shape[1]}, {size}) or (B, {d.shape[1]}, {size}) "
            f"for these {dim}-D displacements, got {tuple(rotations.shape)}"
        )
    spin = (omega * omega).sum(-1, keepdim=True)  # |ω_k|²: the pivot's weights
    if size < dim:  # an angle travels in the first column of a D-vector
        omega = torch.cat([omega, omega.new_zeros(*omega.shape[:-1], dim - size)], -1)
    spin_column = torch.cat([spin, spin.new_zeros(*spin.shape[:-1], dim - 1)], -1)
    columns = torch.cat([d, omega, spin * controls, spin_column], 0)  # (4B, N_c, D)
    blended = apply(columns)
    count = d.shape[0]
    mean_d, mean_omega = blended[:count], blended[count : 2 * count, :, :size]
    moment, total = blended[2 * count : 3 * count], blended[3 * count :, :, :1]
    tiny = torch.finfo(total.dtype).tiny
    centre = moment / torch.where(total > tiny, total, torch.ones_like(total))
    arm = targets - centre  # (B, N_t, D)
    distance = torch.sqrt((arm * arm).sum(-1, keepdim=True) + tiny)
    attenuation = torch.clamp(reach / distance, max=1.0)
    turn = rotation_matrices(attenuation * mean_omega)  # (B, N_t, D, D)
    moved = (turn @ arm[..., None])[..., 0] - arm + mean_d
    return moved if batched else moved[0]


def default_reach(points: Tensor, rotations: Tensor) -> float:
    """The size of the part that turns: half the diagonal of the bounding box of the
    points whose rotation is at least half the largest (rotations (N, r) or (B, N, r),
    the largest over a batch). 1.0 when nothing turns (the reach is then unused)."""
    size = rotations.detach().norm(dim=-1)
    if size.ndim == 2:
        size = size.amax(0)
    largest = float(size.max()) if size.numel() else 0.0
    if largest == 0.0:
        return 1.0
    turning = points.detach()[size >= 0.5 * largest]
    extent = turning.amax(0) - turning.amin(0)
    half_diagonal = 0.5 * float(extent.norm())
    return half_diagonal if half_diagonal > 0 else 1.0
