import pytest
import torch

import vrnet_ext.learning.losses as losses
from vrnet_ext.geometry.transforms import move
from vrnet_ext.model.vrnet import VRNetOutput


def rigid(B=2, N=40, dtype=torch.float64):
    q = torch.linalg.qr(torch.randn(B, 3, 3, dtype=dtype)).Q
    R = q * torch.sign(torch.linalg.det(q)).view(-1, 1, 1)
    t = torch.randn(B, 3, dtype=dtype)
    src = torch.randn(B, N, 3, dtype=dtype)
    return src, R, t, move(src, R, t)


def make_output(src, R, t, vcp, offset):
    B, N, _ = src.shape
    return VRNetOutput(R, t, torch.full((B, N, N), 1.0 / N, dtype=src.dtype), vcp, vcp + offset, offset,
                       torch.zeros(B, 4, N), torch.zeros(B, 4, N))


def test_correspondence_loss_hand_cases():
    gt_idx = torch.tensor([[2, 0, -1, 1]])
    perfect = torch.zeros(1, 4, 3)
    perfect[0, torch.tensor([0, 1, 3]), gt_idx[0, torch.tensor([0, 1, 3])]] = 1.0
    perfect[0, 2, 0] = 1.0  # the outlier's row is ignored
    assert losses.correspondence_loss(perfect, gt_idx).item() == pytest.approx(-1.0)
    uniform = torch.full((1, 4, 3), 1 / 3)
    assert losses.correspondence_loss(uniform, gt_idx).item() == pytest.approx(-1 / 3)
    assert losses.correspondence_loss(uniform, torch.full((1, 4), -1)).item() == 0.0


def test_local_motion_consensus_zero_on_rigid_rcp_and_one_batched_kabsch(monkeypatch):
    src, R, t, rcp = rigid()
    calls = []
    real = losses.kabsch

    def counting(*args, **kwargs):
        calls.append(args[0].shape)
        return real(*args, **kwargs)

    monkeypatch.setattr(losses, "kabsch", counting)
    value = losses.local_motion_consensus_loss(src, rcp, R, t, groups=10, subset_size=5,
                                               generator=torch.Generator().manual_seed(0))
    assert value.item() < 1e-6
    assert calls == [torch.Size([2 * 10, 5, 3])], "all B*G subsets in one batched kabsch call"
    noisy = rcp + 0.1 * torch.randn_like(rcp)
    assert losses.local_motion_consensus_loss(src, noisy, R, t, subset_size=5).item() > 1e-3


def test_node_and_offset_losses_with_known_offsets():
    src, R, t, truth = rigid()
    shift = torch.tensor([0.3, -0.4, 1.2], dtype=src.dtype)
    # L3 = rmse(R X + t, Y''): a constant shift d gives sqrt(|d|^2 / 3)
    value = losses.rmse(move(src, R, t), truth + shift).mean()
    assert value.item() == pytest.approx((shift.square().sum() / 3).sqrt().item())
    out = make_output(src, R, t, vcp=truth - shift, offset=torch.zeros_like(truth))
    total, parts = losses.hybrid_loss(out, src, R, t, losses.HybridLossWeights(l1=0, l2=0, l3=0, l4=1))
    assert parts["L4"] == pytest.approx((shift.square().sum() / 3).sqrt().item())
    assert total.item() == pytest.approx(parts["L4"])


def test_identity_transform_gives_zero_hybrid_loss_and_finite_gradients(device):
    src, R, t, truth = rigid()
    vcp = truth - 0.2
    offset = torch.full_like(truth, 0.2).requires_grad_()
    out = make_output(src, R, t, vcp, offset)
    out.rcp = vcp + offset
    total, parts = losses.hybrid_loss(out, src, R, t, generator=torch.Generator().manual_seed(1))
    for name, value in parts.items():
        assert value < 1e-6, name
    total.backward()
    assert bool(torch.isfinite(offset.grad).all())


def test_geometry_loss_matches_weighting(device):
    src, R, t, truth = rigid()
    scaled = truth * 1.5
    out = make_output(src, R, t, scaled, torch.zeros_like(scaled))
    _, parts = losses.hybrid_loss(out, src, R, t)
    expected = torch.stack([((torch.cdist(s, s) * 0.5) ** 2).mean().sqrt() for s in src]).mean()
    assert parts["L2"] == pytest.approx(expected.item(), rel=1e-6)


def test_gate_and_confidence_terms_use_the_true_positions():
    src, R, t, truth = rigid(B=1, N=6)
    vcp = truth.clone()
    vcp[0, :2] += 0.5  # two VCPs need a correction
    offset = torch.zeros_like(vcp)
    offset[0, 0] = -0.5  # the walk fixes the first one only
    out = make_output(src, R, t, vcp, offset)
    out.gate_logits = torch.tensor([[3.0, -1.0, 0.0, 0.0, -2.0, 1.0]], dtype=src.dtype)
    out.confidence_logits = torch.tensor([[1.0, 2.0, -1.0, 0.5, 0.0, 0.0]], dtype=src.dtype)
    _, parts = losses.hybrid_loss(out, src, R, t, backend="torch")
    bce = torch.nn.functional.binary_cross_entropy_with_logits
    needs = torch.tensor([[1.0, 1, 0, 0, 0, 0]], dtype=src.dtype)
    correct = torch.tensor([[1.0, 0, 1, 1, 1, 1]], dtype=src.dtype)
    assert parts["LG"] == pytest.approx(bce(out.gate_logits, needs).item())
    assert parts["LC"] == pytest.approx(bce(out.confidence_logits, correct).item())
    assert "LG" not in losses.hybrid_loss(make_output(src, R, t, vcp, offset), src, R, t, backend="torch")[1]


def test_offset_log_loss_counts_small_errors_as_much_as_large_ones():
    truth = torch.zeros(1, 4, 3, dtype=torch.float64)
    rcp = truth.clone()
    rcp[0, :, 0] = torch.tensor([0.0, 0.01, 0.01, 1.0])
    value = losses.offset_log_loss(rcp, truth, 0.01)
    expected = (0 + 2 * torch.log1p(torch.tensor(1.0)) + torch.log1p(torch.tensor(100.0))) / 4
    torch.testing.assert_close(value, expected.double().view(1))
    rcp.requires_grad_()
    losses.offset_log_loss(rcp, truth, 0.01).sum().backward()
    # d/dd log(1 + d / s) = 1 / (s + d): a point 1 cm off pulls ~50x harder than one 1 m off
    assert rcp.grad[0, 1, 0] / rcp.grad[0, 3, 0] > 40 and torch.isfinite(rcp.grad).all()


def test_hybrid_loss_with_the_log_offset_form():
    src, R, t, truth = rigid()
    vcp = truth + 0.1
    out = make_output(src, R, t, vcp, torch.zeros_like(vcp))
    paper, parts = losses.hybrid_loss(out, src, R, t, losses.HybridLossWeights())
    log_form, log_parts = losses.hybrid_loss(out, src, R, t, losses.HybridLossWeights(l4=10.0, l4_form="log"))
    assert torch.isfinite(paper) and torch.isfinite(log_form)
    assert log_parts["L4"] == pytest.approx(float(torch.log1p(torch.tensor(0.1 * 3 ** 0.5 / 0.01))), rel=1e-6)


def test_the_motion_term_measures_the_estimate_against_the_truth():
    src, R, t, truth = rigid()
    out = make_output(src, R, t, truth, torch.zeros_like(truth))
    weights = losses.HybridLossWeights(motion=2.0)
    _, exact = losses.hybrid_loss(out, src, R, t, weights, backend="torch")
    assert exact["LM"] == pytest.approx(0.0, abs=1e-9)
    angle = torch.tensor(0.1, dtype=src.dtype)
    about_z = torch.tensor([[angle.cos(), -angle.sin(), 0], [angle.sin(), angle.cos(), 0], [0, 0, 1]], dtype=src.dtype)
    off = make_output(src, R @ about_z, t + 0.3, truth, torch.zeros_like(truth))
    without, parts_without = losses.hybrid_loss(off, src, R, t, losses.HybridLossWeights(), backend="torch")
    total, parts = losses.hybrid_loss(off, src, R, t, weights, backend="torch")
    # rmse(Rz - I): four entries off by (1 - cos, sin) of 9; rmse(t): 0.3 on every axis
    expected = float(((2 * (1 - angle.cos()) ** 2 + 2 * angle.sin() ** 2) / 9).sqrt()) + 0.3
    assert parts["LM"] == pytest.approx(expected, rel=1e-9) and "LM" not in parts_without
    assert float(total - without) == pytest.approx(2.0 * expected, rel=1e-9)
    _, heavier = losses.hybrid_loss(off, src, R, t, losses.HybridLossWeights(motion=2.0, motion_translation=4.0),
                                    backend="torch")
    assert heavier["LM"] == pytest.approx(expected + 3 * 0.3, rel=1e-9)  # only the translation term grows
    _, parts_l1 = losses.hybrid_loss(off, src, R, t, losses.HybridLossWeights(motion=2.0, motion_translation=4.0),
                                     generator=torch.Generator().manual_seed(0), backend="torch")
    _, parts_l1_dcp = losses.hybrid_loss(off, src, R, t, weights, generator=torch.Generator().manual_seed(0),
                                         backend="torch")
    assert parts_l1["L1"] == parts_l1_dcp["L1"]  # L1's motion consensus keeps its own balance
