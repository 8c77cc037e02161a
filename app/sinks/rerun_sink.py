"""A Rerun recording (.rrd) of a run: what the odometry saw, estimated and decided, frame by frame.

Everything is logged on three timelines, ``frame`` (the frame index in the original sequence), ``time`` (the
frame's timestamp in seconds) and ``step`` (the order in which the odometry processed the frames: after a
backward jump, ``frame`` and ``time`` go back while ``step`` goes on, so the replay is on ``step`` beside the
first playing), into a ``RecordingStream`` of its own (never Rerun's global stream), saved to a file with a
default blueprint. Open it with ``rerun FILE.rrd``.

Each pass is a recording of its own: ``restart()`` (Restart on the viser page) ends the recording of the pass
played so far and starts a new one, with a new recording id, in the same file, which then holds the new pass as
every other result file of the folder does (``recording_name`` gets " (pass N)").

A long run goes on in a new file every ``part_frames`` frames (issue 48): FILE.rrd holds the first part, then
FILE.part2.rrd, FILE.part3.rrd, ... (app/sinks/recording_parts.py), each a complete .rrd with its footer, all with
the same recording id, so that ``rerun FILE*.rrd`` opens them as one recording. Each part starts with what a part
opened alone needs from the frames before it (the styles, the camera, the whole path, the event markers).

Entities (the 3D world is the estimate's: the first camera's frame, x right, y down, z forward):

    world/camera                    T_world_cam of each posed frame
    world/camera/image              pinhole (the frustum), the input image (JPEG) and
    world/camera/image/tracked      the pixels the method tracked (FrameResult.points_2d)
    world/camera/image/matches      the frame's feature matches as lines into it (a recovery's, a feature
                                    keyframe's new ones): inliers violet, outliers red; cleared on frames without
    world/trajectory/estimate       the estimated path (LineStrips3D), relogged whole at keyframes ...
    world/trajectory/recent         ... and the frames since then, so that each frame logs a few points only
    world/trajectory/ground_truth   the ground truth, Sim(3)-aligned to the estimate, refitted at keyframes
    world/map/direct_points         the active window's points, colored by inverse depth (turbo, near red)
    world/map/feature_points        the feature map's points (violet)
    world/keyframes/<frame>         a frustum per keyframe: its pose (Transform3D) and a pinhole
    world/events/<kind>             a marker where each non-routine event happened, one entity per kind (the
                                    kinds of one frame stacked upwards from its pose: scene.EventMarkers)
    events                          every event as a TextLog line (failures as WARN/ERROR)
    plots/divergence/ratio, .../threshold   FDMO's divergence test: RMSE after/before against 1 + epsilon
    plots/divergence/events/<lane>  divergences, recoveries, failed recoveries, drops and jumps as markers on that
                                    plot, a row each (scene.PLOT_LANES)
    plots/tracking/*, plots/counts/*, plots/timing_ms/*   scalars (rmse before/after, counts, ms per stage)

Cost: one JPEG encode and four log calls per frame (~3 ms for 640x480 on one core); scalars are buffered and
sent as columns every SCALAR_COLUMN_FRAMES frames, the whole path, the clouds and the keyframes only at
keyframes.
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from app.sinks.recording_parts import PART_FRAMES, later_parts, part_path
from app.sinks.scene import (
    DIVERGENCE_RATIO_COLOR,
    DIVERGENCE_THRESHOLD_COLOR,
    ESTIMATE_COLOR,
    FEATURE_POINT_COLOR,
    GROUND_TRUTH_COLOR,
    KEYFRAME_COLOR,
    LOOP_COLOR,
    OVERLAY_POINT_COLOR,
    PLOT_LANES,
    EventMarkers,
    Framing,
    GroundTruthOverlay,
    PathHistory,
    PlotLane,
    SceneScale,
    event_style,
    event_text,
    framing,
    inverse_depth_colors,
    kind_style,
    match_colors,
)
from vo_core.events import POSE_CORRECTIONS, Event, EventKind, FrameResult, MapSnapshot
from vo_core.geometry.camera import PinholeCamera
from vo_core.trajectory import Trajectory

FRAME_TIMELINE = "frame"
TIME_TIMELINE = "time"
STEP_TIMELINE = "step"

CAMERA = "world/camera"
IMAGE = "world/camera/image"
TRACKED_PIXELS = "world/camera/image/tracked"
MATCHES = "world/camera/image/matches"
ESTIMATE = "world/trajectory/estimate"
RECENT = "world/trajectory/recent"
GROUND_TRUTH = "world/trajectory/ground_truth"
DIRECT_POINTS = "world/map/direct_points"
FEATURE_POINTS = "world/map/feature_points"
KEYFRAMES = "world/keyframes"
LOOPS = "world/loops"  # a line between the two keyframes of each closed loop
EVENT_MARKERS = "world/events"
EVENT_LOG = "events"
DIVERGENCE_PLOTS = "plots/divergence"
DIVERGENCE_RATIO = "plots/divergence/ratio"
DIVERGENCE_THRESHOLD = "plots/divergence/threshold"
DIVERGENCE_EVENTS = "plots/divergence/events"
TRACKING_PLOTS = "plots/tracking"
COUNT_PLOTS = "plots/counts"
TIMING_PLOTS = "plots/timing_ms"

JPEG_QUALITY = 75  # issue 6: about 5x smaller than raw images, at no cost in speed
FULL_PATH_EVERY = 30  # frames: relog the whole path at least this often when no keyframe comes
# frames of scalars sent as one column per entity: each send is a chunk per entity, and the SDK's file sink keeps an
# index entry per chunk (the .rrd footer's manifest) until the recording closes, as wide as the recording's
# timelines x components (~3.5 KiB a chunk): at every keyframe, ~2,200 chunks and ~7 MiB per 1,000 frames (issue 17)
SCALAR_COLUMN_FRAMES = 250
# The SDK's batcher makes a chunk per entity each flush_tick (200 ms by default): at the odometry's few frames a second
# that is a chunk per entity per frame, each indexed in memory until the end (above). Larger batches: a chunk per
# entity every BATCH_SECONDS or BATCH_BYTES (what a viewer following the file lags behind, what waits in memory).
BATCH_SECONDS = 2.0
BATCH_BYTES = 8 * 2**20
FLUSH_TIMEOUT_S = 10.0  # the longest the end of a part or of the recording waits for the batches to reach the file
POINT_RADIUS_UI = 1.5  # map points, in UI points (constant size on screen whatever the scale)
MARKER_RADIUS_UI = 6.0
PATH_RADIUS_UI = 1.5
MATCH_RADIUS_PX = 0.75
PLOT_MARKER_SIZE = 6.0


def keep_pandas_unloaded() -> None:
    """Keep pyarrow from importing pandas (45 MB resident, issue 17) where it is installed but not imported.

    The first time rerun hands pyarrow anything but a numpy array, pyarrow imports pandas only to ask whether the
    object is a pandas one; logging never needs pandas. Here that first attempt fails: pyarrow remembers it and
    does not try again. For a process whose pyarrow serves the recording alone (``fdmo run``): pyarrow's other
    conversions then behave as without pandas (nanosecond timestamps no longer convert to Python objects)."""
    if "pandas" in sys.modules:
        return
    sys.modules["pandas"] = None  # an import of pandas now fails
    try:
        pa.array([0])
    except (AttributeError, ImportError):  # pyarrow 26 reads __version__ of what the failed import gave it
        pass
    finally:
        del sys.modules["pandas"]


class RerunSink:
    """A Sink that records a run into the .rrd file ``path`` (None: kept in memory, see ``memory``)."""

    def __init__(
        self,
        path: str | Path | None,
        camera: PinholeCamera,
        ground_truth: Trajectory | None = None,
        application_id: str = "fdmo",
        *,
        recording_name: str | None = None,
        jpeg_quality: int = JPEG_QUALITY,
        part_frames: int = PART_FRAMES,
    ):
        """``part_frames``: frames per file of the recording (0: one file, however long the run)."""
        if part_frames < 0:
            raise ValueError(f"part_frames {part_frames}: must be 0 (one file) or more")
        self.file = None if path is None else Path(path)
        self.part_frames = part_frames
        self.parts: list[Path] = []  # the files of this pass so far
        self.camera = camera
        self.jpeg_quality = jpeg_quality
        self.ground_truth = GroundTruthOverlay(ground_truth) if ground_truth is not None and len(ground_truth) else None
        self.application_id = application_id
        self.recording_name = recording_name
        self.passes = 0
        self._start_recording()

    def _start_recording(self) -> None:
        """A new recording (a new recording id) for the next pass, and the state of a pass."""
        self.passes += 1
        self.recording = rr.RecordingStream(self.application_id, batcher_config=rr.ChunkBatcherConfig(
            flush_tick=BATCH_SECONDS, flush_num_bytes=BATCH_BYTES))
        self._send_recording_name()
        if self.file is None:
            self.memory = self.recording.memory_recording()
        else:
            for stale in later_parts(self.file):  # an earlier pass's or run's: not parts of this one
                stale.unlink()
            self.parts = [self.file]
            self.recording.save(str(self.file), default_blueprint=default_blueprint())
        self._scalars = _ScalarColumns()
        self.history = PathHistory()
        self._full_path_length = 0  # poses in the last whole-path log
        self._step = 0  # frames processed in this pass: the step of the next one
        self._last: tuple[int, float, int] | None = None  # (frame index, timestamp, step) of the last frame
        self._scale = SceneScale()
        self._frustums: dict[str, float] = {}  # pinhole entity -> the image plane distance it was logged with
        self._keyframes: dict[int, np.ndarray] = {}  # keyframe -> the pose logged
        self._markers = EventMarkers()
        self._plotted_lanes: set[str] = set()  # the lanes of the divergence plot with a series
        self._matches_shown = False
        self._loops: list[np.ndarray] = []  # (2, 3) each: the keyframe and its loop keyframe, as last corrected
        self._clouds: tuple[np.ndarray | None, np.ndarray | None] = (None, None)  # the latest direct, feature
        self._log_styles()

    # ------------------------------------------------------------------------------------ Sink protocol

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        self._start_part_when_due()
        self._last = (result.frame_index, result.timestamp, self._step)
        self._set_time(*self._last)
        if result.T_world_cam is not None:
            self.history.add(result.timestamp, result.T_world_cam)
            self.recording.log(CAMERA, _transform(result.T_world_cam))
            self._log_frustum(IMAGE, ESTIMATE_COLOR)
        if frame is not None and getattr(frame, "image", None) is not None:
            self._log_image(frame.image, result.points_2d)
        self._log_matches(result.matches_2d, result.matches_inlier)
        self._log_markers(result.T_world_cam[:3, 3] if result.T_world_cam is not None
                          else self.history.last_position())
        self._add_scalars(result)
        self._log_path(force_full=result.is_keyframe)
        if self._scalars.frames() >= SCALAR_COLUMN_FRAMES:
            self._scalars.send(self.recording)
        self._step += 1

    def on_event(self, event: Event) -> None:
        self._start_part_when_due()  # an event goes into the part of the frame it comes before
        self._set_time(event.frame_index, event.timestamp, self._step)  # the step of the frame it comes before
        style = event_style(event)
        self.recording.log(EVENT_LOG, rr.TextLog(event_text(event), level=style.level, color=style.color))
        self._markers.add(event)
        if event.kind in POSE_CORRECTIONS:
            self._show_loop(event.details)

    def _show_loop(self, loop: dict) -> None:
        """A closed loop moved the path before it: the whole path again, and the loop's line."""
        self.history.correct(loop)
        self._full_path_length = 0
        self._log_path(force_full=True)
        self._loops.append(np.asarray(loop["positions"], dtype=float))
        self.recording.log(LOOPS, rr.LineStrips3D(self._loops, colors=LOOP_COLOR,
                                                  radii=rr.Radius.ui_points(PATH_RADIUS_UI)))

    def on_map(self, snapshot: MapSnapshot) -> None:
        if self._last is not None:
            self._set_time(*self._last)
        radii = rr.Radius.ui_points(POINT_RADIUS_UI)
        self._clouds = (snapshot.direct_points_world, snapshot.feature_points_world)
        if snapshot.direct_points_world is not None:
            colors = inverse_depth_colors(snapshot.direct_inverse_depths)
            self.recording.log(DIRECT_POINTS, rr.Points3D(snapshot.direct_points_world, colors=colors, radii=radii))
            self._add_scalar(f"{COUNT_PLOTS}/direct_points", len(snapshot.direct_points_world))
        if snapshot.feature_points_world is not None:
            self.recording.log(
                FEATURE_POINTS, rr.Points3D(snapshot.feature_points_world, colors=FEATURE_POINT_COLOR, radii=radii)
            )
            self._add_scalar(f"{COUNT_PLOTS}/feature_points", len(snapshot.feature_points_world))
        if self._scale.follow(self._view()):
            self._frustums.clear()  # every frustum is logged again at the new size
            self._log_frustum(IMAGE, ESTIMATE_COLOR)
        self._log_keyframes(snapshot.keyframe_poses)

    def restart(self) -> None:
        """A new pass: the recording so far is finished, and a new one (a new recording id) starts in its place."""
        self._finish_recording()
        self._start_recording()

    def close(self) -> None:
        self._finish_recording()

    # ------------------------------------------------------------------------------------ parts

    def _finish_recording(self) -> None:
        self._log_markers(self.history.last_position())  # the events after the last frame
        self._log_path(force_full=True)
        self._scalars.send(self.recording)
        view = self._view()
        if view is not None:  # the default view, now that the scene's extent is known
            self.recording.send_blueprint(default_blueprint(view, self._timeline()), make_active=True,
                                          make_default=True)
        self.recording.flush(timeout_sec=FLUSH_TIMEOUT_S)
        self.recording.disconnect()

    def _start_part_when_due(self) -> None:
        """At the first frame past the current part's ``part_frames``: the current file is finished (the SDK writes
        its footer and lets go of its index when the stream moves to another file) and the recording goes on in the
        next one. The blueprint stays in the first and the last part: the SDK keeps every blueprint it made until the
        process ends (0.6-1 MiB each), so one per part would grow."""
        if self.file is None or self.part_frames == 0 or self._step < len(self.parts) * self.part_frames:
            return
        self._scalars.send(self.recording)
        self.recording.flush(timeout_sec=FLUSH_TIMEOUT_S)
        self.parts.append(part_path(self.file, len(self.parts) + 1))
        self.recording.save(str(self.parts[-1]))
        self._send_recording_name()
        self._log_scene()

    def _log_scene(self) -> None:
        """What a part opened alone needs from the frames before it, at the last of them: the styles, the camera and
        its frustum, the whole path and the event markers. The clouds and the keyframes that move come at the next
        keyframe; the old keyframes' frustums are in the parts where they were made (logging them all again would
        take a second of the sink's time at a thousand keyframes)."""
        self._log_styles()
        if self._last is None or len(self.history) == 0:
            return
        self._set_time(*self._last)
        self.recording.log(CAMERA, _transform(self.history.poses[-1]))
        self._frustums.pop(IMAGE, None)
        self._log_frustum(IMAGE, ESTIMATE_COLOR)
        self._log_path(force_full=True)
        for kind in self._markers.positions:
            self._log_marker(kind)

    def _send_recording_name(self) -> None:
        if self.recording_name:
            suffix = f" (pass {self.passes})" if self.passes > 1 else ""
            self.recording.send_recording_name(self.recording_name + suffix)

    def _view(self) -> Framing | None:
        return framing(self.history.positions(), *self._clouds)

    def _timeline(self) -> str:
        """The timeline a recording opens on: ``step`` when frames were played again (on ``frame`` the replay would
        lie over the first playing, its divergence hidden under the values it replaced), ``frame`` otherwise."""
        return STEP_TIMELINE if np.any(np.diff(self.history.timestamps) < 0) else FRAME_TIMELINE

    def _set_time(self, frame_index: int, timestamp: float, step: int) -> None:
        self.recording.set_time(FRAME_TIMELINE, sequence=int(frame_index))
        self.recording.set_time(TIME_TIMELINE, duration=float(timestamp))
        self.recording.set_time(STEP_TIMELINE, sequence=int(step))

    def _log_frustum(self, entity: str, color: tuple[int, int, int]) -> None:
        """The pinhole of ``entity``, its image plane at the scene's frustum size (logged again only when the
        scene's size changed)."""
        depth = self._scale.frustum
        if self._frustums.get(entity) == depth:
            return
        self._frustums[entity] = depth
        self.recording.log(entity, rr.Pinhole(
            image_from_camera=self.camera.K, resolution=[self.camera.width, self.camera.height],
            camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=depth, color=list(color),
        ))

    def _log_keyframes(self, keyframe_poses: dict[int, np.ndarray]) -> None:
        """A frustum per keyframe, its pose logged when new or moved (the window optimization moves them); the
        keyframes no longer in the map are cleared."""
        for index in self._keyframes.keys() - keyframe_poses.keys():
            self.recording.log(f"{KEYFRAMES}/{index}", rr.Clear(recursive=True))
            self._frustums.pop(f"{KEYFRAMES}/{index}", None)
            del self._keyframes[index]
        for index, T_world_cam in keyframe_poses.items():
            entity = f"{KEYFRAMES}/{index}"
            if index not in self._keyframes or not np.array_equal(self._keyframes[index], T_world_cam):
                self._keyframes[index] = np.array(T_world_cam)
                self.recording.log(entity, _transform(T_world_cam))
            self._log_frustum(entity, KEYFRAME_COLOR)

    def _log_image(self, image: np.ndarray, points_2d: np.ndarray | None) -> None:
        # OpenCV's encoder: the same JPEG as rr.Image(...).compress(), in half the time.
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if ok:
            self.recording.log(IMAGE, rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))
        tracked = np.zeros((0, 2)) if points_2d is None else np.asarray(points_2d).reshape(-1, 2)
        self.recording.log(TRACKED_PIXELS, rr.Points2D(tracked, colors=OVERLAY_POINT_COLOR, radii=1.5))

    def _log_matches(self, matches_2d: np.ndarray | None, inlier: np.ndarray | None) -> None:
        """The frame's matches; a frame without any clears the last ones, so that they do not linger."""
        if matches_2d is not None and len(matches_2d):
            segments = np.asarray(matches_2d, dtype=float).reshape(-1, 2, 2)
            self.recording.log(MATCHES, rr.LineStrips2D(segments, colors=match_colors(len(segments), inlier),
                                                        radii=MATCH_RADIUS_PX))
            self._matches_shown = True
        elif self._matches_shown:
            self.recording.log(MATCHES, rr.Clear(recursive=False))
            self._matches_shown = False

    def _log_path(self, force_full: bool) -> bool:
        """The whole path at keyframes (and every FULL_PATH_EVERY frames), only its recent tail otherwise;
        True when the whole path was logged."""
        if len(self.history) == 0:
            return False
        full = force_full or len(self.history) - self._full_path_length >= FULL_PATH_EVERY
        if full:
            self._full_path_length = len(self.history)
            self._log_strip(ESTIMATE, self.history.positions(), ESTIMATE_COLOR)
            self._log_ground_truth()
        self._log_strip(RECENT, self.history.positions(start=max(self._full_path_length - 1, 0)), ESTIMATE_COLOR)
        return full

    def _log_ground_truth(self) -> None:
        if self.ground_truth is None:
            return
        aligned = self.ground_truth.positions_in_estimate_frame(self.history.trajectory())
        if aligned is not None:
            self._log_strip(GROUND_TRUTH, aligned, GROUND_TRUTH_COLOR)

    def _log_strip(self, entity: str, positions: np.ndarray, color: tuple[int, int, int]) -> None:
        self.recording.log(
            entity, rr.LineStrips3D([positions], colors=color, radii=rr.Radius.ui_points(PATH_RADIUS_UI))
        )

    def _log_markers(self, position: np.ndarray | None) -> None:
        """The events since the last frame, marked at ``position`` and in their lanes of the divergence plot."""
        kinds = set(event.kind for event in self._markers.place(position))
        for kind in kinds:
            self._log_marker(kind)
        for lane in PLOT_LANES:
            if kinds & set(lane.kinds):
                self._plot_in_lane(lane)

    def _log_marker(self, kind: EventKind) -> None:
        """Every marker of ``kind`` so far (one entity per kind)."""
        self.recording.log(f"{EVENT_MARKERS}/{kind.value}", rr.Points3D(
            self._markers.stacked(kind, self._scale.marker), colors=kind_style(kind).color, labels=kind.value,
            radii=rr.Radius.ui_points(MARKER_RADIUS_UI),
        ))

    def _plot_in_lane(self, lane: PlotLane) -> None:
        series = f"{DIVERGENCE_EVENTS}/{lane.name}"
        if lane.name not in self._plotted_lanes:
            self._plotted_lanes.add(lane.name)
            self._log_lane_style(lane)
        self._add_scalar(series, lane.height)

    def _log_styles(self) -> None:
        """What is static: the axes of the world, the styles of the divergence plot's series and of its lanes."""
        self.recording.log("world", rr.ViewCoordinates.RDF, static=True)
        self.recording.log(DIVERGENCE_RATIO, rr.SeriesLines(colors=DIVERGENCE_RATIO_COLOR, names="RMSE after / before",
                                                            widths=2.0), static=True)
        self.recording.log(DIVERGENCE_THRESHOLD, rr.SeriesLines(colors=DIVERGENCE_THRESHOLD_COLOR,
                                                                names="threshold 1 + epsilon", widths=1.0), static=True)
        for lane in PLOT_LANES:
            if lane.name in self._plotted_lanes:
                self._log_lane_style(lane)

    def _log_lane_style(self, lane: PlotLane) -> None:
        self.recording.log(f"{DIVERGENCE_EVENTS}/{lane.name}", rr.SeriesPoints(
            colors=lane.color, names=lane.name, marker_sizes=PLOT_MARKER_SIZE), static=True)

    def _add_scalars(self, result: FrameResult) -> None:
        values = {
            DIVERGENCE_RATIO: result.divergence_ratio,
            DIVERGENCE_THRESHOLD: result.divergence_threshold,
            f"{TRACKING_PLOTS}/rmse_before": result.rmse_before,
            f"{TRACKING_PLOTS}/rmse_after": result.rmse_after,
            f"{COUNT_PLOTS}/inliers": result.num_inliers,
            f"{COUNT_PLOTS}/tracked_pixels": None if result.points_2d is None else len(result.points_2d),
            **{f"{TIMING_PLOTS}/{stage}": milliseconds for stage, milliseconds in result.timings_ms.items()},
        }
        for entity, value in values.items():
            if value is not None:
                self._add_scalar(entity, value)

    def _add_scalar(self, entity: str, value: float) -> None:
        """A value at the last frame (the one being logged)."""
        if self._last is not None:
            self._scalars.add(entity, *self._last, value)


def _transform(T_world_cam: np.ndarray) -> rr.Transform3D:
    return rr.Transform3D(translation=T_world_cam[:3, 3], mat3x3=T_world_cam[:3, :3])


class _ScalarColumns:
    """Scalars buffered per entity and sent as columns (one send_columns per entity, not one log per value):
    a log call costs ~0.3 ms, a dozen per frame would cost more than the rest of the sink; and each send is a chunk
    per entity, which the SDK indexes in memory until the recording closes (SCALAR_COLUMN_FRAMES)."""

    def __init__(self) -> None:
        self._rows: dict[str, list[tuple[int, float, int, float]]] = defaultdict(list)

    def add(self, entity: str, frame_index: int, timestamp: float, step: int, value: float) -> None:
        self._rows[entity].append((int(frame_index), float(timestamp), int(step), float(value)))

    def frames(self) -> int:
        """The most values buffered for one entity: about the frames since the last send."""
        return max((len(rows) for rows in self._rows.values()), default=0)

    def send(self, recording: rr.RecordingStream) -> None:
        for entity, rows in self._rows.items():
            frames, times, steps, values = zip(*rows)
            recording.send_columns(
                entity,
                indexes=[rr.TimeColumn(FRAME_TIMELINE, sequence=frames), rr.TimeColumn(TIME_TIMELINE, duration=times),
                         rr.TimeColumn(STEP_TIMELINE, sequence=steps)],
                columns=rr.Scalars.columns(scalars=values),
            )
        self._rows.clear()


def default_blueprint(view: Framing | None = None, timeline: str = FRAME_TIMELINE) -> rrb.Blueprint:
    """The 3D world on the left, looked at from behind and above the path and the dense part of the map (``view``,
    when known); on the right the camera image (with the matches of recoveries and feature keyframes) over the
    plots (tabs: the divergence ratio against its threshold first) and the event log (routine DEBUG lines filtered
    out, one click brings them back). A recording opens on ``timeline`` at its last frame, the whole run in view;
    press play or scrub to replay it."""
    eye = rrb.EyeControls3D(kind="Orbital", eye_up=[0.0, -1.0, 0.0])
    if view is not None:
        eye = rrb.EyeControls3D(kind="Orbital", eye_up=[0.0, -1.0, 0.0], position=view.eye, look_target=view.centre)
    world = rrb.Spatial3DView(
        name="World", origin="world", background=[250, 250, 250], line_grid=rrb.LineGrid3D(visible=False),
        eye_controls=eye,
    )
    image = rrb.Spatial2DView(name="Camera", origin=IMAGE)
    plots = rrb.Tabs(
        # The legend top left: the event lanes run along the bottom, and the run's end is where the cursor is.
        rrb.TimeSeriesView(name="Divergence", origin=DIVERGENCE_PLOTS, plot_legend=rrb.Corner2D.LeftTop),
        rrb.TimeSeriesView(name="Residuals", origin=TRACKING_PLOTS),
        rrb.TimeSeriesView(name="Counts", origin=COUNT_PLOTS),
        rrb.TimeSeriesView(name="Timing (ms)", origin=TIMING_PLOTS),
    )
    events = rrb.TextLogView(
        name="Events", origin=EVENT_LOG,
        rows=rrb.TextLogRows(filter_by_log_level=["INFO", "WARN", "ERROR", "CRITICAL"]),
        columns=rrb.TextLogColumns(text_log_columns=[
            rrb.encodings.TextLogColumn("LogLevel"), rrb.encodings.TextLogColumn("Body")]),
    )
    return rrb.Blueprint(
        rrb.Horizontal(world, rrb.Vertical(image, plots, events, row_shares=[3, 2, 2]), column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=timeline, play_state="Following"),
    )
