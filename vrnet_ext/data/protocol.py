"""The DCP / PRNet / VRNet ModelNet40 pair protocol on numpy arrays.

* Rigid motion: angles uniform in [0, max_angle] about x, y, z; R = Rx Ry Rz as in DCP, which is
  scipy's ``Rotation.from_euler('zyx', [az, ay, ax])`` (extrinsic z, then y, then x);
  translation uniform in [-0.5, 0.5] per axis. ``tgt = R src + t``. Beyond the protocol
  (``rotation_range``): each angle in [-max_angle, max_angle] ("symmetric"), or R uniform over all
  rotations ("so3", a normalised 4-d Gaussian as the quaternion), or such a rotation turned back by
  the rotation of the cube nearest it ("cube_residual": what the rotation search's nearest start
  leaves, uniform over the rotations within 62.8 degrees that are nearer the identity than any
  other rotation of the cube).
* Settings (crops are taken in each cloud's own frame):
  CO all points; PV the ``num_subsampled`` points nearest to a random far point
  (``far_points="prnet"``, the paper's main tables: U[0,1]^3 + 500 s (1,1,1), s in {1,-1}, the SAME
  point for both clouds, each cut in its own frame, as in PRNet's and VRNet's released code, so both
  views look along one diagonal from one side; ``"sphere"``: 500 times a uniformly random
  direction, drawn for each cloud; ``"mixed"``: one of the two per pair, at random;
  ``"symmetric"``: the source's far point as PRNet's, the target's at its mirror image through the
  origin, as in the paper's ablations: more partiality and more outliers);
  RS ``num_subsampled`` random points per cloud; PV+RS first ``pvrs_presample`` random points,
  then the PV crop of those. ``"mixed"`` (for training one model for every setting) draws one of
  the four per pair; its CO pairs keep a random ``num_subsampled`` of the shape's points (the same
  in both clouds), so every pair of a batch has the same size.
* Both clouds are shuffled; ``gt_idx[i]`` is the row of the target holding source point i's
  counterpart, or -1 when the target crop dropped it.
* ND: Gaussian noise sigma 0.01 clipped to +-0.05 on every coordinate of both clouds, added to
  fresh arrays (never to the cached dataset).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vrnet_ext.geometry.transforms import cube_rotations, move
from vrnet_ext.names import DEFAULT_MAX_ANGLE, DEFAULT_ROTATION_RANGE, MIXED, ROTATION_RANGES, SETTINGS

FAR_POINTS = ("prnet", "sphere", "mixed", "symmetric")
# How the default ("prnet") partial views are cut, recorded with measurements so that a table never
# mixes numbers of differently cut pairs.
VIEW_PROTOCOL = "prnet, one far point for both clouds"


@dataclass
class PairSpec:
    """How :func:`make_pair` cuts and moves a pair (the module docstring gives the protocol).

    ``setting``: one of SETTINGS or "mixed"; ``noise``: ND's jitter on both clouds; ``num_points``
    points per shape before the crop, ``num_subsampled`` per cloud after it; ``max_angle_deg``: the
    largest rotation about each axis (degrees); ``rotation_range``: how the angles are drawn (one of
    ROTATION_RANGES); ``max_translation``: per axis, in the shape's unit; ``far_points``: one of
    FAR_POINTS.
    """

    setting: str = "PV"
    noise: bool = False
    num_points: int = 1024
    num_subsampled: int = 768
    pvrs_presample: int | None = None  # PV+RS random pre-sample; default 896/1024 of num_points
    max_angle_deg: float = DEFAULT_MAX_ANGLE
    rotation_range: str = DEFAULT_ROTATION_RANGE
    max_translation: float = 0.5
    far_points: str = "prnet"  # where PV's far points lie: see the module docstring

    def __post_init__(self) -> None:
        if self.rotation_range not in ROTATION_RANGES:
            raise ValueError(f"rotation_range must be one of {ROTATION_RANGES}, got {self.rotation_range!r}")
        if self.far_points not in FAR_POINTS:
            raise ValueError(f"far_points must be one of {FAR_POINTS}, got {self.far_points!r}")
        if self.pvrs_presample is None:
            self.pvrs_presample = max(self.num_subsampled, round(self.num_points * 896 / 1024))
        if self.setting not in SETTINGS + (MIXED,):
            raise ValueError(f"setting must be one of {SETTINGS + (MIXED,)}, got {self.setting!r}")
        if self.setting in ("PV+RS", MIXED) and not self.num_subsampled <= self.pvrs_presample <= self.num_points:
            raise ValueError("PV+RS needs num_subsampled <= pvrs_presample <= num_points")
        if self.setting != "CO" and self.num_subsampled > self.num_points:
            raise ValueError(f"num_subsampled ({self.num_subsampled}) exceeds num_points ({self.num_points})")


def random_motion(rng: np.random.Generator, max_angle_deg: float, max_translation: float,
                  rotation_range: str = DEFAULT_ROTATION_RANGE):
    """(R (3, 3), t (3,), euler_zyx_deg (3,)) with R = Rx Ry Rz, drawn as ``rotation_range`` says (the
    module docstring)."""
    from scipy.spatial.transform import Rotation  # here, not at import: `vrnet register` never needs it

    if rotation_range in ("so3", "cube_residual"):
        turn = Rotation.from_quat(rng.standard_normal(4))  # normalised by scipy: uniform over SO(3)
        if rotation_range == "cube_residual":
            turn = Rotation.from_matrix(cube_residual(turn.as_matrix()))
        az, ay, ax = turn.as_euler("zyx")
    else:
        low = -max_angle_deg if rotation_range == "symmetric" else 0.0
        ax, ay, az = rng.uniform(np.deg2rad(low), np.deg2rad(max_angle_deg), size=3)
    rotation = Rotation.from_euler("zyx", [az, ay, ax]).as_matrix()
    translation = rng.uniform(-max_translation, max_translation, size=3)
    return rotation, translation, np.rad2deg([az, ay, ax])


def cube_residual(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) R -> R G^T with G the rotation of the cube nearest R (largest trace of R G^T): the
    rotation left to register from the rotation search's start G."""
    cube = cube_rotations()
    nearest = cube[np.argmax(np.einsum("ij,kij->k", rotation, cube))]
    return rotation @ nearest.T


def far_point(rng: np.random.Generator, scheme: str) -> np.ndarray:
    """A far point of a partial view (3,): PRNet's near the diagonal, U[0,1]^3 + 500 s (1,1,1) with s
    in {1,-1}, or 500 times a uniformly random direction (``scheme="sphere"``)."""
    if scheme == "sphere":
        direction = rng.standard_normal(3)
        return 500.0 * direction / max(float(np.linalg.norm(direction)), 1e-12)
    return rng.random(3) + 500.0 * rng.choice((1, -1))


def view_points(rng: np.random.Generator, scheme: str) -> tuple[np.ndarray, np.ndarray]:
    """The far points (3,) cutting the source's and the target's partial views, each taken in its
    cloud's own frame: one PRNet point for both ("prnet"), it and its mirror image through the
    origin ("symmetric"), or a random direction for each ("sphere")."""
    if scheme == "sphere":
        return far_point(rng, scheme), far_point(rng, scheme)
    far = far_point(rng, "prnet")
    return far, (-far if scheme == "symmetric" else far)


def nearest_to_far_point(points: np.ndarray, count: int, far: np.ndarray) -> np.ndarray:
    """Indices of the ``count`` points nearest to ``far`` (a partial view), in ascending order."""
    d2 = ((points - far) ** 2).sum(axis=1)
    return np.sort(np.argpartition(d2, count - 1)[:count])


def select(points: np.ndarray, spec: PairSpec, setting: str, rng: np.random.Generator,
           far: np.ndarray | None) -> np.ndarray:
    """Indices kept by ``setting``'s crop (one of SETTINGS), in ascending order (``far``: the far point
    of a PV or PV+RS view)."""
    n = points.shape[0]
    if setting == "CO":
        return np.arange(n)
    if setting == "RS":
        return np.sort(rng.choice(n, spec.num_subsampled, replace=False))
    if setting == "PV":
        return nearest_to_far_point(points, spec.num_subsampled, far)
    pre = np.sort(rng.choice(n, spec.pvrs_presample, replace=False))
    return pre[nearest_to_far_point(points[pre], spec.num_subsampled, far)]


def jitter(points: np.ndarray, rng: np.random.Generator, sigma: float = 0.01, clip: float = 0.05) -> np.ndarray:
    """ND's noise: (N, 3) points plus Gaussian noise of ``sigma`` per coordinate, clipped to +-``clip``
    (a new array)."""
    return points + np.clip(sigma * rng.standard_normal(points.shape), -clip, clip)


def make_pair(base: np.ndarray, spec: PairSpec, rng: np.random.Generator) -> dict:
    """One registration pair from a (num_points, 3) cloud (read-only: nothing is modified)."""
    if base.shape[0] > spec.num_points:
        base = base[np.sort(rng.choice(base.shape[0], spec.num_points, replace=False))]
    setting = spec.setting
    if setting == MIXED:
        setting = SETTINGS[int(rng.integers(len(SETTINGS)))]
        if setting == "CO":
            base = base[np.sort(rng.choice(base.shape[0], spec.num_subsampled, replace=False))]
    rotation, translation, euler = random_motion(rng, spec.max_angle_deg, spec.max_translation, spec.rotation_range)
    moved = move(base, rotation, translation)
    scheme = spec.far_points if spec.far_points != "mixed" else ("prnet", "sphere")[int(rng.integers(2))]
    src_far, tgt_far = view_points(rng, scheme) if setting in ("PV", "PV+RS") else (None, None)
    src_keep = select(base, spec, setting, rng, src_far)
    tgt_keep = select(moved, spec, setting, rng, tgt_far)
    src_keep = src_keep[rng.permutation(src_keep.size)]
    tgt_keep = tgt_keep[rng.permutation(tgt_keep.size)]
    row_in_tgt = np.full(base.shape[0], -1, dtype=np.int64)
    row_in_tgt[tgt_keep] = np.arange(tgt_keep.size)
    src, tgt = base[src_keep], moved[tgt_keep]
    if spec.noise:
        src, tgt = jitter(src, rng), jitter(tgt, rng)
    return {
        "src": src.astype(np.float32),
        "tgt": tgt.astype(np.float32),
        "rotation": rotation.astype(np.float32),
        "translation": translation.astype(np.float32),
        "euler": euler.astype(np.float32),
        "gt_idx": row_in_tgt[src_keep],
    }
