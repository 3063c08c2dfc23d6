"""Voxel downsampling: ``down = ops.voxel_downsample(points, voxel_size)``.

The mean of the points in each occupied cube of edge ``voxel_size``; cubes are counted from the
cloud's minimum corner (cell = floor((p - min) / voxel_size), computed in the points' dtype) and
the rows come in lexicographic (x, y, z) cell order. Not differentiable (a preprocessing step). The
compiled op gives the same values on the CPU and on CUDA (each voxel's points summed in float64 in
input order: deterministic; the reference's ``index_add_`` adds in any order on a GPU).
"""
from __future__ import annotations

import math

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import check_finite, check_float, check_shape, promote_low_precision

MAX_CELL = 2.0 ** 62  # cell coordinates must stay below it (int64 arithmetic)


def voxel_downsample_reference(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Pure PyTorch: torch.unique over the cell coordinates, sums in float64."""
    cells_float = torch.floor((points - points.amin(0)) / voxel_size)
    if float(cells_float.max()) >= MAX_CELL:
        raise ValueError(f"voxel_size {voxel_size:g} is too small for this cloud (more than 2^62 voxels along "
                         "an axis)")
    cells, inverse, counts = torch.unique(cells_float.long(), dim=0, return_inverse=True, return_counts=True)
    sums = torch.zeros(len(cells), 3, dtype=torch.float64, device=points.device)
    sums.index_add_(0, inverse, points.double())
    return (sums / counts.unsqueeze(1)).to(points.dtype)


def voxel_downsample(points: torch.Tensor, voxel_size: float, backend: str = "ext") -> torch.Tensor:
    """points (N, 3), N >= 1 -> (V, 3) voxel means (see the module); ``voxel_size`` > 0 in the points' unit."""
    points = promote_low_precision(points)
    check_float(points, "points")
    check_shape(points, "points", 2, "(N, 3)", last=3)
    if points.shape[0] == 0:
        raise ValueError("points: need at least one point, got 0")
    if isinstance(voxel_size, bool) or not (isinstance(voxel_size, (int, float)) and math.isfinite(voxel_size)
                                            and voxel_size > 0):
        raise ValueError(f"voxel_size must be a finite number > 0, got {voxel_size!r}")
    if use_extension(backend, points.device):
        return torch.ops.vrnet_ext.voxel_downsample(points, float(voxel_size))
    check_finite(points, "points")
    return voxel_downsample_reference(points, float(voxel_size))


if has_extension():

    @torch.library.register_fake("vrnet_ext::voxel_downsample")
    def _voxel_downsample_fake(points, voxel_size):
        voxels = torch.library.get_ctx().new_dynamic_size()
        return points.new_empty((voxels, 3))
