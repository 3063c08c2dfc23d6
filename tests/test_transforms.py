import numpy as np
import torch
from scipy.spatial.transform import Rotation

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
