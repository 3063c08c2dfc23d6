"""Checkpoints are untrusted files: bounded, validated, clear errors naming the file."""
import json
import pickle
import subprocess
import sys
import warnings

import pytest
import torch

from vrnet_ext import VRNet, VRNetConfig
from vrnet_ext.model.checkpoints import CheckpointError, read_checkpoint
from vrnet_ext.model.pretrained import load_model
from vrnet_ext.learning.export import export_pretrained

TINY = dict(k=4, dgcnn_channels=[8, 8], emb_dims=16, heads=2, ff_dims=16, walk_channels=[8, 3])


def write_checkpoint(path, model_config=None, weights=None):
    config = VRNetConfig.small(**TINY).to_dict() if model_config is None else model_config
    if weights is None:
        torch.manual_seed(0)
        weights = VRNet(VRNetConfig.from_dict(config)).state_dict()
    torch.save({"model": weights, "config": {"model": config, "setting": "PV", "split": "UPC"}}, path)
    return path


class Payload:
    def __reduce__(self):
        return (print, ("payload ran",))


def hostile_files(tmp_path):
    text = tmp_path / "notes.pt"
    text.write_text("hello")
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    a_list = tmp_path / "list.pt"
    torch.save([1, 2, 3], a_list)
    no_config = tmp_path / "no_config.pt"
    torch.save({"model": {}}, no_config)
    raw_pickle = tmp_path / "payload.pt"
    raw_pickle.write_bytes(pickle.dumps(Payload()))
    torch_pickle = tmp_path / "torch_payload.pt"
    torch.save({"model": Payload(), "config": {"model": {}}}, torch_pickle)
    truncated = tmp_path / "truncated.pt"
    good = write_checkpoint(tmp_path / "good.pt").read_bytes()
    truncated.write_bytes(good[: len(good) // 2])
    return [text, empty, a_list, no_config, raw_pickle, torch_pickle, truncated]


def test_files_that_are_not_checkpoints_raise_a_clear_error(tmp_path, capsys):
    for path in hostile_files(tmp_path):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with pytest.raises(CheckpointError, match="not a vrnet checkpoint") as info:
                read_checkpoint(path)
        assert not caught, [str(w.message) for w in caught]  # the error alone, no warning of torch's beside it
        assert str(path) in str(info.value) and "weights_only=False" not in str(info.value)
    assert "payload ran" not in capsys.readouterr().out


@pytest.mark.parametrize("field, value", [("iterations", 10**6), ("emb_dims", 8192), ("k", 0), ("heads", 10**4),
                                          ("dgcnn_channels", [8] * 100), ("walk_channels", [10**6, 3]),
                                          ("encoder_layers", 500), ("k", "many"), ("negative_slope", float("nan")),
                                          ("irls_iterations", 10**9), ("irls_scale", float("nan")),
                                          ("irls_kernel", "tukey"), ("polish_iterations", 10**9),
                                          ("polish_iterations", "many"), ("rotation_search_polish", -1),
                                          ("rotation_search_icp_starts", 10**6), ("rotation_search_icp_slides", 10**6),
                                          ("rotation_search_icp", "gicp"), ("max_rotation", 0.0),
                                          ("max_rotation", 270.0), ("max_rotation", "wide"),
                                          ("rotation_search_turn_penalty", -0.5),
                                          ("rotation_search_turn_penalty", float("inf")),
                                          ("rotation_search_turn_penalty", "some")])
def test_config_outside_the_limits_is_refused_before_anything_is_built(tmp_path, field, value):
    config = VRNetConfig.small(**TINY).to_dict()
    config[field] = value
    path = write_checkpoint(tmp_path / "big.pt", config, weights={})
    with pytest.raises(CheckpointError, match=str(tmp_path / "big.pt")):
        load_model(path)


def test_weights_that_do_not_match_the_config_are_refused(tmp_path):
    weights = VRNet(VRNetConfig.small(**TINY)).state_dict()
    weights["features.projection.weight"] = torch.zeros(3, 3, 3)
    with pytest.raises(CheckpointError, match="do not match"):
        load_model(write_checkpoint(tmp_path / "bad.pt", weights=weights))
    del weights["features.projection.weight"]
    with pytest.raises(CheckpointError, match="do not match"):
        load_model(write_checkpoint(tmp_path / "missing.pt", weights=weights))


def test_a_valid_checkpoint_and_its_float16_export_load_in_eval_mode(tmp_path):
    path = write_checkpoint(tmp_path / "good.pt")
    model, state = load_model(path)
    assert not model.training and state["config"]["setting"] == "PV"
    shipped = export_pretrained(path, tmp_path / "shipped.pt", {"data": "test"})
    small = read_checkpoint(shipped)
    assert all(v.dtype == torch.float16 for v in small["model"].values() if v.is_floating_point())
    assert small["card"] == {"data": "test"}
    half, _ = load_model(shipped)
    assert all(p.dtype == torch.float32 for p in half.parameters())
    src, tgt = torch.rand(1, 40, 3), torch.rand(1, 40, 3)
    torch.testing.assert_close(half(src, tgt, return_matching=True).matching,
                               model(src, tgt, return_matching=True).matching, atol=2e-2, rtol=0)


def test_cli_reports_a_bad_checkpoint_without_a_traceback(tmp_path, capsys):
    from vrnet_ext.cli import main

    config = VRNetConfig.small(**TINY).to_dict()
    config["iterations"] = 10**6
    path = write_checkpoint(tmp_path / "hang.pt", config, weights={})
    scan = tmp_path / "scan.xyz"
    scan.write_text("\n".join(f"{i} {i * i % 7} {i % 3}" for i in range(50)))
    for command in (["eval", "--checkpoint", str(path)],
                    ["register", str(scan), str(scan), "--checkpoint", str(path)]):
        assert main(command) == 2
        err = capsys.readouterr().err
        assert "iterations" in err and "Traceback" not in err


def test_cli_export_writes_float16_weights_and_a_model_card(tmp_path):
    from conftest import MODELNET_DIR, requires_modelnet  # noqa: F401
    from vrnet_ext.cli import main

    if not (MODELNET_DIR / "modelnet40_1024_train.h5").exists():
        pytest.skip(f"ModelNet40 not found under {MODELNET_DIR}")
    run = tmp_path / "run"
    assert main(["train", "--preset", "tiny", "--data-dir", str(MODELNET_DIR), "--out-dir", str(run),
                 "--no-progress"]) == 0
    test_json = tmp_path / "test.json"
    assert main(["eval", "--checkpoint", str(run / "best.pt"), "--data-dir", str(MODELNET_DIR), "--max-items", "4",
                 "--json", str(test_json)]) == 0
    assert main(["export", str(run / "best.pt"), "tiny-model", "--out-dir", str(tmp_path / "weights"),
                 "--test-json", str(test_json), "--summary", "A smoke-test model.", "--sessions", "1"]) == 0
    shipped = read_checkpoint(tmp_path / "weights" / "tiny-model.pt")
    assert shipped["card"]["training"]["preset"] == "tiny" and shipped["card"]["training"]["sessions"] == 1
    assert shipped["card"]["test"]["pairs"] == 4 and "validation" in shipped["card"]["training"]
    assert shipped["card"]["training"]["rotations"] == "protocol: each Euler angle in [0, 45] degrees"
    assert "data_dir" not in shipped["config"] and "out_dir" not in shipped["config"]
    card = (tmp_path / "weights" / "tiny-model.md").read_text()
    assert "A smoke-test model." in card and "RMSE(R)" in card
    model, _ = load_model(tmp_path / "weights" / "tiny-model.pt")
    assert not model.training
    assert main(["export", str(run / "best.pt"), "x", "--out-dir", str(tmp_path), "--test-json",
                 str(tmp_path / "missing.json")]) == 2
    assert json.loads(test_json.read_text())["rotations"] == "protocol"  # the run's range (the preset's)
    val_json = tmp_path / "val.json"  # the run's validation pairs: for choosing, never for a card
    assert main(["eval", "--checkpoint", str(run / "best.pt"), "--data-dir", str(MODELNET_DIR), "--max-items", "4",
                 "--partition", "val", "--json", str(val_json), "--no-progress"]) == 0
    val_result, test_result = json.loads(val_json.read_text()), json.loads(test_json.read_text())
    assert val_result["partition"] == "val" and test_result["partition"] == "test"
    assert val_result["RMSE(R)"] != test_result["RMSE(R)"]  # other shapes
    assert main(["export", str(run / "best.pt"), "x", "--out-dir", str(tmp_path), "--test-json", str(val_json)]) == 2
    turned_json = tmp_path / "test_so3.json"  # a card's test table holds the paper's protocol only
    turned_json.write_text(json.dumps({**json.loads(test_json.read_text()), "rotations": "so3"}))
    assert main(["export", str(run / "best.pt"), "x", "--out-dir", str(tmp_path), "--test-json", str(turned_json)]) == 2
    # shipped weights re-exported with another robust solve: the card kept, the test measured with it
    shipped_path = str(tmp_path / "weights" / "tiny-model.pt")
    solve_flags = ["--irls-iterations", "7", "--irls-kernel", "geman_mcclure", "--irls-scale", "0.5",
            "--second-pass-below", "0.4", "--polish-iterations", "2", "--consistency-radius", "0.05"]
    assert main(["export", shipped_path, "tiny-gm", "--out-dir", str(tmp_path / "weights"), *solve_flags]) == 2
    assert main(["export", shipped_path, "tiny-gm", "--out-dir", str(tmp_path / "weights"), *solve_flags,
                 "--test-json", str(test_json)]) == 2  # measured with the model's own solve
    gm_json = tmp_path / "test_gm.json"
    assert main(["eval", "--checkpoint", shipped_path, "--data-dir", str(MODELNET_DIR), "--max-items", "4",
                 "--json", str(gm_json), *solve_flags]) == 0
    assert main(["export", shipped_path, "tiny-gm", "--out-dir", str(tmp_path / "weights"), *solve_flags,
                 "--test-json", str(gm_json), "--note", "Robust solve retuned."]) == 0
    retuned = read_checkpoint(tmp_path / "weights" / "tiny-gm.pt")
    assert retuned["card"]["summary"] == "A smoke-test model." and retuned["card"]["training"]["sessions"] == 1
    assert retuned["card"]["notes"] == ["Robust solve retuned."]
    assert main(["export", str(tmp_path / "weights" / "tiny-gm.pt"), "tiny-gm2", "--out-dir", str(tmp_path / "weights"),
                 "--note", "Kept.", "--note", "Rotations: old."]) == 0
    assert main(["export", str(tmp_path / "weights" / "tiny-gm2.pt"), "tiny-gm3", "--out-dir", str(tmp_path / "weights"),
                 "--drop-notes", "Rotations:", "--note", "Rotations: new."]) == 0
    assert read_checkpoint(tmp_path / "weights" / "tiny-gm3.pt")["card"]["notes"] == [
        "Robust solve retuned.", "Kept.", "Rotations: new."]
    assert retuned["card"]["test"]["irls_scale"] == 0.5 and retuned["card"]["test"]["irls_iterations"] == 7
    model_config = retuned["config"]["model"]
    assert (model_config["irls_iterations"], model_config["irls_kernel"], model_config["irls_scale"],
            model_config["second_pass_below"], model_config["polish_iterations"], model_config["consistency_radius"]) == (
        7, "geman_mcclure", 0.5, 0.4, 2, 0.05)
    assert retuned["card"]["test"]["second_pass_below"] == 0.4 and retuned["card"]["test"]["polish_iterations"] == 2
    assert "irls_kernel: `geman_mcclure`" in (tmp_path / "weights" / "tiny-gm.md").read_text()
    torch.testing.assert_close(retuned["model"], shipped["model"], rtol=0, atol=0)
    # the search's own options, where the file does not search: its estimates and its test table stand
    assert main(["export", shipped_path, "tiny-sp", "--out-dir", str(tmp_path / "weights"),
                 "--rotation-search-polish", "3", "--rotation-search-centre", "10", "0", "0",
                 "--rotation-search-icp-starts", "64", "--rotation-search-icp-slides", "5",
                 "--rotation-search-icp", "trimmed", "--max-rotation", "90",
                 "--rotation-search-turn-penalty", "0.25"]) == 0
    searching = read_checkpoint(tmp_path / "weights" / "tiny-sp.pt")
    assert searching["config"]["model"]["rotation_search_polish"] == 3
    assert searching["config"]["model"]["rotation_search_icp_starts"] == 64
    assert searching["config"]["model"]["rotation_search_icp_slides"] == 5
    assert searching["config"]["model"]["rotation_search_icp"] == "trimmed"
    assert searching["config"]["model"]["max_rotation"] == 90.0
    assert searching["config"]["model"]["rotation_search_turn_penalty"] == 0.25
    assert searching["card"]["test"] == shipped["card"]["test"]
    assert main(["export", shipped_path, "tiny-sp2", "--out-dir", str(tmp_path / "weights"),
                 "--rotation-search-polish", "3", "--rotation-search-below", "0.1"]) == 2  # it searches: test it
    # a model trained on every setting: eval asks for the setting; the card holds one test per cell
    mixed = torch.load(run / "best.pt", weights_only=False)
    mixed["config"]["setting"] = "mixed"
    torch.save(mixed, tmp_path / "mixed.pt")
    assert main(["eval", "--checkpoint", str(tmp_path / "mixed.pt")]) == 2
    cells = []
    for setting in ("CO", "RS"):
        cells.append(tmp_path / f"eval_{setting}.json")
        assert main(["eval", "--checkpoint", str(tmp_path / "mixed.pt"), "--setting", setting, "--data-dir",
                     str(MODELNET_DIR), "--max-items", "4", "--json", str(cells[-1])]) == 0
    assert main(["export", str(tmp_path / "mixed.pt"), "mixed-model", "--out-dir", str(tmp_path / "weights"),
                 *[a for cell in cells for a in ("--test-json", str(cell))]]) == 0
    card = read_checkpoint(tmp_path / "weights" / "mixed-model.pt")["card"]
    assert set(card["tests"]) == {"CO/UPC", "RS/UPC"} and card["tests"]["RS/UPC"]["pairs"] == 4
    assert "## Test: CO/UPC" in (tmp_path / "weights" / "mixed-model.md").read_text()
    # a file-size limit (as a full disk): one line naming the file, non-zero exit, nothing left behind
    script = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000)); "
              "from vrnet_ext.cli import run; sys.argv = ['vrnet'] + sys.argv[1:]; run()")
    full = tmp_path / "full"
    full.mkdir()
    done = subprocess.run([sys.executable, "-c", script, "export", str(run / "best.pt"), "big", "--out-dir", str(full)],
                          capture_output=True, text=True, timeout=300)
    errors = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 1 and len(errors) == 1, done.stderr
    assert str(full / "big.pt") in errors[0] and "File too large" in errors[0]
    assert not list(full.iterdir())


CRAFTED_LOAD = r"""
import resource, sys, torch
from vrnet_ext.model.checkpoints import CheckpointError
from vrnet_ext.model.pretrained import load_model, weights_path
load_model(weights_path("vrnet-pv-upc-rcp"))  # the model's own size is in the baseline
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
try:
    load_model(sys.argv[1])
    print("loaded")
except CheckpointError as error:
    print("refused:", error)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - before)
"""


@pytest.mark.parametrize("crafted", ["zero_stride", "broadcast_rows", "wrong_dtype", "extra_weight"])
def test_a_crafted_checkpoint_is_refused_before_it_is_expanded(tmp_path, crafted):
    """A shipped model's file with one weight replaced by a float16 tensor of 2^28 elements that
    stores one (zero stride) or one row (a broadcast), or by an integer tensor, or with a weight
    added: loading it is refused naming the file and the weight, and the process's peak grows by at
    most 4x the file's size (widening the crafted tensor to float32 would take 1 GiB)."""
    from vrnet_ext.model.pretrained import weights_path

    state = torch.load(weights_path("vrnet-pv-upc-rcp"), weights_only=True)
    name = next(iter(state["model"]))
    huge = {"zero_stride": torch.zeros(1, dtype=torch.float16).expand(2 ** 28),
            "broadcast_rows": torch.zeros(1, 64, dtype=torch.float16).expand(2 ** 22, 64),
            "wrong_dtype": torch.zeros(state["model"][name].shape, dtype=torch.int64),
            "extra_weight": None}[crafted]
    if huge is None:
        state["model"]["extra.weight"] = torch.zeros(1, dtype=torch.float16).expand(2 ** 28)
    else:
        state["model"][name] = huge
    path = tmp_path / "crafted.pt"
    torch.save(state, path)
    done = subprocess.run([sys.executable, "-c", CRAFTED_LOAD, str(path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    verdict, grown = done.stdout.strip().splitlines()[-2:]
    assert verdict.startswith("refused:") and "crafted.pt" in verdict, verdict
    assert ("extra.weight" if crafted == "extra_weight" else name) in verdict, verdict
    assert int(grown) <= 4 * path.stat().st_size, (crafted, int(grown), path.stat().st_size)


def test_export_names_the_run_it_read_when_that_run_is_out_of_bounds(tmp_path):
    config = dict(VRNetConfig.small(**TINY).to_dict(), iterations=10 ** 6)
    torch.manual_seed(0)
    weights = VRNet(VRNetConfig.small(**TINY)).state_dict()
    run = write_checkpoint(tmp_path / "run.pt", model_config=config, weights=weights)
    with pytest.raises(CheckpointError, match=r"run\.pt: model iterations = 1000000 is outside"):
        export_pretrained(run, tmp_path / "out" / "model.pt", {})
    assert not (tmp_path / "out" / "model.pt").exists()


def test_eval_names_a_bad_device_before_reading_a_checkpoint(capsys):
    """``vrnet eval --device``: auto (the default: CUDA when there is one), else a device this
    machine has; anything else is an error naming the option, not a misleading checkpoint error."""
    import torch

    from vrnet_ext.cli import main
    from vrnet_ext.learning.train import resolve_device

    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == "cpu"
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--device", "nonsense"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "argument --device: not a device name" in err and "not a vrnet checkpoint" not in err


@pytest.mark.parametrize("drawn, largest, centre", [(None, None, 22.5), ("protocol", 30.0, 15.0),
                                                    ("symmetric", 45.0, 0.0), ("so3", None, 0.0)])
def test_a_file_searches_about_the_rotations_it_was_trained_on(tmp_path, drawn, largest, centre):
    config = VRNetConfig.small(**TINY).to_dict()
    del config["rotation_search_centre"]  # as files written before the field
    torch.manual_seed(0)
    weights = VRNet(VRNetConfig.from_dict(config)).state_dict()
    training = {"model": config, "setting": "PV", "split": "UPC"}
    training.update({k: v for k, v in (("rotation_range", drawn), ("train_max_angle", largest)) if v is not None})
    torch.save({"model": weights, "config": training}, tmp_path / "run.pt")
    model, _ = load_model(tmp_path / "run.pt")
    assert model.config.rotation_search_centre == (centre,) * 3
    shipped = export_pretrained(tmp_path / "run.pt", tmp_path / "shipped.pt", {})
    assert read_checkpoint(shipped)["config"]["model"]["rotation_search_centre"] == [centre] * 3  # said, not implied
    named = dict(config, rotation_search_centre=[0.0, 10.0, -5.0])  # a file naming its centre keeps it
    torch.save({"model": weights, "config": dict(training, model=named)}, tmp_path / "named.pt")
    assert load_model(tmp_path / "named.pt")[0].config.rotation_search_centre == (0.0, 10.0, -5.0)


@pytest.mark.parametrize("training", [{"rotation_range": "octant"}, {"train_max_angle": float("nan")},
                                      {"train_max_angle": 400.0}, {"train_max_angle": "45"},
                                      {"model_centre": [0.0, 0.0]}, {"model_centre": [float("nan"), 0.0, 0.0]}])
def test_a_bad_search_centre_or_training_range_is_refused_naming_the_file(tmp_path, training):
    config = VRNetConfig.small(**TINY).to_dict()
    del config["rotation_search_centre"]
    if "model_centre" in training:
        config["rotation_search_centre"] = training.pop("model_centre")
    torch.save({"model": {}, "config": {"model": config, **training}}, tmp_path / "odd.pt")
    with pytest.raises(CheckpointError, match=str(tmp_path / "odd.pt")):
        load_model(tmp_path / "odd.pt")


@pytest.mark.parametrize("value", ["0", "-3", "181", "nan", "wide"])
def test_a_bound_on_the_motion_outside_0_to_180_degrees_is_refused_by_the_command_line(value, capsys):
    from vrnet_ext.cli import main

    with pytest.raises(SystemExit) as info:
        main(["eval", "--max-rotation", value])
    assert info.value.code == 2 and "--max-rotation" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["-0.1", "10.5", "nan", "inf", "heavy"])
def test_a_turn_penalty_outside_0_to_10_is_refused_by_the_command_line(value, capsys):
    from vrnet_ext.cli import main

    with pytest.raises(SystemExit) as info:
        main(["eval", "--rotation-search-turn-penalty", value])
    assert info.value.code == 2 and "--rotation-search-turn-penalty" in capsys.readouterr().err
