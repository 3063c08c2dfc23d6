"""How near an estimate brings two clouds, and the point-to-point ICPs that bring them nearer.

Batched over pairs: src (B, N, 3), tgt (B, M, 3), an estimate R (B, 3, 3), t (B, 3) with
R src + t ~ tgt (:mod:`vrnet_ext.geometry.transforms`). Neither needs correspondences: each moved
source point is compared with its nearest target point.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from vrnet_ext.geometry.metrics import turn_deg
from vrnet_ext.geometry.transforms import move
from vrnet_ext.names import ANY_ROTATION, MAX_SEARCH_ICP_SLIDES, MAX_TURN_PENALTY, SEARCH_ICP_SLIDE_REACH, SEARCH_ICPS
from vrnet_ext.ops import kabsch, knn, robust_kabsch

ICP_KERNEL = "cauchy"  # robust_icp: the robust weight of a nearest-point residual
ICP_SCALE = 1.0        # robust_icp: its scale, in medians of the pair's nearest-point distances
ICP_REWEIGHTING = 3    # robust_icp: reweighting steps of each Procrustes solve
ICP_TRIM = 0.5         # trimmed_icp: the share of the nearest-point pairs (the nearer ones) each step solves on
MULTISTART_POINTS = 128  # multistart_icp: source points (evenly strided) of every start's first steps
MULTISTART_FIRST = 10    # multistart_icp: ICP steps of every start on them
MULTISTART_KEEP = 16     # multistart_icp: the starts nearest after them, taken on
MULTISTART_LAST = 40     # multistart_icp: ICP steps of those on every source point
MULTISTART_BATCH = 2 ** 20  # multistart_icp: target points held at once (bounds its memory)
# multistart_icp with a bound on the turn: starts up to this many degrees beyond it are taken too (ICP moves a
# start by up to a few tens of degrees; 512 spread rotations leave every rotation within 28 degrees of one).
MULTISTART_BOUND_MARGIN = 30.0


def nearest_median(src: torch.Tensor, tgt: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
                   backend: str = "ext") -> torch.Tensor:
    """(B,) the median distance from each point of R src + t to its nearest target point: how close
    an estimate brings the clouds, whatever correspondences say (robust to up to half the source
    without a counterpart). ``backend``: that of :func:`vrnet_ext.ops.knn`."""
    with torch.autocast(src.device.type, enabled=False):
        moved = move(src, rotation, translation).contiguous()
    dist2, _ = knn(moved, tgt.to(moved.dtype).contiguous(), 1, backend=backend)
    return dist2[..., 0].median(dim=1).values.sqrt()


def robust_icp(src: torch.Tensor, tgt: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
               steps: int, backend: str = "ext") -> tuple[torch.Tensor, torch.Tensor]:
    """``steps`` steps of robust point-to-point ICP from (R, t), every pair at once: each step pairs
    every moved source point with its nearest target point and solves a Procrustes on those pairs
    followed by :data:`ICP_REWEIGHTING` reweighting steps (:func:`vrnet_ext.ops.robust_kabsch`:
    :data:`ICP_KERNEL` weights at :data:`ICP_SCALE` x the pair's median residual), so that the
    source points without a counterpart (a partial view's cut, noise) lose their say.

    ICP converges to the nearest local minimum: it polishes an estimate that is nearly right (a few
    degrees off), and does not rescue one that is far off. Returns R (B, 3, 3), t (B, 3) in src's dtype.
    ``backend``: that of the ops (:func:`vrnet_ext.ops.knn`, :func:`vrnet_ext.ops.robust_kabsch`).
    """
    def solve(points: torch.Tensor, matched: torch.Tensor, _: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return robust_kabsch(points, matched, None, iterations=ICP_REWEIGHTING, kernel=ICP_KERNEL, scale=ICP_SCALE,
                             backend=backend)
    return _icp(src, tgt, rotation, translation, steps, backend=backend, solve=solve)


def trimmed_icp(src: torch.Tensor, tgt: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
                steps: int, backend: str = "ext") -> tuple[torch.Tensor, torch.Tensor]:
    """``steps`` steps of trimmed point-to-point ICP from (R, t), every pair at once: each step pairs
    every moved source point with its nearest target point and solves a Procrustes
    (:func:`vrnet_ext.ops.kabsch`) on the :data:`ICP_TRIM` nearer share of those pairs (ties at the
    bound all kept): the objective :func:`nearest_median` measures. On two noisy partial views of a
    nearly round shape it holds the truth where :func:`robust_icp`, whose optimum weighs every pair,
    drifts off it. Returns R (B, 3, 3), t (B, 3) in src's dtype. ``backend``: that of the ops."""
    def solve(points: torch.Tensor, matched: torch.Tensor, dist2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        bound = dist2.kthvalue(max(3, math.ceil(ICP_TRIM * dist2.shape[1])), dim=1).values[:, None]
        return kabsch(points, matched, (dist2 <= bound).to(points.dtype), backend=backend)
    return _icp(src, tgt, rotation, translation, steps, backend=backend, solve=solve)


ICPS = {"robust": robust_icp, "trimmed": trimmed_icp}  # the ICP of each name of vrnet_ext.names.SEARCH_ICPS


def _icp(src: torch.Tensor, tgt: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor, steps: int, *,
         backend: str, solve) -> tuple[torch.Tensor, torch.Tensor]:
    """``steps`` ICP steps: each pairs every moved source point with its nearest target point and
    takes ``solve(src, matched (B, N, 3), squared distances (B, N))``'s (R, t)."""
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    with torch.autocast(src.device.type, enabled=False):
        src, tgt = src.contiguous(), tgt.to(src.dtype).contiguous()
        for _ in range(steps):
            moved = move(src, rotation, translation).contiguous()
            dist2, nearest = knn(moved, tgt, 1, backend=backend)
            matched = tgt.gather(1, nearest.expand(-1, -1, 3))
            rotation, translation = solve(src, matched, dist2[..., 0])
    return rotation, translation


def slides(tgt: torch.Tensor, count: int) -> torch.Tensor:
    """(count, 3) offsets of a start's translation for the target cloud ``tgt`` (M, 3): with one, none;
    with more, spread evenly along the target's longest axis over +- :data:`vrnet_ext.names.SEARCH_ICP_SLIDE_REACH` standard
    deviations of its points along it (an odd count includes none). Two partial views of an elongated
    shape, each cut from its own side, put their centroids apart along it."""
    _check_slide_count(count)
    if count == 1:
        return tgt.new_zeros(1, 3)
    centred = tgt - tgt.mean(0)
    _, spread, axes = torch.linalg.svd(centred, full_matrices=False)
    reach = SEARCH_ICP_SLIDE_REACH * spread[0] / math.sqrt(tgt.shape[0])
    return torch.linspace(-1, 1, count, dtype=tgt.dtype, device=tgt.device)[:, None] * reach * axes[0]


def _check_slide_count(count: int) -> None:
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_SEARCH_ICP_SLIDES:
        raise ValueError(f"slides must be an integer in [1, {MAX_SEARCH_ICP_SLIDES}], got {count!r}")


@dataclass(frozen=True)
class TurnPrior:
    """How the searches weigh the turn of an estimate (the angle in degrees by which it turns the source,
    :func:`turn_deg`) beside how near it brings the source to the target.

    ``max_turn``: a bound the caller knows on the motion (:data:`ANY_ROTATION`, the default: none);
    estimates that turn further count as infinitely far. ``penalty`` p: an estimate's distance counts
    (1 + p x turn / 180) times as far (0, the default: every turn alike), so that of two estimates the
    geometry can hardly tell apart (a flip of a nearly round shape under noise) the smaller motion is
    taken, while one clearly nearer still wins: a 180-degree turn must come 1 / (1 + p) as near as no turn.
    """
    max_turn: float = ANY_ROTATION
    penalty: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.max_turn, bool) or not isinstance(self.max_turn, (int, float)) \
                or not 0 < self.max_turn <= ANY_ROTATION:
            raise ValueError(f"max_turn must be in (0, {ANY_ROTATION:g}] degrees, got {self.max_turn!r}")
        if isinstance(self.penalty, bool) or not isinstance(self.penalty, (int, float)) \
                or not 0 <= self.penalty <= MAX_TURN_PENALTY:
            raise ValueError(f"penalty must be in [0, {MAX_TURN_PENALTY:g}], got {self.penalty!r}")

    def beyond(self, rotation: torch.Tensor) -> torch.Tensor:
        """(B,) bool: the rotations (B, 3, 3) that turn by more than ``max_turn`` (none without a bound)."""
        if self.max_turn >= ANY_ROTATION:
            return torch.zeros(rotation.shape[0], dtype=torch.bool, device=rotation.device)
        return turn_deg(rotation) > self.max_turn

    def score(self, rotation: torch.Tensor, distance: torch.Tensor) -> torch.Tensor:
        """``distance`` (B,) of the estimates turning by ``rotation`` (B, 3, 3), weighed by the prior:
        scaled by (1 + penalty x turn / 180), ``inf`` beyond the bound (``distance`` itself without either)."""
        if not self.penalty and self.max_turn >= ANY_ROTATION:
            return distance
        turn = turn_deg(rotation)  # once, for both
        if self.penalty:
            distance = distance * (1 + self.penalty * turn / ANY_ROTATION).to(distance.dtype)
        return distance.masked_fill(turn > self.max_turn, math.inf)


def multistart_icp(src: torch.Tensor, tgt: torch.Tensor, starts: torch.Tensor, backend: str = "ext",
                   slide_count: int = 1, icp: str = "robust", *,
                   prior: TurnPrior = TurnPrior()) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A global registration by ICP alone (``icp``: a name of :data:`ICPS`): for each pair, ICP from
    every rotation of ``starts`` (S, 3, 3), each with ``slide_count`` translations (that which puts
    the turned source's centroid on the target's, moved by each of :func:`slides`), first
    :data:`MULTISTART_FIRST` steps on :data:`MULTISTART_POINTS` of the source's points, then
    :data:`MULTISTART_LAST` steps on all of them from the :data:`MULTISTART_KEEP` starts that brought
    the source nearest the target; the nearest of those is each pair's result (nearest as ``prior``
    weighs it: :meth:`TurnPrior.score`).

    ICP's reach from a start is a few tens of degrees (less on nearly round shapes, where it
    converges slowly along the axis) and a tenth or so of the shape's size, so ``starts`` should
    leave no motion farther than that from one of them
    (:func:`vrnet_ext.geometry.transforms.spread_rotations`), and the slides cover partial views
    whose centroids lie apart. Cost per pair, with C = S x ``slide_count`` starts: C x
    MULTISTART_FIRST nearest-neighbour searches of the strided points, C of every point (the ranking)
    and MULTISTART_KEEP x (MULTISTART_LAST + 1) more.

    With a bound in ``prior`` (``max_turn`` below 180 degrees) only estimates that turn the source by at
    most this much (:func:`turn_deg`) are kept, and only the starts within
    :data:`MULTISTART_BOUND_MARGIN` beyond it are run (at least the start nearest the identity); a
    pair none of whose estimates is within the bound gets the distance ``inf``.

    Returns R (B, 3, 3), t (B, 3) and their :func:`nearest_median` weighed by ``prior`` (B,; the
    median itself with the default prior), in src's dtype.
    """
    if starts.dim() != 3 or starts.shape[1:] != (3, 3) or not starts.shape[0]:
        raise ValueError(f"starts must be (S, 3, 3) rotations with S >= 1, got {tuple(starts.shape)}")
    if icp not in ICPS:
        raise ValueError(f"icp must be one of {SEARCH_ICPS}, got {icp!r}")
    _check_slide_count(slide_count)
    step = ICPS[icp]
    if not src.shape[0]:
        return src.new_zeros(0, 3, 3), src.new_zeros(0, 3), src.new_zeros(0)
    if prior.max_turn < ANY_ROTATION:
        start_turns = turn_deg(starts)
        starts = starts[(start_turns <= prior.max_turn + MULTISTART_BOUND_MARGIN) | (start_turns == start_turns.min())]
    count, points = starts.shape[0] * slide_count, src.shape[1]
    stride = max(1, points // MULTISTART_POINTS)
    keep = min(MULTISTART_KEEP, count)
    at_once = max(1, MULTISTART_BATCH // tgt.shape[1])  # starts held at once
    results = []
    with torch.autocast(src.device.type, enabled=False):
        starts = starts.to(src.dtype)
        for cloud, target in zip(src, tgt.to(src.dtype)):
            turns = starts.repeat(slide_count, 1, 1)  # (C, 3, 3), the start fastest, the slide slowest
            shift = (target.mean(0) - turns @ cloud.mean(0)
                     + slides(target, slide_count).repeat_interleave(starts.shape[0], dim=0))
            found = []
            for first in range(0, count, at_once):
                many = min(at_once, count - first)
                every_src, every_tgt = cloud.expand(many, -1, -1), target.expand(many, -1, -1)
                rotation, translation = step(every_src[:, ::stride][:, :MULTISTART_POINTS], every_tgt,
                                             turns[first:first + many], shift[first:first + many], MULTISTART_FIRST,
                                             backend)
                found.append((rotation, translation, prior.score(rotation, nearest_median(
                    every_src, every_tgt, rotation, translation, backend))))
            rotation, translation, distance = (torch.cat(values) for values in zip(*found))
            kept = distance.topk(keep, largest=False).indices
            every_src, every_tgt = cloud.expand(keep, -1, -1), target.expand(keep, -1, -1)
            rotation, translation = step(every_src, every_tgt, rotation[kept], translation[kept], MULTISTART_LAST,
                                         backend)
            distance = prior.score(rotation, nearest_median(every_src, every_tgt, rotation, translation, backend))
            best = distance.argmin()
            results.append((rotation[best], translation[best], distance[best]))
    rotation, translation, distance = (torch.stack(values) for values in zip(*results))
    return rotation, translation, distance
