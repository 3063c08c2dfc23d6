"""Registration of real scans: an initial estimate (VRNet on a small subsample, or FPFH + RANSAC
from :mod:`vrnet_ext.global_registration`, or the identity), refined by ICP at full scale.

The network was trained on unit-size ModelNet40 shapes of ~1k points, so a scan pair is first
brought to that scale: both clouds are shifted by the same vector and divided by the same factor
(a similarity applied to both sides keeps the rigid motion recoverable exactly), and each is
subsampled to ``network_points``. The estimate is mapped back to metres and, optionally, refined by
point-to-point ICP on voxel-downsampled clouds (``ops.knn`` grid search + weighted ``ops.kabsch``),
whose memory is O(points) plus a bool occupancy grid of at most 2^24 cells (16 MB) for the reach
test: scans of 100k+ points fit in a few hundred MB.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from vrnet_ext import ops
from vrnet_ext.global_registration import fpfh_ransac, ransac
from vrnet_ext.metrics import rotation_error_deg, translation_error
from vrnet_ext.model import VRNet
from vrnet_ext.model.scene import SceneVRNet
from vrnet_ext.memory_plan import plan_registration
from vrnet_ext.preprocessing import subsample, voxel_downsample, voxel_size_for
from vrnet_ext.registration.estimators import make_estimator
from vrnet_ext.registration.fgr import fast_global_registration
from vrnet_ext.transforms import apply, to_homogeneous


REFERENCE_KNN_ELEMENTS = 1 << 24  # 128 MB of float64 distances per chunk for backend="torch"


class IcpFailure(RuntimeError):
    """ICP found too few point pairs within reach of its starting transform."""


@dataclass
class RegistrationResult:
    """One registration of a source scan onto a target scan (of :func:`register`, or one ICP run).

    ``T_target_source`` (4, 4) maps source points into the target frame (:mod:`vrnet_ext.transforms`);
    ``initial`` is the transform the refinement started from.
    """
    T_target_source: np.ndarray
    initial: np.ndarray
    method: str             # the global estimate: "vrnet", "fpfh", "fgr" or "icp" (none)
    estimator: str          # ICP's step: "point_to_point", "point_to_plane" or "gicp"
    iterations: int         # ICP iterations run (0: no refinement)
    converged: bool         # ICP stopped because the transform stopped changing
    fitness: float          # share of the (downsampled) source points with a target point within reach
    inlier_rmse: float      # in the scans' unit, over those points
    correspondences: int    # how many source points those are
    seconds: dict[str, float] = field(default_factory=dict)
    points: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        out = asdict(self)
        out["T_target_source"] = self.T_target_source.tolist()
        out["initial"] = self.initial.tolist()
        return out


def network_estimate(model: VRNet, src: np.ndarray, tgt: np.ndarray, network_points: int, seed: int,
                     device: torch.device, backend: str = "ext") -> np.ndarray:
    """VRNet's 4x4 estimate for a pair of scans given in metres: src (N, 3), tgt (M, 3)."""
    rng = np.random.default_rng(seed)
    src_small, tgt_small = subsample(src, network_points, rng), subsample(tgt, network_points, rng)
    centre = 0.5 * (src_small.mean(0) + tgt_small.mean(0))
    scale = max(np.linalg.norm(src_small - centre, axis=1).max(), np.linalg.norm(tgt_small - centre, axis=1).max())

    def normalised(points: np.ndarray) -> torch.Tensor:
        return torch.as_tensor((points - centre) / scale, dtype=torch.float32, device=device).unsqueeze(0)

    model.eval()
    with torch.no_grad():
        out = model(normalised(src_small), normalised(tgt_small), backend=backend)
    R = out.rotation[0].double().cpu().numpy()
    t_normalised = out.translation[0].double().cpu().numpy()
    # y_n = R x_n + t_n with p_n = (p - c) / s  =>  y = R x + s t_n + c - R c
    return to_homogeneous(R, scale * t_normalised + centre - R @ centre)


SCENE_PAIRS = 1000  # most confident (source, RCP) pairs the scene model hands to RANSAC


def scene_estimate(model: SceneVRNet, src: np.ndarray, tgt: np.ndarray, points: int, seed: int,
                   backend: str = "ext") -> np.ndarray:
    """4x4 estimate from the scene model (:mod:`vrnet_ext.model.scene`): both scans voxel-downsampled
    to about ``points`` points, FPFH, VRNet's head, then RANSAC (inliers within 1.5 voxels) over
    the ``SCENE_PAIRS`` (source point, RCP) pairs of highest confidence."""
    from vrnet_ext.data.scans import describe

    voxel = voxel_size_for(tgt, points)
    src_view, tgt_view = (describe(voxel_downsample(cloud, voxel), voxel) for cloud in (src, tgt))
    model.eval()
    with torch.no_grad():
        out = model(src_view.network_points()[None], src_view.descriptors[None], tgt_view.network_points()[None],
                    tgt_view.descriptors[None], backend=backend)
    keep = out.confidence_logits[0].argsort(descending=True)[:SCENE_PAIRS]
    src_pairs = torch.as_tensor(src_view.points, dtype=torch.float64)[keep]
    rcp_pairs = out.rcp[0, keep].double() * voxel
    pairs = torch.arange(len(keep)).unsqueeze(1).expand(-1, 2)
    return ransac(src_pairs, rcp_pairs, pairs, 1.5 * voxel, seed=seed)[0].cpu().numpy()


class TargetReach:
    """Which points may have a target point within ``reach``: a conservative test on a grid of
    cells slightly larger than ``reach`` (a point qualifies when one of the 27 cells around its own
    holds a target point), so the nearest-neighbour search skips points that cannot be inliers.
    For the grid kNN those are the slow queries: far from every surface, many empty cells away.

    tgt: (1, M, 3) tensor. Where the grid would need more than ``max_cells`` cells (a small reach
    over a large scene), every point qualifies.
    """

    def __init__(self, tgt: torch.Tensor, reach: float, max_cells: int = 1 << 24) -> None:
        self.cell = reach * (1.0 + 1e-6)  # a pair within reach is never two cells apart, rounding included
        self.origin = tgt[0].amin(0) - self.cell  # one empty layer of cells around the target
        cells = torch.floor((tgt[0] - self.origin) / self.cell).long()
        shape = (cells.amax(0) + 2).tolist()
        self.grid = None
        if shape[0] * shape[1] * shape[2] <= max_cells:
            occupied = torch.zeros(shape, dtype=torch.bool, device=tgt.device)
            occupied[cells.unbind(1)] = True
            self.grid = _dilate(occupied)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """points (1, N, 3) -> (N,) bool, False only where no target point is within ``reach``."""
        if self.grid is None:
            return torch.ones(points.shape[1], dtype=torch.bool, device=points.device)
        cells = torch.floor((points[0] - self.origin) / self.cell)
        shape = torch.tensor(self.grid.shape, dtype=cells.dtype, device=cells.device)
        inside = ((cells >= 0) & (cells < shape)).all(1)
        allowed = torch.zeros(points.shape[1], dtype=torch.bool, device=points.device)
        allowed[inside] = self.grid[cells[inside].long().unbind(1)]
        return allowed


def _dilate(occupied: torch.Tensor) -> torch.Tensor:
    """(X, Y, Z) bool grid -> the same grid with every cell next to (26-neighbourhood) a set cell set."""
    for axis in range(3):
        grown = occupied.clone()
        length = occupied.shape[axis] - 1
        grown.narrow(axis, 1, length).logical_or_(occupied.narrow(axis, 0, length))
        grown.narrow(axis, 0, length).logical_or_(occupied.narrow(axis, 1, length))
        occupied = grown
    return occupied


def _nearest_in_reach(moved: torch.Tensor, tgt: torch.Tensor, reach: TargetReach,
                      backend: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest target neighbour of the points of ``moved`` (1, N, 3) that ``reach`` lets through:
    -> (their indices into moved (P,), squared distances (P,), target indices (P,)); P may be 0."""
    candidates = reach(moved).nonzero().squeeze(1)
    if len(candidates) == 0:
        return candidates, moved.new_empty(0), candidates
    # The reference kNN builds a (queries x targets) matrix: feed it chunks of at most
    # REFERENCE_KNN_ELEMENTS entries (the compiled grid search needs O(N) memory and takes all at once).
    chunk = len(candidates) if backend == "ext" else max(1, REFERENCE_KNN_ELEMENTS // tgt.shape[1])
    dist2, idx = [], []
    for start in range(0, len(candidates), chunk):
        d, i = ops.knn(moved[:, candidates[start:start + chunk]], tgt, 1, backend=backend)
        dist2.append(d[0, :, 0])
        idx.append(i[0, :, 0])
    return candidates, torch.cat(dist2), torch.cat(idx)


def _downsampled_pair(src: np.ndarray, tgt: np.ndarray, points: int,
                      device: torch.device) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Both scans voxel-downsampled to about ``points`` points (the voxel edge chosen on tgt)."""
    voxel = voxel_size_for(tgt, points)

    def downsampled(cloud: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(voxel_downsample(cloud, voxel), dtype=torch.float64, device=device)

    return downsampled(src), downsampled(tgt), voxel


def fpfh_estimate(src: np.ndarray, tgt: np.ndarray, points: int, seed: int,
                  device: torch.device = torch.device("cpu")) -> np.ndarray:
    """4x4 estimate from FPFH + RANSAC (:mod:`vrnet_ext.global_registration`) on both scans
    voxel-downsampled to about ``points`` points (the voxel edge sets the feature radii)."""
    src_down, tgt_down, voxel = _downsampled_pair(src, tgt, points, device)
    return fpfh_ransac(src_down, tgt_down, voxel, seed=seed)[0].cpu().numpy()


def fgr_estimate(src: np.ndarray, tgt: np.ndarray, points: int, seed: int,
                 device: torch.device = torch.device("cpu")) -> np.ndarray:
    """4x4 estimate from FPFH + Fast Global Registration (:mod:`vrnet_ext.registration.fgr`) on
    both scans voxel-downsampled to about ``points`` points (FPFH within 5 voxels)."""
    src_down, tgt_down, voxel = _downsampled_pair(src, tgt, points, device)
    src_features = ops.fpfh(src_down, ops.normals(src_down), 5.0 * voxel)
    tgt_features = ops.fpfh(tgt_down, ops.normals(tgt_down), 5.0 * voxel)
    return fast_global_registration(src_down, tgt_down, src_features, tgt_features, seed=seed).cpu().numpy()


def icp(src: np.ndarray, tgt: np.ndarray, initial: np.ndarray, max_distance: float, iterations: int = 50,
        tolerance: float = 1e-6, device: torch.device = torch.device("cpu"), backend: str = "ext",
        estimator: str = "point_to_point", settled: float = 1e-6) -> RegistrationResult:
    """ICP: nearest target neighbour of each moved source point, pairs farther than ``max_distance``
    get weight 0, then one step of ``estimator`` (:mod:`vrnet_ext.registration.estimators`:
    point_to_point, point_to_plane, gicp). Converged when a step changes the transform by less than
    ``tolerance`` (rotation in radians, translation in metres), or when the fitness (a share) and the
    inlier RMSE (in the scans' unit) of the correspondences both change by less than ``settled``
    from one iteration to the next (Open3D's ICPConvergenceCriteria: the pairs have settled). At most
    ``iterations`` steps. Points that :class:`TargetReach` rules out are not searched (they would
    get weight 0 anyway).

    Returns a :class:`RegistrationResult` (method "icp"); raises IcpFailure when fewer than 3 pairs
    are within reach.
    """
    src_t = torch.as_tensor(src, dtype=torch.float64, device=device).unsqueeze(0)
    tgt_t = torch.as_tensor(tgt, dtype=torch.float64, device=device).unsqueeze(0)
    step = make_estimator(estimator)
    step.prepare(src_t[0], tgt_t[0])
    reach = TargetReach(tgt_t, max_distance)
    T = torch.as_tensor(initial, dtype=torch.float64, device=device)
    done, converged, previous = 0, False, None
    while done < iterations:
        moved = apply(T, src_t)
        candidates, dist2, idx = _nearest_in_reach(moved, tgt_t, reach, backend)
        inliers = (dist2 <= max_distance ** 2).to(src_t.dtype)
        count = int(inliers.sum())
        if count < 3:
            raise IcpFailure(f"ICP: fewer than 3 point pairs within max_distance={max_distance:g} of the initial "
                             "estimate (too far off; raise max_distance or check the inputs)")
        current = (count / src_t.shape[1], float((dist2 * inliers).sum() / count) ** 0.5)
        if previous is not None and abs(current[0] - previous[0]) < settled and abs(current[1] - previous[1]) < settled:
            converged = True
            break
        previous = current
        new = step.step(T, candidates, idx, inliers)
        done += 1
        change_rotation = torch.linalg.matrix_norm(new[:3, :3] - T[:3, :3]).item()
        change_translation = torch.linalg.vector_norm(new[:3, 3] - T[:3, 3]).item()
        T = new
        if change_rotation < tolerance and change_translation < tolerance:
            converged = True
            break
    _, dist2, _ = _nearest_in_reach(apply(T, src_t), tgt_t, reach, backend)
    close = dist2[dist2 <= max_distance ** 2]
    rmse = float(close.mean().sqrt()) if len(close) else float("nan")
    return RegistrationResult(T.cpu().numpy(), np.asarray(initial, dtype=np.float64), "icp", estimator, done,
                              converged, len(close) / src_t.shape[1], rmse, len(close),
                              points={"source": len(src), "target": len(tgt)})


LOW_FITNESS = 0.2  # below this share of source points with a target point within reach, warn


def fitness(src: np.ndarray, tgt: np.ndarray, transform: np.ndarray, reach: float, backend: str = "ext") -> float:
    """Share of the points of src (N, 3), moved by the 4x4 ``transform``, that have a point of
    tgt (M, 3) within ``reach``: a score of any transform on a pair (Open3D's fitness)."""
    src_t = torch.as_tensor(src, dtype=torch.float64).unsqueeze(0)
    tgt_t = torch.as_tensor(tgt, dtype=torch.float64).unsqueeze(0)
    T = torch.as_tensor(transform, dtype=torch.float64)
    _, dist2, _ = _nearest_in_reach(apply(T, src_t), tgt_t, TargetReach(tgt_t, reach), backend)
    return int((dist2 <= reach ** 2).sum()) / len(src)


METHODS = ("vrnet", "fpfh", "fgr", "icp")


@dataclass(frozen=True)
class IcpSettings:
    """How :func:`register` refines its global estimate (each field is a ``vrnet register`` flag).

    estimator: the step (:mod:`vrnet_ext.registration.estimators`); points: both scans are
    voxel-downsampled to about this many points (``voxel_size`` overrides); max_distance: the
    inlier reach (default 3 voxels); max_iterations: at most this many steps (0: no ICP); it stops
    earlier once a step moves the transform by less than ``transform_tolerance`` or the fitness and
    inlier RMSE change by less than ``settled`` (see :func:`icp`).
    """

    estimator: str = "point_to_plane"
    points: int = 50_000
    voxel_size: float | None = None
    max_distance: float | None = None
    max_iterations: int = 50
    transform_tolerance: float = 1e-6
    settled: float = 1e-6

    def __post_init__(self) -> None:
        make_estimator(self.estimator)  # ValueError naming the estimator
        for name in ("points", "max_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < (name == "points"):
                raise ValueError(f"IcpSettings.{name} must be an integer >= {int(name == 'points')}, got {value!r}")
        for name in ("voxel_size", "max_distance", "transform_tolerance", "settled"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"IcpSettings.{name} must be a finite number > 0"
                                 f"{' (or None for the default)' if name in ('voxel_size', 'max_distance') else ''}, "
                                 f"got {value!r}")


def register(src: np.ndarray, tgt: np.ndarray, *, method: str | None = None,
             model: VRNet | SceneVRNet | None = None, global_points: int = 5000, network_points: int = 1024,
             icp_settings: IcpSettings = IcpSettings(), seed: int = 0, device: str | torch.device = "cpu",
             backend: str = "ext", max_memory: int | None = None) -> RegistrationResult:
    """Estimates the rigid transform taking src (N, 3) onto tgt (M, 3), both in the same unit.

    method: ``"vrnet"``: a learned initial estimate from ``model`` (a :class:`SceneVRNet` on about
    ``global_points`` points per scan, or a ModelNet40 :class:`VRNet` on ``network_points``
    subsampled points; default: the shipped scene model); ``"fpfh"``: FPFH features + RANSAC on
    about ``global_points`` points per scan; ``"fgr"``: the same features + Fast Global
    Registration; ``"icp"``: ICP from no motion. None: ``"vrnet"`` when a model is given, else
    ``"icp"``. icp_settings: the refinement (:class:`IcpSettings`). With a ModelNet40 network, ICP
    runs from its estimate and from no motion, and the refinement with the higher fitness wins
    (``initial`` is then the start it came from; a warning says when that was not the network's).
    If ICP finds no pairs within reach, the result is the initial estimate with a message in
    ``warnings``. max_memory: a budget in bytes for the process's peak resident memory; the point
    counts are lowered to fit it (:func:`vrnet_ext.memory_plan.plan_registration`, notes in
    ``warnings``) or MemoryBudgetError says at once what would fit.
    """
    method = method or ("vrnet" if model is not None else "icp")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if model is not None and method != "vrnet":
        raise ValueError(f"model is only used by method 'vrnet', not {method!r}")
    if not isinstance(icp_settings, IcpSettings):
        raise TypeError(f"icp_settings must be an IcpSettings, got {type(icp_settings).__name__}")
    for name, value in (("global_points", global_points), ("network_points", network_points)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if global_points < 3:
        raise ValueError(f"global_points must be at least 3, got {global_points}")
    icp_points, voxel_size = icp_settings.points, icp_settings.voxel_size
    if max_memory is not None and voxel_size is not None:
        raise ValueError("give max_memory or voxel_size, not both (the budget chooses the ICP voxel)")
    if method == "vrnet" and model is None:
        from vrnet_ext.pretrained import DEFAULT_SCENE_MODEL, load_pretrained

        model = load_pretrained(DEFAULT_SCENE_MODEL, device)
    plan_notes = []
    if max_memory is not None:
        learned = None if method != "vrnet" else "scene" if isinstance(model, SceneVRNet) else "modelnet"
        plan = plan_registration(max_memory, method, learned, len(src), len(tgt), global_points, network_points,
                                 icp_points)
        global_points, network_points, icp_points = plan.global_points, plan.network_points, plan.icp_points
        plan_notes = plan.notes
    device = torch.device(device)
    seconds, start = {}, time.perf_counter()
    initial = np.eye(4)
    if isinstance(model, SceneVRNet):
        initial = scene_estimate(model, src, tgt, global_points, seed, backend)
    elif model is not None:
        initial = network_estimate(model, src, tgt, network_points, seed, device, backend)
    elif method == "fpfh":
        initial = fpfh_estimate(src, tgt, global_points, seed, device)
    elif method == "fgr":
        initial = fgr_estimate(src, tgt, global_points, seed, device)
    seconds["initial"] = time.perf_counter() - start
    points = {"source": len(src), "target": len(tgt)}
    estimator = icp_settings.estimator
    if icp_settings.max_iterations == 0:
        return RegistrationResult(initial, initial, method, estimator, 0, False, float("nan"), float("nan"), 0,
                                  seconds, points, plan_notes)
    start = time.perf_counter()
    voxel = voxel_size if voxel_size is not None else voxel_size_for(tgt, icp_points)
    src_icp, tgt_icp = voxel_downsample(src, voxel), voxel_downsample(tgt, voxel)
    seconds["downsample"] = time.perf_counter() - start
    points.update(source_icp=len(src_icp), target_icp=len(tgt_icp))
    reach = icp_settings.max_distance if icp_settings.max_distance is not None else 3.0 * voxel
    warnings = list(plan_notes)
    # A network trained on ModelNet40 objects may not fit a pair of scans: with its estimate, ICP
    # also runs from no motion, and the refinement with the higher fitness (then the lower inlier
    # RMSE) wins, with a warning when that is not the network's.
    two_starts = model is not None and not isinstance(model, SceneVRNet)
    starts = {"the VRNet estimate": initial, "no motion": np.eye(4)} if two_starts else {"start": initial}
    start = time.perf_counter()
    refined, failures = {}, []
    for label, guess in starts.items():
        try:
            refined[label] = icp(src_icp, tgt_icp, guess, reach, icp_settings.max_iterations,
                                 icp_settings.transform_tolerance, device, backend, estimator, icp_settings.settled)
        except IcpFailure as failure:
            failures.append(f"{failure} (from {label})")
    seconds["icp"] = time.perf_counter() - start
    if not refined:
        warnings.append(f"{'; '.join(failures)}; returning the unrefined initial estimate")
        return RegistrationResult(initial, initial, method, estimator, 0, False, 0.0, float("nan"), 0, seconds,
                                  points, warnings)
    label = max(refined, key=lambda name: (refined[name].fitness, -refined[name].inlier_rmse))
    best = refined[label]
    if two_starts and label == "no motion":
        learned = refined.get("the VRNet estimate")
        from_network = f"fitness {learned.fitness:.1%}" if learned else "no pairs within reach"
        warnings.append(f"the VRNet estimate does not fit these scans (ICP from it: {from_network}; from no "
                        f"motion: {best.fitness:.1%}); returning the refinement that started from no motion")
    if not best.converged:
        warnings.append(f"ICP did not converge within {icp_settings.max_iterations} iterations (raise "
                        f"IcpSettings.max_iterations)")
    if best.fitness < LOW_FITNESS:
        warnings.append(f"low fitness: only {best.fitness:.1%} of the source points have a target point within "
                        f"{reach:.3g}; the scans may overlap little or the result may be wrong")
    return RegistrationResult(best.T_target_source, best.initial, method, estimator, best.iterations,
                              best.converged, best.fitness, best.inlier_rmse, best.correspondences, seconds, points,
                              warnings)


def transform_errors(estimate: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Rotation error (degrees, isotropic; :func:`vrnet_ext.metrics.rotation_error_deg`) and
    translation error (same unit as the input) of two 4x4 transforms."""
    est, gt = torch.as_tensor(estimate[None]), torch.as_tensor(truth[None])
    return {"rotation_error_deg": float(rotation_error_deg(est[:, :3, :3], gt[:, :3, :3])),
            "translation_error": float(translation_error(est[:, :3, 3], gt[:, :3, 3]))}
