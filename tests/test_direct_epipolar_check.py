"""The start check's independent witness (vo_core/direct/epipolar_check.py): the ORB matches between a start's
keyframes agree with their true motion, contradict a wrong one with the reason, and say nothing where the views
are too close to tell."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from vo_core.direct.config import EpipolarCheckConfig
from vo_core.direct.epipolar_check import EpipolarCheck
from vo_core.geometry.lie import se3, so3_exp
from vo_core.synthetic import make_sequence

KEYFRAMES = [0, 8, 16, 24, 32]  # the smooth preset's room under 2-5 deg of parallax from frame 0


@pytest.fixture(scope="module")
def room():
    sequence = make_sequence("smooth", KEYFRAMES[-1] + 1, 0, 640, 480)
    frames = {frame.index: frame for frame in sequence}
    return sequence, frames


def keyframes_at(room, indices, poses=None):
    sequence, frames = room
    poses = poses or {index: sequence.ground_truth.poses[index] for index in indices}
    return [SimpleNamespace(frame_index=i, image=frames[i].image, T_world_cam=poses[i]) for i in indices]


def wrong_poses(room) -> dict[int, np.ndarray]:
    """Each keyframe's motion from the first turned by 6 deg and its translation sent sideways (the coarse
    initializer's wrong KITTI start: 8 deg, 45 deg)."""
    truth = room[0].ground_truth.poses
    first = truth[KEYFRAMES[0]]
    poses = {KEYFRAMES[0]: first}
    for index in KEYFRAMES[1:]:
        T_first_other = np.linalg.inv(first) @ truth[index]
        turn = so3_exp(np.radians(6.0) * np.array([0.0, 1.0, 0.0]))
        sideways = so3_exp(np.radians(60.0) * np.array([1.0, 0.0, 0.0])) @ T_first_other[:3, 3]
        poses[index] = first @ se3(turn @ T_first_other[:3, :3], sideways)
    return poses


def test_the_true_motion_agrees_with_the_matches(room):
    reason, details = EpipolarCheck(EpipolarCheckConfig()).disagreement(keyframes_at(room, KEYFRAMES), room[0].camera)
    assert reason is None
    assert details["epipolar_pairs"] >= 3  # the pairs were measured, not skipped
    assert details["epipolar_disagreeing"] == 0


def test_a_wrong_motion_is_contradicted_with_the_reason(room):
    keyframes = keyframes_at(room, KEYFRAMES, wrong_poses(room))
    reason, details = EpipolarCheck(EpipolarCheckConfig()).disagreement(keyframes, room[0].camera)
    assert reason is not None and "contradict" in reason
    assert details["epipolar_disagreeing"] >= 2
    worst = details["epipolar_worst"]
    assert worst["rotation_deg"] > 3.0 or worst["direction_deg"] > 30.0


def test_views_too_close_to_tell_say_nothing(room):
    """Frames 0-2 see the room under well below a degree of parallax: no pair qualifies, whatever the poses."""
    keyframes = keyframes_at(room, [0, 1, 2], {i: np.eye(4) if i else room[0].ground_truth.poses[0] for i in (0, 1, 2)})
    reason, details = EpipolarCheck(EpipolarCheckConfig()).disagreement(keyframes, room[0].camera)
    assert reason is None and details["epipolar_pairs"] == 0
