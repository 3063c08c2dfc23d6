import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext import metrics


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
