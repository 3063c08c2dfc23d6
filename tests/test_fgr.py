import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext.data.procedural import room_scan
from vrnet_ext.registration import Fgr, IcpSettings, PointCounts, ScanPair, register, transform_errors
from vrnet_ext.registration.fgr import fast_global_registration, feature_correspondences, tuple_test


def motion(angle_deg: float, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [angle_deg, 10.0, -5.0], degrees=True).as_matrix()
    T[:3, 3] = translation
    return T


def test_exact_correspondences_with_half_outliers_give_the_motion():
    g = torch.Generator().manual_seed(0)
    src = torch.rand(400, 3, generator=g, dtype=torch.float64) * 3
    truth = torch.as_tensor(motion(70.0, [1.0, -0.5, 2.0]))
    tgt = src @ truth[:3, :3].T + truth[:3, 3]
    features = torch.eye(400, dtype=torch.float64)[:, :64] + torch.rand(400, 64, generator=g, dtype=torch.float64)
    wrong = torch.randperm(400, generator=g)[:200]
    tgt_features = features.clone()
    tgt_features[wrong] = torch.rand(200, 64, generator=g, dtype=torch.float64) * 3
    estimate = fast_global_registration(src, tgt, features, tgt_features)
    errors = transform_errors(estimate.numpy(), truth.numpy())
    # the Geman-McClure penalty stops at mu = 0.025 of the scale: far outliers keep a small weight,
    # so FGR lands close to, not exactly on, the motion (ICP finishes the job)
    assert errors["rotation_error_deg"] < 0.05 and errors["translation_error"] < 5e-3, errors


def test_tuple_test_keeps_consistent_triples():
    g = torch.Generator().manual_seed(1)
    src = torch.rand(100, 3, generator=g, dtype=torch.float64)
    tgt = src.clone()
    pairs = torch.stack([torch.arange(100), torch.arange(100)], 1)
    pairs[50:, 1] = torch.randint(0, 100, (50,), generator=g)  # half wrong
    kept = tuple_test(src, tgt, pairs, max_tuples=200, generator=g)
    right = (kept[:, 0] == kept[:, 1]).float().mean()
    assert len(kept) == 600 and right > 0.9, right
    assert feature_correspondences(src, src).tolist() == torch.stack([torch.arange(100)] * 2, 1).tolist()


def test_fgr_registers_a_room_turned_by_60_degrees():
    truth = motion(60.0, [0.4, -0.3, 0.1])
    src, tgt = room_scan(60_000, 1), room_scan(60_000, 2) @ truth[:3, :3].T + truth[:3, 3]
    estimate = Fgr().estimate_pair(ScanPair.of(src, tgt, PointCounts(global_points=3000)), seed=0)
    errors = transform_errors(estimate.T_target_source, truth)
    assert errors["rotation_error_deg"] < 3.0 and errors["translation_error"] < 0.15, errors
    refined = register(src, tgt, method="fgr", global_points=3000, icp_settings=IcpSettings(points=20_000))
    errors = transform_errors(refined.T_target_source, truth)
    assert errors["rotation_error_deg"] < 0.05 and errors["translation_error"] < 0.005, errors


def test_too_few_points():
    with pytest.raises(ValueError, match="at least 3 points"):
        fast_global_registration(torch.rand(2, 3), torch.rand(5, 3), torch.rand(2, 4), torch.rand(5, 4))
