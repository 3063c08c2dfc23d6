"""VRNet's eval forward replayed as CUDA graphs (vrnet_ext.model.cuda_graphs): the eager forward's
results, one graph per shape, the clouds checked before every replay. The GPU cases run in
`.ci/gpu`; here only the refusals."""
from dataclasses import replace

import pytest
import torch

from vrnet_ext import load_pretrained
from vrnet_ext.model.cuda_graphs import CudaGraphForward

requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def clouds(B: int, points: int, seed: int = 0, device: str = "cuda") -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(B, points, 3, generator=g)
    rotation = torch.linalg.qr(torch.randn(B, 3, 3, generator=g, dtype=torch.float64))[0]
    rotation = rotation * torch.sign(torch.linalg.det(rotation))[:, None, None]
    return src.to(device), (src @ rotation.float().mT + 0.1).to(device)


def test_refuses_what_it_cannot_capture():
    model = load_pretrained()
    with pytest.raises(ValueError, match="eval"):
        CudaGraphForward(model.train())
    model.eval().config = replace(model.config, rotation_search_below=0.1)
    with pytest.raises(ValueError, match="rotation_search_below"):
        CudaGraphForward(model)
    if not torch.cuda.is_available():
        model.config = replace(model.config, rotation_search_below=0.0)
        with pytest.raises(ValueError, match="CUDA device"):
            CudaGraphForward(model)


@requires_cuda
@pytest.mark.parametrize("solve", [{"second_pass_below": 0.0}, {}, {"polish_iterations": 5}])
def test_graph_replays_give_the_eager_results(solve):
    model = load_pretrained().cuda()
    model.config = replace(model.config, **solve)
    graphed = CudaGraphForward(model)
    for B, seed in ((1, 0), (1, 1), (4, 2), (1, 3)):  # two shapes, replays with new data
        src, tgt = clouds(B, 768, seed)
        with torch.no_grad():
            expected = model(src, tgt)
        out = graphed(src, tgt)
        torch.testing.assert_close(out.rotation, expected.rotation, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(out.translation, expected.translation, rtol=1e-4, atol=1e-4)
        assert torch.equal(out.second_pass, expected.second_pass) and torch.equal(out.polished, expected.polished)
    assert len(graphed._graphs) == 2


@requires_cuda
def test_a_replay_checks_the_clouds_and_their_device():
    graphed = CudaGraphForward(load_pretrained().cuda())
    src, tgt = clouds(1, 768)
    graphed(src, tgt)
    bad = src.clone()
    bad[0, 5, 1] = float("nan")
    with pytest.raises(ValueError, match="src contains NaN"):
        graphed(bad, tgt)
    with pytest.raises(ValueError, match="tgt must be a CUDA tensor"):
        graphed(src, tgt.cpu())
    torch.testing.assert_close(graphed(src, tgt).rotation, graphed(src, tgt).rotation, rtol=0, atol=0)
