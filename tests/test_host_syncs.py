"""VRNet's forward reads no tensor value on the host but its one input check: on a GPU each such
read is a synchronisation that stalls the launch queue (and breaks CUDA-graph capture).

On the CPU the census counts the operators that return host values or shapes that depend on the
data (``aten._local_scalar_dense`` behind ``bool()`` / ``int()`` / ``.item()``, ``nonzero``, boolean
masks) as the Python code issues them, both backends; on a GPU ``torch.cuda.set_sync_debug_mode``
counts every synchronisation, the compiled kernels' included.
"""
import warnings
from collections import Counter
from dataclasses import replace

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from conftest import requires_ext
from test_model import small_model
from vrnet_ext import load_pretrained, ops
from vrnet_ext.ops import trusted_values

HOST_READS = {"aten._local_scalar_dense.default", "aten.nonzero.default", "aten.is_nonzero.default",
              "aten.equal.default", "aten.masked_select.default", "aten._unique2.default",
              "aten.unique_consecutive.default"}
MASKED = {"aten.index.Tensor", "aten.index_put.default", "aten.index_put_.default"}


class HostReads(TorchDispatchMode):
    """Counts the operators that hand a value or a data-dependent shape to the host."""

    def __init__(self) -> None:
        super().__init__()
        self.count = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func)
        indices = args[1] if name in MASKED and len(args) > 1 else ()
        if name in HOST_READS or any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices or ()):
            self.count[name] += 1
        return func(*args, **(kwargs or {}))


def pair(points: int = 96, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(1, points, 3, generator=g)
    rotation = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0].float()
    return src, src @ rotation.T * torch.sign(torch.det(rotation)) + 0.1


def one_look(model):
    """The model without its data-dependent second look."""
    model.config = replace(model.config, second_pass_below=0.0)
    return model


@requires_ext
@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_eval_forward_reads_the_host_for_its_input_check_and_second_look_only(backend):
    model = load_pretrained()
    assert model.config.second_pass_below > 0
    src, tgt = pair(model.config.k * 8)
    with torch.no_grad():
        expected = model(src, tgt, backend=backend)
        with HostReads() as reads:
            out = model(src, tgt, backend=backend)
        assert reads.count == {"aten._local_scalar_dense.default": 1, "aten.nonzero.default": 1}, reads.count
        with trusted_values(), HostReads() as reads:
            trusted = model(src, tgt, backend=backend)
        assert reads.count == {"aten.nonzero.default": 1}, reads.count  # which pairs take a second look
        one_look(model)
        with HostReads() as reads:
            model(src, tgt, backend=backend)
        assert reads.count == {"aten._local_scalar_dense.default": 1}, reads.count
        with trusted_values(), HostReads() as reads:
            model(src, tgt, backend=backend)
        assert not reads.count, reads.count
    for result in (out, trusted):
        torch.testing.assert_close(result.rotation, expected.rotation, rtol=0, atol=0)


@requires_ext
@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_training_step_reads_the_host_once(backend):
    """Forward and backward of a training-mode model: the finite check of the clouds only."""
    model = small_model().train()
    src, tgt = pair()
    with HostReads() as reads:
        out = model(src, tgt, backend=backend, return_matching=True)
        (out.rotation.square().sum() + out.rcp.square().mean() + out.matching.sum()).backward()
    assert sum(reads.count.values()) == 1, reads.count


def test_trusted_values_skips_the_value_checks_of_the_references_only_inside():
    nan = torch.full((1, 8, 3), float("nan"))
    with pytest.raises(ValueError, match="query"):
        ops.knn(nan, nan, 2, backend="torch")
    with trusted_values():
        ops.knn(nan, nan, 2, backend="torch")  # the caller vouches: no check, no error
    with trusted_values(False), pytest.raises(ValueError, match="query"):
        ops.knn(nan, nan, 2, backend="torch")
    with pytest.raises(ValueError, match="query"):
        ops.knn(nan, nan, 2, backend="torch")


@requires_ext
def test_compiled_kernels_on_the_cpu_check_values_even_inside_trusted_values():
    """CPU kernels rely on finite points for their memory accesses (grid cells of the kNN)."""
    nan = torch.full((1, 8, 3), float("nan"))
    with trusted_values(), pytest.raises(ValueError, match="query"):
        ops.knn(nan, nan, 2, backend="ext")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_forward_synchronises_only_for_its_input_check():
    model = one_look(load_pretrained()).cuda()
    src, tgt = (t.cuda() for t in pair(768))
    with torch.no_grad():
        model(src, tgt)  # warm-up: lazy initialisation may synchronise
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            with trusted_values():
                out = model(src, tgt)
        finally:
            torch.cuda.set_sync_debug_mode("default")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                model(src, tgt)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    assert len([w for w in caught if "synchroniz" in str(w.message)]) == 1, [str(w.message) for w in caught]
    assert torch.isfinite(out.rotation).all()
