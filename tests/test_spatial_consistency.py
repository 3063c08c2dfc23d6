"""ops.spatial_consistency: recovery under heavy outlier ratios, the compiled op against the dense
reference (same inliers, same transform), degenerate inputs and named errors, results on the
inputs' device (the CUDA kernel against the CPU kernel: tests/test_cuda_parity.py, and under the
emulator: tests/test_cuda_emulation.py)."""
import math
import os

import pytest
import torch

from conftest import requires_ext, under_each_cpu_dispatch
from synthetic import correspondences
from vrnet_ext import ops
from vrnet_ext.ops.spatial_consistency import spatial_consistency_reference


def rotation_error_deg(A, B):
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(A.T @ B)) - 1) / 2))))


@pytest.mark.parametrize("backend", ["ext", pytest.param("torch")])
@pytest.mark.parametrize("K,ratio", [(400, 0.5), (400, 0.9), (1500, 0.95)])
def test_recovers_the_motion_under_outliers(backend, K, ratio):
    if backend == "torch" and K > 500:
        pytest.skip("the dense reference is slow at this size")
    p, q, R, t, inlier = correspondences(K, ratio)
    T, mask = ops.spatial_consistency(p, q, 0.03, 0.03, backend=backend)
    assert rotation_error_deg(T[:3, :3], R) < 0.5 and float((T[:3, 3] - t).norm()) < 0.01
    assert T.dtype == torch.float64 and T.shape == (4, 4) and torch.equal(T[3], torch.tensor([0.0, 0, 0, 1]).double())
    precision = float((mask & inlier).sum()) / max(1, int(mask.sum()))
    assert precision > 0.95 and int(mask.sum()) >= 0.9 * int(inlier.sum())


@requires_ext
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("K,ratio,seeds,consensus", [(300, 0.8, 100, 30), (64, 0.5, 5, 2), (200, 0.97, 20, 10)])
@pytest.mark.parametrize("tolerance", [0.03, 0.012])  # the graph in float32; in float64 (extent > 128 tolerances)
def test_compiled_op_matches_the_reference(seed, K, ratio, seeds, consensus, tolerance):
    p, q, *_ = correspondences(K, ratio, seed)
    T, mask = ops.spatial_consistency(p, q, tolerance, 0.03, seeds, consensus)
    T_ref, mask_ref = spatial_consistency_reference(p, q, tolerance, 0.03, seeds, consensus)
    assert torch.equal(mask, mask_ref)
    torch.testing.assert_close(T, T_ref, rtol=1e-9, atol=1e-9)


def test_the_float32_graph_decides_as_float64_away_from_the_boundary():
    """The graph is decided in float32 when the points span at most FLOAT_GRAPH_EXTENT tolerances:
    at that extent, far from the origin, a pair may only change sides within 1 % of the tolerance
    of the boundary | |p_i - p_j| - |q_i - q_j| | = tolerance."""
    from vrnet_ext.ops.spatial_consistency import FLOAT_GRAPH_EXTENT, _compatibility

    g = torch.Generator().manual_seed(3)
    tolerance = 0.05
    p = torch.rand(1500, 3, generator=g, dtype=torch.float64) * FLOAT_GRAPH_EXTENT * tolerance + 1e5
    q = p + torch.randn(1500, 3, generator=g, dtype=torch.float64) * tolerance - 3e4
    in_float32 = _compatibility(p, q, tolerance)
    in_float64 = _compatibility(p, q, tolerance / (1 + 1e-12))  # just past the extent: float64
    gap = (torch.cdist(p, p) - torch.cdist(q, q)).abs()
    changed = in_float32 != in_float64
    assert in_float64.sum() > 1000 and in_float32.sum() > 1000
    assert bool(((gap[changed] - tolerance).abs() < 0.01 * tolerance).all())


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_degenerate_inputs(backend):
    p = torch.rand(50, 3, dtype=torch.float64)
    # no consistent structure at all: some answer, a valid rotation, no crash
    T, mask = ops.spatial_consistency(p, torch.rand(50, 3, dtype=torch.float64), 1e-9, 1e-9, backend=backend)
    torch.testing.assert_close(T[:3, :3] @ T[:3, :3].T, torch.eye(3, dtype=torch.float64))
    assert mask.dtype == torch.bool and mask.shape == (50,)
    # identical points everywhere and collinear correspondences
    same = torch.ones(10, 3, dtype=torch.float64)
    T, mask = ops.spatial_consistency(same, same, 0.1, 0.1, backend=backend)
    assert torch.isfinite(T).all()
    line = torch.linspace(0, 1, 20, dtype=torch.float64)[:, None] * torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    T, mask = ops.spatial_consistency(line, line + 1.0, 0.01, 0.01, backend=backend)
    assert bool(mask.all()) and torch.allclose(line @ T[:3, :3].T + T[:3, 3], line + 1.0, atol=1e-9)
    # float32 input, three correspondences
    tri = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    T, mask = ops.spatial_consistency(tri, tri + 2.0, 0.01, 0.01, backend=backend)
    assert bool(mask.all()) and torch.allclose(T[:3, 3], torch.full((3,), 2.0, dtype=torch.float64), atol=1e-9)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_errors_name_the_argument(backend):
    p = torch.rand(10, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="src must have shape"):
        ops.spatial_consistency(p[:, :2], p[:, :2], 0.1, 0.1, backend=backend)
    with pytest.raises(ValueError, match="tgt must have the shape of src"):
        ops.spatial_consistency(p, p[:5], 0.1, 0.1, backend=backend)
    with pytest.raises(ValueError, match="src must hold 3 to"):
        ops.spatial_consistency(p[:2], p[:2], 0.1, 0.1, backend=backend)
    for bad in (0.0, -1.0, math.nan, math.inf, True):
        with pytest.raises(ValueError, match="tolerance must be a positive number"):
            ops.spatial_consistency(p, p, bad, 0.1, backend=backend)
        with pytest.raises(ValueError, match="inlier_threshold must be a positive number"):
            ops.spatial_consistency(p, p, 0.1, bad, backend=backend)
    with pytest.raises(ValueError, match="seeds must be an integer >= 1"):
        ops.spatial_consistency(p, p, 0.1, 0.1, seeds=0, backend=backend)
    with pytest.raises(ValueError, match="consensus must be an integer >= 2"):
        ops.spatial_consistency(p, p, 0.1, 0.1, consensus=1, backend=backend)
    bad = p.clone()
    bad[3, 1] = math.nan
    with pytest.raises(ValueError, match="src contains NaN or Inf"):
        ops.spatial_consistency(bad, p, 0.1, 0.1, backend=backend)
    with pytest.raises(TypeError, match="src must be a floating tensor"):
        ops.spatial_consistency(p.long(), p, 0.1, 0.1, backend=backend)


@requires_ext
def test_raw_op_checks_its_arguments():
    p = torch.rand(10, 3, dtype=torch.float64)
    with pytest.raises(TypeError, match="src must be float64"):
        torch.ops.vrnet_ext.spatial_consistency(p.float(), p, 0.1, 0.1, 10, 5)
    with pytest.raises(ValueError, match="at most 32768"):
        torch.ops.vrnet_ext.spatial_consistency(torch.zeros(40000, 3, dtype=torch.float64),
                                                torch.zeros(40000, 3, dtype=torch.float64), 0.1, 0.1, 10, 5)
    torch.library.opcheck(torch.ops.vrnet_ext.spatial_consistency.default, (p, p + 1.0, 0.1, 0.1, 10, 5),
                          test_utils=("test_schema", "test_faketensor"))


@requires_ext
def test_the_vector_and_the_portable_graph_give_the_same_fit(tmp_path):
    """Where the CPU has AVX-512 the graph is built by vector code; VRNET_CPU_DISPATCH=generic keeps
    the portable loop. Same transform, same inliers (K = 2,000 and 1,003: full words and a tail;
    the graph in float32 and, at tolerance 0.012, in float64)."""
    script = ("import sys, torch; sys.path.insert(0, sys.argv[2]); from synthetic import correspondences; "
              "from vrnet_ext import ops; out = [ops.spatial_consistency(*correspondences(K, 0.9, seed=K)[:2], tolerance, "
              "0.03) for K in (2000, 1003) for tolerance in (0.03, 0.012)]; torch.save(out, sys.argv[1])")
    results = under_each_cpu_dispatch(script, tmp_path, os.path.dirname(__file__))
    for (T_vector, mask_vector), (T_generic, mask_generic) in zip(*results):
        assert torch.equal(T_vector, T_generic) and torch.equal(mask_vector, mask_generic)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_copies_of_one_wrong_correspondence_do_not_capture_the_fit(backend):
    """About 40 correspondences of the true motion among 60 outliers, and 300 copies of one outlier:
    the copies count once, so the fit is the true motion and the same as without them; every copy
    gets its original's flag."""
    p, q, R, _, inlier = correspondences(100, 0.6, seed=4)
    wrong = int((~inlier).nonzero()[0])
    p_copies = torch.cat([p, p[wrong].expand(300, 3)])
    q_copies = torch.cat([q, q[wrong].expand(300, 3)])
    T, inliers = ops.spatial_consistency(p_copies, q_copies, 0.05, 0.05, backend=backend)
    assert rotation_error_deg(T[:3, :3], R) < 2.0, rotation_error_deg(T[:3, :3], R)
    assert bool((inliers[100:] == inliers[wrong]).all()) and len(inliers) == 400
    distinct = ops.spatial_consistency(p, q, 0.05, 0.05, backend=backend)
    torch.testing.assert_close(T, distinct[0], rtol=0, atol=0)
    torch.testing.assert_close(inliers[:100], distinct[1])
    copies, none = ops.spatial_consistency(p[:1].expand(5, 3), q[:1].expand(5, 3), 0.05, 0.05, backend=backend)
    assert torch.equal(copies, torch.eye(4, dtype=torch.float64)) and not none.any()


def test_results_stay_on_the_inputs_device(device):
    """On the CPU and (with a GPU) on CUDA: the transform and the mask on the inputs' device, the CPU
    kernel's inliers; copies of correspondences counted once there too."""
    with torch.device("cpu"):
        p, q, R, _, inlier = correspondences(400, 0.8)
    T, mask = ops.spatial_consistency(p.to(device), q.to(device), 0.03, 0.03)
    assert T.device.type == device.type and mask.device.type == device.type
    T_cpu, mask_cpu = ops.spatial_consistency(p, q, 0.03, 0.03)
    assert torch.equal(mask.cpu(), mask_cpu) and rotation_error_deg(T.cpu()[:3, :3], R) < 0.5
    torch.testing.assert_close(T.cpu(), T_cpu, rtol=1e-9, atol=1e-9)
    copies = torch.cat([torch.arange(400), torch.zeros(50, dtype=torch.long)])
    T_copies, mask_copies = ops.spatial_consistency(p[copies].to(device), q[copies].to(device), 0.03, 0.03)
    assert torch.equal(mask_copies.cpu(), mask_cpu[copies])
    torch.testing.assert_close(T_copies.cpu(), T_cpu, rtol=1e-9, atol=1e-9)
