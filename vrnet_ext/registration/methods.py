"""The names of the built-in global estimates and the default one (no torch: ``vrnet --help``
lists them). The estimators themselves are in :mod:`vrnet_ext.registration.global_estimators`."""
from __future__ import annotations

GLOBAL_ESTIMATORS = ("sc2", "fpfh", "vrnet", "fgr", "icp")
# The best recall on the real pairs (benchmarks/bench_real_pairs.py; docs/user_guide.md), and on those
# the scene model never saw.
DEFAULT_METHOD = "sc2"
