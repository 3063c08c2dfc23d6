"""Process-wide numeric settings and what the CPU offers."""
from __future__ import annotations

import torch

from vrnet_ext._extension import has_extension


def set_flush_denormal(enabled: bool = True) -> bool:
    """Flush denormal floats to zero (FTZ/DAZ) in every CPU worker thread.

    VRNet's soft matching has many denormal entries (softmax tails, and their gradients), on
    which x86 matrix products run an order of magnitude slower. ``torch.set_flush_denormal``
    only changes the calling thread; the compiled helper also sets the OpenMP/MKL workers.
    Returns False where the CPU has no such mode. Values below ~1.2e-38 (float32) become 0.
    """
    if has_extension():
        return bool(torch.ops.vrnet_ext.set_flush_denormal(enabled))
    return torch.set_flush_denormal(enabled)


def _detect_native_bf16() -> bool:
    checks = [getattr(torch.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    return any(check is not None and bool(check()) for check in checks)


_NATIVE_BF16 = _detect_native_bf16()  # decided once at import (a constant for torch.compile)


def cpu_has_native_bf16() -> bool:
    """True where the CPU multiplies bfloat16 matrices in hardware (AVX512-BF16 or AMX-BF16):
    there a bfloat16 product runs several times faster than a float32 one; elsewhere it is
    emulated and slower."""
    return _NATIVE_BF16


def device_has_native_bf16(device: torch.device) -> bool:
    """True where ``device`` multiplies bfloat16 matrices in hardware: a CPU with AVX512-BF16 or
    AMX (:func:`cpu_has_native_bf16`), a CUDA GPU that supports bfloat16."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    return device.type == "cpu" and cpu_has_native_bf16()


@torch.compiler.assume_constant_result
def cuda_matmul_allows_tf32() -> bool:
    """Whether torch may run float32 matrix products on a GPU in TF32 (10 mantissa bits per operand):
    ``torch.backends.cuda.matmul.fp32_precision = "tf32"``, or ``set_float32_matmul_precision("high")``
    / ``"medium"`` (torch's default: no). A constant for ``torch.compile`` (read when a graph is traced)."""
    matmul = torch.backends.cuda.matmul
    return matmul.fp32_precision == "tf32" if hasattr(matmul, "fp32_precision") else bool(matmul.allow_tf32)


@torch.compiler.assume_constant_result
def _tensor_cores(device_index: int) -> bool:
    return torch.cuda.get_device_capability(device_index)[0] >= 8


def cuda_has_tensor_cores(device: torch.device) -> bool:
    """Whether the CUDA ``device`` has TF32 tensor cores (compute capability 8.0 or later): what the
    compiled kernels that run on them need. A constant for ``torch.compile``."""
    return _tensor_cores(torch.cuda.current_device() if device.index is None else device.index)


@torch.compiler.assume_constant_result
def _multiprocessors(device_index: int) -> int:
    return torch.cuda.get_device_properties(device_index).multi_processor_count


def cuda_multiprocessors(device: torch.device) -> int:
    """The streaming multiprocessors of the CUDA ``device`` (132 on an H100 / H200). A constant for
    ``torch.compile``."""
    return _multiprocessors(torch.cuda.current_device() if device.index is None else device.index)
