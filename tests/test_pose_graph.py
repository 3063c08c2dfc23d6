"""The robust pose graph (vrnet_ext.registration.pose_graph), the loop checks that start it
(cycles) and the small-motion algebra they use (geometry.lie), against exact synthetic graphs."""
import numpy as np
import pytest

from vrnet_ext.geometry.lie import left_jacobian_inverse, motion, point_information, twist
from vrnet_ext.registration.cycles import spanning_tree, triangle_support
from vrnet_ext.registration.pose_graph import PoseEdge, PoseGraphSettings, optimize_pose_graph

POINTS = np.random.default_rng(7).uniform(-2, 2, (300, 3))  # the correspondences every synthetic edge has


def _trajectory(count: int, seed: int) -> np.ndarray:
    """(count, 4, 4) poses of a random walk, the first the identity."""
    rng = np.random.default_rng(seed)
    steps = motion(np.concatenate([rng.normal(0, 0.1, (count, 3)), rng.normal(0, 0.5, (count, 3))], axis=1))
    poses = [np.eye(4)]
    for step in steps[1:]:
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _edge(truth, source, target, rng, noise=0.0, wrong=False, robust=True):
    T = np.linalg.inv(truth[target]) @ truth[source]
    if wrong:
        T = motion(np.concatenate([rng.normal(0, 0.6, 3), rng.normal(0, 1.0, 3)])) @ T
    elif noise:
        T = motion(rng.normal(0, noise, 6)) @ T
    return PoseEdge(source=source, target=target, T_target_source=T, information=point_information(POINTS),
                    correspondences=len(POINTS), robust=robust)


def _chained(edges, count):
    poses = [np.eye(4)]
    for edge in edges[:count - 1]:
        poses.append(poses[-1] @ edge.T_target_source)
    return np.stack(poses)


def test_twist_and_motion_are_inverse_and_information_measures_displacement():
    rng = np.random.default_rng(0)
    xi = np.concatenate([rng.normal(0, 1, (50, 3)), rng.normal(0, 3, (50, 3))], axis=1)
    xi[0, :3] = [np.pi - 1e-9, 0, 0]  # next to a half turn
    np.testing.assert_allclose(motion(twist(motion(xi))), motion(xi), atol=1e-9)
    small = rng.normal(0, 1e-5, 6)
    T = motion(small)
    moved = POINTS @ T[:3, :3].T + T[:3, 3]
    assert np.isclose(((moved - POINTS) ** 2).sum(), small @ point_information(POINTS) @ small, rtol=1e-4)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 0.3, 2.0, np.pi - 1e-3])
def test_left_jacobian_inverse_against_finite_differences(angle):
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    phi = angle * axis / np.linalg.norm(axis)
    R = motion(np.r_[phi, 0, 0, 0])
    eps = 1e-7
    numeric = np.stack([(twist(motion(np.r_[eps * e, 0, 0, 0]) @ R)[:3] - twist(motion(np.r_[-eps * e, 0, 0, 0]) @ R)[:3])
                        / (2 * eps) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(left_jacobian_inverse(phi), numeric, atol=1e-5)


def test_exact_graph_is_recovered_from_a_bad_start():
    truth = _trajectory(30, seed=2)
    rng = np.random.default_rng(3)
    edges = [_edge(truth, i + 1, i, rng) for i in range(29)] + [_edge(truth, j, i, rng) for i, j in
                                                                 [(0, 10), (5, 20), (3, 29), (12, 27)]]
    start = motion(rng.normal(0, 0.2, (30, 6))) @ truth
    start[0] = np.eye(4)
    solution = optimize_pose_graph(start, edges, PoseGraphSettings(reach=1.0))
    np.testing.assert_allclose(solution.poses, truth, atol=1e-7)
    assert solution.kept.all() and solution.displacement.max() < 1e-7


def test_wrong_loop_edges_are_dropped_and_poses_recovered_within_noise():
    """A 200-pose sequence, trusted odometry with noise, 100 loop edges of which 20 % are wrong."""
    count, rng = 200, np.random.default_rng(4)
    truth = _trajectory(count, seed=5)
    edges = [_edge(truth, i + 1, i, rng, noise=1e-3, robust=False) for i in range(count - 1)]
    wrong = np.zeros(len(edges) + 100, dtype=bool)
    for k in range(100):
        i = int(rng.integers(0, count - 12))
        j = i + int(rng.integers(2, 12))
        wrong[len(edges)] = k % 5 == 0
        edges.append(_edge(truth, j, i, rng, noise=1e-3, wrong=k % 5 == 0))
    solution = optimize_pose_graph(_chained(edges, count), edges, PoseGraphSettings(reach=0.05))
    assert not solution.kept[wrong].any()
    assert solution.kept[~wrong].all()
    relative_truth = np.linalg.inv(truth[:-1]) @ truth[1:]
    relative = np.linalg.inv(solution.poses[:-1]) @ solution.poses[1:]
    assert np.abs(twist(np.linalg.inv(relative_truth) @ relative)).max() < 0.01  # odometry noise is 1e-3 per axis


def test_triangle_support_and_spanning_tree_leave_a_wrong_edge_out():
    truth = _trajectory(5, seed=6)
    rng = np.random.default_rng(8)
    pairs = [(i, j) for i in range(5) for j in range(i + 1, 5)]
    edges = [_edge(truth, j, i, rng, wrong=(i, j) == (0, 2)) for i, j in pairs]
    support = triangle_support(edges, reach=0.05)
    assert support[pairs.index((0, 2))] == 0
    assert (np.delete(support, pairs.index((0, 2))) >= 1).all()
    in_tree, poses, placed = spanning_tree(5, edges, support)
    assert placed.all() and not in_tree[pairs.index((0, 2))] and in_tree.sum() == 4
    np.testing.assert_allclose(poses, truth, atol=1e-9)


def test_a_part_no_edge_reaches_is_left_unplaced_by_the_tree():
    truth = _trajectory(4, seed=9)
    rng = np.random.default_rng(10)
    edges = [_edge(truth, 1, 0, rng), _edge(truth, 3, 2, rng)]
    _, _, placed = spanning_tree(4, edges, triangle_support(edges, 0.05))
    assert placed.tolist() == [True, True, False, False]


def test_bad_graphs_get_errors_naming_what_is_wrong():
    truth = _trajectory(3, seed=11)
    rng = np.random.default_rng(12)
    good = [_edge(truth, 1, 0, rng), _edge(truth, 2, 1, rng)]
    settings = PoseGraphSettings(reach=0.1)
    with pytest.raises(ValueError, match=r"edges\[1\] links 2 and 5"):
        optimize_pose_graph(truth, [good[0], _edge(np.concatenate([truth, truth]), 2, 5, rng)], settings)
    with pytest.raises(ValueError, match=r"poses \[2\] are linked to the reference"):
        optimize_pose_graph(truth, good[:1], settings)
    negative = PoseEdge(source=1, target=0, T_target_source=np.eye(4), information=-np.eye(6), correspondences=3)
    with pytest.raises(ValueError, match=r"edges\[0\]: information must be finite and positive semi-definite"):
        optimize_pose_graph(truth, [negative, good[1]], settings)
    with pytest.raises(ValueError, match="reach"):
        PoseGraphSettings(reach=0.0)
    with pytest.raises(ValueError, match="poses must be a finite"):
        optimize_pose_graph(np.full((3, 4, 4), np.nan), good, settings)


def test_bridges_against_removing_each_edge():
    from vrnet_ext.registration.pose_graph import bridges, connected_to

    rng = np.random.default_rng(13)
    for _ in range(30):
        count = int(rng.integers(2, 12))
        pairs = rng.integers(0, count, (int(rng.integers(1, 16)), 2))
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        if not len(pairs):
            continue
        found = bridges(count, pairs[:, 0], pairs[:, 1])
        for i, (a, b) in enumerate(pairs):
            rest = np.delete(pairs, i, axis=0)
            assert found[i] == (not connected_to(a, count, rest[:, 0], rest[:, 1])[b])
