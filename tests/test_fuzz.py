"""The fuzz suite (``tests/fuzz_cases.py``): every target in its own subprocess, so that a crash in
compiled code fails one test with the child's exit status instead of killing the session, and a
hang fails at the timeout.

CI runs a small, derandomised budget (40 examples per target). The nightly profile:
``VRNET_FUZZ_EXAMPLES=5000 python -m pytest tests/test_fuzz.py`` (5000 examples per target, 500 kill
points of training runs), or ``python tests/fuzz_cases.py knn 5000`` for one target.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import requires_ext

pytest.importorskip("hypothesis", reason="the fuzz suite needs hypothesis (pip install -e .[test])")
sys.path.insert(0, str(Path(__file__).parent))
from fuzz_cases import TARGETS  # noqa: E402

EXAMPLES = int(os.environ.get("VRNET_FUZZ_EXAMPLES", "40"))


@requires_ext
@pytest.mark.parametrize("target", TARGETS)
def test_fuzz(target):
    timeout = 120 + 2 * EXAMPLES
    try:
        result = subprocess.run([sys.executable, str(Path(__file__).parent / "fuzz_cases.py"), target, str(EXAMPLES)],
                                capture_output=True, text=True, timeout=timeout,
                                env=dict(os.environ, OMP_NUM_THREADS="1"))
    except subprocess.TimeoutExpired:
        pytest.fail(f"fuzz {target}: no result within {timeout} s (a hang?)")
    assert result.returncode == 0, (f"fuzz {target} failed (exit status {result.returncode}; negative = killed "
                                    f"by that signal):\n{result.stdout[-3000:]}\n{result.stderr[-6000:]}")


def test_accepted_invalid_values_are_refused():
    """Booleans are not numbers, and a viewpoint must be finite."""
    import math

    import torch

    from vrnet_ext import ops

    q = torch.randn(1, 5, 3)
    with pytest.raises(ValueError, match="scale must be a finite number"):
        ops.soft_match(q, q, q, scale=True)
    points = torch.randn(50, 3)
    with pytest.raises(ValueError, match="radius must be a finite number > 0"):
        ops.fpfh(points, ops.normals(points), radius=True)
    with pytest.raises(ValueError, match="viewpoint must have 3 finite coordinates"):
        ops.normals(points, viewpoint=(math.nan, 0.0, 0.0))
