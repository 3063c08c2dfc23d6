import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import opcheck, requires_ext
from vrnet_ext import ops
from vrnet_ext.data.procedural import room_scan
from vrnet_ext.ops.fpfh import fpfh_reference
from vrnet_ext.ops.normals import neighbourhood
from vrnet_ext.preprocessing import voxel_downsample


def room_points(count: int = 30_000, voxel: float = 0.1, dtype=torch.float64) -> torch.Tensor:
    points = torch.as_tensor(voxel_downsample(room_scan(count, 0), voxel), dtype=dtype)
    return points + 1e-3 * torch.randn(points.shape, generator=torch.Generator().manual_seed(0), dtype=dtype)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_fpfh_is_invariant_to_rigid_motion_and_each_histogram_sums_to_100(backend):
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
    expected = torch.where(isolated, 0.0, 100.0).to(points.dtype).unsqueeze(1).expand(-1, 3)
    torch.testing.assert_close(features.view(-1, 3, 11).sum(-1), expected)


@requires_ext
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_matches_the_reference(dtype):
    points = room_points(dtype=dtype)
    normals = ops.normals(points, viewpoint=(5.0, 4.0, 1.5))
    dist2, idx = neighbourhood(points, 40)
    ext = torch.ops.vrnet_ext.fpfh(points, normals, idx, dist2, 0.35)
    ref = fpfh_reference(points, normals, idx, dist2, 0.35)
    rows_equal = ((ext - ref).abs().amax(1) <= (1e-9 if dtype == torch.float64 else 2e-4)).float().mean()
    assert rows_equal > 0.995, rows_equal  # ties at a bin edge round either way
    torch.testing.assert_close(ext.mean(0), ref.mean(0), rtol=0, atol=0.05)


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
             ((points, normals.masked_fill(normals > 0.8, float("inf")), 0.3), ValueError, "normals")]
    for args, error, match in cases:
        with pytest.raises(error, match=match):
            ops.fpfh(*args, backend=backend)


@requires_ext
def test_opcheck():
    points = torch.rand(60, 3, dtype=torch.float64)
    dist2, idx = neighbourhood(points, 10)
    opcheck(torch.ops.vrnet_ext.fpfh.default, (points, ops.normals(points), idx, dist2, 0.3))
