"""Mapping on its own thread (vo_core/mapping_thread.py): the same trajectory as synchronous mapping within a
tolerance, every mapped keyframe reported through the sinks from the tracking thread, a clean stop, errors that
reach the caller, and a mapper that falls behind catching up and saying so."""

from __future__ import annotations

import argparse
import os
import threading

import numpy as np
import pytest

from app.cli import _live_overrides
from test_fdmo_system import FAULT_START, SMOOTH, run
from vo_core.config import load_config
from vo_core.events import EventKind, FrameResult
from vo_core.mapping_thread import MappingThread
from vo_core.system import Odometry

THREADED = ["mapping.threaded=true"]
LIVE = ["mapping.wait_for_keyframes=false", "direct.tracker.rotation_hypotheses=false",
        "direct.start_check.epipolar.beside_mapping=true"]


class Recorder:
    """A sink that remembers what it heard and on which thread."""

    def __init__(self):
        self.events, self.frames, self.maps, self.threads, self.closed = [], [], [], set(), False

    def on_frame(self, frame, result):
        self.frames.append(result)
        self.threads.add(threading.get_ident())

    def on_event(self, event):
        self.events.append(event)
        self.threads.add(threading.get_ident())

    def on_map(self, snapshot):
        self.maps.append(snapshot)
        self.threads.add(threading.get_ident())

    def close(self):
        self.closed = True


@pytest.fixture(scope="module")
def synchronous():
    ate, results, odometry = run("fdmo", SMOOTH)
    odometry.close()
    return ate, results


def test_offline_threaded_mapping_gives_the_synchronous_keyframes_and_poses(synchronous):
    """Offline, no frame is tracked while a keyframe is mapped and every frame is traced: the maps are the
    synchronous ones, and so is every pose but a keyframe's own (it goes out before the window optimization)."""
    sync_ate, sync_results = synchronous
    ate, results, odometry = run("fdmo", SMOOTH, overrides=THREADED)
    odometry.close()
    assert sync_ate < 0.002 and abs(ate - sync_ate) < 0.1 * sync_ate
    assert [r.is_keyframe for r in results] == [r.is_keyframe for r in sync_results]
    for threaded, synchronous_result in zip(results, sync_results):
        if not threaded.is_keyframe and threaded.T_world_cam is not None:
            assert np.array_equal(threaded.T_world_cam, synchronous_result.T_world_cam), threaded.frame_index


def test_live_threaded_mapping_never_waits_for_keyframes_and_stays_accurate(synchronous, monkeypatch):
    """DSO's real-time mode: tracking goes on while a keyframe is mapped, and no keyframe is asked for while one is
    pending (a later frame becomes the next keyframe). How many keyframes that leaves depends on the machine's speed:
    about the synchronous run's number (13 on this sequence; 14 once a mapper that no longer waited for the start's
    witness kept up with every request), not more than a few above it."""
    asked_while_pending = []
    submit = MappingThread.submit

    def watched_submit(self, frame_index, timestamp, job, keyframe=False, **kwargs):
        if keyframe and self.keyframe_pending:
            asked_while_pending.append(frame_index)
        return submit(self, frame_index, timestamp, job, keyframe=keyframe, **kwargs)

    monkeypatch.setattr(MappingThread, "submit", watched_submit)
    sync_ate, sync_results = synchronous
    ate, results, odometry = run("fdmo", SMOOTH, overrides=[*THREADED, "mapping.wait_for_keyframes=false"])
    odometry.close()
    assert all(r.T_world_cam is not None for r in results[-40:])
    assert not asked_while_pending
    assert sum(r.is_keyframe for r in results) <= sum(r.is_keyframe for r in sync_results) + 2
    assert ate < 3 * sync_ate


def test_offline_the_next_frame_is_tracked_and_accepted_while_the_keyframe_is_mapped_on():
    """Offline, tracking waits for a keyframe's new reference, not for its marginalization and new candidates (DSO
    hands its tracker the reference right after the window optimization): the next frame is tracked and accepted
    meanwhile, and its tracing waits in the mapper's queue behind the keyframe."""
    from vo_core.config import load_config
    from vo_core.system import Odometry

    odometry = Odometry(load_config(overrides=["method=fdmo", *THREADED]), SMOOTH.camera)
    frames = iter(SMOOTH)
    for frame in frames:
        odometry.track(frame)
        if odometry.direct.initialized and not odometry.direct.on_probation:
            break
    held, release = threading.Event(), threading.Event()
    select, trace = odometry.direct.selector.select, odometry.direct._trace
    order = []

    def held_select(*args):
        held.set()
        release.wait(10.0)
        order.append("selected")
        return select(*args)

    def noted_trace(*args):
        order.append("traced")
        return trace(*args)

    odometry.direct.selector.select = held_select
    keyframe = next(frame for frame in frames if odometry.track(frame).is_keyframe)
    assert held.wait(5.0)
    odometry.direct._trace = noted_trace
    after = []
    tracking = threading.Thread(target=lambda: after.append(odometry.track(next(frames))))
    tracking.start()
    tracking.join(5.0)
    accepted_while_mapping = bool(after)
    release.set()
    tracking.join()
    odometry.close()
    assert accepted_while_mapping
    assert after[0].frame_index == keyframe.index + 1 and after[0].T_world_cam is not None
    assert order[:2] == ["selected", "traced"]  # the frame is traced after the keyframe is mapped whole


def test_keyframes_mapped_on_the_thread_reach_the_sinks_from_the_tracking_thread():
    from vo_core.config import load_config
    from vo_core.system import Odometry

    recorder = Recorder()
    odometry = Odometry(load_config(overrides=THREADED), SMOOTH.camera, [recorder])
    results = [odometry.track(frame) for frame in SMOOTH]
    assert odometry.mapper._thread.is_alive()
    odometry.close()
    assert not odometry.mapper._thread.is_alive() and recorder.closed
    assert recorder.threads == {threading.get_ident()}
    added = [e for e in recorder.events if e.kind is EventKind.KEYFRAME_ADDED]
    # Every keyframe asked for was mapped and reported (the initializer's first keyframe has no frame result).
    assert sorted(e.frame_index for e in added)[1:] == [r.frame_index for r in results if r.is_keyframe]
    # The last map the sinks got is the one after the last keyframe (snapshots that queued up are coalesced).
    assert max(recorder.maps[-1].keyframe_poses) == added[-1].frame_index
    assert {e.details["keyframe"] for e in recorder.events if e.kind is EventKind.FEATURE_KEYFRAME_ADDED} == {
        e.frame_index for e in added}


def test_threaded_mapping_switches_threads_more_often_while_it_runs():
    """Python's 5 ms switch interval made tracking wait for the mapper's Python each time it came back from a kernel;
    the run's own interval holds while it runs, and Python's comes back at its end."""
    import sys

    from vo_core.config import load_config
    from vo_core.system import Odometry

    before = sys.getswitchinterval()
    odometry = Odometry(load_config(overrides=[*THREADED, "mapping.switch_interval_s=0.0003"]), SMOOTH.camera)
    during = sys.getswitchinterval()
    odometry.close()
    assert during == pytest.approx(0.0003) and sys.getswitchinterval() == before


def test_stopping_mid_run_maps_what_was_queued_and_joins_the_thread():
    from vo_core.config import load_config
    from vo_core.system import Odometry

    recorder = Recorder()
    odometry = Odometry(load_config(overrides=THREADED), SMOOTH.camera, [recorder])
    for frame in list(SMOOTH)[:25]:
        last = odometry.track(frame)
    odometry.close()
    assert not odometry.mapper._thread.is_alive()
    assert recorder.closed and recorder.frames[-1] is last
    asked = [r.frame_index for r in recorder.frames if r.is_keyframe]
    mapped = [e.frame_index for e in recorder.events if e.kind is EventKind.KEYFRAME_ADDED]
    assert asked and set(asked) <= set(mapped)


def test_live_a_frame_after_missed_frames_is_checked_while_the_direct_mapper_works_on():
    """Live, the feature map checks the suspect frame after missed frames without waiting for the direct mapper
    (held back here at a keyframe): waiting made the next frame later still, and suspect in turn. The frame is then
    accepted as any other."""
    from vo_core.config import load_config
    from vo_core.system import Odometry

    odometry = Odometry(load_config(overrides=["method=fdmo", *THREADED, *LIVE]), SMOOTH.camera)
    frames = list(SMOOTH)
    for frame in frames[:FAULT_START]:
        odometry.track(frame)
    odometry.flush()
    held, release = threading.Event(), threading.Event()

    def held_back(result: FrameResult):
        held.set()
        release.wait(10.0)

    odometry.mapper.submit(FAULT_START - 1, frames[FAULT_START - 1].timestamp, held_back, keyframe=True)
    assert held.wait(5.0)
    after_gap = []
    tracking = threading.Thread(target=lambda: after_gap.append(odometry.track(frames[FAULT_START + 3])))
    tracking.start()
    tracking.join(5.0)
    checked_while_mapping = not tracking.is_alive()
    release.set()
    tracking.join()
    odometry.close()
    assert checked_while_mapping
    checked = [e for e in after_gap[0].events if e.kind is EventKind.TRACKING_CHECKED]
    assert checked and "frames were missed" in checked[0].details["reason"]
    assert after_gap[0].T_world_cam is not None


def test_live_the_start_grows_the_feature_map_on_its_thread():
    """Live, the start's two feature keyframes, with the initializer's tracks as their first points, are made on the
    feature mapping thread: the start frame does not wait for them, and they reach the sinks afterwards."""
    from vo_core.config import load_config
    from vo_core.system import Odometry

    recorder = Recorder()
    odometry = Odometry(load_config(overrides=["method=fdmo", *THREADED, *LIVE]), SMOOTH.camera, [recorder])
    for frame in SMOOTH:
        start = odometry.track(frame)
        if any(e.kind is EventKind.INITIALIZATION_SUCCEEDED for e in start.events):
            break
    assert not [e for e in start.events if e.kind is EventKind.FEATURE_KEYFRAME_ADDED]
    odometry.flush()
    odometry.close()
    added = {e.details["keyframe"]: e.details for e in recorder.events if e.kind is EventKind.FEATURE_KEYFRAME_ADDED}
    assert len(added) == 2 and min(added) < start.frame_index == max(added)
    assert added[start.frame_index]["tracked_points"] > 50


def test_an_error_in_the_mapper_is_raised_on_the_tracking_thread():
    mapper = MappingThread(max_queued_frames=3, name="test")

    def broken(result: FrameResult):
        raise ValueError("the window optimization broke")

    mapper.submit(7, 0.7, broken, keyframe=True)
    with pytest.raises(ValueError, match="the window optimization broke"):
        mapper.wait_idle()
    mapper.close()


def test_a_mapper_that_falls_behind_leaves_frames_untraced_and_says_how_many():
    mapper = MappingThread(max_queued_frames=1, name="test")
    release = threading.Event()
    mapped = []

    def slow_keyframe(result: FrameResult):
        release.wait(5.0)
        mapped.append(result.frame_index)

    def trace(result: FrameResult):
        mapped.append(result.frame_index)

    mapper.submit(0, 0.0, slow_keyframe, keyframe=True)
    assert mapper.keyframe_pending
    for index in range(1, 6):
        mapper.submit(index, index / 10, trace, may_skip=True)
    release.set()
    mapper.wait_idle()
    finished = mapper.take_finished()
    mapper.close()
    # After the keyframe, 5 traces wait: the first 3 are left out while more than one waits behind them.
    assert mapped == [0, 4, 5] and not mapper.keyframe_pending
    behind = [e for f in finished for e in f.result.events if e.kind is EventKind.MAPPING_BEHIND]
    assert [(e.frame_index, e.details["untraced_frames"]) for e in behind] == [(4, 3)]


@pytest.mark.parametrize("flags, expected", [
    ({}, ["mapping.threaded=false"]),
    ({"viser": True}, ["mapping.threaded=true"]),
    ({"realtime": True}, ["mapping.threaded=true", *LIVE]),
    ({"realtime": True, "mapping": "sync"}, ["mapping.threaded=false", *LIVE]),
    ({"mapping": "threaded"}, ["mapping.threaded=true"]),
])
def test_the_mapping_mode_of_a_run(flags, expected):
    args = argparse.Namespace(**{"mapping": None, "realtime": False, "viser": False, **flags})
    assert _live_overrides(args) == expected


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="the platform has no idle scheduling class")
@pytest.mark.parametrize("live", [False, True])
def test_the_feature_process_is_idle_offline_and_only_nicer_live(live):
    config = load_config(None, ["method=fdmo", *THREADED, *(LIVE if live else [])])
    odometry = Odometry(config, SMOOTH.camera)
    try:
        assert odometry.features.empty  # answered: the process has set its priority
        pid = odometry.features._process.pid
        niceness = config.mapping.live_feature_niceness if live else config.mapping.feature_niceness
        assert os.getpriority(os.PRIO_PROCESS, pid) == min(os.getpriority(os.PRIO_PROCESS, 0) + niceness, 19)
        assert (os.sched_getscheduler(pid) == os.SCHED_IDLE) == (not live)
    finally:
        odometry.close()
