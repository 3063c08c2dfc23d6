"""Second-order gradients through the compiled ops: where the backward is linear in the incoming
gradient (edge_features, gather_reduce) it is differentiable and gradgradcheck passes; every other
op raises NotImplementedError naming itself rather than contributing nothing."""
import pytest
import torch

from conftest import requires_ext
from vrnet_ext import ops

pytestmark = requires_ext


def test_linear_backwards_are_differentiable():
    torch.manual_seed(0)
    x = torch.randn(1, 2, 9, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 9, (1, 9, 3))
    assert torch.autograd.gradgradcheck(lambda t: ops.edge_features(t, idx).sin(), (x,))
    for reduce in ("max", "min", "sum", "mean"):
        assert torch.autograd.gradgradcheck(lambda t: ops.gather_reduce(t, idx, reduce).sin(), (x,))


def test_a_gradient_penalty_reaches_the_weights():
    """d/dw of |d loss / d x|^2 through edge_features: not None, and equal to the reference's."""
    torch.manual_seed(1)
    x = torch.randn(1, 4, 15, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 15, (1, 15, 3))
    weight = torch.randn(6, 8, dtype=torch.float64, requires_grad=True)
    penalties = []
    for backend in ("ext", "torch"):
        edges = ops.edge_features(x, idx, backend=backend)  # (1, 8, 15, 3)
        loss = torch.einsum("oc,bcnk->bonk", weight, edges).tanh().sum()
        (grad_x,) = torch.autograd.grad(loss, x, create_graph=True)
        (penalty,) = torch.autograd.grad(grad_x.square().sum(), weight)
        penalties.append(penalty)
    torch.testing.assert_close(penalties[0], penalties[1])


def _points(*shape):
    return torch.randn(*shape, dtype=torch.float64, requires_grad=True)


@pytest.mark.parametrize("name, fn", [
    ("knn", lambda p: ops.knn(p, p.detach() + 0.1, 3)[0]),
    ("kabsch", lambda p: ops.kabsch(p, p.detach().flip(1))[0]),
    ("svd3x3", lambda p: ops.svd3x3(p[:, :3])[1]),
    ("pairwise_distance_loss", lambda p: ops.pairwise_distance_loss(p, p.detach() * 1.1)),
    ("soft_match", lambda p: ops.soft_match(p, p.detach(), p.detach())),
    ("edge_norm_max", lambda p: ops.edge_norm_max(p.transpose(1, 2)[:, :2], torch.zeros(1, 8, 2, dtype=torch.long))[0]),
])
def test_other_ops_refuse_second_order_by_name(name, fn):
    p = _points(1, 8, 3)
    with pytest.raises(NotImplementedError, match=f"vrnet_ext.ops.{name}: the compiled kernel is differentiable once"):
        torch.autograd.grad(fn(p).sin().sum(), p, create_graph=True)
    # first order is unaffected
    (first,) = torch.autograd.grad(fn(p).sin().sum(), p)
    assert torch.isfinite(first).all()
