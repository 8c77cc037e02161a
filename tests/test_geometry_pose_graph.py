"""Sim(3) pose graph (vo_core/geometry/pose_graph.py, ORB-SLAM2 OptimizeEssentialGraph): a loop edge takes the scale
and pose drift out of a monocular chain, a consistent graph stays put, fixed nodes never move, and the cost is the
one the module's docstring defines, computed here with vo_core.geometry.lie."""

from __future__ import annotations

import numpy as np
import pytest

from vo_core.geometry.lie import (se3, se3_inverse, sim3, sim3_exp, sim3_inverse, sim3_log, sim3_scale, so3_exp,
                                  so3_geodesic_angle)
from vo_core.geometry.pose_graph import PoseGraphEdge, PoseGraphResult, optimize_pose_graph

ITERATIONS = 20  # ORB-SLAM2's

NODES = 100
RADIUS = 10.0
SCALE_DRIFT = 0.005  # per step: the estimated map grows by this factor at each keyframe (1.64 after 99 steps)
ROTATION_NOISE = 0.002  # rad, per odometry step


def circle_truth(count: int = NODES) -> np.ndarray:
    """Camera-to-world poses evenly around a circle, each facing along it, with a little height change."""
    poses = []
    for k in range(count):
        angle = 2.0 * np.pi * k / count
        position = np.array([RADIUS * np.cos(angle), RADIUS * np.sin(angle), 0.2 * np.sin(3.0 * angle)])
        poses.append(se3(so3_exp(np.array([0.0, 0.0, angle])), position))
    return np.array(poses)


def drifted_loop(seed: int = 0):
    """Monocular odometry around the circle, as ORB-SLAM2 hands it to OptimizeEssentialGraph.

    Each odometry edge is the SE(3) motion between consecutive estimates (scale 1: drift is invisible locally), its
    translation in the local map's units, which grow by SCALE_DRIFT a step, and its rotation a little off. The nodes
    are those motions chained from the first (true) pose. The loop edge from the last keyframe to the first is the
    true relative similarity in the last keyframe's units, as a Sim(3) between their map points would measure it:
    scale c = (1 + SCALE_DRIFT)^(N-1). Returns (nodes, edges, truth, c)."""
    rng = np.random.default_rng(seed)
    truth = circle_truth()
    nodes, edges = [truth[0]], []
    units = 1.0  # local map units per metre at node k
    for k in range(NODES - 1):
        motion = se3_inverse(truth[k]) @ truth[k + 1]
        measured = se3(motion[:3, :3] @ so3_exp(rng.normal(scale=ROTATION_NOISE, size=3)), units * motion[:3, 3])
        edges.append(PoseGraphEdge(k, k + 1, measured))
        nodes.append(nodes[-1] @ measured)
        units *= 1.0 + SCALE_DRIFT
    loop = se3_inverse(truth[-1]) @ truth[0]
    edges.append(PoseGraphEdge(NODES - 1, 0, sim3(units, loop[:3, :3], units * loop[:3, 3])))
    return np.array(nodes), edges, truth, units


def first_fixed(count: int) -> np.ndarray:
    fixed = np.zeros(count, bool)
    fixed[0] = True
    return fixed


def random_similarity(rng: np.random.Generator) -> np.ndarray:
    return sim3_exp(np.concatenate([rng.normal(scale=2.0, size=3), rng.normal(scale=0.8, size=3),
                                    [rng.normal(scale=0.3)]]))


def cost_by_lie(nodes: np.ndarray, edges: list[PoseGraphEdge]) -> float:
    """The documented cost, sum weight e^T Lambda e with e = log(S_i_j^-1 S_world_i^-1 S_world_j), edge by edge
    with lie."""
    total = 0.0
    for edge in edges:
        error = sim3_log(sim3_inverse(edge.S_i_j) @ sim3_inverse(nodes[edge.i]) @ nodes[edge.j])
        information = np.eye(7) if edge.information is None else edge.information
        total += edge.weight * float(error @ information @ error)
    return total


def random_information(rng: np.random.Generator) -> np.ndarray:
    """A symmetric positive definite 7x7 whose eigenvalues span four decades, as a Sim(3) fit's J^T J does."""
    basis, _ = np.linalg.qr(rng.normal(size=(7, 7)))
    return basis @ np.diag(10.0 ** rng.uniform(-2.0, 2.0, 7)) @ basis.T


def test_loop_edge_corrects_scale_and_pose_drift():
    nodes, edges, truth, units = drifted_loop()
    result = optimize_pose_graph(nodes, edges, first_fixed(NODES), iterations=ITERATIONS)

    assert isinstance(result, PoseGraphResult) and result.S_world_nodes.shape == (NODES, 4, 4)
    assert 0 < result.iterations <= ITERATIONS
    assert result.cost_after < 1e-2 * result.cost_before
    error_before = np.linalg.norm(nodes[-1, :3, 3] - truth[-1, :3, 3])
    error_after = np.linalg.norm(result.S_world_nodes[-1, :3, 3] - truth[-1, :3, 3])
    assert error_before > 5.0  # metres: the drift is there to correct
    assert error_after < 0.1 * error_before
    # The last keyframe's map is `units` times too large: its node should scale it back by 1 / units.
    log_scale_error_before = abs(np.log(sim3_scale(nodes[-1])) + np.log(units))
    log_scale_error_after = abs(np.log(sim3_scale(result.S_world_nodes[-1])) + np.log(units))
    assert log_scale_error_after < 0.1 * log_scale_error_before
    # The whole trajectory comes back, not only its end.
    worst_after = np.linalg.norm(result.S_world_nodes[:, :3, 3] - truth[:, :3, 3], axis=1).max()
    assert worst_after < 0.1 * error_before


def test_consistent_graph_stays_put():
    rng = np.random.default_rng(1)
    nodes = np.array([random_similarity(rng) for _ in range(12)])
    pairs = [(k, k + 1) for k in range(11)] + [(0, 6), (3, 9), (11, 2), (5, 1)]
    edges = [PoseGraphEdge(i, j, sim3_inverse(nodes[i]) @ nodes[j], weight=float(rng.uniform(0.5, 3.0)))
             for i, j in pairs]
    result = optimize_pose_graph(nodes, edges, first_fixed(len(nodes)), iterations=ITERATIONS)

    assert result.cost_before < 1e-20
    assert result.cost_after <= result.cost_before
    np.testing.assert_allclose(result.S_world_nodes, nodes, rtol=0.0, atol=1e-9)


def test_fixed_nodes_do_not_move():
    nodes, edges, _, _ = drifted_loop(seed=2)
    fixed = np.zeros(NODES, bool)
    fixed[[0, 30, 65]] = True
    result = optimize_pose_graph(nodes, edges, fixed, iterations=ITERATIONS)

    assert result.cost_after < result.cost_before
    np.testing.assert_array_equal(result.S_world_nodes[fixed], nodes[fixed])
    assert np.abs(result.S_world_nodes[~fixed] - nodes[~fixed]).max() > 0.1  # the others did move


def test_cost_is_the_weighted_sim3_log_of_the_documented_residual():
    rng = np.random.default_rng(3)
    nodes = np.array([random_similarity(rng) for _ in range(6)])
    edges = [PoseGraphEdge(i, j, sim3_inverse(nodes[i]) @ nodes[j] @ sim3_exp(rng.normal(scale=0.2, size=7)),
                           weight=float(rng.uniform(0.5, 3.0)), information=information)
             for (i, j), information in zip([(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4)],
                                            [None, random_information(rng), None, random_information(rng), None,
                                             random_information(rng), random_information(rng)])]
    result = optimize_pose_graph(nodes, edges, first_fixed(len(nodes)), iterations=ITERATIONS)

    assert result.cost_before == pytest.approx(cost_by_lie(nodes, edges), rel=1e-12)
    assert result.cost_after == pytest.approx(cost_by_lie(result.S_world_nodes, edges), rel=1e-12)
    assert result.cost_after < 0.5 * result.cost_before
    # At the minimum no small move of a free node lowers the cost (the Jacobian is the right one).
    for node in (2, 5):
        for axis in range(7):
            for step in (-1e-4, 1e-4):
                moved = result.S_world_nodes.copy()
                moved[node] = sim3_exp(step * np.eye(7)[axis]) @ moved[node]
                assert cost_by_lie(moved, edges) >= result.cost_after - 1e-12


def test_an_edge_pulls_along_what_its_information_is_sure_of():
    """Two measurements of one relative pose that disagree: one sure of the translation and unsure of the rotation,
    the other the reverse. The optimum takes each component from the edge sure of it (a loop's Sim(3) from a narrow
    view pins some directions and leaves others to the odometry)."""
    translation_sure = np.diag([1e4, 1e4, 1e4, 1e-4, 1e-4, 1e-4, 1.0])
    rotation_sure = np.diag([1e-4, 1e-4, 1e-4, 1e4, 1e4, 1e4, 1.0])
    by_translation = se3(so3_exp(np.array([0.0, 0.2, 0.0])), np.array([1.0, 0.0, 0.0]))
    by_rotation = se3(so3_exp(np.array([0.0, 0.0, 0.0])), np.array([0.0, 1.0, 0.0]))
    edges = [PoseGraphEdge(0, 1, by_translation, information=translation_sure),
             PoseGraphEdge(0, 1, by_rotation, information=rotation_sure)]
    result = optimize_pose_graph(np.array([np.eye(4), np.eye(4)]), edges, first_fixed(2), iterations=ITERATIONS)

    moved = result.S_world_nodes[1]
    assert so3_geodesic_angle(moved[:3, :3], by_rotation[:3, :3]) < 1e-3
    # by_translation^-1 moved has no translation part only where moved's centre is by_translation's.
    np.testing.assert_allclose(moved[:3, 3], by_translation[:3, 3], atol=1e-3)


def test_deterministic():
    nodes, edges, _, _ = drifted_loop(seed=4)
    first = optimize_pose_graph(nodes, edges, first_fixed(NODES), iterations=ITERATIONS)
    second = optimize_pose_graph(nodes, edges, first_fixed(NODES), iterations=ITERATIONS)
    np.testing.assert_array_equal(first.S_world_nodes, second.S_world_nodes)
    assert (first.iterations, first.cost_after) == (second.iterations, second.cost_after)


def test_input_is_not_modified_and_a_node_without_edges_stays():
    nodes, edges, _, _ = drifted_loop(seed=5)
    lonely = se3(so3_exp(np.array([0.1, 0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    with_lonely = np.concatenate([nodes, lonely[None]])
    copy = with_lonely.copy()
    result = optimize_pose_graph(with_lonely, edges, first_fixed(NODES + 1), iterations=ITERATIONS)
    np.testing.assert_array_equal(with_lonely, copy)
    np.testing.assert_array_equal(result.S_world_nodes[-1], lonely)


@pytest.mark.parametrize("fixed, edge, message", [
    (np.zeros(3, bool), PoseGraphEdge(0, 1, np.eye(4)), "fixed"),
    (np.ones(2, bool), PoseGraphEdge(0, 1, np.eye(4)), r"\(3,\)"),
    (np.array([True, False, False]), PoseGraphEdge(0, 3, np.eye(4)), "outside"),
    (np.array([True, False, False]), PoseGraphEdge(1, 1, np.eye(4)), "itself"),
    (np.array([True, False, False]), PoseGraphEdge(0, 1, np.eye(4), weight=0.0), "positive"),
    (np.array([True, False, False]), PoseGraphEdge(0, 1, np.eye(4), information=np.diag([1.0] * 6 + [0.0])),
     "positive definite"),
    (np.array([True, False, False]), PoseGraphEdge(0, 1, np.eye(4), information=np.eye(7) + np.eye(7, k=1)),
     "symmetric"),
])
def test_bad_input_is_refused(fixed, edge, message):
    with pytest.raises(ValueError, match=message):
        optimize_pose_graph(np.array([np.eye(4)] * 3), [edge], fixed, iterations=ITERATIONS)
