"""The registration pipeline of real scans: the global estimator built once, a memory plan, both
scans prepared once (:class:`~vrnet_ext.registration.prepared.ScanPair`), a global estimate
(:mod:`global_estimators`) and any further starts, then ICP (:mod:`refinement`) from each on both
scans voxel-downsampled, with warnings when the result is doubtful."""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from vrnet_ext.geometry.io import as_points
from vrnet_ext.geometry.preprocessing import coarse_in_float32
from vrnet_ext.geometry.transforms import in_shifted_frames
from vrnet_ext.model import VRNet
from vrnet_ext.model.scene import SceneVRNet
from vrnet_ext.registration.budget import device_memory_cap, plan_registration
from vrnet_ext.registration.global_estimators import GlobalEstimator, make_global_estimator
from vrnet_ext.names import DEFAULT_METHOD
from vrnet_ext.registration.counts import PointCounts
from vrnet_ext.registration.prepared import ScanPair
from vrnet_ext.registration.refinement import COARSE_FACTOR, IcpFailure, IcpProblem, IcpSettings, icp
from vrnet_ext.registration.result import RegistrationResult

LOW_FITNESS = 0.2  # below this share of source points with a target point within reach, warn
SPARSE = 1.5  # a reach below this many point spacings of the target cannot judge the overlap
FITNESS_TIE = 0.005  # refinements whose fitness differs by less converged to the same fit
ESTIMATE_SLACK = 2.0  # global voxels a robust fit's estimate may lie from the refinement it agrees with (its inlier bound)
AMBIGUOUS = 0.4  # a rival alignment with this share of the estimate's consistent matches: warn (calibrated)
WHOLE_FIT = 0.9  # a refinement fitting this share of the source explains about all of it (no small overlap slid)


@dataclass(frozen=True)
class RegistrationRun:
    """The settings of :func:`register`, resolved once (:meth:`of`): the global estimator (built
    once), the point counts asked for, the refinement, the seed, where and how to compute, the
    memory budget. Registering many pairs with one run (:func:`register_prepared`) builds the
    estimator (and loads a model) once."""

    estimator: GlobalEstimator
    counts: PointCounts
    icp: IcpSettings
    seed: int
    device: torch.device
    backend: str
    max_memory: int | None

    @classmethod
    def of(cls, *, method: str | GlobalEstimator | None = None, model: VRNet | SceneVRNet | None = None,
           global_points: int = PointCounts.global_points, network_points: int = PointCounts.network_points,
           icp_settings: IcpSettings = IcpSettings(), seed: int = 0, device: str | torch.device = "cpu",
           backend: str = "ext", max_memory: int | None = None) -> "RegistrationRun":
        """The arguments of :func:`register` (same names, same meaning) checked and resolved."""
        _require_icp_settings(icp_settings)
        counts = PointCounts(global_points=global_points, network_points=network_points,
                             icp_points=icp_settings.points)
        if max_memory is not None and icp_settings.voxel_size is not None:
            raise ValueError("give max_memory or voxel_size, not both (the budget chooses the ICP voxel)")
        device = torch.device(device)
        return cls(estimator=_global_estimator(method, model, device, backend), counts=counts, icp=icp_settings,
                   seed=seed, device=device, backend=backend, max_memory=max_memory)


def register(src, tgt, *, method: str | GlobalEstimator | None = None,
             model: VRNet | SceneVRNet | None = None, global_points: int = PointCounts.global_points,
             network_points: int = PointCounts.network_points, icp_settings: IcpSettings = IcpSettings(),
             seed: int = 0, device: str | torch.device = "cpu", backend: str = "ext",
             max_memory: int | None = None) -> RegistrationResult:
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
    model); ``"fgr"``: FPFH + Fast Global Registration; ``"icp"``: ICP from no motion; ``"auto"``:
    ``"sc2"``, checked by ``"fpfh"``'s estimate (it must land where ICP from ``"sc2"`` ended); when
    ``"sc2"`` finds no estimate, ICP from it is doubtful (:func:`doubt`) or the check lands
    elsewhere, ``"fpfh"`` and ``"vrnet"`` too, ICP from each and the best fit that another confirms
    kept, else ``"vrnet"``'s unless another fits :data:`WHOLE_FIT` of the source (``selection`` says
    why; a scene ``model`` is used for its ``"vrnet"``). None: ``"vrnet"`` when a model is given,
    else ``"auto"`` (the default of ``vrnet register`` too).
    icp_settings: the refinement (:class:`IcpSettings`). When the estimator asks for it
    (``also_start_from``: the scene network also starts from ``"sc2"``'s estimate, a ModelNet40 network
    from no motion), ICP runs from each start and the refinement with the higher fitness wins
    (``initial`` is the start it came from, ``start`` names it; a warning says when that was not the
    estimator's own). Every start shares one preparation of each scan (voxels, FPFH: a
    :class:`~vrnet_ext.registration.prepared.ScanPair`). If ICP finds no pairs within reach, the result
    is the initial estimate with a message in ``warnings``. max_memory: a budget in bytes for the
    process's peak resident memory (on a CUDA ``device``: for its peak on that GPU); the point counts
    are lowered to fit it (:func:`vrnet_ext.registration.budget.plan_registration` with the estimator's
    own cost, :meth:`GlobalEstimator.peak_mb`; on a GPU the whole scans' steps run on the host where
    they would not fit; notes in ``warnings``) or MemoryBudgetError says at once what would fit; on
    the CPU, from then on the process gives the memory it frees back to the system
    (:func:`vrnet_ext.registration.budget.return_freed_memory`, glibc's allocator setting); on a GPU
    its allocator is capped at the budget for the run (:func:`~vrnet_ext.registration.budget.device_memory_cap`).
    """
    _require_icp_settings(icp_settings)
    src, tgt = as_points(src, "src"), as_points(tgt, "tgt")
    shape_notes = _shape_notes(src, "src") + _shape_notes(tgt, "tgt")
    run = RegistrationRun.of(method=method, model=model, global_points=global_points, network_points=network_points,
                             icp_settings=icp_settings, seed=seed, device=device, backend=backend,
                             max_memory=max_memory)
    if not _far_from_origin(src, tgt):
        result = _register_centred(src, tgt, run)
    else:
        centre = np.median(tgt, axis=0)
        result = _register_centred(src - centre, tgt - centre, run)
        result.T_target_source = in_shifted_frames(result.T_target_source, centre)
        result.initial = in_shifted_frames(result.initial, centre)
    result.warnings = shape_notes + result.warnings
    return result


def _require_icp_settings(value) -> None:
    if not isinstance(value, IcpSettings):
        raise TypeError(f"icp_settings must be an IcpSettings, got {type(value).__name__}")


def _global_estimator(method, model, device: torch.device, backend: str) -> GlobalEstimator:
    """The estimator object :func:`register` was given, or the built-in one it names (built here,
    once; ``"vrnet"`` without a model loads the shipped scene model)."""
    if method is not None and not isinstance(method, str):
        if not callable(getattr(method, "estimate", None)):
            raise TypeError(f"method must be a name or a GlobalEstimator, got {type(method).__name__}")
        if model is not None:
            raise ValueError("model is only used by method 'vrnet', not by a GlobalEstimator object")
        return method
    method = method or ("vrnet" if model is not None else DEFAULT_METHOD)
    if method == "vrnet" and model is None:
        from vrnet_ext.model.pretrained import DEFAULT_SCENE_MODEL, load_pretrained

        model = load_pretrained(DEFAULT_SCENE_MODEL, device)
    return make_global_estimator(method, model, backend)


COLLINEAR = 1e-3  # a cloud whose second principal extent is below this share of its first is a line
SHAPE_SAMPLE = 20_000  # points whose spread judges the shape (evenly strided)


def _shape_notes(points: np.ndarray, name: str) -> list[str]:
    """ValueError naming the argument when every point of ``points`` (N, 3) coincides; a warning when
    they lie on a line (the rotation about it is then undetermined). The line is judged on the
    points nearest their median (all but the farthest 1 %): one stray point far away does not make
    a scan a line."""
    if not (points != points[0]).any():  # (an axis-0 min / max takes ten times longer on (N, 3) rows)
        raise ValueError(f"{name}: all {len(points)} points coincide; a rigid transform between such clouds "
                         f"is undefined")
    sample = points[:: max(1, len(points) // SHAPE_SAMPLE)]
    distance = np.linalg.norm(sample - np.median(sample, axis=0), axis=1)
    core = sample[distance <= np.quantile(distance, 0.99)]
    spread = np.linalg.svd(core - core.mean(axis=0), compute_uv=False)
    if len(spread) > 1 and spread[1] < COLLINEAR * spread[0]:
        return [f"{name} lies on a line: the rotation about that line is undetermined, whatever the fitness says"]
    return []


def _far_from_origin(src: np.ndarray, tgt: np.ndarray) -> bool:
    """Whether float32 coordinates would be too coarse for the target's extent."""
    largest = max(-src.min(), src.max(), -tgt.min(), tgt.max())  # (no |x| copy of the scans)
    return coarse_in_float32(largest, float(np.max(tgt.max(axis=0) - tgt.min(axis=0))))


def _register_centred(src: np.ndarray, tgt: np.ndarray, run: RegistrationRun) -> RegistrationResult:
    """:func:`register` on clouds near enough to the origin for float32."""
    counts, warnings, scan_device = run.counts, [], run.device
    if run.max_memory is not None:
        plan = plan_registration(run.max_memory, run.estimator, len(src), len(tgt), counts, run.device)
        counts, warnings = plan.counts, list(plan.notes)
        scan_device = run.device if plan.scans_on_device else torch.device("cpu")
    with device_memory_cap(run.device, run.max_memory):
        result = register_prepared(ScanPair.of(src, tgt, counts, run.device, scan_device), run)
    result.warnings = warnings + result.warnings
    return result


def register_prepared(pair: ScanPair, run: RegistrationRun) -> RegistrationResult:
    """The global estimate and ICP of :func:`register` on a pair already prepared (its clouds near
    the origin, its point counts fitted to any budget): many registrations between a set of scans
    share each scan's preparation this way. With the default estimator (``"auto"``), a doubtful
    refinement (:func:`doubt`), or one its checker does not land on (:func:`_cross_check`), brings in
    the others, those that fit ``run.max_memory``."""
    src, tgt, warnings = pair.src.points, pair.tgt.points, []
    seconds: dict[str, float] = {}
    estimate, starts = _global_starts(pair, run, seconds)
    name, step = getattr(run.estimator, "name", GlobalEstimator.name), run.icp.step
    own = next(iter(starts))
    points = {"source": len(src), "target": len(tgt), **estimate.points}
    matches = dict(consensus=estimate.consensus, rival_consensus=estimate.rival_consensus)
    unrefined = dict(T_target_source=estimate.T_target_source, initial=estimate.T_target_source, method=name,
                     icp_step=step, iterations=0, converged=False, inlier_rmse=float("nan"), correspondences=0,
                     seconds=seconds, points=points, warnings=warnings, start=own, **matches)
    if run.icp.max_iterations == 0:
        warnings += _rival_note(estimate)
        return RegistrationResult(fitness=float("nan"), **unrefined)
    problem = _icp_problem(pair, run, seconds, points)
    refined, failures = _refine(problem, pair, starts, run, seconds)
    selection = ""
    if hasattr(run.estimator, "fallbacks"):
        reason, checked = estimate.selection or doubt(refined.get(own)), ()
        checker = getattr(run.estimator, "checker", None)
        if reason is None and checker is not None:
            check, _ = run.estimator.fallbacks(pair, run.max_memory, (checker,))
            if check:
                checked = (checker,)
                reason, more = _cross_check(problem, pair, run, seconds, first=refined[own], checker=checker,
                                            estimator=check[checker])
                refined.update(more)
        if reason:
            members = run.estimator.members  # (those before ``own`` found no estimate)
            fallbacks, left_out = run.estimator.fallbacks(pair, run.max_memory, [
                member for member in members[members.index(own) + 1:] if member not in checked])
            warnings += left_out
            others = _fallback_starts(fallbacks, pair, run, seconds)
            more, more_failures = _refine(problem, pair, others, run, seconds)
            refined.update(more)
            failures += more_failures
            selection = (f"{reason}; " if estimate.selection else f"{own} {reason}; ") if refined else ""
    if not refined:
        warnings.append(f"{'; '.join(failures)}; returning the unrefined initial estimate")
        warnings += _rival_note(estimate)
        return RegistrationResult(fitness=0.0, **unrefined)
    winner = _best_fit(refined, own)
    if selection:
        winner, why, agreed = _agreed(problem, refined, own, getattr(run.estimator, "arbiter", None))
        selection += why
        if not agreed:
            apart = (f"ICP from {', '.join(refined)} ended apart" if len(refined) > 1
                     else f"only {winner}'s estimate could be refined")
            warnings.append(f"no two estimators agree ({apart}): the result may be wrong")
    best = refined[winner]
    if not selection and winner != own:
        from_own = f"fitness {refined[own].fitness:.1%}" if own in refined else "no pairs within reach"
        warnings.append(f"{_label(own)} does not fit these scans (ICP from it: {from_own}; from "
                        f"{_label(winner)}: {best.fitness:.1%}); returning the refinement that started from "
                        f"{_label(winner)}")
    settings = problem.settings
    if not best.converged:
        warnings.append(f"ICP did not converge within {settings.max_iterations} iterations (raise "
                        f"IcpSettings.max_iterations)")
    degenerate = problem.degeneracy(best.T_target_source)
    if degenerate:
        warnings.append(degenerate)
    if best.fitness < LOW_FITNESS:
        warnings.append(_low_fitness_note(best.fitness, settings.max_distance, problem.spacing()))
    if best.fitness < WHOLE_FIT:
        warnings += _rival_note(estimate)
    return RegistrationResult(T_target_source=best.T_target_source, initial=best.initial, method=name, icp_step=step,
                              iterations=best.iterations, converged=best.converged, fitness=best.fitness,
                              inlier_rmse=best.inlier_rmse, correspondences=best.correspondences, seconds=seconds,
                              points=points, warnings=warnings, start=winner, selection=selection, **matches)


def _rival_note(estimate: RegistrationResult) -> list[str]:
    """A warning when another alignment is supported by at least :data:`AMBIGUOUS` times as many
    consistent matches as the global estimate (``rival_consensus``; calibrated on
    ``benchmarks/bench_default.py``'s pairs, where every result below that share was right).
    :func:`register_prepared` leaves it out where the refinement fits :data:`WHOLE_FIT` of the
    source or more: no wrong result of those pairs fitted so much without another warning, and a
    rival there was mostly the scan sliding along its own surfaces (a discretely symmetric object,
    which fits whole either way, is not told apart)."""
    if estimate.consensus <= 0 or estimate.rival_consensus < AMBIGUOUS * estimate.consensus:
        return []
    share = estimate.rival_consensus / estimate.consensus
    return [f"ambiguous: another alignment is supported by {estimate.rival_consensus} consistent feature matches "
            f"against {estimate.consensus} for the global estimate's ({share:.0%}); where scans repeat themselves or "
            f"overlap little, the result may be the wrong one"]


def _best_fit(refined: dict[str, RegistrationResult], own: str) -> str:
    """The start whose refinement fits best; the estimator's own (``own``) unless another fits clearly
    better (by more than :data:`FITNESS_TIE`)."""
    winner = max(refined, key=lambda start: (refined[start].fitness, -refined[start].inlier_rmse))
    if own in refined and refined[own].fitness >= refined[winner].fitness - FITNESS_TIE:
        return own
    return winner


def _agreed(problem: IcpProblem, refined: dict[str, RegistrationResult], own: str,
            arbiter: str | None) -> tuple[str, str, bool]:
    """The refinement to keep when several estimators ran, why, and whether two starts agreed on it:
    the best fit among those where the most other starts ended too (:func:`_same_alignment`); when no
    two agree, ``arbiter``'s (the default's scene model: fitness favours alignments that slide a small
    overlap onto a large surface), unless the best fit explains about the whole source (at least
    :data:`WHOLE_FIT` of it), else the best fit."""
    fits = ", ".join(f"{start} {result.fitness:.1%}" for start, result in refined.items())
    support = {start: [other for other in refined if other != start
                       and _same_alignment(problem, refined[other].T_target_source, refined[start].T_target_source)]
               for start in refined}
    most = max(len(others) for others in support.values())
    if most > 0:
        winner = _best_fit({start: refined[start] for start in refined if len(support[start]) == most}, own)
        return winner, f"refined from each ({fits}): {winner}'s, where {' and '.join(support[winner])} ended too", True
    winner = _best_fit(refined, own)
    if arbiter in refined and refined[winner].fitness < WHOLE_FIT:
        return arbiter, f"refined from each ({fits}): no two ended together; {arbiter}'s, the arbiter's", False
    return winner, f"refined from each ({fits}): no two ended together; the best fit, {winner}'s", False


def _apart(problem: IcpProblem, a: np.ndarray, b: np.ndarray) -> float:
    """The RMS distance between the source's ICP points moved by transform ``a`` and by ``b`` (4, 4)."""
    points = problem.src[0]
    difference = torch.as_tensor(a - b, dtype=points.dtype, device=points.device)
    return float((points @ difference[:3, :3].T + difference[:3, 3]).square().sum(dim=1).mean().sqrt())


def _same_alignment(problem: IcpProblem, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two refinements (4, 4) place the source within ICP's reach of each other."""
    return _apart(problem, a, b) < problem.settings.max_distance


def _cross_check(problem: IcpProblem, pair: ScanPair, run: RegistrationRun, seconds: dict[str, float], *,
                 first: RegistrationResult, checker: str, estimator: GlobalEstimator
                 ) -> tuple[str | None, dict[str, RegistrationResult]]:
    """Whether the first estimator's confident refinement ``first`` is doubtful after all -> (why, or
    None; the refinement from the checker's estimate by its name, when it ran and ended elsewhere).
    A second, independent estimator (``checker``, e.g. RANSAC on the same features) must land where
    ``first`` did: its estimate (within ICP's reach plus :data:`ESTIMATE_SLACK` global voxels: a
    robust fit's own accuracy) or else ICP from it. One that finds no estimate or whose ICP finds no
    pairs says nothing either way. A result both reach from different hypotheses is rarely wrong; one
    they disagree on often is (:func:`register_prepared` then runs every member)."""
    starts = _fallback_starts({checker: estimator}, pair, run, seconds)
    slack = problem.settings.max_distance + ESTIMATE_SLACK * pair.global_voxel
    if checker not in starts or _apart(problem, starts[checker], first.T_target_source) < slack:
        return None, {}
    refined, _ = _refine(problem, pair, starts, run, seconds)
    if checker not in refined or _same_alignment(problem, refined[checker].T_target_source, first.T_target_source):
        return None, {}
    return f"ended apart from ICP from the {checker} estimate", refined


def doubt(refined: RegistrationResult | None) -> str | None:
    """Why the refinement from the default's first estimator is doubtful (the others then run), or
    None: no pairs within reach, ICP not converged, or a fitness below ``LOW_FITNESS``."""
    if refined is None:
        return "found no pairs within reach"
    if not refined.converged:
        return "did not converge"
    if refined.fitness < LOW_FITNESS:
        return f"fits {refined.fitness:.1%} of the source"
    return None


def _fallback_starts(estimators: dict[str, GlobalEstimator], pair: ScanPair, run: RegistrationRun,
                     seconds: dict[str, float]) -> dict[str, np.ndarray]:
    """Each fallback estimator's estimate on the prepared pair, by name (one that fails gives none)."""
    starts = {}
    for other, estimator in estimators.items():
        start = time.perf_counter()
        try:
            starts[other] = _as_estimate(other, estimator.estimate_pair(pair, run.seed)).T_target_source
        except ValueError:
            pass  # e.g. too few consistent matches: the others still run
        seconds[f"initial ({other})"] = time.perf_counter() - start
    return starts


def _global_starts(pair: ScanPair, run: RegistrationRun, seconds: dict[str, float]) -> tuple[RegistrationResult,
                                                                                  dict[str, np.ndarray]]:
    """The estimator's estimate on the prepared pair, and every start ICP runs from (by name: the
    estimator's own, then those of ``also_start_from``, on the same prepared scans); times in ``seconds``."""
    start = time.perf_counter()
    estimator = run.estimator
    name = getattr(estimator, "name", GlobalEstimator.name)
    estimate = _as_estimate(name, _estimate(estimator, pair, run.seed))
    seconds["initial"] = time.perf_counter() - start
    starts = {estimate.start if hasattr(estimator, "members") else name: estimate.T_target_source}
    for other in getattr(estimator, "also_start_from", ()):
        start = time.perf_counter()
        starts[other] = _as_estimate(other, make_global_estimator(other, backend=run.backend)
                                     .estimate_pair(pair, run.seed)).T_target_source
        seconds[f"initial ({other})"] = time.perf_counter() - start
    return estimate, starts


def _estimate(estimator, pair: ScanPair, seed: int):
    """The estimator's answer on the prepared pair (an object that only has ``estimate`` gets the arrays)."""
    if hasattr(estimator, "estimate_pair"):
        return estimator.estimate_pair(pair, seed)
    return estimator.estimate(pair.src.points, pair.tgt.points, seed)


def _icp_problem(pair: ScanPair, run: RegistrationRun, seconds: dict[str, float],
                 points: dict[str, int]) -> IcpProblem:
    """Both scans voxel-downsampled for ICP and prepared once for every start, the reach resolved;
    the ICP point counts go into ``points``."""
    start = time.perf_counter()
    voxel = run.icp.voxel_size if run.icp.voxel_size is not None else pair.tgt.edge_for(pair.counts.icp_points)
    src_icp, tgt_icp = pair.src.downsampled(voxel), pair.tgt.downsampled(voxel)
    points.update(source_icp=len(src_icp), target_icp=len(tgt_icp))
    reach = run.icp.max_distance if run.icp.max_distance is not None else 3.0 * voxel
    problem = IcpProblem(src_icp, tgt_icp, replace(run.icp, voxel_size=voxel, max_distance=reach), run.device,
                         run.backend)
    seconds["downsample"] = time.perf_counter() - start
    return problem


def _refine(problem: IcpProblem, pair: ScanPair, starts: dict[str, np.ndarray], run: RegistrationRun,
            seconds: dict[str, float]) -> tuple[dict[str, RegistrationResult], list[str]]:
    """ICP from every start on the prepared problem -> (refinements by start, failure messages)."""
    start = time.perf_counter()
    refined, failures = {}, []
    for name, guess in starts.items():
        try:
            start_at = guess
            if problem.settings.coarse_start and np.array_equal(guess, np.eye(4)):
                start_at = _coarse_start(pair, problem.settings.voxel_size, problem.settings, run)
            refined[name] = problem.run(start_at)
            refined[name].initial = guess
        except IcpFailure as failure:
            failures.append(f"{failure} (from {_label(name)})")
    seconds["icp"] = seconds.get("icp", 0.0) + time.perf_counter() - start
    return refined, failures


def _coarse_start(pair: ScanPair, voxel: float, settings: IcpSettings, run: RegistrationRun) -> np.ndarray:
    """ICP from no motion on both scans downsampled ``COARSE_FACTOR`` times coarser, with a reach
    as much longer -> its 4x4 estimate (the identity if it finds no pairs)."""
    coarse = COARSE_FACTOR * voxel
    src_coarse, tgt_coarse = pair.src.downsampled(coarse), pair.tgt.downsampled(coarse)
    if min(len(src_coarse), len(tgt_coarse)) < 3:
        return np.eye(4)
    coarse_settings = replace(settings, max_distance=COARSE_FACTOR * settings.max_distance)
    try:
        return icp(src_coarse, tgt_coarse, np.eye(4), coarse_settings, device=run.device,
                   backend=run.backend).T_target_source
    except IcpFailure:
        return np.eye(4)


def _low_fitness_note(fitness: float, reach: float, spacing: float) -> str:
    """The warning for a low fitness: the scans may overlap little or the result be wrong; unless the
    reach is shorter than the clouds' own point spacing (they came downsampled), where the share of
    points within reach says little and a coarser ICP voxel is the remedy."""
    measured = f"only {fitness:.1%} of the source points have a target point within {reach:.3g}"
    if reach < SPARSE * spacing:
        return (f"low fitness: {measured}, less than the target's point spacing ({spacing:.3g}: the clouds came "
                f"downsampled), so the share says little; refine at their resolution with voxel_size={spacing:.2g}")
    return f"low fitness: {measured}; the scans may overlap little or the result may be wrong"


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
