"""Loads the compiled kernels (``vrnet_ext._C``) and tells which devices they serve.

If the module is missing or fails to load, the package still imports: every op falls back to
its pure-PyTorch reference and one warning says why.
"""
from __future__ import annotations

import warnings

import torch

from vrnet_ext.names import BACKENDS

try:
    from vrnet_ext import _C  # noqa: F401  (importing registers torch.ops.vrnet_ext.*)

    LOAD_ERROR: Exception | None = None
except ImportError as exc:  # pragma: no cover - exercised only on broken installs
    LOAD_ERROR = exc
    warnings.warn(
        f"vrnet_ext: compiled kernels unavailable ({exc}); every op falls back to its "
        "pure-PyTorch reference. Reinstall with `pip install --no-build-isolation .`.",
        RuntimeWarning,
        stacklevel=2,
    )



def has_extension() -> bool:
    """True when the compiled module loaded."""
    return LOAD_ERROR is None


def _kernel_device_types() -> frozenset[str]:
    if LOAD_ERROR is not None:
        return frozenset()
    keys = {"cpu": torch._C.DispatchKey.CPU, "cuda": torch._C.DispatchKey.CUDA}
    return frozenset(
        name for name, key in keys.items()
        if torch._C._dispatch_has_kernel_for_dispatch_key("vrnet_ext::knn", key)
    )


KERNEL_DEVICE_TYPES = _kernel_device_types()


# Ops built for a lower precision: autocast leaves their inputs as they are (``attention`` takes
# the bfloat16 heads that autocast's projections produce).
NATIVE_PRECISION_OPS = frozenset({"vrnet_ext::attention"})


def _register_autocast() -> None:
    """Every compiled op but those of ``NATIVE_PRECISION_OPS`` runs in float32 under autocast: its
    inputs are promoted and autocast is off inside it, so the matrix products a kernel issues
    itself (the GEMM tiles of ``knn``) are not lowered to bfloat16 behind its back."""
    names = [name for name in torch._C._dispatch_get_all_op_names()
             if name.startswith("vrnet_ext::") and name not in NATIVE_PRECISION_OPS]
    for name in names:
        for device_type in KERNEL_DEVICE_TYPES:
            torch.library.register_autocast(name, device_type, torch.float32)


if LOAD_ERROR is None:
    _register_autocast()


def has_kernel(device: torch.device) -> bool:
    """True when the compiled module has kernels for ``device`` (fixed at import: traceable)."""
    return device.type in KERNEL_DEVICE_TYPES


def use_extension(backend: str, device: torch.device) -> bool:
    """Whether an op call should run the compiled kernel (``backend="ext"``) or the reference."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    return backend == "ext" and has_kernel(device)
