import h5py
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import MODELNET_DIR, requires_modelnet
from vrnet_ext.data import ModelNet40Pairs, PairSpec, load_h5, make_pair
from vrnet_ext.data.modelnet import spread_positions
from vrnet_ext.data.protocol import cube_residual, random_motion
from vrnet_ext.geometry.transforms import cube_rotations


def test_rotation_is_dcp_rx_ry_rz():
    R, _, euler = random_motion(np.random.default_rng(3), 45.0, 0.5)
    az, ay, ax = np.deg2rad(euler)
    Rx = Rotation.from_euler("x", ax).as_matrix()
    Ry = Rotation.from_euler("y", ay).as_matrix()
    Rz = Rotation.from_euler("z", az).as_matrix()
    np.testing.assert_allclose(R, Rx @ Ry @ Rz, atol=1e-12)
    assert np.all((euler >= 0) & (euler <= 45))


def test_the_protocol_draws_each_angle_in_zero_to_max_and_symmetric_on_both_sides():
    protocol = np.stack([random_motion(np.random.default_rng(seed), 30.0, 0.5)[2] for seed in range(400)])
    symmetric = np.stack([random_motion(np.random.default_rng(seed), 30.0, 0.5, "symmetric")[2] for seed in range(400)])
    assert protocol.min() >= 0 and protocol.max() <= 30
    assert symmetric.min() >= -30 and symmetric.max() <= 30
    assert (symmetric < -20).mean(axis=0).min() > 0.1 and (symmetric > 20).mean(axis=0).min() > 0.1
    # the protocol's draws are the ones the paper's tables were measured on: unchanged by the option
    R, t, euler = random_motion(np.random.default_rng(3), 45.0, 0.5)
    R2, t2, euler2 = random_motion(np.random.default_rng(3), 45.0, 0.5, "protocol")
    assert np.array_equal(R, R2) and np.array_equal(t, t2) and np.array_equal(euler, euler2)


def test_so3_rotations_are_uniform():
    rotations = np.stack([random_motion(np.random.default_rng(seed), 45.0, 0.5, "so3")[0] for seed in range(2000)])
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (2000, 3, 3)),
                               atol=1e-9)
    # uniform over SO(3): the mean of R vanishes, and the angle's cumulative distribution is (t - sin t) / pi
    assert np.abs(rotations.mean(axis=0)).max() < 0.05
    angles = np.sort(np.arccos(np.clip((np.trace(rotations, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    expected = (angles - np.sin(angles)) / np.pi
    assert np.abs(np.arange(1, 2001) / 2000 - expected).max() < 0.04  # Kolmogorov-Smirnov, 2000 draws


def test_spread_positions_sample_a_class_sorted_list_in_proportion():
    assert spread_positions(10, 4).tolist() == [0, 2, 5, 7]
    assert spread_positions(3, 5).tolist() == [0, 1, 2] and spread_positions(7, 7).tolist() == list(range(7))
    labels = np.repeat(np.arange(40), 25)  # a file of 40 classes of 25 shapes, listed class by class
    assert np.bincount(labels[spread_positions(labels.size, 80)], minlength=40).tolist() == [2] * 40


@requires_modelnet
def test_max_items_keeps_shapes_of_every_class():
    pairs = ModelNet40Pairs(MODELNET_DIR, partition="test", setting="PV", max_items=100)
    assert len(pairs) == 100 and np.unique(pairs.labels).size >= 30  # not the first class's 100 airplanes


def test_cube_residual_rotations_are_what_the_nearest_cube_start_leaves():
    cube = cube_rotations()
    small = Rotation.from_rotvec(np.deg2rad(40.0) * np.array([0.6, -0.8, 0.0])).as_matrix()
    for start in cube:  # a rotation 40 degrees from a start is brought back to those 40 degrees
        np.testing.assert_allclose(cube_residual(small @ start), small, atol=1e-12)
    rotations = np.stack([random_motion(np.random.default_rng(seed), 45.0, 0.5, "cube_residual")[0]
                          for seed in range(2000)])
    angles = np.rad2deg(np.arccos(np.clip((np.trace(rotations, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angles.max() <= 62.81 and angles.max() > 55  # the whole cell of the identity, up to its corners
    # the identity is the nearest rotation of the cube to every draw, and the draws lean no way
    assert (np.einsum("nij,kij->nk", rotations, cube).argmax(axis=1) == 0).all()
    assert np.abs(rotations.mean(axis=0) - np.diag(np.diag(rotations.mean(axis=0)))).max() < 0.05


def test_pairs_follow_the_rotation_range_and_a_bad_one_is_refused():
    base = np.random.default_rng(0).standard_normal((1024, 3))
    pair = make_pair(base, PairSpec(setting="RS", rotation_range="symmetric"), np.random.default_rng(5))
    inliers = pair["gt_idx"] >= 0
    moved = pair["src"] @ pair["rotation"].T + pair["translation"]
    np.testing.assert_allclose(moved[inliers], pair["tgt"][pair["gt_idx"][inliers]], atol=1e-5)
    with pytest.raises(ValueError, match="rotation_range must be one of"):
        PairSpec(rotation_range="octant")


@pytest.mark.parametrize("setting,count", [("CO", 1024), ("PV", 768), ("RS", 768), ("PV+RS", 768)])
def test_settings_counts_and_ground_truth(setting, count):
    base = np.random.default_rng(0).standard_normal((1024, 3))
    base.setflags(write=False)
    pair = make_pair(base, PairSpec(setting=setting), np.random.default_rng(1))
    assert pair["src"].shape == (count, 3) and pair["tgt"].shape == (count, 3)
    inliers = pair["gt_idx"] >= 0
    moved = pair["src"] @ pair["rotation"].T + pair["translation"]
    np.testing.assert_allclose(moved[inliers], pair["tgt"][pair["gt_idx"][inliers]], atol=1e-5)
    if setting == "CO":
        assert inliers.all()
    else:  # outliers really have no counterpart in the target
        d = np.linalg.norm(moved[~inliers][:, None] - pair["tgt"][None], axis=-1).min(axis=1)
        assert (~inliers).any() and (d > 1e-6).all()
    assert np.abs(pair["translation"]).max() <= 0.5


def test_mixed_setting_draws_every_setting_at_one_size():
    base = np.random.default_rng(0).standard_normal((1024, 3))
    base.setflags(write=False)
    kinds = set()
    for seed in range(40):
        pair = make_pair(base, PairSpec(setting="mixed"), np.random.default_rng(seed))
        assert pair["src"].shape == (768, 3) and pair["tgt"].shape == (768, 3)
        inliers = pair["gt_idx"] >= 0
        moved = pair["src"] @ pair["rotation"].T + pair["translation"]
        np.testing.assert_allclose(moved[inliers], pair["tgt"][pair["gt_idx"][inliers]], atol=1e-5)
        if inliers.all():
            kinds.add("CO")
            continue
        # a partial view keeps a compact cap of the shape: its points lie on one side of the centroid
        src_centroid = pair["src"].mean(axis=0)
        kinds.add("PV" if np.linalg.norm(src_centroid) > 0.3 else "RS")
    assert kinds == {"CO", "PV", "RS"}
    with pytest.raises(ValueError, match="setting must be one of"):
        PairSpec(setting="all")


def view_direction(cloud, view):
    """Unit vector from the centre of ``cloud`` (N, 3) away from the centroid of the points a partial
    ``view`` (V, 3) of it dropped: towards the far point that cut the view."""
    kept = np.linalg.norm(cloud[:, None] - view[None], axis=-1).min(axis=1) < 1e-5
    away = cloud.mean(axis=0) - cloud[~kept].mean(axis=0)
    return away / np.linalg.norm(away)


@pytest.mark.parametrize("far_points", ["prnet", "sphere", "mixed"])
def test_partial_views_look_along_the_diagonal_only_with_prnet_far_points(far_points):
    rng = np.random.default_rng(0)
    sphere = rng.standard_normal((1024, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    sphere.setflags(write=False)
    diagonal = np.ones(3) / np.sqrt(3)
    off_diagonal = []
    for seed in range(40):
        pair = make_pair(sphere, PairSpec(setting="PV", far_points=far_points), np.random.default_rng(seed))
        assert pair["src"].shape == pair["tgt"].shape == (768, 3)
        off_diagonal.append(1 - abs(view_direction(sphere, pair["src"]) @ diagonal))
    off_diagonal = np.array(off_diagonal)
    if far_points == "prnet":
        assert off_diagonal.max() < 0.02, off_diagonal
    elif far_points == "sphere":
        assert (off_diagonal > 0.05).mean() > 0.7, off_diagonal
    else:
        assert 0.2 < (off_diagonal < 0.02).mean() < 0.8, off_diagonal
    with pytest.raises(ValueError, match="far_points must be one of"):
        PairSpec(far_points="north")


@pytest.mark.parametrize("far_points, agreement", [("prnet", 1), ("symmetric", -1)])
def test_both_views_are_cut_by_one_far_point_or_its_mirror_image(far_points, agreement):
    """PRNet's and VRNet's code cut the target (in its own frame) by the source's far point; the
    paper's ablations by its mirror image through the origin."""
    rng = np.random.default_rng(1)
    sphere = rng.standard_normal((1024, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    sphere.setflags(write=False)
    for seed in range(20):
        pair = make_pair(sphere, PairSpec(setting="PV", far_points=far_points), np.random.default_rng(seed))
        R, t = pair["rotation"].astype(np.float64), pair["translation"].astype(np.float64)
        src_view = view_direction(sphere, pair["src"])
        # the target's view in the source's frame, turned into the target's frame
        tgt_view = R @ view_direction(sphere, (pair["tgt"] - t) @ R)
        assert src_view @ tgt_view * agreement > 0.99, (seed, src_view, tgt_view)


def test_prnet_far_points_keep_the_pairs_of_earlier_versions():
    """The default pairs are drawn exactly as before ``far_points`` existed (same random stream)."""
    rng = np.random.default_rng(5)
    base = rng.standard_normal((1024, 3))
    pair = make_pair(base, PairSpec(setting="PV"), np.random.default_rng(11))
    replay = np.random.default_rng(11)
    rotation = Rotation.from_euler("zyx", replay.uniform(0, np.deg2rad(45), 3)[::-1]).as_matrix()
    translation = replay.uniform(-0.5, 0.5, 3)
    far = replay.random(3) + 500.0 * replay.choice((1, -1))
    keep = np.sort(np.argpartition(((base - far) ** 2).sum(axis=1), 767)[:768])
    np.testing.assert_allclose(pair["rotation"], rotation, atol=1e-6)
    np.testing.assert_allclose(pair["translation"], translation, atol=1e-6)
    np.testing.assert_array_equal(np.sort(pair["src"], axis=0), np.sort(base[keep].astype(np.float32), axis=0))


def test_noise_is_bounded_and_never_touches_the_source_array():
    base = np.random.default_rng(0).standard_normal((1024, 3)).astype(np.float32)
    before = base.copy()
    for seed in range(5):
        pair = make_pair(base, PairSpec(setting="CO", noise=True), np.random.default_rng(seed))
    np.testing.assert_array_equal(base, before)
    clean = make_pair(base, PairSpec(setting="CO", noise=False), np.random.default_rng(4))
    delta = pair["src"] - clean["src"]
    assert 0 < np.abs(delta).max() <= 0.05 + 1e-6


@requires_modelnet
def test_nd_dataset_does_not_accumulate_noise_across_epochs():
    ds = ModelNet40Pairs(MODELNET_DIR, partition="train", setting="CO", split="ND", max_items=4)
    cached = ds.points.copy()
    first = ds[0]["src"]
    for epoch in range(3):
        ds.set_epoch(epoch)
        for i in range(len(ds)):
            ds[i]
    ds.set_epoch(0)
    np.testing.assert_array_equal(ds.points, cached)
    torch.testing.assert_close(ds[0]["src"], first, rtol=0, atol=0)


@requires_modelnet
def test_determinism_and_epochs():
    test_a = ModelNet40Pairs(MODELNET_DIR, partition="test", setting="PV", max_items=5)
    test_b = ModelNet40Pairs(MODELNET_DIR, partition="test", setting="PV", max_items=5)
    for key in ("src", "tgt", "rotation", "gt_idx"):
        assert torch.equal(test_a[3][key], test_b[3][key])
    train = ModelNet40Pairs(MODELNET_DIR, partition="train", setting="PV", max_items=5)
    e0 = train[1]["rotation"]
    train.set_epoch(1)
    assert not torch.equal(train[1]["rotation"], e0)
    train.set_epoch(0)
    assert torch.equal(train[1]["rotation"], e0)


@requires_modelnet
def test_splits():
    uc_train = ModelNet40Pairs(MODELNET_DIR, partition="train", split="UC")
    uc_test = ModelNet40Pairs(MODELNET_DIR, partition="test", split="UC")
    assert uc_train.labels.max() < 20 and uc_test.labels.min() >= 20
    train = ModelNet40Pairs(MODELNET_DIR, partition="train")
    val = ModelNet40Pairs(MODELNET_DIR, partition="val")
    test = ModelNet40Pairs(MODELNET_DIR, partition="test")
    assert len(train) + len(val) == 9843 and len(test) == 2468
    train_keys = {p.tobytes() for p in train.points}
    assert not any(p.tobytes() in train_keys for p in val.points), "val must be disjoint from train"
    # the held-out shapes do not follow a run's seed: a run of another seed never trains on them
    other_train = ModelNet40Pairs(MODELNET_DIR, partition="train", seed=7)
    other_val = ModelNet40Pairs(MODELNET_DIR, partition="val", seed=7)
    assert np.array_equal(other_val.points, val.points) and np.array_equal(other_train.points, train.points)
    assert not torch.equal(other_train[0]["src"], train[0]["src"]), "the seed still draws the training pairs"
    item = test[0]
    assert item["src"].dtype == torch.float32 and item["gt_idx"].dtype == torch.int64


def test_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_h5(tmp_path / "missing.h5")
    corrupt = tmp_path / "corrupt.h5"
    corrupt.write_bytes(b"definitely not hdf5")
    with pytest.raises(ValueError, match="cannot read"):
        load_h5(corrupt)
    wrong = tmp_path / "wrong.h5"
    with h5py.File(wrong, "w") as f:
        f["points"] = np.zeros((2, 10, 3))
    with pytest.raises(ValueError, match="lacks"):
        load_h5(wrong)
    with pytest.raises(ValueError, match="setting"):
        PairSpec(setting="XY")


def release_part(path, shapes, seed):
    """A file of the modelnet40_ply_hdf5_2048 layout: data (S, 2048, 3), label (S, 1), normal."""
    rng = np.random.default_rng(seed)
    with h5py.File(path, "w") as f:
        f.create_dataset("data", data=rng.normal(size=(shapes, 2048, 3)).astype(np.float32))
        f.create_dataset("label", data=rng.integers(0, 40, (shapes, 1)).astype(np.uint8))
        f.create_dataset("normal", data=np.zeros((shapes, 2048, 3), np.float32))


def test_vrnet_data_makes_the_modelnet40_files_from_the_release_archive(tmp_path, capsys):
    """A tiny archive of the release's layout (two train parts, one test part, in a folder inside
    the zip) becomes the two files, first 1024 points of each shape, parts in numeric order; the
    pairs the commands build come from them."""
    import zipfile

    from vrnet_ext.cli import main

    parts = {"ply_data_train0.h5": (3, 0), "ply_data_train1.h5": (2, 1), "ply_data_test0.h5": (4, 2)}
    with zipfile.ZipFile(tmp_path / "modelnet40_ply_hdf5_2048.zip", "w") as archive:
        for name, (shapes, seed) in parts.items():
            release_part(tmp_path / name, shapes, seed)
            archive.write(tmp_path / name, f"modelnet40_ply_hdf5_2048/{name}")
    out = tmp_path / "made"
    assert main(["data", "modelnet40", str(tmp_path / "modelnet40_ply_hdf5_2048.zip"), "--out-dir", str(out)]) == 0
    assert "(5 shapes)" in capsys.readouterr().out
    with h5py.File(out / "modelnet40_1024_train.h5") as made, h5py.File(tmp_path / "ply_data_train1.h5") as second:
        assert made["data"].shape == (5, 1024, 3) and made["label"].shape == (5, 1)
        np.testing.assert_array_equal(made["data"][3:], second["data"][:, :1024])
    pairs = ModelNet40Pairs(out, partition="test", max_items=4)
    assert len(pairs) == 4 and pairs[0]["src"].shape[1] == 3
    (tmp_path / "empty").mkdir()
    assert main(["data", "modelnet40", str(tmp_path / "empty")]) == 2
    assert "no ply_data_train*.h5" in capsys.readouterr().err
