"""Keyframe decision, keyframe marginalization choice and motion hypotheses (DSO's rules)."""

from __future__ import annotations

import numpy as np

from test_direct_support import pose
from vo_core.direct.config import KeyframeConfig
from vo_core.direct.keyframe_policy import fraction_in_view, keyframes_to_marginalize, needs_keyframe
from vo_core.direct.motion_model import motion_hypotheses
from vo_core.geometry.motion_model import extrapolate
from vo_core.geometry.lie import se3_inverse

CONFIG = KeyframeConfig()


def test_keyframe_when_translation_flow_brightness_or_rmse_grows():
    def decide(flow_t=0.0, flow_rt=0.0, factor=1.0, rmse=1.0):
        return needs_keyframe(np.array([flow_t**2, 0.0, flow_rt**2]), factor, rmse, 1.0, 640, 480, CONFIG)

    assert not decide()
    # DSO at 640x480: translation-only flow above 0.04 (w + h) = 25 px, or both above 50 px.
    assert not decide(flow_t=20.0) and decide(flow_t=30.0)
    assert not decide(flow_rt=40.0) and decide(flow_rt=60.0)
    assert decide(factor=np.exp(0.6))  # 2 |log a| > 1
    assert decide(rmse=2.5)  # more than twice the first RMSE on this keyframe


def test_marginalization_drops_keyframes_out_of_view_then_the_redundant_one():
    ids = np.arange(8)
    positions = np.array([[0.1 * i, 0.0, 0.0] for i in range(8)])
    in_view = np.ones(8)
    in_view[2] = 0.01
    dropped = keyframes_to_marginalize(ids, positions, in_view, np.zeros(8), CONFIG)
    assert 2 in dropped
    assert 0 not in dropped  # the first keyframe only leaves when out of view
    assert len(ids) - len(dropped) < CONFIG.max_frames
    assert keyframes_to_marginalize(ids[:4], positions[:4], np.ones(4), np.zeros(4), CONFIG) == []


def test_the_share_of_points_in_view_counts_what_lands_in_front_of_the_viewer_and_inside_its_image():
    intrinsics = np.array([100.0, 100.0, 49.5, 39.5])  # 100 x 80 pixels
    uv = np.array([[u, v] for u in range(0, 100, 10) for v in range(0, 80, 10)], float)  # 80 points, all inside
    idepth = np.full(len(uv), 0.5)  # 2 m away
    assert fraction_in_view(uv, idepth, np.eye(4), intrinsics, 100, 80) == 1.0
    # Half a field of view to the right (the viewer 1 m to the right at 2 m depth is 50 px): the left half leaves.
    right = se3_inverse(pose(translation=(1.0, 0.0, 0.0)))
    assert fraction_in_view(uv, idepth, right, intrinsics, 100, 80) == 0.5
    # Turned around: everything is behind the viewer.
    behind = se3_inverse(pose((0.0, np.pi, 0.0)))
    assert fraction_in_view(uv, idepth, behind, intrinsics, 100, 80) == 0.0


def test_constant_velocity_comes_first_and_extrapolates_the_last_motion():
    T_world_ref = pose()
    T_world_prev2 = pose((0.0, 0.01, 0.0), (0.1, 0.0, 0.0))
    T_world_prev1 = pose((0.0, 0.02, 0.0), (0.2, 0.0, 0.0))
    hypotheses = motion_hypotheses(T_world_prev2, T_world_prev1, T_world_ref, 0.02)
    expected_world_frame = T_world_prev1 @ se3_inverse(T_world_prev2) @ T_world_prev1
    np.testing.assert_allclose(hypotheses[0], se3_inverse(expected_world_frame) @ T_world_ref, atol=1e-12)
    assert len(hypotheses) == 5 + 26  # DSO: 5 motion guesses and 26 rotated constant-velocity guesses
    np.testing.assert_allclose(hypotheses[4], np.eye(4))  # zero motion from the keyframe
    assert all(np.allclose(h[:3, :3].T @ h[:3, :3], np.eye(3)) for h in hypotheses)
    # Live runs leave the rotations out: DSO's 5 motion guesses, the same ones.
    np.testing.assert_allclose(np.array(motion_hypotheses(T_world_prev2, T_world_prev1, T_world_ref, None)),
                               np.array(hypotheses[:5]))


def test_missed_frames_add_the_constant_velocity_over_the_time_that_passed():
    T_world_ref = pose()
    T_world_prev2 = pose((0.0, 0.01, 0.0), (0.1, 0.0, 0.0))
    T_world_prev1 = pose((0.0, 0.02, 0.0), (0.2, 0.0, 0.0))
    regular = motion_hypotheses(T_world_prev2, T_world_prev1, T_world_ref, 0.02)
    after_gap = motion_hypotheses(T_world_prev2, T_world_prev1, T_world_ref, 0.02, time_ratio=3.0)
    step = T_world_prev1 @ se3_inverse(T_world_prev2)  # the last motion, in the world frame
    expected_world_frame = step @ step @ step @ T_world_prev1
    np.testing.assert_allclose(after_gap[-1], se3_inverse(expected_world_frame) @ T_world_ref, atol=1e-9)
    assert len(after_gap) == len(regular) + 1
    np.testing.assert_allclose(np.array(after_gap[:-1]), np.array(regular))  # DSO's guesses first, unchanged


def test_after_a_jump_the_next_frame_moves_at_the_jump_s_velocity_not_by_the_whole_jump():
    T_world_ref = pose()
    T_world_prev2 = pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    T_world_prev1 = pose((0.0, 0.09, 0.0), (0.0, 0.0, 0.9))  # 9 frame intervals between the two
    hypotheses = motion_hypotheses(T_world_prev2, T_world_prev1, T_world_ref, 0.02, time_ratio=1.0 / 9.0)
    regular = motion_hypotheses(T_world_prev2, T_world_prev1, T_world_ref, 0.02)
    assert len(hypotheses) == len(regular)
    T_world_frame = T_world_ref @ se3_inverse(hypotheses[0])
    step = se3_inverse(T_world_prev1) @ T_world_frame
    # One ninth of the last motion (DSO would repeat all of it): nine such steps make the jump.
    np.testing.assert_allclose(np.linalg.matrix_power(step, 9), se3_inverse(T_world_prev2) @ T_world_prev1, atol=1e-9)


def test_the_pose_predicted_after_a_gap_repeats_the_last_motion_over_the_time_that_passed():
    T_world_prev2 = pose((0.0, 0.01, 0.0), (0.1, 0.0, 0.0))
    T_world_prev1 = pose((0.0, 0.02, 0.0), (0.2, 0.0, 0.0))
    posed = [(1.0, T_world_prev2), (1.1, T_world_prev1)]
    step = T_world_prev1 @ se3_inverse(T_world_prev2)  # the last motion, in the world frame
    # 11 intervals later (10 frames lost): the last motion 11 times over.
    np.testing.assert_allclose(extrapolate(posed, 2.2), np.linalg.matrix_power(step, 11) @ T_world_prev1, atol=1e-9)
    np.testing.assert_allclose(extrapolate(posed[-1:], 2.2), T_world_prev1)  # one pose: no velocity
    np.testing.assert_allclose(extrapolate([(1.1, T_world_prev2), (1.1, T_world_prev1)], 2.2), T_world_prev1)
    assert extrapolate([], 2.2) is None
