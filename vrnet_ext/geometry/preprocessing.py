"""Preprocessing of scans: voxel downsampling, the voxel edge for a point budget, subsampling.

Points are (N, 3) float arrays in the scans' unit (metres for the shared scenes).
"""
from __future__ import annotations

import numpy as np
import torch

from vrnet_ext import ops


FLOAT32_RELATIVE_SPACING = 1e-5  # re-centre when float32 would round coordinates coarser than this x the extent


def coarse_in_float32(largest_coordinate: float, extent: float) -> bool:
    """Whether float32 spacing at ``largest_coordinate`` (e.g. a UTM northing, 5e6 m: 0.5 m) exceeds
    FLOAT32_RELATIVE_SPACING of the cloud's ``extent``: then the cloud must be re-centred before any
    float32 cast."""
    return float(np.spacing(np.float32(largest_coordinate))) > FLOAT32_RELATIVE_SPACING * extent


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Mean of the points in each occupied voxel of edge ``voxel_size`` -> (V, 3), same dtype
    (:func:`vrnet_ext.ops.voxel_downsample`, the compiled op; rows in (x, y, z) voxel order)."""
    return ops.voxel_downsample(torch.from_numpy(np.ascontiguousarray(points)), voxel_size).numpy()


STRAY_POINTS = 2  # extreme points per axis end that voxel_size_for ignores


CLOSE_ENOUGH = 0.9  # voxel_size_for stops once the count is within this share of the target
DISTINCT = 1e-9     # points closer than this share of a scan's extent count as one (its distinct points)


SPACING_SAMPLE = 2000  # points whose nearest neighbours measure a cloud's spacing (evenly strided)


def point_spacing(points: np.ndarray | torch.Tensor, backend: str = "ext") -> float:
    """The median distance from a point of ``points`` (N >= 2, 3) to its nearest other point, over an
    even sample of at most :data:`SPACING_SAMPLE` of them: the cloud's resolution."""
    points = torch.as_tensor(points)
    picked = points[:: max(1, len(points) // SPACING_SAMPLE)]
    dist2, _ = ops.knn(picked[None], points[None], 2, backend=backend)
    return float(dist2[0, :, 1].sqrt().median())


def voxel_size_for(points: np.ndarray | torch.Tensor, target_points: int) -> float:
    """A voxel edge that leaves at most ``target_points`` of a scan (N, 3), and at least 90 % of them
    where the search gets there within 30 tries — never finer than the spacing of the points it
    leaves (:func:`point_spacing`): the radii counted in voxels (FPFH's, ICP's reach) then reach
    a point's neighbours on a sparse scan too (an object's range scan of a few thousand points,
    a scan that came downsampled), where a count alone would ask for an edge below its resolution.
    Downsampled at a count's edge, a dense scan's points lie 0.6-0.85 edges apart, so the floor
    leaves it alone. ``points``: an array, or a tensor on any device, where the search then counts
    the voxels (on a GPU each count is a few kernels, not a pass over the scan on the host).

    The scale is the diagonal of the scan's box without its two most extreme points at each end of
    each axis, so one or two stray points far away (a reflection, a bad range reading) do not make
    the voxels coarse. A first guess comes from the voxel count at a hundredth of that diagonal and
    surface scaling (V ~ 1/size^2); the search then steps by that scaling, and bisects (in log
    size) once it has edges on both sides of the target. A scan of no more than ``target_points``
    points keeps about all of its distinct points (but for the floor): a thousandth of that
    diagonal where that keeps 90 % of them, else (a dense scan) the edge the search finds for their
    count, so asking for more points never leaves fewer."""
    return voxel_edge_and_points(points, target_points)[0]


def voxel_edge_and_points(points: np.ndarray | torch.Tensor,
                          target_points: int) -> tuple[float, torch.Tensor | None]:
    """:func:`voxel_size_for`'s edge and the scan downsampled at it ((V, 3), on the points' device),
    which the search has made on its way, or None where the spacing floor set the edge."""
    if target_points < 1:
        raise ValueError(f"target_points must be >= 1, got {target_points}")
    points = torch.as_tensor(points)
    edge, left = _edge_for_count(points, target_points)
    if left is None:
        left = ops.voxel_downsample(points, edge)
    if len(left) > 1:
        spacing = point_spacing(left)
        if spacing > edge:
            return spacing, None
    return edge, left


def _edge_for_count(points: torch.Tensor, target_points: int) -> tuple[float, torch.Tensor | None]:
    """:func:`voxel_size_for` without the spacing floor -> (the edge, the points downsampled at it,
    or None where the search did not downsample at that edge)."""
    trim = min(STRAY_POINTS, (len(points) - 1) // 2)
    low = points.topk(trim + 1, dim=0, largest=False).values[-1]  # the (trim + 1)-th smallest per axis
    high = points.topk(trim + 1, dim=0).values[-1]
    extent = float(torch.linalg.vector_norm(high - low)) or 1.0
    if len(points) <= target_points:
        distinct = len(ops.voxel_downsample(points, extent * DISTINCT))
        fine = ops.voxel_downsample(points, extent / 1000.0)
        if len(fine) >= CLOSE_ENOUGH * distinct:
            return extent / 1000.0, fine
        target_points = distinct  # dense, e.g. a LiDAR scan near its sensor
    coarse = extent / 100.0
    size = coarse * (len(ops.voxel_downsample(points, coarse)) / target_points) ** 0.5
    fits, too_fine = None, None  # the finest edge known to leave <= target points; an edge known to leave more
    fitting = None  # the points downsampled at ``fits``
    for _ in range(30):
        left = ops.voxel_downsample(points, size)
        count = len(left)
        if count <= target_points:
            if fits is None or size < fits:
                fits, fitting = size, left
            if count >= CLOSE_ENOUGH * target_points:
                return size, left
        else:
            too_fine = size if too_fine is None else max(too_fine, size)
        if fits is not None and too_fine is not None:
            if fits / too_fine < 1.001:
                break
            size = (fits * too_fine) ** 0.5
        else:
            size *= 1.02 * max(1.0, (count / target_points) ** 0.5) if count > target_points \
                else max(0.5, (count / target_points) ** 0.5) / 1.02
    return (fits, fitting) if fits is not None else (size, None)


def subsample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``count`` of the (N, 3) points, drawn without replacement, in their original order."""
    if len(points) <= count:
        return points
    return points[np.sort(rng.choice(len(points), count, replace=False))]
