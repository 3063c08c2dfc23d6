import copy

import pytest
import torch

from conftest import compile_fullgraph, requires_ext
from vrnet_ext import ops
from vrnet_ext.nn import EdgeConv


def make_pair(C, O, dtype, negative_scales=False):
    fused = EdgeConv(C, O).to(dtype)
    if negative_scales:  # some channels with a negative BN scale exercise the min branch
        with torch.no_grad():
            fused.bn.weight.copy_(torch.randn(O, dtype=dtype))
            fused.bn.bias.copy_(torch.randn(O, dtype=dtype))
    return fused, copy.deepcopy(fused)


def graph(x, k):
    points = x.detach().mT
    return ops.knn(points, points, k)[1]


@requires_ext
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("negative_scales", [False, True])
@pytest.mark.parametrize("B,C,O,N,k", [(1, 3, 8, 33, 33), (4, 16, 24, 101, 10)])
def test_matches_materialising_layer(device, dtype, negative_scales, B, C, O, N, k):
    fused, reference = make_pair(C, O, dtype, negative_scales)
    x = (torch.randn(B, C, N, dtype=dtype) * 3 + 1).requires_grad_()
    idx = graph(x, k)
    grad = torch.randn(B, O, N, dtype=dtype)
    tol = dict(rtol=2e-4, atol=2e-4) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-9)
    for step in range(3):  # several train steps: running stats must track identically
        out_f = fused(x, idx)
        out_r = reference(x, idx, backend="torch")
        torch.testing.assert_close(out_f, out_r, **tol)
        gx_f, gw_f, gg_f, gb_f = torch.autograd.grad((out_f * grad).sum(), (x, fused.conv.weight, fused.bn.weight, fused.bn.bias))
        gx_r, gw_r, gg_r, gb_r = torch.autograd.grad((out_r * grad).sum(), (x, reference.conv.weight, reference.bn.weight, reference.bn.bias))
        for a, b in ((gx_f, gx_r), (gw_f, gw_r), (gg_f, gg_r), (gb_f, gb_r)):
            torch.testing.assert_close(a, b, **tol)
    torch.testing.assert_close(fused.bn.running_mean, reference.bn.running_mean, **tol)
    torch.testing.assert_close(fused.bn.running_var, reference.bn.running_var, **tol)
    assert int(fused.bn.num_batches_tracked) == int(reference.bn.num_batches_tracked) == 3
    fused.eval()
    reference.eval()
    torch.testing.assert_close(fused(x, idx), reference(x, idx, backend="torch"), **tol)


@requires_ext
def test_gradcheck_train_mode(device):
    layer = EdgeConv(3, 4).double()
    x = torch.randn(2, 3, 12, dtype=torch.float64, requires_grad=True)
    idx = graph(x, 4)
    assert torch.autograd.gradcheck(lambda t: layer(t, idx), (x,))


@requires_ext
def test_torch_compile_fullgraph(device):
    layer = EdgeConv(3, 8).eval()
    x = torch.randn(2, 3, 50)
    idx = graph(x, 6)
    fn = compile_fullgraph(layer)
    torch.testing.assert_close(fn(x, idx), layer(x, idx))


def test_bad_input():
    layer = EdgeConv(3, 8)
    with pytest.raises(ValueError, match="x must have shape"):
        layer(torch.randn(2, 4, 10), torch.zeros(2, 10, 3, dtype=torch.long))
