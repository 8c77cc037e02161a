"""The feature half in a process of its own (vo_core/features/feature_process.py): it answers as FeatureOdometry
here does, its errors are raised here, a closed or dead process says so instead of hanging, and one started ahead
of the odometry serves it."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from vo_core.features import feature_process
from vo_core.features.config import FeatureConfig
from vo_core.features.feature_odometry import FeatureOdometry
from vo_core.features.feature_process import FeatureProcess
from vo_core.synthetic import make_sequence

SEQUENCE = make_sequence("smooth", num_frames=13, seed=2, width=320, height=240)
KEYFRAMES = [SEQUENCE[i] for i in (0, 4, 8, 12)]


def grow(features) -> list[dict]:
    """Keyframes at the true poses, every one in the direct window; the reports as the events carry them."""
    reports = []
    window = {}
    for frame in KEYFRAMES:
        window[frame.index] = frame.T_world_cam
        depth = float(np.median(frame.depth[np.isfinite(frame.depth)]))
        report = features.add_keyframe(frame.index, frame.timestamp, frame.image, frame.T_world_cam, depth, window)
        reports.append({**report.as_details(), "ms": None})
    return reports


@pytest.fixture(scope="module")
def both():
    here, there = FeatureOdometry(FeatureConfig(), SEQUENCE.camera), FeatureProcess(FeatureConfig(), SEQUENCE.camera)
    reports = grow(here), grow(there)
    yield here, there, reports
    there.close()


def test_the_process_grows_the_same_feature_map(both):
    here, there, (reports_here, reports_there) = both
    assert reports_there == reports_here and sum(r["new_points"] for r in reports_here) > 100
    assert np.array_equal(there.points_world(), here.points_world())
    assert there.newest_keyframe == here.newest_keyframe == KEYFRAMES[-1].index and not there.empty
    poses_here, poses_there = here.keyframe_poses(), there.keyframe_poses()
    assert poses_there.keys() == poses_here.keys()
    assert all(np.array_equal(poses_there[k], poses_here[k]) for k in poses_here)


def test_the_process_recovers_as_this_one_does(both):
    here, there, _ = both
    frame = SEQUENCE[10]
    outcome_here = here.recover(frame.image, KEYFRAMES[-1].index)
    outcome_there = there.recover(frame.image, KEYFRAMES[-1].index)
    assert outcome_here.succeeded and outcome_there.succeeded
    assert np.array_equal(outcome_there.pose.T_world_cam, outcome_here.pose.T_world_cam)
    assert np.array_equal(there.point_positions(outcome_there.pose.point_ids),
                          here.point_positions(outcome_here.pose.point_ids))


def test_an_error_there_is_raised_here(both):
    here, there, _ = both
    with pytest.raises(Exception) as raised_here:
        here.point_positions(np.array([10**9]))
    with pytest.raises(type(raised_here.value), match=str(raised_here.value)):
        there.point_positions(np.array([10**9]))
    assert there.newest_keyframe == KEYFRAMES[-1].index  # it answers on


def test_only_the_feature_halfs_methods_are_offered(both):
    _, there, _ = both
    with pytest.raises(AttributeError, match="'map'"):
        there.map  # the map lives in the process alone


def test_a_closed_or_dead_process_says_so():
    closed = FeatureProcess(FeatureConfig(), SEQUENCE.camera)
    assert closed.empty
    closed.close()
    closed.close()
    with pytest.raises(RuntimeError, match="closed before points_world"):
        closed.points_world()

    dead = FeatureProcess(FeatureConfig(), SEQUENCE.camera)
    dead._process.kill()
    with pytest.raises(RuntimeError, match="ended unexpectedly"):
        dead.points_world()
    dead.close()


@pytest.mark.parametrize("started_on", ["the main thread", "another thread"])
def test_ctrl_c_to_the_process_group_is_left_to_the_parent(started_on):
    """Ctrl-C in a terminal signals the whole group; the parent ends the run and then closes the process, which must
    still answer meanwhile, even when the signal came while it was starting (importing)."""
    if started_on == "the main thread":
        starting = FeatureProcess(FeatureConfig(), SEQUENCE.camera)
    else:
        started = []
        thread = threading.Thread(target=lambda: started.append(FeatureProcess(FeatureConfig(), SEQUENCE.camera)))
        thread.start()
        thread.join()
        starting = started[0]
    os.kill(starting._process.pid, signal.SIGINT)
    time.sleep(0.5)
    assert starting.empty
    os.kill(starting._process.pid, signal.SIGINT)
    assert starting.newest_keyframe is None
    starting.close()


def test_a_process_started_ahead_serves_the_next_feature_half_as_a_new_one_would(both):
    """``start_ahead`` (before the app's imports, or in a live run's warm-up): the next FeatureProcess takes that
    process, whose kernels were loaded on a made-up scene, and grows the same feature map as one started with it;
    the one after starts its own."""
    here, _, (reports_here, _) = both
    feature_process.start_ahead()
    feature_process.start_ahead()  # one waits at a time
    (ahead, _), = feature_process._ahead
    taken, fresh = FeatureProcess(FeatureConfig(), SEQUENCE.camera), FeatureProcess(FeatureConfig(), SEQUENCE.camera)
    try:
        assert taken._process is ahead and fresh._process is not ahead and not feature_process._ahead
        assert grow(taken) == reports_here
        assert np.array_equal(taken.points_world(), here.points_world())
    finally:
        taken.close()
        fresh.close()


def test_a_process_started_ahead_that_died_is_left_for_a_new_one():
    feature_process.start_ahead()
    (ahead, _), = feature_process._ahead
    ahead.kill()
    ahead.join()
    features = FeatureProcess(FeatureConfig(), SEQUENCE.camera)
    try:
        assert features._process is not ahead and features.empty
    finally:
        features.close()


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="the platform has no idle scheduling class")
@pytest.mark.parametrize("idle", [False, True])
def test_the_process_runs_at_the_priority_it_is_given(idle):
    """Offline runs put the feature half's process in the idle scheduling class, on top of its niceness (so that it
    takes a core only where tracking and the direct mapper leave one); live runs only make it nicer."""
    features = FeatureProcess(FeatureConfig(), SEQUENCE.camera, niceness=3, idle=idle)
    try:
        assert features.empty  # answered: the process has set its priority
        pid = features._process.pid
        assert os.getpriority(os.PRIO_PROCESS, pid) == min(os.getpriority(os.PRIO_PROCESS, 0) + 3, 19)
        assert (os.sched_getscheduler(pid) == os.SCHED_IDLE) == idle
    finally:
        features.close()


def test_a_keyframe_described_ahead_is_checked_from_that_description_when_its_image_comes_as_a_copy(monkeypatch):
    """Through the process's pipe every call brings its own copy of the image: the keyframe described beside the
    caller (describe_ahead) must still serve its check, not be described and checked again on the caller's wait."""
    features = FeatureOdometry(FeatureConfig(), SEQUENCE.camera)
    grow(features)
    described = []
    original = features._described_and_checked
    monkeypatch.setattr(features, "_described_and_checked", lambda *args: described.append(args[0]) or original(*args))
    frame = SEQUENCE[10]
    features.describe_ahead(frame.index, frame.timestamp, frame.image, frame.T_world_cam)
    check = features.check_keyframe(frame.index, frame.timestamp, frame.image.copy(), frame.T_world_cam, 1.0)
    assert described == [frame.index] and check is not None and check.inliers >= 30
    other = SEQUENCE[11]
    features.describe_ahead(frame.index, frame.timestamp, frame.image, frame.T_world_cam)
    features.check_keyframe(frame.index, frame.timestamp, other.image, frame.T_world_cam, 1.0)
    assert described == [frame.index] * 3  # another image: described again
    features.close()
