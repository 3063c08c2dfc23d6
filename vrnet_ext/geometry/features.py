"""FPFH at a voxel size and feature matching: the descriptors of the FPFH-based estimators and of
the scene model (:class:`ScanView`, :func:`describe`), and nearest-neighbour matches between two
sets of descriptors."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from vrnet_ext import ops

FEATURE_RADIUS_VOXELS = 5.0  # FPFH radius in voxels (Open3D's global registration tutorial)


def voxel_fpfh(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """FPFH (N, 33) of a cloud voxel-downsampled at ``voxel_size``, at Open3D's tutorial radii:
    normals from 30 neighbours, features within 5 voxels."""
    return ops.fpfh(points, ops.normals(points), FEATURE_RADIUS_VOXELS * voxel_size)


@dataclass(eq=False)
class ScanView:
    """One downsampled scan: ``points`` (V, 3) in the scan's unit, ``voxel`` edge, FPFH (V, 33) float32
    (on the device they were computed on)."""

    points: np.ndarray
    voxel: float
    descriptors: torch.Tensor
    _nearest: dict[int, tuple[ScanView, torch.Tensor]] = field(default_factory=dict, repr=False)

    def nearest_in(self, other: ScanView) -> torch.Tensor:
        """(V,) each point's nearest descriptor among ``other``'s (:func:`nearest_features`), computed
        once per pair of views (the estimators of one registration share them)."""
        if id(other) not in self._nearest:  # the view is kept with the result: its id stays its own
            self._nearest[id(other)] = (other, nearest_features(self.descriptors, other.descriptors))
        return self._nearest[id(other)][1]

    def network_points(self) -> torch.Tensor:
        """(V, 3) float32 points in voxel units (the network's coordinates), beside the descriptors."""
        return torch.as_tensor(self.points / self.voxel, dtype=torch.float32, device=self.descriptors.device)

    def tensor(self) -> torch.Tensor:
        """(V, 3) float64 points, beside the descriptors."""
        return torch.as_tensor(self.points, dtype=torch.float64, device=self.descriptors.device)


def describe(points: np.ndarray, voxel: float, device: torch.device = torch.device("cpu")) -> ScanView:
    """Voxel-downsampled points (V, 3) (sensor at the origin) -> :class:`ScanView` with FPFH
    computed on ``device``."""
    if len(points) < 3:
        raise ValueError(f"points: need at least 3 points after downsampling, got {len(points)}")
    descriptors = voxel_fpfh(torch.as_tensor(points, dtype=torch.float64, device=device), voxel)
    return ScanView(points, voxel, descriptors.float())


def nearest_features(query: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """(N, F), (M, F) descriptors -> the index (N,) of each query row's nearest reference row,
    through ``ops.knn`` in float32 (1.6x faster than float64 for FPFH; its bins, sums of weights in
    [0, 200], keep 7 significant digits, and only exact near-ties can come out differently)."""
    _, nearest = ops.knn(query.float()[None], reference.float()[None], 1)
    return nearest[0, :, 0]


def nearest_both_ways(src_features: torch.Tensor, tgt_features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, F), (M, F) descriptors -> (each source point's nearest target (N,), each target point's
    nearest source (M,)) (:func:`nearest_features`)."""
    return nearest_features(src_features, tgt_features), nearest_features(tgt_features, src_features)


def mutual_matches(src_features: torch.Tensor, tgt_features: torch.Tensor) -> torch.Tensor:
    """(N, F), (M, F) -> (C, 2) index pairs (i, j): j is i's nearest target feature and i is j's
    nearest source feature. Falls back to every source point's nearest target feature when fewer
    than 10 pairs are mutual."""
    return mutual_of(*nearest_both_ways(src_features, tgt_features))


def mutual_of(forward: torch.Tensor, backward: torch.Tensor) -> torch.Tensor:
    """:func:`mutual_matches` from the nearest features both ways, forward (N,), backward (M,)."""
    src_idx = torch.arange(forward.shape[0], device=forward.device)
    mutual = backward[forward] == src_idx
    if int(mutual.sum()) < 10:
        mutual = torch.ones_like(mutual)
    return torch.stack([src_idx[mutual], forward[mutual]], dim=1)
