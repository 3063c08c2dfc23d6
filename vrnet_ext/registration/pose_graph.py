"""Robust pose-graph optimisation: the poses of many scans from pairwise registrations, with the
wrong pairwise edges found and dropped.

Each edge is one pairwise registration ``T_target_source`` with its information matrix (the 6x6
sum of ``J^T J`` over the ICP correspondences, :func:`vrnet_ext.geometry.lie.point_information`
of the moved source points, in the target frame), as Choi et al. (2015) and Open3D's multiway registration build them.
With poses ``X_i`` (``T_reference_scan``), an edge's error is the motion
``E = X_target^-1 X_source T_target_source^-1`` of the target frame; its twist ``r``
(:mod:`vrnet_ext.geometry.lie`) moves the edge's correspondences by ``s = r^T information r`` in
total (squared distances), so ``sqrt(s / correspondences)`` is their RMS displacement.

The cost is robust: each edge contributes the Geman-McClure ``rho(s) = c s / (c + s)`` with
``c = correspondences * reach^2`` (``reach``: :class:`PoseGraphSettings`), which is the line
process of Choi et al. in closed form (Black and Rangarajan's duality): an edge's weight
``(c / (c + s))^2`` falls below 1/4 exactly when the poses move its correspondences by more than
``reach`` RMS, and such an edge is reported dropped. Edges marked ``robust=False`` (odometry one
trusts) cost ``s``. Minimised by Levenberg-Marquardt on left perturbations ``X_i <- motion(d_i) X_i``
in float64, each step a sparse direct solve (``scipy.sparse.linalg.spsolve``: the normal equations
of a pose graph are sparse, 6 unknowns per pose); the reference pose stays fixed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg

from vrnet_ext.geometry.lie import left_jacobian_inverse, motion, skew, twist

DROP_WEIGHT = 0.25  # an edge below this weight moves its correspondences by more than the reach: dropped


@dataclass(frozen=True, kw_only=True)
class PoseEdge:
    """One pairwise registration between scans ``source`` and ``target`` (indices into the poses):
    ``T_target_source`` (4, 4), ``information`` (6, 6) of its ``correspondences`` (> 0) point pairs."""

    source: int
    target: int
    T_target_source: np.ndarray
    information: np.ndarray
    correspondences: int
    robust: bool = True


@dataclass(frozen=True)
class PoseGraphSettings:
    """reach: the RMS displacement (the scans' unit) beyond which an edge counts as wrong (the ICP
    reach is the natural choice); at most ``max_iterations`` Levenberg-Marquardt steps, stopping
    once a step lowers the cost by less than ``tolerance`` of it."""

    reach: float
    max_iterations: int = 100
    tolerance: float = 1e-6

    def __post_init__(self) -> None:
        if not (np.isfinite(self.reach) and self.reach > 0):
            raise ValueError(f"PoseGraphSettings.reach must be a finite number > 0, got {self.reach!r}")
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"PoseGraphSettings.max_iterations must be an integer >= 1, got {self.max_iterations!r}")


@dataclass(kw_only=True)
class PoseGraphSolution:
    """poses (P, 4, 4) ``T_reference_scan``; per edge, in the order given: ``weight`` (E,) in (0, 1],
    ``kept`` (E,) bool (weight >= 1/4 or not robust), ``displacement`` (E,) the RMS displacement of
    its correspondences under the poses; ``iterations`` run, final robust ``cost``."""

    poses: np.ndarray
    weight: np.ndarray
    kept: np.ndarray
    displacement: np.ndarray
    iterations: int
    cost: float


class _Edges:
    """The edges as arrays: indices (E,), measured motions, information, robust scales c (E,)."""

    def __init__(self, edges: list[PoseEdge], reach: float) -> None:
        self.source = np.array([e.source for e in edges], dtype=np.int64)
        self.target = np.array([e.target for e in edges], dtype=np.int64)
        self.measured_inverse = np.linalg.inv(np.stack([e.T_target_source for e in edges]).astype(np.float64))
        self.information = np.stack([e.information for e in edges]).astype(np.float64)
        self.count = np.array([e.correspondences for e in edges], dtype=np.float64)
        self.robust = np.array([e.robust for e in edges])
        self.scale = self.count * reach ** 2

    def errors(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """-> error motions E (E, 4, 4), their twists r (E, 6), s = r^T information r (E,)."""
        error = np.linalg.inv(poses[self.target]) @ poses[self.source] @ self.measured_inverse
        r = twist(error)
        return error, r, np.einsum("ei,eij,ej->e", r, self.information, r)

    def weights(self, s: np.ndarray) -> np.ndarray:
        """The robust weight rho'(s) of each edge (1 for the non-robust)."""
        return np.where(self.robust, (self.scale / (self.scale + s)) ** 2, 1.0)

    def cost(self, s: np.ndarray) -> float:
        return float(np.where(self.robust, self.scale * s / (self.scale + s), s).sum())


def _normal_equations(poses: np.ndarray, edges: _Edges) -> tuple[scipy.sparse.csr_matrix, np.ndarray]:
    """Gauss-Newton system of the robust cost, IRLS-weighted, over all poses: (6P, 6P) H, (6P,) g."""
    error, r, s = edges.errors(poses)
    weighted = edges.weights(s)[:, None, None] * edges.information
    # d r / d(target-frame perturbation of the error motion), then of the target pose's world perturbation
    to_error = np.tile(np.eye(6), (len(r), 1, 1))
    to_error[:, :3, :3] = left_jacobian_inverse(r[:, :3])
    to_error[:, 3:, :3] = -skew(error[:, :3, 3])
    rotation_t = poses[edges.target, :3, :3].swapaxes(1, 2)
    conjugate = np.zeros_like(to_error)
    conjugate[:, :3, :3] = rotation_t
    conjugate[:, 3:, 3:] = rotation_t
    conjugate[:, 3:, :3] = -rotation_t @ skew(poses[edges.target, :3, 3])
    A = to_error @ conjugate  # d r / d d_source; d r / d d_target = -A
    block = A.swapaxes(1, 2) @ weighted @ A
    gradient = (A.swapaxes(1, 2) @ (weighted @ r[..., None]))[..., 0]
    size = 6 * len(poses)
    g = np.zeros(size)
    np.add.at(g.reshape(-1, 6), edges.source, gradient)
    np.add.at(g.reshape(-1, 6), edges.target, -gradient)
    offsets = np.arange(6)
    rows, cols, values = [], [], []
    for a, b, sign in ((edges.source, edges.source, 1), (edges.target, edges.target, 1),
                       (edges.source, edges.target, -1), (edges.target, edges.source, -1)):
        rows.append((6 * a[:, None, None] + offsets[None, :, None]).repeat(6, 2).ravel())
        cols.append((6 * b[:, None, None] + offsets[None, None, :]).repeat(6, 1).ravel())
        values.append(sign * block.ravel())
    H = scipy.sparse.coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(size, size)).tocsr()
    return H, g


def connected_to(reference: int, count: int, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(count,) bool: the nodes linked to ``reference`` through the edges ``source[i] - target[i]``."""
    graph = scipy.sparse.coo_matrix((np.ones(len(source)), (source, target)), shape=(count, count))
    _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
    return labels == labels[reference]


def bridges(count: int, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(E,) bool: the edges ``source[i] - target[i]`` whose removal disconnects their two nodes (no
    loop passes through them; parallel edges are never bridges). Tarjan's low-link, iteratively."""
    links: list[list[tuple[int, int]]] = [[] for _ in range(count)]
    for edge, (a, b) in enumerate(zip(source.tolist(), target.tolist())):
        links[a].append((b, edge))
        links[b].append((a, edge))
    order, low = [-1] * count, [0] * count
    found = np.zeros(len(source), dtype=bool)
    clock = 0
    for root in range(count):
        if order[root] >= 0:
            continue
        order[root] = low[root] = clock
        clock += 1
        stack = [(root, -1, iter(links[root]))]
        while stack:
            node, via, pending = stack[-1]
            advanced = False
            for other, edge in pending:
                if edge == via:
                    continue
                if order[other] < 0:
                    order[other] = low[other] = clock
                    clock += 1
                    stack.append((other, edge, iter(links[other])))
                    advanced = True
                    break
                low[node] = min(low[node], order[other])
            if advanced:
                continue
            stack.pop()
            if stack:
                parent = stack[-1][0]
                low[parent] = min(low[parent], low[node])
                if low[node] > order[parent]:
                    found[via] = True
    return found


def optimize_pose_graph(poses: np.ndarray, edges: list[PoseEdge], settings: PoseGraphSettings,
                        reference: int = 0) -> PoseGraphSolution:
    """The poses (P, 4, 4) minimising the robust cost of ``edges`` (module docstring), starting from
    ``poses`` (``T_reference_scan``, e.g. chained along a spanning tree), with ``poses[reference]``
    fixed. ValueError when an edge names a pose that does not exist, when its information is not
    symmetric positive semi-definite, or when a pose is not linked to the reference by any edge."""
    poses = np.array(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.isfinite(poses).all():
        raise ValueError(f"poses must be a finite (P, 4, 4) array, got shape {poses.shape}")
    count = len(poses)
    if not edges:
        raise ValueError("edges is empty: a pose graph needs at least one edge")
    for index, edge in enumerate(edges):
        if not (0 <= edge.source < count and 0 <= edge.target < count) or edge.source == edge.target:
            raise ValueError(f"edges[{index}] links {edge.source} and {edge.target}: two different poses in [0, {count})")
        if edge.correspondences < 1 or not np.isfinite(edge.information).all() or \
                np.linalg.eigvalsh(0.5 * (edge.information + edge.information.T)).min() < -1e-9 * np.abs(edge.information).max():
            raise ValueError(f"edges[{index}]: information must be finite and positive semi-definite, "
                             f"with correspondences >= 1")
    data = _Edges(edges, settings.reach)
    linked = connected_to(reference, count, data.source, data.target)
    if not linked.all():
        raise ValueError(f"poses {np.flatnonzero(~linked).tolist()} are linked to the reference pose {reference} by "
                         f"no edge; optimise each connected part on its own")
    free = np.ones(6 * count, dtype=bool)
    free[6 * reference: 6 * reference + 6] = False
    damping, iterations = 1e-6, 0
    cost = data.cost(data.errors(poses)[2])
    while iterations < settings.max_iterations and cost > 0:
        iterations += 1
        H, g = _normal_equations(poses, data)
        H = H[free][:, free].tocsc()
        diagonal = H.diagonal()
        floor = 1e-12 * max(diagonal.max(), 1e-300)
        improved = False
        while damping < 1e12:
            step = scipy.sparse.linalg.spsolve(
                H + scipy.sparse.diags(damping * (diagonal + floor), format="csc"), -g[free])
            delta = np.zeros(6 * count)
            delta[free] = step
            trial = motion(delta.reshape(count, 6)) @ poses
            trial_cost = data.cost(data.errors(trial)[2])
            if np.isfinite(trial_cost) and trial_cost < cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break
        poses, previous, cost = trial, cost, trial_cost
        damping = max(damping / 10.0, 1e-9)
        if previous - cost <= settings.tolerance * previous:
            break
    _, _, s = data.errors(poses)
    weight = data.weights(s)
    return PoseGraphSolution(poses=poses, weight=weight, kept=(weight >= DROP_WEIGHT) | ~data.robust,
                             displacement=np.sqrt(s / data.count), iterations=iterations, cost=cost)


__all__ = ["DROP_WEIGHT", "PoseEdge", "PoseGraphSettings", "PoseGraphSolution", "bridges", "connected_to",
           "optimize_pose_graph"]
