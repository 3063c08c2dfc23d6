"""Rigid transforms: the package's one convention, written down once.

A motion maps a source frame into a target frame, ``y = R x + t`` for column vectors, and is named
``T_target_source``. Point clouds are stored as rows, (..., N, 3), so the code reads
``x @ R^T + t``. A 4x4 homogeneous matrix holds ``R`` in its top-left 3x3 block and ``t`` in its
last column; (R, t) pairs are (..., 3, 3) and (..., 3). Every function works on numpy arrays and
torch tensors alike (with batch dimensions in front), and is differentiable for tensors.
"""
from __future__ import annotations

import numpy as np


def _matmul_would_round(x) -> bool:
    """Whether a matrix product of ``x`` would run in TF32 (10 bits of each operand kept: a
    thousandth of a cloud's size, 0.06 degrees in a composed rotation): a float32 GPU tensor while
    torch allows TF32 there. Such products are written as multiply-adds in float32 instead."""
    if not getattr(x, "is_cuda", False):  # arrays and CPU tensors (no torch import: `--help` loads none)
        return False
    import torch

    from vrnet_ext.runtime import cuda_matmul_allows_tf32

    return x.dtype == torch.float32 and cuda_matmul_allows_tf32()


def rotate_rows(points, rotation):
    """(..., N, 3) points, (..., 3, 3) R -> R x for every point (``points @ R^T``), in float32 also
    where torch allows TF32 products on the GPU."""
    if not _matmul_would_round(points):
        return points @ rotation.swapaxes(-1, -2)
    return (points[..., 0:1] * rotation[..., None, :, 0] + points[..., 1:2] * rotation[..., None, :, 1]
            + points[..., 2:3] * rotation[..., None, :, 2])


def move(points, rotation, translation):
    """(..., N, 3) points, (..., 3, 3) R, (..., 3) t -> R x + t for every point."""
    return rotate_rows(points, rotation) + translation[..., None, :]


def apply(T, points):
    """(..., 4, 4) homogeneous T, (..., N, 3) points -> T applied to every point."""
    return move(points, T[..., :3, :3], T[..., :3, 3])


def compose(rotation_2, translation_2, rotation_1, translation_1):
    """The motion (R2, t2) after (R1, t1) -> (R2 R1, R2 t1 + t2) ((..., 3, 3), (..., 3) each)."""
    if not _matmul_would_round(rotation_1):
        return rotation_2 @ rotation_1, (rotation_2 @ translation_1[..., None])[..., 0] + translation_2
    rotation = rotate_rows(rotation_1.swapaxes(-1, -2), rotation_2).swapaxes(-1, -2)  # (R1^T R2^T)^T = R2 R1
    return rotation, rotate_rows(translation_1[..., None, :], rotation_2)[..., 0, :] + translation_2


def cube_rotations() -> np.ndarray:
    """The 24 rotations that map a cube onto itself (the signed permutation matrices of determinant
    +1), (24, 3, 3) float64, the identity first. Every rotation lies within 62.8 degrees of one of
    them."""
    import itertools

    found = [np.eye(3)]
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[range(3), order] = signs
            if np.linalg.det(matrix) > 0 and not np.array_equal(matrix, np.eye(3)):
                found.append(matrix)
    return np.stack(found)


def search_starts(centre_zyx_degrees=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The rotation search's starts, (S, 3, 3) float64: the 23 cube rotations other than the identity
    (every motion M lies within 62.8 degrees of one of them, G, and M G^T is what is left to register
    from the source turned by G); where the centre C (Euler angles z, y, x in degrees, scipy's
    ``"zyx"``) is not the identity, also the 24 rotations C^T G (M (C^T G)^T = M G^T C lies within
    62.8 degrees of C)."""
    cube = cube_rotations()
    if not np.any(centre_zyx_degrees):
        return cube[1:]
    from scipy.spatial.transform import Rotation  # here, not at import: `vrnet register` never needs it

    centre = Rotation.from_euler("zyx", centre_zyx_degrees, degrees=True).as_matrix()
    return np.concatenate([cube[1:], centre.T @ cube])


def spread_rotations(count: int) -> np.ndarray:
    """``count`` rotations spread evenly over all of SO(3), (count, 3, 3) float64: the super-Fibonacci
    spiral of unit quaternions (Alexa, CVPR 2022), the same set for the same count. With 512 every
    rotation lies within 28 degrees of one of them (with 128, 46)."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count must be a positive integer, got {count!r}")
    s = np.arange(count) + 0.5
    near, far = np.sqrt(s / count), np.sqrt(1.0 - s / count)
    alpha, beta = 2 * np.pi * s / np.sqrt(2.0), 2 * np.pi * s / 1.533751168755204288118041  # psi**4 = psi + 4
    x, y, z, w = near * np.sin(alpha), near * np.cos(alpha), far * np.sin(beta), far * np.cos(beta)
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1).reshape(count, 3, 3)


def to_homogeneous(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(3, 3) R and (3,) t -> (4, 4) float64 numpy matrix."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(rotation), np.asarray(translation)
    return T


def from_normalised(rotation, translation_normalised, src_centre, tgt_centre, scale):
    """A motion (R, t') estimated between normalised clouds ``(src - src_centre) / scale`` and
    ``(tgt - tgt_centre) / scale`` -> (R, t) between the clouds themselves:
    ``t = scale t' + tgt_centre - R src_centre``. Arrays or tensors, (3, 3) and (3,)."""
    return rotation, scale * translation_normalised + tgt_centre - (rotation @ src_centre[..., None])[..., 0]


def translation(vector) -> np.ndarray:
    """(3,) t -> the (4, 4) float64 matrix of the pure translation by t."""
    return to_homogeneous(np.eye(3), vector)


def in_shifted_frames(T, shift) -> np.ndarray:
    """A (4, 4) motion estimated between clouds that were both shifted by ``-shift`` (3,), expressed
    between the original clouds: ``translation(shift) @ T @ translation(-shift)``."""
    return translation(shift) @ np.asarray(T, dtype=np.float64) @ translation(-np.asarray(shift, dtype=np.float64))


def chain(count: int, links: list[tuple[int, int, np.ndarray]], root: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The poses of ``count`` frames in the frame of ``root``, from relative motions: ``links`` holds
    ``(target, source, T_target_source)`` triples (either direction is walked); each frame the links
    reach gets ``T_root_frame`` along the first path a breadth-first search finds -> (poses
    (count, 4, 4), the identity where not reached; reached (count,) bool)."""
    steps: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(count)]
    for target, source, T in links:
        T = np.asarray(T, dtype=np.float64)
        steps[target].append((source, T))
        steps[source].append((target, np.linalg.inv(T)))
    poses = np.tile(np.eye(4), (count, 1, 1))
    reached = np.zeros(count, dtype=bool)
    reached[root] = True
    frontier = [root]
    while frontier:
        following = []
        for frame in frontier:
            for other, T in steps[frame]:
                if not reached[other]:
                    poses[other], reached[other] = poses[frame] @ T, True
                    following.append(other)
        frontier = following
    return poses, reached


__all__ = ["apply", "chain", "compose", "from_normalised", "in_shifted_frames", "move", "to_homogeneous", "translation"]
