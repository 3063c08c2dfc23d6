"""data.real_pairs: the manifest reader (bounded, named errors), the training / validation split,
the provider's ground truth (turned scans, truth that maps the source onto the target), and
`vrnet train-scene --real-pairs`."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import DATA_DIR
from synthetic import box_scan
from vrnet_ext.cli import main
from vrnet_ext.data.real_pairs import RealPairProvider, read_manifest, split
from vrnet_ext.geometry.transforms import apply, to_homogeneous
from vrnet_ext.learning.scene_training import pair_tensors

HEADER = "pair_id\tsource_file\ttarget_file\tgt_file\tkind\toverlap_frac\n"


def fake_real_pairs(folder, indoor: int = 6, kitti: tuple[str, ...] = ("kitti00_0_4", "kitti01_0_4")):
    """A real_pairs folder of box scans: each pair's target is its source moved by a known motion."""
    (folder / "clouds").mkdir(parents=True)
    (folder / "gt").mkdir()
    rows = []
    names = [f"3dmatch_rk_{i}_{i + 1}" for i in range(indoor)] + list(kitti)
    for number, name in enumerate(names):
        source = box_scan(3000, seed=number)
        truth = to_homogeneous(Rotation.from_rotvec([0.1, -0.2, 0.3 * number]).as_matrix(), np.array([0.3, 0.1, -0.2]))
        np.save(folder / "clouds" / f"{name}_src.npy", source.astype(np.float32))
        np.save(folder / "clouds" / f"{name}_tgt.npy", apply(truth, source).astype(np.float32))
        np.savetxt(folder / "gt" / f"{name}.txt", truth)
        kind = "outdoor-lidar-kitti" if name.startswith("kitti") else "indoor-3DMatch"
        rows.append(f"{name}\tclouds/{name}_src.npy\tclouds/{name}_tgt.npy\tgt/{name}.txt\t{kind}\t0.5\n")
    (folder / "MANIFEST.tsv").write_text(HEADER + "".join(rows))
    return names


def test_split_holds_out_every_third_indoor_pair_and_kitti_outside_sequence_00(tmp_path):
    names = fake_real_pairs(tmp_path)
    training, validation = split(read_manifest(tmp_path))
    assert [p.pair_id for p in validation] == [names[2], names[5], "kitti01_0_4"]
    assert [p.pair_id for p in training] == [names[0], names[1], names[3], names[4], "kitti00_0_4"]
    assert validation[-1].outdoor and not validation[0].outdoor


def test_manifest_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="MANIFEST.tsv"):
        read_manifest(tmp_path)
    (tmp_path / "MANIFEST.tsv").write_text("pair_id\tsource_file\n")
    with pytest.raises(ValueError, match=r"MANIFEST.tsv: the header lacks the columns \['target_file'"):
        read_manifest(tmp_path)


def test_provider_truth_maps_the_turned_source_onto_the_turned_target(tmp_path):
    fake_real_pairs(tmp_path, indoor=3, kitti=())
    pairs = read_manifest(tmp_path)
    provider = RealPairProvider(pairs, synthetic_share=0.0)
    scans = provider.scans()
    rng = np.random.default_rng(0)
    for pair in pairs:
        real = provider(pair.pair_id, scans[pair.pair_id], 0.1, rng)
        batch = pair_tensors(real)
        distance = torch.cdist(batch["truth"][0], batch["tgt"][0]).min(1).values  # voxel units
        assert float(distance.median()) < 0.7, pair.pair_id
        assert not np.allclose(real.T_tgt_src[:3, :3], np.loadtxt(pair.gt)[:3, :3])  # the scans were turned


def test_provider_mixes_in_self_supervised_pairs_and_checks_its_share(tmp_path):
    fake_real_pairs(tmp_path, indoor=1, kitti=())
    pairs = read_manifest(tmp_path)
    with pytest.raises(ValueError, match="synthetic_share"):
        RealPairProvider(pairs, synthetic_share=1.5)
    provider = RealPairProvider(pairs, synthetic_share=1.0)
    source = provider.scans()[pairs[0].pair_id]
    provider(pairs[0].pair_id, source, 0.1, np.random.default_rng(0))
    assert provider._targets == {}, "a self-supervised pair never reads the target scan"


def test_train_scene_on_real_pairs_trains_on_the_training_pairs_only(tmp_path, capsys):
    names = fake_real_pairs(tmp_path / "real")
    out = tmp_path / "scene.pt"
    assert main(["train-scene", "--real-pairs", str(tmp_path / "real"), "--out", str(out), "--steps", "2",
                 "--points", "300", "--no-progress"]) == 0
    state = torch.load(out, weights_only=False)
    assert state["scans"] == sorted([names[0], names[1], names[3], names[4], "kitti00_0_4"])
    assert main(["train-scene", "--out", str(out)]) == 2
    assert "give point-cloud files, --real-pairs, or both" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train-scene", "--real-pairs", str(tmp_path / "none"), "--out", str(out)])
    assert "is not a folder" in capsys.readouterr().err


@pytest.mark.skipif(not (DATA_DIR / "scenes" / "real_pairs" / "MANIFEST.tsv").exists(),
                    reason="real_pairs not found under ../shared/data/scenes")
def test_the_shared_real_pairs_split_keeps_kinds_on_both_sides():
    training, validation = split(read_manifest(DATA_DIR / "scenes" / "real_pairs"))
    assert len(training) + len(validation) == 45 and not {p.pair_id for p in training} & {p.pair_id for p in validation}
    for kind in ("indoor-3DMatch", "indoor-3DLoMatch", "outdoor-lidar-kitti"):
        assert any(p.kind == kind for p in training) and any(p.kind == kind for p in validation), kind


def test_success_follows_the_kind_and_a_bad_overlap_names_the_pair(tmp_path):
    fake_real_pairs(tmp_path, indoor=1)
    indoor, _, outdoor = read_manifest(tmp_path)
    assert indoor.subset == "3DMatch" and outdoor.subset == "KITTI"
    assert indoor.registered(14.0, 0.29) and not indoor.registered(14.0, 0.31) and not indoor.registered(16.0, 0.1)
    assert outdoor.registered(4.9, 1.9) and not outdoor.registered(5.1, 0.1)
    text = (tmp_path / "MANIFEST.tsv").read_text().replace("\t0.5\n", "\tabout half\n", 1)
    (tmp_path / "MANIFEST.tsv").write_text(text)
    with pytest.raises(ValueError, match="pair '3dmatch_rk_0_1' has overlap_frac 'about half', not a number"):
        read_manifest(tmp_path)
