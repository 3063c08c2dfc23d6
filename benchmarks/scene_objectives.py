"""How far a shared scene's ground-truth poses are determined by its scans (the redkitchen's 10 fragments): from
one `register_scene` result (the robust pose graph, no map pass), three ways of refining all poses
against the scans, each measured against the ground truth after every round, and the ground truth
itself tested as a refinement's starting point.

    python benchmarks/scene_objectives.py [--data ../shared/data/scenes/real_pairs] [--scene redkitchen] [--rounds 6]
                                          [--json objectives.json] [--markdown objectives.md]

* ``map``: each scan but the first refined in turn by point-to-plane ICP against all the others
  merged at their current poses (``register_scene``'s map pass, repeated: block coordinate descent);
* ``pairwise``: every pair with 1,000+ points within reach at the current poses registered again by
  ICP from its current relative pose, then the pose graph over those edges (Choi et al.'s refinement
  as Open3D's reconstruction system runs it);
* ``joint``: one Gauss-Newton step per round of the point-to-plane residuals of every scan's points
  to their nearest point among all the other scans, all poses at once (multi-view ICP);
* ``truth``: each scan ICP-refined against the others placed by the ground truth, from the truth.

Everything at the scene's ICP voxel and reach (as ``register_scene`` chooses them); errors are the
scans' rotation (degrees) and translation errors against the ground truth, both in the first scan's
frame (``scene_errors``).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from bench_register_scene import DEFAULT_DATA, SCENES, truth_poses  # benchmarks/, the script's folder
from outputs import cpu_description, write_outputs

PAIR_POINTS = 1000  # a pair registered again in ``pairwise`` when this many points lie within reach


def _errors(poses: np.ndarray, truth: np.ndarray) -> dict:
    from vrnet_ext.registration.result import transform_errors

    errors = [transform_errors(pose, true) for pose, true in zip(poses, truth)]
    rotation = np.array([e["rotation_error_deg"] for e in errors])
    translation = np.array([e["translation_error"] for e in errors])
    return {"rmse_rotation_deg": float(np.sqrt(np.mean(rotation ** 2))), "max_rotation_deg": float(rotation.max()),
            "rmse_translation": float(np.sqrt(np.mean(translation ** 2))), "max_translation": float(translation.max()),
            "translation": translation.tolist()}


def _merged_others(scans, poses, i, voxel):
    from vrnet_ext.geometry.preprocessing import voxel_downsample
    from vrnet_ext.geometry.transforms import apply

    return voxel_downsample(np.concatenate([apply(poses[j], s) for j, s in enumerate(scans) if j != i]), voxel)


def map_round(scans, normals, poses, settings):
    from vrnet_ext.registration.refinement import icp

    poses = poses.copy()
    for i in range(1, len(scans)):
        poses[i] = icp(scans[i], _merged_others(scans, poses, i, settings.voxel_size), poses[i],
                       settings).T_target_source
    return poses


def pairwise_round(scans, normals, poses, settings):
    from vrnet_ext.geometry.lie import point_information
    from vrnet_ext.geometry.transforms import apply
    from vrnet_ext.registration.pose_graph import PoseEdge, PoseGraphSettings, optimize_pose_graph
    from vrnet_ext.registration.refinement import IcpFailure, icp, pairs_within_reach

    edges = []
    for target in range(len(scans)):
        for source in range(target + 1, len(scans)):
            relative = np.linalg.inv(poses[target]) @ poses[source]
            if len(pairs_within_reach(scans[source], scans[target], relative, settings.max_distance)[0]) < PAIR_POINTS:
                continue
            try:
                T = icp(scans[source], scans[target], relative, settings).T_target_source
            except IcpFailure:
                continue
            index, _ = pairs_within_reach(scans[source], scans[target], T, settings.max_distance)
            edges.append(PoseEdge(source=source, target=target, T_target_source=T, correspondences=len(index),
                                  information=point_information(apply(T, scans[source][index]))))
    return optimize_pose_graph(poses, edges, PoseGraphSettings(reach=settings.max_distance)).poses


def joint_round(scans, normals, poses, settings):
    from vrnet_ext import ops
    from vrnet_ext.geometry.lie import motion
    from vrnet_ext.geometry.transforms import apply

    count = len(scans)
    world = [apply(pose, s) for pose, s in zip(poses, scans)]
    facing = [n @ pose[:3, :3].T for pose, n in zip(poses, normals)]
    H, g = np.zeros((6 * count, 6 * count)), np.zeros(6 * count)
    for i in range(count):
        others = [j for j in range(count) if j != i]
        ref = np.concatenate([world[j] for j in others])
        dist2, index = ops.knn(torch.as_tensor(world[i])[None], torch.as_tensor(ref)[None], 1)
        close = (dist2[0, :, 0] <= settings.max_distance ** 2).numpy()
        index = index[0, :, 0].numpy()[close]
        owner = np.concatenate([np.full(len(world[j]), j) for j in others])[index]
        p, q, n = world[i][close], ref[index], np.concatenate([facing[j] for j in others])[index]
        residual = ((p - q) * n).sum(1)
        along_i, along_j = np.concatenate([np.cross(p, n), n], 1), -np.concatenate([np.cross(q, n), n], 1)
        for j in np.unique(owner):
            rows = owner == j
            a, b, r = along_i[rows], along_j[rows], residual[rows]
            for x, jx in ((i, a), (j, b)):
                g[6 * x:6 * x + 6] += jx.T @ r
                for y, jy in ((i, a), (j, b)):
                    H[6 * x:6 * x + 6, 6 * y:6 * y + 6] += jx.T @ jy
    step = np.zeros(6 * count)
    step[6:] = np.linalg.solve(H[6:, 6:], -g[6:])  # the first scan's pose stays fixed
    return motion(step.reshape(count, 6)) @ poses


def truth_equilibrium(scans, truth, settings) -> list[dict]:
    from vrnet_ext.registration.refinement import icp
    from vrnet_ext.registration.result import transform_errors

    return [transform_errors(icp(scans[i], _merged_others(scans, truth, i, settings.voxel_size), truth[i],
                                 settings).T_target_source, truth[i]) for i in range(len(scans))]


def main(argv: list[str] | None = None) -> None:
    from vrnet_ext import ops
    from vrnet_ext.cli.common import DefaultsHelpFormatter
    from vrnet_ext.geometry.io import read_points
    from vrnet_ext.geometry.preprocessing import voxel_downsample
    from vrnet_ext.registration.multiway import SceneOptions, register_scene
    from vrnet_ext.registration.refinement import NORMAL_NEIGHBOURS, IcpSettings

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the real pairs' folder (MANIFEST.tsv, clouds/)")
    parser.add_argument("--scene", choices=sorted(SCENES), default="redkitchen", help="the scene to refine")
    parser.add_argument("--rounds", type=int, default=6, help="refinement rounds of each kind")
    parser.add_argument("--json", help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    data, files = Path(args.data), SCENES[args.scene]
    truth = truth_poses(data, files)
    truth = np.linalg.inv(truth[0]) @ truth
    scene = register_scene([data / f for f in files], SceneOptions(map_icp=False))
    settings = IcpSettings(voxel_size=scene.voxel, max_distance=scene.reach)
    scans = [voxel_downsample(read_points(data / f).astype(np.float64), scene.voxel) for f in files]
    normals = [ops.normals(torch.as_tensor(s), NORMAL_NEIGHBOURS).numpy() for s in scans]
    rows = [{"refinement": "none (pose graph)", "round": 0, **_errors(scene.poses, truth), "seconds": 0.0}]
    for name, step in (("map", map_round), ("pairwise", pairwise_round), ("joint", joint_round)):
        poses = scene.poses
        for k in range(1, args.rounds + 1):
            begin = time.perf_counter()
            poses = step(scans, normals, poses, settings)
            seconds = time.perf_counter() - begin
            rows.append({"refinement": name, "round": k, **_errors(poses, truth), "seconds": seconds})
            print(f"{name} round {k}: {rows[-1]['max_rotation_deg']:.2f} deg / {rows[-1]['max_translation']:.3f}",
                  flush=True)
    moved = truth_equilibrium(scans, truth, settings)
    lines = [f"{args.scene}, {len(files)} scans ({cpu_description()}, {time.strftime('%Y-%m-%d')}): each refinement "
             f"from the robust pose graph's poses, errors against the ground truth (degrees / metres).", "",
             "| refinement | round | RMSE | largest | translation per scan | s / round |",
             "|---|---:|---:|---:|---|---:|"]
    for row in rows:
        lines.append(f"| {row['refinement']} | {row['round']} | {row['rmse_rotation_deg']:.2f} / "
                     f"{row['rmse_translation']:.3f} | {row['max_rotation_deg']:.2f} / {row['max_translation']:.3f} | "
                     f"{' '.join(f'{t:.3f}' for t in row['translation'])} | {row['seconds']:.1f} |")
    lines += ["", "ICP of each scan against the others placed by the ground truth, from the truth, moves it by: " +
              ", ".join(f"{e['rotation_error_deg']:.2f} / {e['translation_error']:.3f}" for e in moved)]
    write_outputs("\n".join(lines), {"machine": cpu_description(), "date": time.strftime("%Y-%m-%d"),
                                     "scene": args.scene, "rows": rows, "truth_moves": moved}, args.markdown, args.json)


if __name__ == "__main__":
    main()
