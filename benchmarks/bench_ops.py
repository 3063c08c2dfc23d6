"""Speed and peak memory of every vrnet_ext op against its pure-PyTorch reference.

    python benchmarks/bench_ops.py [--quick] [--json PATH] [--threads 2] [--only knn,kabsch] [--device cuda]

Times are medians of repeated forward(+backward) calls after a warm-up, both implementations
timed in this process (on CUDA with CUDA events around each call). On CPU, peak memory is the
extra resident memory (VmHWM above the RSS once the inputs exist) of one call, measured in a fresh
subprocess per case and implementation, so that allocator caches of earlier cases do not hide it;
on CUDA it is the peak of the caching allocator above the inputs (torch.cuda.max_memory_allocated).
The CUDA cases are the sizes of the GPU floors (issue 4). Prints a table of ratios and writes JSON
records ``{"op", "case", "impl", "median_s", "peak_mb"}``. Optional tools found installed
(roma, torch_cluster, pykdtree, small_gicp, open3d) are added as extra implementations.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from vrnet_ext import ops
from vrnet_ext.nn import EdgeConv
from vrnet_ext.ops.kabsch import reweighting_steps
from outputs import cpu_description  # benchmarks/, the script's folder


@dataclass
class Case:
    op: str
    name: str
    make_inputs: Callable[[], tuple]
    impls: dict[str, Callable[..., object]]
    quick: bool = True          # part of --quick
    skip: dict[str, str] | None = None  # impl -> reason it is not run


def _fwd_bwd(fn):
    """Runs fn(*inputs) and backpropagates the sum of its (first) float output."""
    def run(*inputs):
        out = fn(*inputs)
        out = out[0] if isinstance(out, tuple) else out
        out.sum().backward()
    return run


def _grad(*tensors):
    return tuple(t.requires_grad_() if t.is_floating_point() else t for t in tensors)


def _clouds(B, N, C, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, N, C, generator=g)


def _torch_cluster_knn(k):
    import torch_cluster

    def run(x):
        B, N, C = x.shape
        batch = torch.arange(B, device=x.device).repeat_interleave(N)
        return torch_cluster.knn(x.reshape(-1, C), x.reshape(-1, C), k, batch, batch)
    return run


def _knn_case(B, N, C, k, quick=True, skip_torch=None):
    def make():
        return (_clouds(B, N, C),)
    impls = {b: (lambda x, b=b: ops.knn(x, x, k, backend=b)) for b in ("ext", "torch")}
    if C > 3:  # the plain composite (ties in any order; distances by the matrix-product form on a GPU)
        impls["cdist + topk"] = lambda x: torch.cdist(x, x).topk(k, dim=-1, largest=False)
    if importlib.util.find_spec("torch_cluster"):
        impls["torch_cluster"] = _torch_cluster_knn(k)
    skip = {name: skip_torch for name in ("torch", "cdist + topk")} if skip_torch else None
    return Case("knn", f"C={C} B={B} N=M={N} k={k}", make, impls, quick, skip)


def _edge_conv_case(B, C, O, N, k):
    def make():
        layer = EdgeConv(C, O).train()
        x = _clouds(B, C, N).requires_grad_()
        idx = ops.knn(x.detach().mT, x.detach().mT, k)[1]
        return layer, x, idx
    impls = {b: _fwd_bwd(lambda layer, x, idx, b=b: layer(x, idx, backend=b)) for b in ("ext", "torch")}
    return Case("EdgeConv", f"{C}->{O} train fwd+bwd B={B} N={N} k={k}", make, impls)


def _edge_norm_max_case(B, O, N, k):
    def make():
        projections = _clouds(B, 2 * O, N).requires_grad_()
        idx = torch.randint(0, N, (B, N, k), generator=torch.Generator().manual_seed(1))
        return projections, idx, torch.ones(O, requires_grad=True), torch.zeros(O, requires_grad=True)
    impls = {b: _fwd_bwd(lambda p, i, w, bias, b=b: ops.edge_norm_max(p, i, w, bias, backend=b)) for b in ("ext", "torch")}
    return Case("edge_norm_max", f"batch stats fwd+bwd B={B} O={O} N={N} k={k}", make, impls)


def _graph_case(op, fn, B, C, N, k):
    def make():
        x = _clouds(B, C, N).requires_grad_()
        return x, torch.randint(0, N, (B, N, k), generator=torch.Generator().manual_seed(1))
    impls = {b: _fwd_bwd(lambda x, idx, b=b: fn(x, idx, b)) for b in ("ext", "torch")}
    return Case(op, f"fwd+bwd B={B} C={C} N={N} k={k}", make, impls)


def _roma_procrustes(src, tgt):
    import roma

    w = torch.full(src.shape[:2], 1.0 / src.shape[1], dtype=src.dtype, device=src.device)
    src_c, tgt_c = (w.unsqueeze(-1) * src).sum(1), (w.unsqueeze(-1) * tgt).sum(1)
    H = ((src - src_c.unsqueeze(1)) * w.unsqueeze(-1)).mT @ (tgt - tgt_c.unsqueeze(1))
    R = roma.special_procrustes(H.mT)
    return R, tgt_c - (R @ src_c.unsqueeze(-1)).squeeze(-1)


def _kabsch_case(B, N):
    def make():
        src = _clouds(B, N, 3)
        return _grad(src, src + 0.1 * _clouds(B, N, 3, seed=1))
    impls = {b: _fwd_bwd(lambda s, t, b=b: ops.kabsch(s, t, backend=b)) for b in ("ext", "torch")}
    if importlib.util.find_spec("roma"):
        impls["roma"] = _fwd_bwd(_roma_procrustes)
    return Case("kabsch", f"fwd+bwd B={B} N={N}", make, impls)


def _robust_kabsch_case(B, N, iterations=20):
    """VRNet's serving solve: 20 Geman-McClure steps at 0.15 medians, a third of the targets off."""
    def make():
        src = _clouds(B, N, 3)
        tgt = src + 0.01 * _clouds(B, N, 3, seed=1)
        tgt[:, : N // 3] += _clouds(B, N // 3, 3, seed=2)
        return src, tgt, torch.rand(B, N, generator=torch.Generator().manual_seed(3)) + 0.05

    def solve(backend, per_step=False):
        def run(s, t, w):
            with torch.no_grad():
                if per_step:  # the same steps as tensor ops around the compiled kabsch
                    return reweighting_steps(s, t, w, iterations, "geman_mcclure", 0.15, 1e-3, "ext")
                return ops.robust_kabsch(s, t, w, iterations, "geman_mcclure", 0.15, backend=backend)
        return run

    impls = {"ext": solve("ext"), "torch": solve("torch"), "ext kabsch per step": solve("ext", per_step=True)}
    return Case("robust_kabsch", f"fwd {iterations} steps B={B} N={N}", make, impls)


def _svd_case(B):
    def make():
        return _grad(_clouds(B, 3, 3))
    impls = {b: _fwd_bwd(lambda A, b=b: ops.svd3x3(A, backend=b)[1]) for b in ("ext", "torch")}
    return Case("svd3x3", f"fwd+bwd (S) B={B}", make, impls)


def _pdl_case(N, quick=True, skip_torch=None, B=1):
    def make():
        x = _clouds(B, N, 3)
        return _grad(x, 1.1 * x + 0.01 * _clouds(B, N, 3, seed=1))
    impls = {b: _fwd_bwd(lambda x, y, b=b: ops.pairwise_distance_loss(x, y, backend=b)) for b in ("ext", "torch")}
    skip = {"torch": skip_torch} if skip_torch else None
    return Case("pairwise_distance_loss", f"fwd+bwd B={B} N={N}", make, impls, quick, skip)


def _scan_points(voxel: float) -> torch.Tensor:
    """A room-sized synthetic scan (vrnet_ext.data.procedural.room_scan, 300k points) voxel-downsampled."""
    from vrnet_ext.data.procedural import room_scan
    from vrnet_ext.geometry.preprocessing import voxel_downsample

    return torch.as_tensor(voxel_downsample(room_scan(300_000, 0), voxel))


def _scan_knn_case(k=20, points=300_000, stray=False):
    """3-D kNN of every point of a scan among the others: the ICP / normals workload (with
    ``stray``: one more point 100 km away, which must not change the time much). Columns: pykdtree
    and small_gicp (both kd-trees, build included, this process's thread count)."""
    def make():
        from vrnet_ext.data.procedural import room_scan

        cloud = torch.as_tensor(room_scan(points, 0))
        if stray:
            cloud = torch.cat([cloud, torch.tensor([[1e5, 0.0, 0.0]], dtype=cloud.dtype)])
        return (cloud,)
    impls = {"ext": lambda x: ops.knn(x[None], x[None], k)}
    if importlib.util.find_spec("pykdtree"):
        def pykdtree_knn(x):
            from pykdtree.kdtree import KDTree

            points = x.cpu().numpy()
            return KDTree(points).query(points, k=k)
        impls["pykdtree"] = pykdtree_knn
    if importlib.util.find_spec("small_gicp"):
        def small_gicp_knn(x):
            import small_gicp

            points = x.cpu().numpy()
            threads = torch.get_num_threads()
            return small_gicp.KdTree(points, threads).batch_knn_search(points, k, threads)
        impls["small_gicp"] = small_gicp_knn
    skip = {"torch": f"the reference needs a {points // 1000}k x {points // 1000}k matrix"}
    impls["torch"] = lambda x: None
    far = " + 1 point 100 km away" if stray else ""
    return Case("knn", f"scan C=3 N=M={points // 1000}k k={k}{far}", make, impls, True, skip)


def _open3d_cloud(points: torch.Tensor):
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.cpu().numpy()))


def _normals_case(voxel=0.05):
    """Columns: Open3D's estimate_normals (30 neighbours within 2 voxels, its tutorial's setting)."""
    def make():
        return (_scan_points(voxel),)
    impls = {b: (lambda x, b=b: ops.normals(x, 30, backend=b)) for b in ("ext", "torch")}
    if importlib.util.find_spec("open3d"):
        import open3d as o3d

        impls["open3d"] = lambda x: _open3d_cloud(x).estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    return Case("normals", f"room scan at {voxel} m voxels, k=30", make, impls)


def _fpfh_case(voxel=0.05):
    """Columns: Open3D's compute_fpfh_feature (radius 5 voxels, at most 100 neighbours, as ours)."""
    def make():
        points = _scan_points(voxel)
        return points, ops.normals(points)
    impls = {b: (lambda x, n, b=b: ops.fpfh(x, n, 5 * voxel, backend=b)) for b in ("ext", "torch")}
    if importlib.util.find_spec("open3d"):
        import open3d as o3d

        def open3d_fpfh(x, n):
            cloud = _open3d_cloud(x)
            cloud.normals = o3d.utility.Vector3dVector(n.cpu().numpy())
            return o3d.pipelines.registration.compute_fpfh_feature(
                cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        impls["open3d"] = open3d_fpfh
    return Case("fpfh", f"room scan at {voxel} m voxels, r=5 voxels", make, impls)


def _voxel_downsample_case(voxel):
    """A 300k-point room scan. Columns: Open3D's voxel_down_sample (cloud construction included,
    as a user holding an array pays it) and a numpy np.unique + bincount version."""
    def make():
        from vrnet_ext.data.procedural import room_scan

        return (torch.as_tensor(room_scan(300_000, 0)),)
    impls = {b: (lambda x, b=b: ops.voxel_downsample(x, voxel, backend=b)) for b in ("ext", "torch")}

    def numpy_unique(x):
        points = x.cpu().numpy()
        cells = np.floor((points - points.min(0)) / voxel).astype(np.int64)
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        return np.stack([np.bincount(inverse, points[:, a], len(counts)) for a in range(3)], 1) / counts[:, None]
    impls["numpy"] = numpy_unique
    if importlib.util.find_spec("open3d"):
        impls["open3d"] = lambda x: _open3d_cloud(x).voxel_down_sample(voxel)
    return Case("voxel_downsample", f"scan N=300k voxel={voxel}", make, impls)


def _spatial_consistency_case(K, outlier_ratio=0.9, quick=True, skip_torch=None, host_column=False):
    """K putative correspondences, ``outlier_ratio`` of them random. Columns: our RANSAC on the same
    correspondences (registration.ransac, 50k hypotheses at most, 0.999 confidence) and Open3D's
    registration_ransac_based_on_correspondence (the best existing tool installed here); with
    ``host_column`` (GPU inputs) the CPU kernel too, the copies to and from the host included (what a
    registration on the GPU ran before the op had a CUDA kernel)."""
    tolerance = 0.03

    def make():
        g = torch.Generator().manual_seed(0)
        p = torch.rand(K, 3, generator=g, dtype=torch.float64) * 2
        angle = torch.tensor(1.2, dtype=torch.float64)
        R = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
        R[:2, :2] = torch.stack([torch.stack([angle.cos(), -angle.sin()]), torch.stack([angle.sin(), angle.cos()])])
        q = p @ R.T + torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
        outlier = torch.rand(K, generator=g) < outlier_ratio
        q[outlier] = torch.rand(int(outlier.sum()), 3, generator=g, dtype=torch.float64) * 2
        return p, q

    impls = {b: (lambda p, q, b=b: ops.spatial_consistency(p, q, tolerance, tolerance, backend=b))
             for b in ("ext", "torch")}
    if host_column:
        def on_host(p, q):
            T, inliers = ops.spatial_consistency(p.cpu(), q.cpu(), tolerance, tolerance)
            return T.to(p.device), inliers.to(p.device)
        impls["ext, CPU kernel"] = on_host

    def ours_ransac(p, q):
        from vrnet_ext.registration.ransac import ransac

        pairs = torch.arange(p.shape[0], device=p.device).unsqueeze(1).expand(-1, 2)
        return ransac(p, q, pairs, tolerance)

    impls["ransac (ours)"] = ours_ransac
    if importlib.util.find_spec("open3d"):
        import open3d as o3d

        def open3d_ransac(p, q):
            reg = o3d.pipelines.registration
            pairs = o3d.utility.Vector2iVector(np.stack([np.arange(p.shape[0])] * 2, 1))
            return reg.registration_ransac_based_on_correspondence(
                _open3d_cloud(p), _open3d_cloud(q), pairs, tolerance, reg.TransformationEstimationPointToPoint(False),
                3, [], reg.RANSACConvergenceCriteria(100000, 0.999))
        impls["open3d ransac"] = open3d_ransac
    skip = {"torch": skip_torch} if skip_torch else None
    return Case("spatial_consistency", f"K={K} outliers={outlier_ratio:.0%}", make, impls, quick, skip)


def _tf32_matmuls(fn):
    """fn run with torch's float32 matmul precision "high" (TF32 allowed), the setting restored after."""
    def run(*inputs):
        previous = torch.get_float32_matmul_precision()
        torch.set_float32_matmul_precision("high")
        try:
            return fn(*inputs)
        finally:
            torch.set_float32_matmul_precision(previous)
    return run


def _soft_match_case(B, N, c, D, backward=True, quick=True, skip_torch=None, sharpness=1.0, gpu_columns=False):
    """The best existing tool is torch's scaled_dot_product_attention (a flash-attention kernel on
    CPU and GPU): the same product, without the log-normaliser VRNet's matching statistics need
    (``sdpa + lse``: with it, by products on blocks of query rows). ``sharpness`` multiplies the
    queries: at 60 most scores lie over 87 below their row's maximum (exponentials under float32's
    normal range), as in a trained model's sharp matching. ``gpu_columns``: also the dense blocks
    the GPU runs past the flash kernel's sizes, and ext / sdpa with TF32 allowed."""
    from vrnet_ext.ops.soft_match import dense_in_query_blocks, query_block

    def make():
        tensors = (_clouds(B, N, c) * sharpness, _clouds(B, N, c, seed=1), _clouds(B, N, D, seed=2))
        return _grad(*tensors) if backward else tensors

    def sdpa(q, k, v):
        return torch.nn.functional.scaled_dot_product_attention(q, k, v)

    def sdpa_and_lse(q, k, v):
        block = query_block(q.shape[0], k.shape[1])
        lse = torch.cat([torch.logsumexp(torch.bmm(q[:, i:i + block], k.mT) * c ** -0.5, dim=-1)
                         for i in range(0, q.shape[1], block)], dim=1)
        return sdpa(q, k, v), lse

    impls = {b: (lambda q, k, v, b=b: ops.soft_match(q, k, v, backend=b)) for b in ("ext", "torch")}
    impls["sdpa"] = sdpa
    if gpu_columns:
        impls["ext, dense blocks"] = lambda q, k, v: dense_in_query_blocks(q, k, v, c ** -0.5).out
        impls["ext, TF32"] = _tf32_matmuls(impls["ext"])
        impls["sdpa + lse"] = sdpa_and_lse
        impls["sdpa, TF32"] = _tf32_matmuls(sdpa)
    if backward:
        impls = {name: _fwd_bwd(fn) for name, fn in impls.items()}
    skip = {"torch": skip_torch} if skip_torch else None
    kind = ("fwd+bwd" if backward else "fwd") + ("" if sharpness == 1.0 else f" sharp x{sharpness:g}")
    return Case("soft_match", f"{kind} B={B} N=M={N} c={c} D={D}", make, impls, quick, skip)


def _attention_case(B, H, N, D, quick=True):
    """Inference on bfloat16 heads (the Transformer's attention). The reference is torch's
    scaled_dot_product_attention, a fused flash-attention kernel and the best existing tool."""
    def make():
        g = torch.Generator().manual_seed(0)
        return tuple((torch.randn(B, H, N, D, generator=g) * 2).bfloat16() for _ in range(3))

    impls = {b: (lambda q, k, v, b=b: ops.attention(q, k, v, backend=b)) for b in ("ext", "torch")}
    return Case("attention", f"fwd bf16 B={B} H={H} N=M={N} D={D}", make, impls, quick)


def cuda_cases() -> list[Case]:
    return [
        _knn_case(8, 16384, 3, 20),
        _knn_case(1, 100000, 3, 20, skip_torch="the reference needs ~80 GB (two 100k x 100k matrices)"),
        _knn_case(1, 50000, 3, 1),  # an ICP iteration's correspondences
        _knn_case(28, 1024, 64, 20),  # the DGCNN's feature graphs in a training step
        _knn_case(28, 1024, 128, 20),
        _knn_case(8, 4096, 64, 20),
        _knn_case(1, 100000, 64, 20, skip_torch="a 100k x 100k matrix needs 40 GB"),
        _graph_case("edge_features", lambda x, i, b: ops.edge_features(x, i, backend=b), 28, 64, 1024, 20),
        _graph_case("gather_reduce", lambda x, i, b: ops.gather_reduce(x, i, "max", backend=b), 28, 64, 1024, 20),
        _edge_conv_case(28, 64, 64, 1024, 20),
        _svd_case(1 << 20),
        _kabsch_case(1 << 20, 16),
        _robust_kabsch_case(64, 768),
        _pdl_case(4096),
        _pdl_case(65536, skip_torch="the reference needs ~70 GB of N x N matrices"),
        _soft_match_case(28, 768, 512, 515, gpu_columns=True),
        _soft_match_case(1, 5000, 32, 35, backward=False, gpu_columns=True),  # the scene model's matching
        _soft_match_case(1, 16384, 32, 35, gpu_columns=True),  # four blocks of query rows: the recomputing backward
        _soft_match_case(1, 50000, 32, 35, backward=False, skip_torch="the reference needs ~20 GB (50k x 50k)",
                         gpu_columns=True),
        _soft_match_case(1, 100000, 32, 35, backward=False, skip_torch="the reference needs ~80 GB (100k x 100k)",
                         gpu_columns=True),
        _voxel_downsample_case(0.02),
        _spatial_consistency_case(1000, host_column=True),
        _spatial_consistency_case(5000, 0.95, skip_torch="the dense reference takes ~20 s per call", host_column=True),
    ]


def all_cases(device: str = "cpu") -> list[Case]:
    if device != "cpu":
        return cuda_cases()
    return [
        _knn_case(1, 16384, 3, 20),
        _knn_case(1, 50000, 3, 20, skip_torch="the reference needs ~20 GB (two 50k x 50k matrices)"),
        _knn_case(8, 1024, 64, 20),
        _knn_case(8, 4096, 64, 20, quick=False),
        _knn_case(2, 768, 32, 10),  # a DGCNN feature graph at inference: two clouds of one GEMM tile
        _graph_case("edge_features", lambda x, i, b: ops.edge_features(x, i, backend=b), 8, 64, 1024, 20),
        _graph_case("gather_reduce", lambda x, i, b: ops.gather_reduce(x, i, "max", backend=b), 8, 64, 1024, 20),
        _edge_norm_max_case(8, 64, 1024, 20),
        _edge_conv_case(8, 64, 64, 1024, 20),
        _svd_case(65536),
        _kabsch_case(65536, 16),
        _robust_kabsch_case(1, 768),  # one pair's serving solve
        _robust_kabsch_case(16, 768),
        _pdl_case(768, B=16),  # L2 on a training batch of ModelNet40 pairs
        _pdl_case(4096),
        _pdl_case(16384, quick=False, skip_torch="the reference needs ~7 GB of N x N matrices"),
        _scan_knn_case(),
        _scan_knn_case(1, 200_000),
        _scan_knn_case(1, 200_000, stray=True),
        _normals_case(),
        _fpfh_case(),
        _voxel_downsample_case(0.02),
        _voxel_downsample_case(0.1),
        _spatial_consistency_case(1000),
        _spatial_consistency_case(5000, 0.95, quick=False, skip_torch="the dense reference takes ~20 s per call"),
        _soft_match_case(16, 768, 128, 131),
        _soft_match_case(16, 768, 128, 131, sharpness=60.0),
        _soft_match_case(1, 8192, 32, 35, backward=False),
        _soft_match_case(1, 50000, 32, 35, backward=False, quick=False,
                         skip_torch="the reference needs ~20 GB (two 50k x 50k matrices)"),
        _attention_case(2, 4, 768, 32),  # one pair's Transformer attention (both clouds as one batch)
        _attention_case(32, 4, 768, 32, quick=False),  # 16 pairs
    ]


def to_device(inputs: tuple, device: str) -> tuple:
    """The case's inputs on ``device`` as leaves (requires_grad kept), modules moved."""
    moved = []
    for item in inputs:
        if isinstance(item, torch.Tensor):
            item = item.detach().to(device).requires_grad_(item.requires_grad)
        elif isinstance(item, torch.nn.Module):
            item = item.to(device)
        moved.append(item)
    return tuple(moved)


def _time(fn, inputs, repeats: int, device: str) -> float:
    fn(*inputs)  # warm-up
    times = []
    for _ in range(repeats):
        if device == "cpu":
            start = time.perf_counter()
            fn(*inputs)
            times.append(time.perf_counter() - start)
        else:
            begin, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            begin.record()
            fn(*inputs)
            end.record()
            end.synchronize()
            times.append(begin.elapsed_time(end) / 1000.0)
    return statistics.median(times)


def _time_threads(fn, inputs, repeats: int, thread_counts: tuple[int, ...]) -> dict[int, float]:
    """CPU medians of fn(*inputs) at each intra-op thread count, the counts taking turns call by
    call (so a change in the machine's load between calls hits every count alike)."""
    times: dict[int, list[float]] = {n: [] for n in thread_counts}
    for n in thread_counts:  # warm-up at each count
        torch.set_num_threads(n)
        fn(*inputs)
    for _ in range(repeats):
        for n in thread_counts:
            torch.set_num_threads(n)
            start = time.perf_counter()
            fn(*inputs)
            times[n].append(time.perf_counter() - start)
    torch.set_num_threads(thread_counts[0])
    return {n: statistics.median(t) for n, t in times.items()}


def cuda_peak_mb(fn, inputs) -> float:
    """Peak CUDA memory of one call above what is allocated before it."""
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    baseline = torch.cuda.memory_allocated()
    fn(*inputs)
    torch.cuda.synchronize()
    return max(0.0, (torch.cuda.max_memory_allocated() - baseline) / 2**20)


def _rss_mb(field: str) -> float:
    status = open("/proc/self/status").read()
    return int(re.search(rf"{field}:\s+(\d+)", status).group(1)) / 1024.0


def measure_peak_mb(case: Case, impl: str) -> float:
    """Extra peak resident memory of one call (run in a fresh process: see main)."""
    inputs = case.make_inputs()
    baseline = _rss_mb("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:  # reset VmHWM to the current RSS
        f.write("5")
    case.impls[impl](*inputs)
    return max(0.0, _rss_mb("VmHWM") - baseline)


def _peak_in_subprocess(op: str, name: str, impl: str, threads: int) -> float | None:
    cmd = [sys.executable, __file__, "--measure-memory", op, name, impl, "--threads", str(threads)]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        print(f"  memory run failed for {op} [{name}] {impl}: {result.stderr.strip()[-300:]}", file=sys.stderr)
        return None
    return float(result.stdout.strip().splitlines()[-1])


def _format_table(records: list[dict]) -> str:
    rows = {}
    for r in records:
        rows.setdefault((r["op"], r["case"]), {})[r["impl"]] = r
    header = f"{'op':<24} {'case':<34} {'ext s':>9} {'torch s':>9} {'speedup':>8} {'ext MB':>8} {'torch MB':>9} {'mem ratio':>9}  other"
    lines = [header, "-" * len(header)]
    for (op, case), impls in rows.items():
        ext, ref = impls.get("ext", {}), impls.get("torch", {})
        def fmt(v, spec):
            return format(v, spec) if isinstance(v, (int, float)) else "-"
        speed = ref["median_s"] / ext["median_s"] if ext.get("median_s") and ref.get("median_s") else None
        mem = (ref["peak_mb"] / max(ext["peak_mb"], 0.1)) if ext.get("peak_mb") is not None and ref.get("peak_mb") is not None else None
        others = ", ".join(f"{k} {v['median_s']:.4f}s" for k, v in impls.items() if k not in ("ext", "torch") and v.get("median_s"))
        if ref.get("skipped"):
            others = (others + "; " if others else "") + "torch skipped: " + ref["skipped"]
        lines.append(f"{op:<24} {case:<34} {fmt(ext.get('median_s'), '9.4f')} {fmt(ref.get('median_s'), '9.4f')} "
                     f"{fmt(speed, '7.1f') + 'x' if speed else '       -'} {fmt(ext.get('peak_mb'), '8.1f')} "
                     f"{fmt(ref.get('peak_mb'), '9.1f')} {fmt(mem, '8.1f') + 'x' if mem else '        -'}  {others}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, skip the largest cases")
    parser.add_argument("--json", default=None, help="write the records to this JSON file")
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    parser.add_argument("--only", default=None, help="comma-separated op names to run")
    parser.add_argument("--no-memory", action="store_true", help="skip the peak-memory measurements")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where inputs live (default cpu)")
    parser.add_argument("--beside-busy", action="store_true",
                        help="time while another process keeps one core busy (a shared machine, a DDP rank, a "
                             "data-loader worker); the compiled ops also run at 1 thread, the two counts taking turns "
                             "call by call (impl 'ext, 1 thread')")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per cell (default 7, 3 with --quick)")
    parser.add_argument("--measure-memory", nargs=3, metavar=("OP", "CASE", "IMPL"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.repeats is not None and args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    busy = None
    if args.beside_busy:
        busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        _run(args)
    finally:
        if busy is not None:
            busy.kill()


def _run(args) -> None:
    torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("bench_ops: --device cuda: no CUDA device is available")
    cases = all_cases(args.device)
    if args.measure_memory:
        op, name, impl = args.measure_memory
        case = next(c for c in cases if c.op == op and c.name == name)
        print(measure_peak_mb(case, impl))
        return
    selected = [c for c in cases if (c.quick or not args.quick)
                and (args.only is None or c.op in args.only.split(","))]
    repeats = args.repeats or (3 if args.quick else 7)
    records = []
    for case in selected:
        inputs = to_device(case.make_inputs(), args.device)
        for impl, fn in case.impls.items():
            reason = (case.skip or {}).get(impl)
            record = {"op": case.op, "case": case.name, "impl": impl, "median_s": None, "peak_mb": None}
            if reason:
                record["skipped"] = reason
            elif impl == "ext" and args.beside_busy and args.device == "cpu" and args.threads != 1:
                medians = _time_threads(fn, inputs, repeats, (args.threads, 1))
                record["median_s"] = medians[args.threads]
                records.append({"op": case.op, "case": case.name, "impl": "ext, 1 thread", "median_s": medians[1],
                                "peak_mb": None})
            else:
                record["median_s"] = _time(fn, inputs, repeats, args.device)
                if not args.no_memory:
                    record["peak_mb"] = (cuda_peak_mb(fn, inputs) if args.device == "cuda"
                                         else _peak_in_subprocess(case.op, case.name, impl, args.threads))
            records.append(record)
            print(f"{case.op:<24} {case.name:<34} {impl:<6} "
                  + (f"{record['median_s']:.4f} s  {record['peak_mb'] or 0:.1f} MB" if not reason else f"skipped ({reason})"),
                  flush=True)
    print()
    gpu = f", GPU {torch.cuda.get_device_name()}" if args.device == "cuda" else ""
    print(f"machine: {cpu_description()}{gpu}, torch {torch.__version__}, "
          f"device {args.device}, threads {args.threads}, repeats {repeats}"
          + (", beside a busy process" if args.beside_busy else ""))
    print(_format_table(records))
    if args.json:
        meta = {"torch": torch.__version__, "threads": args.threads, "repeats": repeats, "cpu_count": os.cpu_count(),
                "beside_busy": args.beside_busy,
                "device": torch.cuda.get_device_name() if args.device == "cuda" else platform.machine(),
                "machine": cpu_description()}
        with open(args.json, "w") as f:
            json.dump([dict(r, **meta) for r in records], f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
