import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import DATA_DIR, MODELNET_DIR, help_defaults_are_clean, requires_cuda_kernels, requires_modelnet
from synthetic import motion, room
from vrnet_ext import ops
from vrnet_ext.cli import main
from vrnet_ext import load_pretrained
from vrnet_ext.geometry.io import read_points, read_transform, write_ply
from vrnet_ext.geometry.preprocessing import point_spacing, voxel_downsample
from vrnet_ext.registration import (IcpFailure, IcpSettings, ObjectNetwork, PointCounts, ScanPair, icp, register,
                                    transform_errors)
from vrnet_ext.registration.refinement import TargetReach
from vrnet_ext.geometry.transforms import apply, to_homogeneous
from vrnet_ext.names import GLOBAL_ESTIMATORS


def point_to_point(max_distance: float, **settings) -> IcpSettings:
    """ICP point to point within ``max_distance``, stopping at steps below 1e-6."""
    return IcpSettings(step="point_to_point", max_distance=max_distance, transform_tolerance=1e-6, **settings)

LIDAR = DATA_DIR / "scenes" / "lidar_pair"


def test_voxel_downsample_averages_each_voxel():
    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2]])
    got = voxel_downsample(points, 1.0)
    np.testing.assert_allclose(sorted(got.tolist()), [[0.2, 0.2, 0.2], [1.5, 0.2, 0.2]])
    with pytest.raises(ValueError, match="voxel_size"):
        voxel_downsample(points, 0.0)


def test_voxel_downsample_matches_a_per_voxel_mean_in_row_major_voxel_order():
    rng = np.random.default_rng(5)
    points = rng.normal(scale=3.0, size=(5000, 3)) - 7.0
    voxel = 0.8
    groups = {}
    for p, cell in zip(points, map(tuple, np.floor((points - points.min(0)) / voxel).astype(int))):
        groups.setdefault(cell, []).append(p)
    expected = np.array([np.mean(groups[cell], axis=0) for cell in sorted(groups)])
    np.testing.assert_allclose(voxel_downsample(points, voxel), expected, rtol=0, atol=1e-12)
    # more voxels in the box than an int64 key can number: the occupied ones are numbered instead
    far = np.vstack([points, [[1e6, 1e6, 1e6]]])
    np.testing.assert_allclose(voxel_downsample(far, 1e-4)[-1], [1e6, 1e6, 1e6])
    assert len(voxel_downsample(far, 1e-4)) == len(np.unique(far, axis=0))
    with pytest.raises(ValueError, match="too small"):
        voxel_downsample(np.array([[0.0, 0.0, 0.0], [1e3, 1e3, 1e3]]), 1e-17)


def test_icp_recovers_a_small_motion():
    src = room()
    truth = motion(6.0, [0.1, -0.05, 0.08])
    result = icp(src, apply(truth, src), np.eye(4), point_to_point(0.5))
    errors = transform_errors(result.T_target_source, truth)
    assert errors["rotation_error_deg"] < 1e-3 and errors["translation_error"] < 1e-4, errors
    assert result.fitness > 0.99 and result.inlier_rmse < 1e-4 and result.iterations < 50 and result.converged
    assert result.correspondences == round(result.fitness * len(src)) and result.method == "icp"


def test_target_reach_never_rules_out_a_point_within_reach():
    rng = np.random.default_rng(3)
    tgt = torch.as_tensor(room(2000)).unsqueeze(0)
    reach = 0.07
    queries = torch.cat([torch.as_tensor(rng.uniform(-1, 5, size=(3000, 3))),
                         tgt[0, :500] + torch.as_tensor(rng.normal(scale=0.05, size=(500, 3))),
                         torch.tensor([[1e12, -1e12, 3.0], [-40.0, 2.0, 2.0]], dtype=torch.float64)]).unsqueeze(0)
    nearest = torch.cdist(queries[0], tgt[0]).amin(1)
    allowed = TargetReach(tgt, reach)(queries)
    assert allowed.shape == (queries.shape[1],) and allowed.dtype == torch.bool
    assert bool(allowed[nearest <= reach].all())
    assert not bool(allowed[nearest > 4 * reach].any())  # beyond the 27 voxels: always ruled out
    assert int(allowed.sum()) < int((nearest <= 4 * reach).sum()) + 1


def test_target_reach_lets_everything_through_over_its_cell_budget():
    tgt = torch.as_tensor(room(200)).unsqueeze(0)
    far = tgt + 100.0
    assert not bool(TargetReach(tgt, 0.1)(far).any())
    assert bool(TargetReach(tgt, 0.1, max_cells=1000)(far).all())


def test_icp_skipping_out_of_reach_points_changes_nothing(monkeypatch):
    """Partial overlap: most moved source points have no target point within reach."""
    src = room(3000)
    truth = motion(4.0, [0.05, 0.02, -0.03])
    tgt = apply(truth, src)
    tgt = tgt[tgt[:, 0] < 2.0]
    filtered = icp(src, tgt, np.eye(4), point_to_point(0.1))
    monkeypatch.setattr(TargetReach, "__call__", lambda self, points: torch.ones(points.shape[1], dtype=torch.bool))
    unfiltered = icp(src, tgt, np.eye(4), point_to_point(0.1))
    np.testing.assert_allclose(filtered.T_target_source, unfiltered.T_target_source, rtol=0, atol=1e-12)
    assert (filtered.iterations, filtered.fitness) == (unfiltered.iterations, unfiltered.fitness)
    assert filtered.inlier_rmse == pytest.approx(unfiltered.inlier_rmse, rel=1e-12)


class ExactModel(torch.nn.Module):
    """Stands in for VRNet: solves the normalised pair exactly (points correspond row by row)."""

    def forward(self, src, tgt, backend=None):
        R, t = ops.kabsch(src, tgt)
        return type("Out", (), {"rotation": R, "translation": t})()


def test_network_estimate_undoes_the_normalisation():
    src = room(500) * 30.0 + 200.0  # far from the origin and not unit-sized: a scan in metres
    truth = motion(40.0, [5.0, -3.0, 2.0])
    pair = ScanPair.of(src, apply(truth, src), PointCounts(network_points=10_000))
    T = ObjectNetwork(ExactModel()).estimate_pair(pair, seed=0).T_target_source
    errors = transform_errors(T, truth)
    assert errors["rotation_error_deg"] < 1e-3 and errors["translation_error"] < 1e-3, errors


def test_register_from_identity_and_without_icp():
    src = room()
    truth = motion(4.0, [0.05, 0.02, -0.04])
    result = register(src, apply(truth, src), icp_settings=IcpSettings(points=3000))
    # voxel means of a rotated cloud do not correspond exactly: a small bias remains
    assert transform_errors(result.T_target_source, truth)["rotation_error_deg"] < 0.2
    assert result.points["source_icp"] <= len(src)
    plain = register(src, apply(truth, src), model=ExactModel(), network_points=10_000,
                     icp_settings=IcpSettings(max_iterations=0))
    assert transform_errors(plain.T_target_source, truth)["rotation_error_deg"] < 1e-3
    assert plain.iterations == 0


def test_icp_out_of_reach_returns_the_initial_estimate_with_a_warning():
    src = room(1000)
    far = to_homogeneous(np.eye(3), np.array([50.0, 0.0, 0.0]))
    with pytest.raises(IcpFailure, match="fewer than 3 point pairs"):
        icp(src, src, far, point_to_point(0.1))
    result = register(src, src + np.array([50.0, 0.0, 0.0]), method="icp",
                      icp_settings=IcpSettings(max_distance=0.1))
    assert result.iterations == 0 and np.array_equal(result.T_target_source, np.eye(4))
    assert "unrefined initial estimate" in result.warnings[0]


def test_cli_register(tmp_path, capsys):
    src = room()
    truth = motion(5.0, [0.1, 0.0, 0.05])
    write_ply(tmp_path / "src.ply", src)
    np.save(tmp_path / "tgt.npy", apply(truth, src))
    np.savetxt(tmp_path / "gt.txt", truth)
    args = ["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.npy"), "--gt", str(tmp_path / "gt.txt"),
            "--json", str(tmp_path / "r.json"), "--out", str(tmp_path / "moved.ply"), "--plot", str(tmp_path / "r.png"),
            "--icp-points", "3000"]
    assert main(args) == 0
    record = json.loads((tmp_path / "r.json").read_text())
    assert record["errors"]["rotation_error_deg"] < 0.2 and record["peak_rss_mb"] > 0
    np.testing.assert_allclose(read_points(tmp_path / "moved.ply"), apply(np.array(record["T_target_source"]), src), atol=1e-5)
    assert (tmp_path / "r.png").stat().st_size > 10_000
    assert main(["register", str(tmp_path / "src.ply"), str(tmp_path / "missing.ply")]) == 2
    assert "missing.ply: no such file" in capsys.readouterr().err
    # the ground truth of the other direction: the errors are reported, with a warning saying so
    np.savetxt(tmp_path / "inverse.txt", np.linalg.inv(truth))
    assert main(args[:4] + [str(tmp_path / "inverse.txt"), "--icp-points", "3000"]) == 0
    assert "matches the inverse of --gt" in capsys.readouterr().err


def test_the_register_picture_shows_input_result_and_truth_with_the_fit_in_its_title(tmp_path, monkeypatch):
    """--plot draws the source before any motion, after the result and (with --gt) after the ground
    truth, each from above and from the side, under a title with the method, fitness and errors."""
    import vrnet_ext.plots as plots

    drawn = []
    monkeypatch.setattr(plots, "_save", lambda fig, path, dpi: drawn.append(fig) or path)
    src = room()
    truth = motion(5.0, [0.1, 0.0, 0.05])
    np.save(tmp_path / "src.npy", src)
    np.save(tmp_path / "tgt.npy", apply(truth, src))
    np.savetxt(tmp_path / "gt.txt", truth)
    assert main(["register", str(tmp_path / "src.npy"), str(tmp_path / "tgt.npy"), "--gt", str(tmp_path / "gt.txt"),
                 "--plot", str(tmp_path / "r.png"), "--icp-points", "3000"]) == 0
    (fig,) = drawn
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == [f"{row}: {view}" for row in ("input (no motion)", "result", "ground truth")
                      for view in ("top view (x, y)", "side view (x, z)")], titles
    heading = fig._suptitle.get_text()
    assert heading.startswith("FPFH + spatial consistency + ICP (point_to_plane): fitness ") and "inlier RMSE" in heading
    assert "against the ground truth: rotation " in heading, heading
    colours = {tuple(collection.get_facecolor()[0][:3]) for collection in fig.axes[0].collections}
    assert len(colours) == 2  # source and target in their own colours, both half transparent
    assert all(collection.get_alpha() < 1 for collection in fig.axes[0].collections)


def test_the_vrnet_executable_writes_everything_and_keeps_its_exit_status(tmp_path):
    """``vrnet`` ends with os._exit: every output written, stdout flushed (even to a pipe), the status kept."""
    src = room(2000)
    write_ply(tmp_path / "src.ply", src)
    np.save(tmp_path / "tgt.npy", apply(motion(3.0, [0.05, 0.0, 0.0]), src))
    vrnet = [sys.executable, "-c", "import sys; from vrnet_ext.cli import run; sys.argv[0] = 'vrnet'; run()"]
    done = subprocess.run(vrnet + ["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.npy"), "--method", "icp",
                                   "--json", str(tmp_path / "r.json"), "--out", str(tmp_path / "moved.ply")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.rstrip().endswith(f"wrote {tmp_path / 'r.json'}"), done.stdout
    assert json.loads((tmp_path / "r.json").read_text())["T_target_source"]
    assert len(read_points(tmp_path / "moved.ply")) == len(src)
    missing = subprocess.run(vrnet + ["register", str(tmp_path / "src.ply"), str(tmp_path / "no.ply")],
                             capture_output=True, text=True, timeout=300)
    assert missing.returncode == 2 and "no.ply: no such file" in missing.stderr
    usage = subprocess.run(vrnet + ["register", "--icp-step", "bogus"], capture_output=True, text=True, timeout=300)
    assert usage.returncode == 2 and "invalid choice" in usage.stderr
    renamed = subprocess.run(vrnet + ["register", str(tmp_path / "src.ply"), str(tmp_path / "no.ply"), "--estimator",
                                      "gicp"], capture_output=True, text=True, timeout=300)
    assert "--estimator is now --icp-step" in renamed.stderr and "no.ply: no such file" in renamed.stderr
    assert subprocess.run(vrnet + ["--help"], capture_output=True, text=True, timeout=300).returncode == 0


@pytest.mark.parametrize("command", [[], ["register"], ["eval"], ["train"], ["export"], ["plot"], ["demo"],
                                     ["train-scene"]])
def test_help_does_not_load_torch(command):
    """`vrnet --help` and a subcommand's help answer without importing torch (seconds on a small CPU),
    and name each option's default once."""
    probe = ("import sys\nfrom vrnet_ext.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
             "print('torch' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", probe, *command, "--help"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "usage: vrnet" in done.stdout and done.stdout.split()[-1] == "False", done.stdout[-300:]
    assert help_defaults_are_clean(done.stdout), done.stdout


def test_short_commands_let_openmp_threads_sleep_unless_told_otherwise(tmp_path):
    """OMP_WAIT_POLICY=PASSIVE for `vrnet register` (set before torch loads OpenMP); a value in the
    environment is kept, and training commands leave it unset."""
    probe = ("import os, sys; from vrnet_ext.cli import main; main(sys.argv[1:]); "
             "print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}

    def policy(args: list[str], **extra: str) -> str:
        done = subprocess.run([sys.executable, "-c", probe, *args], capture_output=True, text=True, timeout=300,
                              env=dict(env, **extra))
        return done.stdout.split()[-2:]

    register = ["register", str(tmp_path / "a.ply"), str(tmp_path / "b.ply")]  # missing files: exits 2 after parsing
    assert policy(register) == ["PASSIVE", "True"]
    assert policy(register, OMP_WAIT_POLICY="ACTIVE") == ["ACTIVE", "True"]
    assert policy(["train", "--data-dir", str(tmp_path / "none"), "--preset", "tiny"])[0] == "None"


@requires_modelnet
def test_cli_register_with_checkpoint(tmp_path):
    from vrnet_ext.learning.train import TrainConfig, train

    train(TrainConfig.from_preset("tiny", data_dir=str(MODELNET_DIR), out_dir=str(tmp_path / "run"), progress=False,
                                  stage1_epochs=1, stage2_epochs=0))
    src = room(800)
    write_ply(tmp_path / "src.ply", src)
    write_ply(tmp_path / "tgt.ply", apply(motion(3.0, [0.02, 0, 0]), src))
    args = ["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply"), "--checkpoint",
            str(tmp_path / "run" / "last.pt"), "--network-points", "64", "--icp-iterations", "0",
            "--json", str(tmp_path / "r.json")]
    assert main(args) == 0
    record = json.loads((tmp_path / "r.json").read_text())
    initial = np.array(record["initial"])
    assert np.isfinite(initial).all() and record["checkpoint"].endswith("last.pt")
    np.testing.assert_allclose(initial[:3, :3] @ initial[:3, :3].T, np.eye(3), atol=1e-5)


@pytest.mark.skipif(not (LIDAR / "source.ply").exists(), reason=f"LiDAR pair not found under {LIDAR}")
def test_real_lidar_pair_icp_matches_reference():
    """Measured: 0.29 deg / 1.5 cm from the reference GICP transform (which itself agrees with an
    independent fast_gicp estimate within 0.23 deg / 1.9 cm)."""
    src, tgt = read_points(LIDAR / "source.ply"), read_points(LIDAR / "target.ply")
    truth = read_transform(LIDAR / "T_target_source.txt")
    errors = transform_errors(register(src, tgt, method="icp").T_target_source, truth)
    assert errors["rotation_error_deg"] < 0.5 and errors["translation_error"] < 0.05, errors
    # the coarse start is what reaches the pair's 0.5 m offset: the fine reach is 3 voxels of ~2.3 cm
    fine_only = register(src, tgt, method="icp", icp_settings=IcpSettings(coarse_start=False))
    assert transform_errors(fine_only.T_target_source, truth)["translation_error"] > 0.1


@pytest.mark.skipif(not (LIDAR / "source.ply").exists(), reason=f"LiDAR pair not found under {LIDAR}")
def test_georeferenced_lidar_pair_through_the_cli(tmp_path):
    """The LiDAR pair shifted to UTM-like coordinates (5e5, 5e6, 100) m, in float64 files, through
    `vrnet register`: every moved point within 1 cm of the unshifted result (float32 alone is 0.5 m
    coarse there)."""
    from vrnet_ext.geometry.transforms import in_shifted_frames

    src, tgt = read_points(LIDAR / "source.ply"), read_points(LIDAR / "target.ply")
    shift = np.array([5e5, 5e6, 100.0])
    np.save(tmp_path / "src.npy", src + shift)
    np.save(tmp_path / "tgt.npy", tgt + shift)
    assert main(["register", str(tmp_path / "src.npy"), str(tmp_path / "tgt.npy"), "--json",
                 str(tmp_path / "shifted.json"), "--out", str(tmp_path / "moved.ply")]) == 0
    shifted = np.array(json.loads((tmp_path / "shifted.json").read_text())["T_target_source"])
    unshifted = in_shifted_frames(register(src, tgt).T_target_source, shift)
    moved = apply(shifted, src + shift)
    assert np.abs(moved - apply(unshifted, src + shift)).max() < 0.01
    assert np.abs(read_points(tmp_path / "moved.ply") - moved).max() < 1e-6


def test_python_register_gives_the_cli_result_from_numpy(tmp_path):
    """vrnet_ext.register with default arguments on numpy arrays = `vrnet register` on the files."""
    import vrnet_ext

    kitchen = DATA_DIR / "scenes" / "3dmatch_redkitchen"
    if not (kitchen / "cloud_bin_0.ply").exists():
        pytest.skip(f"kitchen fragments not found under {kitchen}")
    for source, target in (("cloud_bin_4.ply", "cloud_bin_0.ply"), ("cloud_bin_10.ply", "cloud_bin_4.ply")):
        assert main(["register", str(kitchen / source), str(kitchen / target), "--json", str(tmp_path / "r.json")]) == 0
        record = json.loads((tmp_path / "r.json").read_text())
        result = vrnet_ext.register(read_points(kitchen / source), read_points(kitchen / target))
        assert result.method == record["method"] == "auto"
        difference = transform_errors(result.T_target_source, np.array(record["T_target_source"]))
        assert difference["rotation_error_deg"] < 0.01 and difference["translation_error"] < 1e-4, difference


def test_cli_register_rejects_bad_options_before_any_work(tmp_path, capsys):
    from vrnet_ext.cli import main

    cloud = np.random.default_rng(0).normal(size=(200, 3)).astype(np.float32)
    write_ply(tmp_path / "a.ply", cloud)
    a = str(tmp_path / "a.ply")
    bad = [["--icp-points", "0"], ["--icp-points", "-5"], ["--voxel-size", "nan"], ["--voxel-size", "0"],
           ["--max-distance", "nan"], ["--max-distance", "inf"], ["--max-distance", "0"], ["--max-distance", "-1"],
           ["--device", "nonsense"], ["--json", str(tmp_path / "missing" / "r.json")],
           ["--icp-iterations", "-1"], ["--fpfh-points", "0"]]
    for options in bad:
        with pytest.raises(SystemExit) as exit_info:
            main(["register", a, a, *options])
        assert exit_info.value.code == 2, options
        err = capsys.readouterr().err
        assert options[0] in err and "Traceback" not in err, (options, err)
    # --fpfh takes no value: the two files stay the two files
    assert main(["register", a, a, "--fpfh", "--icp-iterations", "0"]) in (0, 2)
    err = capsys.readouterr().err
    assert "invalid int" not in err
    gt_ply = tmp_path / "gt.ply"
    write_ply(gt_ply, cloud)
    assert main(["register", a, a, "--gt", str(gt_ply), "--icp-iterations", "0"]) == 2
    assert "gt.ply" in capsys.readouterr().err


def test_a_stray_far_point_in_the_target_does_not_change_the_icp_result():
    src = room(20000)
    tgt = apply(motion(3.0, [0.1, -0.05, 0.02]), room(20000, seed=1))
    clean = register(src, tgt, method="icp", icp_settings=IcpSettings(points=5000))
    for distance in (1e3, 1e5):
        stray = np.vstack([tgt, [[distance, 0.0, 0.0]]])
        result = register(src, stray, method="icp", icp_settings=IcpSettings(points=5000))
        assert transform_errors(result.T_target_source, clean.T_target_source)["rotation_error_deg"] < 0.05, distance
        # the voxel search may settle a hair finer or coarser; never coarse (the old failure)
        assert abs(result.points["target_icp"] - clean.points["target_icp"]) <= 0.01 * clean.points["target_icp"]


def test_icp_with_the_reference_knn_works_in_bounded_chunks(monkeypatch):
    import vrnet_ext.registration.refinement as refinement_module

    monkeypatch.setattr(refinement_module, "REFERENCE_KNN_ELEMENTS", 5000)  # force many chunks
    src = room(3000)
    tgt = apply(motion(2.0, [0.05, 0.0, 0.02]), room(3000, seed=1))
    ext = icp(src, tgt, np.eye(4), point_to_point(0.3), backend="ext")
    reference = icp(src, tgt, np.eye(4), point_to_point(0.3), backend="torch")
    np.testing.assert_allclose(reference.T_target_source, ext.T_target_source, atol=1e-9)
    assert reference.iterations == ext.iterations


def test_a_network_estimate_that_fits_worse_than_no_motion_is_dropped_with_a_warning():
    src = room(6000)
    tgt = apply(motion(2.0, [0.05, 0.02, 0.0]), room(6000, seed=1))

    class Wrong(torch.nn.Module):  # stands in for a model that does not transfer: a 90 deg turn
        config = type("Config", (), {"backend": "ext"})()

        def forward(self, src, tgt, backend=None):
            R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).expand(src.shape[0], 3, 3)
            return type("Out", (), dict(rotation=R, translation=torch.zeros(src.shape[0], 3)))()

    result = register(src, tgt, model=Wrong(), icp_settings=IcpSettings(points=3000))
    assert any("does not fit these scans" in w for w in result.warnings), result.warnings
    np.testing.assert_allclose(result.initial, np.eye(4))
    assert transform_errors(result.T_target_source, motion(2.0, [0.05, 0.02, 0.0]))["rotation_error_deg"] < 0.5


def test_low_fitness_and_unconverged_icp_are_reported():
    src = room(4000)
    far_off = apply(motion(40.0, [1.0, 0.5, 0.0]), room(4000, seed=1))
    result = register(src, far_off, method="icp", icp_settings=IcpSettings(points=2000, max_iterations=2))
    assert any("did not converge" in w for w in result.warnings), result.warnings
    assert any("low fitness" in w for w in result.warnings) or result.fitness >= 0.2
    assert result.to_dict()["warnings"] == result.warnings


def test_any_global_estimator_plugs_into_register():
    from vrnet_ext.registration import GlobalEstimator

    truth = motion(20.0, [0.3, -0.1, 0.05])
    src = room(6000)
    tgt = apply(truth, room(6000, seed=1))

    class Oracle(GlobalEstimator):  # a user's own estimator: the truth, off by 2 degrees
        name = "oracle"

        def estimate(self, src, tgt, seed):
            return truth @ motion(2.0, [0.0, 0.0, 0.0])

    result = register(src, tgt, method=Oracle(), icp_settings=IcpSettings(points=4000))
    assert result.method == "oracle" and not result.warnings, result.warnings
    np.testing.assert_allclose(result.initial, truth @ motion(2.0, [0.0, 0.0, 0.0]))
    assert transform_errors(result.T_target_source, truth)["rotation_error_deg"] < 0.5

    class Broken(GlobalEstimator):
        def estimate(self, src, tgt, seed):
            return np.full((4, 4), np.nan)

    with pytest.raises(ValueError, match="custom estimator returned no finite 4x4"):
        register(src, tgt, method=Broken())
    with pytest.raises(TypeError, match="method must be a name or a GlobalEstimator"):
        register(src, tgt, method=42)
    with pytest.raises(ValueError, match="model is only used by method 'vrnet'"):
        register(src, tgt, method=Oracle(), model=ExactModel())


def test_a_coarse_start_gives_the_fine_icp_a_head_start():
    src = room(20000)
    truth = motion(4.0, [0.35, -0.2, 0.05])
    tgt = apply(truth, room(20000, seed=1))
    fine_only = register(src, tgt, method="icp", icp_settings=IcpSettings(voxel_size=0.03, coarse_start=False))
    coarse = register(src, tgt, method="icp", icp_settings=IcpSettings(voxel_size=0.03))
    for result in (fine_only, coarse):
        errors = transform_errors(result.T_target_source, truth)
        assert errors["rotation_error_deg"] < 0.01 and errors["translation_error"] < 0.001, errors
    assert coarse.iterations < fine_only.iterations
    np.testing.assert_allclose(coarse.initial, np.eye(4))  # the start, not the coarse stage's result


def test_outputs_are_complete_or_absent(tmp_path):
    """A file-size limit (as a full disk) while writing --out: one line naming the file, a non-zero
    exit, nothing at the final path and no temporary left behind."""
    cloud = np.random.default_rng(0).normal(size=(3000, 3))
    write_ply(tmp_path / "a.ply", cloud)
    target = tmp_path / "moved.ply"
    script = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000)); "
              "from vrnet_ext.cli import run; sys.argv = ['vrnet'] + sys.argv[1:]; run()")
    done = subprocess.run([sys.executable, "-c", script, "register", str(tmp_path / "a.ply"), str(tmp_path / "a.ply"),
                           "--method", "icp", "--out", str(target)], capture_output=True, text=True, timeout=300)
    assert done.returncode != 0, done.stdout
    errors = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and str(target) in errors[0] and "File too large" in errors[0], done.stderr
    assert not target.exists() and not list(tmp_path.glob(".moved*"))


def test_coincident_points_are_refused_and_a_line_is_warned_about():
    line = np.outer(np.linspace(0.0, 1.0, 200), [1.0, 2.0, 3.0])
    result = register(line, line + 0.1, method="icp")
    assert any("src lies on a line" in w for w in result.warnings)
    assert any("tgt lies on a line" in w for w in result.warnings)
    solid = np.random.default_rng(0).normal(size=(500, 3))
    assert not any("line" in w for w in register(solid, solid, method="icp").warnings)
    with pytest.raises(ValueError, match="src: all 100 points coincide"):
        register(np.ones((100, 3)), solid, method="icp")
    with pytest.raises(ValueError, match="tgt: all 100 points coincide"):
        register(solid, np.full((100, 3), 5e6), model=load_pretrained("vrnet-pv-upc-rcp"))


def test_a_prepared_icp_problem_runs_from_several_starts_like_icp():
    from vrnet_ext.registration import IcpProblem

    rng = np.random.default_rng(3)
    src = rng.normal(size=(800, 3)) * [2.0, 1.0, 0.5]
    truth = to_homogeneous(Rotation.from_euler("z", 8, degrees=True).as_matrix(), [0.1, 0.0, 0.05])
    tgt = apply(truth, src)
    settings = IcpSettings(max_distance=0.5, transform_tolerance=1e-6)
    problem = IcpProblem(src, tgt, settings)
    for start in (np.eye(4), to_homogeneous(np.eye(3), [0.05, 0.0, 0.0])):
        prepared = problem.run(start)
        once = icp(src, tgt, start, settings)
        np.testing.assert_array_equal(prepared.T_target_source, once.T_target_source)
        assert prepared.iterations == once.iterations and prepared.fitness == once.fitness
        assert transform_errors(prepared.T_target_source, truth)["rotation_error_deg"] < 0.01


def test_every_option_of_every_command_has_help_naming_its_default():
    """Each option of each `vrnet` command says what it does, and one with a default to show
    (not None, empty or a flag's False) names it in its help."""
    import argparse

    from vrnet_ext.cli import build_parser

    def commands(parser, prefix=""):  # every (sub)command, nested ones (vrnet data modelnet40) included
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    yield f"{prefix}{name}", child
                    yield from commands(child, f"{prefix}{name} ")

    for name, parser in commands(build_parser()):
        formatter = parser._get_formatter()
        for action in parser._actions:
            if not action.option_strings or isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"vrnet {name} {action.option_strings[0]} has no help"
            shown = action.default not in (None, False, "", [], argparse.SUPPRESS) and action.nargs != 0
            if shown:
                assert "default" in formatter._get_help_string(action), f"vrnet {name} {action.option_strings[0]}"


KITCHEN_LOG = DATA_DIR / "scenes" / "3dmatch_redkitchen" / "gt_3DMatch_redkitchen.log"


@pytest.mark.skipif(not KITCHEN_LOG.exists(), reason=f"3DMatch kitchen fragments not found beside {KITCHEN_LOG}")
def test_register_takes_the_official_3dmatch_log_as_ground_truth(capsys):
    """The pair is picked by the fragments' file names (cloud_bin_0 onto cloud_bin_4: the log's
    block "0 4" inverted) or by --gt-fragments; the errors are small either way."""
    folder = KITCHEN_LOG.parent
    pair = [str(folder / "cloud_bin_0.ply"), str(folder / "cloud_bin_4.ply")]
    for extra in ([], ["--gt-fragments", "0", "4"]):
        assert main(["register", *pair, "--gt", str(KITCHEN_LOG), *extra, "--json", "-"]) == 0
        captured = capsys.readouterr()
        errors = json.loads(captured.out)["errors"]
        assert errors["rotation_error_deg"] < 5.0 and errors["translation_error"] < 0.2, errors
        assert "inverse of --gt" not in captured.err


def test_an_old_option_name_still_works_hidden_and_says_the_new_one(tmp_path, capsys):
    assert main(["demo", "--model", "vrnet-pv-upc-rcp", "--pairs", "1", "--out", str(tmp_path / "d.png")]) == 0
    captured = capsys.readouterr()
    assert "--model is now --checkpoint" in captured.err and "model vrnet-pv-upc-rcp" in captured.out
    from vrnet_ext.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["demo", "--help"])
    assert "--model" not in capsys.readouterr().out


def test_a_plane_and_a_corridor_are_reported_as_undetermined_and_real_rooms_are_not():
    """A plane turned by 40 degrees comes back with a warning naming the three free directions
    (rotation about its normal, translation along it); a corridor, the translation along it; the
    room corner, none."""
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (20_000, 2)), 0.0005 * rng.normal(size=20_000)]
    turn = to_homogeneous(Rotation.from_euler("z", 40, degrees=True).as_matrix(), np.zeros(3))
    result = register(plane, apply(turn, plane), method="icp", icp_settings=IcpSettings(points=5000))
    (note,) = [w for w in result.warnings if "does not determine" in w]
    assert "3 of the transform's 6 directions" in note and "rotation about (0.00, 0.00, 1.00)" in note.replace("-", "")
    walls = [np.c_[rng.uniform(-5, 5, 8000), np.full(8000, side), rng.uniform(0, 2, 8000)] for side in (-1.0, 1.0)]
    corridor = np.concatenate([*walls, np.c_[rng.uniform(-5, 5, 8000), rng.uniform(-1, 1, 8000), np.zeros(8000)]])
    result = register(corridor, corridor + [0.3, 0.0, 0.0], method="icp", icp_settings=IcpSettings(points=8000))
    (note,) = [w for w in result.warnings if "does not determine" in w]
    assert "1 of the transform's 6 directions (translation along (1.00" in note.replace("-", "")
    src = room()
    assert not [w for w in register(src, apply(motion(5.0, [0.1, 0.0, 0.0]), src), method="icp").warnings
                if "does not determine" in w]


@pytest.mark.parametrize("count", [6000, 8000, 10_000])
def test_clouds_of_identical_points_are_refused_naming_the_argument(count):
    with pytest.raises(ValueError, match=f"src: all {count} points coincide"):
        register(np.full((count, 3), 0.1), room(), method="icp")


def test_one_far_point_does_not_make_a_room_a_line():
    src = np.vstack([room(), [[1e4, 0.0, 0.0]]])
    result = register(src, src + [0.05, 0.0, 0.0], method="icp", icp_settings=IcpSettings(points=3000))
    assert not [w for w in result.warnings if "line" in w], result.warnings
    line = np.c_[np.linspace(0, 10, 5000), np.zeros((5000, 2))] + 1e-6 * np.random.default_rng(1).normal(size=(5000, 3))
    assert any("src lies on a line" in w for w in register(line, line + [0.05, 0, 0], method="icp").warnings)


def test_sparse_clouds_are_refined_at_their_spacing_and_a_finer_voxel_names_the_remedy():
    """Clouds sparser than ICP's point count asks for (they came downsampled): the voxel chosen is
    their spacing, so the fit counts the points within reach of a neighbour; a ``voxel_size`` given
    finer than that gets a low-fitness note that is not taken for a doubtful result: it names the
    clouds' spacing and the voxel size that fits it."""
    src, tgt = room(seed=0), apply(motion(3.0, [0.02, 0.0, 0.0]), room(seed=1))
    result = register(src, tgt, method="icp")
    assert result.fitness > 0.5 and not [w for w in result.warnings if w.startswith("low fitness")], result.warnings
    fine = register(src, tgt, method="icp", icp_settings=IcpSettings(voxel_size=point_spacing(tgt) / 5))
    (note,) = [w for w in fine.warnings if w.startswith("low fitness")]
    assert "point spacing" in note and "voxel_size=" in note and "may be wrong" not in note, note
    spacing = float(note.split("voxel_size=")[1])
    refined = register(src, tgt, method="icp", icp_settings=IcpSettings(voxel_size=spacing))
    assert refined.fitness > 0.5 and not [w for w in refined.warnings if w.startswith("low fitness")]


@pytest.mark.parametrize("method", GLOBAL_ESTIMATORS)
@pytest.mark.parametrize("budgeted", [False, True])
def test_every_method_runs_on_each_device_with_and_without_a_budget(method, budgeted, device):
    """register() with every built-in method, on the CPU and (with a GPU) on CUDA, with no budget and
    with one (the process's own memory; on a GPU the host's), registers a room turned by 10 degrees,
    the default twice with the same transform bit for bit; a budget below what the process already
    holds is refused naming max_memory."""
    from vrnet_ext.registration.budget import MB, MemoryBudgetError, resident_mb

    src = room(6000)
    truth = motion(10.0, [0.2, -0.1, 0.05])
    budget = int((resident_mb() + 1500) * MB) if budgeted else None
    result = register(src, apply(truth, src), method=method, device=device, max_memory=budget)
    errors = transform_errors(result.T_target_source, truth)
    assert errors["rotation_error_deg"] < 2.0 and errors["translation_error"] < 0.05, (method, errors)
    if method == "auto" and not budgeted:
        again = register(src, apply(truth, src), method=method, device=device)
        np.testing.assert_array_equal(again.T_target_source, result.T_target_source)
    if budgeted:
        with pytest.raises(MemoryBudgetError, match="max_memory"):
            register(src, apply(truth, src), method=method, device=device, max_memory=int(resident_mb() * MB) // 2)


def test_a_gpu_budget_plans_the_gpu_and_moves_whole_scans_to_the_host(monkeypatch):
    """On a CUDA device the plan counts what the process holds there and the GPU's cost of whole
    scans: with room, all on the GPU; with room for the downsampled stages only, the whole scans'
    steps on the host (said in a note); with room for neither, refused at once naming the device."""
    from vrnet_ext.registration import budget
    from vrnet_ext.registration.global_estimators import SpatialConsistency

    cuda = torch.device("cuda")
    monkeypatch.setattr(budget, "held_mb", lambda device=None: 100.0 if budget.on_gpu(device) else 5000.0)
    scans = (10_000_000, 8_000_000)
    whole_mb = budget.GPU_SCAN_BYTES_PER_POINT * scans[0] / budget.MB
    roomy = budget.plan_registration(int((whole_mb + 200) * budget.MB), SpatialConsistency(), *scans, PointCounts(),
                                     cuda)
    assert roomy.scans_on_device and roomy.counts == PointCounts() and not roomy.notes
    assert roomy.predicted_peak_mb == pytest.approx(100.0 + budget.MARGIN_MB + whole_mb)
    downsampled_mb = budget.predicted_peak_mb(SpatialConsistency(), scans, PointCounts(), 100.0, cuda, False)
    assert downsampled_mb < 400 < whole_mb
    tight = budget.plan_registration(400 * budget.MB, SpatialConsistency(), *scans, PointCounts(), cuda)
    assert not tight.scans_on_device and tight.predicted_peak_mb == pytest.approx(downsampled_mb)
    assert any("voxel-downsampled on the host" in note for note in tight.notes)
    with pytest.raises(budget.MemoryBudgetError, match="max_memory 110 MB on cuda cannot be met"):
        budget.plan_registration(110 * budget.MB, SpatialConsistency(), *scans, PointCounts(), cuda)
    host = budget.plan_registration(8 * 2 ** 30, SpatialConsistency(), *scans, PointCounts())  # the CPU: as before
    assert host.scans_on_device and host.predicted_peak_mb > 5000.0


def test_the_gpu_cap_is_set_for_the_run_restored_after_and_turns_running_out_into_a_budget_error(monkeypatch):
    from types import SimpleNamespace

    from vrnet_ext.registration import budget

    fractions = []
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: SimpleNamespace(total_memory=8 * 2 ** 30))
    monkeypatch.setattr(torch.cuda, "get_per_process_memory_fraction", lambda device: 0.75)
    monkeypatch.setattr(torch.cuda, "set_per_process_memory_fraction", lambda f, device: fractions.append(f))
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: None)
    with budget.device_memory_cap(torch.device("cuda"), 2 * 2 ** 30):
        assert fractions == [0.25]
    assert fractions == [0.25, 0.75]
    with pytest.raises(budget.MemoryBudgetError, match="max_memory 2048 MB on cuda was reached"):
        with budget.device_memory_cap(torch.device("cuda"), 2 * 2 ** 30):
            raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 3.00 GiB")
    assert fractions[-1] == 0.75
    with budget.device_memory_cap(torch.device("cpu"), 2 * 2 ** 30), budget.device_memory_cap(None, None):
        pass
    assert len(fractions) == 4


@requires_cuda_kernels
def test_cuda_budget_bounds_the_gpu_peak():
    """On the GPU, register() under max_memory stays within it (torch's peak allocation) or is
    refused with MemoryBudgetError; whole scans too large for the budget are downsampled on the host."""
    from vrnet_ext.registration.budget import MB, MemoryBudgetError

    src = room(200_000)
    truth = motion(10.0, [0.2, -0.1, 0.05])
    for budget_mb in (2048, 64, 24):
        torch.cuda.reset_peak_memory_stats()
        try:
            result = register(src, apply(truth, src), device="cuda", max_memory=budget_mb * MB)
        except MemoryBudgetError as error:
            assert "max_memory" in str(error)
            continue
        assert torch.cuda.max_memory_allocated() <= budget_mb * MB, budget_mb
        assert transform_errors(result.T_target_source, truth)["rotation_error_deg"] < 2.0
