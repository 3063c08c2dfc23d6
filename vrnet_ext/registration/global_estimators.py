"""Global estimators: an initial ``T_target_source`` for two scans with no prior, behind one
small interface (:class:`GlobalEstimator`) that :func:`vrnet_ext.registration.register` takes by
name or as an object.

Scans are (N, 3) float arrays in one unit (metres for the shared data); every estimator returns a
:class:`~vrnet_ext.registration.result.RegistrationResult` (``RegistrationResult.global_estimate``:
``T_target_source`` maps source points into the target frame, :mod:`vrnet_ext.geometry.transforms`;
``consensus`` counts the correspondences it agreed on; ``points`` the points it used).

Built in (:data:`GLOBAL_ESTIMATORS`): ``"vrnet"`` (a learned estimate: :class:`SceneNetwork` for a
:class:`~vrnet_ext.model.scene.SceneVRNet`, :class:`ObjectNetwork` for a ModelNet40
:class:`~vrnet_ext.model.VRNet`), ``"fpfh"`` (:class:`FpfhRansac`), ``"fgr"`` (:class:`Fgr`) and
``"sc2"`` (:class:`SpatialConsistency`) and ``"icp"`` (:class:`NoMotion`: ICP alone, from the
identity).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch

from vrnet_ext.model import VRNet
from vrnet_ext.model.scene import SceneVRNet
from vrnet_ext.geometry.preprocessing import subsample, voxel_downsample, voxel_size_for
from vrnet_ext.registration.fgr import fast_global_registration
from vrnet_ext.registration.methods import GLOBAL_ESTIMATORS
from vrnet_ext import ops
from vrnet_ext.geometry.features import nearest_features, voxel_fpfh
from vrnet_ext.registration.ransac import fpfh_ransac, ransac
from vrnet_ext.registration.result import RegistrationResult
from vrnet_ext.geometry.transforms import from_normalised, to_homogeneous

CPU = torch.device("cpu")


class GlobalEstimator:
    """What :func:`~vrnet_ext.registration.register` needs of a global estimate.

    Subclass it (or give any object these attributes): ``name`` labels the result
    (``RegistrationResult.method``); ``also_start_from``: names of built-in estimators whose
    estimates ICP also starts from, the refinement with the higher fitness winning (for estimators
    that may not transfer to a pair, such as a network trained on other data: the result is then
    never worse than theirs); ``memory_profile``: the key of
    :func:`vrnet_ext.registration.budget.plan_registration`'s per-point costs, or None when unknown (a
    ``max_memory`` budget then plans only the ICP stage).
    """

    name: ClassVar[str] = "custom"
    also_start_from: ClassVar[tuple[str, ...]] = ()
    memory_profile: ClassVar[str | None] = None
    memory_scale: ClassVar[float] = 1.0  # per-point cost against the profile's (a larger model costs more)

    def estimate(self, src: np.ndarray, tgt: np.ndarray, seed: int) -> RegistrationResult:
        """src (N, 3), tgt (M, 3) -> :meth:`RegistrationResult.global_estimate` (a bare (4, 4)
        ``T_target_source`` array is accepted from an estimator of one's own); ``seed`` fixes any sampling."""
        raise NotImplementedError


@dataclass
class NoMotion(GlobalEstimator):
    """The identity: ICP alone (scans already roughly aligned)."""

    name: ClassVar[str] = "icp"
    memory_profile: ClassVar[str | None] = "icp"

    def estimate(self, src, tgt, seed):
        return RegistrationResult.global_estimate(np.eye(4), self.name)


def _counts(src: torch.Tensor, tgt: torch.Tensor) -> dict[str, int]:
    return {"source_global": len(src), "target_global": len(tgt)}


def downsampled_pair(src: np.ndarray, tgt: np.ndarray, points: int,
                     device: torch.device = CPU) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Both scans voxel-downsampled to about ``points`` points (the voxel edge chosen on tgt)
    -> (src (N', 3), tgt (M', 3) float64 tensors, voxel edge)."""
    voxel = voxel_size_for(tgt, points)

    def downsampled(cloud: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(voxel_downsample(cloud, voxel), dtype=torch.float64, device=device)

    return downsampled(src), downsampled(tgt), voxel


@dataclass
class _OnDownsampledScans(GlobalEstimator):
    """An estimator that works on both scans voxel-downsampled to about ``points`` points on
    ``device`` (the voxel edge, chosen on the target, sets the feature radii)."""

    points: int = 5000
    device: torch.device = CPU

    def downsampled(self, src: np.ndarray, tgt: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, float]:
        return downsampled_pair(src, tgt, self.points, self.device)


@dataclass
class FpfhRansac(_OnDownsampledScans):
    """FPFH + RANSAC (:mod:`vrnet_ext.registration.ransac`) on the downsampled scans."""

    name: ClassVar[str] = "fpfh"
    memory_profile: ClassVar[str | None] = "fpfh"

    def estimate(self, src, tgt, seed):
        src_down, tgt_down, voxel = self.downsampled(src, tgt)
        T, inliers = fpfh_ransac(src_down, tgt_down, voxel, seed=seed)
        return RegistrationResult.global_estimate(T.cpu().numpy(), self.name, inliers, _counts(src_down, tgt_down))


@dataclass
class Fgr(_OnDownsampledScans):
    """FPFH + Fast Global Registration (:mod:`vrnet_ext.registration.fgr`) on the downsampled scans."""

    name: ClassVar[str] = "fgr"
    memory_profile: ClassVar[str | None] = "fgr"

    def estimate(self, src, tgt, seed):
        src_down, tgt_down, voxel = self.downsampled(src, tgt)
        T = fast_global_registration(src_down, tgt_down, voxel_fpfh(src_down, voxel), voxel_fpfh(tgt_down, voxel),
                                     seed=seed)
        return RegistrationResult.global_estimate(T.cpu().numpy(), self.name, points=_counts(src_down, tgt_down))


@dataclass
class SpatialConsistency(_OnDownsampledScans):
    """FPFH matches filtered by spatial consistency (:func:`vrnet_ext.ops.spatial_consistency`, the
    idea of SC^2-PCR): both scans voxel-downsampled to about ``points`` points, each source point
    matched to its nearest target feature, correspondences compatible when the distances they span
    agree within 2 voxels, inliers within 2 voxels; ``seeds`` fits of ``consensus`` neighbours."""

    seeds: int = 100
    consensus: int = 30
    name: ClassVar[str] = "sc2"
    memory_profile: ClassVar[str | None] = "sc2"

    def estimate(self, src, tgt, seed):
        src_down, tgt_down, voxel = self.downsampled(src, tgt)
        nearest = nearest_features(voxel_fpfh(src_down, voxel), voxel_fpfh(tgt_down, voxel))
        transform, inliers = ops.spatial_consistency(src_down, tgt_down[nearest], 2.0 * voxel, 2.0 * voxel,
                                                     self.seeds, self.consensus)
        if int(inliers.sum()) < 3:
            raise ValueError("spatial consistency found no set of 3 or more consistent FPFH matches: the features "
                             "do not match (try another point count for --global-points)")
        return RegistrationResult.global_estimate(transform.numpy(), self.name, int(inliers.sum()),
                                                  _counts(src_down, tgt_down))


SCENE_PAIRS = 1000  # most confident (source, RCP) pairs the scene model hands to its robust fit
ROBUST_FITS = ("ransac", "sc2", "sc2+fpfh")


@dataclass
class SceneNetwork(GlobalEstimator):
    """The scene model (:mod:`vrnet_ext.model.scene`): both scans voxel-downsampled to about
    ``points`` points, FPFH, VRNet's head, then a robust fit over the ``pairs`` (source point, RCP)
    pairs of highest confidence: ``robust="ransac"`` (inliers within 1.5 voxels), ``"sc2"``
    (spatial consistency, tolerance and inliers 2 voxels, as :class:`SpatialConsistency`) or
    ``"sc2+fpfh"`` (spatial consistency over those pairs and every source point's nearest FPFH
    match together: :class:`SpatialConsistency` with the network's correspondences added). A
    network may not transfer to scans unlike its training pairs, so ICP also starts from the
    default estimator's estimate (spatial consistency) and the better fit wins."""

    model: SceneVRNet
    points: int = 5000
    backend: str = "ext"
    robust: str = "sc2+fpfh"  # chosen on the validation pairs (model card of scene-fpfh-vrnet-real)
    pairs: int = SCENE_PAIRS
    name: ClassVar[str] = "vrnet"
    also_start_from: ClassVar[tuple[str, ...]] = ("sc2",)
    memory_profile: ClassVar[str | None] = "scene"

    def __post_init__(self) -> None:
        if self.robust not in ROBUST_FITS:
            raise ValueError(f"robust must be one of {ROBUST_FITS}, got {self.robust!r}")

    @property
    def memory_scale(self) -> float:
        """This model's per-point cost against the shipped scene model's (the planner's profile)."""
        from vrnet_ext.model.scene import SceneConfig

        return max(1.0, self.model.config.values_per_point() / SceneConfig().values_per_point())

    def estimate(self, src, tgt, seed):
        from vrnet_ext.geometry.features import describe

        voxel = voxel_size_for(tgt, self.points)
        src_view, tgt_view = (describe(voxel_downsample(cloud, voxel), voxel) for cloud in (src, tgt))
        self.model.eval()
        with torch.no_grad():
            out = self.model(src_view.network_points()[None], src_view.descriptors[None],
                             tgt_view.network_points()[None], tgt_view.descriptors[None], backend=self.backend)
        keep = out.confidence_logits[0].argsort(descending=True)[:self.pairs]
        src_points = torch.as_tensor(src_view.points, dtype=torch.float64)
        src_pairs, tgt_pairs = src_points[keep], out.rcp[0, keep].double() * voxel  # (source point, its RCP)
        if self.robust != "ransac":
            if self.robust == "sc2+fpfh":  # and (source point, its nearest target descriptor's point)
                nearest = nearest_features(src_view.descriptors, tgt_view.descriptors)
                src_pairs = torch.cat([src_pairs, src_points])
                tgt_pairs = torch.cat([tgt_pairs, torch.as_tensor(tgt_view.points, dtype=torch.float64)[nearest]])
            T, inliers = ops.spatial_consistency(src_pairs, tgt_pairs, 2.0 * voxel, 2.0 * voxel)
            consensus = int(inliers.sum())
            if consensus < 3:
                raise ValueError("spatial consistency found no set of 3 or more consistent (source, RCP) pairs")
        else:
            pairs = torch.arange(len(keep)).unsqueeze(1).expand(-1, 2)
            T, consensus = ransac(src_pairs, tgt_pairs, pairs, 1.5 * voxel, seed=seed)
        return RegistrationResult.global_estimate(T.cpu().numpy(), self.name, consensus,
                                                  {"source_global": len(src_view.points),
                                                   "target_global": len(tgt_view.points)})


@dataclass
class ObjectNetwork(GlobalEstimator):
    """A ModelNet40 VRNet on scans: both are shifted by the same vector and divided by the same
    factor to the unit sphere it was trained on (a similarity applied to both sides keeps the rigid
    motion recoverable exactly), each subsampled to ``points`` points; the estimate is mapped back
    to the scans' unit. It may not transfer to scans, so ICP also runs from no motion."""

    model: VRNet
    points: int = 1024
    device: torch.device = field(default=CPU)
    backend: str = "ext"
    name: ClassVar[str] = "vrnet"
    also_start_from: ClassVar[tuple[str, ...]] = ("icp",)
    memory_profile: ClassVar[str | None] = "modelnet"

    def estimate(self, src, tgt, seed):
        rng = np.random.default_rng(seed)
        src_small, tgt_small = subsample(src, self.points, rng), subsample(tgt, self.points, rng)
        centre = 0.5 * (src_small.mean(0) + tgt_small.mean(0))
        scale = max(np.linalg.norm(src_small - centre, axis=1).max(),
                    np.linalg.norm(tgt_small - centre, axis=1).max())

        def normalised(points: np.ndarray) -> torch.Tensor:
            return torch.as_tensor((points - centre) / scale, dtype=torch.float32, device=self.device).unsqueeze(0)

        self.model.eval()
        with torch.no_grad():
            out = self.model(normalised(src_small), normalised(tgt_small), backend=self.backend)
        R = out.rotation[0].double().cpu().numpy()
        t_normalised = out.translation[0].double().cpu().numpy()
        return RegistrationResult.global_estimate(to_homogeneous(*from_normalised(R, t_normalised, centre, centre, scale)),
                                                  self.name, len(src_small), {"source_global": len(src_small),
                                                                              "target_global": len(tgt_small)})


def make_global_estimator(method: str, model: VRNet | SceneVRNet | None = None, global_points: int = 5000,
                          network_points: int = 1024, device: torch.device = CPU,
                          backend: str = "ext") -> GlobalEstimator:
    """The built-in estimator called ``method`` (one of :data:`GLOBAL_ESTIMATORS`); ``"vrnet"``
    needs ``model`` (the scene model runs on ``global_points`` points per scan, a ModelNet40 VRNet
    on ``network_points``)."""
    if method not in GLOBAL_ESTIMATORS:
        raise ValueError(f"method must be one of {GLOBAL_ESTIMATORS} or a GlobalEstimator, got {method!r}")
    if model is not None and method != "vrnet":
        raise ValueError(f"model is only used by method 'vrnet', not {method!r}")
    if method == "vrnet":
        if model is None:
            raise ValueError("method 'vrnet' needs a model")
        if isinstance(model, SceneVRNet):
            return SceneNetwork(model, global_points, backend)
        return ObjectNetwork(model, network_points, device, backend)
    if method == "fpfh":
        return FpfhRansac(global_points, device)
    if method == "fgr":
        return Fgr(global_points, device)
    if method == "sc2":
        return SpatialConsistency(global_points, device)
    return NoMotion()
