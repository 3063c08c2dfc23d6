"""Scans prepared once per registration and shared by every global estimator and every ICP start
(as small_gicp and Open3D prepare clouds before aligning them): a :class:`PreparedScan` keeps the
voxel-downsampled copies and FPFH views it has made, by voxel edge; a :class:`ScanPair` holds the
source and target with the point counts of the run (:class:`~vrnet_ext.registration.counts.PointCounts`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import torch

from vrnet_ext import ops
from vrnet_ext.geometry.features import ScanView, describe
from vrnet_ext.geometry.preprocessing import voxel_edge_and_points
from vrnet_ext.registration.counts import PointCounts

CPU = torch.device("cpu")


@dataclass
class PreparedScan:
    """One scan, ``points`` (N, 3) float64 in its unit, with what the stages of a registration made
    of it on ``device``, each made on first use and then reused. ``scan_device``: where the steps
    that read the whole scan run (voxel-edge searches, downsampling; None: ``device``), the host
    when a GPU's memory budget leaves no room for them."""

    points: np.ndarray
    device: torch.device = CPU
    scan_device: torch.device | None = None
    _downsampled: dict[float, np.ndarray] = field(default_factory=dict, repr=False)
    _views: dict[float, ScanView] = field(default_factory=dict, repr=False)

    def on_device(self) -> torch.Tensor:
        """``points`` as a tensor on ``scan_device``, where voxel edges are searched and voxels averaged:
        on the CPU the array's own memory, elsewhere a copy made for the call and not kept (a scene's
        scans would otherwise all stay on the GPU at full resolution)."""
        return torch.as_tensor(self.points, device=self.scan_device or self.device)

    def downsampled(self, voxel: float) -> np.ndarray:
        """(V, 3) float64: the centroid of the points in each ``voxel``-edged cell (computed on
        ``scan_device``)."""
        if voxel not in self._downsampled:
            self._downsampled[voxel] = ops.voxel_downsample(self.on_device(), voxel).cpu().numpy()
        return self._downsampled[voxel]

    def edge_for(self, count: int) -> float:
        """The voxel edge that leaves about ``count`` of the scan's points
        (:func:`~vrnet_ext.geometry.preprocessing.voxel_size_for`); the points the search downsampled
        at that edge are kept for :meth:`downsampled`."""
        edge, left = voxel_edge_and_points(self.on_device(), count)
        if left is not None and edge not in self._downsampled:
            self._downsampled[edge] = left.cpu().numpy()
        return edge

    def view(self, voxel: float) -> ScanView:
        """The scan downsampled at ``voxel`` with its FPFH descriptors (V, 33) on ``device``."""
        if voxel not in self._views:
            self._views[voxel] = describe(self.downsampled(voxel), voxel, self.device)
        return self._views[voxel]


@dataclass
class ScanPair:
    """Source and target of one registration, prepared once, and the point counts of the run.
    ``voxel``: the global estimators' voxel edge when fixed for many pairs (a scene: each scan's
    FPFH is then computed once), else None (:attr:`global_voxel` derives it from the target)."""

    src: PreparedScan
    tgt: PreparedScan
    counts: PointCounts = PointCounts()
    voxel: float | None = None

    @classmethod
    def of(cls, src: np.ndarray, tgt: np.ndarray, counts: PointCounts = PointCounts(),
           device: torch.device = CPU, scan_device: torch.device | None = None) -> "ScanPair":
        """src (N, 3), tgt (M, 3) arrays -> a pair prepared on ``device``, the whole scans' steps on
        ``scan_device`` (None: ``device``)."""
        return cls(PreparedScan(np.asarray(src, dtype=np.float64), device, scan_device),
                   PreparedScan(np.asarray(tgt, dtype=np.float64), device, scan_device), counts)

    @property
    def device(self) -> torch.device:
        return self.tgt.device

    @property
    def scans_on_device(self) -> bool:
        """Whether the steps that read whole scans run on :attr:`device`."""
        return self.tgt.scan_device in (None, self.tgt.device)

    @cached_property
    def global_voxel(self) -> float:
        """The voxel edge that leaves the target about ``counts.global_points`` points (the global
        estimators' feature radii are multiples of it), unless fixed by ``voxel``."""
        return self.voxel if self.voxel is not None else self.tgt.edge_for(self.counts.global_points)

    def global_views(self) -> tuple[ScanView, ScanView]:
        """Both scans at :attr:`global_voxel`, with their FPFH descriptors."""
        voxel = self.global_voxel
        return self.src.view(voxel), self.tgt.view(voxel)
