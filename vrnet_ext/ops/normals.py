"""Surface normals of a point cloud: ``normals = ops.normals(points, neighbours=30)``.

Each point's normal is the least-variance direction of itself and its ``neighbours`` nearest
points (the eigenvector of the smallest eigenvalue of their covariance), signed to face
``viewpoint`` (the sensor: the origin of a 3DMatch fragment or a LiDAR scan). Not differentiable.
"""
from __future__ import annotations

import math

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import check_finite, check_float, check_shape, float32_region, promote_low_precision
from vrnet_ext.ops.knn import knn


def neighbourhood(points: torch.Tensor, neighbours: int) -> tuple[torch.Tensor, torch.Tensor]:
    """points (N, 3) -> (squared distances (N, k), indices (N, k)) of each point's k = min(neighbours,
    N - 1) nearest other points; ValueError when k < 2."""
    k = min(neighbours, points.shape[0] - 1)
    if k < 2:
        raise ValueError(f"points: need at least 3 points, got {points.shape[0]}")
    dist2, idx = knn(points[None], points[None], k, exclude_self=True)
    return dist2[0], idx[0]


def normals_reference(points: torch.Tensor, idx: torch.Tensor, viewpoint: tuple[float, float, float]) -> torch.Tensor:
    """Pure PyTorch: eigh of each (k + 1)-point covariance."""
    around = torch.cat([points[:, None], points[idx]], dim=1)  # (N, k + 1, 3)
    centred = around - around.mean(dim=1, keepdim=True)
    _, vectors = torch.linalg.eigh(centred.mT @ centred)
    normals = vectors[..., 0]
    facing = ((torch.tensor(viewpoint, dtype=points.dtype, device=points.device) - points) * normals).sum(-1)
    return torch.where(facing.unsqueeze(-1) < 0, -normals, normals)


def normals(points: torch.Tensor, neighbours: int = 30, viewpoint: tuple[float, float, float] = (0.0, 0.0, 0.0),
            backend: str = "ext") -> torch.Tensor:
    """points (N, 3) -> unit normals (N, 3) facing ``viewpoint`` (see the module)."""
    points = promote_low_precision(points)
    check_float(points, "points")
    check_shape(points, "points", 2, "(N, 3)", last=3)
    if isinstance(neighbours, bool) or not isinstance(neighbours, int) or neighbours < 2:
        raise ValueError(f"neighbours must be an integer >= 2, got {neighbours!r}")
    if len(viewpoint) != 3:
        raise ValueError(f"viewpoint must have 3 coordinates, got {viewpoint!r}")
    check_finite(points, "points")
    _, idx = neighbourhood(points, neighbours)
    viewpoint = tuple(float(v) for v in viewpoint)
    if not all(math.isfinite(v) for v in viewpoint):
        raise ValueError(f"viewpoint must have 3 finite coordinates, got {viewpoint!r}")
    if use_extension(backend, points.device):
        return torch.ops.vrnet_ext.normals(points, idx, list(viewpoint))
    with float32_region(points):
        return normals_reference(points, idx, viewpoint)


if has_extension():

    @torch.library.register_fake("vrnet_ext::normals")
    def _normals_fake(points, idx, viewpoint):
        return torch.empty_like(points)
