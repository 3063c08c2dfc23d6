import importlib
from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import compile_fullgraph, requires_ext
from vrnet_ext import VRNet, VRNetConfig, has_extension, ops
from vrnet_ext.geometry.metrics import rotation_error_deg


def small_model(**overrides):
    torch.manual_seed(0)
    return VRNet(VRNetConfig.small(k=6, dgcnn_channels=(16, 16, 32), emb_dims=32, ff_dims=64,
                                   walk_channels=(32, 16, 3), **overrides))


def clouds(B=2, N=60, M=50):
    return torch.randn(B, N, 3), torch.randn(B, M, 3)


def test_paper_defaults():
    cfg = VRNetConfig()
    assert (cfg.k, cfg.dgcnn_channels, cfg.emb_dims, cfg.heads, cfg.ff_dims) == (20, (64, 64, 128, 256), 512, 4, 1024)
    assert cfg.walk_channels == (512, 256, 512, 256, 128, 16, 3)
    model = VRNet()
    assert model.walk.net[0].in_channels == 1024


def test_output_shapes_and_invariants(device):
    model = small_model().train()
    src, tgt = clouds()
    out = model(src, tgt, return_matching=True)
    assert out.rotation.shape == (2, 3, 3) and out.translation.shape == (2, 3)
    assert out.matching.shape == (2, 60, 50)
    assert out.vcp.shape == out.rcp.shape == out.offset.shape == (2, 60, 3)
    torch.testing.assert_close(out.matching.sum(-1), torch.ones(2, 60))
    torch.testing.assert_close(torch.linalg.det(out.rotation), torch.ones(2), rtol=0, atol=1e-5)
    torch.testing.assert_close(out.rcp, out.vcp + out.offset)
    torch.testing.assert_close(out.vcp, out.matching @ tgt)


@requires_ext
@pytest.mark.parametrize("train", [True, False])
def test_backends_agree(device, train):
    model = small_model().train(train)
    src, tgt = clouds()
    state = {k: v.clone() for k, v in model.state_dict().items()}
    fast = model(src, tgt, backend="ext", return_matching=True)
    model.load_state_dict(state)
    slow = model(src, tgt, backend="torch", return_matching=True)
    for name in ("rotation", "translation", "matching", "vcp", "rcp"):
        torch.testing.assert_close(getattr(fast, name), getattr(slow, name), rtol=1e-3, atol=2e-4, msg=name)


def test_permutation_equivariance_sanity(device):
    model = small_model(transformer_precision="fp32").eval()  # the function itself, to float32 rounding
    src, tgt = clouds()
    perm_src, perm_tgt = torch.randperm(60), torch.randperm(50)
    with torch.no_grad():
        base = model(src, tgt, return_matching=True)
        moved = model(src[:, perm_src], tgt[:, perm_tgt], return_matching=True)
    torch.testing.assert_close(moved.rotation, base.rotation, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(moved.translation, base.translation, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(moved.rcp, base.rcp[:, perm_src], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(moved.matching, base.matching[:, perm_src][:, :, perm_tgt], rtol=1e-4, atol=1e-6)


def test_walk_starts_as_no_correction():
    model = small_model().train()
    src, tgt = clouds()
    out = model(src, tgt)
    assert not out.offset.any() and torch.equal(out.rcp, out.vcp)
    out.rcp.square().sum().backward()
    assert model.walk.net[-1].weight.grad.abs().sum() > 0, "the zero layer must still learn"
    assert small_model(walk_zero_init=False).walk.net[-1].weight.abs().sum() > 0


def test_dcp_ablation_and_iterations(device):
    src, tgt = clouds()
    dcp = small_model(correction_walk=False).eval()
    out = dcp(src, tgt)
    assert dcp.walk is None and torch.equal(out.rcp, out.vcp) and not out.offset.any()
    iterative = small_model(iterations=3).eval()
    single = small_model(iterations=1).eval()  # the same weights (same seed), one pass per call
    with torch.no_grad():
        out3 = iterative(src, tgt)
        R, t, moved = torch.eye(3).expand(2, 3, 3), torch.zeros(2, 3), src
        for _ in range(3):  # each pass estimates the motion still left between the moved source and tgt
            step = single(moved, tgt)
            R, t = step.rotation @ R, (step.rotation @ t.unsqueeze(-1)).squeeze(-1) + step.translation
            moved = src @ R.mT + t.unsqueeze(1)
    torch.testing.assert_close(out3.rotation, R, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out3.translation, t, rtol=1e-4, atol=1e-5)
    assert (out3.rotation - single(src, tgt).rotation).abs().max() > 1e-3, "three passes must differ from one"


def test_later_passes_reuse_the_targets_features():
    """In eval mode only the first pass runs the DGCNN on the target (both clouds as one batch);
    later iterations and the second pass run it on the moved source alone. In training every pass
    runs it on both clouds (their batch statistics are the pass's own)."""
    model = small_model(iterations=3, consistency_radius=1.0)
    src, tgt = turned_pairs()
    model.train()
    model(src, tgt)  # running statistics that are not the initial ones
    clouds_seen = []
    model.features.register_forward_hook(lambda module, inputs, output: clouds_seen.append(inputs[0].shape[0]))
    B = src.shape[0]
    with torch.no_grad():
        model(src, tgt)
    assert clouds_seen == [B] * 6
    clouds_seen.clear()
    model.eval()
    with torch.no_grad():
        model(src, tgt)
        model.config.second_pass_below = 1.0  # every pair is retried
        model(src, tgt)
    assert clouds_seen == [2 * B, B, B] + [2 * B, B, B, B]


@requires_ext
@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_torch_compile(device, backend):
    model = small_model().eval()
    src, tgt = clouds()
    compiled = compile_fullgraph(lambda s, t: model(s, t, backend=backend))
    with torch.no_grad():
        torch.testing.assert_close(compiled(src, tgt).rotation, model(src, tgt, backend=backend).rotation,
                                   rtol=1e-4, atol=1e-5)


def test_bad_input():
    model = small_model()
    src, tgt = clouds()
    with pytest.raises(ValueError, match="src"):
        model(src[0], tgt)
    with pytest.raises(ValueError, match="tgt"):
        model(src, tgt[..., :2])
    with pytest.raises(TypeError, match="src"):
        model(src.long(), tgt)
    with pytest.raises(ValueError, match="batch"):
        model(src, tgt[:1])
    with pytest.raises(ValueError, match="at least k"):
        model(src[:, :4], tgt)
    poisoned = src.clone()
    poisoned[1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="src contains NaN"):
        model(poisoned, tgt)
    with pytest.raises(ValueError, match="tgt contains NaN"):
        model(src, tgt.clone().fill_(float("inf")))
    with pytest.raises(TypeError, match="src.*float64.*float32"):
        model(src.double(), tgt.double())
    with pytest.raises(ValueError, match="walk_channels"):
        VRNetConfig(walk_channels=(8, 4))


def test_gated_walk_with_confidence_starts_as_unweighted_vcp_procrustes():
    from vrnet_ext.ops import kabsch

    model = small_model(walk_gate=True, walk_confidence=True).eval()
    src, tgt = clouds()
    out = model(src, tgt)
    assert model.walk.net[-1].out_channels == 5  # offset (3) + gate + confidence
    assert not out.offset.any() and torch.equal(out.rcp, out.vcp)
    torch.testing.assert_close(out.weights, torch.full((2, 60), 0.5))
    R, t = kabsch(src, out.vcp)
    torch.testing.assert_close(out.rotation, R)
    torch.testing.assert_close(out.translation, t)


def test_gate_scales_the_offset_and_confidence_weights_the_procrustes():
    from vrnet_ext.ops import kabsch

    model = small_model(walk_gate=True, walk_confidence=True).eval()
    last = model.walk.net[-1]
    with torch.no_grad():
        last.weight.normal_()
        last.bias[3] = -40.0  # gate logit: the offsets of every point vanish
    src, tgt = clouds()
    out = model(src, tgt)
    assert out.offset.abs().max() < 1e-12 and out.gate_logits.shape == (2, 60)
    torch.testing.assert_close(out.rcp, out.vcp)
    R, t = kabsch(src, out.rcp, torch.sigmoid(out.confidence_logits))
    torch.testing.assert_close(out.rotation, R)
    torch.testing.assert_close(out.translation, t)
    R_plain, _ = kabsch(src, out.rcp)
    assert (out.rotation - R_plain).abs().max() > 1e-4, "the weights must change the estimate"
    with torch.no_grad():
        last.bias[3] = 40.0  # gate open: the raw offsets pass unchanged
    opened = model(src, tgt, return_matching=True)
    raw = model.walk.net(torch.cat([opened.src_embedding, torch.bmm(opened.tgt_embedding, opened.matching.mT)], 1))
    torch.testing.assert_close(opened.offset, raw[:, :3].transpose(1, 2))


@pytest.mark.parametrize("kernel, scale", [("cauchy", 0.5), ("geman_mcclure", 1.0), ("welsch", 0.75)])
def test_the_model_solves_with_its_irls_options(kernel, scale):
    model = small_model(irls_iterations=4, irls_kernel=kernel, irls_scale=scale).eval()
    a, b = clouds()
    with torch.no_grad():
        out = model(a, b)
    again = ops.robust_kabsch(a, out.rcp, out.weights, 4, kernel, scale, model.config.irls_min_scale)
    torch.testing.assert_close(out.rotation, again[0])
    torch.testing.assert_close(out.translation, again[1])


def test_irls_options_are_checked():
    from vrnet_ext.model.config import IRLS_KERNELS
    from vrnet_ext.ops.kabsch import ROBUST_KERNELS

    assert IRLS_KERNELS == ROBUST_KERNELS  # the torch-free config names the op's kernels
    with pytest.raises(ValueError, match="irls_kernel"):
        VRNetConfig(irls_kernel="huber")
    with pytest.raises(ValueError, match="irls_scale"):
        VRNetConfig(irls_scale=0.0)


def test_walk_match_stats_are_the_rows_peak_and_entropy():
    model = small_model(walk_match_stats=True, walk_gate=True, walk_confidence=True).eval()
    assert model.walk.net[0].in_channels == 2 * 32 + 2
    src, tgt = clouds()
    seen = {}
    model.walk.register_forward_pre_hook(lambda module, args: seen.setdefault("seeds", args[0]))
    out = model(src, tgt, return_matching=True)
    peak, entropy = seen["seeds"][:, -2], seen["seeds"][:, -1]
    torch.testing.assert_close(peak, out.matching.max(-1).values)
    torch.testing.assert_close(entropy, -(out.matching * out.matching.log()).sum(-1))


def test_procrustes_on_vcps_with_the_walks_confidences():
    from vrnet_ext.ops import kabsch

    model = small_model(walk_gate=True, walk_confidence=True, procrustes_points="vcp").eval()
    with torch.no_grad():
        model.walk.net[-1].weight.normal_()  # offsets, gate and confidences all non-trivial
    src, tgt = clouds()
    out = model(src, tgt)
    assert (out.rcp - out.vcp).abs().max() > 1e-3
    R, t = kabsch(src, out.vcp, out.weights)
    torch.testing.assert_close(out.rotation, R)
    torch.testing.assert_close(out.translation, t)
    with pytest.raises(ValueError, match="procrustes_points"):
        VRNetConfig(procrustes_points="both")


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_streamed_matching_equals_the_dense_matrix_path(device, backend):
    """Without return_matching the VCPs, matched features and row statistics come from
    ops.soft_match; outputs and every parameter's gradient equal the dense path's."""
    if backend == "ext" and not has_extension():
        pytest.skip("compiled module vrnet_ext._C is not built")
    model = small_model(walk_match_stats=True, walk_gate=True, walk_confidence=True).train()
    with torch.no_grad():
        model.walk.net[-1].bias.normal_()  # an open, non-trivial walk
    src, tgt = clouds()
    runs = []
    for dense in (False, True):
        model.zero_grad()
        out = model(src, tgt, backend=backend, return_matching=dense)
        (out.rcp.square().sum() + out.rotation.sum() + out.confidence_logits.sum()).backward()
        runs.append((out, {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}))
    (streamed, streamed_grads), (dense, dense_grads) = runs
    assert streamed.matching is None and dense.matching is not None
    for name in ("rotation", "translation", "vcp", "rcp", "gate_logits", "confidence_logits"):
        torch.testing.assert_close(getattr(streamed, name), getattr(dense, name), rtol=1e-4, atol=1e-5, msg=name)
    assert streamed_grads.keys() == dense_grads.keys() and len(dense_grads) > 10
    for name, grad in dense_grads.items():  # float32 rounding, relative to each gradient's size
        assert (streamed_grads[name] - grad).abs().max() <= 1e-4 * grad.abs().max() + 1e-7, name


def test_a_confidence_trunk_keeps_the_offsets_loss_out_of_the_confidences():
    from vrnet_ext.learning.losses import offset_log_loss

    model = small_model(walk_gate=True, walk_confidence=True, walk_confidence_trunk=True).train()
    assert model.walk.net[-1].out_channels == 4 and model.walk.confidence_net[-1].out_channels == 1
    src, tgt = clouds()
    out = model(src, tgt)
    torch.testing.assert_close(out.weights, torch.full((2, 60), 0.5))  # zero-initialised like the shared head
    offset_log_loss(out.rcp, src + 0.1, 0.01).mean().backward()
    assert all(p.grad is None or not p.grad.any() for p in model.walk.confidence_net.parameters())
    assert any(p.grad is not None and p.grad.any() for p in model.walk.net.parameters())
    with pytest.raises(ValueError, match="walk_confidence_trunk needs walk_confidence"):
        VRNetConfig.small(walk_confidence_trunk=True)


def test_eval_mode_features_of_both_clouds_in_one_batch_equal_separate_passes():
    """Clouds of one size go through DGCNN as one batch in eval mode: each cloud's features are the
    same as from a pass of its own (BatchNorm on running statistics)."""
    model = small_model()
    model.train()
    model(*clouds(B=4, N=40, M=40))  # running statistics that are not the initial ones
    model.eval()
    src, tgt = clouds(B=3, N=50, M=50)
    with torch.no_grad():
        batched = model._features(src, tgt, "torch")
        separate = (model.features(src, "torch"), model.features(tgt, "torch"))
    for one, other in zip(batched, separate):
        torch.testing.assert_close(one, other, rtol=1e-5, atol=1e-6)


def test_frozen_features_run_as_at_inference_and_the_walk_still_learns():
    """Stage 2 (features frozen and in eval mode, the walk training): the features, VCPs and
    matching statistics are those of an eval-mode forward bit for bit, recorded by no autograd
    graph, while the walk's outputs carry gradients to its parameters. A cloud that requires a
    gradient still gets one through the frozen features."""
    from vrnet_ext.learning.train import set_stage, stage_train_mode

    model = small_model(walk_gate=True, walk_confidence=True, walk_match_stats=True)
    model.train()
    model(*clouds(B=4, N=40, M=40))  # running statistics that are not the initial ones
    src, tgt = clouds(B=3, N=50, M=50)
    with torch.no_grad():
        served = model.eval()(src, tgt)
    params = [p for group in set_stage(model, 2) for p in group["params"]]
    model.train()
    stage_train_mode(model, 2)
    assert model.walk.training and not model.features.training and not model.transformer.training
    assert not model.features_need_grad(src, tgt)
    out = model(src, tgt)
    for name in ("src_embedding", "tgt_embedding", "vcp"):
        assert torch.equal(getattr(out, name), getattr(served, name)), name
        assert not getattr(out, name).requires_grad, name
    out.rcp.square().sum().backward()
    assert all(p.grad is not None for p in params)
    src_with_grad = src.clone().requires_grad_()
    assert model.features_need_grad(src_with_grad, tgt)
    model(src_with_grad, tgt).vcp.sum().backward()
    assert src_with_grad.grad is not None and bool(src_with_grad.grad.abs().sum() > 0)


def test_transformer_precision_choice(monkeypatch):
    import vrnet_ext.model.vrnet as vrnet_module

    src = clouds()[0]
    for native in (True, False):
        monkeypatch.setattr(vrnet_module, "cpu_has_native_bf16", lambda native=native: native)
        model = small_model()
        assert model.train().transformer_in_bf16(src) is False  # training: its own autocast decides
        assert model.eval().transformer_in_bf16(src) is native
        model.train().transformer.eval()  # stage 2 of training: the Transformer is frozen
        assert model.transformer_in_bf16(src) is native
        model.eval()
        assert model.transformer_in_bf16(src.double()) is False
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert model.transformer_in_bf16(src) is False  # an enclosing region decides
        model.config.transformer_precision = "fp32"
        assert model.transformer_in_bf16(src) is False
        model.config.transformer_precision = "bf16"
        assert model.train().transformer_in_bf16(src) is True
    with pytest.raises(ValueError, match="transformer_precision"):
        VRNetConfig.small(transformer_precision="half")


def test_bf16_transformer_stays_close_to_float32():
    """The bf16 Transformer changes the features by bfloat16 rounding only: the estimate moves by a
    small fraction of a degree, the outputs stay float32."""
    model = small_model().eval()
    src, tgt = clouds()
    with torch.no_grad():
        model.config.transformer_precision = "fp32"
        exact = model(src, tgt)
        model.config.transformer_precision = "bf16"
        fast = model(src, tgt)
    assert fast.rotation.dtype == torch.float32 and fast.src_embedding.dtype == torch.float32
    assert not torch.equal(fast.src_embedding, exact.src_embedding)  # bfloat16 did run
    torch.testing.assert_close(fast.src_embedding, exact.src_embedding, rtol=0.05, atol=0.05)
    assert float(rotation_error_deg(fast.rotation, exact.rotation).max()) < 1.0


def turned_pairs(B=6, N=60):
    """Targets that are the sources turned about z by growing angles, plus a little noise."""
    from vrnet_ext.geometry.transforms import move

    torch.manual_seed(3)
    src = torch.randn(B, N, 3)
    angles = torch.linspace(0.2, 2.5, B)
    rotation = torch.zeros(B, 3, 3)
    rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 1, 0], rotation[:, 1, 1] = (angles.cos(), -angles.sin(),
                                                                                angles.sin(), angles.cos())
    rotation[:, 2, 2] = 1
    return src, move(src, rotation, torch.zeros(B, 3)) + 0.01 * torch.randn(B, N, 3)


def test_consistency_is_the_share_of_rcps_on_the_estimate():
    src, tgt = turned_pairs()
    model = small_model(consistency_radius=1.0).eval()
    with torch.no_grad():
        out = model(src, tgt)
    moved = src.double() @ out.rotation.double().mT + out.translation.double()[:, None]
    expected = ((moved - out.rcp.double()).norm(dim=-1) < 1.0).double().mean(dim=-1)
    torch.testing.assert_close(out.consistency.double(), expected)
    assert 0 < out.consistency.min() and out.consistency.max() < 1  # the radius cuts through every pair
    assert not out.second_pass.any()  # second_pass_below = 0: never


def test_the_second_pass_keeps_the_more_consistent_pass_of_each_pair():
    from vrnet_ext.geometry.transforms import compose, move

    src, tgt = turned_pairs()
    single = small_model(consistency_radius=1.0).eval()
    with torch.no_grad():
        first = single(src, tgt)
        again = single(move(src, first.rotation, first.translation), tgt)
        R2, t2 = compose(again.rotation, again.translation, first.rotation, first.translation)
        moved = move(src, R2, t2)
        consistency2 = ((moved - again.rcp).norm(dim=-1) < 1.0).float().mean(dim=-1)
    below = float(first.consistency.sort().values[-2])  # every pair is retried but the most consistent one
    retried = first.consistency < below
    expected_second = retried & (consistency2 > first.consistency)
    assert expected_second.any() and not expected_second.all(), "the pairs must exercise both outcomes"
    model = small_model(consistency_radius=1.0, second_pass_below=below).eval()
    with torch.no_grad():
        out = model(src, tgt)
    assert torch.equal(out.second_pass, expected_second)
    pick = expected_second[:, None, None]
    torch.testing.assert_close(out.rotation, torch.where(pick, R2, first.rotation), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.translation, torch.where(pick[:, 0], t2, first.translation), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.rcp, torch.where(pick, again.rcp, first.rcp), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.consistency, torch.where(expected_second, consistency2, first.consistency))
    with torch.no_grad():  # each pair alone gets what it gets in the batch
        alone = [model(src[i:i + 1], tgt[i:i + 1]) for i in range(len(src))]
    torch.testing.assert_close(torch.cat([a.rotation for a in alone]), out.rotation, rtol=1e-4, atol=1e-5)
    assert torch.equal(torch.cat([a.second_pass for a in alone]), out.second_pass)
    src.requires_grad_(True)  # the kept rows stay differentiable in the clouds
    model(src, tgt).rotation.sum().backward()
    assert src.grad is not None and torch.isfinite(src.grad).all() and src.grad[expected_second].abs().sum() > 0
    model.train()  # training sees the configured passes only
    assert not model(src, tgt).second_pass.any()


def test_the_second_look_chosen_on_the_device_matches_the_host_choice():
    """A CUDA graph cannot branch on which pairs are due: every pair looks again and the choice is
    made on the device; the result is the host choice's."""
    src, tgt = turned_pairs()
    model = small_model(consistency_radius=1.0).eval()
    with torch.no_grad():
        below = float(model(src, tgt).consistency.sort().values[-2])
        model.config = replace(model.config, second_pass_below=below)
        results = []
        for every in (False, True):
            out = model(src, tgt)
            first = small_model(consistency_radius=1.0).eval()(src, tgt)
            model._second_looks(src, tgt, first, model.config.backend, False, None, every=every)
            results.append(first)
    host, device = results
    assert torch.equal(host.second_pass, device.second_pass) and host.second_pass.any()
    assert torch.equal(out.second_pass, host.second_pass)
    for name in ("rotation", "translation", "consistency", "rcp"):
        torch.testing.assert_close(getattr(device, name), getattr(host, name), rtol=1e-4, atol=1e-5)


def _looked_twice(model, src, tgt, start):
    """A plain model's estimate of each pair from src turned by ``start`` (3, 3), and of a pass from
    that estimate, whichever agrees more with its RCPs: (rotation, translation, consistency) of src,
    as the search takes each start (radius 1)."""
    from vrnet_ext.geometry.transforms import compose, move

    first = model(move(src, start.expand(len(src), 3, 3), torch.zeros(len(src), 3)), tgt)
    R1 = first.rotation @ start
    again = model(move(src, R1, first.translation), tgt)
    R2, t2 = compose(again.rotation, again.translation, R1, first.translation)
    consistency2 = ((move(src, R2, t2) - again.rcp).norm(dim=-1) < 1.0).float().mean(dim=-1)
    better = consistency2 > first.consistency
    return (torch.where(better[:, None, None], R2, R1), torch.where(better[:, None], t2, first.translation),
            torch.maximum(consistency2, first.consistency))


def _nearest_median(src, tgt, rotation, translation):
    """Brute force in float64: the median distance from R src + t to the nearest target point."""
    moved = src.double() @ rotation.double().mT + translation.double()[:, None]
    return torch.cdist(moved, tgt.double()).min(dim=-1).values.median(dim=-1).values


@pytest.mark.parametrize("centre", [(0.0, 0.0, 0.0), (22.5, 22.5, 22.5)])
def test_the_rotation_search_keeps_the_start_that_brings_each_doubtful_pair_closest(centre):
    from vrnet_ext.geometry.transforms import search_starts

    src, tgt = turned_pairs()
    starts = torch.as_tensor(np.concatenate([np.eye(3)[None], search_starts(centre)]), dtype=src.dtype)
    plain = small_model(consistency_radius=1.0).eval()
    with torch.no_grad():
        first = plain(src, tgt)
        runs = [_looked_twice(plain, src, tgt, g) for g in starts[1:]]
    distance = torch.stack([_nearest_median(src, tgt, run[0], run[1]) for run in runs], dim=1)  # (B, S)
    best = distance.argmin(dim=1)
    below = float(first.consistency.sort().values[-2])  # every pair but the most consistent one searches
    searched = first.consistency < below
    turned = searched & (distance.min(dim=1).values < _nearest_median(src, tgt, first.rotation, first.translation))
    assert turned.any(), "some searched pair must take a start (a kept row: the second-pass tests)"
    found_R = torch.stack([runs[int(b)][0][i] for i, b in enumerate(best)])
    found_t = torch.stack([runs[int(b)][1][i] for i, b in enumerate(best)])
    model = small_model(consistency_radius=1.0, rotation_search_below=below, rotation_search_centre=centre).eval()
    with torch.no_grad():
        out = model(src, tgt)
    pick = turned[:, None, None]
    torch.testing.assert_close(out.rotation, torch.where(pick, found_R, first.rotation), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.translation, torch.where(pick[:, 0], found_t, first.translation),
                               rtol=1e-4, atol=1e-5)
    expected_start = torch.where(pick, starts[1 + best], torch.eye(3).expand(len(src), 3, 3))
    assert torch.equal(out.start_rotation, expected_start)
    assert torch.linalg.det(out.rotation.double()).sub(1).abs().max() < 1e-5  # still rotations
    with torch.no_grad():  # each pair alone gets what it gets in the batch
        alone = [model(src[i:i + 1], tgt[i:i + 1]) for i in range(len(src))]
    torch.testing.assert_close(torch.cat([a.rotation for a in alone]), out.rotation, rtol=1e-4, atol=1e-5)
    model.train()  # training sees the configured passes only
    assert torch.equal(model(src, tgt).start_rotation, torch.eye(3).expand(len(src), 3, 3))


def test_the_search_polish_compares_every_start_after_its_icp():
    from vrnet_ext.geometry.alignment import robust_icp
    from vrnet_ext.geometry.transforms import search_starts

    src, tgt = turned_pairs(B=4, N=80)
    steps = 6
    starts = torch.as_tensor(search_starts((0.0, 0.0, 0.0)), dtype=src.dtype)
    plain = small_model(consistency_radius=1.0).eval()

    def polished(R, t):  # the polish as a reference: ICP from (R, t), kept where nearer (float64 brute force)
        R2, t2 = robust_icp(src, tgt, R, t, steps, backend="torch")
        nearer = _nearest_median(src, tgt, R2, t2) < _nearest_median(src, tgt, R, t)
        return torch.where(nearer[:, None, None], R2, R), torch.where(nearer[:, None], t2, t), nearer

    with torch.no_grad():
        first = plain(src, tgt)
        own = polished(first.rotation, first.translation)
        runs = [polished(*_looked_twice(plain, src, tgt, g)[:2]) for g in starts]
    distance = torch.stack([_nearest_median(src, tgt, run[0], run[1]) for run in runs], dim=1)  # (B, S)
    best = distance.argmin(dim=1)
    turned = distance.min(dim=1).values < _nearest_median(src, tgt, own[0], own[1])
    model = small_model(consistency_radius=1.0, rotation_search_below=1.0, rotation_search_polish=steps).eval()
    with torch.no_grad():
        out = model(src, tgt)
    found_R = torch.stack([runs[int(b)][0][i] for i, b in enumerate(best)])
    pick = turned[:, None, None]
    torch.testing.assert_close(out.rotation, torch.where(pick, found_R, own[0]), rtol=1e-3, atol=1e-3)
    assert torch.equal(out.start_rotation, torch.where(pick, starts[best], torch.eye(3).expand(len(src), 3, 3)))
    expected_polished = torch.where(turned, torch.stack([runs[int(b)][2][i] for i, b in enumerate(best)]), own[2])
    assert torch.equal(out.polished, expected_polished) and out.polished.any()
    searched_only = small_model(consistency_radius=1.0, rotation_search_below=1.0).eval()
    with torch.no_grad():  # the polished candidates bring the source at least as near as the unpolished ones
        unpolished = searched_only(src, tgt)
    assert (_nearest_median(src, tgt, out.rotation, out.translation)
            <= _nearest_median(src, tgt, unpolished.rotation, unpolished.translation) + 1e-6).all()


@pytest.mark.parametrize("slides, icp, share", [(1, "robust", None), (3, "trimmed", 1.0)])
def test_the_icp_search_replaces_a_searched_pair_where_it_brings_the_source_nearer(monkeypatch, slides, icp, share):
    """After the search and the polish, the searched pairs (all but the two most consistent) get
    multistart_icp's estimate (with the config's slides and ICP) where it is clearly nearer
    (ICP_SEARCH_NEARER; ``share`` replaces it where not None), marked icp_search; the pair not searched
    and the training forward never."""
    from vrnet_ext.geometry.alignment import multistart_icp
    from vrnet_ext.geometry.transforms import spread_rotations
    from vrnet_ext.model import vrnet as vrnet_module
    if share is not None:
        monkeypatch.setattr(vrnet_module, "ICP_SEARCH_NEARER", share)
    ICP_SEARCH_NEARER = vrnet_module.ICP_SEARCH_NEARER

    src, tgt = turned_pairs(B=4, N=64)
    plain = small_model(consistency_radius=1.0).eval()
    with torch.no_grad():
        below = float(plain(src, tgt).consistency.sort().values[-2])
    options = dict(consistency_radius=1.0, rotation_search_below=below, polish_iterations=2)
    searched_only = small_model(**options).eval()
    model = small_model(**options, rotation_search_icp_starts=48, rotation_search_icp_slides=slides,
                        rotation_search_icp=icp).eval()
    with torch.no_grad():
        before = searched_only(src, tgt)
        out = model(src, tgt)
        R, t, distance = multistart_icp(src, tgt, torch.as_tensor(spread_rotations(48)), slide_count=slides, icp=icp)
        searched = plain(src, tgt).consistency < below
    so_far = _nearest_median(src, tgt, before.rotation, before.translation)
    nearer = searched & (distance.double() < ICP_SEARCH_NEARER * so_far)
    assert nearer.any() and searched.sum() == 2
    assert torch.equal(out.searched, searched) and torch.equal(before.searched, searched)
    assert torch.equal(out.icp_search, nearer) and not before.icp_search.any()
    torch.testing.assert_close(out.rotation, torch.where(nearer[:, None, None], R, before.rotation), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.translation, torch.where(nearer[:, None], t, before.translation), rtol=1e-4, atol=1e-5)
    assert not out.polished[nearer].any()
    model.train()
    assert not model(src, tgt).icp_search.any()
    model.eval()  # a share below every searched pair's: none is clearly nearer
    monkeypatch.setattr(vrnet_module, "ICP_SEARCH_NEARER", 0.99 * float((distance.double() / so_far)[searched].min()))
    with torch.no_grad():
        assert not model(src, tgt).icp_search.any()


def _from_every_start(B=8):
    """B turned pairs, a plain model's output for them and its estimate from each start of the
    search about the identity (:func:`_looked_twice`): what the search's choices are checked against."""
    from vrnet_ext.geometry.transforms import search_starts

    src, tgt = turned_pairs(B=B)
    starts = torch.as_tensor(search_starts((0.0, 0.0, 0.0)), dtype=src.dtype)
    plain = small_model(consistency_radius=1.0).eval()
    with torch.no_grad():
        return src, tgt, plain(src, tgt), [_looked_twice(plain, src, tgt, g) for g in starts]


def test_a_bound_on_the_motion_keeps_the_search_and_its_icp_within_it():
    """With max_rotation, a pair whose estimate turns further is searched whatever its consistency,
    and the search keeps the nearest of the estimates within the bound (the pair's own among them,
    where it is); a pair with none within keeps its own; the others are left as they are. The ICP
    search that follows replaces an estimate only with one within the bound."""
    from vrnet_ext.geometry.metrics import turn_deg

    src, tgt, first, runs = _from_every_start()
    first_turn = turn_deg(first.rotation)
    bound = float(first_turn.median())
    below = 0.5 * float(first.consistency.min())  # no pair is doubtful by its consistency
    assert below > 0
    searched = first_turn > bound
    assert searched.any() and (~searched).any()
    distance = torch.stack([_nearest_median(src, tgt, R, t).masked_fill(turn_deg(R) > bound, float("inf"))
                            for R, t, _ in runs], dim=1)  # (B, S)
    best = distance.argmin(dim=1)
    taken = searched & torch.isfinite(distance.min(dim=1).values)  # the pair's own is beyond the bound
    found_R = torch.stack([runs[int(b)][0][i] for i, b in enumerate(best)])
    model = small_model(consistency_radius=1.0, rotation_search_below=below, max_rotation=bound).eval()
    with torch.no_grad():
        out = model(src, tgt)
    assert torch.equal(out.searched, searched)
    torch.testing.assert_close(out.rotation, torch.where(taken[:, None, None], found_R, first.rotation),
                               rtol=1e-4, atol=1e-5)
    assert (turn_deg(out.rotation)[taken] <= bound + 1e-6).all()
    unbounded = small_model(consistency_radius=1.0, rotation_search_below=below).eval()
    with torch.no_grad():
        assert not unbounded(src, tgt).searched.any()
    with_icp = small_model(consistency_radius=1.0, rotation_search_below=below, max_rotation=bound,
                           rotation_search_icp_starts=48).eval()
    with torch.no_grad():
        icp_out = with_icp(src, tgt)
    assert (turn_deg(icp_out.rotation)[icp_out.icp_search] <= bound + 1e-6).all()
    assert (turn_deg(icp_out.rotation)[taken] <= bound + 1e-6).all()


@pytest.mark.parametrize("penalty", [0.5, 10.0])
def test_a_turn_penalty_weighs_the_search_s_distances_by_the_turn(monkeypatch, penalty):
    """With rotation_search_turn_penalty p, the search compares (1 + p x turn / 180) x each estimate's
    nearest-point median (the pair's own among them): a brute-force reference of its choice, which
    differs from the choice without the penalty for some pair; the ICP search weighs its results
    and the estimate it would replace the same way."""
    from vrnet_ext.geometry.alignment import TurnPrior, multistart_icp
    from vrnet_ext.geometry.metrics import turn_deg
    from vrnet_ext.geometry.transforms import spread_rotations
    from vrnet_ext.model import vrnet as vrnet_module

    src, tgt, first, runs = _from_every_start()
    candidates = [(first.rotation, first.translation)] + [(R, t) for R, t, _ in runs]  # the pair's own first
    distance = torch.stack([_nearest_median(src, tgt, R, t) for R, t in candidates], dim=1)  # (B, 1 + S)
    turn = torch.stack([turn_deg(R) for R, _ in candidates], dim=1)
    weighed = distance * (1 + penalty * turn / 180)
    below = 1.1 * float(first.consistency.max())  # every pair is searched
    choice, plain_choice = weighed.argmin(dim=1), distance.argmin(dim=1)
    assert (choice != plain_choice).any(), "the penalty must change some pair's choice"
    model = small_model(consistency_radius=1.0, rotation_search_below=min(below, 1.0),
                        rotation_search_turn_penalty=penalty).eval()
    with torch.no_grad():
        out = model(src, tgt)
    assert out.searched.all()
    want = torch.stack([candidates[int(c)][0][i] for i, c in enumerate(choice)])
    torch.testing.assert_close(out.rotation, want, rtol=1e-4, atol=1e-5)
    with torch.no_grad():
        R, t, icp_weighed = multistart_icp(src, tgt, torch.as_tensor(spread_rotations(48)),
                                           prior=TurnPrior(penalty=penalty))
    share_weighed = icp_weighed.double() / weighed.min(dim=1).values  # what the ICP search compares ...
    share_plain = _nearest_median(src, tgt, R, t) / distance.gather(1, choice[:, None])[:, 0]  # ... not this
    apart = (share_weighed - share_plain).abs().argmax()
    assert (share_weighed - share_plain).abs().max() > 1e-3
    monkeypatch.setattr(vrnet_module, "ICP_SEARCH_NEARER", float(share_weighed[apart] + share_plain[apart]) / 2)
    nearer = share_weighed < vrnet_module.ICP_SEARCH_NEARER
    assert not torch.equal(nearer, share_plain < vrnet_module.ICP_SEARCH_NEARER)
    with_icp = small_model(consistency_radius=1.0, rotation_search_below=min(below, 1.0),
                           rotation_search_icp_starts=48, rotation_search_turn_penalty=penalty).eval()
    with torch.no_grad():
        icp_out = with_icp(src, tgt)
    assert torch.equal(icp_out.icp_search, nearer)
    torch.testing.assert_close(icp_out.rotation, torch.where(nearer[:, None, None], R, out.rotation),
                               rtol=1e-4, atol=1e-5)


def test_the_rotation_search_takes_only_the_pairs_the_second_pass_left_doubtful():
    src, tgt = turned_pairs()
    looked = small_model(consistency_radius=1.0, second_pass_below=1.0).eval()
    with torch.no_grad():
        after_second = looked(src, tgt)
    below = float(after_second.consistency.sort().values[-2])
    both = small_model(consistency_radius=1.0, second_pass_below=1.0, rotation_search_below=below).eval()
    with torch.no_grad():
        out = both(src, tgt)
    left = after_second.consistency >= below  # not searched: exactly the second pass's rows
    torch.testing.assert_close(out.rotation[left], after_second.rotation[left])
    closer = _nearest_median(src, tgt, out.rotation, out.translation)  # a search only ever keeps a closer row
    assert (closer <= _nearest_median(src, tgt, after_second.rotation, after_second.translation) + 1e-6).all()
    assert torch.equal(out.start_rotation[left], torch.eye(3).expand(int(left.sum()), 3, 3))


def test_the_shipped_model_registers_any_rotation_with_the_search():
    import numpy as np
    from scipy.spatial.transform import Rotation

    from vrnet_ext.data.procedural import chair
    from vrnet_ext.geometry.transforms import move
    from vrnet_ext import load_pretrained

    rng = np.random.default_rng(11)
    base = chair(rng)[:768].astype(np.float32)
    rotations = torch.as_tensor(Rotation.random(6, random_state=5).as_matrix(), dtype=torch.float32)
    src = torch.from_numpy(base).expand(6, -1, -1).contiguous()
    tgt = move(src, rotations, torch.zeros(6, 3))
    tgt = tgt[:, torch.from_numpy(rng.permutation(768))]
    model = load_pretrained()
    with torch.no_grad():
        model.config.rotation_search_below = 0.0
        plain = rotation_error_deg(model(src, tgt).rotation, rotations)
        model.config.rotation_search_below = 0.5
        searched = rotation_error_deg(model(src, tgt).rotation, rotations)
    assert (plain > 5).any(), plain  # rotations the model alone does not register ...
    assert (searched < 1).all(), searched  # ... all registered with the search


def test_the_polish_keeps_its_icp_estimate_where_it_brings_the_source_nearer():
    from vrnet_ext.geometry.alignment import robust_icp

    src, tgt = turned_pairs()
    plain = small_model(consistency_radius=0.3).eval()
    with torch.no_grad():
        first = plain(src, tgt)
        R, t = robust_icp(src, tgt, first.rotation, first.translation, 4)
    nearer = _nearest_median(src, tgt, R, t) < _nearest_median(src, tgt, first.rotation, first.translation)
    assert nearer.any()
    model = small_model(consistency_radius=0.3, polish_iterations=4).eval()
    with torch.no_grad():
        out = model(src, tgt)
    assert torch.equal(out.polished, nearer) and not first.polished.any()
    torch.testing.assert_close(out.rotation, torch.where(nearer[:, None, None], R, first.rotation))
    torch.testing.assert_close(out.translation, torch.where(nearer[:, None], t, first.translation))
    torch.testing.assert_close(out.rcp, first.rcp)  # the network's points stay; the consistency follows the estimate
    moved = src.double() @ out.rotation.double().mT + out.translation.double()[:, None]
    expected = ((moved - out.rcp.double()).norm(dim=-1) < 0.3).double().mean(dim=-1)
    torch.testing.assert_close(out.consistency.double(), expected)
    with torch.no_grad():  # the forward's last step, on an output at hand: a new output, the given one untouched
        again = plain.eval().polished(src, tgt, first, 4)
    torch.testing.assert_close(again.rotation, out.rotation, rtol=0, atol=0)
    assert torch.equal(again.polished, nearer) and not first.polished.any()
    with pytest.raises(ValueError, match="not the clouds of out"):
        plain.polished(src[:2], tgt[:2], first, 4)
    with pytest.raises(ValueError, match="steps"):
        plain.polished(src, tgt, first, -1)
    model.train()  # training sees the passes only
    trained = model(src, tgt)
    assert not trained.polished.any()
    torch.testing.assert_close(trained.rotation, plain.train()(src, tgt).rotation)


def test_the_polish_sharpens_the_shipped_model_on_noisy_pairs():
    from scipy.spatial.transform import Rotation

    from vrnet_ext.data.procedural import chair
    from vrnet_ext.geometry.transforms import move
    from vrnet_ext import load_pretrained

    rng = np.random.default_rng(3)
    src = torch.from_numpy(chair(rng)[:768].astype(np.float32)).expand(6, -1, -1).contiguous()
    rotations = torch.as_tensor(Rotation.from_euler("zyx", rng.uniform(0, 45, (6, 3)), degrees=True).as_matrix(),
                                dtype=torch.float32)
    noise = torch.from_numpy(rng.normal(scale=0.01, size=(6, 768, 3)).astype(np.float32))
    tgt = move(src, rotations, torch.zeros(6, 3)) + noise
    model = load_pretrained()
    with torch.no_grad():
        plain = rotation_error_deg(model(src, tgt).rotation, rotations)
        model.config.polish_iterations = 10
        polished = rotation_error_deg(model(src, tgt).rotation, rotations)
    assert plain.median() > 0.2 and polished.median() < 0.5 * plain.median(), (plain, polished)


@pytest.mark.parametrize("field, value", [("second_pass_below", 1.5), ("second_pass_below", -0.1),
                                          ("second_pass_below", float("nan")), ("consistency_radius", 0.0),
                                          ("rotation_search_below", 2.0), ("rotation_search_below", float("nan")),
                                          ("rotation_search_centre", (0.0, 0.0)), ("rotation_search_centre", (0, 0, 200)),
                                          ("consistency_radius", float("inf")), ("polish_iterations", -1),
                                          ("polish_iterations", 1001), ("polish_iterations", 2.5),
                                          ("polish_iterations", True), ("rotation_search_polish", -2),
                                          ("rotation_search_polish", 1001), ("rotation_search_polish", False),
                                          ("rotation_search_icp_starts", -1), ("rotation_search_icp_starts", 4097),
                                          ("rotation_search_icp_starts", 8.0), ("rotation_search_icp_starts", True),
                                          ("rotation_search_icp_slides", 0), ("rotation_search_icp_slides", 65),
                                          ("rotation_search_icp_slides", 2.0), ("rotation_search_icp", "gicp")])
def test_second_pass_options_are_checked(field, value):
    with pytest.raises(ValueError, match=field):
        VRNetConfig(**{field: value})


@pytest.mark.parametrize("tensor_cores", [True, False])
def test_feature_graphs_on_a_gpu(monkeypatch, tensor_cores):
    """On a GPU, graphs of learned features take the compiled kNN where it runs on the tensor cores, else
    the reference; graphs of the points, and every graph off the GPU, the backend asked for."""
    from vrnet_ext.model.dgcnn import graph_backend

    knn_module = importlib.import_module("vrnet_ext.ops.knn")  # the module (vrnet_ext.ops.knn is the op)
    monkeypatch.setattr(knn_module, "cuda_has_tensor_cores", lambda device: tensor_cores)
    gpu, cpu, f32 = torch.device("cuda", 0), torch.device("cpu"), torch.float32
    on_gpu = "ext" if tensor_cores else "torch"
    assert graph_backend(gpu, f32, 64, 20, "ext") == on_gpu
    assert graph_backend(gpu, torch.bfloat16, 128, 20, "ext") == on_gpu
    assert graph_backend(gpu, f32, 256, 20, "ext") == "torch" and graph_backend(gpu, f32, 64, 33, "ext") == "torch"
    assert graph_backend(gpu, torch.float64, 64, 20, "ext") == "torch"
    assert graph_backend(gpu, f32, 3, 20, "ext") == "ext"  # the points: the compiled kNN is 6x ahead there
    assert graph_backend(cpu, f32, 64, 20, "ext") == "ext" and graph_backend(cpu, f32, 64, 20, "torch") == "torch"
    assert graph_backend(gpu, f32, 64, 20, "torch") == "torch"


