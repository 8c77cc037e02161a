"""Two runs of a method on the same input give the same result files, byte for byte, timings aside (issue 17): the
trajectory, the keyframes, frames.csv, the maps, the events and metrics.json. The input has a drop in the middle,
so that the runs go through more than tracking (fdmo: a failed tracking, a recovery and a restart of the direct map;
direct: a failed tracking and a new map)."""

from __future__ import annotations

import json

import pytest

from app.pipeline import run_sequence
from app.sinks.files import DIRECT_MAP_FILE, EVENTS_FILE, FEATURE_MAP_FILE, FRAMES_FILE, KEYFRAMES_FILE, \
    METRICS_FILE, TRAJECTORY_FILE
from vo_core.config import load_config
from vo_core.synthetic import make_sequence
from vo_core.system import Odometry

SEQUENCE = make_sequence("smooth", 50, seed=0, width=320, height=240)
DROPS = [(20, 20)]  # frames 20..39: tracking fails, a recovery brings the camera back
# The events each method's runs must go through: the paths the comparison covers.
PATHS = {"fdmo": {"frames_dropped", "tracking_failed", "recovery_succeeded", "direct_restarted"},
         "direct": {"frames_dropped", "tracking_failed", "reinitialization"}}
SAME_BYTES = (TRAJECTORY_FILE, KEYFRAMES_FILE, FRAMES_FILE, DIRECT_MAP_FILE, FEATURE_MAP_FILE)


def without_timings(value):
    """``value`` (parsed JSON) without the milliseconds and seconds a stage took: keys "ms", "*_ms", "*_s", "fps"."""
    if isinstance(value, dict):
        return {key: without_timings(item) for key, item in value.items()
                if not (key in ("ms", "fps") or key.endswith(("_ms", "_s")))}
    if isinstance(value, list):
        return [without_timings(item) for item in value]
    return value


@pytest.mark.parametrize("method", sorted(PATHS))
def test_two_runs_give_the_same_files(method, tmp_path):
    for name in ("first", "second"):
        run_sequence(SEQUENCE, load_config(overrides=[f"method={method}"]), tmp_path / name, drops=DROPS)
    first, second = tmp_path / "first", tmp_path / "second"
    events = [[json.loads(line) for line in (folder / EVENTS_FILE).read_text().splitlines()] for folder in (first, second)]
    kinds = {event["kind"] for event in events[0]}
    assert PATHS[method] <= kinds, kinds
    assert without_timings(events[0]) == without_timings(events[1])
    for name in SAME_BYTES:  # a map file is written when the map is not empty: fdmo has both, direct one
        contents = [(folder / name).read_bytes() if (folder / name).is_file() else None for folder in (first, second)]
        assert contents[0] == contents[1] and (contents[0] is not None or name == FEATURE_MAP_FILE), name
    metrics = [without_timings(json.loads((folder / METRICS_FILE).read_text())) for folder in (first, second)]
    assert metrics[0] == metrics[1]


def test_the_feature_map_grown_beside_tracking_gives_the_synchronous_files(tmp_path, monkeypatch):
    """Synchronous mapping grows the feature map at a keyframe on the feature half's worker while the next frames are
    tracked; whatever reads the map waits for it first. The run's files are the ones of growing it in turn, the feature
    keyframes' events at the same frames (they reach the sinks a few frames later)."""
    config = load_config(overrides=["method=fdmo"])
    run_sequence(SEQUENCE, config, tmp_path / "beside", drops=DROPS)
    monkeypatch.setattr(Odometry, "_grows_beside", lambda self, initialization: False)
    run_sequence(SEQUENCE, config, tmp_path / "in_turn", drops=DROPS)
    beside, in_turn = tmp_path / "beside", tmp_path / "in_turn"
    events = [sorted(json.dumps(without_timings(json.loads(line)), sort_keys=True)
                     for line in (folder / EVENTS_FILE).read_text().splitlines()) for folder in (beside, in_turn)]
    assert any('"feature_keyframe_added"' in event for event in events[0])
    assert events[0] == events[1]
    for name in SAME_BYTES:
        assert (beside / name).read_bytes() == (in_turn / name).read_bytes(), name
