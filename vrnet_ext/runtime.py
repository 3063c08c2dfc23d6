"""Process-wide numeric settings."""
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
