"""VRNet's eval forward replayed as CUDA graphs: one graph per input shape, captured on first use.

A forward of one pair launches hundreds of small kernels; replaying them as one graph removes the
per-launch host cost. Capture needs a forward without host reads: the clouds are checked once
before each replay (one synchronisation), the forward runs inside
:func:`vrnet_ext.ops.trusted_values`, and a configured second look is taken by every pair with the
choice made on the device (:meth:`VRNet._second_looks`), so a graphed forward costs a second look
per pair where the eager one pays only for the pairs that are due. The rotation search branches on
data and is refused. Each graph keeps its own memory pool (the forward's peak at that shape) until
the object is dropped; outputs are fresh tensors (cloned from the graph's).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from vrnet_ext.model.vrnet import VRNet, VRNetOutput
from vrnet_ext.ops._checks import check_all_finite, trusted_values

WARMUP_FORWARDS = 2  # eager forwards on a side stream before a capture (lazy initialisation, caches)


@dataclass
class _Graph:
    graph: torch.cuda.CUDAGraph
    src: torch.Tensor
    tgt: torch.Tensor
    out: VRNetOutput


class CudaGraphForward:
    """``graphed(src, tgt)`` returns what ``model(src, tgt, backend=backend)`` returns, for CUDA
    tensors, replaying a graph captured per (shapes, dtype, device). ``model`` in eval mode, on the
    GPU, with ``rotation_search_below`` 0; gradients are not recorded."""

    def __init__(self, model: VRNet, backend: str | None = None) -> None:
        if model.training:
            raise ValueError("CudaGraphForward replays the eval forward: call model.eval() first")
        if model.config.rotation_search_below > 0:
            raise ValueError("CudaGraphForward cannot capture the rotation search (it branches on the data): "
                             "set rotation_search_below to 0 or run the model eagerly")
        if not torch.cuda.is_available():
            raise ValueError("CudaGraphForward needs a CUDA device")
        self.model, self.backend = model, backend
        self._graphs: dict[tuple, _Graph] = {}

    def __call__(self, src: torch.Tensor, tgt: torch.Tensor) -> VRNetOutput:
        for name, cloud in (("src", src), ("tgt", tgt)):
            if not isinstance(cloud, torch.Tensor) or not cloud.is_cuda:
                raise ValueError(f"{name} must be a CUDA tensor for a CUDA graph, got "
                                 f"{cloud.device if isinstance(cloud, torch.Tensor) else type(cloud).__name__}")
        key = (tuple(src.shape), tuple(tgt.shape), src.dtype, tgt.dtype, src.device)
        captured = self._graphs.get(key)
        if captured is None:
            captured = self._graphs[key] = self._capture(src, tgt)  # the model checks the clouds here
        else:
            check_all_finite({"src": src, "tgt": tgt})
        captured.src.copy_(src)
        captured.tgt.copy_(tgt)
        captured.graph.replay()
        values = {f.name: getattr(captured.out, f.name) for f in fields(VRNetOutput)}
        return VRNetOutput(**{name: None if value is None else value.clone() for name, value in values.items()})

    def _capture(self, src: torch.Tensor, tgt: torch.Tensor) -> _Graph:
        static_src, static_tgt = src.clone(), tgt.clone()
        with torch.no_grad():
            self.model(static_src, static_tgt, backend=self.backend)  # checks the clouds and their shapes
            side = torch.cuda.Stream(device=src.device)
            side.wait_stream(torch.cuda.current_stream(src.device))
            with torch.cuda.stream(side), trusted_values():
                for _ in range(WARMUP_FORWARDS):
                    self.model(static_src, static_tgt, backend=self.backend)
            torch.cuda.current_stream(src.device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph), trusted_values():
                out = self.model(static_src, static_tgt, backend=self.backend)
        return _Graph(graph=graph, src=static_src, tgt=static_tgt, out=out)


__all__ = ["CudaGraphForward"]
