import subprocess
import sys
import textwrap

import pytest
import torch

from conftest import (DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext,
                      tolerances, under_each_cpu_dispatch)
from vrnet_ext import ops
from vrnet_ext.ops.soft_match import soft_match_reference


def dense64(query, key, values, scale):
    """Float64 brute force: the matrix, then its products."""
    scores = query.double() @ key.double().mT * scale
    return torch.softmax(scores, -1) @ values.double(), torch.logsumexp(scores, -1)


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B,N,M,c,D", [(1, 1, 1, 1, 1), (2, 129, 513, 32, 35), (1, 300, 1100, 5, 3),
                                       (3, 7, 1025, 64, 1), (1, 513, 40, 3, 4)])
def test_matches_float64_dense_values_and_gradients(device, dtype, B, N, M, c, D):
    query = non_contiguous(torch.randn(B, N, c, dtype=dtype)).requires_grad_()
    key = non_contiguous(torch.randn(B, M, c, dtype=dtype)).requires_grad_()
    values = torch.randn(B, M, D, dtype=dtype).requires_grad_()
    scale = 0.7
    result = ops.soft_match(query, key, values, scale, return_stats=True)
    want_out, want_lse = dense64(query, key, values, scale)
    tol = tolerances(dtype)
    torch.testing.assert_close(result.out, want_out.to(dtype), **tol)
    torch.testing.assert_close(result.lse, want_lse.to(dtype), **tol)
    grad_out, grad_lse = torch.randn(B, N, D, dtype=dtype), torch.randn(B, N, dtype=dtype)
    got = torch.autograd.grad((result.out * grad_out).sum() + (result.lse * grad_lse).sum(), (query, key, values))
    want = torch.autograd.grad((want_out * grad_out.double()).sum() + (want_lse * grad_lse.double()).sum(),
                               (query, key, values))
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w.to(dtype), **tol)


@requires_ext
def test_default_scale_and_backends_agree(device):
    query, key, values = torch.randn(2, 50, 16), torch.randn(2, 70, 16), torch.randn(2, 70, 6)
    torch.testing.assert_close(ops.soft_match(query, key, values),
                               torch.softmax(query @ key.mT / 4.0, -1) @ values, rtol=1e-5, atol=1e-6)
    ext = ops.soft_match(query, key, values, return_stats=True)
    ref = ops.soft_match(query, key, values, backend="torch", return_stats=True)
    torch.testing.assert_close(ext.out, ref.out)
    torch.testing.assert_close(ext.lse, ref.lse)
    assert torch.equal(ext.argmax, ref.argmax)


@requires_ext
def test_gradcheck_and_opcheck(device):
    query = torch.randn(2, 9, 4, dtype=torch.float64, requires_grad=True)
    key = torch.randn(2, 13, 4, dtype=torch.float64, requires_grad=True)
    values = torch.randn(2, 13, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q, k, v: tuple(ops.soft_match(q, k, v, 0.9, return_stats=True)[:2]),
                                    (query, key, values))
    assert torch.autograd.gradgradcheck(lambda q, k, v: ops.soft_match(q, k, v, 0.9, backend="torch"),
                                        (query, key, values))
    if device.type != "cpu":  # the flash kernels' ops (schema, fake kernels) where the GPU takes them
        from vrnet_ext.ops.soft_match import flash_fits

        q, k, v = (t.detach().float() for t in (query, key, values))
        if not flash_fits(q, v):
            return
        out, lse, _ = torch.ops.vrnet_ext.soft_match_flash(q, k, v, 0.5, 3, 0)
        opcheck(torch.ops.vrnet_ext.soft_match_flash.default, (q, k, v, 0.5, 3, 0))
        opcheck(torch.ops.vrnet_ext.soft_match_flash.default, (q, k, v, 0.5, 1, 1 << 20))  # keys split
        opcheck(torch.ops.vrnet_ext.soft_match_flash_backward.default,
                (torch.randn_like(out), torch.randn_like(lse), q, k, v, out, lse, 0.5, 1))
        return
    opcheck(torch.ops.vrnet_ext.soft_match.default,
            (query.float().detach().requires_grad_(), key.float().detach().requires_grad_(),
             values.float().detach().requires_grad_(), 0.5))


@requires_ext
@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_degenerate_inputs(device, backend):
    query, key, values = torch.randn(1, 6, 3), torch.randn(1, 1, 3), torch.randn(1, 1, 2)
    # one candidate: every row takes it whole
    torch.testing.assert_close(ops.soft_match(query, key, values, backend=backend), values.expand(1, 6, 2))
    # equal keys or scale 0: the plain mean of the values; ties: the first maximum is the peak
    key, values = torch.ones(1, 600, 3), torch.randn(1, 600, 2)
    result = ops.soft_match(query, key, values, backend=backend, return_stats=True)
    torch.testing.assert_close(result.out, values.mean(1, keepdim=True).expand(1, 6, 2))
    assert result.argmax.eq(0).all()
    torch.testing.assert_close(ops.soft_match(query, torch.randn(1, 600, 3), values, 0.0, backend=backend),
                               values.mean(1, keepdim=True).expand(1, 6, 2))
    # scores up to 1e6 (exp overflows float32): stable, and a one-hot row picks its best key
    angles = torch.arange(700.0) * (6.283185 / 700)  # unit keys on a circle: q . k is largest for k = q
    key = torch.stack([angles.cos(), angles.sin(), torch.zeros(700)], -1).unsqueeze(0)
    best = key[0, 650]
    sharp = ops.soft_match(best.expand(1, 4, 3).contiguous(), key, torch.arange(700.0).reshape(1, 700, 1), 1e6,
                           backend=backend, return_stats=True)
    torch.testing.assert_close(sharp.out, torch.full((1, 4, 1), 650.0))
    assert sharp.argmax.eq(650).all() and torch.isfinite(sharp.lse).all()
    # no query rows, no value channels
    assert ops.soft_match(query[:, :0], key, torch.randn(1, 700, 2), backend=backend).shape == (1, 0, 2)
    assert ops.soft_match(query, key, torch.randn(1, 700, 0), backend=backend).shape == (1, 6, 0)


@requires_ext
def test_scores_that_overflow_to_minus_infinity_weigh_nothing(device):
    """Keys whose scores overflow to -inf fill the first tiles (more than one tile of 512); the later,
    finite scores decide the row, as in the dense reference."""
    far = torch.tensor([-1e20, 0.0, 0.0]).expand(1100, 3)
    near = torch.stack([torch.arange(1.0, 51.0) * 1e-20, torch.zeros(50), torch.zeros(50)], -1)
    key = torch.cat([far, near]).unsqueeze(0).to(device)
    query = torch.tensor([[[1.0, 0.0, 0.0], [0.5, 0.0, 0.0]]], device=device)
    values = torch.randn(1, 1150, 2, device=device)
    results = []
    for backend in ("ext", "torch"):
        inputs = [t.clone().requires_grad_() for t in (query, key, values)]
        result = ops.soft_match(*inputs, scale=1e20, backend=backend, return_stats=True)
        grads = torch.autograd.grad(result.out.sum(), inputs[2])
        results.append((result.out, result.lse, result.argmax, grads[0]))
    for got, want in zip(*results):
        assert torch.isfinite(got.float()).all()
        torch.testing.assert_close(got, want)
    assert results[0][2].eq(1149).all()


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
def test_sharp_rows_whose_other_weights_underflow(device, dtype):
    """Most scores lie hundreds (float32) or thousands (float64) below their row's maximum, where
    the exponential is subnormal or zero: values, log-normaliser and gradients still match the
    float64 brute force (the kernel raises such exponents to its floor, a weight of at most ~1e-38
    of the row's largest). Each score carries a rounding error in proportion to its size, so the
    tolerances grow with the spread (float32 at spread 400: out 1e-4, as the CPU kernel's error
    reaches 4.5e-5 on some seeds)."""
    spread = 400.0 if dtype == torch.float32 else 3000.0
    query = torch.randn(2, 70, 8, dtype=dtype, device=device)
    key = torch.randn(2, 600, 8, dtype=dtype, device=device)
    values = torch.randn(2, 600, 5, dtype=dtype, device=device)
    scale = spread / 8
    inputs = [t.clone().requires_grad_() for t in (query, key, values)]
    result = ops.soft_match(*inputs, scale=scale, return_stats=True)
    want_out, want_lse = dense64(query, key, values, scale)
    scores = (query.double() @ key.double().mT) * scale
    assert ((scores - scores.amax(-1, keepdim=True)) < -100).double().mean() > 0.5
    tol = tolerances(dtype)
    torch.testing.assert_close(result.out, want_out.to(dtype), rtol=tol["rtol"], atol=tol["atol"] * spread / 40)
    torch.testing.assert_close(result.lse, want_lse.to(dtype), rtol=tol["rtol"], atol=tol["atol"] * spread)
    grad_out = torch.randn(2, 70, 5, dtype=dtype, device=device)
    got = torch.autograd.grad((result.out * grad_out).sum(), inputs)
    dense_inputs = [t.double().requires_grad_() for t in (query, key, values)]
    dense_out = dense64(*dense_inputs, scale)[0]
    want = torch.autograd.grad((dense_out * grad_out.double()).sum(), dense_inputs)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w.to(dtype), rtol=tol["rtol"], atol=tol["atol"] * spread)


@requires_ext
def test_denormals_flushed_inside_the_op_only():
    """The CPU kernel flushes denormals while it runs (a sharp row's far terms) and restores every
    thread's own mode: afterwards denormal arithmetic still gives denormals, on the calling thread
    and on the intra-op workers."""
    from vrnet_ext.runtime import set_flush_denormal

    set_flush_denormal(False)
    query = torch.randn(2, 300, 16, requires_grad=True)
    key, values = torch.randn(2, 400, 16), torch.randn(2, 400, 3)
    ops.soft_match(query * 60, key, values).sum().backward()
    tiny = torch.finfo(torch.float32).tiny / 4
    assert (torch.tensor([tiny]) * 1.0).item() == tiny
    assert bool(((torch.full((1 << 20,), tiny) * 1.0) == tiny).all())


@requires_ext
def test_unused_outputs_get_no_gradient_work(device):
    query = torch.randn(1, 20, 8, requires_grad=True)
    key, values = torch.randn(1, 30, 8), torch.randn(1, 30, 3)
    ops.soft_match(query, key, values, return_stats=True).lse.sum().backward()
    # d lse_i / d q_i = scale sum_j P_ij k_j
    expected = ops.soft_match(query.detach(), key, key) / 8 ** 0.5
    torch.testing.assert_close(query.grad, expected)


@requires_ext
@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_torch_compile_fullgraph(device, backend):
    query, key, values = torch.randn(2, 40, 8), torch.randn(2, 50, 8), torch.randn(2, 50, 3)
    fn = compile_fullgraph(lambda q, k, v: ops.soft_match(q, k, v, backend=backend) * 2)
    torch.testing.assert_close(fn(query, key, values), ops.soft_match(query, key, values, backend=backend) * 2)


@requires_ext
def test_low_precision_inputs_compute_in_float32(device):
    query, key, values = torch.randn(1, 30, 8), torch.randn(1, 40, 8), torch.randn(1, 40, 3)
    out = ops.soft_match(query.bfloat16(), key.bfloat16(), values.bfloat16())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, ops.soft_match(query.bfloat16().float(), key.bfloat16().float(),
                                                   values.bfloat16().float()))
    with torch.autocast(device.type, dtype=torch.bfloat16):
        assert ops.soft_match(query, key, values).dtype == torch.float32


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    query, key, values = torch.randn(2, 5, 4), torch.randn(2, 7, 4), torch.randn(2, 7, 3)
    cases = [
        ((query[0], key, values), ValueError, "query"),
        ((query, key[..., :3], values), ValueError, "feature size"),
        ((query, key, values[:, :6]), ValueError, "values"),
        ((query, key[:1], values[:1]), ValueError, "batch"),
        ((query, key[:, :0], values[:, :0]), ValueError, "at least one point"),
        ((query[..., :0], key[..., :0], values), ValueError, "feature channel"),
        ((query.long(), key, values), TypeError, "query"),
        ((query, key.double(), values), TypeError, "key"),
        ((query, key, values, float("nan")), ValueError, "scale"),
        ((query.masked_fill(query > 1, float("nan")), key, values), ValueError, "query"),
        ((query, key, values.masked_fill(values > 1, float("inf"))), ValueError, "values"),
        ((query * 1e30, key * 1e30, values), ValueError, "overflow"),
    ]
    for args, error, name in cases:
        with pytest.raises(error, match=name):
            ops.soft_match(*args, backend=backend)


@pytest.mark.parametrize("max_scores", [1, 2 * 7 * 50, 2 * 7 * 50 + 1, 10 ** 6])
def test_dense_in_query_blocks_equals_the_reference(device, max_scores):
    """Blocks of one row, of 7 rows (the last of 5), and one block: values and gradients."""
    from vrnet_ext.ops.soft_match import dense_in_query_blocks

    query, key, values = (torch.randn(2, n, c, dtype=torch.float64, requires_grad=True)
                          for n, c in ((40, 8), (50, 8), (50, 3)))
    got = dense_in_query_blocks(query, key, values, 0.9, max_scores)
    want = soft_match_reference(query, key, values, 0.9)
    for a, b in zip(got, want):  # products over fewer rows may round differently
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    projection = torch.randn(2, 40, 3, dtype=torch.float64)
    grads = [torch.autograd.grad((r.out * projection).sum() + r.lse.sum(), (query, key, values)) for r in (got, want)]
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("max_scores", [1, 3 * 5 * 9 + 1])
def test_dense_in_query_blocks_gradients(device, max_scores):
    """The recomputing backward of more than one block: first and second order against finite
    differences, the log-normaliser's gradient included, a sharp row and a duplicated key."""
    from vrnet_ext.ops.soft_match import dense_in_query_blocks

    torch.manual_seed(0)
    query, key, values = (torch.randn(3, n, c, dtype=torch.float64) for n, c in ((7, 4), (9, 4), (9, 2)))
    query[0, 0] *= 6.0
    key[1, 3] = key[1, 2]
    inputs = tuple(t.requires_grad_() for t in (query, key, values))

    def fn(q, k, v):
        result = dense_in_query_blocks(q, k, v, 0.8, max_scores)
        return result.out, result.lse

    assert torch.autograd.gradcheck(fn, inputs)
    assert torch.autograd.gradgradcheck(fn, inputs)


def test_dense_in_query_blocks_compile_fullgraph(device):
    """Several blocks (the recomputing backward) under torch.compile(fullgraph=True): values and
    gradients as the reference's."""
    from vrnet_ext.ops.soft_match import dense_in_query_blocks

    inputs = [torch.randn(2, n, c, requires_grad=True) for n, c in ((40, 8), (50, 8), (50, 3))]
    fn = compile_fullgraph(lambda q, k, v: dense_in_query_blocks(q, k, v, 0.9, 300).out)
    got, want = fn(*inputs), soft_match_reference(*inputs, 0.9).out
    torch.testing.assert_close(got, want)
    for a, b in zip(torch.autograd.grad(got.sum(), inputs), torch.autograd.grad(want.sum(), inputs)):
        torch.testing.assert_close(a, b)


def test_reference_is_the_dense_formula():
    query, key, values = torch.randn(1, 4, 2, dtype=torch.float64), torch.randn(1, 5, 2, dtype=torch.float64), \
        torch.randn(1, 5, 3, dtype=torch.float64)
    out, lse = dense64(query, key, values, 1.3)
    ref = soft_match_reference(query, key, values, 1.3)
    torch.testing.assert_close(ref.out, out)
    torch.testing.assert_close(ref.lse, lse)


@requires_ext
def test_50k_points_forward_within_100mb_of_its_inputs():
    """Issue 10's floor: N = M = 50,000, c = 32, D = 35 (the dense matrix would be 10 GB)."""
    script = textwrap.dedent("""
        import resource, torch
        from vrnet_ext import ops
        torch.manual_seed(0)
        q, k, v = torch.randn(1, 50000, 32), torch.randn(1, 50000, 32), torch.randn(1, 50000, 35)
        ops.soft_match(q[:, :10], k[:, :600], v[:, :600])  # warm-up: allocator, thread pool
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        out = ops.soft_match(q, k, v)
        after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        assert torch.isfinite(out).all()
        print((after - before) / 1024)
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    growth_mb = float(run.stdout.strip().splitlines()[-1])
    assert growth_mb < 100, f"peak RSS grew {growth_mb:.0f} MB"


@requires_ext
def test_contiguous_inputs_that_require_grad_on_several_threads():
    """The kernel slices its inputs on OpenMP worker threads; inputs with autograd history must not
    reach the tile products there (regression: mm_out refused them at 2 threads)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        query = torch.randn(1, 300, 8, requires_grad=True)
        key, values = torch.randn(1, 700, 8, requires_grad=True), torch.randn(1, 700, 4, requires_grad=True)
        out = ops.soft_match(query * 1.0, key, values)
        out.sum().backward()
        assert query.grad is not None and key.grad is not None and values.grad is not None
    finally:
        torch.set_num_threads(threads)


@requires_ext
def test_the_vector_and_the_portable_rows_agree(tmp_path):
    """Where the CPU has AVX-512 the forward's row operations (scale and first maximum, shift, sum)
    run on vector registers; VRNET_CPU_DISPATCH=generic keeps the portable loops. Same outputs, bit
    for bit: both precisions, rows shorter than a register and over several key tiles, tied maxima."""
    script = ("import sys, torch; from vrnet_ext import ops; g = torch.Generator().manual_seed(7); out = []\n"
              "for dtype in (torch.float32, torch.float64):\n"
              "    for N, M in ((5, 3), (70, 1100), (300, 513)):\n"
              "        q = torch.randn(2, N, 16, generator=g, dtype=dtype)\n"
              "        k = torch.randn(2, M, 16, generator=g, dtype=dtype); k[:, 1::2] = k[:, ::2][:, :k[:, 1::2].shape[1]]\n"
              "        v = torch.randn(2, M, 5, generator=g, dtype=dtype)\n"
              "        out.append(tuple(ops.soft_match(q, k, v, 0.7, return_stats=True)))\n"
              "torch.save(out, sys.argv[1])")
    results = under_each_cpu_dispatch(script, tmp_path)
    for vector, generic in zip(*results):
        for a, b in zip(vector, generic):
            assert torch.equal(a, b)


def test_flash_kernel_passes_follow_torchs_tf32_setting():
    """The CUDA flash kernel's products: three (split TF32) unless TF32 is allowed for CUDA matmuls,
    by either of torch's APIs; read without a GPU."""
    from vrnet_ext.ops.soft_match import flash_passes

    matmul = torch.backends.cuda.matmul
    previous = matmul.fp32_precision
    try:
        assert flash_passes() == 3
        matmul.fp32_precision = "tf32"
        assert flash_passes() == 1
        matmul.fp32_precision = previous
        torch.set_float32_matmul_precision("high")
        assert flash_passes() == 1
    finally:
        torch.set_float32_matmul_precision("highest")
        matmul.fp32_precision = previous
    assert flash_passes() == 3
