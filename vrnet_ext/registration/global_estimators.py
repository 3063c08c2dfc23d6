"""Global estimators: an initial ``T_target_source`` for two scans with no prior, behind one
small interface (:class:`GlobalEstimator`) that :func:`vrnet_ext.registration.register` takes by
name or as an object.

Scans are (N, 3) float arrays in one unit (metres for the shared data), prepared once per registration
(:class:`~vrnet_ext.registration.prepared.ScanPair`: the voxels and FPFH every start shares); every
estimator returns a
:class:`~vrnet_ext.registration.result.RegistrationResult` (``RegistrationResult.global_estimate``:
``T_target_source`` maps source points into the target frame, :mod:`vrnet_ext.geometry.transforms`;
``consensus`` counts the correspondences it agreed on; ``points`` the points it used).

Built in (:data:`GLOBAL_ESTIMATORS`): ``"vrnet"`` (a learned estimate: :class:`SceneNetwork` for a
:class:`~vrnet_ext.model.scene.SceneVRNet`, :class:`ObjectNetwork` for a ModelNet40
:class:`~vrnet_ext.model.VRNet`), ``"fpfh"`` (:class:`FpfhRansac`), ``"fgr"`` (:class:`Fgr`) and
``"sc2"`` (:class:`SpatialConsistency`), ``"icp"`` (:class:`NoMotion`: ICP alone, from the
identity), and the default ``"auto"`` (:class:`Adaptive`: spatial consistency, and the others when its
result is doubtful).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Sequence

import numpy as np
import torch

from vrnet_ext.model import VRNet
from vrnet_ext.model.scene import SceneVRNet
from vrnet_ext.geometry.preprocessing import subsample
from vrnet_ext.registration.fgr import fast_global_registration
from vrnet_ext.names import AUTO_MEMBERS, DEFAULT_SCENE_MODEL, GLOBAL_ESTIMATORS
from vrnet_ext.registration.budget import MB, predicted_peak_mb
from vrnet_ext.registration.counts import PointCounts
from vrnet_ext.registration.prepared import ScanPair
from vrnet_ext import ops
from vrnet_ext.geometry.features import ScanView, mutual_of
from vrnet_ext.registration.ransac import SCORING_MB as RANSAC_SCORING_MB, ransac
from vrnet_ext.registration.result import RegistrationResult
from vrnet_ext.geometry.transforms import from_normalised, to_homogeneous

# Peak growth of each estimator's stage, in MB: intercept + bytes per point / MB, fitted as upper bounds
# of each stage's measured peak (benchmarks/bench_memory_plan.py; :mod:`vrnet_ext.registration.budget`).
FPFH_MB, FPFH_BYTES_PER_POINT = 36.0, 1300.0  # normals, FPFH (100 neighbours), matching, RANSAC
GRAPH_MB = 38.0                                # SC2: FPFH + the compatibility graph, one bit per pair of points
FGR_MB, FGR_BYTES_PER_POINT = 48.0, 1150.0    # FPFH + Fast Global Registration's correspondence sets
SCENE_MB, SCENE_BYTES_PER_POINT = 18.0, 21800.0  # FPFH + the scene network's context graph, per point per scan
NETWORK_MB, NETWORK_BYTES_PER_POINT = 40.0, 20000.0  # the ModelNet40 VRNet (streamed matching), per point per cloud
# (NETWORK_*: fitted on whole-process peaks before the stages were measured one by one)


class GlobalEstimator:
    """What :func:`~vrnet_ext.registration.register` needs of a global estimate.

    Subclass it and implement :meth:`estimate` (on two arrays) or :meth:`estimate_pair` (on a
    :class:`~vrnet_ext.registration.prepared.ScanPair`, sharing its voxels and FPFH with the other
    starts). ``name`` labels the result (``RegistrationResult.method``); ``also_start_from``: names of
    built-in estimators whose estimates ICP also starts from, the refinement with the higher fitness
    winning (for estimators that may not transfer to a pair, such as a network trained on other data:
    the result is then never worse than theirs). For a ``max_memory`` budget, ``sized_by`` names the
    :class:`~vrnet_ext.registration.counts.PointCounts` fields its work follows and :meth:`peak_mb`
    states its cost (None: unknown, only ICP is planned).
    """

    name: ClassVar[str] = "custom"
    also_start_from: ClassVar[tuple[str, ...]] = ()
    sized_by: ClassVar[tuple[str, ...]] = ()

    def peak_mb(self, largest_scan: int, counts: PointCounts) -> float | None:
        """How much the process's peak grows while it estimates at ``counts`` (MB, an upper bound),
        on scans of at most ``largest_scan`` points; None when unknown."""
        return None

    def estimate(self, src: np.ndarray, tgt: np.ndarray, seed: int) -> RegistrationResult:
        """src (N, 3), tgt (M, 3) -> :meth:`RegistrationResult.global_estimate` (a bare (4, 4)
        ``T_target_source`` array is accepted from an estimator of one's own); ``seed`` fixes any
        sampling. Built-in estimators prepare the pair with the default point counts."""
        if type(self).estimate_pair is GlobalEstimator.estimate_pair:
            raise NotImplementedError(f"{type(self).__name__} implements neither estimate nor estimate_pair")
        return self.estimate_pair(ScanPair.of(src, tgt), seed)

    def estimate_pair(self, pair: ScanPair, seed: int) -> RegistrationResult:
        """:meth:`estimate` on a prepared pair (what :func:`register` calls)."""
        return self.estimate(pair.src.points, pair.tgt.points, seed)


class NoMotion(GlobalEstimator):
    """The identity: ICP alone (scans already roughly aligned)."""

    name: ClassVar[str] = "icp"

    def peak_mb(self, largest_scan, counts):
        return 0.0

    def estimate_pair(self, pair, seed):
        return RegistrationResult.global_estimate(np.eye(4), self.name)


def _counts(src: ScanView, tgt: ScanView) -> dict[str, int]:
    return {"source_global": len(src.points), "target_global": len(tgt.points)}


def _fpfh_mb(global_points: int) -> float:
    return FPFH_MB + FPFH_BYTES_PER_POINT * global_points / MB


class FpfhRansac(GlobalEstimator):
    """FPFH + RANSAC (:mod:`vrnet_ext.registration.ransac`) on both scans voxel-downsampled to about
    ``PointCounts.global_points`` points (the voxel edge, chosen on the target, sets the radii)."""

    name: ClassVar[str] = "fpfh"
    sized_by: ClassVar[tuple[str, ...]] = ("global_points",)

    def peak_mb(self, largest_scan, counts):
        return max(_fpfh_mb(counts.global_points), RANSAC_SCORING_MB)

    def estimate_pair(self, pair, seed):
        src, tgt = pair.global_views()
        matches = mutual_of(src.nearest_in(tgt), tgt.nearest_in(src))  # the views' matches, shared with sc2
        T, inliers = ransac(src.tensor(), tgt.tensor(), matches, 1.5 * src.voxel, seed=seed)
        return RegistrationResult.global_estimate(T.cpu().numpy(), self.name, inliers, _counts(src, tgt))


class Fgr(GlobalEstimator):
    """FPFH + Fast Global Registration (:mod:`vrnet_ext.registration.fgr`) on both scans
    voxel-downsampled to about ``PointCounts.global_points`` points."""

    name: ClassVar[str] = "fgr"
    sized_by: ClassVar[tuple[str, ...]] = ("global_points",)

    def peak_mb(self, largest_scan, counts):
        return FGR_MB + FGR_BYTES_PER_POINT * counts.global_points / MB

    def estimate_pair(self, pair, seed):
        src, tgt = pair.global_views()
        T = fast_global_registration(src.tensor(), tgt.tensor(), src.descriptors, tgt.descriptors, seed=seed)
        return RegistrationResult.global_estimate(T.cpu().numpy(), self.name, points=_counts(src, tgt))


@dataclass
class SpatialConsistency(GlobalEstimator):
    """FPFH matches filtered by spatial consistency (:func:`vrnet_ext.ops.spatial_consistency`, the
    idea of SC^2-PCR): both scans voxel-downsampled to about ``PointCounts.global_points`` points,
    each source point matched to its nearest target feature, correspondences compatible when the
    distances they span agree within 2 voxels, inliers within 2 voxels; ``seeds`` fits of
    ``consensus`` neighbours. The same fit on the matches its inliers left out measures the rival
    alignment (``rival_consensus``: how many matches agree on the best other alignment; scans that
    repeat themselves, or overlap little, have one nearly as well supported)."""

    seeds: int = 100
    consensus: int = 30
    name: ClassVar[str] = "sc2"
    sized_by: ClassVar[tuple[str, ...]] = ("global_points",)

    def peak_mb(self, largest_scan, counts):
        points = min(counts.global_points, largest_scan)  # the compatibility graph: one bit per pair
        return max(_fpfh_mb(counts.global_points), GRAPH_MB + points * points / 8 / MB)

    def estimate_pair(self, pair, seed):
        src, tgt = pair.global_views()
        transform, inliers, rival = self.fit(src.tensor(), tgt.tensor()[src.nearest_in(tgt)], src.voxel)
        if int(inliers.sum()) < 3:
            raise ValueError("spatial consistency found no set of 3 or more consistent FPFH matches: the features "
                             "do not match (try another global_points)")
        return RegistrationResult.global_estimate(transform.cpu().numpy(), self.name, int(inliers.sum()),
                                                  _counts(src, tgt), rival_consensus=rival)

    def fit(self, src: torch.Tensor, tgt: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor, int]:
        """Matched points src[i] <-> tgt[i] (K, 3), ``voxel`` the unit of the tolerances -> ((4, 4)
        float64 transform, (K,) bool inliers, the inlier count of the same fit on the matches
        those inliers left out: the best other alignment's support, 0 below 3)."""
        transform, inliers = ops.spatial_consistency(src, tgt, 2.0 * voxel, 2.0 * voxel, self.seeds, self.consensus)
        left = ~inliers
        if int(left.sum()) < 3:
            return transform, inliers, 0
        rival = int(ops.spatial_consistency(src[left], tgt[left], 2.0 * voxel, 2.0 * voxel, self.seeds,
                                            self.consensus)[1].sum())
        return transform, inliers, rival if rival >= 3 else 0


SCENE_PAIRS = 1000  # most confident (source, RCP) pairs the scene model hands to its robust fit
ROBUST_FITS = ("ransac", "sc2", "sc2+fpfh")


@dataclass
class SceneNetwork(GlobalEstimator):
    """The scene model (:mod:`vrnet_ext.model.scene`): both scans voxel-downsampled to about
    ``PointCounts.global_points`` points, FPFH, VRNet's head, then a robust fit over the ``pairs``
    (source point, RCP) pairs of highest confidence: ``robust="ransac"`` (inliers within 1.5
    voxels), ``"sc2"`` (spatial consistency, tolerance and inliers 2 voxels, as
    :class:`SpatialConsistency`) or ``"sc2+fpfh"`` (spatial consistency over those pairs and every
    source point's nearest FPFH match together: :class:`SpatialConsistency` with the network's
    correspondences added). A network may not transfer to scans unlike its training pairs, so ICP
    also starts from the default estimator's estimate (spatial consistency, on the same prepared
    scans) and the better fit wins. The model runs on the pair's device."""

    model: SceneVRNet
    backend: str = "ext"
    robust: str = "sc2+fpfh"  # chosen on the validation pairs (model card of scene-fpfh-vrnet-real)
    pairs: int = SCENE_PAIRS
    name: ClassVar[str] = "vrnet"
    also_start_from: ClassVar[tuple[str, ...]] = ("sc2",)
    sized_by: ClassVar[tuple[str, ...]] = ("global_points",)

    def __post_init__(self) -> None:
        if self.robust not in ROBUST_FITS:
            raise ValueError(f"robust must be one of {ROBUST_FITS}, got {self.robust!r}")

    @property
    def memory_scale(self) -> float:
        """This model's per-point cost against the shipped scene model's (a larger model costs more)."""
        from vrnet_ext.model.scene import SceneConfig

        return max(1.0, self.model.config.values_per_point() / SceneConfig().values_per_point())

    def peak_mb(self, largest_scan, counts):
        return SCENE_MB + self.memory_scale * SCENE_BYTES_PER_POINT * counts.global_points / MB

    def estimate_pair(self, pair, seed):
        src_view, tgt_view = pair.global_views()
        voxel = src_view.voxel
        self.model.eval()
        with torch.no_grad():
            out = self.model(src_view.network_points()[None], src_view.descriptors[None],
                             tgt_view.network_points()[None], tgt_view.descriptors[None], backend=self.backend)
        keep = out.confidence_logits[0].argsort(descending=True)[:self.pairs]
        src_points = src_view.tensor()
        src_pairs, tgt_pairs = src_points[keep], out.rcp[0, keep].double() * voxel  # (source point, its RCP)
        if self.robust != "ransac":
            if self.robust == "sc2+fpfh":  # and (source point, its nearest target descriptor's point)
                nearest = src_view.nearest_in(tgt_view)
                src_pairs = torch.cat([src_pairs, src_points])
                tgt_pairs = torch.cat([tgt_pairs, tgt_view.tensor()[nearest]])
            T, inliers = ops.spatial_consistency(src_pairs, tgt_pairs, 2.0 * voxel, 2.0 * voxel)
            consensus = int(inliers.sum())
            if consensus < 3:
                raise ValueError("spatial consistency found no set of 3 or more consistent (source, RCP) pairs")
        else:
            pairs = torch.arange(len(keep), device=src_points.device).unsqueeze(1).expand(-1, 2)
            T, consensus = ransac(src_pairs, tgt_pairs, pairs, 1.5 * voxel, seed=seed)
        return RegistrationResult.global_estimate(T.cpu().numpy(), self.name, consensus, _counts(src_view, tgt_view))


@dataclass
class ObjectNetwork(GlobalEstimator):
    """A ModelNet40 VRNet on scans: both are shifted by the same vector and divided by the same
    factor to the unit sphere it was trained on (a similarity applied to both sides keeps the rigid
    motion recoverable exactly), each subsampled to ``PointCounts.network_points`` points; the
    estimate is mapped back to the scans' unit. It may not transfer to scans, so ICP also runs from
    no motion. The model runs on the pair's device."""

    model: VRNet
    backend: str = "ext"
    name: ClassVar[str] = "vrnet"
    also_start_from: ClassVar[tuple[str, ...]] = ("icp",)
    sized_by: ClassVar[tuple[str, ...]] = ("network_points",)

    def peak_mb(self, largest_scan, counts):
        return NETWORK_MB + NETWORK_BYTES_PER_POINT * counts.network_points / MB

    def estimate_pair(self, pair, seed):
        rng = np.random.default_rng(seed)
        points = pair.counts.network_points
        src_small, tgt_small = subsample(pair.src.points, points, rng), subsample(pair.tgt.points, points, rng)
        centre = 0.5 * (src_small.mean(0) + tgt_small.mean(0))
        scale = max(np.linalg.norm(src_small - centre, axis=1).max(),
                    np.linalg.norm(tgt_small - centre, axis=1).max())

        def normalised(cloud: np.ndarray) -> torch.Tensor:
            return torch.as_tensor((cloud - centre) / scale, dtype=torch.float32, device=pair.device).unsqueeze(0)

        self.model.eval()
        with torch.no_grad():
            out = self.model(normalised(src_small), normalised(tgt_small), backend=self.backend)
        R = out.rotation[0].double().cpu().numpy()
        t_normalised = out.translation[0].double().cpu().numpy()
        T = to_homogeneous(*from_normalised(R, t_normalised, centre, centre, scale))
        return RegistrationResult.global_estimate(T, self.name, len(src_small), {"source_global": len(src_small),
                                                                                 "target_global": len(tgt_small)})


def network_estimator(model: VRNet | SceneVRNet, backend: str = "ext") -> GlobalEstimator:
    """The learned estimator for ``model``: :class:`SceneNetwork` for a scene model, else :class:`ObjectNetwork`."""
    if model is None:
        raise ValueError("method 'vrnet' needs a model")
    return SceneNetwork(model, backend) if isinstance(model, SceneVRNet) else ObjectNetwork(model, backend)


@dataclass
class Adaptive(GlobalEstimator):
    """The default (``"auto"``): the first of ``members`` (spatial consistency) estimates; when the
    refinement from it is doubtful, or the ``checker``'s estimate (RANSAC on the same features)
    does not end where it did (:func:`vrnet_ext.registration.pipeline.register_prepared` says
    when), the others estimate on the same prepared scans too, ICP runs from each, and the best fit
    among the refinements another one confirms wins, else the ``arbiter``'s (the pipeline's
    ``_agreed``). ``model``: the scene model of the ``"vrnet"`` member (default:
    the shipped one, loaded on first need, on the pair's device). A memory budget is planned for the
    first member; the others run only where they fit it."""

    model: SceneVRNet | None = None
    backend: str = "ext"
    name: ClassVar[str] = "auto"
    members: ClassVar[tuple[str, ...]] = AUTO_MEMBERS
    arbiter: ClassVar[str] = "vrnet"  # whose refinement is kept when no two members' refinements agree
    checker: ClassVar[str] = "fpfh"  # whose estimate must land where a confident first refinement did
    sized_by: ClassVar[tuple[str, ...]] = ("global_points",)

    def __post_init__(self) -> None:
        self._built: dict[str, GlobalEstimator] = {}

    def member(self, name: str, device: torch.device | None = None) -> GlobalEstimator:
        """The member estimator ``name``, built on first use (the scene model loaded on ``device``)."""
        if name not in self._built:
            if name == "vrnet" and self.model is None:
                from vrnet_ext.model.pretrained import load_pretrained

                self.model = load_pretrained(DEFAULT_SCENE_MODEL, device or torch.device("cpu"))
            self._built[name] = make_global_estimator(name, self.model if name == "vrnet" else None, self.backend)
        return self._built[name]

    def peak_mb(self, largest_scan, counts):
        """The first member's cost: the others run only when it is doubtful, and under a memory budget
        only where they fit it (:meth:`fallbacks`)."""
        return self.member(self.members[0]).peak_mb(largest_scan, counts)

    def estimate_pair(self, pair, seed):
        """The first member's estimate; where it finds none (ValueError), the next one's: ``start``
        names the member that answered, ``selection`` says which found none and why."""
        failures = []
        for name in self.members:
            try:
                estimate = self.member(name, pair.device).estimate_pair(pair, seed)
            except ValueError as error:
                failures.append(f"{name} found no estimate ({error})")
                continue
            estimate.method, estimate.start, estimate.selection = self.name, name, "; ".join(failures)
            return estimate
        raise ValueError("; ".join(failures))

    def fallbacks(self, pair: ScanPair, budget_bytes: int | None = None,
                  names: Sequence[str] | None = None) -> tuple[dict[str, GlobalEstimator], list[str]]:
        """The members ``names`` (default: all but the first, those that estimate when its refinement
        is doubtful) by name; under a memory budget only those whose predicted peak fits it, with a
        note for each one left out."""
        scans, kept, notes = (len(pair.src.points), len(pair.tgt.points)), {}, []
        for name in (self.members[1:] if names is None else names):
            member = self.member(name, pair.device)
            peak = None if budget_bytes is None else predicted_peak_mb(member, scans, pair.counts, device=pair.device,
                                                                       scans_on_device=pair.scans_on_device)
            if peak is not None and peak > budget_bytes / MB:
                notes.append(f"{name} was not tried: it needs about {peak:.0f} MB, more than max_memory "
                             f"{budget_bytes / MB:.0f} MB")
            else:
                kept[name] = member
        return kept, notes


# The built-in estimators by name (their names, torch-free, in :data:`GLOBAL_ESTIMATORS`); "vrnet" is
# built from a model and a backend, the others from nothing.
BUILT_IN = {"auto": Adaptive, "sc2": SpatialConsistency, "fpfh": FpfhRansac, "vrnet": network_estimator, "fgr": Fgr,
            "icp": NoMotion}


def make_global_estimator(method: str, model: VRNet | SceneVRNet | None = None,
                          backend: str = "ext") -> GlobalEstimator:
    """The built-in estimator called ``method`` (one of :data:`GLOBAL_ESTIMATORS`); ``"vrnet"``
    needs ``model`` and runs it with ``backend``."""
    if method not in BUILT_IN:
        raise ValueError(f"method must be one of {GLOBAL_ESTIMATORS} or a GlobalEstimator, got {method!r}")
    if method == "auto":
        if model is not None and not isinstance(model, SceneVRNet):
            raise ValueError("method 'auto' takes a scene model (SceneVRNet), not a ModelNet40 VRNet; use method 'vrnet'")
        return Adaptive(model, backend)
    if method != "vrnet":
        if model is not None:
            raise ValueError(f"model is only used by method 'vrnet', not {method!r}")
        return BUILT_IN[method]()
    return network_estimator(model, backend)
