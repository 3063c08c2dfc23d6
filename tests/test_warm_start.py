import pytest
import torch

from vrnet_ext.model import VRNet, VRNetConfig
from vrnet_ext.learning.warm_start import init_features_from, init_walk_from


def small_config(**overrides):
    values = dict(k=6, dgcnn_channels=(16, 16, 32), emb_dims=32, ff_dims=64, walk_channels=(32, 16, 3),
                  walk_gate=True, walk_confidence=True)
    return VRNetConfig.small(**dict(values, **overrides))


def saved_run(tmp_path, config, seed=0):
    """A trained-looking model (every walk weight non-zero) written as a training checkpoint."""
    torch.manual_seed(seed)
    model = VRNet(config).eval()
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            if tensor.is_floating_point() and "running_var" not in name:
                tensor.copy_(torch.randn_like(tensor) * 0.3)
    path = tmp_path / f"run{seed}.pt"
    torch.save({"model": model.state_dict(), "config": {"model": config.to_dict()}}, path)
    return model, path


def test_a_shared_walk_split_into_two_mlps_computes_what_it_did(tmp_path):
    shared, path = saved_run(tmp_path, small_config())
    split = VRNet(small_config(walk_confidence_trunk=True)).eval()
    init_features_from(split, str(path))
    init_walk_from(split, str(path))
    src, tgt = torch.randn(2, 60, 3), torch.randn(2, 50, 3)
    with torch.no_grad():
        before, after = shared(src, tgt), split(src, tgt)
    assert before.confidence_logits.abs().max() > 0.1 and before.offset.abs().max() > 1e-3
    for name in ("offset", "gate_logits", "confidence_logits", "rcp", "rotation", "translation"):
        torch.testing.assert_close(getattr(after, name), getattr(before, name), msg=name)


def test_a_walk_of_the_same_shape_is_copied_and_mismatches_name_the_argument(tmp_path):
    source, path = saved_run(tmp_path, small_config(walk_confidence_trunk=True))
    model = VRNet(small_config(walk_confidence_trunk=True))
    init_walk_from(model, str(path))
    for name, tensor in source.walk.state_dict().items():
        torch.testing.assert_close(model.walk.state_dict()[name], tensor, msg=name)
    with pytest.raises(ValueError, match="walk_from: .* cannot start a shared-trunk walk"):
        init_walk_from(VRNet(small_config()), str(path))
    with pytest.raises(ValueError, match=r"walk_from: .*other settings \(walk_gate\)"):
        init_walk_from(VRNet(small_config(walk_confidence_trunk=True, walk_gate=False)), str(path))
    with pytest.raises(ValueError, match=r"features_from: .*other settings \(emb_dims, ff_dims\)"):
        init_features_from(VRNet(small_config(emb_dims=64, ff_dims=128)), str(path))
