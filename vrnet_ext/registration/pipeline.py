"""The registration pipeline of real scans: a global estimate (:mod:`global_estimators`), then
ICP (:mod:`refinement`) on both scans voxel-downsampled, with warnings when the result is doubtful."""
from __future__ import annotations

import time

import numpy as np
import torch

from vrnet_ext.geometry.io import as_points
from vrnet_ext.registration.budget import plan_registration
from vrnet_ext.model import VRNet
from vrnet_ext.model.scene import SceneVRNet
from vrnet_ext.geometry.preprocessing import coarse_in_float32, voxel_downsample, voxel_size_for
from vrnet_ext.registration.global_estimators import GlobalEstimator, make_global_estimator
from vrnet_ext.registration.methods import DEFAULT_METHOD
from vrnet_ext.registration.refinement import COARSE_FACTOR, IcpFailure, IcpProblem, IcpSettings, icp
from vrnet_ext.registration.result import RegistrationResult
from vrnet_ext.geometry.transforms import in_shifted_frames

LOW_FITNESS = 0.2  # below this share of source points with a target point within reach, warn
FITNESS_TIE = 0.005  # refinements whose fitness differs by less converged to the same fit


def _check_count(name: str, value, smallest: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < smallest:
        raise ValueError(f"{name} must be an integer >= {smallest}, got {value!r}")


def _coarse_start(src: np.ndarray, tgt: np.ndarray, voxel: float, reach: float, settings: IcpSettings,
                  device: torch.device, backend: str) -> np.ndarray:
    """ICP from no motion on both scans downsampled ``COARSE_FACTOR`` times coarser, with a reach
    as much longer -> its 4x4 estimate (the identity if it finds no pairs)."""
    coarse = COARSE_FACTOR * voxel
    src_coarse, tgt_coarse = voxel_downsample(src, coarse), voxel_downsample(tgt, coarse)
    if min(len(src_coarse), len(tgt_coarse)) < 3:
        return np.eye(4)
    try:
        return icp(src_coarse, tgt_coarse, np.eye(4), COARSE_FACTOR * reach, settings.max_iterations,
                   settings.transform_tolerance, device, backend, settings.estimator,
                   settings.settled).T_target_source
    except IcpFailure:
        return np.eye(4)


def register(src, tgt, *, method: str | GlobalEstimator | None = None,
             model: VRNet | SceneVRNet | None = None, global_points: int = 5000, network_points: int = 1024,
             icp_settings: IcpSettings = IcpSettings(), seed: int = 0, device: str | torch.device = "cpu",
             backend: str = "ext", max_memory: int | None = None) -> RegistrationResult:
    """Estimates the rigid transform taking src (N, 3) onto tgt (M, 3), both in the same unit.

    src, tgt: numpy arrays or torch tensors of shape (N, 3), objects with a ``points`` attribute
    (an Open3D point cloud) or file paths (:func:`vrnet_ext.geometry.io.as_points`). They are handled in
    float64; when they lie so far from the origin that float32 would blur them (georeferenced
    coordinates: UTM, ~1e6 m), both are shifted by the target's median before any float32
    computation (an estimator object then sees the shifted clouds), and the result is expressed
    in the original frames.

    method: a :class:`GlobalEstimator` object, or the name of a built-in one: ``"sc2"``: FPFH
    matches filtered by spatial consistency on about ``global_points`` points per scan;
    ``"fpfh"``: the same features + RANSAC; ``"vrnet"``: a learned initial
    estimate from ``model`` (a :class:`SceneVRNet` on about ``global_points`` points per scan, or a
    ModelNet40 :class:`VRNet` on ``network_points`` subsampled points; default: the shipped scene
    model); ``"fgr"``: FPFH + Fast Global Registration; ``"icp"``: ICP from no motion. None:
    ``"vrnet"`` when a model is given, else ``"sc2"`` (the default of ``vrnet register`` too).
    icp_settings: the refinement (:class:`IcpSettings`). When the estimator asks for it
    (``also_start_from``: the scene network also starts from ``"sc2"``'s estimate, a ModelNet40 network
    from no motion), ICP runs from each start and the refinement with the higher fitness wins
    (``initial`` is the start it came from, ``start`` names it; a warning says when that was not the
    estimator's own). If ICP finds no pairs within reach, the result
    is the initial estimate with a message in ``warnings``. max_memory: a budget in bytes for the
    process's peak resident memory; the point counts are lowered to fit it
    (:func:`vrnet_ext.registration.budget.plan_registration`, notes in ``warnings``; for a
    GlobalEstimator object only ICP's) or MemoryBudgetError says at once what would fit.
    """
    if not isinstance(icp_settings, IcpSettings):
        raise TypeError(f"icp_settings must be an IcpSettings, got {type(icp_settings).__name__}")
    src, tgt = as_points(src, "src"), as_points(tgt, "tgt")
    shape_notes = _shape_notes(src, "src") + _shape_notes(tgt, "tgt")
    args = (method, model, global_points, network_points, icp_settings, seed, device, backend, max_memory)
    if not _far_from_origin(src, tgt):
        result = _register_centred(src, tgt, *args)
    else:
        centre = np.median(tgt, axis=0)
        result = _register_centred(src - centre, tgt - centre, *args)
        result.T_target_source = in_shifted_frames(result.T_target_source, centre)
        result.initial = in_shifted_frames(result.initial, centre)
    result.warnings = shape_notes + result.warnings
    return result


COLLINEAR = 1e-3  # a cloud whose second principal extent is below this share of its first is a line
SHAPE_SAMPLE = 20_000  # points whose spread judges the shape (evenly strided)


def _shape_notes(points: np.ndarray, name: str) -> list[str]:
    """ValueError when every point of ``points`` (N, 3) coincides; a warning when they lie on a line
    (the rotation about it is then undetermined)."""
    sample = points[:: max(1, len(points) // SHAPE_SAMPLE)]
    spread = np.linalg.svd(sample - sample.mean(axis=0), compute_uv=False)
    if spread[0] <= 1e-12 * max(1.0, float(np.abs(sample).max())):
        raise ValueError(f"{name}: all {len(points)} points coincide; a rigid transform between such clouds "
                         f"is undefined")
    if spread[1] < COLLINEAR * spread[0]:
        return [f"{name} lies on a line: the rotation about that line is undetermined, whatever the fitness says"]
    return []


def _far_from_origin(src: np.ndarray, tgt: np.ndarray) -> bool:
    """Whether float32 coordinates would be too coarse for the target's extent."""
    largest = max(np.abs(src).max(), np.abs(tgt).max())
    return coarse_in_float32(largest, float(np.max(tgt.max(axis=0) - tgt.min(axis=0))))


def _register_centred(src: np.ndarray, tgt: np.ndarray, method, model, global_points: int, network_points: int,
                      icp_settings: IcpSettings, seed: int, device, backend: str,
                      max_memory: int | None) -> RegistrationResult:
    """:func:`register` on clouds near enough to the origin for float32."""
    _check_count("global_points", global_points, 3)
    _check_count("network_points", network_points, 1)
    icp_points, voxel_size = icp_settings.points, icp_settings.voxel_size
    if max_memory is not None and voxel_size is not None:
        raise ValueError("give max_memory or voxel_size, not both (the budget chooses the ICP voxel)")
    device = torch.device(device)
    given = method if method is not None and not isinstance(method, str) else None
    if given is not None:
        if not callable(getattr(given, "estimate", None)):
            raise TypeError(f"method must be a name or a GlobalEstimator, got {type(given).__name__}")
        if model is not None:
            raise ValueError("model is only used by method 'vrnet', not by a GlobalEstimator object")
    else:
        method = method or ("vrnet" if model is not None else DEFAULT_METHOD)
        if method == "vrnet" and model is None:
            from vrnet_ext.model.pretrained import DEFAULT_SCENE_MODEL, load_pretrained

            model = load_pretrained(DEFAULT_SCENE_MODEL, device)
    plan_notes = []
    if max_memory is not None:
        planned = None if given is not None else make_global_estimator(method, model)
        profile = None if planned is None else planned.memory_profile
        scale = 1.0 if planned is None else planned.memory_scale
        plan = plan_registration(max_memory, profile, len(src), len(tgt), global_points, network_points, icp_points,
                                 scale)
        global_points, network_points, icp_points = plan.global_points, plan.network_points, plan.icp_points
        plan_notes = plan.notes
    estimator = given or make_global_estimator(method, model, global_points, network_points, device, backend)
    seconds, start = {}, time.perf_counter()
    estimate = _as_estimate(estimator.name, estimator.estimate(src, tgt, seed))
    initial, consensus = estimate.T_target_source, estimate.consensus
    seconds["initial"] = time.perf_counter() - start
    starts = {estimator.name: initial}
    for name in estimator.also_start_from:
        start = time.perf_counter()
        other = make_global_estimator(name, None, global_points, network_points, device, backend)
        starts[name] = _as_estimate(name, other.estimate(src, tgt, seed)).T_target_source
        seconds[f"initial ({name})"] = time.perf_counter() - start
    points = {"source": len(src), "target": len(tgt), **estimate.points}
    step = icp_settings.estimator
    if icp_settings.max_iterations == 0:
        return RegistrationResult(initial, initial, estimator.name, step, 0, False, float("nan"), float("nan"), 0,
                                  seconds, points, plan_notes, start=estimator.name, consensus=consensus)
    start = time.perf_counter()
    voxel = voxel_size if voxel_size is not None else voxel_size_for(tgt, icp_points)
    src_icp, tgt_icp = voxel_downsample(src, voxel), voxel_downsample(tgt, voxel)
    seconds["downsample"] = time.perf_counter() - start
    points.update(source_icp=len(src_icp), target_icp=len(tgt_icp))
    reach = icp_settings.max_distance if icp_settings.max_distance is not None else 3.0 * voxel
    warnings = list(plan_notes)
    start = time.perf_counter()
    refined, failures = {}, []
    problem = IcpProblem(src_icp, tgt_icp, reach, step, device, backend)  # prepared once for every start
    for name, guess in starts.items():
        try:
            start_at = guess
            if icp_settings.coarse_start and np.array_equal(guess, np.eye(4)):
                start_at = _coarse_start(src, tgt, voxel, reach, icp_settings, device, backend)
            refined[name] = problem.run(start_at, icp_settings.max_iterations, icp_settings.transform_tolerance,
                                        icp_settings.settled)
            refined[name].initial = guess
        except IcpFailure as failure:
            failures.append(f"{failure} (from {_label(name)})")
    seconds["icp"] = time.perf_counter() - start
    if not refined:
        warnings.append(f"{'; '.join(failures)}; returning the unrefined initial estimate")
        return RegistrationResult(initial, initial, estimator.name, step, 0, False, 0.0, float("nan"), 0, seconds,
                                  points, warnings, start=estimator.name, consensus=consensus)
    winner = max(refined, key=lambda name: (refined[name].fitness, -refined[name].inlier_rmse))
    if estimator.name in refined and refined[estimator.name].fitness >= refined[winner].fitness - FITNESS_TIE:
        winner = estimator.name  # the estimator's own start unless another fits clearly better
    best = refined[winner]
    if winner != estimator.name:
        own = estimator.name
        from_own = f"fitness {refined[own].fitness:.1%}" if own in refined else "no pairs within reach"
        warnings.append(f"{_label(own)} does not fit these scans (ICP from it: {from_own}; from "
                        f"{_label(winner)}: {best.fitness:.1%}); returning the refinement that started from "
                        f"{_label(winner)}")
    if not best.converged:
        warnings.append(f"ICP did not converge within {icp_settings.max_iterations} iterations (raise "
                        f"IcpSettings.max_iterations)")
    if best.fitness < LOW_FITNESS:
        warnings.append(f"low fitness: only {best.fitness:.1%} of the source points have a target point within "
                        f"{reach:.3g}; the scans may overlap little or the result may be wrong")
    return RegistrationResult(best.T_target_source, best.initial, estimator.name, step, best.iterations,
                              best.converged, best.fitness, best.inlier_rmse, best.correspondences, seconds, points,
                              warnings, start=winner,
                              consensus=consensus)


def _as_estimate(name: str, value) -> RegistrationResult:
    """A global estimator's answer as a :class:`RegistrationResult` (a bare 4x4 array, as an estimator
    of one's own may return, becomes one); ValueError unless it holds a finite 4x4 transform."""
    if not isinstance(value, RegistrationResult):
        value = RegistrationResult.global_estimate(np.asarray(value, dtype=np.float64), name)
    T = value.T_target_source
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"the {name} estimator returned no finite 4x4 transform (shape {T.shape})")
    return value


def _label(name: str) -> str:
    """How a start is named in warnings."""
    return "no motion" if name == "icp" else f"the {name} estimate"
