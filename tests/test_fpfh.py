import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import opcheck, requires_ext
from vrnet_ext import ops
from vrnet_ext.data.procedural import room_scan
from vrnet_ext.ops.fpfh import fpfh_reference
from vrnet_ext.ops.normals import neighbourhood
from vrnet_ext.geometry.preprocessing import voxel_downsample


def room_points(count: int = 30_000, voxel: float = 0.1, dtype=torch.float64) -> torch.Tensor:
    points = torch.as_tensor(voxel_downsample(room_scan(count, 0), voxel), dtype=dtype)
    return points + 1e-3 * torch.randn(points.shape, generator=torch.Generator().manual_seed(0), dtype=dtype)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_fpfh_is_invariant_to_rigid_motion_and_each_histogram_sums_to_200(backend):
    points = room_points()
    normals = ops.normals(points, viewpoint=(5.0, 4.0, 1.5))
    R = torch.tensor(Rotation.from_euler("zyx", [70, -20, 35], degrees=True).as_matrix())
    t = torch.tensor([3.0, -1.0, 0.5], dtype=torch.float64)
    features = ops.fpfh(points, normals, radius=0.5, backend=backend)
    moved = ops.fpfh(points @ R.T + t, normals @ R.T, radius=0.5, backend=backend)
    assert features.shape == (points.shape[0], 33)
    close = ((moved - features).abs().amax(1) < 1e-6).float().mean()
    assert close > 0.995, close  # an angle on a bin edge may land in the next bin after rounding
    nearest2, _ = ops.knn(points[None], points[None], 1, exclude_self=True)
    isolated = nearest2[0, :, 0] > 0.25  # no neighbour within the radius 0.5: an all-zero feature
    expected = torch.where(isolated, 0.0, 200.0).to(points.dtype).unsqueeze(1).expand(-1, 3)
    torch.testing.assert_close(features.view(-1, 3, 11).sum(-1), expected)


def open3d_fpfh_brute_force(points: np.ndarray, normals: np.ndarray, radius: float) -> np.ndarray:
    """FPFH as Open3D's compute_fpfh_feature defines it (every point within radius, no neighbour cap),
    one pair at a time in float64."""
    n = len(points)
    d2 = ((points[:, None] - points[None]) ** 2).sum(-1)
    spfh = np.zeros((n, 3, 11))
    for i in range(n):
        for j in range(n):
            if not 0 < d2[i, j] <= radius * radius:
                continue
            d = (points[j] - points[i]) / np.sqrt(d2[i, j])
            u, other = normals[i], normals[j]
            if abs(normals[i] @ d) < abs(normals[j] @ d):  # the frame on the normal closer to the line
                u, other, d = normals[j], normals[i], -d
            v = np.cross(d, u)
            if np.linalg.norm(v) == 0:
                theta = alpha = phi = 0.0
            else:
                v = v / np.linalg.norm(v)
                w = np.cross(u, v)
                theta, alpha, phi = np.arctan2(w @ other, u @ other), v @ other, u @ d
            for block, (value, low, span) in enumerate(((theta, -np.pi, 2 * np.pi), (alpha, -1, 2), (phi, -1, 2))):
                spfh[i, block, min(10, max(0, int(np.floor((value - low) / span * 11))))] += 1
        counts = spfh[i].sum(-1, keepdims=True)
        spfh[i] = np.where(counts > 0, spfh[i] * 100 / np.maximum(counts, 1), 0)
    out = np.zeros_like(spfh)
    for i in range(n):
        mixed = sum(spfh[j] / d2[i, j] for j in range(n) if 0 < d2[i, j] <= radius * radius)
        if np.ndim(mixed):
            sums = mixed.sum(-1, keepdims=True)
            out[i] = spfh[i] + np.where(sums > 0, mixed * 100 / np.maximum(sums, 1e-300), 0)
    return out.reshape(n, 33)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_fpfh_is_open3d_s_definition_at_every_scale(backend):
    rng = np.random.default_rng(4)
    points = rng.normal(size=(120, 3)) * [1.0, 1.0, 0.2]
    normals = rng.normal(size=(120, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[5] = (points[7] - points[5]) / np.linalg.norm(points[7] - points[5])  # a normal along a joining line
    points[9] = points[8]  # a duplicate point
    expected = open3d_fpfh_brute_force(points, normals, 0.9)
    for scale in (1.0, 1e-9, 1e9):
        got = ops.fpfh(torch.tensor(points * scale), torch.tensor(normals), 0.9 * scale, max_neighbours=120,
                       backend=backend).numpy()
        rows_equal = (np.abs(got - expected).max(1) < 1e-7).mean()
        assert rows_equal > 0.97, (scale, rows_equal)  # an angle on a bin edge may round either way


def test_fpfh_bins_are_open3d_s():
    o3d = pytest.importorskip("open3d", reason="Open3D (an optional comparison tool) is not installed")
    points = room_points()
    normals = ops.normals(points, viewpoint=(5.0, 4.0, 1.5))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.numpy()))
    cloud.normals = o3d.utility.Vector3dVector(normals.numpy())
    theirs = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=0.5, max_nn=100)).data).T
    ours = ops.fpfh(points, normals, 0.5, max_neighbours=100).numpy()
    assert (np.abs(ours - theirs).max(1) < 1e-6).mean() > 0.9  # the 100-neighbour cap breaks ties its own way
    assert np.abs(ours - theirs).mean() < 0.05


@requires_ext
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_matches_the_reference(dtype, device):
    points = room_points(dtype=dtype).to(device)
    normals = ops.normals(points, viewpoint=(5.0, 4.0, 1.5))
    dist2, idx = neighbourhood(points, 40)
    ext = torch.ops.vrnet_ext.fpfh(points, normals, idx, dist2, 0.35)
    ref = fpfh_reference(points, normals, idx, dist2, 0.35)
    rows_equal = ((ext - ref).abs().amax(1) <= (1e-9 if dtype == torch.float64 else 2e-4)).float().mean()
    assert rows_equal > 0.995, rows_equal  # ties at a bin edge round either way
    torch.testing.assert_close(ext.mean(0), ref.mean(0), rtol=0, atol=0.05)
    assert ext.device == points.device


@requires_ext
def test_duplicate_points_and_isolated_points_are_finite():
    points = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [0.1, 0, 0], [0.0, 0.1, 0], [5.0, 5, 5]], dtype=torch.float64)
    normals = torch.tensor([[0.0, 0, 1]], dtype=torch.float64).expand(5, 3).contiguous()
    for backend in ("ext", "torch"):
        features = ops.fpfh(points, normals, 0.5, backend=backend)
        assert torch.isfinite(features).all() and features[4].abs().sum() == 0
    torch.testing.assert_close(ops.fpfh(points, normals, 0.5), ops.fpfh(points, normals, 0.5, backend="torch"))


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(backend):
    points = torch.rand(40, 3)
    normals = torch.nn.functional.normalize(torch.rand(40, 3), dim=1)
    cases = [((points, normals[:5], 0.3), ValueError, "normals"), ((points, normals, 0.0), ValueError, "radius"),
             ((points, normals, float("nan")), ValueError, "radius"), ((points, normals.double(), 0.3), TypeError, "dtype"),
             ((points[:2], normals[:2], 0.3), ValueError, "at least 3 points"),
             ((points, normals.masked_fill(normals > 0.8, float("inf")), 0.3), ValueError, "normals"),
             ((points, normals.index_fill(0, torch.tensor([7]), 0.0), 0.3), ValueError,
              "normals must be unit vectors: 1 of 40 are not \\(first: row 7, length 0\\)"),
             ((points, normals * 1e30, 0.3), ValueError, "normals must be unit vectors: 40 of 40")]
    for args, error, match in cases:
        with pytest.raises(error, match=match):
            ops.fpfh(*args, backend=backend)


@requires_ext
def test_opcheck():
    points = torch.rand(60, 3, dtype=torch.float64)
    dist2, idx = neighbourhood(points, 10)
    opcheck(torch.ops.vrnet_ext.fpfh.default, (points, ops.normals(points), idx, dist2, 0.3))
