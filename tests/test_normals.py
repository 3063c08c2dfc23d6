import pytest
import torch

from conftest import opcheck, requires_ext
from vrnet_ext import ops
from vrnet_ext.data.procedural import room_scan
from vrnet_ext.geometry.preprocessing import voxel_downsample


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_normals_of_a_plane_face_the_viewpoint(backend, device):
    g = torch.Generator().manual_seed(0)
    plane = torch.cat([torch.rand(300, 2, generator=g, dtype=torch.float64), torch.zeros(300, 1, dtype=torch.float64)], 1)
    plane = plane.to(device)
    up = ops.normals(plane, viewpoint=(0.5, 0.5, 2.0), backend=backend)
    down = ops.normals(plane, viewpoint=(0.5, 0.5, -2.0), backend=backend)
    torch.testing.assert_close(up, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=device).expand(300, 3))
    torch.testing.assert_close(down, -up)


@requires_ext
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_matches_the_reference_on_a_noisy_room(dtype, device):
    points = torch.as_tensor(voxel_downsample(room_scan(20_000, 0), 0.1), dtype=dtype).to(device)
    ext = ops.normals(points, 17, viewpoint=(5.0, 4.0, 1.5))
    ref = ops.normals(points.double(), 17, viewpoint=(5.0, 4.0, 1.5), backend="torch")
    assert ext.dtype == dtype and ext.shape == points.shape and ext.device == points.device
    torch.testing.assert_close(ext.norm(dim=1), torch.ones(len(points), dtype=dtype, device=device))
    # eigenvectors of (nearly) repeated eigenvalues (edges, corners) are not unique: compare the rest
    agree = (ext.double() * ref).sum(1) > 1 - 1e-5
    assert agree.float().mean() > 0.98, agree.float().mean()


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(backend):
    points = torch.rand(50, 3)
    cases = [((points[:2],), ValueError, "at least 3 points"), ((points[:, :2],), ValueError, "points"),
             ((points.long(),), TypeError, "points"), ((points.masked_fill(points > 0.9, float("nan")),), ValueError, "NaN"),
             ((points, 1), ValueError, "neighbours"), ((points, 10, (0.0, 0.0)), ValueError, "viewpoint")]
    for args, error, match in cases:
        with pytest.raises(error, match=match):
            ops.normals(*args, backend=backend)


@requires_ext
def test_opcheck():
    from vrnet_ext.ops.normals import neighbourhood

    points = torch.rand(60, 3, dtype=torch.float64)
    _, idx = neighbourhood(points, 10)
    opcheck(torch.ops.vrnet_ext.normals.default, (points, idx, [0.0, 0.0, 0.0]))
