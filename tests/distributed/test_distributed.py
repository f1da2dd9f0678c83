"""Sharded IDW, mesh morph and POD (torchmorph.distributed) against the single-process
modules: 2 gloo ranks on the loopback interface, float64, to 1e-12; and ranks given
data that differs: every rank raises, naming what differs.

One spawn of two processes (tests/distributed/_distributed_worker.py) computes everything the
ranks compute; the tests compare it here with IDW, MeshMorph and PODReducer.
"""

from __future__ import annotations

import shutil
import socket

import _distributed_worker as worker
import pytest
import torch
import torch.multiprocessing as mp

from torchmorph import IDW, MeshMorph
from torchmorph._state import NotFittedError
from torchmorph.distributed import ShardedIDW, ShardedPOD, load_partitioned, shard_rows
from torchmorph.distributed._agreement import digest, tensor_checksums
from torchmorph.pod import PODReducer

TOLERANCE = {"atol": 1e-12, "rtol": 1e-12}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="module")
def ranks(tmp_path_factory):
    """What rank 0 and rank 1 computed, and the directory they wrote to."""
    outdir = tmp_path_factory.mktemp("distributed")
    mp.spawn(worker.run, args=(2, _free_port(), str(outdir)), nprocs=2, join=True)
    return [torch.load(outdir / f"rank{r}.pt", weights_only=False) for r in range(2)], outdir


def _rows(split: str, rank: int) -> torch.Tensor:
    sizes = worker.SPLITS[split]
    start = sum(sizes[:rank])
    return torch.arange(start, start + sizes[rank])


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize("split", list(worker.SPLITS))
@pytest.mark.slow  # two spawned processes
def test_sharded_idw_forward_equals_single_process(ranks, split, mode):
    results, _ = ranks
    controls, targets, displacements, _ = worker.idw_data()
    reference = IDW(controls, targets, mode=mode)(displacements)
    for rank, result in enumerate(results):
        rows = _rows(split, rank)
        assert torch.equal(result[f"idw/{split}/{mode}/rows"], rows)
        local = result[f"idw/{split}/{mode}/forward"]
        assert local.shape == (2, len(rows), 3)
        torch.testing.assert_close(local, reference[:, rows], **TOLERANCE)
        torch.testing.assert_close(result[f"idw/{split}/{mode}/gathered"], reference, **TOLERANCE)
    # the coincident target takes its control's displacement exactly on its rank
    assert torch.equal(results[0][f"idw/{split}/{mode}/forward"][:, 3], displacements[:, 5])


@pytest.mark.parametrize("split", list(worker.SPLITS))
@pytest.mark.slow  # two spawned processes
def test_sharded_idw_in_tree_mode_is_within_tolerance_of_the_exact_map(ranks, split):
    """mode='tree' on every rank (each rank's tree on its own targets): the gathered
    result, the ranks' adjoints summed and a ShardedPOD fitted through them, against the
    exact dense IDW (so small a cloud is summed exactly by the tree: this checks the
    plumbing; the tree's accuracy is tested in tests/idw)."""
    results, _ = ranks
    controls, targets, displacements, weights = worker.idw_data()
    exact = IDW(controls, targets, mode="dense")
    reference = exact(displacements)
    adjoint = sum(result[f"idw/{split}/tree/adjoint"] for result in results)
    expected = exact.weights_matrix().mT @ weights
    pod = PODReducer(num_modes=4).fit(exact, worker.training(controls))
    for result in results:
        gathered = result[f"idw/{split}/tree/gathered"]
        assert float((gathered - reference).norm() / reference.norm()) <= 1e-4
        projected = result[f"pod/{split}/tree/forward"]
        assert projected is None or torch.allclose(projected, pod(displacements), atol=1e-6)
    assert float((adjoint - expected).norm() / expected.norm()) <= 1e-4
    # a tolerance under auto: the sampled tree on the ranks with targets, exact on the empty one
    for rank, result in enumerate(results):
        gathered = result[f"idw/{split}/auto_tree/gathered"]
        assert float((gathered - reference).norm() / reference.norm()) <= 1e-3
        empty = worker.SPLITS[split][rank] == 0
        kind = ("matrix_free", None) if empty else ("tree", "sampled")
        assert result[f"idw/{split}/auto_tree/kind"] == kind


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize("split", list(worker.SPLITS))
@pytest.mark.slow  # two spawned processes
def test_sharded_idw_gradients_equal_single_process(ranks, split, mode):
    results, _ = ranks
    controls, targets, displacements, weights = worker.idw_data()
    d = displacements.clone().requires_grad_()
    c = controls.clone().requires_grad_()
    t = targets.clone().requires_grad_()
    (IDW(controls, targets, mode=mode)(d, controls=c, targets=t) * weights).sum().backward()
    assert d.grad.abs().max() > 0 and c.grad.abs().max() > 0 and t.grad.abs().max() > 0
    for rank, result in enumerate(results):
        # replicated inputs: every rank holds the whole gradient
        torch.testing.assert_close(result[f"idw/{split}/{mode}/grad_d"], d.grad, **TOLERANCE)
        torch.testing.assert_close(result[f"idw/{split}/{mode}/grad_c"], c.grad, **TOLERANCE)
        # local targets: their own rows
        torch.testing.assert_close(
            result[f"idw/{split}/{mode}/grad_t"], t.grad[_rows(split, rank)], **TOLERANCE
        )


@pytest.mark.parametrize("split", list(worker.SPLITS))
@pytest.mark.slow  # two spawned processes
def test_sharded_pod_equals_single_process(ranks, split):
    results, _ = ranks
    controls, targets, displacements, _ = worker.idw_data()
    training = worker.training(controls)
    reference = PODReducer(num_modes=4).fit(IDW(controls, targets, mode="dense"), training)
    for result in results:
        torch.testing.assert_close(
            result[f"pod/{split}/singular_values"], reference.singular_values_, **TOLERANCE
        )
    # the modes, assembled over ranks, equal the reference's up to sign
    modes = torch.cat([result[f"pod/{split}/modes"] for result in results], 1)
    signs = torch.sign((modes * reference.modes_).sum((1, 2)))
    assert torch.equal(signs.abs(), torch.ones(4, dtype=signs.dtype))
    torch.testing.assert_close(modes * signs[:, None, None], reference.modes_, **TOLERANCE)
    torch.testing.assert_close(
        results[0][f"pod/{split}/projection"], results[1][f"pod/{split}/projection"], rtol=0, atol=0
    )
    full = reference(displacements)
    for rank, result in enumerate(results):
        for mode in ("dense", "matrix_free"):  # P from the stored W, or from the adjoint
            torch.testing.assert_close(
                result[f"pod/{split}/{mode}/forward"], full[:, _rows(split, rank)], **TOLERANCE
            )
    torch.testing.assert_close(results[0][f"pod/{split}/gathered"], full, **TOLERANCE)
    assert results[1][f"pod/{split}/gathered"] is None
    for result in results:  # the function under ShardedPOD.fit, on the same snapshots
        modes, singular_values, _ = result[f"basis/{split}"]
        assert torch.equal(modes, result[f"pod/{split}/modes"])
        assert torch.equal(singular_values, result[f"pod/{split}/singular_values"])


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize("layout", ["default", "interleaved", "empty"])
@pytest.mark.slow  # two spawned processes
def test_sharded_mesh_morph_equals_single_process(ranks, layout, mode):
    results, _ = ranks
    mesh, boundary, node_weights = worker.mesh_data()
    morph = MeshMorph(mesh, mode=mode)
    reference = morph(boundary)
    d = boundary.clone().requires_grad_()
    points = mesh.points.clone().requires_grad_()
    (morph(d, points=points) * node_weights).sum().backward()
    count = mesh.points.shape[0]
    owned = [results[r][f"mesh/{layout}/{mode}/owned"] for r in range(2)]
    assert torch.equal(torch.cat(owned).sort().values, torch.arange(count))
    if layout == "default":  # half of the boundary and half of the interior nodes each
        for rank in range(2):
            expected = (
                torch.cat(
                    [
                        mesh.boundary_nodes[
                            shard_rows(len(mesh.boundary_nodes), rank=rank, world_size=2)
                        ],
                        mesh.interior_nodes[
                            shard_rows(len(mesh.interior_nodes), rank=rank, world_size=2)
                        ],
                    ]
                )
                .sort()
                .values
            )
            assert torch.equal(owned[rank], expected)
    if layout == "empty":
        assert owned[1].numel() == 0
        assert results[1][f"mesh/{layout}/{mode}/forward"].shape == (0, 3)
    for rank, result in enumerate(results):
        key = f"mesh/{layout}/{mode}"
        torch.testing.assert_close(result[f"{key}/forward"], reference[owned[rank]], **TOLERANCE)
        torch.testing.assert_close(result[f"{key}/grad_d"], d.grad, **TOLERANCE)
        torch.testing.assert_close(result[f"{key}/grad_points"], points.grad, **TOLERANCE)
    torch.testing.assert_close(results[0][f"mesh/{layout}/{mode}/gathered"], reference, **TOLERANCE)
    assert results[1][f"mesh/{layout}/{mode}/gathered"] is None


@pytest.mark.slow  # two spawned processes
def test_sharded_mesh_morph_takes_the_tree_by_its_tolerance(ranks):
    """ShardedMeshMorph(mesh, tolerance=...) under auto (the threshold lowered in the
    workers): each rank's sampled tree, the gathered morph within the tolerance."""
    results, _ = ranks
    mesh, boundary, _ = worker.mesh_data()
    reference = MeshMorph(mesh)(boundary)
    for result in results:
        assert result["mesh/auto_tree/kind"] == ("tree", "sampled")
        gathered = result["mesh/auto_tree/gathered"]
        assert 0 < float((gathered - reference).norm() / reference.norm()) <= 1e-3


@pytest.mark.parametrize("mode", ["dense", "matrix_free"])
@pytest.mark.parametrize("layout", ["default", "interleaved", "empty"])
@pytest.mark.slow  # two spawned processes
def test_sharded_mesh_pod_equals_single_process(ranks, layout, mode):
    results, _ = ranks
    mesh, boundary, _ = worker.mesh_data()
    training = worker.mesh_training(boundary)
    reference = PODReducer(num_modes=3).fit(MeshMorph(mesh, mode="dense"), training)(boundary)
    for result in results:
        owned = result[f"mesh/{layout}/{mode}/owned"]
        local = result[f"mesh/{layout}/{mode}/pod_forward"]
        torch.testing.assert_close(local, reference[owned], **TOLERANCE)
        # the boundary rows are copied, exactly
        is_boundary = torch.isin(owned, mesh.boundary_nodes)
        rows = torch.searchsorted(mesh.boundary_nodes, owned[is_boundary])
        assert torch.equal(local[is_boundary], boundary[rows])


@pytest.mark.slow  # two spawned processes
def test_restored_sharded_pod_runs_without_its_morph(ranks):
    results, _ = ranks
    _, _, displacements, _ = worker.idw_data()
    _, boundary, _ = worker.mesh_data()
    for result in results:
        restored = ShardedPOD(num_modes=4)
        restored.load_state_dict(result["pod/uneven/state"])
        assert restored.is_fitted and restored.num_inputs == 40 and restored.dim == 3
        assert torch.equal(restored(displacements), result["pod/uneven/dense/forward"])
        mesh_pod = ShardedPOD(num_modes=3)  # boundary rows copied, from the state alone
        mesh_pod.load_state_dict(result["mesh/interleaved/matrix_free/pod_state"])
        assert torch.equal(mesh_pod(boundary), result["mesh/interleaved/matrix_free/pod_forward"])
        assert torch.equal(mesh_pod.output_rows_, result["mesh/interleaved/matrix_free/owned"])
    state = results[1]["pod/uneven/state"]
    with pytest.raises(
        ValueError, match="num_modes: the state was saved with num_modes=4 but this ShardedPOD"
    ):
        ShardedPOD(num_modes=3).load_state_dict(state)
    tampered = dict(state, output_rows_=state["output_rows_"][1:])
    with pytest.raises(ValueError, match=r"'output_rows_'\]: must hold the global ids of the 8"):
        ShardedPOD(num_modes=4).load_state_dict(tampered)
    tampered = dict(state, projection_=state["projection_"][:, 1:])
    with pytest.raises(ValueError, match=r"'projection_'\]: has shape \(4, 39, 3\)"):
        ShardedPOD(num_modes=4).load_state_dict(tampered)
    # a state of the first layout (no copied rows): refused, not run wrongly
    old = {
        name: state[name]
        for name in ("modes_", "singular_values_", "energy_captured_", "projection_")
    }
    old["_extra_state"] = {"energy_tolerance": 1e-5, "num_modes": 4, "num_modes_": 4}
    with pytest.raises(ValueError, match="saved before version 2 .* fit the ShardedPOD again"):
        ShardedPOD(num_modes=4).load_state_dict(old)
    with pytest.raises(NotFittedError, match="this ShardedPOD is not fitted yet"):
        ShardedPOD()(displacements[0])


#: Each rank's message when the ranks disagree (rank 0's, rank 1's; one for both).
STOP_IDW = "; every rank stops building a ShardedIDW"
STOP_MESH = "; every rank stops building a ShardedMeshMorph"
STOP_POD = "; every rank stops fitting a ShardedPOD"
STOP_GATHER = "; every rank stops gathering rows"
DIFFERENT_VALUES = "holds other values on some ranks (replicated data must be equal bit for bit)"
REFERRED = "ValueError: {} failed its check on rank {} (that rank raised the error that says why)"
DISAGREEMENTS = {
    "controls_shifted": f"ValueError: controls {DIFFERENT_VALUES}{STOP_IDW}",
    "control_fewer": (
        f"ValueError: controls has shape (39, 3) on some ranks and (40, 3) on others{STOP_IDW}"
    ),
    "dtype": (
        "ValueError: controls has dtype torch.float32 on some ranks and torch.float64 on "
        f"others{STOP_IDW}"
    ),
    "power": f"ValueError: power is 2 on some ranks and 4 on others{STOP_IDW}",
    "tolerance": (
        f"ValueError: coincidence_tolerance is 1e-09 on some ranks and 1e-06 on others{STOP_IDW}"
    ),
    "overlapping_rows": (
        "ValueError: target_rows must partition the 31 target rows across the ranks: 3 are "
        "provided by no rank and 3 by several"
    ),
    "rows_on_one_rank": (
        f"ValueError: target_rows is given on some ranks and None on others{STOP_IDW}"
    ),
    "nan_target": (
        REFERRED.format("targets", 1) + STOP_IDW,
        "ValueError: targets holds 1 NaN or infinite value(s)",
    ),
    "tree_tolerance": f"ValueError: tolerance is 0.0001 on some ranks and 0.001 on others{STOP_IDW}",
    "error_control": (
        "ValueError: error_control (-1: None, 0: 'certified', 1: 'sampled') is -1 on some ranks "
        f"and 1 on others{STOP_IDW}"
    ),
    "mode": (
        (
            "ValueError: IDW(controls, targets) failed on rank 1 (that rank raised the error "
            f"that says why){STOP_IDW}"
        ),
        "ValueError: mode must be one of 'auto', 'dense', 'matrix_free', 'tree'; got 'bogus'",
    ),
    "not_a_tensor": (
        REFERRED.format("targets", 1) + STOP_IDW,
        "TypeError: targets must be a torch.Tensor, got list",
    ),
    "mesh_points": f"ValueError: mesh.points {DIFFERENT_VALUES}{STOP_MESH}",
    "selection": (
        "ValueError: plan: no face named 'inlet'",
        (
            "ValueError: plan: the selection failed on rank 0 (that rank raised the error "
            f"that says why){STOP_MESH}"
        ),
    ),
    "mesh_owned_overlap": (
        "ValueError: owned_nodes must partition the 125 mesh nodes across the ranks: 115 are "
        "owned by no rank and 10 by several"
    ),
    "pod_displacements": f"ValueError: displacements {DIFFERENT_VALUES}{STOP_POD}",
    "pod_dtype": (
        "ValueError: displacements has dtype torch.float32 on some ranks and torch.float64 on "
        f"others{STOP_POD}"
    ),
    "pod_num_modes": f"ValueError: num_modes is 3 on some ranks and 4 on others{STOP_POD}",
    "pod_inf": (
        REFERRED.format("displacements", 1) + STOP_POD,
        "ValueError: displacements holds 1 NaN or infinite value(s)",
    ),
    "pod_mesh_points_moved": f"ValueError: morph.points {DIFFERENT_VALUES}{STOP_POD}",
    "pod_reducer_on_a_shard": tuple(
        f"ValueError: morph returns {rows} of the 31 rows of a sharded map: a POD of one "
        "rank's rows is not the map's; fit a torchmorph.distributed.ShardedPOD on every rank "
        "instead"
        for rows in (23, 8)
    ),
    "pod_output_rows": (
        "ValueError: morph.output_rows must partition the 26 output rows across the ranks: "
        "13 are provided by no rank and 13 by several"
    ),
    "basis_dim": (
        "ValueError: snapshots has shape (4, n, 2) on some ranks and (4, n, 3) on others; "
        "every rank stops computing a sharded POD basis"
    ),
    "gather_width": (
        f"ValueError: local has shape (n, 2) on some ranks and (n, 3) on others{STOP_GATHER}"
    ),
    "gather_dtype": (
        "ValueError: local has dtype torch.float32 on some ranks and torch.float64 on others"
        + STOP_GATHER
    ),
    "gather_gap": (
        "ValueError: rows must partition the 5 rows across the ranks: 1 is provided by no "
        "rank and 0 by several"
    ),
    "gather_overlap": (
        "ValueError: rows must partition the 5 rows across the ranks: 2 are provided by no "
        "rank and 2 by several"
    ),
    "gather_num_rows": f"ValueError: num_rows is 5 on some ranks and 6 on others{STOP_GATHER}",
    "save_gap": (
        "ValueError: rows must partition the 5 rows across the ranks: 1 is provided by no "
        "rank and 0 by several"
    ),
}


@pytest.mark.parametrize("case", list(DISAGREEMENTS))
@pytest.mark.slow  # two spawned processes
def test_ranks_that_disagree_all_raise_naming_the_difference(ranks, case):
    results, outdir = ranks
    expected = DISAGREEMENTS[case]
    expected = (expected, expected) if isinstance(expected, str) else expected
    assert [result[f"error/{case}"] for result in results] == list(expected)
    if case == "save_gap":  # refused before anything was written
        assert not (outdir / "gap").exists() or not any((outdir / "gap").iterdir())


@pytest.mark.slow  # two spawned processes
def test_partitioned_files_and_batched_gather(ranks):
    results, outdir = ranks
    mesh, boundary, _ = worker.mesh_data()
    torch.testing.assert_close(
        load_partitioned(outdir / "parts"), MeshMorph(mesh, mode="dense")(boundary), **TOLERANCE
    )
    assert sorted(p.name for p in (outdir / "parts").iterdir()) == [
        "part-00000-of-00002.pt",
        "part-00001-of-00002.pt",
    ]
    expected = torch.tensor([0.0, 1.0, 0.0, 1.0, 0.0])[None, :, None].expand(2, 5, 2)
    torch.testing.assert_close(results[0]["gather_batched"], expected, rtol=0, atol=0)
    assert results[1]["gather_batched"] is None
    torch.testing.assert_close(load_partitioned(outdir / "batched"), expected + 1, rtol=0, atol=0)


@pytest.mark.slow  # two spawned processes
def test_load_partitioned_refuses_parts_that_do_not_belong_together(ranks, tmp_path):
    _, outdir = ranks
    second = "part-00001-of-00002.pt"
    mixed = tmp_path / "mixed"
    shutil.copytree(outdir / "batched", mixed)
    shutil.copy(outdir / "other_run" / second, mixed / second)
    with pytest.raises(ValueError, match="parts 0 and 1 were written by different runs"):
        load_partitioned(mixed)

    changed = tmp_path / "changed"
    shutil.copytree(outdir / "batched", changed)
    part = torch.load(changed / second, weights_only=True)
    part["values"] = part["values"] + 1
    torch.save(part, changed / second)
    with pytest.raises(ValueError, match="part 1's rows or values do not match the checksums"):
        load_partitioned(changed)

    # parts without a run record (as 0.1.0 wrote them) are still checked row by row
    plain = tmp_path / "plain"
    plain.mkdir()

    def write(rank: int, rows: list[int], width: int = 2, dtype=torch.float32) -> None:
        values = torch.ones(2, len(rows), width, dtype=dtype)
        part = {"rows": torch.tensor(rows), "values": values, "num_rows": 5}
        torch.save(part, plain / f"part-{rank:05d}-of-00002.pt")

    write(0, [0, 2, 4])
    write(1, [1])
    with pytest.raises(ValueError, match="hold each of the 5 rows exactly once: 1 are in no part"):
        load_partitioned(plain)
    write(1, [1, 2, 3])
    with pytest.raises(ValueError, match="0 are in no part and 1 in several"):
        load_partitioned(plain)
    write(1, [1, 3], width=3)
    with pytest.raises(ValueError, match=r"part 1 holds values of shape \(2, 2, 3\)"):
        load_partitioned(plain)
    write(1, [1, 3], dtype=torch.float64)
    with pytest.raises(ValueError, match="and dtype torch.float64, part 0 of shape"):
        load_partitioned(plain)
    write(1, [1, 3])
    torch.testing.assert_close(load_partitioned(plain), torch.ones(2, 5, 2))
    (plain / second).unlink()
    with pytest.raises(ValueError, match=r"parts of ranks \[1\] are missing"):
        load_partitioned(plain)


@pytest.mark.slow  # two spawned processes
def test_planar_sharded_pod_equals_single_process(ranks):
    results, _ = ranks
    _, _, weights, training, probe = worker.planar_data()
    everything = torch.arange(weights.shape[0] + 2)
    reference = PODReducer(num_modes=3).fit(worker.PlanarRows(weights, everything), training)
    assert reference.dim == 2
    expected = reference(probe)
    for rank, result in enumerate(results):
        local = result["planar/pod_forward"]
        assert local.shape == (13, 2)
        torch.testing.assert_close(local, expected[worker.PLANAR_SPLIT[rank]], **TOLERANCE)
    assert torch.equal(results[0]["planar/pod_forward"][0], probe[0])  # copied, exactly
    torch.testing.assert_close(results[0]["planar/pod_gathered"], expected, **TOLERANCE)


@pytest.mark.slow  # two spawned processes
def test_planar_sharded_idw_equals_single_process(ranks):
    results, _ = ranks
    if "planar/idw_error" in results[0]:
        assert results[0]["planar/idw_error"] == results[1]["planar/idw_error"]
        pytest.skip(f"torchmorph.idw.IDW refuses 2-D points: {results[0]['planar/idw_error']}")
    controls, targets, _, training, probe = worker.planar_data()
    reference = IDW(controls, targets)
    expected = reference(probe)
    reduced = PODReducer(num_modes=3).fit(reference, training)(probe)
    for rank, result in enumerate(results):
        torch.testing.assert_close(result["planar/idw_forward"], expected[rank::2], **TOLERANCE)
        torch.testing.assert_close(result["planar/idw_pod_forward"], reduced[rank::2], **TOLERANCE)


def test_checksums_see_bits_not_layout():
    generator = torch.Generator().manual_seed(3)
    values = torch.randn(50, 3, generator=generator, dtype=torch.float64)
    assert tensor_checksums(values) == tensor_checksums(values.T.contiguous().T)
    assert tensor_checksums(values) == tensor_checksums(values.clone())
    swapped = values[[1, 0, *range(2, 50)]]
    assert tensor_checksums(swapped) != tensor_checksums(values)
    nudged = values.clone()
    nudged[17, 2] = torch.nextafter(nudged[17, 2], torch.tensor(10.0, dtype=torch.float64))
    assert all(
        a != b for a, b in zip(tensor_checksums(nudged), tensor_checksums(values), strict=True)
    )
    assert tensor_checksums(torch.tensor([0.0, -0.0])) == tensor_checksums(torch.zeros(2))
    assert tensor_checksums(values.float()) != tensor_checksums(values)
    assert all(0 <= value < 2**48 for value in tensor_checksums(values))
    rows = torch.arange(5)
    assert digest(rows, values) != digest(values, rows)
    assert digest("tetra", rows) != digest("triangle", rows)


def test_shard_rows_splits_evenly():
    slices = [shard_rows(10, rank=r, world_size=4) for r in range(4)]
    assert [(s.start, s.stop) for s in slices] == [(0, 3), (3, 6), (6, 8), (8, 10)]
    assert shard_rows(1, rank=1, world_size=2) == slice(1, 1)
    with pytest.raises(ValueError, match=r"rank must be in \[0, 2\), got 2"):
        shard_rows(5, rank=2, world_size=2)
    with pytest.raises(ValueError, match="count must be a non-negative integer"):
        shard_rows(-1, rank=0, world_size=2)


def test_needs_a_process_group():
    controls, targets, _, _ = worker.idw_data()
    with pytest.raises(RuntimeError, match="torch.distributed is not initialized"):
        ShardedIDW(controls, targets)
