import pytest
import torch

from conftest import DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext
from vrnet_ext import ops


def random_graph(B, N, k, M=None):
    return torch.randint(0, M or N, (B, N, k))


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,C,N,k", [(1, 1, 1, 1), (1, 3, 37, 37), (3, 5, 129, 20), (2, 64, 257, 9)])
def test_forward_backward_parity(device, dtype, B, C, N, k):
    x = non_contiguous(torch.randn(B, C, N, dtype=dtype)).requires_grad_()
    idx = random_graph(B, N, k)
    grad = torch.randn(B, 2 * C, N, k, dtype=dtype)
    outs, grads = [], []
    for backend in ("ext", "torch"):
        out = ops.edge_features(x, idx, backend=backend)
        out.backward(grad)
        outs.append(out)
        grads.append(x.grad)
        x.grad = None
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0)
    torch.testing.assert_close(grads[0], grads[1])
    assert torch.equal(outs[0][:, C:, :, 0], x.detach()), "second half must be x_i"


@requires_ext
@pytest.mark.parametrize("layout", ["expanded", "permuted", "sliced"])
def test_backward_reads_strided_gradients(device, layout):
    B, C, N, k = 2, 3, 41, 7
    x = torch.randn(B, C, N, dtype=torch.float64, device=device)
    idx = random_graph(B, N, k).to(device)
    dense = torch.randn(B, 2 * C, N, k, dtype=torch.float64, device=device)
    grad = {"expanded": dense[:1, :, :1, :].expand(B, 2 * C, N, k),
            "permuted": dense.permute(0, 1, 3, 2).contiguous().permute(0, 1, 3, 2),
            "sliced": torch.randn(B, 4 * C, N, 2 * k, dtype=torch.float64, device=device)[:, ::2, :, 1::2]}[layout]
    expected = torch.ops.vrnet_ext.edge_features_backward(grad.contiguous(), idx, N)
    torch.testing.assert_close(torch.ops.vrnet_ext.edge_features_backward(grad, idx, N), expected)
    x.requires_grad_()
    ops.edge_features(x, idx).backward(grad)
    torch.testing.assert_close(x.grad, expected)


@requires_ext
def test_gradcheck_and_opcheck(device):
    x = torch.randn(2, 4, 13, dtype=torch.float64, requires_grad=True)
    idx = random_graph(2, 13, 5)
    assert torch.autograd.gradcheck(lambda t: ops.edge_features(t, idx), (x,))
    opcheck(torch.ops.vrnet_ext.edge_features.default, (x.float().detach().requires_grad_(), idx))


@requires_ext
def test_torch_compile_fullgraph(device):
    x, idx = torch.randn(2, 4, 30), random_graph(2, 30, 6)
    fn = compile_fullgraph(lambda t, i: ops.edge_features(t, i))
    torch.testing.assert_close(fn(x, idx), ops.edge_features(x, idx))


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    x, idx = torch.randn(2, 4, 10), random_graph(2, 10, 3)
    cases = [
        ((torch.randn(4, 10), idx), ValueError, "x"),
        ((x, idx.int()), TypeError, "idx"),
        ((x.int(), idx), TypeError, "x"),
        ((x, idx[:1]), ValueError, "batch"),
        ((x, idx[:, :5]), ValueError, "idx"),
        ((x, idx[..., :0]), ValueError, "k >= 1"),
        ((x, idx + 10), ValueError, "outside"),
        ((x, idx - 11), ValueError, "outside"),
        ((x, idx.to("meta")), ValueError, "idx"),
        ((x[..., :0], idx[:, :0]), ValueError, "empty"),
    ]
    for args, error, name in cases:
        with pytest.raises(error, match=name):
            ops.edge_features(*args, backend=backend)
