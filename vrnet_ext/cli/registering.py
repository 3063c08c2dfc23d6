"""``vrnet register`` and ``vrnet demo``."""
from __future__ import annotations

import argparse
import resource
import sys

from vrnet_ext.cli.common import (DefaultsHelpFormatter, RenamedOption, Switch, as_flags, device_name, json_output,
                                  memory_size, nonnegative_int, picture_path, positive_float, positive_int,
                                  report_and_record, writable_path)


def add_register(sub) -> None:
    p = sub.add_parser(
        "register", help="register two real scans (PLY, PCD, NPY, XYZ/TXT/PTS/CSV, KITTI .bin)",
        description="Estimates the rigid transform taking SOURCE onto TARGET: a global estimate (--method sc2: "
                    "FPFH matches filtered by spatial consistency, the default; --method fpfh: FPFH + RANSAC; "
                    "--method vrnet: the shipped scene model, FPFH descriptors under VRNet's head, or --checkpoint, "
                    "with ICP also started from sc2's estimate and the better fit kept; --method fgr: FPFH + Fast "
                    "Global Registration; --method icp: none), refined by ICP (--icp-step) on voxel-downsampled "
                    "clouds. --max-memory sizes everything to a memory budget. Prints the 4x4 transform (source -> "
                    "target); --json, --out and --plot write the result, the moved source and a picture.",
        formatter_class=DefaultsHelpFormatter)
    p.add_argument("source", help="point-cloud file to move")
    p.add_argument("target", help="point-cloud file to align to (same unit)")
    p.add_argument("--gt", default=None,
                   help="ground truth, to report the errors: a 4x4 transform file (SOURCE into TARGET's frame), or a "
                        "3DMatch gt.log (the pair picked by --gt-fragments, or by cloud_bin_<i> file names)")
    p.add_argument("--gt-fragments", type=int, nargs=2, metavar=("SOURCE_INDEX", "TARGET_INDEX"), default=None,
                   help="with a 3DMatch gt.log: the fragment indices of SOURCE and TARGET")
    p.add_argument("--json", type=json_output, default=None, help="write the result here (- for standard output)")
    p.add_argument("--out", type=writable_path, default=None, help="write the moved source as a PLY here")
    p.add_argument("--plot", type=picture_path, default=None,
                   help="write a picture here (.png, .pdf, .svg, .jpg): the source before any motion, after the result "
                        "and after --gt, from above and from the side")
    add_registration_options(p)


def add_registration_options(p) -> None:
    """The options of how to register (shared by ``register`` and ``register-batch``)."""
    from vrnet_ext.names import (BACKENDS, DEFAULT_BACKEND, DEFAULT_ICP_STEP, DEFAULT_METHOD, GLOBAL_ESTIMATORS,
                                 ICP_STEPS)
    from vrnet_ext.registration.counts import PointCounts

    p.add_argument("--method", choices=GLOBAL_ESTIMATORS, default=argparse.SUPPRESS,
                   help=f"global estimate (default: {DEFAULT_METHOD}: sc2, checked by fpfh's estimate; when ICP from "
                        f"sc2's estimate is doubtful or fpfh lands elsewhere, vrnet too, the best fit that another "
                        f"confirms kept, else vrnet's; vrnet when --checkpoint is given)")
    initial = p.add_mutually_exclusive_group()
    initial.add_argument("--checkpoint", default=None,
                         help="with --method vrnet: shipped model name or checkpoint (a scene model of `vrnet "
                              "train-scene`, or best.pt of `vrnet train`); default: the shipped scene model")
    initial.add_argument("--fpfh", action="store_true", help=argparse.SUPPRESS)  # 0.1's name of --method fpfh
    p.add_argument("--global-points", type=positive_int, default=PointCounts.global_points,
                   help="about this many points per scan for the global estimate (scene model, FPFH)")
    p.add_argument("--fpfh-points", dest="global_points", type=positive_int, action=RenamedOption,
                   help=argparse.SUPPRESS)
    p.add_argument("--max-memory", type=memory_size, default=None,
                   help="peak memory budget of the whole run, e.g. 2GB or 512MB (with --device cuda: of the "
                        "GPU's memory): sizes the point counts and fails at once if the budget cannot be met")
    p.add_argument("--network-points", type=positive_int, default=PointCounts.network_points,
                   help="points per cloud fed to VRNet")
    p.add_argument("--icp-points", type=positive_int, default=PointCounts.icp_points,
                   help="about this many points per cloud for ICP")
    p.add_argument("--voxel-size", type=positive_float, default=None,
                   help="ICP voxel edge, in the scans' unit (default: from --icp-points)")
    p.add_argument("--max-distance", type=positive_float, default=None,
                   help="ICP inlier reach, in the scans' unit (default: 3 voxels)")
    p.add_argument("--icp-iterations", type=nonnegative_int, default=50, help="0: no ICP")
    p.add_argument("--icp-tolerance", type=positive_float, default=1e-4,
                   help="ICP stops when a step moves the transform by less (radians; the scans' unit)")
    p.add_argument("--coarse-start", action=Switch, default=True,
                   help="ICP from no motion first runs on 4x coarser voxels with a 4x longer reach")
    p.add_argument("--icp-step", choices=ICP_STEPS, default=DEFAULT_ICP_STEP,
                   help="ICP step: point-to-point (Kabsch), point-to-plane, or plane-to-plane (GICP)")
    p.add_argument("--estimator", dest="icp_step", choices=ICP_STEPS, action=RenamedOption, help=argparse.SUPPRESS)
    p.add_argument("--backend", choices=BACKENDS, default=DEFAULT_BACKEND,
                   help="ext: the compiled kernels; torch: the pure-PyTorch references")
    p.add_argument("--device", type=device_name, default="cpu",
                   help="torch device to run on, e.g. cpu or cuda (cpu unless asked: the pipeline's voxels, normals, "
                        "FPFH and global estimates run CPU kernels, a GPU speeds up ICP's products only)")
    p.add_argument("--seed", type=int, default=0, help="seed of the global estimate's sampling")


INITIAL_NAMES = {"vrnet": "VRNet", "fpfh": "FPFH + RANSAC", "sc2": "FPFH + spatial consistency", "fgr": "FPFH + FGR",
                 "icp": "identity"}


def run_register(args) -> int:
    return report_and_record(args, _register_and_report)


def _register_and_report(args) -> dict:
    """Registers, prints the report and writes --out / --plot -> the JSON record."""
    import numpy as np

    from vrnet_ext.geometry.io import read_ground_truth, read_points, write_ply
    from vrnet_ext.geometry.transforms import apply
    from vrnet_ext.names import DEFAULT_SCENE_MODEL
    from vrnet_ext.registration import register, transform_errors

    arguments = registration_arguments(args)
    src, tgt = read_points(args.source), read_points(args.target)
    fragments = tuple(args.gt_fragments) if args.gt_fragments else None
    truth = read_ground_truth(args.gt, args.source, args.target, fragments) if args.gt else None
    result = register(src, tgt, **arguments)
    record = result.to_dict()
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    record.update(source=str(args.source), target=str(args.target), peak_rss_mb=peak_mb,
                  checkpoint=args.checkpoint or (DEFAULT_SCENE_MODEL if result.method == "vrnet" or
                                                  "initial (vrnet)" in result.seconds else None))
    unconverged = " (not converged)" if result.iterations and not result.converged else ""
    print(f"source {len(src)} points, target {len(tgt)} points; "
          f"initial estimate: {INITIAL_NAMES[result.start]}; "
          f"ICP ({result.icp_step}) iterations {result.iterations}{unconverged}, "
          f"fitness {result.fitness:.3f}, inlier RMSE {result.inlier_rmse:.4g}; "
          f"{sum(result.seconds.values()):.1f} s, peak memory {peak_mb:.0f} MB")
    for warning in result.warnings:
        print(f"vrnet register: warning: {as_flags(warning, vars(args))}", file=sys.stderr)
    print("transform (source -> target):")
    print(np.array2string(result.T_target_source, precision=6, suppress_small=True))
    if truth is not None:
        record["errors_initial"] = transform_errors(result.initial, truth)
        record["errors"] = transform_errors(result.T_target_source, truth)
        for label in ("errors_initial", "errors"):
            e = record[label]
            print(f"{label}: rotation {e['rotation_error_deg']:.3f} deg, translation {e['translation_error']:.4g}")
        swapped = transform_errors(result.T_target_source, np.linalg.inv(truth))
        if swapped["rotation_error_deg"] < 0.2 * record["errors"]["rotation_error_deg"] and \
                record["errors"]["rotation_error_deg"] > 2.0:
            print(f"vrnet register: warning: the estimate matches the inverse of --gt {args.gt} far better "
                  f"({swapped['rotation_error_deg']:.2f} deg): --gt must map SOURCE into TARGET's frame; this one "
                  f"seems to map TARGET into SOURCE's", file=sys.stderr)
    if args.out:
        write_ply(args.out, apply(result.T_target_source, src))
        print(f"wrote {args.out}")
    if args.plot:
        from vrnet_ext.plots import plot_registration

        views = {"input (no motion)": np.eye(4), "result": result.T_target_source}
        if truth is not None:
            views["ground truth"] = truth
        print(f"wrote {plot_registration(src, tgt, views, args.plot, title=plot_title(result, record))}")
    return record


def plot_title(result, record: dict) -> str:
    """What a picture of a registration says above it: the method, the fit, the errors against the
    ground truth when there is one, and the first warning."""
    lines = [f"{INITIAL_NAMES[result.start]} + ICP ({result.icp_step}): fitness {result.fitness:.1%}, "
             f"inlier RMSE {result.inlier_rmse:.3g}"]
    if "errors" in record:
        errors = record["errors"]
        lines.append(f"against the ground truth: rotation {errors['rotation_error_deg']:.2f} deg, translation "
                     f"{errors['translation_error']:.3g}")
    if result.warnings:
        lines.append(f"warning: {result.warnings[0][:110]}")
    return "\n".join(lines)


def add_success_options(p, what: str) -> None:
    """--success-rotation and --success-translation: when ``what`` counts as registered."""
    from vrnet_ext.names import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION

    p.add_argument("--success-rotation", type=positive_float, default=SUCCESS_ROTATION_DEG,
                   help=f"{what} counts as registered below this rotation error (degrees)")
    p.add_argument("--success-translation", type=positive_float, default=SUCCESS_TRANSLATION,
                   help="... and below this translation error (the scans' unit)")


def registration_arguments(args) -> dict:
    """``register()``'s keyword arguments from the command's options (the model loaded first when
    --checkpoint names one, so that a bad file fails before any scan is read; the method left to
    ``register()``'s default when no option names one)."""
    from vrnet_ext.registration import IcpSettings

    if args.max_memory is not None and not str(args.device).startswith("cuda"):  # a GPU's: planned per run
        from vrnet_ext.registration.budget import require_headroom

        require_headroom(args.max_memory)
    if args.fpfh:
        print("vrnet: warning: --fpfh is now --method fpfh", file=sys.stderr)
    method = getattr(args, "method", None) or ("fpfh" if args.fpfh else "vrnet" if args.checkpoint else None)
    if args.fpfh and method != "fpfh" or args.checkpoint and method != "vrnet":
        raise ValueError(f"--method {method} does not take {'--fpfh' if args.fpfh else '--checkpoint'}")
    model = None
    if args.checkpoint:
        from vrnet_ext.model.pretrained import load_model

        model = load_model(args.checkpoint, args.device)[0]
    icp_settings = IcpSettings(step=args.icp_step, points=args.icp_points, voxel_size=args.voxel_size,
                               max_distance=args.max_distance, max_iterations=args.icp_iterations,
                               transform_tolerance=args.icp_tolerance, coarse_start=args.coarse_start)
    return dict(method=method, model=model, global_points=args.global_points, network_points=args.network_points,
                icp_settings=icp_settings, seed=args.seed, device=args.device, backend=args.backend,
                max_memory=args.max_memory)


def add_demo(sub) -> None:
    p = sub.add_parser("demo", help="register a few pairs with the shipped model (no data needed)",
                       description="Builds pairs with the paper's protocol (768-point partial views, angles in "
                                   "[0, 45) deg) from procedural chairs, or from ModelNet40 test shapes with "
                                   "--data-dir, registers them with a shipped model, prints the errors and times "
                                   "and draws the first pair.",
                       formatter_class=DefaultsHelpFormatter)
    p.add_argument("--checkpoint", default=None,
                   help="shipped model name or checkpoint path, as for `vrnet eval` (default: the shipped PV/UPC "
                        "model)")
    p.add_argument("--model", dest="checkpoint", action=RenamedOption, help=argparse.SUPPRESS)
    p.add_argument("--data-dir", default=None, help="use ModelNet40 test shapes from this folder instead")
    p.add_argument("--pairs", type=int, default=4, help="pairs to register")
    p.add_argument("--seed", type=int, default=0, help="seed of the shapes and motions")
    p.add_argument("--out", type=picture_path, default="demo.png", help="picture of the first pair")
    p.add_argument("--json", type=json_output, default=None, help="also write the results here (- for standard output)")


def run_demo(args) -> int:
    return report_and_record(args, _demo_and_report)


def _demo_and_report(args) -> dict:
    """Runs the demo and prints its table -> the JSON record."""
    from vrnet_ext.demo import run_demo
    from vrnet_ext.model.pretrained import DEFAULT_MODEL, load_vrnet

    name = args.checkpoint or DEFAULT_MODEL
    model, _ = load_vrnet(name)
    result = run_demo(model, args.pairs, args.seed, args.data_dir, args.out)
    print(f"model {name}; {result['shapes']}")
    print(f"{'pair':>4} {'true angle':>11} {'rot. error':>11} {'VCP-only':>9} {'transl. error':>14} {'time':>8}")
    for row in result["pairs"]:
        print(f"{row['pair']:>4} {row['true_angle_deg']:>9.1f}°  {row['rotation_error_deg']:>9.3f}° "
              f"{row['vcp_only_rotation_error_deg']:>8.3f}° {row['translation_error']:>14.4f} {row['seconds']:>7.3f}s")
    print(f"mean rotation error {result['mean_rotation_error_deg']:.3f}°, mean translation error "
          f"{result['mean_translation_error']:.4f}, median {result['median_seconds_per_pair']:.3f} s per pair")
    print("(VCP-only: the rotation error of a Procrustes on the virtual corresponding points alone, before the "
          "correction walk rectifies them: what the walk adds)")
    if result.get("plot"):
        print(f"wrote {result['plot']}")
    return result
