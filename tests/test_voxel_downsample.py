import math
from collections import defaultdict

import numpy as np
import pytest
import torch

from conftest import DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext
from vrnet_ext import ops
from vrnet_ext.data.procedural import room_scan
from vrnet_ext.ops.voxel_downsample import voxel_downsample_reference
from vrnet_ext.geometry.preprocessing import point_spacing, voxel_downsample, voxel_size_for


def brute_force(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Python dict of cells -> float64 sums, rows sorted by cell: the definition, one point at a time."""
    low = points.amin(0)
    cells = torch.floor((points - low) / voxel_size).long().tolist()
    groups = defaultdict(list)
    for cell, point in zip(cells, points.double().tolist()):
        groups[tuple(cell)].append(point)
    return torch.from_numpy(np.array([np.mean(groups[c], axis=0) for c in sorted(groups)], dtype=np.float64))


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("N,voxel_size", [(1, 0.1), (2, 10.0), (97, 0.05), (1000, 0.013), (5000, 1e-4), (3000, 7.0)])
def test_kernel_matches_reference_and_brute_force(dtype, N, voxel_size, device):
    """The CPU and the CUDA kernel give the CPU reference's values bit for bit."""
    g = torch.Generator().manual_seed(N)
    points = (torch.rand(N, 3, generator=g, dtype=torch.float64, device="cpu")
              * torch.tensor([3.0, 0.5, 1.0], device="cpu") - 1.7).to(dtype)
    ext = ops.voxel_downsample(points.to(device), voxel_size)
    assert ext.dtype == dtype and ext.device.type == device.type
    ext = ext.cpu()
    torch.testing.assert_close(ext, voxel_downsample_reference(points, voxel_size), rtol=0, atol=0)
    torch.testing.assert_close(ext.double(), brute_force(points, voxel_size), rtol=0,
                               atol=1e-12 if dtype == torch.float64 else 1e-6)


@requires_ext
def test_awkward_layouts_duplicates_and_cell_borders():
    # points exactly on cell borders, repeated points, a (3, N) array seen transposed
    grid = torch.stack(torch.meshgrid(*[torch.arange(4, dtype=torch.float64) * 0.25] * 3, indexing="ij"), -1).reshape(-1, 3)
    points = torch.cat([grid, grid, grid[:5]])
    for layout in (points, non_contiguous(points), points.T.contiguous().T):
        ext = ops.voxel_downsample(layout, 0.25)
        torch.testing.assert_close(ext, voxel_downsample_reference(points, 0.25), rtol=0, atol=0)
    assert len(ops.voxel_downsample(points, 0.25)) == 64
    assert len(ops.voxel_downsample(points, 1.0)) == 1  # extent 0.75 < 1: one voxel


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(backend, device):
    points = torch.rand(50, 3)
    cases = [((points[:0], 0.1), ValueError, "at least one point"), ((points[:, :2], 0.1), ValueError, "points"),
             ((points.long(), 0.1), TypeError, "points"), ((points, 0.0), ValueError, "voxel_size"),
             ((points, float("nan")), ValueError, "voxel_size"), ((points, -1.0), ValueError, "voxel_size"),
             ((points, True), ValueError, "voxel_size"),
             ((points.masked_fill(points > 0.9, float("inf")), 0.1), ValueError, "NaN or Inf"),
             ((torch.tensor([[0.0, 0.0, 0.0], [1e30, 0.0, 0.0]]), 1e-30), ValueError, "too small")]
    for args, error, match in cases:
        with pytest.raises(error, match=match):
            ops.voxel_downsample(*args, backend=backend)


@requires_ext
def test_opcheck():
    opcheck(torch.ops.vrnet_ext.voxel_downsample.default, (torch.rand(200, 3), 0.1))


@requires_ext
def test_torch_compile_fullgraph():
    points = torch.rand(500, 3)
    fn = compile_fullgraph(lambda p: ops.voxel_downsample(p, 0.1))  # data-dependent row count (fake kernel)
    torch.testing.assert_close(fn(points), ops.voxel_downsample(points, 0.1), rtol=0, atol=0)


@requires_ext
def test_low_precision_inputs_are_promoted():
    points = torch.rand(300, 3)
    torch.testing.assert_close(ops.voxel_downsample(points.bfloat16(), 0.2), ops.voxel_downsample(points.bfloat16().float(), 0.2))


def test_numpy_front_end_and_voxel_size_for():
    scan = room_scan(30_000, 0)
    down = voxel_downsample(scan, 0.05)
    assert down.dtype == scan.dtype and isinstance(down, np.ndarray)
    for target in (1000, 5000, 20_000):
        size = voxel_size_for(scan, target)
        count = len(voxel_downsample(scan, size))
        assert 0.9 * target <= count <= target, (target, count)
    assert voxel_size_for(scan[:100], 5000) > 0 and math.isfinite(voxel_size_for(scan[:100], 5000))


def test_asking_for_more_points_than_a_scan_has_never_leaves_fewer():
    """A dense scan (most points packed near a sensor, as in a LiDAR sweep) with fewer points than
    asked for: the edge keeps most of them (at least as many as any smaller ask), where a
    thousandth of the scan's extent would merge most of the dense part; a sparse one keeps most,
    and exact copies of points do not make a scan dense."""
    rng = np.random.default_rng(3)
    near = rng.normal(scale=0.5, size=(18_000, 3))  # 18k points within about a metre
    far = rng.uniform(-100, 100, size=(2_000, 3))    # 2k points over 200 m
    scan = np.concatenate([near, far])
    counts = {ask: len(voxel_downsample(scan, voxel_size_for(scan, ask))) for ask in (10_000, 19_000, 20_000, 50_000)}
    assert len(voxel_downsample(scan, 200 / 1000)) < 0.5 * len(scan)  # what a thousandth of the extent keeps
    assert counts[50_000] >= 0.8 * len(scan) and counts[20_000] >= counts[19_000] >= counts[10_000], counts
    sparse = rng.uniform(-1, 1, size=(3_000, 3))
    assert len(voxel_downsample(sparse, voxel_size_for(sparse, 5_000))) >= 0.9 * len(sparse)
    copies = np.concatenate([sparse, sparse[:1_500]])  # exact copies merge at any edge: not a dense scan
    assert voxel_size_for(copies, 5_000) == voxel_size_for(sparse, 5_000)


def test_the_edge_is_never_finer_than_the_points_it_leaves():
    """A sparse surface (a range scan of 3,000 samples 1 cm apart, 60 cm across) asked for more
    points than it has: the edge is its spacing, not a thousandth of its extent (0.8 mm), so FPFH's
    radius and ICP's reach, counted in edges, reach its neighbours (a dense scan's edge is the
    count's alone: test_numpy_front_end_and_voxel_size_for)."""
    rng = np.random.default_rng(4)
    grid = np.stack(np.meshgrid(np.arange(60) * 0.01, np.arange(50) * 0.01, [0.0]), -1).reshape(-1, 3)
    scan = grid + rng.normal(scale=1e-3, size=grid.shape)
    for ask in (5_000, 50_000):
        edge = voxel_size_for(scan, ask)
        assert edge == pytest.approx(point_spacing(scan), rel=0.05) and 0.007 < edge < 0.011, edge
        assert len(voxel_downsample(scan, edge)) >= 0.9 * len(scan)
