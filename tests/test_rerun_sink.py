"""The Rerun sink: a short synthetic run with a divergence and a recovery into a .rrd, read back with
rerun.chunk.RrdReader."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from app.sinks import rerun_sink as sink_module  # noqa: E402
from app.sinks.recording_parts import recording_files  # noqa: E402
from app.sinks.rerun_sink import RerunSink  # noqa: E402
from app.sinks.scene import PLOT_LANES  # noqa: E402
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot  # noqa: E402
from vo_core.geometry.camera import PinholeCamera  # noqa: E402
from vo_core.geometry.lie import sim3, so3_exp, transform_points  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402

CAMERA = PinholeCamera(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5)
FRAMES = 12
LOST_FRAME = 5  # no pose: tracking failed there
KEYFRAMES = (0, 4, 8)
RECOVERY_FRAME = 7  # a divergence, then a recovery from the feature map: its matches, outliers among them
RECOVERY_INLIERS = np.array([True, True, False, True, False, True, True])
FEATURE_KEYFRAME = 8  # the feature map grows: its new matches (all inliers)
NEW_MATCHES = 5
THRESHOLD = 1.1  # the divergence test's 1 + epsilon
PERIOD_S = 0.05
# The ground truth is the estimate under this similarity: once aligned it must fall back onto the estimate.
S_GT_EST = sim3(2.5, so3_exp(np.array([0.1, -0.3, 0.2])), np.array([1.0, -2.0, 0.5]))


def camera_pose(index: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, 0.05 * index, 0.0]))
    T[:3, 3] = [0.1 * index, 0.02 * index**1.5, 0.05 * np.sin(index)]
    return T


def ground_truth() -> Trajectory:
    timestamps = np.arange(FRAMES) * PERIOD_S
    poses = np.array([camera_pose(i) for i in range(FRAMES)])
    poses[:, :3, 3] = transform_points(S_GT_EST, poses[:, :3, 3])
    return Trajectory(timestamps, poses)


def synthetic_image(index: int) -> np.ndarray:
    image = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
    cv2.circle(image, (40 + 5 * index, 60), 20, 255, -1)
    return image


def divergence_ratio(index: int) -> float:
    return 1.6 if index == RECOVERY_FRAME else 0.75


def frame_events(i: int, timestamp: float) -> list[Event]:
    events = [Event(EventKind.KEYFRAME_ADDED, i, timestamp)] if i in KEYFRAMES else []
    if i == 0:
        events.append(Event(EventKind.INITIALIZATION_SUCCEEDED, i, timestamp, {"points": 120}))
    if i == LOST_FRAME:
        events.append(Event(EventKind.TRACKING_FAILED, i, timestamp, {"reason": "too few points"}))
    if i == RECOVERY_FRAME:
        events += [Event(kind, i, timestamp) for kind in (EventKind.DIVERGENCE_DETECTED, EventKind.RECOVERY_TRIED,
                                                          EventKind.RECOVERY_SUCCEEDED)]
    if i == FEATURE_KEYFRAME:
        events.append(Event(EventKind.FEATURE_KEYFRAME_ADDED, i, timestamp))
    return events


def frame_matches(i: int, rng) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(matches, inlier flags): a recovery's with outliers, a feature keyframe's new ones (all inliers), else none."""
    if i == RECOVERY_FRAME:
        return rng.uniform(0, 100, (len(RECOVERY_INLIERS), 4)), RECOVERY_INLIERS
    if i == FEATURE_KEYFRAME:
        return rng.uniform(0, 100, (NEW_MATCHES, 4)), None
    return None, None


def run_synthetic(sink: RerunSink) -> None:
    rng = np.random.default_rng(3)
    for i in range(FRAMES):
        timestamp = i * PERIOD_S
        lost = i == LOST_FRAME
        events = frame_events(i, timestamp)
        for event in events:
            sink.on_event(event)
        matches, inlier = frame_matches(i, rng)
        result = FrameResult(
            i, timestamp, None if lost else camera_pose(i), tracked=not lost, is_keyframe=i in KEYFRAMES,
            rmse_before=None if lost else 8.0, rmse_after=None if lost else 8.0 * divergence_ratio(i),
            num_inliers=40 + i, points_2d=rng.uniform(0, 100, (30, 2)), matches_2d=matches, matches_inlier=inlier,
            divergence_ratio=None if lost else divergence_ratio(i), divergence_threshold=THRESHOLD,
            timings_ms={"track": 1.5, "total": 2.0}, events=events,
        )
        sink.on_frame(SimpleNamespace(index=i, timestamp=timestamp, image=synthetic_image(i)), result)
        if result.is_keyframe:
            sink.on_map(MapSnapshot(
                direct_points_world=rng.normal(size=(50, 3)), direct_inverse_depths=rng.uniform(0.2, 2.0, 50),
                feature_points_world=rng.normal(size=(20, 3)),
                keyframe_poses={k: camera_pose(k) for k in KEYFRAMES if k <= i},
            ))
    sink.on_event(Event(EventKind.FRAMES_DROPPED, FRAMES, FRAMES * PERIOD_S, {"count": 3}))
    sink.close()


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> dict[str, list]:
    """The chunks of the recording, grouped by entity path."""
    path = tmp_path_factory.mktemp("rerun") / "run.rrd"
    run_synthetic(RerunSink(str(path), CAMERA, ground_truth=ground_truth()))
    chunks: dict[str, list] = {}
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        chunks.setdefault(chunk.entity_path, []).append(chunk)
    return chunks


def column(chunks: list, name: str) -> list:
    """One column of an entity's temporal chunks, rows in frame order."""
    rows = []
    for chunk in chunks:
        table = chunk.to_record_batch().to_pydict()
        if name in table and "frame" in table:
            rows += sorted(zip(table["frame"], table[name]), key=lambda row: row[0])
    return [value for _, value in sorted(rows, key=lambda row: row[0])]


def test_entities_are_the_documented_ones(recording):
    expected = {sink_module.CAMERA, sink_module.IMAGE, sink_module.TRACKED_PIXELS, sink_module.MATCHES,
                sink_module.ESTIMATE, sink_module.RECENT, sink_module.GROUND_TRUTH, sink_module.DIRECT_POINTS,
                sink_module.FEATURE_POINTS, sink_module.EVENT_LOG, sink_module.DIVERGENCE_RATIO,
                sink_module.DIVERGENCE_THRESHOLD, "world/keyframes/4", "world/events/recovery_succeeded",
                "plots/divergence/events/divergence", "plots/tracking/rmse_after", "plots/counts/inliers",
                "plots/timing_ms/track"}
    assert {"/" + entity for entity in expected} <= set(recording)


def test_camera_pose_is_logged_for_each_posed_frame_on_the_frame_timeline(recording):
    posed = [i for i in range(FRAMES) if i != LOST_FRAME]
    assert column(recording["/world/camera"], "frame") == posed
    translations = column(recording["/world/camera"], "Transform3D:translation")
    np.testing.assert_allclose(np.array(translations).reshape(-1, 3), [camera_pose(i)[:3, 3] for i in posed],
                               atol=1e-6)
    times = column(recording["/world/camera"], "time")
    np.testing.assert_allclose([t.total_seconds() for t in times], np.array(posed) * PERIOD_S, atol=1e-6)


def test_images_are_jpeg_on_every_frame(recording):
    media_types = column(recording["/world/camera/image"], "EncodedImage:media_type")
    assert [m for m in media_types if m is not None] == [["image/jpeg"]] * FRAMES
    blob = bytes(column(recording["/world/camera/image"], "EncodedImage:blob")[-1][0])
    decoded = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decoded.shape == (CAMERA.height, CAMERA.width)
    assert np.abs(decoded.astype(int) - synthetic_image(FRAMES - 1)).mean() < 3.0


def test_pinhole_frustum_holds_the_intrinsics(recording):
    intrinsics = column(recording["/world/camera/image"], "Pinhole:image_from_camera")
    intrinsics = [matrix for matrix in intrinsics if matrix is not None]
    assert intrinsics  # logged with the first pose, again only when the scene's size changes a lot
    # Rerun stores the 3x3 matrix column-major.
    np.testing.assert_allclose(np.reshape(intrinsics[0], (3, 3)).T, CAMERA.K, atol=1e-4)


def test_events_are_logged_with_levels(recording):
    texts = column(recording["/events"], "TextLog:text")
    levels = column(recording["/events"], "TextLog:level")
    lines = dict(zip((text[0] for text in texts), (level[0] for level in levels)))
    assert lines["frame 0 initialization_succeeded (points=120)"] == "INFO"
    assert lines["frame 5 tracking_failed (reason=too few points)"] == "ERROR"
    assert lines["frame 12 frames_dropped (count=3)"] == "INFO"
    assert sum(text[0].endswith(" keyframe_added") for text in texts) == len(KEYFRAMES)


def test_event_markers_sit_on_the_trajectory_one_entity_per_kind(recording):
    marked = {path.removeprefix("/world/events/") for path in recording if path.startswith("/world/events/")}
    # Keyframes are routine: not marked.
    assert marked == {"initialization_succeeded", "tracking_failed", "divergence_detected", "recovery_tried",
                      "recovery_succeeded", "frames_dropped"}
    # The failure at the lost frame is marked where the camera last was, the divergence where the recovery put the
    # camera; the recovery's attempt and success above it (y points down), in the order they came.
    failure = column(recording["/world/events/tracking_failed"], "Points3D:positions")[-1]
    np.testing.assert_allclose(failure, [camera_pose(LOST_FRAME - 1)[:3, 3]], atol=1e-6)
    stack = [column(recording[f"/world/events/{kind}"], "Points3D:positions")[-1][0]
             for kind in ("divergence_detected", "recovery_tried", "recovery_succeeded")]
    np.testing.assert_allclose(stack[0], camera_pose(RECOVERY_FRAME)[:3, 3], atol=1e-6)
    lifts = np.subtract(stack, stack[0])
    np.testing.assert_allclose(lifts[:, [0, 2]], 0.0, atol=1e-6)
    assert 0.0 > lifts[1, 1] > lifts[2, 1]
    colors = {kind: column(recording[f"/world/events/{kind}"], "Points3D:colors")[-1][0] for kind in marked}
    assert len(set(colors.values())) == len(marked)  # each kind its own color


def test_divergence_ratio_is_plotted_against_its_threshold_with_the_events_on_it(recording):
    ratios = column(recording["/plots/divergence/ratio"], "Scalars:scalars")
    posed = [i for i in range(FRAMES) if i != LOST_FRAME]
    np.testing.assert_allclose(np.ravel(ratios), [divergence_ratio(i) for i in posed])
    thresholds = column(recording["/plots/divergence/threshold"], "Scalars:scalars")
    np.testing.assert_allclose(np.ravel(thresholds), THRESHOLD)
    assert column(recording["/plots/divergence/threshold"], "frame") == list(range(FRAMES))
    # Divergences (the tracking failure among them) and recoveries are markers on the plot, in lanes of their own.
    lanes = {lane.name: lane for lane in PLOT_LANES}
    assert column(recording["/plots/divergence/events/divergence"], "frame") == [LOST_FRAME, RECOVERY_FRAME]
    assert column(recording["/plots/divergence/events/recovery"], "frame") == [RECOVERY_FRAME]
    np.testing.assert_allclose(np.ravel(column(recording["/plots/divergence/events/recovery"], "Scalars:scalars")),
                               lanes["recovery"].height)


def test_ground_truth_is_aligned_onto_the_estimate(recording):
    strip = np.array(column(recording["/world/trajectory/ground_truth"], "LineStrips3D:strips")[-1][0])
    posed = [i for i in range(FRAMES) if i != LOST_FRAME]
    np.testing.assert_allclose(strip, [camera_pose(i)[:3, 3] for i in posed], atol=1e-5)


def test_full_path_at_keyframes_and_scalars(recording):
    assert column(recording["/world/trajectory/estimate"], "frame")[: len(KEYFRAMES)] == list(KEYFRAMES)
    assert column(recording["/plots/counts/inliers"], "frame") == list(range(FRAMES))


def test_both_clouds_in_colors_of_their_own(recording):
    direct = column(recording["/world/map/direct_points"], "Points3D:colors")[-1]
    features = column(recording["/world/map/feature_points"], "Points3D:colors")[-1]
    assert len(column(recording["/world/map/direct_points"], "Points3D:positions")[-1]) == 50
    assert len(column(recording["/world/map/feature_points"], "Points3D:positions")[-1]) == 20
    assert len(set(direct)) > 5  # colored by inverse depth, not one color
    assert len(set(features)) == 1 and not set(features) & set(direct)


def test_each_keyframe_is_a_frustum(recording):
    for index in KEYFRAMES:
        chunks = recording[f"/world/keyframes/{index}"]
        translation = column(chunks, "Transform3D:translation")[-1]
        np.testing.assert_allclose(np.ravel(translation), camera_pose(index)[:3, 3], atol=1e-6)
        intrinsics = [matrix for matrix in column(chunks, "Pinhole:image_from_camera") if matrix is not None]
        np.testing.assert_allclose(np.reshape(intrinsics[-1], (3, 3)).T, CAMERA.K, atol=1e-4)
        assert column(chunks, "frame")[0] == index  # appears when it became a keyframe


def test_restart_is_a_new_recording_in_the_same_file(tmp_path):
    path = tmp_path / "run.rrd"
    sink = RerunSink(path, CAMERA, recording_name="bundled")
    for index in range(3):
        sink.on_frame(SimpleNamespace(image=None), FrameResult(index, index * PERIOD_S, camera_pose(index), True))
    first_id = sink.recording.get_recording_id()
    sink.restart()
    for index in range(2):
        sink.on_frame(SimpleNamespace(image=None), FrameResult(index, index * PERIOD_S, camera_pose(index), True))
    assert len(sink.history) == 2
    sink.close()
    recordings = rr.chunk.RrdReader(path).recordings()
    assert [entry.recording_id for entry in recordings] == [sink.recording.get_recording_id()] != [first_id]
    camera = [chunk for chunk in rr.chunk.RrdReader(path).stream().to_chunks() if chunk.entity_path == "/world/camera"]
    assert column(camera, "frame") == [0, 1]  # the new pass alone


def test_frames_played_again_go_on_along_the_step_timeline(tmp_path):
    """A backward jump: frames 3-4 come again; the frame timeline goes back, the step timeline does not."""
    path = tmp_path / "jump.rrd"
    sink = RerunSink(path, CAMERA)
    for index in (0, 1, 2, 3, 4, 3, 4):
        sink.on_frame(SimpleNamespace(image=None), FrameResult(index, index * PERIOD_S, camera_pose(index), True))
    sink.close()
    camera = [chunk for chunk in rr.chunk.RrdReader(path).stream().to_chunks() if chunk.entity_path == "/world/camera"]
    rows = sorted(zip(column(camera, "step"), column(camera, "frame")))
    assert rows == list(enumerate([0, 1, 2, 3, 4, 3, 4]))
    assert opening_timeline(path) == "step"  # the replay beside the first playing, not over it


def opening_timeline(path) -> str:
    """The timeline the recording's blueprint opens on: the last one sent (the file's blueprints come in no order)."""
    reader = rr.chunk.RrdReader(path)
    panels = [chunk.to_record_batch().to_pydict() for blueprint in reader.blueprints()
              for chunk in reader.stream(store=blueprint).to_chunks() if chunk.entity_path == "/time_panel"]
    return max((panel["log_time"][0], panel["TimePanelBlueprint:timeline"][0][0]) for panel in panels
               if "TimePanelBlueprint:timeline" in panel)[1]


def test_recording_carries_the_default_blueprint(tmp_path):
    path = tmp_path / "run.rrd"
    run_synthetic(RerunSink(str(path), CAMERA))
    blueprints = rr.chunk.RrdReader(path).blueprints()
    assert blueprints and all(entry.application_id == "fdmo" for entry in blueprints)
    views = {chunk.entity_path for chunk in rr.chunk.RrdReader(path).stream(store=blueprints[-1]).to_chunks()}
    assert any(path.startswith("/view/") for path in views)  # the views of default_blueprint
    assert opening_timeline(path) == "frame"  # no frame played twice


# ------------------------------------------------------------------------ the helpers both viewers share


def test_path_history_keeps_every_position_past_its_first_buffer():
    from app.sinks.scene import PathHistory

    path = PathHistory()
    for index in range(150):  # more than the first buffer holds
        path.add(0.1 * index, camera_pose(index))
    np.testing.assert_allclose(path.positions(), [camera_pose(i)[:3, 3] for i in range(150)])
    np.testing.assert_allclose(path.positions(start=148), [camera_pose(i)[:3, 3] for i in (148, 149)])
    assert len(path.trajectory()) == 150


def test_inverse_depth_colors_run_from_blue_far_to_red_near():
    from app.sinks.scene import inverse_depth_colors

    colors = inverse_depth_colors(np.linspace(0.1, 2.0, 50)).astype(int)
    assert colors.shape == (50, 3)
    far, near = colors[0], colors[-1]
    assert far[2] > far[0] and near[0] > near[2]


def test_event_text_leaves_long_details_to_the_events_file():
    from app.sinks.scene import event_text

    event = Event(EventKind.INITIALIZATION_SUCCEEDED, 7, 0.7,
                  {"points": 2000, "affine": [0.5, 8.25], "first_T_world_cam": np.eye(4).tolist(), "rmse": 1.23456})
    assert event_text(event) == "frame 7 initialization_succeeded (points=2000, affine=[0.5, 8.25], rmse=1.235)"


def test_every_event_kind_has_a_style_and_failures_stand_out():
    from app.sinks.scene import EVENT_STYLES

    assert set(EVENT_STYLES) == set(EventKind)
    assert {EVENT_STYLES[kind].level for kind in (EventKind.TRACKING_FAILED, EventKind.RECOVERY_FAILED)} == {"ERROR"}
    assert EVENT_STYLES[EventKind.DIVERGENCE_DETECTED].level == "WARN"


def matches_by_frame(recording) -> dict[int, tuple]:
    """Frame -> (strips, colors) of the matches entity; (None, None) where it was cleared."""
    rows = {}
    for chunk in recording["/world/camera/image/matches"]:
        table = chunk.to_record_batch().to_pydict()
        for index, frame in enumerate(table["frame"]):
            rows[frame] = tuple(table.get(name, [None] * (index + 1))[index]
                                for name in ("LineStrips2D:strips", "LineStrips2D:colors"))
    return rows


def test_matches_of_recoveries_and_feature_keyframes_inliers_and_outliers_apart(recording):
    from app.sinks.scene import MATCH_INLIER_COLOR, MATCH_OUTLIER_COLOR

    rows = matches_by_frame(recording)
    assert set(rows) == {RECOVERY_FRAME, FEATURE_KEYFRAME, FEATURE_KEYFRAME + 1}  # logged where there are some
    strips, colors = rows[RECOVERY_FRAME]
    assert len(strips) == len(RECOVERY_INLIERS) and all(len(strip) == 2 for strip in strips)
    rgba = [((color >> 24) & 255, (color >> 16) & 255, (color >> 8) & 255) for color in colors]
    assert rgba == [MATCH_INLIER_COLOR if inlier else MATCH_OUTLIER_COLOR for inlier in RECOVERY_INLIERS]
    strips, colors = rows[FEATURE_KEYFRAME]
    assert len(strips) == NEW_MATCHES and len(set(colors)) == 1
    assert rows[FEATURE_KEYFRAME + 1] == (None, None)  # cleared: the keyframe's lines do not linger


def test_the_default_view_holds_the_whole_path_and_the_dense_map_not_the_far_points():
    from app.sinks.scene import framing

    rng = np.random.default_rng(0)
    path = np.column_stack([np.linspace(-3.0, 3.0, 60), np.zeros(60), np.zeros(60)])
    dense = rng.normal([0.0, 0.0, 2.0], 0.5, size=(2000, 3))
    far = rng.normal([0.0, 0.0, 500.0], 50.0, size=(400, 3))  # one point in six, triangulated far away
    view = framing(path, np.vstack([dense, far]))
    assert view.size < 10.0  # the path is 6 long, the dense cloud 2 deep: not the 500 of the far points
    assert np.all(np.linalg.norm(path - view.centre, axis=1) <= view.size / 2)  # the whole path in view
    assert np.mean(np.linalg.norm(dense - view.centre, axis=1) <= view.size / 2) > 0.95


def test_a_recording_leaves_pandas_unloaded(tmp_path):
    """Issue 17: pyarrow imports pandas (45 MB resident) to look at what rerun hands it; fdmo run keeps it out and
    records the same entities. A fresh interpreter: this one may have pandas loaded by other tests."""
    pytest.importorskip("pandas")  # where it is not installed there is nothing to keep out
    path = tmp_path / "run.rrd"
    script = (
        "import sys; sys.path.insert(0, 'tests'); import test_rerun_sink as t; t.sink_module.keep_pandas_unloaded(); "
        f"t.run_synthetic(t.RerunSink({str(path)!r}, t.CAMERA, ground_truth=t.ground_truth())); "
        "print('pandas' in sys.modules)"
    )
    result = subprocess.run([sys.executable, "-W", "error::UserWarning", "-c", script], capture_output=True,
                            text=True, cwd=Path(__file__).resolve().parents[1])
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["False"]
    entities = {chunk.entity_path for chunk in rr.chunk.RrdReader(path).stream().to_chunks()}
    assert {"/" + entity for entity in (sink_module.IMAGE, sink_module.EVENT_LOG, sink_module.DIRECT_POINTS)} <= entities


# ------------------------------------------------------------------------ a long run in parts (issue 48)

PART_FRAMES = 5  # the 12 frames in three files: steps 0-4, 5-9, 10-11
RERUN_CLI = Path(sys.executable).with_name("rerun")  # installed with rerun-sdk, beside the interpreter


@pytest.fixture(scope="module")
def parts(tmp_path_factory) -> list[Path]:
    path = tmp_path_factory.mktemp("parts") / "run.rrd"
    run_synthetic(RerunSink(path, CAMERA, ground_truth=ground_truth(), recording_name="synthetic",
                            part_frames=PART_FRAMES))
    return recording_files(path)


def steps(path: Path, entity: str, component: str | None = None) -> list[int]:
    """The steps at which ``entity`` (its ``component``, where given) was logged in the file ``path``, in order."""
    rows = []
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        table = chunk.to_record_batch().to_pydict()
        if chunk.entity_path == entity and "step" in table and (component is None or component in table):
            values = table[component or "step"]
            rows += [step for step, value in zip(table["step"], values) if value is not None]
    return sorted(rows)


def test_a_long_run_goes_on_in_parts_of_one_recording_that_each_verify(parts):
    assert [path.name for path in parts] == ["run.rrd", "run.part2.rrd", "run.part3.rrd"]
    # One recording id in every file: Rerun pools them into one recording (`rerun run*.rrd`).
    ids = {(entry.application_id, entry.recording_id) for path in parts
           for entry in rr.chunk.RrdReader(path).recordings()}
    assert len(ids) == 1
    verified = subprocess.run([str(RERUN_CLI), "rrd", "verify", *map(str, parts)], capture_output=True, text=True)
    assert verified.returncode == 0, verified.stderr  # each part complete, its footer included


def test_together_the_parts_hold_every_frame_once(parts):
    """Each part holds its own frames (their images, their scalars); a part after the first starts with the camera
    where the last frame of the one before left it."""
    own = [list(range(start, min(start + PART_FRAMES, FRAMES))) for start in range(0, FRAMES, PART_FRAMES)]
    assert [steps(path, "/world/camera/image", "EncodedImage:blob") for path in parts] == own
    posed = [[step for step in part if step != LOST_FRAME] for part in own]
    assert [steps(path, "/world/camera") for path in parts] == [posed[0]] + [
        [before[-1], *steps_of_part] for before, steps_of_part in zip(posed, posed[1:])]
    ratios = [step for path in parts for step in steps(path, "/plots/divergence/ratio")]
    assert ratios == [step for part in posed for step in part]  # each posed frame's value, once


def test_a_part_opened_alone_starts_with_what_the_frames_before_it_left(parts):
    """The second part starts at step 4 with the styles, the name, the camera and its frustum, the whole path (and
    the ground truth) and the event markers so far, though none of them changed at that step; the keyframes and the
    clouds come at its first keyframe (8)."""
    second: dict[str, list] = {}
    for chunk in rr.chunk.RrdReader(parts[1]).stream().to_chunks():
        second.setdefault(chunk.entity_path, []).append(chunk)
    assert {"/world", "/__properties", "/plots/divergence/ratio"} <= set(second)  # static: axes, name, style
    first_step = PART_FRAMES - 1
    for entity in ("/world/camera", "/world/trajectory/estimate", "/world/trajectory/ground_truth",
                   "/world/events/initialization_succeeded"):
        assert steps(parts[1], entity)[0] == first_step, entity
    assert any(matrix is not None for matrix in column(second["/world/camera/image"], "Pinhole:image_from_camera"))
    assert np.array(column(second["/world/trajectory/estimate"], "LineStrips3D:strips")[0][0]).shape == (
        first_step + 1 - (LOST_FRAME < first_step), 3)  # every pose up to step 4, the lost frame's none
    for entity in ("/world/keyframes/8", "/world/map/direct_points"):
        assert set(steps(parts[1], entity)) == {8}, entity


def test_a_new_recording_removes_the_parts_of_an_older_one(tmp_path):
    """A run into the same file (or a Restart from the viser page) replaces the recording there, parts included:
    `rerun run*.rrd` must not pool an older run's parts with the new one."""
    path = tmp_path / "run.rrd"

    def play(sink: RerunSink, frames: int) -> None:
        for index in range(frames):
            sink.on_frame(SimpleNamespace(image=None), FrameResult(index, index * PERIOD_S, camera_pose(index), True))

    older = RerunSink(path, CAMERA, part_frames=2)
    play(older, 6)
    older.close()
    assert len(recording_files(path)) == 3
    newer = RerunSink(path, CAMERA, part_frames=2)
    play(newer, 3)
    assert recording_files(path) == [path, path.with_name("run.part2.rrd")]
    newer.restart()
    play(newer, 1)
    newer.close()
    assert recording_files(path) == [path]
    assert [entry.recording_id for entry in rr.chunk.RrdReader(path).recordings()] == [
        newer.recording.get_recording_id()]


def test_recording_files_come_in_part_order_and_leave_other_files_out(tmp_path):
    names = ["run.rrd", "run.part10.rrd", "run.part2.rrd", "run.part2x.rrd", "other.part3.rrd", "run.part3.rrd.bak"]
    for name in names:
        (tmp_path / name).write_bytes(b"")
    found = recording_files(tmp_path / "run.rrd")
    assert [path.name for path in found] == ["run.rrd", "run.part2.rrd", "run.part10.rrd"]
    assert recording_files(tmp_path / "missing" / "run.rrd") == []
