import pytest
import torch

from conftest import DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext, under_each_cpu_dispatch
from vrnet_ext.ops.edge_norm_max import edge_norm_max, edge_norm_max_reference


def make_inputs(B, O, N, k, dtype, offset=0.0, affine=True, running=False, negative=True):
    projections = torch.randn(B, 2 * O, N, dtype=dtype) * 2 + offset
    idx = torch.randint(0, N, (B, N, k))
    weight = bias = running_mean = running_var = None
    if affine:
        weight = torch.rand(O, dtype=dtype) + 0.5
        if negative:  # negative scales take the min over the neighbours
            weight[::2] *= -1
        bias = torch.randn(O, dtype=dtype)
    if running:
        running_mean = torch.randn(O, dtype=dtype) + offset
        running_var = torch.rand(O, dtype=dtype) * 3 + 0.1
    return projections, idx, weight, bias, running_mean, running_var


def tolerance(dtype):
    return dict(rtol=1e-4, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-9)


def forward_and_grads(impl, projections, idx, weight, bias, running_mean, running_var, grad):
    leaves = [t.detach().clone().requires_grad_() if t is not None else None for t in (projections, weight, bias)]
    out, mean, var = impl(leaves[0], idx, leaves[1], leaves[2], running_mean, running_var, 1e-5, 0.2)
    out.backward(grad)
    return [out, mean, var] + [t.grad if t is not None else None for t in leaves]


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("running", [False, True])
@pytest.mark.parametrize("affine", [True, False])
@pytest.mark.parametrize("B,O,N,k", [(1, 1, 2, 1), (1, 3, 17, 17), (3, 5, 33, 4), (2, 64, 129, 20)])
def test_matches_reference(device, dtype, running, affine, B, O, N, k):
    inputs = make_inputs(B, O, N, k, dtype, affine=affine, running=running)
    grad = torch.randn(B, O, N, dtype=dtype)
    expected = forward_and_grads(edge_norm_max_reference, *inputs, grad)
    got = forward_and_grads(edge_norm_max, *inputs, grad)
    for name, g, e in zip(("out", "mean", "var", "grad projections", "grad weight", "grad bias"), got, expected):
        if e is None:
            assert g is None, name
            continue
        torch.testing.assert_close(g, e, **tolerance(dtype), msg=lambda m: f"{name}: {m}")
    assert not any(t.requires_grad for t in (got[1], got[2], expected[1], expected[2]))  # statistics, both paths


@requires_ext
def test_non_contiguous_and_low_precision_inputs(device):
    projections, idx, weight, bias, _, _ = make_inputs(2, 6, 40, 7, torch.float32)
    expected = edge_norm_max(projections, idx, weight, bias)
    strided = edge_norm_max(non_contiguous(projections), non_contiguous(idx), weight[::1], bias)
    for a, b in zip(strided, expected):
        torch.testing.assert_close(a, b)
    half = edge_norm_max(projections.bfloat16(), idx, weight, bias)  # promoted to float32
    assert half[0].dtype == torch.float32
    reference = edge_norm_max_reference(projections.bfloat16().float(), idx, weight, bias)
    torch.testing.assert_close(half[0], reference[0], rtol=1e-4, atol=1e-4)


@requires_ext
@pytest.mark.parametrize("running", [False, True])
def test_gradcheck_and_opcheck(device, running):
    projections, idx, weight, bias, running_mean, running_var = make_inputs(2, 3, 9, 4, torch.float64, running=running)
    leaves = tuple(t.requires_grad_() for t in (projections, weight, bias))
    assert torch.autograd.gradcheck(
        lambda p, w, b: edge_norm_max(p, idx, w, b, running_mean, running_var)[0], leaves)
    args = (projections.detach().float().requires_grad_(), idx, weight.detach().float().requires_grad_(),
            bias.detach().float().requires_grad_(),
            None if running_mean is None else running_mean.float(),
            None if running_var is None else running_var.float(), 1e-5, 0.2)
    opcheck(torch.ops.vrnet_ext.edge_norm_max.default, args)


@requires_ext
def test_running_statistics_backward_keeps_a_nan_to_its_own_edges(device):
    """With running statistics nothing flows through them: a NaN value reaches only the gradients
    of the edges it wins, as in the reference (not every neighbour term of its channel)."""
    inputs = list(make_inputs(2, 4, 40, 5, torch.float64, running=True))
    inputs[0][0, 1, 7] = float("nan")
    grad = torch.randn(2, 4, 40, dtype=torch.float64)
    got = forward_and_grads(edge_norm_max, *inputs, grad)
    expected = forward_and_grads(edge_norm_max_reference, *inputs, grad)
    for g, e in zip(got, expected):
        torch.testing.assert_close(g, e, rtol=1e-9, atol=1e-9, equal_nan=True)
    assert torch.isfinite(got[3][:, 1]).float().mean() > 0.9


@requires_ext
def test_statistics_accurate_far_from_the_origin(device):
    """Values ~1e4 with unit spread: the variance must not cancel (float32 in, float64 reference)."""
    projections, idx, weight, bias, _, _ = make_inputs(4, 8, 200, 10, torch.float32, offset=1e4)
    ref_out, ref_mean, ref_var = edge_norm_max_reference(projections.double(), idx, weight.double(), bias.double())
    out, mean, var = edge_norm_max(projections, idx, weight, bias, None, None, 1e-5, 0.2)
    torch.testing.assert_close(var.double(), ref_var, rtol=1e-5, atol=0)
    torch.testing.assert_close(mean.double(), ref_mean, rtol=1e-7, atol=0)
    torch.testing.assert_close(out.double(), ref_out, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("value", [0.0, 0.1, 3.7, 1e4])
def test_zero_variance_channels_backward_like_float64(device, value):
    """A constant channel has zero variance; its exact gradient is (g - mean g) / sqrt(eps) scaled, not
    0: float32 must give the float64 reference's, for values float32 cannot hold exactly too."""
    torch.manual_seed(0)
    projections = torch.randn(2, 8, 30)
    projections[:, 0], projections[:, 4] = value, -value / 3  # channel 0: every edge the same
    idx = torch.randint(0, 30, (2, 30, 6))
    upstream = torch.randn(2, 4, 30)
    weight, bias = torch.rand(4) + 0.5, torch.randn(4)
    grads = []
    for dtype, op in ((torch.float32, edge_norm_max), (torch.float64, edge_norm_max_reference)):
        inputs = [t.to(device, dtype).requires_grad_() for t in (projections, weight, bias)]
        out = op(inputs[0], idx.to(device), inputs[1], inputs[2])[0]
        grads.append(torch.autograd.grad((out * upstream.to(device, dtype)).sum(), inputs))
    for got, want in zip(*grads):
        torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-3)


@requires_ext
def test_degenerate_inputs(device):
    # constant values: zero variance, the output is the bias through the LeakyReLU
    projections = torch.full((2, 6, 10), 3.0)
    idx = torch.randint(0, 10, (2, 10, 4))
    bias = torch.tensor([1.0, -1.0, 0.5])
    out, _, var = edge_norm_max(projections, idx, torch.ones(3), bias)
    assert torch.equal(var, torch.zeros(3))
    torch.testing.assert_close(out, torch.nn.functional.leaky_relu(bias, 0.2).view(1, 3, 1).expand(2, 3, 10))
    # ties: the gradient of the max goes to the first neighbour slot holding it
    projections = torch.tensor([[[1.0, 5.0, 5.0, 2.0], [0.0, 0.0, 0.0, 0.0]]], requires_grad=True)
    idx = torch.tensor([[[2, 1, 0], [0, 1, 2], [3, 3, 3], [1, 2, 3]]])
    stats = (torch.zeros(1), torch.ones(1))
    edge_norm_max(projections, idx, None, None, *stats, eps=1e-5)[0][0, 0, 0].backward()
    assert projections.grad[0, 0].nonzero().flatten().tolist() == [2]
    # NaN propagates to the output like the reference (never silently dropped)
    projections = torch.randn(1, 4, 8)
    projections[0, 0, 3] = float("nan")
    idx = torch.randint(0, 8, (1, 8, 3))
    out, mean, _ = edge_norm_max(projections, idx)
    ref_out, ref_mean, _ = edge_norm_max_reference(projections, idx)
    assert torch.equal(out.isnan(), ref_out.isnan()) and torch.equal(mean.isnan(), ref_mean.isnan())


@requires_ext
def test_torch_compile_fullgraph(device):
    projections, idx, weight, bias, _, _ = make_inputs(2, 4, 30, 5, torch.float32)
    fn = compile_fullgraph(lambda p, i: edge_norm_max(p, i, weight, bias)[0])
    torch.testing.assert_close(fn(projections, idx), edge_norm_max(projections, idx, weight, bias)[0])


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    projections, idx = torch.randn(2, 8, 10), torch.randint(0, 10, (2, 10, 3))
    ones = torch.ones(4)
    cases = [
        ((projections[:, :7], idx), {}, ValueError, "2O"),
        ((projections, idx[:, :9]), {}, ValueError, "N = 10"),
        ((projections, idx + 10), {}, ValueError, "outside"),
        ((projections, idx.float()), {}, TypeError, "idx"),
        ((projections, idx), {"running_mean": ones}, ValueError, "together"),
        ((projections, idx), {"weight": torch.ones(5)}, ValueError, "weight"),
        ((projections, idx), {"bias": torch.ones(4, dtype=torch.long)}, TypeError, "bias"),
        ((projections, idx), {"eps": 0.0}, ValueError, "eps"),
        ((projections[:1, :, :1], idx[:1, :1, :1] * 0), {}, ValueError, "more than one edge"),
    ]
    for args, kwargs, error, match in cases:
        with pytest.raises(error, match=match):
            edge_norm_max(*args, backend=backend, **kwargs)


@requires_ext
def test_backward_op_checks_its_arguments():
    projections, idx = torch.randn(2, 8, 10), torch.randint(0, 10, (2, 10, 3))
    grad, arg = torch.randn(2, 4, 10), torch.zeros(2, 4, 10, dtype=torch.int32)
    stats = (torch.zeros(4, dtype=torch.float64), torch.ones(4, dtype=torch.float64))
    op = torch.ops.vrnet_ext.edge_norm_max_backward
    cases = [
        ((grad[:, :3], projections, idx, arg, None, None, *stats, True, 1e-5, 0.2), "grad_out"),
        ((grad, projections, idx, arg + 3, None, None, *stats, True, 1e-5, 0.2), "arg"),
        ((grad, projections, idx, arg[:1], None, None, *stats, True, 1e-5, 0.2), "arg"),
        ((grad, projections, idx, arg, None, None, stats[0][:3], stats[1], True, 1e-5, 0.2), "mean"),
    ]
    for args, match in cases:
        with pytest.raises(ValueError, match=match):
            op(*args)
    with pytest.raises(TypeError, match="arg must be int32"):
        op(grad, projections, idx, arg.long(), None, None, *stats, True, 1e-5, 0.2)
    with pytest.raises(TypeError, match="mean must be float64"):
        op(grad, projections, idx, arg, None, None, stats[0].float(), stats[1], True, 1e-5, 0.2)


def test_a_negative_slope_is_refused_everywhere():
    """The max over neighbours is taken before the LeakyReLU: exact only for an increasing one."""
    from vrnet_ext.nn import EdgeConv

    projections, idx = torch.randn(1, 4, 10), torch.randint(0, 10, (1, 10, 3))
    for backend in ("ext", "torch"):
        with pytest.raises(ValueError, match="negative_slope must be a finite number >= 0"):
            edge_norm_max(projections, idx, negative_slope=-0.2, backend=backend)
        with pytest.raises(ValueError, match="negative_slope must be a finite number >= 0"):
            edge_norm_max(projections, idx, negative_slope=float("nan"), backend=backend)
    with pytest.raises(ValueError, match="negative_slope must be a finite number >= 0"):
        torch.ops.vrnet_ext.edge_norm_max(projections, idx, None, None, None, None, 1e-5, -0.5)
    with pytest.raises(ValueError, match="negative_slope must be a finite number >= 0"):
        EdgeConv(3, 8, negative_slope=-0.1)


@requires_ext
def test_the_vector_and_the_portable_pass_agree(tmp_path):
    """Where the CPU has AVX-512 the neighbour pass runs on 64-byte registers; VRNET_CPU_DISPATCH=generic
    keeps 16-byte ones. The same operations per lane: outputs and statistics equal bit for bit
    (batch and running statistics, both precisions, channel counts with and without a remainder)."""
    script = ("import sys, torch; from vrnet_ext import ops; g = torch.Generator().manual_seed(3); out = []\n"
              "for dtype in (torch.float32, torch.float64):\n"
              "    for O in (16, 37, 64):\n"
              "        p = torch.randn(2, 2 * O, 150, generator=g, dtype=dtype)\n"
              "        idx = torch.randint(0, 150, (2, 150, 10), generator=g)\n"
              "        w, b = torch.randn(O, generator=g, dtype=dtype), torch.randn(O, generator=g, dtype=dtype)\n"
              "        rm, rv = torch.randn(O, generator=g, dtype=dtype), torch.rand(O, generator=g, dtype=dtype) + 0.5\n"
              "        out += [ops.edge_norm_max(p, idx, w, b, None, None, 1e-5, 0.2),\n"
              "                ops.edge_norm_max(p, idx, w, b, rm, rv, 1e-5, 0.2)]\n"
              "torch.save(out, sys.argv[1])")
    results = under_each_cpu_dispatch(script, tmp_path)
    for vector, generic in zip(*results):
        for a, b in zip(vector, generic):
            assert torch.equal(a, b)
