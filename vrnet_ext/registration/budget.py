"""Sizing a registration run to a memory budget (``vrnet register --max-memory 2GB``).

The budget bounds the peak resident memory of the whole process: what it already holds (Python,
torch, the scans just read) plus what the run keeps through all its stages (copies of the scans) and
the largest transient of the stages that follow. Those grow linearly with the scans' size and the
point counts (never beyond the larger scan's); the coefficients below (those
of the global estimators beside each estimator, :meth:`~vrnet_ext.registration.GlobalEstimator.peak_mb`)
were fitted on this project's CPU machine as upper bounds of whole-process peaks of each method on
the 3DMatch kitchen and LiDAR pairs and a synthetic pair of 3,000,000-point scans at 1,000-20,000
global and 5,000-200,000 ICP points (at least 3 % above every peak measured for the fit, as close to
them as the fit allows), with no further safety factor; a fresh run found the predictions 1-18 %
above the measured peaks (``benchmarks/bench_memory_plan.py`` compares them with fresh measurements;
``benchmarks/bench_large_scene.py`` checks whole runs under budgets). The plan keeps the requested point counts when
they fit, else lowers them (never below the ``MIN_*`` counts), and raises :class:`MemoryBudgetError`
before any heavy work when even the smallest run would not fit, saying what would.
"""
from __future__ import annotations

import re
import resource
from dataclasses import dataclass, field, replace
from typing import Protocol

from vrnet_ext.registration.counts import PointCounts

MB = 2 ** 20
MARGIN_MB = 26.0     # allocator slack, small tensors, the result
# Peak growth of the stages every run has, in MB: intercept + bytes per point / MB
# (benchmarks/bench_memory_plan.py compares the predicted peaks with measured ones); each global
# estimator states its own (GlobalEstimator.peak_mb).
RETAINED_BYTES_PER_INPUT_POINT = 19.0        # kept through every stage, per point of the larger scan
VOXEL_BYTES_PER_INPUT_POINT = 48.0           # voxel_downsample of the larger scan
ICP_MB, ICP_BYTES_PER_POINT = 25.0, 187.0    # per point of source + target after downsampling
MIN_GLOBAL_POINTS, MIN_ICP_POINTS, MIN_NETWORK_POINTS = 1000, 5000, 256
FLOORS = {"global_points": MIN_GLOBAL_POINTS, "network_points": MIN_NETWORK_POINTS, "icp_points": MIN_ICP_POINTS}

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


def require_headroom(budget_bytes: int) -> None:
    """MemoryBudgetError at once if this process alone (Python, torch) already needs more than
    the budget plus room for the smallest run; called before any scan is read."""
    now_mb = resident_mb()
    floor_mb = now_mb + MARGIN_MB + ICP_MB
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


def transient_mb(estimator: CostedEstimator | None, largest_scan: int, counts: PointCounts) -> float:
    """What the run keeps through its stages plus the largest transient of them (MB): the voxel grid,
    ICP and the global estimator's own cost (:meth:`GlobalEstimator.peak_mb`; None or unknown: not
    counted)."""
    counts = replace(counts, global_points=min(counts.global_points, largest_scan),  # no scan grows
                     icp_points=min(counts.icp_points, largest_scan))
    stages = [VOXEL_BYTES_PER_INPUT_POINT * largest_scan / MB,
              ICP_MB + ICP_BYTES_PER_POINT * 2 * counts.icp_points / MB]
    cost = getattr(estimator, "peak_mb", None)  # an estimator object of one's own may not state it
    own = None if cost is None else cost(largest_scan, counts)
    if own is not None:
        stages.append(own)
    return RETAINED_BYTES_PER_INPUT_POINT * largest_scan / MB + max(stages)


def predicted_peak_mb(estimator: CostedEstimator | None, largest_scan: int, counts: PointCounts,
                      held_mb: float | None = None) -> float:
    """The peak resident memory (MB) this process is expected to reach if it registers with
    ``estimator`` at ``counts`` holding ``held_mb`` (default: what it holds now): the margin and the
    largest stage on top."""
    held = resident_mb() if held_mb is None else held_mb
    return held + MARGIN_MB + transient_mb(estimator, largest_scan, counts)


def plan_registration(budget_bytes: int, estimator: CostedEstimator | None, source_points: int,
                      target_points: int, requested: PointCounts) -> RegistrationPlan:
    """Point counts that keep the process's peak within ``budget_bytes``: ``requested`` where they
    fit, else lowered (never below the ``MIN_*`` counts), ICP's and those the estimator is
    ``sized_by``. Raises :class:`MemoryBudgetError` when what the process holds now plus even the
    smallest counts' transients would not fit."""
    budget_mb = budget_bytes / MB
    now_mb = resident_mb()  # what the process holds now (an earlier peak of a long-lived process is past)
    largest = max(source_points, target_points)
    shrinkable = ("icp_points", *(getattr(estimator, "sized_by", ()) or ()))
    counts = requested

    def predicted(at: PointCounts) -> float:
        return predicted_peak_mb(estimator, largest, at, now_mb)

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
