"""What both viewers show, worked out once and independently of either viewer library.

The Rerun sink and the viser page draw the same things: the estimated path, the ground truth aligned to it,
the direct cloud colored by inverse depth and the feature cloud in a colour of its own, the matches of a
recovery or a feature keyframe (inliers and outliers), events styled by how serious they are and marked where
they happened, and a default view of the path and the dense part of the map. This module holds those shared
pieces, in the estimate's world frame (the odometry's, in its own monocular scale), so the two viewers never
disagree about where something is, how big it is drawn or what color it has.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from vo_core.errors import InputError
from vo_core.eval import associate, fit_alignment
from vo_core.eval.associate import DEFAULT_MAX_DT_S
from vo_core.events import Event, EventKind
from vo_core.geometry.lie import sim3_inverse, transform_points
from vo_core.trajectory import Trajectory, loop_corrected

MIN_POSES_TO_ALIGN = 3  # Umeyama's Sim(3) needs three non-collinear positions

# Colors (RGB) of the layers, the same in both viewers.
ESTIMATE_COLOR = (230, 80, 40)
GROUND_TRUTH_COLOR = (40, 170, 90)
FEATURE_POINT_COLOR = (170, 40, 255)  # violet: a hue the direct cloud's turbo colormap never takes
KEYFRAME_COLOR = (70, 110, 230)
CURRENT_CAMERA_COLOR = (230, 40, 40)
OVERLAY_POINT_COLOR = (60, 230, 60)
MATCH_INLIER_COLOR = FEATURE_POINT_COLOR  # feature matches the pose accepted, in the feature map's color
MATCH_OUTLIER_COLOR = (255, 40, 40)
LOOP_COLOR = (255, 215, 0)  # a closed loop's line between its two keyframes, and its events
DIVERGENCE_RATIO_COLOR = ESTIMATE_COLOR
DIVERGENCE_THRESHOLD_COLOR = (120, 120, 120)

# The inverse depths between these percentiles span the colormap; outliers take its end colors, so one
# point very close to the camera does not wash the rest of the cloud into a single color.
INVERSE_DEPTH_PERCENTILES = (2.0, 98.0)
# OpenCV's turbo colormap as a 256-entry RGB table, looked up by index (applyColorMap rebuilds it every call).
_TURBO_RGB = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_TURBO)[:, 0, ::-1].copy()


@dataclass(frozen=True)
class EventStyle:
    """How an event is shown: its log level (Rerun's TextLog levels), its color, and whether it is marked on
    the trajectory (routine bookkeeping such as a new keyframe is logged but not marked)."""

    level: str
    color: tuple[int, int, int]
    marked: bool = True


_ROUTINE = EventStyle("DEBUG", (150, 150, 150), marked=False)
EVENT_STYLES: dict[EventKind, EventStyle] = {
    EventKind.INITIALIZATION_STARTED: EventStyle("INFO", (120, 200, 255)),
    EventKind.INITIALIZATION_SUCCEEDED: EventStyle("INFO", (40, 200, 80)),
    EventKind.INITIALIZATION_FAILED: EventStyle("WARN", (255, 160, 0)),
    EventKind.INITIALIZER_MODEL: _ROUTINE,
    EventKind.INITIALIZATION_REJECTED: EventStyle("WARN", (255, 80, 160)),
    EventKind.TRACKING_OK: _ROUTINE,
    EventKind.TRACKING_FAILED: EventStyle("ERROR", (230, 30, 30)),
    EventKind.DIVERGENCE_DETECTED: EventStyle("WARN", (255, 120, 0)),
    EventKind.TRACKING_CHECKED: EventStyle("DEBUG", (180, 200, 120), marked=False),  # a suspicion dispelled
    EventKind.TRACKING_UNVERIFIED: EventStyle("WARN", (255, 170, 60)),  # a suspicion neither dispelled nor confirmed
    EventKind.RECOVERY_TRIED: EventStyle("INFO", (240, 220, 40)),
    EventKind.RECOVERY_SUCCEEDED: EventStyle("INFO", (0, 210, 210)),
    EventKind.RECOVERY_FAILED: EventStyle("ERROR", (200, 0, 60)),
    EventKind.DIRECT_RESUMED: EventStyle("INFO", (0, 200, 140)),
    EventKind.DIRECT_RESTARTED: EventStyle("WARN", (0, 150, 255)),
    EventKind.FEATURE_TRACKING: EventStyle("INFO", FEATURE_POINT_COLOR),
    EventKind.REINITIALIZATION: EventStyle("WARN", (220, 60, 220)),
    EventKind.REINITIALIZATION_ABANDONED: EventStyle("INFO", (120, 220, 120)),
    EventKind.KEYFRAME_ADDED: _ROUTINE,
    EventKind.FEATURE_KEYFRAME_ADDED: _ROUTINE,
    EventKind.KEYFRAME_OVERRULED: EventStyle("WARN", (255, 100, 40)),  # the direct map drifted from the feature map
    EventKind.FEATURE_KEYFRAME_CULLED: _ROUTINE,
    EventKind.KEYFRAME_MARGINALIZED: _ROUTINE,
    EventKind.LOOP_CANDIDATE: EventStyle("DEBUG", (200, 190, 120), marked=False),  # most are refused, as they should
    EventKind.LOOP_CLOSED: EventStyle("INFO", LOOP_COLOR),
    EventKind.MAPS_MERGED: EventStyle("INFO", LOOP_COLOR),
    EventKind.SCALE_JUMP: EventStyle("WARN", (255, 200, 0)),
    EventKind.MAP_POINTS_CULLED: _ROUTINE,
    EventKind.WINDOW_OPTIMIZED: _ROUTINE,
    EventKind.MAPPING_BEHIND: EventStyle("WARN", (200, 140, 90), marked=False),  # frames left untraced, not a failure
    EventKind.FRAME_SKIPPED: EventStyle("WARN", (160, 160, 160)),
    EventKind.FRAME_REPEATED: EventStyle("WARN", (160, 160, 160)),
    EventKind.FRAMES_DROPPED: EventStyle("INFO", (90, 90, 255)),
    EventKind.FRAMES_JUMPED: EventStyle("INFO", (40, 40, 160)),
}
_UNLISTED = EventStyle("INFO", (120, 120, 120))


def event_style(event: Event) -> EventStyle:
    return kind_style(event.kind)


def kind_style(kind: EventKind) -> EventStyle:
    """The style of an event kind; a kind added to the core later is shown plainly rather than refused."""
    return EVENT_STYLES.get(kind, _UNLISTED)


@dataclass(frozen=True)
class PlotLane:
    """A row of markers on the divergence plot for events of ``kinds``, at ``height``: below the ratio (which sits
    near 1), so that it says when they happened and they never hide one another; colored as its first kind."""

    name: str
    kinds: tuple[EventKind, ...]
    height: float

    @property
    def color(self) -> tuple[int, int, int]:
        return kind_style(self.kinds[0]).color


PLOT_LANES = (
    PlotLane("divergence", (EventKind.DIVERGENCE_DETECTED, EventKind.TRACKING_FAILED, EventKind.KEYFRAME_OVERRULED),
             0.4),
    PlotLane("recovery", (EventKind.RECOVERY_SUCCEEDED,), 0.3),
    PlotLane("recovery_failed", (EventKind.RECOVERY_FAILED, EventKind.REINITIALIZATION), 0.2),
    PlotLane("drop_or_jump", (EventKind.FRAMES_DROPPED, EventKind.FRAMES_JUMPED), 0.1),
)


def event_text(event: Event) -> str:
    """One line for a log: ``frame 12 divergence_detected (ratio=1.31)``. Details too long for a line (poses,
    matrices) are left to events.jsonl."""
    shown = {key: _short(value) for key, value in event.details.items()}
    details = ", ".join(f"{key}={text}" for key, text in shown.items() if text is not None)
    return f"frame {event.frame_index} {event.kind.value}" + (f" ({details})" if details else "")


MAX_LISTED_VALUES = 3


def _short(value) -> str | None:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        if len(value) > MAX_LISTED_VALUES or not all(isinstance(item, (int, float)) for item in value):
            return None
        return "[" + ", ".join(_short(item) for item in value) + "]"
    return str(value)


def inverse_depth_colors(inverse_depths: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB: the turbo colormap over the inverse depths, near points red, far points blue."""
    inverse_depths = np.asarray(inverse_depths, dtype=np.float64).reshape(-1)
    if len(inverse_depths) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    low, high = np.percentile(inverse_depths, INVERSE_DEPTH_PERCENTILES)
    normalized = (inverse_depths - low) / max(high - low, 1e-12)
    return _TURBO_RGB[np.round(255.0 * np.clip(normalized, 0.0, 1.0)).astype(np.intp)]


def match_colors(count: int, inlier: np.ndarray | None) -> np.ndarray:
    """(count, 3) uint8 RGB of feature matches: inliers in the feature map's color, outliers red (``inlier`` None:
    every match is an inlier, as the new matches of a feature keyframe)."""
    colors = np.tile(np.uint8(MATCH_INLIER_COLOR), (count, 1))
    if inlier is not None:
        colors[~np.asarray(inlier, dtype=bool)] = MATCH_OUTLIER_COLOR
    return colors


# The default view holds the path and the map points near it: a cloud point farther from the path than
# NEAR_PATH_FACTOR x the median distance of the cloud to the path is ignored (a few points triangulated far away
# would otherwise shrink the scene to a dot), and of what remains the box between CLOUD_PERCENTILES is framed
# with the path's box between PATH_PERCENTILES (a pose or two thrown far by a divergence left out).
NEAR_PATH_FACTOR = 3.0
CLOUD_PERCENTILES = (2.0, 98.0)
PATH_PERCENTILES = (1.0, 99.0)
MAX_FRAMING_POINTS = 5000  # a regular subsample of larger clouds: the bounds do not need every point
MIN_SCENE_SIZE = 1.0
VIEW_OFFSET = np.array([0.0, -0.5, -1.0])  # behind and above (the world's y points down)


@dataclass(frozen=True)
class Framing:
    """A box to look at: its centre and its diagonal."""

    centre: np.ndarray
    size: float

    @property
    def eye(self) -> np.ndarray:
        """Where a viewer looks from: behind and above the centre, far enough to see the whole box."""
        return self.centre + VIEW_OFFSET * self.size


def framing(path: np.ndarray | None, *clouds: np.ndarray | None) -> Framing | None:
    """The default view of the path and the dense part of the clouds around it; None without points."""
    path = _finite(path)
    cloud = _finite(*clouds)
    if len(cloud) > MAX_FRAMING_POINTS:
        cloud = cloud[:: len(cloud) // MAX_FRAMING_POINTS + 1]
    if len(path) and len(cloud):
        distances, _ = cKDTree(path).query(cloud)
        cloud = cloud[distances <= NEAR_PATH_FACTOR * max(float(np.median(distances)), 1e-9)]
    boxes = [np.percentile(points, percentiles, axis=0) for points, percentiles in
             ((path, PATH_PERCENTILES), (cloud, CLOUD_PERCENTILES)) if len(points)]
    if not boxes:
        return None
    low, high = np.min([box[0] for box in boxes], axis=0), np.max([box[1] for box in boxes], axis=0)
    return Framing((low + high) / 2.0, max(float(np.linalg.norm(high - low)), MIN_SCENE_SIZE))


def _finite(*point_sets: np.ndarray | None) -> np.ndarray:
    parts = [np.asarray(points, dtype=float).reshape(-1, 3) for points in point_sets if points is not None]
    points = np.concatenate(parts) if parts else np.zeros((0, 3))
    return points[np.all(np.isfinite(points), axis=1)]


# Things are drawn at fractions of the scene's extent (monocular scale is arbitrary), resized only when the extent
# changed by RESIZE_FACTOR (a resize at every keyframe would make the scene flicker).
FRUSTUM_FRACTION = 0.03
POINT_FRACTION = 0.003
MARKER_FRACTION = 0.012
RESIZE_FACTOR = 1.5


def resized(size: float, reference: float) -> bool:
    """Whether a scene of ``size`` is drawn differently from one of ``reference``: RESIZE_FACTOR apart."""
    return not 1.0 / RESIZE_FACTOR < size / reference < RESIZE_FACTOR


class SceneScale:
    """The sizes of frustums, points and event markers, following the scene's extent."""

    def __init__(self) -> None:
        self.size = MIN_SCENE_SIZE

    def follow(self, view: Framing | None) -> bool:
        """Take ``view``'s extent if it differs enough from the one drawn; True when the sizes changed."""
        if view is None or not resized(view.size, self.size):
            return False
        self.size = view.size
        return True

    @property
    def frustum(self) -> float:
        return FRUSTUM_FRACTION * self.size

    @property
    def point(self) -> float:
        return POINT_FRACTION * self.size

    @property
    def marker(self) -> float:
        return MARKER_FRACTION * self.size


UP = np.array([0.0, -1.0, 0.0])  # in the world of the first camera (y down)
MARKER_STACK_SPACING = 3.5  # marker sizes between the markers of the kinds that happened at one pose


class EventMarkers:
    """Where the marked events (``EventStyle.marked``) happened, by kind. An event comes before its frame's result,
    so it is placed at the pose of the next frame tracked, or at the last pose known when that frame got none.
    The kinds placed at one pose (a divergence, its recovery, a restart) are stacked upwards from it in the order
    they came, so that neither their markers nor Rerun's labels hide one another."""

    def __init__(self) -> None:
        self.positions: dict[EventKind, list[np.ndarray]] = defaultdict(list)
        self._ranks: dict[EventKind, list[int]] = defaultdict(list)  # each position's place in its stack
        self._pending: list[Event] = []

    def add(self, event: Event) -> None:
        if event_style(event).marked:
            self._pending.append(event)

    def place(self, position: np.ndarray | None) -> list[Event]:
        """Place the events waiting for a pose at ``position`` (None: no pose yet, they keep waiting); returns them."""
        if position is None or not self._pending:
            return []
        placed, self._pending = self._pending, []
        stack = list(dict.fromkeys(event.kind for event in placed))
        for event in placed:
            self.positions[event.kind].append(np.asarray(position, dtype=float))
            self._ranks[event.kind].append(stack.index(event.kind))
        return placed

    def stacked(self, kind: EventKind, marker_size: float) -> np.ndarray:
        """(N, 3) where the markers of ``kind`` are drawn: its positions, lifted to their places in their stacks."""
        lift = MARKER_STACK_SPACING * marker_size * np.outer(self._ranks[kind], UP)
        return np.array(self.positions[kind]).reshape(-1, 3) + lift


class PathHistory:
    """The poses estimated so far, in the order they came (timestamps go back after a backward jump). The positions
    are kept in a buffer that doubles when full, so that reading them costs a copy, not a loop over the poses."""

    def __init__(self) -> None:
        self.timestamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self._positions = np.empty((64, 3))

    def __len__(self) -> int:
        return len(self.poses)

    def add(self, timestamp: float, T_world_cam: np.ndarray) -> None:
        if len(self.poses) == len(self._positions):
            self._positions = np.concatenate([self._positions, np.empty_like(self._positions)])
        self._positions[len(self.poses)] = T_world_cam[:3, 3]
        self.timestamps.append(float(timestamp))
        self.poses.append(np.asarray(T_world_cam, dtype=float))

    def correct(self, correction: dict) -> None:
        """Every pose as a closed loop moved it (``correction``: the LOOP_CLOSED event's details)."""
        if self.poses:
            self.poses = list(loop_corrected(correction, np.array(self.timestamps), np.array(self.poses)))
            self._positions[:len(self.poses)] = [T[:3, 3] for T in self.poses]

    def positions(self, start: int = 0) -> np.ndarray:
        """(N - start, 3) camera centres, from pose ``start`` on (a copy)."""
        return self._positions[start:len(self.poses)].copy()

    def last_position(self) -> np.ndarray | None:
        return self._positions[len(self.poses) - 1].copy() if self.poses else None

    def trajectory(self) -> Trajectory:
        """The latest pose of each timestamp, in time order (a frame played again after a backward jump counts
        once, with its new pose): what the ground truth is aligned to."""
        times = np.array(self.timestamps)
        _, last_from_the_end = np.unique(times[::-1], return_index=True)  # sorted by time
        latest = len(times) - 1 - last_from_the_end
        return Trajectory(times[latest], np.array(self.poses).reshape(-1, 4, 4)[latest])


class GroundTruthOverlay:
    """The ground truth brought into the estimate's frame: the inverse of the Sim(3) Umeyama alignment of the
    poses matched so far (the same association and alignment as ``fdmo eval``), refitted on request."""

    def __init__(self, ground_truth: Trajectory, max_dt: float = DEFAULT_MAX_DT_S):
        self.ground_truth = ground_truth
        self.max_dt = max_dt

    def positions_in_estimate_frame(self, estimate: Trajectory) -> np.ndarray | None:
        """(M, 3) ground-truth positions matched to ``estimate`` so far, mapped by S_est_gt = S_gt_est^-1;
        None while no alignment can be fitted (too few matches, or an estimate that has not moved)."""
        if len(estimate) < MIN_POSES_TO_ALIGN:
            return None
        try:
            matched_estimate, matched_truth = associate(estimate, self.ground_truth, self.max_dt)
            if len(matched_estimate) < MIN_POSES_TO_ALIGN:
                return None
            alignment = fit_alignment(matched_estimate, matched_truth, "sim3")
        except InputError:
            return None
        return transform_points(sim3_inverse(alignment.transform), matched_truth.positions)
