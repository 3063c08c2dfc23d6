"""The default method (``auto``) beside each built-in method it combines, on pairs none of them was
tuned on, in one run; and the calibration of its doubt.

    python benchmarks/bench_default.py [--data ../shared/data/scenes/real_pairs] [--seeds 2]
        [--extra-rotation 180] [--cuts 3] [--scans 3] [--sets real 'real turned' cuts crops scans]
        [--json default.json] [--markdown default.md] [--plot doubt.png]

Sets (each pair once per seed; the seed also draws the turns):

* ``real``: the 45 real pairs (3DMatch, 3DLoMatch, KITTI) as they are;
* ``real turned``: the same with each source turned about its centroid by a random rotation of up
  to ``--extra-rotation`` degrees (the ground truth follows);
* ``cuts``: object-like pairs cut from the 10 redkitchen fragments: two balls of 0.8 m radius around
  points 0.5 m apart, the second turned about its centre by 24, 48 or 72 degrees (``--cuts`` pairs
  per fragment and angle), so overlap is partial and the motion large;
* ``crops``: the indoor real pairs with the source cut by a plane so that 30, 20 or 10 % of it
  overlaps the target (within 2.5 cm under the ground truth; pairs that overlap less already are
  left out), the low-overlap regime;
* ``scans``: synthetic range scans of object-sized things: a ball of 0.6 m radius of a redkitchen
  fragment seen by two virtual depth cameras 1.5 m away, one from where the fragment's sensor was,
  the other 24, 48 or 72 degrees round it (``--scans`` pairs per fragment and angle); each keeps
  what is visible (a depth buffer) and resamples it (one point per pixel of about the fragment's
  own spacing, with noise of half that), each scan in its camera's frame, and both are shrunk to
  a fifth (24 cm across; the translation threshold shrinks as much) — sparse scans of a few
  thousand points whose samples differ between views, as an object scanner's do.

Methods: ``auto`` (the default: ``sc2`` checked by ``fpfh``'s estimate; when its refinement is
doubtful or the check lands elsewhere, ``fpfh`` and ``vrnet`` too, the best confirmed fit kept),
``sc2``, ``fpfh``, ``vrnet``, each as ``register()`` runs it in this process with the same seed.
Reported per set and method: recall (3DMatch's thresholds indoors, KITTI's outdoors), the median
time per pair, how many wrong results carried no warning, and how many right ones carried one (false
alarms); and per set and seed, the default's recall beside the best single method's. The picture, the calibration of the tests that bring in the other estimators: the share of
``sc2`` results that are right against the fitness of its refinement (the doubt threshold marked),
and by what the default did with them (doubtful fit, check agreed, check apart).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "scenes" / "real_pairs"
METHODS = ("auto", "sc2", "fpfh", "vrnet")
SINGLE_METHODS = METHODS[1:]  # the built-in methods the default combines
CUT_RADIUS, CUT_SPACING, CUT_ANGLES = 0.8, 0.5, (24.0, 48.0, 72.0)
SCAN_RADIUS, SCAN_DISTANCE, OBJECT_SCALE = 0.6, 1.5, 0.2  # the "scans" set (metres before shrinking)
SETS = ("real", "real turned", "cuts", "crops", "scans")
TRANSFORM_DECIMALS = 7  # each run's transform as recorded (0.1 um, 1e-5 degrees: the record stays small)


def turned(points: np.ndarray, degrees: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``points`` turned about their centroid by ``degrees`` about a random axis -> (points, the 4x4 turn)."""
    from scipy.spatial.transform import Rotation

    from vrnet_ext.geometry.transforms import apply, to_homogeneous

    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(degrees)).as_matrix()
    centre = points.mean(axis=0)
    turn = to_homogeneous(R, centre - R @ centre)
    return apply(turn, points), turn


def real_cases(data: Path, seed: int, extra: float):
    """(set, name, source, target, truth, outdoor, scale) of the real pairs, turned by up to ``extra``
    degrees (scale: of the translation threshold, 1 but for the ``scans`` set)."""
    from vrnet_ext.data.real_pairs import read_manifest
    from vrnet_ext.geometry.io import read_points

    rng = np.random.default_rng(seed)
    for pair in read_manifest(data):
        source, truth = read_points(pair.source), np.loadtxt(pair.gt)
        if extra:
            source, turn = turned(source, rng.uniform(0.0, extra), rng)
            truth = truth @ np.linalg.inv(turn)
        yield ("real turned" if extra else "real"), pair.pair_id, source, read_points(pair.target), truth, pair.outdoor, 1.0


def cut_cases(data: Path, seed: int, per_angle: int):
    """(set, name, source, target, truth, outdoor, scale) of pairs cut from the redkitchen fragments."""
    from vrnet_ext.geometry.io import read_points

    rng = np.random.default_rng(1000 + seed)
    for path in sorted((data / "clouds").glob("3dm_rk_*.npy")):
        fragment = read_points(path)
        for angle in CUT_ANGLES:
            for k in range(per_angle):
                centre = fragment[rng.integers(len(fragment))]
                direction = rng.normal(size=3)
                other = centre + CUT_SPACING * direction / np.linalg.norm(direction)
                target = fragment[np.linalg.norm(fragment - centre, axis=1) < CUT_RADIUS]
                source = fragment[np.linalg.norm(fragment - other, axis=1) < CUT_RADIUS]
                if min(len(source), len(target)) < 2000:
                    continue
                source, turn = turned(source, angle, rng)
                yield "cuts", f"{path.stem} {angle:.0f} deg #{k}", source, target, np.linalg.inv(turn), False, 1.0


CROP_OVERLAPS = (0.3, 0.2, 0.1)  # the "crops" set: the share of the source's points that overlap the target
OVERLAP_RADIUS = 0.025  # a source point overlaps where a target point is this close under the truth (the manifest's)


def cropped(source: np.ndarray, target: np.ndarray, truth: np.ndarray, overlap: float) -> np.ndarray | None:
    """The source cut by a plane so that about ``overlap`` of what is left lies on the target
    (within :data:`OVERLAP_RADIUS` under the truth): the plane is normal to the direction from the
    source's centre to its overlapping part's, moved until the share fits. None where the source
    overlaps less already or too few points would be left."""
    from scipy.spatial import cKDTree

    from vrnet_ext.geometry.transforms import apply

    distance, _ = cKDTree(target).query(apply(truth, source), distance_upper_bound=OVERLAP_RADIUS)
    overlapping = np.isfinite(distance)
    if overlapping.mean() <= overlap or overlapping.sum() < 100:
        return None
    direction = source[overlapping].mean(axis=0) - source.mean(axis=0)
    along = source @ (direction / np.linalg.norm(direction))
    order = np.argsort(along)
    share = np.cumsum(overlapping[order]) / np.arange(1, len(order) + 1)  # overlap share of the k lowest
    fits = np.flatnonzero((share <= overlap) & (np.arange(1, len(order) + 1) >= 2000))
    if len(fits) == 0:
        return None
    return source[order[:fits[-1] + 1]]


def crop_cases(data: Path, seed: int):
    """(set, name, source, target, truth, outdoor, scale) of the indoor real pairs cut to lower overlaps."""
    for subset, name, source, target, truth, outdoor, scale in real_cases(data, seed, 0.0):
        if outdoor:
            continue
        for overlap in CROP_OVERLAPS:
            cut = cropped(source, target, truth, overlap)
            if cut is not None:
                yield "crops", f"{name} {overlap:.0%}", cut, target, truth, outdoor, scale


def camera_at(eye: np.ndarray, centre: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The 4x4 pose (camera to world) of a camera at ``eye`` looking at ``centre`` (its z axis),
    turned about that axis at random."""
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    side = np.cross(rng.normal(size=3), forward)
    side /= np.linalg.norm(side)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = np.stack([side, np.cross(forward, side), forward], axis=1), eye
    return pose


def range_scan(points: np.ndarray, pose: np.ndarray, pixel: float, rng: np.random.Generator) -> np.ndarray:
    """What a depth camera at ``pose`` sees of ``points`` (N, 3), in its frame: the points in front of
    it projected onto pixels of ``pixel`` radians; a point is hidden where a block of 3 x 3 pixels
    holds one nearer by more than 3 blocks' width (a depth buffer that the gaps between samples do
    not fool); each pixel returns its nearest visible point, with noise of half a pixel's footprint."""
    local = (points - pose[:3, 3]) @ pose[:3, :3]
    local = local[local[:, 2] > 1e-3]
    u = np.floor(local[:, 0] / local[:, 2] / pixel).astype(np.int64)
    v = np.floor(local[:, 1] / local[:, 2] / pixel).astype(np.int64)
    _, block = np.unique(np.stack([u // 3, v // 3], axis=1), axis=0, return_inverse=True)
    nearest = np.full(block.max() + 1, np.inf)
    np.minimum.at(nearest, block, local[:, 2])
    visible = local[:, 2] <= nearest[block] * (1.0 + 9.0 * pixel)
    local, u, v = local[visible], u[visible], v[visible]
    order = np.lexsort((local[:, 2], v, u))
    first = np.ones(len(order), dtype=bool)
    first[1:] = (np.diff(u[order]) != 0) | (np.diff(v[order]) != 0)
    seen = local[order[first]]
    return seen + rng.normal(scale=0.5 * pixel * seen[:, 2:], size=seen.shape)


def scan_cases(data: Path, seed: int, per_angle: int):
    """(set, name, source, target, truth, outdoor, scale) of synthetic range scans of balls of the
    redkitchen fragments (the module's ``scans``), shrunk by :data:`OBJECT_SCALE`."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2000 + seed)
    for path in sorted((data / "clouds").glob("3dm_rk_*.npy")):
        fragment = np.load(path).astype(np.float64)
        for angle in CUT_ANGLES:
            for k in range(per_angle):
                centre = fragment[rng.integers(len(fragment))]
                ball = fragment[np.linalg.norm(fragment - centre, axis=1) < SCAN_RADIUS]
                distance, _ = cKDTree(ball).query(ball[:: max(1, len(ball) // 2000)], 2)
                pixel = float(np.median(distance[:, 1])) / SCAN_DISTANCE  # a pixel ~ the fragment's spacing
                towards_sensor = -centre / np.linalg.norm(centre)  # a fragment's frame is its first camera's
                axis = np.cross(towards_sensor, rng.normal(size=3))
                turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(angle))
                target_camera = camera_at(centre + SCAN_DISTANCE * towards_sensor, centre, rng)
                source_camera = camera_at(centre + SCAN_DISTANCE * turn.apply(towards_sensor), centre, rng)
                target = range_scan(ball, target_camera, pixel, rng)
                source = range_scan(ball, source_camera, pixel, rng)
                if min(len(source), len(target)) < 2000:
                    continue
                truth = np.linalg.inv(target_camera) @ source_camera
                truth[:3, 3] *= OBJECT_SCALE
                yield ("scans", f"{path.stem} {angle:.0f} deg #{k}", OBJECT_SCALE * source, OBJECT_SCALE * target,
                       truth, False, OBJECT_SCALE)


def failed(message: str):
    """The record of a registration that raised: the identity, no fit, its message as the warning."""
    from vrnet_ext.registration.result import RegistrationResult

    return RegistrationResult(T_target_source=np.eye(4), initial=np.eye(4), method="", icp_step="none", iterations=0,
                              converged=False, fitness=0.0, inlier_rmse=float("nan"), correspondences=0,
                              warnings=[f"error: {message}"])


def record_of(result, truth: np.ndarray, outdoor: bool, scale: float, seconds: float) -> dict:
    from vrnet_ext.data.real_pairs import SUCCESS_THRESHOLDS
    from vrnet_ext.registration.result import transform_errors

    errors = transform_errors(result.T_target_source, truth)
    max_re, max_te = SUCCESS_THRESHOLDS["outdoor" if outdoor else "indoor"]
    success = errors["rotation_error_deg"] < max_re and errors["translation_error"] < scale * max_te
    return {"success": bool(success), **errors,
            "fitness": result.fitness, "converged": result.converged, "warnings": result.warnings,
            "consensus": result.consensus, "rival_consensus": result.rival_consensus,
            "start": result.start, "selection": result.selection, "seconds": seconds,
            "transform": np.round(np.asarray(result.T_target_source), TRANSFORM_DECIMALS).tolist()}


def summary_rows(records: list[dict]) -> list[dict]:
    rows = []
    for subset in dict.fromkeys(r["set"] for r in records):
        for method in METHODS:
            chosen = [r for r in records if r["set"] == subset and r["method"] == method]
            right = [r for r in chosen if r["success"]]
            rows.append({"set": subset, "method": method, "pairs": len(chosen), "registered": len(right),
                         "median_s": statistics.median(r["seconds"] for r in chosen),
                         "wrong_without_warning": sum(not r["success"] and not r["warnings"] for r in chosen),
                         "false_alarms": sum(bool(r["warnings"]) for r in right)})
    return rows


def seed_rows(records: list[dict]) -> list[dict]:
    """Per set and seed: the default's registered pairs and the best single method's (and which)."""
    rows = []
    for subset, seed in dict.fromkeys((r["set"], r["seed"]) for r in records):
        right = {method: sum(r["success"] for r in records if (r["set"], r["seed"], r["method"]) == (subset, seed, method))
                 for method in METHODS}
        best = max(right[method] for method in SINGLE_METHODS)
        rows.append({"set": subset, "seed": seed, "pairs": sum(1 for r in records if (r["set"], r["seed"], r["method"])
                                                               == (subset, seed, "auto")),
                     "auto": right["auto"], "best": best,
                     "best_methods": [method for method in SINGLE_METHODS if right[method] == best]})
    return rows


CHECK_OUTCOMES = ("doubtful fit", "check agreed", "check apart")  # what auto did after sc2's refinement


def check_outcome(auto: dict) -> str:
    """What the default did with sc2's refinement in one run (its ``selection`` says it)."""
    if not auto["selection"]:
        return "check agreed"
    return "check apart" if "ended apart from ICP from" in auto["selection"] else "doubtful fit"


RIVAL_EDGES = (0.0, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.5)  # bins of the rival share in the picture


def _right_by_bin(ax, values: np.ndarray, success: np.ndarray, edges, threshold: float, doubt: str) -> None:
    """One calibration panel: each result (1 = right) against ``values``, the share right per bin of
    ``edges`` (its count above), and the test's ``threshold`` (``doubt`` labels it)."""
    jitter = np.random.default_rng(0).uniform(-0.03, 0.03, len(values))
    ax.scatter(np.minimum(values, edges[-1]), success + jitter, s=8, c=np.where(success, "tab:green", "tab:red"),
               alpha=0.5, label="one pair (1 = right)")
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (values >= low) & (values < high)
        if inside.any():
            ax.plot([low, high], [success[inside].mean()] * 2, color="black", linewidth=2)
            ax.annotate(f"{inside.sum()}", ((low + high) / 2, success[inside].mean() + 0.03), ha="center", fontsize=7)
    ax.plot([], [], color="black", linewidth=2, label="share right in the bin (n above)")
    ax.axvline(threshold, color="tab:blue", linestyle="--", label=doubt)
    ax.set_ylabel("right (rotation and translation within thresholds)")
    ax.set_ylim(-0.1, 1.15)
    ax.legend(loc="lower right", fontsize=8)


def plot(records: list[dict], path: str) -> None:
    """Left: the share of ``sc2`` results that are right against the fitness of their refinement (the
    doubt threshold marked). Middle: the share right of ``sc2``'s results by what the default then
    did (refinement doubtful; confident and the second estimator's check agreed; confident and it
    landed elsewhere). Right: the share of the default's results that are right against its rival
    alignment's support (matches consistent with the best other alignment, as a share of the
    estimate's; the ambiguity warning's threshold marked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vrnet_ext.registration.pipeline import AMBIGUOUS, LOW_FITNESS

    first = [r for r in records if r["method"] == "sc2"]
    fig, (ax, check, rival) = plt.subplots(1, 3, figsize=(18, 4.5), gridspec_kw={"width_ratios": [2, 1, 1.6]})
    _right_by_bin(ax, np.array([r["fitness"] for r in first]), np.array([r["success"] for r in first]),
                  (0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.6, 1.0), LOW_FITNESS,
                  f"doubt below {LOW_FITNESS} (or ICP not converged)")
    ax.set_xlabel("fitness of the refinement from sc2 (share of source points with a target point within reach)")
    ax.set_title("sc2's fit against being right")
    runs = {(r["set"], r["pair"], r["seed"]): r for r in first}
    outcome = {key: check_outcome(r) for r in records if r["method"] == "auto"
               for key in [(r["set"], r["pair"], r["seed"])] if key in runs}
    shares, counts = [], []
    for name in CHECK_OUTCOMES:
        right = [runs[key]["success"] for key, what in outcome.items() if what == name]
        shares.append(np.mean(right) if right else 0.0)
        counts.append(len(right))
    bars = check.bar(range(len(CHECK_OUTCOMES)), shares, color=["tab:gray", "tab:green", "tab:red"])
    for bar, count in zip(bars, counts):
        check.annotate(f"n = {count}", (bar.get_x() + bar.get_width() / 2, bar.get_height() + 0.02), ha="center",
                       fontsize=8)
    check.set_xticks(range(len(CHECK_OUTCOMES)), CHECK_OUTCOMES)
    check.set_ylim(0, 1.15)
    check.set_ylabel("share of sc2's results that are right")
    check.set_title("What the default did with sc2's refinement")
    measured = [r for r in records if r["method"] == "auto" and r.get("consensus", 0) > 0]
    _right_by_bin(rival, np.array([r["rival_consensus"] / r["consensus"] for r in measured]),
                  np.array([r["success"] for r in measured]), RIVAL_EDGES, AMBIGUOUS,
                  f"ambiguity warning from {AMBIGUOUS}")
    rival.set_xlabel("rival alignment's consistent matches / the estimate's")
    rival.set_title("The default's result against its rival's support")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> None:
    from vrnet_ext.cli.common import DefaultsHelpFormatter
    from vrnet_ext.registration import register

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the real pairs' folder (MANIFEST.tsv, clouds/)")
    parser.add_argument("--seeds", type=int, default=2, help="seeds per pair (each draws its own turns)")
    parser.add_argument("--extra-rotation", type=float, default=180.0, help="largest turn of the 'real turned' set")
    parser.add_argument("--cuts", type=int, default=3, help="pairs per fragment and angle of the 'cuts' set (0: none)")
    parser.add_argument("--scans", type=int, default=3,
                        help="pairs per fragment and angle of the 'scans' set (0: none)")
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS, help="sets to run")
    parser.add_argument("--limit", type=int, default=None, help="at most this many pairs per set and seed")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    parser.add_argument("--plot", default=None, help="draw the calibration picture here (none: no picture)")
    args = parser.parse_args(argv)
    data, records = Path(args.data), []
    for seed in range(args.seeds):
        sources = {"real": real_cases(data, seed, 0.0), "real turned": real_cases(data, seed, args.extra_rotation),
                   "cuts": cut_cases(data, seed, args.cuts), "crops": crop_cases(data, seed),
                   "scans": scan_cases(data, seed, args.scans)}
        for subset in args.sets:
            for count, (name_set, name, source, target, truth, outdoor, scale) in enumerate(sources[subset]):
                if args.limit is not None and count >= args.limit:
                    break
                for method in METHODS:  # interleaved: every method once per pair
                    started = time.perf_counter()
                    try:
                        result = register(source, target, method=method, seed=seed)
                    except ValueError as error:  # e.g. no consistent matches: a failure with its message
                        result = failed(str(error))
                    record = record_of(result, truth, outdoor, scale, time.perf_counter() - started)
                    records.append({"set": name_set, "pair": name, "seed": seed, "method": method, **record})
                    print(f"{name_set} | {name} | seed {seed} | {method}: {'ok' if record['success'] else 'FAIL'} "
                          f"fitness {record['fitness']:.3f} {record['seconds']:.2f} s", file=sys.stderr, flush=True)
    rows = summary_rows(records)
    lines = [f"The default (`auto`) beside the methods it combines ({cpu_description()}, {time.strftime('%Y-%m-%d')}; "
             f"{args.seeds} seeds, turns up to {args.extra_rotation:g} deg).", "",
             "| set | method | registered | median s / pair | wrong without a warning | false alarms |",
             "|---|---|---:|---:|---:|---:|"]
    lines += [f"| {r['set']} | {r['method']} | {r['registered']} / {r['pairs']} ({r['registered'] / r['pairs']:.1%}) | "
              f"{r['median_s']:.2f} | {r['wrong_without_warning']} | {r['false_alarms']} |" for r in rows]
    seeds = seed_rows(records)
    lines += ["", "Per seed: the default beside the best single method (the floor: never below it).", "",
              "| set | seed | auto | best single method |", "|---|---:|---:|---|"]
    lines += [f"| {r['set']} | {r['seed']} | {r['auto']} / {r['pairs']} | {r['best']} ({', '.join(r['best_methods'])}) |"
              for r in seeds]
    write_outputs("\n".join(lines), {"machine": cpu_description(), "date": time.strftime("%Y-%m-%d"),
                                     "summary": rows, "per_seed": seeds, "runs": records}, args.markdown, args.json)
    if args.plot:
        plot(records, args.plot)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
