import pytest
import torch
from torch import nn

from vrnet_ext.model.transformer import PAIRS_PER_PASS, MultiHeadAttention, Transformer


def _twin_attention(dims=24, heads=4):
    torch.manual_seed(0)
    reference = nn.MultiheadAttention(dims, heads, batch_first=True).double()
    ours = MultiHeadAttention(dims, heads, dropout=0.0).double()
    ours.load_state_dict(reference.state_dict())
    return reference, ours


def test_attention_has_the_parameters_of_torch_multihead_attention():
    reference, ours = _twin_attention()
    assert {k: v.shape for k, v in ours.state_dict().items()} == {k: v.shape for k, v in reference.state_dict().items()}


@pytest.mark.parametrize("cross", [False, True])
def test_attention_equals_torch_multihead_attention(cross):
    reference, ours = _twin_attention()
    queries = torch.randn(3, 17, 24, dtype=torch.float64, requires_grad=True)
    memory = torch.randn(3, 11, 24, dtype=torch.float64, requires_grad=True) if cross else None
    kv = queries if memory is None else memory
    expected = reference(queries, kv, kv, need_weights=False)[0]
    got = ours(queries, memory)
    torch.testing.assert_close(got, expected)
    upstream = torch.randn_like(expected)
    inputs = [queries] + ([memory] if cross else [])
    expected_grads = torch.autograd.grad(expected, inputs + list(reference.parameters()), upstream)
    got_grads = torch.autograd.grad(got, inputs + list(ours.parameters()), upstream)
    for e, g in zip(expected_grads, got_grads):
        torch.testing.assert_close(g, e)


def test_attention_rejects_dims_not_divisible_by_heads():
    with pytest.raises(ValueError, match="divisible by heads"):
        MultiHeadAttention(10, 4, dropout=0.0)


@pytest.mark.parametrize("points", [(19, 19), (19, 13)])
@pytest.mark.parametrize("batch", [2, 2 * PAIRS_PER_PASS + 1])
@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_transformer_is_eta_in_both_directions(points, batch, backend):
    """Equal sizes run both directions as one batch, and the compiled backend takes a large batch
    in slices of PAIRS_PER_PASS pairs; the result and its gradients are still
    Phi_X = F_X + eta(F_X, F_Y), Phi_Y = F_Y + eta(F_Y, F_X)."""
    torch.manual_seed(0)
    transformer = Transformer(16, 2, 32, 1, 1, dropout=0.0).double()
    src = torch.randn(batch, 16, points[0], dtype=torch.float64, requires_grad=True)
    tgt = torch.randn(batch, 16, points[1], dtype=torch.float64, requires_grad=True)
    phi_x, phi_y = transformer(src, tgt, backend=backend)
    fx, fy = src.transpose(1, 2), tgt.transpose(1, 2)
    want_x = (fx + transformer._eta(fx, fy, "torch")).transpose(1, 2)
    want_y = (fy + transformer._eta(fy, fx, "torch")).transpose(1, 2)
    torch.testing.assert_close(phi_x, want_x)
    torch.testing.assert_close(phi_y, want_y)
    assert phi_x.shape == src.shape and phi_y.shape == tgt.shape
    upstream = torch.randn_like(phi_x), torch.randn_like(phi_y)
    parameters = list(transformer.parameters())
    got = torch.autograd.grad((phi_x, phi_y), [src, tgt] + parameters, upstream)
    want = torch.autograd.grad((want_x, want_y), [src, tgt] + parameters, upstream)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w)


def _autocast_transformer():
    torch.manual_seed(3)
    model = Transformer(32, 4, 64, 1, 1, 0.0).eval()
    src, tgt = torch.randn(2, 32, 40), torch.randn(2, 32, 40)
    return model, src, tgt


def _under_autocast(model, src, tgt, grad: bool, backend: str = "ext"):
    with torch.set_grad_enabled(grad), torch.autocast("cpu", dtype=torch.bfloat16):
        return tuple(t.detach() for t in model(src, tgt, backend=backend))


def test_autocast_inference_reuses_its_casts_with_the_same_results():
    """Without gradients the bfloat16 casts of the weights are made once and kept: the outputs equal
    those of autocast's own per-call casts (taken while gradients are recorded) bit for bit (the
    attention itself on the reference in both, since recording gradients picks the reference)."""
    model, src, tgt = _autocast_transformer()
    recorded = _under_autocast(model, src, tgt, grad=True, backend="torch")
    for _ in range(2):
        for got, expected in zip(_under_autocast(model, src, tgt, grad=False, backend="torch"), recorded):
            assert torch.equal(got, expected)
    cached = [m.__dict__.get("_inference_cache", {}) for m in model.modules()]
    assert sum(len(c) for c in cached) == 20  # weight and bias: 3 x (packed + output projection), 2 x 2 linears
    assert set(model.state_dict()) == set(Transformer(32, 4, 64, 1, 1, 0.0).state_dict())


def test_autocast_casts_follow_weights_changed_in_place_or_replaced():
    model, src, tgt = _autocast_transformer()
    _under_autocast(model, src, tgt, grad=False)  # fills the cache
    with torch.no_grad():
        model.decoder[0].feed_forward.net[1].weight.mul_(2)
        model.encoder[0].self_attention.attention.in_proj_weight.add_(0.1)
    model.decoder[0].cross_attention.attention.out_proj.weight.data = torch.randn(32, 32)
    for got, expected in zip(_under_autocast(model, src, tgt, grad=False, backend="torch"),
                             _under_autocast(model, src, tgt, grad=True, backend="torch")):
        assert torch.equal(got, expected)


def test_autocast_training_still_reaches_every_weight():
    model, src, tgt = _autocast_transformer()
    model.train()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = sum(t.float().square().mean() for t in model(src, tgt))
    loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
