"""The result files: valid at every moment of a run, and they parse back with the project's readers."""

from __future__ import annotations

import json

import numpy as np
import pytest
from ply_reader import read_ply

from app.sinks.files import (
    CONFIG_FILE,
    DIRECT_MAP_FILE,
    EVENTS_FILE,
    FEATURE_MAP_FILE,
    FRAMES_FILE,
    GROUND_TRUTH_FILE,
    KEYFRAMES_FILE,
    METRICS_FILE,
    TRAJECTORY_FILE,
    FilesSink,
)
from vo_core.config import load_config
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot
from vo_core.geometry.lie import se3_exp
from vo_core.trajectory import Trajectory, read_trajectory


def pose(i: int) -> np.ndarray:
    return se3_exp(np.array([0.1 * i, -0.02 * i, 0.05 * i, 0.01 * i, 0.03 * i, -0.02 * i]))


def result(i: int, tracked: bool = True, keyframe: bool = False) -> FrameResult:
    # Timestamps like TUM's: large values whose microseconds must survive the round trip.
    return FrameResult(i, 1305031102.175304 + i / 30.0, pose(i) if tracked else None, tracked, keyframe)


@pytest.fixture
def sink(tmp_path):
    files = FilesSink(tmp_path / "out")
    files.begin(load_config(overrides=["method=direct", "seed=7"]))
    yield files
    files.close()


def feed(sink: FilesSink, count: int = 8) -> None:
    for i in range(count):
        frame_result = result(i, tracked=i >= 2, keyframe=i in (2, 5))
        if i == 2:
            sink.on_event(Event(EventKind.INITIALIZATION_SUCCEEDED, i, frame_result.timestamp,
                                {"points": np.int64(812), "rmse": np.float32(1.5), "uv": np.zeros((2, 2)),
                                 "ratio": float("nan")}))
        sink.on_frame(None, frame_result)


def test_trajectory_is_complete_while_the_run_is_still_going(sink):
    feed(sink)
    # Not closed: this is what an interrupted run leaves behind.
    trajectory = read_trajectory(sink.out_dir / TRAJECTORY_FILE)
    expected = [result(i) for i in range(2, 8)]
    np.testing.assert_allclose(trajectory.timestamps, [r.timestamp for r in expected], rtol=0, atol=1e-6)
    np.testing.assert_allclose(trajectory.poses, [r.T_world_cam for r in expected], atol=1e-6)
    keyframes = read_trajectory(sink.out_dir / KEYFRAMES_FILE)
    np.testing.assert_allclose(keyframes.poses, [pose(2), pose(5)], atol=1e-6)


def test_events_are_one_strict_json_object_per_line(sink):
    feed(sink)
    lines = (sink.out_dir / EVENTS_FILE).read_text().splitlines()
    assert len(lines) == 1
    event = json.loads(lines[0])
    assert event == {"frame": 2, "timestamp": pytest.approx(result(2).timestamp), "kind": "initialization_succeeded",
                     "details": {"points": 812, "rmse": 1.5, "uv": [[0.0, 0.0], [0.0, 0.0]], "ratio": None}}


def test_final_keyframe_poses_replace_the_ones_at_insertion(sink):
    feed(sink)
    moved = {2: pose(2) @ se3_exp(np.full(6, 0.01)), 5: pose(5)}
    sink.write_keyframes(moved)
    sink.on_frame(None, result(8, keyframe=True))  # the file stays open for more keyframes
    keyframes = read_trajectory(sink.out_dir / KEYFRAMES_FILE)
    np.testing.assert_allclose(keyframes.poses, [moved[2], moved[5], pose(8)], atol=1e-6)


def hung(i: int, keyframe: int, T_ref_cam: np.ndarray) -> FrameResult:
    """Frame ``i`` tracked against ``keyframe`` (at pose(keyframe)) at ``T_ref_cam`` from it."""
    frame_result = FrameResult(i, result(i).timestamp, pose(keyframe) @ T_ref_cam, True, i == keyframe)
    frame_result.reference_keyframe, frame_result.T_ref_cam = keyframe, T_ref_cam
    return frame_result


STEP = se3_exp(np.array([0.05, 0.0, 0.01, 0.0, 0.02, 0.0]))
MOVED_KEYFRAME = pose(2) @ se3_exp(np.full(6, 0.03))


def final_trajectory(out_dir, replayed: bool) -> Trajectory:
    """Frames 2-6 (2 a keyframe, 3 and 4 tracked against it, 5 posed by the feature map, 6 against a keyframe the
    run no longer knows; frame 3 played again where ``replayed``), then a window optimization's move of keyframe 2."""
    files = FilesSink(out_dir)
    files.begin(load_config())
    for frame_result in (hung(2, 2, np.eye(4)), hung(3, 2, STEP), hung(4, 2, STEP @ STEP), result(5),
                         hung(6, 9, STEP), *([hung(3, 2, STEP)] if replayed else [])):
        files.on_frame(None, frame_result)
    files.write_final_poses({2: MOVED_KEYFRAME, 5: pose(5)})
    files.close()
    return read_trajectory(out_dir / TRAJECTORY_FILE)


def test_the_final_trajectory_hangs_each_frame_on_its_keyframes_final_pose_as_dsos_result(tmp_path):
    """Frames tracked against a keyframe a window optimization moved afterwards move with it (DSO's printResult);
    a pose that hangs on no direct keyframe (the feature map's), or on one the run no longer knows, stays as given."""
    final = final_trajectory(tmp_path, replayed=False)
    np.testing.assert_allclose(final.poses, [MOVED_KEYFRAME, MOVED_KEYFRAME @ STEP, MOVED_KEYFRAME @ STEP @ STEP,
                                             pose(5), pose(9) @ STEP], atol=1e-6)


def test_a_run_that_played_frames_again_keeps_its_poses_as_given(tmp_path):
    """Keyframes are known by frame number, and a frame played twice may have been a keyframe twice."""
    as_given = final_trajectory(tmp_path, replayed=True)
    np.testing.assert_allclose(as_given.poses, [pose(2), pose(2) @ STEP, pose(2) @ STEP @ STEP, pose(5),
                                                pose(9) @ STEP], atol=1e-6)


def test_metrics_and_config_parse_back(sink):
    sink.write_metrics({"frames": np.int64(8), "fps": np.float64(12.5), "evaluation": None})
    assert json.loads((sink.out_dir / METRICS_FILE).read_text()) == {"frames": 8, "fps": 12.5, "evaluation": None}
    assert not list(sink.out_dir.glob("*.partial"))
    config = load_config(sink.out_dir / CONFIG_FILE)
    assert (config.method, config.seed) == ("direct", 7)


def test_a_new_pass_starts_the_files_afresh(sink):
    feed(sink)
    sink.begin(load_config())
    sink.on_frame(None, result(3))
    assert len(read_trajectory(sink.out_dir / TRAJECTORY_FILE)) == 1
    assert (sink.out_dir / EVENTS_FILE).read_text() == ""


def test_frames_csv_has_a_line_per_frame_with_the_tracking_residuals(sink):
    sink.on_frame(None, FrameResult(0, 10.0, None, False))
    sink.on_frame(None, FrameResult(1, 10.5, pose(1), True, True, rmse_before=12.5, rmse_after=7.25,
                                    num_inliers=812, divergence_threshold=1.1))
    table = np.genfromtxt(sink.out_dir / FRAMES_FILE, delimiter=",", names=True)
    assert table.dtype.names == ("frame", "timestamp", "tracked", "is_keyframe", "rmse_before", "rmse_after",
                                 "num_inliers", "divergence_threshold")
    np.testing.assert_array_equal(table[1].tolist(), [1, 10.5, 1, 1, 12.5, 7.25, 812, 1.1])
    assert table[0].tolist()[:4] == (0, 10.0, 0, 0) and np.isnan(table[0].tolist()[4:]).all()  # empty: no value


def test_maps_round_trip_through_ply_and_an_empty_map_leaves_no_file(sink):
    rng = np.random.default_rng(0)
    direct, features = rng.normal(size=(30, 3)) * 5, rng.normal(size=(12, 3))
    features[3] = np.inf
    sink.write_maps(MapSnapshot(direct, rng.uniform(0.1, 3.0, 30), features))
    np.testing.assert_allclose(read_ply(sink.out_dir / DIRECT_MAP_FILE)[0], direct, rtol=1e-6)
    points, colors = read_ply(sink.out_dir / FEATURE_MAP_FILE)
    np.testing.assert_allclose(points, np.delete(features, 3, axis=0), rtol=1e-6)
    assert len(np.unique(colors, axis=0)) == 1
    sink.write_maps(MapSnapshot(direct_points_world=np.zeros((0, 3)), direct_inverse_depths=np.zeros(0)))
    assert not (sink.out_dir / DIRECT_MAP_FILE).exists() and not (sink.out_dir / FEATURE_MAP_FILE).exists()


def test_ground_truth_file_is_written_when_there_is_one(sink):
    truth = Trajectory(1305031102.175304 + np.arange(5) / 30.0, [pose(i) for i in range(5)])
    sink.write_ground_truth(truth)
    written = read_trajectory(sink.out_dir / GROUND_TRUTH_FILE)
    np.testing.assert_allclose(written.timestamps, truth.timestamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(written.poses, truth.poses, atol=1e-6)
    sink.write_ground_truth(None)
    assert not (sink.out_dir / GROUND_TRUTH_FILE).exists()


def test_frames_played_again_keep_one_line_per_timestamp_their_latest_outcome(sink):
    """A backward jump: frames 3-5 are processed again; frame 4 gets another pose, frame 5 none this time."""
    feed(sink)  # frames 0-7, posed from 2
    moved = pose(4) @ se3_exp(np.full(6, 0.02))
    for i, T in ((3, pose(3)), (4, moved), (5, None)):
        sink.on_frame(None, FrameResult(i, result(i).timestamp, T, T is not None))
    trajectory = read_trajectory(sink.out_dir / TRAJECTORY_FILE)  # strictly increasing timestamps, or it raises
    expected = {2: pose(2), 3: pose(3), 4: moved, 6: pose(6), 7: pose(7)}
    np.testing.assert_allclose(trajectory.timestamps, [result(i).timestamp for i in expected], rtol=0, atol=1e-6)
    np.testing.assert_allclose(trajectory.poses, list(expected.values()), atol=1e-6)
    np.testing.assert_allclose(sink.estimate().poses, trajectory.poses, atol=1e-6)
    sink.on_frame(None, result(8))  # playing on past the latest frame appends again
    assert len(read_trajectory(sink.out_dir / TRAJECTORY_FILE)) == 6
    frames = np.genfromtxt(sink.out_dir / FRAMES_FILE, delimiter=",", names=True)
    assert frames["frame"].tolist() == [*range(8), 3, 4, 5, 8]  # a line per processing, in processing order


def test_poses_retracted_by_a_rejected_start_leave_the_trajectory(sink):
    """A start found wrong after the hand-over takes back the poses its map gave (INITIALIZATION_REJECTED's
    ``retracted``): trajectory.tum must not mix that map with the next one, keyframes.tum loses its keyframe,
    frames.csv says those frames untracked, and the files go on growing after the rewrite."""
    feed(sink)
    retracted = [result(i).timestamp for i in (2, 3, 4)]
    sink.on_event(Event(EventKind.INITIALIZATION_REJECTED, 5, result(5).timestamp,
                        {"reason": "test", "retracted": retracted}))
    kept = read_trajectory(sink.out_dir / TRAJECTORY_FILE)
    assert len(kept) == 3
    assert not np.isin(np.array(retracted), kept.timestamps).any()
    assert sink.estimate().timestamps.tolist() == kept.timestamps.tolist()
    sink.on_frame(None, result(8))
    frames = np.genfromtxt(sink.out_dir / FRAMES_FILE, delimiter=",", names=True)
    assert frames["frame"].tolist() == list(range(9))
    assert frames["tracked"].tolist() == [0, 0, 0, 0, 0, 1, 1, 1, 1]
    assert frames["is_keyframe"].tolist() == [0, 0, 0, 0, 0, 1, 0, 0, 0]
    sink.write_keyframes({2: pose(2), 5: pose(5)})  # the odometry's every keyframe ever, the retracted one too
    assert read_trajectory(sink.out_dir / KEYFRAMES_FILE).timestamps.tolist() == pytest.approx([result(5).timestamp])


def test_the_run_statistics_do_not_count_retracted_poses_as_tracked():
    from app.pipeline import _Statistics

    statistics = _Statistics()
    for i in range(6):
        statistics.on_frame(None, result(i, tracked=i >= 1))
    statistics.on_event(Event(EventKind.INITIALIZATION_REJECTED, 5, result(5).timestamp,
                              {"reason": "test", "retracted": [result(i).timestamp for i in (1, 2, 3)]}))
    counts = statistics.counts()
    assert counts["tracked_frames"] == 2 and counts["tracked_fraction"] == pytest.approx(2 / 6)


def started(sink: FilesSink, first: int = 0, succeeded_at: int = 3) -> None:
    """Frames ``first``..``succeeded_at``-1 untracked, then a start that succeeds at ``succeeded_at`` and poses
    ``first`` as its first keyframe (as the direct initializer reports it)."""
    for i in range(first, succeeded_at):
        sink.on_frame(None, result(i, tracked=False))
    sink.on_event(Event(EventKind.INITIALIZATION_SUCCEEDED, succeeded_at, result(succeeded_at).timestamp,
                        {"first_frame": first, "first_T_world_cam": pose(first).tolist()}))
    sink.on_frame(None, result(succeeded_at, keyframe=True))


def test_the_first_keyframe_of_a_start_is_tracked_in_every_file_once_the_start_succeeds(sink):
    """Issue 47: frame 0 was in keyframes.tum but untracked in frames.csv and absent from trajectory.tum."""
    started(sink)
    frames = np.genfromtxt(sink.out_dir / FRAMES_FILE, delimiter=",", names=True)
    assert frames["tracked"].tolist() == [1, 0, 0, 1] and frames["is_keyframe"].tolist() == [1, 0, 0, 1]
    for name in (TRAJECTORY_FILE, KEYFRAMES_FILE):
        written = read_trajectory(sink.out_dir / name)
        assert written.timestamps.tolist() == pytest.approx([result(0).timestamp, result(3).timestamp])
        assert np.allclose(written.poses[0], pose(0), atol=1e-6)
    assert sink.estimate().timestamps.tolist() == pytest.approx([result(0).timestamp, result(3).timestamp])


def test_a_rejected_start_takes_back_its_first_keyframe_too(sink):
    started(sink)
    sink.on_event(Event(EventKind.INITIALIZATION_REJECTED, 4, result(4).timestamp,
                        {"reason": "test", "first_frame": 0, "retracted": [result(3).timestamp]}))
    frames = np.genfromtxt(sink.out_dir / FRAMES_FILE, delimiter=",", names=True)
    assert frames["tracked"].tolist() == [0, 0, 0, 0] and frames["is_keyframe"].tolist() == [0, 0, 0, 0]
    for name in (TRAJECTORY_FILE, KEYFRAMES_FILE):
        assert (sink.out_dir / name).read_text().splitlines()[1:] == []  # the header alone


def test_the_run_statistics_count_the_first_keyframe_as_tracked_until_its_start_is_rejected():
    from app.pipeline import _Statistics

    statistics = _Statistics()
    for i in range(3):
        statistics.on_frame(None, result(i, tracked=False))
    statistics.on_event(Event(EventKind.INITIALIZATION_SUCCEEDED, 3, result(3).timestamp,
                              {"first_frame": 0, "first_T_world_cam": pose(0).tolist()}))
    statistics.on_frame(None, result(3))
    assert statistics.counts()["tracked_frames"] == 2
    statistics.on_event(Event(EventKind.INITIALIZATION_REJECTED, 4, result(4).timestamp,
                              {"reason": "test", "first_frame": 0, "retracted": [result(3).timestamp]}))
    assert statistics.counts()["tracked_frames"] == 0


@pytest.mark.parametrize("method", ["fdmo", "klt"])
def test_every_file_of_the_bundled_run_agrees_on_the_keyframes(tmp_path, method):
    """Every keyframe of keyframes.tum is in trajectory.tum and tracked and a keyframe in frames.csv, and the
    summary counts as many keyframes as keyframes.tum has lines."""
    from app.cli import main

    out = tmp_path / "run"
    assert main(["run", "--out", str(out), "--no-rrd", "--quiet", "--method", method]) == 0
    keyframes = read_trajectory(out / KEYFRAMES_FILE).timestamps
    trajectory = read_trajectory(out / TRAJECTORY_FILE).timestamps
    frames = np.genfromtxt(out / FRAMES_FILE, delimiter=",", names=True)
    metrics = json.loads((out / METRICS_FILE).read_text())
    assert len(keyframes) > 2 and np.isin(keyframes, trajectory).all()
    at_keyframes = np.isin(np.round(frames["timestamp"], 6), np.round(keyframes, 6))
    assert at_keyframes.sum() == len(keyframes)
    assert (frames["tracked"][at_keyframes] == 1).all() and (frames["is_keyframe"][at_keyframes] == 1).all()
    assert metrics["keyframes"] == len(keyframes)
    assert metrics["tracked_frames"] == frames["tracked"].sum() == len(trajectory) == metrics["posed_frames"]
