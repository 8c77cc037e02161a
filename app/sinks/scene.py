"""What both viewers show, worked out once and independently of either viewer library.

The Rerun sink and the viser page draw the same things: the estimated path, the ground truth aligned to it,
the direct cloud colored by inverse depth, events styled by how serious they are. This module holds those
shared pieces, in the estimate's world frame (the odometry's, in its own monocular scale), so the two
viewers never disagree about where something is or what color it has.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.errors import InputError
from vo_core.eval import associate, fit_alignment
from vo_core.eval.associate import DEFAULT_MAX_DT_S
from vo_core.events import Event, EventKind
from vo_core.geometry.lie import sim3_inverse, transform_points
from vo_core.trajectory import Trajectory

MIN_POSES_TO_ALIGN = 3  # Umeyama's Sim(3) needs three non-collinear positions

# Colors (RGB) of the layers, the same in both viewers.
ESTIMATE_COLOR = (230, 80, 40)
GROUND_TRUTH_COLOR = (40, 170, 90)
FEATURE_POINT_COLOR = (250, 170, 20)
KEYFRAME_COLOR = (70, 110, 230)
CURRENT_CAMERA_COLOR = (230, 40, 40)
OVERLAY_POINT_COLOR = (60, 230, 60)
MATCH_COLOR = (250, 170, 20)  # feature matches, in the feature map's color

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
    EventKind.TRACKING_OK: _ROUTINE,
    EventKind.TRACKING_FAILED: EventStyle("ERROR", (230, 30, 30)),
    EventKind.DIVERGENCE_DETECTED: EventStyle("WARN", (255, 120, 0)),
    EventKind.TRACKING_CHECKED: EventStyle("DEBUG", (180, 200, 120)),
    EventKind.RECOVERY_TRIED: EventStyle("INFO", (240, 220, 40)),
    EventKind.RECOVERY_SUCCEEDED: EventStyle("INFO", (0, 210, 210)),
    EventKind.RECOVERY_FAILED: EventStyle("ERROR", (200, 0, 60)),
    EventKind.DIRECT_RESTARTED: EventStyle("WARN", (0, 150, 255)),
    EventKind.FEATURE_TRACKING: EventStyle("INFO", (250, 170, 20)),
    EventKind.REINITIALIZATION: EventStyle("WARN", (220, 60, 220)),
    EventKind.KEYFRAME_ADDED: _ROUTINE,
    EventKind.FEATURE_KEYFRAME_ADDED: _ROUTINE,
    EventKind.FEATURE_KEYFRAME_CULLED: _ROUTINE,
    EventKind.KEYFRAME_MARGINALIZED: _ROUTINE,
    EventKind.MAP_POINTS_CULLED: _ROUTINE,
    EventKind.WINDOW_OPTIMIZED: _ROUTINE,
    EventKind.FRAME_SKIPPED: EventStyle("WARN", (160, 160, 160)),
    EventKind.FRAME_REPEATED: EventStyle("WARN", (160, 160, 160)),
    EventKind.FRAMES_DROPPED: EventStyle("INFO", (90, 90, 255)),
}
_UNLISTED = EventStyle("INFO", (120, 120, 120))


def event_style(event: Event) -> EventStyle:
    """The style of an event's kind; a kind added to the core later is shown plainly rather than refused."""
    return EVENT_STYLES.get(event.kind, _UNLISTED)


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


# The scene's extent is the diagonal of the box holding the path and the clouds between these percentiles (stray
# far points ignored), never below MIN_SCENE_SIZE; a viewer looks at its centre from VIEW_OFFSET x extent.
SCENE_PERCENTILES = (10.0, 50.0, 90.0)
MIN_SCENE_SIZE = 1.0
VIEW_OFFSET = np.array([0.0, -0.5, -1.0])  # behind and above (the world's y points down)


@dataclass(frozen=True)
class Framing:
    centre: np.ndarray
    size: float

    @property
    def eye(self) -> np.ndarray:
        return self.centre + VIEW_OFFSET * self.size


def framing(*point_sets: np.ndarray | None) -> Framing | None:
    """Where to look to see the path and the clouds: their robust centre and extent; None without points."""
    parts = [np.asarray(points).reshape(-1, 3) for points in point_sets if points is not None and len(points)]
    if not parts:
        return None
    low, centre, high = np.percentile(np.concatenate(parts), SCENE_PERCENTILES, axis=0)
    return Framing(centre, max(float(np.linalg.norm(high - low)), MIN_SCENE_SIZE))


class PathHistory:
    """The poses estimated so far, in the order they came (timestamps increase along a pass). The positions are
    kept in a buffer that doubles when full, so that reading them costs a copy, not a loop over the poses."""

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

    def positions(self, start: int = 0) -> np.ndarray:
        """(N - start, 3) camera centres, from pose ``start`` on (a copy)."""
        return self._positions[start:len(self.poses)].copy()

    def trajectory(self) -> Trajectory:
        return Trajectory(np.array(self.timestamps), np.array(self.poses).reshape(-1, 4, 4))

    def extent(self) -> float:
        """The diagonal of the positions' bounding box: the size of the scene so far, in its own units."""
        positions = self.positions()
        return float(np.linalg.norm(np.ptp(positions, axis=0))) if len(positions) else 0.0


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
