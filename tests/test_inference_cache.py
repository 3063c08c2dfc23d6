import torch
from torch import nn

from vrnet_ext.model.dgcnn import DGCNN
from vrnet_ext.nn import PointwiseMLP, inference_cached


def test_kept_while_the_sources_are_unchanged_and_recomputed_when_they_change():
    module = nn.Linear(3, 2)
    calls = []

    def doubled():
        calls.append(1)
        return module.weight.detach() * 2

    with torch.no_grad():
        first = inference_cached(module, "doubled", (module.weight, None), doubled)
        assert inference_cached(module, "doubled", (module.weight, None), doubled) is first and len(calls) == 1
        module.weight.add_(1)  # in place: a new version
        changed = inference_cached(module, "doubled", (module.weight, None), doubled)
        assert len(calls) == 2 and torch.equal(changed, module.weight * 2)
        module.weight = nn.Parameter(torch.zeros(2, 3))  # replaced: new storage
        assert torch.equal(inference_cached(module, "doubled", (module.weight, None), doubled), torch.zeros(2, 3))
        assert len(calls) == 3
    inference_cached(module, "doubled", (module.weight, None), doubled)  # recording gradients: never cached
    inference_cached(module, "doubled", (module.weight, None), doubled)
    assert len(calls) == 5


def _trained_statistics(module: nn.Module, *inputs) -> None:
    module.train()
    with torch.no_grad():
        for _ in range(3):
            module(*inputs)
    module.eval()


def _fresh(module: nn.Module, *inputs) -> torch.Tensor:
    """The module's output with every kept value computed afresh (its caches emptied first), without
    gradients, as the cached forwards run (grad mode may take other matrix-product paths)."""
    for sub in module.modules():
        sub.__dict__.pop("_inference_cache", None)
    with torch.no_grad():
        return module(*inputs)


def test_folded_pointwise_layers_follow_their_statistics():
    """Eval-mode folds are kept between forwards without gradients, give the per-call folds' results
    bit for bit, and follow running statistics and weights changed in place."""
    torch.manual_seed(0)
    mlp = PointwiseMLP(nn.Conv1d(6, 8, 1, bias=False), nn.BatchNorm1d(8), nn.ReLU(), nn.Conv1d(8, 3, 1))
    x = torch.randn(2, 6, 50)
    _trained_statistics(mlp, x)
    fresh = _fresh(mlp, x)
    with torch.no_grad():
        assert torch.equal(mlp(x), fresh) and torch.equal(mlp(x), fresh)
        mlp[1].running_var.mul_(2)
        mlp[3].weight.add_(0.5)
        kept = mlp(x)
    assert torch.equal(kept, _fresh(mlp, x))


def test_dgcnn_eval_features_follow_their_weights():
    torch.manual_seed(1)
    dgcnn = DGCNN((8, 8, 16), 16, 5, 0.2)
    points = torch.randn(2, 40, 3)
    _trained_statistics(dgcnn, points)
    fresh = _fresh(dgcnn, points)
    with torch.no_grad():
        assert torch.equal(dgcnn(points), fresh) and torch.equal(dgcnn(points), fresh)
        dgcnn.layers[1].conv.weight.mul_(-1)
        dgcnn.projection_bn.running_mean.add_(0.3)
        kept = dgcnn(points)
    assert torch.equal(kept, _fresh(dgcnn, points))
