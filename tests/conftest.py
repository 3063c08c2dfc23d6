"""Shared test helpers: dtype tolerances, opcheck / torch.compile wrappers, data paths."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from vrnet_ext import has_extension
from vrnet_ext._extension import has_kernel

DTYPES = [torch.float32, torch.float64]
requires_ext = pytest.mark.skipif(not has_extension(), reason="compiled module vrnet_ext._C is not built")

CUDA_KERNELS = torch.cuda.is_available() and has_kernel(torch.device("cuda"))
requires_cuda_kernels = pytest.mark.skipif(
    not CUDA_KERNELS,
    reason="no CUDA device" if not torch.cuda.is_available() else "vrnet_ext._C was built without CUDA kernels",
)


# The tests compare float32 results with float32 references at float32 tolerances: on a GPU the
# products must be full float32, not TensorFloat-32 (cuDNN's convolutions default to it).
torch.backends.cuda.matmul.allow_tf32 = False
torch.backends.cudnn.allow_tf32 = False


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=requires_cuda_kernels)])
def device(request):
    """Runs a test once per device; tensors the test creates land there (torch default device)."""
    torch.set_default_device(request.param)
    yield torch.device(request.param)
    torch.set_default_device(None)

DATA_DIR = Path(os.environ.get("VRNET_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
MODELNET_DIR = DATA_DIR / "modelnet40"
requires_modelnet = pytest.mark.skipif(
    not (MODELNET_DIR / "modelnet40_1024_train.h5").exists(),
    reason=f"ModelNet40 HDF5 files not found under {MODELNET_DIR} (set VRNET_DATA)",
)


def help_defaults_are_clean(help_text: str) -> bool:
    """No option's default named twice ("... default: X) (default: Y)") or named empty or None."""
    text = " ".join(help_text.split())
    return not re.search(r"default: [^()]*\) \(default:|\(default: (None)?\)", text)


def tolerances(dtype: torch.dtype) -> dict:
    return dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-10)


def opcheck(op, args) -> None:
    """torch.library.opcheck: schema, autograd registration, fake kernel, AOT dispatch."""
    torch.library.opcheck(op, args)


def compile_fullgraph(fn, backend: str = "aot_eager"):
    """torch.compile with fullgraph=True: any graph break raises."""
    torch._dynamo.reset()
    return torch.compile(fn, fullgraph=True, backend=backend)


def under_each_cpu_dispatch(script: str, tmp_path: Path, *args: str) -> tuple:
    """Runs ``script`` (Python source that ``torch.save``s its results to ``sys.argv[1]``; further
    ``args`` follow) in a fresh process with the default CPU dispatch (vector code where the CPU has
    it) and with ``VRNET_CPU_DISPATCH=generic`` (the portable loops): (default, generic) results."""
    results = []
    for dispatch in ("default", "generic"):
        path = tmp_path / f"{dispatch}.pt"
        done = subprocess.run([sys.executable, "-c", script, str(path), *args],
                              env=dict(os.environ, VRNET_CPU_DISPATCH=dispatch), capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stderr
        results.append(torch.load(path))
    return tuple(results)


class ChairPairs(torch.utils.data.Dataset):
    """``count`` training pairs of procedural chairs (96 points, 64 kept), seeded by (``seed``, index):
    a pair provider for ``vrnet_ext.learning.train.train`` that needs no ModelNet40."""

    def __init__(self, count: int, seed: int):
        self.count, self.seed = count, seed

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int) -> dict:
        import numpy as np

        from vrnet_ext.data import PairSpec, make_pair
        from vrnet_ext.data.procedural import chair

        rng = np.random.default_rng([self.seed, index])
        pair = make_pair(chair(rng)[:96], PairSpec(num_points=96, num_subsampled=64), rng)
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in pair.items()}


def non_contiguous(t: torch.Tensor) -> torch.Tensor:
    """Same values, transposed storage (last two dims stored swapped)."""
    out = t.mT.contiguous().mT
    assert not out.is_contiguous() or t.shape[-1] == 1 or t.shape[-2] == 1
    return out


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def pytest_terminal_summary(terminalreporter):
    """After a run that executed the emulated CUDA kernels: which ran, how often, on how many cases."""
    import sys

    module = sys.modules.get("test_cuda_emulation")
    if module is not None and hasattr(torch.ops.vrnet_ext_emu, "emu_stats"):
        terminalreporter.section("CUDA kernels executed under the emulator")
        terminalreporter.write_line(module.summary())
