"""Small rigid motions as 6-vectors, for optimisers over poses (float64 numpy, batched in front).

A twist ``xi = (omega, v)`` (..., 6) holds a rotation vector ``omega`` (axis times angle, radians)
then a translation ``v`` in the scans' unit; :func:`motion` turns it into the 4x4 transform with
rotation ``exp([omega]x)`` and translation ``v`` (so a twist of a motion near the identity is the
displacement ``omega x q + v`` it gives a point q, to first order), and :func:`twist` is its
inverse. Frames and the 4x4 layout: :mod:`vrnet_ext.geometry.transforms`.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def skew(vector):
    """(..., 3) a -> (..., 3, 3) [a]x, the matrix with [a]x b = a x b (numpy arrays or torch tensors)."""
    if type(vector).__module__.startswith("torch"):
        import torch

        stack = torch.stack
    else:
        vector, stack = np.asarray(vector, dtype=np.float64), np.stack
    x, y, z = vector[..., 0], vector[..., 1], vector[..., 2]
    zero = 0 * x
    return stack([stack([zero, -z, y], -1), stack([z, zero, -x], -1), stack([-y, x, zero], -1)], -2)


def motion(xi: np.ndarray) -> np.ndarray:
    """(..., 6) twists -> (..., 4, 4) transforms: rotation exp([omega]x), translation v."""
    xi = np.asarray(xi, dtype=np.float64)
    flat = xi.reshape(-1, 6)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(flat[:, :3]).as_matrix()
    T[:, :3, 3] = flat[:, 3:]
    return T.reshape(*xi.shape[:-1], 4, 4)


def twist(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) transforms -> (..., 6) twists (rotation vector of angle in [0, pi], translation)."""
    T = np.asarray(T, dtype=np.float64)
    flat = T.reshape(-1, 4, 4)
    xi = np.concatenate([Rotation.from_matrix(flat[:, :3, :3]).as_rotvec(), flat[:, :3, 3]], axis=1)
    return xi.reshape(*T.shape[:-2], 6)


def left_jacobian_inverse(rotation_vector: np.ndarray) -> np.ndarray:
    """(..., 3) phi -> (..., 3, 3): how phi = rotvec(R) changes when R is turned by a small rotation
    from the left, ``rotvec(exp([w]x) R) = phi + (this matrix) w`` to first order."""
    phi = np.asarray(rotation_vector, dtype=np.float64)
    angle = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = angle < 1e-6
    safe = np.where(small, 1.0, angle)
    # 1/a^2 - (1 + cos a) / (2 a sin a), written with half angles (finite up to a = pi); -> 1/12 as a -> 0
    factor = np.where(small, 1.0 / 12.0, 1.0 / safe ** 2 - np.cos(safe / 2) / (2.0 * safe * np.sin(safe / 2)))
    return np.eye(3) - 0.5 * K + factor * (K @ K)


def point_information(points: np.ndarray) -> np.ndarray:
    """(N, 3) points q -> (6, 6) sum of J^T J with J = [-[q]x | I] (3, 6): the twist xi of a small
    motion moves these points by sum |omega x q + v|^2 = xi^T (this matrix) xi in total."""
    q = np.asarray(points, dtype=np.float64)
    information = np.zeros((6, 6))
    s = q.sum(axis=0)
    qq = q.T @ q
    information[:3, :3] = np.trace(qq) * np.eye(3) - qq  # sum [q]x^T [q]x
    information[:3, 3:] = skew(s)  # sum (-[q]x)^T I = sum [q]x
    information[3:, :3] = skew(s).T
    information[3:, 3:] = len(q) * np.eye(3)
    return information


__all__ = ["left_jacobian_inverse", "motion", "point_information", "skew", "twist"]
