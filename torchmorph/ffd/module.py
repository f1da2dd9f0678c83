"""The :class:`FFD` module: a box, its control lattice and the per-axis basis matrices
of the points inside it as registered buffers, over :mod:`torchmorph.ffd.functional`."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchmorph._checks import as_points, check_positive, check_same_device_dtype
from torchmorph._state import check_saved_hyperparameters, resize_buffers_for_load
from torchmorph.ffd.functional import (
    AXES,
    Basis,
    check_box,
    check_displacements,
    control_coordinates,
    ffd_apply,
    ffd_bases,
    scatter_inside,
)
from torchmorph.ffd.lattice import lattice_sum

__all__ = ["FFD"]


class FFD(nn.Module):
    """Free-form deformation: displacements of a control lattice in a box to
    displacements of points (Sederberg and Parry 1986, eq. 1; PyGeM's ``FFD``).

    A point x inside the box has local coordinates ``s = Rᵀ (x − origin) / lengths`` in
    [0, 1]^D and moves by ``d(x) = Σ_(i,j,k) B_i(s_1) B_j(s_2) B_k(s_3) d_ijk``, where
    ``d_ijk`` is the displacement of control point (i, j, k); a point outside the box
    does not move. It is a shape parametrisation (move a surface by FFD, then its volume
    mesh by :class:`~torchmorph.IDW` with the surface displacements as control values)
    and a volume morph by itself.

    Parameters
    ----------
    points : Tensor, shape (N, D)
        The points to move, D = 2 or 3 (float32 or float64; arrays become float64).
    origin : Tensor or sequence, shape (D,)
        The box corner at control point (0, …, 0) (PyGeM's ``box_origin``).
    lengths : Tensor or sequence, shape (D,)
        Edge lengths of the box along its axes, > 0 (PyGeM's ``box_length``).
    shape : sequence of D ints
        Control points per axis (n_1, …, n_D) (PyGeM's ``n_control_points``): >= 2
        for ``"bernstein"`` (degree n_k − 1 on axis k), >= degree + 1 for ``"bspline"``.
    basis : {"bernstein", "bspline"}
        Bernstein polynomials (PyGeM, SU2's ``BEZIER``) or clamped uniform B-splines
        (the knot vector of SU2's ``BSPLINE_UNIFORM``): knots ``degree + 1`` times at 0
        and at 1 and uniform between, so that the lattice corners and faces interpolate.
    degree : int, optional
        B-spline degree, default 3; must be None for the Bernstein basis.
    rotation : Tensor or array, shape (D, D), optional
        Orthogonal matrix whose columns are the box's axes, so that the box is
        ``origin + R · ([0, L_1] × … × [0, L_D])``; PyGeM's ``FFD.rotation_matrix``
        (from ``rot_angle``). None: an axis-aligned box.
    block_bytes : int, optional
        Byte budget of one block of temporaries in :meth:`forward` (default 4 MiB on the
        CPU, 256 MiB on CUDA; see :mod:`torchmorph.ffd.lattice`).

    Attributes
    ----------
    points : buffer, shape (N, D)
        A copy of the points.
    origin, lengths : buffers, shape (D,)
    rotation : buffer, shape (D, D)
        The identity for an axis-aligned box.
    inside : buffer, shape (N_in,), int64
        Indices of the points in the closed box, ascending.
    basis_x, basis_y, basis_z : buffers, shapes (N_in, n_k)
        The basis matrix of each axis at the inside points (``basis_z`` in 3-D only).
    build_time : float
        Seconds spent computing the bases.

    Raises
    ------
    ValueError
        Naming the argument: points not (N, 2) or (N, 3), empty or not finite; origin,
        lengths or rotation of the wrong shape, not finite, on another device or dtype
        than the points (tensors); lengths <= 0; a shape entry too small for the basis;
        an unknown basis; a degree given with the Bernstein basis; a rotation that is not
        orthogonal.

    Notes
    -----
    **Units.** Displacements are in physical units along the global axes. PyGeM's
    parameters are normalised and along the box's axes: ``array_mu_x[i, j, k]`` etc.
    map to ``d_ijk = R @ (lengths * (mu_x, mu_y, mu_z)[i, j, k])`` (without rotation,
    ``d[..., a] = lengths[a] * array_mu_<a>``); PyGeM's deformed points are
    ``points + ffd(d)``.

    **The box.** A point is inside when each local coordinate lies in the closed [0, 1]
    (as PyGeM), widened by a few units of rounding (``BOUNDARY_ULPS``) so that a point
    on a face computed as 1 + 1 ulp still counts; the bases are evaluated at the
    coordinates clamped to [0, 1]. The map is continuous across the box's boundary only
    when the control points on its faces do not move (for the Bernstein basis and
    clamped B-splines, the faces move with their own control points); the module does
    not enforce it. Which points are inside is fixed when the module is built.

    **Control points.** :attr:`control_points` gives their reference positions: uniform
    for Bernstein, the Greville abscissae of the knots for B-splines. An affine field
    ``d(x) = A x + b`` sampled there (``d_ijk = A c_ijk + b``) is reproduced exactly at
    every inside point (linear precision of both bases); a uniform ``d_ijk = b``
    translates every inside point by b.

    **Other codes.** The Bernstein map is PyGeM's (the tests compare with its formula;
    ``benchmarks/ffd.py`` finds PyGeM's own ``FFD`` within 2e-15 of it). The B-spline knots are SU2's for
    ``BSPLINE_UNIFORM`` (``degree + 1`` zeros and ones, uniform between). Local
    coordinates here are the affine ``Rᵀ (x − origin) / lengths``; SU2 and pyGeo instead
    find a point's parametric coordinates by inverting the lattice map x(s) = Σ B(s) c.
    The two agree when the reference control points are at :attr:`control_points`
    (uniform for Bernstein, Greville for B-splines, where x(s) is affine); a B-spline
    lattice of uniformly spaced control points in SU2 or pyGeo parametrises the box
    differently, and its points move differently.

    **Gradients.** :meth:`forward` is differentiable in the displacements (its
    backward pass recomputes the tensor-product weights block by block and keeps only
    the bases); pass moved ``points`` to differentiate in them as well. With the stored
    points, the forward composes with ``torch.func``: ``vmap`` over displacements (a
    mapped family equals the batched call), ``grad``, ``jacrev`` and ``jacfwd``.

    **State.** :meth:`state_dict` holds the buffers and, as extra state, ``basis``,
    ``degree`` and ``shape``. Loading a state saved with another basis, degree or lattice
    shape raises ``ValueError`` naming the field; the geometry (points, box, bases) is
    taken from the state whatever the number of points. The B-spline basis is dense
    per axis: its local support is not exploited (a 10 × 10 × 10 B-spline lattice costs
    what a Bernstein one does).

    Examples
    --------
    A PyGeM box (``pygem_ffd``, its parameters set) ported; ``x`` the points, (N, 3):

    >>> mu = np.stack([pygem_ffd.array_mu_x, pygem_ffd.array_mu_y, pygem_ffd.array_mu_z], -1)
    >>> ffd = FFD(x, origin=pygem_ffd.box_origin, lengths=pygem_ffd.box_length,
    ...           shape=tuple(pygem_ffd.n_control_points), rotation=pygem_ffd.rotation_matrix)
    >>> d = torch.from_numpy((mu * pygem_ffd.box_length) @ pygem_ffd.rotation_matrix.T)
    >>> moved = x + ffd(d)  # pygem_ffd(x.numpy()), to rounding
    """

    points: Tensor
    origin: Tensor
    lengths: Tensor
    rotation: Tensor
    inside: Tensor

    def __init__(
        self,
        points: Tensor,
        *,
        origin: Tensor | Sequence[float],
        lengths: Tensor | Sequence[float],
        shape: Sequence[int],
        basis: Basis = "bernstein",
        degree: int | None = None,
        rotation: Tensor | None = None,
        block_bytes: int | None = None,
    ) -> None:
        super().__init__()
        points, origin_t, lengths_t, sizes, basis, degree, rotation_t = check_box(
            points, origin, lengths, shape, basis, degree, rotation
        )
        self.basis: Basis = basis
        self.degree = degree
        self.shape = sizes
        self.block_bytes = (
            None if block_bytes is None else int(check_positive(block_bytes, "block_bytes"))
        )
        with torch.no_grad():
            points = points.detach().clone()
            origin_t, lengths_t = origin_t.detach().clone(), lengths_t.detach().clone()
            rotation_t = rotation_t.detach().clone()
            began = time.perf_counter()
            inside, bases = ffd_bases(
                points,
                origin=origin_t,
                lengths=lengths_t,
                shape=sizes,
                basis=basis,
                degree=degree,
                rotation=rotation_t,
            )
            self.build_time = time.perf_counter() - began
        self.register_buffer("points", points)
        self.register_buffer("origin", origin_t)
        self.register_buffer("lengths", lengths_t)
        self.register_buffer("rotation", rotation_t)
        self.register_buffer("inside", inside)
        for axis, matrix in zip(self._basis_names(), bases, strict=True):
            self.register_buffer(axis, matrix)

    # ------------------------------------------------------------------ views
    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def num_points(self) -> int:
        return self.points.shape[0]

    @property
    def num_inside(self) -> int:
        return self.inside.shape[0]

    def _basis_names(self) -> list[str]:
        return [f"basis_{axis}" for axis in AXES[: self.dim]]

    @property
    def bases(self) -> list[Tensor]:
        """The per-axis basis matrices, shapes (N_in, n_k)."""
        return [self._buffers[name] for name in self._basis_names()]  # type: ignore[misc]

    @property
    def inside_mask(self) -> Tensor:
        """Boolean (N,): which points are in the box."""
        mask = torch.zeros(self.num_points, dtype=torch.bool, device=self.points.device)
        mask[self.inside] = True
        return mask

    @property
    def control_points(self) -> Tensor:
        """Reference positions of the control points, shape (n_1, …, n_D, D), physical
        units: ``origin + R · (lengths ⊙ ξ)``, ξ uniform (Bernstein) or the Greville
        abscissae (B-splines)."""
        axes = [
            torch.tensor(
                control_coordinates(size, self.basis, self.degree),
                dtype=self.points.dtype,
                device=self.points.device,
            )
            for size in self.shape
        ]
        local = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
        return self.origin + (local * self.lengths) @ self.rotation.T

    # ------------------------------------------------------------------ state
    def _hyperparameters(self) -> dict[str, object]:
        return {"basis": self.basis, "degree": self.degree, "shape": self.shape}

    def get_extra_state(self) -> dict:
        return self._hyperparameters()

    def set_extra_state(self, state: dict) -> None:
        check_saved_hyperparameters("FFD", _as_saved(state), self._hyperparameters())

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        if prefix + "_extra_state" in state_dict:  # before anything is loaded
            check_saved_hyperparameters(
                "FFD", _as_saved(state_dict[prefix + "_extra_state"]), self._hyperparameters()
            )
        names = ("points", "inside", *self._basis_names())
        resize_buffers_for_load(self, state_dict, prefix, names)
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        if self.points.shape[1:] != (self.dim,):
            error_msgs.append(f"points: shape {tuple(self.points.shape)} is not (N, {self.dim})")
        for name, size in zip(self._basis_names(), self.shape, strict=True):
            matrix = self._buffers[name]
            assert matrix is not None
            if matrix.shape != (self.num_inside, size):
                error_msgs.append(
                    f"{name}: shape {tuple(matrix.shape)} does not match "
                    f"{self.num_inside} inside points x {size} control points"
                )
        if self.num_inside and int(self.inside.max()) >= self.num_points:
            error_msgs.append(f"inside: indices beyond the {self.num_points} points")

    # ---------------------------------------------------------------- forward
    def forward(self, displacements: Tensor, *, points: Tensor | None = None) -> Tensor:
        """Displacements of the points under the lattice displacements.

        Parameters
        ----------
        displacements : Tensor, shape (..., n_1, …, n_D, D)
            Control-point displacements in physical units (e.g. (5, 5, 5, 3), or
            (B, 5, 5, 5, 3) for a batch), on the module's device and dtype.
        points : Tensor, shape (N, D), optional
            Moved positions of the module's points to use instead of the stored ones:
            the bases are recomputed from them, differentiably (a point that left or
            entered the box is outside or inside for this call).

        Returns
        -------
        Tensor, shape (..., N, D)
            Zero for the points outside the box. A batched result is a view of a
            (N, batch, D) buffer (not contiguous: ``.contiguous()`` copies it).
        """
        check_displacements(displacements, self.shape)
        check_same_device_dtype(self.points, "the module's points", displacements, "displacements")
        if points is not None:
            if not isinstance(points, Tensor):
                raise TypeError(f"points must be a torch.Tensor, got {type(points).__name__}")
            if points.shape != self.points.shape:
                raise ValueError(
                    f"points must have shape {tuple(self.points.shape)}, got {tuple(points.shape)}"
                )
            check_same_device_dtype(self.points, "the module's points", points, "points")
            as_points(points, "points", dim=self.dim)
            return ffd_apply(
                points=points,
                displacements=displacements,
                origin=self.origin,
                lengths=self.lengths,
                basis=self.basis,
                degree=self.degree,
                rotation=self.rotation,
                block_bytes=self.block_bytes,
            )
        moved = lattice_sum(self.bases, displacements, block_bytes=self.block_bytes)
        return scatter_inside(moved, self.inside, self.num_points)

    def extra_repr(self) -> str:
        lattice = " x ".join(str(size) for size in self.shape)
        degree = "" if self.degree is None else f", degree={self.degree}"
        return (
            f"num_points={self.num_points}, num_inside={self.num_inside}, "
            f"lattice={lattice}, basis={self.basis!r}{degree}"
        )


def _as_saved(state: Any) -> Any:
    """A saved extra state with its lattice shape as a tuple (a list after a round trip
    through a format that has no tuples)."""
    if isinstance(state, dict) and isinstance(state.get("shape"), list):
        return {**state, "shape": tuple(state["shape"])}
    return state
