"""Shapes the package makes itself (no data needed): chair-like objects of boxes and cylinders,
and room-like scans (:func:`room_scan`) for registration tests and benchmarks.

Each shape has a seat, a backrest, four legs and one armrest, with sizes drawn from the generator,
so no two are alike and none has a rotational symmetry (the armrest sits on one side only). Points
are sampled uniformly over the surface area and normalised as ModelNet40's PointNet files are:
centred on their centroid and scaled into the unit sphere.
"""
from __future__ import annotations

import numpy as np


def _box_surface(rng: np.random.Generator, centre, size, count: int) -> np.ndarray:
    """``count`` points uniform on the surface of an axis-aligned box."""
    size = np.asarray(size, dtype=np.float64)
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    face_axis = rng.choice(3, size=count, p=areas / areas.sum())
    points = rng.uniform(-0.5, 0.5, size=(count, 3))
    points[np.arange(count), face_axis] = rng.choice([-0.5, 0.5], size=count)
    return points * size + np.asarray(centre)


def _cylinder_surface(rng: np.random.Generator, base, radius: float, height: float, count: int) -> np.ndarray:
    """``count`` points uniform on the side of a vertical (y-axis) cylinder."""
    angle = rng.uniform(0, 2 * np.pi, size=count)
    y = rng.uniform(0, height, size=count)
    return np.stack([radius * np.cos(angle), y, radius * np.sin(angle)], axis=1) + np.asarray(base)


def chair(rng: np.random.Generator, num_points: int = 1024) -> np.ndarray:
    """(num_points, 3) float32 surface points of a random asymmetric chair, in the unit sphere."""
    width, depth = rng.uniform(0.7, 1.1), rng.uniform(0.6, 0.9)
    seat_height, seat_thickness = rng.uniform(0.6, 0.9), rng.uniform(0.06, 0.12)
    back_height, leg_radius = rng.uniform(0.6, 1.0), rng.uniform(0.03, 0.06)
    arm_side = rng.choice([-1.0, 1.0])
    parts = [
        ("box", (0.0, seat_height, 0.0), (width, seat_thickness, depth)),
        ("box", (0.0, seat_height + back_height / 2, -depth / 2), (width, back_height, seat_thickness)),
        ("box", (arm_side * width / 2, seat_height + 0.25, 0.0), (seat_thickness, 0.06, depth * 0.8)),
    ]
    for sx in (-1, 1):
        for sz in (-1, 1):
            parts.append(("cylinder", (sx * (width / 2 - 0.08), 0.0, sz * (depth / 2 - 0.08)), leg_radius, seat_height))
    areas = []
    for part in parts:
        if part[0] == "box":
            sx, sy, sz = part[2]
            areas.append(2 * (sx * sy + sy * sz + sx * sz))
        else:
            areas.append(2 * np.pi * part[2] * part[3])
    counts = rng.multinomial(num_points, np.asarray(areas) / np.sum(areas))
    clouds = []
    for part, count in zip(parts, counts):
        if part[0] == "box":
            clouds.append(_box_surface(rng, part[1], part[2], count))
        else:
            clouds.append(_cylinder_surface(rng, part[1], part[2], part[3], count))
    points = np.concatenate(clouds)[rng.permutation(num_points)]
    points -= points.mean(axis=0)
    points /= np.linalg.norm(points, axis=1).max()
    return points.astype(np.float32)


def room_scan(points: int, seed: int) -> np.ndarray:
    """A 10 x 8 x 3 m room with a table and two boxes, sampled uniformly by area, 3 mm noise."""
    rng = np.random.default_rng(seed)
    boxes = [((0, 0, 0), (10, 8, 3)), ((2, 2, 0), (4, 3, 0.8)), ((6, 5, 0), (6.6, 5.8, 1.5)),
             ((7.5, 1, 0), (8.5, 1.5, 2.2))]
    faces = []
    for low, high in boxes:
        low, high = np.array(low, float), np.array(high, float)
        for axis in range(3):
            for side in (low, high):
                others = [a for a in range(3) if a != axis]
                faces.append((axis, side[axis], low[others], high[others], others))
    areas = np.array([np.prod(h - l) for _, _, l, h, _ in faces])
    counts = rng.multinomial(points, areas / areas.sum())
    cloud = []
    for (axis, level, low, high, others), count in zip(faces, counts):
        p = np.empty((count, 3))
        p[:, axis] = level
        p[:, others] = rng.uniform(low, high, (count, 2))
        cloud.append(p)
    return np.concatenate(cloud) + rng.normal(0.0, 0.003, (points, 3))


__all__ = ["chair", "room_scan"]
