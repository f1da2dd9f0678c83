"""Shape morphing of a tetrahedral mesh, SPEC.md §3 (the paper's Algorithm 2).

:class:`MeshMorph` composes the pieces: control points chosen from the
boundary nodes (all of them, or a :class:`~torchmorph.selection.SelectionPlan`
for SIDW/ESIDW), an :class:`~torchmorph.idw.IDW` from the selected points to
the interior nodes, and the scatter of boundary and interior displacements
into one nodal field.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from ._checks import check_same_device_dtype, check_vectors
from ._state import resize_buffers_for_load
from .idw import DEFAULT_BLOCK_BYTES, DEFAULT_DENSE_BYTES, IDW, Mode
from .mesh import TetMesh
from .quality import signed_volumes

if TYPE_CHECKING:
    from .selection import SelectionPlan

__all__ = ["MeshMorph"]


class MeshMorph(nn.Module):
    """IDW / SIDW / ESIDW morph of a tetrahedral mesh (Algorithm 2).

    Selection phase (once, here): choose the control points among the boundary
    nodes — every boundary node when ``plan`` is None (plain IDW), else the
    union of Algorithm 1 per region plus the enrichment sets of ``plan`` —
    and assemble W between them and the interior nodes.
    Deformation phase (:meth:`forward`, many times): boundary nodes take their
    prescribed displacement exactly; interior nodes get ``W d_selected``.

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh.
    plan : SelectionPlan, optional
        Control-point selection (SIDW/ESIDW). None: all boundary nodes.
    power : float
        IDW exponent (default 4).
    mode : {"auto", "dense", "matrix_free"}
        Passed to :class:`~torchmorph.idw.IDW`.
    generator : torch.Generator, optional
        Randomness of the selection (random start points and strategy).
    block_bytes, dense_bytes : int
        Passed to :class:`~torchmorph.idw.IDW`.

    Attributes
    ----------
    boundary_nodes : buffer (N_b,)
        Global ids of the boundary nodes; the rows of a boundary displacement.
    interior_nodes : buffer (N_int,)
        Global ids of the nodes interpolated by IDW.
    selected : buffer (N_sel,)
        Indices into ``boundary_nodes`` of the control points.
    control_nodes : buffer (N_sel,)
        Global ids of the control points.
    idw : IDW
        The interpolation from control points to interior nodes.
    selection_time, assembly_time : float
        Seconds spent selecting control points and assembling W.

    Notes
    -----
    Does not check the morphed mesh for inverted tetrahedra on its own: call
    :meth:`count_inverted` (or :func:`torchmorph.quality.count_inverted`).

    :meth:`forward` is differentiable with respect to the boundary displacement
    and to ``points``, works under ``torch.func`` transforms (``vmap`` over a
    parameter, ``jacrev``/``jacfwd`` with respect to it) and, with a dense W, under
    ``torch.compile(fullgraph=True)``; see :class:`~torchmorph.idw.IDW`.
    """

    def __init__(
        self,
        mesh: TetMesh,
        plan: SelectionPlan | None = None,
        *,
        power: float = 4.0,
        mode: Mode = "auto",
        generator: torch.Generator | None = None,
        block_bytes: int = DEFAULT_BLOCK_BYTES,
        dense_bytes: int = DEFAULT_DENSE_BYTES,
    ) -> None:
        super().__init__()
        if not isinstance(mesh, TetMesh):
            raise TypeError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
        boundary = mesh.boundary_nodes
        interior = mesh.interior_nodes
        start = time.perf_counter()
        if plan is None:
            control_nodes = boundary
        else:
            control_nodes = torch.as_tensor(plan.select(mesh, generator=generator),
                                            dtype=torch.long).unique()
        self.selection_time = time.perf_counter() - start
        selected = torch.searchsorted(boundary, control_nodes)
        if control_nodes.numel() == 0:
            raise ValueError("plan selected no control points")
        if (selected >= boundary.numel()).any() or not torch.equal(
            boundary[selected.clamp_max(boundary.numel() - 1)], control_nodes
        ):
            raise ValueError("plan selected nodes that are not boundary nodes")
        points = mesh.points
        self.register_buffer("points", points.detach().clone())
        self.register_buffer("tets", mesh.tets.clone())
        self.register_buffer("boundary_nodes", boundary.clone())
        self.register_buffer("interior_nodes", interior.clone())
        self.register_buffer("selected", selected)
        self.register_buffer("control_nodes", control_nodes.clone())
        self.node_sets = {name: nodes.clone() for name, nodes in mesh.node_sets.items()}
        self.idw = IDW(self.points[control_nodes], self.points[interior], power=power, mode=mode,
                       block_bytes=block_bytes, dense_bytes=dense_bytes)
        self.assembly_time = self.idw.assembly_time

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        resize_buffers_for_load(self, state_dict, prefix, (
            "points", "tets", "boundary_nodes", "interior_nodes", "selected", "control_nodes"))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ------------------------------------------------------------------ sizes
    @property
    def num_nodes(self) -> int:
        return self.points.shape[0]

    @property
    def num_boundary(self) -> int:
        return self.boundary_nodes.shape[0]

    @property
    def num_interior(self) -> int:
        return self.interior_nodes.shape[0]

    @property
    def num_controls(self) -> int:
        return self.selected.shape[0]

    @property
    def boundary_points(self) -> Tensor:
        """Reference coordinates of the boundary nodes, shape (N_b, 3)."""
        return self.points[self.boundary_nodes]

    # ------------------------------------------------------------ boundary data
    def boundary_mask(self, names: str | Sequence[str]) -> Tensor:
        """Boolean mask over the boundary nodes of the nodes in the named sets."""
        names = [names] if isinstance(names, str) else list(names)
        mask = torch.zeros(self.num_nodes, dtype=torch.bool, device=self.points.device)
        for name in names:
            if name not in self.node_sets:
                known = ", ".join(sorted(self.node_sets)) or "none"
                raise ValueError(f"unknown node set {name!r}; known: {known}")
            mask[self.node_sets[name].to(mask.device)] = True
        return mask[self.boundary_nodes]

    def boundary_displacement(
        self,
        moving: str | Sequence[str],
        displacement: Callable[[Tensor], Tensor],
    ) -> Tensor:
        """Boundary displacement that moves the named sets and fixes the rest.

        Parameters
        ----------
        moving : str or sequence of str
            Node sets that move (e.g. ``"wing"``); every other boundary node
            gets zero displacement.
        displacement : callable
            Maps reference coordinates (n, 3) to displacements (n, 3) or
            (B, n, 3).

        Returns
        -------
        Tensor, shape (N_b, 3) or (B, N_b, 3)
        """
        mask = self.boundary_mask(moving)
        moved_points = self.boundary_points[mask]
        values = displacement(moved_points)
        if not isinstance(values, Tensor) or values.shape[-2:] != moved_points.shape or \
                values.ndim not in (2, 3):
            shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
            raise ValueError(f"displacement must return shape ({moved_points.shape[0]}, 3) or "
                             f"(B, {moved_points.shape[0]}, 3), got {shape}")
        out = values.new_zeros(*values.shape[:-2], self.num_boundary, 3)
        return out.index_copy(-2, torch.nonzero(mask).flatten(), values)

    def controls_from_boundary(self, boundary_displacement: Tensor) -> Tensor:
        """The displacement of the selected control points, (N_sel, 3) or (B, N_sel, 3)."""
        return boundary_displacement.index_select(-2, self.selected)

    def assemble(self, boundary_displacement: Tensor, interior_displacement: Tensor) -> Tensor:
        """Scatter boundary and interior displacements into one nodal field (N, 3)."""
        shape = (*boundary_displacement.shape[:-2], self.num_nodes, 3)
        field = boundary_displacement.new_zeros(shape)
        field = field.index_copy(-2, self.boundary_nodes, boundary_displacement)
        return field.index_copy(-2, self.interior_nodes, interior_displacement)

    def _check_boundary(self, boundary_displacement: Tensor) -> None:
        check_vectors(boundary_displacement, "boundary_displacement", self.num_boundary,
                      what="boundary nodes")
        check_same_device_dtype(self.points, "the mesh points", boundary_displacement,
                                "boundary_displacement")

    # ----------------------------------------------------------------- morph
    def forward(self, boundary_displacement: Tensor, *, points: Tensor | None = None) -> Tensor:
        """Morph: displacement of every node of the mesh.

        Parameters
        ----------
        boundary_displacement : Tensor, shape (N_b, 3) or (B, N_b, 3)
            Prescribed displacement of every boundary node, ordered as
            ``boundary_nodes``.
        points : Tensor, shape (N, 3), optional
            Moved reference coordinates (shape optimisation): W is rebuilt
            differentiably from them.

        Returns
        -------
        Tensor, shape (N, 3) or (B, N, 3)
            Boundary rows equal ``boundary_displacement`` exactly.
        """
        self._check_boundary(boundary_displacement)
        controls = self.controls_from_boundary(boundary_displacement)
        if points is None:
            interior = self.idw(controls)
        else:
            if not isinstance(points, Tensor) or points.shape != self.points.shape:
                shape = tuple(points.shape) if isinstance(points, Tensor) else type(points)
                raise ValueError(f"points must have shape {tuple(self.points.shape)}, got {shape}")
            interior = self.idw(controls, controls=points[self.control_nodes],
                                targets=points[self.interior_nodes])
        return self.assemble(boundary_displacement, interior)

    def deformed_points(self, displacement: Tensor) -> Tensor:
        """Reference points plus a nodal displacement (N, 3) or (B, N, 3)."""
        return self.points + displacement

    def count_inverted(self, displacement: Tensor) -> int | Tensor:
        """Number of tets whose signed volume is <= 0 after ``displacement``.

        ``displacement`` is a nodal field (N, 3) (an int is returned) or a batch
        (B, N, 3) (a tensor of B counts).
        """
        check_vectors(displacement, "displacement", self.num_nodes, what="mesh nodes")
        with torch.no_grad():
            counts = (signed_volumes(self.deformed_points(displacement.detach()), self.tets) <= 0)
            counts = counts.sum(-1)
        return int(counts) if counts.ndim == 0 else counts

    def extra_repr(self) -> str:
        return (f"num_nodes={self.num_nodes}, num_boundary={self.num_boundary}, "
                f"num_interior={self.num_interior}, num_controls={self.num_controls}, "
                f"mode={self.idw.mode!r}")
