import pytest
import torch

from conftest import (DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext, tolerances,
                      under_each_cpu_dispatch)
from vrnet_ext import ops


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 2), (3, 37), (2, 1029)])
def test_forward_backward_parity(device, dtype, B, N):
    x = non_contiguous(torch.randn(B, N, 3, dtype=dtype)).requires_grad_()
    y = (torch.randn(B, N, 3, dtype=dtype) * 1.5).requires_grad_()
    outs, grads = [], []
    for backend in ("ext", "torch"):
        loss = ops.pairwise_distance_loss(x, y, backend=backend)
        (loss * torch.arange(1, B + 1, dtype=dtype)).sum().backward()
        outs.append(loss)
        grads.append((x.grad, y.grad))
        x.grad = y.grad = None
    tol = tolerances(dtype)
    torch.testing.assert_close(outs[0], outs[1], **tol)
    torch.testing.assert_close(grads[0], grads[1], rtol=tol["rtol"] * 10, atol=tol["atol"] * 10)


@requires_ext
def test_rigid_motion_gives_zero_loss_and_finite_gradient(device):
    x = torch.randn(2, 100, 3, dtype=torch.float64)
    R = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64)).Q
    y = (x @ R.T + 3.0).requires_grad_()
    loss = ops.pairwise_distance_loss(x, y)
    assert loss.max() < 1e-12
    loss.sum().backward()
    assert bool(torch.isfinite(y.grad).all())


@requires_ext
def test_coincident_points_have_finite_gradient(device):
    x = torch.randn(1, 20, 3, dtype=torch.float64)
    x[0, 5] = x[0, 6] = x[0, 7]
    y = torch.randn(1, 20, 3, dtype=torch.float64)
    y[0, 1] = y[0, 2]
    x.requires_grad_()
    y.requires_grad_()
    ops.pairwise_distance_loss(x, y).sum().backward()
    assert bool(torch.isfinite(x.grad).all()) and bool(torch.isfinite(y.grad).all())


@requires_ext
def test_hand_checkable_value(device):
    x = torch.tensor([[[0.0, 0, 0], [1, 0, 0]]], dtype=torch.float64)
    y = torch.tensor([[[0.0, 0, 0], [3, 0, 0]]], dtype=torch.float64)
    # pairs (0,1) and (1,0) differ by 2, the diagonal by 0: sqrt((4 + 4) / 4)
    torch.testing.assert_close(ops.pairwise_distance_loss(x, y), torch.tensor([2.0 ** 0.5], dtype=torch.float64))


@requires_ext
def test_gradcheck_opcheck_compile(device):
    x = torch.randn(2, 9, 3, dtype=torch.float64, requires_grad=True)
    y = torch.randn(2, 9, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: ops.pairwise_distance_loss(a, b), (x, y))
    opcheck(torch.ops.vrnet_ext.pairwise_distance_loss.default, (x.float().detach().requires_grad_(), y.float().detach().requires_grad_()))
    fn = compile_fullgraph(lambda a, b: ops.pairwise_distance_loss(a, b))
    torch.testing.assert_close(fn(x.detach(), y.detach()), ops.pairwise_distance_loss(x.detach(), y.detach()))


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    x = torch.randn(2, 10, 3)
    cases = [
        ((x[0], x), ValueError, "x"),
        ((x, x[:, :4]), ValueError, "y"),
        ((x[:, :1], x[:, :1]), ValueError, "at least 2"),
        ((x.long(), x), TypeError, "x"),
        ((x, x.double()), TypeError, "y"),
        ((x, x.to("meta")), ValueError, "y"),
    ]
    for args, error, name in cases:
        with pytest.raises(error, match=name):
            ops.pairwise_distance_loss(*args, backend=backend)
    poisoned = x.clone()
    poisoned[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        ops.pairwise_distance_loss(poisoned, x, backend=backend)


@requires_ext
def test_the_vector_and_the_portable_loops_agree(tmp_path):
    """Where the CPU has AVX-512 the partner loops run 8 doubles per register; VRNET_CPU_DISPATCH=generic
    keeps the portable loops. The same operations per lane: loss and gradients equal bit for bit
    (both precisions, point counts with and without a remainder of 8, coincident points)."""
    script = ("import sys, torch; from vrnet_ext import ops; g = torch.Generator().manual_seed(5); out = []\n"
              "for dtype in (torch.float32, torch.float64):\n"
              "    for N in (2, 8, 37, 300):\n"
              "        x = torch.randn(3, N, 3, generator=g, dtype=dtype)\n"
              "        y = (x + 0.1 * torch.randn(3, N, 3, generator=g, dtype=dtype))\n"
              "        x[0, N // 2] = x[0, 0]\n"
              "        x.requires_grad_(); y.requires_grad_()\n"
              "        loss = ops.pairwise_distance_loss(x, y)\n"
              "        (loss * torch.tensor([1.0, -2.0, 0.5], dtype=dtype)).sum().backward()\n"
              "        out.append((loss.detach(), x.grad, y.grad))\n"
              "torch.save(out, sys.argv[1])")
    results = under_each_cpu_dispatch(script, tmp_path)
    for vector, generic in zip(*results):
        for a, b in zip(vector, generic):
            assert torch.equal(a, b)
