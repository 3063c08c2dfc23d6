"""Preprocessing of scans: voxel downsampling, the voxel edge for a point budget, subsampling.

Points are (N, 3) float arrays in the scans' unit (metres for the shared scenes).
"""
from __future__ import annotations

import numpy as np


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Mean of the points in each occupied voxel of edge ``voxel_size`` -> (V, 3)."""
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    if not np.isfinite(voxel_size):
        raise ValueError(f"voxel_size must be finite, got {voxel_size}")
    cells_float = np.floor((points - points.min(0)) / voxel_size)
    if float(cells_float.max(initial=0.0)) >= 2.0 ** 62:
        raise ValueError(f"voxel_size {voxel_size:g} is too small for a cloud of extent "
                         f"{np.ptp(points, axis=0).tolist()} (more than 2^62 voxels along an axis)")
    cells = cells_float.astype(np.int64)
    sizes = cells.max(0) + 1
    if float(np.prod(sizes.astype(np.float64))) < 2.0 ** 62:
        keys = (cells[:, 0] * sizes[1] + cells[:, 1]) * sizes[2] + cells[:, 2]  # row-major voxel number
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    else:  # a far-flung cloud (stray points km away): number the occupied voxels row by row instead
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.stack([np.bincount(inverse, weights=points[:, axis], minlength=len(counts)) for axis in range(3)], 1)
    return (sums / counts[:, None]).astype(points.dtype)


STRAY_POINTS = 2  # extreme points per axis end that voxel_size_for ignores


def voxel_size_for(points: np.ndarray, target_points: int) -> float:
    """A voxel edge that leaves roughly ``target_points`` of a scan (surface scaling: V ~ 1/size^2).

    The search starts from a thousandth of the diagonal of the scan's box without its two most extreme
    points at each end of each axis, so one or two stray points far away (a reflection, a bad range
    reading) do not make the voxels coarse."""
    if target_points < 1:
        raise ValueError(f"target_points must be >= 1, got {target_points}")
    trim = min(STRAY_POINTS, (len(points) - 1) // 2)
    ordered = np.sort(points, axis=0)
    extent = float(np.linalg.norm(ordered[len(points) - 1 - trim] - ordered[trim])) or 1.0
    size = extent / 1000.0
    for _ in range(30):
        count = len(voxel_downsample(points, size))
        if count <= target_points:
            return size
        size *= max(1.1, (count / target_points) ** 0.5)
    return size


def subsample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    if len(points) <= count:
        return points
    return points[np.sort(rng.choice(len(points), count, replace=False))]
