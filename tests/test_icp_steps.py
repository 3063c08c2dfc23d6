"""ICP's refinement plug-ins on pairs with exact ground truth: one room, moved by a known motion and
sampled twice independently (no point is shared), 3 mm noise."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext.data.procedural import room_scan
from vrnet_ext.ops.normals import neighbourhood
from vrnet_ext.names import ICP_STEPS
from vrnet_ext.registration import IcpSettings, icp, transform_errors
from vrnet_ext.registration.icp_steps import (PLANE_FLATNESS, gauss_newton_step, make_icp_step,
                                               plane_covariances, se3_exp, symmetric_inverse)


@pytest.fixture(scope="module")
def room_pair():
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("zyx", [3.0, -2.0, 1.5], degrees=True).as_matrix()
    truth[:3, 3] = [0.05, -0.04, 0.02]
    return room_scan(30_000, 1), room_scan(30_000, 2) @ truth[:3, :3].T + truth[:3, 3], truth


@pytest.mark.parametrize("estimator", ["point_to_plane", "gicp"])
def test_plane_based_refinement_reaches_the_exact_motion(room_pair, estimator):
    src, tgt, truth = room_pair
    result = icp(src, tgt, np.eye(4), IcpSettings(step=estimator, max_distance=0.3, max_iterations=100,
                                                     transform_tolerance=1e-6))
    errors = transform_errors(result.T_target_source, truth)
    assert errors["rotation_error_deg"] <= 0.01 and errors["translation_error"] <= 0.0005, errors
    assert result.converged and result.fitness > 0.95 and result.icp_step == estimator


def test_point_to_point_is_biased_by_the_sampling(room_pair):
    src, tgt, truth = room_pair
    result = icp(src, tgt, np.eye(4), IcpSettings(step="point_to_point", max_distance=0.3, max_iterations=100,
                                                     transform_tolerance=1e-6))
    errors = transform_errors(result.T_target_source, truth)
    assert errors["rotation_error_deg"] < 0.1 and errors["translation_error"] < 0.01, errors


def test_se3_exp_matches_rodrigues():
    xi = torch.tensor([0.3, -1.2, 0.5, 1.0, 2.0, -3.0], dtype=torch.float64)
    T = se3_exp(xi)
    np.testing.assert_allclose(T[:3, :3].numpy(), Rotation.from_rotvec(xi[:3].numpy()).as_matrix(), atol=1e-12)
    tiny = se3_exp(torch.tensor([0, 0, 0, 1.0, 2.0, 3.0], dtype=torch.float64))
    np.testing.assert_allclose(tiny[:3, 3].numpy(), [1.0, 2.0, 3.0])


def test_symmetric_inverse_matches_lapack():
    A = torch.randn(500, 3, 3, dtype=torch.float64)
    M = A @ A.mT + 1e-3 * torch.eye(3, dtype=torch.float64)  # down to badly conditioned
    torch.testing.assert_close(symmetric_inverse(M), torch.linalg.inv(M), rtol=1e-8, atol=1e-8)


def test_plane_covariances_flatten_the_local_covariance():
    """Eigenvectors of each point's covariance (itself + neighbours), eigenvalues (eps, 1, 1)."""
    torch.manual_seed(0)
    points = torch.randn(300, 3, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.05], dtype=torch.float64)
    _, idx = neighbourhood(points, 10)
    around = torch.cat([points[:, None], points[idx]], dim=1)
    centred = around - around.mean(dim=1, keepdim=True)
    vectors = torch.linalg.eigh(centred.mT @ centred)[1]
    scale = torch.tensor([PLANE_FLATNESS, 1.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(plane_covariances(points, 10),
                               vectors @ torch.diag_embed(scale.expand(300, 3)) @ vectors.mT, rtol=1e-7, atol=1e-7)


def test_gauss_newton_with_information_equals_whitened_step():
    torch.manual_seed(1)
    J, residual, weights = torch.randn(50, 3, 6, dtype=torch.float64), torch.randn(50, 3, dtype=torch.float64), torch.rand(50, dtype=torch.float64)
    A = torch.randn(50, 3, 3, dtype=torch.float64)
    information = A @ A.mT + torch.eye(3, dtype=torch.float64)
    L = torch.linalg.cholesky(information).mT  # L^T L = information
    T = se3_exp(torch.tensor([0.1, -0.2, 0.05, 0.3, 0.0, -0.1], dtype=torch.float64))
    whitened = gauss_newton_step(L @ J, (L @ residual[..., None])[..., 0], weights, T)
    torch.testing.assert_close(gauss_newton_step(J, residual, weights, T, information), whitened)


def test_unknown_step_names_the_argument():
    with pytest.raises(ValueError, match="step must be one of"):
        make_icp_step("plane_to_point")
    assert set(ICP_STEPS) == {"point_to_point", "point_to_plane", "gicp"}


def test_icp_settings_are_checked_when_made():
    from vrnet_ext.registration import IcpSettings, register

    for kwargs, match in [({"step": "plane"}, "IcpSettings.step must be one of"), ({"points": 0}, "IcpSettings.points"),
                          ({"max_iterations": -1}, "IcpSettings.max_iterations"),
                          ({"max_distance": float("nan")}, "IcpSettings.max_distance"),
                          ({"voxel_size": 0.0}, "IcpSettings.voxel_size"), ({"settled": -1e-6}, "IcpSettings.settled")]:
        with pytest.raises(ValueError, match=match):
            IcpSettings(**kwargs)
    with pytest.raises(TypeError, match="estimator"):  # renamed to step in 0.2
        IcpSettings(estimator="gicp")
    with pytest.raises(TypeError, match="icp_settings must be an IcpSettings"):
        register(np.zeros((5, 3)), np.zeros((5, 3)), icp_settings={"points": 10})


def test_the_normal_equations_sum_in_one_order_whatever_the_thread_count(tmp_path):
    """ICP's J^T W J over 3 to 200,000 rows: the float64 matrix product to rounding, and the same bits
    with 1 thread and with 2 (one long BLAS product splits its sum by thread count)."""
    import subprocess
    import sys

    from vrnet_ext.registration.icp_steps import GRAM_ROWS, fixed_order_product

    script = ("import sys, torch; torch.set_num_threads(int(sys.argv[2])); "
              "from vrnet_ext.registration.icp_steps import fixed_order_product; "
              "g = torch.Generator().manual_seed(0); "
              "pairs = [(torch.randn(n, 6, generator=g, dtype=torch.float64), torch.randn(n, k, generator=g, "
              "dtype=torch.float64)) for n, k in ((3, 6), (GRAM, 6), (GRAM + 1, 6), (5_000, 6), (200_000, 6))]; "
              "torch.save([fixed_order_product(a, b) for a, b in pairs], sys.argv[1])").replace("GRAM", str(GRAM_ROWS))
    results = []
    for threads in (1, 2):
        path = tmp_path / f"{threads}.pt"
        subprocess.run([sys.executable, "-c", script, str(path), str(threads)], check=True, timeout=120)
        results.append(torch.load(path))
    assert all(torch.equal(one, two) for one, two in zip(*results))
    g = torch.Generator().manual_seed(1)
    for rows in (1, GRAM_ROWS - 1, 3 * GRAM_ROWS + 5):
        left, right = (torch.randn(rows, 6, generator=g, dtype=torch.float64) for _ in range(2))
        torch.testing.assert_close(fixed_order_product(left, right), left.T @ right, rtol=1e-12, atol=1e-12)
