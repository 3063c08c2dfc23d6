import importlib
import math
import os

import pytest
import torch
from torch.nn import functional as F

from vrnet_ext import ops
from conftest import opcheck, requires_ext, under_each_cpu_dispatch

attention_module = importlib.import_module("vrnet_ext.ops.attention")  # ops.attention is the function
products_on_amx = attention_module.products_on_amx  # the real one (the fixture below replaces the module's)

SHAPES = [  # (B, H, N, M, D)
    (2, 4, 768, 768, 32),  # the Transformer's heads (2 clouds x 4 heads of 32 channels)
    (1, 1, 1, 1, 16),      # one query, one key
    (2, 3, 65, 63, 32),    # odd key count (a zero key pads the packed values), a partial query block
    (1, 2, 130, 1, 64),    # one key: the output is v
    (1, 2, 37, 29, 24),    # a head size the tile products do not take (plain loops)
    (1, 1, 5, 7, 80),      # a head size over 64
]


@pytest.fixture(autouse=True)
def kernel_serves_on_any_cpu(monkeypatch):
    """The kernel serves only where its products run on AMX; its tests run it on every CPU."""
    monkeypatch.setattr(attention_module, "products_on_amx", lambda head_channels: True)


def _heads(B, H, N, M, D, seed=0, spread=2.0):
    g = torch.Generator().manual_seed(seed)
    q = (torch.randn(B, H, N, D, generator=g) * spread).bfloat16()
    k = (torch.randn(B, H, M, D, generator=g) * spread).bfloat16()
    v = torch.randn(B, H, M, D, generator=g).bfloat16()
    return q, k, v


def _error(got, expected):
    diff = got.double() - expected
    return diff.abs().max().item(), diff.square().mean().sqrt().item()


@requires_ext
@pytest.mark.parametrize("shape", SHAPES)
def test_matches_the_float64_attention_as_closely_as_torchs_kernel(shape):
    """Against float64 attention of the same bfloat16 heads: within bfloat16's rounding, and no
    further off than torch's own bfloat16 kernel (RMS error within 1.5x of it)."""
    q, k, v = _heads(*shape)
    exact = F.scaled_dot_product_attention(q.double(), k.double(), v.double())
    got = ops.attention(q, k, v)
    assert got.dtype == torch.bfloat16 and got.shape == q.shape
    torch.testing.assert_close(got.double(), exact, rtol=2e-2, atol=2e-2)
    torch_max, torch_rms = _error(F.scaled_dot_product_attention(q, k, v), exact)
    ours_max, ours_rms = _error(got, exact)
    assert ours_rms <= 1.5 * torch_rms + 1e-5
    assert ours_max <= 2 * torch_max + 1e-3


@requires_ext
@pytest.mark.parametrize("shape", [(8, 4, 70, 2048, 32), (1, 1, 64, 20000, 32)])
def test_buffers_over_the_kept_size(shape):
    """Packed heads (first shape) or a worker's scores (second) over the 4 MB a thread keeps between
    calls: temporary buffers, the same accuracy."""
    q, k, v = _heads(*shape)
    exact = F.scaled_dot_product_attention(q.double(), k.double(), v.double())
    got = ops.attention(q, k, v)
    torch.testing.assert_close(got.double(), exact, rtol=2e-2, atol=2e-2)
    assert _error(got, exact)[1] <= 1.5 * _error(F.scaled_dot_product_attention(q, k, v), exact)[1] + 1e-5


@requires_ext
def test_sharp_and_flat_rows():
    """Scores spread over hundreds (all weight on one key; the rest underflow) and all equal
    (uniform weights): both within bfloat16 rounding of the float64 result."""
    q, k, v = _heads(1, 2, 40, 300, 32, spread=6.0)
    exact = F.scaled_dot_product_attention(q.double(), k.double(), v.double())
    torch.testing.assert_close(ops.attention(q, k, v).double(), exact, rtol=2e-2, atol=2e-2)
    flat = torch.zeros_like(q)
    torch.testing.assert_close(ops.attention(flat, k, v).double(), v.double().mean(dim=2, keepdim=True).expand_as(flat),
                               rtol=2e-2, atol=1e-2)


@requires_ext
def test_scale_and_strided_heads():
    """Heads viewed out of one packed (B, L, 3, H, D) projection (the Transformer's layout) give the
    result of contiguous copies bit for bit; ``scale`` is honoured; the result's memory is
    (B, N, H, D)."""
    g = torch.Generator().manual_seed(1)
    packed = (torch.randn(2, 50, 3 * 4 * 32, generator=g) * 2).bfloat16()
    q, k, v = packed.view(2, 50, 3, 4, 32).permute(2, 0, 3, 1, 4)
    got = ops.attention(q, k, v, scale=0.3)
    assert torch.equal(got, ops.attention(q.contiguous(), k.contiguous(), v.contiguous(), scale=0.3))
    assert got.permute(0, 2, 1, 3).is_contiguous()
    exact = F.scaled_dot_product_attention(q.double(), k.double(), v.double(), scale=0.3)
    torch.testing.assert_close(got.double(), exact, rtol=2e-2, atol=2e-2)
    transposed = k.transpose(2, 3).contiguous().transpose(2, 3)  # channels not unit-stride
    assert torch.equal(ops.attention(q, transposed, v, scale=0.3), got)


@requires_ext
def test_the_vector_and_the_portable_softmax_agree(tmp_path):
    """Where the CPU has AVX512-BF16 the softmax rows and the final scaling run as vector code;
    VRNET_CPU_DISPATCH=generic keeps the portable loops. For head sizes the tile products do not
    take (the plain loops in both) the results agree bit for bit, odd sizes and sharp rows included;
    with the tile products (head size 32) the portable path stays as close to float64 as the
    vector one."""
    script = ("import math, sys, torch, vrnet_ext; assert vrnet_ext.has_extension(); out = []\n"
              "g = torch.Generator().manual_seed(2)\n"
              "for B, H, N, M, D, s in ((1, 2, 37, 29, 24, 2.0), (2, 1, 70, 131, 8, 9.0), (1, 3, 64, 17, 40, 1.0),\n"
              "                         (2, 4, 100, 120, 32, 2.0)):\n"
              "    q, k, v = (torch.randn(B, H, L, D, generator=g) * f for L, f in ((N, s), (M, s), (M, 1.0)))\n"
              "    heads = (q.bfloat16(), k.bfloat16(), v.bfloat16())\n"
              "    out.append((q, k, v, torch.ops.vrnet_ext.attention(*heads, 1 / math.sqrt(D))))\n"
              "torch.save(out, sys.argv[1])")
    vector, generic = under_each_cpu_dispatch(script, tmp_path)
    for (q, k, v, got_vector), (_, _, _, got_generic) in zip(vector[:3], generic[:3]):
        assert torch.equal(got_vector, got_generic)
    q, k, v, got_vector = vector[3]
    exact = F.scaled_dot_product_attention(*(t.bfloat16().double() for t in (q, k, v)))
    assert _error(generic[3][3], exact)[1] <= 1.5 * _error(got_vector, exact)[1] + 1e-5


@requires_ext
def test_reference_runs_where_the_kernel_does_not_serve(monkeypatch):
    """float32 heads, backend="torch", dropout, recorded gradients, key sets over MAX_KEYS and a CPU
    without bfloat16 products run torch's kernel: its results bit for bit (and its gradients)."""
    q, k, v = _heads(1, 2, 20, 30, 32)
    for args in ((q.float(), k.float(), v.float()), (q, k, v)):
        assert torch.equal(ops.attention(*args, backend="torch"), F.scaled_dot_product_attention(*args))
    assert torch.equal(ops.attention(q.float(), k.float(), v.float()),
                       F.scaled_dot_product_attention(q.float(), k.float(), v.float()))
    leaf = q.float().requires_grad_()
    out = ops.attention(leaf, k.float(), v.float())
    (grad,) = torch.autograd.grad(out.sum(), leaf)
    expected_leaf = q.float().requires_grad_()
    (expected,) = torch.autograd.grad(F.scaled_dot_product_attention(expected_leaf, k.float(), v.float()).sum(),
                                      expected_leaf)
    assert torch.equal(grad, expected)
    torch.manual_seed(0)
    dropped = ops.attention(q, k, v, dropout_p=0.5)
    torch.manual_seed(0)
    assert torch.equal(dropped, F.scaled_dot_product_attention(q, k, v, dropout_p=0.5))
    monkeypatch.setattr(attention_module, "MAX_KEYS", 29)
    assert torch.equal(ops.attention(q, k, v), F.scaled_dot_product_attention(q, k, v))
    monkeypatch.setattr(attention_module, "MAX_KEYS", 1 << 16)
    monkeypatch.setattr(attention_module, "products_on_amx", lambda head_channels: False)
    assert torch.equal(ops.attention(q, k, v), F.scaled_dot_product_attention(q, k, v))


@requires_ext
def test_the_kernel_serves_only_where_its_products_run_on_amx():
    """Its plain loops are ~15x slower than torch's kernel (a Zen 4 CPU: AVX512-BF16 without AMX), so
    the kernel reports where it multiplies on AMX tiles: an AMX CPU and heads of 16 to 64 channels in
    steps of 16, never other head sizes."""
    tiles = torch.cpu._is_amx_tile_supported() and os.environ.get("VRNET_CPU_DISPATCH") != "generic"
    for channels in (16, 32, 48, 64):
        assert products_on_amx(channels) == tiles
    for channels in (1, 8, 24, 80, 128):
        assert not products_on_amx(channels)


@requires_ext
def test_under_autocast_the_kernel_keeps_bfloat16():
    """Autocast leaves the op's bfloat16 heads as they are; float32 heads go to the reference, which
    autocast runs in bfloat16."""
    q, k, v = _heads(1, 2, 20, 30, 32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = ops.attention(q, k, v)
        direct = torch.ops.vrnet_ext.attention(q, k, v, 1 / math.sqrt(32))
        from_float = ops.attention(q.float(), k.float(), v.float())
    assert got.dtype == torch.bfloat16 and torch.equal(got, ops.attention(q, k, v)) and torch.equal(direct, got)
    assert from_float.dtype == torch.bfloat16
    torch.testing.assert_close(from_float, got, rtol=2e-2, atol=2e-2)


@requires_ext
def test_op_registration():
    q, k, v = _heads(1, 2, 20, 30, 32)
    opcheck(torch.ops.vrnet_ext.attention.default, (q, k, v, 0.2))


@requires_ext
def test_the_kernel_rejects_non_finite_heads():
    q, k, v = _heads(1, 2, 10, 12, 16)
    nan_k = k.clone()
    nan_k[0, 1, 3, 2] = float("nan")
    cases = (((q, nan_k, v), "k contains NaN"), ((q, k, v.masked_fill(v > 1, float("inf"))), "v contains NaN"),
             ((q.masked_fill(q > 2, float("-inf")), k, v), "q contains NaN"))
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            ops.attention(*args)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_inputs_raise_naming_the_argument(backend):
    q, k, v = _heads(1, 2, 10, 12, 16)
    cases = [
        ((q, k[:, :, :, :8], v), {}, ValueError, "k must have shape"),
        ((q, k, v[:, :, :5]), {}, ValueError, "v must have k's shape"),
        ((q[0], k, v), {}, ValueError, "q must have shape"),
        ((q, k.float(), v), {}, TypeError, "share a dtype"),
        ((q, k.int(), v), {}, TypeError, "k must be a floating tensor"),
        ((q, k[:, :, :0], v[:, :, :0]), {}, ValueError, "at least one key"),
        ((q, k, v), {"scale": 0.0}, ValueError, "scale must be"),
        ((q, k, v), {"scale": float("nan")}, ValueError, "scale must be"),
        ((q, k, v), {"dropout_p": 1.0}, ValueError, "dropout_p"),
    ]
    for args, kwargs, error, message in cases:
        with pytest.raises(error, match=message):
            ops.attention(*args, backend=backend, **kwargs)


@requires_ext
def test_the_compiled_op_checks_its_arguments():
    q, k, v = _heads(1, 2, 10, 12, 16)
    with pytest.raises(TypeError, match="q must be bfloat16"):
        torch.ops.vrnet_ext.attention(q.float(), k, v, 0.25)
    with pytest.raises(ValueError, match="scale must be"):
        torch.ops.vrnet_ext.attention(q, k, v, -1.0)
    with pytest.raises(ValueError, match="q contains NaN"):
        torch.ops.vrnet_ext.attention(q.masked_fill(q > 1, float("nan")), k, v, 0.25)
