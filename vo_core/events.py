"""What the odometry tells the outside world: per-frame results, typed events and the Sink protocol.

The core never imports a viewer. It is handed sinks (objects with the methods of ``Sink``) and calls them,
the way DSO calls its Output3DWrapper. Every pose here is ``T_world_cam`` (camera-to-world, 4x4), every
timestamp is in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Protocol, runtime_checkable

import numpy as np


class EventKind(str, Enum):
    """Every kind of event the system can emit; the string value is what events.jsonl stores."""

    INITIALIZATION_STARTED = "initialization_started"
    INITIALIZATION_SUCCEEDED = "initialization_succeeded"
    INITIALIZATION_FAILED = "initialization_failed"
    INITIALIZER_MODEL = "initializer_model"  # H or F chosen, with scores
    # a start failed its check after the hand-over: discarded, its poses retracted
    INITIALIZATION_REJECTED = "initialization_rejected"
    TRACKING_OK = "tracking_ok"
    TRACKING_FAILED = "tracking_failed"
    DIVERGENCE_DETECTED = "divergence_detected"  # FDMO 4.2.1: RMSE_after / RMSE_before > 1 + eps, or confirmed
    TRACKING_CHECKED = "tracking_checked"  # a suspect direct pose that the feature map confirmed
    TRACKING_UNVERIFIED = "tracking_unverified"  # a suspect direct pose kept: the feature map too weak to overrule it
    RECOVERY_TRIED = "recovery_tried"  # FDMO 4.2.2 started: the candidates it will try
    RECOVERY_SUCCEEDED = "recovery_succeeded"
    RECOVERY_FAILED = "recovery_failed"
    DIRECT_RESUMED = "direct_resumed"  # direct tracking goes on in the same window from a recovered pose
    DIRECT_RESTARTED = "direct_restarted"  # the direct map starts over at a recovered pose, same scale
    FEATURE_TRACKING = "feature_tracking"  # a frame posed by the feature map while direct tracking is not back
    REINITIALIZATION = "reinitialization"  # the last resort: a new map at a new scale (it begins to initialize)
    REINITIALIZATION_ABANDONED = "reinitialization_abandoned"  # the old map came back first: it goes on, same scale
    KEYFRAME_ADDED = "keyframe_added"
    FEATURE_KEYFRAME_ADDED = "feature_keyframe_added"  # FDMO 4.3: the feature map grew at a direct keyframe
    FEATURE_KEYFRAME_CULLED = "feature_keyframe_culled"  # FDMO 4.4: redundant, its direct twin marginalized
    KEYFRAME_MARGINALIZED = "keyframe_marginalized"
    LOOP_CANDIDATE = "loop_candidate"  # a place the bag of words recognised, taken or refused and why
    LOOP_CLOSED = "loop_closed"  # a loop corrected the map: each keyframe's correction moves the poses before it
    MAPS_MERGED = "maps_merged"  # an older map (started before a loss) joined the active one: one frame and scale
    KEYFRAME_OVERRULED = "keyframe_overruled"  # a new direct keyframe does not join the feature map (judge_keyframe)
    SCALE_JUMP = "scale_jump"  # the direct map's scale jumped or collapsed at a keyframe
    MAP_POINTS_CULLED = "map_points_culled"
    WINDOW_OPTIMIZED = "window_optimized"
    MAPPING_BEHIND = "mapping_behind"  # the mapping thread fell behind and left frames untraced to catch up
    FRAME_SKIPPED = "frame_skipped"  # unreadable image skipped by the loader
    FRAME_REPEATED = "frame_repeated"  # the same image as the frame before (a stalled camera): no pose
    FRAMES_DROPPED = "frames_dropped"  # by the player: on purpose (scripted or live), or late (source "realtime")
    FRAMES_JUMPED = "frames_jumped"  # the player went on from another frame, back or ahead (scripted or live)


# The events whose details move poses given earlier (vo_core.trajectory.loop_corrected): every sink that keeps poses
# applies them, in the order they come.
POSE_CORRECTIONS = (EventKind.LOOP_CLOSED, EventKind.MAPS_MERGED)


@dataclass(frozen=True)
class Event:
    """One thing that happened at one frame; ``details`` holds JSON-serializable values."""

    kind: EventKind
    frame_index: int
    timestamp: float
    details: dict[str, Any] = field(default_factory=dict)

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "frame": self.frame_index,
            "timestamp": self.timestamp,
            "kind": self.kind.value,
            "details": self.details,
        }


@dataclass
class FrameResult:
    """The outcome of tracking one frame.

    ``T_world_cam`` is None when the frame got no pose (before initialization, or a tracking failure).
    ``rmse_before``/``rmse_after`` are the photometric residuals of the direct alignment before and after
    optimization (FDMO's divergence test), None for methods without them.
    ``timings_ms`` maps a stage name to milliseconds spent on it for this frame.
    ``points_2d`` are the pixels the method tracked in this frame (selected direct points or features).
    ``matches_2d`` are feature matches drawn as lines: rows (u_from, v_from, u_to, v_to), from the pixel in the
    image they were matched to (a keyframe, the previous frame) to the pixel in this frame; ``matches_inlier``
    says which of them the pose accepted (None: all of them).
    ``divergence_ratio`` is RMSE_after / RMSE_before of the direct alignment the system judged (FDMO 4.2.1),
    with ``divergence_threshold`` 1 + epsilon.
    ``scale_ratio`` and ``mean_inverse_depth`` are set at direct keyframes (the direct map's scale watch): the new
    keyframe's speed (its translation from the previous keyframe over the time between them) over the median of the
    recent keyframes' speeds, and the mean inverse depth of the window's active points, in the map's own units.
    """

    frame_index: int
    timestamp: float
    T_world_cam: np.ndarray | None
    tracked: bool
    is_keyframe: bool = False
    rmse_before: float | None = None
    rmse_after: float | None = None
    num_inliers: int | None = None
    points_2d: np.ndarray | None = None
    matches_2d: np.ndarray | None = None  # (K, 4)
    matches_inlier: np.ndarray | None = None  # (K,) bool
    divergence_ratio: float | None = None
    divergence_threshold: float | None = None
    scale_ratio: float | None = None
    mean_inverse_depth: float | None = None
    # The direct keyframe the pose hangs on and the pose relative to it (DSO's trackingRef and camToTrackingRef):
    # a tracked frame's reference, a keyframe itself (identity). The trajectory's final poses are composed on that
    # keyframe's final pose; None where the pose came from elsewhere (the feature map, an initializer).
    reference_keyframe: int | None = None
    T_ref_cam: np.ndarray | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)


@dataclass
class MapSnapshot:
    """The maps as they stand, for viewers: world points with colors or inverse depths, keyframe poses."""

    direct_points_world: np.ndarray | None = None  # (N, 3)
    direct_inverse_depths: np.ndarray | None = None  # (N,)
    feature_points_world: np.ndarray | None = None  # (M, 3)
    keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)  # frame index -> T_world_cam
    feature_keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)  # the feature map's keyframes


@runtime_checkable
class Sink(Protocol):
    """What the app implements to receive the odometry's output. All methods are called on the tracking thread."""

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        """A frame was processed; ``frame`` is the datasets.Frame that was tracked."""

    def on_event(self, event: Event) -> None:
        """An event happened (also listed in the FrameResult of its frame, or with a mapping thread, of the frame
        the mapper worked on)."""

    def on_map(self, snapshot: MapSnapshot) -> None:
        """The maps changed (after a keyframe, a window optimization or a recovery)."""

    def close(self) -> None:
        """The run ended; flush and release."""


class EventBus:
    """Fans results and events out to the sinks the system was given."""

    def __init__(self, sinks: list[Sink] | None = None):
        self.sinks: list[Sink] = list(sinks or [])

    def event(self, event: Event) -> None:
        for sink in self.sinks:
            sink.on_event(event)

    def frame(self, frame: Any, result: FrameResult) -> None:
        for sink in self.sinks:
            sink.on_frame(frame, result)

    def map(self, snapshot: MapSnapshot) -> None:
        for sink in self.sinks:
            sink.on_map(snapshot)

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()
