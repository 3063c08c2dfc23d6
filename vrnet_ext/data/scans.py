"""Self-supervised training pairs of the scene model, cut from single scans.

``synthetic_pair`` makes a training pair from ONE scan: two overlapping slabs of it (cut along a
random direction, 20-80 % shared), each turned by its own random rotation about the sensor (the
origin) and voxel-downsampled on its own randomly shifted grid, so no point is shared exactly;
the ground truth is the relative rotation. Nothing of a second scan is used, so a model trained
on fragment k never saw the registration of any pair.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vrnet_ext.geometry.features import ScanView, describe
from vrnet_ext.geometry.preprocessing import voxel_downsample
from vrnet_ext.geometry.transforms import move

@dataclass
class ScanPair:
    """Two views of one scan and the motion between them (``T_tgt_src`` maps source coordinates,
    in the scan's unit, into the target's frame)."""

    src: ScanView
    tgt: ScanView
    T_tgt_src: np.ndarray  # (4, 4): tgt ~ R src + t


def _slab(points: np.ndarray, direction: np.ndarray, low: float, high: float) -> np.ndarray:
    along = points @ direction
    lo, hi = np.quantile(along, [low, high])
    return points[(along >= lo) & (along <= hi)]


def view(points: np.ndarray, rotation: np.ndarray, voxel: float, rng: np.random.Generator) -> np.ndarray:
    """``points`` (N, 3) turned by ``rotation`` about the origin and voxel-downsampled on a grid
    shifted by a random fraction of ``voxel`` -> (V, 3)."""
    shift = rng.uniform(0.0, voxel, 3)
    return voxel_downsample(move(points, rotation, shift), voxel) - shift


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
    src_view = describe(view(src_points, rotation_src, size, rng), size)
    tgt_view = describe(view(tgt_points, rotation_tgt, size, rng), size)
    T = np.eye(4)
    T[:3, :3] = rotation_tgt @ rotation_src.T
    return ScanPair(src_view, tgt_view, T)
