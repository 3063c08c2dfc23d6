"""Every CUDA kernel of csrc/ executed on the CPU under the CUDA emulator (tests/cuda_emu, headers in csrc/cuda_emu), with its
sanitizer on: the emulator's self-tests (broken kernels it must report, good patterns it must pass),
then the CUDA glue of every op (torch.ops.vrnet_ext_emu) against the CPU op (torch.ops.vrnet_ext) on
the same inputs, forward and backward, and the same named errors for bad input.

The emulated module is built by tests/cuda_emu/build.py (about 30 s on 2 cores, incremental). The
last test checks that every __global__ function in csrc/ ran; the run prints per-kernel launch
counts (see conftest.py)."""
from __future__ import annotations

import collections
import importlib
import math
import re
from pathlib import Path

import pytest
import torch

from conftest import DTYPES, non_contiguous, tolerances
from synthetic import lane_crowded_features, rounding_biased_features
from vrnet_ext.ops.soft_match import soft_match_reference
from cuda_emu import build as emu_build

CSRC = Path(__file__).resolve().parents[1] / "csrc"
CASES: collections.Counter = collections.Counter()


@pytest.fixture(scope="module", autouse=True)
def emulated():
    emu_build.load()
    torch.ops.vrnet_ext_emu.emu_configure(0, True, True)


def cpu_op(name):
    return getattr(torch.ops.vrnet_ext, name)


def emu_op(name):
    return getattr(torch.ops.vrnet_ext_emu, name)


def run_both(name: str, *args):
    """The CPU op and the emulated CUDA op on the same arguments: both results, or the same error."""
    CASES[name] += 1
    try:
        expected = cpu_op(name)(*args)
    except Exception as error:  # bad input: the CUDA glue raises the same error naming the same argument
        with pytest.raises(type(error)) as raised:
            emu_op(name)(*args)
        assert str(raised.value).split()[0] == str(error).split()[0], (str(raised.value), str(error))
        return None, None
    got = emu_op(name)(*args)
    as_tuple = lambda r: r if isinstance(r, (tuple, list)) else (r,)
    return as_tuple(expected), as_tuple(got)


def assert_same(name: str, *args, exact: bool = False, scale: float = 1.0):
    expected, got = run_both(name, *args)
    if expected is None:
        return None
    for a, b in zip(expected, got):
        assert a.shape == b.shape and a.dtype == b.dtype, name
        if exact or not a.is_floating_point():
            assert torch.equal(a, b) or (a.is_floating_point() and torch.equal(a.isnan(), b.isnan())
                                         and torch.equal(a.nan_to_num(), b.nan_to_num())), name
        else:
            tol = tolerances(a.dtype)
            torch.testing.assert_close(b, a, rtol=tol["rtol"] * scale, atol=tol["atol"] * scale, equal_nan=True)
    return expected


# --------------------------------------------------------------------------------------------------
# The emulator's self-tests.

def selftest(name: str, x: torch.Tensor) -> torch.Tensor:
    return torch.ops.vrnet_ext_emu.selftest(name, x)


@pytest.mark.parametrize("name, finding", [
    ("oob_write", r"out-of-bounds global write of 4 bytes .* past the end of argument 2.*block \(1,0,0\), thread \(0,0,0\)"),
    ("missing_sync", r"never written in this launch|without a barrier in between"),
    ("partial_barrier", r"__syncthreads\(\) not reached by every thread of the block: 32 of 64"),
    ("divergent_barrier", r"divergent __syncthreads\(\)"),
    ("shared_race", r"shared-memory race: write-write on shared offset 0"),
    ("invalid_shuffle_width", r"warp shuffle with width 24"),
    ("shuffle_missing_lanes", r"warp collective never completes: .* lanes \{16,17"),
    ("mma_beside_a_shuffle", r"meet at a tensor-core product and another collective"),
    ("inter_block_race", r"inter-block race on argument 1"),
])
def test_broken_kernels_are_reported(name, finding):
    with pytest.raises(RuntimeError, match=finding) as raised:
        selftest(name, torch.randn(64))
    assert f"kernel {name}_kernel" in str(raised.value)


def test_order_dependent_reduction_is_reported():
    """One float atomicAdd per block: the blocks in a seeded order and concurrently round differently.
    The concurrent order is the threads' schedule, which now and then sums in the same rounding as
    the seeded one (about a third of the launches here), so the kernel is launched up to 12 times,
    each with another seeded order, and must be reported by one of them."""
    generator = torch.Generator().manual_seed(1)
    x = ((torch.rand(64, generator=generator) - 0.5) * 10.0 ** torch.randint(-3, 9, (64,), generator=generator)).float()
    for _ in range(12):
        try:
            selftest("order_dependent_sum", x)
        except RuntimeError as error:
            assert "results depend on the order of blocks: argument 1" in str(error)
            return
    pytest.fail("none of 12 launches reported the order-dependent sum")


def test_wrong_shuffle_width_gives_a_wrong_sum():
    x = torch.arange(32, dtype=torch.float32)
    assert not torch.equal(selftest("narrow_shuffle_sum", x), torch.full((32,), float(x.sum())))


def test_good_patterns_pass():
    x = torch.randn(1000)
    sums = selftest("block_sum", x)  # divergent `if (warp == 0)` second-level shuffle reduction
    torch.testing.assert_close(sums, torch.stack([c.double().sum().float() for c in x.split(256)]))
    x = torch.randn(128)
    early = selftest("early_warp_exit", x)  # warps 2 and 3 return before warps 0 and 1 shuffle
    torch.testing.assert_close(early[:64], x[:64].view(2, 32).double().sum(1).float().repeat_interleave(32))
    torch.testing.assert_close(selftest("dynamic_shared", x), x.flip(0))
    counters = selftest("integer_atomics", torch.randint(-50, 50, (300,)).float().requires_grad_(False))
    assert counters.shape == (3,)


def test_warp_intrinsics():
    x = torch.randn(32)
    out = selftest("warp_intrinsics", x).view(32, 8)
    lanes = torch.arange(32)
    ballot = sum(1 << i for i in range(16) if x[i] > 0)
    assert torch.all(out[:, 0] == ballot)
    assert torch.all(out[:, 1] == float(bool((x > 2).any())))
    assert torch.all(out[:, 2] == 1.0)
    torch.testing.assert_close(out[:, 3], x[(lanes // 16) * 16 + 3])
    up = torch.where(lanes % 8 >= 2, lanes - 2, lanes)
    torch.testing.assert_close(out[:, 4], x[up])
    down = torch.where(lanes % 8 + 3 < 8, lanes + 3, lanes)
    torch.testing.assert_close(out[:, 5], x[down])
    torch.testing.assert_close(out[:, 6], x[lanes ^ 5])
    even = lanes[::2]
    torch.testing.assert_close(out[::2, 7], x[torch.where(even + 2 < 32, even + 2, even)])
    assert torch.all(out[1::2, 7] == -1)


def test_integer_atomics_match():
    x = torch.randint(-50, 50, (300,)).float()
    counters = selftest("integer_atomics", x)
    assert counters.tolist() == [float(x.sum()), float(x.min()), float(x.max())]


def test_launch_errors_are_python_errors():
    with pytest.raises(ValueError, match="unknown self-test kernel"):
        selftest("no_such_kernel", torch.randn(4))


# --------------------------------------------------------------------------------------------------
# Parity: the CUDA glue and kernels, emulated, against the CPU ops.

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N,M,C,k,exclude", [
    (1, 1, 1, 3, 1, False), (2, 301, 257, 3, 20, False), (1, 50, 50, 3, 49, True), (3, 97, 130, 3, 129, False),
    (2, 37, 53, 5, 17, False), (1, 129, 100, 64, 8, False), (1, 40, 40, 1, 40, False), (1, 60, 60, 8, 10, True),
    (1, 70, 90, 16, 70, False), (0, 5, 5, 3, 2, False), (1, 0, 5, 3, 2, False), (2, 45, 300, 33, 1, False),
    (1, 40, 70, 128, 20, True), (1, 30, 40, 200, 20, False),
])
def test_knn(dtype, B, N, M, C, k, exclude):
    query = torch.randn(B, N, C, dtype=dtype)
    ref = query if exclude else torch.randn(B, M, C, dtype=dtype)
    dist, idx = assert_same("knn", query, ref, k, exclude, exact=True)
    grad = torch.randn(dist.shape, dtype=dtype)
    assert_same("knn_backward", grad, query, ref, idx)


@pytest.mark.parametrize("C", [3, 7])
def test_knn_far_from_origin_and_ties(C):
    """Clouds 1e4 away from the origin (the expanded formula cancels without centring) and duplicated
    points (exact ties, broken by the lower index)."""
    base = torch.randn(1, 40, C) * 0.01 + 1e4
    ref = torch.cat([base, base[:, :10]], dim=1)
    assert_same("knn", base, ref, 12, False, exact=True)
    assert_same("knn", non_contiguous(torch.randn(2, 33, C)), torch.randn(2, 45, C), 5, False, exact=True)


@pytest.mark.parametrize("C", [4, 64, 128])
def test_knn_tensor_core_ranking_proven_or_rescanned(C):
    """float32 feature rows take the tensor-core path: each lane keeps candidates by approximate (TF32)
    distances, an exact ranking follows, and a row whose ranking the bound cannot prove is scanned whole.
    Cases that must fail the proof: a lane holding more of the nearest than it keeps, near-ties finer than
    the products' error, exact ties on a lattice, norms that overflow; and the proof's own cases: a cloud far from
    the origin, self-excluded batches over several tiles of rows and references."""
    generator = torch.Generator().manual_seed(C)
    query, ref = lane_crowded_features(C, generator)
    for k in (20, 32):
        assert_same("knn", query, ref, k, False, exact=True)
    assert_same("knn", *rounding_biased_features(C, generator), 20, False, exact=True)
    lattice = torch.randint(-2, 3, (1, 500, C), generator=generator).float()
    assert_same("knn", lattice[:, :40], lattice, 17, False, exact=True)
    far = torch.randn(1, 70, C, generator=generator) + 1e4
    assert_same("knn", far, far, 9, True, exact=True)
    pair = torch.randn(2, 200, C, generator=generator)
    assert_same("knn", pair, pair, 20, True, exact=True)
    assert_same("knn", non_contiguous(torch.randn(2, 70, C, generator=generator)),
                torch.randn(2, 129, C, generator=generator), 1, False, exact=True)
    overflowing = torch.randn(1, 90, C, generator=generator)
    overflowing[0, 7] *= 1e25  # its squared norm, and its distances, overflow float32
    assert_same("knn", overflowing, overflowing, 12, False, exact=True)
    assert_same("knn", overflowing * 1e20, overflowing[:, :40], 5, False, exact=True)


def test_knn_tensor_core_proof_as_modelled():
    """The rows the emulated kernel cannot prove are those benchmarks/knn_proof_rate.py's model of its
    arithmetic predicts (up to a few rows at the bound's edge: the model accumulates in float64): what the
    documented proof rates rest on."""
    import sys

    sys.path.insert(0, str(CSRC.parent / "benchmarks"))
    from knn_proof_rate import proven_rows

    generator = torch.Generator().manual_seed(3)
    normal = torch.randn(1, 300, 64, generator=generator)
    lattice = torch.randint(-2, 3, (1, 300, 8), generator=generator).float()
    for query, ref, k in [(normal, normal, 20), (*rounding_biased_features(16, generator), 20),
                          (*lane_crowded_features(32, generator), 20), (lattice, lattice, 5)]:
        CASES["knn_unproven_rows"] += 1
        unproven = emu_op("knn_unproven_rows")(query, ref, k, False)[0]
        modelled = ~proven_rows(query[0], ref[0], k)
        assert (unproven != modelled).sum() <= max(1, len(modelled) // 100), (int(unproven.sum()), int(modelled.sum()))
    assert not emu_op("knn_unproven_rows")(normal, normal, 20, False).any()  # every normal row proven
    with pytest.raises(ValueError, match="tensor-core search"):
        emu_op("knn_unproven_rows")(normal.double(), normal.double(), 20, False)


@pytest.mark.parametrize("dtype", DTYPES)
def test_knn_grid(dtype):
    """Reference clouds of 8,192 points or more go through the grid (the CPU's layout): a scan with
    duplicated points (ties), far strays kept apart from the grid, queries inside, beside and far
    outside it, k from 1 to 64, and a batch of two clouds searching themselves."""
    from vrnet_ext.data.procedural import room_scan

    ref = torch.as_tensor(room_scan(9000, 0)).to(dtype)
    ref[100:110] = ref[:10]                                               # exact ties
    ref[200:205] = torch.tensor([[1e4, 0, 0], [0, -3e3, 5], [40, 40, 40], [-7, 2e3, 1], [0, 0, 9e3]], dtype=dtype)
    query = torch.cat([ref[::40] + 0.01, torch.tensor([[50.0, 50, 50], [1e4, 1, 1], [-30, 0, 2]], dtype=dtype)])
    for k in (1, 20, 64):
        assert_same("knn", query[None], ref[None], k, False, exact=True)
    pair = torch.stack([ref, ref.flip(0) * 1.5])
    assert_same("knn", pair, pair, 8, True, exact=True)


def test_knn_bad_input_same_errors():
    q = torch.randn(1, 10, 3)
    assert run_both("knn", q, q, 11, False) == (None, None)
    assert run_both("knn", q, torch.randn(1, 10, 4), 2, False) == (None, None)
    bad = q.clone()
    bad[0, 3, 1] = math.nan
    assert run_both("knn", bad, q, 2, False) == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,C,N,k", [(1, 1, 1, 1), (3, 5, 129, 20), (2, 64, 257, 9), (1, 3, 30, 30)])
def test_edge_features_and_gather_reduce(dtype, B, C, N, k):
    x = torch.randn(B, C, N, dtype=dtype)
    idx = torch.randint(0, N, (B, N, k))
    out = assert_same("edge_features", x, idx, exact=True)[0]
    assert_same("edge_features_backward", torch.randn(out.shape, dtype=dtype), idx, N)
    assert_same("edge_features", non_contiguous(x), idx, exact=True)
    assert run_both("edge_features", x, idx - 1) == (None, None)
    assert run_both("edge_features_backward", out, idx, N + 1) == (None, None)
    x_nan = x.clone()
    x_nan.view(-1)[:: max(1, x.numel() // 5)] = math.nan
    for values in (x, x_nan):
        for reduce in ("max", "min", "sum", "mean"):
            out, arg = assert_same("gather_reduce", values, idx, reduce, exact=reduce in ("max", "min"))
            assert_same("gather_reduce_backward", torch.randn(out.shape, dtype=dtype), idx, arg, reduce, N)
    assert run_both("gather_reduce", x, idx, "median") == (None, None)
    assert run_both("gather_reduce", x, idx + N, "max") == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
def test_svd3x3(dtype):
    A = torch.randn(301, 3, 3, dtype=dtype)
    A[0] = 0
    A[1] = torch.eye(3, dtype=dtype)
    A[2] = torch.outer(torch.randn(3, dtype=dtype), torch.randn(3, dtype=dtype))  # rank 1
    A[3] = torch.diag(torch.tensor([2.0, 2.0, 1.0], dtype=dtype))  # repeated singular values
    U, S, V = assert_same("svd3x3", A)
    grads = [torch.randn(t.shape, dtype=dtype) for t in (U, S, V)]
    assert_same("svd3x3_backward", *grads, U, S, V, scale=10)
    assert_same("svd3x3", torch.empty(0, 3, 3, dtype=dtype))
    assert run_both("svd3x3", torch.randn(2, 3, 4, dtype=dtype)) == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("N,k", [(3, 2), (130, 17), (1000, 30)])
def test_normals(dtype, N, k):
    """Same per-point routine on both devices; a flat patch (repeated singular values), coincident
    points and a viewpoint far off; non-contiguous inputs; bad input raises the same errors."""
    from vrnet_ext.ops.normals import neighbourhood

    points = torch.randn(N, 3, dtype=dtype)
    points[: N // 3, 2] = 0  # a plane
    if N > 10:
        points[N // 3: N // 3 + 2] = points[N // 3 + 2]  # three coincident points
    idx = neighbourhood(points, k)[1]
    for viewpoint in ([0.0, 0.0, 0.0], [1e3, -2e3, 5.0]):
        assert_same("normals", points, idx, viewpoint)
    assert_same("normals", non_contiguous(points), non_contiguous(idx), [0.0, 0.0, 1.0])
    assert_same("normals", torch.empty(0, 3, dtype=dtype), torch.empty(0, 2, dtype=torch.int64), [0.0, 0.0, 0.0])
    assert run_both("normals", points, idx + N, [0.0, 0.0, 0.0]) == (None, None)
    assert run_both("normals", points, idx[:, :1], [0.0, 0.0, 0.0]) == (None, None)
    assert run_both("normals", points, idx, [0.0, 0.0]) == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("N,k,radius", [(3, 2, 10.0), (150, 20, 0.6), (800, 40, 0.3)])
def test_fpfh(dtype, N, k, radius):
    """Same per-point routines on both devices: duplicates (no frame), isolated points (all-zero
    rows), a normal along the joining line; non-contiguous inputs; bad input raises the same errors."""
    from vrnet_ext import ops
    from vrnet_ext.ops.normals import neighbourhood

    points = torch.rand(N, 3, dtype=dtype)
    if N > 10:
        points[1] = points[0]  # a duplicate
        points[2] = 50.0  # isolated
    normals = ops.normals(points)
    dist2, idx = neighbourhood(points, k)
    assert_same("fpfh", points, normals, idx, dist2, radius)
    assert_same("fpfh", non_contiguous(points), non_contiguous(normals), non_contiguous(idx),
                non_contiguous(dist2), radius)
    empty = torch.empty(0, 3, dtype=dtype)
    assert_same("fpfh", empty, empty, torch.empty(0, 2, dtype=torch.int64), torch.empty(0, 2, dtype=dtype), radius)
    assert run_both("fpfh", points, normals, idx, dist2, 0.0) == (None, None)
    assert run_both("fpfh", points, normals[:2], idx, dist2, radius) == (None, None)
    assert run_both("fpfh", points, normals, idx, dist2[:, :1], radius) == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 3), (37, 45), (2, 1000)])
def test_kabsch(dtype, B, N):
    src, tgt = torch.randn(B, N, 3, dtype=dtype), torch.randn(B, N, 3, dtype=dtype)
    weights = torch.rand(B, N, dtype=dtype)
    weights[:, ::4] = 0
    assert_same("kabsch", src, tgt, weights)
    assert_same("kabsch_backward", torch.randn(B, 3, 3, dtype=dtype), torch.randn(B, 3, dtype=dtype), src, tgt,
                weights, scale=10)
    assert_same("kabsch", non_contiguous(src), tgt, weights)


def test_kabsch_huge_weights_scaled_by_their_maximum():
    """Weights near the largest double: their raw sum overflows; scaled by the maximum it does not."""
    src, tgt = torch.randn(2, 37, 3, dtype=torch.float64), torch.randn(2, 37, 3, dtype=torch.float64)
    weights = torch.full((2, 37), 1e307, dtype=torch.float64)
    R, t = assert_same("kabsch", src, tgt, weights)
    assert torch.isfinite(R).all() and torch.isfinite(t).all()
    gR, gt = torch.randn(2, 3, 3, dtype=torch.float64), torch.randn(2, 3, dtype=torch.float64)
    grads = assert_same("kabsch_backward", gR, gt, src, tgt, weights, scale=10)
    assert all(torch.isfinite(g).all() for g in grads)


def test_kabsch_weight_gradient_terms_stay_double():
    """float32 coordinates ~1e37: the weight gradient's per-point terms (coordinates times gradients)
    overflow float32 (the CPU keeps them in double; the CUDA kernel must too)."""
    src = torch.randn(1, 40, 3) * 1e37
    tgt = torch.randn(1, 40, 3) * 1e37
    weights = (torch.rand(1, 40) + 0.1) * 1e6  # the final gradient divides by the total weight: finite
    grads = assert_same("kabsch_backward", torch.randn(1, 3, 3), torch.randn(1, 3) * 100, src, tgt, weights, scale=10)
    assert torch.isfinite(grads[2]).all()


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 6), (9, 45), (2, 300), (1, 1029)])
@pytest.mark.parametrize("kernel", ["cauchy", "geman_mcclure", "welsch"])
def test_robust_kabsch(dtype, B, N, kernel):
    src = torch.randn(B, N, 3, dtype=dtype)
    tgt = src.flip(2) + 0.01 * torch.randn(B, N, 3, dtype=dtype)
    tgt[:, : N // 3] += torch.randn(B, N // 3, 3, dtype=dtype)  # a third far off
    weights = torch.rand(B, N, dtype=dtype) + 0.05
    for iterations, scale in ((0, 3.0), (4, 0.5)):
        assert_same("robust_kabsch", src, tgt, weights, iterations, kernel, scale, 1e-3, scale=10)
    assert_same("robust_kabsch", non_contiguous(src), tgt, weights, 2, kernel, 1.0, 1e-3, scale=10)


def test_robust_kabsch_selects_the_lower_median_of_ties_and_stops_where_weights_vanish():
    src = torch.randn(3, 8, 3, dtype=torch.float64)
    tgt = src.clone()
    tgt[0, :4] += 1.0  # residuals in two tied groups
    tgt[1, :, 0] *= -1
    tgt[2] = 0  # every residual the same
    for scale in (3.0, 0.01):
        R, t = assert_same("robust_kabsch", src, tgt, torch.ones(3, 8, dtype=torch.float64), 6, "welsch", scale, 1e-3,
                           scale=10)
        assert torch.isfinite(R).all() and torch.isfinite(t).all()


def test_kabsch_bad_input_same_errors():
    src = torch.randn(1, 5, 3)
    assert run_both("kabsch", src, src, -torch.ones(1, 5)) == (None, None)
    assert run_both("kabsch", src, src, torch.zeros(1, 5)) == (None, None)
    assert run_both("robust_kabsch", src, src, torch.ones(1, 5), -1, "cauchy", 1.0, 1e-3) == (None, None)
    assert run_both("robust_kabsch", src, src, torch.ones(1, 5), 3, "tukey", 1.0, 1e-3) == (None, None)
    assert run_both("robust_kabsch", src, src, torch.zeros(1, 5), 3, "cauchy", 1.0, 1e-3) == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 2), (3, 37), (2, 300)])
def test_pairwise_distance_loss(dtype, B, N):
    x, y = torch.randn(B, N, 3, dtype=dtype), torch.randn(B, N, 3, dtype=dtype)
    x[0, 1] = x[0, 0]  # a zero distance: its gradient term is 0
    (loss,) = assert_same("pairwise_distance_loss", x, y)
    assert_same("pairwise_distance_loss_backward", torch.randn(B, dtype=dtype), x, y, loss)
    assert_same("pairwise_distance_loss", non_contiguous(x), y)
    assert run_both("pairwise_distance_loss", x, y[:, :1]) == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("running", [False, True])
@pytest.mark.parametrize("B,O,N,k", [(1, 1, 5, 5), (2, 7, 70, 9), (1, 40, 130, 3)])
def test_edge_norm_max(dtype, running, B, O, N, k):
    """Forward and backward against the CPU's fused op: tiles across batches, channels past a
    block's 32, negative BN weights (the min over the neighbours), a NaN in one channel, values far
    from the origin in another."""
    projections = torch.randn(B, 2 * O, N, dtype=dtype) * 2
    projections[:, -1] += 1e4
    if O > 2:
        projections[0, 1, 3] = float("nan")
    idx = torch.randint(0, N, (B, N, k))
    weight = torch.randn(O, dtype=dtype)
    bias = torch.randn(O, dtype=dtype)
    stats = (torch.randn(O, dtype=dtype), torch.rand(O, dtype=dtype) + 0.5) if running else (None, None)
    tol = {key: value * 10 for key, value in tolerances(dtype).items()}  # float64 statistics of `dtype` values
    for args in ((projections, idx, weight, bias), (non_contiguous(projections), idx, None, None)):
        expected, got = run_both("edge_norm_max", *args, *stats, 1e-5, 0.2)
        for a, b in zip(expected, got):
            torch.testing.assert_close(b, a, equal_nan=True, **({} if a.dtype == torch.int32 else tol))
    out, mean, var, arg = expected
    grad = torch.randn(B, O, N, dtype=dtype)
    assert_same("edge_norm_max_backward", grad, projections, idx, arg, weight, bias, mean, var, not running, 1e-5, 0.2,
                scale=100)
    assert run_both("edge_norm_max_backward", grad, projections, idx, arg + k, weight, bias, mean, var, not running,
                    1e-5, 0.2) == (None, None)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("N,voxel_size", [(1, 0.1), (500, 0.05), (3000, 0.3), (200, 1e-7)])
def test_voxel_downsample(dtype, N, voxel_size):
    """Bit for bit the CPU kernel's: packed cell keys, and (edge 1e-7: cells past 2^21) one sort per
    axis; duplicate points, a point on a cell border, an offset far from the origin."""
    points = torch.rand(N, 3, dtype=dtype) * 2 + 1e3
    if N > 10:
        points[5] = points[3]
        points[7, 0] = points[8, 0] + voxel_size
    assert_same("voxel_downsample", points, voxel_size, exact=True)
    assert_same("voxel_downsample", non_contiguous(points), voxel_size, exact=True)


def test_voxel_downsample_bad_input_same_errors():
    points = torch.rand(50, 3, dtype=torch.float64)
    bad = points.clone()
    bad[7, 2] = math.inf
    assert run_both("voxel_downsample", bad, 0.1) == (None, None)
    assert run_both("voxel_downsample", points * 1e10, 1e-300) == (None, None)  # more than 2^62 cells
    assert run_both("voxel_downsample", points, 0.0) == (None, None)
    assert run_both("voxel_downsample", points[:, :2], 0.1) == (None, None)


# soft_match_flash has no CPU kernel: the emulated kernel is checked against the float64 reference.
FLASH_EPS = {3: 2.0 ** -22, 1: 2.0 ** -12}  # score error per unit of scale * max|q| * max|k| (3 passes, TF32)


def flash_errors(query, key, values, scale, passes, target_blocks=0):
    """The emulated flash kernel's largest errors against float64, in units of what its tensor-core
    rounding allows: out, lse (both should be at most 1) and the argmax (equal wherever the float64
    peak leads the runner-up by more than the score tolerance). ``target_blocks``: as the op's (0: the
    keys in one part)."""
    CASES["soft_match_flash"] += 1
    out, lse, argmax = emu_op("soft_match_flash")(query, key, values, scale, passes, target_blocks)
    ref = soft_match_reference(query.double(), key.double(), values.double(), scale)
    span = abs(scale) * query.double().norm(dim=-1).max() * key.double().norm(dim=-1).max()
    score_tol = FLASH_EPS[passes] * (1 + span) + 1e-6 * ref.lse.abs().max()
    value_size = values.double().abs().max() if values.numel() else torch.tensor(0.0, dtype=torch.float64)
    out_err = (out.double() - ref.out).abs().max() / (2 * score_tol * (1 + value_size)) if out.numel() else 0.0
    lse_err = (lse.double() - ref.lse).abs().max() / score_tol
    scores = torch.bmm(query.double(), key.double().mT) * scale
    top2 = scores.topk(min(2, key.shape[1]), dim=-1).values
    clear = (top2[..., 0] - top2[..., -1] > 2 * score_tol) | (key.shape[1] == 1)
    assert clear.any() or key.shape[1] > 1
    return float(out_err), float(lse_err), bool(torch.equal(argmax[clear], ref.argmax[clear]))


@pytest.mark.parametrize("passes", [3, 1])
@pytest.mark.parametrize("B,N,M,C,D", [(1, 1, 1, 1, 1), (2, 70, 45, 33, 35), (1, 130, 100, 64, 64),
                                       (2, 17, 33, 8, 3), (1, 5, 40, 3, 0), (1, 64, 64, 32, 64)])
def test_soft_match_flash(passes, B, N, M, C, D):
    """Tiles with rows and keys past the ends, c and D off the 8-wide fragments, both limits."""
    query, key, values = torch.randn(B, N, C), torch.randn(B, M, C), torch.randn(B, M, D)
    out_err, lse_err, argmax_ok = flash_errors(query, key, values, C ** -0.5, passes)
    assert out_err <= 1 and lse_err <= 1 and argmax_ok


@pytest.mark.parametrize("passes", [3, 1])
@pytest.mark.parametrize("B,N,M,target_blocks", [(1, 70, 600, 64), (2, 5, 2100, 64), (1, 5, 4200, 64),
                                                 (3, 10, 700, 3)])
def test_soft_match_flash_keys_in_parts(passes, B, N, M, target_blocks):
    """Few query rows: the keys split into parts of at least 256 (2, 8 and 15 parts, the last shorter than
    the others; none where the rows already fill target_blocks), then combined."""
    query, key, values = torch.randn(B, N, 24), torch.randn(B, M, 24), torch.randn(B, M, 35)
    out_err, lse_err, argmax_ok = flash_errors(query, key, values, 24 ** -0.5, passes, target_blocks)
    assert out_err <= 1 and lse_err <= 1 and argmax_ok
    unit = torch.nn.functional.normalize(key, dim=-1)
    unit[:, M - 1] = unit[:, 5]  # the peak in the first and the last part: the first wins
    _, _, argmax = emu_op("soft_match_flash")(unit[:, [5, 5]] * 4, unit, values, 1.0, passes, target_blocks)
    assert argmax.eq(5).all()


@pytest.mark.parametrize("passes", [3, 1])
def test_soft_match_flash_sharp_far_and_ties(passes):
    """Features far from the origin with a sharp scale (the row peak dominates; the rescaling of the
    accumulators when the maximum grows tile after tile), keys repeated (the first peak wins),
    non-contiguous inputs and a negative scale."""
    query = torch.randn(2, 40, 16) + 30
    key = torch.randn(2, 90, 16) + 30
    key[:, [6, 10, 70]] = key[:, 3:4]  # copies of a key in its tile and a later one: the first is the peak
    values = torch.randn(2, 90, 7) * 100
    out_err, lse_err, argmax_ok = flash_errors(query, key, values, 0.05, passes)
    assert out_err <= 1 and lse_err <= 1 and argmax_ok
    unit = torch.nn.functional.normalize(key, dim=-1)
    _, _, argmax = emu_op("soft_match_flash")(unit[:, [3, 70, 3]] * 5, unit, values, 1.0, passes, 0)
    assert argmax.eq(3).all()  # the peak, reached at 3, 6, 10 and 70: the first
    out_err, lse_err, argmax_ok = flash_errors(non_contiguous(query), non_contiguous(key), values, -0.2, passes)
    assert out_err <= 1 and lse_err <= 1 and argmax_ok


def flash_gradient_errors(query, key, values, scale, passes):
    """The emulated flash backward's largest gradient errors (query, key, values) against float64, in
    units of what its tensor-core rounding allows (each should be at most 1)."""
    CASES["soft_match_flash_backward"] += 1
    grad_out, grad_lse = torch.randn(*query.shape[:2], values.shape[2]), torch.randn(*query.shape[:2])
    out, lse, _ = emu_op("soft_match_flash")(query, key, values, scale, passes, 0)
    got = emu_op("soft_match_flash_backward")(grad_out, grad_lse, query, key, values, out, lse, scale, passes)
    leaves = [t.double().requires_grad_() for t in (query, key, values)]
    ref = soft_match_reference(*leaves, scale)
    want = torch.autograd.grad((ref.out * grad_out.double()).sum() + (ref.lse * grad_lse.double()).sum(), leaves)
    span = abs(scale) * query.double().norm(dim=-1).max() * key.double().norm(dim=-1).max()
    score_tol = FLASH_EPS[passes] * (1 + span)
    return [float((g.double() - w).abs().max() / (4 * score_tol * (1 + w.abs().max()))) if w.numel() else 0.0
            for g, w in zip(got, want)]


@pytest.mark.parametrize("passes", [3, 1])
@pytest.mark.parametrize("B,N,M,C,D", [(1, 1, 1, 1, 1), (2, 70, 45, 33, 35), (1, 130, 100, 64, 64),
                                       (2, 17, 33, 8, 3), (1, 5, 40, 3, 0), (1, 64, 64, 32, 64)])
def test_soft_match_flash_backward(passes, B, N, M, C, D):
    """dK and dV per block of keys, dQ per block of queries: keys and queries past the ends of their
    tiles, c and D off the 8-wide fragments, both limits, no value channels."""
    query, key, values = torch.randn(B, N, C), torch.randn(B, M, C), torch.randn(B, M, D)
    assert max(flash_gradient_errors(query, key, values, C ** -0.5, passes)) <= 1


@pytest.mark.parametrize("passes", [3, 1])
def test_soft_match_flash_backward_sharp_and_far(passes):
    query, key = torch.randn(2, 40, 16) + 30, torch.randn(2, 90, 16) + 30
    assert max(flash_gradient_errors(query, key, torch.randn(2, 90, 7) * 100, 0.05, passes)) <= 1
    assert max(flash_gradient_errors(non_contiguous(query), non_contiguous(key), torch.randn(2, 90, 7), -0.2,
                                     passes)) <= 1


@pytest.mark.parametrize("with_lse", [True, False])
@pytest.mark.parametrize("create_graph", [False, True])
def test_soft_match_flash_autograd(with_lse, create_graph):
    """The flash path's autograd function on the emulated kernels (registered for this test as the CPU
    kernels of vrnet_ext::soft_match_flash and its backward): outputs and gradients as the
    reference's, with and without a gradient reaching the log-normaliser, and with a graph of the
    backward (torch's products then, so that second derivatives exist)."""
    soft_match_module = importlib.import_module("vrnet_ext.ops.soft_match")
    library = torch.library.Library("vrnet_ext", "IMPL")
    for name in ("soft_match_flash", "soft_match_flash_backward"):
        library.impl(name, emu_op(name), "CPU")
    before = CASES["soft_match_flash_backward"]
    try:
        inputs = [torch.randn(2, 50, 12), torch.randn(2, 70, 12), torch.randn(2, 70, 5)]
        weights = torch.randn(2, 50, 5), torch.randn(2, 50)
        results = []
        for run in (lambda q, k, v: soft_match_module._SoftMatchFlash.apply(q, k, v, 0.3, 3, 0),
                    lambda q, k, v: soft_match_reference(q, k, v, 0.3)):
            leaves = [t.clone().requires_grad_() for t in inputs]
            out, lse, _ = run(*leaves)
            loss = (out * weights[0]).sum() + ((lse * weights[1]).sum() if with_lse else 0)
            grads = torch.autograd.grad(loss, leaves, create_graph=create_graph)
            assert all(g.requires_grad == create_graph for g in grads)
            results.append([out, lse, *grads])
    finally:
        library._destroy()
    for got, expected in zip(*results):
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5)
    assert before == CASES["soft_match_flash_backward"]  # counted by the parity tests only


def test_soft_match_flash_backward_bad_input():
    query, key, values = torch.randn(1, 5, 8), torch.randn(1, 6, 8), torch.randn(1, 6, 3)
    out, lse, _ = emu_op("soft_match_flash")(query, key, values, 1.0, 3, 0)
    grad_out, grad_lse = torch.randn(1, 5, 3), torch.randn(1, 5)
    for args, message in [((grad_out[:, :4], grad_lse, query, key, values, out, lse, 1.0, 3), "grad_out"),
                          ((grad_out, grad_lse, query, key, values, out, lse[:, :4], 1.0, 3), "lse"),
                          ((grad_out, grad_lse, query, key, values, out, lse, 1.0, 0), "passes")]:
        with pytest.raises((ValueError, TypeError), match=message):
            emu_op("soft_match_flash_backward")(*args)


def test_soft_match_flash_bad_input():
    good = torch.randn(1, 5, 8), torch.randn(1, 6, 8), torch.randn(1, 6, 3)
    for args, message in [((*good, 1.0, 2, 0), "passes"),
                          ((torch.randn(1, 5, 65), torch.randn(1, 6, 65), good[2], 1.0, 3, 0), "at most 64"),
                          ((good[0], good[1], torch.randn(1, 6, 65), 1.0, 3, 0), "at most 64"),
                          ((*(t.double() for t in good), 1.0, 3, 0), "float32"),
                          ((good[0], good[1], good[2][:, :5], 1.0, 3, 0), "values"),
                          ((*good, math.inf, 3, 0), "scale")]:
        with pytest.raises((ValueError, TypeError), match=message):
            emu_op("soft_match_flash")(*args)


@pytest.mark.parametrize("K,ratio,seeds,consensus", [(3, 0.0, 5, 2), (64, 0.5, 5, 2), (130, 0.8, 20, 10),
                                                     (300, 0.9, 40, 30), (90, 0.3, 200, 500)])
@pytest.mark.parametrize("tolerance", [0.03, 0.012])  # the graph in float32; in float64 (extent > 128 tolerances)
def test_spatial_consistency(K, ratio, seeds, consensus, tolerance):
    """The graph, the seeds (more asked for than there are correspondences), each seed's neighbours
    (consensus past the degree) and fits as the CPU op's: the same inliers; the refits sum in
    another order, so the transform agrees to rounding."""
    from synthetic import correspondences

    p, q, *_ = correspondences(K, ratio, seed=K)
    expected, got = run_both("spatial_consistency", p, q, tolerance, 0.03, seeds, consensus)
    assert torch.equal(got[1], expected[1])
    torch.testing.assert_close(got[0], expected[0], rtol=1e-12, atol=1e-12)
    assert_same("spatial_consistency", non_contiguous(p), q, tolerance, 0.03, seeds, consensus, scale=1e-3)


def test_spatial_consistency_crowded_seeds():
    """Correspondences crowded within a few tolerances: most candidate seeds lie near a seed of an
    earlier round or of their own round: at tolerance 0.02, 81 seeds out of 600 candidates (every
    round of the seeds kernel), 519 turned down; at 0.015, the 100th seed is the 252nd candidate.
    Fits of 3 correspondences and inlier thresholds near the noise (2.5e-4), so that which seeds are
    fitted shows in the result; below 3 inliers everywhere (3e-5, 1e-5) the best seed's own fit is
    returned, not refitted."""
    from synthetic import correspondences

    p, q, *_ = correspondences(600, 0.5, seed=5)
    for tolerance, threshold in ((0.02, 2e-4), (0.015, 2e-4), (0.02, 6e-5), (0.02, 3e-5), (0.02, 1e-5)):
        expected, got = run_both("spatial_consistency", p * 0.05, q * 0.05, tolerance, threshold, 100, 2)
        assert torch.equal(got[1], expected[1]) and int(got[1].sum()) < 600
        torch.testing.assert_close(got[0], expected[0], rtol=1e-12, atol=1e-12)


def test_spatial_consistency_seeds_after_the_first_round():
    """600 mutually compatible clutter correspondences within one tolerance of each other (one seed
    among them: every later candidate, in every round of the seeds kernel, lies near it), then 10 of
    the true motion: with 2 seeds the second must be a true one, the only fit with 10 inliers."""
    from scipy.spatial.transform import Rotation

    g = torch.Generator().manual_seed(0)
    good = torch.rand(10, 3, generator=g, dtype=torch.float64) * 2
    clutter_p = torch.rand(600, 3, generator=g, dtype=torch.float64) * 0.05 + torch.tensor([3.0, 0, 0]).double()
    clutter_q = torch.rand(600, 3, generator=g, dtype=torch.float64) * 0.05 + torch.tensor([0, 30.0, 0]).double()
    R = torch.tensor(Rotation.from_rotvec([0.3, -1.2, 0.8]).as_matrix())
    p, q = torch.cat([clutter_p, good]), torch.cat([clutter_q, good @ R.T + 0.5])
    expected, got = run_both("spatial_consistency", p, q, 0.1, 0.002, 2, 8)
    assert torch.equal(got[1], expected[1]) and torch.equal(got[1].nonzero().flatten(), torch.arange(600, 610))
    torch.testing.assert_close(got[0][:3, :3], R)


def test_spatial_consistency_degenerate_and_bad_input():
    """No compatible pair (no seed: the identity), identical points, a line, the same errors."""
    p = torch.rand(70, 3, dtype=torch.float64)
    assert_same("spatial_consistency", p, torch.rand(70, 3, dtype=torch.float64), 1e-9, 1e-9, 10, 5, exact=True)
    assert_same("spatial_consistency", p, p + 1.0, 1e-3, 1e-3, 10, 5, scale=1e-3)
    same = torch.ones(10, 3, dtype=torch.float64)
    line = torch.linspace(0, 1, 20, dtype=torch.float64)[:, None] * torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    for points in (same, line):  # rotations about the points fit as well: each must map them onto their targets
        for T, inliers in run_both("spatial_consistency", points, points + 1.0, 0.01, 0.01, 10, 5):
            torch.testing.assert_close(points @ T[:3, :3].T + T[:3, 3], points + 1.0)
            torch.testing.assert_close(T[:3, :3] @ T[:3, :3].T, torch.eye(3, dtype=torch.float64))
            assert bool(inliers.all())
    bad = p.clone()
    bad[3, 1] = math.nan
    assert run_both("spatial_consistency", bad, p, 0.1, 0.1, 10, 5) == (None, None)
    assert run_both("spatial_consistency", p.float(), p, 0.1, 0.1, 10, 5) == (None, None)
    assert run_both("spatial_consistency", p, p, 0.1, 0.1, 0, 5) == (None, None)


# --------------------------------------------------------------------------------------------------

def test_every_kernel_ran():
    """Every __global__ function in csrc/ was launched by the tests above (run the whole file)."""
    kernels = set()
    for path in CSRC.rglob("*.cuh"):
        kernels.update(re.findall(r"__global__\s+void\s+(\w+)", path.read_text()))
    for path in CSRC.rglob("*.cu"):
        kernels.update(re.findall(r"__global__\s+void\s+(\w+)", path.read_text()))
    launched = {line.split()[0] for line in torch.ops.vrnet_ext_emu.emu_stats().splitlines()}
    assert kernels, "no kernels found"
    assert not kernels - launched, f"never launched: {sorted(kernels - launched)}"


def summary() -> str:
    """Per-kernel launches, blocks and threads, and parity cases per op (printed by conftest)."""
    lines = ["kernel launches blocks threads"]
    lines += torch.ops.vrnet_ext_emu.emu_stats().splitlines()
    lines += ["", "op parity-cases"] + [f"{name} {count}" for name, count in sorted(CASES.items())]
    return "\n".join(lines)
