"""How many points each stage of a registration works on (torch-free: ``vrnet register --help``
shows the defaults). The names of the methods and ICP steps are in :mod:`vrnet_ext.names`."""
from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral

@dataclass(frozen=True)
class PointCounts:
    """About how many points each stage of a registration works on, per scan: the global estimate
    on scans voxel-downsampled to ``global_points`` (FPFH, spatial consistency, RANSAC, FGR, the
    scene model), a ModelNet40 network on ``network_points`` subsampled ones, ICP on scans
    voxel-downsampled to ``icp_points``. A memory budget lowers them
    (:func:`vrnet_ext.registration.budget.plan_registration`)."""

    global_points: int = 5000
    network_points: int = 1024
    icp_points: int = 50_000

    def __post_init__(self) -> None:
        for name, smallest in (("global_points", 3), ("network_points", 1), ("icp_points", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, Integral) or value < smallest:
                raise ValueError(f"{name} must be an integer >= {smallest}, got {value!r}")
            object.__setattr__(self, name, int(value))
