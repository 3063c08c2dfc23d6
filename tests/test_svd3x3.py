import pytest
import torch

from conftest import DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext, tolerances
from vrnet_ext import ops


def degenerate_matrices(dtype):
    u = torch.linalg.qr(torch.randn(6, 3, 3, dtype=torch.float64)).Q
    v = torch.linalg.qr(torch.randn(6, 3, 3, dtype=torch.float64)).Q
    s = torch.tensor([[3, 2, 0], [3, 0, 0], [0, 0, 0], [2, 2, 1], [1, 1, 1], [2, 2, 2 - 1e-7]], dtype=torch.float64)
    return (u @ torch.diag_embed(s) @ v.mT).to(dtype)


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B", [1, 7, 1000])
def test_decomposition(device, dtype, B):
    A = non_contiguous(torch.randn(B, 3, 3, dtype=dtype))
    U, S, V = ops.svd3x3(A)
    tol = tolerances(dtype)
    eye = torch.eye(3, dtype=dtype).expand(B, 3, 3)
    torch.testing.assert_close(U @ torch.diag_embed(S) @ V.mT, A, rtol=tol["rtol"], atol=tol["atol"] * 10)
    torch.testing.assert_close(U.mT @ U, eye, rtol=0, atol=tol["atol"] * 10)
    torch.testing.assert_close(V.mT @ V, eye, rtol=0, atol=tol["atol"] * 10)
    torch.testing.assert_close(S, ops.svd3x3(A, backend="torch")[1], **tol)
    assert bool((S[:, :-1] >= S[:, 1:]).all())


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
def test_degenerate_matrices(device, dtype):
    A = degenerate_matrices(dtype).requires_grad_()
    U, S, V = ops.svd3x3(A)
    torch.testing.assert_close(U @ torch.diag_embed(S) @ V.mT, A.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(U.mT @ U, torch.eye(3, dtype=dtype).expand(6, 3, 3), rtol=0, atol=1e-5)
    (U.sum() + S.sum() + V.sum()).backward()
    assert bool(torch.isfinite(A.grad).all()), "backward must stay finite on repeated/zero singular values"


@requires_ext
def test_gradcheck_gauge_invariant_outputs(device):
    A = torch.randn(4, 3, 3, dtype=torch.float64, requires_grad=True)

    def invariants(M):  # S, U V^T and U diag(S) V^T do not depend on the sign of (u_i, v_i)
        U, S, V = ops.svd3x3(M)
        return S, U @ V.mT, U @ torch.diag_embed(S.square()) @ V.mT

    assert torch.autograd.gradcheck(invariants, (A,))


@requires_ext
def test_backward_matches_reference(device):
    A = torch.randn(50, 3, 3, dtype=torch.float64, requires_grad=True)
    grads = []
    for backend in ("ext", "torch"):
        U, S, V = ops.svd3x3(A, backend=backend)
        (S.sin().sum() + (U @ V.mT).square().mul(torch.arange(9.0, dtype=torch.float64).view(3, 3)).sum()).backward()
        grads.append(A.grad)
        A.grad = None
    torch.testing.assert_close(grads[0], grads[1])


@requires_ext
def test_opcheck_and_compile(device):
    A = torch.randn(5, 3, 3, requires_grad=True)
    opcheck(torch.ops.vrnet_ext.svd3x3.default, (A,))
    fn = compile_fullgraph(lambda m: ops.svd3x3(m)[1])
    torch.testing.assert_close(fn(A.detach()), ops.svd3x3(A.detach())[1])


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    for bad, error in [(torch.randn(3, 3), ValueError), (torch.randn(2, 3, 4), ValueError),
                       (torch.randn(2, 4, 3), ValueError), (torch.ones(2, 3, 3, dtype=torch.int32), TypeError),
                       (torch.randn(2, 3, 3, dtype=torch.complex64), TypeError)]:
        with pytest.raises(error, match="A"):
            ops.svd3x3(bad, backend=backend)
    A = torch.randn(2, 3, 3)
    A[1, 1, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        ops.svd3x3(A, backend=backend)


@pytest.mark.parametrize("scale", [1e-10, 1e-12, 1e-30])
def test_gradients_stay_exact_at_tiny_scales(scale):
    # regression: an absolute damping floor (1e-12) gave relative errors of 5e-4 at 1e-10, 0.64 at 1e-12
    A = (torch.randn(6, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * scale).requires_grad_()
    weights = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64).expand(6, 3)

    def sign_invariant(backend):
        U, S, V = ops.svd3x3(A, backend=backend)
        return (U @ torch.diag_embed(weights) @ V.mT).sum() + S.sum()

    ours, = torch.autograd.grad(sign_invariant("ext"), A)
    reference, = torch.autograd.grad(sign_invariant("torch"), A)
    assert (ours - reference).norm() / reference.norm() < 1e-8
