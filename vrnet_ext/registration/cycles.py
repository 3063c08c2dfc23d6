"""Which pairwise registrations of a set of scans agree with each other, and the poses they give
before any optimisation.

Three scans registered pairwise close a loop: going round it must come back to where it started.
A loop of three edges is *consistent* when, for each of its edges, the loop's leftover motion
moves that edge's own correspondences by at most ``reach`` RMS (the same measure as the pose
graph's, :mod:`vrnet_ext.registration.pose_graph`). A wrong registration rarely closes a consistent
loop with two others, so the number of consistent loops an edge belongs to (its *support*) ranks
edges before any pose is known. :func:`spanning_tree` chains the best-supported edges into
initial poses (the optimiser then trusts the tree's edges, as Open3D trusts its odometry edges).
"""
from __future__ import annotations

from collections import defaultdict

import numpy as np

from vrnet_ext.geometry.lie import twist
from vrnet_ext.geometry.transforms import chain
from vrnet_ext.registration.pose_graph import PoseEdge


def _motion_between(edges: list[PoseEdge], index: dict[frozenset, int], a: int, b: int) -> np.ndarray:
    """T_a_b (4, 4): scan b's points into scan a's frame, from the edge between them."""
    edge = edges[index[frozenset((a, b))]]
    return edge.T_target_source if edge.target == a else np.linalg.inv(edge.T_target_source)


def triangle_support(edges: list[PoseEdge], reach: float) -> np.ndarray:
    """(E,) int: for each edge, the consistent loops of three edges it belongs to (module docstring).
    At most one edge per pair of scans is looked at (the first)."""
    index: dict[frozenset, int] = {}
    neighbours: dict[int, set[int]] = defaultdict(set)
    for i, edge in enumerate(edges):
        index.setdefault(frozenset((edge.source, edge.target)), i)
        neighbours[edge.source].add(edge.target)
        neighbours[edge.target].add(edge.source)
    support = np.zeros(len(edges), dtype=np.int64)
    for pair, i in index.items():
        a, b = sorted(pair)
        for c in neighbours[a] & neighbours[b]:
            if c <= b:
                continue  # each loop once, from its two smallest scans
            members = [i, index[frozenset((b, c))], index[frozenset((a, c))]]
            if all(_closes(edges, index, edges[m], a + b + c - edges[m].source - edges[m].target, reach)
                   for m in members):
                support[members] += 1
    return support


def _closes(edges: list[PoseEdge], index: dict[frozenset, int], edge: PoseEdge, other: int, reach: float) -> bool:
    """Whether the loop target -> source -> other -> target, seen in ``edge``'s target frame, moves
    ``edge``'s correspondences by at most ``reach`` RMS."""
    t, s = edge.target, edge.source
    loop = edge.T_target_source @ _motion_between(edges, index, s, other) @ _motion_between(edges, index, other, t)
    r = twist(loop)
    return float(r @ edge.information @ r) <= edge.correspondences * reach ** 2


def spanning_tree(count: int, edges: list[PoseEdge], support: np.ndarray,
                  reference: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The maximum spanning forest of the edges by (support, correspondences) (Kruskal), and the poses
    chained along it from ``reference`` -> (in_tree (E,) bool, poses (count, 4, 4) ``T_reference_scan``,
    placed (count,) bool: linked to the reference; the others' poses are the identity)."""
    parent = list(range(count))

    def root(node: int) -> int:
        while parent[node] != node:
            parent[node] = parent[parent[node]]
            node = parent[node]
        return node

    in_tree = np.zeros(len(edges), dtype=bool)
    for i in sorted(range(len(edges)), key=lambda i: (-support[i], -edges[i].correspondences, i)):
        a, b = root(edges[i].source), root(edges[i].target)
        if a != b:
            parent[a] = b
            in_tree[i] = True
    poses, placed = chain(count, [(edges[i].target, edges[i].source, edges[i].T_target_source)
                                  for i in np.flatnonzero(in_tree)], reference)
    return in_tree, poses, placed


__all__ = ["spanning_tree", "triangle_support"]
