import pytest
import torch

from conftest import DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext
from vrnet_ext import ops
from vrnet_ext.ops.kabsch import robust_kabsch_reference, robust_weights


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


def outlier_problem(B, N, dtype, seed, far=0.3):
    """src, tgt with 40 % of the targets pushed off by up to ``far`` (some only slightly), the truth."""
    from scipy.spatial.transform import Rotation

    g = torch.Generator().manual_seed(seed)  # drawn on the CPU, the same on every device
    cpu64 = dict(generator=g, dtype=torch.float64, device="cpu")
    src = torch.rand(B, N, 3, **cpu64) * 2 - 1
    R = torch.tensor(Rotation.from_euler("zyx", [-40, 25, 5], degrees=True).as_matrix(), device="cpu").expand(B, 3, 3)
    tgt = src @ R.mT - 0.2 + 1e-4 * torch.randn(B, N, 3, **cpu64)
    pushed = int(0.4 * N)
    tgt[:, :pushed] += far * torch.rand(B, pushed, 3, **cpu64)
    device = torch.get_default_device()
    return src.to(device, dtype), tgt.to(device, dtype), R.to(device, dtype)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_robust_kabsch_ignores_gross_outliers_that_spoil_plain_kabsch(backend):
    from vrnet_ext.geometry.metrics import rotation_error_deg

    g = torch.Generator().manual_seed(0)
    src = torch.rand(3, 200, 3, generator=g, dtype=torch.float64) * 2 - 1
    R = random_rotation(1).expand(3, 3, 3)
    tgt = src @ R.mT + 0.3
    tgt[:, :60] = torch.rand(3, 60, 3, generator=g, dtype=torch.float64)  # 30 % wrong correspondences
    plain, _ = ops.robust_kabsch(src, tgt, None, 0, backend=backend)
    robust, t = ops.robust_kabsch(src, tgt, None, 5, backend=backend)
    assert rotation_error_deg(plain, R).min() > 0.5
    assert rotation_error_deg(robust, R).max() < 1e-3 and (t - 0.3).abs().max() < 1e-5
    torch.testing.assert_close(plain, ops.kabsch(src, tgt, backend=backend)[0])


@pytest.mark.parametrize("backend", ["ext", "torch"])
@pytest.mark.parametrize("kernel, scale", [("cauchy", 0.5), ("geman_mcclure", 1.0), ("geman_mcclure", 3.0),
                                           ("welsch", 0.75)])
def test_a_tight_or_steep_kernel_removes_the_bias_of_outliers_near_the_inliers(backend, kernel, scale):
    from vrnet_ext.geometry.metrics import rotation_error_deg

    src, tgt, R = outlier_problem(2, 300, torch.float64, seed=1)
    rotation, translation = ops.robust_kabsch(src, tgt, None, 10, kernel, scale, 1e-6, backend=backend)
    assert rotation_error_deg(rotation, R).max() < 0.005 and (translation + 0.2).abs().max() < 1e-4
    _, wide = ops.robust_kabsch(src, tgt, None, 10, "cauchy", 3.0, 1e-6, backend=backend)
    assert (wide + 0.2).abs().max() > 1e-3  # Cauchy at 3 medians still lets the near outliers pull


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N", [(1, 3), (4, 4), (5, 37), (3, 768)])
@pytest.mark.parametrize("kernel", ["cauchy", "geman_mcclure", "welsch"])
def test_robust_kabsch_matches_the_reference(device, dtype, B, N, kernel):
    src, tgt, _ = outlier_problem(B, N, torch.float64, seed=N)
    weights = torch.rand(B, N, dtype=torch.float64)
    if N > 4:  # some points without a say (a fully determined problem otherwise)
        weights[:, ::5] = 0
    src, tgt, weights = (a.to(device, dtype) for a in (src, tgt, weights))
    # With 3-4 points a few steps leave under 3 with a say: a degenerate problem, any minimiser.
    for iterations, scale in ((0, 3.0), (1, 3.0)) + (((3, 3.0), (20, 0.15)) if N > 4 else ()):
        got = ops.robust_kabsch(non_contiguous(src), tgt, weights, iterations, kernel, scale)
        want = robust_kabsch_reference(src.double(), tgt.double(), weights.double(), iterations, kernel, scale)
        atol = 2e-4 if dtype == torch.float32 else 1e-9
        for a, b in zip(got, want):
            assert a.dtype == dtype
            torch.testing.assert_close(a.double(), b, rtol=0, atol=atol)


@pytest.mark.parametrize("kernel", ["cauchy", "geman_mcclure", "welsch"])
def test_robust_weights_are_one_at_zero_and_fall_with_the_residual(kernel):
    u = torch.linspace(0, 5, 51, dtype=torch.float64)
    w = robust_weights(kernel, u)
    expected = {"cauchy": 1 / (1 + u**2), "geman_mcclure": 1 / (1 + u**2) ** 2, "welsch": torch.exp(-u**2)}[kernel]
    torch.testing.assert_close(w, expected)
    assert w[0] == 1 and (w.diff() < 0).all()
    with pytest.raises(ValueError, match="kernel"):
        robust_weights("tukey", u)


@requires_ext
def test_robust_kabsch_is_differentiable_through_its_steps(device):
    src, tgt, _ = outlier_problem(2, 12, torch.float64, seed=3)
    weights = torch.rand(2, 12, dtype=torch.float64) + 0.1
    args = tuple(a.to(device).clone().requires_grad_() for a in (src, tgt, weights))
    assert torch.autograd.gradcheck(lambda s, g, w: ops.robust_kabsch(s, g, w, 3, "geman_mcclure", 1.0), args)
    with torch.no_grad():  # the single-pass kernel and the differentiable steps agree
        fused = ops.robust_kabsch(*args, 3, "geman_mcclure", 1.0)
    stepped = ops.robust_kabsch(*args, 3, "geman_mcclure", 1.0)
    assert stepped[0].requires_grad and not fused[0].requires_grad
    for a, b in zip(fused, stepped):
        torch.testing.assert_close(a, b.detach())


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_robust_kabsch_keeps_a_pair_whose_welsch_weights_all_vanish(backend):
    src = torch.randn(2, 9, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    tgt = src.clone()
    tgt[0] += torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64) * torch.randn(9, 1, dtype=torch.float64)
    tgt[1, :, 0] *= -1  # a mirror: residuals all far beyond 30 scales of the smallest
    R, t = ops.robust_kabsch(src, tgt, None, 5, "welsch", 0.01, backend=backend)
    assert torch.isfinite(R).all() and torch.isfinite(t).all()
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(2, dtype=torch.float64))


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_robust_kabsch_bad_options(backend):
    src = torch.randn(2, 10, 3)
    cases = [
        (dict(iterations=-1), "iterations"),
        (dict(iterations=1001), "iterations"),
        (dict(iterations=True), "iterations"),
        (dict(iterations=2.5), "iterations"),
        (dict(kernel="huber"), "kernel"),
        (dict(scale=0.0), "scale"),
        (dict(scale=float("nan")), "scale"),
        (dict(min_scale=-1.0), "min_scale"),
        (dict(min_scale=float("inf")), "min_scale"),
    ]
    for options, name in cases:
        with pytest.raises(ValueError, match=name):
            ops.robust_kabsch(src, src + 1, backend=backend, **options)
    with pytest.raises(ValueError, match="weights"):
        ops.robust_kabsch(src, src, torch.zeros(2, 10), backend=backend)


@requires_ext
def test_robust_kabsch_op_checks_its_arguments():
    src = torch.randn(2, 10, 3)
    weights = torch.ones(2, 10)
    op = torch.ops.vrnet_ext.robust_kabsch
    for args, name in [((src, src, weights, -1, "cauchy", 1.0, 1e-3), "iterations"),
                       ((src, src, weights, 3, "tukey", 1.0, 1e-3), "kernel"),
                       ((src, src, weights, 3, "cauchy", float("nan"), 1e-3), "scale"),
                       ((src, src, weights, 3, "cauchy", 1.0, 0.0), "min_scale"),
                       ((src, src[:, :4], weights, 3, "cauchy", 1.0, 1e-3), "tgt")]:
        with pytest.raises(ValueError, match=name):
            op(*args)


@requires_ext
def test_robust_kabsch_opcheck_and_compile(device):
    src, tgt, _ = outlier_problem(4, 10, torch.float32, seed=5)
    src, tgt = src.to(device), tgt.to(device)
    weights = torch.rand(4, 10) + 0.1
    opcheck(torch.ops.vrnet_ext.robust_kabsch.default, (src, tgt, weights, 3, "welsch", 0.75, 1e-3))
    fn = compile_fullgraph(lambda s, g: ops.robust_kabsch(s, g, None, 5, "geman_mcclure", 0.15))
    with torch.no_grad():
        torch.testing.assert_close(fn(src, tgt), ops.robust_kabsch(src, tgt, None, 5, "geman_mcclure", 0.15))
    src_grad = src.clone().requires_grad_()  # the differentiable steps compile too
    R, t = fn(src_grad, tgt)
    (R.sum() + t.sum()).backward()
    torch.testing.assert_close(R.detach(), ops.robust_kabsch(src, tgt, None, 5, "geman_mcclure", 0.15)[0])
    assert torch.isfinite(src_grad.grad).all()
