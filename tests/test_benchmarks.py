"""The benchmark scripts run and write the documented JSON records (no timing assertions)."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import MODELNET_DIR, help_defaults_are_clean, requires_modelnet

ROOT = Path(__file__).resolve().parents[1]


def run(args, tmp_path):
    result = subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


NOT_SCRIPTS = {"outputs.py", "open3d_pipeline.py"}  # modules the scripts import


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "benchmarks").glob("*.py") if p.name not in NOT_SCRIPTS))
def test_every_benchmark_answers_help_and_names_each_default_once(script, tmp_path):
    text = run([str(ROOT / "benchmarks" / script), "--help"], tmp_path)
    assert text.startswith("usage:") and help_defaults_are_clean(text), text


def test_bench_ops_writes_records(tmp_path):
    out = tmp_path / "ops.json"
    stdout = run([str(ROOT / "benchmarks" / "bench_ops.py"), "--quick", "--only", "svd3x3", "--json", str(out)], tmp_path)
    records = json.loads(out.read_text())
    assert {r["impl"] for r in records} >= {"ext", "torch"}
    for r in records:
        assert {"op", "case", "impl", "median_s", "peak_mb"} <= set(r)
        assert r["median_s"] > 0 and r["peak_mb"] is not None and r["peak_mb"] >= 0
    assert "speedup" in stdout


def test_bench_train_step_runs(tmp_path):
    out = tmp_path / "step.json"
    run([str(ROOT / "benchmarks" / "bench_train_step.py"), "--preset", "tiny", "--steps", "1", "--json", str(out)], tmp_path)
    records = json.loads(out.read_text())
    assert {(r["stage"], r["impl"]) for r in records} == {(1, "ext"), (1, "torch"), (2, "ext"), (2, "torch")}


@requires_modelnet
def test_bench_inference_times_every_variant_on_the_same_pairs(tmp_path):
    out = tmp_path / "inference.json"
    run([str(ROOT / "benchmarks" / "bench_inference.py"), "--batches", "1", "2", "--pairs", "4", "--repeats", "1",
         "--data-dir", str(MODELNET_DIR), "--json", str(out)], tmp_path)
    record = json.loads(out.read_text())
    rows, meta = record["rows"], record["meta"]
    variants = ("torch", "torch, bf16 Transformer", "ext", "ext, bf16 Transformer")
    assert {(r["variant"], r["batch"]) for r in rows} == {(v, b) for v in variants for b in (1, 2)}
    by_variant = {r["variant"]: r for r in rows if r["batch"] == 1}
    assert by_variant["torch"]["vs_reference"] == 1.0 and all(r["pairs_per_s"] > 0 for r in rows)
    assert by_variant["torch, bf16 Transformer"]["vs_same_precision"] == 1.0
    assert abs(by_variant["ext"]["rms_angle_deg"] - by_variant["torch"]["rms_angle_deg"]) < 0.01
    assert abs(by_variant["ext, bf16 Transformer"]["rms_angle_deg"] - by_variant["ext"]["rms_angle_deg"]) < 0.05
    # the count includes the Transformer's attention (6 of them, 2 x 2 N^2 x 128 each: 1.8 GFLOP at N = 768)
    assert meta["reference_gflop_per_pair"] > 1.8 and meta["fp32_matmul_gflop_per_s"] > 0
    assert meta["fp32_bound_pairs_per_s"] == pytest.approx(meta["fp32_matmul_gflop_per_s"] / meta["reference_gflop_per_pair"])
    assert all(r["gflop_per_s"] == pytest.approx(r["pairs_per_s"] * meta["reference_gflop_per_pair"]) for r in rows)


def test_reduced_precision_rounds_as_bfloat16_does_and_only_in_its_scope():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import torch
    from reduced_precision import RoundedProducts, round_mantissa

    x = torch.cat([torch.randn(10000) * 1e3, torch.tensor([float("inf"), -float("inf"), 1 + 2.0 ** -8])])
    assert torch.equal(round_mantissa(x, 7), x.bfloat16().float())
    assert round_mantissa(torch.tensor([1 + 2.0 ** -11, 1 + 3 * 2.0 ** -11]), 10).tolist() == [1.0, 1 + 2.0 ** -9]
    a, b = torch.randn(5, 7), torch.randn(7, 3)
    with RoundedProducts(7, "matching"):  # outside the soft matching: untouched
        assert torch.equal(a @ b, torch.mm(a, b))
    plain = torch.mm(a, b)
    with RoundedProducts(7, "all"):
        rounded = torch.mm(a, b)
    assert torch.equal(rounded, torch.mm(a.bfloat16().float(), b.bfloat16().float())) and not torch.equal(rounded, plain)


@requires_modelnet
def test_reduced_precision_writes_a_row_per_variant(tmp_path):
    out = tmp_path / "precision.json"
    run([str(ROOT / "benchmarks" / "reduced_precision.py"), "--max-items", "2", "--data-dir", str(MODELNET_DIR),
         "--json", str(out)], tmp_path)
    rows = json.loads(out.read_text())["rows"]
    assert [r["precision"] for r in rows] == ["fp32", "tf32 matching", "tf32 DGCNN",
                                              "tf32 Transformer", "tf32 walk", "tf32 transforms as products", "tf32",
                                              "tf32, transforms as products", "bf16 Transformer (autocast)",
                                              "bf16 matching", "bf16"]
    assert rows[-1]["RMSE(R)"] != rows[0]["RMSE(R)"]  # bfloat16 everywhere moves the estimates
    assert all(r["pairs"] == rows[0]["pairs"] > 0 and r["RMSE(R)"] >= 0 for r in rows)


def test_knn_proof_model_fails_where_the_kernel_must_scan_whole():
    """The model of the tensor-core kNN's proof (benchmarks/knn_proof_rate.py) on the emulator tests' cases:
    near-ties finer than the products' error bound, or rows crowded into one lane, are not proven; random
    rows are."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import torch
    from knn_proof_rate import proven_rows
    from synthetic import lane_crowded_features, rounding_biased_features

    generator = torch.Generator().manual_seed(0)
    query, ref = rounding_biased_features(64, generator)
    assert not proven_rows(query[0], ref[0], 20).any()
    query, ref = lane_crowded_features(64, generator)
    assert not proven_rows(query[0], ref[0], 20)[0]
    rows = torch.randn(500, 64, generator=generator)
    assert proven_rows(rows, rows, 20).float().mean() > 0.99


@requires_modelnet
def test_knn_proof_rate_writes_a_row_per_width(tmp_path):
    out = tmp_path / "proof.json"
    run([str(ROOT / "benchmarks" / "knn_proof_rate.py"), "--models", "vrnet-pv-upc-rcp", "--pairs", "1",
         "--data-dir", str(MODELNET_DIR), "--fpfh-voxels", "--json", str(out)], tmp_path)
    rows = json.loads(out.read_text())["rows"]
    assert {r["C"] for r in rows} == {32, 64, 128} and {r["passes"] for r in rows} == {1, 3}
    assert all(0 <= r["proven"] <= r["rows"] and r["rows"] > 0 for r in rows)


LIDAR = ROOT.parent / "shared" / "data" / "scenes" / "lidar_pair"
REAL_PAIRS = ROOT.parent / "shared" / "data" / "scenes" / "real_pairs"


@pytest.mark.skipif(not (REAL_PAIRS / "MANIFEST.tsv").exists(), reason=f"real pairs not found under {REAL_PAIRS}")
def test_bench_global_fit_times_both_fits_on_the_same_descriptors(tmp_path):
    out = tmp_path / "fit.json"
    run([str(ROOT / "benchmarks" / "bench_global_fit.py"), "--max-pairs", "1", "--seeds", "1", "--json", str(out),
         "--markdown", str(tmp_path / "fit.md")], tmp_path)
    result = json.loads(out.read_text())
    assert [r["method"] for r in result["rows"]] == ["sc2", "fpfh"] and result["ratio"] > 0
    assert {r["method"] for r in result["records"]} == {"sc2", "fpfh"} and (tmp_path / "fit.md").exists()


@pytest.mark.skipif(not (LIDAR / "source.ply").exists(), reason=f"LiDAR pair not found under {LIDAR}")
def test_bench_register_device_compares_with_the_cpu_in_the_same_run(tmp_path):
    from conftest import DATA_DIR

    if not (DATA_DIR / "scenes" / "3dmatch_redkitchen").exists():
        pytest.skip(f"kitchen scans not found under {DATA_DIR / 'scenes'}")
    run([str(ROOT / "benchmarks" / "bench_register_device.py"), "--data", str(DATA_DIR / "scenes"), "--pairs",
         "kitchen 4->0", "--repeats", "1", "--json", "device.json", "--markdown", "device.md"], tmp_path)
    (row,) = json.loads((tmp_path / "device.json").read_text())["rows"]
    assert row["method"] == "default" and row["repeatable"] and row["vs_cpu_rotation_deg"] == 0.0
    assert row["truth"]["rotation_error_deg"] < 5 and row["peak_gpu_mb"] is None
    assert "kitchen 4->0 | default" in (tmp_path / "device.md").read_text()


def test_bench_device_budget_records_each_budget(tmp_path):
    run([str(ROOT / "benchmarks" / "bench_device_budget.py"), "--points", "50000", "--budgets", "4GB", "1MB",
         "--json", "budget.json", "--markdown", "budget.md"], tmp_path)
    roomy, tiny = json.loads((tmp_path / "budget.json").read_text())["rows"]
    assert roomy["outcome"] == "registered" and roomy["within"] and roomy["errors"]["rotation_error_deg"] < 1
    assert tiny["outcome"] == "refused" and "max_memory 1 MB cannot be met" in tiny["message"] and tiny["within"] is None
    assert "| 4096 | registered |" in (tmp_path / "budget.md").read_text()


def test_bench_register_batch_on_synthetic_pairs(tmp_path):
    run([str(ROOT / "benchmarks" / "bench_register_batch.py"), "--synthetic", "2", "--no-singles", "--processes", "2",
         "--json", "batch.json"], tmp_path)
    record = json.loads((tmp_path / "batch.json").read_text())
    assert record["pairs"] == 2 and record["synthetic"] and record["recall"] == 1.0
    assert list(record["seconds"]) == ["register-batch", "torchrun, 2 processes x 1 thread"]
    assert record["identical"] == {"torchrun = register-batch": True}


def test_bench_large_scene_and_bench_register_run_on_the_lidar_pair(tmp_path):
    run([str(ROOT / "benchmarks" / "bench_large_scene.py"), "--pairs", "LiDAR", "--methods", "fpfh", "--budgets", "2GB",
         "--skip-synthetic", "--memory-sizes", "1000", "--json", "large.json", "--markdown", "large.md"], tmp_path)
    record = json.loads((tmp_path / "large.json").read_text())
    (lidar,) = record["runs"]
    assert lidar["success"] and lidar["peak_rss_mb"] < 2048, lidar
    assert record["soft_match_memory"][0]["streamed_mb"] is not None
    run([str(ROOT / "benchmarks" / "bench_register.py"), "--pairs", "LiDAR", "--repeats", "1", "--estimators",
         "point_to_point", "--json", "register.json", "--markdown", "register.md"], tmp_path)
    summary = json.loads((tmp_path / "register.json").read_text())["summary"]
    ours = [e for e in summary if e["implementation"].startswith("ours fpfh")]
    assert ours and ours[0]["success"], summary


def test_bench_real_pairs_runs_turned_pairs(tmp_path):
    from conftest import DATA_DIR

    if not (DATA_DIR / "scenes" / "real_pairs" / "MANIFEST.tsv").exists():
        pytest.skip(f"real pairs not found under {DATA_DIR / 'scenes'}")
    run([str(ROOT / "benchmarks" / "bench_real_pairs.py"), "--pairs", "kitti01_0_4", "--seeds", "1", "--methods",
         "default", "--extra-rotation", "180", "--out-dir", str(tmp_path)], tmp_path)
    record = json.loads((tmp_path / "real_pairs.json").read_text())
    (only,) = record["runs"]
    assert only["method"] == "default" and only["subset"] == "KITTI" and "rotation_error_deg" in only, only
    assert {row["subset"] for row in record["summary"]} >= {"KITTI", "unseen", "all"}
    assert (tmp_path / "real_pairs.png").stat().st_size > 0 and (tmp_path / "real_pairs.md").exists()


@pytest.mark.skipif(not (LIDAR / "source.ply").exists(), reason=f"LiDAR pair not found under {LIDAR}")
def test_bench_memory_plan_predicts_at_least_the_measured_peak(tmp_path):
    run([str(ROOT / "benchmarks" / "bench_memory_plan.py"), "--pairs", "LiDAR", "--methods", "icp",
         "--json", "plan.json", "--markdown", "plan.md"], tmp_path)
    rows = json.loads((tmp_path / "plan.json").read_text())["rows"]
    assert [r["counts"] for r in rows] == ["default", "smallest", "large"]
    for row in rows:  # a budget the plan accepts must hold: no prediction below the measured peak
        assert row["predicted_mb"] >= row["peak_mb"], row
        assert set(row["predicted_stages_mb"]) == {"global", "preparation", "iterations"}
        if sys.platform.startswith("linux"):  # each stage measured on its own
            assert set(row["measured_stages_mb"]) == {"global", "preparation", "iterations"}, row
    summary = json.loads((tmp_path / "plan.json").read_text())["summary"]
    assert summary["planned_rows"] == 3 and summary["smallest_ratio"][0] >= 1.0
    assert "at the smallest counts" in (tmp_path / "plan.md").read_text()


@requires_modelnet
@pytest.mark.parametrize("ablation", ["iterations", "outliers", "matches", "ransac"])
def test_ablations_write_json_and_png(tmp_path, ablation):
    run([str(ROOT / "benchmarks" / "ablations.py"), ablation, "--max-items", "2", "--batch-size", "2",
         "--data-dir", str(MODELNET_DIR), "--out-dir", str(tmp_path)], tmp_path)
    result = json.loads((tmp_path / f"ablation_{ablation}.json").read_text())
    assert result["pairs"] == 2 and len(result["rows"]) == (6 if ablation == "iterations" else 5)
    assert (tmp_path / f"ablation_{ablation}.png").stat().st_size > 10_000


def test_modelnet40_summary_takes_each_cells_serving_model_and_its_newest_measurement(tmp_path):
    """Dated measurements of CO / UPC by the model that serves it: the one naming its current weights
    and solve beats newer ones that name neither, one naming other weights or another solve is stale;
    a measurement of a model that does not serve a cell is ignored; unmeasured cells say so."""
    from vrnet_ext.model.pretrained import model_for

    serving = model_for("CO", "UPC")
    errors = {"RMSE(R)": 0.05, "MAE(R)": 0.01, "RMSE(t)": 2e-4, "MAE(t)": 3e-5}
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from modelnet40_tables import solve_options, weights_digest

    current, solve = weights_digest(serving), solve_options(serving)
    other_solve = dict(solve, irls_scale=solve["irls_scale"] * 2)
    for day, scale, model, weights, solved in (
            ("2026-01-00", 1.0, serving, current, solve), ("2026-01-01", 10.0, serving, None, None),
            ("2026-01-02", 3.0, serving, current, None),  # no solve named: the Cauchy one at 3 medians
            ("2026-01-03", 0.1, "another-model", None, None),
            ("2026-01-04", 0.5, serving, "0" * 16, solve),  # other weights: stale
            ("2026-01-05", 0.2, serving, current, other_solve)):  # another solve: stale
        (tmp_path / "results" / day).mkdir(parents=True)
        cell = {"model": model, "setting": "CO", "split": "UPC", "pairs": 2468,
                "methods": {"vrnet": {k: v * scale for k, v in errors.items()}}}
        if weights:
            cell["weights"] = weights
        if solved:
            cell["solve"] = solved
        (tmp_path / "results" / day / "modelnet40_tables_x.json").write_text(json.dumps({"results": [cell]}))
    run([str(ROOT / "benchmarks" / "modelnet40_summary.py"), "--results", str(tmp_path / "results"),
         "--json", "summary.json", "--png", "summary.png"], tmp_path)
    cells = {(c["setting"], c["split"]): c for c in json.loads((tmp_path / "summary.json").read_text())["cells"]}
    assert len(cells) == 12
    co = cells[("CO", "UPC")]
    assert co["model"] == serving and co["ours"]["RMSE(R)"] == 0.05 and co["reached"] == 4
    assert co["ours"]["source"].endswith("2026-01-00/modelnet40_tables_x.json")
    assert all("ours" not in c for key, c in cells.items() if key != ("CO", "UPC"))
    assert (tmp_path / "summary.png").stat().st_size > 10_000


def test_modelnet40_summary_skips_partial_view_measurements_of_other_views(tmp_path):
    """A PV cell measured on pairs cut another way (no ``views``, or other ones) is stale, however new;
    a CO cell does not depend on views; a cell measured on other rotations than the protocol's is
    never the paper's comparison."""
    from vrnet_ext.data.protocol import VIEW_PROTOCOL
    from vrnet_ext.model.pretrained import model_for

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from modelnet40_tables import solve_options

    errors = {"RMSE(R)": 0.3, "MAE(R)": 0.05, "RMSE(t)": 2e-3, "MAE(t)": 3e-4}
    for day, scale, views, rotations in (("2026-01-00", 1.0, VIEW_PROTOCOL, None), ("2026-01-01", 2.0, None, None),
                                         ("2026-01-02", 3.0, "another cut", "protocol"),
                                         ("2026-01-03", 0.1, VIEW_PROTOCOL, "so3")):
        (tmp_path / "results" / day).mkdir(parents=True)
        results = [{"model": model_for(setting, "UPC"), "setting": setting, "split": "UPC", "pairs": 10,
                    "solve": solve_options(model_for(setting, "UPC")),
                    "methods": {"vrnet": {k: v * scale for k, v in errors.items()}}} for setting in ("PV", "CO")]
        for cell in results:
            if views:
                cell["views"] = views
            if rotations:
                cell["rotations"] = rotations
        (tmp_path / "results" / day / "modelnet40_tables_x.json").write_text(json.dumps({"results": results}))
    run([str(ROOT / "benchmarks" / "modelnet40_summary.py"), "--results", str(tmp_path / "results"),
         "--json", "summary.json"], tmp_path)
    cells = {(c["setting"], c["split"]): c for c in json.loads((tmp_path / "summary.json").read_text())["cells"]}
    assert cells[("PV", "UPC")]["ours"]["RMSE(R)"] == 0.3
    assert cells[("CO", "UPC")]["ours"]["RMSE(R)"] == pytest.approx(0.9)


@requires_modelnet
def test_modelnet40_tables_draw_the_rotation_range_and_search_only_in_the_vrnet_row(tmp_path):
    common = [str(ROOT / "benchmarks" / "modelnet40_tables.py"), "--models", "vrnet-pv-upc-rcp", "--max-items", "4",
              "--batch-size", "4", "--data-dir", str(MODELNET_DIR), "--methods", "vrnet", "vcp",
              "--rotation-range", "so3"]
    rows = {}
    for below in ("0", "0.5"):
        run(common + ["--rotation-search-below", below, "--json", f"{below}.json", "--markdown", f"{below}.md"],
            tmp_path)
        (rows[below],) = json.loads((tmp_path / f"{below}.json").read_text())["results"]
        assert rows[below]["rotations"] == "so3" and rows[below]["solve"]["rotation_search_below"] == float(below)
        assert "rotations: so3" in (tmp_path / f"{below}.md").read_text()
    assert rows["0"]["methods"]["vcp"]["RMSE(R)"] == rows["0.5"]["methods"]["vcp"]["RMSE(R)"]  # one pass, no search
    assert rows["0"]["methods"]["vrnet"]["turned_share"] == 0 < rows["0.5"]["methods"]["vrnet"]["turned_share"]
    assert rows["0.5"]["methods"]["vrnet"]["RMSE(R)"] < rows["0"]["methods"]["vrnet"]["RMSE(R)"]
    run(common + ["--rotation-search-below", "0.5", "--swap", "--json", "swap.json", "--markdown", "swap.md"], tmp_path)
    (swapped,) = json.loads((tmp_path / "swap.json").read_text())["results"]
    assert swapped["swapped"] and "swapped: target onto source" in (tmp_path / "swap.md").read_text()
    for row in (rows["0.5"], swapped):  # the ground truth of either direction: every pair registered
        assert row["methods"]["vrnet"]["RMSE(R)"] < 1.0, row


@requires_modelnet
def test_rotation_search_criteria_scores_every_start_on_validation_pairs(tmp_path):
    run([str(ROOT / "benchmarks" / "rotation_search_criteria.py"), "--models", "vrnet-pv-upc-rcp", "--pairs", "2",
         "--data-dir", str(MODELNET_DIR), "--json", "criteria.json"], tmp_path)
    (row,) = json.loads((tmp_path / "criteria.json").read_text())["rows"]
    assert row["cell"] == "PV / UPC" and row["pairs"] == 2
    assert all(0 <= row[criterion] <= row["oracle"] for criterion in ("consistency", "median_nn", "fitness_0.05"))


def test_modelnet40_rotations_puts_each_cells_estimates_side_by_side(tmp_path):
    """Runs alone and with the search, on two kinds of pairs: one row per cell and kind, both
    estimates in it; a later folder's estimate replaces an earlier one's; a row of two models, or an
    estimate measured twice in one folder, is refused."""
    tables = tmp_path / "tables"
    tables.mkdir()

    def cell(model, rotations, swapped, below, recall):
        return {"model": model, "setting": "PV", "split": "UPC", "pairs": 100, "rotations": rotations,
                "swapped": swapped, "solve": {"rotation_search_below": below},
                "methods": {"vrnet": {"recall(RE<5,TE<0.1)": recall, "RMSE(R)": 90 * (1 - recall),
                                      "seconds_per_pair": 0.02 + below}}}

    for name, cells in (("a", [cell("m", "so3", False, 0.0, 0.2), cell("m", "protocol", True, 0.0, 0.5)]),
                        ("b", [cell("m", "so3", False, 0.1, 1.0), cell("m", "protocol", True, 0.1, 0.99)])):
        (tables / f"{name}.json").write_text(json.dumps({"results": cells}))
    run([str(ROOT / "benchmarks" / "modelnet40_rotations.py"), "--tables", str(tables), "--json", "r.json",
         "--markdown", "r.md", "--note", "a note"], tmp_path)
    rows = {row["pairs_of"]: row for row in json.loads((tmp_path / "r.json").read_text())["rows"]}
    assert set(rows) == {"so3", "protocol, swapped"}
    assert rows["so3"]["alone"]["recall"] == 0.2 and rows["so3"]["search"]["recall"] == 1.0
    assert "| so3 | PV / UPC | `m` | 100 | 20.0% | 100.0% |" in (tmp_path / "r.md").read_text()
    later = tmp_path / "later"  # a re-run of one estimate, in a folder read after the first
    later.mkdir()
    polished = cell("m", "so3", False, 0.2, 0.9)
    polished["solve"].update(polish_iterations=10, rotation_search_polish=30, rotation_search_icp_starts=512,
                             rotation_search_icp_slides=17, rotation_search_icp="trimmed",
                             rotation_search_turn_penalty=0.25)
    (later / "a.json").write_text(json.dumps({"results": [polished]}))
    run([str(ROOT / "benchmarks" / "modelnet40_rotations.py"), "--tables", str(tables), str(later), "--json", "r2.json",
         "--markdown", "r2.md"], tmp_path)
    rows = {row["pairs_of"]: row for row in json.loads((tmp_path / "r2.json").read_text())["rows"]}
    assert rows["so3"]["search"]["recall"] == 0.9 and rows["so3"]["search"]["source"] == "later/a.json"
    assert rows["so3"]["search"]["polish_iterations"] == 10 and rows["so3"]["alone"]["polish_iterations"] == 0
    assert rows["so3"]["search"]["search_polish"] == 30 and rows["so3"]["alone"]["search_polish"] == 0
    assert "| 0 / 10 | 30 | 512 × 17, trimmed | 0.25 |" in (tmp_path / "r2.md").read_text()
    assert rows["so3"]["search"]["turn_penalty"] == 0.25 and rows["so3"]["alone"]["turn_penalty"] == 0
    assert rows["so3"]["alone"]["recall"] == 0.2 and rows["protocol, swapped"]["search"]["recall"] == 0.99
    bounded = tmp_path / "bounded"  # a search given a bound on the motion: a row of its own
    bounded.mkdir()
    told = cell("m", "so3", False, 0.1, 0.95)
    told["solve"]["max_rotation"] = 90.0
    (bounded / "a.json").write_text(json.dumps({"results": [told]}))
    run([str(ROOT / "benchmarks" / "modelnet40_rotations.py"), "--tables", str(tables), str(bounded), "--json",
         "r3.json", "--markdown", "r3.md"], tmp_path)
    rows = {row["pairs_of"]: row for row in json.loads((tmp_path / "r3.json").read_text())["rows"]}
    assert rows["so3, bound 90°"]["search"]["recall"] == 0.95 and "alone" not in rows["so3, bound 90°"]
    assert rows["so3"]["search"]["recall"] == 1.0

    def refused(*folders):
        result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "modelnet40_rotations.py"), "--tables",
                                 *map(str, folders)], cwd=tmp_path, capture_output=True, text=True)
        assert result.returncode == 2 and "Traceback" not in result.stderr
        return result.stderr

    (later / "b.json").write_text(json.dumps({"results": [cell("other", "protocol", True, 0.0, 1.0)]}))
    assert "another model" in refused(tables, later)  # beside the first folder's search row of model m
    (tables / "c.json").write_text(json.dumps({"results": [cell("other", "so3", False, 0.1, 1.0)]}))
    assert "measured twice" in refused(tables)


@requires_modelnet
def test_modelnet40_tables_two_passes_leave_the_one_pass_row_and_the_model_as_they_were(tmp_path):
    """``vrnet2`` is a second run of the same network (two passes) beside the one-pass ``vrnet`` row:
    the one-pass row is the same as without it, and the two rows differ."""
    common = [str(ROOT / "benchmarks" / "modelnet40_tables.py"), "--models", "vrnet-pv-upc-rcp", "--max-items", "3",
              "--batch-size", "2", "--data-dir", str(MODELNET_DIR)]
    run(common + ["--methods", "vrnet", "vrnet2", "--json", "both.json", "--markdown", "both.md"], tmp_path)
    run(common + ["--methods", "vrnet", "--json", "one.json", "--markdown", "one.md"], tmp_path)
    (both,) = json.loads((tmp_path / "both.json").read_text())["results"]
    (one,) = json.loads((tmp_path / "one.json").read_text())["results"]
    assert both["methods"]["vrnet"]["RMSE(R)"] == one["methods"]["vrnet"]["RMSE(R)"]
    assert both["methods"]["vrnet2"]["RMSE(R)"] != both["methods"]["vrnet"]["RMSE(R)"]
    assert "VRNet, 2 passes" in (tmp_path / "both.md").read_text()


@requires_modelnet
def test_modelnet40_tables_take_solve_flags_and_keep_the_vcp_row_to_one_pass(tmp_path):
    """``--second-pass-below`` changes the ``vrnet`` row and is recorded in ``solve``; the ``vcp`` row
    is Kabsch on one pass's VCPs either way."""
    common = [str(ROOT / "benchmarks" / "modelnet40_tables.py"), "--models", "vrnet-rs-upc-rcp", "--max-items", "4",
              "--batch-size", "2", "--data-dir", str(MODELNET_DIR), "--methods", "vrnet", "vcp"]
    rows = {}
    for below in ("0", "1"):
        run(common + ["--second-pass-below", below, "--json", f"{below}.json", "--markdown", f"{below}.md"], tmp_path)
        (rows[below],) = json.loads((tmp_path / f"{below}.json").read_text())["results"]
        assert rows[below]["solve"]["second_pass_below"] == float(below)
    assert rows["0"]["methods"]["vcp"]["RMSE(R)"] == rows["1"]["methods"]["vcp"]["RMSE(R)"]
    assert rows["0"]["methods"]["vrnet"]["second_pass_share"] == 0
    assert 0 < rows["1"]["methods"]["vrnet"]["second_pass_share"] <= 1
    assert rows["0"]["methods"]["vrnet"]["RMSE(R)"] != rows["1"]["methods"]["vrnet"]["RMSE(R)"]
    run(common + ["--polish-iterations", "5", "--json", "p.json", "--markdown", "p.md"], tmp_path)
    (polished,) = json.loads((tmp_path / "p.json").read_text())["results"]
    assert polished["solve"]["polish_iterations"] == 5 and rows["0"]["solve"]["polish_iterations"] == 0
    assert polished["methods"]["vcp"]["RMSE(R)"] == rows["0"]["methods"]["vcp"]["RMSE(R)"]
    assert rows["0"]["methods"]["vrnet"]["polished_share"] == 0 < polished["methods"]["vrnet"]["polished_share"]
    assert polished["methods"]["vrnet"]["RMSE(R)"] != rows["0"]["methods"]["vrnet"]["RMSE(R)"]
    # the row goes into a model card: only for weights that solve the way it was measured
    from vrnet_ext.cli import main
    from vrnet_ext.model.checkpoints import read_checkpoint
    from vrnet_ext.model.pretrained import weights_path

    run(common + ["--second-pass-below", "1", "--json", "c.json", "--markdown", "c.md", "--card-json-dir", "cards"],
        tmp_path)
    card_json = str(tmp_path / "cards" / "vrnet-rs-upc-rcp_RS_UPC.json")
    export = ["export", str(weights_path("vrnet-rs-upc-rcp")), "rs", "--out-dir", str(tmp_path / "w"),
              "--test-json", card_json]
    assert main(export + ["--second-pass-below", "0.3"]) == 2
    assert main(export + ["--second-pass-below", "1"]) == 0
    card = read_checkpoint(tmp_path / "w" / "rs.pt")["card"]
    assert card["test"]["RMSE(R)"] == rows["1"]["methods"]["vrnet"]["RMSE(R)"] and card["test"]["pairs"] == 4
    assert card["test_note"].startswith("`modelnet40_tables.py` on 4 ModelNet40 test pairs (RS / UPC")


def test_modelnet40_summary_lists_two_pass_rows_apart_from_the_comparison(tmp_path):
    """A cell measured with one and two passes: the one-pass row decides ``reached``; the two-pass row
    is listed in a table of its own."""
    from vrnet_ext.model.pretrained import model_for

    one_pass = {"RMSE(R)": 0.5, "MAE(R)": 0.05, "RMSE(t)": 1e-3, "MAE(t)": 1e-4}  # CO / UC: above the paper
    two_passes = {k: v / 100 for k, v in one_pass.items()}
    (tmp_path / "results" / "2026-01-00").mkdir(parents=True)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from modelnet40_tables import solve_options

    cell = {"model": model_for("CO", "UC"), "setting": "CO", "split": "UC", "pairs": 2468,
            "solve": solve_options(model_for("CO", "UC")), "methods": {"vrnet": one_pass, "vrnet2": two_passes}}
    (tmp_path / "results" / "2026-01-00" / "modelnet40_tables_x.json").write_text(json.dumps({"results": [cell]}))
    run([str(ROOT / "benchmarks" / "modelnet40_summary.py"), "--results", str(tmp_path / "results"),
         "--json", "summary.json", "--markdown", "summary.md"], tmp_path)
    cells = {(c["setting"], c["split"]): c for c in json.loads((tmp_path / "summary.json").read_text())["cells"]}
    co = cells[("CO", "UC")]
    assert co["reached"] == 0 and co["two_passes_reached"] == 4 and co["two_passes"]["RMSE(R)"] == 0.005
    text = (tmp_path / "summary.md").read_text()
    assert "0 of 12 cells" in text and "with two passes" in text


def test_modelnet40_summary_compares_the_served_estimate_and_lists_one_pass_apart(tmp_path):
    """A model served with a second pass: the measurement naming it decides ``reached``; one of the
    same weights without it is listed as the one-pass row, one naming no second pass counts as one
    pass, and one with another threshold is stale."""
    from vrnet_ext.model.pretrained import model_for

    serving = model_for("RS", "UPC")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from modelnet40_tables import solve_options, weights_digest

    solve = solve_options(serving)
    assert solve["second_pass_below"] > 0, "the shipped ModelNet40 models take a second pass where it is needed"
    # naming no second pass, nor the search's own options (moot where the served model does not search)
    unrecorded = {k: v for k, v in solve.items()
                  if k not in ("second_pass_below", "consistency_radius", "rotation_search_polish")}
    errors = {"RMSE(R)": 1.0, "MAE(R)": 0.1, "RMSE(t)": 1e-3, "MAE(t)": 1e-4}
    for day, scale, solved in (("2026-01-00", 1.0, solve), ("2026-01-01", 3.0, unrecorded),
                               ("2026-01-02", 0.1, dict(solve, second_pass_below=solve["second_pass_below"] / 2))):
        (tmp_path / "results" / day).mkdir(parents=True)
        cell = {"model": serving, "setting": "RS", "split": "UPC", "pairs": 2468, "weights": weights_digest(serving),
                "solve": solved, "methods": {"vrnet": {**{k: v * scale for k, v in errors.items()},
                                                       "second_pass_share": 0.25}}}
        (tmp_path / "results" / day / "modelnet40_tables_x.json").write_text(json.dumps({"results": [cell]}))
    run([str(ROOT / "benchmarks" / "modelnet40_summary.py"), "--results", str(tmp_path / "results"),
         "--json", "summary.json", "--markdown", "summary.md"], tmp_path)
    cells = {(c["setting"], c["split"]): c for c in json.loads((tmp_path / "summary.json").read_text())["cells"]}
    rs = cells[("RS", "UPC")]
    assert rs["ours"]["RMSE(R)"] == 1.0 and rs["reached"] == 4 and rs["one_pass"]["RMSE(R)"] == 3.0
    assert rs["one_pass_reached"] == 2
    text = (tmp_path / "summary.md").read_text()
    assert "| 25 % |" in text and "with one pass only" in text


def test_bench_register_scene_measures_the_kitti_scene_and_the_optimiser(tmp_path):
    from conftest import DATA_DIR

    if not (DATA_DIR / "scenes" / "real_pairs" / "MANIFEST.tsv").exists():
        pytest.skip(f"real pairs not found under {DATA_DIR / 'scenes'}")
    run([str(ROOT / "benchmarks" / "bench_register_scene.py"), "--data", str(DATA_DIR / "scenes" / "real_pairs"),
         "--scenes", "kitti00", "--graph-poses", "60", "--json", "scene.json", "--markdown", "scene.md"], tmp_path)
    record = json.loads((tmp_path / "scene.json").read_text())
    ours = record["scenes"]["kitti00"]["ours"]
    assert ours["errors"]["recall_after"] == 1.0 and ours["errors"]["optimised"]["max_rotation_deg"] < 1.0, ours
    assert record["scenes"]["kitti00"]["truth_fit"]["pairs"] == 4
    assert record["optimiser"]["wrong_dropped"] == record["optimiser"]["wrong_loops"]
    assert "kitti00 | ours" in (tmp_path / "scene.md").read_text()


def test_scene_objectives_refines_the_kitti_scene_every_way(tmp_path):
    from conftest import DATA_DIR

    if not (DATA_DIR / "scenes" / "real_pairs" / "MANIFEST.tsv").exists():
        pytest.skip(f"real pairs not found under {DATA_DIR / 'scenes'}")
    run([str(ROOT / "benchmarks" / "scene_objectives.py"), "--data", str(DATA_DIR / "scenes" / "real_pairs"),
         "--scene", "kitti00", "--rounds", "1", "--json", "objectives.json"], tmp_path)
    record = json.loads((tmp_path / "objectives.json").read_text())
    assert [row["refinement"] for row in record["rows"]] == ["none (pose graph)", "map", "pairwise", "joint"]
    assert all(row["max_rotation_deg"] < 1.0 and len(row["translation"]) == 4 for row in record["rows"]), record
    assert len(record["truth_moves"]) == 4


def test_bench_default_runs_every_method_on_a_cut_pair_and_draws_the_calibration(tmp_path):
    from conftest import DATA_DIR

    if not (DATA_DIR / "scenes" / "real_pairs" / "MANIFEST.tsv").exists():
        pytest.skip(f"real pairs not found under {DATA_DIR / 'scenes'}")
    run([str(ROOT / "benchmarks" / "bench_default.py"), "--data", str(DATA_DIR / "scenes" / "real_pairs"), "--seeds", "1",
         "--sets", "cuts", "scans", "--cuts", "1", "--scans", "1", "--limit", "1", "--json", "default.json",
         "--markdown", "default.md", "--plot", "doubt.png"], tmp_path)
    record = json.loads((tmp_path / "default.json").read_text())
    assert {r["method"] for r in record["runs"]} == {"auto", "sc2", "fpfh", "vrnet"} and len(record["runs"]) == 8
    assert {r["set"] for r in record["runs"]} == {"cuts", "scans"} and (tmp_path / "doubt.png").stat().st_size > 0
    assert [(row["set"], row["seed"]) for row in record["per_seed"]] == [("cuts", 0), ("scans", 0)]


def test_a_synthetic_range_scan_sees_the_near_surface_once_per_pixel():
    """bench_default's range scans: of two parallel planes one behind the other, a camera facing them
    sees the near one only, at most one point per pixel, in its own frame (z along its view)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_default import camera_at, range_scan

    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 201), np.linspace(-0.5, 0.5, 201), [0.0]), -1).reshape(-1, 3)
    near, far = grid + [0.0, 0.0, 1.0], grid + [0.0, 0.0, 1.5]
    camera = camera_at(np.zeros(3), np.array([0.0, 0.0, 1.0]), rng)
    pixel = 0.01  # radians: about two grid steps at 1 m
    scan = range_scan(np.concatenate([far, near]), camera, pixel, rng)
    assert np.abs(scan[:, 2] - 1.0).max() < 0.05  # every point on the near plane, depth 1 m along the view
    pixels = (1.0 / pixel) ** 2  # the near plane's area in pixels (about 4 grid points each)
    assert 0.9 * pixels < len(scan) < 1.1 * pixels, len(scan)


@requires_modelnet
def test_finetune_validation_compares_two_models_on_validation_pairs_with_one_solve(tmp_path):
    from vrnet_ext.model.pretrained import weights_path

    run([str(ROOT / "benchmarks" / "finetune_validation.py"), "--before", "vrnet-pv-upc-rcp",
         "--after", str(weights_path("vrnet-pv-upc-rcp")), "--max-items", "3", "--batch-size", "3",
         "--search-below", "0.5", "--irls-iterations", "0", "--data-dir", str(MODELNET_DIR),
         "--json", "val.json", "--markdown", "val.md"], tmp_path)
    record = json.loads((tmp_path / "val.json").read_text())
    assert record["partition"] == "val" and (record["setting"], record["split"]) == ("PV", "UPC")
    assert record["solve"]["irls_iterations"] == 0 and "rotation_search_below" not in record["solve"]
    rows = record["rows"]
    assert [(r["rotations"], r["rotation_search_below"]) for r in rows[:3]] == [("so3", 0.5), ("symmetric", 0.0),
                                                                               ("protocol", 0.0)]
    for before, after in zip(rows[:3], rows[3:]):  # the same weights under both names: the same errors
        assert before["pairs"] == after["pairs"] == 3 and before["model"] != after["model"]
        assert before["rmse_r"] == after["rmse_r"] and before["recall"] == after["recall"]
    assert "| so3 |" in (tmp_path / "val.md").read_text()


@requires_modelnet
def test_polish_validation_polishes_one_forward_per_set_on_validation_pairs(tmp_path):
    from vrnet_ext.model.pretrained import weights_path

    run([str(ROOT / "benchmarks" / "polish_validation.py"), "--models", "vrnet-rs-upc-rcp",
         str(weights_path("vrnet-rs-upc-rcp")), "--steps", "0", "4", "--rotations", "protocol", "so3",
         "--search-below", "0.5", "--search-polish", "0", "3", "--max-items", "3", "--batch-size", "2",
         "--data-dir", str(MODELNET_DIR), "--json", "polish.json", "--markdown", "polish.md"], tmp_path)
    record = json.loads((tmp_path / "polish.json").read_text())
    assert record["partition"] == "val" and record["steps"] == [0, 4] and record["search_polish"] == [0, 3]
    rows = record["rows"]
    assert [(r["rotations"], r["rotation_search_below"], r["rotation_search_polish"], r["polish_iterations"])
            for r in rows[:6]] == [("protocol", 0.0, 0, 0), ("protocol", 0.0, 0, 4), ("so3", 0.5, 0, 0),
                                   ("so3", 0.5, 0, 4), ("so3", 0.5, 3, 0), ("so3", 0.5, 3, 4)]
    assert all(r["cell"] == "RS / UPC" and r["pairs"] == 3 for r in rows)
    for shipped, file in zip(rows[:6], rows[6:]):  # the same weights by name and by path: the same errors
        assert shipped["rmse_r"] == file["rmse_r"] and shipped["model"] != file["model"]
    assert rows[0]["polished_share"] == 0 < rows[1]["polished_share"] and rows[0]["rmse_r"] != rows[1]["rmse_r"]
    assert rows[2]["polished_share"] == 0 < rows[4]["polished_share"]  # the searched pairs' polish marks them
    assert "| RS / UPC | so3 | 0.5 | 3 | 4 | 3 |" in (tmp_path / "polish.md").read_text()


@requires_modelnet
def test_icp_search_validation_puts_each_share_beside_one_forward(tmp_path):
    run([str(ROOT / "benchmarks" / "icp_search_validation.py"), "--models", "vrnet-pvrs-nd-rcp", "--starts", "24",
         "--slides", "3", "--icp", "robust", "trimmed", "--nearer", "1", "0.5", "--rotations", "so3", "--search-below", "1", "--max-items", "3", "--batch-size", "2",
         "--data-dir", str(MODELNET_DIR), "--json", "icp.json", "--markdown", "icp.md"], tmp_path)
    record = json.loads((tmp_path / "icp.json").read_text())
    assert record["partition"] == "val" and record["starts"] == 24 and record["slides"] == 3
    rows = record["rows"]
    assert [(r["icp"], r["nearer"]) for r in rows] == [("robust", 1.0), ("robust", 0.5), ("trimmed", 1.0),
                                                         ("trimmed", 0.5)]
    assert all(r["cell"] == "PV+RS / ND" for r in rows)
    assert all(r["searched"] == 3 and r["pairs"] == 3 for r in rows)  # below 1: every pair searched
    assert rows[1]["replaced"] <= rows[0]["replaced"] <= 3  # a lower share replaces no more pairs
    assert rows[3]["replaced"] <= rows[2]["replaced"] <= 3
    for change in record["changes"]:
        assert change["ratio"] < 1 and abs(change["error_before"] - change["error_after"]) > 5
    assert all(entry["icp"] in ("robust", "trimmed") for entry in record["changes"] + record["wrong"])
    for pair in record["wrong"]:  # every pair left off by either estimate, with the truth's distance beside it
        assert max(pair["error_before"], pair["error_after"]) > 5 and pair["truth_ratio"] > 0
        assert 0 <= pair["truth_turn"] <= 180 and pair["searched"]
    assert "| `vrnet-pvrs-nd-rcp` | PV+RS / ND | trimmed | 24 | 3 | 0.5 | 3 |" in (tmp_path / "icp.md").read_text()
    assert "truth's distance ratio" in (tmp_path / "icp.md").read_text()
