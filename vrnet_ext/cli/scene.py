"""``vrnet register-scene``: many scans of one scene into one frame, with a fused cloud and a map
(:mod:`vrnet_ext.registration.multiway`)."""
from __future__ import annotations

import resource
import sys
from pathlib import Path

from vrnet_ext.cli.common import (DefaultsHelpFormatter, Switch, as_flags, json_output, nonnegative_int, picture_path,
                                  positive_int, report_and_record, writable_path)
from vrnet_ext.cli.registering import add_registration_options, add_success_options, registration_arguments

MAX_LIST_BYTES = 1 << 24  # a list of scan paths (16 MB is ~100,000 paths)


def add_register_scene(sub) -> None:
    p = sub.add_parser(
        "register-scene", help="align many scans of one scene into one frame (pose graph, fused cloud, map)",
        description="Registers pairs of SCANS as `vrnet register` does (every pair of a small set; for more scans "
                    "than --all-pairs-up-to, each with its next --neighbours and with the scans the first poses "
                    "put nearest), ranks the pairs by the loops of three they close consistently, chains the "
                    "best-supported ones into initial poses and optimises all poses with a robust pose graph that "
                    "drops the wrong pairs. Prints each scan's pose (4x4, into the first scan's frame) and the "
                    "pairs dropped; writes the fused cloud, a top-view map and a JSON record on request. With "
                    "--gt-poses it reports each scan's errors and the pairs registered before and after the "
                    "optimisation. Use it for a set of fragments or a scan sequence of one place; for unrelated "
                    "pairs, `vrnet register-batch`.",
        formatter_class=DefaultsHelpFormatter)
    p.add_argument("scans", nargs="*", help="point-cloud files, in capture order for a sequence")
    p.add_argument("--list", default=None, help="a text file of scan paths, one per line (relative to its folder)")
    p.add_argument("--json", type=json_output, default=None, help="write the poses, pairs and warnings here "
                                                                   "(- for standard output)")
    p.add_argument("--out", type=writable_path, default=None, help="write the fused cloud as a PLY here")
    p.add_argument("--plot", type=picture_path, default=None, help="draw a top view of the map here (e.g. map.png)")
    p.add_argument("--cache", type=writable_path, default=None,
                   help="JSON Lines file of registered pairs: read and extended, so a stopped run resumes and a "
                        "rerun with the same scans and settings skips the pairs it has")
    p.add_argument("--gt-poses", default=None,
                   help="ground-truth poses, one per scan in order: lines of 12 numbers (KITTI poses.txt), of 16, "
                        "or 4 lines of 4; or a 3DMatch gt.log of pairs, the scans named cloud_bin_<i>")
    from vrnet_ext.names import SCENE_ALL_PAIRS_UP_TO, SCENE_LOOP_CANDIDATES, SCENE_NEIGHBOURS

    add_success_options(p, "a pair")
    p.add_argument("--all-pairs-up-to", type=nonnegative_int, default=SCENE_ALL_PAIRS_UP_TO,
                   help="register every pair of at most this many scans")
    p.add_argument("--neighbours", type=positive_int, default=SCENE_NEIGHBOURS,
                   help="more scans: register each with its next this many")
    p.add_argument("--loop-candidates", type=nonnegative_int, default=SCENE_LOOP_CANDIDATES,
                   help="more scans: and with up to this many others that the first poses put nearest")
    p.add_argument("--map-icp", action=Switch, default=True,
                   help="after the pose graph, refine each scan by ICP against the scans it was registered with")
    p.add_argument("--progress", action=Switch, default=True, help="progress bar")
    add_registration_options(p)


def scan_list(path: str) -> list[str]:
    """The scan paths of a --list file (blank and '#' lines skipped), relative to its folder."""
    listed = Path(path)
    if not listed.is_file():
        raise FileNotFoundError(f"--list {path}: no such file")
    if listed.stat().st_size > MAX_LIST_BYTES:
        raise ValueError(f"--list {path}: {listed.stat().st_size} bytes is too large for a list of scan paths")
    try:
        lines = listed.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise ValueError(f"--list {path}: not a text file of scan paths") from None
    return [str(listed.parent / line.strip()) for line in lines if line.strip() and not line.lstrip().startswith("#")]


def run_register_scene(args) -> int:
    return report_and_record(args, _register_scene_and_report)


def _register_scene_and_report(args) -> dict:
    """Registers the scene, prints the report and writes --out / --plot -> the JSON record."""
    import numpy as np

    from vrnet_ext.geometry.io import read_poses, write_ply
    from vrnet_ext.registration.multiway import SceneOptions, register_scene

    scans = list(args.scans) + (scan_list(args.list) if args.list else [])
    if len(scans) < 2:
        raise ValueError("give at least 2 scans (as arguments or with --list)")
    truth = read_poses(args.gt_poses, scans) if args.gt_poses else None
    options = SceneOptions(register=registration_arguments(args), all_pairs_up_to=args.all_pairs_up_to,
                           neighbours=args.neighbours, loop_candidates=args.loop_candidates, map_icp=args.map_icp)
    result = register_scene(scans, options, cache=args.cache, progress=args.progress)
    record = result.to_dict()
    record["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    dropped = [edge for edge in result.edges if not edge.kept]
    print(f"{int(result.placed.sum())} of {len(scans)} scans placed from {len(result.edges)} registered pairs "
          f"({len(dropped)} dropped by the pose graph); ICP voxel {result.voxel:.3g}, reach {result.reach:.3g}; "
          f"{sum(result.seconds.values()):.1f} s, peak memory {record['peak_rss_mb']:.0f} MB")
    for edge in dropped:
        print(f"  dropped {result.names[edge.source]} -> {result.names[edge.target]}: fitness {edge.fitness:.3f}, "
              f"moves its pairs by {edge.displacement:.3g} RMS under the final poses")
    for name, pose, placed in zip(result.names, result.poses, result.placed):
        if placed:
            print(f"{name}:\n{np.array2string(pose, precision=6, suppress_small=True)}")
    for warning in result.warnings:
        print(f"vrnet register-scene: warning: {as_flags(warning, vars(args))}", file=sys.stderr)
    if truth is not None:
        from vrnet_ext.registration.scene_metrics import scene_errors

        errors = scene_errors(result, truth, success_rotation_deg=args.success_rotation,
                              success_translation=args.success_translation)
        record["errors"] = errors
        for label in ("initial", "optimised"):
            e = errors[label]
            print(f"{label} poses: rotation error RMSE {e['rmse_rotation_deg']:.3f} deg (largest "
                  f"{e['max_rotation_deg']:.3f}), translation error RMSE {e['rmse_translation']:.4g} (largest "
                  f"{e['max_translation']:.4g})")
        print(f"pairs registered: {errors['recall_before']:.1%} pairwise, {errors['recall_after']:.1%} after the "
              f"pose graph")
    if args.out:
        write_ply(args.out, result.fused)
        print(f"wrote {args.out} ({len(result.fused)} points)")
    if args.plot:
        from vrnet_ext.geometry.io import read_points
        from vrnet_ext.plots import plot_scene

        clouds = [read_points(scan) if placed else None for scan, placed in zip(scans, result.placed)]
        print(f"wrote {plot_scene(clouds, result.poses, result.names, result.edges, args.plot)}")
    return record
