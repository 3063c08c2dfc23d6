"""Many scans of one scene in one frame (multiway registration, as Open3D's tutorial and mapping
tools do it): candidate pairs registered with the pairwise pipeline (each scan prepared once),
the edges ranked by the loops they close (:mod:`~vrnet_ext.registration.cycles`), initial poses
chained along the best-supported spanning tree, then a robust pose-graph optimisation
(:mod:`~vrnet_ext.registration.pose_graph`) that drops the wrong edges; a fused cloud of every
placed scan. Poses are ``T_first_scan`` (4, 4): each scan's points into the first readable scan's
frame (:mod:`vrnet_ext.geometry.transforms`).
"""
from __future__ import annotations

import hashlib
import itertools
import json
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vrnet_ext.geometry.atomic import write_json_lines
from vrnet_ext.geometry.io import PointCloudError, as_points
from vrnet_ext.geometry.lie import point_information
from vrnet_ext.geometry.preprocessing import coarse_in_float32, voxel_downsample, voxel_size_for
from vrnet_ext.geometry.transforms import apply, in_shifted_frames
from vrnet_ext.names import SCENE_ALL_PAIRS_UP_TO, SCENE_LOOP_CANDIDATES, SCENE_NEIGHBOURS
from vrnet_ext.registration.cycles import spanning_tree, triangle_support
from vrnet_ext.registration.pipeline import RegistrationRun, register_prepared
from vrnet_ext.registration.pose_graph import PoseEdge, PoseGraphSettings, bridges, optimize_pose_graph
from vrnet_ext.registration.prepared import PreparedScan, ScanPair
from vrnet_ext.registration.refinement import IcpFailure, icp, pairs_within_reach

MIN_SCAN_POINTS = 100  # fewer points than this cannot be registered reliably: such a scan is skipped
REACH_VOXELS = 3.0  # the ICP reach and the pose graph's, in ICP voxels (as register()'s default reach)


@dataclass(frozen=True)
class SceneOptions:
    """How :func:`register_scene` works. ``register``: the keyword arguments of
    :func:`~vrnet_ext.registration.register` for every pair (method, model, global_points,
    network_points, icp_settings, seed, device, backend; not max_memory); the global and ICP voxel
    edges are chosen once for the whole scene (the median of the scans' own) unless
    ``icp_settings.voxel_size`` fixes the ICP one. Candidate pairs: every pair when there are at most
    ``all_pairs_up_to`` scans; else each scan with its next ``neighbours`` in the given order, then
    with up to ``loop_candidates`` scans that those first poses put nearest (loop closures).
    ``map_icp``: after the pose graph, each placed scan is refined by ICP against the scans it was
    registered with, as the optimised poses place them (:func:`_refine_against_map`)."""

    register: dict[str, Any] = field(default_factory=dict)
    all_pairs_up_to: int = SCENE_ALL_PAIRS_UP_TO
    neighbours: int = SCENE_NEIGHBOURS
    loop_candidates: int = SCENE_LOOP_CANDIDATES
    map_icp: bool = True

    def __post_init__(self) -> None:
        for name in ("all_pairs_up_to", "neighbours", "loop_candidates"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < (name == "neighbours"):
                raise ValueError(f"SceneOptions.{name} must be an integer >= {int(name == 'neighbours')}, "
                                 f"got {value!r}")
        if self.register.get("max_memory") is not None:
            raise ValueError("register_scene does not take max_memory: give icp_settings.voxel_size and "
                             "global_points to bound the work per pair")


@dataclass(kw_only=True)
class SceneEdge:
    """One registered pair: scans ``source`` and ``target`` (indices into the scans),
    ``T_target_source`` (4, 4), the pairwise fitness, inlier RMSE and correspondences, the loops of
    three it closes consistently (``support``), whether the initial spanning tree used it
    (``in_tree``), and after the optimisation its ``weight``, whether it was ``kept``, and how far
    the pose graph's poses move its correspondences (``displacement``, RMS, the scans' unit)."""

    source: int
    target: int
    T_target_source: np.ndarray
    fitness: float
    inlier_rmse: float
    correspondences: int
    warnings: list[str]
    seconds: float
    information: np.ndarray = field(repr=False)
    support: int = 0
    in_tree: bool = False
    weight: float = float("nan")
    kept: bool = False
    displacement: float = float("nan")

    def to_dict(self) -> dict:
        return {**asdict(self), "T_target_source": np.asarray(self.T_target_source).tolist(),
                "information": np.asarray(self.information).tolist()}


@dataclass(kw_only=True)
class SceneResult:
    """The scene: ``names`` (P,) of the scans, ``poses`` (P, 4, 4) ``T_first_scan`` (NaN for a scan
    not ``placed``), ``initial_poses`` chained along the spanning tree before the optimisation,
    the ``edges`` (:class:`SceneEdge`), ``fused`` (F, 3): every placed scan moved into the first's
    frame and merged on the ICP voxel grid (``voxel``), ``reach`` the ICP and pose-graph reach,
    ``warnings``, ``seconds`` by stage."""

    names: list[str]
    poses: np.ndarray
    initial_poses: np.ndarray
    placed: np.ndarray
    edges: list[SceneEdge]
    fused: np.ndarray
    voxel: float
    reach: float
    warnings: list[str]
    seconds: dict[str, float]

    def to_dict(self) -> dict:
        """JSON-ready (without the fused cloud): poses as nested lists, null for scans not placed."""
        return {"names": self.names,
                "poses": [pose.tolist() if placed else None for pose, placed in zip(self.poses, self.placed)],
                "initial_poses": [pose.tolist() if placed else None
                                  for pose, placed in zip(self.initial_poses, self.placed)],
                "edges": [edge.to_dict() for edge in self.edges], "voxel": self.voxel, "reach": self.reach,
                "fused_points": len(self.fused), "warnings": self.warnings, "seconds": self.seconds}


@dataclass
class _Scene:
    """The scans being registered: names, prepared scans (None: skipped), the shift that brought
    them near the origin, the voxels and the pairwise run."""

    names: list[str]
    scans: list[PreparedScan | None]
    shift: np.ndarray
    global_voxel: float
    voxel: float
    reach: float
    run: RegistrationRun
    warnings: list[str]


def _default_names(scans: Sequence) -> list[str]:
    """A file's name (its path where two share a name), else ``scan <i>``."""
    paths = [Path(scan) if isinstance(scan, (str, os.PathLike)) else None for scan in scans]
    short = [path.name for path in paths if path is not None]
    unique = len(set(short)) == len(short)
    return [(path.name if unique else str(path)) if path is not None else f"scan {i}" for i, path in enumerate(paths)]


def _read_scans(scans: Sequence, names: Sequence[str] | None, options: SceneOptions) -> _Scene:
    """Every scan read (an unreadable or too small one skipped with a warning naming it), shifted
    near the origin when float32 would blur it, and the scene's voxels chosen."""
    if names is not None and len(names) != len(scans):
        raise ValueError(f"names has {len(names)} entries for {len(scans)} scans")
    names = [str(name) for name in names] if names is not None else _default_names(scans)
    points: list[np.ndarray | None] = []
    warnings = []
    for name, scan in zip(names, scans):
        try:
            cloud = as_points(scan, name)
            if len(cloud) < MIN_SCAN_POINTS:
                raise ValueError(f"{name}: {len(cloud)} points, fewer than {MIN_SCAN_POINTS}")
            points.append(cloud)
        except (PointCloudError, FileNotFoundError, ValueError) as error:
            warnings.append(f"skipped {error}" if str(error).startswith(name) else f"skipped {name}: {error}")
            points.append(None)
    usable = [cloud for cloud in points if cloud is not None]
    if len(usable) < 2:
        raise ValueError(f"register_scene needs at least 2 readable scans with {MIN_SCAN_POINTS}+ points, got "
                         f"{len(usable)}" + (f" ({'; '.join(warnings)})" if warnings else ""))
    extent = max(float(np.max(cloud.max(0) - cloud.min(0))) for cloud in usable)
    largest = max(float(np.abs(cloud).max()) for cloud in usable)
    shift = np.median(usable[0], axis=0) if coarse_in_float32(largest, extent) else np.zeros(3)
    run = RegistrationRun.of(**options.register)
    global_voxel = float(np.median([voxel_size_for(cloud, run.counts.global_points) for cloud in usable]))
    voxel = run.icp.voxel_size or float(np.median([voxel_size_for(cloud, run.counts.icp_points) for cloud in usable]))
    reach = run.icp.max_distance or REACH_VOXELS * voxel
    run = replace(run, icp=replace(run.icp, voxel_size=voxel, max_distance=reach))
    prepared = [PreparedScan(cloud - shift, run.device) if cloud is not None else None for cloud in points]
    return _Scene(names=names, scans=prepared, shift=shift, global_voxel=global_voxel, voxel=voxel, reach=reach,
                  run=run, warnings=warnings)


def _run_key(scene: _Scene) -> str:
    """What a cached pair depends on besides its two scans: the run's settings and the voxels."""
    run = scene.run
    model = getattr(run.estimator, "model", None)
    weights = hashlib.blake2b(digest_size=16)
    if model is not None:
        for tensor in model.state_dict().values():
            weights.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    settings = dict(method=getattr(run.estimator, "name", type(run.estimator).__name__), counts=asdict(run.counts),
                    icp=asdict(run.icp), seed=run.seed, backend=run.backend, global_voxel=scene.global_voxel,
                    model=weights.hexdigest() if model is not None else None)
    return json.dumps(settings, sort_keys=True, default=str)


def _digest(scan: PreparedScan) -> str:
    return hashlib.blake2b(np.ascontiguousarray(scan.points).tobytes(), digest_size=16).hexdigest()


RECORD_SHAPES = {"T_target_source": (4, 4), "information": (6, 6), "fitness": (), "inlier_rmse": (),
                 "correspondences": (), "seconds": ()}


def _complete(record: dict) -> bool:
    """Whether a cached record holds an edge (or a failure) as :func:`_register_pair` writes them; a
    record edited or cut otherwise is registered again."""
    if "error" in record:
        return isinstance(record["error"], str)
    try:
        return isinstance(record.get("warnings"), list) and all(
            np.asarray(record[key], dtype=np.float64).shape == shape for key, shape in RECORD_SHAPES.items())
    except (KeyError, TypeError, ValueError):
        return False


def _register_pair(scene: _Scene, source: int, target: int) -> dict:
    """One candidate pair registered -> its cache record: the transform, the pairwise scores and the
    information matrix of its correspondences, or the reason it gave no edge."""
    started = time.perf_counter()
    src, tgt = scene.scans[source], scene.scans[target]
    try:
        result = register_prepared(ScanPair(src, tgt, scene.run.counts, scene.global_voxel), scene.run)
    except (ValueError, RuntimeError) as error:
        return {"error": f"{type(error).__name__}: {error}", "seconds": time.perf_counter() - started}
    src_icp, tgt_icp = src.downsampled(scene.voxel), tgt.downsampled(scene.voxel)
    moved_index, _ = pairs_within_reach(src_icp, tgt_icp, result.T_target_source, scene.reach, scene.run.backend)
    if len(moved_index) < 3:
        return {"error": "fewer than 3 point pairs within reach after ICP", "seconds": time.perf_counter() - started}
    moved = apply(result.T_target_source, src_icp[moved_index])
    return {"T_target_source": result.T_target_source.tolist(), "fitness": result.fitness,
            "inlier_rmse": result.inlier_rmse, "correspondences": int(len(moved_index)),
            "information": point_information(moved).tolist(), "warnings": result.warnings,
            "seconds": time.perf_counter() - started}


class _PairCache:
    """Pair records by key, read from and appended to a JSON Lines file (None: kept in memory only).
    A file that is not such a cache is refused (ValueError naming it), never overwritten; a last line
    a kill cut short is dropped; a record edited into another shape is registered again."""

    def __init__(self, path: str | os.PathLike | None) -> None:
        self.path = Path(path) if path is not None else None
        self.records: dict[str, dict] = {}
        if self.path is None or not self.path.exists():
            return
        try:
            lines = self.path.read_text(encoding="utf-8").splitlines()
        except (UnicodeDecodeError, OSError) as error:
            raise ValueError(f"cache {self.path}: not a pair cache of register_scene ({error})") from None
        for number, line in enumerate(lines, 1):
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                if number == len(lines):
                    write_json_lines(self.path, list(self.records.values()))  # the line a kill cut short
                    break
                record = None
            if not isinstance(record, dict) or not isinstance(record.get("key"), str):
                raise ValueError(f"cache {self.path}: line {number} is not a pair record; not a pair cache of "
                                 f"register_scene (give a new file name)")
            if _complete(record):
                self.records[record["key"]] = record

    def get(self, key: str, make) -> dict:
        if key not in self.records:
            self.records[key] = {"key": key, **make()}
            if self.path is not None:
                with open(self.path, "a") as sink:
                    sink.write(json.dumps(self.records[key]) + "\n")
        return self.records[key]


def _edges_for(scene: _Scene, pairs: list[tuple[int, int]], cache: _PairCache, progress: bool) -> list[SceneEdge]:
    """The candidate pairs (target, source) registered (or read from the cache) -> their edges (a
    pair whose registration failed gives none)."""
    from tqdm import tqdm

    run_key, edges, digests = _run_key(scene), [], {}
    for target, source in tqdm(pairs, desc="pairs", unit="pair", disable=not progress):
        for scan in (source, target):
            digests.setdefault(scan, _digest(scene.scans[scan]))
        key = hashlib.blake2b(f"{run_key} {digests[source]} {digests[target]}".encode(), digest_size=16).hexdigest()
        record = cache.get(key, lambda: _register_pair(scene, source, target))
        if "error" in record:
            continue
        edges.append(SceneEdge(source=source, target=target, T_target_source=np.array(record["T_target_source"]),
                               fitness=record["fitness"], inlier_rmse=record["inlier_rmse"],
                               correspondences=record["correspondences"], warnings=record["warnings"],
                               seconds=record["seconds"], information=np.array(record["information"])))
    return edges


def _pose_edges(edges: list[SceneEdge]) -> list[PoseEdge]:
    return [PoseEdge(source=e.source, target=e.target, T_target_source=e.T_target_source, information=e.information,
                     correspondences=e.correspondences) for e in edges]


def _loop_candidates(scene: _Scene, usable: list[int], poses: np.ndarray, placed: np.ndarray,
                     known: set[tuple[int, int]], count: int) -> list[tuple[int, int]]:
    """Pairs not yet registered whose scans the current poses put close: for each placed scan, the
    ``count`` others whose centres are nearest, if nearer than the larger of their radii (RMS distance
    of their points from their centre)."""
    centres, radii = {}, {}
    for i in usable:
        sample = scene.scans[i].downsampled(scene.voxel)
        centre = sample.mean(axis=0)
        centres[i] = apply(poses[i], centre[None])[0]
        radii[i] = float(np.sqrt(((sample - centre) ** 2).sum(1).mean()))
    chosen = set()
    for i in usable:
        if not placed[i]:
            continue
        near = sorted((float(np.linalg.norm(centres[i] - centres[j])), j) for j in usable
                      if j != i and placed[j] and (min(i, j), max(i, j)) not in known)
        for distance, j in near[:count]:
            if distance < max(radii[i], radii[j]):
                chosen.add((min(i, j), max(i, j)))
    return sorted(chosen)


def _unchecked(count: int, edges: list[SceneEdge]) -> list[int]:
    """Kept edges whose removal cuts the kept graph (bridges): no loop checks them."""
    kept = [i for i, e in enumerate(edges) if e.kept]
    source = np.array([edges[i].source for i in kept], dtype=np.int64)
    target = np.array([edges[i].target for i in kept], dtype=np.int64)
    return [kept[k] for k in np.flatnonzero(bridges(count, source, target))]


def register_scene(scans: Sequence, options: SceneOptions = SceneOptions(), *, names: Sequence[str] | None = None,
                   cache: str | os.PathLike | None = None, progress: bool = False) -> SceneResult:
    """Registers many scans of one scene into the frame of the first readable one.

    scans: file paths, (N, 3) arrays or tensors, or objects with ``points`` (as
    :func:`~vrnet_ext.registration.register` takes), in one unit and, for a sequence, in capture
    order; names: how warnings and outputs name them (default: the file names, or ``scan <i>``).
    An unreadable scan or one with fewer than ``MIN_SCAN_POINTS`` points is skipped with a warning; a
    scan no registration links to the first one is left unplaced (NaN pose, a warning naming it).
    cache: a JSON Lines file of registered pairs, read and appended to (a run stopped or killed
    resumes there; a pair is reused only for the same scans and settings). progress: a bar over pairs.
    """
    started = time.perf_counter()
    scene = _read_scans(scans, names, options)
    seconds = {"read": time.perf_counter() - started}
    usable = [i for i, scan in enumerate(scene.scans) if scan is not None]
    reference, count = usable[0], len(scene.scans)
    if usable[0] != 0:
        scene.warnings.append(f"poses are in the frame of {scene.names[reference]}, the first readable scan")
    if len(usable) <= options.all_pairs_up_to:
        pairs = list(itertools.combinations(usable, 2))
    else:
        pairs = [(a, b) for k, a in enumerate(usable) for b in usable[k + 1:k + 1 + options.neighbours]]
    pair_cache = _PairCache(cache)
    started = time.perf_counter()
    edges = _edges_for(scene, pairs, pair_cache, progress)
    if len(usable) > options.all_pairs_up_to and options.loop_candidates and edges:
        support = triangle_support(_pose_edges(edges), scene.reach)
        _, poses, placed = spanning_tree(count, _pose_edges(edges), support, reference)
        loops = _loop_candidates(scene, usable, poses, placed, set(pairs), options.loop_candidates)
        edges += _edges_for(scene, loops, pair_cache, progress)
    seconds["pairs"] = time.perf_counter() - started
    started = time.perf_counter()
    result = _optimise(scene, edges, reference, count)
    seconds["pose_graph"] = time.perf_counter() - started
    if options.map_icp and result.placed.sum() > 1:
        started = time.perf_counter()
        result.poses = _refine_against_map(scene, result, reference)
        seconds["map_icp"] = time.perf_counter() - started
    started = time.perf_counter()
    result.fused = _fuse(scene, result.poses, result.placed)
    seconds["fuse"] = time.perf_counter() - started
    if scene.shift.any():
        for poses in (result.poses, result.initial_poses):
            poses[result.placed] = [in_shifted_frames(pose, scene.shift) for pose in poses[result.placed]]
        result.fused = result.fused + scene.shift
    result.seconds = seconds
    return result


def _optimise(scene: _Scene, edges: list[SceneEdge], reference: int, count: int) -> SceneResult:
    """Support, spanning tree, robust pose graph over the scans linked to the reference -> the
    result (fused cloud and times filled in by the caller)."""
    warnings = list(scene.warnings)
    poses = np.full((count, 4, 4), np.nan)
    initial = poses.copy()
    placed = np.zeros(count, dtype=bool)
    placed[reference] = True
    poses[reference] = initial[reference] = np.eye(4)
    if edges:
        pose_edges = _pose_edges(edges)
        support = triangle_support(pose_edges, scene.reach)
        in_tree, chained, placed = spanning_tree(count, pose_edges, support, reference)
        for edge, supported, tree in zip(edges, support, in_tree):
            edge.support, edge.in_tree = int(supported), bool(tree)
        inside = [i for i, e in enumerate(edges) if placed[e.source] and placed[e.target]]
        index = -np.ones(count, dtype=np.int64)
        index[placed] = np.arange(placed.sum())
        graph = [replace(pose_edges[i], source=int(index[edges[i].source]), target=int(index[edges[i].target]),
                         robust=not in_tree[i]) for i in inside]
        solution = optimize_pose_graph(chained[placed], graph, PoseGraphSettings(reach=scene.reach),
                                       reference=int(index[reference]))
        poses[placed], initial[placed] = solution.poses, chained[placed]
        for k, i in enumerate(inside):
            edges[i].weight, edges[i].kept = float(solution.weight[k]), bool(solution.kept[k])
            edges[i].displacement = float(solution.displacement[k])
        bridges = _unchecked(count, edges)
        if bridges:
            listed = ", ".join(f"{scene.names[edges[i].source]} - {scene.names[edges[i].target]}" for i in bridges)
            warnings.append(f"{len(bridges)} registration(s) that no loop of scans checks place part of the scene "
                            f"({listed}): those poses are only as good as those pairs")
    missing = [scene.names[i] for i, scan in enumerate(scene.scans) if scan is not None and not placed[i]]
    if missing:
        warnings.append(f"not placed (no registration links them to {scene.names[reference]}): {', '.join(missing)}")
    return SceneResult(names=scene.names, poses=poses, initial_poses=initial, placed=placed, edges=edges,
                       fused=np.zeros((0, 3)), voxel=scene.voxel, reach=scene.reach, warnings=warnings, seconds={})


def _refine_against_map(scene: _Scene, result: SceneResult, reference: int) -> np.ndarray:
    """Each placed scan but the reference refined by ICP (the scene's settings and reach), from its
    pose, against the placed scans it was registered with (kept or dropped: a right pair the pose
    graph outvoted still overlaps; a wrong one's scan lies elsewhere and finds no pairs within reach),
    moved by the optimised poses and merged on the ICP voxel grid: the pairwise registrations' small
    disagreements, which the pose graph can only share out, are settled on all of a scan's overlaps
    at once. For up to ``all_pairs_up_to`` scans those are all the others; beyond, the candidate pairs
    bound the work. A scan whose ICP finds no pairs within reach keeps its pose."""
    poses, placed, refined = result.poses, result.placed, result.poses.copy()
    linked: dict[int, set[int]] = {}
    for edge in result.edges:
        if placed[edge.source] and placed[edge.target]:
            linked.setdefault(edge.source, set()).add(edge.target)
            linked.setdefault(edge.target, set()).add(edge.source)
    for i in np.flatnonzero(placed):
        if i == reference or not linked.get(i):
            continue
        others = voxel_downsample(np.concatenate([apply(poses[j], scene.scans[j].downsampled(scene.voxel))
                                                  for j in sorted(linked[i])]), scene.voxel)
        try:
            refined[i] = icp(scene.scans[i].downsampled(scene.voxel), others, poses[i], scene.run.icp,
                             device=scene.run.device, backend=scene.run.backend).T_target_source
        except IcpFailure:
            pass
    return refined


def _fuse(scene: _Scene, poses: np.ndarray, placed: np.ndarray) -> np.ndarray:
    """Every placed scan at the ICP voxel, moved by its pose, merged on the same voxel grid."""
    moved = [apply(poses[i], scene.scans[i].downsampled(scene.voxel)) for i in np.flatnonzero(placed)]
    return voxel_downsample(np.concatenate(moved), scene.voxel)


__all__ = ["MIN_SCAN_POINTS", "SceneEdge", "SceneOptions", "SceneResult", "register_scene"]
