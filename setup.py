"""Build the compiled module ``vrnet_ext._C`` against the torch that is already installed.

CUDA sources (``csrc/*/*.cu``) are compiled only when the installed torch is a CUDA build and a
toolkit is found (``torch.utils.cpp_extension.CUDA_HOME``), or when ``FORCE_CUDA=1``.
``VRNET_FORCE_CPU=1`` always builds the CPU-only module. The GPU architectures come from
``TORCH_CUDA_ARCH_LIST`` (e.g. ``"9.0+PTX"`` for H100/H200 plus PTX for newer GPUs); unset, torch
picks the visible GPUs' architectures.
"""
import glob
import os
import sys

from setuptools import setup

try:
    from torch.utils import cpp_extension
except ImportError:  # pip's build isolation hides the torch the user installed
    sys.exit("vrnet_ext compiles against the PyTorch you have installed: install torch first "
             "(e.g. pip install torch), then pip install --no-build-isolation vrnet_ext (or '.' in a clone)")

ROOT = os.path.dirname(os.path.abspath(__file__))
# No --use_fast_math: the CUDA kernels must round like the CPU ones (tests compare them).
NVCC_FLAGS = ["-O3", "--expt-relaxed-constexpr", "-lineinfo"]


def _want_cuda() -> bool:
    if os.environ.get("VRNET_FORCE_CPU", "0") == "1":
        return False
    if os.environ.get("FORCE_CUDA", "0") == "1":
        return True
    import torch

    return torch.version.cuda is not None and cpp_extension.CUDA_HOME is not None


def _extension():
    # csrc/cuda_emu holds only the emulator's headers (its runtime is test infrastructure: tests/cuda_emu).
    sources = glob.glob(os.path.join("csrc", "**", "*.*"), recursive=True)
    cpp_sources = sorted(p for p in sources if p.endswith(".cpp"))
    cuda_sources = sorted(p for p in sources if p.endswith(".cu"))
    # -ffp-contract=off: no fused multiply-adds behind our back, so the CPU kernels round exactly as
    # written (the CUDA kNN rounds the same way with __fadd_rn/__fmul_rn; tests compare them bit for bit).
    cxx_flags = ["-O3", "-fopenmp", "-ffp-contract=off", "-DTORCH_ASSERT_ONLY_METHOD_OPERATORS"]
    common = dict(
        name="vrnet_ext._C",
        include_dirs=[os.path.join(ROOT, "csrc")],
        extra_link_args=["-fopenmp"],
    )
    if _want_cuda() and cuda_sources:
        return cpp_extension.CUDAExtension(
            sources=cpp_sources + cuda_sources,
            define_macros=[("VRNET_WITH_CUDA", None)],
            extra_compile_args={"cxx": cxx_flags, "nvcc": NVCC_FLAGS},
            **common,
        )
    return cpp_extension.CppExtension(
        sources=cpp_sources, extra_compile_args={"cxx": cxx_flags}, **common
    )


setup(
    ext_modules=[_extension()],
    cmdclass={"build_ext": cpp_extension.BuildExtension.with_options(use_ninja=True)},
)
