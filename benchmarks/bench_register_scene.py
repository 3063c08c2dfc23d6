"""Multiway registration of the shared scenes against their ground-truth poses: `vrnet register-scene`
and Open3D's multiway registration, in one run.

    python benchmarks/bench_register_scene.py [--data ../shared/data/scenes/real_pairs]
                                              [--json scene.json] [--markdown scene.md]

Scenes: ``redkitchen``, the 10 3DMatch fragments of the real pairs (0, 1, 4, 5, 6, 7, 10, 21, 34,
59); ``kitti00``, KITTI 00 frames 0, 4, 9 and 15. Their ground-truth poses chain the official
pairwise ground truth of the real pairs' manifest from the first scan (it is consistent to 1e-8).

Both run in a fresh process each (time and peak RSS include imports and reading the scans), on the
same voxel edges (the scene's median ``voxel_size_for`` at 5,000 points for the global estimate and
``vrnet``'s default ICP points, computed here and handed to Open3D; ours computes them itself):

* ``ours``: ``vrnet register-scene`` with its defaults (every pair: ``sc2`` + point-to-plane ICP,
  loop checks, the robust pose graph);
* ``open3d``: every pair with Open3D's FPFH + RANSAC + point-to-plane ICP (``open3d_pipeline.py``,
  as ``bench_register.py`` runs it), the information matrix from the ICP correspondences
  (``get_information_matrix_from_point_clouds``), a pose graph with consecutive scans as odometry
  edges and every other pair as an uncertain loop edge, and ``global_optimization`` (Levenberg-
  Marquardt, line process, reach 3 ICP voxels, prune threshold 0.25, reference scan 0), as
  Open3D's multiway tutorial and reconstruction system do.

Metrics (:func:`vrnet_ext.registration.scene_errors`): each scan's rotation and translation error
against its ground-truth pose in the first scan's frame (RMSE and largest), before the
optimisation (ours: the spanning-tree chain; Open3D: the odometry chain) and after, and the share of
registered pairs within 15 deg / 30 cm pairwise and after the optimisation.

How well the ground truth itself fits the scans: for every pair of the manifest in a scene, the
share of the source's points (at the ICP voxel) with a target point within one ICP voxel, under the
ground truth and under our optimised poses ("truth fits worse": in how many pairs the ground truth's
share is the lower one); the same for each scan against all the others merged, and for the scan
our poses put farthest from the ground truth.

``--graph-poses N`` (default 1,000) also times the optimiser alone on a synthetic sequence: a random
walk of N poses with noisy trusted odometry and N / 3 loop edges, a fifth of them wrong (best of 3).
"""
from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "scenes" / "real_pairs"
SCENES = {"redkitchen": [f"clouds/3dm_rk_{k:03d}.npy" for k in (0, 1, 4, 5, 6, 7, 10, 21, 34, 59)],
          "kitti00": [f"clouds/kitti00_{k:06d}.npy" for k in (0, 4, 9, 15)]}
GLOBAL_POINTS = 5000

OPEN3D_SCENE = textwrap.dedent(f"""
    import json, resource, sys, time
    sys.path.insert(0, {str(ROOT / "benchmarks")!r})
    import numpy as np
    import open3d as o3d
    from open3d_pipeline import cloud, features, global_estimate, icp_clouds, refine, reg
    from vrnet_ext.geometry.io import read_points
    out, voxel, icp_voxel, *paths = sys.argv[1:]
    voxel, icp_voxel = float(voxel), float(icp_voxel)
    begin = time.perf_counter()
    clouds = [cloud(read_points(path)) for path in paths]
    described = [features(pcd, voxel) for pcd in clouds]
    refined = [icp_clouds(pcd, pcd, icp_voxel, "point_to_plane")[0] for pcd in clouds]
    graph = reg.PoseGraph()
    odometry = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odometry))
    edges = []
    for target in range(len(paths)):
        for source in range(target + 1, len(paths)):
            initial = global_estimate(described[source], described[target], voxel).transformation
            icp = refine(refined[source], refined[target], icp_voxel, initial, "point_to_plane")
            T = np.asarray(icp.transformation)
            information = reg.get_information_matrix_from_point_clouds(refined[source], refined[target],
                                                                       3 * icp_voxel, T)
            consecutive = source == target + 1
            if consecutive:
                odometry = odometry @ T  # T_first_source: the tutorial's odometry chain
                graph.nodes.append(reg.PoseGraphNode(odometry))
            graph.edges.append(reg.PoseGraphEdge(source, target, T, information, uncertain=not consecutive))
            edges.append({{"source": source, "target": target, "T_target_source": T.tolist(), "fitness": icp.fitness}})
    initial_poses = [np.asarray(node.pose).tolist() for node in graph.nodes]
    option = reg.GlobalOptimizationOption(max_correspondence_distance=3 * icp_voxel, edge_prune_threshold=0.25,
                                          reference_node=0)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    kept_before = len(graph.edges)
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(), option)
    kept = {{(e.source_node_id, e.target_node_id) for e in graph.edges}}
    for edge in edges:
        edge["kept"] = (edge["source"], edge["target"]) in kept
    json.dump({{"poses": [np.asarray(node.pose).tolist() for node in graph.nodes], "initial_poses": initial_poses,
               "edges": edges, "seconds": time.perf_counter() - begin,
               "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}}, open(out, "w"))
""")


def truth_poses(data: Path, files: list[str]) -> np.ndarray:
    """(P, 4, 4) ground-truth ``T_first_scan``, chained through the manifest's pairs among ``files``."""
    from vrnet_ext.geometry.transforms import chain

    links = []
    with open(data / "MANIFEST.tsv", newline="") as f:
        for row in csv.DictReader(f, delimiter="\t"):
            if row["source_file"] in files and row["target_file"] in files:  # the gt maps source into target
                links.append((files.index(row["target_file"]), files.index(row["source_file"]),
                              np.loadtxt(data / row["gt_file"])))
    poses, reached = chain(len(files), links)
    if not reached.all():
        raise SystemExit(f"bench_register_scene: no ground-truth chain reaches {[f for f, r in zip(files, reached) if not r]}")
    return poses


def voxels(paths: list[Path]) -> tuple[float, float]:
    """The scene's median voxel edges for the global estimate and ICP, as register_scene picks them."""
    from vrnet_ext.geometry.io import read_points
    from vrnet_ext.geometry.preprocessing import voxel_size_for
    from vrnet_ext.registration.counts import PointCounts

    clouds = [read_points(path) for path in paths]
    return (float(np.median([voxel_size_for(c, GLOBAL_POINTS) for c in clouds])),
            float(np.median([voxel_size_for(c, PointCounts.icp_points) for c in clouds])))


def as_scene(names: list[str], record: dict, reach: float):
    """Open3D's poses and edges as a SceneResult, to be measured as ours is."""
    from vrnet_ext.registration.multiway import SceneEdge, SceneResult

    edges = [SceneEdge(source=e["source"], target=e["target"], T_target_source=np.array(e["T_target_source"]),
                       fitness=e["fitness"], inlier_rmse=float("nan"), correspondences=0, warnings=[], seconds=0.0,
                       information=np.eye(6), kept=e["kept"]) for e in record["edges"]]
    return SceneResult(names=names, poses=np.array(record["poses"]), initial_poses=np.array(record["initial_poses"]),
                       placed=np.ones(len(names), dtype=bool), edges=edges, fused=np.zeros((0, 3)), voxel=reach / 3,
                       reach=reach, warnings=[], seconds={})


def ours_as_scene(record: dict):
    from vrnet_ext.registration.multiway import SceneEdge, SceneResult

    edges = [SceneEdge(**{**e, "T_target_source": np.array(e["T_target_source"]),
                          "information": np.array(e["information"])}) for e in record["edges"]]
    nan = np.full((4, 4), np.nan)
    return SceneResult(names=record["names"], poses=np.array([p if p is not None else nan for p in record["poses"]]),
                       initial_poses=np.array([p if p is not None else nan for p in record["initial_poses"]]),
                       placed=np.array([p is not None for p in record["poses"]]), edges=edges, fused=np.zeros((0, 3)),
                       voxel=record["voxel"], reach=record["reach"], warnings=record["warnings"],
                       seconds=record["seconds"])


def time_optimiser(count: int, seed: int = 0) -> dict:
    """The pose graph alone on a synthetic sequence of ``count`` poses (module docstring)."""
    from vrnet_ext.geometry.lie import motion, point_information
    from vrnet_ext.registration.pose_graph import PoseEdge, PoseGraphSettings, optimize_pose_graph

    rng = np.random.default_rng(seed)
    steps = motion(np.concatenate([rng.normal(0, 0.05, (count, 3)), rng.normal(0, 0.3, (count, 3))], axis=1))
    truth = [np.eye(4)]
    for step in steps[1:]:
        truth.append(truth[-1] @ step)
    truth = np.stack(truth)
    information = point_information(rng.uniform(-2, 2, (500, 3)))

    def edge(source, target, wrong=False, robust=True):
        error = rng.normal(0, 0.6, 6) if wrong else rng.normal(0, 1e-3, 6)
        return PoseEdge(source=source, target=target, T_target_source=motion(error) @ np.linalg.inv(truth[target])
                        @ truth[source], information=information, correspondences=500, robust=robust)

    edges = [edge(i + 1, i, robust=False) for i in range(count - 1)]
    wrong = []
    for k in range(count // 3):
        i = int(rng.integers(0, count - 12))
        wrong.append(k % 5 == 0)
        edges.append(edge(i + int(rng.integers(2, 12)), i, wrong=wrong[-1]))
    start = [np.eye(4)]
    for e in edges[:count - 1]:
        start.append(start[-1] @ e.T_target_source)
    times = []
    for _ in range(3):
        began = time.perf_counter()
        solution = optimize_pose_graph(np.stack(start), edges, PoseGraphSettings(reach=0.05))
        times.append(time.perf_counter() - began)
    loops = solution.kept[count - 1:]
    return {"poses": count, "edges": len(edges), "wrong_loops": int(sum(wrong)), "seconds": min(times),
            "iterations": solution.iterations, "wrong_dropped": int((~loops[np.array(wrong)]).sum()),
            "right_dropped": int((~loops[~np.array(wrong)]).sum())}


def truth_fit(data: Path, files: list[str], truth: np.ndarray, poses: np.ndarray, icp_voxel: float) -> dict:
    """How well the ground truth and ``poses`` fit the scans, as the share of source points with a
    point within one ICP voxel: per manifest pair of the scene, and per scan against every other scan
    merged (``scans``: file name -> (under the truth, under ``poses``))."""
    from vrnet_ext.geometry.io import read_points
    from vrnet_ext.geometry.preprocessing import voxel_downsample
    from vrnet_ext.geometry.transforms import apply
    from vrnet_ext.registration.refinement import fitness

    clouds = {name: voxel_downsample(read_points(data / name), icp_voxel) for name in files}
    worse, shares = 0, []
    with open(data / "MANIFEST.tsv", newline="") as f:
        for row in csv.DictReader(f, delimiter="\t"):
            if row["source_file"] in clouds and row["target_file"] in clouds:
                s, t = files.index(row["source_file"]), files.index(row["target_file"])
                src, tgt = clouds[row["source_file"]], clouds[row["target_file"]]
                under_truth = fitness(src, tgt, np.linalg.inv(truth[t]) @ truth[s], icp_voxel)
                under_ours = fitness(src, tgt, np.linalg.inv(poses[t]) @ poses[s], icp_voxel)
                worse += under_truth < under_ours
                shares.append((under_truth, under_ours))
    scans = {}
    for k, name in enumerate(files):
        others = [j for j in range(len(files)) if j != k]
        scans[Path(name).name] = tuple(fitness(clouds[name], np.concatenate([apply(frame[j], clouds[files[j]]) for j in others]),
                                    frame[k], icp_voxel) for frame in (truth, poses))
    return {"pairs": len(shares), "truth_fits_worse": int(worse),
            "median_fitness_truth": float(np.median([a for a, _ in shares])),
            "median_fitness_ours": float(np.median([b for _, b in shares])), "scans": scans}


def run(command: list[str]) -> float:
    started = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"bench_register_scene: {' '.join(command[:4])} failed:\n{proc.stderr[-2000:]}")
    return time.perf_counter() - started


def main(argv: list[str] | None = None) -> None:
    from vrnet_ext.cli.common import DefaultsHelpFormatter
    from vrnet_ext.registration.scene_metrics import scene_errors

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the real pairs' folder (MANIFEST.tsv, clouds/)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES), help="scenes to run")
    parser.add_argument("--graph-poses", type=int, default=1000, help="poses of the synthetic graph (0: skip)")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    data, work = Path(args.data), Path(tempfile.mkdtemp())
    have_open3d = importlib.util.find_spec("open3d") is not None
    rows, fits, record = [], [], {"machine": cpu_description(), "date": time.strftime("%Y-%m-%d"), "scenes": {}}
    for scene in args.scenes:
        paths = [data / name for name in SCENES[scene]]
        truth = truth_poses(data, SCENES[scene])
        global_voxel, icp_voxel = voxels(paths)
        names = [path.name for path in paths]
        results = {}
        out = work / f"{scene}_ours.json"
        wall = run([sys.executable, "-m", "vrnet_ext.cli", "register-scene", *map(str, paths), "--json", str(out),
                    "--global-points", str(GLOBAL_POINTS), "--no-progress"])
        ours = json.loads(out.read_text())
        results["ours"] = (ours_as_scene(ours), wall, ours["peak_rss_mb"])
        fit = truth_fit(data, SCENES[scene], truth, results["ours"][0].poses, icp_voxel)
        fits.append(f"{scene}: the ground truth fits the scans worse than our poses in {fit['truth_fits_worse']} of "
                    f"{fit['pairs']} pairs (median fitness within one ICP voxel {fit['median_fitness_truth']:.3f} "
                    f"vs {fit['median_fitness_ours']:.3f}), and each scan against all the others merged in "
                    f"{sum(a < b for a, b in fit['scans'].values())} of {len(fit['scans'])} scans.")
        if have_open3d:
            out = work / f"{scene}_open3d.json"
            wall = run([sys.executable, "-c", OPEN3D_SCENE, str(out), str(global_voxel), str(icp_voxel), *map(str, paths)])
            theirs = json.loads(out.read_text())
            results["open3d"] = (as_scene(names, theirs, 3 * icp_voxel), wall, theirs["peak_rss_mb"])
        record["scenes"][scene] = {"truth_fit": fit}
        for name, (result, wall, peak) in results.items():
            errors = scene_errors(result, truth)
            if name == "ours":
                worst = max(errors["scans"], key=lambda scan: scan["translation_error"])
                under_truth, under_ours = fit["scans"][worst["name"]]
                fits.append(f"{scene}: our farthest scan from the ground truth, {worst['name']} "
                            f"({worst['rotation_error_deg']:.2f} deg / {worst['translation_error']:.3f}), fits the other "
                            f"scans {under_ours:.3f} under our poses, {under_truth:.3f} under the ground truth.")
            dropped = sum(not edge.kept for edge in result.edges)
            record["scenes"][scene][name] = {"errors": errors, "process_s": wall, "peak_rss_mb": peak,
                                             "pairs": len(result.edges), "dropped": dropped}
            before, after = errors["initial"], errors["optimised"]
            rows.append(f"| {scene} | {name} | {len(result.edges)} / {dropped} | "
                        f"{before['max_rotation_deg']:.2f} / {before['max_translation']:.3f} | "
                        f"{after['rmse_rotation_deg']:.2f} / {after['rmse_translation']:.3f} | "
                        f"{after['max_rotation_deg']:.2f} / {after['max_translation']:.3f} | "
                        f"{errors['recall_before']:.0%} -> {errors['recall_after']:.0%} | {wall:.1f} | {peak:.0f} |")
        if not have_open3d:
            rows.append(f"| {scene} | open3d | not installed | | | | | | |")
    footer = ["", *fits]
    if args.graph_poses:
        graph = record["optimiser"] = time_optimiser(args.graph_poses)
        footer += ["", f"The optimiser alone, {graph['poses']} poses and {graph['edges']} edges ({graph['wrong_loops']} "
                      f"wrong loop edges): {graph['seconds']:.2f} s, {graph['iterations']} iterations; wrong edges "
                      f"dropped {graph['wrong_dropped']} / {graph['wrong_loops']}, right ones dropped "
                      f"{graph['right_dropped']}."]
    table = "\n".join([
        f"Multiway registration against ground-truth poses ({record['machine']}, {record['date']}); errors in "
        "degrees / metres, each scan's pose in the first scan's frame.", "",
        "| scene | implementation | pairs / dropped | before: largest | after: RMSE | after: largest | "
        "pairs registered | s (process) | peak MB |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|", *rows, *footer])
    write_outputs(table, record, args.markdown, args.json)


if __name__ == "__main__":
    main()
