"""register_scene / vrnet register-scene on synthetic rooms cut into overlapping views with known
poses: the poses, the pair cache, bad scans, far-off coordinates, the command's outputs."""
import json
from dataclasses import replace

import numpy as np
import pytest
from synthetic import room_views

from vrnet_ext.cli import main
from vrnet_ext.registration.multiway import SceneOptions, register_scene
from vrnet_ext.registration.scene_metrics import scene_errors


@pytest.fixture(scope="module")
def views():
    return room_views(4, seed=0)


@pytest.fixture(scope="module")
def scene(views):
    return register_scene(views[0])


def test_every_view_is_placed_at_its_pose(views, scene):
    errors = scene_errors(scene, views[1])
    assert scene.placed.all()
    assert errors["optimised"]["max_rotation_deg"] < 0.5 and errors["optimised"]["max_translation"] < 0.02
    assert errors["recall_after"] == 1.0
    np.testing.assert_array_equal(scene.poses[0], np.eye(4))
    assert len(scene.edges) <= 6 and all(edge.kept == (edge.weight >= 0.25) for edge in scene.edges)
    assert len(scene.fused) > 1000 and not scene.warnings


def test_the_pair_cache_resumes_without_registering_again(views, tmp_path, monkeypatch):
    import vrnet_ext.registration.multiway as multiway

    cache = tmp_path / "pairs.jsonl"
    first = register_scene(views[0][:3], cache=cache)
    with open(cache, "a") as sink:
        sink.write('{"key": "unfinish')  # a line a kill cut short
    calls = []
    real = multiway.register_prepared
    monkeypatch.setattr(multiway, "register_prepared", lambda *a: calls.append(a) or real(*a))
    again = register_scene(views[0][:3], cache=cache)
    assert not calls
    np.testing.assert_array_equal(again.poses, first.poses)
    assert len(cache.read_text().splitlines()) == 3
    register_scene(views[0][:3], SceneOptions(register={"seed": 1}), cache=cache)  # other settings: registered again
    assert len(calls) == 3 and len(cache.read_text().splitlines()) == 6
    lines = cache.read_text().splitlines()
    edited = json.loads(lines[0])
    edited["information"] = [[1.0]]  # a record in another shape: registered again
    cache.write_text("\n".join([json.dumps(edited), *lines[1:]]) + "\n")
    register_scene(views[0][:3], cache=cache)
    assert len(calls) == 4


def test_a_file_that_is_not_a_pair_cache_is_refused_and_left_alone(views, tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("my scans\nof the kitchen\n")
    with pytest.raises(ValueError, match=r"cache .*notes.txt: line 1 is not a pair record"):
        register_scene(views[0][:2], cache=notes)
    assert notes.read_text() == "my scans\nof the kitchen\n"


def test_far_from_origin_scans_give_the_same_poses(views, scene):
    offset = np.array([4.5e5, 5.2e6, 120.0])
    shifted = register_scene([view + offset for view in views[0]])
    shift = np.eye(4)
    shift[:3, 3] = offset
    np.testing.assert_allclose(np.linalg.inv(shift) @ shifted.poses @ shift, scene.poses, atol=2e-3)


def test_bad_scans_are_skipped_or_left_unplaced_with_a_warning(views, tmp_path):
    missing = tmp_path / "missing.ply"
    tiny = np.random.default_rng(0).uniform(size=(20, 3))
    elsewhere = np.random.default_rng(1).uniform(size=(3000, 3)) * 0.3 + 50.0  # overlaps no view
    result = register_scene([views[0][0], missing, tiny, views[0][1], elsewhere])
    assert result.placed.tolist() == [True, False, False, True, True]
    text = " ".join(result.warnings)
    assert "skipped missing.ply" in text and "scan 2: 20 points, fewer than 100" in text
    assert "no loop of scans checks" in text and "scan 4 - scan " in text  # the far blob rests on one pair
    with pytest.raises(ValueError, match="at least 2 readable scans"):
        register_scene([views[0][0], missing])
    with pytest.raises(ValueError, match="names has 1 entries for 2 scans"):
        register_scene(views[0][:2], names=["a"])
    with pytest.raises(ValueError, match="SceneOptions.neighbours"):
        SceneOptions(neighbours=0)


def test_a_long_sequence_registers_neighbours_and_loop_candidates(views):
    result = register_scene(views[0], SceneOptions(all_pairs_up_to=2, neighbours=1, loop_candidates=1))
    pairs = {(edge.target, edge.source) for edge in result.edges}
    assert {(0, 1), (1, 2), (2, 3)} <= pairs and len(pairs) < 6
    assert scene_errors(result, views[1])["optimised"]["max_translation"] < 0.05


def test_the_command_writes_poses_cloud_and_map(views, tmp_path, capsys):
    paths = []
    for k, view in enumerate(views[0]):
        paths.append(tmp_path / f"view_{k}.npy")
        np.save(paths[-1], view)
    (tmp_path / "scans.txt").write_text("# the views\n" + "\n".join(p.name for p in paths) + "\n")
    (tmp_path / "poses.txt").write_text("\n".join(" ".join(map(str, pose[:3].ravel())) for pose in views[1]))
    out = tmp_path / "out"
    out.mkdir()
    code = main(["register-scene", "--list", str(tmp_path / "scans.txt"), "--json", str(out / "scene.json"),
                 "--out", str(out / "fused.ply"), "--plot", str(out / "map.png"), "--cache", str(out / "pairs.jsonl"),
                 "--gt-poses", str(tmp_path / "poses.txt"), "--no-progress"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    record = json.loads((out / "scene.json").read_text())
    assert record["names"] == [p.name for p in paths] and len(record["poses"]) == 4
    assert record["errors"]["optimised"]["max_translation"] < 0.02
    assert "100.0% after the pose graph" in printed.out
    for name in ("fused.ply", "map.png"):
        assert (out / name).stat().st_size > 0 and f"wrote {out / name}" in printed.out
    assert len((out / "pairs.jsonl").read_text().splitlines()) == 6
    assert main(["register-scene", str(paths[0]), "--no-progress"]) == 2
    assert "at least 2 scans" in capsys.readouterr().err
    assert main(["register-scene", "--list", str(tmp_path / "nothing.txt")]) == 2
    assert "--list" in capsys.readouterr().err
    (tmp_path / "bad_poses.txt").write_text("1 2 3\n")
    assert main(["register-scene", *map(str, paths), "--gt-poses", str(tmp_path / "bad_poses.txt")]) == 2
    assert "expected 4 poses" in capsys.readouterr().err


def test_the_map_pass_pulls_a_scan_back_onto_the_scans_it_was_registered_with(views):
    """The last pass (``SceneOptions.map_icp``): a scan 2 degrees and 3 cm off while the others sit at
    their true poses is moved back by ICP against the scans it was registered with; the reference and
    a scan registered with none never move; off, nothing runs."""
    from synthetic import motion

    import vrnet_ext.registration.multiway as multiway

    scene = multiway._read_scans(views[0], None, SceneOptions())
    truth = np.linalg.inv(views[1][0]) @ views[1]  # T_first_scan
    off = truth.copy()
    off[2] = motion(2.0, [0.03, -0.01, 0.0], seed=3) @ truth[2]
    off[3] = motion(2.0, [0.03, -0.01, 0.0], seed=4) @ truth[3]
    edges = [multiway.SceneEdge(source=2, target=j, T_target_source=np.eye(4), fitness=1.0, inlier_rmse=0.0,
                                correspondences=1, warnings=[], seconds=0.0, information=np.eye(6), kept=j == 0)
             for j in (0, 1)]
    placed = np.ones(len(truth), dtype=bool)
    result = multiway.SceneResult(names=scene.names, poses=off, initial_poses=off, placed=placed, edges=edges,
                                  fused=np.zeros((0, 3)), voxel=scene.voxel, reach=scene.reach, warnings=[], seconds={})
    refined = multiway._refine_against_map(scene, result, reference=0)
    errors = scene_errors(replace(result, poses=refined), views[1])["scans"]
    assert errors[2]["rotation_error_deg"] < 0.3 and errors[2]["translation_error"] < 0.01, errors[2]
    np.testing.assert_array_equal(refined[0], truth[0])
    np.testing.assert_array_equal(refined[3], off[3])  # registered with none: not refined
    assert "map_icp" in register_scene(views[0][:2]).seconds
    assert "map_icp" not in register_scene(views[0][:2], SceneOptions(map_icp=False)).seconds
