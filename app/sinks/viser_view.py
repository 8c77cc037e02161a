"""The live browser page (viser): the 3D scene, the current image, the divergence plot, status, the event log and
playback controls.

Two threads meet here. The tracking thread calls the Sink methods, which only store what arrived (under a lock,
a few microseconds). A refresher thread draws the stored state into the page at ``refresh_hz`` (the page does
not need every frame, and drawing never slows tracking). The controls run on viser's threads and only call the
Player, which applies them when the next frame is about to be handed out; the pipeline calls ``restart()`` when
a new pass starts (Restart), which clears the page.

Scene (the estimate's world: first camera frame, y down, so "up" is -y): the path, the ground truth aligned to
it (Sim(3), refitted when the keyframes change), keyframe frustums with thumbnails, the current camera, the
direct cloud colored by inverse depth and the feature cloud in violet, and a marker where each non-routine event
happened (colored by kind); each layer can be switched off. The view follows the path and the dense part of the
map (scene.framing) while "follow the scene" is on.

Playback: with ``wait_for_browser`` the player is held until the first browser connects, so that nobody misses
the start; the frame rate shown is the terminal's (frames over the player's playing time, pauses left out).
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np
import viser
import viser.transforms as vtf
import viser.uplot as uplot

from app.progress import FrameRate
from app.sinks.scene import (
    CURRENT_CAMERA_COLOR,
    DIVERGENCE_RATIO_COLOR,
    DIVERGENCE_THRESHOLD_COLOR,
    ESTIMATE_COLOR,
    FEATURE_POINT_COLOR,
    GROUND_TRUTH_COLOR,
    KEYFRAME_COLOR,
    LOOP_COLOR,
    MIN_SCENE_SIZE,
    OVERLAY_POINT_COLOR,
    PLOT_LANES,
    EventMarkers,
    Framing,
    GroundTruthOverlay,
    PathHistory,
    SceneScale,
    event_style,
    event_text,
    framing,
    inverse_depth_colors,
    kind_style,
    match_colors,
    resized,
)
from vo_core.events import POSE_CORRECTIONS, Event, EventKind, FrameResult, MapSnapshot
from vo_core.geometry.camera import PinholeCamera
from vo_core.trajectory import Trajectory

logger = logging.getLogger(__name__)

REFRESH_HZ = 10.0  # page updates per second; the odometry runs at its own pace
EVENT_LOG_LENGTH = 12  # events listed on the page, newest first
THUMBNAIL_WIDTH = 120  # pixels of a keyframe frustum's thumbnail
# Images of the last frames, kept (by reference) for the thumbnails of keyframes announced late: an initializer
# makes its first frame a keyframe only once it succeeds, several frames later.
RECENT_IMAGES = 32
LINE_THICKNESS_PX = 3.0
# Point clouds as float32: viser's default, float16, overflows past 65504 (far feature points became inf, with a
# RuntimeWarning: overflow encountered in cast) and keeps 3 digits (a point 100 m out moves in 6 cm steps).
POINT_PRECISION = "float32"
MAX_FRAMES = 1000  # the most frames a drop or a jump back asks for
SPEEDS = (0.0, 4.0, 0.25)  # slider min, max, step; 0 = as fast as possible
DEFAULT_FRAMES = 10
# The view follows the scene when it grew or shrank (scene.resized) or when its centre moved by this fraction of it.
RECENTRE_FRACTION = 0.25
PLOT_FRAMES = 300  # the divergence plot shows the last frames processed
PLOT_PLACEHOLDER = [(0, None, None, frozenset()), (1, None, None, frozenset())]
# The page's chart does not rescale its y axis when data comes (viser keeps the user's zoom), so the range is
# set from here: 0 to the largest value shown, rounded up to PLOT_TOP_STEP, at least PLOT_MIN_TOP.
PLOT_MIN_TOP = 1.5
PLOT_TOP_STEP = 0.5

LAYERS = ("trajectory", "ground truth", "direct cloud", "feature cloud", "keyframes", "camera", "events")


class PlayerControls(Protocol):
    """What the page asks of the player (app.player.Player)."""

    paused: bool
    finished: bool
    speed: float

    def pause(self) -> None: ...
    def resume(self) -> None: ...
    def step(self) -> None: ...
    def drop_next(self, count: int) -> None: ...
    def jump_back(self, count: int) -> None: ...
    def request_restart(self) -> None: ...
    def stop(self) -> None: ...
    def playing_time(self) -> float: ...


@dataclass
class _LiveState:
    """What the sink methods store for the refresher; written under ViserView._state_lock only."""

    path: PathHistory = field(default_factory=PathHistory)
    loops: list[np.ndarray] = field(default_factory=list)  # (2, 3) each: a closed loop's two keyframes
    frame_index: int | None = None
    image: np.ndarray | None = None
    points_2d: np.ndarray | None = None
    matches_2d: np.ndarray | None = None
    matches_inlier: np.ndarray | None = None
    T_world_cam: np.ndarray | None = None
    tracked: bool = False
    divergence_ratio: float | None = None
    divergence_threshold: float | None = None
    processed: int = 0
    tracked_count: int = 0
    keyframes: int = 0
    dropped: int = 0
    jumps: int = 0
    thumbnails: dict[int, np.ndarray] = field(default_factory=dict)
    recent_images: OrderedDict = field(default_factory=OrderedDict)  # frame index -> image
    keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)
    direct_points: np.ndarray | None = None
    direct_colors: np.ndarray | None = None
    feature_points: np.ndarray | None = None
    markers: EventMarkers = field(default_factory=EventMarkers)
    pending_kinds: set[EventKind] = field(default_factory=set)  # events waiting for their frame (the plot)
    # (step, ratio, threshold, kinds of the frame's events) of the last frames, for the divergence plot
    divergence: deque = field(default_factory=lambda: deque(maxlen=PLOT_FRAMES))
    events: deque = field(default_factory=lambda: deque(maxlen=EVENT_LOG_LENGTH))


@dataclass
class _Drawing:
    """A consistent copy of the live state, taken under the lock, drawn outside it."""

    path: np.ndarray
    loops: np.ndarray  # (K, 2, 3)
    trajectory: Trajectory | None
    image: np.ndarray | None
    points_2d: np.ndarray | None
    matches_2d: np.ndarray | None
    matches_inlier: np.ndarray | None
    T_world_cam: np.ndarray | None
    thumbnails: dict[int, np.ndarray]
    keyframe_poses: dict[int, np.ndarray]
    direct_points: np.ndarray | None
    direct_colors: np.ndarray | None
    feature_points: np.ndarray | None
    markers: dict[EventKind, np.ndarray]
    divergence: list[tuple]
    status: str
    events: list[Event]


class ViserView:
    """A Sink that serves the live page at http://host:port (the server starts here, ``close`` stops it)."""

    def __init__(
        self,
        camera: PinholeCamera,
        player: PlayerControls,
        ground_truth: Trajectory | None = None,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        refresh_hz: float = REFRESH_HZ,
        wait_for_browser: bool = False,
        title: str = "FDMO",
    ):
        self.title = title  # the panel's label: what is played
        self.camera = camera
        self.player = player
        self.ground_truth = GroundTruthOverlay(ground_truth) if ground_truth is not None and len(ground_truth) else None
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("-y")
        self._state_lock = threading.Lock()
        self._scene_lock = threading.RLock()
        self._state = _LiveState()
        self._rate = FrameRate(player.playing_time)
        # Versions count changes across restarts, so a fresh pass is never mistaken for one already drawn.
        self._frame_version = self._map_version = 0
        self._drawn_frame_version = self._drawn_map_version = 0
        self._drawn_player: tuple[bool, bool] | None = None  # (paused, finished) when last drawn
        self._cleared = False
        self._nodes: dict[str, tuple[str, Any]] = {}  # scene node name -> (layer, handle)
        self._scale = SceneScale()
        self._view = Framing(np.array([0.0, 0.0, MIN_SCENE_SIZE]), MIN_SCENE_SIZE)
        self._view_fitted = False  # the view of this pass has been fitted once
        self._frame_view(self._view)
        self._build_panel()
        self._holding = wait_for_browser
        if wait_for_browser:
            player.pause()
            self.server.on_client_connect(lambda _: self._release())
        self._stopping = threading.Event()
        self._refresher = threading.Thread(target=self._refresh_loop, args=(1.0 / refresh_hz,), daemon=True,
                                           name="viser-refresh")
        self._refresher.start()

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.port}"

    def _release(self) -> None:
        """The first browser is here: playback starts."""
        if self._holding:
            self._holding = False
            self.player.resume()

    # ------------------------------------------------------------------------------------ Sink protocol

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        with self._state_lock:
            state = self._state
            self._rate.count()
            state.frame_index = result.frame_index
            state.image = getattr(frame, "image", None)
            state.points_2d = result.points_2d
            state.matches_2d, state.matches_inlier = result.matches_2d, result.matches_inlier
            state.T_world_cam = result.T_world_cam
            state.tracked = result.tracked
            state.divergence_ratio, state.divergence_threshold = result.divergence_ratio, result.divergence_threshold
            state.divergence.append((state.processed, result.divergence_ratio, result.divergence_threshold,
                                     frozenset(state.pending_kinds)))
            state.pending_kinds.clear()
            state.processed += 1
            state.tracked_count += bool(result.tracked)
            if result.T_world_cam is not None:
                state.path.add(result.timestamp, result.T_world_cam)
            state.markers.place(state.path.last_position() if result.T_world_cam is None else result.T_world_cam[:3, 3])
            if result.is_keyframe:
                state.keyframes += 1
            if state.image is not None:
                state.recent_images[result.frame_index] = state.image
                if len(state.recent_images) > RECENT_IMAGES:
                    state.recent_images.popitem(last=False)
            self._frame_version += 1

    def on_event(self, event: Event) -> None:
        with self._state_lock:
            state = self._state
            if event.kind is EventKind.FRAMES_DROPPED:
                state.dropped += int(event.details.get("count", 0))
            state.jumps += event.kind is EventKind.FRAMES_JUMPED
            if event.kind in POSE_CORRECTIONS:  # the path before it moves, and the loop is drawn
                state.path.correct(event.details)
                state.loops.append(np.asarray(event.details["positions"], dtype=float))
            if event_style(event).marked:
                state.events.appendleft(event)
                state.markers.add(event)
                state.pending_kinds.add(event.kind)
            self._frame_version += 1

    def on_map(self, snapshot: MapSnapshot) -> None:
        direct_colors = None
        if snapshot.direct_points_world is not None:
            direct_colors = inverse_depth_colors(snapshot.direct_inverse_depths)
        with self._state_lock:
            state = self._state
            for index in snapshot.keyframe_poses.keys() - state.thumbnails.keys():
                if index in state.recent_images:
                    state.thumbnails[index] = _thumbnail(state.recent_images[index])
            state.keyframe_poses = dict(snapshot.keyframe_poses)
            state.direct_points, state.direct_colors = snapshot.direct_points_world, direct_colors
            state.feature_points = snapshot.feature_points_world
            self._map_version += 1

    def restart(self) -> None:
        """A new pass (Restart): forget the one shown so far; the next refresh clears the page."""
        with self._state_lock:
            self._state = _LiveState()
            self._rate.restart()
            self._cleared = True

    def close(self) -> None:
        self._stopping.set()
        self._refresher.join(timeout=5.0)
        self.server.stop()

    # ------------------------------------------------------------------------------------ the panel

    def _build_panel(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False)
        gui.main_panel.dock_right()
        gui.set_panel_label(self.title)
        self.status = gui.add_markdown("waiting for the first frame")
        self.image = gui.add_image(np.zeros((self.camera.height, self.camera.width, 3), np.uint8),
                                   label="camera", format="jpeg", jpeg_quality=80)
        # Two empty frames until there are two real ones: from less the page's chart never finds its x range again.
        self._plot_top = PLOT_MIN_TOP
        self.divergence_plot = gui.add_uplot(*_plot_columns(PLOT_PLACEHOLDER), title="divergence: RMSE after / before",
                                             aspect=2.5, scales=_plot_scales(self._plot_top), padding=(12, 16, 0, 0),
                                             legend=uplot.Legend(show=True))
        with gui.add_folder("Playback"):
            self.play_pause = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE)
            self.step_button = gui.add_button("Step one frame", icon=viser.Icon.PLAYER_SKIP_FORWARD)
            initial_speed = float(np.clip(self.player.speed, SPEEDS[0], SPEEDS[1]))
            self.speed = gui.add_slider("Speed (0 = max)", *SPEEDS, initial_value=initial_speed)
            self.frame_count = gui.add_number("N frames", DEFAULT_FRAMES, min=1, max=MAX_FRAMES, step=1)
            self.drop_button = gui.add_button("Drop N frames", icon=viser.Icon.PLAYER_TRACK_NEXT)
            self.jump_button = gui.add_button("Jump back N frames", icon=viser.Icon.PLAYER_TRACK_PREV)
            self.restart_button = gui.add_button("Restart", icon=viser.Icon.REFRESH, color="red")
        with gui.add_folder("Layers"):
            self.follow = gui.add_checkbox("follow the scene", True)
            self.layers = {name: gui.add_checkbox(name, True) for name in LAYERS}
        with gui.add_folder("Events"):
            self.event_log = gui.add_markdown("no events yet")

        self.play_pause.on_click(lambda _: self._toggle_pause())
        self.step_button.on_click(lambda _: self.player.step())
        self.speed.on_update(lambda _: setattr(self.player, "speed", self.speed.value))
        self.drop_button.on_click(lambda _: self.player.drop_next(int(self.frame_count.value)))
        self.jump_button.on_click(lambda _: self.player.jump_back(int(self.frame_count.value)))
        self.restart_button.on_click(lambda _: self.player.request_restart())
        self.follow.on_update(lambda _: self._fit_clients(self._view) if self.follow.value else None)
        for name, checkbox in self.layers.items():
            checkbox.on_update(lambda _, layer=name: self._show_layer(layer))

    def _toggle_pause(self) -> None:
        if self.player.paused:
            self.player.resume()
        else:
            self.player.pause()
        self._show_play_state()

    def _show_play_state(self) -> None:
        """Pause while playing, Play while paused; at the end of the sequence a disabled Play (Restart plays again)."""
        finished = getattr(self.player, "finished", False)
        paused = self.player.paused or finished
        self.play_pause.label = "Play" if paused else "Pause"
        self.play_pause.icon = viser.Icon.PLAYER_PLAY if paused else viser.Icon.PLAYER_PAUSE
        self.play_pause.disabled = finished

    # ------------------------------------------------------------------------------------ drawing

    def _refresh_loop(self, period_s: float) -> None:
        while not self._stopping.wait(period_s):
            try:
                self.refresh()
            except Exception:  # a drawing bug must not freeze the page for the rest of the run
                logger.exception("viser view: refresh failed")

    def refresh(self) -> None:
        """Draw what changed since the last refresh (called by the refresher thread; safe from any thread)."""
        player_state = (self.player.paused, getattr(self.player, "finished", False))
        with self._scene_lock:
            with self._state_lock:
                # A pause, a step or the end of the sequence changes the status line without a new frame.
                frame_changed = self._frame_version != self._drawn_frame_version or player_state != self._drawn_player
                map_changed = self._map_version != self._drawn_map_version
                cleared, self._cleared = self._cleared, False
                if not (frame_changed or map_changed or cleared):
                    return
                self._drawn_frame_version, self._drawn_map_version = self._frame_version, self._map_version
                self._drawn_player = player_state
                drawing = self._copy_for_drawing(with_trajectory=map_changed)
            if cleared:
                self._clear_scene()
            if frame_changed or cleared:
                self._draw_frame(drawing)
            if map_changed:
                self._draw_map(drawing)

    def _copy_for_drawing(self, with_trajectory: bool) -> _Drawing:
        state = self._state
        return _Drawing(
            path=state.path.positions(), loops=np.array(state.loops).reshape(-1, 2, 3),
            trajectory=state.path.trajectory() if with_trajectory and self.ground_truth is not None else None,
            image=state.image, points_2d=state.points_2d, matches_2d=state.matches_2d,
            matches_inlier=state.matches_inlier, T_world_cam=state.T_world_cam,
            thumbnails=dict(state.thumbnails), keyframe_poses=dict(state.keyframe_poses),
            direct_points=state.direct_points, direct_colors=state.direct_colors,
            feature_points=state.feature_points,
            markers={kind: state.markers.stacked(kind, self._scale.marker) for kind in state.markers.positions},
            divergence=list(state.divergence), status=self._status_text(state), events=list(state.events),
        )

    def _status_text(self, state: _LiveState) -> str:
        if state.processed == 0:
            return "waiting for the first frame"
        condition = "tracking" if state.tracked else "lost" if len(state.path) else "initializing"
        if getattr(self.player, "finished", False):
            condition += ", sequence finished"
        elif self.player.paused:
            condition += ", paused"
        return (
            f"**{condition}** at frame {state.frame_index}, {self._rate.fps():.1f} fps\n\n"
            f"{_divergence_text(state.divergence_ratio, state.divergence_threshold)}\n\n"
            f"| processed | tracked | keyframes | dropped | jumps |\n|---|---|---|---|---|\n"
            f"| {state.processed} | {state.tracked_count} | {state.keyframes} | {state.dropped} | {state.jumps} |"
        )

    def _draw_frame(self, drawing: _Drawing) -> None:
        scene = self.server.scene
        self.status.content = drawing.status
        self.event_log.content = _event_markdown(drawing.events)
        self._show_play_state()
        if drawing.image is not None:
            self.image.image = _overlay(drawing.image, drawing.points_2d, drawing.matches_2d, drawing.matches_inlier)
        self._draw_plot(drawing.divergence)
        if len(drawing.path) >= 2:
            self._add("trajectory", "/trajectory", scene.add_line_segments, points=_segments(drawing.path),
                      colors=ESTIMATE_COLOR, thickness=LINE_THICKNESS_PX, thickness_units="screen")
        if len(drawing.loops):
            self._add("loops", "/loops", scene.add_line_segments, points=drawing.loops, colors=LOOP_COLOR,
                      thickness=LINE_THICKNESS_PX, thickness_units="screen")
        if drawing.T_world_cam is not None:
            camera = self._node("/camera")
            if camera is None:
                camera = self._add("camera", "/camera", scene.add_camera_frustum, **self._frustum(),
                                   color=CURRENT_CAMERA_COLOR, thickness=LINE_THICKNESS_PX, thickness_units="screen")
            camera.wxyz, camera.position = _wxyz_position(drawing.T_world_cam)
        for kind, positions in drawing.markers.items():
            if self._marker_count(kind) != len(positions):
                self._add("events", f"/events/{kind.value}", scene.add_point_cloud,
                          points=positions.astype(np.float32), colors=kind_style(kind).color,
                          point_size=self._scale.marker, point_shape="circle", precision=POINT_PRECISION)

    def _draw_plot(self, rows: list[tuple]) -> None:
        columns, _ = _plot_columns(rows if len(rows) >= len(PLOT_PLACEHOLDER) else PLOT_PLACEHOLDER)
        values = np.concatenate(columns[1:3])
        largest = np.max(values[np.isfinite(values)], initial=0.0)
        top = max(PLOT_MIN_TOP, PLOT_TOP_STEP * np.ceil(largest / PLOT_TOP_STEP + 0.01))
        if top != self._plot_top:
            self._plot_top = top
            self.divergence_plot.scales = _plot_scales(top)
        self.divergence_plot.data = columns

    def _marker_count(self, kind: EventKind) -> int:
        node = self._node(f"/events/{kind.value}")
        return 0 if node is None else len(node.points)

    def _draw_map(self, drawing: _Drawing) -> None:
        scene = self.server.scene
        self._fit_scene(drawing)
        if drawing.direct_points is not None:
            self._add("direct cloud", "/map/direct", scene.add_point_cloud,
                      points=drawing.direct_points.astype(np.float32), colors=drawing.direct_colors,
                      point_size=self._scale.point, point_shape="circle", precision=POINT_PRECISION)
        if drawing.feature_points is not None:
            self._add("feature cloud", "/map/features", scene.add_point_cloud,
                      points=drawing.feature_points.astype(np.float32), colors=FEATURE_POINT_COLOR,
                      point_size=self._scale.point, point_shape="diamond", precision=POINT_PRECISION)
        for index, T_world_cam in drawing.keyframe_poses.items():
            frustum = self._node(f"/keyframes/{index}")
            if frustum is None:
                frustum = self._add("keyframes", f"/keyframes/{index}", scene.add_camera_frustum,
                                    **self._frustum(), color=KEYFRAME_COLOR,
                                    image=drawing.thumbnails.get(index), thickness=1.5, thickness_units="screen")
            frustum.wxyz, frustum.position = _wxyz_position(T_world_cam)
        if drawing.trajectory is not None:
            aligned = self.ground_truth.positions_in_estimate_frame(drawing.trajectory)
            if aligned is not None and len(aligned) >= 2:
                self._add("ground truth", "/ground_truth", scene.add_line_segments, points=_segments(aligned),
                          colors=GROUND_TRUTH_COLOR, thickness=LINE_THICKNESS_PX, thickness_units="screen")

    def _fit_scene(self, drawing: _Drawing) -> None:
        """Follow the scene's size (frustums, markers) and, when it grew, shrank or moved, the view of the clients
        that follow it and of those that connect next."""
        view = framing(drawing.path, drawing.direct_points, drawing.feature_points)
        if view is None:
            return
        if self._scale.follow(view):
            for layer, handle in self._nodes.values():
                if layer in ("keyframes", "camera"):
                    handle.scale = self._scale.frustum
                elif layer == "events":
                    handle.point_size = self._scale.marker
        moved = np.linalg.norm(view.centre - self._view.centre) > RECENTRE_FRACTION * self._view.size
        if not self._view_fitted or moved or resized(view.size, self._view.size):
            self._view, self._view_fitted = view, True
            self._frame_view(view)
            if self.follow.value:
                self._fit_clients(view)

    def _frame_view(self, view: Framing) -> None:
        """Where clients that connect from now on start looking from."""
        self.server.initial_camera.look_at = view.centre
        self.server.initial_camera.position = view.eye

    def _fit_clients(self, view: Framing) -> None:
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.look_at = view.centre
                client.camera.position = view.eye

    def _frustum(self) -> dict[str, float]:
        fov_y = 2.0 * np.arctan2(self.camera.height / 2.0, self.camera.fy)
        return {"fov": float(fov_y), "aspect": self.camera.width / self.camera.height, "scale": self._scale.frustum}

    def _add(self, layer: str, name: str, add_node, **properties) -> Any:
        """Create (or replace) a scene node of a layer, shown or hidden as the layer's checkbox says."""
        handle = add_node(name, visible=self.layers[layer].value, **properties)
        self._nodes[name] = (layer, handle)
        return handle

    def _node(self, name: str) -> Any:
        return self._nodes[name][1] if name in self._nodes else None

    def _show_layer(self, layer: str) -> None:
        visible = self.layers[layer].value
        with self._scene_lock:
            for node_layer, handle in self._nodes.values():
                if node_layer == layer:
                    handle.visible = visible

    def _clear_scene(self) -> None:
        for _, handle in self._nodes.values():
            handle.remove()
        self._nodes.clear()
        self._view_fitted = False


def _divergence_text(ratio: float | None, threshold: float | None) -> str:
    """The divergence test of the last frame: its ratio against the threshold."""
    if ratio is None or threshold is None:
        return "divergence ratio: none"
    verdict = "**above**" if ratio > threshold else "below"
    return f"divergence ratio {ratio:.3f}, {verdict} the threshold {threshold:.3f}"


def _plot_columns(rows: list[tuple]) -> tuple[tuple[np.ndarray, ...], tuple[uplot.Series, ...]]:
    """The divergence plot's data and series: the ratio and its threshold over the frames processed, and a series of
    points per lane (scene.PLOT_LANES) at the frames of its events (NaN elsewhere: nothing drawn)."""
    steps = np.array([row[0] for row in rows], dtype=float)
    ratio = np.array([np.nan if row[1] is None else row[1] for row in rows], dtype=float)
    threshold = np.array([np.nan if row[2] is None else row[2] for row in rows], dtype=float)
    markers = [np.array([lane.height if row[3] & set(lane.kinds) else np.nan for row in rows], dtype=float)
               for lane in PLOT_LANES]
    series = (
        uplot.Series(label="frames processed"),
        uplot.Series(label="ratio", stroke=_css(DIVERGENCE_RATIO_COLOR), width=2, points=uplot.Series_Points(show=False)),
        uplot.Series(label="threshold", stroke=_css(DIVERGENCE_THRESHOLD_COLOR), width=1, dash=(6, 4),
                     points=uplot.Series_Points(show=False)),
        *(uplot.Series(label=lane.name.replace("_", " "), stroke=_css(lane.color), width=0,
                       points=uplot.Series_Points(show=True, size=9, fill=_css(lane.color)))
          for lane in PLOT_LANES),
    )
    return (steps, ratio, threshold, *markers), series


def _plot_scales(top: float) -> dict[str, uplot.Scale]:
    return {"x": uplot.Scale(time=False, auto=True), "y": uplot.Scale(range=(0.0, top))}


def _css(color: tuple[int, int, int]) -> str:
    return "rgb({}, {}, {})".format(*color)


def _segments(positions: np.ndarray) -> np.ndarray:
    """(N-1, 2, 3) float32 line segments joining consecutive positions (viser draws segments, not strips)."""
    return np.stack([positions[:-1], positions[1:]], axis=1).astype(np.float32)


def _wxyz_position(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return vtf.SO3.from_matrix(T_world_cam[:3, :3]).wxyz, T_world_cam[:3, 3].copy()


def _rgb(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image


def _thumbnail(image: np.ndarray) -> np.ndarray:
    height = max(1, round(image.shape[0] * THUMBNAIL_WIDTH / image.shape[1]))
    return _rgb(cv2.resize(image, (THUMBNAIL_WIDTH, height), interpolation=cv2.INTER_AREA))


def _overlay(image: np.ndarray, points_2d: np.ndarray | None, matches_2d: np.ndarray | None,
             matches_inlier: np.ndarray | None) -> np.ndarray:
    """The image in RGB with the feature matches as lines (inliers and outliers in their colors) and the tracked
    pixels as 3x3 dots over them (painted in one vectorized write)."""
    rgb = _rgb(image).copy()
    if matches_2d is not None and len(matches_2d):
        segments = np.round(np.asarray(matches_2d, dtype=float).reshape(-1, 2, 2)).astype(np.int32)
        colors = match_colors(len(segments), matches_inlier)
        for color in np.unique(colors, axis=0):
            same = np.all(colors == color, axis=1)
            cv2.polylines(rgb, list(segments[same]), isClosed=False, color=color.tolist(), thickness=1)
    if points_2d is None or len(points_2d) == 0:
        return rgb
    height, width = rgb.shape[:2]
    pixels = np.round(np.asarray(points_2d, dtype=float).reshape(-1, 2)).astype(int)
    offsets = np.array([(du, dv) for du in (-1, 0, 1) for dv in (-1, 0, 1)])
    dots = (pixels[:, None, :] + offsets[None]).reshape(-1, 2)
    inside = (dots[:, 0] >= 0) & (dots[:, 0] < width) & (dots[:, 1] >= 0) & (dots[:, 1] < height)
    rgb[dots[inside, 1], dots[inside, 0]] = OVERLAY_POINT_COLOR
    return rgb


def _event_markdown(events: list[Event]) -> str:
    if not events:
        return "no events yet"
    return "\n".join(f"- {event_style(event).level}: {event_text(event)}" for event in events)
