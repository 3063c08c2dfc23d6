"""CUDA kernels against the CPU kernels on the same inputs: outputs, gradients, determinism.

Comparisons against the pure-PyTorch references on CUDA live in each op's own test file (they run
once per device through the ``device`` fixture)."""
import pytest
import torch

from conftest import DTYPES, requires_cuda_kernels, tolerances
from synthetic import lane_crowded_features, rounding_biased_features
from vrnet_ext import ops

pytestmark = requires_cuda_kernels


def run_both(fn, *inputs):
    """fn's outputs and input gradients (backward of a fixed random projection) on CPU and CUDA."""
    results = []
    projection = None
    for device in ("cpu", "cuda"):
        args = [t.detach().to(device).requires_grad_(t.is_floating_point()) for t in inputs]
        outs = fn(*args)
        outs = outs if isinstance(outs, tuple) else (outs,)
        floats = [o for o in outs if o.is_floating_point()]
        if projection is None:
            projection = [torch.randn(o.shape, dtype=o.dtype, device="cpu") for o in floats]
        loss = sum((o * p.to(device)).sum() for o, p in zip(floats, projection))
        grads = torch.autograd.grad(loss, [a for a in args if a.requires_grad])
        results.append(([o.cpu() for o in outs], [g.cpu() for g in grads]))
    return results


def assert_parity(fn, *inputs, exact_outputs=False):
    (cpu_out, cpu_grad), (cuda_out, cuda_grad) = run_both(fn, *inputs)
    tol = tolerances(inputs[0].dtype)
    for a, b in zip(cpu_out, cuda_out):
        if exact_outputs or not a.is_floating_point():
            assert torch.equal(a, b)
        else:
            torch.testing.assert_close(b, a, **tol)
    for a, b in zip(cpu_grad, cuda_grad):
        torch.testing.assert_close(b, a, rtol=tol["rtol"] * 10, atol=tol["atol"] * 10)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N,M,k", [(1, 1, 1, 1), (2, 301, 257, 20), (1, 700, 650, 64), (3, 97, 130, 129),
                                     (2, 9000, 8192, 1), (1, 20000, 50000, 20)])  # the last two: the grid
def test_knn_3d_identical_to_cpu(dtype, B, N, M, k):
    """C = 3 uses exact differences on both devices: same distances and indices, bit for bit."""
    query, ref = torch.randn(B, N, 3, dtype=dtype), torch.randn(B, M, 3, dtype=dtype)
    assert_parity(lambda q, r: ops.knn(q, r, k), query, ref, exact_outputs=True)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("C,B,N,M,k", [(64, 2, 1029, 1100, 20), (5, 1, 37, 53, 53), (512, 3, 100, 300, 16)])
def test_knn_features_match_cpu(dtype, C, B, N, M, k):
    query, ref = torch.randn(B, N, C, dtype=dtype), torch.randn(B, M, C, dtype=dtype)
    cpu = ops.knn(query, ref, k)
    cuda = ops.knn(query.cuda(), ref.cuda(), k)
    torch.testing.assert_close(cuda[0].cpu(), cpu[0], **tolerances(dtype))
    differ = cuda[1].cpu() != cpu[1]
    if differ.any():  # dot products round differently on the GPU: only near-ties may swap
        assert (cpu[0][differ] - cuda[0].cpu()[differ]).abs().max() <= 1e-4 * (1 + cpu[0].abs().max())


@pytest.mark.parametrize("C,B,N,M,k,exclude", [(64, 4, 1024, 1024, 20, False), (128, 2, 768, 768, 20, False),
                                               (4, 1, 500, 3000, 32, True), (100, 3, 77, 129, 1, False)])
def test_knn_tensor_cores_identical_to_cpu(C, B, N, M, k, exclude):
    """float32 feature rows on TF32 tensor cores: candidates, then the exact ranking, proven or rescanned,
    so the CPU's distances and indices bit for bit; also where the proof must fail."""
    generator = torch.Generator().manual_seed(C)
    query = torch.randn(B, N, C, generator=generator)
    ref = query if exclude else torch.randn(B, M, C, generator=generator)
    cases = [(query, ref, k, exclude), (*lane_crowded_features(C, generator), 20, False),
             (*rounding_biased_features(C, generator), 20, False)]
    for q, r, neighbours, self_excluded in cases:
        cpu = ops.knn(q, r, neighbours, exclude_self=self_excluded)
        cuda = ops.knn(q.cuda(), r.cuda(), neighbours, exclude_self=self_excluded)
        assert torch.equal(cuda[0].cpu(), cpu[0]) and torch.equal(cuda[1].cpu(), cpu[1])


def test_knn_exclude_self_and_chunking():
    """Many queries and refs: the feature path runs over several dot-product chunks."""
    points = torch.randn(4, 3000, 8)
    cpu = ops.knn(points, points, 10, exclude_self=True)
    cuda = ops.knn(points.cuda(), points.cuda(), 10, exclude_self=True)
    torch.testing.assert_close(cuda[0].cpu(), cpu[0], **tolerances(torch.float32))
    assert not bool((cuda[1].cpu() == torch.arange(3000).view(1, -1, 1)).any())


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,C,N,k", [(1, 1, 1, 1), (3, 5, 129, 20), (2, 64, 257, 9)])
def test_edge_features_and_gather_reduce(dtype, B, C, N, k):
    x = torch.randn(B, C, N, dtype=dtype)
    idx = torch.randint(0, N, (B, N, k))
    assert_parity(lambda t, i: ops.edge_features(t, i), x, idx, exact_outputs=True)
    for reduce in ("max", "min", "sum", "mean"):
        assert_parity(lambda t, i: ops.gather_reduce(t, i, reduce), x, idx)


@pytest.mark.parametrize("dtype", DTYPES)
def test_svd3x3_and_kabsch(dtype):
    A = torch.randn(1001, 3, 3, dtype=dtype)
    U, S, V = ops.svd3x3(A.cuda())
    torch.testing.assert_close((U @ torch.diag_embed(S) @ V.mT).cpu(), A, **tolerances(dtype))
    torch.testing.assert_close(S.cpu(), ops.svd3x3(A)[1], **tolerances(dtype))
    for B, N in [(1, 3), (257, 37), (2, 5000)]:
        src, tgt = torch.randn(B, N, 3, dtype=dtype), torch.randn(B, N, 3, dtype=dtype)
        weights = torch.rand(B, N, dtype=dtype)
        assert_parity(lambda s, g, w: ops.kabsch(s, g, w), src, tgt, weights)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 6), (64, 768), (3, 5000)])
def test_robust_kabsch_matches_cpu(dtype, B, N):
    src = torch.randn(B, N, 3, dtype=dtype)
    tgt = src.flip(2) + 0.01 * torch.randn(B, N, 3, dtype=dtype)
    tgt[:, : N // 3] += torch.randn(B, N // 3, 3, dtype=dtype)
    weights = torch.rand(B, N, dtype=dtype) + 0.05
    tol = {key: value * 10 for key, value in tolerances(dtype).items()}
    for kernel in ("cauchy", "geman_mcclure", "welsch"):
        cpu = ops.robust_kabsch(src, tgt, weights, 20, kernel)
        cuda = ops.robust_kabsch(src.cuda(), tgt.cuda(), weights.cuda(), 20, kernel)
        for a, b in zip(cpu, cuda):
            torch.testing.assert_close(b.cpu(), a, **tol)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("running", [False, True])
@pytest.mark.parametrize("B,O,N,k", [(1, 1, 5, 5), (28, 64, 1024, 20), (3, 40, 130, 3)])
def test_edge_norm_max_matches_cpu(dtype, running, B, O, N, k):
    projections = torch.randn(B, 2 * O, N, dtype=dtype) * 2
    idx = torch.randint(0, N, (B, N, k))
    weight, bias = torch.randn(O, dtype=dtype), torch.randn(O, dtype=dtype)
    stats = (torch.randn(O, dtype=dtype), torch.rand(O, dtype=dtype) + 0.5) if running else (None, None)

    def op(p, w, b):
        return ops.edge_norm_max(p, idx.to(p.device), w, b, *(None if t is None else t.to(p.device) for t in stats))

    assert_parity(op, projections, weight, bias)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 2), (3, 37), (2, 1029)])
def test_pairwise_distance_loss(dtype, B, N):
    x, y = torch.randn(B, N, 3, dtype=dtype), torch.randn(B, N, 3, dtype=dtype)
    assert_parity(lambda a, b: ops.pairwise_distance_loss(a, b), x, y)


def test_backward_is_deterministic():
    """No atomics in any backward: two runs give bit-identical gradients."""
    x = torch.randn(2, 16, 500, device="cuda", requires_grad=True)
    idx = torch.randint(0, 500, (2, 500, 20), device="cuda")
    points = torch.randn(2, 500, 3, device="cuda", requires_grad=True)
    runs = []
    for _ in range(2):
        loss = (ops.edge_features(x, idx).sin().sum() + ops.gather_reduce(x, idx, "max").sum()
                + ops.knn(points, points, 16)[0].sum() + ops.kabsch(points, points.flip(1))[0].sum()
                + ops.edge_norm_max(x, idx)[0].sin().sum())
        runs.append(torch.autograd.grad(loss, (x, points)))
    for a, b in zip(*runs):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", DTYPES)
def test_normals_match_cpu(dtype):
    """The same double-precision per-point routine on both devices (normals/normals_math.h)."""
    from vrnet_ext.ops.normals import neighbourhood

    points = torch.randn(2000, 3, dtype=dtype)
    idx = neighbourhood(points, 30)[1]
    cpu = torch.ops.vrnet_ext.normals(points, idx, [0.0, 0.0, 0.0])
    cuda = torch.ops.vrnet_ext.normals(points.cuda(), idx.cuda(), [0.0, 0.0, 0.0])
    torch.testing.assert_close(cuda.cpu(), cpu, **tolerances(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_fpfh_match_cpu(dtype):
    """The same per-point routines on both devices (fpfh/fpfh_math.h)."""
    from vrnet_ext.ops.normals import neighbourhood

    points = torch.rand(3000, 3, dtype=dtype)
    normals = ops.normals(points)
    dist2, idx = neighbourhood(points, 40)
    cpu = torch.ops.vrnet_ext.fpfh(points, normals, idx, dist2, 0.1)
    cuda = torch.ops.vrnet_ext.fpfh(points.cuda(), normals.cuda(), idx.cuda(), dist2.cuda(), 0.1)
    rows_equal = ((cuda.cpu() - cpu).abs().amax(1) <= (1e-9 if dtype == torch.float64 else 2e-4)).float().mean()
    assert rows_equal > 0.995, rows_equal  # an angle on a bin edge may round into the next bin


@pytest.mark.parametrize("K,ratio,tolerance", [(3, 0.0, 0.03), (1000, 0.9, 0.03), (5000, 0.95, 0.03), (4000, 0.8, 0.012)])
def test_spatial_consistency_matches_cpu(K, ratio, tolerance):
    """The graph, seeds and seed fits are the CPU kernel's; the refits sum in another order (and nvcc
    fuses the rotation's products): the same inliers, the transform to rounding."""
    from synthetic import correspondences

    with torch.device("cpu"):
        p, q, *_ = correspondences(K, ratio, seed=K)
    T_cpu, mask_cpu = torch.ops.vrnet_ext.spatial_consistency(p, q, tolerance, 0.03, 100, 30)
    T, mask = torch.ops.vrnet_ext.spatial_consistency(p.cuda(), q.cuda(), tolerance, 0.03, 100, 30)
    assert torch.equal(mask.cpu(), mask_cpu)
    torch.testing.assert_close(T.cpu(), T_cpu, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("voxel_size", [0.02, 1e-7])  # packed cell keys; one sort per axis
def test_voxel_downsample_identical_to_cpu(dtype, voxel_size):
    from vrnet_ext.data.procedural import room_scan

    points = torch.as_tensor(room_scan(50_000, 0)).to(dtype)
    cpu = torch.ops.vrnet_ext.voxel_downsample(points, voxel_size)
    assert torch.equal(torch.ops.vrnet_ext.voxel_downsample(points.cuda(), voxel_size).cpu(), cpu)


@pytest.mark.parametrize("precision", ["highest", "high"])
@pytest.mark.parametrize("B,N,M,C,D", [(1, 1, 1, 1, 1), (2, 300, 257, 32, 35), (1, 1000, 4000, 64, 3),
                                       (3, 65, 33, 33, 64)])
def test_soft_match_flash_matches_cpu(precision, B, N, M, C, D):
    """The flash kernel (c, D <= 64) against the CPU kernel: outputs and gradients, its argmax where the
    peak is clear; TF32 (precision "high") within TF32's error. Repeats bit for bit."""
    query, key, values = torch.randn(B, N, C), torch.randn(B, M, C), torch.randn(B, M, D)
    previous = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision(precision)
    try:
        (cpu_out, cpu_grad), (cuda_out, cuda_grad) = run_both(
            lambda q, k, v: tuple(ops.soft_match(q, k, v, return_stats=True)), query, key, values)
        again = ops.soft_match(query.cuda(), key.cuda(), values.cuda(), return_stats=True)
    finally:
        torch.set_float32_matmul_precision(previous)
    loose = 1 if precision == "highest" else 300
    tol = tolerances(torch.float32)
    for a, b in zip(cpu_out[:2], cuda_out[:2]):
        torch.testing.assert_close(b, a, rtol=tol["rtol"] * loose, atol=tol["atol"] * loose)
    for a, b in zip(cpu_grad, cuda_grad):
        torch.testing.assert_close(b, a, rtol=tol["rtol"] * 10 * loose, atol=tol["atol"] * 10 * loose)
    scores = torch.bmm(query.double(), key.double().mT) / C ** 0.5
    top2 = scores.topk(min(2, M), dim=-1).values
    clear = (top2[..., 0] - top2[..., -1] > 1e-3) | (M == 1)
    assert torch.equal(cuda_out[2][clear], cpu_out[2][clear])
    assert all(torch.equal(a.cpu(), b) for a, b in zip(again, cuda_out))
