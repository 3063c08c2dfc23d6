"""The shipped weights: present, small, float16, loadable, and working on the paper's partial views."""
import json

import numpy as np
import pytest
import torch

from conftest import MODELNET_DIR
from vrnet_ext import load_pretrained
from vrnet_ext.model.checkpoints import read_checkpoint
from vrnet_ext.data import PairSpec, make_pair
from vrnet_ext.data.procedural import chair
from vrnet_ext.geometry.metrics import rotation_error_deg
from vrnet_ext.model.scene import SCENE_FORMAT
from vrnet_ext.model.pretrained import DEFAULT_MODEL, WEIGHTS_DIR, available, model_card, weights_path


def test_the_default_model_ships_as_small_float16_weights_with_a_card():
    assert DEFAULT_MODEL in available()
    total = sum(path.stat().st_size for path in WEIGHTS_DIR.glob("*.pt"))
    assert total <= 20 * 2**20, f"shipped weights take {total / 2**20:.1f} MB"
    for name in available():
        state = read_checkpoint(weights_path(name))
        assert all(v.dtype == torch.float16 for v in state["model"].values() if v.is_floating_point())
        assert weights_path(name).with_suffix(".md").exists(), f"{name} has no model card"
        card = model_card(name)
        if state.get("format") == SCENE_FORMAT:  # a scene model: its training scans and held-out results
            assert card["training"]["scans"] and card["training"]["steps"] > 0 and card.get("results")
        else:
            # the whole official test split: 2,468 shapes; for UC its 1,266 shapes of labels 20-39
            whole = 1266 if card["training"]["split"] == "UC" else 2468
            tests = card.get("tests") or {f"{card['training']['setting']}/{card['training']['split']}": card["test"]}
            assert card["training"]["setting"] and all(t["pairs"] >= whole for t in tests.values()), name
            solve = state["config"]["model"]  # a test that records its robust solve was measured with the model's
            for test in tests.values():
                for key in ("irls_iterations", "irls_scale", "second_pass_below", "consistency_radius"):
                    assert key not in test or test[key] == solve.get(key), (name, key)


def test_load_pretrained_registers_a_partial_view_pair():
    model = load_pretrained()
    assert not model.training and all(p.dtype == torch.float32 for p in model.parameters())
    rng = np.random.default_rng(7)
    pairs = [make_pair(chair(rng), PairSpec(setting="PV"), rng) for _ in range(4)]
    src = torch.from_numpy(np.stack([p["src"] for p in pairs]))
    tgt = torch.from_numpy(np.stack([p["tgt"] for p in pairs]))
    assert src.shape == tgt.shape == (4, 768, 3)
    with torch.no_grad():
        out = model(src, tgt)
    assert out.rotation.shape == (4, 3, 3) and torch.isfinite(out.translation).all()
    with pytest.raises(ValueError, match="no shipped model"):
        load_pretrained("no-such-model")


@pytest.mark.skipif(not (MODELNET_DIR / "modelnet40_1024_test.h5").exists(), reason="ModelNet40 not found")
def test_the_default_model_is_accurate_on_modelnet40_test_pairs():
    from vrnet_ext.data import ModelNet40Pairs

    data = ModelNet40Pairs(MODELNET_DIR, partition="test", setting="PV", split="UPC", max_items=48)
    batch = {k: torch.stack([data[i][k] for i in range(len(data))]) for k in ("src", "tgt", "rotation")}
    with torch.no_grad():
        out = load_pretrained()(batch["src"], batch["tgt"])
    errors = rotation_error_deg(out.rotation, batch["rotation"])
    assert float(errors.median()) < 3.0, errors


def test_vrnet_demo_runs_without_data(tmp_path, capsys):
    from vrnet_ext.cli import main

    out = tmp_path / "demo.png"
    assert main(["demo", "--pairs", "2", "--out", str(out), "--json", str(tmp_path / "demo.json")]) == 0
    assert out.stat().st_size > 20_000
    result = json.loads((tmp_path / "demo.json").read_text())
    assert len(result["pairs"]) == 2 and "rotation error" in capsys.readouterr().out


def test_eval_picks_the_shipped_model_of_the_setting_and_split(tmp_path, capsys, monkeypatch):
    import vrnet_ext.model.pretrained as pretrained
    from vrnet_ext.cli import main
    from vrnet_ext.model.pretrained import model_for

    assert model_for("PV", "UPC") == "vrnet-pv-upc-rcp" and model_for("PV", "ND") == "vrnet-pv-nd-rcp"
    assert model_for("CO", "UPC") == "vrnet-co-upc-rcp"
    assert model_for("RS", "UPC") == "vrnet-rs-upc-rcp" and model_for("PV+RS", "UPC") == "vrnet-mixed-upc-rcp"
    assert model_for("RS", "UC") == "vrnet-rs-uc-rcp" and model_for("PV+RS", "UC") == "vrnet-pvrs-uc-rcp"
    assert model_for("CO", "UC") == "vrnet-co-uc-rcp" and model_for("PV", "UC") == "vrnet-pv-uc-rcp"
    assert model_for("RS", "ND") == "vrnet-rs-nd-rcp" and model_for("PV+RS", "ND") == "vrnet-pvrs-nd-rcp"
    assert model_for("CO", "ND") == "vrnet-co-nd-rcp"
    with monkeypatch.context() as patched:  # a cell without a shipped model: a clear error
        patched.setattr(pretrained, "WEIGHTS_DIR", tmp_path)
        assert main(["eval", "--setting", "RS", "--split", "ND"]) == 2
        assert "no shipped model is trained for setting RS / split ND" in capsys.readouterr().err
    if not (MODELNET_DIR / "modelnet40_1024_test.h5").exists():
        pytest.skip("ModelNet40 not found")
    out = tmp_path / "e.json"
    assert main(["eval", "--split", "ND", "--max-items", "4", "--data-dir", str(MODELNET_DIR), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["checkpoint"] == "vrnet-pv-nd-rcp"


def test_model_for_prefers_the_model_of_the_setting_then_one_trained_on_every_setting(tmp_path, monkeypatch):
    import vrnet_ext.model.pretrained as pretrained

    for name, setting, split in (("pv-upc", "PV", "UPC"), ("all-upc", "mixed", "UPC"), ("pv-nd", "PV", "ND")):
        torch.save({"model": {}, "config": {"model": {}, "setting": setting, "split": split}},
                   tmp_path / f"{name}.pt")
    torch.save({"model": {}, "config": {"model": {}, "setting": "PV", "split": "UC"},
                "card": {"cells": ["CO/UC", "PV/UC"]}}, tmp_path / "pv-uc.pt")
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path)
    assert pretrained.model_for("PV", "UPC") == "pv-upc"
    assert pretrained.model_for("RS", "UPC") == pretrained.model_for("CO", "UPC") == "all-upc"
    assert pretrained.model_for("PV", "ND") == "pv-nd" and pretrained.model_for("RS", "ND") is None
    assert pretrained.model_for("CO", "UC") == "pv-uc" and pretrained.cells("pv-uc") == ["CO/UC", "PV/UC"]
    torch.save({"model": {}, "config": {"model": {}, "setting": "mixed", "split": "ND"}, "card": {"cells": []}},
               tmp_path / "all-nd.pt")  # a starting point that serves no cell
    assert pretrained.cells("all-nd") == [] and pretrained.model_for("RS", "ND") is None


def test_every_cell_is_served_by_exactly_one_shipped_model():
    """``cells()`` of the shipped models partitions the paper's 12 cells, and ``model_for`` agrees."""
    from vrnet_ext.data.modelnet import SPLITS
    from vrnet_ext.data.protocol import SETTINGS
    from vrnet_ext.model.pretrained import available, cells, model_for

    for setting in SETTINGS:
        for split in SPLITS:
            serving = [name for name in available("vrnet") if f"{setting}/{split}" in cells(name)]
            assert serving == [model_for(setting, split)], (setting, split, serving)


def _run_checkpoint(path, seconds, start=None):
    from vrnet_ext import VRNet, VRNetConfig

    config = VRNetConfig.small(k=4, dgcnn_channels=[8, 8], emb_dims=16, heads=2, ff_dims=16, walk_channels=[8, 3])
    torch.manual_seed(0)
    torch.save({"model": VRNet(config).state_dict(), "train_seconds": seconds,
                "config": {"model": config.to_dict(), "setting": "PV", "split": "UPC", "features_from": start}}, path)
    return path


def test_training_time_follows_warm_starts_back_to_the_shipped_model_they_began_from(tmp_path, monkeypatch):
    """A card counts the runs since its shipped starting point; ``training_seconds`` adds the chain of
    cards; exporting under the starting point's own name takes over its history."""
    import vrnet_ext.model.pretrained as pretrained
    from vrnet_ext.learning.export import export_pretrained, training_facts
    from vrnet_ext.learning.lineage import Lineage, lineage_of

    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path / "weights")
    scratch = _run_checkpoint(tmp_path / "scratch.pt", 100.0)
    assert lineage_of(read_checkpoint(scratch), "scratch") == Lineage(None, 100.0)
    export_pretrained(scratch, tmp_path / "weights" / "base.pt", {"training": training_facts(scratch)})
    first = _run_checkpoint(tmp_path / "first.pt", 20.0, start=str(tmp_path / "weights" / "base.pt"))
    second = _run_checkpoint(tmp_path / "second.pt", 3.0, start=str(first))
    facts = training_facts(second)
    assert (facts["starting_point"], facts["runs_seconds"], facts["train_seconds"]) == ("base", 23.0, 3.0)
    export_pretrained(second, tmp_path / "weights" / "child.pt", {"training": facts})
    assert pretrained.training_seconds("base") == 100.0 and pretrained.training_seconds("child") == 123.0
    assert "training in all: 123 s (runs_seconds plus" in (tmp_path / "weights" / "child.md").read_text()

    again = _run_checkpoint(tmp_path / "again.pt", 7.0, start=str(tmp_path / "weights" / "child.pt"))
    export_pretrained(again, tmp_path / "weights" / "child.pt", {"training": training_facts(again, "child")})
    training = pretrained.model_card("child")["training"]
    assert (training["starting_point"], training["runs_seconds"]) == ("base", 30.0)
    assert pretrained.training_seconds("child") == 130.0

    gone = _run_checkpoint(tmp_path / "gone.pt", 5.0, start=str(tmp_path / "deleted.pt"))
    assert lineage_of(read_checkpoint(gone), "gone") == Lineage(str(tmp_path / "deleted.pt"), 5.0)
    export_pretrained(gone, tmp_path / "weights" / "orphan.pt", {"training": training_facts(gone)})
    assert pretrained.training_seconds("orphan") is None  # its start is not shipped: unknown, not zero
    export_pretrained(scratch, tmp_path / "weights" / "old.pt", {"training": {"train_seconds": 9.0}})
    assert pretrained.training_seconds("old") is None  # a card that never recorded its start
    export_pretrained(scratch, tmp_path / "weights" / "odd.pt",
                      {"training": {"starting_point": ["base"], "runs_seconds": "many"}})
    assert pretrained.training_seconds("odd") is None  # card values of the wrong type: unknown, no crash


def test_a_loop_of_warm_starts_is_refused_naming_the_checkpoint(tmp_path):
    from vrnet_ext.learning.lineage import lineage_of

    loop = _run_checkpoint(tmp_path / "loop.pt", 1.0, start=str(tmp_path / "loop.pt"))
    with pytest.raises(ValueError, match="loop.pt"):
        lineage_of(read_checkpoint(loop), str(loop))


def test_every_shipped_vrnet_card_knows_its_whole_training_time():
    from vrnet_ext.model.pretrained import training_seconds

    for name in available("vrnet"):
        seconds = training_seconds(name)
        assert seconds is not None and seconds >= model_card(name)["training"]["train_seconds"], name
