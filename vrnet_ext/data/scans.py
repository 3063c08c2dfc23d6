"""Scans as :class:`~vrnet_ext.model.scene.SceneVRNet` sees them, and self-supervised training pairs.

``describe`` turns voxel-downsampled points into the network's input (voxel units + FPFH); the
same function serves training and ``vrnet register --method vrnet``.

``synthetic_pair`` makes a training pair from ONE scan: two overlapping slabs of it (cut along a
random direction, 20-80 % shared), each turned by its own random rotation about the sensor (the
origin) and voxel-downsampled on its own randomly shifted grid, so no point is shared exactly;
the ground truth is the relative rotation. Nothing of a second scan is used, so a model trained
on fragment k never saw the registration of any pair.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vrnet_ext import ops
from vrnet_ext.preprocessing import voxel_downsample

FEATURE_RADIUS_VOXELS = 5.0  # FPFH radius, as fpfh_ransac (Open3D's tutorial)


@dataclass
class ScanView:
    """One downsampled scan: ``points`` (V, 3) in the scan's unit, ``voxel`` edge, FPFH (V, 33)."""

    points: np.ndarray
    voxel: float
    descriptors: torch.Tensor

    def network_points(self) -> torch.Tensor:
        """(V, 3) float32 points in voxel units (the network's coordinates)."""
        return torch.as_tensor(self.points / self.voxel, dtype=torch.float32)


def describe(points: np.ndarray, voxel: float) -> ScanView:
    """Voxel-downsampled points (V, 3) (sensor at the origin) -> :class:`ScanView` with FPFH."""
    if len(points) < 3:
        raise ValueError(f"points: need at least 3 points after downsampling, got {len(points)}")
    cloud = torch.as_tensor(points, dtype=torch.float64)
    descriptors = ops.fpfh(cloud, ops.normals(cloud), FEATURE_RADIUS_VOXELS * voxel)
    return ScanView(points, voxel, descriptors.float())


@dataclass
class ScanPair:
    src: ScanView
    tgt: ScanView
    T_tgt_src: np.ndarray  # (4, 4): tgt ~ R src + t


def _slab(points: np.ndarray, direction: np.ndarray, low: float, high: float) -> np.ndarray:
    along = points @ direction
    lo, hi = np.quantile(along, [low, high])
    return points[(along >= lo) & (along <= hi)]


def _view(points: np.ndarray, rotation: np.ndarray, voxel: float, rng: np.random.Generator) -> np.ndarray:
    shift = rng.uniform(0.0, voxel, 3)
    return voxel_downsample(points @ rotation.T + shift, voxel) - shift


def synthetic_pair(scan: np.ndarray, voxel: float, rng: np.random.Generator) -> ScanPair:
    """A training pair cut from one scan (N, 3) at about ``voxel`` resolution (see the module)."""
    from scipy.spatial.transform import Rotation  # training only: `vrnet register` never needs it

    direction = Rotation.random(random_state=rng).apply([1.0, 0.0, 0.0])
    split = rng.uniform(0.35, 0.65)
    overlap = rng.uniform(0.2, 0.8) * min(split, 1.0 - split)
    src_points = _slab(scan, direction, 0.0, split + overlap)
    tgt_points = _slab(scan, direction, split - overlap, 1.0)
    rotation_src, rotation_tgt = (Rotation.random(random_state=rng).as_matrix() for _ in range(2))
    size = voxel * rng.uniform(0.8, 1.25)
    src_view = describe(_view(src_points, rotation_src, size, rng), size)
    tgt_view = describe(_view(tgt_points, rotation_tgt, size, rng), size)
    T = np.eye(4)
    T[:3, :3] = rotation_tgt @ rotation_src.T
    return ScanPair(src_view, tgt_view, T)
