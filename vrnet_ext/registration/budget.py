"""Sizing a registration run to a memory budget (``vrnet register --max-memory 2GB``).

On the CPU the budget bounds the peak resident memory of the whole process: what it already holds (Python,
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

On a CUDA device the budget bounds the GPU's peak (``torch.cuda.max_memory_allocated``: what the
process holds there, such as a model, included), planned the same way with the same stage costs
for the stages that work on downsampled points, and :data:`GPU_SCAN_BYTES_PER_POINT` for the steps
that read whole scans (the voxel-edge searches and the downsampling). Where those would not fit,
they run on the host (:attr:`RegistrationPlan.scans_on_device` False) and only downsampled points go
to the GPU. :func:`device_memory_cap` then makes the GPU's allocator refuse to pass the budget
during the run: a stage the plan underestimated fails with :class:`MemoryBudgetError` instead of
exceeding it. The GPU's figures are upper bounds read from the allocations of the code, not yet
fitted on a GPU.
"""
from __future__ import annotations

import contextlib
import ctypes
import re
import resource
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Protocol

from vrnet_ext.registration.counts import PointCounts

if TYPE_CHECKING:  # torch loads with the first registration, not with `vrnet --max-memory 2GB`'s parsing
    import torch

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
# A whole scan's steps on a GPU, per point of the larger scan: the scan's float64 copy (24 bytes) and,
# within each voxel downsampling of it, the cells (24), their keys (8), the sort's keys, indices and
# scratch (~32), the voxel starts (~17), the finiteness test; doubled for the allocator's rounding
# and the per-axis sort of scans wider than 2^21 cells. Read from the code, not yet measured.
GPU_SCAN_BYTES_PER_POINT = 250.0
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


def on_gpu(device: torch.device | None) -> bool:
    """Whether a budget for ``device`` (None: the CPU) bounds a CUDA device's memory."""
    return device is not None and device.type == "cuda"


def held_mb(device: torch.device | None = None) -> float:
    """What this process holds now where ``device``'s budget applies, in MB: on a CUDA device the
    memory torch has allocated there, elsewhere (None: the CPU) the resident memory (:func:`resident_mb`)."""
    if on_gpu(device):
        import torch

        return torch.cuda.memory_allocated(device) / MB
    return resident_mb()


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
    scans_on_device: bool = True  # whether the steps that read whole scans run on the run's device


STAGES = ("global", "preparation", "iterations")  # a run's stages in turn (stage_peaks_mb)


def stage_peaks_mb(estimator: CostedEstimator | None, scan_points: tuple[int, int],
                   counts: PointCounts, whole_scans: bool = True) -> dict[str, float]:
    """The peak growth (MB) of each stage of a run on scans of ``scan_points`` (source, target) points,
    by :data:`STAGES`: the global estimate (a voxel search over the larger scan, the estimator's own
    cost: :meth:`GlobalEstimator.peak_mb`; None or unknown: not counted), then on what it leaves
    ICP's preparation (its voxel search with the downsampled copies, or its problem's tensors) and
    ICP's iterations. ICP's points are bounded by the requested count per scan, or all of a smaller
    scan's points. ``whole_scans`` False: the voxel searches over whole scans run elsewhere (on the
    host, for a GPU) and are not counted."""
    largest = max(scan_points)
    global_points = min(counts.global_points, largest)  # no scan grows
    icp_points = sum(min(counts.icp_points, points) for points in scan_points)
    cost = getattr(estimator, "peak_mb", None)  # an estimator object of one's own may not state it
    own = None if cost is None else cost(largest, replace(counts, global_points=global_points))
    estimates = "global_points" in (getattr(estimator, "sized_by", ()) or ())
    voxel_search = VOXEL_BYTES_PER_INPUT_POINT * largest / MB if whole_scans else 0.0
    kept = GLOBAL_KEPT_MB + GLOBAL_KEPT_BYTES_PER_POINT * global_points / MB if estimates else FIRST_STAGE_MB
    return {"global": max(voxel_search, own or 0.0) if estimates else (own or 0.0),
            "preparation": kept + max(voxel_search + DOWNSAMPLED_BYTES_PER_POINT * icp_points / MB,
                                      ICP_PREPARE_MB + ICP_PREPARE_BYTES_PER_POINT * icp_points / MB),
            "iterations": kept + ICP_MB + ICP_BYTES_PER_POINT * icp_points / MB}


def transient_mb(estimator: CostedEstimator | None, scan_points: tuple[int, int], counts: PointCounts,
                 whole_scans: bool = True) -> float:
    """The peak growth (MB) of a run: its largest stage (:func:`stage_peaks_mb`)."""
    return max(stage_peaks_mb(estimator, scan_points, counts, whole_scans).values())


def predicted_peak_mb(estimator: CostedEstimator | None, scan_points: tuple[int, int], counts: PointCounts,
                      held: float | None = None, device: torch.device | None = None,
                      scans_on_device: bool = True) -> float:
    """The peak memory (MB) this process is expected to reach where ``device``'s budget applies (the
    host's resident memory; a GPU's allocations) if it registers scans of ``scan_points`` (source,
    target) points with ``estimator`` at ``counts`` holding ``held`` MB there (default: what it holds
    now, :func:`held_mb`): the margin and the largest stage on top. On a GPU the steps that read
    whole scans count :data:`GPU_SCAN_BYTES_PER_POINT` where ``scans_on_device``, nothing else."""
    held = held_mb(device) if held is None else held
    if not on_gpu(device):
        return held + MARGIN_MB + transient_mb(estimator, scan_points, counts)
    whole = GPU_SCAN_BYTES_PER_POINT * max(scan_points) / MB if scans_on_device else 0.0
    return held + MARGIN_MB + max(whole, transient_mb(estimator, scan_points, counts, whole_scans=False))


def plan_registration(budget_bytes: int, estimator: CostedEstimator | None, source_points: int,
                      target_points: int, requested: PointCounts,
                      device: torch.device | None = None) -> RegistrationPlan:
    """Point counts that keep the process's peak on ``device`` within ``budget_bytes``: ``requested``
    where they fit, else lowered (never below the ``MIN_*`` counts), ICP's and those the estimator is
    ``sized_by``; on a GPU, the steps that read whole scans on the host when they would not fit there.
    Raises :class:`MemoryBudgetError` when what the process holds now plus even the smallest counts'
    transients would not fit. On the CPU, from then on freed memory goes back to the system
    (:func:`return_freed_memory`)."""
    if not on_gpu(device):
        return_freed_memory()
    budget_mb = budget_bytes / MB
    now_mb = held_mb(device)  # what the process holds now (an earlier peak of a long-lived process is past)
    shrinkable = ("icp_points", *(getattr(estimator, "sized_by", ()) or ()))
    scans = (source_points, target_points)
    whole_scan_mb = GPU_SCAN_BYTES_PER_POINT * max(scans) / MB
    scans_on_device = not on_gpu(device) or now_mb + MARGIN_MB + whole_scan_mb <= budget_mb
    counts = requested

    def predicted(at: PointCounts) -> float:
        return predicted_peak_mb(estimator, scans, at, now_mb, device, scans_on_device)

    where, holders = (f" on {device}", "this process") if on_gpu(device) else ("", "Python, torch and the scans")
    while predicted(counts) > budget_mb:
        lower = {name: max(FLOORS[name], int(getattr(counts, name) * 0.8)) for name in shrinkable
                 if getattr(counts, name) > FLOORS[name]}
        if not lower:
            raise MemoryBudgetError(
                f"max_memory {budget_mb:.0f} MB{where} cannot be met: the smallest run (global estimate on "
                f"{MIN_GLOBAL_POINTS} points, ICP on {MIN_ICP_POINTS}) needs about "
                f"{predicted(replace(requested, **FLOORS)):.0f} MB, {now_mb:.0f} MB of it held already ({holders})")
        counts = replace(counts, **lower)
    notes = [f"{name} {getattr(counts, name)} instead of {getattr(requested, name)} to stay within {budget_mb:.0f} MB"
             for name in ("global_points", "network_points", "icp_points")
             if getattr(counts, name) < getattr(requested, name)]
    if not scans_on_device:
        notes.append(f"the scans were voxel-downsampled on the host: on {device} their {max(scans)} points would "
                     f"need about {whole_scan_mb:.0f} MB of max_memory {budget_mb:.0f} MB")
    return RegistrationPlan(counts=counts, predicted_peak_mb=predicted(counts), budget_mb=budget_mb, notes=notes,
                            scans_on_device=scans_on_device)


@contextlib.contextmanager
def device_memory_cap(device: torch.device | None, budget_bytes: int | None) -> Iterator[None]:
    """Within the block, a CUDA device's allocator refuses to hold more than ``budget_bytes`` for this
    process (``torch.cuda.set_per_process_memory_fraction``; its cache emptied first, the previous
    fraction restored after): an allocation that would pass it raises :class:`MemoryBudgetError`
    naming the budget. Elsewhere, or without a budget, nothing."""
    if not on_gpu(device) or budget_bytes is None:
        yield
        return
    import torch

    total = torch.cuda.get_device_properties(device).total_memory
    getter = getattr(torch.cuda, "get_per_process_memory_fraction", None)
    previous = getter(device) if getter is not None else 1.0
    torch.cuda.empty_cache()
    torch.cuda.set_per_process_memory_fraction(min(1.0, budget_bytes / total), device)
    try:
        yield
    except torch.OutOfMemoryError as error:
        raise MemoryBudgetError(f"max_memory {budget_bytes / MB:.0f} MB on {device} was reached: the run needs more "
                                f"than planned ({str(error).splitlines()[0]}); lower the point counts or allow "
                                "more") from None
    finally:
        torch.cuda.set_per_process_memory_fraction(previous, device)
