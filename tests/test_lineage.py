import pytest
import torch

from conftest import ChairPairs
from vrnet_ext.learning.export import export_pretrained, training_facts
from vrnet_ext.learning.lineage import Lineage, lineage_of
from vrnet_ext.learning.train import TrainConfig, train
from vrnet_ext.model.checkpoints import read_checkpoint


def _run(tmp_path, name, **overrides) -> dict:
    values = dict(out_dir=str(tmp_path / name), progress=False, stage1_epochs=1, stage2_epochs=1)
    cfg = TrainConfig.from_preset("tiny", **dict(values, **overrides))
    train(cfg, datasets=(ChairPairs(8, 0), ChairPairs(4, 1)))
    return read_checkpoint(tmp_path / name / "last.pt")


def _ship(tmp_path, name, run) -> dict:
    """``vrnet export``'s card for ``run`` shipped as ``name``; returns its training section."""
    checkpoint = tmp_path / run / "last.pt"
    training = training_facts(checkpoint, name)
    export_pretrained(checkpoint, tmp_path / "weights" / f"{name}.pt", {"training": training})
    return training


def test_runs_record_their_chain_when_they_start_so_replacing_a_shipped_start_counts_each_run_once(
        tmp_path, monkeypatch):
    """A chain that replaces the shipped model it began from, and goes on from its own run: the
    export counts every run once (following the paths as they are now would count run b twice)."""
    import vrnet_ext.model.pretrained as pretrained

    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path / "weights")
    scratch = _run(tmp_path, "scratch")
    assert scratch["lineage"] == Lineage(None, 0.0).to_dict()
    _ship(tmp_path, "base", "scratch")
    base_seconds = round(scratch["train_seconds"], 1)

    b = _run(tmp_path, "b", features_from=str(tmp_path / "weights" / "base.pt"))
    assert b["lineage"] == {"starting_point": "base", "seconds": 0.0,
                            "start_training": {"starting_point": None, "runs_seconds": base_seconds}}
    _ship(tmp_path, "base", "b")  # replaces the file b started from
    c = _run(tmp_path, "c", features_from=str(tmp_path / "b" / "last.pt"))
    assert c["lineage"] == dict(b["lineage"], seconds=b["train_seconds"])
    training = _ship(tmp_path, "base", "c")
    assert training["starting_point"] is None
    expected = c["train_seconds"] + b["train_seconds"] + base_seconds
    assert training["runs_seconds"] == pytest.approx(expected, abs=0.11)
    assert pretrained.training_seconds("base") == pytest.approx(expected, abs=0.11)

    resumed = _run(tmp_path, "c", features_from=str(tmp_path / "weights" / "base.pt"), stage2_epochs=2,
                   resume=str(tmp_path / "c" / "last.pt"))
    assert resumed["epoch"] == 1 and resumed["lineage"] == c["lineage"]  # recorded at the start, kept on resume


def test_a_run_without_a_record_is_followed_back_by_path(tmp_path):
    state = _run(tmp_path, "old")
    del state["lineage"]
    torch.save(state, tmp_path / "old.pt")
    child = dict(state, config=dict(state["config"], features_from=str(tmp_path / "old.pt")), train_seconds=2.0)
    assert lineage_of(child, "child") == Lineage(None, 2.0 + state["train_seconds"])


@pytest.mark.parametrize("record", [
    None, [], {"starting_point": "a", "seconds": 1.0},
    {"starting_point": 3, "seconds": 1.0, "start_training": None},
    {"starting_point": "a", "seconds": -1.0, "start_training": None},
    {"starting_point": "a", "seconds": float("nan"), "start_training": None},
    {"starting_point": "a", "seconds": True, "start_training": None},
    {"starting_point": "a", "seconds": 1.0, "start_training": {"runs_seconds": "many"}},
    {"starting_point": "a", "seconds": 1.0, "start_training": {"starting_point": ["x"]}},
    {"starting_point": "a", "seconds": 1.0, "start_training": {"other": 1}},
])
def test_a_malformed_lineage_record_is_refused_naming_the_file(record):
    state = {"config": {"model": {}}, "train_seconds": 1.0, "lineage": record}
    with pytest.raises(ValueError, match="run.pt: malformed 'lineage' record"):
        lineage_of(state, "run.pt")


def test_a_start_with_a_malformed_record_is_refused_naming_the_start(tmp_path):
    from vrnet_ext.learning.lineage import lineage_before

    state = _run(tmp_path, "bad")
    state["lineage"] = {"starting_point": "a", "seconds": -5.0, "start_training": None}
    torch.save(state, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match=f"{tmp_path / 'bad.pt'}: malformed 'lineage' record"):
        lineage_before(str(tmp_path / "bad.pt"), "--features-from")


def test_a_shipped_start_whose_card_holds_no_valid_seconds_is_recorded_as_unknown(tmp_path):
    from vrnet_ext.learning.lineage import lineage_before

    checkpoint = tmp_path / "scratch" / "last.pt"
    _run(tmp_path, "scratch")
    export_pretrained(checkpoint, tmp_path / "odd.pt",
                      {"training": {"starting_point": None, "runs_seconds": float("inf")}})
    lineage = lineage_before(str(tmp_path / "odd.pt"), "--features-from")
    assert lineage == Lineage("odd", 0.0, {"starting_point": None, "runs_seconds": None})
    assert Lineage.from_dict(lineage.to_dict(), "run") == lineage  # the record reads back
