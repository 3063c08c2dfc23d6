"""Sizing a registration run to a memory budget (``vrnet register --max-memory 2GB``).

The budget bounds the peak resident memory of the whole process: what it already holds (Python,
torch, the scans just read) plus the largest of the run's stages in turn (:func:`stage_peaks_mb`):
the global estimate, ICP's preparation on what the estimate leaves, ICP's iterations. Each grows
linearly with the scans' size and the point counts (never beyond a scan's own); the coefficients
below (those of the global estimators beside each estimator,
:meth:`~vrnet_ext.registration.GlobalEstimator.peak_mb`) were fitted on this project's CPU machine
as upper bounds of each stage's measured peak, for each method on the 3DMatch kitchen and LiDAR
pairs and a synthetic pair of 3,000,000-point scans at 1,000-20,000 global and 5,000-200,000 ICP
points (``benchmarks/bench_memory_plan.py`` measures the stages and the whole run afresh;
``benchmarks/bench_large_scene.py`` checks whole runs under budgets). Under a budget, memory a stage
frees goes back to the system before the next one allocates (:func:`return_freed_memory`): without
it, what glibc's heap kept after the global estimate of the 3,000,000-point pair ranged over 17-57 MB
with the order of earlier allocations (18-26 MB with it), which no per-stage bound can foresee. The
plan keeps the requested point counts when they fit, else lowers them (never below the ``MIN_*``
counts), and raises :class:`MemoryBudgetError` before any heavy work when even the smallest run
would not fit, saying what would.
"""
from __future__ import annotations

import ctypes
import re
import resource
from dataclasses import dataclass, field, replace
from typing import Protocol

from vrnet_ext.registration.counts import PointCounts

MB = 2 ** 20
MARGIN_MB = 6.0      # allocator slack, small tensors, the result
# Peak growth of the stages every run has, in MB: intercept + bytes per point / MB
# (benchmarks/bench_memory_plan.py compares the predicted peaks with measured ones); each global
# estimator states its own (GlobalEstimator.peak_mb).
VOXEL_BYTES_PER_INPUT_POINT = 50.0           # a voxel-edge search over the larger scan
DOWNSAMPLED_BYTES_PER_POINT = 48.0           # ICP's downsampled copies, kept while its voxel is searched
ICP_PREPARE_MB, ICP_PREPARE_BYTES_PER_POINT = 4.0, 215.0   # ICP's problem: tensors, reach grid
ICP_MB, ICP_BYTES_PER_POINT = 8.0, 190.0     # the problem kept + ICP's iterations
GLOBAL_KEPT_MB, GLOBAL_KEPT_BYTES_PER_POINT = 24.0, 1000.0  # what a global estimate leaves (views, code)
FIRST_STAGE_MB = 12.0                        # code and pools a run's first stage loads (ICP alone)
MIN_GLOBAL_POINTS, MIN_ICP_POINTS, MIN_NETWORK_POINTS = 1000, 5000, 256
FLOORS = {"global_points": MIN_GLOBAL_POINTS, "network_points": MIN_NETWORK_POINTS, "icp_points": MIN_ICP_POINTS}

M_MMAP_THRESHOLD = -3            # glibc's mallopt parameter
MAPPED_BLOCK_BYTES = 1 << 20     # under a budget, blocks of at least this size are mapped on their own

_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmgt]?)(i?b?)\s*$", re.IGNORECASE)


class MemoryBudgetError(ValueError):
    """The budget cannot be met; the message says what the smallest run would need."""


def parse_memory_size(text: str) -> int:
    """'2GB', '512MB', '1.5G', '4096' (bytes) -> bytes (K/M/G/T are powers of 1024)."""
    match = _SIZE.match(str(text))
    if not match:
        raise ValueError(f"not a memory size: {text!r} (e.g. 2GB, 512MB, 1.5G)")
    number, unit = float(match.group(1)), match.group(2).lower()
    value = int(number * 1024 ** " kmgt".index(unit or " "))
    if value <= 0:
        raise ValueError(f"a memory size must be > 0, got {text!r}")
    return value


def resident_mb() -> float:
    """The resident memory this process holds now, in MB (elsewhere than Linux: its peak so far,
    the best bound available)."""
    try:
        return int(re.search(r"VmRSS:\s+(\d+)", open("/proc/self/status").read()).group(1)) / 1024.0
    except (OSError, AttributeError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def return_freed_memory() -> None:
    """Make memory a stage frees go back to the system before the next stage allocates: glibc then
    maps every block of at least :data:`MAPPED_BLOCK_BYTES` on its own (its adaptive default keeps
    freed blocks of up to 32 MB in its heap, so a process's peak would depend on the order of earlier
    allocations and exceed what the stages hold at once). Set for the whole process, once a budget is
    asked for; elsewhere than glibc, nothing."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt(M_MMAP_THRESHOLD, MAPPED_BLOCK_BYTES)


def require_headroom(budget_bytes: int) -> None:
    """MemoryBudgetError at once if this process alone (Python, torch) already needs more than
    the budget plus room for the smallest run; called before any scan is read (and from then on
    freed memory goes back to the system, :func:`return_freed_memory`)."""
    return_freed_memory()
    now_mb = resident_mb()
    floor_mb = now_mb + MARGIN_MB + FIRST_STAGE_MB + ICP_MB
    if budget_bytes / MB < floor_mb:
        raise MemoryBudgetError(f"max_memory {budget_bytes / MB:.0f} MB cannot be met: Python and torch alone "
                                f"hold {now_mb:.0f} MB; allow at least {floor_mb:.0f} MB plus room for the scans")


class CostedEstimator(Protocol):
    """What the planner reads of a global estimator (:class:`~vrnet_ext.registration.GlobalEstimator`)."""

    sized_by: tuple[str, ...]

    def peak_mb(self, largest_scan: int, counts: PointCounts) -> float | None: ...


@dataclass
class RegistrationPlan:
    """Point counts for one run and the peak they are expected to reach."""

    counts: PointCounts
    predicted_peak_mb: float
    budget_mb: float
    notes: list[str] = field(default_factory=list)


STAGES = ("global", "preparation", "iterations")  # a run's stages in turn (stage_peaks_mb)


def stage_peaks_mb(estimator: CostedEstimator | None, scan_points: tuple[int, int],
                   counts: PointCounts) -> dict[str, float]:
    """The peak growth (MB) of each stage of a run on scans of ``scan_points`` (source, target) points,
    by :data:`STAGES`: the global estimate (a voxel search over the larger scan, the estimator's own
    cost: :meth:`GlobalEstimator.peak_mb`; None or unknown: not counted), then on what it leaves
    ICP's preparation (its voxel search with the downsampled copies, or its problem's tensors) and
    ICP's iterations. ICP's points are bounded by the requested count per scan, or all of a smaller
    scan's points."""
    largest = max(scan_points)
    global_points = min(counts.global_points, largest)  # no scan grows
    icp_points = sum(min(counts.icp_points, points) for points in scan_points)
    cost = getattr(estimator, "peak_mb", None)  # an estimator object of one's own may not state it
    own = None if cost is None else cost(largest, replace(counts, global_points=global_points))
    estimates = "global_points" in (getattr(estimator, "sized_by", ()) or ())
    voxel_search = VOXEL_BYTES_PER_INPUT_POINT * largest / MB
    kept = GLOBAL_KEPT_MB + GLOBAL_KEPT_BYTES_PER_POINT * global_points / MB if estimates else FIRST_STAGE_MB
    return {"global": max(voxel_search, own or 0.0) if estimates else (own or 0.0),
            "preparation": kept + max(voxel_search + DOWNSAMPLED_BYTES_PER_POINT * icp_points / MB,
                                      ICP_PREPARE_MB + ICP_PREPARE_BYTES_PER_POINT * icp_points / MB),
            "iterations": kept + ICP_MB + ICP_BYTES_PER_POINT * icp_points / MB}


def transient_mb(estimator: CostedEstimator | None, scan_points: tuple[int, int], counts: PointCounts) -> float:
    """The peak growth (MB) of a run: its largest stage (:func:`stage_peaks_mb`)."""
    return max(stage_peaks_mb(estimator, scan_points, counts).values())


def predicted_peak_mb(estimator: CostedEstimator | None, scan_points: tuple[int, int], counts: PointCounts,
                      held_mb: float | None = None) -> float:
    """The peak resident memory (MB) this process is expected to reach if it registers scans of
    ``scan_points`` (source, target) points with ``estimator`` at ``counts`` holding ``held_mb``
    (default: what it holds now): the margin and the largest stage on top."""
    held = resident_mb() if held_mb is None else held_mb
    return held + MARGIN_MB + transient_mb(estimator, scan_points, counts)


def plan_registration(budget_bytes: int, estimator: CostedEstimator | None, source_points: int,
                      target_points: int, requested: PointCounts) -> RegistrationPlan:
    """Point counts that keep the process's peak within ``budget_bytes``: ``requested`` where they
    fit, else lowered (never below the ``MIN_*`` counts), ICP's and those the estimator is
    ``sized_by``. Raises :class:`MemoryBudgetError` when what the process holds now plus even the
    smallest counts' transients would not fit. From then on freed memory goes back to the system
    (:func:`return_freed_memory`)."""
    return_freed_memory()
    budget_mb = budget_bytes / MB
    now_mb = resident_mb()  # what the process holds now (an earlier peak of a long-lived process is past)
    shrinkable = ("icp_points", *(getattr(estimator, "sized_by", ()) or ()))
    counts = requested

    def predicted(at: PointCounts) -> float:
        return predicted_peak_mb(estimator, (source_points, target_points), at, now_mb)

    while predicted(counts) > budget_mb:
        lower = {name: max(FLOORS[name], int(getattr(counts, name) * 0.8)) for name in shrinkable
                 if getattr(counts, name) > FLOORS[name]}
        if not lower:
            raise MemoryBudgetError(
                f"max_memory {budget_mb:.0f} MB cannot be met: the smallest run (global estimate on "
                f"{MIN_GLOBAL_POINTS} points, ICP on {MIN_ICP_POINTS}) needs about "
                f"{predicted(replace(requested, **FLOORS)):.0f} MB, "
                f"{now_mb:.0f} MB of it held already (Python, torch and the scans)")
        counts = replace(counts, **lower)
    notes = [f"{name} {getattr(counts, name)} instead of {getattr(requested, name)} to stay within {budget_mb:.0f} MB"
             for name in ("global_points", "network_points", "icp_points")
             if getattr(counts, name) < getattr(requested, name)]
    return RegistrationPlan(counts=counts, predicted_peak_mb=predicted(counts), budget_mb=budget_mb, notes=notes)
