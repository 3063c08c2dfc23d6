"""docs/benchmarks.md, assembled from benchmarks/results/ (never edited by hand).

    python benchmarks/benchmarks_page.py > docs/benchmarks.md

Newest results first. A result the benchmark wrote as Markdown beside its JSON is included as it
is; op timings (lists of bench_ops.py records) become one table per file, each op's implementations
side by side with their ratio to the pure-PyTorch reference. tests/test_docs.py checks that
docs/benchmarks.md is exactly this rendering of the results folder.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
# Tables measured before partial views were cut as the paper's (one far point for both clouds).
EARLIER_VIEWS = "; its PV and PV+RS rows on earlier pairs, whose target view had a far point of its own"
TITLES = {  # file stem (without a numbered suffix) -> what wrote it
    "real_pairs": "Real scan pairs (`bench_real_pairs.py`)",
    "real_pairs_turned": "Real scan pairs turned by a further rotation (`bench_real_pairs.py --extra-rotation`)",
    "real_pairs_cross_check": "Real scan pairs, the default with its check by a second estimator beside sc2 and fpfh (`bench_real_pairs.py --methods default sc2 fpfh --seeds 1`)",
    "modelnet40_summary": "ModelNet40, the paper's 12 cells (`modelnet40_summary.py`)",
    "modelnet40_tables": "ModelNet40 tables (`modelnet40_tables.py`)" + EARLIER_VIEWS,
    "modelnet40_tables_nd": "ModelNet40 tables, noisy data (`modelnet40_tables.py`)" + EARLIER_VIEWS,
    "modelnet40_tables_uc": "ModelNet40 tables, unseen categories (`modelnet40_tables.py`)" + EARLIER_VIEWS,
    "modelnet40_tables_cells": "ModelNet40 tables, CO / RS / PV+RS cells (`modelnet40_tables.py --settings CO RS PV+RS`)" + EARLIER_VIEWS,
    "modelnet40_tables_uc_cells": "ModelNet40 tables, every UC cell (`modelnet40_tables.py --models vrnet-mixed-uc-rcp vrnet-pv-uc-rcp`)" + EARLIER_VIEWS,
    "modelnet40_tables_co_upc": "ModelNet40 tables, CO / UPC (`modelnet40_tables.py --models vrnet-co-upc-rcp --methods vrnet vcp`)",
    "modelnet40_tables_co_nd": "ModelNet40 tables, CO / ND (`modelnet40_tables.py --models vrnet-co-nd-rcp --methods vrnet vcp`)",
    "modelnet40_tables_pv_uc": "ModelNet40 tables, PV / UC and CO / UC (`modelnet40_tables.py --models vrnet-pv-uc-rcp --methods vrnet vcp`)" + EARLIER_VIEWS,
    "modelnet40_tables_pv_nd": "ModelNet40 tables, PV / ND (`modelnet40_tables.py --models vrnet-pv-nd-rcp --methods vrnet vcp`)" + EARLIER_VIEWS,
    "modelnet40_tables_uc_views": "ModelNet40 tables, PV / UC and CO / UC on the paper's views (`modelnet40_tables.py --models vrnet-pv-uc-rcp --methods vrnet vcp`)",
    "modelnet40_tables_nd_views": "ModelNet40 tables, PV / ND and PV+RS / ND on the paper's views (`modelnet40_tables.py --models vrnet-pv-nd-rcp vrnet-pvrs-nd-rcp --methods vrnet vcp`)",
    "modelnet40_tables_views_pv": "ModelNet40 tables, PV cells on the paper's views (`modelnet40_tables.py --models vrnet-pv-upc-rcp vrnet-pv-uc-rcp vrnet-pv-nd-rcp --settings PV`)",
    "modelnet40_tables_views_pvrs": "ModelNet40 tables, PV+RS cells on the paper's views (`modelnet40_tables.py --models vrnet-mixed-upc-rcp vrnet-mixed-uc-rcp vrnet-mixed-nd-rcp --settings PV+RS`)",
    "modelnet40_tables_co_uc": "ModelNet40 tables, CO / UC (`modelnet40_tables.py --models vrnet-co-uc-rcp --methods vrnet vcp`)",
    "modelnet40_tables_rs_uc": "ModelNet40 tables, RS / UC (`modelnet40_tables.py --models vrnet-rs-uc-rcp --methods vrnet vcp [vrnet2]`)",
    "modelnet40_tables_pvrs_uc": "ModelNet40 tables, PV+RS / UC (`modelnet40_tables.py --models vrnet-pvrs-uc-rcp --methods vrnet vcp [vrnet2]`)",
    "modelnet40_tables_rs_upc": "ModelNet40 tables, RS / UPC (`modelnet40_tables.py --models vrnet-rs-upc-rcp --methods vrnet vcp vrnet2`)",
    "modelnet40_tables_pvrs_nd": "ModelNet40 tables, PV+RS / ND (`modelnet40_tables.py --models vrnet-pvrs-nd-rcp --methods vrnet vcp vrnet2`)",
    "modelnet40_tables_two_passes": "ModelNet40 tables, two passes (`modelnet40_tables.py --models <the serving models> --methods vrnet2`)",
    "modelnet40_tables_second_pass": "ModelNet40 tables, every cell with a second pass where the RCPs disagree (`modelnet40_tables.py --methods vrnet --second-pass-below 0.5 --consistency-radius 0.02`)",
    "modelnet40_tables_two_passes_more": "ModelNet40 tables, two passes, CO / ND, PV / ND, RS / ND and PV+RS / UPC (`modelnet40_tables.py --models vrnet-co-nd-rcp vrnet-pv-nd-rcp vrnet-rs-nd-rcp vrnet-mixed-upc-rcp --methods vrnet2`)",
    "modelnet40_tables_rs_nd": "ModelNet40 tables, RS / ND (`modelnet40_tables.py --models vrnet-rs-nd-rcp --methods vrnet vcp`)",
    "modelnet40_tables_nd_cells": "ModelNet40 tables, CO / RS / PV+RS with noise (`modelnet40_tables.py --models vrnet-mixed-nd-rcp --settings CO RS PV+RS`)" + EARLIER_VIEWS,
    "rotations": "ModelNet40 beyond the protocol's rotations, each cell's model alone and with its rotation search (`modelnet40_rotations.py` over `modelnet40_tables.py --methods vrnet --max-items 100 --rotation-range symmetric|so3 [--swap] --rotation-search-below 0|0.1`)",
    "finetune_pv_upc_symmetric": "Fine-tuning PV / UPC on symmetric rotations on a CPU, on validation pairs (`vrnet train --rotation-range symmetric`, `vrnet eval --partition val`)",
    "finetune_rs_upc_symmetric": "Fine-tuning RS / UPC on symmetric rotations on a CPU, on validation pairs (`vrnet train --rotation-range symmetric`, `vrnet eval --partition val`)",
    "finetune_pv_nd_symmetric": "Fine-tuning PV / ND on symmetric rotations on a CPU, on validation pairs (`vrnet train --rotation-range symmetric`)",
    "finetune_pv_nd_views": "Fine-tuning PV / ND on symmetric rotations and views cut in any direction on a CPU, on validation pairs (`vrnet train --rotation-range symmetric --far-points mixed`, `vrnet eval --partition val`); shipped",
    "modelnet40_tables_pv_nd": "ModelNet40 tables, PV / ND with the model fine-tuned on symmetric rotations and mixed views (`modelnet40_tables.py --models vrnet-pv-nd-rcp --methods vrnet`)",
    "rotations_pv_nd": "ModelNet40 PV / ND beyond the protocol's rotations with the model fine-tuned on symmetric rotations and mixed views, alone and with its rotation search (`modelnet40_rotations.py` over `modelnet40_tables.py --models vrnet-pv-nd-rcp --methods vrnet --max-items 100 --rotation-range symmetric|so3 [--swap] --rotation-search-below 0|0.1`)",
    "finetune_pvrs_nd_views": "Fine-tuning PV+RS / ND on symmetric rotations and views cut in any direction on a CPU, on validation pairs (`vrnet train --rotation-range symmetric --far-points mixed`, `vrnet eval --partition val`); shipped",
    "modelnet40_tables_pvrs_nd": "ModelNet40 tables, PV+RS / ND with the model fine-tuned on symmetric rotations and mixed views (`modelnet40_tables.py --models vrnet-pvrs-nd-rcp --methods vrnet`)",
    "rotations_pvrs_nd": "ModelNet40 PV+RS / ND beyond the protocol's rotations with the model fine-tuned on symmetric rotations and mixed views, alone and with its rotation search (`modelnet40_rotations.py` over `modelnet40_tables.py --models vrnet-pvrs-nd-rcp --methods vrnet --max-items 100 --rotation-range symmetric|so3 [--swap] --rotation-search-below 0|0.1`)",
    "finetune_pv_nd_epoch2": "A second epoch of the PV / ND fine-tune on symmetric rotations and mixed views, on validation pairs (`vrnet train --rotation-range symmetric --far-points mixed --seed 4321`); not shipped",
    "finetune_rs_nd_symmetric": "Fine-tuning RS / ND on symmetric rotations on a CPU, on validation pairs (`vrnet train --rotation-range symmetric`, `vrnet eval --partition val`); shipped",
    "modelnet40_tables_rs_nd": "ModelNet40 tables, RS / ND with the model fine-tuned on symmetric rotations (`modelnet40_tables.py --models vrnet-rs-nd-rcp --methods vrnet`)",
    "rotations_rs_nd": "ModelNet40 RS / ND beyond the protocol's rotations with the model fine-tuned on symmetric rotations, alone and with its rotation search (`modelnet40_rotations.py` over `modelnet40_tables.py --models vrnet-rs-nd-rcp --methods vrnet --max-items 100 --rotation-range symmetric|so3 [--swap] --rotation-search-below 0|0.1`)",
    "finetune_pv_nd_walk": "The PV / ND walk retrained on symmetric rotations and mixed views, on validation pairs (`vrnet train --stage1-epochs 0 --stage2-epochs 1 --rotation-range symmetric --far-points mixed`); not shipped",
    "finetune_co_nd_symmetric": "Fine-tuning CO / ND on symmetric rotations on a CPU, on validation pairs (`vrnet train --rotation-range symmetric`, `finetune_validation.py`); shipped",
    "modelnet40_tables_co_nd_sym": "ModelNet40 tables, CO / ND with the model fine-tuned on symmetric rotations (`modelnet40_tables.py --models vrnet-co-nd-rcp --methods vrnet`)",
    "rotations_co_nd": "ModelNet40 CO / ND beyond the protocol's rotations with the model fine-tuned on symmetric rotations, alone and with its rotation search (`modelnet40_rotations.py` over `modelnet40_tables.py --models vrnet-co-nd-rcp --methods vrnet --max-items 100 --rotation-range symmetric|so3 [--swap] --rotation-search-below 0|0.1`)",
    "finetune_pv_nd_cube": "Fine-tuning PV / ND on the rotations the rotation search leaves (cube residuals) and mixed views on a CPU, on validation pairs (`vrnet train --rotation-range cube_residual --far-points mixed`, `finetune_validation.py`); not shipped",
    "rotations_all": "ModelNet40 beyond the protocol's rotations on 100 shapes spread over each test split, all twelve cells, each cell's model alone and with its rotation search (`modelnet40_rotations.py --tables rotations_alone rotations_spread rotations_centred`, over `modelnet40_tables.py --methods vrnet --max-items 100 --rotation-range so3|symmetric [--swap] --rotation-search-below 0|0.1`)",
    "rotations_whole_centred": "ModelNet40 whole test splits with symmetric angles, each cell's model with its rotation search (about the centre of its training rotations too, where that is not the identity; `modelnet40_rotations.py` over `modelnet40_tables.py --methods vrnet --rotation-range symmetric --rotation-search-below 0.1`)",
    "rotations_centred": "ModelNet40 beyond the protocol's rotations on 100 shapes spread over each test split, the eight protocol-trained cells' models with their rotation search about the centre of their training rotations too (`modelnet40_rotations.py` over `modelnet40_tables.py --methods vrnet --max-items 100 --rotation-range so3|symmetric [--swap] --rotation-search-below 0.1`)",
    "rotations_spread": "ModelNet40 beyond the protocol's rotations on 100 shapes spread over each test split, every cell's model with its rotation search (`modelnet40_rotations.py` over `modelnet40_tables.py --methods vrnet --max-items 100 --rotation-range so3|symmetric [--swap] --rotation-search-below 0.1`)",
    "rotations_nearest": "ModelNet40 beyond the protocol's rotations, the rotation search keeping the start that brings the source closest to the target (`modelnet40_rotations.py` over `modelnet40_tables.py --methods vrnet --max-items 100 --rotation-range symmetric|so3 [--swap] --rotation-search-below 0|0.1`; the model-alone rows as in `rotations`)",
    "rotations_whole_nearest": "ModelNet40 with each angle in [-45, 45] degrees on whole test splits, four cells with the rotation search keeping the start that brings the source closest to the target (`modelnet40_rotations.py` over `modelnet40_tables.py --methods vrnet --rotation-range symmetric --rotation-search-below 0.1`)",
    "rotation_search_criteria": "How the rotation search should choose among its starts, on validation pairs (`rotation_search_criteria.py`)",
    "rotations_whole_splits": "ModelNet40 with each angle in [-45, 45] degrees on whole test splits, four cells alone and with the rotation search (`modelnet40_rotations.py` over `modelnet40_tables.py --methods vrnet --rotation-range symmetric --rotation-search-below 0|0.1`)",
    "polish_validation_nd": "The geometric polish on validation pairs of the four ND cells, protocol and symmetric rotations with the search (`polish_validation.py --models <the ND models>`)",
    "polish_validation_protocol": "The geometric polish on validation pairs of the eight noise-free cells, the protocol's rotations (`polish_validation.py --rotations protocol`)",
    **{f"modelnet40_tables_{cell}_polish": f"ModelNet40 tables, {label} / ND with the shipped geometric polish (`modelnet40_tables.py --models vrnet-{cell.split('_')[0]}-nd-rcp --methods vrnet --polish-iterations 10`)"
       for cell, label in (("co_nd", "CO"), ("pv_nd", "PV"), ("rs_nd", "RS"), ("pvrs_nd", "PV+RS"))},
    "rotations_whole": "ModelNet40 whole test splits with symmetric angles, each cell's model with its rotation search, RS / UPC added and PV / ND with its polish (`modelnet40_rotations.py --tables rotations_whole_centred rotations_whole`)",
    **{f"search_polish_{cells}": f"The rotation search polishing its starts on validation pairs with symmetric angles, {label} (`polish_validation.py --rotations symmetric --search-polish 0 30`)"
       for cells, label in (("rs_upc", "RS / UPC"), ("uc", "PV+RS / UC and RS / UC"))},
    "rotations_whole_polish": "ModelNet40 whole test splits with symmetric angles, each cell's model with its rotation search, PV+RS / UC again with the search polishing its starts (`modelnet40_rotations.py --tables rotations_whole_centred rotations_whole rotations_whole_polish`)",
    "rotations_whole_all": "ModelNet40 whole test splits with symmetric angles, all twelve cells, each cell's model with its rotation search: PV+RS / UPC, RS / ND and PV+RS / ND added, CO / UPC and PV / UPC again with their 47 starts (`modelnet40_rotations.py --tables rotations_whole_centred rotations_whole rotations_whole_polish rotations_whole_rest rotations_whole_upc`)",
    "rotations_whole_all_icp": "ModelNet40 whole test splits with symmetric angles, all twelve cells, each cell's model with its rotation search: RS / ND, PV+RS / ND, PV+RS / UC, PV+RS / UPC, RS / UPC and PV / ND again with the multi-start ICP their models now ship, PV / ND once more with its slides and trimmed ICP (`modelnet40_rotations.py --tables rotations_whole_centred rotations_whole rotations_whole_polish rotations_whole_rest rotations_whole_upc rotations_whole_icp rotations_whole_slides`)",
    **{f"icp_search_validation_{cells}": f"The rotation search's multi-start ICP on validation pairs with symmetric angles, {label}, each share of the estimate's distance its result must come below (`icp_search_validation.py --models {models}`)"
       for cells, label, models in (("rs_nd", "RS / ND", "vrnet-rs-nd-rcp"),
                                    ("pv_nd", "PV+RS / ND and PV / ND", "vrnet-pvrs-nd-rcp vrnet-pv-nd-rcp"),
                                    ("rs_upc", "RS / UPC, the whole partition", "vrnet-rs-upc-rcp --max-items 984"),
                                    ("pvrs_upc", "PV+RS / UPC, the whole partition",
                                     "vrnet-mixed-upc-rcp --setting PV+RS --max-items 984"),
                                    ("pvrs_uc", "PV+RS / UC, the whole partition", "vrnet-pvrs-uc-rcp --max-items 491"),
                                    ("pv_nd_whole", "PV / ND, the whole partition",
                                     "vrnet-pv-nd-rcp --max-items 984 --nearer 1 0.85"),
                                    ("pv_nd_slides", "PV / ND, the whole partition, trimmed ICP with 17 slides",
                                     "vrnet-pv-nd-rcp --max-items 984 --slides 17 --icp trimmed"),
                                    ("pv_nd_slides9", "PV / ND, the whole partition, trimmed ICP with 9 slides",
                                     "vrnet-pv-nd-rcp --max-items 984 --slides 9 --icp trimmed"),
                                    ("rs_nd_trimmed", "RS / ND, the whole partition, robust and trimmed ICP",
                                     "vrnet-rs-nd-rcp --max-items 984 --icp robust trimmed"),
                                    ("pvrs_nd_whole", "PV+RS / ND, the whole partition, robust and trimmed ICP",
                                     "vrnet-pvrs-nd-rcp --max-items 984 --icp robust trimmed"),
                                    ("pvrs_nd_slides", "PV+RS / ND, the whole partition, trimmed ICP with 17 slides",
                                     "vrnet-pvrs-nd-rcp --max-items 984 --slides 17 --icp trimmed"))},
    "memory_plan": "Memory planner: predicted vs measured peaks (`bench_memory_plan.py`)",
    "memory_plan_refit": "Memory planner refitted as upper bounds, with a 3,000,000-point pair (`bench_memory_plan.py`)",
    "memory_plan_scene": "Memory planner, scene model (`bench_memory_plan.py --methods vrnet vrnet-large`)",
    "memory_plan_stages": "Memory planner by stage, every run returning freed memory (`bench_memory_plan.py`)",
    "large": "Large scenes under memory budgets (`bench_large_scene.py`)",
    "register": "Registration against Open3D and small_gicp (`bench_register.py`)",
    "register_lidar": "Registration, LiDAR pair (`bench_register.py`)",
    "register_lidar7": "Registration, LiDAR pair (`bench_register.py`)",
    "register_gicp": "Registration with GICP (`bench_register.py`)",
    "register_busy": "Registration beside a busy process (`bench_register.py --beside-busy`)",
    "inference": "ModelNet40 inference speed (`bench_inference.py`)",
    "inference_avx2": "ModelNet40 inference speed on a CPU without bfloat16 products (`bench_inference.py --variants ext`)",
    "inference_avx2_slices": "ModelNet40 inference speed on a CPU without bfloat16 products, the Transformer taking large batches in slices of 4 pairs (`bench_inference.py --variants ext torch`)",
    "inference_avx2_second_pass": "ModelNet40 inference speed on a CPU without bfloat16 products, the model taking its second pass where its RCPs disagree (`bench_inference.py --variants ext`)",
    "degeneracy": "How well real scans constrain ICP: the smallest eigenvalue share at the ground truth (`bench_degeneracy.py`)",
    "register_batch": "Many pairs: one process per pair, `register-batch`, `torchrun` with 2 processes (`bench_register_batch.py`)",
    "default": "The default (`auto`) beside the methods it combines, on pairs none was tuned on (`bench_default.py`)",
    "default_cross_check": "The default (`auto`) with its check by a second estimator, beside the methods it combines (`bench_default.py`)",
    "default_ambiguity": "The default (`auto`) with the ambiguity warning (a rival alignment's support), beside the methods it combines (`bench_default.py`)",
    "default_scans": "The default (`auto`) with voxel edges never finer than the scans' spacing, on object range scans too, beside the methods it combines (`bench_default.py`)",
    "device_budget_cpu": "A 10-million-point pair under `max_memory` on the CPU (`bench_device_budget.py`)",
    "reduced_precision_pv_upc": "What TF32 and bfloat16 products cost `vrnet-pv-upc-rcp`, simulated on the CPU, validation pairs (`reduced_precision.py --model vrnet-pv-upc-rcp`)",
    "reduced_precision_pv_nd": "What TF32 and bfloat16 products cost `vrnet-pv-nd-rcp`, simulated on the CPU, validation pairs (`reduced_precision.py --model vrnet-pv-nd-rcp`)",
    "register_scene": "Many scans of one scene against ground-truth poses: `register-scene` and Open3D's multiway registration (`bench_register_scene.py`)",
    "scene_objectives": "How far the redkitchen fragments determine their ground-truth poses: three refinements of all poses, round by round (`scene_objectives.py --rounds 8`)",
    "icp_from_truth": "Where ICP goes when it starts from the official ground truth (`bench_icp_from_truth.py`)",
    "global_fit": "Spatial consistency vs RANSAC, matching + fit on the same descriptors (`bench_global_fit.py`)",
    "scene_validation": "Scene models on the validation pairs (`scene_validation.py`)",
    "ops": "Op timings (`bench_ops.py`)",
    "ops_spatial_consistency": "Spatial consistency op timings (`bench_ops.py --only spatial_consistency`)",
    "ops_robust_kabsch_avx2": "Kabsch and robust Kabsch timings on a CPU without AVX-512 (`bench_ops.py --only robust_kabsch,kabsch`)",
    "busy": "Op timings beside a busy process (`bench_ops.py --beside-busy`)",
    "busy_1": "Op timings beside a busy process (`bench_ops.py --beside-busy`)",
    "busy_2": "Op timings beside a busy process (`bench_ops.py --beside-busy`)",
    "edgeconv": "EdgeConv timings (`bench_ops.py`)",
    "ops_knn": "kNN timings (`bench_ops.py --quick --only knn`)",
    "ops_knn_edge": "kNN, edge_norm_max and EdgeConv timings (`bench_ops.py --only knn,edge_norm_max,EdgeConv`)",
    "ops_attention": "Attention timings (`bench_ops.py --only attention`)",
    "ops_soft_match_avx2": "Soft matching timings on a CPU without AVX-512, with a sharp case (`bench_ops.py --only soft_match`)",
    "ops_avx2": "kNN, EdgeConv and L2 loss timings on a CPU without AVX-512 (`bench_ops.py --quick --only knn,pairwise_distance_loss,EdgeConv`)",
    "inference_amx_h200_host": "ModelNet40 inference speed on an AMX CPU, 2 threads on 2 cores of the GPU machine's host (`bench_inference.py --pairs 64 --variants torch ext \"ext, bf16 Transformer\"`)",
    "inference_amx_vm": "ModelNet40 inference speed on an AMX CPU, a quiet 2-core machine, 2 threads (`bench_inference.py`)",
    "inference_zen4_vm": "ModelNet40 inference speed on an AVX512-BF16 CPU without AMX (AMD EPYC), 2 cores, 2 threads, after the attention kernel stopped serving CPUs without AMX (`bench_inference.py --pairs 64`)",
    "ops_amx_vm": "Op timings on an AMX CPU, a quiet 2-core machine, 2 threads, beside Open3D, pykdtree, small_gicp, roma and SDPA (`bench_ops.py`)",
    "ops_soft_match_amx_vm": "Soft matching timings on an AMX CPU, denormals flushed inside the op (`bench_ops.py --only soft_match`)",
    "inference_cuda_h200": "ModelNet40 inference speed on an NVIDIA H200 (`bench_inference.py --device cuda --pairs 64 --variants torch ext \"ext, bf16 Transformer\"`)",
    "ops_cuda_h200": "Op timings on an NVIDIA H200, soft matching dense up to 2^26 scores (`bench_ops.py --device cuda --no-memory --repeats 5`)",
    "ops_cuda_h200_streamed": "Op timings on an NVIDIA H200, soft matching always streamed: the first GPU run (`bench_ops.py --device cuda --no-memory --repeats 5`)",
    "train_step_cuda_h200": "Training steps and one-pair inference on an NVIDIA H200 (`bench_train_step.py --device cuda --preset paper --steps 3 --inference-points 768`)",
    "train_step_cuda_h200_streamed": "Training steps and one-pair inference on an NVIDIA H200, soft matching always streamed: the first GPU run (`bench_train_step.py --device cuda --preset paper --steps 3 --inference-points 768`)",
    "inference_cuda_h200_cdist_graphs": "ModelNet40 inference speed on an NVIDIA H200, the DGCNN's feature graphs by `cdist` + `topk` (`bench_inference.py --device cuda --pairs 64 --variants torch ext \"ext, bf16 Transformer\"`)",
    "ops_cuda_h200_dense_blocks": "Op timings on an NVIDIA H200, large soft matchings without gradients in dense blocks (`bench_ops.py --device cuda --no-memory --repeats 5`)",
    "train_step_cuda_h200_cdist_graphs": "Training steps and one-pair inference on an NVIDIA H200, the DGCNN's feature graphs by `cdist` + `topk` (`bench_train_step.py --device cuda --preset paper --steps 3 --inference-points 768`)",
    "inference_cuda_h200_rerun": "ModelNet40 inference speed on an NVIDIA H200, another lease of the machine (`bench_inference.py --device cuda --pairs 64 --variants torch ext \"ext, bf16 Transformer\"`)",
    "ops_cuda_h200_blocked_backward": "Op timings on an NVIDIA H200, soft matching in blocks with a recomputing backward (`bench_ops.py --device cuda --no-memory --repeats 5`)",
    "train_step_cuda_h200_rerun": "Training steps and one-pair inference on an NVIDIA H200, another lease of the machine (`bench_train_step.py --device cuda --preset paper --steps 3 --inference-points 768`)",
    "ablation_iterations": "Ablation: VRNet with iterations (`ablations.py iterations`)",
    "ablation_outliers": "Ablation: robustness to outliers (`ablations.py outliers`)",
    "ablation_matches": "Ablation: correct matches vs outlier ratio (`ablations.py matches`)",
    "ablation_ransac": "Ablation: RANSAC vs the correction walk (`ablations.py ransac`)",
}


def op_table(records: list[dict]) -> str:
    """bench_ops.py records -> one row per (op, case, implementation), with the ratio to the
    reference implementation of the same case."""
    reference = {(r["op"], r["case"]): r["median_s"] for r in records if r["impl"] == "torch"}
    lines = ["| op | case | implementation | median (ms) | peak (MB) | vs reference |", "|---|---|---|---:|---:|---:|"]
    for r in records:
        ref = reference.get((r["op"], r["case"]))
        ratio = f"{ref / r['median_s']:.2f}x" if ref and r["median_s"] else "–"
        peak = f"{r['peak_mb']:.1f}" if isinstance(r.get("peak_mb"), (int, float)) else "–"
        median = f"{1000 * r['median_s']:.3f}" if isinstance(r.get("median_s"), (int, float)) else "–"
        lines.append(f"| {r['op']} | {r['case']} | {r['impl']} | {median} | {peak} | {ratio} |")
    first = records[0]
    lines.insert(0, f"{first.get('machine') or str(first.get('cpu_count', '?')) + ' CPUs'}, "
                    f"{first.get('threads', '?')} threads, torch "
                    f"{first.get('torch', '?')}, device {first.get('device', 'cpu')}"
                    f"{', beside a busy process' if first.get('beside_busy') else ''}.\n")
    return "\n".join(lines)


def ablation_table(result: dict) -> str:
    """benchmarks/ablations.py JSON -> a table: one row per iteration count or per outlier ratio."""
    rows = result["rows"]
    lines = [f"{result['pairs']} ModelNet40 PV/UPC test pairs, model `{result['model']}`, {result['date']}, "
             f"{result['machine']}.", ""]
    if "iterations" in rows[0]:
        lines += ["| iterations | RMSE(R) | MAE(R) | RMSE(t) | MAE(t) | ms / pair | paper RMSE(R) | paper RMSE(t) |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|"]
        lines += [f"| {r['iterations']} | {r['RMSE(R)']:.4g} | {r['MAE(R)']:.4g} | {r['RMSE(t)']:.4g} | "
                  f"{r['MAE(t)']:.4g} | {r['ms_per_pair']:.1f} | {r['paper']['RMSE(R)']} | {r['paper']['RMSE(t)']} |"
                  for r in rows]
    elif "correct_match_ratio" in rows[0]:
        keys = list(rows[0]["correct_match_ratio"])
        lines += ["| points | outlier ratio | " + " | ".join(keys) + " |", "|---:|---:|" + "---:|" * len(keys)]
        lines += [f"| {r['points']} | {100 * r['outlier_ratio']:.1f} % | "
                  + " | ".join(f"{r['correct_match_ratio'][k]:.3f}" for k in keys) + " |" for r in rows]
    else:
        methods = list(rows[0]["methods"])
        lines += ["| points | outlier ratio | " + " | ".join(f"{m} RMSE(R) / RMSE(t)" for m in methods) + " |",
                  "|---:|---:|" + "---:|" * len(methods)]
        lines += [f"| {r['points']} | {100 * r['outlier_ratio']:.1f} % | "
                  + " | ".join(f"{r['methods'][m]['RMSE(R)']:.3g} / {r['methods'][m]['RMSE(t)']:.3g}" for m in methods)
                  + " |" for r in rows]
    return "\n".join(lines)


def train_step_table(records: list[dict]) -> str:
    """bench_train_step.py records -> one row per (stage, implementation)."""
    first = records[0]
    lines = [f"Preset `{first['preset']}`, {first['points']} points, {first['device']}, {first['threads']} threads, "
             f"torch {first['torch']}.", "", "| stage | impl | batch | seconds |", "|---|---|---:|---:|"]
    lines += [f"| {r['stage']} | {r['impl']} | {r['batch_size']} | {r['median_s']:.4f} |" for r in records]
    return "\n".join(lines)


def section(json_path: Path) -> str:
    title = TITLES.get(json_path.stem, json_path.stem)
    link = f"[{json_path.name}](../{json_path.relative_to(RESULTS.parents[1]).as_posix()})"
    markdown, picture = json_path.with_suffix(".md"), json_path.with_suffix(".png")
    if markdown.exists():
        body = markdown.read_text().strip()
    elif json_path.stem.startswith("ablation_"):
        body = ablation_table(json.loads(json_path.read_text()))
    else:
        data = json.loads(json_path.read_text())
        records = data if isinstance(data, list) and data else [{}]
        body = (op_table(data) if "op" in records[0] else train_step_table(data) if "stage" in records[0]
                else f"(see {link})")
    if picture.exists():
        body += f"\n\n![{json_path.stem}](../{picture.relative_to(RESULTS.parents[1]).as_posix()})"
    return f"### {title}\n\nFrom {link}.\n\n{body}\n"


def render() -> str:
    parts = ["# Benchmarks", "",
             "Every table below is generated from `benchmarks/results/` by `benchmarks/benchmarks_page.py`; "
             "each names the JSON it comes from and the script that measured it. Newest first.", ""]
    for folder in sorted((p for p in RESULTS.iterdir() if p.is_dir()), reverse=True):
        parts += [f"## {folder.name}", ""]
        for json_path in sorted(folder.glob("*.json")):
            parts.append(section(json_path))
    return "\n".join(parts).rstrip() + "\n"


if __name__ == "__main__":
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    print(render(), end="")
