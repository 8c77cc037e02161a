"""The result files: valid at every moment of a run, and they parse back with the project's readers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.sinks.files import CONFIG_FILE, EVENTS_FILE, KEYFRAMES_FILE, METRICS_FILE, TRAJECTORY_FILE, FilesSink
from vo_core.config import load_config
from vo_core.events import Event, EventKind, FrameResult
from vo_core.geometry.lie import se3_exp
from vo_core.trajectory import read_trajectory


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
