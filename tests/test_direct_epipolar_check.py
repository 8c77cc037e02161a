"""The start check's independent witness (vo_core/init/epipolar_check.py): the ORB matches between a start's
keyframes agree with their true motion, contradict a wrong one with the reason, refuse a wrong rotation and a
reversed translation where the views are too close for the essential matrix's own motion, and say nothing where
they share too few matches. The start stays on probation until the witness answers: beside mapping (live input) when it is
done, offline at the next window optimization."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from vo_core.direct.config import EpipolarCheckConfig, StartCheckConfig
from vo_core.direct.start_check import StartCheck
from vo_core.direct.window import WindowReport
from vo_core.geometry.lie import se3, so3_exp
from vo_core.init.epipolar_check import EpipolarCheck
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


def moved(room, indices, degrees: float = 0.0, sign: float = 1.0):
    """The true poses of ``indices``, each one's motion from the first turned by ``degrees`` about the vertical and
    its translation times ``sign``."""
    truth = room[0].ground_truth.poses
    first = truth[indices[0]]
    turn = so3_exp(np.radians(degrees) * np.array([0.0, 1.0, 0.0]))
    poses = {indices[0]: first}
    for index in indices[1:]:
        T_first_other = np.linalg.inv(first) @ truth[index]
        poses[index] = first @ se3(turn @ T_first_other[:3, :3], sign * T_first_other[:3, 3])
    return poses


CLOSE = [0, 1, 2]  # the room under well below a degree of parallax: no pair qualifies for the essential motion


@pytest.mark.parametrize("degrees, refused", [(0.0, False), (6.0, True)])
def test_views_too_close_for_the_essential_motion_still_refuse_a_wrong_rotation(room, degrees, refused):
    """The essential matrix's own motion is noise here (no pair qualifies), but the direct motion, taken as the
    hypothesis, must explain the matches: a rotation 6 degrees off moves them off their epipolar lines (the drone
    clip's wrong start at half its frame rate: 20-40 degrees off on pairs under 0.25 degrees of parallax)."""
    keyframes = keyframes_at(room, CLOSE, moved(room, CLOSE, degrees))
    reason, details = EpipolarCheck(EpipolarCheckConfig()).disagreement(keyframes, room[0].camera)
    assert details["epipolar_pairs"] == 0
    assert (reason is not None) == refused
    if refused:
        assert "explains under 50%" in reason and details["epipolar_least_explained"]["explained"] < 0.5


def test_a_reversed_translation_leaves_the_matches_unexplained(room):
    """The epipolar lines do not see the translation's sign: a mirrored start, its camera moving backward, is
    explained only where the matches' rays meet in front of both cameras, which they do not."""
    keyframes = keyframes_at(room, KEYFRAMES, moved(room, KEYFRAMES, sign=-1.0))
    reason, details = EpipolarCheck(EpipolarCheckConfig()).disagreement(keyframes, room[0].camera)
    assert reason is not None
    assert details["epipolar_unexplained"] == len(KEYFRAMES) - 1


def test_views_that_share_too_few_matches_say_nothing(room):
    keyframes = keyframes_at(room, KEYFRAMES[:3], wrong_poses(room))
    for keyframe in keyframes[1:]:
        keyframe.image = np.zeros_like(keyframe.image)  # nothing to match
    reason, details = EpipolarCheck(EpipolarCheckConfig()).disagreement(keyframes, room[0].camera)
    assert reason is None and details["epipolar_pairs"] == 0 and details["epipolar_unexplained"] == 0


# passes the direct measures
REPORT = WindowReport(6, 2.0, 1.0, 0.0, 0.0, 100, 1000, 10, 1152.0, np.ones(100, bool), 1.0)


def probation_keyframes(room, poses):
    return [SimpleNamespace(**vars(k), active_idepth=np.ones(10), camera=room[0].camera)
            for k in keyframes_at(room, KEYFRAMES, poses)]


def probation_with_witness(room, poses, beside_mapping=True):
    """A start check taken through its window optimizations (all passing the direct measures) with the room's
    keyframes at ``poses``; returns the check after the last one, its witness started."""
    config = StartCheckConfig(epipolar=EpipolarCheckConfig(beside_mapping=beside_mapping))
    check = StartCheck(config, KEYFRAMES[0], KEYFRAMES[1], "features", epipolar=EpipolarCheck(config.epipolar))
    keyframes = probation_keyframes(room, poses)
    for _ in range(config.window_optimizations + 1):  # the hand-over's own, then the probation's
        assert check.observe(REPORT, keyframes) is None
    return check


def test_a_witness_beside_mapping_keeps_the_start_on_probation_until_it_refuses_it(room):
    check = probation_with_witness(room, wrong_poses(room))
    assert check.witness is not None
    check.witness.result(timeout=60)
    reason = check.witness_failure()
    assert reason is not None and "contradict" in reason
    assert not check.passed  # a refused start never passes
    assert check.details()["epipolar_disagreeing"] >= 2  # its measures join the event's


def test_a_witness_beside_mapping_that_agrees_lets_the_start_pass_once_it_answered(room, monkeypatch):
    answer = threading.Event()
    disagreement = EpipolarCheck.disagreement

    def held_back(self, keyframes, camera):
        answer.wait(timeout=60)
        return disagreement(self, keyframes, camera)

    monkeypatch.setattr(EpipolarCheck, "disagreement", held_back)
    check = probation_with_witness(room, None)
    assert not check.passed and check.witness_failure() is None  # still on probation, not refused
    answer.set()
    check.witness.result(timeout=60)
    assert check.witness_failure() is None and check.passed


@pytest.mark.parametrize("refused", [True, False])
def test_an_offline_witness_answers_at_the_next_optimization_however_soon_it_is_done(room, refused):
    """Offline the witness's verdict falls at the window optimization after the start's last one, not when its thread
    gets done: the same run at any speed. Its work runs beside the frames in between."""
    poses = wrong_poses(room) if refused else None
    check = probation_with_witness(room, poses, beside_mapping=False)
    check.witness.result(timeout=60)
    assert check.witness_failure() is None and not check.passed  # done, but not due yet
    reason = check.observe(REPORT, probation_keyframes(room, poses))
    if refused:
        assert reason is not None and "contradict" in reason and not check.passed
    else:
        assert reason is None and check.passed


def test_a_closed_check_drops_the_pairs_it_has_not_started(room, monkeypatch):
    """A start discarded before its last optimization closes its check (DirectOdometry._end_start_check): the pairs
    ``prepare`` queued and no thread has started are cancelled, not measured for no one."""
    started = threading.Event()
    release = threading.Event()

    def slow_measure(self, anchor_features, other_image, camera):
        started.set()
        release.wait(10.0)

    monkeypatch.setattr(EpipolarCheck, "_measure_images", slow_measure)
    check = EpipolarCheck(EpipolarCheckConfig())
    keyframes = keyframes_at(room, KEYFRAMES)
    check.prepare(keyframes, room[0].camera)
    assert started.wait(10.0)
    check.close()
    release.set()
    pairs = [check._images[(KEYFRAMES[0], other)] for other in KEYFRAMES[1:]]
    cancelled = [pair.cancelled() for pair in pairs]
    assert any(cancelled)  # at most one pair per thread had started: the rest are dropped
    assert not cancelled[0]  # the first one queued was running
