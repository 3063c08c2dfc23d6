import json
import os
import re
import subprocess
import sys

import pytest
import torch

from conftest import MODELNET_DIR, ChairPairs, requires_modelnet
from vrnet_ext.model.checkpoints import read_checkpoint as load_checkpoint
from vrnet_ext.learning.train import TrainConfig, train


def tiny(tmp_path, name, **overrides):
    values = dict(data_dir=str(MODELNET_DIR), out_dir=str(tmp_path / name), progress=False)
    values.update(overrides)
    return TrainConfig.from_preset("tiny", **values)


def records(run_dir):
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@requires_modelnet
def test_training_lowers_the_loss(tmp_path):
    cfg = tiny(tmp_path, "fit", stage1_epochs=6, stage2_epochs=0, max_train_items=8, setting="CO",
               lr_stage1=3e-3)
    train(cfg)
    losses = [r["train_L0"] for r in records(tmp_path / "fit")]
    assert losses[-1] < losses[0] - 0.01, losses


@requires_modelnet
def test_resume_continues_bit_exactly(tmp_path):
    train(tiny(tmp_path, "straight", stage1_epochs=2, stage2_epochs=1))
    train(tiny(tmp_path, "part", stage1_epochs=1, stage2_epochs=0))
    part = tmp_path / "part" / "last.pt"
    train(tiny(tmp_path, "part", stage1_epochs=2, stage2_epochs=1, resume=str(part)))
    straight = load_checkpoint(tmp_path / "straight" / "last.pt")
    resumed = load_checkpoint(tmp_path / "part" / "last.pt")
    assert straight["step"] == resumed["step"] and straight["stage"] == resumed["stage"] == 2
    for key, value in straight["model"].items():
        assert torch.equal(value, resumed["model"][key]), key
    assert [r["train_loss"] for r in records(tmp_path / "straight")] == [r["train_loss"] for r in records(tmp_path / "part")]


@requires_modelnet
def test_checkpoint_is_weights_only_and_evaluable(tmp_path):
    train(tiny(tmp_path, "run"))
    assert (tmp_path / "run" / "curves.png").stat().st_size > 10_000
    state = torch.load(tmp_path / "run" / "best.pt", weights_only=True)
    assert {"model", "optimizer", "config", "step", "stage"} <= set(state)
    # best.pt is the epoch with the lowest val RMSE(R) over both stages, whatever stage it came from
    rmse = [r["val_RMSE(R)"] for r in records(tmp_path / "run")]
    assert state["best_rmse"] == min(rmse) and state["step"] == records(tmp_path / "run")[rmse.index(min(rmse))]["step"]
    for stage in (1, 2):
        assert torch.load(tmp_path / "run" / f"best_stage{stage}.pt", weights_only=True)["stage"] == stage
    from vrnet_ext.cli import main

    out = tmp_path / "eval.json"
    assert main(["eval", "--checkpoint", str(tmp_path / "run" / "best.pt"), "--max-items", "4",
                 "--data-dir", str(MODELNET_DIR), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["pairs"] == 4 and result["RMSE(R)"] >= 0 and result["inference_seconds_per_pair"] > 0


@requires_modelnet
def test_ddp_two_cpu_processes_keep_identical_replicas(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
           "-m", "vrnet_ext.cli", "train", "--preset", "tiny", "--data-dir", str(MODELNET_DIR),
           "--out-dir", str(tmp_path / "ddp"), "--batch-size", "2", "--no-progress"]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    logged = records(tmp_path / "ddp")
    assert len(logged) == 2 and all(r["world_size"] == 2 for r in logged)
    assert all(r["replica_max_abs_diff"] == 0.0 for r in logged)
    assert logged[0]["step"] == 16 // (2 * 2)  # 16 pairs split over 2 ranks, batch 2 each


def test_cli_flags_override_the_preset():
    from vrnet_ext.cli import build_parser, build_train_config

    args = build_parser().parse_args(["train", "--preset", "small", "--flush-denormal", "0", "--batch-size", "3",
                                      "--classes", "1", "2", "--setting", "PV+RS", "--emb-dims", "64"])
    cfg = build_train_config(args)
    assert cfg.runtime.flush_denormal is False and cfg.schedule.batch_size == 3 and cfg.data.classes == [1, 2]
    assert cfg.data.setting == "PV+RS" and cfg.model["emb_dims"] == 64 and cfg.schedule.stage1_epochs == 3
    default = build_train_config(build_parser().parse_args(["train", "--preset", "small"]))
    assert default.runtime.flush_denormal is True


def test_cli_errors_are_readable(tmp_path, capsys):
    from vrnet_ext.cli import main

    assert main(["train", "--preset", "tiny", "--data-dir", str(tmp_path), "--out-dir", str(tmp_path / "o")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["eval", "--data-dir", str(tmp_path)]) == 2  # the shipped PV / UPC model, but no data there
    assert "not found" in capsys.readouterr().err


@requires_modelnet
def test_resume_from_a_mid_epoch_checkpoint_continues_bit_exactly(tmp_path, monkeypatch):
    import vrnet_ext.learning.train as train_module

    train(tiny(tmp_path, "straight", stage1_epochs=2, stage2_epochs=1))
    mid_epoch = []
    real_save = train_module._save

    def keep_mid_epoch(checkpoint, path):
        if checkpoint["partial"] is not None and checkpoint["partial"]["batches"] == 2:
            copy = tmp_path / f"mid{len(mid_epoch)}.pt"  # the state dict shares the live weights' storage
            torch.save(checkpoint, copy)
            mid_epoch.append(load_checkpoint(copy))
        real_save(checkpoint, path)

    monkeypatch.setattr(train_module, "_save", keep_mid_epoch)
    train(tiny(tmp_path, "part", stage1_epochs=2, stage2_epochs=1, checkpoint_minutes=1e-9))
    monkeypatch.undo()
    assert [c["stage"] for c in mid_epoch] == [1, 1, 2]  # batch 2 of each epoch (4 batches per epoch)
    resume_from = tmp_path / "mid1.pt"  # stage 1, epoch 2, after 2 of its 4 batches
    train(tiny(tmp_path, "resumed", stage1_epochs=2, stage2_epochs=1, resume=str(resume_from)))
    straight = load_checkpoint(tmp_path / "straight" / "last.pt")
    resumed = load_checkpoint(tmp_path / "resumed" / "last.pt")
    assert straight["step"] == resumed["step"]
    for key, value in straight["model"].items():
        assert torch.equal(value, resumed["model"][key]), key
    # the resumed epoch's mean training loss counts the batches done before the stop
    assert [r["train_loss"] for r in records(tmp_path / "resumed")] == [r["train_loss"] for r in records(tmp_path / "straight")][1:]


@requires_modelnet
def test_a_stop_signal_saves_a_mid_epoch_checkpoint_that_resumes_bit_exactly(tmp_path):
    import signal
    import time

    # Every run in its own process with one thread: bit-exactness needs the same summation orders.
    env = dict(os.environ, OMP_NUM_THREADS="1")

    def command(out_dir, *extra):
        return [sys.executable, "-m", "vrnet_ext.cli", "train", "--preset", "tiny", "--data-dir", str(MODELNET_DIR),
                "--out-dir", str(out_dir), "--stage1-epochs", "2", "--stage2-epochs", "0", "--max-train-items", "40",
                "--batch-size", "2", "--no-progress", *extra]

    straight, run = tmp_path / "straight", tmp_path / "run"
    subprocess.run(command(straight), check=True, capture_output=True, env=env, timeout=300)
    process = subprocess.Popen(command(run), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    for _ in range(600):  # wait until the first epoch has ended, then ask for a stop in the second
        if (run / "metrics.jsonl").exists():
            break
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=300)
    stopped = load_checkpoint(run / "last.pt")
    if stopped["partial"] is None:
        pytest.skip("the run finished before the signal arrived")
    # saved and resumable, but not finished: the status says the signal stopped it (128 + 15)
    assert process.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "--resume" in out and stopped["partial"]["epoch"] == 1
    subprocess.run(command(run, "--resume", str(run / "last.pt")), check=True, capture_output=True, env=env,
                   timeout=300)
    expected, resumed = load_checkpoint(straight / "last.pt"), load_checkpoint(run / "last.pt")
    assert expected["step"] == resumed["step"]
    for key, value in expected["model"].items():
        assert torch.equal(value, resumed["model"][key]), key


@requires_modelnet
def test_resume_extends_a_finished_stage_with_this_runs_milestones(tmp_path):
    train(tiny(tmp_path, "run", stage1_epochs=1, stage2_epochs=1, max_train_items=8, batch_size=2))
    last = tmp_path / "run" / "last.pt"
    train(tiny(tmp_path, "run", stage1_epochs=1, stage2_epochs=3, max_train_items=8, batch_size=2,
               lr_milestones=[2], resume=str(last)))
    stage2 = [r for r in records(tmp_path / "run") if r["stage"] == 2]
    lr = TrainConfig.from_preset("tiny").schedule.lr_stage2
    assert [r["epoch"] for r in stage2] == [1, 2, 3]
    # each epoch's record holds the rate it ran with: the milestone at 2 lowers it after two epochs
    assert [r["lr"] for r in stage2] == pytest.approx([lr, lr, lr * 0.1])


def test_freeze_confidence_trains_the_offsets_only():
    from vrnet_ext.model import VRNet, VRNetConfig
    from vrnet_ext.learning.train import set_stage, stage_train_mode

    model = VRNet(VRNetConfig.small(k=6, dgcnn_channels=(16, 16, 32), emb_dims=32, ff_dims=64,
                                    walk_channels=(32, 16, 3), walk_confidence=True, walk_confidence_trunk=True))
    groups = set_stage(model, 2, freeze_confidence=True)
    stage_train_mode(model, 2, freeze_confidence=True)
    assert len(groups) == 1
    assert {id(p) for p in groups[0]["params"]} == {id(p) for p in model.walk.net.parameters()}
    assert not any(p.requires_grad for p in model.walk.confidence_net.parameters())
    assert not any(p.requires_grad for m in model.feature_modules() for p in m.parameters())
    assert model.walk.net.training and not model.walk.confidence_net.training  # BatchNorm statistics kept
    groups = set_stage(model, 2)
    assert len(groups) == 1 and {id(p) for p in groups[0]["params"]} == {id(p) for p in model.walk.parameters()}
    with pytest.raises(ValueError, match="freeze_confidence needs walk_confidence_trunk"):
        TrainConfig.from_preset("tiny", freeze_confidence=True)
    with pytest.raises(ValueError, match="loss_motion must be a finite number >= 0"):
        TrainConfig.from_preset("tiny", loss_motion=-1.0)
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="loss_motion_translation must be a finite number >= 0"):
            TrainConfig.from_preset("tiny", loss_motion_translation=bad)


def test_features_fine_tuned_in_stage_2_form_their_own_group():
    from vrnet_ext.model import VRNet, VRNetConfig
    from vrnet_ext.learning.train import set_stage, stage_train_mode

    model = VRNet(VRNetConfig.small(k=6, dgcnn_channels=(16, 16, 32), emb_dims=32, ff_dims=64,
                                    walk_channels=(32, 16, 3), walk_confidence=True))
    groups = set_stage(model, 2, features_lr=3e-5)
    stage_train_mode(model, 2, features_lr=3e-5)
    features = [p for m in model.feature_modules() for p in m.parameters()]
    assert {id(p) for p in groups[0]["params"]} == {id(p) for p in model.walk.parameters()}
    assert groups[1]["lr"] == 3e-5 and {id(p) for p in groups[1]["params"]} == {id(p) for p in features}
    # the features' weights learn, their BatchNorm statistics stay those the walk is served on
    assert not any(m.training for m in model.feature_modules()) and model.walk.training
    src, tgt = torch.randn(2, 40, 3), torch.randn(2, 40, 3)
    model(src, tgt).translation.sum().backward()  # the estimate reaches the features through the matching
    assert all(p.grad is not None for p in features)
    with pytest.raises(ValueError, match="lr_features_stage2"):
        TrainConfig.from_preset("tiny", lr_features_stage2=-1e-5)


def test_stage_2_fine_tunes_the_features_only_when_asked(tmp_path):
    """Stage 2 leaves the stage-1 features bit for bit by default and moves them with a rate of
    their own; a run resumes only with the same choice (the optimizer's groups differ)."""
    def feature_weights(path):
        state = load_checkpoint(path)["model"]
        return {k: v for k, v in state.items() if not k.startswith("walk.") and v.is_floating_point()}

    runs = {}
    for name, rate in (("frozen", 0.0), ("tuned", 1e-3)):
        cfg = TrainConfig.from_preset("tiny", out_dir=str(tmp_path / name), progress=False, lr_features_stage2=rate)
        train(cfg, datasets=(ChairPairs(8, 0), ChairPairs(4, 1)))
        runs[name] = (feature_weights(tmp_path / name / "best_stage1.pt"), feature_weights(tmp_path / name / "last.pt"))
    before, after = runs["frozen"]
    assert all(torch.equal(before[k], after[k]) for k in before)
    before, after = runs["tuned"]
    assert any(not torch.equal(before[k], after[k]) for k in before if k.endswith("weight"))
    assert all(torch.equal(before[k], after[k]) for k in before if k.endswith(("running_mean", "running_var")))
    with pytest.raises(ValueError, match="lr_features_stage2 0.001, this run with 0.0"):
        train(TrainConfig.from_preset("tiny", out_dir=str(tmp_path / "tuned"), progress=False, stage2_epochs=2,
                                      resume=str(tmp_path / "tuned" / "last.pt")),
              datasets=(ChairPairs(8, 0), ChairPairs(4, 1)))


@requires_modelnet
def test_resuming_or_warm_starting_from_the_wrong_kind_of_file_is_a_named_error(tmp_path):
    """Shipped weights and scene models hold no training state: a ValueError naming the file, no KeyError."""
    from vrnet_ext.model.pretrained import DEFAULT_SCENE_MODEL, weights_path

    shipped, scene = weights_path("vrnet-pv-upc-rcp"), weights_path(DEFAULT_SCENE_MODEL)
    for path in (shipped, scene):
        with pytest.raises(ValueError, match=f"resume: {path}.*not a checkpoint of `vrnet train`"):
            train(tiny(tmp_path, "resume", resume=str(path)))
    with pytest.raises(ValueError, match=f"features_from: {scene} is not a VRNet checkpoint"):
        train(tiny(tmp_path, "warm", features_from=str(scene)))


def test_invalid_options_are_refused_naming_the_argument_and_on_the_command_line_the_flag(capsys):
    from vrnet_ext.cli import main

    for overrides, flag in ((dict(stage1_epochs=-1), "--stage1-epochs"), (dict(seed=-1), "--seed"),
                            (dict(num_points=5000), "--num-points"), (dict(lr_milestones=[-5]), "--lr-milestones"),
                            (dict(loss_l4=float("nan")), "--loss-l4"), (dict(lr_stage2=0.0), "--lr-stage2"),
                            (dict(num_subsampled=2000, num_points=1024), "--num-subsampled"),
                            (dict(train_max_angle=0.0), "--train-max-angle"),
                            (dict(train_max_angle=720.0), "--train-max-angle")):
        name = next(iter(overrides))
        with pytest.raises(ValueError, match=f"^{name} "):
            TrainConfig.from_preset("tiny", **overrides)
        argv = [token for key, value in overrides.items()
                for token in ["--" + key.replace("_", "-"), *map(str, value if isinstance(value, list) else [value])]]
        assert main(["train", "--preset", "tiny", *argv]) == 2
        assert f"error: {flag} " in capsys.readouterr().err


def test_cli_refuses_an_output_file_and_a_missing_gpu_naming_the_flag(tmp_path, capsys):
    from vrnet_ext.cli import main
    from vrnet_ext.cli.common import checkpoint_or_shipped
    from vrnet_ext.model.pretrained import weights_path

    # a shipped model's name stands for its weights file (the path is what the run's config records)
    assert checkpoint_or_shipped("vrnet-pv-upc-rcp") == str(weights_path("vrnet-pv-upc-rcp"))
    existing_checkpoint = tmp_path / "run.pt"
    existing_checkpoint.write_bytes(b"")
    assert checkpoint_or_shipped(str(existing_checkpoint)) == str(existing_checkpoint)

    existing = tmp_path / "a_file"
    existing.write_text("")
    cases = [(["--out-dir", str(existing)], "--out-dir.*is a file"),
             (["--out-dir", str(existing / "sub")], "--out-dir.*not a writable folder"),
             (["--features-from", "no-such-model"], "--features-from.*neither a file nor a shipped model"),
             (["--walk-from", str(tmp_path)], "--walk-from.*neither a file nor a shipped model")]
    if not torch.cuda.is_available():
        cases.append((["--device", "cuda"], "--device.*no CUDA device"))
    for flags, message in cases:
        with pytest.raises(SystemExit) as info:
            main(["train", "--preset", "tiny", *flags])
        assert info.value.code == 2
        assert re.search(message, capsys.readouterr().err)


@requires_modelnet
def test_wider_training_rotations_leave_the_validation_pairs_as_the_protocol_draws_them():
    import numpy as np

    from vrnet_ext.learning.train import _datasets
    from vrnet_ext.geometry.metrics import euler_zyx_deg

    def largest_angle(dataset) -> float:
        return max(float(np.abs(euler_zyx_deg(dataset[i]["rotation"])).max()) for i in range(len(dataset)))

    wide_train, wide_val = _datasets(TrainConfig.from_preset("tiny", data_dir=str(MODELNET_DIR), train_max_angle=90.0))
    train_pairs, val_pairs = _datasets(TrainConfig.from_preset("tiny", data_dir=str(MODELNET_DIR)))
    assert wide_train.spec.max_angle_deg == 90.0 and wide_val.spec.max_angle_deg == 45.0
    assert largest_angle(train_pairs) <= 45.0 + 1e-3 < 60.0 < largest_angle(wide_train)
    for i in range(4):
        assert np.array_equal(wide_val[i]["src"].numpy(), val_pairs[i]["src"].numpy())
        assert np.array_equal(wide_val[i]["rotation"].numpy(), val_pairs[i]["rotation"].numpy())


@requires_modelnet
def test_the_rotation_range_draws_the_training_and_validation_pairs():
    import numpy as np

    from vrnet_ext.learning.train import _datasets
    from vrnet_ext.geometry.metrics import euler_zyx_deg

    def angles(dataset):
        return np.stack([euler_zyx_deg(dataset[i]["rotation"]) for i in range(len(dataset))])

    for pairs in _datasets(TrainConfig.from_preset("tiny", data_dir=str(MODELNET_DIR), rotation_range="symmetric")):
        assert pairs.spec.rotation_range == "symmetric"
        drawn = angles(pairs)
        assert (drawn < 0).any() and np.abs(drawn).max() <= 45.0 + 1e-3
    with pytest.raises(ValueError, match="^rotation_range must be one of"):
        TrainConfig.from_preset("tiny", rotation_range="octant")


def test_train_takes_any_pair_provider(tmp_path):
    """Datasets of one's own (here procedural chairs, no ModelNet40 needed) instead of the config's."""
    cfg = TrainConfig.from_preset("tiny", out_dir=str(tmp_path / "run"), progress=False)
    record = train(cfg, datasets=(ChairPairs(8, 0), ChairPairs(4, 1)))
    assert record["stage"] == 2 and (tmp_path / "run" / "best.pt").exists()
    assert "val_RMSE(R)" in json.loads((tmp_path / "run" / "metrics.jsonl").read_text().splitlines()[-1])


def test_the_config_is_typed_sections_stored_flat_and_read_back():
    from dataclasses import fields

    from vrnet_ext.learning.config import SECTIONS

    names = [f.name for section in SECTIONS.values() for f in fields(section)]
    assert len(names) == len(set(names)), "an option name in two sections"
    cfg = TrainConfig.from_preset("tiny", batch_size=3, setting="PV", loss_l4=5.0, resume="x.pt", num_workers=1)
    assert (cfg.schedule.batch_size, cfg.data.setting, cfg.loss.loss_l4, cfg.start.resume,
            cfg.runtime.num_workers) == (3, "PV", 5.0, "x.pt", 1)
    flat = cfg.to_dict()
    assert set(flat) == set(names) | {"preset", "model"} and flat["batch_size"] == 3
    assert TrainConfig.from_flat(flat) == cfg
    with pytest.raises(ValueError, match=r"unknown training options: \['optimiser'\]"):
        TrainConfig.from_preset("tiny", optimiser="sgd")
    with pytest.raises(ValueError, match="batch_size must be an integer >= 1, got 0"):
        TrainConfig.from_preset("tiny", batch_size=0)


@pytest.mark.parametrize("native", [True, False])
def test_auto_precision_follows_the_cpu_and_resume_keeps_it(tmp_path, monkeypatch, native):
    """--precision auto trains in bf16 only where the CPU multiplies bfloat16 in hardware; the run
    records the precision chosen, and an auto resume on another CPU keeps it."""
    import vrnet_ext.learning.train as train_module

    monkeypatch.setattr(train_module, "device_has_native_bf16", lambda device: native)
    data = (ChairPairs(8, 0), ChairPairs(4, 1))
    run = tmp_path / "run"
    train(TrainConfig.from_preset("tiny", out_dir=str(run), stage2_epochs=0, progress=False), datasets=data)
    chosen = "bf16" if native else "fp32"
    assert json.loads((run / "config.json").read_text())["precision"] == chosen
    assert load_checkpoint(run / "last.pt")["config"]["precision"] == chosen
    monkeypatch.setattr(train_module, "device_has_native_bf16", lambda device: not native)
    train(TrainConfig.from_preset("tiny", out_dir=str(run), progress=False, resume=str(run / "last.pt")),
          datasets=data)
    assert load_checkpoint(run / "last.pt")["config"]["precision"] == chosen


def test_explicit_bf16_on_a_cpu_without_it_warns(tmp_path, monkeypatch):
    import vrnet_ext.learning.train as train_module

    monkeypatch.setattr(train_module, "device_has_native_bf16", lambda device: False)
    cfg = TrainConfig.from_preset("tiny", out_dir=str(tmp_path / "run"), precision="bf16", stage2_epochs=0,
                                  progress=False)
    with pytest.warns(UserWarning, match="precision bf16: this CPU has no bfloat16 matrix products"):
        train(cfg, datasets=(ChairPairs(4, 0), ChairPairs(4, 1)))
    assert json.loads((tmp_path / "run" / "config.json").read_text())["precision"] == "bf16"


class Killed(BaseException):
    """Stands in for SIGKILL: raised instead of one file write, nothing after it runs."""


def test_a_kill_at_any_write_then_resume_gives_the_files_of_an_uninterrupted_run(tmp_path, monkeypatch):
    """A run killed before any one of its checkpoint, best-model or metrics writes, then resumed
    from its ``last.pt`` (or started again when there is none yet), ends with the same models and
    metrics rows as a run never killed, and no hidden temporary files."""
    import vrnet_ext.learning.train as train_module

    writes, kill_at = [], [None]
    save, log = train_module._save, train_module._log

    def write(real, *args):
        if len(writes) == kill_at[0]:
            raise Killed
        writes.append(args[-1].name if isinstance(args[-1], os.PathLike) else "metrics")
        real(*args)

    monkeypatch.setattr(train_module, "_save", lambda checkpoint, path: write(save, checkpoint, path))
    monkeypatch.setattr(train_module, "_log", lambda out_dir, record: write(log, out_dir, record))

    def run(out, **overrides):
        cfg = TrainConfig.from_preset("tiny", out_dir=str(out), progress=False, stage1_epochs=2, stage2_epochs=2,
                                      **overrides)
        return train(cfg, datasets=(ChairPairs(8, 0), ChairPairs(4, 1)))

    def outcome(out):
        models = {name: load_checkpoint(out / name) for name in ("last.pt", "best.pt", "best_stage1.pt",
                                                                 "best_stage2.pt") if (out / name).exists()}
        rows = [{k: v for k, v in json.loads(line).items() if not k.endswith("seconds")}
                for line in (out / "metrics.jsonl").read_text().splitlines()]
        return models, rows

    run(tmp_path / "straight")
    straight_models, straight_rows = outcome(tmp_path / "straight")
    order = list(writes)
    assert order.count("metrics") == 4 and order[-1] == "last.pt"
    for k in range(len(order)):
        out = tmp_path / f"killed_{k}"
        writes.clear()
        kill_at[0] = k
        with pytest.raises(Killed):
            run(out)
        kill_at[0] = None
        (out / ".last.pt.leftover.pt").write_bytes(b"half a checkpoint")
        run(out, resume=str(out / "last.pt")) if (out / "last.pt").exists() else run(out)
        models, rows = outcome(out)
        assert rows == straight_rows, f"kill before write {k} ({order[k]})"
        assert set(models) == set(straight_models), k
        for name, model in models.items():
            assert (model["stage"], model["epoch"], model["step"]) == tuple(straight_models[name][key] for key in
                                                                           ("stage", "epoch", "step")), (k, name)
            assert all(torch.equal(model["model"][p], straight_models[name]["model"][p]) for p in model["model"]), \
                (k, name)
        assert not [p.name for p in out.iterdir() if p.name.startswith(".")], k


def test_every_training_option_is_read_as_its_annotation_says():
    """The parser's type of each `vrnet train` option comes from its section's annotation itself
    (int or float, also inside `X | None`), not from the annotation's text."""
    import argparse
    import typing

    from vrnet_ext.cli import build_parser
    from vrnet_ext.learning.config import SECTIONS

    train_parser = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)][0].choices["train"]
    types = {action.dest: action.type for action in train_parser._actions}
    hints = {name: hint for section in SECTIONS.values() for name, hint in typing.get_type_hints(section).items()}
    assert len(hints) > 30
    for name, hint in hints.items():
        plain = [arg for arg in typing.get_args(hint) if arg is not type(None)] or [hint]
        if name in types and plain[0] in (int, float) and len(plain) == 1:  # (str: also choices, type None)
            assert types[name] is plain[0], (name, hint, types[name])


@requires_modelnet
def test_resuming_a_finished_run_into_another_folder_says_so_and_points_to_its_models(tmp_path, capsys):
    from vrnet_ext.cli import main

    common = ["train", "--preset", "tiny", "--data-dir", str(MODELNET_DIR), "--no-progress"]
    assert main([*common, "--out-dir", str(tmp_path / "a")]) == 0
    capsys.readouterr()
    assert main([*common, "--out-dir", str(tmp_path / "b"), "--resume", str(tmp_path / "a" / "last.pt")]) == 0
    out = capsys.readouterr().out
    assert "holds a finished run" in out and f"--checkpoint {tmp_path / 'a' / 'best.pt'}" in out, out
    assert (tmp_path / "a" / "best.pt").exists()
