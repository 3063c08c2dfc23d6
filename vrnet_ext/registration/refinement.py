"""ICP refinement at full scale: the nearest target point of each moved source point (``ops.knn``
grid search), pairs beyond the reach get weight 0, then one ICP step
(:mod:`vrnet_ext.registration.icp_steps`). Memory is O(points) plus a bool occupancy grid of at
most 2^24 cells (16 MB) for the reach test: scans of 100k+ points fit in a few hundred MB.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vrnet_ext import ops
from vrnet_ext.registration.degeneracy import degeneracy_note
from vrnet_ext.registration.icp_steps import make_icp_step
from vrnet_ext.names import DEFAULT_ICP_STEP, ICP_STEPS
from vrnet_ext.registration.counts import PointCounts
from vrnet_ext.registration.result import RegistrationResult
from vrnet_ext.geometry.preprocessing import point_spacing
from vrnet_ext.geometry.transforms import apply


NORMAL_NEIGHBOURS = 20  # the target normals of the degeneracy check (as point-to-plane's)
COARSE_FACTOR = 4  # IcpSettings.coarse_start: the coarse voxel edge and reach, in fine ones
REFERENCE_KNN_ELEMENTS = 1 << 24  # 128 MB of float64 distances per chunk for backend="torch"


class IcpFailure(RuntimeError):
    """ICP found too few point pairs within reach of its starting transform."""


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


class IcpProblem:
    """One ICP problem, prepared once and run from any number of starts (as small_gicp prepares
    clouds before aligning): both scans as float64 tensors, the step's per-cloud data (normals
    for point-to-plane, covariances for GICP) and the reach grid (:class:`TargetReach`).

    src (N, 3), tgt (M, 3) arrays in one unit; settings: :class:`IcpSettings` (its ``max_distance``
    must be set: pairs farther apart get weight 0).
    """

    def __init__(self, src: np.ndarray, tgt: np.ndarray, settings: IcpSettings,
                 device: torch.device = torch.device("cpu"), backend: str = "ext") -> None:
        if settings.max_distance is None:
            raise ValueError("settings.max_distance must be set for ICP (register() derives it from the voxel edge)")
        self.settings, self.backend = settings, backend
        self.src = torch.as_tensor(src, dtype=torch.float64, device=device).unsqueeze(0)
        self.tgt = torch.as_tensor(tgt, dtype=torch.float64, device=device).unsqueeze(0)
        self.step = make_icp_step(settings.step)
        self.step.prepare(self.src[0], self.tgt[0])
        self.reach = TargetReach(self.tgt, settings.max_distance)
        self._tgt_normals = getattr(self.step, "tgt_normals", None)  # point-to-plane's; others' made on demand
        self._final = None  # (transform, moved source, pairs within reach) where the last run ended

    def run(self, initial: np.ndarray) -> RegistrationResult:
        """ICP from ``initial`` (4, 4); see :func:`icp`."""
        src_t, tgt_t, settings = self.src, self.tgt, self.settings
        max_distance = settings.max_distance
        T = torch.as_tensor(initial, dtype=torch.float64, device=src_t.device)
        done, converged, previous = 0, False, None
        while done < settings.max_iterations:
            moved = apply(T, src_t)
            candidates, dist2, idx = _nearest_in_reach(moved, tgt_t, self.reach, self.backend)
            inliers = (dist2 <= max_distance ** 2).to(src_t.dtype)
            count = int(inliers.sum())
            if count < 3:
                raise IcpFailure(f"ICP: fewer than 3 point pairs within max_distance={max_distance:g} of the initial "
                                 "estimate (too far off; raise max_distance or check the inputs)")
            current = (count / src_t.shape[1], float((dist2 * inliers).sum() / count) ** 0.5)
            if previous is not None and abs(current[0] - previous[0]) < settings.settled \
                    and abs(current[1] - previous[1]) < settings.settled:
                converged = True
                break
            previous = current
            new = self.step.step(T, candidates, idx, inliers)
            done += 1
            change_rotation = torch.linalg.matrix_norm(new[:3, :3] - T[:3, :3]).item()
            change_translation = torch.linalg.vector_norm(new[:3, 3] - T[:3, 3]).item()
            T = new
            if change_rotation < settings.transform_tolerance and change_translation < settings.transform_tolerance:
                converged = True
                break
        moved = apply(T, src_t)
        pairs = _nearest_in_reach(moved, tgt_t, self.reach, self.backend)
        self._final = (T.cpu().numpy(), moved, pairs)  # the degeneracy check of this result reuses them
        dist2 = pairs[1]
        close = dist2[dist2 <= max_distance ** 2]
        rmse = float(close.mean().sqrt()) if len(close) else float("nan")
        return RegistrationResult(T_target_source=self._final[0], initial=np.asarray(initial, dtype=np.float64),
                                  method="icp", icp_step=settings.step, iterations=done, converged=converged,
                                  fitness=len(close) / src_t.shape[1], inlier_rmse=rmse, correspondences=len(close),
                                  points={"source": src_t.shape[1], "target": tgt_t.shape[1]})


    def spacing(self) -> float:
        """The target's resolution (:func:`~vrnet_ext.geometry.preprocessing.point_spacing`)."""
        return point_spacing(self.tgt[0], self.backend)

    def degeneracy(self, transform: np.ndarray) -> str | None:
        """A warning when the pairs within reach under ``transform`` (4, 4) leave directions of the
        transform unconstrained (:mod:`vrnet_ext.registration.degeneracy`), else None."""
        if self._final is not None and np.array_equal(self._final[0], transform):
            _, moved, (candidates, dist2, idx) = self._final  # the pairs the last run ended with
        else:
            moved = apply(torch.as_tensor(transform, dtype=torch.float64, device=self.src.device), self.src)
            candidates, dist2, idx = _nearest_in_reach(moved, self.tgt, self.reach, self.backend)
        close = dist2 <= self.settings.max_distance ** 2
        if self._tgt_normals is None:
            self._tgt_normals = ops.normals(self.tgt[0], NORMAL_NEIGHBOURS)
        return degeneracy_note(moved[0, candidates[close]], self._tgt_normals[idx[close]])


def icp(src: np.ndarray, tgt: np.ndarray, initial: np.ndarray, settings: IcpSettings, *,
        device: torch.device = torch.device("cpu"), backend: str = "ext") -> RegistrationResult:
    """ICP: nearest target point of each moved source point, pairs farther than
    ``settings.max_distance`` (required here) get weight 0, then one step of ``settings.step``
    (:mod:`vrnet_ext.registration.icp_steps`: point_to_point, point_to_plane, gicp). Converged when
    a step changes the transform by less than ``settings.transform_tolerance`` (rotation in radians,
    translation in the scans' unit), or when the fitness (a share) and the inlier RMSE (in the
    scans' unit) of the correspondences both change by less than ``settings.settled`` from one
    iteration to the next (Open3D's ICPConvergenceCriteria: the pairs have settled). At most
    ``settings.max_iterations`` steps. Points that :class:`TargetReach` rules out are not searched
    (they would get weight 0 anyway). Several starts on the same scans: prepare an
    :class:`IcpProblem` once.

    Returns a :class:`RegistrationResult` (method "icp"); raises IcpFailure when fewer than 3 pairs
    are within reach.
    """
    return IcpProblem(src, tgt, settings, device, backend).run(initial)


def pairs_within_reach(src: np.ndarray, tgt: np.ndarray, transform: np.ndarray, reach: float,
                       backend: str = "ext") -> tuple[np.ndarray, np.ndarray]:
    """The points of src (N, 3), moved by the 4x4 ``transform``, whose nearest point of tgt (M, 3) is
    within ``reach`` -> (their indices into src (P,), those nearest points' indices into tgt (P,))."""
    src_t = torch.as_tensor(src, dtype=torch.float64).unsqueeze(0)
    tgt_t = torch.as_tensor(tgt, dtype=torch.float64).unsqueeze(0)
    T = torch.as_tensor(transform, dtype=torch.float64)
    candidates, dist2, idx = _nearest_in_reach(apply(T, src_t), tgt_t, TargetReach(tgt_t, reach), backend)
    close = dist2 <= reach ** 2
    return candidates[close].numpy(), idx[close].numpy()


def fitness(src: np.ndarray, tgt: np.ndarray, transform: np.ndarray, reach: float, backend: str = "ext") -> float:
    """Share of the points of src (N, 3), moved by the 4x4 ``transform``, that have a point of
    tgt (M, 3) within ``reach``: a score of any transform on a pair (Open3D's fitness)."""
    return len(pairs_within_reach(src, tgt, transform, reach, backend)[0]) / len(src)


@dataclass(frozen=True)
class IcpSettings:
    """How :func:`register` refines its global estimate (each field is a ``vrnet register`` flag).

    step: the ICP step (:mod:`vrnet_ext.registration.icp_steps`); points: both scans are
    voxel-downsampled to about this many points (``voxel_size`` overrides); max_distance: the
    inlier reach (default 3 voxels); max_iterations: at most this many steps (0: no ICP); it stops
    earlier once a step moves the transform by less than ``transform_tolerance`` (radians and the
    scans' unit: 1e-4 is 0.006 degrees and 0.1 mm for scans in metres; finer steps are below what
    the pairs of a real scan resolve, and GICP's Gauss-Newton steps circle there as pairs come and
    go) or the fitness and inlier RMSE change by less than ``settled`` (see :func:`icp`).
    coarse_start: ICP from no motion (the identity: method "icp", or the second start of a network
    that may not transfer) first runs on both scans downsampled to a ``COARSE_FACTOR`` times coarser
    voxel with a reach ``COARSE_FACTOR`` times longer, so it pulls in from farther off.
    """

    step: str = DEFAULT_ICP_STEP
    points: int = PointCounts.icp_points
    voxel_size: float | None = None
    max_distance: float | None = None
    max_iterations: int = 50
    transform_tolerance: float = 1e-4
    settled: float = 1e-6
    coarse_start: bool = True

    def __post_init__(self) -> None:
        if self.step not in ICP_STEPS:
            raise ValueError(f"IcpSettings.step must be one of {ICP_STEPS}, got {self.step!r}")
        if not isinstance(self.coarse_start, bool):
            raise ValueError(f"IcpSettings.coarse_start must be True or False, got {self.coarse_start!r}")
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

