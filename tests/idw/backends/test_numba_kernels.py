"""The fused CPU kernels (numba) against a float64 brute force written here.

The reference follows the paper's eqs. (1)–(2) in the ratio form: for target i and
control k, d²_ik by direct differences, m_i = max(min_k d²_ik, tiny); an ordinary row
has weights (m_i / d²_ik)^(p/2) normalised by their sum, a coincident row
(m_i <= radius2) weighs the controls within the radius equally.
"""

from __future__ import annotations

import importlib.util
import sys

import pytest
import torch

pytest.importorskip("numba")

from torchmorph.idw.backends.numba import kernels

POWERS = [0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 7.5]  # every power code
DTYPES = [torch.float32, torch.float64]
RADIUS2 = 1e-20  # (1e-10 × a unit diagonal)²: the library's default coincidence radius


def reference_unnormalised(targets, controls, power, radius2):
    """(r, m): the unnormalised float64 weights r_ik and the floored nearest m_i."""
    t, c = targets.double(), controls.double()
    tiny = torch.finfo(targets.dtype).tiny
    d2 = (t[:, None, :] - c[None, :, :]).square().sum(-1)
    nearest = d2.amin(1, keepdim=True).clamp_min(tiny)
    ratio = (nearest / d2.clamp_min(tiny)) ** (power / 2)
    coincident = nearest <= radius2
    within = (d2 <= radius2).double()
    return torch.where(coincident, within, ratio), nearest[:, 0]


def reference_weights(targets, controls, power, radius2=RADIUS2):
    r, _ = reference_unnormalised(targets, controls, power, radius2)
    return r / r.sum(1, keepdim=True)


def cloud(n_targets, n_controls, dim, dtype, seed=0):
    """Points in the unit cube (the caller's normalisation keeps clouds about unit size)."""
    generator = torch.Generator().manual_seed(seed)
    targets = torch.rand(n_targets, dim, generator=generator, dtype=torch.float64)
    controls = torch.rand(n_controls, dim, generator=generator, dtype=torch.float64)
    return targets.to(dtype), controls.to(dtype)


def random_values(rows, columns, dtype, seed=1):
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(rows, columns, generator=generator, dtype=torch.float64).to(dtype)


def tolerance(dtype):
    return {"rtol": 0, "atol": 2e-6 if dtype == torch.float32 else 1e-12}


@pytest.fixture(autouse=True)
def one_torch_thread(one_thread):
    """Kernels follow torch's thread count: one, unless a test says otherwise."""


# --------------------------------------------------------------------------- #
# values against the brute force
# --------------------------------------------------------------------------- #
def test_available():
    assert kernels.available()


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_nearest_squared_matches_brute_force(dtype, dim):
    # more targets than one block and controls over several chunks, both with a ragged end
    targets, controls = cloud(kernels.ROWS * 3 + 5, kernels.CHUNK * 2 + 7, dim, dtype)
    nearest = kernels.nearest_squared(targets, controls)
    exact = (targets.double()[:, None] - controls.double()[None]).square().sum(-1).amin(1)
    assert nearest.dtype == dtype and nearest.shape == (targets.shape[0],)
    torch.testing.assert_close(
        nearest.double(), exact, rtol=1e-6 if dtype == torch.float32 else 1e-14, atol=0
    )


def test_nearest_squared_is_zero_on_a_control():
    targets, controls = cloud(20, 300, 3, torch.float32)
    targets[7] = controls[123]
    assert kernels.nearest_squared(targets, controls)[7] == 0


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("extra", [0, 1])
def test_the_cpu_backend_finds_the_nearest_control_by_brute_force_or_a_kd_tree(
    dtype, extra, monkeypatch
):
    import torchmorph.idw.backends.numba as numba_backend

    n_controls = numba_backend.KD_TREE_BYTES // torch.empty(0, dtype=dtype).element_size() + extra
    targets, controls = cloud(40, n_controls, 3, dtype)
    targets[5] = controls[-1]  # on a control: exactly 0, floored at tiny
    used = []
    for module, name in ((kernels, "nearest_squared"), (numba_backend, "nearest_by_kd_tree")):
        original = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, f=original, n=name: used.append(n) or f(*a))
    nearest = numba_backend.NumbaBackend().nearest(targets, controls)
    assert used == ["nearest_squared" if extra == 0 else "nearest_by_kd_tree"]
    exact = (targets.double()[:, None] - controls.double()[None]).square().sum(-1).amin(1)
    exact = exact.clamp_min(torch.finfo(dtype).tiny)
    assert nearest.dtype == dtype and nearest[5] == torch.finfo(dtype).tiny
    torch.testing.assert_close(
        nearest.double(), exact, rtol=1e-6 if dtype == torch.float32 else 1e-14, atol=0
    )


@pytest.fixture
def small_gemm_blocks(monkeypatch):
    """Blocks of 7 rows of W (ragged at the end) for the many-column path."""
    import torchmorph.idw.backends.numba as numba_backend

    monkeypatch.setattr(numba_backend, "GEMM_BLOCK_BYTES", 7 * 30 * 8)
    return numba_backend


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("power", [1.0, 4.0, 7.5])
def test_many_columns_go_through_blocks_of_w_and_gemm(dtype, power, small_gemm_blocks):
    fused = small_gemm_blocks
    targets, controls = cloud(45, 30, 3, dtype)
    controls[4] = controls[3]
    targets[10], targets[20] = controls[3], controls[9]  # on two duplicates; on one control
    backend = fused.NumbaBackend()
    expected_w = reference_weights(targets, controls, power)
    threads = torch.get_num_threads()
    tolerance = {"rtol": 1e-5, "atol": 1e-6} if dtype == torch.float32 else {}
    for columns in (fused.GEMM_COLUMNS, fused.GEMM_COLUMNS + 1, 3 * 16):
        values = random_values(30, columns, dtype)
        nearest2 = None if columns > fused.GEMM_COLUMNS else backend.nearest(targets, controls)
        assert backend.needs_nearest(columns) == (columns <= fused.GEMM_COLUMNS)
        out, sums = backend.apply(targets, controls, values, power, RADIUS2, nearest2)
        assert (sums is None) == (columns > fused.GEMM_COLUMNS)
        assert out.dtype == dtype and out.shape == (45, columns)
        torch.testing.assert_close(out.double(), expected_w @ values.double(), **tolerance)
        torch.testing.assert_close(out[10], (values[3] + values[4]) / 2, **tolerance)
        torch.testing.assert_close(out[20], values[9], **tolerance)
        grad = random_values(45, columns, dtype, seed=2)
        back = backend.apply_transposed(targets, controls, grad, power, RADIUS2, nearest2, sums)
        torch.testing.assert_close(back.double(), expected_w.T @ grad.double(), **tolerance)
        assert torch.get_num_threads() == threads  # the caller's thread count is left alone


def test_a_batch_of_many_displacements_differentiates_through_the_blocks(small_gemm_blocks):
    from torch.autograd import gradcheck

    from torchmorph import IDW

    targets, controls = cloud(20, 30, 3, torch.float64)
    batch = small_gemm_blocks.GEMM_COLUMNS // 3 + 1
    displacements = random_values(batch * 30, 3, torch.float64).reshape(batch, 30, 3)
    fused = IDW(controls, targets, mode="matrix_free", implementation="fused")
    plain = IDW(controls, targets, mode="matrix_free", implementation="torch")
    torch.testing.assert_close(fused(displacements), plain(displacements))
    assert gradcheck(fused, (displacements.requires_grad_(True),))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("power", POWERS)
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("columns", [1, 3, 48])
def test_apply_matches_brute_force(dtype, power, dim, columns):
    targets, controls = cloud(kernels.ROWS * 2 + 3, kernels.CHUNK + 40, dim, dtype)
    values = random_values(controls.shape[0], columns, dtype)
    nearest2 = kernels.nearest_squared(targets, controls)
    out, sums = kernels.apply(targets, controls, values, power, RADIUS2, nearest2)
    r, _ = reference_unnormalised(targets, controls, power, RADIUS2)
    exact = (r / r.sum(1, keepdim=True)) @ values.double()
    assert out.shape == (targets.shape[0], columns) and out.dtype == dtype
    torch.testing.assert_close(out.double(), exact, **tolerance(dtype))
    torch.testing.assert_close(
        sums.double(), r.sum(1), rtol=2e-6 if dtype == torch.float32 else 1e-12, atol=0
    )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("power", POWERS)
def test_apply_interpolates_exactly_at_the_controls(dtype, power):
    targets, controls = cloud(10, 200, 3, dtype)
    targets[::2] = controls[[0, 50, 100, 150, 199]]
    values = random_values(200, 3, dtype)
    out, sums = kernels.apply(
        targets, controls, values, power, RADIUS2, kernels.nearest_squared(targets, controls)
    )
    assert torch.equal(out[::2], values[[0, 50, 100, 150, 199]])
    assert torch.equal(sums[::2], torch.ones(5, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_target_on_a_control_with_zero_radius_takes_its_value(dtype):
    # m_i = tiny, the coincident control's ratio is 1 and every other one underflows to 0
    targets, controls = cloud(4, 100, 3, dtype)
    targets[1] = controls[42]
    values = random_values(100, 3, dtype)
    out, _ = kernels.apply(
        targets, controls, values, 4.0, 0.0, kernels.nearest_squared(targets, controls)
    )
    assert torch.equal(out[1], values[42])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("power", [1.0, 4.0])
def test_coincident_duplicates_take_the_mean(dtype, power):
    targets, controls = cloud(6, 300, 3, dtype)
    controls[250] = controls[10]  # a duplicated control, the copies in different chunks
    controls[251] = controls[10]
    targets[3] = controls[10]
    values = random_values(300, 2, dtype)
    out, sums = kernels.apply(
        targets, controls, values, power, RADIUS2, kernels.nearest_squared(targets, controls)
    )
    mean = values[[10, 250, 251]].double().mean(0)
    torch.testing.assert_close(out[3].double(), mean, **tolerance(dtype))
    assert sums[3] == 3
    # the same mean whatever the order of the controls
    order = torch.randperm(300, generator=torch.Generator().manual_seed(3))
    shuffled, _ = kernels.apply(
        targets,
        controls[order],
        values[order],
        power,
        RADIUS2,
        kernels.nearest_squared(targets, controls[order]),
    )
    torch.testing.assert_close(shuffled[3].double(), mean, **tolerance(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("power", POWERS)
@pytest.mark.parametrize("dim", [2, 3])
def test_streaming_apply_matches_brute_force_in_one_pass(dtype, power, dim):
    # several chunks of controls, ordered far to near so that the nearest distance falls
    # chunk after chunk and the partial sums are rescaled each time
    targets, controls = cloud(kernels.ROWS * 2 + 3, 3 * kernels.CHUNK + 17, dim, dtype)
    order = torch.argsort((controls.double() - 0.5).square().sum(1), descending=True)
    controls = controls[order].contiguous()
    values = random_values(controls.shape[0], 4, dtype)
    out, sums, nearest2 = kernels.apply_streaming(targets, controls, values, power, RADIUS2)
    r, nearest = reference_unnormalised(targets, controls, power, RADIUS2)
    exact = (r / r.sum(1, keepdim=True)) @ values.double()
    torch.testing.assert_close(out.double(), exact, **tolerance(dtype))
    torch.testing.assert_close(
        sums.double(), r.sum(1), rtol=4e-6 if dtype == torch.float32 else 1e-12, atol=0
    )
    torch.testing.assert_close(
        nearest2.double(), nearest, rtol=4e-7 if dtype == torch.float32 else 1e-14, atol=0
    )


@pytest.mark.parametrize("dtype", DTYPES)
def test_streaming_apply_restarts_a_row_at_its_first_coincident_control(dtype):
    targets, controls = cloud(6, 3 * kernels.CHUNK, 3, dtype)
    last = 3 * kernels.CHUNK - 1
    controls[last - 300] = controls[last]  # duplicates in two later chunks
    targets[2] = controls[last]  # met only in the last chunks, after regular sums
    targets[4] = controls[0]  # met in the first chunk
    values = random_values(controls.shape[0], 2, dtype)
    out, sums, _ = kernels.apply_streaming(targets, controls, values, 4.0, RADIUS2)
    mean = values[[last - 300, last]].double().mean(0)
    torch.testing.assert_close(out[2].double(), mean, **tolerance(dtype))
    assert sums[2] == 2 and sums[4] == 1
    assert torch.equal(out[4], values[0])


def test_controls_within_the_radius_count_equally():
    # a target within the radius of two distinct controls weighs both by 1/2
    targets = torch.tensor([[0.5, 0.5], [0.1, 0.9]], dtype=torch.float64)
    controls = torch.tensor(
        [[0.5, 0.5 + 1e-9], [0.5, 0.5 - 2e-9], [0.0, 0.0], [1.0, 1.0]], dtype=torch.float64
    )
    values = torch.tensor([[1.0], [3.0], [10.0], [20.0]], dtype=torch.float64)
    out, _ = kernels.apply(
        targets, controls, values, 4.0, 1e-16, kernels.nearest_squared(targets, controls)
    )
    assert out[0, 0] == 2.0
    exact = reference_weights(targets, controls, 4.0, 1e-16) @ values
    torch.testing.assert_close(out, exact, rtol=0, atol=1e-14)


def test_float32_accumulation_at_case_b_scale():
    """Float32 error <= 1e-6 of max |d| with 14,126 controls (a sample of targets)."""
    targets, controls = cloud(48, 14126, 3, torch.float32, seed=4)
    values = random_values(14126, 3, torch.float32)
    out, _ = kernels.apply(
        targets, controls, values, 4.0, RADIUS2, kernels.nearest_squared(targets, controls)
    )
    exact = reference_weights(targets, controls, 4.0) @ values.double()
    error = (out.double() - exact).abs().max() / values.double().abs().max()
    assert error <= 1e-6


# --------------------------------------------------------------------------- #
# the transpose and the dense matrix
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("power", POWERS)
@pytest.mark.parametrize("columns", [1, 3])
def test_apply_transposed_matches_brute_force(dtype, power, columns):
    targets, controls = cloud(kernels.CHUNK + 30, kernels.ROWS * 2 + 5, 3, dtype)
    targets[5] = controls[3]  # a coincident row
    targets[6] = controls[3]
    grad = random_values(targets.shape[0], columns, dtype, seed=5)
    nearest2 = kernels.nearest_squared(targets, controls)
    _, sums = kernels.apply(
        targets, controls, random_values(controls.shape[0], 1, dtype), power, RADIUS2, nearest2
    )
    result = kernels.apply_transposed(targets, controls, grad, power, RADIUS2, nearest2, sums)
    exact = reference_weights(targets, controls, power).T @ grad.double()
    assert result.shape == (controls.shape[0], columns) and result.dtype == dtype
    torch.testing.assert_close(
        result.double(), exact, rtol=0, atol=2e-5 if dtype == torch.float32 else 1e-12
    )


@pytest.mark.parametrize("dtype", DTYPES)
def test_apply_transposed_is_the_adjoint_of_apply(dtype):
    # <W v, g> = <v, Wᵀ g>
    targets, controls = cloud(70, 90, 2, dtype)
    values, grad = random_values(90, 3, dtype), random_values(70, 3, dtype, seed=6)
    nearest2 = kernels.nearest_squared(targets, controls)
    out, sums = kernels.apply(targets, controls, values, 3.0, RADIUS2, nearest2)
    back = kernels.apply_transposed(targets, controls, grad, 3.0, RADIUS2, nearest2, sums)
    torch.testing.assert_close(
        (out.double() * grad.double()).sum(),
        (values.double() * back.double()).sum(),
        rtol=1e-5 if dtype == torch.float32 else 1e-12,
        atol=0,
    )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("power", POWERS)
@pytest.mark.parametrize("dim", [2, 3])
def test_weights_match_brute_force(dtype, power, dim):
    targets, controls = cloud(kernels.WEIGHT_ROWS * 3 + 1, kernels.CHUNK * 2 + 11, dim, dtype)
    targets[2] = controls[300]
    dense = kernels.weights(targets, controls, power, RADIUS2)
    exact = reference_weights(targets, controls, power)
    assert dense.shape == exact.shape and dense.dtype == dtype and dense.is_contiguous()
    torch.testing.assert_close(
        dense.double(), exact, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-14
    )
    torch.testing.assert_close(
        dense.double().sum(1),
        torch.ones(targets.shape[0], dtype=torch.float64),
        rtol=0,
        atol=1e-5 if dtype == torch.float32 else 1e-13,
    )
    assert dense[2, 300] == 1 and dense[2].count_nonzero() == 1


def test_weights_fill_out_and_agree_with_apply():
    targets, controls = cloud(37, 301, 3, torch.float64)
    out = torch.full((37, 301), torch.nan, dtype=torch.float64)
    result = kernels.weights(targets, controls, 4.0, RADIUS2, out=out)
    assert result is out and not out.isnan().any()
    values = random_values(301, 3, torch.float64)
    applied, _ = kernels.apply(
        targets, controls, values, 4.0, RADIUS2, kernels.nearest_squared(targets, controls)
    )
    torch.testing.assert_close(out @ values, applied, rtol=0, atol=1e-14)


# --------------------------------------------------------------------------- #
# threads, empty inputs, bad arguments, no numba
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("dtype", DTYPES)
def test_one_and_two_threads_agree(dtype):
    # the blocks do not depend on the thread count, so neither do the results
    targets, controls = cloud(kernels.ROWS * 5 + 3, 700, 3, dtype)
    values = random_values(700, 3, dtype)
    grad = random_values(targets.shape[0], 3, dtype)
    results = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        nearest2 = kernels.nearest_squared(targets, controls)
        out, sums = kernels.apply(targets, controls, values, 4.0, RADIUS2, nearest2)
        back = kernels.apply_transposed(targets, controls, grad, 4.0, RADIUS2, nearest2, sums)
        results.append(
            (nearest2, out, sums, back, kernels.weights(targets, controls, 4.0, RADIUS2))
        )
    for one, two in zip(*results, strict=True):
        assert torch.equal(one, two)
    import numba

    assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS  # restored


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_kernels_leave_torchs_thread_count_as_the_caller_set_it(threads):
    # numba's OpenMP layer shares the OpenMP runtime with torch: restoring numba's own
    # count after a call once set torch's too (1 became 2 after the first kernel call)
    from torchmorph import IDW

    targets, controls = cloud(40, 30, 3, torch.float64)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        kernels.nearest_squared(targets, controls)
        assert torch.get_num_threads() == threads
        IDW(controls, targets, mode="matrix_free", implementation="fused")(
            random_values(9 * 30, 3, torch.float64).reshape(9, 30, 3)  # 27 columns: blocks
        )
        assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(before)


def test_no_targets():
    controls = torch.rand(5, 3)
    targets = torch.empty(0, 3)
    assert kernels.nearest_squared(targets, controls).shape == (0,)
    out, sums = kernels.apply(targets, controls, torch.rand(5, 2), 4.0, 0.0, torch.empty(0))
    assert out.shape == (0, 2) and sums.shape == (0,)
    back = kernels.apply_transposed(
        targets, controls, torch.empty(0, 2), 4.0, 0.0, torch.empty(0), torch.empty(0)
    )
    assert torch.equal(back, torch.zeros(5, 2))
    assert kernels.weights(targets, controls, 4.0, 0.0).shape == (0, 5)


def test_bad_arguments_name_themselves():
    targets, controls = cloud(4, 6, 3, torch.float64)
    nearest2 = kernels.nearest_squared(targets, controls)
    values = torch.rand(6, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"controls must have dtype torch.float64 like targets"):
        kernels.nearest_squared(targets, controls.float())
    with pytest.raises(ValueError, match=r"targets must be float32 or float64, got torch.int64"):
        kernels.nearest_squared(targets.long(), controls)
    with pytest.raises(ValueError, match=r"controls must have shape \(N_c, 3\) like targets"):
        kernels.nearest_squared(targets, controls[:, :2])
    with pytest.raises(ValueError, match="controls must hold at least one point"):
        kernels.nearest_squared(targets, controls[:0])
    with pytest.raises(ValueError, match=r"values must have shape \(6, K\): one row per control"):
        kernels.apply(targets, controls, values[:5], 4.0, 0.0, nearest2)
    with pytest.raises(ValueError, match=r"nearest2 must have shape \(4,\)"):
        kernels.apply(targets, controls, values, 4.0, 0.0, nearest2[:3])
    with pytest.raises(ValueError, match="power must be finite and > 0, got 0.0"):
        kernels.apply(targets, controls, values, 0.0, 0.0, nearest2)
    with pytest.raises(ValueError, match="radius2 must be finite and >= 0, got -1.0"):
        kernels.apply(targets, controls, values, 4.0, -1.0, nearest2)
    with pytest.raises(ValueError, match=r"grad must have shape \(4, K\): one row per target"):
        kernels.apply_transposed(targets, controls, values, 4.0, 0.0, nearest2, nearest2)
    with pytest.raises(ValueError, match=r"out must be a contiguous tensor of shape \(4, 6\)"):
        kernels.weights(targets, controls, 4.0, 0.0, out=torch.empty(6, 4, dtype=torch.float64))
    with pytest.raises(TypeError, match="targets must be a torch.Tensor, got ndarray"):
        kernels.nearest_squared(targets.numpy(), controls)


def test_without_numba_the_module_imports_and_is_unavailable(monkeypatch):
    # fresh copies of the kernel modules, imported where numba cannot be (the originals
    # are put back in sys.modules by monkeypatch afterwards)
    import torchmorph.idw.backends.numba as package

    monkeypatch.setitem(sys.modules, "numba", None)
    for name in ("_jit", "kernels"):
        monkeypatch.delitem(sys.modules, f"{package.__name__}.{name}", raising=False)
        monkeypatch.setattr(package, name, getattr(package, name, None), raising=False)
    module = importlib.import_module("torchmorph.idw.backends.numba.kernels")
    assert module.available() is False
    with pytest.raises(RuntimeError, match="the fused CPU kernels need numba: pip install numba"):
        module.nearest_squared(torch.zeros(1, 3), torch.zeros(2, 3))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("columns", [1, 3, 48])
def test_dense_apply_matches_torch(dtype, columns):
    targets, controls = cloud(kernels.ROWS + 9, kernels.CHUNK * 2 + 3, 3, dtype)
    dense = kernels.weights(targets, controls, 4.0, RADIUS2)
    values = random_values(controls.shape[0], columns, dtype)
    result = kernels.dense_apply(dense, values)
    assert result.shape == (targets.shape[0], columns) and result.dtype == dtype
    torch.testing.assert_close(
        result.double(),
        dense.double() @ values.double(),
        rtol=0,
        atol=1e-6 if dtype == torch.float32 else 1e-14,
    )


def test_dense_apply_messages():
    with pytest.raises(ValueError, match=r"values must have shape \(4, K\): one row per column"):
        kernels.dense_apply(torch.rand(3, 4), torch.rand(3, 2))
    with pytest.raises(ValueError, match="weights must be contiguous"):
        kernels.dense_apply(torch.rand(4, 3).T, torch.rand(4, 2))
