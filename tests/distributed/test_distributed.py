"""Sharded IDW, mesh morph and POD (torchmorph.distributed) against the single-process
modules: 2 gloo ranks on the loopback interface, float64, to 1e-12.

One spawn of two processes (tests/distributed/_distributed_worker.py) computes everything the
ranks compute; the tests compare it here with IDW, MeshMorph and PODReducer.
"""

from __future__ import annotations

import socket

import _distributed_worker as worker
import pytest
import torch
import torch.multiprocessing as mp

from torchmorph import IDW, MeshMorph
from torchmorph.distributed import ShardedIDW, load_partitioned, shard_rows
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
    training = worker._training(controls)
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
        torch.testing.assert_close(
            result[f"pod/{split}/forward"], full[:, _rows(split, rank)], **TOLERANCE
        )


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


@pytest.mark.parametrize("layout", ["default", "interleaved", "empty"])
@pytest.mark.slow  # two spawned processes
def test_sharded_mesh_pod_equals_single_process(ranks, layout):
    results, _ = ranks
    mesh, boundary, _ = worker.mesh_data()
    morph = MeshMorph(mesh, mode="dense")
    training = torch.stack(
        [boundary * k for k in (1.0, -0.5, 2.0)] + [boundary.flip(0) * 0.3, boundary.roll(5, 0)]
    )
    reference = PODReducer(num_modes=3).fit(morph, training)(boundary)
    for result in results:
        owned = result[f"mesh/{layout}/dense/owned"]
        torch.testing.assert_close(
            result[f"mesh/{layout}/dense/pod_forward"], reference[owned], **TOLERANCE
        )


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
    (outdir / "batched" / "part-00001-of-00002.pt").unlink()
    with pytest.raises(ValueError, match=r"parts of ranks \[1\] are missing"):
        load_partitioned(outdir / "batched")


@pytest.mark.slow  # two spawned processes
def test_partition_must_cover_every_node_once(ranks):
    results, _ = ranks
    count = worker.mesh_data()[0].points.shape[0]
    for result in results:
        assert result["partition_error"] == (
            f"owned_nodes must partition the {count} mesh nodes across the ranks: "
            f"{count - 10} nodes are owned by no rank and 10 by several"
        )


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


def test_sharded_pod_state_round_trips_and_is_checked():
    from torchmorph.distributed import ShardedPOD

    generator = torch.Generator().manual_seed(0)
    source = ShardedPOD(energy_tolerance=1e-6)
    source.modes_ = torch.randn(2, 7, 3, generator=generator, dtype=torch.float64)
    source.singular_values_ = torch.tensor([2.0, 1.0], dtype=torch.float64)
    source.energy_captured_ = torch.tensor([0.8, 1.0], dtype=torch.float64)
    source.projection_ = torch.randn(2, 5, 3, generator=generator, dtype=torch.float64)
    source.num_modes_ = 2
    state = source.state_dict()
    loaded = ShardedPOD(energy_tolerance=1e-6)
    loaded.load_state_dict(state)
    assert loaded.num_modes_ == 2 and loaded.is_fitted
    for name in ShardedPOD._BUFFERS:
        assert torch.equal(getattr(loaded, name), getattr(source, name))
    with pytest.raises(ValueError, match="energy_tolerance: the state was saved with"):
        ShardedPOD().load_state_dict(state)
    tampered = dict(state, projection_=state["projection_"][:1])
    with pytest.raises(ValueError, match="do not both hold num_modes_=2 modes"):
        ShardedPOD(energy_tolerance=1e-6).load_state_dict(tampered)
