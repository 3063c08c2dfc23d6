"""How well the scans' geometry pins the rigid transform down: the point-to-plane information
matrix at ICP's final correspondences, sum over pairs of J^T J with J = [((p - c) x n) / L, n]
(rotation about the pairs' centroid c, scaled by their RMS radius L so that the six directions
compare on one scale). A plane leaves the rotation about its normal and the translation along it
free (three directions with no information); a corridor, the translation along it. Directions
whose eigenvalue is below :data:`DEGENERATE` of the largest are reported: there the result rests on
noise, whatever the fitness says (Zhang & Singh, "On degeneracy of optimization-based state
estimation problems", 2016)."""
from __future__ import annotations

import torch

# Share of the largest eigenvalue below which a direction is unconstrained. On the 45 real pairs
# (3DMatch, 3DLoMatch, KITTI, at the ground truth) the smallest share was 0.015; a plane gives 2e-4,
# a straight corridor 5e-4 (benchmarks/bench_degeneracy.py).
DEGENERATE = 3e-3


def constraint_spectrum(points: torch.Tensor, normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """points (P, 3) in the target frame, normals (P, 3) of their target matches -> (eigenvalues (6,)
    ascending, as shares of the largest; eigenvectors (6, 6) as columns: rotation (scaled) then
    translation coordinates)."""
    points, normals = points.double(), normals.double()
    centred = points - points.mean(0)
    radius = centred.square().sum(1).mean().sqrt().clamp_min(1e-12)
    J = torch.cat([torch.linalg.cross(centred, normals) / radius, normals], 1)
    values, vectors = torch.linalg.eigh(J.T @ J / len(points))
    return values / values[-1].clamp_min(1e-300), vectors


def degeneracy_note(points: torch.Tensor, normals: torch.Tensor) -> str | None:
    """A warning naming the directions the correspondences leave unconstrained, or None."""
    if len(points) < 6:
        return "ICP ended with fewer than 6 point pairs: the transform is not determined by them"
    values, vectors = constraint_spectrum(points, normals)
    free = [vectors[:, k] for k in range(6) if float(values[k]) < DEGENERATE]
    if not free:
        return None
    described = []
    for vector in free:
        rotation, translation = vector[:3], vector[3:]
        kind, axis = ("rotation about", rotation) if rotation.norm() >= translation.norm() else ("translation along",
                                                                                                   translation)
        axis = axis / axis.norm()
        described.append(f"{kind} ({float(axis[0]):.2f}, {float(axis[1]):.2f}, {float(axis[2]):.2f})")
    return (f"the scans' geometry does not determine {len(free)} of the transform's 6 directions "
            f"({'; '.join(described)}): the result there rests on noise, whatever the fitness says "
            f"(a plane, a corridor or a symmetric shape)")
