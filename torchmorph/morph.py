"""Shape morphing of a mesh (Ballarin et al. 2017, section 2, Algorithm 2).

:class:`MeshMorph` composes the pieces: control points chosen from the
boundary nodes (all of them, or a :class:`~torchmorph.selection.SelectionPlan`
for SIDW/ESIDW), an :class:`~torchmorph.idw.IDW` (or, with ``method="rbf"``, an
:class:`~torchmorph.rbf.RBF`) from the selected points to the interior nodes, and
the scatter of boundary and interior displacements into one nodal field. Nothing of
it depends on the element kinds or on the dimension: a :class:`~torchmorph.mesh.Mesh`
of any kinds, 2-D or 3-D, is morphed alike (the paper: SIDW/ESIDW "can be applied to
any dimension and to arbitrary meshes"); the cells only serve the boundary and the
validity checks.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from torchmorph._checks import check_same_device_dtype, check_vectors
from torchmorph._morph_methods import (
    Method,
    build_interpolant,
    check_method_options,
    check_moved_points,
    check_transforms,
    interpolation_matrix,
    solver_of,
)
from torchmorph._morph_state import (
    STATE_VERSION,
    check_interpolant_state,
    check_morph_state,
    check_variant,
    upgraded_state,
)
from torchmorph._state import check_saved_hyperparameters, resize_buffers_for_load
from torchmorph.idw.module import DEFAULT_DENSE_BYTES, IDW, Implementation, Mode
from torchmorph.idw.stiffened import StiffenedIDW
from torchmorph.mesh.cells import cell_kind
from torchmorph.mesh.model import CellBlock, Mesh
from torchmorph.mesh.quality import inverted_cells
from torchmorph.rbf.module import RBF
from torchmorph.rbf.partition import PartitionRBF
from torchmorph.rbf.sparse import SparseRBF

if TYPE_CHECKING:
    from torchmorph.selection.plan import AdaptivePlan, SelectionPlan

__all__ = ["MeshMorph"]


class MeshMorph(nn.Module):
    """IDW / SIDW / ESIDW (or RBF) morph of a mesh of any element kinds, 2-D or 3-D
    (Algorithm 2).

    Selection phase (once, here): choose the control points among the boundary
    nodes — every boundary node when ``plan`` is None (plain IDW), else the
    union of Algorithm 1 per region plus the enrichment sets of ``plan`` —
    and assemble W between them and the interior nodes (``method="rbf"``: factorise
    the RBF system of the control points instead).
    Deformation phase (:meth:`forward`, many times): boundary nodes take their
    prescribed displacement exactly; interior nodes get ``W d_selected``.

    Parameters
    ----------
    mesh : Mesh
        The reference mesh (a :class:`~torchmorph.mesh.TetMesh` or any
        :class:`~torchmorph.mesh.Mesh`: mixed, quadratic, 2-D). Its boundary is the
        facets used once; the mid-side nodes of quadratic boundary facets are boundary
        nodes, and the others interior nodes.
    plan : SelectionPlan or AdaptivePlan, optional
        Control-point selection: SIDW/ESIDW, or error-driven (AdaptivePlan). None: all
        boundary nodes. Either method interpolates from the controls it selects; an
        AdaptivePlan measures the error of this morph's method (its RBF options
        included) unless its own ``method`` says otherwise.
    method : {"idw", "rbf"}
        How the interior follows the controls: inverse distance weighting (the paper's
        eq. 2, default) or radial basis functions (:class:`~torchmorph.rbf.RBF`, exact at
        the controls, reproducing affine motions with ``degree >= 1``). An option of the
        other method is a ``ValueError`` naming it.
    power : float
        IDW exponent (default 4). IDW only.
    stiffening_length, stiffening_power : float, optional
        Near-wall stiffening of IDW (:class:`~torchmorph.idw.StiffenedIDW`): weights
        ``r^-p + ℓ^(q-p) r^-q`` with ℓ = ``stiffening_length`` (the thickness of the
        layer that moves nearly rigidly with its wall, in the mesh's units) and
        q = ``stiffening_power`` (default p + 2). IDW only; not with ``mode="tree"``.
    kernel, epsilon, degree, support_radius
        RBF only: passed to :class:`~torchmorph.rbf.RBF` (defaults: the thin-plate
        spline, degree 1; epsilon and support_radius as RBF requires for the kernel).
    solver, fit_tolerance : optional
        RBF only: the dense fit (default), the partition of unity (PartitionRBF, a few
        1e-3 from the global fit far from the controls; ``fit_tolerance``, its
        ``tolerance``, makes it the global fit), the sparse global fit of a Wendland
        kernel (SparseRBF), or ``"auto"``: beyond PARTITION_CONTROLS controls the sparse
        fit (Wendland) or the partition; neither takes moved ``points`` in :meth:`forward`.
    mode : {"auto", "dense", "matrix_free", "tree"}
        Passed to :class:`~torchmorph.idw.IDW` or :class:`~torchmorph.rbf.RBF`
        (``"tree"`` is IDW's only).
    tolerance, error_control : optional
        IDW's (:class:`~torchmorph.idw.IDW`): the tree's relative error (default 1e-4) and
        ``"certified"`` or the faster ``"sampled"`` in tree mode; a ``tolerance`` lets
        ``mode="auto"`` take the sampled tree where faster (stiffening stays exact).
    generator : torch.Generator, optional
        Randomness of the selection (random start points and strategy).
    block_bytes, dense_bytes : int, optional
        Passed to :class:`~torchmorph.idw.IDW` (defaults: sized for the device, and
        half of the free memory).
    implementation : {"auto", "fused", "torch"}
        Passed to :class:`~torchmorph.idw.IDW`: fused kernels (Triton on CUDA, numba
        on the CPU) or torch operations. IDW only.
    coincidence_tolerance : float
        Passed to :class:`~torchmorph.idw.IDW`. IDW only.

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
    method : str
        ``"idw"`` or ``"rbf"``.
    idw : IDW or StiffenedIDW
        With ``method="idw"``: the interpolation from control points to interior nodes
        (a StiffenedIDW with ``stiffening_length``).
    rbf : RBF
        With ``method="rbf"``: the same, by radial basis functions.
    interpolant : IDW or RBF
        Whichever of the two the morph has.
    selection_time, assembly_time : float
        Seconds spent selecting control points and assembling W (RBF: factorising the
        system and, dense, assembling its evaluation matrix).

    Notes
    -----
    Does not check the morphed mesh for inverted cells on its own: call
    :meth:`count_inverted` (or :func:`torchmorph.mesh.quality.count_inverted`).
    Every marker of the mesh (node sets, the nodes of face sets, groups) is a node set
    of the morph (:attr:`node_sets`), so a moving boundary can be named by an SU2
    marker or an OpenFOAM patch. Displacements are D-vectors, D the mesh's dimension.

    :meth:`forward` is differentiable with respect to the boundary displacement
    and to ``points``, works under ``torch.func`` transforms (``vmap`` over a
    parameter, ``jacrev``/``jacfwd`` with respect to it) and, with a dense W, under
    ``torch.compile(fullgraph=True)``; see :class:`~torchmorph.idw.IDW`.

    With ``method="rbf"`` everything above holds (the morph is linear in the
    displacement: POD reduction, :meth:`adjoint`, :meth:`weights_matrix` computed from
    the RBF, gradients, batches) except the rotation-aware morph (``rotations=``, which
    blends IDW's positive weights) and ``mode="tree"``: both raise ``ValueError``; and
    ``torch.func``: a transformed displacement, or ``vmap`` over ``points``, raise
    ``ValueError`` (the RBF's LAPACK solve does not pass through them; ``grad``/``jacrev``
    in the points work, ``jacfwd`` in them does not); ``torch.compile`` runs it with
    graph breaks (no ``fullgraph``).
    The method and the RBF's hyper-parameters are part of :meth:`state_dict`: a state
    loads only into a morph of the same method and hyper-parameters (states saved before
    the method existed are IDW's).
    """

    # buffers, registered in __init__
    points: Tensor
    cell_nodes: Tensor
    cell_orientation: Tensor
    boundary_nodes: Tensor
    interior_nodes: Tensor
    selected: Tensor
    control_nodes: Tensor
    node_set_members: Tensor
    node_set_offsets: Tensor

    def __init__(
        self,
        mesh: Mesh,
        plan: SelectionPlan | AdaptivePlan | None = None,
        *,
        method: Method = "idw",
        power: float | None = None,
        stiffening_length: float | None = None,
        stiffening_power: float | None = None,
        kernel: str | None = None,
        epsilon: float | None = None,
        degree: int | None = None,
        support_radius: float | None = None,
        solver: str | None = None,
        fit_tolerance: float | None = None,
        mode: Mode = "auto",
        generator: torch.Generator | None = None,
        block_bytes: int | None = None,
        dense_bytes: int | None = DEFAULT_DENSE_BYTES,
        implementation: Implementation | None = None,
        coincidence_tolerance: float | None = None,
        tolerance: float | None = None,
        error_control: str | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(mesh, Mesh):
            raise TypeError(
                f"mesh must be a torchmorph Mesh (or TetMesh), got {type(mesh).__name__}"
            )
        given = {  # IDW's, then RBF's
            "power": power, "stiffening_length": stiffening_length,
            "stiffening_power": stiffening_power, "implementation": implementation,
            "coincidence_tolerance": coincidence_tolerance, "tolerance": tolerance,
            "error_control": error_control, "kernel": kernel, "epsilon": epsilon,
            "degree": degree, "support_radius": support_radius, "solver": solver,
            "fit_tolerance": fit_tolerance,
        }  # fmt: skip
        options = check_method_options(method, mode, given)
        self.method: str = method
        boundary = mesh.boundary_nodes
        interior = mesh.interior_nodes
        start = time.perf_counter()
        control_nodes = select_controls(mesh, plan, generator, (method, options))
        self.selection_time = time.perf_counter() - start
        selected = boundary_rows(boundary, control_nodes)
        points = mesh.points
        self.register_buffer("points", points.detach().clone())
        self.register_buffer("cell_nodes", torch.cat([b.nodes.reshape(-1) for b in mesh.cells]))
        self.register_buffer("cell_orientation", torch.cat(mesh.orientation).clone())
        self._cell_blocks: list[tuple[str, int]] = [(b.kind, b.nodes.shape[0]) for b in mesh.cells]
        self.register_buffer("boundary_nodes", boundary.clone())
        self.register_buffer("interior_nodes", interior.clone())
        self.register_buffer("selected", selected)
        self.register_buffer("control_nodes", control_nodes.clone())
        names = list(mesh.markers)
        members = [mesh.node_set(name).reshape(-1).long() for name in names]
        sizes = torch.tensor([0, *(len(nodes) for nodes in members)], dtype=torch.long)
        self._node_set_names: list[str] = names
        self.register_buffer(
            "node_set_members",
            torch.cat([boundary.new_empty(0), *(nodes.to(boundary.device) for nodes in members)]),
        )
        self.register_buffer("node_set_offsets", torch.cumsum(sizes, 0).to(boundary.device))
        interpolant = build_interpolant(
            method,
            self.points[control_nodes],
            self.points[interior],
            mode=mode,
            block_bytes=block_bytes,
            dense_bytes=dense_bytes,
            options=options,
        )
        if isinstance(interpolant, (IDW, StiffenedIDW)):
            self.idw = interpolant
            self.assembly_time = interpolant.assembly_time
        else:
            self.rbf = interpolant
            self.assembly_time = interpolant.fit_time + getattr(interpolant, "evaluation_time", 0.0)

    def _stiffening(self) -> list[float] | None:
        idw = self._modules.get("idw")
        if isinstance(idw, StiffenedIDW):
            return [idw.stiffening_power, idw.stiffening_length]
        return None

    @property
    def interpolant(self) -> IDW | StiffenedIDW | RBF | PartitionRBF | SparseRBF:
        """The interpolation from the control points to the interior nodes: :attr:`idw`
        or :attr:`rbf`."""
        return self._modules[self.method]  # type: ignore[return-value]

    # ------------------------------------------------------------------ state
    _STATE_BUFFERS = (
        "points",
        "cell_nodes",
        "cell_orientation",
        "boundary_nodes",
        "interior_nodes",
        "selected",
        "control_nodes",
        "node_set_members",
        "node_set_offsets",
    )
    _STATE_VERSION = STATE_VERSION

    @property
    def node_sets(self) -> dict[str, Tensor]:
        """The mesh's named node sets (global node ids), as given to the constructor.

        Copies: editing them does not change the morph (its state is the
        ``node_set_members`` / ``node_set_offsets`` buffers)."""
        offsets = self.node_set_offsets.tolist()
        return {
            name: self.node_set_members[offsets[k] : offsets[k + 1]].clone()
            for k, name in enumerate(self._node_set_names)
        }

    def get_extra_state(self) -> dict[str, Any]:
        return {
            "version": self._STATE_VERSION,
            "method": self.method,
            "stiffening": self._stiffening(),
            "solver": solver_of(self.interpolant),
            "node_set_names": list(self._node_set_names),
            "cell_blocks": [list(block) for block in self._cell_blocks],
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self._node_set_names = list(state["node_set_names"])
        self._cell_blocks = [(str(kind), int(count)) for kind, count in state["cell_blocks"]]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        state_dict = upgraded_state(state_dict, prefix)
        check_morph_state(state_dict, prefix)
        extra = state_dict.get(prefix + "_extra_state")
        if extra is not None:  # before anything is loaded
            check_saved_hyperparameters("MeshMorph", extra, {"method": self.method})
            check_variant(extra, self._stiffening(), solver_of(self.interpolant))
        check_interpolant_state(state_dict, prefix + self.method + ".", self.interpolant)
        resize_buffers_for_load(self, state_dict, prefix, self._STATE_BUFFERS)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def cells(self) -> tuple[CellBlock, ...]:
        """The reference mesh's cell blocks, as stored (see :attr:`Mesh.cells`)."""
        blocks, start = [], 0
        for kind, count in self._cell_blocks:
            width = cell_kind(kind).num_nodes
            nodes = self.cell_nodes[start : start + count * width].reshape(count, width)
            blocks.append(CellBlock(kind, nodes))
            start += count * width
        return tuple(blocks)

    def reference_mesh(self) -> Mesh:
        """The reference mesh as stored in the module's state (points, cells, markers as
        node sets), for quality measures and norms on it."""
        return Mesh.from_checked(self.points, self.cells, self._orientations(), self.node_sets)

    def _orientations(self) -> tuple[Tensor, ...]:
        counts = [count for _, count in self._cell_blocks]
        return tuple(self.cell_orientation.split(counts))

    @property
    def dim(self) -> int:
        """The dimension D of the points and the displacements."""
        return int(self.points.shape[1])

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
        """Reference coordinates of the boundary nodes, shape (N_b, D)."""
        return self.points[self.boundary_nodes]

    # ------------------------------------------------------------ boundary data
    def boundary_mask(self, names: str | Sequence[str]) -> Tensor:
        """Boolean mask over the boundary nodes of the nodes in the named markers."""
        names = [names] if isinstance(names, str) else list(names)
        mask = torch.zeros(self.num_nodes, dtype=torch.bool, device=self.points.device)
        node_sets = self.node_sets
        for name in names:
            if name not in node_sets:
                known = ", ".join(node_sets) or "(none)"
                raise ValueError(f"unknown marker {name!r}; known: {known}")
            mask[node_sets[name].to(mask.device)] = True
        return mask[self.boundary_nodes]

    def boundary_displacement(
        self,
        moving: str | Sequence[str],
        displacement: Callable[[Tensor], Tensor],
    ) -> Tensor:
        """Boundary displacement that moves the named markers and fixes the rest.

        Parameters
        ----------
        moving : str or sequence of str
            Markers that move (e.g. ``"wing"``); every other boundary node gets zero
            displacement.
        displacement : callable
            Maps reference coordinates (n, D) to displacements (n, D) or (B, n, D).

        Returns
        -------
        Tensor, shape (N_b, D) or (B, N_b, D)
        """
        mask = self.boundary_mask(moving)
        moved_points = self.boundary_points[mask]
        values = displacement(moved_points)
        if (
            not isinstance(values, Tensor)
            or values.shape[-2:] != moved_points.shape
            or values.ndim not in (2, 3)
        ):
            shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
            count = moved_points.shape[0]
            raise ValueError(
                f"displacement must return shape ({count}, {self.dim}) or "
                f"(B, {count}, {self.dim}), got {shape}"
            )
        out = values.new_zeros(*values.shape[:-2], self.num_boundary, self.dim)
        return out.index_copy(-2, torch.nonzero(mask).flatten(), values)

    def controls_from_boundary(self, boundary_displacement: Tensor) -> Tensor:
        """The displacement of the selected control points, (N_sel, D) or (B, N_sel, D)."""
        return boundary_displacement.index_select(-2, self.selected)

    def assemble(self, boundary_displacement: Tensor, interior_displacement: Tensor) -> Tensor:
        """Scatter boundary and interior displacements into one nodal field (N, D)."""
        shape = (*boundary_displacement.shape[:-2], self.num_nodes, self.dim)
        field = boundary_displacement.new_zeros(shape)
        field = field.index_copy(-2, self.boundary_nodes, boundary_displacement)
        return field.index_copy(-2, self.interior_nodes, interior_displacement)

    def _check_boundary(self, boundary_displacement: Tensor) -> None:
        check_vectors(
            boundary_displacement,
            "boundary_displacement",
            self.num_boundary,
            dim=self.dim,
            what="boundary nodes",
        )
        check_same_device_dtype(
            self.points, "the mesh points", boundary_displacement, "boundary_displacement"
        )

    # ----------------------------------------------------------------- morph
    def forward(
        self,
        boundary_displacement: Tensor,
        *,
        points: Tensor | None = None,
        rotations: str | Tensor | None = None,
        reach: float | None = None,
    ) -> Tensor:
        """Morph: displacement of every node of the mesh (``W d_selected`` inside: IDW or
        RBF, as ``method``).

        Parameters
        ----------
        boundary_displacement : Tensor, shape (N_b, D) or (B, N_b, D)
            Prescribed displacement of every boundary node, ordered as
            ``boundary_nodes``.
        points : Tensor, shape (N, D), optional
            Moved reference coordinates (shape optimisation): W (RBF: the system) is
            rebuilt differentiably from them.
        rotations : None, "fit" or Tensor, optional
            Rotation-aware IDW for large rotations
            (:func:`torchmorph.large_motions.rotation_aware`): ``"fit"`` fits each
            boundary node's rotation to its neighbourhood's motion; a tensor (N_b, r) or
            (B, N_b, r) gives them (r = 1 angle in 2-D, 3 rotation vector in 3-D).
            None (default): plain IDW. ``method="idw"`` only.
        reach : float, optional
            With ``rotations``: the distance from the turning part within which the
            rotation is carried whole (default: that part's size).

        Returns
        -------
        Tensor, shape (N, D) or (B, N, D)
            Boundary rows equal ``boundary_displacement`` exactly.
        """
        self._check_boundary(boundary_displacement)
        if points is not None and (
            not isinstance(points, Tensor) or points.shape != self.points.shape
        ):
            shape = tuple(points.shape) if isinstance(points, Tensor) else type(points)
            raise ValueError(f"points must have shape {tuple(self.points.shape)}, got {shape}")
        if reach is not None and rotations is None:
            raise ValueError("reach: only a rotation-aware morph (rotations=...) takes a reach")
        check_transforms(self.method, boundary_displacement, points)
        if rotations is not None and self.method != "idw":
            raise ValueError(
                f"rotations: the rotation-aware morph blends IDW weights (method='idw'); this "
                f"morph's method is {self.method!r}"
            )
        if rotations is not None:
            from torchmorph.large_motions import rotation_aware

            interior = rotation_aware(
                self, boundary_displacement, rotations=rotations, points=points, reach=reach
            )
            return self.assemble(boundary_displacement, interior)
        controls = self.controls_from_boundary(boundary_displacement)
        if points is not None:
            check_moved_points(self.interpolant)
        if points is None:
            interior = self.interpolant(controls)
        else:
            interior = self.interpolant(
                controls, controls=points[self.control_nodes], targets=points[self.interior_nodes]
            )
        return self.assemble(boundary_displacement, interior)

    # ------------------------------------------------- the linear-map protocol
    def copied_rows(self) -> tuple[Tensor, Tensor]:
        """(output rows, input rows) that :meth:`forward` copies unchanged: every
        boundary node takes its prescribed displacement. Used by
        :class:`~torchmorph.pod.PODReducer`, which reproduces them exactly."""
        rows = torch.arange(self.num_boundary, device=self.boundary_nodes.device)
        return self.boundary_nodes, rows

    @property
    def weight_columns(self) -> Tensor:
        """The input rows (boundary indices) that :meth:`weights_matrix` reads."""
        return self.selected

    def weights_matrix(self) -> Tensor:
        """W (N_int, N_sel): ``forward(d)[:, interior_nodes] = W @ d[:, selected]``.

        IDW's stored (or assembled) W; for ``method="rbf"`` the RBF applied to the unit
        displacements of the controls (one batched solve and evaluation, N_int x N_sel
        memory)."""
        if self.method == "idw":
            return self.idw.weights_matrix()
        return interpolation_matrix(self.rbf, self.num_controls, self.dim)

    def adjoint(self, fields: Tensor) -> Tensor:
        """The transpose of the morph: nodal fields (B, N, D) -> (B, N_b, D).

        Boundary rows pass through; interior rows are mapped by Wᵀ onto the control
        points (one GEMM with IDW's dense W, a vector-Jacobian product of the IDW or
        RBF otherwise). The morph is linear, so ``<morph(d), g> = <d, adjoint(g)>``.
        """
        dim = self.dim
        check_vectors(fields, "fields", self.num_nodes, dim=dim, what="mesh nodes")
        batch = fields if fields.ndim == 3 else fields.unsqueeze(0)
        interior = batch.index_select(1, self.interior_nodes)
        weights = getattr(self.interpolant, "weights", None)
        if isinstance(weights, Tensor):
            columns = interior.permute(1, 0, 2).reshape(self.num_interior, -1)  # (N_int, D B)
            controls = (columns.mT @ weights).reshape(batch.shape[0], dim, -1).mT
        elif isinstance(self.interpolant, IDW) and self.interpolant.mode == "tree":
            controls = self.interpolant.transposed(interior)  # the tree's own transpose
        else:
            with torch.enable_grad():
                shape = (batch.shape[0], self.num_controls, dim)
                probe = batch.new_zeros(shape, requires_grad=True)
                (controls,) = torch.autograd.grad(
                    self.interpolant(probe), probe, grad_outputs=interior
                )
        result = batch.index_select(1, self.boundary_nodes)
        result = result.index_add(1, self.selected, controls)
        return result if fields.ndim == 3 else result[0]

    def deformed_points(self, displacement: Tensor) -> Tensor:
        """Reference points plus a nodal displacement (N, D) or (B, N, D)."""
        return self.points + displacement

    def inverted(self, displacement: Tensor) -> Tensor:
        """Mask of the cells that ``displacement`` inverts (a corner Jacobian or the volume
        <= 0, as :func:`torchmorph.mesh.quality.inverted`).

        ``displacement`` is a nodal field (N, D) or a batch (B, N, D); the mask has
        shape (M,) or (B, M), cells numbered across blocks in order.
        """
        check_vectors(displacement, "displacement", self.num_nodes, dim=self.dim, what="mesh nodes")
        moved = self.deformed_points(displacement.detach())
        return inverted_cells(moved, self.cells, self._orientations())

    def count_inverted(self, displacement: Tensor) -> int:
        """Number of cells that ``displacement`` (N, D) inverts.

        Always an int, as :func:`torchmorph.mesh.quality.count_inverted`; for a batch
        (B, N, D) count with ``inverted(displacement).sum(-1)``.
        """
        if isinstance(displacement, Tensor) and displacement.ndim == 3:
            raise ValueError(
                "displacement: count_inverted takes one field (N, D); for a "
                "batch (B, N, D) use inverted(displacement).sum(-1)"
            )
        return int(self.inverted(displacement).sum())

    def extra_repr(self) -> str:
        return (
            f"num_nodes={self.num_nodes}, num_boundary={self.num_boundary}, "
            f"num_interior={self.num_interior}, num_controls={self.num_controls}, "
            f"method={self.method!r}, mode={getattr(self.interpolant, 'mode', solver_of(self.interpolant))!r}"
        )


def select_controls(
    mesh: Mesh,
    plan: SelectionPlan | AdaptivePlan | None,
    generator: torch.Generator | None,
    morph: tuple[str, dict[str, Any]] | None = None,
) -> Tensor:
    """The control points of Algorithm 2's selection phase: every boundary node without a
    plan, else the plan's selection (SIDW/ESIDW, or error-driven for the interpolation
    ``morph``, its method and options); sorted unique global node ids."""
    from torchmorph.selection.plan import AdaptivePlan

    if plan is None:
        return mesh.boundary_nodes
    follows = {"morph": morph} if isinstance(plan, AdaptivePlan) else {}
    nodes = plan.select(mesh, generator=generator, **follows)
    return torch.as_tensor(nodes, dtype=torch.long).unique()


def boundary_rows(boundary: Tensor, control_nodes: Tensor) -> Tensor:
    """The rows of ``boundary`` (sorted node ids) that hold ``control_nodes``; ``ValueError``
    if there are none or some are no boundary nodes."""
    if control_nodes.numel() == 0:
        raise ValueError("plan selected no control points")
    control_nodes = control_nodes.to(boundary.device)
    rows = torch.searchsorted(boundary, control_nodes)
    if (rows >= boundary.numel()).any() or not torch.equal(
        boundary[rows.clamp_max(boundary.numel() - 1)], control_nodes
    ):
        raise ValueError("plan selected nodes that are not boundary nodes")
    return rows
