"""ICP's refinement plug-ins on pairs with exact ground truth: one room, moved by a known motion and
sampled twice independently (no point is shared), 3 mm noise."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext.data.procedural import room_scan
from vrnet_ext.registration import icp, transform_errors
from vrnet_ext.registration.estimators import ESTIMATORS, make_estimator, se3_exp


@pytest.fixture(scope="module")
def room_pair():
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("zyx", [3.0, -2.0, 1.5], degrees=True).as_matrix()
    truth[:3, 3] = [0.05, -0.04, 0.02]
    return room_scan(30_000, 1), room_scan(30_000, 2) @ truth[:3, :3].T + truth[:3, 3], truth


@pytest.mark.parametrize("estimator", ["point_to_plane", "gicp"])
def test_plane_based_refinement_reaches_the_exact_motion(room_pair, estimator):
    src, tgt, truth = room_pair
    result = icp(src, tgt, np.eye(4), 0.3, 100, estimator=estimator)
    errors = transform_errors(result.T_target_source, truth)
    assert errors["rotation_error_deg"] <= 0.01 and errors["translation_error"] <= 0.0005, errors
    assert result.converged and result.fitness > 0.95 and result.estimator == estimator


def test_point_to_point_is_biased_by_the_sampling(room_pair):
    src, tgt, truth = room_pair
    result = icp(src, tgt, np.eye(4), 0.3, 100, estimator="point_to_point")
    errors = transform_errors(result.T_target_source, truth)
    assert errors["rotation_error_deg"] < 0.1 and errors["translation_error"] < 0.01, errors


def test_se3_exp_matches_rodrigues():
    xi = torch.tensor([0.3, -1.2, 0.5, 1.0, 2.0, -3.0], dtype=torch.float64)
    T = se3_exp(xi)
    np.testing.assert_allclose(T[:3, :3].numpy(), Rotation.from_rotvec(xi[:3].numpy()).as_matrix(), atol=1e-12)
    tiny = se3_exp(torch.tensor([0, 0, 0, 1.0, 2.0, 3.0], dtype=torch.float64))
    np.testing.assert_allclose(tiny[:3, 3].numpy(), [1.0, 2.0, 3.0])


def test_unknown_estimator_names_the_argument():
    with pytest.raises(ValueError, match="estimator must be one of"):
        make_estimator("plane_to_point")
    assert set(ESTIMATORS) == {"point_to_point", "point_to_plane", "gicp"}


def test_icp_settings_are_checked_when_made():
    from vrnet_ext.registration import IcpSettings, register

    for kwargs, match in [({"estimator": "plane"}, "estimator must be one of"), ({"points": 0}, "IcpSettings.points"),
                          ({"max_iterations": -1}, "IcpSettings.max_iterations"),
                          ({"max_distance": float("nan")}, "IcpSettings.max_distance"),
                          ({"voxel_size": 0.0}, "IcpSettings.voxel_size"), ({"settled": -1e-6}, "IcpSettings.settled")]:
        with pytest.raises(ValueError, match=match):
            IcpSettings(**kwargs)
    with pytest.raises(TypeError, match="icp_settings must be an IcpSettings"):
        register(np.zeros((5, 3)), np.zeros((5, 3)), icp_settings={"points": 10})
