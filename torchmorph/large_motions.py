"""Large motions of a mesh morph: rotation-aware IDW and morphing in increments.

Two remedies for the sheared and inverted cells that plain IDW (Algorithm 2 of
Ballarin et al. 2017) produces around a body that turns far:

- **Rotations** (:func:`rotation_aware`; ``MeshMorph(...)(d, rotations="fit")``): each
  control point carries the rotation of its neighbourhood on the boundary surface as
  well as its displacement, and the interior receives the blended rigid motion of
  :mod:`torchmorph.idw.rotations`. A rigid rotation of the whole moving boundary then
  moves the cells next to it rigidly.
- **Increments** (:func:`morph_in_steps`): the motion is applied in ``steps`` parts,
  each from the previous morphed mesh (the IDW weights of eq. 2 rebuilt from the current
  positions), along a path of boundary displacements — the final one reached in equal
  parts, or a family such as a rotation by a growing angle. Every step's mesh is checked
  for inverted cells: the first step that inverts one is reported, and ``refine`` splits
  a failing step into halves (up to that many times) before giving up.

Both work on any :class:`~torchmorph.morph.MeshMorph` (any element kinds, 2-D or 3-D,
IDW or a selection), are differentiable like its forward pass, and take batches (the
steps of a batch are walked one displacement at a time). Increments work with
``method="rbf"`` as well (the RBF system factorised again from each step's positions);
rotations do not (they blend IDW's positive weights): a ``ValueError``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from torch import Tensor

from torchmorph.idw.rotations import (
    blend_rigid_motions,
    default_reach,
    fit_rotations,
    rotation_size,
)
from torchmorph.mesh.quality import inverted_cells


class MeshMorph(Protocol):
    """What these functions use of a :class:`~torchmorph.morph.MeshMorph` (named here
    by its parts, so that the morph module can import this one)."""

    points: Tensor
    boundary_nodes: Tensor
    interior_nodes: Tensor
    control_nodes: Tensor
    selected: Tensor
    method: str

    @property
    def interpolant(self) -> Any: ...

    @property
    def dim(self) -> int: ...

    @property
    def cells(self) -> Any: ...

    def reference_mesh(self) -> Any: ...

    def controls_from_boundary(self, boundary_displacement: Tensor) -> Tensor: ...

    def _check_boundary(self, boundary_displacement: Tensor) -> None: ...

    def _orientations(self) -> tuple[Tensor, ...]: ...


__all__ = ["SteppedMorph", "boundary_neighbours", "morph_in_steps", "rotation_aware"]

Path = Tensor | Callable[[float], Tensor]


def boundary_neighbours(morph: MeshMorph) -> Tensor:
    """Each boundary node's neighbourhood on the boundary surface: itself and the nodes
    that share a boundary facet with it, as rows of ``morph.boundary_nodes``, shape
    (N_b, K) padded with -1. Computed once per morph and kept (not in its state)."""
    cached = getattr(morph, "_boundary_neighbours", None)
    if cached is not None and cached.device == morph.points.device:
        return cached
    boundary = morph.boundary_nodes
    count = boundary.shape[0]
    pairs = [torch.arange(count, device=boundary.device).repeat(2, 1)]
    for block in morph.reference_mesh().boundary_facets:
        rows = torch.searchsorted(boundary, block.nodes)  # facet nodes as boundary rows
        width = rows.shape[1]
        first = rows.repeat_interleave(width, dim=1).reshape(-1)
        second = rows.repeat(1, width).reshape(-1)
        pairs.append(torch.stack([first, second]))
    edges = torch.unique(torch.cat(pairs, 1), dim=1)  # sorted by the first row
    degree = torch.bincount(edges[0], minlength=count)
    width = int(degree.max()) if count else 0
    start = torch.cumsum(degree, 0) - degree
    column = torch.arange(edges.shape[1], device=boundary.device) - start[edges[0]]
    table = torch.full((count, width), -1, dtype=torch.long, device=boundary.device)
    table[edges[0], column] = edges[1]
    setattr(morph, "_boundary_neighbours", table)  # noqa: B010  (a cache, not state)
    return table


def _boundary_rotations(
    morph: MeshMorph, boundary_displacement: Tensor, rotations: str | Tensor, points: Tensor
) -> Tensor:
    size = rotation_size(morph.dim)
    if isinstance(rotations, str):
        if rotations != "fit":
            raise ValueError(
                f"rotations must be None, 'fit' or a tensor of rotations, got {rotations!r}"
            )
        reference = points[morph.boundary_nodes]
        return fit_rotations(
            reference, reference + boundary_displacement, boundary_neighbours(morph)
        )
    if not isinstance(rotations, Tensor):
        raise TypeError(
            f"rotations must be None, 'fit' or a Tensor, got {type(rotations).__name__}"
        )
    expected = (*boundary_displacement.shape[:-1], size)
    if rotations.shape != expected and rotations.shape != expected[-2:]:
        raise ValueError(
            f"rotations must have shape {expected[-2:]} or {expected} (one "
            f"{'angle' if size == 1 else 'rotation vector'} per boundary node), got "
            f"{tuple(rotations.shape)}"
        )
    if rotations.dtype != boundary_displacement.dtype or rotations.device != points.device:
        raise ValueError(
            f"rotations must have the displacement's dtype and device "
            f"({boundary_displacement.dtype}, {points.device}), got {rotations.dtype}, "
            f"{rotations.device}"
        )
    if not bool(torch.isfinite(rotations).all()):
        raise ValueError("rotations must be finite (found NaN or inf)")
    return rotations


def rotation_aware(
    morph: MeshMorph,
    boundary_displacement: Tensor,
    *,
    rotations: str | Tensor = "fit",
    points: Tensor | None = None,
    reach: float | None = None,
) -> Tensor:
    """The interior displacement of the blended rigid motions of the control points.

    Parameters
    ----------
    morph : MeshMorph
    boundary_displacement : Tensor, shape (N_b, D) or (B, N_b, D)
    rotations : "fit" or Tensor
        ``"fit"``: each boundary node's rotation fitted to the motion of its
        neighbourhood (:func:`boundary_neighbours`); a tensor (N_b, r) or (B, N_b, r):
        given rotations (r = 1, an angle in radians, in 2-D; r = 3, a rotation vector in
        3-D), e.g. the rotation of a rigid part.
    points : Tensor, shape (N, D), optional
        Positions to morph from instead of the reference (W rebuilt from them).
    reach : float, optional
        ℓ of :mod:`torchmorph.idw.rotations`: targets within it of the turning part's
        pivot turn fully, farther ones less. Default: the size of the turning part
        (:func:`~torchmorph.idw.rotations.default_reach` of the boundary nodes).

    Returns
    -------
    Tensor, shape (N_int, D) or (B, N_int, D)
    """
    if morph.method != "idw":
        raise ValueError(
            f"rotations: the rotation-aware morph blends IDW weights (method='idw'); this "
            f"morph's method is {morph.method!r}"
        )
    reference = morph.points if points is None else points
    omega = _boundary_rotations(morph, boundary_displacement, rotations, reference)
    if reach is None:
        reach = default_reach(reference[morph.boundary_nodes], omega)
    controls = reference[morph.control_nodes]
    targets = reference[morph.interior_nodes]

    def apply(values: Tensor) -> Tensor:
        if points is None:
            return morph.interpolant(values)
        return morph.interpolant(values, controls=controls, targets=targets)

    return blend_rigid_motions(
        apply,
        controls=controls,
        targets=targets,
        displacements=morph.controls_from_boundary(boundary_displacement),
        rotations=omega.index_select(-2, morph.selected),
        reach=reach,
    )


@dataclass
class SteppedMorph:
    """The result of :func:`morph_in_steps`.

    Attributes
    ----------
    displacement : Tensor, shape (N, D) or (B, N, D)
        Every node's displacement from the reference after the last step.
    fractions : list of float
        The path parameter t reached by each step taken (1.0 last), refinements
        included; per batch member when batched.
    inverted : list of int
        Inverted cells after each of those steps.
    first_inverted : float or None
        The path parameter of the first step after which a cell was inverted (None:
        every step kept every cell valid). For a batch, the smallest over the batch.
    """

    displacement: Tensor
    fractions: list = field(default_factory=list)
    inverted: list = field(default_factory=list)
    first_inverted: float | None = None


def _path_function(morph: MeshMorph, path: Path) -> Callable[[float], Tensor]:
    if callable(path) and not isinstance(path, Tensor):
        return path
    if not isinstance(path, Tensor):
        raise TypeError(
            f"path must be a boundary displacement Tensor or a callable t -> Tensor, got "
            f"{type(path).__name__}"
        )
    morph._check_boundary(path)
    return lambda t: t * path


def morph_in_steps(
    morph: MeshMorph,
    path: Path,
    steps: int,
    *,
    rotations: str | None = None,
    reach: float | None = None,
    refine: int = 0,
) -> SteppedMorph:
    """Apply a boundary motion in ``steps`` increments, each from the previous mesh.

    Parameters
    ----------
    morph : MeshMorph
    path : Tensor or callable
        The final boundary displacement (N_b, D) or (B, N_b, D), reached in equal
        parts; or ``path(t)`` giving the boundary displacement at t in [0, 1] (t = 0 the
        reference, t = 1 the final motion), e.g. a rotation by t times the angle.
    steps : int
        Number of equal steps of t (>= 1); 1 is the plain morph.
    rotations : None or "fit"
        ``"fit"``: each step is rotation-aware (:func:`rotation_aware`), the rotations
        fitted to that step's motion of the boundary.
    reach : float, optional
        Passed to :func:`rotation_aware` (default: the turning part's size, per step).
    refine : int
        A step after which a cell is inverted is split into halves, recursively, up to
        this many times (0: never); the result reports the steps actually taken.

    Returns
    -------
    SteppedMorph
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if isinstance(refine, bool) or not isinstance(refine, int) or refine < 0:
        raise ValueError(f"refine must be a non-negative integer, got {refine!r}")
    if rotations not in (None, "fit"):
        raise ValueError(f"rotations must be None or 'fit' for stepped morphs, got {rotations!r}")
    function = _path_function(morph, path)
    final = function(1.0)
    morph._check_boundary(final)
    if final.ndim == 3:  # a batch: each member walks its own steps
        results = [
            _walk(morph, _member(function, k), steps, rotations, reach, refine)
            for k in range(final.shape[0])
        ]
        firsts = [r.first_inverted for r in results if r.first_inverted is not None]
        return SteppedMorph(
            displacement=torch.stack([r.displacement for r in results]),
            fractions=[r.fractions for r in results],
            inverted=[r.inverted for r in results],
            first_inverted=min(firsts) if firsts else None,
        )
    return _walk(morph, function, steps, rotations, reach, refine)


def _member(function: Callable[[float], Tensor], k: int) -> Callable[[float], Tensor]:
    return lambda t: function(t)[k]


def _walk(
    morph: MeshMorph,
    function: Callable[[float], Tensor],
    steps: int,
    rotations: str | None,
    reach: float | None,
    refine: int,
) -> SteppedMorph:
    reference = morph.points
    boundary, interior = morph.boundary_nodes, morph.interior_nodes
    orientations = morph._orientations()
    result = SteppedMorph(displacement=torch.zeros_like(reference))
    current = reference
    previous_t, previous_boundary = 0.0, torch.zeros_like(reference[boundary])

    def advance(t: float, depth: int) -> None:
        nonlocal current, previous_t, previous_boundary
        target = function(t)
        increment = target - previous_boundary
        if rotations == "fit":
            moved = rotation_aware(morph, increment, rotations="fit", points=current, reach=reach)
        else:
            controls = morph.controls_from_boundary(increment)
            moved = morph.interpolant(
                controls,
                controls=current[morph.control_nodes],
                targets=current[interior],
            )
        candidate = current.index_copy(0, interior, current[interior] + moved)
        candidate = candidate.index_copy(0, boundary, reference[boundary] + target)
        bad = int(inverted_cells(candidate.detach(), morph.cells, orientations).sum())
        if bad and depth < refine:
            start = previous_t
            advance(0.5 * (start + t), depth + 1)
            advance(t, depth + 1)
            return
        current, previous_t, previous_boundary = candidate, t, target
        result.fractions.append(t)
        result.inverted.append(bad)
        if bad and result.first_inverted is None:
            result.first_inverted = t

    for k in range(1, steps + 1):
        advance(k / steps, 0)
    # the boundary rows exactly as prescribed (not the round-off of positions minus reference)
    result.displacement = (current - reference).index_copy(0, boundary, previous_boundary)
    return result
