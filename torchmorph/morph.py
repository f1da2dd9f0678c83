"""Shape morphing of a tetrahedral mesh (Ballarin et al. 2017, section 2, Algorithm 2).

:class:`MeshMorph` composes the pieces: control points chosen from the
boundary nodes (all of them, or a :class:`~torchmorph.selection.SelectionPlan`
for SIDW/ESIDW), an :class:`~torchmorph.idw.IDW` from the selected points to
the interior nodes, and the scatter of boundary and interior displacements
into one nodal field.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from torchmorph._checks import check_same_device_dtype, check_vectors
from torchmorph._state import resize_buffers_for_load
from torchmorph.idw.module import DEFAULT_DENSE_BYTES, IDW, Implementation, Mode
from torchmorph.mesh.model import TetMesh
from torchmorph.mesh.quality import signed_volumes

if TYPE_CHECKING:
    from torchmorph.selection.plan import SelectionPlan

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
    block_bytes, dense_bytes : int, optional
        Passed to :class:`~torchmorph.idw.IDW` (defaults: sized for the device, and
        half of the free memory).
    implementation : {"auto", "fused", "torch"}
        Passed to :class:`~torchmorph.idw.IDW`: fused kernels (Triton on CUDA, numba
        on the CPU) or torch operations.

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
    :meth:`count_inverted` (or :func:`torchmorph.mesh.quality.count_inverted`).

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
        block_bytes: int | None = None,
        dense_bytes: int | None = DEFAULT_DENSE_BYTES,
        implementation: Implementation = "auto",
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
            control_nodes = torch.as_tensor(
                plan.select(mesh, generator=generator), dtype=torch.long
            ).unique()
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
        names = list(mesh.node_sets)
        members = [mesh.node_sets[name].reshape(-1).long() for name in names]
        sizes = torch.tensor([0, *(len(nodes) for nodes in members)], dtype=torch.long)
        self._node_set_names: list[str] = names
        self.register_buffer(
            "node_set_members",
            torch.cat([boundary.new_empty(0), *(nodes.to(boundary.device) for nodes in members)]),
        )
        self.register_buffer("node_set_offsets", torch.cumsum(sizes, 0).to(boundary.device))
        self.idw = IDW(
            self.points[control_nodes],
            self.points[interior],
            power=power,
            mode=mode,
            block_bytes=block_bytes,
            dense_bytes=dense_bytes,
            implementation=implementation,
        )
        self.assembly_time = self.idw.assembly_time

    # ------------------------------------------------------------------ state
    _STATE_BUFFERS = (
        "points",
        "tets",
        "boundary_nodes",
        "interior_nodes",
        "selected",
        "control_nodes",
        "node_set_members",
        "node_set_offsets",
    )
    _STATE_VERSION = 1

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
        return {"version": self._STATE_VERSION, "node_set_names": list(self._node_set_names)}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self._node_set_names = list(state["node_set_names"])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        _check_morph_state(state_dict, prefix)
        resize_buffers_for_load(self, state_dict, prefix, self._STATE_BUFFERS)
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
        node_sets = self.node_sets
        for name in names:
            if name not in node_sets:
                known = ", ".join(sorted(node_sets)) or "none"
                raise ValueError(f"unknown node set {name!r}; known: {known}")
            mask[node_sets[name].to(mask.device)] = True
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
        if (
            not isinstance(values, Tensor)
            or values.shape[-2:] != moved_points.shape
            or values.ndim not in (2, 3)
        ):
            shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
            raise ValueError(
                f"displacement must return shape ({moved_points.shape[0]}, 3) or "
                f"(B, {moved_points.shape[0]}, 3), got {shape}"
            )
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
        check_vectors(
            boundary_displacement, "boundary_displacement", self.num_boundary, what="boundary nodes"
        )
        check_same_device_dtype(
            self.points, "the mesh points", boundary_displacement, "boundary_displacement"
        )

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
            interior = self.idw(
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
        """W (N_int, N_sel): ``forward(d)[:, interior_nodes] = W @ d[:, selected]``."""
        return self.idw.weights_matrix()

    def adjoint(self, fields: Tensor) -> Tensor:
        """The transpose of the morph: nodal fields (B, N, 3) -> (B, N_b, 3).

        Boundary rows pass through; interior rows are mapped by Wᵀ onto the control
        points (one GEMM with a dense W, a vector-Jacobian product of the IDW
        otherwise). The morph is linear, so ``<morph(d), g> = <d, adjoint(g)>``.
        """
        check_vectors(fields, "fields", self.num_nodes, what="mesh nodes")
        batch = fields if fields.ndim == 3 else fields.unsqueeze(0)
        interior = batch.index_select(1, self.interior_nodes)
        weights = getattr(self.idw, "weights", None)
        if isinstance(weights, Tensor):
            columns = interior.permute(1, 0, 2).reshape(self.num_interior, -1)  # (N_int, 3B)
            controls = (columns.mT @ weights).reshape(batch.shape[0], 3, -1).mT
        else:
            with torch.enable_grad():
                probe = batch.new_zeros(batch.shape[0], self.num_controls, 3, requires_grad=True)
                (controls,) = torch.autograd.grad(self.idw(probe), probe, grad_outputs=interior)
        result = batch.index_select(1, self.boundary_nodes)
        result = result.index_add(1, self.selected, controls)
        return result if fields.ndim == 3 else result[0]

    def deformed_points(self, displacement: Tensor) -> Tensor:
        """Reference points plus a nodal displacement (N, 3) or (B, N, 3)."""
        return self.points + displacement

    def inverted(self, displacement: Tensor) -> Tensor:
        """Mask of the tets whose signed volume is <= 0 after ``displacement``.

        ``displacement`` is a nodal field (N, 3) or a batch (B, N, 3); the mask has
        shape (M,) or (B, M) (as :func:`torchmorph.mesh.quality.inverted`).
        """
        check_vectors(displacement, "displacement", self.num_nodes, what="mesh nodes")
        with torch.no_grad():
            return signed_volumes(self.deformed_points(displacement.detach()), self.tets) <= 0

    def count_inverted(self, displacement: Tensor) -> int:
        """Number of tets whose signed volume is <= 0 after ``displacement`` (N, 3).

        Always an int, as :func:`torchmorph.mesh.quality.count_inverted`; for a batch
        (B, N, 3) count with ``inverted(displacement).sum(-1)``.
        """
        if isinstance(displacement, Tensor) and displacement.ndim == 3:
            raise ValueError(
                "displacement: count_inverted takes one field (N, 3); for a "
                "batch (B, N, 3) use inverted(displacement).sum(-1)"
            )
        return int(self.inverted(displacement).sum())

    def extra_repr(self) -> str:
        return (
            f"num_nodes={self.num_nodes}, num_boundary={self.num_boundary}, "
            f"num_interior={self.num_interior}, num_controls={self.num_controls}, "
            f"mode={self.idw.mode!r}"
        )


def _check_morph_state(state_dict, prefix: str) -> None:
    """Raise ``ValueError`` naming the field if a MeshMorph state is inconsistent.

    Runs before anything is loaded, so a rejected state leaves the module as it was.
    Missing entries are left to ``load_state_dict``'s own missing-key report.
    """

    def entry(name: str) -> Any:
        return state_dict.get(prefix + name)

    def fail(name: str, message: str) -> None:
        raise ValueError(f"state_dict[{prefix + name!r}]: {message}")

    def index(name: str, size: int | None = None) -> Tensor | None:
        value = entry(name)
        if value is None:
            return None
        if (
            not isinstance(value, Tensor)
            or value.ndim != 1
            or value.is_floating_point()
            or value.dtype == torch.bool
        ):
            fail(name, "must be a 1-D integer tensor")
        if (
            size is not None
            and value.numel()
            and (int(value.min()) < 0 or int(value.max()) >= size)
        ):
            fail(name, f"holds indices outside [0, {size})")
        return value

    extra = entry("_extra_state")
    if extra is not None:
        if (
            not isinstance(extra, dict)
            or not isinstance(extra.get("node_set_names"), list)
            or not all(isinstance(n, str) and n for n in extra["node_set_names"])
        ):
            fail("_extra_state", "must hold 'node_set_names', a list of non-empty strings")
        if extra.get("version") != MeshMorph._STATE_VERSION:
            fail(
                "_extra_state",
                f"version {extra.get('version')!r} is not {MeshMorph._STATE_VERSION}",
            )
    points = entry("points")
    if points is None:
        return
    if (
        not isinstance(points, Tensor)
        or points.ndim != 2
        or points.shape[1] != 3
        or not points.is_floating_point()
    ):
        fail("points", f"must be a floating tensor (N, 3), got {getattr(points, 'shape', points)}")
    num_nodes = points.shape[0]
    tets = entry("tets")
    if tets is not None:
        if not isinstance(tets, Tensor) or tets.ndim != 2 or tets.shape[1] != 4:
            fail("tets", "must have shape (M, 4)")
        if tets.numel() and (int(tets.min()) < 0 or int(tets.max()) >= num_nodes):
            fail("tets", f"holds vertex indices outside [0, {num_nodes})")
    boundary = index("boundary_nodes", num_nodes)
    interior = index("interior_nodes", num_nodes)
    if boundary is not None and interior is not None:
        together = torch.cat([boundary, interior]).cpu()
        if together.numel() != num_nodes or not torch.equal(
            torch.sort(together).values, torch.arange(num_nodes)
        ):
            fail(
                "interior_nodes",
                f"boundary_nodes and interior_nodes must split the {num_nodes} nodes into two sets",
            )
    selected = index("selected", None if boundary is None else boundary.numel())
    controls = index("control_nodes", num_nodes)
    if (
        selected is not None
        and controls is not None
        and boundary is not None
        and not torch.equal(boundary.cpu()[selected.cpu()], controls.cpu())
    ):
        fail("control_nodes", "must equal boundary_nodes[selected]")
    members = index("node_set_members", num_nodes)
    offsets = index("node_set_offsets")
    if members is not None and offsets is not None:
        steps = offsets.cpu().diff()
        if (
            offsets.numel() == 0
            or int(offsets[0]) != 0
            or int(offsets[-1]) != members.numel()
            or bool((steps < 0).any())
        ):
            fail("node_set_offsets", "must rise from 0 to the number of node_set_members")
        if extra is not None and offsets.numel() != len(extra["node_set_names"]) + 1:
            fail(
                "node_set_offsets",
                f"holds {offsets.numel() - 1} node sets but the names are "
                f"{len(extra['node_set_names'])}",
            )
    for name, expected in (
        ("idw.controls", None if controls is None else controls.numel()),
        ("idw.targets", None if interior is None else interior.numel()),
    ):
        value = entry(name)
        if expected is not None and isinstance(value, Tensor) and value.shape[0] != expected:
            fail(name, f"has {value.shape[0]} rows but the morph's state needs {expected}")
