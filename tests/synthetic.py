"""Synthetic clouds and motions that several test modules share (test modules never import each
other)."""
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from vrnet_ext.geometry.transforms import to_homogeneous


def room(count=4000, seed=0):
    """Points on three orthogonal walls of a 4 m room corner plus a box: enough structure for ICP."""
    rng = np.random.default_rng(seed)
    walls = rng.uniform(0, 4, size=(count, 3))
    walls[: count // 3, 0] = 0
    walls[count // 3: 2 * count // 3, 1] = 0
    walls[2 * count // 3:, 2] = 0
    box = rng.uniform(1, 1.6, size=(count // 4, 3))
    box[:, rng.integers(0, 3, count // 4)] = 1.0
    return np.concatenate([walls, box]).astype(np.float64)


def motion(degrees, translation, seed=1):
    """A 4x4 rigid motion: ``degrees`` about an axis drawn with ``seed``, then ``translation``."""
    R = Rotation.from_rotvec(np.radians(degrees) * Rotation.random(random_state=seed).as_rotvec() /
                             np.linalg.norm(Rotation.random(random_state=seed).as_rotvec())).as_matrix()
    return to_homogeneous(R, np.asarray(translation, dtype=float))


def box_scan(points: int = 4000, seed: int = 0) -> np.ndarray:
    """Inside of a 4 x 3 x 2.5 box with a table, sampled by area (sensor near the centre)."""
    rng = np.random.default_rng(seed)
    faces = rng.integers(0, 6, points)
    scan = rng.uniform([-2, -1.5, -1.25], [2, 1.5, 1.25], (points, 3))
    for face in range(6):
        scan[faces == face, face % 3] = [-2, -1.5, -1.25, 2, 1.5, 1.25][face]
    table = rng.uniform([-0.5, -0.3, -0.5], [0.5, 0.3, -0.5], (points // 4, 3))
    return np.concatenate([scan, table]) + rng.normal(0, 0.003, (points + points // 4, 3))


def furnished_room(points: int = 20000, seed: int = 0) -> np.ndarray:
    """:func:`box_scan` with six boxes of furniture at random places and sizes: a room with no symmetry."""
    rng = np.random.default_rng(seed)
    parts = [box_scan(points, seed)]
    for _ in range(6):
        low = rng.uniform([-1.8, -1.3, -1.25], [1.2, 0.8, -1.25])
        size = rng.uniform([0.2, 0.2, 0.3], [0.8, 0.7, 1.5])
        faces = rng.integers(0, 6, points // 10)
        box = low + rng.uniform(0, 1, (points // 10, 3)) * size
        for face in range(6):
            box[faces == face, face % 3] = low[face % 3] + (face >= 3) * size[face % 3]
        parts.append(box)
    return np.concatenate(parts)


def room_views(count: int = 4, seed: int = 0, radius: float = 2.0) -> tuple[list[np.ndarray], np.ndarray]:
    """``count`` overlapping views of :func:`furnished_room` (the points within ``radius`` of camera
    positions along the room's length), each in its own frame -> (views, poses (count, 4, 4)
    ``T_room_view``)."""
    room_points = furnished_room(seed=seed)
    rng = np.random.default_rng(seed + 1)
    views, poses = [], []
    for k, x in enumerate(np.linspace(-1.2, 1.2, count)):
        centre = np.array([x, rng.uniform(-0.3, 0.3), 0.0])
        inside = room_points[np.linalg.norm(room_points - centre, axis=1) < radius]
        pose = motion(rng.uniform(5, 30), centre, seed=seed * 100 + k)
        views.append((inside - pose[:3, 3]) @ pose[:3, :3])  # T_room_view^-1 applied
        poses.append(pose)
    return views, np.stack(poses)


def correspondences(K, outlier_ratio, seed=0, noise=0.005):
    """(p, q, R, t, inlier): K float64 correspondences q = R p + t + noise, a share ``outlier_ratio`` of
    them replaced by random points (``inlier`` marks the rest)."""
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(K, 3, generator=g, dtype=torch.float64) * 2
    R = torch.tensor(Rotation.from_rotvec([0.3, -1.2, 0.8]).as_matrix())
    t = torch.tensor([0.5, -1.0, 0.3], dtype=torch.float64)
    q = p @ R.T + t + torch.randn(K, 3, generator=g, dtype=torch.float64) * noise
    outlier = torch.rand(K, generator=g) < outlier_ratio
    q[outlier] = torch.rand(int(outlier.sum()), 3, generator=g, dtype=torch.float64) * 2
    return p, q, R, t, ~outlier


def lane_crowded_features(C: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Three query rows and 256 reference rows whose 24 nearest to the first query all lie in the reference
    rows 8 i and 8 i + 1: one lane's quarter on the tensor cores, more than the 16 candidates it keeps."""
    query = torch.randn(1, 3, C, generator=generator)
    ref = torch.randn(1, 256, C, generator=generator) * 10
    crowd = torch.tensor([j for j in range(96) if j % 8 < 2])
    ref[0, crowd] = query[0, 0] + 0.1 * torch.randn(len(crowd), C, generator=generator)
    return query, ref


def rounding_biased_features(C: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """One query row and 300 reference rows at squared distances 1 + 1e-6 u from it (u uniform in [0, 1)),
    with their mirror images far away (the reference mean is then exactly 0, so the rows are centred as
    given). TF32 rounds the query's first value down by 2^-11 of it and each row's by up to 2^-13: with one
    TF32 product per pair every approximate distance would come out about 1e-3 too large, give or take 2e-4
    from row to row, and lanes would keep rows by rounding noise; split products narrow that to ~1e-7, still
    far wider than the rows' differences, so no row's ranking may be proven."""
    first = 1 + 0.49 * 2**-10
    exact_in_tf32 = torch.randint(-4, 5, (300,), generator=generator) * 2**-10
    below_tf32 = (torch.rand(300, generator=generator, dtype=torch.float64) * 2 - 1) * 2**-13
    rows_first = 1 + exact_in_tf32.double() + below_tf32
    squared = 1 + 1e-6 * torch.rand(300, generator=generator, dtype=torch.float64)
    rest = torch.nn.functional.normalize(torch.randn(300, C - 1, generator=generator, dtype=torch.float64), dim=1)
    rest = rest * (squared - (first - rows_first) ** 2).sqrt()[:, None]
    near = torch.cat([rows_first[:, None], rest], dim=1).float()
    query = torch.zeros(1, 1, C)
    query[0, 0, 0] = first
    return query, torch.cat([near, -near])[None]
