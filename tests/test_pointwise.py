import pytest
import torch
from torch import nn

from vrnet_ext.model.dgcnn import DGCNN
from vrnet_ext.nn import PointwiseMLP, folded_affine
from vrnet_ext.ops import knn


def trained_like(module: nn.Module) -> nn.Module:
    """Random BatchNorm affine parameters and running statistics (away from the identity)."""
    torch.manual_seed(1)
    for m in module.modules():
        if isinstance(m, nn.BatchNorm1d):
            with torch.no_grad():
                m.weight.uniform_(-2, 2)
                m.bias.normal_()
                m.running_mean.normal_()
                m.running_var.uniform_(0.1, 3)
    return module


def mlp(bias_first: bool) -> PointwiseMLP:
    torch.manual_seed(0)
    return trained_like(PointwiseMLP(nn.Conv1d(7, 12, 1, bias=bias_first), nn.BatchNorm1d(12), nn.ReLU(),
                                     nn.Conv1d(12, 5, 1, bias=False), nn.BatchNorm1d(5), nn.ReLU(),
                                     nn.Conv1d(5, 3, 1)))


@pytest.mark.parametrize("bias_first", [False, True])
@pytest.mark.parametrize("layout", ["channel-major", "point-major"])
def test_folded_eval_matches_the_layers(bias_first, layout):
    model = mlp(bias_first).eval()
    x = torch.randn(2, 13, 7).transpose(1, 2) if layout == "point-major" else torch.randn(2, 7, 13)
    expected = nn.Sequential(*model)(x)
    torch.testing.assert_close(model(x), expected, rtol=1e-5, atol=1e-5)
    x64, model64 = x.double(), mlp(bias_first).double().eval()
    torch.testing.assert_close(model64(x64), nn.Sequential(*model64)(x64), rtol=1e-12, atol=1e-12)


def test_training_mode_runs_the_layers_and_updates_statistics():
    model = mlp(True).train()
    x = torch.randn(2, 7, 13)
    before = model[1].running_mean.clone()
    out = model(x)
    assert not torch.equal(model[1].running_mean, before)
    out.sum().backward()
    assert model[0].weight.grad is not None


def test_eval_gradients_reach_the_parameters_and_the_input():
    model = mlp(True).eval()
    x = torch.randn(2, 7, 13, dtype=torch.float64, requires_grad=True)
    model = model.double()
    assert torch.autograd.gradcheck(lambda inp: model(inp), (x,))
    model(x).sum().backward()
    assert model[1].weight.grad is not None and model[0].weight.grad is not None


def test_folded_affine_of_a_conv_without_batchnorm_is_the_conv():
    conv = nn.Conv1d(4, 6, 1)
    weight, bias = folded_affine(conv, None)
    assert torch.equal(weight, conv.weight[:, :, 0]) and torch.equal(bias, conv.bias)


def test_only_1x1_convolutions_are_accepted():
    model = PointwiseMLP(nn.Conv1d(3, 4, 3), nn.BatchNorm1d(4)).eval()
    with pytest.raises(TypeError, match="1x1 Conv1d"):
        model(torch.randn(1, 3, 9))


def test_dgcnn_eval_projection_matches_the_layers():
    model = trained_like(DGCNN((8, 8), 16, 4, 0.2)).eval()
    with torch.no_grad():
        model.projection_bn.running_mean.normal_()
        model.projection_bn.running_var.uniform_(0.5, 2)
    points = torch.randn(2, 40, 3)
    folded = model(points)
    with torch.no_grad():  # the same layers without folding: BatchNorm as a module
        outputs, x = [], points.transpose(1, 2)
        for layer in model.layers:
            idx = knn(x.transpose(1, 2), x.transpose(1, 2), model.k)[1]
            x = layer(x, idx)
            outputs.append(x)
        expected = torch.nn.functional.leaky_relu(model.projection_bn(model.projection(torch.cat(outputs, 1))), 0.2)
    torch.testing.assert_close(folded, expected, rtol=1e-5, atol=1e-5)
