"""``--method features``: ORB-SLAM2's tracking and local mapping as odometry, no loop closing (the feature-based
system FDMO is compared with, on the same inputs and with the same outputs).

Per frame:

    not initialized: ORB features into the two-frame start (features/orb_initializer.py); once it has a map, the
        map's two keyframes, and local mapping of the second
    a new map on probation (ours): once it has mapped ``probation_keyframes`` more keyframes, the start witness
        compares the epipolar geometry of its keyframes' ORB matches with their poses (vo_core/init/epipolar_check.py,
        the check of the direct odometry's starts); a start it contradicts is taken back (its poses retracted) and
        the start begins again from the frame
    tracking: motion model or reference keyframe, then the local map (features/feature_tracking.py); where tracking
        wants a keyframe, the frame becomes one and local mapping runs on it (features/local_mapping.py) before the next
        frame: ORB-SLAM2's two threads, one after the other. ORB-SLAM2 takes keyframes only while local mapping
        is idle; here, once the camera time its local mapping would have been busy has passed
    lost: no pose; while the map has at most 5 keyframes it starts over (ORB-SLAM2's reset), at the last pose
        and the old map's scene depth as unit, and the poses given in it are taken back (ORB-SLAM2's reset clears the
        trajectory with the map); otherwise every frame tries the global relocalization, and after 3 s without one
        a new map starts there in the same way (ORB-SLAM3)

The ORB extractor, the vocabulary, the feature map and its covisibility, the matchers, the pose-only
optimization, the relocalization and the triangulation are the ones FDMO's feature half uses (vo_core/features/);
this front end adds the state machine and the local mapping with free poses. Like the KLT baseline it is a pipeline
of its own: it returns results with their events and never talks to sinks (vo_core/system.py does).
"""

from __future__ import annotations

import dataclasses
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import Enum
from types import SimpleNamespace
from typing import Callable

import cv2
import numpy as np

from vo_core.geometry.motion_model import extrapolate
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot
from vo_core.features.config import FeatureConfig
from vo_core.features.feature_map import FeatureKeyframe, FeatureMap
from vo_core.features.feature_tracking import FeatureTracker, TrackedFrame, TrackingOutcome, local_mapping_idle
from vo_core.features.local_mapping import LocalMapper, LocalMappingReport
from vo_core.features.mapping import FeatureMapper
from vo_core.features.orb import OrbExtractor
from vo_core.features.orb_initializer import OrbInitializer, TwoFrameMap
from vo_core.features.recovery import FrameFeatures, Relocalizer
from vo_core.features.vocabulary import load_vocabulary
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points

# ORB-SLAM2 Track: a frame within 2 frames of a relocalization has no velocity yet (mnLastRelocFrameId + 2).
FRAMES_WITHOUT_VELOCITY_AFTER_RELOCALIZATION = 2


class State(Enum):
    NOT_INITIALIZED = "not_initialized"
    OK = "ok"
    LOST = "lost"


@dataclass
class YoungMap:
    """A map until it is established (its start proven by the witness, and as many keyframes as a map that is not
    reset when lost): its start's two frames and the frames posed in it, taken back where the start is refused or the
    map is lost while young."""

    first_frame: int
    second_frame: int
    posed_timestamps: list[float] = field(default_factory=list)


@dataclass
class StartProbation:
    """A new map until its start has proven itself: its keyframes' images in mapping order, for the witness."""

    witness: object  # an EpipolarCheck (vo_core/init): prepare, disagreement, close
    images: dict[int, np.ndarray] = field(default_factory=dict)  # keyframe frame index -> image

    def views(self, feature_map: FeatureMap) -> list:
        """The probation keyframes still in the map as the witness reads them: frame index, image, pose now."""
        return [SimpleNamespace(frame_index=index, image=image, T_world_cam=feature_map.keyframes[index].T_world_cam)
                for index, image in self.images.items() if index in feature_map.keyframes]


class FeatureOnlyOdometry:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, seed: int = 0,
                 start_witness: Callable[[], object | None] = lambda: None):
        self.config = config
        self.camera = camera
        self.seed = seed
        self.start_witness = start_witness  # a fresh witness for each new map's probation (None: none)
        self.probation: StartProbation | None = None
        self.young: YoungMap | None = None  # the map while its poses may still be taken back
        self.reference_image: np.ndarray | None = None  # the start's reference frame's image (the first keyframe's)
        vocabulary = load_vocabulary(config.vocabulary)
        self.vocabulary = vocabulary
        start_features = config.odometry.initialization.features_factor * config.orb.num_features
        self.start_extractor = OrbExtractor(dataclasses.replace(config.orb, num_features=start_features))
        self.relocalizer = Relocalizer(config, camera, vocabulary)
        self.tracker = FeatureTracker(config, camera, self.relocalizer)
        self.local_mapper = LocalMapper(config, camera, FeatureMapper(config, camera, vocabulary))
        self.initializer = OrbInitializer(config, camera, seed)
        self.map = FeatureMap()
        self.state = State.NOT_INITIALIZED
        self.last: TrackedFrame | None = None
        self.posed: list[tuple[float, np.ndarray]] = []  # the last two poses (timestamp, T_world_cam): velocity
        self.frames_processed = 0
        self.relocalized_at = -np.inf  # frames_processed at the last relocalization
        self.lost_at: float | None = None  # the timestamp of the frame tracking was lost at
        self.keyframed_at = -np.inf  # timestamp of the last keyframe
        # The camera's frame interval: the shortest seen between two frames (dropped frames only lengthen them).
        self.frame_period = np.inf
        self.previous_timestamp = None
        self.T_world_origin = np.eye(4)  # where the next map's first keyframe goes, and its scene depth
        self.origin_depth = 1.0
        self._events: list[Event] = []
        self._timings: dict[str, float] = {}
        self._frame = None

    # ------------------------------------------------------------------------------------ per frame

    def process(self, frame) -> FrameResult:
        self._events, self._timings, self._frame = [], {}, frame
        cv2.setRNGSeed(self.seed + frame.index)  # OpenCV's RANSAC (relocalization) draws from its global generator
        start = time.perf_counter()
        self._clock(frame.timestamp)
        if self.state is State.LOST:
            result = self._relocalize(frame)
        else:
            with self._stage("orb"):
                features = (self._extract_for_start(frame.image) if self.state is State.NOT_INITIALIZED
                            else self.relocalizer.extract(frame.image))
            if self.state is State.NOT_INITIALIZED:
                result = self._initialize(frame, features)
            else:
                result = self._track(frame, features)
        self.frames_processed += 1
        self._timings["total"] = (time.perf_counter() - start) * 1000.0
        result.timings_ms, result.events = self._timings, self._events
        return result

    def map_snapshot(self) -> MapSnapshot:
        points = self.map.points
        return MapSnapshot(
            feature_points_world=points.position[points.alive].copy(),
            keyframe_poses={k.frame_index: k.T_world_cam.copy() for k in self.map.keyframes.values()},
        )

    def final_keyframe_poses(self) -> dict[int, np.ndarray]:
        """The keyframes' poses the final trajectory hangs frames on, the culled ones' included (FeatureMap)."""
        return self.map.final_poses()

    # ------------------------------------------------------------------------------------ initialization

    def _initialize(self, frame, features: FrameFeatures) -> FrameResult:
        with self._stage("initialization"):
            step = self.initializer.step(frame.index, frame.timestamp, features)
        if step.failure is not None and (step.started or self.initializer.reference is None):
            self._emit(EventKind.INITIALIZATION_FAILED, reason=step.failure)
        if step.started:
            self.reference_image = frame.image
            self._emit(EventKind.INITIALIZATION_STARTED, reference_frame=frame.index, features=len(features.features))
        if step.model is not None:
            self._emit(EventKind.INITIALIZER_MODEL, **step.model)
        if step.map is None:
            return self._no_pose(features.features.uv)
        return self._start_map(frame, features, step.map)

    def _extract_for_start(self, image: np.ndarray) -> FrameFeatures:
        """More features until the start (ORB-SLAM2's initialization extractor): more matches to choose from."""
        features = self.start_extractor.extract(image)
        bow, nodes = self.vocabulary.transform(features.descriptors)
        return FrameFeatures(features, bow, nodes, 0.0)

    def _start_map(self, frame, features: FrameFeatures, start: TwoFrameMap) -> FrameResult:
        """ORB-SLAM2 CreateInitialMapMonocular: the two keyframes and their points, placed at the origin with the
        origin's scene depth as unit, then local mapping of the second keyframe."""
        T_first_second = start.T_first_second.copy()
        T_first_second[:3, 3] *= self.origin_depth
        first = self._new_keyframe(start.first_index, start.first_timestamp, start.first, self.T_world_origin)
        second = self._new_keyframe(frame.index, frame.timestamp, features, self.T_world_origin @ T_first_second)
        points = transform_points(self.T_world_origin, self.origin_depth * start.points_first)
        level = second.features.level[start.feature_second]
        ids = self.map.points.add(points, second.features.descriptors[start.feature_second], second.keyframe_id,
                                  np.linalg.norm(points - second.centre, axis=1), level)
        first.point_ids[start.feature_first] = ids
        second.point_ids[start.feature_second] = ids
        self.map.representative_descriptors(ids)
        self.map.update_normals(ids)
        self._emit(EventKind.INITIALIZATION_SUCCEEDED, **start.details, first_T_world_cam=first.T_world_cam.tolist(),
                   second_frame=frame.index)
        tracked = TrackedFrame(frame.index, frame.timestamp, features, second.T_world_cam, second.point_ids.copy(),
                               second.frame_index)
        self.state = State.OK
        self.posed = [(start.first_timestamp, first.T_world_cam)]
        self._map_keyframe(second, tracked)
        self.young = YoungMap(start.first_index, frame.index, [frame.timestamp])
        witness = self.start_witness()
        if witness is not None:
            images = {start.first_index: self.reference_image, frame.index: frame.image}
            self.probation = StartProbation(witness, images)
            witness.prepare(self.probation.views(self.map), self.camera)
        self._moved_to(tracked)
        return self._pose_result(tracked, None, is_keyframe=True, inliers=len(ids))

    # ------------------------------------------------------------------------------------ tracking

    def _track(self, frame, features: FrameFeatures) -> FrameResult:
        current = TrackedFrame(frame.index, frame.timestamp, features, reference_keyframe=self.last.reference_keyframe)
        with self._stage("track"):
            outcome = self.tracker.track(self.map, current, self.last, self._predicted(frame.timestamp),
                                         self._relocalized_recently())
        if not outcome.succeeded:
            return self._lost(frame, current, outcome)
        return self._tracked(current, outcome)

    def _tracked(self, current: TrackedFrame, outcome: TrackingOutcome) -> FrameResult:
        """A frame with a pose: its points' statistics, the keyframe decision, the motion model."""
        matched = current.point_ids[current.matched]
        self.local_mapper.statistics.count(len(self.map.points), outcome.visible_points, matched)
        last = self.last
        keyframe = None
        if self._needs_keyframe(current, outcome.inliers) and current.frame_index not in self.map.keyframes:
            keyframe = self._new_keyframe(current.frame_index, current.timestamp, current.features,
                                          current.T_world_cam, current.point_ids.copy())
            self._map_keyframe(keyframe, current)
        if self.young is not None:
            self.young.posed_timestamps.append(current.timestamp)
        if self.probation is not None:
            refused = self._check_start(current, keyframe)
            if refused is not None:
                return refused
        if self.probation is None and not self._young_by_size:
            self.young = None  # established: its poses stay, whatever follows
        self._moved_to(current)
        return self._pose_result(current, last, is_keyframe=keyframe is not None, inliers=outcome.inliers)

    def _predicted(self, timestamp: float) -> np.ndarray | None:
        """The constant-velocity pose (ORB-SLAM2's motion model, over the time that passed); None without a
        velocity (just after the start's first frame is lost or a relocalization)."""
        if len(self.posed) < 2:
            return None
        if self.frames_processed < self.relocalized_at + FRAMES_WITHOUT_VELOCITY_AFTER_RELOCALIZATION:
            return None
        return extrapolate(self.posed, timestamp)

    def _needs_keyframe(self, current: TrackedFrame, inliers: int) -> bool:
        """ORB-SLAM2 NeedNewKeyFrame (monocular): not soon after a relocalization once the map has more keyframes
        than the grace has frames; otherwise while local mapping is idle and the frame tracks few of its reference
        keyframe's points (FeatureTracker.tracks_few_reference_points). ORB-SLAM2's other conditions never decide
        here: with mMinFrames = 0, "mMaxFrames since the last keyframe" only matters where local mapping is busy,
        and then a monocular keyframe is refused anyway."""
        tracking = self.config.odometry.tracking
        if self._relocalized_recently() and len(self.map) > self._frames_in(tracking.relocalization_grace_s):
            return False
        mapping_idle = local_mapping_idle(current.timestamp - self.keyframed_at, self.frame_period,
                                          tracking.local_mapping_busy_s)
        return mapping_idle and self.tracker.tracks_few_reference_points(self.map, current, inliers)

    def _relocalized_recently(self) -> bool:
        grace = self._frames_in(self.config.odometry.tracking.relocalization_grace_s)
        return self.frames_processed < self.relocalized_at + grace

    def _frames_in(self, seconds: float) -> float:
        """Frames at the camera's rate in a while (rounded: timestamps are not exact multiples of the period)."""
        return np.round(seconds / self.frame_period) if np.isfinite(self.frame_period) else 0.0

    def _clock(self, timestamp: float) -> None:
        if self.previous_timestamp is not None and timestamp > self.previous_timestamp:
            self.frame_period = min(self.frame_period, timestamp - self.previous_timestamp)
        self.previous_timestamp = timestamp

    def _moved_to(self, current: TrackedFrame) -> None:
        self.posed = (self.posed + [(current.timestamp, current.T_world_cam)])[-2:]
        self.last = current

    # ------------------------------------------------------------------------------------ the start's probation

    def _check_start(self, current: TrackedFrame, keyframe: FeatureKeyframe | None) -> FrameResult | None:
        """A frame posed in a map on probation. Its keyframes' images are measured as they come (beside tracking);
        at the last probation keyframe the witness compares them with the poses the map gives them now. Returns the
        frame's result where the start is taken back."""
        probation = self.probation
        if keyframe is None:
            return None
        probation.images[keyframe.frame_index] = self._frame.image
        views = probation.views(self.map)
        if len(probation.images) < 2 + self.config.odometry.initialization.probation_keyframes:
            probation.witness.prepare(views, self.camera)
            return None
        self.probation = None
        reason, measures = probation.witness.disagreement(views, self.camera)
        return None if reason is None else self._take_back_start(reason, measures)

    def _take_back_start(self, reason: str, measures: dict) -> FrameResult:
        """The start failed its probation: the map goes, its poses are taken back (``_retract_young_map``), and the
        start begins again from this frame, placed where the refused one was."""
        self._retract_young_map(reason, measures)
        self._forget_map()
        with self._stage("orb"):
            features = self._extract_for_start(self._frame.image)
        return self._initialize(self._frame, features)

    @property
    def _young_by_size(self) -> bool:
        """Whether the map has fewer keyframes than one that is not reset when lost (ORB-SLAM2: at most 5)."""
        return len(self.map) < self.config.odometry.initialization.reset_when_lost_below_keyframes

    def _retract_young_map(self, reason: str, measures: dict) -> None:
        """The young map's start is refused: the poses given in it are retracted (the first frame's with
        ``first_frame``; this frame's is not one of them: it starts the next map or gets none)."""
        young = self.young
        self._emit(EventKind.INITIALIZATION_REJECTED, reason=reason, initializer="orb", first_frame=young.first_frame,
                   second_frame=young.second_frame, keyframes=len(self.map), **measures,
                   retracted=[t for t in young.posed_timestamps if t != self._frame.timestamp])

    def _forget_map(self) -> None:
        if self.probation is not None:
            self.probation.witness.close()
        self.probation, self.young = None, None
        self.map = FeatureMap()
        self.local_mapper.reset()
        self.initializer.reset()
        self.posed, self.last = [], None
        self.state, self.lost_at = State.NOT_INITIALIZED, None

    # ------------------------------------------------------------------------------------ lost, relocalized

    def _lost(self, frame, current: TrackedFrame, outcome: TrackingOutcome) -> FrameResult:
        """No pose. A young map starts over (ORB-SLAM2 resets with at most 5 keyframes), and its poses are taken
        back: ORB-SLAM2's Tracking::Reset clears the trajectory with the map (a start that held for a few keyframes
        and lost them proved nothing; TUM fr1/desk, seed 0: 11 frames of a map begun at frame 35 and lost at 46, at
        a scale of their own). An established map waits for the relocalization."""
        self._emit(EventKind.TRACKING_FAILED, reason=outcome.reason, stage=outcome.stage, keyframes=len(self.map))
        if not self._young_by_size:
            self.state, self.lost_at = State.LOST, frame.timestamp
            return self._no_pose(current.features.features.uv)
        reason = "the map was lost with few keyframes"
        if self.young is not None:
            self._retract_young_map(f"{reason} (ORB-SLAM2's reset: the map and the poses given in it go)", {})
        return self._start_over(frame, current.features, reason=reason)

    def _start_over(self, frame, features: FrameFeatures, reason: str) -> FrameResult:
        """A new map, begun from this frame where the camera was last posed and at the old map's scene depth."""
        newest = self.map.newest()
        self.T_world_origin = self.last.T_world_cam
        self.origin_depth = newest.scene_depth if np.isfinite(newest.scene_depth) else self.origin_depth
        self._emit(EventKind.REINITIALIZATION, from_frame=frame.index, keyframes=len(self.map), reason=reason)
        self._forget_map()
        return self._initialize(frame, features)

    def _relocalize(self, frame) -> FrameResult:
        with self._stage("relocalization"):
            current, outcome = self.tracker.relocalize(self.map, frame.image, frame.index, frame.timestamp)
        recovery = outcome.relocalization
        self._emit(EventKind.RECOVERY_TRIED, candidates=recovery.candidates)
        if not outcome.succeeded:
            details = recovery.details() if not recovery.succeeded else {"stage": outcome.stage}
            self._emit(EventKind.RECOVERY_FAILED, **{**details, "reason": outcome.reason})
            lost_s = frame.timestamp - self.lost_at
            if lost_s > self.config.odometry.tracking.new_map_after_lost_s:
                return self._start_over(frame, current.features,
                                        reason=f"no relocalization for {lost_s:.1f} s: a new map")
            return self._no_pose(current.features.features.uv)
        self._emit(EventKind.RECOVERY_SUCCEEDED, **recovery.details(), local_map_inliers=outcome.inliers)
        self.state, self.lost_at = State.OK, None
        self.relocalized_at = self.frames_processed
        self.posed = []  # no velocity across the gap
        return self._tracked(current, outcome)

    # ------------------------------------------------------------------------------------ keyframes

    def _new_keyframe(self, frame_index: int, timestamp: float, features: FrameFeatures, T_world_cam: np.ndarray,
                      point_ids: np.ndarray | None = None) -> FeatureKeyframe:
        keyframe = FeatureKeyframe(self.map.next_keyframe_id, frame_index, timestamp, T_world_cam.copy(),
                                   features.features, features.bow, features.nodes, point_ids=point_ids,
                                   in_direct_window=False)
        self.map.add_keyframe(keyframe)
        return keyframe

    def _map_keyframe(self, keyframe: FeatureKeyframe, current: TrackedFrame) -> LocalMappingReport:
        """Local mapping on the new keyframe; the frame takes the keyframe's adjusted pose and follows a
        renumbering of the points."""
        with self._stage("local_mapping"):
            report = self.local_mapper.process(self.map, keyframe)
        self.keyframed_at = keyframe.timestamp
        if report.renumbered is not None and self.last is not None:  # the frame takes the keyframe's ids below
            observed = self.last.matched
            self.last.point_ids[observed] = report.renumbered[self.last.point_ids[observed]]
        current.T_world_cam = keyframe.T_world_cam.copy()
        current.point_ids = keyframe.point_ids.copy()
        current.reference_keyframe = keyframe.frame_index
        self._emit(EventKind.KEYFRAME_ADDED, **report.as_details())
        if report.culled_points:
            self._emit(EventKind.MAP_POINTS_CULLED, count=report.culled_points, reason="MapPointCulling")
        if report.ba_keyframes:
            self._emit(EventKind.WINDOW_OPTIMIZED, keyframes=report.ba_keyframes, landmarks=report.ba_points,
                       rms_before_sigma=round(report.ba_rms_before, 3), rms_after_sigma=round(report.ba_rms_after, 3))
        for culled in report.culled_keyframes:
            self._emit(EventKind.FEATURE_KEYFRAME_CULLED, keyframe=culled, reason="KeyFrameCulling: redundant")
        return report

    # ------------------------------------------------------------------------------------ output

    def _pose_result(self, current: TrackedFrame, last: TrackedFrame | None, is_keyframe: bool,
                     inliers: int) -> FrameResult:
        features = current.features.features
        matched = current.matched
        result = FrameResult(self._frame.index, self._frame.timestamp, current.T_world_cam.copy(), tracked=True,
                             is_keyframe=is_keyframe, num_inliers=inliers, points_2d=features.uv[matched].copy())
        reference = self.map.keyframes.get(current.reference_keyframe)
        if reference is not None:  # ORB-SLAM2's SaveTrajectoryTUM: the pose relative to its reference keyframe
            result.reference_keyframe = reference.frame_index
            result.T_ref_cam = se3_inverse(reference.T_world_cam) @ result.T_world_cam
        if last is not None:
            shared, in_current, in_last = np.intersect1d(current.point_ids[matched], last.point_ids[last.matched],
                                                         return_indices=True)
            result.matches_2d = np.hstack([last.features.features.uv[last.matched[in_last]],
                                           features.uv[matched[in_current]]])
        return result

    def _no_pose(self, points_2d: np.ndarray) -> FrameResult:
        return FrameResult(self._frame.index, self._frame.timestamp, None, tracked=False,
                           points_2d=np.asarray(points_2d).copy())

    def _emit(self, kind: EventKind, **details) -> None:
        self._events.append(Event(kind, self._frame.index, float(self._frame.timestamp), details))

    @contextmanager
    def _stage(self, name: str):
        start = time.perf_counter()
        yield
        self._timings[name] = self._timings.get(name, 0.0) + (time.perf_counter() - start) * 1000.0
