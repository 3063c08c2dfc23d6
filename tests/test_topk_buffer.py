"""The kNN top-k buffers (csrc/knn/topk.h) are host + device code; the CUDA kernels use RegisterTopK,
which the CPU kernels do not. This compiles tests/cpp/topk_check.cpp with the host compiler so that
its logic (ordering, ties, capacity above k, fewer candidates than k) is checked on every machine."""
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("g++") is None, reason="no g++ on this machine")
def test_topk_buffers_match_sorting(tmp_path):
    binary = tmp_path / "topk_check"
    subprocess.run(["g++", "-std=c++17", "-O2", "-Wall", "-Werror", f"-I{ROOT / 'csrc'}",
                    str(ROOT / "tests" / "cpp" / "topk_check.cpp"), "-o", str(binary)], check=True)
    result = subprocess.run([str(binary)], capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stdout[-3000:]
