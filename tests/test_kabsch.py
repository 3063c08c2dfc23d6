import pytest
import torch

from conftest import DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext
from vrnet_ext import ops


def random_rotation(B, dtype=torch.float64):
    q = torch.linalg.qr(torch.randn(B, 3, 3, dtype=torch.float64)).Q
    q = q * torch.sign(torch.linalg.det(q)).view(-1, 1, 1)
    return q.to(dtype)


def transformed(B, N, dtype, noise=0.0):
    R = random_rotation(B, dtype)
    t = torch.randn(B, 3, dtype=dtype)
    src = torch.randn(B, N, 3, dtype=dtype)
    tgt = src @ R.mT + t.unsqueeze(1) + noise * torch.randn(B, N, 3, dtype=dtype)
    return src, tgt, R, t


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 3), (5, 37), (64, 1000)])
def test_recovers_known_transform(device, dtype, B, N):
    src, tgt, R, t = transformed(B, N, dtype)
    R_est, t_est = ops.kabsch(non_contiguous(src), tgt)
    atol = 1e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(R_est, R, rtol=0, atol=atol)
    torch.testing.assert_close(t_est, t, rtol=0, atol=atol)
    torch.testing.assert_close(torch.linalg.det(R_est), torch.ones(B, dtype=dtype), rtol=0, atol=atol)


@requires_ext
def test_float32_accuracy_against_float64(device):
    src, tgt, _, _ = transformed(4096, 32, torch.float64, noise=0.3)
    R64 = ops.kabsch(src, tgt, backend="torch")[0]
    R32 = ops.kabsch(src.float(), tgt.float())[0]
    assert (R32.double() - R64).abs().max() <= 1e-5


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
def test_weighted_parity_and_outlier_rejection(device, dtype):
    src, tgt, R, t = transformed(6, 50, dtype, noise=0.05)
    weights = torch.rand(6, 50, dtype=dtype)
    for got, want in zip(ops.kabsch(src, tgt, weights), ops.kabsch(src, tgt, weights, backend="torch")):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    clean_src, clean_tgt, R, t = transformed(2, 40, dtype)
    clean_tgt[:, :10] += 5 * torch.randn(2, 10, 3, dtype=dtype)  # outliers with zero weight
    w = torch.ones(2, 40, dtype=dtype)
    w[:, :10] = 0
    R_est, t_est = ops.kabsch(clean_src, clean_tgt, w)
    torch.testing.assert_close(R_est, R, rtol=0, atol=1e-4)
    # Weights enter once: scaling all weights changes nothing.
    torch.testing.assert_close(ops.kabsch(src, tgt, weights * 7.5)[0], ops.kabsch(src, tgt, weights)[0])


@requires_ext
def test_reflection_is_fixed(device):
    src = torch.randn(3, 20, 3, dtype=torch.float64)
    tgt = src * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # a mirror image
    R, _ = ops.kabsch(src, tgt)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(3, dtype=torch.float64))
    torch.testing.assert_close(R, ops.kabsch(src, tgt, backend="torch")[0], rtol=0, atol=1e-8)


@requires_ext
def test_gradcheck_src_tgt_weights(device):
    src, tgt, _, _ = transformed(3, 8, torch.float64, noise=0.2)
    weights = torch.rand(3, 8, dtype=torch.float64) + 0.1
    args = tuple(a.clone().requires_grad_() for a in (src, tgt, weights))
    assert torch.autograd.gradcheck(lambda s, g, w: ops.kabsch(s, g, w), args)


@requires_ext
def test_backward_matches_reference(device):
    src, tgt, _, _ = transformed(20, 30, torch.float64, noise=0.3)
    weights = torch.rand(20, 30, dtype=torch.float64)
    grads = []
    for backend in ("ext", "torch"):
        args = [a.clone().requires_grad_() for a in (src, tgt, weights)]
        R, t = ops.kabsch(*args, backend=backend)
        (R.square().mul(torch.arange(9.0, dtype=torch.float64).view(3, 3)).sum() + t.sin().sum()).backward()
        grads.append([a.grad for a in args])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)


@requires_ext
@pytest.mark.parametrize("case", ["collinear", "duplicate", "planar_symmetric"])
def test_degenerate_inputs_stay_finite(device, case):
    if case == "collinear":
        src = torch.linspace(0, 1, 10, dtype=torch.float64).view(1, 10, 1) * torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    elif case == "duplicate":
        src = torch.ones(1, 10, 3, dtype=torch.float64)
    else:  # a square: two equal singular values
        src = torch.tensor([[[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]]], dtype=torch.float64)
    src = src.clone().requires_grad_()
    tgt = (src.detach() @ random_rotation(1).mT + 1).requires_grad_()
    R, t = ops.kabsch(src, tgt)
    assert bool(torch.isfinite(R).all()) and bool(torch.isfinite(t).all())
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(1, dtype=torch.float64))
    torch.testing.assert_close(src.detach() @ R.mT + t.unsqueeze(1), tgt.detach(), rtol=0, atol=1e-8)
    (R.sum() + t.sum()).backward()
    assert bool(torch.isfinite(src.grad).all()) and bool(torch.isfinite(tgt.grad).all())


@requires_ext
def test_opcheck_and_compile(device):
    src, tgt, _, _ = transformed(4, 10, torch.float32, noise=0.1)
    weights = torch.rand(4, 10) + 0.1
    opcheck(torch.ops.vrnet_ext.kabsch.default, (src.requires_grad_(), tgt.requires_grad_(), weights.requires_grad_()))
    fn = compile_fullgraph(lambda s, g: ops.kabsch(s, g))
    torch.testing.assert_close(fn(src.detach(), tgt.detach()), ops.kabsch(src.detach(), tgt.detach()))


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    src = torch.randn(2, 10, 3)
    cases = [
        ((src[0], src), ValueError, "src"),
        ((src, src[:, :5]), ValueError, "tgt"),
        ((src, src, torch.ones(2, 9)), ValueError, "weights"),
        ((src.int(), src), TypeError, "src"),
        ((src, src.double()), TypeError, "tgt"),
        ((src[:, :2], src[:, :2]), ValueError, "at least 3"),
        ((src[:, :0], src[:, :0]), ValueError, "at least 3"),
        ((src, src, -torch.ones(2, 10)), ValueError, "non-negative"),
        ((src, src, torch.zeros(2, 10)), ValueError, "sum to zero"),
        ((src, src.to("meta")), ValueError, "tgt"),
    ]
    for args, error, name in cases:
        with pytest.raises(error, match=name):
            ops.kabsch(*args, backend=backend)
    poisoned = src.clone()
    poisoned[0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="NaN or Inf"):
        ops.kabsch(src, poisoned, backend=backend)


def test_huge_weights_and_coordinates_keep_exact_results_and_gradients():
    g = torch.Generator().manual_seed(2)
    src = torch.randn(2, 10, 3, dtype=torch.float64, generator=g)
    tgt = src.flip(1) + 0.1
    R_unit, t_unit = ops.kabsch(src, tgt, torch.ones(2, 10, dtype=torch.float64))
    R_huge, t_huge = ops.kabsch(src, tgt, torch.full((2, 10), 1e300, dtype=torch.float64))  # the sum overflows
    torch.testing.assert_close(R_huge, R_unit)
    torch.testing.assert_close(t_huge, t_unit)
    # float32 at |x| ~ 1e20: the weight gradient's intermediates overflow float32 (regression)
    x = (torch.randn(1, 8, 3, generator=g) * 1e20).requires_grad_()
    y = torch.randn(1, 8, 3, generator=g) * 1e20
    w = (torch.rand(1, 8, generator=g) + 0.1).requires_grad_()
    ops.kabsch(x, y, w)[0].sum().backward()
    w64 = w.detach().double().requires_grad_()
    ops.kabsch(x.detach().double(), y.double(), w64)[0].sum().backward()
    assert torch.isfinite(w.grad).all()
    assert (w.grad.double() - w64.grad).norm() / w64.grad.norm() < 1e-4
