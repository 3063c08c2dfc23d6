"""Builds the emulated CUDA module: every ``csrc/<op>/<op>_cuda.cu`` compiled as C++ for the CPU
emulator (its headers in ``csrc/cuda_emu``, which the kernels include; its runtime here, in
``runtime.cpp``, test infrastructure only) with GCC's thread-sanitizer *instrumentation*, whose hooks the
emulator's runtime defines, plus the emulator's self-test kernels, linked into one shared library
that registers the ``vrnet_ext_emu`` ops.

``build()`` writes ``build/cuda_emu/build.ninja`` and runs ninja (incremental: only changed
translation units are recompiled); ``load()`` builds and loads it once per process.
"""
from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import torch
from torch.utils import cpp_extension

ROOT = Path(__file__).resolve().parents[2]
CSRC = ROOT / "csrc"
HERE = Path(__file__).resolve().parent
BUILD_DIR = ROOT / "build" / "cuda_emu"
LIBRARY = BUILD_DIR / "vrnet_cuda_emu.so"

_loaded = False


def kernel_sources() -> list[Path]:
    """The CUDA glue files whose kernels the emulator runs (all of csrc's)."""
    return sorted(CSRC.glob("*/*_cuda.cu"))


def _flags() -> list[str]:
    abi = int(torch._C._GLIBCXX_USE_CXX11_ABI)
    includes = [str(CSRC), *cpp_extension.include_paths(), sysconfig.get_paths()["include"]]
    return ["-std=c++20", "-fPIC", "-O1", "-g0", "-ffp-contract=off", f"-D_GLIBCXX_USE_CXX11_ABI={abi}",
            "-DVRNET_CUDA_EMULATION", "-DTORCH_ASSERT_ONLY_METHOD_OPERATORS", "-Wno-deprecated-declarations",
            *[f"-I{path}" for path in includes]]


def _ninja_file() -> str:
    flags = " ".join(_flags())
    libs = " ".join(f"-L{path} -Wl,-rpath,{path}" for path in cpp_extension.library_paths())
    units = [(HERE / "runtime.cpp", "cxx")]
    units += [(source, "cxx_instrumented") for source in kernel_sources()]
    units += [(HERE / "selftest_kernels.cu", "cxx_instrumented")]
    lines = [
        f"flags = {flags}",
        "rule cxx",
        "  command = c++ -MMD -MF $out.d $flags -x c++ -c $in -o $out",
        "  depfile = $out.d",
        "  deps = gcc",
        "rule cxx_instrumented",
        # Instrumentation only: the emulator's runtime defines the __tsan_* hooks (no libtsan).
        "  command = c++ -MMD -MF $out.d $flags -fsanitize=thread -x c++ -c $in -o $out",
        "  depfile = $out.d",
        "  deps = gcc",
        "rule link",
        f"  command = c++ -shared $in -o $out {libs} -lc10 -ltorch_cpu -ltorch",
    ]
    objects = []
    for source, rule in units:
        obj = f"{source.parent.name}_{source.stem}.o"
        objects.append(obj)
        lines.append(f"build {obj}: {rule} {source}")
    lines.append(f"build {LIBRARY.name}: link {' '.join(objects)}")
    return "\n".join(lines) + "\n"


def build(verbose: bool = False) -> Path:
    """Builds (or brings up to date) the emulated module; returns its path."""
    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    ninja_file = BUILD_DIR / "build.ninja"
    text = _ninja_file()
    if not ninja_file.exists() or ninja_file.read_text() != text:
        ninja_file.write_text(text)
    jobs = str(max(1, min(4, os.cpu_count() or 1)))
    result = subprocess.run([sys.executable, "-m", "ninja", "-C", str(BUILD_DIR), "-j", jobs],
                            capture_output=not verbose, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"building the emulated CUDA module failed:\n{result.stdout}\n{result.stderr}")
    return LIBRARY


def load() -> None:
    """Builds and loads the module once: its ops appear under ``torch.ops.vrnet_ext_emu``."""
    global _loaded
    if not _loaded:
        torch.ops.load_library(str(build()))
        _loaded = True


if __name__ == "__main__":
    print(build(verbose=True))
