"""Sharded IDW, mesh morph and POD on ``torch.distributed`` (gloo on the CPU, NCCL on GPUs).

A mesh too large for one process is partitioned: each rank owns a slice of the
nodes (its partition of the mesh). The control points and their displacements are
small (the boundary, or the selected part of it) and are replicated on every rank;
each rank assembles only its own rows of W (dense, or matrix-free through
:func:`torchmorph.idw.idw_apply`), so memory and work per rank are
O(N_owned · N_c). The forward pass returns the rank's own rows: no communication.

Launch with ``torchrun`` (or ``torch.multiprocessing``) and call
``torch.distributed.init_process_group`` first::

    dist.init_process_group("gloo")            # "nccl" with one GPU per rank
    morph = ShardedMeshMorph(mesh, plan)       # every rank: the same mesh and plan
    local = morph(boundary_displacement)       # (N_owned, D): rows morph.owned_nodes
    full = morph.gather(local)                 # (N, D) on rank 0, None elsewhere

Fields have D components (2 or 3: the points' dimension).

The ranks agree first
---------------------
Every collective entry point (building a module, ``ShardedPOD.fit``,
:func:`gather_rows`, :func:`save_partitioned`) begins with one all-reduce of a
fingerprint: checksums of the replicated tensors (controls, mesh points and cells,
training displacements), the hyper-parameters that change the result (``power``,
``coincidence_tolerance``, ``energy_tolerance``, ``num_modes``), the shapes and dtypes,
and each rank's verdict on its own inputs. Then either no rank raises or every rank
raises a ``ValueError`` that names what differs (a rank whose own input is bad raises
its own error, the others name it and the rank): no rank is left waiting in a
collective for one that raised. Row partitions (``target_rows``, ``owned_nodes``,
the rows given to :func:`gather_rows`) are checked by an all-reduce of one 32-bit
count per row.

What the ranks exchange
-----------------------
* Building a module: the fingerprint (it also carries the ranks' target counts),
  the global bounding box of the targets (an all-reduce of 2·D numbers; it sets
  the coincidence radius exactly as the single-process module does), the selected
  control points (a broadcast from rank 0) and the partition checks (with
  ``owned_nodes`` or ``target_rows`` given: an all-reduce of one integer per row).
* Backward: one all-reduce of the gradients to the replicated inputs
  (displacements, moved control or mesh positions).
* :class:`ShardedPOD` fit: the fingerprint, one all-gather of an n × n triangle per
  rank and one all-reduce of the online matrix; its online phase is local and needs
  only its state (a restored ``ShardedPOD`` runs without its morph).
* :func:`gather_rows` / :func:`save_partitioned`: only when asked (the fingerprint,
  the partition of the rows, the data); :func:`load_partitioned` checks that the
  parts were written together (every part records every part's checksums).

Boundary data known only on the ranks that own the boundary nodes is replicated
with ``gather_rows(values, rows, N_b, dst=None)`` (an all-gather; not
differentiable) before the forward pass.

Autograd
--------
Replicated inputs pass through :func:`replicate`, a custom autograd function that
is the identity forward and all-reduces (sums) the gradients backward: when every
rank backpropagates its part of a loss that is a sum over the nodes (its own
nodes' terms), every rank then holds the gradient of the total loss — the
single-process gradient — so an optimiser step on any rank takes the same step.
``torch.distributed.nn.functional.all_reduce`` is not used: it sums in the forward
pass as well (applied to a replicated input it would multiply it by the world
size), and one function over all replicated inputs issues one collective per
backward pass in a fixed order, whatever each rank's graph looks like.

Caveats: every rank must call ``backward`` (a rank with no nodes too: its output
is empty but connected to the inputs); a loss term on the replicated inputs
themselves (a regulariser on the displacement) must be added on one rank only,
or it is counted once per rank; replicated inputs must require grad on every
rank alike.
"""

from __future__ import annotations

from torchmorph.distributed._common import (
    gather_rows,
    load_partitioned,
    replicate,
    save_partitioned,
    shard_rows,
)
from torchmorph.distributed.morph import ShardedIDW, ShardedMeshMorph
from torchmorph.distributed.pod import ShardedPOD, sharded_pod_basis

__all__ = [
    "ShardedIDW",
    "ShardedMeshMorph",
    "ShardedPOD",
    "gather_rows",
    "load_partitioned",
    "replicate",
    "save_partitioned",
    "shard_rows",
    "sharded_pod_basis",
]
