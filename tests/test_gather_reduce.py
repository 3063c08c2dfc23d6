import pytest
import torch

from conftest import DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext
from vrnet_ext import ops

REDUCTIONS = ["max", "min", "sum", "mean"]


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("reduce", REDUCTIONS)
@pytest.mark.parametrize("B,C,M,N,k", [(1, 1, 1, 1, 1), (1, 3, 37, 37, 37), (3, 64, 129, 100, 20), (2, 5, 50, 257, 3)])
def test_forward_backward_parity(device, dtype, reduce, B, C, M, N, k):
    values = non_contiguous(torch.randn(B, C, M, dtype=dtype)).requires_grad_()
    idx = torch.randint(0, M, (B, N, k))
    grad = torch.randn(B, C, N, dtype=dtype)
    outs, grads = [], []
    for backend in ("ext", "torch"):
        out = ops.gather_reduce(values, idx, reduce, backend=backend)
        out.backward(grad)
        outs.append(out)
        grads.append(values.grad)
        values.grad = None
    assert outs[0].shape == (B, C, N)
    torch.testing.assert_close(outs[0], outs[1])
    torch.testing.assert_close(grads[0], grads[1])


@requires_ext
def test_max_backward_routes_to_first_winner_on_ties(device):
    values = torch.tensor([[[1.0, 5.0, 5.0, 2.0]]], requires_grad=True)
    idx = torch.tensor([[[2, 1, 0]]])  # neighbours 2 and 1 tie at 5: slot 0 (point 2) wins
    ops.gather_reduce(values, idx, "max").sum().backward()
    assert values.grad.tolist() == [[[0.0, 0.0, 1.0, 0.0]]]


@requires_ext
@pytest.mark.parametrize("reduce", REDUCTIONS)
def test_gradcheck_and_opcheck(device, reduce):
    values = torch.randn(2, 3, 11, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 11, (2, 7, 4))
    assert torch.autograd.gradcheck(lambda v: ops.gather_reduce(v, idx, reduce), (values,))
    opcheck(torch.ops.vrnet_ext.gather_reduce.default, (values.float().detach().requires_grad_(), idx, reduce))


@requires_ext
def test_torch_compile_fullgraph(device):
    values, idx = torch.randn(2, 8, 40), torch.randint(0, 40, (2, 40, 5))
    fn = compile_fullgraph(lambda v, i: ops.gather_reduce(v, i, "max") + ops.gather_reduce(v, i, "mean"))
    torch.testing.assert_close(fn(values, idx), ops.gather_reduce(values, idx, "max") + ops.gather_reduce(values, idx, "mean"))


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    values, idx = torch.randn(2, 4, 10), torch.randint(0, 10, (2, 6, 3))
    with pytest.raises(ValueError, match="reduce"):
        ops.gather_reduce(values, idx, "median", backend=backend)
    cases = [
        ((values[0], idx), ValueError, "values"),
        ((values, idx.float()), TypeError, "idx"),
        ((values.long(), idx), TypeError, "values"),
        ((values, idx[:1]), ValueError, "batch"),
        ((values, idx + 10), ValueError, "outside"),
        ((values, idx[..., :0]), ValueError, "k >= 1"),
        ((values[..., :0], idx[:, :0]), ValueError, "empty"),
    ]
    for args, error, name in cases:
        with pytest.raises(error, match=name):
            ops.gather_reduce(*args, backend=backend)
