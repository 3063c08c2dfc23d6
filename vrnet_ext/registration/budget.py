"""Sizing a registration run to a memory budget (``vrnet register --max-memory 2GB``).

The budget bounds the peak resident memory of the whole process: what it already holds (Python,
torch, the scans just read) plus the largest transient of the stages that follow. Those transients
grow linearly with the point counts (never beyond the larger scan's); the coefficients below were
fitted on this project's CPU machine to whole-process peaks of each method on the 3DMatch kitchen
and LiDAR pairs at 1,000-20,000 global and 5,000-200,000 ICP points
(``benchmarks/bench_memory_plan.py``: the prediction lies within 0-25 % above the measured peak
there; ``benchmarks/bench_large_scene.py`` checks whole runs under budgets) and carry a 25 % safety
factor on each stage. The plan keeps the requested point counts when
they fit, else lowers them (never below the ``MIN_*`` counts), and raises :class:`MemoryBudgetError`
before any heavy work when even the smallest run would not fit, saying what would.
"""
from __future__ import annotations

import re
import resource
from dataclasses import dataclass, field

MB = 2 ** 20
SAFETY = 1.25
MARGIN_MB = 20.0     # allocator slack, small tensors, the result
# Peak growth of each stage, in MB: intercept + bytes per point / MB (benchmarks/bench_memory_plan.py
# compares the predicted peaks with measured ones).
VOXEL_BYTES_PER_INPUT_POINT = 110.0          # voxel_downsample of the larger scan
ICP_MB, ICP_BYTES_PER_POINT = 14.0, 270.0    # per point of source + target after downsampling
FPFH_MB, FPFH_BYTES_PER_POINT = 33.0, 5500.0  # normals, FPFH (100 neighbours), matching, RANSAC / SC2
FGR_MB, FGR_BYTES_PER_POINT = 50.0, 4000.0    # FPFH + Fast Global Registration's correspondence sets
SCENE_MB, SCENE_BYTES_PER_POINT = 60.0, 21000.0  # FPFH + the scene network's context graph, per point per scan
NETWORK_MB, NETWORK_BYTES_PER_POINT = 40.0, 20000.0  # the ModelNet40 VRNet (streamed matching), per point per cloud
MIN_GLOBAL_POINTS, MIN_ICP_POINTS, MIN_NETWORK_POINTS = 1000, 5000, 256

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
    floor_mb = now_mb + MARGIN_MB + SAFETY * ICP_MB
    if budget_bytes / MB < floor_mb:
        raise MemoryBudgetError(f"max_memory {budget_bytes / MB:.0f} MB cannot be met: Python and torch alone "
                                f"hold {now_mb:.0f} MB; allow at least {floor_mb:.0f} MB plus room for the scans")


@dataclass
class RegistrationPlan:
    """Point counts for one run and the peak they are expected to reach."""

    global_points: int
    network_points: int
    icp_points: int
    predicted_peak_mb: float
    budget_mb: float
    notes: list[str] = field(default_factory=list)


PROFILES = ("icp", "fpfh", "fgr", "sc2", "scene", "modelnet")  # GlobalEstimator.memory_profile values


def _stage_mb(profile: str | None, largest_scan: int, global_points: int, network_points: int,
              icp_points: int, scale: float = 1.0) -> float:
    """Largest transient of the run's stages (MB), safety factor included; ``profile``: the global
    estimator's (:data:`PROFILES`; None: unknown, only the voxel grid and ICP are predicted);
    ``scale``: its per-point cost against the shipped model's (a larger scene model costs more)."""
    global_points, icp_points = min(global_points, largest_scan), min(icp_points, largest_scan)  # no scan grows
    stages = [VOXEL_BYTES_PER_INPUT_POINT * largest_scan / MB,
              ICP_MB + ICP_BYTES_PER_POINT * 2 * icp_points / MB]
    if profile in ("fpfh", "sc2"):
        stages.append(FPFH_MB + FPFH_BYTES_PER_POINT * global_points / MB)
    if profile == "fgr":
        stages.append(FGR_MB + FGR_BYTES_PER_POINT * global_points / MB)
    if profile == "sc2":  # the compatibility graph: one bit per pair of correspondences (one per point)
        stages.append(FPFH_MB + global_points * global_points / 8 / MB)
    elif profile == "scene":
        stages.append(SCENE_MB + scale * SCENE_BYTES_PER_POINT * global_points / MB)
    elif profile == "modelnet":
        stages.append(NETWORK_MB + NETWORK_BYTES_PER_POINT * network_points / MB)
    return SAFETY * max(stages)


def plan_registration(budget_bytes: int, profile: str | None, source_points: int, target_points: int,
                      global_points: int, network_points: int, icp_points: int,
                      scale: float = 1.0) -> RegistrationPlan:
    """Point counts that keep the process's peak within ``budget_bytes``.

    profile: the global estimator's memory profile (:data:`PROFILES`, or None when unknown);
    scale: its per-point cost relative to the profile's (``GlobalEstimator.memory_scale``).
    Raises :class:`MemoryBudgetError` when what the process holds now plus even the smallest
    counts' transients would not fit.
    """
    budget_mb = budget_bytes / MB
    now_mb = resident_mb()  # what the process holds now (an earlier peak of a long-lived process is past)
    largest = max(source_points, target_points)
    counts = {"global_points": global_points, "network_points": network_points, "icp_points": icp_points}
    floors = {"global_points": MIN_GLOBAL_POINTS, "network_points": MIN_NETWORK_POINTS,
              "icp_points": MIN_ICP_POINTS}
    if profile is not None and profile not in PROFILES:
        raise ValueError(f"memory profile must be one of {PROFILES} or None, got {profile!r}")
    used = {"icp_points"} | ({"global_points"} if profile in ("fpfh", "fgr", "sc2", "scene") else set()) \
        | ({"network_points"} if profile == "modelnet" else set())
    notes = []

    def predicted() -> float:
        return now_mb + MARGIN_MB + _stage_mb(profile, largest, **counts, scale=scale)

    while predicted() > budget_mb:
        shrinkable = [name for name in sorted(used) if counts[name] > floors[name]]
        if not shrinkable:
            raise MemoryBudgetError(
                f"max_memory {budget_mb:.0f} MB cannot be met: the smallest run (global estimate on "
                f"{MIN_GLOBAL_POINTS} points, ICP on {MIN_ICP_POINTS}) needs about "
                f"{_smallest_mb(now_mb, profile, source_points, target_points, scale):.0f} MB, "
                f"{now_mb:.0f} MB of it held already (Python, torch and the scans)")
        for name in shrinkable:
            counts[name] = max(floors[name], int(counts[name] * 0.8))
    for name, requested in (("global_points", global_points), ("network_points", network_points),
                            ("icp_points", icp_points)):
        if counts[name] < requested:
            notes.append(f"{name} {counts[name]} instead of {requested} to stay within {budget_mb:.0f} MB")
    return RegistrationPlan(counts["global_points"], counts["network_points"], counts["icp_points"], predicted(),
                            budget_mb, notes)


def _smallest_mb(now_mb: float, profile: str | None, source_points: int, target_points: int,
                 scale: float = 1.0) -> float:
    return now_mb + MARGIN_MB + _stage_mb(profile, max(source_points, target_points), MIN_GLOBAL_POINTS,
                                          MIN_NETWORK_POINTS, MIN_ICP_POINTS, scale)
