from unittest import mock

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext.geometry import transforms
from vrnet_ext.geometry.transforms import apply, compose, from_normalised, move, to_homogeneous


def test_compose_is_the_product_of_the_homogeneous_matrices_for_arrays_and_batched_tensors():
    rng = np.random.default_rng(0)
    R1, R2 = Rotation.random(2, random_state=1).as_matrix()
    t1, t2 = rng.normal(size=3), rng.normal(size=3)
    R, t = compose(R2, t2, R1, t1)
    np.testing.assert_allclose(to_homogeneous(R, t), to_homogeneous(R2, t2) @ to_homogeneous(R1, t1), atol=1e-12)
    points = rng.normal(size=(5, 3))
    np.testing.assert_allclose(move(points, R, t), move(move(points, R1, t1), R2, t2), atol=1e-12)
    batch = torch.tensor(np.stack([R1, R2])), torch.tensor(np.stack([t1, t2]))
    Rb, tb = compose(*batch, *batch)
    np.testing.assert_allclose(apply(torch.tensor(to_homogeneous(Rb[1].numpy(), tb[1].numpy())), torch.tensor(points)),
                               move(move(points, R2, t2), R2, t2), atol=1e-12)


def test_from_normalised_maps_the_clouds_themselves():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3)) * 40 + 100
    R, t = Rotation.random(random_state=3).as_matrix(), rng.normal(size=3) * 10
    tgt = move(src, R, t)
    src_centre, tgt_centre, scale = src.mean(0), tgt.mean(0) + 1.0, 55.0
    t_normalised = (R @ src_centre + t - tgt_centre) / scale  # (tgt - c_t) / s = R (src - c_s) / s + t_n
    got_R, got_t = from_normalised(R, t_normalised, src_centre, tgt_centre, scale)
    np.testing.assert_allclose(move(src, got_R, got_t), tgt, atol=1e-9)
    got = from_normalised(torch.tensor(R), torch.tensor(t_normalised), torch.tensor(src_centre),
                          torch.tensor(tgt_centre), scale)
    np.testing.assert_allclose(got[1].numpy(), got_t, atol=1e-12)


def test_points_move_and_motions_compose_in_float32_where_gpu_products_would_round():
    """Where a GPU would run float32 matrix products in TF32 (torch allows it), the transforms use
    multiply-adds instead: errors of float32, not of 10-bit operands (the branch taken here on the CPU
    by declaring the products rounding)."""
    rotation_1, rotation_2 = (torch.linalg.qr(torch.randn(4, 3, 3, dtype=torch.float64))[0] for _ in range(2))
    translation_1, translation_2 = torch.randn(4, 3, dtype=torch.float64), torch.randn(4, 3, dtype=torch.float64)
    points = torch.randn(4, 500, 3, dtype=torch.float64) * 100
    exact = transforms.move(points, rotation_1, translation_1), transforms.compose(rotation_2, translation_2,
                                                                                  rotation_1, translation_1)
    with mock.patch.object(transforms, "_matmul_would_round", lambda x: True):
        moved = transforms.move(points.float(), rotation_1.float(), translation_1.float())
        rotation, translation = transforms.compose(rotation_2.float(), translation_2.float(), rotation_1.float(),
                                                   translation_1.float())
    assert (moved.double() - exact[0]).abs().max() < 1e-4 * 100  # float32 of coordinates up to ~400
    assert (rotation.double() - exact[1][0]).abs().max() < 1e-6
    assert (translation.double() - exact[1][1]).abs().max() < 1e-5


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_transforms_on_a_gpu_with_tf32_allowed_keep_float32():
    rotation = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))[0]
    points = torch.randn(20000, 3, dtype=torch.float64) * 100
    matmul = torch.backends.cuda.matmul
    previous = matmul.fp32_precision
    matmul.fp32_precision = "tf32"
    try:
        moved = transforms.move(points.float().cuda(), rotation.float().cuda(), torch.zeros(3, device="cuda"))
    finally:
        matmul.fp32_precision = previous
    assert (moved.double().cpu() - points @ rotation.T).abs().max() < 1e-4 * 100


def _angles_deg(rotations):
    return np.rad2deg(np.arccos(np.clip((np.trace(rotations, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def test_the_search_starts_leave_every_motion_near_the_identity_and_near_the_centre():
    from vrnet_ext.geometry.transforms import cube_rotations, search_starts

    cube = cube_rotations()
    np.testing.assert_array_equal(search_starts(), cube[1:])  # about the identity: the 23 other cube rotations
    centre_angles = (22.5, 22.5, 22.5)
    starts = search_starts(centre_angles)
    assert starts.shape == (47, 3, 3)
    np.testing.assert_array_equal(starts[:23], cube[1:])
    np.testing.assert_allclose(starts @ starts.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (47, 3, 3)), atol=1e-12)
    centre = Rotation.from_euler("zyx", centre_angles, degrees=True).as_matrix()
    motions = Rotation.random(3000, random_state=7).as_matrix()
    left = motions[:, None] @ starts[None, 23:].transpose(0, 1, 3, 2)  # what each centred start leaves, M G^T
    from_centre = _angles_deg(left @ centre.T).min(axis=1)
    assert from_centre.max() <= 62.81 and from_centre.max() > 55  # every motion, up to the cells' corners
    from_identity = _angles_deg(motions[:, None] @ cube[None].transpose(0, 1, 3, 2)).min(axis=1)
    assert from_identity.max() <= 62.81
    with pytest.raises(ValueError):
        search_starts((1.0, 2.0))


@pytest.mark.parametrize("count, reach", [(128, 46.0), (512, 28.0)])
def test_spread_rotations_leave_every_motion_near_one_of_them(count, reach):
    from vrnet_ext.geometry.transforms import spread_rotations

    spread = spread_rotations(count)
    assert spread.shape == (count, 3, 3) and spread.dtype == np.float64
    np.testing.assert_allclose(spread @ spread.transpose(0, 2, 1), np.broadcast_to(np.eye(3), spread.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(spread), 1.0, atol=1e-12)
    np.testing.assert_array_equal(spread_rotations(count), spread)  # the same set for the same count
    motions = Rotation.random(5000, random_state=3).as_matrix()
    nearest = _angles_deg(motions[:, None] @ spread[None].transpose(0, 1, 3, 2)).min(axis=1)
    assert nearest.max() <= reach and nearest.max() > 0.6 * reach  # evenly: no motion far, the bound not loose
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="count"):
            spread_rotations(bad)
