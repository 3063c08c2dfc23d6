import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext.geometry import metrics


def test_euler_and_isotropic_errors_on_known_transforms():
    R = torch.tensor(Rotation.from_euler("zyx", [10, 20, 30], degrees=True).as_matrix())[None]
    np.testing.assert_allclose(metrics.euler_zyx_deg(R), [[10, 20, 30]], atol=1e-9)
    Rz = torch.tensor(Rotation.from_euler("z", 7, degrees=True).as_matrix())[None]
    assert metrics.rotation_error_deg(Rz, torch.eye(3, dtype=torch.float64)[None]).item() == pytest.approx(7.0)
    assert metrics.rotation_error_deg(Rz, Rz).item() == pytest.approx(0.0, abs=1e-12)
    tiny = torch.tensor(Rotation.from_euler("x", 1e-4, degrees=True).as_matrix(), dtype=torch.float32)[None]
    assert metrics.rotation_error_deg(tiny, torch.eye(3)[None]).item() == pytest.approx(1e-4, rel=1e-2)
    t = torch.tensor([[3.0, 4.0, 0.0]])
    assert metrics.translation_error(t, torch.zeros(1, 3)).item() == pytest.approx(5.0)


def test_summarize_perfect_and_offset_predictions():
    R = Rotation.from_euler("zyx", np.random.default_rng(0).uniform(0, 45, (20, 3)), degrees=True).as_matrix()
    t = np.random.default_rng(1).uniform(-0.5, 0.5, (20, 3))
    perfect = metrics.summarize(R, R, t, t)
    assert perfect["RMSE(R)"] < 1e-9 and perfect["RMSE(t)"] == 0 and perfect["recall(RE<1,TE<0.01)"] == 1.0
    off = metrics.summarize(R, R, t + np.array([0.1, 0, 0]), t)
    assert off["MAE(t)"] == pytest.approx(0.1 / 3) and off["RMSE(t)"] == pytest.approx((0.01 / 3) ** 0.5)
    assert off["TE mean"] == pytest.approx(0.1)


def test_chamfer_and_match_ratio():
    a = torch.randn(2, 50, 3)
    assert metrics.chamfer_distance(a, a).abs().max() < 1e-6
    b = torch.randn(2, 70, 3) + 0.5
    d2 = torch.cdist(a, b).square()
    oracle = d2.min(dim=2).values.mean(dim=1) + d2.min(dim=1).values.mean(dim=1)
    torch.testing.assert_close(metrics.chamfer_distance(a, b), oracle, rtol=1e-4, atol=1e-5)
    eye, zero = torch.eye(3).expand(2, 3, 3), torch.zeros(2, 3)
    moved = a.clone()
    moved[:, :10] += 1.0
    torch.testing.assert_close(metrics.correct_match_ratio(moved, a, eye, zero), torch.full((2,), 0.8, dtype=torch.float64))


def test_correspondence_error_is_the_distance_from_the_true_position():
    src = torch.randn(2, 6, 3, dtype=torch.float64)
    R = torch.tensor(Rotation.random(2, random_state=0).as_matrix())
    t = torch.randn(2, 3, dtype=torch.float64)
    truth = src @ R.mT + t.unsqueeze(1)
    shift = torch.zeros_like(truth)
    shift[0, 2] = torch.tensor([0.0, 0.3, 0.4])
    expected = torch.zeros(2, 6, dtype=torch.float64)
    expected[0, 2] = 0.5
    torch.testing.assert_close(metrics.correspondence_error(truth + shift, src, R, t), expected)


class _PerfectWalk(torch.nn.Module):
    """Stands in for VRNet: exact matches for inliers, random soft rows for outliers, RCPs = truth."""

    config = type("Config", (), {"backend": "torch", "irls_min_scale": 1e-3, "irls_iterations": 0,
                                 "irls_kernel": "cauchy", "irls_scale": 3.0})()

    def forward(self, src, tgt, backend=None, return_matching=False):
        from vrnet_ext.ops import kabsch
        gt_idx = self.gt_idx.expand(src.shape[0], -1)
        scores = torch.randn(src.shape[0], src.shape[1], tgt.shape[1], generator=torch.Generator().manual_seed(1))
        matching = torch.softmax(4 * scores.to(src.dtype), dim=-1)
        inl = gt_idx >= 0
        matching[inl] = torch.nn.functional.one_hot(gt_idx[inl], tgt.shape[1]).to(src.dtype)
        vcp = matching @ tgt
        rcp = src @ self.R.T + self.t
        R, t = kabsch(src, rcp, backend="torch")
        self.last = type("Out", (), dict(rotation=R, translation=t, matching=matching, vcp=vcp, rcp=rcp,
                                         offset=rcp - vcp, consistency=torch.ones(src.shape[0]),
                                         second_pass=torch.zeros(src.shape[0], dtype=torch.bool)))()
        return self.last


def test_evaluate_reports_vcp_and_rcp_errors_on_inliers_and_outliers():
    from vrnet_ext.learning.evaluate import evaluate
    from vrnet_ext.ops import kabsch
    g = torch.Generator().manual_seed(0)
    src = torch.randn(20, 3, generator=g, dtype=torch.float64)
    R = torch.tensor(Rotation.from_euler("zyx", [20, 10, 5], degrees=True).as_matrix())
    t = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    tgt = src[:15] @ R.T + t
    gt_idx = torch.cat([torch.arange(15), torch.full((5,), -1)])
    item = dict(src=src, tgt=tgt, rotation=R, translation=t, gt_idx=gt_idx)
    model = _PerfectWalk()
    model.gt_idx, model.R, model.t = gt_idx, R, t
    result = evaluate(model, [item, item], batch_size=2, progress=False)
    assert result["RCP error (inliers)"] < 1e-12 and result["RCP error (outliers)"] < 1e-12
    assert result["VCP error (inliers)"] < 1e-12
    truth = src @ R.T + t
    vcp = model.last.vcp  # (2, 20, 3): one batch of the pair twice, with different outlier rows
    expected_outlier_error = (vcp[:, 15:] - truth[15:]).norm(dim=-1).mean().item()
    assert result["VCP error (outliers)"] == pytest.approx(expected_outlier_error)
    R_vcp, _ = kabsch(src.expand(2, 20, 3), vcp, backend="torch")
    expected_re = metrics.rotation_error_deg(R_vcp, R.expand(2, 3, 3)).mean().item()
    assert result["RE mean [VCP]"] == pytest.approx(expected_re)
    assert result["RE mean [VCP]"] > 0.1 and result["RE mean (deg)"] < 1e-6 and result["RE mean [RCP]"] < 1e-6
    assert result["consistency"] == 1.0 and result["second pass"] == 0.0
    assert result["RMSE(R) [RCP]"] < 1e-6 < result["RMSE(R) [VCP]"]
